"""The OMPL side of planning: the only module that imports ``ompl`` (lazily, on first use).

- **state space**: a d-dimensional ``RealVectorStateSpace`` (d = 2: ``[y, z]``, d = 3:
  ``[x, y, z]``, chosen by the cost map's dimension) over a box (the grid, or the search box of
  :func:`errplan.planning.plan.search_box`);
- **validity**: the point is in a usable cell (:meth:`CostMap.point_ok`, compiled) and, with an
  anatomy attached (:meth:`CostMap.attach_anatomy`), robustly clear of every obstacle;
- **motion validation** (:class:`CellWalkMotionValidator`) is exact: every cell the straight motion
  crosses is usable (the compiled cell walk), so paths never leave the usable region between their
  vertices; with an anatomy, every tip of the motion is also robustly clear (exact: the hull of the
  port box and the motion's two ends, :mod:`errplan.anatomy`); the cost map's further checks ride on the
  same call (``cm._clear``): the endoscope's view, and the arms outside the body
  (:mod:`errplan.planning.arm_checks`, the dearest, last: compiled with a capsule broad phase, coal's
  mesh queries only where the arms come near each other);
- **objective** (:class:`FieldObjective`): ``integral (1 + weight * metric) ds``, exact on the
  multilinear field, computed in ``motionCost`` by the compiled walk; ``motionCostHeuristic`` is the
  admissible ``distance * min(1 + weight * metric)``. (In ompl 2.0.1 a Python
  ``StateCostIntegralObjective`` subclass is never called from C++, hence ``motionCost``.)
- **planner by name** (:data:`PLANNERS`), stopped by its iteration budget, a guard against stalled
  informed sampling (counted too), (optionally) the first exact solution, or only when the user set one,
  a time cap (:func:`search`).

The Python overrides are as thin as OMPL allows: each reads the d coordinates of its states and
makes one call into a compiled kernel with one packed array (about 1 us per call, against 5-50 us
for a pure-Python walk; benchmarks/planning.py).
"""
from __future__ import annotations

import math
import time as _time
from typing import Any

import numpy as np

from ..errors import ErrplanError
from . import cellwalk

# Planners that work with a Python objective in ompl 2.0.1 (PRM/PRMstar deadlock on the GIL with a
# Python objective; AORRTC fails when the straight line is valid).
PLANNERS = ("RRTstar", "InformedRRTstar", "SORRTstar", "BITstar", "FMT", "BFMT", "RRTConnect")
DEFAULT_PLANNER = "BITstar"
# The search's budget per query when ``[planner] iterations`` does not set one: iterations (planner
# termination checks), per planner and dimension. A search ends at its budget on any machine, so a plan
# is a function of the scenario and the seed. These are the caps the searches had when the budget was a
# time (1 s per query, 75 % of it for the search, at a rate measured per planner on 2 shared cores), so
# the bundled scenarios keep their plans.
DEFAULT_ITERATIONS = {"BITstar": 7500, "RRTstar": 187, "InformedRRTstar": 187, "SORRTstar": 187,
                      "FMT": 1500, "BFMT": 1500, "RRTConnect": 1500}
DEFAULT_ITERATIONS_SPATIAL = {"BITstar": 3750, "RRTstar": 600, "InformedRRTstar": 600, "SORRTstar": 600,
                              "FMT": 1500, "BFMT": 1500, "RRTConnect": 1500}
# FMT* and BFMT* plan on a fixed sample set drawn up front: this many samples per iteration of the budget
# (300 samples for the default 1500 iterations, at least 100).
FMT_SAMPLES_PER_ITERATION = 0.2
# OMPL's informed samplers for a general objective draw uniform samples and reject those whose
# heuristic cost is outside a cost shell; when the shell is thin (short queries near the edge of the
# region) they stall inside one iteration. A search normally makes 20-50 heuristic calls per
# iteration (benchmarks/planning.py); past this many per allowed iteration the heuristic drops to 0
# (still admissible) and the search stops ("sampling"): counted, so the same on every machine.
HEURISTIC_CALLS_PER_ITERATION = 100
_ROADMAP = ("PRM", "PRMstar", "LazyPRM", "LazyPRMstar", "SPARS", "SPARStwo")


def default_iterations(planner: str, dim: int = 2) -> int:
    """The search budget (iterations per query) of ``planner`` in dimension ``dim`` when the scenario sets none."""
    return (DEFAULT_ITERATIONS if dim == 2 else DEFAULT_ITERATIONS_SPATIAL).get(planner, 750)


def fmt_samples(iterations: int) -> int:
    """FMT*'s sample set for a search budget of ``iterations`` (a count: the same samples on every machine)."""
    return max(100, int(FMT_SAMPLES_PER_ITERATION * iterations))


def _ompl():
    from ompl import base as ob, geometric as og, util as ou
    return ob, og, ou


def quiet() -> None:
    """Silence OMPL's console log."""
    _ompl()[2].setLogLevel(_ompl()[2].LOG_NONE)


