"""Path refinement on the exact objective: shortcuts and a coarse-to-fine vertex relaxation.

Works on polylines (n, d) of a :class:`~errplan.planning.costmap.CostMap` of either dimension.
Every accepted change keeps the path valid (the exact cell walk) and lowers its exact cost, so the
result is never worse than the input; deterministic.
"""
from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass

import numpy as np

from ..errors import ErrplanError
from . import cellwalk


#: The refinement's budget per path when the caller gives none: evaluations of a segment (its cell walk,
#: and its clearance check when the cost map has one). The refinements of the port scenario's queries take
#: 1,505 to 36,389, those of the spatial tests' synthetic fields about 40,000, so this bounds a pathological
#: path, not a usual one.
REFINE_EVALUATIONS = 200_000
#: With arm checks (:mod:`errplan.planning.arm_checks`, a cost map's ``arm_checks``), their share of that
#: budget: at most this many of the refinement's clearance checks per path (each checks a motion of the
#: moving arm against the held ones: tens of ms, where a cell walk takes about 1 us).
REFINE_ARM_CHECKS = 200


@dataclass
class RefineResult:
    """Outcome of :func:`refine_path`: the path (n, d) and its cost before and after.

    ``evaluations``: segment evaluations spent (``checks`` of them clearance checks of a cost map with arm
    checks); ``stopped_by``: "converged" (every level relaxed to its finest step), "evaluations" (the
    budget), "arm checks" (their share of it) or "time" (the optional time cap: machine-dependent)."""

    path: np.ndarray
    cost: float
    cost_before: float
    sweeps: int
    time: float
    evaluations: int = 0
    stopped_by: str = "converged"
    checks: int = 0


class _Budget(Exception):
    """Raised by a counted evaluation past the budget or the time cap (caught by :func:`refine_path`)."""


class _Counter:
    """Counts segment evaluations against a budget, and reads the clock only when a time cap is set."""

    def __init__(self, budget: int, deadline: float | None, checks: float = math.inf):
        self.n, self.budget, self.deadline, self.why = 0, budget, deadline, ""
        self.checks, self.max_checks = 0, checks

    def tick_check(self) -> None:
        """A clearance check with arm checks: counted in the budget and in its own share."""
        if self.checks >= self.max_checks:
            self.why = "arm checks"
            raise _Budget
        self.tick()
        self.checks += 1

    def tick(self) -> None:
        if self.n >= self.budget:
            self.why = "evaluations"
            raise _Budget
        if self.deadline is not None and _time.perf_counter() > self.deadline:
            self.why = "time"
            raise _Budget
        self.n += 1


def _segment_fn(cm, count=None):
    """``seg(a, b, check=True) -> (ok, cost)`` on two points given as lists (the compiled walk);
    each call ticks ``count`` (a :class:`_Counter`) when given."""
    D = cm._D
    tick = count.tick if count is not None else (lambda: None)
    if cm.dim == 2:
        walk2 = cellwalk.walk2

        def seg(a, b, check=True):
            tick()
            return walk2(D, a[0], a[1], b[0], b[1], check, True)
    else:
        walk3 = cellwalk.walk3

        def seg(a, b, check=True):
            tick()
            return walk3(D, a[0], a[1], a[2], b[0], b[1], b[2], check, True)
    return seg


def _clear_fn(cm, count=None):
    """``clear(a, b) -> bool``: every tip of the motion robustly clear of the cost map's anatomy
    (:meth:`CostMap.attach_anatomy`), or None without one; each call ticks ``count`` when given. The
    refinement calls it only on a change it would accept (cheaper and in the usable region), the dearer
    check last."""
    c = getattr(cm, "_clear", None)
    if c is None:
        return None
    tick = (lambda: None) if count is None else (
        count.tick_check if getattr(cm, "arm_checks", None) is not None else count.tick)

    def clear(a, b):
        tick()
        return c(a[0], a[1], a[2], b[0], b[1], b[2])

    return clear


