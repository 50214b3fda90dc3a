"""``errplan plan SCENARIO [--json F] [--record F.rrd] [--query NAME] [--iterations N] [--time T] [--planner NAME]
[--seed N] [--workers N] [--truth T.toml]``.

Plans every ``[[query]]`` of the scenario (planar or spatial) on its worst-case fields (errplan.planning), prints per
query the planned and the direct (straight) path (cost, length, max ||G||, max phi_hat_max), then
picks certified per-segment gains (errplan.gains), simulates both paths (errplan.pipeline) and
optionally records everything to rerun. ``--truth T.toml`` simulates the planned and direct paths on T's truth
(its arm and geometry, port and ``[effects]``) instead of the scenario's own. The JSON is the "plan JSON" of docs/interfaces.md
(``queries[].{name, start, goal, planned, direct, gains, simulation}``).

The fields' tiles and the queries' gains and simulations run on ``--workers`` processes (all cores); the
planner runs alone. A first run compiles the planner's, the gains' and the anatomy's kernels in a second
process meanwhile (:mod:`errplan.cli.warmup`), paused while the planner runs, so that it plans as a later
run does. The results are those of :func:`errplan.api.plan`, whatever the workers.
"""
from __future__ import annotations

import math

from ..report import Progress, format_table, write_json


def _num(x, scale: float = 1.0):
    return float("nan") if x is None else x * scale


def plan_table(plan) -> str:
    """The per-query table of a :class:`~errplan.planning.ScenarioPlan`, with a line for every query a time cap
    cut (such a plan depends on the machine)."""
    from ..planning.plan import NOT_REPRODUCIBLE, NOT_REPRODUCIBLE_REFINE

    rows = []
    for q in plan.queries:
        for label, p in (("planned", q.planned), ("direct", q.direct)):
            status = "yes" if p.valid else ("not certifiable" if p.in_workspace else "leaves workspace")
            rows.append([q.name if label == "planned" else "", label, _num(p.cost), p.length * 1000,
                         _num(p.max_G_norm), _num(p.max_phi_hat_max, 180 / math.pi),
                         _num(p.length_G_above_1, 1000), len(p.path), status])
    st = plan.settings
    cm = plan.costmap
    cert = f"certifiable (rho* <= {cm.rho_bound:g})" if cm.certifiable else "not restricted to certifiable tips"
    budget = f"{st.iteration_cap(cm.dim)} iterations per query" + (
        "" if st.time is None else f" (time cap {st.time:g} s)")
    title = (f"plan of {plan.scenario}: cost = integral (1 + {plan.weight:g} * {plan.metric}) ds, {cert}; "
             f"{st.planner}, {budget}, seed {st.seed}")
    table = format_table(["query", "path", "cost (m)", "length (mm)", "max ||G||", "max phi_hat_max (deg)",
                          "||G||>=1 (mm)", "vertices", "valid"], rows, title)
    lines = [table]
    for q in plan.queries:
        d, p = q.direct, q.planned
        if d.cost is not None and d.valid:
            change = f"cost {100 * (p.cost / d.cost - 1):+.1f}% vs direct, length {100 * (p.length / d.length - 1):+.1f}%"
        else:
            change = "the direct path is not usable (" + ("not certifiable" if d.in_workspace else "leaves the workspace") + ")"
        lines.append(f"{q.name}: {change}; search {q.time_solve:.2f} s ({q.iterations} iterations, stopped by "
                     f"{q.stopped_by}) + refine {q.time_refine:.2f} s")
        if q.stopped_by == "time":
            lines.append(f"{q.name}: " + NOT_REPRODUCIBLE.format(cap=st.time, iterations=q.iterations))
        elif q.refine_stopped_by == "time":
            lines.append(f"{q.name}: " + NOT_REPRODUCIBLE_REFINE.format(cap=st.time, evaluations=q.refine_evaluations))
    lines.append("max ||G||, max phi_hat_max: worst case along the path at the scenario gain; ||G||>=1: length of "
                 "the path where the worst-case ||G|| >= 1 (monotonic convergence not guaranteed at that gain)")
    shape = " x ".join(str(len(a)) for a in cm.mf.axes)
    lines.append(f"fields: {shape} grid at {cm.h * 1000:g} mm, computed in {plan.field_time:.1f} s")
    return "\n".join(lines)


