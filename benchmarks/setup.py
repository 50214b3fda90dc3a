"""How the setup placement (``setup_placement``) scales with the number of base candidates: the bundled
two-UR5 setup with 1, 2, 3 (and more with ``--max``) bases per arm, taken in order from its lists.

    python benchmarks/setup.py [--max 3] [--workers 1]

The query: ``scenarios/ur5_setup.toml`` "bases and triad around the task region" (two UR5s with their
collision meshes, a mesh torso, candidates on the wall at 80 mm, 18 targets at 40 mm, arm checks at 30 mm,
patient clearance 20 mm). Per row: the bases per arm, the candidates per role (instrument candidates are
(base, port) pairs), the setups (all combinations), the share the bound prunes, wall and CPU time (this
process's, ``time.process_time``), and the parts: coverage of every (base, port) pair (fields, clearance),
the arm checks (their coal queries), the patient checks (their coal queries), the search. Each row runs in
this process after a warm-up on one base per arm (kernels compiled, the yaw-0 reachability map cached).
The machine is shared: the load averages at the start and the end are in the title.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from errplan.api import load_setup  # noqa: E402
from errplan.report import format_table  # noqa: E402
from errplan.tolerance.setup import setup_placement  # noqa: E402


def with_bases(tol, k: int):
    b = {n: v[:k] for n, v in tol.options["bases"].items()}
    return dataclasses.replace(tol, options=dict(tol.options, bases=b))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--max", type=int, default=3, help="largest number of bases per arm (default: 3)")
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args(argv)
    load0 = os.getloadavg()[0]
    st = load_setup(REPO / "scenarios" / "ur5_setup.toml")
    tol = st.triads[0]
    setup_placement(st, with_bases(tol, 1), workers=1)  # warm
    rows = []
    for k in range(1, args.max + 1):
        t = with_bases(tol, k)
        c0, t0 = time.process_time(), time.perf_counter()
        r = setup_placement(st, t, workers=args.workers)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        s, tm = r["search"], r["timing"]
        n1, n2 = r["instruments"]
        nb = [len(r["bases"][n]) for n in (n1, n2)]
        cands = f"{nb[0] * len(r['candidates'][n1])} x {nb[1] * len(r['candidates'][n2])} x " \
                f"{len(r['candidates']['endoscope'])}"
        rows.append([f"{nb[0]} x {nb[1]}", cands, f"{s['setups']:,}", 100 * s["pruned_share"], wall, cpu,
                     tm["coverage_s"], tm["arm_s"], f"{tm['arm_queries']:,}", tm["patient_s"],
                     f"{tm['patient_queries']:,}", tm["search_s"], r["best"]["score"], s["ties"]])
    load1 = os.getloadavg()[0]
    print(format_table(["bases", "candidates", "setups", "pruned %", "wall s", "CPU s", "coverage s", "arm s",
                        "arm queries", "patient s", "patient queries", "search s", "best S", "ties"], rows,
                       f"setup placement, ur5_setup.toml, {args.workers} worker(s); load {load0:.1f} -> {load1:.1f}"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
