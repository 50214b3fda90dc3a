"""Planning a query and a scenario: settings, the two-phase search, refinement, results.

:func:`plan_query` checks the endpoints (one clear :class:`~errplan.errors.InfeasibleError` naming
the query, the endpoint and the value), runs the OMPL search (:mod:`errplan.planning.ompl_adapter`)
inside the box where a path cheaper than a known one can lie (:func:`search_box`), refines the best
path (:func:`errplan.planning.refine.refine_path`) and reports planned vs direct
(:class:`QueryPlan`). :func:`plan_scenario` does it for every ``[[query]]`` of a scenario on its
worst-case fields (:class:`ScenarioPlan`). The same code plans planar (``[y, z]``) and spatial
(``[x, y, z]``) scenarios; only the cost map's dimension differs.
"""
from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..errors import ErrplanError, InfeasibleError
from . import ompl_adapter
from .costmap import CostMap
from .ompl_adapter import DEFAULT_PLANNER, check_planner, default_iterations
from .refine import REFINE_EVALUATIONS, refine_path
from .report import PathReport, jsonable, path_report
from .seed import cell_graph, seed_path

# Whether plan_query adds the coarse cell-graph path (errplan.planning.seed) as a candidate, by
# dimension: in the plane the sampling planners find the right side of every hole within the budget
# (benchmarks/planning.py, planar tables), in space they miss narrow passages.
GRID_SEED = {2: False, 3: True}
#: The line the plan table prints for a query whose search the time cap cut (``stopped_by`` "time"), and
#: for one whose refinement it cut (``refine_stopped_by`` "time").
NOT_REPRODUCIBLE = ("stopped by the time cap ({cap:g} s) after {iterations} iterations: this plan is not "
                    "reproducible on another machine (set [planner] iterations and drop the cap)")
NOT_REPRODUCIBLE_REFINE = ("refinement stopped by the time cap ({cap:g} s) after {evaluations} evaluations: this "
                           "plan is not reproducible on another machine (drop the cap)")


