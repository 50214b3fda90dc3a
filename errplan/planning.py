"""Tip-path planning on the worst-case error fields, in OMPL's own terms (P1 Sec. IV).

P1 Sec. IV: "a path planner could then trade off between indirect and direct paths". Here the
precomputed worst-case fields (:mod:`errplan.fields`) become the cost of an OMPL planning problem:

- **state space**: a 2-D ``RealVectorStateSpace`` over the field's grid bounds, points ``[y, z]`` (m);
- **validity** (:class:`CostMap`): a grid node is *usable* when it is in the robust workspace
  (``MetricField.valid``: reachable under every instance of the error set), its metric is finite and,
  with ``[planner] certifiable = true``, ``rho_star <= 1 - certify_margin`` (some gain certifies
  monotonic convergence there). A point is valid when it lies in a grid cell whose four corners are
  usable (the *usable cells*; the region is their closed union). This is conservative: the bilinear
  interpolation of the fields is only ever read inside cells whose corners were all evaluated and
  found valid;
- **motion validation** is exact, not sampled: a straight motion is valid when every cell it passes
  through is usable (a grid traversal, Amanatides & Woo), so a path never leaves the usable region
  between its vertices, whatever the resolution;
- **objective** (:class:`FieldObjective`): ``cost = integral of (1 + weight * metric) ds`` with
  ``metric`` the bilinear interpolation of the chosen field (``phi_hat_max`` | ``G_norm`` |
  ``phi_max`` | ``rho_star``). Along a straight line the bilinear interpolant is a quadratic of the
  arc length inside each cell, so :meth:`CostMap.segment` integrates it *exactly* cell by cell;
  ``motionCostHeuristic`` is the admissible ``distance * (1 + weight * min metric)``;
- **planner** by name (:data:`PLANNERS`, default BIT*: benchmarks/planning.py), OMPL's RNG seeded
  from ``[planner] seed``, sampling restricted to the box where a path cheaper than a known one can
  lie (:func:`search_box`), stopped by an iteration cap (so that a run is a function of the seed)
  or the time budget, whichever comes first; the solution is then refined by :func:`refine_path`
  (shortcuts and a coarse-to-fine vertex relaxation on the same exact objective), every change kept
  only if it keeps validity and lowers the cost;
- **errors** (:class:`~errplan.errors.InfeasibleError`): an unusable start or goal (which one, why:
  outside the grid, outside the robust workspace, or ``rho_star`` above its bound, and by how much),
  endpoints in disconnected parts of the region, or no exact solution within the budget.

The independent optimum that every quality claim is measured against is
:func:`errplan.reference.grid_optimum` (Dijkstra on the grid with long moves).

Results are dataclasses (:class:`PathReport`, :class:`QueryPlan`, :class:`ScenarioPlan`) with a
``to_json()`` giving the ``P`` objects of the plan JSON (docs/interfaces.md); the gain and
simulation steps add their keys to :attr:`QueryPlan.extra`.

Numbers: y, z and lengths in m; ``phi_*`` in rad; costs in m (a weighted length).
"""
from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from .errors import ErrplanError, InfeasibleError

METRIC_NAMES = ("phi_hat_max", "G_norm", "phi_max", "rho_star")
# Planners that work with a Python objective in ompl 2.0.1 (PRM/PRMstar deadlock on the GIL with a
# Python objective; AORRTC fails when the straight line is valid).
PLANNERS = ("RRTstar", "InformedRRTstar", "SORRTstar", "BITstar", "FMT", "BFMT", "RRTConnect")


# ============================================================================= cost map
def _near_cells(u: float) -> tuple[int, ...]:
    """Cell indices along one axis whose closed interval contains grid coordinate ``u`` (both
    neighbours when ``u`` is within 1e-9 cell of a grid line)."""
    r = round(u)
    if abs(u - r) < 1e-9:
        return (r, r - 1)
    return (math.floor(u),)


def _dda_axis(u: float, du: float) -> tuple[int, int, float, float]:
    """Amanatides-Woo set-up along one grid axis for a segment starting at cell coordinate ``u``
    with total change ``du``: starting cell (ties on a grid line go in the motion direction),
    step sign, parameter step per cell and parameter of the first cell boundary."""
    if du > 0:
        i = math.floor(u + 1e-12)
        return i, 1, 1.0 / du, (i + 1 - u) / du
    if du < 0:
        i = math.ceil(u - 1e-12) - 1
        return i, -1, -1.0 / du, (i - u) / du
    return math.floor(u), 0, math.inf, math.inf