def _workers(args) -> int:
    """``--workers`` (default: every core this process may use)."""
    from ..cluster import default_workers
    from ..errors import ErrplanError

    n = getattr(args, "workers", None)
    if n is None:
        return default_workers()
    if n < 1:
        raise ErrplanError(f"--workers {n}: expected a number of worker processes >= 1")
    return n


def _fields_part(sc) -> str | None:
    """The warm-up part of the search :func:`errplan.planning.plan.fields_for_planning` runs (with the exact
    |phi_max| in the plane, or in 3-D where it is the cost; :func:`errplan.cli.warmup.fields_part`)."""
    from . import warmup

    return warmup.fields_part(sc, sc.dim == 2 or sc.planner.metric == "phi_max")


def _warm_up(sc) -> None:
    """A first run: kernels compiled in a second process (:func:`errplan.cli.warmup.start`; a warm cache
    starts nothing), in the order the steps need them. In 3-D the fields' search first, while this process
    loads and checks the arm (its kinematics, its reachability map's build, the anatomy's clearances),
    then the planner's and the gains'; in the plane this process compiles the search itself (there is no
    map to build meanwhile) while the other compiles the planner's and the gains' kernels."""
    from . import warmup

    part = _fields_part(sc) if sc.dim == 3 else None
    warmup.start(((part,) if part else ()) + (f"plan{sc.dim}", f"gains{sc.dim}"))


def plan_arm(sc, args, progress=None, workers: int = 1, record: str | None = None, truth_sc=None):
    """:func:`errplan.api.plan` of one arm's model ``sc`` (``args``: ``query``, ``planner``, ``iterations``,
    ``time``, ``seed``), step by step: the fields on ``workers`` processes; the plan with a first run's warm-up
    paused (the planner's budget is CPU time it must not share); the queries' gains and simulations on
    ``workers`` processes, once the warm-up has compiled the gains' kernels and this process has loaded
    them (each worker has them). The same :class:`~errplan.planning.ScenarioPlan`."""
    import time as _time

    from ..api import _part
    from ..pipeline import run_pipeline
    from ..planning import plan_scenario
    from ..planning.plan import fields_for_planning
    from . import warmup

    part = _fields_part(sc)
    if sc.dim == 3 and warmup.active():  # a first run: what the replays call, here while the search compiles
        warmup.load_here(("arm",) + (("anatomy",) if sc.anatomy is not None else ()))
    if part:
        warmup.wait(part)
    t0 = _time.perf_counter()
    mf = fields_for_planning(sc, progress=_part(progress, 0.0, 0.4), workers=workers)
    t_fields = _time.perf_counter() - t0
    warmup.wait(f"plan{sc.dim}")
    with warmup.paused():
        plan = plan_scenario(sc, mf, query=args.query, planner=args.planner, time=args.time, seed=args.seed,
                             iterations=getattr(args, "iterations", None), progress=_part(progress, 0.4, 0.5))
    plan.field_time = t_fields
    warmup.wait(f"gains{sc.dim}")
    if workers > 1 and len(plan.queries) > 1:
        warmup.load_here((f"gains{sc.dim}",) + (("arm", "fields3g") if sc.dim == 3 else ()))
    res = run_pipeline(sc, plan.queries, mf, record=record, progress=_part(progress, 0.5, 1.0), workers=workers,
                       truth_sc=truth_sc)
    plan.runs = res["runs"]
    return plan


