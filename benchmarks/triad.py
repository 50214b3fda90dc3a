"""Speed of the triad placement (``triad_placement``) on the bundled setups: candidates per role,
triads, the share the branch and bound prunes, and wall and CPU time with 1 and 2 local workers.

    python benchmarks/triad.py [--repeat 1] [--brute] [--setup abdomen_triad|ur5_triad|all]

The queries: ``scenarios/abdomen_triad.toml`` "triad for the task region" (two PHANToM 1.5 arms and an
endoscope, candidates on the ellipsoid wall at 35 mm, 125 targets at 20 mm, no arm checks) and
``scenarios/ur5_triad.toml`` "triad around the task region" (two UR5s with their collision meshes, a
mesh torso, candidates at 50 mm, arm checks on: ``arm_clearance`` 30 mm). Each configuration runs
``triad_placement`` in this process (kernels compiled and cached); the table gives the fastest wall
time, this process's CPU time (the work itself with 1 worker; with 2, the parent's share), and the
parts: per-candidate coverage (fields, clearance; tasks), the exact shaft distances, the arm checks
(inverse kinematics and coal's collision queries; their count), the search.
``--brute`` adds the unpruned search (every triad). All configurations must give the same best
triad (checked). The machine is shared: the load averages at the start and the end are in the title.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from errplan.api import load_setup  # noqa: E402
from errplan.report import format_table  # noqa: E402
from errplan.tolerance.triad import triad_placement  # noqa: E402

SETUPS = ("abdomen_triad", "ur5_triad")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--brute", action="store_true", help="also the unpruned search")
    ap.add_argument("--setup", choices=SETUPS + ("all",), default="all")
    args = ap.parse_args(argv)
    for name in (SETUPS if args.setup == "all" else (args.setup,)):
        bench(REPO / "scenarios" / f"{name}.toml", args)
    return 0


def bench(SETUP: Path, args) -> None:
    load0 = os.getloadavg()[0]
    st = load_setup(SETUP)
    tol = st.triads[0]
    triad_placement(st, tol, workers=1)  # warm: kernels, arm, anatomy
    configs = [("branch and bound", True, 1), ("branch and bound", True, 2)]
    if args.brute:
        configs.append(("brute force", False, 1))
    rows, best = [], None
    for label, prune, w in configs:
        runs = []
        for _ in range(max(args.repeat, 1)):
            c0, t0 = time.process_time(), time.perf_counter()
            r = triad_placement(st, tol, workers=w, prune=prune)
            runs.append((time.perf_counter() - t0, time.process_time() - c0, r))
        wall, cpu, r = min(runs, key=lambda x: x[0])
        if best is None:
            best = r["best"]["indices"]
        assert r["best"]["indices"] == best, (label, w, r["best"]["indices"], best)
        s, tm = r["search"], r["timing"]
        n = {k: len(v) for k, v in r["candidates"].items()}
        rows.append([label, w, " x ".join(str(v) for v in n.values()), r["targets"], f"{s['triads']:,}",
                     f"{100 * s['pruned_share']:.2f}", wall, cpu, tm["coverage_s"], tm["distances_s"],
                     tm["arm_s"] if st.arm_clearance is not None else "off", f"{tm['arm_queries']:,}",
                     f"{r['rejected']['arm_clearance'] or 0:,}", tm["search_s"]])
    title = (f"triad placement of {SETUP.name} (load {load0:.1f} -> {os.getloadavg()[0]:.1f} on "
             f"{os.cpu_count()} cores)")
    print(format_table(["search", "workers", "candidates", "targets", "triads", "pruned %", "wall s", "cpu s",
                        "coverage s", "distances s", "arm checks s", "arm queries", "arm rejected", "search s"],
                       rows, title))
    print()


if __name__ == "__main__":
    raise SystemExit(main())
