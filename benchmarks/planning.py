"""Planner benchmark: cost ratio to the grid optimum and time, per OMPL planner.

    python benchmarks/planning.py [--time 1.0] [--random 8] [--planners RRTstar,BITstar,...]
                                  [--uncapped] [--resolution 0.002] [--seed 11]

Queries: every bundled [[query]] of scenarios/beasley2004_port.toml and beasley2004_bounded.toml,
plus ``--random`` seeded random queries per scenario (start and goal uniform in the usable
region, at least 50 mm apart), half of them drawn among queries whose grid optimum is at least
2 % cheaper than the straight line or whose straight line is not usable ("hard"). The reference is
errplan.reference.grid_optimum (Dijkstra, moves up to 4 cells, 48-connected), on the same
CostMap. For each planner: ``raw`` = cost of the OMPL solution / grid optimum, ``final`` = after
errplan's refine_path (what `errplan plan` returns), time = search + refine per query (s),
``iters/s`` = planner iterations per second of search. By default each planner runs with errplan's
settings (iteration cap ITERATION_RATE * 0.75 * time, time cap); ``--uncapped`` lets every planner
use its whole search time.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from errplan.errors import ErrplanError  # noqa: E402
from errplan.planning import (PLANNERS, PlannerSettings, costmap_for, fields_for_planning,  # noqa: E402
                              plan_query)
from errplan.reference import GridGraph, grid_optimum  # noqa: E402
from errplan.report import format_table  # noqa: E402
from errplan.scenario import load_scenario  # noqa: E402


def random_queries(cm, graph, n: int, rng: np.random.Generator, hard: bool) -> list[tuple]:
    cells = np.argwhere(cm.cell_ok)
    out = []
    tries = 0
    while len(out) < n and tries < 5000:
        tries += 1
        a, b = cells[rng.choice(len(cells), 2)]
        s = (cm.y0 + (a[0] + rng.random()) * cm.h, cm.z0 + (a[1] + rng.random()) * cm.h)
        g = (cm.y0 + (b[0] + rng.random()) * cm.h, cm.z0 + (b[1] + rng.random()) * cm.h)
        if math.dist(s, g) < 0.05 or not cm.connected(s, g):
            continue
        ref = grid_optimum(cm, s, g, graph.radius, graph=graph)
        ok, c = cm.path_cost([s, g])
        if hard and ok and ref.cost > 0.98 * c:
            continue
        out.append((f"rand{'H' if hard else ''}{len(out)}", s, g, ref.cost))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--time", type=float, default=1.0)
    ap.add_argument("--random", type=int, default=8, help="random queries per scenario (half of them hard)")
    ap.add_argument("--planners", default="BITstar,RRTstar,InformedRRTstar,SORRTstar,FMT,BFMT,RRTConnect")
    ap.add_argument("--uncapped", action="store_true", help="no iteration cap: every planner runs its full time")
    ap.add_argument("--resolution", type=float, default=None)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--radius", type=int, default=4, help="move radius of the grid reference")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args(argv)
    planners = args.planners.split(",")
    for p in planners:
        if p not in PLANNERS:
            raise SystemExit(f"unknown planner {p}; choose from {', '.join(PLANNERS)}")
    rng = np.random.default_rng(args.seed)
    problems = []
    setup_rows = []
    for name in ("beasley2004_port", "beasley2004_bounded"):
        sc = load_scenario(ROOT / "scenarios" / f"{name}.toml")
        t0 = time.perf_counter()
        mf = fields_for_planning(sc, args.resolution)
        tf = time.perf_counter() - t0
        cm = costmap_for(sc, mf)
        t0 = time.perf_counter()
        graph = GridGraph(cm, args.radius)
        tg = time.perf_counter() - t0
        qs = []
        for q in sc.queries:
            ref = grid_optimum(cm, q.start, q.goal, args.radius, graph=graph)
            qs.append((q.name, q.start, q.goal, ref.cost))
        qs += random_queries(cm, graph, args.random - args.random // 2, rng, hard=False)
        qs += random_queries(cm, graph, args.random // 2, rng, hard=True)
        t0 = time.perf_counter()
        for _, s, g, _ in qs:
            grid_optimum(cm, s, g, args.radius, graph=graph)
        tq = (time.perf_counter() - t0) / max(len(qs), 1)
        setup_rows.append([sc.name, f"{cm.ny}x{cm.nz}", cm.h * 1000, tf, tg, tq, len(qs)])
        problems.append((sc, cm, qs))
    print(format_table(["scenario", "grid", "res (mm)", "fields (s)", "reference graph (s)", "reference/query (s)",
                        "queries"], setup_rows, "setup (fields with rho_star, reference graph and search)"))
    print()
    rows = []
    for pname in planners:
        raw, fin, times, rates, fails, worse_direct = [], [], [], [], 0, 0
        for sc, cm, qs in problems:
            for qname, s, g, ref in qs:
                st = PlannerSettings(pname, args.time, sc.planner.seed,
                                     iterations=10**9 if args.uncapped else None)
                try:
                    qp = plan_query(cm, s, g, st, name=qname)
                except ErrplanError as e:
                    fails += 1
                    if args.verbose:
                        print(f"  {pname} {sc.name} {qname}: {e}")
                    continue
                raw.append(qp.raw_cost / ref)
                fin.append(qp.planned.cost / ref)
                times.append(qp.time_total)
                rates.append(qp.iterations / max(qp.time_solve, 1e-9))
                if qp.direct.valid and qp.planned.cost > 1.05 * qp.direct.cost:
                    worse_direct += 1
                if args.verbose:
                    print(f"  {pname:16s} {sc.name:20s} {qname:12s} raw {raw[-1]:.4f} final {fin[-1]:.4f} "
                          f"{qp.time_solve:.2f}+{qp.time_refine:.2f} s {qp.iterations} it ({qp.stopped_by})")
        n = len(raw)
        if n == 0:
            rows.append([pname, 0, fails, "-", "-", "-", "-", "-", "-", "-", "-"])
            continue
        rows.append([pname, n, fails, float(np.mean(raw)), float(np.max(raw)), float(np.mean(fin)),
                     float(np.max(fin)), int(np.sum(np.array(fin) > 1.05)), float(np.mean(times)),
                     float(np.max(times)), float(np.median(rates))])
    mode = "uncapped (full time)" if args.uncapped else "errplan settings (iteration cap + time cap)"
    print(format_table(["planner", "solved", "failed", "raw mean", "raw max", "final mean", "final max",
                        "final > 1.05", "time mean (s)", "time max (s)", "iters/s"], rows,
                       f"cost / grid optimum over {sum(len(q) for _, _, q in problems)} queries, "
                       f"{args.time:g} s budget, {mode}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