def seed(n: int) -> None:
    """Seed OMPL's RNG (before any planner or sampler exists) with ``n + 1`` (OMPL refuses 0)."""
    _ompl()[2].RNG.setSeed(int(n) + 1)


_CLASSES: dict[str, Any] = {}


def _classes() -> dict[str, Any]:
    """The OMPL subclasses (defined on first use so that importing errplan.planning does not import
    ompl): one motion validator and one objective per dimension."""
    if _CLASSES:
        return _CLASSES
    ob, _, _ = _ompl()
    walk2, walk3 = cellwalk.walk2, cellwalk.walk3

    class CellWalkMotionValidator(ob.MotionValidator):
        """Exact motion validation: every grid cell the straight motion crosses is usable."""

        def __init__(self, si, cm):
            super().__init__(si)
            self._D = cm._D

        def checkMotion(self, s1, s2):  # noqa: N802 (OMPL's name)
            return walk2(self._D, s1[0], s1[1], s2[0], s2[1], True, False)[0]

    class CellWalkMotionValidator3(CellWalkMotionValidator):
        def checkMotion(self, s1, s2):  # noqa: N802
            return walk3(self._D, s1[0], s1[1], s1[2], s2[0], s2[1], s2[2], True, False)[0]

    class ClearMotionValidator3(CellWalkMotionValidator):
        """The cell walk, then the anatomy: every tip of the motion robustly clear (exact, one query)."""

        def __init__(self, si, cm):
            super().__init__(si, cm)
            self._clear = cm._clear

        def checkMotion(self, s1, s2):  # noqa: N802
            a0, a1, a2, b0, b1, b2 = s1[0], s1[1], s1[2], s2[0], s2[1], s2[2]
            return walk3(self._D, a0, a1, a2, b0, b1, b2, True, False)[0] and self._clear(a0, a1, a2, b0, b1, b2)

    class FieldObjective(ob.OptimizationObjective):
        """``integral (1 + weight * metric) ds`` of each motion, exact on the multilinear field, with
        the admissible heuristic ``distance * min(1 + weight * metric)``."""

        def __init__(self, si, cm):
            super().__init__(si)
            self._D = cm._D
            self._fmin = cm.f_min
            self._Cost = ob.Cost
            self._zero = ob.Cost(0.0)
            self._clock = _time.perf_counter
            self.deadline = math.inf  # the time cap, when the user set one
            self.heuristic_calls = 0
            self.max_heuristic_calls = math.inf

        def motionCost(self, s1, s2):  # noqa: N802
            return self._Cost(walk2(self._D, s1[0], s1[1], s2[0], s2[1], False, True)[1])

        def motionCostHeuristic(self, s1, s2):  # noqa: N802
            # Past the sampling guard or the time cap the heuristic drops to 0 (still admissible): OMPL's rejection
            # sampler for informed sets loops without checking the termination condition, and a
            # zero heuristic accepts the next sample so that the planner gets to check it.
            self.heuristic_calls += 1
            if self.heuristic_calls > self.max_heuristic_calls or self._clock() > self.deadline:
                return self._zero
            return self._Cost(math.hypot(s1[0] - s2[0], s1[1] - s2[1]) * self._fmin)

    class FieldObjective3(FieldObjective):
        def motionCost(self, s1, s2):  # noqa: N802
            return self._Cost(walk3(self._D, s1[0], s1[1], s1[2], s2[0], s2[1], s2[2], False, True)[1])

        def motionCostHeuristic(self, s1, s2):  # noqa: N802
            self.heuristic_calls += 1
            if self.heuristic_calls > self.max_heuristic_calls or self._clock() > self.deadline:
                return self._zero
            dx, dy, dz = s1[0] - s2[0], s1[1] - s2[1], s1[2] - s2[2]
            return self._Cost(math.sqrt(dx * dx + dy * dy + dz * dz) * self._fmin)

    _CLASSES.update(mv={2: CellWalkMotionValidator, 3: CellWalkMotionValidator3}, clear_mv=ClearMotionValidator3,
                    obj={2: FieldObjective, 3: FieldObjective3})
    return _CLASSES