class CostMap:
    """Usable region and integrand ``1 + weight * metric`` of a :class:`~errplan.fields.MetricField`.

    Parameters
    ----------
    mf : MetricField
        The worst-case fields (``rho_star`` needed when ``certifiable`` or ``metric = "rho_star"``).
    metric : str
        Field used as the state cost: ``phi_hat_max`` (rad), ``G_norm`` (1), ``phi_max`` (rad),
        ``rho_star`` (1).
    weight : float
        ``cost = integral (1 + weight * metric) ds``; ``weight >= 0``.
    certifiable : bool
        Keep only nodes with ``rho_star <= 1 - certify_margin``.
    certify_margin : float
        Margin below 1 for ``rho_star``.

    Attributes
    ----------
    y, z : ndarray
        Grid axes (m); ``h`` the spacing.
    node_ok : ndarray of bool, (ny, nz)
        Usable nodes.
    cell_ok : ndarray of bool, (ny-1, nz-1)
        Usable cells (all four corners usable).
    integrand : ndarray, (ny, nz)
        ``1 + weight * metric`` at the nodes (the maximum over the usable nodes where unusable, so
        that costs stay finite; never read inside a usable cell).
    f_min : float
        Smallest integrand over usable nodes (the heuristic's factor).
    """

    def __init__(self, mf, metric: str = "phi_hat_max", weight: float = 1.0, certifiable: bool = True,
                 certify_margin: float = 0.02):
        if metric not in METRIC_NAMES:
            raise ErrplanError(f"metric = {metric!r}: expected one of {', '.join(METRIC_NAMES)}")
        if not (weight >= 0 and math.isfinite(weight)):
            raise ErrplanError(f"weight = {weight!r}: expected a finite number >= 0")
        self.mf = mf
        self.metric = metric
        self.weight = float(weight)
        self.certifiable = bool(certifiable)
        self.certify_margin = float(certify_margin)
        self.y = np.asarray(mf.y, float)
        self.z = np.asarray(mf.z, float)
        if len(self.y) < 2 or len(self.z) < 2:
            raise ErrplanError("the field grid needs at least 2 x 2 points to plan on")
        self.h = float(mf.resolution)
        self.y0 = float(self.y[0])
        self.z0 = float(self.z[0])
        self.ny, self.nz = len(self.y), len(self.z)
        m = np.asarray(mf.array(metric), float)
        ok = np.asarray(mf.valid, bool) & np.isfinite(m)
        if self.certifiable:
            rs = np.asarray(mf.array("rho_star"), float)
            self.rho_bound = 1.0 - self.certify_margin
            with np.errstate(invalid="ignore"):
                # rho* = 1 marks "no gain contracts" (fields.minimize_gain): never certifiable,
                # even with certify_margin = 0.
                ok &= np.isfinite(rs) & (rs <= self.rho_bound) & (rs < 1.0)
        else:
            self.rho_bound = None
        self.node_ok = ok
        self.cell_ok = ok[:-1, :-1] & ok[1:, :-1] & ok[:-1, 1:] & ok[1:, 1:]
        f = 1.0 + self.weight * np.where(ok, m, 0.0)
        self.f_min = float(f[ok].min()) if ok.any() else 1.0
        self.f_max = float(f[ok].max()) if ok.any() else 1.0
        self.integrand = np.where(ok, f, self.f_max)
        # Plain-Python copies for the per-motion loops (numpy calls there are ~5x slower).
        self._build_lists()

    # ------------------------------------------------------------------ internals
    def _build_lists(self) -> None:
        f = self.integrand
        nzc = self.nz - 1
        # Bilinear coefficients per cell in local coordinates (a, b) in [0, 1]^2:
        # f = c0 + ca a + cb b + cab a b.
        f00, f10, f01, f11 = f[:-1, :-1], f[1:, :-1], f[:-1, 1:], f[1:, 1:]
        self._c0 = f00.ravel().tolist()
        self._ca = (f10 - f00).ravel().tolist()
        self._cb = (f01 - f00).ravel().tolist()
        self._cab = (f11 - f10 - f01 + f00).ravel().tolist()
        self._ok = self.cell_ok.ravel().tolist()
        self._nzc = nzc
        self._nyc = self.ny - 1

    # ------------------------------------------------------------------ points
    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(y_lo, y_hi, z_lo, z_hi)`` of the grid, m."""
        return self.y0, float(self.y[-1]), self.z0, float(self.z[-1])

    @property
    def any_usable(self) -> bool:
        return bool(self.cell_ok.any())

    def point_ok(self, y: float, z: float) -> bool:
        """True if ``[y, z]`` lies in a usable cell (closed cells: a point on an edge or a corner
        counts if any cell touching it is usable)."""
        ok = self._ok
        nzc, nyc = self._nzc, self._nyc
        for i in _near_cells((y - self.y0) / self.h):
            if 0 <= i < nyc:
                for j in _near_cells((z - self.z0) / self.h):
                    if 0 <= j < nzc and ok[i * nzc + j]:
                        return True
        return False

    def integrand_at(self, y: float, z: float) -> float:
        """Bilinear ``1 + weight * metric`` at a point (clamped to the grid)."""
        u = min(max((y - self.y0) / self.h, 0.0), self._nyc - 1e-12)
        v = min(max((z - self.z0) / self.h, 0.0), self._nzc - 1e-12)
        i, j = int(u), int(v)
        a, b = u - i, v - j
        k = i * self._nzc + j
        return self._c0[k] + self._ca[k] * a + self._cb[k] * b + self._cab[k] * a * b

    # ------------------------------------------------------------------ segments
    def segment(self, ya: float, za: float, yb: float, zb: float, check: bool = True,
                cost: bool = True) -> tuple[bool, float]:
        """Validity and exact cost of the straight motion ``[ya, za] -> [yb, zb]``.

        Walks the grid cells the segment passes through (in order) and integrates the bilinear
        integrand exactly in each (a quadratic of the arc length). Returns ``(ok, cost)``: ``ok``
        is False as soon as a cell is unusable or the segment leaves the grid (then, with
        ``check``, the walk stops early and the cost is ``inf``).
        """
        h = self.h
        u = (ya - self.y0) / h
        v = (za - self.z0) / h
        du = (yb - ya) / h
        dv = (zb - za) / h
        length = math.hypot(yb - ya, zb - za)
        nyc, nzc = self._nyc, self._nzc
        okl = self._ok
        c0l, cal, cbl, cabl = self._c0, self._ca, self._cb, self._cab
        # Starting cell: the one the segment enters (ties on a grid line go in the motion direction).
        i, su, tdu, tu = _dda_axis(u, du)
        j, sv, tdv, tv = _dda_axis(v, dv)
        on_u_line = du == 0 and abs(u - round(u)) < 1e-9
        on_v_line = dv == 0 and abs(v - round(v)) < 1e-9
        if on_u_line:
            i = int(round(u))
        if on_v_line:
            j = int(round(v))
        t0 = 0.0
        total = 0.0
        ok = True
        while True:
            t1 = tu if tu < tv else tv
            if t1 > 1.0 - 1e-9:  # the last piece (a crossing within 1e-9 of the end is the end)
                t1 = 1.0
            if t1 > t0:
                ci, cj = i, j
                if 0 <= ci < nyc and 0 <= cj < nzc and okl[ci * nzc + cj]:
                    good = True
                else:
                    good = False
                    # A motion along a grid line borders two cells: either one makes it valid.
                    if on_u_line and 0 <= i - 1 < nyc and 0 <= cj < nzc and okl[(i - 1) * nzc + cj]:
                        ci, good = i - 1, True
                    elif on_v_line and 0 <= ci < nyc and 0 <= j - 1 < nzc and okl[ci * nzc + j - 1]:
                        cj, good = j - 1, True
                    elif (on_u_line and on_v_line and 0 <= i - 1 < nyc and 0 <= j - 1 < nzc
                          and okl[(i - 1) * nzc + j - 1]):  # a zero-length motion on a grid node
                        ci, cj, good = i - 1, j - 1, True
                if not good:
                    ok = False
                    if check:
                        return False, math.inf
                if cost:
                    if 0 <= ci < nyc and 0 <= cj < nzc:
                        k = ci * nzc + cj
                        # local coordinates at t: a = u + du t - ci, b = v + dv t - cj
                        a0 = u - ci
                        b0 = v - cj
                        c0, ca, cb, cab = c0l[k], cal[k], cbl[k], cabl[k]
                        # f(t) = A + B t + C t^2
                        A = c0 + ca * a0 + cb * b0 + cab * a0 * b0
                        B = ca * du + cb * dv + cab * (a0 * dv + b0 * du)
                        C = cab * du * dv
                        total += (A * (t1 - t0) + 0.5 * B * (t1 * t1 - t0 * t0)
                                  + C * (t1 * t1 * t1 - t0 * t0 * t0) / 3.0)
                    else:
                        total += self.f_max * (t1 - t0)
                t0 = t1
            if t1 >= 1.0:
                break
            # Crossings closer than 1e-9 (in units of the motion) pass through a grid corner:
            # step diagonally rather than through a sliver of the cell beside the corner.
            if tu <= tv:
                if tv - tu < 1e-9:
                    j += sv
                    tv += tdv
                i += su
                tu += tdu
            else:
                if tu - tv < 1e-9:
                    i += su
                    tu += tdu
                j += sv
                tv += tdv
        return ok, total * length

    def pieces(self, ya: float, za: float, yb: float, zb: float) -> list[tuple[float, float, int, int, bool]]:
        """The cells a straight motion passes through, in order: ``(t0, t1, i, j, usable)`` with
        ``t`` the motion parameter in [0, 1] and ``(i, j)`` the cell (the same walk as
        :meth:`segment`, written for clarity rather than speed; used for reporting)."""
        h = self.h
        u, v = (ya - self.y0) / h, (za - self.z0) / h
        du, dv = (yb - ya) / h, (zb - za) / h
        on_u = du == 0 and abs(u - round(u)) < 1e-9
        on_v = dv == 0 and abs(v - round(v)) < 1e-9

        def start(x, d, on):
            if on:
                return int(round(x)), 0, math.inf, math.inf
            if d > 0:
                c = math.floor(x + 1e-12)
                return c, 1, (c + 1 - x) / d, 1.0 / d
            if d < 0:
                c = math.ceil(x - 1e-12) - 1
                return c, -1, (x - c) / -d, -1.0 / d
            return math.floor(x), 0, math.inf, math.inf

        i, si, tu, tdu = start(u, du, on_u)
        j, sj, tv, tdv = start(v, dv, on_v)
        out = []
        t0 = 0.0
        while True:
            t1 = min(tu, tv)
            if t1 > 1.0 - 1e-9:
                t1 = 1.0
            if t1 > t0 or not out:
                cands = ([(i, j)] + ([(i - 1, j)] if on_u else []) + ([(i, j - 1)] if on_v else [])
                         + ([(i - 1, j - 1)] if on_u and on_v else []))
                good = [c for c in cands if 0 <= c[0] < self._nyc and 0 <= c[1] < self._nzc and self.cell_ok[c]]
                ci, cj = good[0] if good else (i, j)
                out.append((t0, t1, ci, cj, bool(good)))
                t0 = t1
            if t1 >= 1.0:
                return out
            step_u = tu <= tv or tu - tv < 1e-9
            step_v = tv <= tu or tv - tu < 1e-9
            if step_u:
                i += si
                tu += tdu
            if step_v:
                j += sj
                tv += tdv

    def field_max(self, name: str, path) -> float | None:
        """Exact maximum of the bilinear field ``name`` (an attribute of the MetricField) along a
        polyline (n, 2), or None if the path meets a cell with an undefined corner."""
        a = np.asarray(self.mf.array(name), float)
        path = np.asarray(path, float)
        best = -math.inf
        for (ya, za), (yb, zb) in zip(path[:-1], path[1:]) if len(path) > 1 else [(path[0], path[0])]:
            for t0, t1, ci, cj, _ in self.pieces(float(ya), float(za), float(yb), float(zb)):
                if not (0 <= ci < self._nyc and 0 <= cj < self._nzc):
                    return None
                f00, f10, f01, f11 = a[ci, cj], a[ci + 1, cj], a[ci, cj + 1], a[ci + 1, cj + 1]
                if not all(math.isfinite(x) for x in (f00, f10, f01, f11)):
                    return None
                a0 = (ya - self.y0) / self.h - ci
                b0 = (za - self.z0) / self.h - cj
                du, dv = (yb - ya) / self.h, (zb - za) / self.h
                ca, cb, cab = f10 - f00, f01 - f00, f11 - f10 - f01 + f00
                A = f00 + ca * a0 + cb * b0 + cab * a0 * b0
                B = ca * du + cb * dv + cab * (a0 * dv + b0 * du)
                C = cab * du * dv
                ts = [t0, t1]
                if C < 0 and t0 < -B / (2 * C) < t1:
                    ts.append(-B / (2 * C))
                best = max(best, max(A + B * t + C * t * t for t in ts))
        return float(best)

    def field_length_above(self, name: str, path, threshold: float = 1.0) -> float | None:
        """Length (m) of a polyline where the bilinear field ``name`` is >= ``threshold`` (exact per
        piece: the field is a quadratic of the motion parameter in each cell), or None if the path
        meets a cell with an undefined corner."""
        a = np.asarray(self.mf.array(name), float)
        path = np.asarray(path, float)
        total = 0.0
        for (ya, za), (yb, zb) in zip(path[:-1], path[1:]):
            seg_len = math.hypot(yb - ya, zb - za)
            for t0, t1, ci, cj, _ in self.pieces(float(ya), float(za), float(yb), float(zb)):
                if not (0 <= ci < self._nyc and 0 <= cj < self._nzc):
                    return None
                f00, f10, f01, f11 = a[ci, cj], a[ci + 1, cj], a[ci, cj + 1], a[ci + 1, cj + 1]
                if not all(math.isfinite(x) for x in (f00, f10, f01, f11)):
                    return None
                a0 = (ya - self.y0) / self.h - ci
                b0 = (za - self.z0) / self.h - cj
                du, dv = (yb - ya) / self.h, (zb - za) / self.h
                ca, cb, cab = f10 - f00, f01 - f00, f11 - f10 - f01 + f00
                A = f00 + ca * a0 + cb * b0 + cab * a0 * b0 - threshold
                B = ca * du + cb * dv + cab * (a0 * dv + b0 * du)
                C = cab * du * dv
                # split [t0, t1] at the roots of A + B t + C t^2 and add the parts where it is >= 0
                cuts = [t0, t1]
                if abs(C) > 1e-300:
                    disc = B * B - 4 * A * C
                    if disc >= 0:
                        r = math.sqrt(disc)
                        cuts += [(-B - r) / (2 * C), (-B + r) / (2 * C)]
                elif abs(B) > 1e-300:
                    cuts.append(-A / B)
                cuts = sorted(t for t in cuts if t0 <= t <= t1)
                for p0, p1 in zip(cuts[:-1], cuts[1:]):
                    tm = 0.5 * (p0 + p1)
                    if A + B * tm + C * tm * tm >= 0:
                        total += (p1 - p0) * seg_len
        return float(total)

    def motion_ok(self, ya: float, za: float, yb: float, zb: float) -> bool:
        return self.segment(ya, za, yb, zb, check=True, cost=False)[0]

    def path_cost(self, pts: Sequence[Sequence[float]]) -> tuple[bool, float]:
        """``(valid, cost)`` of a polyline (n, 2): the sum of exact segment costs."""
        ok, total = True, 0.0
        for (ya, za), (yb, zb) in zip(pts[:-1], pts[1:]):
            o, c = self.segment(float(ya), float(za), float(yb), float(zb), check=False)
            ok &= o
            total += c
        return ok, total


    def path_ok(self, pts: Sequence[Sequence[float]]) -> bool:
        """True if every segment of the polyline stays in the usable region."""
        return all(self.motion_ok(float(a[0]), float(a[1]), float(b[0]), float(b[1]))
                   for a, b in zip(pts[:-1], pts[1:]))

    # ------------------------------------------------------------------ regions
    def _cell_index(self, p: Sequence[float]) -> tuple[int, int] | None:
        """A usable cell containing ``p`` (closed cells), or None."""
        for i in _near_cells((p[0] - self.y0) / self.h):
            for j in _near_cells((p[1] - self.z0) / self.h):
                if 0 <= i < self._nyc and 0 <= j < self._nzc and self.cell_ok[i, j]:
                    return i, j
        return None

    @property
    def components(self) -> np.ndarray:
        """Labels (ny-1, nz-1) of the connected parts of the usable region (cells touching at an
        edge or a corner are connected; 0 = unusable)."""
        if not hasattr(self, "_labels"):
            from scipy.ndimage import label
            self._labels = label(self.cell_ok, structure=np.ones((3, 3), int))[0]
        return self._labels

    def connected(self, a: Sequence[float], b: Sequence[float]) -> bool:
        ca, cb = self._cell_index(a), self._cell_index(b)
        if ca is None or cb is None:
            return False
        lab = self.components
        return bool(lab[ca] == lab[cb])

    def nearest_usable(self, p: Sequence[float], mask: np.ndarray | None = None) -> tuple[np.ndarray, float] | None:
        """Nearest point of the region made of the cells in ``mask`` (default: usable cells) to
        ``p``, and its distance (m); None if the region is empty."""
        cells = self.cell_ok if mask is None else mask
        ii, jj = np.nonzero(cells)
        if len(ii) == 0:
            return None
        y_lo, z_lo = self.y0 + ii * self.h, self.z0 + jj * self.h
        qy = np.clip(p[0], y_lo, y_lo + self.h)
        qz = np.clip(p[1], z_lo, z_lo + self.h)
        d = np.hypot(qy - p[0], qz - p[1])
        k = int(np.argmin(d))
        return np.array([qy[k], qz[k]]), float(d[k])

    def explain_point(self, p: Sequence[float], what: str = "point") -> str | None:
        """None if ``p`` is usable, otherwise a one-line reason naming the point, the cause and
        by how much (distance to the nearest usable tip, or ``rho_star`` against its bound)."""
        p = [float(p[0]), float(p[1])]
        if not all(math.isfinite(x) for x in p):
            return f"{what} {p} is not a finite point"
        if self.point_ok(*p):
            return None
        where = f"{what} [{p[0]:.4f}, {p[1]:.4f}] m"
        near = self.nearest_usable(p)
        tail = (f"; the nearest usable tip is [{near[0][0]:.4f}, {near[0][1]:.4f}] m, {near[1] * 1000:.1f} mm away"
                if near else "; no tip of the field is usable")
        y_lo, y_hi, z_lo, z_hi = self.bounds
        if not (y_lo <= p[0] <= y_hi and z_lo <= p[1] <= z_hi):
            return (f"{where} is outside the field grid (y in [{y_lo:.3f}, {y_hi:.3f}], z in "
                    f"[{z_lo:.3f}, {z_hi:.3f}] m), so outside the workspace" + tail)
        # Which corners of the surrounding cell fail, and why.
        i = min(max(math.floor((p[0] - self.y0) / self.h), 0), self._nyc - 1)
        j = min(max(math.floor((p[1] - self.z0) / self.h), 0), self._nzc - 1)
        corners = [(i, j), (i + 1, j), (i, j + 1), (i + 1, j + 1)]
        valid = np.asarray(self.mf.valid, bool)
        if not all(valid[c] for c in corners):
            ws = valid[:-1, :-1] & valid[1:, :-1] & valid[:-1, 1:] & valid[1:, 1:]
            nw = self.nearest_usable(p, ws)
            d = f"{nw[1] * 1000:.1f} mm" if nw else "?"
            return (f"{where} is outside the robust workspace (not reachable under every instance of the "
                    f"error set: joint limits or the shaft through the port; {d} from the nearest "
                    f"reachable tip)" + tail)
        if self.certifiable:
            rs = np.asarray(self.mf.rho_star, float)
            worst = max(float(rs[c]) for c in corners)
            if worst > self.rho_bound:
                return (f"{where}: no gain can certify monotonic convergence there: rho_star = {worst:.4f} > "
                        f"1 - certify_margin = {self.rho_bound:.4f} (by {worst - self.rho_bound:.4f})" + tail)
            if not worst < 1.0:  # usable tips need rho_star < 1 even with certify_margin = 0
                return (f"{where}: no gain can certify monotonic convergence there: rho_star = {worst:.4f} "
                        f"(needs < 1)" + tail)
        return f"{where}: the {self.metric} field is undefined there" + tail


# ============================================================================= OMPL pieces
def _ompl():
    from ompl import base as ob, geometric as og, util as ou
    return ob, og, ou


_CLASSES: dict[str, Any] = {}


def _classes():
    """The OMPL subclasses (defined on first use so that importing this module does not import ompl)."""
    if _CLASSES:
        return _CLASSES
    ob, _, _ = _ompl()

    class CellWalkMotionValidator(ob.MotionValidator):
        """Exact motion validation: every grid cell the straight motion crosses is usable."""

        def __init__(self, si, cm: CostMap):
            super().__init__(si)
            self._seg = cm.segment

        def checkMotion(self, s1, s2):  # noqa: N802 (OMPL's name)
            return self._seg(s1[0], s1[1], s2[0], s2[1], True, False)[0]

    class FieldObjective(ob.OptimizationObjective):
        """``integral (1 + weight * metric) ds`` of each motion, exact on the bilinear field, with the
        admissible heuristic ``distance * min(1 + weight * metric)``.

        (A Python ``StateCostIntegralObjective`` subclass is never called from C++ in ompl 2.0.1,
        so the integral is done here, in ``motionCost``, with plain floats.)
        """

        def __init__(self, si, cm: CostMap):
            super().__init__(si)
            self._seg = cm.segment
            self._fmin = cm.f_min
            self._Cost = ob.Cost
            self._zero = ob.Cost(0.0)
            self._clock = _time.perf_counter
            self.deadline = math.inf
            self.heuristic_calls = 0
            self.max_heuristic_calls = math.inf

        def motionCost(self, s1, s2):  # noqa: N802
            return self._Cost(self._seg(s1[0], s1[1], s2[0], s2[1], False, True)[1])

        def motionCostHeuristic(self, s1, s2):  # noqa: N802
            # After the deadline the heuristic drops to 0 (still admissible): OMPL's rejection
            # sampler for informed sets loops without checking the termination condition, and a
            # zero heuristic accepts the next sample so that the planner gets to check it.
            self.heuristic_calls += 1
            if self.heuristic_calls > self.max_heuristic_calls or self._clock() > self.deadline:
                return self._zero
            return self._Cost(math.hypot(s1[0] - s2[0], s1[1] - s2[1]) * self._fmin)

    _CLASSES.update(mv=CellWalkMotionValidator, obj=FieldObjective)
    return _CLASSES


def make_space_information(cm: CostMap, bounds: tuple[float, float, float, float] | None = None):
    """``(space, si)``: a 2-D ``RealVectorStateSpace`` over ``bounds`` ``(y_lo, y_hi, z_lo, z_hi)``
    (m, default: the grid bounds) and its ``SpaceInformation`` with the point validity and the
    exact motion validator of ``cm``."""
    ob, _, _ = _ompl()
    space = ob.RealVectorStateSpace(2)
    b = ob.RealVectorBounds(2)
    y_lo, y_hi, z_lo, z_hi = bounds or cm.bounds
    b.setLow(0, y_lo)
    b.setHigh(0, y_hi)
    b.setLow(1, z_lo)
    b.setHigh(1, z_hi)
    space.setBounds(b)
    si = ob.SpaceInformation(space)
    point_ok = cm.point_ok
    si.setStateValidityChecker(lambda s: point_ok(s[0], s[1]))
    si.setMotionValidator(_classes()["mv"](si, cm))
    # Used only by OMPL routines that interpolate states themselves: finer than the grid.
    si.setStateValidityCheckingResolution(min(1.0, 0.25 * cm.h / max(space.getMaximumExtent(), 1e-12)))
    si.setup()
    return space, si


def make_objective(si, cm: CostMap):
    """The :class:`FieldObjective` of ``cm`` on ``si``."""
    return _classes()["obj"](si, cm)


# Iterations (planner termination checks) per second of budget: the planner stops after
# ``time * ITERATION_RATE`` iterations or ``time`` seconds, whichever comes first. The iteration cap
# makes a run a function of the seed (on this reference machine, 2 cores, it is reached in about
# half the time budget; benchmarks/planning.py); the time cap bounds it on slower machines, and
# PlanResult.stopped_by says which one ended the search.
ITERATION_RATE = {"BITstar": 10000, "RRTstar": 250, "InformedRRTstar": 250, "SORRTstar": 250,
                  "FMT": 2000, "BFMT": 2000, "RRTConnect": 2000}
DEFAULT_PLANNER = "BITstar"
# OMPL's informed samplers for a general objective draw uniform samples and reject those whose
# heuristic cost is outside a cost shell; when the shell is thin (short queries near the edge of the
# region) they stall inside one iteration. A search normally makes 20-50 heuristic calls per
# iteration (benchmarks/planning.py); past this many per allowed iteration the heuristic drops to 0
# (still admissible) and the search stops ("sampling"): deterministic, unlike a time limit.
HEURISTIC_CALLS_PER_ITERATION = 100


def _make_planner(name: str, si, time_budget: float):
    _, og, _ = _ompl()
    if name in ("PRM", "PRMstar", "LazyPRM", "LazyPRMstar", "SPARS", "SPARStwo"):
        raise ErrplanError(f"planner = {name!r}: roadmap planners deadlock with errplan's Python objective "
                           f"in ompl 2.0.1 (they run threads that need the GIL); use one of {', '.join(PLANNERS)}")
    if name not in PLANNERS:
        raise ErrplanError(f"planner = {name!r}: expected one of {', '.join(PLANNERS)}")
    pl = getattr(og, name)(si)
    if name in ("FMT", "BFMT"):
        # FMT* evaluates the neighbour pairs of a fixed sample set: size it to the budget
        # (about 0.3-0.5 s for 300 samples here), and let it use the cost-to-go heuristic.
        pl.setNumSamples(max(100, int(400 * time_budget)))
        pl.setHeuristics(True)
    return pl


# ============================================================================= path refinement
@dataclass
class RefineResult:
    """Outcome of :func:`refine_path`: the path (n, 2) and its cost before and after."""

    path: np.ndarray
    cost: float
    cost_before: float
    sweeps: int
    time: float


def _reduce_vertices(cm: CostMap, pts: list[list[float]], seg_cost: list[float]) -> bool:
    """Greedy shortcuts: from each vertex, jump to the farthest later vertex whose straight
    connection is valid and not more expensive than the sub-path it replaces."""
    changed = False
    i = 0
    while i < len(pts) - 2:
        best = None
        sub = seg_cost[i]
        acc = [sub]
        for j in range(i + 2, len(pts)):
            acc.append(acc[-1] + seg_cost[j - 1])
        for j in range(len(pts) - 1, i + 1, -1):
            ok, c = cm.segment(pts[i][0], pts[i][1], pts[j][0], pts[j][1])
            if ok and c <= acc[j - i - 1] * (1 + 1e-12):
                best = (j, c)
                break
        if best is not None:
            j, c = best
            del pts[i + 1:j]
            seg_cost[i:j] = [c]
            changed = True
        i += 1
    return changed


def _relax(cm: CostMap, pts: list[list[float]], seg_cost: list[float], step: float, stop: float,
           max_sweeps: int, deadline: float | None, tangent: bool) -> int:
    """Gauss-Seidel vertex relaxation (see :func:`refine_path`); returns the number of sweeps."""
    seg = cm.segment
    sweeps = 0
    while step >= stop and sweeps < max_sweeps:
        if deadline is not None and _time.perf_counter() > deadline:
            break
        sweeps += 1
        moved = 0
        for k in range(1, len(pts) - 1):
            a, p, b = pts[k - 1], pts[k], pts[k + 1]
            ty, tz = b[0] - a[0], b[1] - a[1]
            tn = math.hypot(ty, tz)
            if tn == 0:
                continue
            ty, tz = ty / tn, tz / tn
            here = seg_cost[k - 1] + seg_cost[k]
            best = None
            dirs = ((-tz, ty), (tz, -ty), (ty, tz), (-ty, -tz)) if tangent else ((-tz, ty), (tz, -ty))
            for dy, dz in dirs:
                q0, q1 = p[0] + step * dy, p[1] + step * dz
                ok1, c1 = seg(a[0], a[1], q0, q1, True)
                if not ok1 or c1 >= here:
                    continue
                ok2, c2 = seg(q0, q1, b[0], b[1], True)
                if ok2 and c1 + c2 < here - 1e-15:
                    here = c1 + c2
                    best = (q0, q1, c1, c2)
            if best is not None:
                pts[k] = [best[0], best[1]]
                seg_cost[k - 1], seg_cost[k] = best[2], best[3]
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
            out.append([a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t])
    return out


def refine_path(cm: CostMap, path, *, spacing: float | None = None, min_step: float | None = None,
                max_sweeps: int = 60, deadline: float | None = None) -> RefineResult:
    """Lower the cost of a valid polyline (n, 2) (m) by shortcuts and a coarse-to-fine relaxation.

    1. Greedy shortcuts (never raising the cost). 2. Coarse-to-fine relaxation: the path is
    subdivided into vertices about ``length / 8`` apart and relaxed, then subdivided to half that
    spacing and relaxed again, down to ``spacing`` (default ``max(2 h, length / 64)``, at most
    ``length / 16``). Relaxing: each interior vertex in turn tries moves of ``+-step`` across (and,
    at the finest level, along) the path and keeps the best one that lowers the exact cost of its
    two segments while keeping both valid; the step starts at a quarter of the spacing and halves
    when a sweep moves nothing, down to ``spacing / 16`` (``min_step``, default ``h / 32``, at the
    finest level). The coarse levels remove the long-wavelength error that a fine vertex relaxation
    alone removes very slowly. 3. Shortcuts again. Every accepted change keeps the path valid and
    lowers its cost, so the result is never worse than the input. Deterministic; ``deadline`` (a
    ``time.perf_counter()`` value) stops it early.
    """
    t0 = _time.perf_counter()
    orig = [[float(p[0]), float(p[1])] for p in np.asarray(path, float)]
    pts = [p[:] for p in orig]
    seg = cm.segment
    ok0, cost0 = cm.path_cost(pts)
    if not ok0:
        raise ErrplanError("refine_path: the input path leaves the usable region")

    def costs(p):
        return [seg(a[0], a[1], b[0], b[1], False)[1] for a, b in zip(p[:-1], p[1:])]

    seg_cost = costs(pts)
    _reduce_vertices(cm, pts, seg_cost)
    length = sum(math.dist(a, b) for a, b in zip(pts[:-1], pts[1:]))
    finest = spacing or min(max(2 * cm.h, length / 64), length / 16)
    sp = max(length / 8, finest)
    sweeps = 0
    while True:
        pts = _subdivide(pts, sp)
        seg_cost = costs(pts)
        last = sp <= finest * (1 + 1e-9)
        stop = (min_step or cm.h / 32) if last else sp / 16
        sweeps += _relax(cm, pts, seg_cost, 0.25 * sp, stop, max_sweeps, deadline, tangent=last)
        if last or (deadline is not None and _time.perf_counter() > deadline):
            break
        sp = max(sp / 2, finest)
    _reduce_vertices(cm, pts, seg_cost)
    ok1, cost1 = cm.path_cost(pts)
    if not ok1 or cost1 >= cost0:
        pts, cost1 = orig, cost0
    return RefineResult(np.array(pts), cost1, cost0, sweeps, _time.perf_counter() - t0)


# ============================================================================= results
def _jsonable(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


@dataclass
class PathReport:
    """One path of a query (the ``P`` object of the plan JSON, docs/interfaces.md).

    Attributes
    ----------
    path : ndarray (n, 2)
        Vertices ``[y, z]`` (m) from start to goal; straight segments between them.
    cost : float or None
        ``integral (1 + weight * metric) ds`` (m), exact on the bilinear field; None when the path
        leaves the robust workspace (the field is undefined there).
    length : float
        Length (m).
    max_G_norm, max_phi_hat_max : float or None
        Largest worst-case ``||G||`` (at the scenario gain) and ``phi_hat_max`` (rad) along the path:
        the exact maximum of the bilinear fields on every piece of every segment
        (:meth:`CostMap.field_max`); None outside the workspace.
    valid : bool
        The path stays in the usable region (workspace and, if asked, certifiable).
    in_workspace : bool
        The path stays in the robust workspace (reachable under every error instance).
    length_G_above_1 : float or None
        Length (m) of the path where the worst-case ``||G|| >= 1`` (no monotonic convergence
        guaranteed at the scenario gain).
    max_rho_star : float or None
        Largest ``rho_star`` along the path (when the fields have it).
    """

    path: np.ndarray
    cost: float | None
    length: float
    max_G_norm: float | None
    max_phi_hat_max: float | None
    valid: bool
    in_workspace: bool
    length_G_above_1: float | None = None
    max_rho_star: float | None = None

    def to_json(self) -> dict:
        return {"path": [[float(a), float(b)] for a, b in self.path], "cost": _jsonable(self.cost),
                "length": float(self.length), "max_G_norm": _jsonable(self.max_G_norm),
                "max_phi_hat_max": _jsonable(self.max_phi_hat_max), "valid": bool(self.valid),
                "in_workspace": bool(self.in_workspace), "length_G_above_1": _jsonable(self.length_G_above_1),
                "max_rho_star": _jsonable(self.max_rho_star)}


def path_report(cm: CostMap, path, workspace_map: CostMap | None = None) -> PathReport:
    """The :class:`PathReport` of a polyline on ``cm`` (``workspace_map``: the same objective
    without the certifiable restriction, used for paths that leave the usable region)."""
    path = np.asarray(path, float)
    length = float(np.sum(np.hypot(*np.diff(path, axis=0).T))) if len(path) > 1 else 0.0
    valid, cost = cm.path_cost(path)
    wm = workspace_map
    if valid:
        in_ws = True
    else:
        if wm is None:
            wm = cm if not cm.certifiable else CostMap(cm.mf, cm.metric, cm.weight, certifiable=False)
        in_ws, cost = wm.path_cost(path)
    mx_g = mx_p = above = mx_r = None
    if in_ws:
        m = cm if valid else wm
        mx_g, mx_p = m.field_max("G_norm", path), m.field_max("phi_hat_max", path)
        above = m.field_length_above("G_norm", path, 1.0)
        if getattr(cm.mf, "rho_star", None) is not None:
            mx_r = m.field_max("rho_star", path)
    else:
        cost = None
    return PathReport(path, cost, length, mx_g, mx_p, bool(valid), bool(in_ws), above, mx_r)


@dataclass(frozen=True)
class PlannerSettings:
    """How to search: OMPL planner name, time budget per query (s), seed, iteration cap, refinement.

    ``iterations`` (default ``time * ITERATION_RATE[planner]``) caps the planner's iterations so a run
    depends only on the seed while the cap is reached within ``time``.
    """

    planner: str = DEFAULT_PLANNER
    time: float = 1.0
    seed: int = 1
    iterations: int | None = None
    refine: bool = True
    refine_share: float = 0.25  # share of the time budget kept for refine_path

    @classmethod
    def from_scenario(cls, sc, planner: str | None = None, time: float | None = None,
                      seed: int | None = None, **kw) -> "PlannerSettings":
        p = sc.planner
        return cls(planner=planner or p.planner, time=float(time if time is not None else p.time),
                   seed=int(seed if seed is not None else p.seed), **kw)

    def iteration_cap(self) -> int:
        if self.iterations is not None:
            return int(self.iterations)
        return max(50, int(self.time * (1 - self.refine_share) * ITERATION_RATE.get(self.planner, 1000)))

    def check(self) -> None:
        if self.planner not in PLANNERS:
            _make_planner(self.planner, None, 0.0)  # raises the explanatory error
        if not (self.time > 0 and math.isfinite(self.time)):
            raise ErrplanError(f"time = {self.time!r}: expected a planning time > 0 s")
        if isinstance(self.seed, bool) or self.seed < 0:
            raise ErrplanError(f"seed = {self.seed!r}: expected an integer >= 0")


@dataclass
class QueryPlan:
    """The plan of one query: planned and direct paths, and how the search went.

    ``extra`` holds keys added by later steps (``gains``, ``simulation``); :meth:`to_json` merges it.
    """

    name: str
    start: tuple[float, float]
    goal: tuple[float, float]
    planned: PathReport
    direct: PathReport
    planner: str
    seed: int
    iterations: int
    stopped_by: str  # how the last search phase ended (see plan_query): "iterations" (the cap),
    #                  "time" (the budget), "sampling" (stalled informed sampling), "planner" (by itself)
    time_solve: float
    time_refine: float
    raw_cost: float  # cost of the planner's own path, before refine_path
    extra: dict = field(default_factory=dict)

    @property
    def time_total(self) -> float:
        return self.time_solve + self.time_refine

    def to_json(self) -> dict:
        out = {"name": self.name, "start": [float(self.start[0]), float(self.start[1])],
               "goal": [float(self.goal[0]), float(self.goal[1])],
               "planned": self.planned.to_json(), "direct": self.direct.to_json(),
               "search": {"planner": self.planner, "seed": self.seed, "iterations": self.iterations,
                          "stopped_by": self.stopped_by, "time_solve": self.time_solve,
                          "time_refine": self.time_refine, "raw_cost": _jsonable(self.raw_cost)}}
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

    def to_json(self) -> dict:
        return {"scenario": self.scenario,
                "objective": {"metric": self.metric, "weight": self.weight, "certifiable": self.certifiable,
                              "certify_margin": self.costmap.certify_margin,
                              "resolution": self.costmap.h,
                              "definition": "integral of (1 + weight * metric) ds, metric bilinear in the field"},
                "queries": [q.to_json() for q in self.queries]}


# ============================================================================= planning
def check_endpoints(cm: CostMap, start, goal, name: str = "query") -> None:
    """Raise :class:`InfeasibleError` naming the endpoint, the cause and by how much when the start
    or goal is unusable, or when they lie in disconnected parts of the usable region."""
    for what, p in (("start", start), ("goal", goal)):
        msg = cm.explain_point(p, f"{name}: {what}")
        if msg:
            raise InfeasibleError(msg)
    if not cm.connected(start, goal):
        raise InfeasibleError(f"{name}: start {list(map(float, start))} and goal {list(map(float, goal))} lie in "
                              f"disconnected parts of the usable region: no path exists")


def search_box(cm: CostMap, start, goal, bound_cost: float) -> tuple[float, float, float, float]:
    """Bounding box (y_lo, y_hi, z_lo, z_hi) of every path from ``start`` to ``goal`` cheaper than
    ``bound_cost``: such a path through x is at least ``|x - start| + |x - goal|`` long and costs at
    least ``f_min`` per metre, so x lies in the ellipse with foci start, goal and major axis
    ``bound_cost / f_min``. Padded by two cells and clipped to the grid."""
    s, g = np.asarray(start, float), np.asarray(goal, float)
    d = float(np.hypot(*(g - s)))
    a = max(0.5 * bound_cost / cm.f_min, 0.5 * d)
    b = math.sqrt(max(a * a - 0.25 * d * d, 0.0))
    th = math.atan2(g[1] - s[1], g[0] - s[0]) if d > 0 else 0.0
    hy = math.sqrt((a * math.cos(th)) ** 2 + (b * math.sin(th)) ** 2) + 2 * cm.h
    hz = math.sqrt((a * math.sin(th)) ** 2 + (b * math.cos(th)) ** 2) + 2 * cm.h
    c = 0.5 * (s + g)
    y_lo, y_hi, z_lo, z_hi = cm.bounds
    return (max(y_lo, c[0] - hy), min(y_hi, c[0] + hy), max(z_lo, c[1] - hz), min(z_hi, c[1] + hz))


def _search(cm: CostMap, start, goal, planner_name: str, box, cap: int, t_end: float,
            first_only: bool) -> tuple[np.ndarray | None, int, str, str]:
    """One OMPL search in ``box``: ``(path or None, iterations, stopped_by, status)``.

    Stops after ``cap`` iterations, at ``t_end`` (a ``time.perf_counter()`` value) or, with
    ``first_only``, at the first exact solution.
    """
    ob, og, _ = _ompl()
    space, si = make_space_information(cm, box)
    obj = make_objective(si, cm)
    ss = og.SimpleSetup(si)
    s = space.allocState()
    s[0], s[1] = start
    g = space.allocState()
    g[0], g[1] = goal
    ss.setStartAndGoalStates(s, g)
    ss.setOptimizationObjective(obj)
    planner = _make_planner(planner_name, si, max(t_end - _time.perf_counter(), 0.0))
    ss.setPlanner(planner)
    pdef = ss.getProblemDefinition()
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
    path = np.array([[p.getState(i)[0], p.getState(i)[1]] for i in range(p.getStateCount())])
    path[0], path[-1] = start, goal
    return path, n, why[0], str(status)


def plan_query(cm: CostMap, start, goal, settings: PlannerSettings | None = None, name: str = "query",
               workspace_map: CostMap | None = None) -> QueryPlan:
    """Plan one query on ``cm`` with OMPL, refine the solution, and report planned vs direct.

    The search runs in the box where a path cheaper than a known one can be (:func:`search_box`):
    the straight line's cost when it is usable; otherwise a first search over the whole grid stops
    at its first solution, whose cost bounds the box of the second. This keeps informed samplers
    (BIT*, Informed RRT*) from stalling on a small informed set in a large space. Every iteration
    counts against one cap, and both phases share the time budget.

    Raises :class:`InfeasibleError` for an unusable start or goal, disconnected endpoints, or no
    exact solution within the budget (no partial result is returned).
    """
    _, _, ou = _ompl()
    st = settings or PlannerSettings()
    st.check()
    start = (float(start[0]), float(start[1]))
    goal = (float(goal[0]), float(goal[1]))
    check_endpoints(cm, start, goal, name)
    ou.setLogLevel(ou.LOG_NONE)
    t_begin = _time.perf_counter()
    direct = path_report(cm, np.array([start, goal]), workspace_map)
    if math.dist(start, goal) < 1e-12:  # nothing to plan
        return QueryPlan(name, start, goal, direct, direct, st.planner, st.seed, 0, "planner", 0.0, 0.0, 0.0)
    t_end = t_begin + (st.time * (1 - st.refine_share) if st.refine else st.time)
    cap = st.iteration_cap()
    # OMPL refuses seed 0: seed s maps to s + 1. Reseed before anything draws from the RNG so that
    # each query is a function of the seed, whatever was planned before in this process.
    ou.RNG.setSeed(st.seed + 1)
    used = 0
    first = None
    if direct.valid:
        bound = direct.cost
    else:
        first, used, why, status = _search(cm, start, goal, st.planner, None, cap, t_end, first_only=True)
        if first is None:
            raise InfeasibleError(
                f"{name}: {st.planner} found no path from {list(start)} to {list(goal)} within the budget "
                f"({_time.perf_counter() - t_begin:.2f} s, {used} iterations; status: {status}); "
                f"try a longer --time")
        bound = cm.path_cost(first)[1]
    box = search_box(cm, start, goal, bound)
    raw, n, why, status = _search(cm, start, goal, st.planner, box, max(cap - used, 1), t_end, first_only=False)
    used += n
    if raw is None:
        raw = first
    if raw is None:
        raise InfeasibleError(
            f"{name}: {st.planner} found no path from {list(start)} to {list(goal)} within the budget "
            f"({_time.perf_counter() - t_begin:.2f} s, {used} iterations; status: {status}); try a longer --time")
    ok, raw_cost = cm.path_cost(raw)
    if not ok:  # cannot happen with the exact motion validator; refuse rather than return it
        raise InfeasibleError(f"{name}: internal: the planner's path leaves the usable region")
    best, best_cost = raw, raw_cost
    for cand in ([first] if first is not None else []) + ([np.array([start, goal])] if direct.valid else []):
        c = cm.path_cost(cand)[1]
        if c < best_cost:
            best, best_cost = cand, c
    time_solve = _time.perf_counter() - t_begin
    t1 = _time.perf_counter()
    if st.refine:
        best = refine_path(cm, best, deadline=t_begin + st.time).path
    time_refine = _time.perf_counter() - t1
    planned = path_report(cm, best, workspace_map)
    return QueryPlan(name, start, goal, planned, direct, st.planner, st.seed, used, why, time_solve,
                     time_refine, float(raw_cost))


def fields_for_planning(sc, resolution: float | None = None, progress=None):
    """The worst-case fields a scenario's planner needs (``rho_star`` too when certifiable or when
    it is the metric), at ``resolution`` (default ``[fields] resolution``)."""
    from .fields import compute_fields

    need_rho = sc.planner.certifiable or sc.planner.metric == "rho_star"
    return compute_fields(sc, resolution, rho_star=need_rho, progress=progress)


def costmap_for(sc, mf) -> CostMap:
    """The :class:`CostMap` of a scenario's ``[planner]`` table on the fields ``mf``."""
    p = sc.planner
    need_rho = p.certifiable or p.metric == "rho_star"
    if need_rho and getattr(mf, "rho_star", None) is None:
        raise ErrplanError("the fields have no rho_star (needed by [planner] certifiable = true or metric = "
                           "\"rho_star\"): compute them with rho_star=True (errplan fields --rho-star)")
    return CostMap(mf, p.metric, p.weight, p.certifiable, p.certify_margin)