def run(args) -> int:
    from ..errors import ErrplanError
    from .. import api
    from ..pipeline import summary_table
    from ..planning import select_queries

    from ..inputs import check_output
    from . import check_seed

    from ..scenario import read_setup

    workers = _workers(args)
    _warm_up(read_setup(args.scenario).arms[0])  # before the checks: loading the arm compiles its kernels
    st = api.load_setup(args.scenario)
    truth_path = getattr(args, "truth", None)
    if st.several:
        if truth_path is not None:
            raise ErrplanError(f"--truth {truth_path}: a scenario with several instruments plans each arm among the "
                               "others; --truth takes a scenario with one arm")
        return _run_setup(st, args, workers)
    sc = st.arm(args.arm)
    truth_sc = None
    if truth_path is not None:
        from ..models import arm_model as _am
        from ..pipeline import check_truth_pair

        try:
            truth_sc = _am(api.load_scenario(truth_path))
        except ErrplanError as e:
            raise ErrplanError(f"--truth {truth_path}: {e}") from None
        check_truth_pair(sc, truth_sc)
    select_queries(sc, args.query)  # a bad --query fails before the fields are computed
    for opt, value in (("--json", args.json), ("--record", args.record)):
        check_output(opt, value)
    check_seed("--seed", args.seed)
    if args.seed is None and sc.planner.seed > 2**32 - 1:
        raise ErrplanError(f"{sc.source}: [planner] seed = {sc.planner.seed}: expected an integer from 0 to 4294967295")
    prog = Progress("plan", quiet=args.quiet)
    prog.quiet = prog.quiet or not prog.tty  # progress only on a terminal: an error stays the one line on stderr
    from ..models import arm_model

    sc = arm_model(sc)  # built once (in 3-D the arm's reachability map): every step below takes it
    plan = plan_arm(sc, args, prog, workers, record=args.record, truth_sc=truth_sc)
    prog.done()
    print(plan_table(plan))
    print()
    on = f"; simulated on the truth of {truth_sc.name} ({truth_path})" if truth_sc is not None else ""
    print(summary_table(plan.runs, f"certified gains and simulation: {sc.name}{on}"))
    if args.json:
        write_json(args.json, plan.to_json())
    if args.record:
        print(f"recording: {args.record}  (open it with `errplan view {args.record}`)")
    return 0


def _run_setup(st, args, workers: int = 1) -> int:
    """Several arms: every query (or ``--query``) with its arm (``--arm``: only that arm's), the other
    instruments held at rest and the endoscope's shaft as obstacles of the moving arm
    (:meth:`errplan.scenario.Setup.moving`); the plan JSON's queries add ``arm``, ``visible``, the shaft
    clearances and ``min_arm_clearance`` (:func:`setup_figures`)."""
    from ..errors import ErrplanError
    from ..inputs import check_output
    from ..pipeline import summary_table
    from . import check_seed

    names = [args.arm] if args.arm is not None else list(st.arm_names)
    if args.arm is not None:
        st.arm(args.arm)
    from ..models import build

    models = dict(zip(st.arm_names, build(st)))  # each arm built once, as it moves among the others
    jobs = []
    for n in names:
        sc = models[n]
        qs = [q for q in sc.queries if args.query is None or q.name == args.query]
        if qs:
            jobs.append((n, sc))
    if not jobs:
        what = f" of arm {args.arm!r}" if args.arm else ""
        if args.query:
            raise ErrplanError(f"--query {args.query!r}: no such query{what} in {st.source}")
        raise ErrplanError(f"{st.source}: no [[query]]{what} to plan")
    for opt, value in (("--json", args.json), ("--record", args.record)):
        check_output(opt, value)
    check_seed("--seed", args.seed)
    prog = Progress("plan", quiet=args.quiet)
    prog.quiet = prog.quiet or not prog.tty
    plans = []
    for n, sc in jobs:
        plans.append((n, sc, plan_arm(sc, args, prog, workers)))
    prog.done()
    out = {"scenario": st.name, "queries": []}
    for n, sc, plan in plans:
        print(plan_table(plan))
        print()
        print(summary_table(plan.runs, f"certified gains and simulation: {sc.name}"))
        j = plan.to_json()
        out.setdefault("objective", j["objective"])
        runs = {r.name: r for r in plan.runs}
        for qj, qp in zip(j["queries"], plan.queries):
            fig = setup_figures(st, n, sc, qp, runs.get(qp.name), qj, plan.costmap)
            out["queries"].append(qj)
            ms, vis, ma = fig["min_shaft_clearance"], fig["visible"], fig["min_arm_clearance"]
            mm = lambda x: "-" if x is None else f"{x * 1000:.1f} mm"  # noqa: E731
            vis_t = "-" if vis is None else f"{100 * vis:.0f}%"
            arm_t = "" if st.arm_clearance is None else (f", smallest arm clearance {mm(ma)} (required "
                                                         f"{st.arm_clearance * 1000:g} mm)")
            print(f"{qp.name} (arm {n}): smallest shaft clearance {mm(ms)} (path {mm(fig['min_shaft_clearance_path'])}, "
                  f"replays {mm(fig['min_shaft_clearance_replays'])}; required {st.shaft_clearance * 1000:g} mm), "
                  f"visible {vis_t}{arm_t}")
        print()
    if args.record:  # first: the recording is the output most likely to fail, written atomically
        from ..recording.setup import record_setup_plan

        record_setup_plan(args.record, st, plans)
    if args.json:
        write_json(args.json, out)
    if args.record:
        print(f"recording: {args.record}  (open it with `errplan view {args.record}`)")
    return 0