def make_space_information(cm, bounds: tuple[float, ...] | None = None):
    """``(space, si)``: a d-dimensional ``RealVectorStateSpace`` over ``bounds`` (``(lo, hi)`` of
    every axis in turn, m; default the grid, :attr:`CostMap.bounds`) and its ``SpaceInformation``
    with the point validity and the exact motion validator of ``cm``."""
    ob, _, _ = _ompl()
    d = cm.dim
    space = ob.RealVectorStateSpace(d)
    b = ob.RealVectorBounds(d)
    bb = bounds or cm.bounds
    for k in range(d):
        b.setLow(k, float(bb[2 * k]))
        b.setHigh(k, float(bb[2 * k + 1]))
    space.setBounds(b)
    si = ob.SpaceInformation(space)
    D = cm._D
    if d == 2:
        point_ok = cellwalk.point_ok2
        si.setStateValidityChecker(lambda s: point_ok(D, s[0], s[1]))
    elif cm._clear is None:
        point_ok = cellwalk.point_ok3
        si.setStateValidityChecker(lambda s: point_ok(D, s[0], s[1], s[2]))
    else:  # an anatomy: a state is valid when it is in a usable cell and robustly clear
        point_ok, clear = cellwalk.point_ok3, cm._clear

        def valid(s):
            x, y, z = s[0], s[1], s[2]
            return point_ok(D, x, y, z) and clear(x, y, z, x, y, z)

        si.setStateValidityChecker(valid)
    si.setMotionValidator((_classes()["clear_mv"] if cm._clear is not None else _classes()["mv"][d])(si, cm))
    # Used only by OMPL routines that interpolate states themselves: finer than the grid.
    si.setStateValidityCheckingResolution(min(1.0, 0.25 * cm.h / max(space.getMaximumExtent(), 1e-12)))
    si.setup()
    return space, si


def make_objective(si, cm):
    """The :class:`FieldObjective` of ``cm`` on ``si``."""
    return _classes()["obj"][cm.dim](si, cm)


def make_planner(name: str, si, iterations: int):
    """The OMPL planner called ``name`` on ``si`` for a search budget of ``iterations`` (clear errors for
    unknown or deadlocking names)."""
    _, og, _ = _ompl()
    check_planner(name)
    pl = getattr(og, name)(si)
    if name in ("FMT", "BFMT"):
        # FMT* evaluates the neighbour pairs of a fixed sample set: size it to the budget
        # (about 0.3-0.5 s for 300 samples here), and let it use the cost-to-go heuristic.
        pl.setNumSamples(fmt_samples(iterations))
        pl.setHeuristics(True)
    return pl


def check_planner(name: str) -> None:
    if name in _ROADMAP:
        raise ErrplanError(f"planner = {name!r}: roadmap planners deadlock with errplan's Python objective "
                           f"in ompl 2.0.1 (they run threads that need the GIL); use one of {', '.join(PLANNERS)}")
    if name not in PLANNERS:
        raise ErrplanError(f"planner = {name!r}: expected one of {', '.join(PLANNERS)}")


def search(cm, start, goal, planner_name: str, box, cap: int, t_end: float | None,
           first_only: bool, budget: int) -> tuple[np.ndarray | None, int, str, str]:
    """One OMPL search in ``box`` (flat ``(lo, hi)`` per axis, None: the grid):
    ``(path (n, d) or None, iterations, stopped_by, status)``.

    Stops after ``cap`` iterations ("iterations"), when the informed sampler stalls
    (``HEURISTIC_CALLS_PER_ITERATION``, "sampling"), with ``first_only`` at the first exact solution,
    or by itself ("planner"): all counted, so the same on every machine. Only when ``t_end`` (a
    ``time.perf_counter()`` value: the user's time cap) is given does the clock stop it too ("time";
    such a search depends on the machine). ``budget``: the query's whole search budget (iterations),
    which sizes FMT*'s sample set, the same in both phases of a query.
    """
    ob, og, _ = _ompl()
    d = cm.dim
    space, si = make_space_information(cm, box)
    obj = make_objective(si, cm)
    ss = og.SimpleSetup(si)
    s = space.allocState()
    g = space.allocState()
    for k in range(d):
        s[k] = float(start[k])
        g[k] = float(goal[k])
    ss.setStartAndGoalStates(s, g)
    ss.setOptimizationObjective(obj)
    planner = make_planner(planner_name, si, budget)
    ss.setPlanner(planner)
    pdef = ss.getProblemDefinition()
    t_end = math.inf if t_end is None else t_end
    obj.deadline = t_end
    obj.max_heuristic_calls = HEURISTIC_CALLS_PER_ITERATION * cap
    count = [0]
    why = ["planner"]
    clock = _time.perf_counter
    # Planners publish their solution to the problem definition only when solve() returns; the
    # anytime ones report their best cost as they go.
    best_cost = getattr(planner, "bestCost", None)

    def found() -> bool:
        return math.isfinite(best_cost().value()) if best_cost else pdef.hasExactSolution()

    def ptc() -> bool:
        count[0] += 1
        if count[0] > cap:
            why[0] = "iterations"
            return True
        if obj.heuristic_calls > obj.max_heuristic_calls:
            why[0] = "sampling"
            return True
        if clock() > t_end:
            why[0] = "time"
            return True
        if first_only and found():
            why[0] = "first solution"
            return True
        return False

    status = ss.solve(ob.PlannerTerminationCondition(ptc))
    n = min(count[0], cap)
    if not ss.haveExactSolutionPath():
        return None, n, why[0], str(status)
    p = ss.getSolutionPath()
    path = np.array([[p.getState(i)[k] for k in range(d)] for i in range(p.getStateCount())])
    path[0], path[-1] = start, goal
    return path, n, why[0], str(status)
