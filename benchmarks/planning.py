"""Planner benchmark: cost ratio to the grid optimum and time, per OMPL planner, planar and spatial.

    python benchmarks/planning.py [--dims 2,3,arms] [--iterations N] [--time T] [--random 8] [--random3 8]
                                  [--planners RRTstar,BITstar,...] [--uncapped] [--no-grid-seed]
                                  [--resolution 0.002] [--seed 11] [--spatial-scenario] [--workers N]

Planar (``--dims 2``): every bundled [[query]] of scenarios/beasley2004_port.toml and
beasley2004_bounded.toml, plus ``--random`` seeded random queries per scenario (start and goal
uniform in the usable region, at least 50 mm apart), half of them drawn among queries whose grid
optimum is at least 2 % cheaper than the straight line or whose straight line is not usable
("hard"). The reference is errplan.planning.reference.grid_optimum (Dijkstra, moves up to 4 cells,
48 directions), on the same CostMap.

Spatial (``--dims 3``): the synthetic spatial fields of tests/test_planning_spatial.py (a hole
along the port axis, a bar with a thin passage below it, an invalid shell, a non-certifiable blob;
41 x 41 x 33 nodes at 5 mm) with two objectives, phi_hat_max with weight 1 (certifiable) and G_norm
with weight 4 (not certifiable); per objective the query across the port-axis hole and
``--random3`` seeded random queries (half hard). With ``--spatial-scenario``, also the fields of
scenarios/phantom15_spatial.toml (computed here, ``--workers``). Reference: grid_optimum with moves
up to 3 cells (290 directions, at most 2.5 % above the continuous optimum in free space).

Two arms (``--dims arms``): the two UR5s of scenarios/ur5_triad.toml (``--arm-scenario`` another setup) with
``[setup] arm_clearance``. Per moving arm: the cost of one arm check, the Python check
(``ArmChecks.point_ok_exact``/``motion_ok_exact``: pinocchio placements, coal on every pair whose bounding
spheres come within the clearance) against the compiled one (``point_ok``/``motion_ok``: tips, inverse
kinematics, placements and a capsule broad phase compiled, coal on the undecided mesh pieces only), on
``--arm-states`` seeded random tips of the fields' region and as many straight motions of 3 cm from them,
with how many answers differ (must be 0), in CPU time (the process's, so that other work on the machine
does not count) and, for the compiled check, also wall time, each the best of ``--arm-repeats`` runs over the
same tips and motions (the pairs' memory of nearest triangles and directions emptied before each run); then
each query of that arm planned on the scenario's fields
(``--resolution3``, default the scenario's) with either check: iterations, what stopped the search, search
time, cost.

For each planner: ``raw`` = cost of the OMPL solution / grid optimum, ``final`` = after errplan's
candidates and refine_path (what `errplan plan` returns), ``from OMPL`` = queries whose returned
path was refined from the OMPL search's result (rather than the straight line or, in space, the
coarse cell-graph path), time = search + refine per query (s), ``iters/s`` = planner iterations per
second of search. By default each planner runs with errplan's settings (its default iteration budget,
``DEFAULT_ITERATIONS`` / ``DEFAULT_ITERATIONS_SPATIAL``, or ``--iterations``; no time cap unless ``--time``
gives one); ``--uncapped`` lets every planner run until the time cap (``--time``, default 1 s there) instead
of a budget; ``--no-grid-seed`` plans without the coarse cell-graph candidate (OMPL and refinement alone).
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from errplan.errors import ErrplanError  # noqa: E402
from errplan.planning import (PLANNERS, CostMap, PlannerSettings, costmap_for, fields_for_planning,  # noqa: E402
                              plan_query)
from errplan.planning.reference import GridGraph, grid_optimum  # noqa: E402
from errplan.report import format_table  # noqa: E402
from errplan.api import load_scenario  # noqa: E402

COLUMNS = ["planner", "solved", "failed", "raw mean", "raw max", "final mean", "final max", "final > 1.05",
           "from OMPL", "time mean (s)", "time max (s)", "iters/s"]


def random_queries(cm, graph, n: int, rng: np.random.Generator, hard: bool) -> list[tuple]:
    """Planar random queries (unchanged from the planar benchmark)."""
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


def run_planners(planners, problems, args, verbose) -> list[list]:
    """One table row per planner over ``problems`` = [(label, cm, settings, [(name, s, g, ref)])]."""
    rows = []
    for pname in planners:
        raw, fin, times, rates, fails, from_ompl = [], [], [], [], 0, 0
        for label, cm, base, qs in problems:
            for qname, s, g, ref in qs:
                st = replace(base, planner=pname, iterations=10**9 if args.uncapped else args.iterations,
                             grid_seed=False if args.no_grid_seed else None)
                try:
                    qp = plan_query(cm, s, g, st, name=qname)
                except ErrplanError as e:
                    fails += 1
                    if verbose:
                        print(f"  {pname} {label} {qname}: {e}")
                    continue
                raw.append(qp.raw_cost / ref)
                fin.append(qp.planned.cost / ref)
                times.append(qp.time_total)
                rates.append(qp.iterations / max(qp.time_solve, 1e-9))
                from_ompl += qp.source in ("planner", "first solution")
                if verbose:
                    print(f"  {pname:16s} {label:20s} {qname:12s} raw {raw[-1]:.4f} final {fin[-1]:.4f} "
                          f"{qp.time_solve:.2f}+{qp.time_refine:.2f} s {qp.iterations} it ({qp.stopped_by}, "
                          f"from {qp.source})", flush=True)
        n = len(raw)
        if n == 0:
            rows.append([pname, 0, fails] + ["-"] * (len(COLUMNS) - 3))
            continue
        raw_f = [r for r in raw if math.isfinite(r)]
        rows.append([pname, n, fails, float(np.mean(raw_f)) if raw_f else "-", float(np.max(raw_f)) if raw_f else "-",
                     float(np.mean(fin)), float(np.max(fin)), int(np.sum(np.array(fin) > 1.05)), from_ompl,
                     float(np.mean(times)), float(np.max(times)), float(np.median(rates))])
    return rows


def planar(args, planners) -> None:
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
        setup_rows.append([sc.name, cm.grid_text().split(" grid")[0], cm.h * 1000, tf, tg, tq, len(qs)])
        problems.append((sc.name, cm, PlannerSettings(planners[0], args.time, sc.planner.seed), qs))
    print(format_table(["scenario", "grid", "res (mm)", "fields (s)", "reference graph (s)", "reference/query (s)",
                        "queries"], setup_rows, "planar setup (fields with rho_star, reference graph and search)"))
    print()
    rows = run_planners(planners, problems, args, args.verbose)
    print(format_table(COLUMNS, rows, f"planar: cost / grid optimum over {sum(len(p[3]) for p in problems)} queries, "
                                      f"{_mode(args)}"))


def spatial(args, planners) -> None:
    from test_planning_spatial import random_queries as random_queries_3d, synthetic_field

    rng = np.random.default_rng(args.seed)
    mf = synthetic_field()
    problems = []
    setup_rows = []
    cases = [("synthetic phi_hat_max x1", mf, "phi_hat_max", 1.0, True),
             ("synthetic G_norm x4", mf, "G_norm", 4.0, False)]
    if args.spatial_scenario:
        sc = load_scenario(ROOT / "scenarios" / "phantom15_spatial.toml")
        t0 = time.perf_counter()
        mfs = fields_for_planning(sc, args.resolution3, workers=args.workers)
        print(f"phantom15_spatial fields: {time.perf_counter() - t0:.1f} s")
        p = sc.planner
        cases.append((sc.name, mfs, p.metric, p.weight, p.certifiable))
    for label, field, metric, weight, cert in cases:
        cm = CostMap(field, metric, weight, cert, 0.02)
        t0 = time.perf_counter()
        graph = GridGraph(cm, args.radius3)
        tg = time.perf_counter() - t0
        qs = []
        across = ((-0.06, 0.0, 0.33), (0.06, 0.0, 0.33))
        if cm.point_ok(*across[0]) and cm.point_ok(*across[1]) and cm.connected(*across):
            qs.append(("across-axis", *across, grid_optimum(cm, *across, args.radius3, graph=graph).cost))
        for k, (s, g, ref) in enumerate(random_queries_3d(cm, graph, args.random3, rng, radius=args.radius3)):
            qs.append((f"rand{k}", s, g, ref.cost))
        t0 = time.perf_counter()
        for _, s, g, _ in qs:
            grid_optimum(cm, s, g, args.radius3, graph=graph)
        tq = (time.perf_counter() - t0) / max(len(qs), 1)
        setup_rows.append([label, cm.grid_text().split(" grid")[0], cm.h * 1000, graph.edges, tg, tq, len(qs)])
        problems.append((label, cm, PlannerSettings(planners[0], args.time, 1), qs))
    print(format_table(["fields", "grid", "res (mm)", "reference edges", "reference graph (s)", "reference/query (s)",
                        "queries"], setup_rows, "spatial setup (reference graph and search)"))
    print()
    rows = run_planners(planners, problems, args, args.verbose)
    mode = _mode(args)
    seed = "without the coarse cell-graph candidate" if args.no_grid_seed else "with the coarse cell-graph candidate"
    print(format_table(COLUMNS, rows, f"spatial: cost / grid optimum over {sum(len(p[3]) for p in problems)} "
                                      f"queries, {mode}, {seed}"))


def _mode(args) -> str:
    if args.uncapped:
        return f"no iteration budget, {args.time:g} s time cap"
    budget = "each planner's default iteration budget" if args.iterations is None else f"{args.iterations} iterations"
    return "errplan settings (" + budget + ("" if args.time is None else f", {args.time:g} s time cap") + ")"


def arm_checks_case(args) -> None:
    from errplan.api import load_setup
    from errplan.models import arm_model
    from errplan.kinematics.urdf.broadphase import piece_memory
    from errplan.planning.arm_checks import ArmChecks

    path = Path(args.arm_scenario) if args.arm_scenario else ROOT / "scenarios" / "ur5_triad.toml"
    st = load_setup(path)
    cost_rows, plan_rows = [], []
    for name in st.arm_names:
        sc = st.moving(name)
        checks = ArmChecks.from_model(arm_model(sc))
        if checks is None:
            raise SystemExit(f"{path}: no [setup] arm_clearance, so no arm checks")
        rng = np.random.default_rng(args.seed)
        lo = np.array([sc.fields.region[k][0] for k in "xyz"])
        hi = np.array([sc.fields.region[k][1] for k in "xyz"])
        tips = lo + rng.random((args.arm_states, 3)) * (hi - lo)
        d = rng.normal(size=tips.shape)
        ends = tips + 0.03 * d / np.linalg.norm(d, axis=1)[:, None]
        checks.point_ok(*tips[0])  # compiled (or loaded) before the clock
        row = [name]
        answers = {}
        for label, fn, pairs in (("state", "point_ok", [(t,) for t in tips]),
                                 ("motion", "motion_ok", list(zip(tips, ends)))):
            args_of = [tuple(np.concatenate(p)) for p in pairs]
            f = getattr(checks, fn + "_exact")
            t0 = time.process_time()  # CPU time: the machine may be shared
            answers[label + "_exact"] = [f(*p) for p in args_of]
            row.append((time.process_time() - t0) / len(pairs) * 1e3)
            f = getattr(checks, fn)
            cpu = wall = math.inf
            for _ in range(args.arm_repeats):
                checks._memory = piece_memory(*checks._kernel_args()[0][2:4])
                t0, w0 = time.process_time(), time.perf_counter()
                answers[label] = [f(*p) for p in args_of]
                cpu, wall = min(cpu, time.process_time() - t0), min(wall, time.perf_counter() - w0)
            row += [cpu / len(pairs) * 1e3, wall / len(pairs) * 1e3]
            row.append(int(np.sum(np.array(answers[label + "_exact"]) != np.array(answers[label]))))
        row.insert(5, float(np.mean(answers["state"])))
        row.append(float(np.mean(answers["motion"])))
        cost_rows.append(row)
        if not args.arm_plan:
            continue
        t0 = time.perf_counter()
        mf = fields_for_planning(sc, args.resolution3, workers=args.workers)
        tf = time.perf_counter() - t0
        cm = costmap_for(sc, mf)
        for q in sc.queries:
            for way, compiled in (("Python", False), ("compiled", True)):
                cm.arm_checks.compiled = compiled
                stt = PlannerSettings.from_model(sc, time=args.time if args.arm_time is None else args.arm_time)
                t0 = time.perf_counter()
                try:
                    qp = plan_query(cm, q.start, q.goal, stt, name=q.name)
                except ErrplanError as e:
                    plan_rows.append([q.name, way, "-", "failed", time.perf_counter() - t0, "-", str(e)[:40]])
                    continue
                plan_rows.append([q.name, way, qp.iterations, qp.stopped_by, qp.time_solve, qp.planned.cost,
                                  f"{tf:.0f} s fields"])
    print(format_table(["arm", "state Python (ms)", "state compiled (ms)", "state compiled wall (ms)",
                        "states differing", "states kept", "motion Python (ms)", "motion compiled (ms)", "motion compiled wall (ms)",
                        "motions differing", "motions kept"], cost_rows,
                       f"arm checks on {path.name}: {args.arm_states} random tips of the fields' region and as "
                       f"many 3 cm motions from them, CPU time per check (compiled: also wall; best of "
                       f"{args.arm_repeats} runs)"))
    if plan_rows:
        print()
        print(format_table(["query", "arm check", "iterations", "stopped by", "search (s)", "cost", "note"], plan_rows,
                           f"plans on {path.name} with either arm check (seed of the scenario, "
                           + ("the scenario's iteration budget)" if (args.time if args.arm_time is None else args.arm_time) is None
                              else f"{args.time if args.arm_time is None else args.arm_time:g} s time cap)")))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dims", default="2,3", help="which tables: 2 (planar), 3 (spatial), arms (two-arm checks)")
    ap.add_argument("--arm-scenario", default=None, help="the setup of --dims arms (default scenarios/ur5_triad.toml)")
    ap.add_argument("--arm-states", type=int, default=300, help="random tips (and motions) per arm of --dims arms")
    ap.add_argument("--arm-repeats", type=int, default=5, help="runs of the compiled checks (best kept) of --dims arms")
    ap.add_argument("--arm-plan", action=argparse.BooleanOptionalAction, default=True,
                    help="also plan the setup's queries with either check (--dims arms)")
    ap.add_argument("--arm-time", type=float, default=None, help="time cap of those plans (default --time)")
    ap.add_argument("--iterations", type=int, default=None, help="search budget per query (default: each planner's)")
    ap.add_argument("--time", type=float, default=None, help="time cap per query, s (default: none; 1 with --uncapped)")
    ap.add_argument("--random", type=int, default=8, help="planar random queries per scenario (half of them hard)")
    ap.add_argument("--random3", type=int, default=8, help="spatial random queries per objective (half hard)")
    ap.add_argument("--planners", default="BITstar,RRTstar,InformedRRTstar,SORRTstar,FMT,BFMT,RRTConnect")
    ap.add_argument("--uncapped", action="store_true", help="no iteration budget: every planner runs until the time cap")
    ap.add_argument("--no-grid-seed", action="store_true", help="no coarse cell-graph candidate (spatial default: on)")
    ap.add_argument("--resolution", type=float, default=None, help="planar fields resolution (m)")
    ap.add_argument("--resolution3", type=float, default=None, help="phantom15_spatial fields resolution (m)")
    ap.add_argument("--spatial-scenario", action="store_true", help="also plan on phantom15_spatial.toml's fields")
    ap.add_argument("--workers", type=int, default=None, help="field workers for --spatial-scenario")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--radius", type=int, default=4, help="move radius of the planar grid reference")
    ap.add_argument("--radius3", type=int, default=3, help="move radius of the spatial grid reference")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args(argv)
    if args.uncapped and args.time is None:
        args.time = 1.0
    planners = args.planners.split(",")
    for p in planners:
        if p not in PLANNERS:
            raise SystemExit(f"unknown planner {p}; choose from {', '.join(PLANNERS)}")
    dims = set(args.dims.split(","))
    if "2" in dims:
        planar(args, planners)
        print()
    if "3" in dims:
        spatial(args, planners)
        print()
    if "arms" in dims:
        arm_checks_case(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