def setup_figures(st, name: str, sc, qp, run, qj: dict, cm) -> dict:
    """The several-instrument figures of one planned query, added to its plan JSON ``qj`` (and returned):

    * ``arm``, ``visible`` (:func:`errplan.planning.setup_checks.path_figures`);
    * ``min_shaft_clearance_path``: the exact distance from the robust moving shaft (every true port of
      the box) along the planned path to every held shaft and the endoscope's;
    * per simulated run of the planned path, under the scenario's truth (``simulation.planned``) and under
      every corner of the port box (``simulation.corners.planned[i]``), its ``min_shaft_clearance``: the
      shaft through that run's true port sweeping each step's triangle
      (:func:`errplan.planning.setup_checks.run_shaft_clearance`); ``min_shaft_clearance_replays`` the
      smallest of them;
    * ``min_shaft_clearance``: the smallest of the path's and the replays' (None when nothing is held);
    * ``min_arm_clearance``: with ``[setup] arm_clearance``, the smallest clearance between the moving
      arm's links along the planned path (sampled as the planner's motion check samples it) and every held
      arm's (:meth:`errplan.planning.arm_checks.ArmChecks.path_clearance`); None without arm checks.
    """
    from ..pipeline import corner_plant, truth_plant
    from ..planning.setup_checks import held_hulls, path_figures, run_shaft_clearance

    fig = path_figures(st, name, qp.planned.path)
    path_min = fig.pop("min_shaft_clearance")
    hulls = held_hulls(st, name)
    reps = []
    if run is not None and hulls:
        sim = qj.get("simulation", {})
        d = run_shaft_clearance(hulls, truth_plant(sc).true_port, run.sim_planned.sim.tip)
        sim.get("planned", {})["min_shaft_clearance"] = d
        reps.append(d)
        corner_js = sim.get("corners", {}).get("planned", [])
        for i, (th, rep) in enumerate(zip(run.corners, run.corner_planned)):
            d = run_shaft_clearance(hulls, corner_plant(sc, th).true_port, rep.sim.tip)
            if i < len(corner_js):
                corner_js[i]["min_shaft_clearance"] = d
            reps.append(d)
    rep_min = min(reps) if reps else None
    both = [x for x in (path_min, rep_min) if x is not None]
    checks = getattr(cm, "arm_checks", None)
    arm_min = None
    if checks is not None:
        arm_min = checks.path_clearance(qp.planned.path)
        arm_min = None if not math.isfinite(arm_min) else arm_min
    fig.update(min_shaft_clearance=min(both) if both else None, min_shaft_clearance_path=path_min,
               min_shaft_clearance_replays=rep_min, min_arm_clearance=arm_min)
    qj.update(fig)
    return fig