def select_queries(sc, name: str | None = None) -> list:
    """The scenario's queries, or only the one called ``name`` (clear error listing the names)."""
    qs = list(sc.queries)
    if not qs:
        raise ErrplanError(f"{sc.source}: the scenario has no [[query]] to plan (add [[query]] tables with "
                           f"name, start = [y, z], goal = [y, z])")
    if name is None:
        return qs
    for q in qs:
        if q.name == name:
            return [q]
    raise ErrplanError(f"--query {name!r}: no such query in {sc.source}; its queries are: "
                       + ", ".join(repr(q.name) for q in qs))


def plan_scenario(sc, mf=None, *, query: str | None = None, planner: str | None = None,
                  time: float | None = None, seed: int | None = None, settings: PlannerSettings | None = None,
                  progress: Callable[[float, str], None] | None = None) -> ScenarioPlan:
    """Plan every ``[[query]]`` of a scenario (or only ``query``) on its worst-case fields.

    ``mf`` (a :class:`~errplan.fields.MetricField`) is computed when not given. ``planner``,
    ``time`` and ``seed`` override ``[planner]``. Every endpoint is checked before any search,
    so a bad query fails fast with :class:`InfeasibleError`. Returns a :class:`ScenarioPlan`.
    """
    qs = select_queries(sc, query)
    st = settings or PlannerSettings.from_scenario(sc, planner=planner, time=time, seed=seed)
    st.check()
    t0 = _time.perf_counter()
    if mf is None:
        mf = fields_for_planning(sc, progress=progress)
    field_time = _time.perf_counter() - t0
    cm = costmap_for(sc, mf)
    if not cm.any_usable:
        raise InfeasibleError(f"{sc.source}: no grid cell is usable for planning (robust workspace"
                              + (f" with rho_star <= {cm.rho_bound:g}" if cm.certifiable else "") + " is empty)")
    for q in qs:
        check_endpoints(cm, q.start, q.goal, f"query {q.name!r}")
    wm = CostMap(mf, cm.metric, cm.weight, certifiable=False) if cm.certifiable else cm
    plans = []
    for n, q in enumerate(qs):
        if progress:
            progress(n / len(qs), f"planning {q.name}")
        plans.append(plan_query(cm, q.start, q.goal, st, name=f"query {q.name!r}", workspace_map=wm))
        plans[-1].name = q.name
    if progress:
        progress(1.0, "planned")
    return ScenarioPlan(sc.name, cm.metric, cm.weight, cm.certifiable, st, plans, cm, field_time)
