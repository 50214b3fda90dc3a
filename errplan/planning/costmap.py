"""The d-dimensional cost map: usable region, exact segment cost and validity, regions, explanations.

:class:`CostMap` turns a :class:`~errplan.fields.MetricField` (planar ``[y, z]`` or spatial
``[x, y, z]``) into what the planner needs:

- **usable nodes**: in the robust workspace (``valid``: reachable under every instance of the error
  set), the metric finite and, when ``certifiable``, ``rho_star <= 1 - certify_margin`` (and
  ``< 1``: some gain certifies monotonic convergence there);
- **usable cells**: cells (squares in the plane, voxels in space) whose ``2**d`` corners are all
  usable. The usable region is their closed union; a point is valid when it lies in one. The
  multilinear interpolation of the fields is therefore only ever read inside cells whose corners
  were all evaluated and found valid;
- **the integrand** ``1 + weight * metric`` at the nodes, bi- or trilinear in each cell;
- **segments**: :meth:`CostMap.segment` walks the cells a straight motion passes through and
  integrates the integrand exactly in each (compiled, :mod:`errplan.planning.cellwalk`); a motion
  is valid when every cell it passes through is usable, so a path never leaves the region between
  its vertices, whatever the resolution;
- exact maxima and lengths above a threshold of any field along a polyline (reports), connected
  parts of the region, and a one-line explanation of an unusable point.

Points are d-vectors in metres in the field's axis order (``[y, z]`` or ``[x, y, z]``).
"""
from __future__ import annotations

import itertools
import math
from typing import Sequence

import numpy as np

from ..errors import ErrplanError
from . import cellwalk

METRIC_NAMES = ("phi_hat_max", "G_norm", "phi_max", "rho_star")


def _near_cells(u: float) -> tuple[int, ...]:
    """Cell indices along one axis whose closed interval contains grid coordinate ``u`` (both
    neighbours when ``u`` is within 1e-9 cell of a grid line)."""
    r = round(u)
    if abs(u - r) < 1e-9:
        return (r, r - 1)
    return (math.floor(u),)


def _corner_slices(d: int) -> list[tuple[slice, ...]]:
    """Slices of a node array giving, for every cell, the value at one corner; corner ``c`` in
    ``itertools.product((0, 1), repeat=d)`` order."""
    return [tuple(slice(1, None) if b else slice(None, -1) for b in c) for c in itertools.product((0, 1), repeat=d)]


def multilinear_coefficients(f: np.ndarray) -> list[np.ndarray]:
    """Per-cell coefficients of the multilinear interpolant of node array ``f`` in local coordinates.

    Planar ``[c0, ca, cb, cab]``; spatial ``[c0, ca, cb, cc, cab, cac, cbc, cabc]`` (the order
    :mod:`errplan.planning.cellwalk` reads them in).
    """
    if f.ndim == 2:
        f00, f10, f01, f11 = f[:-1, :-1], f[1:, :-1], f[:-1, 1:], f[1:, 1:]
        return [f00, f10 - f00, f01 - f00, f11 - f10 - f01 + f00]
    c = {k: f[s] for k, s in zip(itertools.product((0, 1), repeat=3), _corner_slices(3))}
    f000, f100, f010, f001 = c[0, 0, 0], c[1, 0, 0], c[0, 1, 0], c[0, 0, 1]
    f110, f101, f011, f111 = c[1, 1, 0], c[1, 0, 1], c[0, 1, 1], c[1, 1, 1]
    return [f000, f100 - f000, f010 - f000, f001 - f000,
            f110 - f100 - f010 + f000, f101 - f100 - f001 + f000, f011 - f010 - f001 + f000,
            f111 - f110 - f101 - f011 + f100 + f010 + f001 - f000]