def _directions(t: list[float], tangent: bool) -> list[list[float]]:
    """Trial move directions of a vertex whose neighbours are joined by unit vector ``t``: across
    the path (planar: both normals; spatial: both ways along two orthonormal normals and their
    diagonals) and, with ``tangent``, along it."""
    if len(t) == 2:
        ty, tz = t
        dirs = [[-tz, ty], [tz, -ty]]
    else:
        # n1: the axis least aligned with t, made orthogonal to t; n2 = t x n1.
        k = min(range(3), key=lambda i: abs(t[i]))
        e = [0.0, 0.0, 0.0]
        e[k] = 1.0
        n1 = [e[i] - t[k] * t[i] for i in range(3)]
        nn = math.sqrt(sum(x * x for x in n1))
        n1 = [x / nn for x in n1]
        n2 = [t[1] * n1[2] - t[2] * n1[1], t[2] * n1[0] - t[0] * n1[2], t[0] * n1[1] - t[1] * n1[0]]
        r = math.sqrt(0.5)
        dirs = [n1, [-x for x in n1], n2, [-x for x in n2]]
        for s1, s2 in ((1, 1), (-1, -1), (1, -1), (-1, 1)):
            dirs.append([r * (s1 * a + s2 * b) for a, b in zip(n1, n2)])
    if tangent:
        dirs += [list(t), [-x for x in t]]
    return dirs


def _reduce_vertices(seg, pts: list[list[float]], seg_cost: list[float], clear=None) -> bool:
    """Greedy shortcuts: from each vertex, jump to the farthest later vertex whose straight
    connection is valid and not more expensive than the sub-path it replaces."""
    changed = False
    i = 0
    while i < len(pts) - 2:
        best = None
        acc = [seg_cost[i]]
        for j in range(i + 2, len(pts)):
            acc.append(acc[-1] + seg_cost[j - 1])
        for j in range(len(pts) - 1, i + 1, -1):
            ok, c = seg(pts[i], pts[j])
            if ok and c <= acc[j - i - 1] * (1 + 1e-12) and (clear is None or clear(pts[i], pts[j])):
                best = (j, c)
                break
        if best is not None:
            j, c = best
            del pts[i + 1:j]
            seg_cost[i:j] = [c]
            changed = True
        i += 1
    return changed


def _relax(seg, pts: list[list[float]], seg_cost: list[float], step: float, stop: float,
           max_sweeps: int, tangent: bool, clear=None, sweeps_done: list[int] | None = None) -> int:
    """Gauss-Seidel vertex relaxation (see :func:`refine_path`); returns the number of sweeps (also
    added to ``sweeps_done[0]`` as they start, for a caller that the budget interrupts)."""
    sweeps = 0
    d = len(pts[0])
    while step >= stop and sweeps < max_sweeps:
        sweeps += 1
        if sweeps_done is not None:
            sweeps_done[0] += 1
        moved = 0
        for k in range(1, len(pts) - 1):
            a, p, b = pts[k - 1], pts[k], pts[k + 1]
            t = [b[i] - a[i] for i in range(d)]
            tn = math.hypot(*t)
            if tn == 0:
                continue
            t = [x / tn for x in t]
            here = seg_cost[k - 1] + seg_cost[k]
            best = None
            for dv in _directions(t, tangent):
                q = [p[i] + step * dv[i] for i in range(d)]
                ok1, c1 = seg(a, q)
                if not ok1 or c1 >= here:
                    continue
                ok2, c2 = seg(q, b)
                if ok2 and c1 + c2 < here - 1e-15 and (clear is None or (clear(a, q) and clear(q, b))):
                    here = c1 + c2
                    best = (q, c1, c2)
            if best is not None:
                pts[k] = best[0]
                seg_cost[k - 1], seg_cost[k] = best[1], best[2]
                moved += 1
        if moved == 0:
            step *= 0.5
    return sweeps


def _subdivide(pts: list[list[float]], spacing: float) -> list[list[float]]:
    out = [pts[0]]
    for a, b in zip(pts[:-1], pts[1:]):
        n = max(1, math.ceil(math.dist(a, b) / spacing - 1e-9))
        for k in range(1, n + 1):
            t = k / n
            out.append([x + (y - x) * t for x, y in zip(a, b)])
    return out


