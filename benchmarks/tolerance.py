"""Speed of the port-placement sweep (issue 12): time per candidate, planar and spatial, and the
speed-up from 1 to 2 local workers and on a 2-worker dask LocalCluster.

    python benchmarks/tolerance.py [--repeat 2] [--quick]

The queries are the bundled examples, without their refinement:

- planar: ``scenarios/beasley2004_bounded.toml`` "port for a task near N": 121 candidate ports at
  10 mm, a task region of 527 points at 6 mm, P1's arm, a +-5 mm port box and +-1 /m^2 loads
  (5 samples per axis, then the fields' local refinement);
- spatial: ``scenarios/phantom15_placement.toml`` "port for a task around L-M-N": 36 candidates at
  20 mm, 245 region points at 30 mm, the PHANToM 1.5 with a waist, a +-5 mm 3-D port box and
  lateral loads up to 1 /m^2 in any direction (3 samples per axis, 8 load directions).

Each configuration runs the sweep (``port_placement``: what ``errplan tolerance`` does, in this
process, kernels compiled and cached, the arm loaded) ``--repeat`` times; the table gives the
fastest wall time of the sweep alone (map_tasks over the candidates), the time per candidate and
the speed-up against 1 worker, and for the in-process run the CPU time per candidate (the work
itself, whatever the load). The three configurations of a query must give identical numbers
(checked). The machine is shared: the load averages at the start and the end are in the title.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from errplan.api import load_scenario  # noqa: E402
from errplan.tolerance import port_placement  # noqa: E402
from errplan.report import format_table  # noqa: E402

QUERIES = {
    "planar": REPO / "scenarios" / "beasley2004_bounded.toml",
    "spatial": REPO / "scenarios" / "phantom15_placement.toml",
}


def sweep(sc, o, *, workers=1, scheduler=None, quick=False):
    """The query's sweep without refinement; adds ``cpu_seconds`` (this process's CPU time: the work
    itself when ``workers == 1``, whatever the machine's load)."""
    cand = dict(o["candidates"])
    spacing = o["spacing"]
    if quick:  # a quarter of the candidates or fewer
        spacing = 2 * spacing
    c0 = time.process_time()
    r = port_placement(sc, cand, spacing, o["region"], resolution=o.get("resolution"), gain=o.get("gain"),
                       certify_margin=o.get("certify_margin"), refine=False, workers=workers, scheduler=scheduler,
                       keep_arrays=False)
    r["cpu_seconds"] = time.process_time() - c0
    return r


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="twice the candidate spacing (a smoke run)")
    args = ap.parse_args(argv)
    load = os.getloadavg()[0]
    rows = []
    cluster = None
    try:
        from distributed import LocalCluster

        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    except Exception as e:  # noqa: BLE001 - reported, the local rows still run
        print(f"no LocalCluster ({e}); its rows are skipped", file=sys.stderr)
    try:
        for label, path in QUERIES.items():
            sc = load_scenario(path)
            tol = next(t for t in sc.tolerances if t.kind == "port_placement")
            o = tol.options
            sweep(sc, o, workers=1, quick=True)  # warm: kernels compiled/cached, arm and reach map loaded
            base = None
            ref = None
            configs = [("1 local worker", dict(workers=1)), ("2 local workers", dict(workers=2))]
            if cluster is not None:
                configs.append(("2-worker LocalCluster", dict(scheduler=cluster.scheduler_address)))
            for name, kw in configs:
                best = None
                for _ in range(max(1, args.repeat)):
                    r = sweep(sc, o, quick=args.quick, **kw)
                    best = r if best is None or r["sweep_seconds"] < best["sweep_seconds"] else best
                    if ref is None:
                        ref = r
                    assert r["candidates"] == ref["candidates"] and r["best"] == ref["best"], (label, name)
                t = best["sweep_seconds"]
                n = len(best["candidates"])
                base = base or t
                cpu = best["cpu_seconds"] / n if kw.get("workers") == 1 else float("nan")
                rows.append([label, name, n, best["region_points"], t, t / n, 1000 * t / n / best["region_points"],
                             cpu, base / t])
            print(f"{label}: best port {[round(1000 * v, 1) for v in ref['best']]} mm, coverage "
                  f"{100 * ref['coverage']:.1f}% ({ref['covered']}/{ref['region_points']}), max rho* "
                  f"{ref['max_rho_star']:.4f}", file=sys.stderr)
    finally:
        if cluster is not None:
            cluster.close()
    print(format_table(["placement", "where", "candidates", "region points", "sweep s", "s / candidate",
                        "ms / region point", "CPU s / candidate", "speed-up"], rows,
                       f"port-placement sweep (fastest of {args.repeat}; load average {load:.1f} at the start, "
                       f"{os.getloadavg()[0]:.1f} at the end, on {os.cpu_count()} cores)"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