def _is_count(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


@dataclass(frozen=True)
class PlannerSettings:
    """How to search: OMPL planner name, budgets per query, seed, refinement.

    The budgets are counted, so a plan is a function of the scenario and the seed on every machine:
    ``iterations`` (default :func:`~errplan.planning.ompl_adapter.default_iterations` of the planner and
    dimension) for the search, ``refine_evaluations`` (default
    :data:`~errplan.planning.refine.REFINE_EVALUATIONS`) for the refinement, of them at most
    ``refine_arm_checks`` (default :data:`~errplan.planning.refine.REFINE_ARM_CHECKS`) clearance checks with
    arm checks. ``time`` (s per query, default
    None: no cap) is a safety cap only: a search or refinement it cuts ends by the clock, and the plan says
    so (``stopped_by`` "time"): such a plan depends on the machine.
    """

    planner: str = DEFAULT_PLANNER
    time: float | None = None
    seed: int = 1
    iterations: int | None = None
    refine: bool = True
    refine_evaluations: int | None = None
    refine_arm_checks: int | None = None
    grid_seed: bool | None = None  # add the coarse cell-graph candidate (None: GRID_SEED[dim])

    @classmethod
    def from_model(cls, m, planner: str | None = None, time: float | None = None,
                   seed: int | None = None, iterations: int | None = None, **kw) -> "PlannerSettings":
        """The ``[planner]`` table of an arm's model (or scenario), ``planner``/``time``/``seed``/``iterations``
        overriding it."""
        p = m.planner
        t = time if time is not None else getattr(p, "time", None)
        it = iterations if iterations is not None else getattr(p, "iterations", None)
        return cls(planner=planner or p.planner, time=None if t is None else float(t),
                   seed=int(seed if seed is not None else p.seed), iterations=it, **kw)

    def iteration_cap(self, dim: int = 2) -> int:
        """The search's budget per query (iterations) in dimension ``dim``."""
        if self.iterations is not None:
            return int(self.iterations)
        return default_iterations(self.planner, dim)

    def refine_budget(self) -> int:
        """The refinement's budget per path (segment evaluations)."""
        return REFINE_EVALUATIONS if self.refine_evaluations is None else int(self.refine_evaluations)

    def use_grid_seed(self, dim: int = 2) -> bool:
        return GRID_SEED.get(dim, True) if self.grid_seed is None else bool(self.grid_seed)

    def check(self) -> None:
        check_planner(self.planner)
        if self.time is not None and (isinstance(self.time, bool) or not (self.time > 0 and math.isfinite(self.time))):
            raise ErrplanError(f"time = {self.time!r}: expected a time cap > 0 s (or none)")
        if self.iterations is not None and not (_is_count(self.iterations) and self.iterations >= 1):
            raise ErrplanError(f"iterations = {self.iterations!r}: expected an integer >= 1 (the search's budget per query)")
        for key in ("refine_evaluations", "refine_arm_checks"):
            v = getattr(self, key)
            if v is not None and not (_is_count(v) and v >= 0):
                raise ErrplanError(f"{key} = {v!r}: expected an integer >= 0")
        if isinstance(self.seed, bool) or self.seed < 0:
            raise ErrplanError(f"seed = {self.seed!r}: expected an integer >= 0")


@dataclass
class QueryPlan:
    """The plan of one query: planned and direct paths, and how the search went.

    ``extra`` holds keys added by later steps (``gains``, ``simulation``); :meth:`to_json` merges it.
    """

    name: str
    start: tuple[float, ...]
    goal: tuple[float, ...]
    planned: PathReport
    direct: PathReport
    planner: str
    seed: int
    iterations: int
    stopped_by: str  # how the last search phase ended (see plan_query): "iterations" (the budget),
    #                  "sampling" (stalled informed sampling), "planner" (by itself), "time" (the time cap,
    #                  when set, cut the search: the plan depends on the machine)
    time_solve: float
    time_refine: float
    raw_cost: float  # cost of the planner's own path, before refine_path
    extra: dict = field(default_factory=dict)
    seed_cost: float | None = None  # cost of the coarse cell-graph path (errplan.planning.seed), if used
    source: str = "planner"  # the candidate the returned path was refined from: "planner", "first
    #                          solution", "direct" or "grid seed"
    refine_evaluations: int = 0  # segment evaluations the refinement spent (its counted budget)
    refine_stopped_by: str = "converged"  # "converged", "evaluations" (its budget), "arm checks" (their share
    #                                       of it) or "time" (the cap)
    time_cap: float | None = None  # the settings' time cap (s), None without one

    @property
    def reproducible(self) -> bool:
        """Whether the plan is a function of the scenario and the seed: no time cap cut it."""
        return self.stopped_by != "time" and self.refine_stopped_by != "time"

    @property
    def time_total(self) -> float:
        return self.time_solve + self.time_refine

    def to_json(self, timing: bool = True) -> dict:
        """The query object of the plan JSON; ``timing=False`` leaves out the two wall-clock times,
        the only values that differ between two runs with the same seed and settings."""
        out = {"name": self.name, "start": [float(v) for v in self.start],
               "goal": [float(v) for v in self.goal],
               "planned": self.planned.to_json(), "direct": self.direct.to_json(),
               "search": {"planner": self.planner, "seed": self.seed, "iterations": self.iterations,
                          "stopped_by": self.stopped_by, "time_solve": self.time_solve,
                          "time_refine": self.time_refine, "raw_cost": jsonable(self.raw_cost),
                          "grid_seed_cost": jsonable(self.seed_cost), "source": self.source,
                          "refine_evaluations": self.refine_evaluations,
                          "refine_stopped_by": self.refine_stopped_by, "time_cap": self.time_cap,
                          "reproducible": self.reproducible}}
        if not timing:
            del out["search"]["time_solve"], out["search"]["time_refine"]
        out.update(self.extra)
        return out


@dataclass
class ScenarioPlan:
    """Plans of a scenario's queries, the objective they share and the field they were made on."""

    scenario: str
    metric: str
    weight: float
    certifiable: bool
    settings: PlannerSettings
    queries: list[QueryPlan]
    costmap: CostMap
    field_time: float = 0.0
    runs: list = field(default_factory=list)  # simulated runs (errplan.api.plan), for the summary table

    def to_json(self, timing: bool = True) -> dict:
        interp = "bilinear" if self.costmap.dim == 2 else "trilinear"
        return {"scenario": self.scenario,
                "objective": {"metric": self.metric, "weight": self.weight, "certifiable": self.certifiable,
                              "certify_margin": self.costmap.certify_margin,
                              "resolution": self.costmap.h,
                              "definition": f"integral of (1 + weight * metric) ds, metric {interp} in the field"},
                "queries": [q.to_json(timing) for q in self.queries]}


# ============================================================================= planning
def check_endpoints(cm: CostMap, start, goal, name: str = "query") -> None:
    """Raise :class:`InfeasibleError` naming the endpoint, the cause and by how much when the start
    or goal is unusable, or when they lie in disconnected parts of the usable region."""
    from .arm_checks import explain_point as explain_arms

    for what, p in (("start", start), ("goal", goal)):
        msg = explain_arms(cm, p, f"{name}: {what}") or cm.explain_point(p, f"{name}: {what}")
        if msg:
            raise InfeasibleError(msg)
    if not cm.connected(start, goal):
        raise InfeasibleError(f"{name}: start {list(map(float, start))} and goal {list(map(float, goal))} lie in "
                              f"disconnected parts of the usable region: no path exists")


def search_box(cm: CostMap, start, goal, bound_cost: float) -> tuple[float, ...]:
    """Bounding box (``(lo, hi)`` per axis, flat) of every path from ``start`` to ``goal`` cheaper
    than ``bound_cost``: such a path through x is at least ``|x - start| + |x - goal|`` long and
    costs at least ``f_min`` per metre, so x lies in the ellipse (ellipsoid of revolution in space)
    with foci start, goal and major axis ``bound_cost / f_min``. Padded by two cells and clipped to
    the grid."""
    s, g = np.asarray(start, float), np.asarray(goal, float)
    d = float(np.linalg.norm(g - s)) if cm.dim != 2 else float(np.hypot(*(g - s)))
    a = max(0.5 * bound_cost / cm.f_min, 0.5 * d)
    b = math.sqrt(max(a * a - 0.25 * d * d, 0.0))
    if cm.dim == 2:
        th = math.atan2(g[1] - s[1], g[0] - s[0]) if d > 0 else 0.0
        half = [math.sqrt((a * math.cos(th)) ** 2 + (b * math.sin(th)) ** 2),
                math.sqrt((a * math.sin(th)) ** 2 + (b * math.cos(th)) ** 2)]
    else:
        e = (g - s) / d if d > 0 else np.eye(cm.dim)[0]
        half = [math.sqrt(a * a * e[k] ** 2 + b * b * (1.0 - e[k] ** 2)) for k in range(cm.dim)]
    c = 0.5 * (s + g)
    lim = cm.bounds
    out = []
    for k in range(cm.dim):
        hk = half[k] + 2 * cm.h
        out += [max(lim[2 * k], c[k] - hk), min(lim[2 * k + 1], c[k] + hk)]
    return tuple(out)


def _no_path(name, st, start, goal, t_begin, used, status, why) -> InfeasibleError:
    more = ("a longer --time cap (or none)" if why == "time"
            else "more iterations ([planner] iterations or --iterations)")
    return InfeasibleError(
        f"{name}: {st.planner} found no path from {list(start)} to {list(goal)} within the budget "
        f"({_time.perf_counter() - t_begin:.2f} s, {used} iterations; status: {status}); try {more}")


def plan_query(cm: CostMap, start, goal, settings: PlannerSettings | None = None, name: str = "query",
               workspace_map: CostMap | None = None) -> QueryPlan:
    """Plan one query on ``cm`` with OMPL, refine the solution, and report planned vs direct.

    ``start``, ``goal``: d-vectors (m) in the field's axis order. The search runs in the box where
    a path cheaper than a known one can be (:func:`search_box`): the cheaper of the straight line
    (when it is usable) and the coarse cell-graph path (:func:`errplan.planning.seed.seed_path`,
    when ``settings.use_grid_seed(d)``); without either, a first search over the whole grid stops
    at its first solution, whose cost bounds the box of the second. This keeps informed samplers
    (BIT*, Informed RRT*) from stalling on a small informed set in a large space. Every iteration
    counts against one budget (``settings.iteration_cap``), so the search ends at the same point on every
    machine; the optional time cap (``settings.time``) bounds the whole query. The best of the planner's path,
    the first solution and the straight line is refined (:func:`refine_path`), and so is the
    coarse path; the cheaper result is returned, so the plan is never costlier than a usable
    straight line.

    Raises :class:`InfeasibleError` for an unusable start or goal, disconnected endpoints, or no
    exact solution within the budget (no partial result is returned).
    """
    st = settings or PlannerSettings()
    st.check()
    start = tuple(float(v) for v in start)
    goal = tuple(float(v) for v in goal)
    check_endpoints(cm, start, goal, name)
    ompl_adapter.quiet()
    use_seed = st.use_grid_seed(cm.dim)
    if use_seed:
        cell_graph(cm)  # built once per cost map, outside the query's budget (like the cost map itself)
    t_begin = _time.perf_counter()
    direct = path_report(cm, np.array([start, goal]), workspace_map)
    if math.dist(start, goal) < 1e-12:  # nothing to plan
        return QueryPlan(name, start, goal, direct, direct, st.planner, st.seed, 0, "planner", 0.0, 0.0, 0.0,
                         time_cap=st.time)
    t_end = None if st.time is None else t_begin + st.time  # a safety cap only, when the user set one
    cap = st.iteration_cap(cm.dim)
    # Reseed before anything draws from the RNG so that each query is a function of the seed,
    # whatever was planned before in this process.
    ompl_adapter.seed(st.seed)
    from .arm_checks import path_clear  # the arm checks, which the fields and the cell graph do not hold

    direct_ok = direct.valid and path_clear(cm, [start, goal])
    bound = direct.cost if direct_ok else math.inf
    coarse = seed_path(cm, start, goal, limit=bound) if use_seed else None
    coarse = coarse if coarse is None or path_clear(cm, coarse[0]) else None
    if coarse is not None:
        bound = coarse[1]
    used = 0
    first = None
    status = ""
    if not math.isfinite(bound):
        first, used, why, status = ompl_adapter.search(cm, start, goal, st.planner, None, cap, t_end, first_only=True,
                                                         budget=cap)
        if first is None:
            raise _no_path(name, st, start, goal, t_begin, used, status, why)
        bound = cm.path_cost(first)[1]
    box = search_box(cm, start, goal, bound)
    raw, n, why, status = ompl_adapter.search(cm, start, goal, st.planner, box, max(cap - used, 1), t_end,
                                              first_only=False, budget=cap)
    used += n
    if raw is None:
        raw = first
    if raw is None and coarse is None and not direct_ok:
        raise _no_path(name, st, start, goal, t_begin, used, status, why)
    cands = []  # (source, path, exact cost)
    if raw is not None:
        ok, raw_cost = cm.path_cost(raw)
        if not ok:  # cannot happen with the exact motion validator; refuse rather than return it
            raise InfeasibleError(f"{name}: internal: the planner's path leaves the usable region")
        cands.append(("planner" if raw is not first else "first solution", raw, raw_cost))
    else:
        raw_cost = math.inf
    if first is not None and first is not raw:
        cands.append(("first solution", first, cm.path_cost(first)[1]))
    if direct_ok:
        cands.append(("direct", np.array([start, goal]), direct.cost))
    best = min(cands, key=lambda c: c[2]) if cands else None  # the first of equal costs
    time_solve = _time.perf_counter() - t_begin
    t1 = _time.perf_counter()
    results = []
    spent, refine_why = 0, "converged"
    for src, path, cost in ([best] if best else []) + ([("grid seed", *coarse)] if coarse is not None else []):
        if st.refine:
            rr = refine_path(cm, path, evaluations=st.refine_budget(), arm_checks=st.refine_arm_checks, deadline=t_end)
            path, cost = rr.path, rr.cost
            spent += rr.evaluations
            if rr.stopped_by != "converged" and refine_why != "time":
                refine_why = rr.stopped_by
        results.append((cost, len(results), src, path))
    cost, _, source, path = min(results)
    time_refine = _time.perf_counter() - t1
    planned = path_report(cm, path, workspace_map)
    return QueryPlan(name, start, goal, planned, direct, st.planner, st.seed, used, why, time_solve,
                     time_refine, float(raw_cost), seed_cost=None if coarse is None else float(coarse[1]),
                     source=source, refine_evaluations=spent, refine_stopped_by=refine_why, time_cap=st.time)


def fields_for_planning(sc, resolution: float | None = None, progress=None, **kw):
    """The worst-case fields a scenario's planner needs (``rho_star`` too when certifiable or when
    it is the metric), at ``resolution`` (default ``[fields] resolution``). Further keywords
    (``workers``, ``metrics``, ``scheduler``) go to :func:`errplan.fields.compute_fields`."""
    from ..fields import compute_fields

    need_rho = sc.planner.certifiable or sc.planner.metric == "rho_star"
    kw = {k: v for k, v in kw.items() if v is not None}
    if sc.dim == 3 and "metrics" not in kw:
        # In 3-D the exact |phi_max| is the costly metric: compute it only when it is the cost.
        kw["metrics"] = ("G_norm", "phi_hat_max") + (("phi_max",) if sc.planner.metric == "phi_max" else ())
    return compute_fields(sc, resolution, rho_star=need_rho, progress=progress, **kw)


#: m: with ``[planner] certifiable = true`` the planner keeps ``[anatomy] clearance + BALL_MARGIN`` from the
#: anatomy. A segment's convergence ball has radius = its length + the switch tolerance (1 mm by default,
#: :class:`errplan.gains.GainOptions`), so a path that only keeps the clearance can never have a clear ball
#: where it grazes an obstacle; with this margin the gain schedule's halving makes every ball clear with
#: segments of up to ``BALL_MARGIN - switch_tolerance`` (1 mm) there.
BALL_MARGIN = 0.002


def costmap_for(sc, mf) -> CostMap:
    """The :class:`CostMap` of a scenario's ``[planner]`` table on the fields ``mf``."""
    p = sc.planner
    need_rho = p.certifiable or p.metric == "rho_star"
    if need_rho and getattr(mf, "rho_star", None) is None:
        raise ErrplanError("the fields have no rho_star (needed by [planner] certifiable = true or metric = "
                           "\"rho_star\"): compute them with rho_star=True (errplan fields --rho-star)")
    dim = sc.dim
    if mf.dim != dim:
        raise ErrplanError(f"{sc.source}: the fields are {mf.dim}-D but the scenario is {dim}-D")
    from ..fields.compute import anatomy_model

    margin = BALL_MARGIN if p.certifiable else 0.0
    cm = CostMap(mf, p.metric, p.weight, p.certifiable, p.certify_margin).attach_anatomy(anatomy_model(sc), margin)
    if getattr(sc, "view", None) is not None:  # [endoscope] keep_visible (errplan.scenario.Setup.moving)
        from .setup_checks import view_checker

        cm.attach_view(view_checker(sc))
    from ..models import arm_model
    from .arm_checks import ArmChecks, attach

    return attach(cm, ArmChecks.from_model(arm_model(sc)))  # [setup] arm_clearance (errplan.scenario.Setup.moving)


def select_queries(sc, name: str | None = None) -> list:
    """The scenario's queries, or only the one called ``name`` (clear error listing the names)."""
    qs = list(sc.queries)
    if not qs:
        pt = "[" + ", ".join(getattr(sc, "axes", ("y", "z"))) + "]"
        raise ErrplanError(f"{sc.source}: the scenario has no [[query]] to plan (add [[query]] tables with "
                           f"name, start = {pt}, goal = {pt})")
    if name is None:
        return qs
    for q in qs:
        if q.name == name:
            return [q]
    raise ErrplanError(f"--query {name!r}: no such query in {sc.source}; its queries are: "
                       + ", ".join(repr(q.name) for q in qs))


def plan_scenario(sc, mf=None, *, query: str | None = None, planner: str | None = None,
                  time: float | None = None, seed: int | None = None, iterations: int | None = None,
                  settings: PlannerSettings | None = None,
                  progress: Callable[[float, str], None] | None = None,
                  workers: int | None = None) -> ScenarioPlan:
    """Plan every ``[[query]]`` of a scenario (or only ``query``) on its worst-case fields.

    ``mf`` (a :class:`~errplan.fields.MetricField`, planar or spatial) is computed when not given
    (:func:`fields_for_planning`; ``workers`` goes to :func:`errplan.fields.compute_fields`).
    ``planner``, ``time`` (the time cap), ``seed`` and ``iterations`` (the search's budget) override
    ``[planner]``. Every endpoint is checked before
    any search, so a bad query fails fast with :class:`InfeasibleError`. Returns a
    :class:`ScenarioPlan`.
    """
    qs = select_queries(sc, query)
    st = settings or PlannerSettings.from_model(sc, planner=planner, time=time, seed=seed, iterations=iterations)
    st.check()
    t0 = _time.perf_counter()
    if mf is None:
        mf = fields_for_planning(sc, progress=progress, workers=workers)
    field_time = _time.perf_counter() - t0
    cm = costmap_for(sc, mf)
    if not cm.any_usable:
        raise InfeasibleError(f"{sc.source}: no grid cell is usable for planning (robust workspace"
                              + (f" with rho_star <= {cm.rho_bound:g}" if cm.certifiable else "") + " is empty)")
    for q in qs:
        check_endpoints(cm, q.start, q.goal, f"query {q.name!r}")
    wm = cm
    if cm.certifiable:  # the same anatomy, with its margin, and the same view
        wm = CostMap(mf, cm.metric, cm.weight, certifiable=False).attach_anatomy(cm.anatomy)
        wm.anatomy_margin = cm.anatomy_margin
        if getattr(cm, "_view", None) is not None:
            wm.attach_view(cm._view)
    plans = []
    for n, q in enumerate(qs):
        if progress:
            progress(n / len(qs), f"planning {q.name}")
        plans.append(plan_query(cm, q.start, q.goal, st, name=f"query {q.name!r}", workspace_map=wm))
        plans[-1].name = q.name
    if progress:
        progress(1.0, "planned")
    return ScenarioPlan(sc.name, cm.metric, cm.weight, cm.certifiable, st, plans, cm, field_time)