def piece_poly(F: np.ndarray, a0: Sequence[float], da: Sequence[float]) -> list[float]:
    """Coefficients ``[A, B, C(, E)]`` of the multilinear interpolant of one cell along a line,
    ``f(t) = A + B t + C t^2 (+ E t^3)``, for corner values ``F`` (shape ``(2,) * d``), local
    start ``a0`` and local change per unit of ``t`` ``da`` (cells)."""
    if F.ndim == 2:
        f00, f10, f01, f11 = F[0, 0], F[1, 0], F[0, 1], F[1, 1]
        (a, b), (du, dv) = a0, da
        ca, cb, cab = f10 - f00, f01 - f00, f11 - f10 - f01 + f00
        return [f00 + ca * a + cb * b + cab * a * b, ca * du + cb * dv + cab * (a * dv + b * du), cab * du * dv]
    c0, ca, cb, cc, cab, cac, cbc, cabc = (float(x.item()) for x in multilinear_coefficients(F))
    (a, b, g), (du, dv, dw) = a0, da
    return [c0 + ca * a + cb * b + cc * g + cab * a * b + cac * a * g + cbc * b * g + cabc * a * b * g,
            ca * du + cb * dv + cc * dw + cab * (a * dv + b * du) + cac * (a * dw + g * du)
            + cbc * (b * dw + g * dv) + cabc * (a * b * dw + a * g * dv + b * g * du),
            cab * du * dv + cac * du * dw + cbc * dv * dw + cabc * (a * dv * dw + b * du * dw + g * du * dv),
            cabc * du * dv * dw]


def _poly(c: Sequence[float], t: float) -> float:
    if len(c) == 3:
        return c[0] + c[1] * t + c[2] * t * t
    return c[0] + c[1] * t + c[2] * t * t + c[3] * t * t * t


def _real_roots(c: Sequence[float]) -> list[float]:
    """Real roots of ``c[0] + c[1] t + ...`` (degree <= 3; leading zeros dropped)."""
    c = list(c)
    while len(c) > 1 and abs(c[-1]) <= 1e-300:
        c.pop()
    if len(c) <= 1:
        return []
    if len(c) == 2:
        return [-c[0] / c[1]]
    if len(c) == 3:
        A, B, C = c
        disc = B * B - 4 * A * C
        if disc < 0:
            return []
        r = math.sqrt(disc)
        return [(-B - r) / (2 * C), (-B + r) / (2 * C)]
    r = np.roots(c[::-1])
    return [float(x.real) for x in r if abs(x.imag) <= 1e-12 * max(1.0, abs(x))]