def refine_path(cm, path, *, spacing: float | None = None, min_step: float | None = None,
                max_sweeps: int = 60, evaluations: int | None = None, arm_checks: int | None = None,
                deadline: float | None = None) -> RefineResult:
    """Lower the cost of a valid polyline (n, d) (m) by shortcuts and a coarse-to-fine relaxation.

    1. Greedy shortcuts (never raising the cost). 2. Coarse-to-fine relaxation: the path is
    subdivided into vertices about ``length / 8`` apart and relaxed, then subdivided to half that
    spacing and relaxed again, down to ``spacing`` (default ``max(2 h, length / 64)``, at most
    ``length / 16``). Relaxing: each interior vertex in turn tries moves of ``+-step`` across (and,
    at the finest level, along) the path and keeps the best one that lowers the exact cost of its
    two segments while keeping both valid; the step starts at a quarter of the spacing and halves
    when a sweep moves nothing, down to ``spacing / 16`` (``min_step``, default ``h / 32``, at the
    finest level). In space "across" is eight directions: both ways along two normals of the path
    and along their diagonals. The coarse levels remove the long-wavelength error that a fine vertex
    relaxation alone removes very slowly. 3. Shortcuts again. Every accepted change keeps the path
    valid and lowers its cost, so the result is never worse than the input.

    The budget is counted: at most ``evaluations`` segment evaluations (default
    :data:`REFINE_EVALUATIONS`; a cell walk or a clearance check each count one), of them at most
    ``arm_checks`` clearance checks when the cost map has arm checks (default :data:`REFINE_ARM_CHECKS`),
    at most ``max_sweeps`` sweeps per level; the refinement stops where the budget runs out, keeping every
    change made so far, so the result is the same on every machine. ``deadline`` (a
    ``time.perf_counter()`` value: a time cap) stops it too, only when given; then the result depends on
    the machine, and ``stopped_by`` says "time" when it cut.
    """
    t0 = _time.perf_counter()
    budget = REFINE_EVALUATIONS if evaluations is None else int(evaluations)
    checks = REFINE_ARM_CHECKS if arm_checks is None else int(arm_checks)
    if budget < 0 or checks < 0:
        raise ErrplanError(f"refine_path: evaluations = {evaluations!r}, arm_checks = {arm_checks!r}: "
                           "expected integers >= 0")
    orig = [[float(x) for x in p] for p in np.asarray(path, float).reshape(-1, cm.dim)]
    pts = [p[:] for p in orig]
    count = _Counter(budget, deadline, checks)
    seg = _segment_fn(cm, count)
    clear = _clear_fn(cm, count)
    ok0, cost0 = cm.path_cost(pts)
    if not ok0:
        raise ErrplanError("refine_path: the input path leaves the usable region")
    free = _segment_fn(cm)  # segment costs of a path already checked (not a search step: not counted)

    def costs(p):
        return [free(a, b, False)[1] for a, b in zip(p[:-1], p[1:])]

    sweeps = [0]
    holder = [pts]
    try:
        seg_cost = costs(pts)
        _reduce_vertices(seg, pts, seg_cost, clear)
        length = sum(math.dist(a, b) for a, b in zip(pts[:-1], pts[1:]))
        finest = spacing or min(max(2 * cm.h, length / 64), length / 16)
        sp = max(length / 8, finest)
        while True:
            pts = _subdivide(pts, sp)
            holder[0] = pts
            seg_cost = costs(pts)
            last = sp <= finest * (1 + 1e-9)
            stop = (min_step or cm.h / 32) if last else sp / 16
            _relax(seg, pts, seg_cost, 0.25 * sp, stop, max_sweeps, tangent=last, clear=clear, sweeps_done=sweeps)
            if last:
                break
            sp = max(sp / 2, finest)
        _reduce_vertices(seg, pts, seg_cost, clear)
        why = "converged"
    except _Budget:  # every change made so far kept the path valid and cheaper: keep them
        pts = holder[0]
        why = count.why
    ok1, cost1 = cm.path_cost(pts)
    if not ok1 or cost1 >= cost0:
        pts, cost1 = orig, cost0
    return RefineResult(np.array(pts), cost1, cost0, sweeps[0], _time.perf_counter() - t0, count.n, why, count.checks)