class CostMap:
    """Usable region and integrand ``1 + weight * metric`` of a :class:`~errplan.fields.MetricField`.

    Parameters
    ----------
    mf : MetricField
        The worst-case fields, planar (arrays (ny, nz)) or spatial (arrays (nx, ny, nz));
        ``rho_star`` needed when ``certifiable`` or ``metric = "rho_star"``.
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
    dim : int
        2 (points ``[y, z]``) or 3 (points ``[x, y, z]``).
    axes, axis_names : tuple
        Grid axes (m) and their names; ``origin`` (d,) the first node, ``h`` the spacing (m),
        ``shape`` the node counts. ``x`` (spatial only), ``y``, ``z``, ``x0``, ``y0``, ``z0``,
        ``nx``, ``ny``, ``nz`` name them one by one.
    node_ok : ndarray of bool, ``shape``
        Usable nodes.
    cell_ok : ndarray of bool, ``shape - 1``
        Usable cells (all ``2**d`` corners usable).
    integrand : ndarray, ``shape``
        ``1 + weight * metric`` at the nodes (the maximum over the usable nodes where unusable, so
        that costs stay finite; never read inside a usable cell).
    f_min, f_max : float
        Smallest and largest integrand over usable nodes (``f_min`` is the heuristic's factor).
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
        self.axis_names = tuple(getattr(mf, "axis_names", ("y", "z")))
        self.axes = tuple(np.asarray(getattr(mf, a), float) for a in self.axis_names)
        self.dim = len(self.axes)
        if self.dim not in (2, 3):
            raise ErrplanError(f"the field has {self.dim} axes: planning needs a planar or a spatial grid")
        if any(len(a) < 2 for a in self.axes):
            raise ErrplanError("the field grid needs at least 2 points along every axis to plan on "
                               f"(it has {' x '.join(str(len(a)) for a in self.axes)})")
        for name, a in zip(self.axis_names, self.axes):
            setattr(self, name, a)
            setattr(self, name + "0", float(a[0]))
            setattr(self, "n" + name, len(a))
        self.h = float(mf.resolution)
        self.origin = np.array([a[0] for a in self.axes], float)
        self.shape = tuple(len(a) for a in self.axes)
        m = np.asarray(mf.array(metric), float)
        if m.shape != self.shape:
            raise ErrplanError(f"field {metric!r} has shape {m.shape}, expected {self.shape} (the grid axes)")
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
        cell = np.ones(tuple(n - 1 for n in self.shape), bool)
        for s in _corner_slices(self.dim):
            cell &= ok[s]
        self.cell_ok = cell
        f = 1.0 + self.weight * np.where(ok, m, 0.0)
        self.f_min = float(f[ok].min()) if ok.any() else 1.0
        self.f_max = float(f[ok].max()) if ok.any() else 1.0
        self.integrand = np.where(ok, f, self.f_max)
        self._cells = cell.shape
        self._D = cellwalk.pack(self.origin, self.h, cell.shape, multilinear_coefficients(self.integrand),
                                cell, self.f_max)
        self.anatomy = None  # errplan.anatomy.ShaftClearance, attached by attach_anatomy
        self.anatomy_margin = 0.0  # m of anatomy.required kept beyond [anatomy] clearance (attach_anatomy)
        self._clear = None
        if self.dim == 2:
            self._walk, self._point, self._path = cellwalk.walk2, cellwalk.point_ok2, cellwalk.path_cost2
        else:
            self._walk, self._point, self._path = cellwalk.walk3, cellwalk.point_ok3, cellwalk.path_cost3
        # Compile (or load from numba's cache) now, not inside a planner's time budget.
        o = [float(v) for v in self.origin]
        self._walk(self._D, *o, *o, True, True)
        self._point(self._D, *o)
        self._path(self._D, self.origin[None, :].copy())

    # ------------------------------------------------------------------ points
    @property
    def bounds(self) -> tuple[float, ...]:
        """``(lo, hi)`` of every axis in turn (``(y_lo, y_hi, z_lo, z_hi)`` in the plane), m."""
        return tuple(v for a in self.axes for v in (float(a[0]), float(a[-1])))

    @property
    def any_usable(self) -> bool:
        return bool(self.cell_ok.any())

    def grid_text(self) -> str:
        """``"221 x 172 grid at 2 mm"``."""
        return f"{' x '.join(str(n) for n in self.shape)} grid at {self.h * 1000:g} mm"

    def attach_anatomy(self, model, margin: float = 0.0) -> "CostMap":
        """Keep every point of every path robustly clear of ``model``'s obstacles (an
        :class:`errplan.anatomy.ShaftClearance`; spatial): from now on a point is valid only when it is
        also clear, and a motion only when every tip of it is (exact: one hull query per motion, not
        samples), in :meth:`point_ok`, :meth:`segment`, :meth:`motion`, :meth:`path_cost`, the planner's
        checks and refinement. The cost is unchanged (no clearance term).

        ``margin`` (m): keep ``[anatomy] clearance + margin`` instead (the certifiable planner's room for
        the convergence balls of the gain schedule, :data:`errplan.planning.plan.BALL_MARGIN`); the
        attached model's ``required`` includes it, :attr:`anatomy_margin` says how much of it is margin."""
        if model is None or model.empty:
            return self
        if self.dim != 3:
            raise ErrplanError("anatomy is spatial: the cost map is planar")
        if not (margin >= 0 and math.isfinite(margin)):
            raise ErrplanError(f"anatomy margin = {margin!r}: expected a length >= 0 m")
        if margin > 0:
            from dataclasses import replace

            model = replace(model, required=model.required + margin)
        self.anatomy = model
        self.anatomy_margin = float(margin)
        self._clear = model.checker()
        return self

    def attach_view(self, visible) -> "CostMap":
        """Also keep every tip of every motion visible: ``visible(ax, ay, az, bx, by, bz) -> bool`` for a
        straight motion (:func:`errplan.planning.setup_checks.view_checker`), checked with the anatomy's clearance
        wherever that is (points, motions, the planner's checks, the refinement)."""
        if visible is None:
            return self
        if self.dim != 3:
            raise ErrplanError("an endoscope's view is spatial: the cost map is planar")
        self._view = visible
        return self.and_clear(visible)

    def and_clear(self, check) -> "CostMap":
        """Join ``check(ax, ay, az, bx, by, bz) -> bool`` (a straight motion's extra test: the view, the
        arms) to the motion check: a motion is valid when the current check and ``check`` both pass
        (``check`` asked only after the current one passes)."""
        clear = self._clear
        if clear is None:
            self._clear = check
        else:
            self._clear = lambda ax, ay, az, bx, by, bz: (clear(ax, ay, az, bx, by, bz)
                                                         and check(ax, ay, az, bx, by, bz))
        return self

    def point_ok(self, *p: float) -> bool:
        """True if the point (d coordinates) lies in a usable cell (closed cells: a point on a face,
        an edge or a corner counts if any cell touching it is usable), and is robustly clear of the
        anatomy when one is attached."""
        ok = self._point(self._D, *p)
        if ok and self._clear is not None:
            ok = self._clear(*p, *p)
        return ok

    def integrand_at(self, *p: float) -> float:
        """Multilinear ``1 + weight * metric`` at a point (clamped to the grid)."""
        u = [min(max((p[k] - self.origin[k]) / self.h, 0.0), self._cells[k] - 1e-12) for k in range(self.dim)]
        i = [int(x) for x in u]
        F = self.integrand[tuple(slice(a, a + 2) for a in i)]
        return float(piece_poly(F, [x - a for x, a in zip(u, i)], [0.0] * self.dim)[0])

    # ------------------------------------------------------------------ segments
    def segment(self, *coords: float, check: bool = True, cost: bool = True) -> tuple[bool, float]:
        """Validity and exact cost of the straight motion ``a -> b`` given as ``2 d`` coordinates
        (``ya, za, yb, zb`` or ``xa, ya, za, xb, yb, zb``).

        Walks the cells the segment passes through (in order) and integrates the multilinear
        integrand exactly in each (a polynomial of the arc length of degree <= d). Returns
        ``(ok, cost)``: ``ok`` is False when a cell is unusable or the segment leaves the grid
        (then, with ``check``, the walk stops early and the cost is ``inf``).
        """
        return self._walk(self._D, *coords, check, cost)

    def motion(self, a: Sequence[float], b: Sequence[float], check: bool = True) -> tuple[bool, float]:
        """:meth:`segment` of two points (d-sequences)."""
        return self._walk(self._D, *map(float, a), *map(float, b), check, True)

    def motion_ok(self, *coords: float) -> bool:
        return self._walk(self._D, *coords, True, False)[0]

    def path_cost(self, pts: Sequence[Sequence[float]]) -> tuple[bool, float]:
        """``(valid, cost)`` of a polyline (n, d): the sum of exact segment costs."""
        pts = np.ascontiguousarray(pts, dtype=float).reshape(-1, self.dim)
        ok, c = self._path(self._D, pts)
        return bool(ok), float(c)

    def path_ok(self, pts: Sequence[Sequence[float]]) -> bool:
        """True if every segment of the polyline stays in the usable region."""
        pts = np.asarray(pts, float)
        return all(self.motion_ok(*map(float, a), *map(float, b)) for a, b in zip(pts[:-1], pts[1:]))

    def pieces(self, a: Sequence[float], b: Sequence[float]) -> list[tuple[float, float, tuple[int, ...], bool]]:
        """The cells a straight motion passes through, in order: ``(t0, t1, cell, usable)`` with
        ``t`` the motion parameter in [0, 1] and ``cell`` the index tuple (the same walk as
        :meth:`segment`, written for clarity rather than speed; used for reporting)."""
        d, h = self.dim, self.h
        u = [(float(a[k]) - self.origin[k]) / h for k in range(d)]
        du = [(float(b[k]) - float(a[k])) / h for k in range(d)]
        on = [du[k] == 0 and abs(u[k] - round(u[k])) < 1e-9 for k in range(d)]
        idx, step, tmax, tdel = [], [], [], []
        for k in range(d):
            if on[k]:
                idx.append(int(round(u[k])))
                step.append(0)
                tmax.append(math.inf)
                tdel.append(math.inf)
            elif du[k] > 0:
                c = math.floor(u[k] + 1e-12)
                idx.append(c), step.append(1), tmax.append((c + 1 - u[k]) / du[k]), tdel.append(1.0 / du[k])
            elif du[k] < 0:
                c = math.ceil(u[k] - 1e-12) - 1
                idx.append(c), step.append(-1), tmax.append((u[k] - c) / -du[k]), tdel.append(-1.0 / du[k])
            else:
                idx.append(math.floor(u[k])), step.append(0), tmax.append(math.inf), tdel.append(math.inf)
        offsets = [o for o in itertools.product(*[(0, 1) if on[k] else (0,) for k in range(d)])]
        out = []
        t0 = 0.0
        while True:
            tm = min(tmax)
            t1 = 1.0 if tm > 1.0 - 1e-9 else tm
            if t1 > t0 or not out:
                cands = [tuple(i - o for i, o in zip(idx, off)) for off in offsets]
                good = [c for c in cands if all(0 <= c[k] < self._cells[k] for k in range(d)) and self.cell_ok[c]]
                out.append((t0, t1, good[0] if good else tuple(idx), bool(good)))
                t0 = t1
            if t1 >= 1.0:
                return out
            for k in range(d):
                if tmax[k] - tm < 1e-9:
                    idx[k] += step[k]
                    tmax[k] += tdel[k]

    def _piece_polys(self, name: str, path, shift: float = 0.0):
        """For every piece of every segment of ``path``: ``(t0, t1, poly, segment length)`` of the
        field ``name`` minus ``shift``; None when a piece meets a cell with an undefined corner."""
        arr = np.asarray(self.mf.array(name), float)
        path = np.asarray(path, float).reshape(-1, self.dim)
        segs = list(zip(path[:-1], path[1:])) if len(path) > 1 else [(path[0], path[0])]
        out = []
        for a, b in segs:
            seg_len = float(np.linalg.norm(b - a))
            for t0, t1, cell, _ in self.pieces(a, b):
                if not all(0 <= cell[k] < self._cells[k] for k in range(self.dim)):
                    return None
                F = arr[tuple(slice(c, c + 2) for c in cell)]
                if not np.all(np.isfinite(F)):
                    return None
                a0 = [(a[k] - self.origin[k]) / self.h - cell[k] for k in range(self.dim)]
                da = [(b[k] - a[k]) / self.h for k in range(self.dim)]
                c = piece_poly(F, a0, da)
                c[0] -= shift
                out.append((t0, t1, c, seg_len))
        return out

    def field_max(self, name: str, path) -> float | None:
        """Exact maximum of the multilinear field ``name`` (an attribute of the MetricField) along a
        polyline (n, d), or None if the path meets a cell with an undefined corner."""
        pcs = self._piece_polys(name, path)
        if pcs is None:
            return None
        best = -math.inf
        for t0, t1, c, _ in pcs:
            ts = [t0, t1]
            if len(c) == 3:  # planar: a quadratic, maximal inside only when concave
                A, B, C = c
                if C < 0 and t0 < -B / (2 * C) < t1:
                    ts.append(-B / (2 * C))
            else:
                ts += [t for t in _real_roots([c[1], 2 * c[2], 3 * c[3]]) if t0 < t < t1]
            best = max(best, max(_poly(c, t) for t in ts))
        return float(best)

    def field_length_above(self, name: str, path, threshold: float = 1.0) -> float | None:
        """Length (m) of a polyline where the multilinear field ``name`` is >= ``threshold`` (exact
        per piece: the field is a polynomial of the motion parameter in each cell), or None if the
        path meets a cell with an undefined corner."""
        path = np.asarray(path, float).reshape(-1, self.dim)
        if len(path) < 2:
            return 0.0
        pcs = self._piece_polys(name, path, threshold)
        if pcs is None:
            return None
        total = 0.0
        for t0, t1, c, seg_len in pcs:
            cuts = sorted(t for t in [t0, t1] + _real_roots(c) if t0 <= t <= t1)
            for p0, p1 in zip(cuts[:-1], cuts[1:]):
                if _poly(c, 0.5 * (p0 + p1)) >= 0:
                    total += (p1 - p0) * seg_len
        return float(total)

    # ------------------------------------------------------------------ regions
    def _cell_index(self, p: Sequence[float]) -> tuple[int, ...] | None:
        """A usable cell containing ``p`` (closed cells), or None."""
        near = [_near_cells((float(p[k]) - self.origin[k]) / self.h) for k in range(self.dim)]
        for c in itertools.product(*near):
            if all(0 <= c[k] < self._cells[k] for k in range(self.dim)) and self.cell_ok[c]:
                return c
        return None

    @property
    def components(self) -> np.ndarray:
        """Labels (cell shape) of the connected parts of the usable region (cells touching at a
        face, an edge or a corner are connected; 0 = unusable)."""
        if not hasattr(self, "_labels"):
            from scipy.ndimage import label
            self._labels = label(self.cell_ok, structure=np.ones((3,) * self.dim, int))[0]
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
        idx = np.nonzero(cells)
        if len(idx[0]) == 0:
            return None
        q = np.empty((len(idx[0]), self.dim))
        for k in range(self.dim):
            lo = self.origin[k] + idx[k] * self.h
            q[:, k] = np.clip(float(p[k]), lo, lo + self.h)
        d = np.sqrt(np.sum((q - np.asarray(p, float)) ** 2, axis=1))
        k = int(np.argmin(d))
        return q[k], float(d[k])

    #: how many usable cells (nearest first) :meth:`suggest_usable` looks into, and how many points it checks
    SUGGEST_CELLS = 64
    SUGGEST_CHECKS = 512

    def suggest_usable(self, p: Sequence[float], decimals: int = 4) -> tuple[np.ndarray, float] | None:
        """A tip near ``p`` that passes every check :meth:`explain_point` makes (and the arm checks, when
        attached), written with ``decimals`` decimals as a message prints it, and its distance from ``p``
        (m); None if none of the points looked at passes.

        Usable by construction: candidates are the nearest point of each of the nearest usable cells and
        points between it and the cell's centre (a cell's nearest point can lie on its boundary, where
        the shaft's robust clearance to an obstacle is only just short), rounded as printed, ordered by
        distance; the first that the very checks refusing ``p`` accept is returned. So a suggestion
        pasted back as the query's endpoint passes those checks."""
        if not self.any_usable:
            return None
        x = np.asarray([float(v) for v in p])
        idx = np.nonzero(self.cell_ok)
        lo = np.stack([self.origin[k] + idx[k] * self.h for k in range(self.dim)], axis=1)
        near = np.clip(x, lo, lo + self.h)
        d = np.linalg.norm(near - x, axis=1)
        order = np.argsort(d, kind="stable")[: self.SUGGEST_CELLS]
        cand = []
        for i in order:
            centre = lo[i] + 0.5 * self.h
            for t in (0.0, 0.05, 0.25, 0.5, 1.0):
                cand.append(np.round(near[i] + t * (centre - near[i]), decimals))
        cand = np.unique(np.asarray(cand), axis=0)
        dist = np.linalg.norm(cand - x, axis=1)
        for k in np.argsort(dist, kind="stable")[: self.SUGGEST_CHECKS]:
            if self._usable_tip(cand[k]):
                return cand[k], float(dist[k])
        return None

    def _usable_tip(self, q) -> bool:
        """Whether tip ``q`` passes :meth:`point_ok` and the arm checks (when attached)."""
        if not self.point_ok(*map(float, q)):
            return False
        if getattr(self, "arm_checks", None) is not None:
            from .arm_checks import explain_point as explain_arms

            return explain_arms(self, q) is None
        return True

    def _required_text(self) -> str:
        req = self.anatomy.required - self.anatomy_margin
        if self.anatomy_margin <= 0:
            return f"[anatomy] clearance = {req * 1000:.1f} mm"
        return (f"[anatomy] clearance = {req * 1000:.1f} mm + the {self.anatomy_margin * 1000:.1f} mm a certifiable "
                "plan keeps for its convergence balls")

    def explain_point(self, p: Sequence[float], what: str = "point") -> str | None:
        """None if ``p`` is usable, otherwise a one-line reason naming the point, the cause and
        by how much (distance to the nearest usable tip, or ``rho_star`` against its bound)."""
        p = [float(v) for v in p]
        if len(p) != self.dim:
            names = ", ".join(self.axis_names)
            return f"{what} {p} has {len(p)} coordinates, expected {self.dim} ([{names}]) for this field"
        if not all(math.isfinite(x) for x in p):
            return f"{what} {p} is not a finite point"
        if self.point_ok(*p):
            return None
        fmt = lambda v: "[" + ", ".join(f"{x:.4f}" for x in v) + "]"  # noqa: E731
        where = f"{what} {fmt(p)} m"
        near = self.suggest_usable(p)
        if near is not None:
            tail = f"; the nearest usable tip is {fmt(near[0])} m, {near[1] * 1000:.1f} mm away"
        elif self.any_usable:
            tail = "; no usable tip was found near it"
        else:
            tail = "; no tip of the field is usable"
        b = self.bounds
        if not all(b[2 * k] <= p[k] <= b[2 * k + 1] for k in range(self.dim)):
            box = ", ".join(f"{n} in [{b[2 * k]:.3f}, {b[2 * k + 1]:.3f}]" for k, n in enumerate(self.axis_names))
            return f"{where} is outside the field grid ({box} m), so outside the workspace" + tail
        if self.anatomy is not None:
            c = float(self.anatomy.tip(np.array(p)))
            if c < self.anatomy.required:
                return (f"{where} is not robustly clear of the anatomy: the shaft comes {c * 1000:.1f} mm from an "
                        f"obstacle under some true port, less than {self._required_text()}" + tail)
        # Which corners of the surrounding cell fail, and why.
        i = [min(max(math.floor((p[k] - self.origin[k]) / self.h), 0), self._cells[k] - 1) for k in range(self.dim)]
        corners = [tuple(a + o for a, o in zip(i, off)) for off in itertools.product((0, 1), repeat=self.dim)]
        valid = np.asarray(self.mf.valid, bool)
        cl = getattr(self.mf, "clearance", None)
        if self.anatomy is not None and cl is not None:
            low = [float(cl[c]) for c in corners if np.isfinite(cl[c]) and cl[c] < self.anatomy.required]
            if low:
                return (f"{where}: its grid cell is not robustly clear of the anatomy (at a corner the shaft comes "
                        f"{min(low) * 1000:.1f} mm from an obstacle or the tip is that close to the body wall, under "
                        f"some true port; {self._required_text()})" + tail)
        if not all(valid[c] for c in corners):
            ws = np.ones(self.cell_ok.shape, bool)
            for s in _corner_slices(self.dim):
                ws &= valid[s]
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
