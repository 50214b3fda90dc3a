"""An independent, near-optimal reference for the planner: Dijkstra on the field grid with long moves.

Every claim about the quality of a planned path is a ratio to :func:`grid_optimum`, the exact
shortest path of the same objective ``integral (1 + weight * metric) ds`` over the same usable
region (:class:`errplan.planning.CostMap`: cells whose four corners are usable) among polylines
whose vertices are grid nodes (plus the start and the goal), with moves to every node ``(a, b)``
cells away, ``max(|a|, |b|) <= radius`` and ``gcd(a, b) = 1`` (radius 2: 16-connected, 3: 32,
4: 48 + ...). Edges are valid only when every cell they cross is usable, so the reference path also
stays in the region between its vertices.

The implementation shares nothing with the planner's cost code: edge costs here are vectorised
over the grid with Simpson's rule on each piece between grid-line crossings (exact for the
bilinear interpolant, a quadratic along a line inside a cell), and the search is
``scipy.sparse.csgraph.dijkstra``. Restricting directions to the move set makes the grid optimum
an upper bound of the continuous optimum; the excess is at most ``1 / cos(gap / 2) - 1`` of the
cost for the largest angular gap between moves (radius 2: 2.7 %, 3: 1.3 %, 4: 0.8 %, 6: 0.4 %),
and in practice much smaller (tested by refinement in tests/test_planning.py).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from .errors import InfeasibleError


@dataclass
class ReferenceResult:
    """The grid optimum of one query.

    Attributes
    ----------
    cost : float
        Optimal cost (m, weighted length) among grid polylines with the move set.
    path : ndarray (n, 2)
        The optimal polyline ``[y, z]`` (m) from start to goal.
    radius : int
        Move radius used (see module docstring).
    angular_bound : float
        ``1 / cos(gap / 2) - 1``: the largest relative excess of a move-set path over a straight
        line in the worst direction.
    time : float
        Seconds spent (edge costs + search).
    """

    cost: float
    path: np.ndarray
    radius: int
    angular_bound: float
    time: float


def moves(radius: int) -> list[tuple[int, int]]:
    """Primitive moves ``(a, b)`` with ``max(|a|, |b|) <= radius`` and ``gcd(|a|, |b|) = 1``."""
    out = []
    for a in range(-radius, radius + 1):
        for b in range(-radius, radius + 1):
            if (a, b) != (0, 0) and math.gcd(abs(a), abs(b)) == 1:
                out.append((a, b))
    return out


def angular_bound(radius: int) -> float:
    ang = sorted({math.atan2(b, a) % (2 * math.pi) for a, b in moves(radius)})
    gaps = [b - a for a, b in zip(ang, ang[1:] + [ang[0] + 2 * math.pi])]
    return 1.0 / math.cos(max(gaps) / 2) - 1.0


def _pieces(a: int, b: int) -> list[tuple[float, float, int, int]]:
    """Pieces ``(t0, t1, di, dj)`` of the move from a grid node by ``(a, b)`` cells: parameter
    interval and the cell ``(i + di, j + dj)`` it lies in."""
    ts = {0.0, 1.0}
    for k in range(1, abs(a)):
        ts.add(k / abs(a))
    for k in range(1, abs(b)):
        ts.add(k / abs(b))
    ts = sorted(ts)
    out = []
    for t0, t1 in zip(ts[:-1], ts[1:]):
        if t1 - t0 < 1e-12:
            continue
        tm = 0.5 * (t0 + t1)
        out.append((t0, t1, math.floor(a * tm), math.floor(b * tm)))
    return out


def _bilinear(f: np.ndarray, ci, cj, a, b):
    """Bilinear value of node array ``f`` in cells ``(ci, cj)`` at local coordinates ``(a, b)``."""
    return ((1 - a) * (1 - b) * f[ci, cj] + a * (1 - b) * f[ci + 1, cj]
            + (1 - a) * b * f[ci, cj + 1] + a * b * f[ci + 1, cj + 1])


def segment_cost(cm, p: np.ndarray, q: np.ndarray) -> tuple[bool, float]:
    """Validity and cost of the straight segment ``p -> q`` (m) on ``cm`` by Simpson's rule on each
    piece between grid-line crossings (independent of :meth:`CostMap.segment`)."""
    p = np.asarray(p, float)
    q = np.asarray(q, float)
    h = cm.h
    u0 = (p - [cm.y0, cm.z0]) / h
    d = (q - p) / h
    ts = [0.0, 1.0]
    for ax in range(2):
        if abs(d[ax]) > 1e-15:
            lo, hi = sorted((u0[ax], u0[ax] + d[ax]))
            ks = np.arange(math.ceil(lo), math.floor(hi) + 1)
            ts.extend(((ks - u0[ax]) / d[ax]).tolist())
    t = np.unique(np.clip(ts, 0.0, 1.0))
    t0, t1 = t[:-1], t[1:]
    keep = t1 - t0 > 1e-9
    t0, t1 = t0[keep], t1[keep]
    if len(t0) == 0:
        t0, t1 = np.array([0.0]), np.array([1.0])
    tm = 0.5 * (t0 + t1)
    um = u0 + tm[:, None] * d
    ci = np.floor(um[:, 0]).astype(int)
    cj = np.floor(um[:, 1]).astype(int)
    # A motion along a grid line: the cells on both sides of the line touch it.
    on_line = [abs(d[ax]) < 1e-15 and abs(u0[ax] - round(u0[ax])) < 1e-9 for ax in range(2)]
    if on_line[0]:
        ci[:] = round(u0[0])
    if on_line[1]:
        cj[:] = round(u0[1])
    ny, nz = cm.cell_ok.shape
    def usable(ii, jj):
        inside = (ii >= 0) & (ii < ny) & (jj >= 0) & (jj < nz)
        out = np.zeros(len(ii), bool)
        out[inside] = cm.cell_ok[ii[inside], jj[inside]]
        return out

    good = usable(ci, cj)
    if on_line[0]:
        good |= usable(ci - 1, cj)
    if on_line[1]:
        good |= usable(ci, cj - 1)
    ok = bool(good.all())
    if not ok:
        return False, math.inf
    # Evaluate in a cell that exists (on a line the interpolant is the same on both sides).
    ci = np.clip(ci, 0, ny - 1)
    cj = np.clip(cj, 0, nz - 1)
    f = cm.integrand
    length = float(np.hypot(*(q - p)))
    total = 0.0
    for tt, w in ((t0, 1.0), (tm, 4.0), (t1, 1.0)):
        uu = u0 + tt[:, None] * d
        total = total + w * _bilinear(f, ci, cj, uu[:, 0] - ci, uu[:, 1] - cj)
    return ok, float(np.sum(total * (t1 - t0)) / 6.0 * length)


def _edge_arrays(cm, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Validity (ny, nz) and cost of the move ``(a, b)`` from every node (vectorised)."""
    f = cm.integrand
    cell = cm.cell_ok
    ny, nz = f.shape
    valid = np.zeros((ny, nz), bool)
    cost = np.zeros((ny, nz))
    # Nodes (i, j) whose move stays on the grid.
    i_lo, i_hi = max(0, -a), min(ny, ny - a)
    j_lo, j_hi = max(0, -b), min(nz, nz - b)
    if i_lo >= i_hi or j_lo >= j_hi:
        return valid, cost
    I = np.arange(i_lo, i_hi)[:, None]
    J = np.arange(j_lo, j_hi)[None, :]
    v = np.ones((i_hi - i_lo, j_hi - j_lo), bool)
    c = np.zeros(v.shape)
    length = math.hypot(a, b) * cm.h
    for t0, t1, di, dj in _pieces(a, b):
        ci, cj = I + di, J + dj
        inb = (ci >= 0) & (ci < ny - 1) & (cj >= 0) & (cj < nz - 1)
        cic, cjc = np.clip(ci, 0, ny - 2), np.clip(cj, 0, nz - 2)
        v &= inb & cell[cic, cjc]
        s = 0.0
        for tt, w in ((t0, 1.0), (0.5 * (t0 + t1), 4.0), (t1, 1.0)):
            s = s + w * _bilinear(f, cic, cjc, a * tt - di, b * tt - dj)
        c += s * (t1 - t0) / 6.0 * length
    # Axis moves along a grid line border two cells: the other side also makes them valid.
    if a == 0 or b == 0:
        v2 = np.ones_like(v)
        for t0, t1, di, dj in _pieces(a, b):
            di2, dj2 = (di - 1, dj) if a == 0 else (di, dj - 1)
            ci, cj = I + di2, J + dj2
            inb = (ci >= 0) & (ci < ny - 1) & (cj >= 0) & (cj < nz - 1)
            v2 &= inb & cell[np.clip(ci, 0, ny - 2), np.clip(cj, 0, nz - 2)]
        v |= v2
    valid[i_lo:i_hi, j_lo:j_hi] = v
    cost[i_lo:i_hi, j_lo:j_hi] = c
    return valid, cost


class GridGraph:
    """The move graph of a :class:`~errplan.planning.CostMap` (built once, reused per query)."""

    def __init__(self, cm, radius: int = 4):
        t0 = time.perf_counter()
        self.cm = cm
        self.radius = int(radius)
        ny, nz = cm.integrand.shape
        self.shape = (ny, nz)
        n = ny * nz
        idx = np.arange(n).reshape(ny, nz)
        rows, cols, vals = [], [], []
        for a, b in moves(self.radius):
            v, c = _edge_arrays(cm, a, b)
            src = idx[v]
            ii, jj = np.nonzero(v)
            dst = (ii + a) * nz + (jj + b)
            rows.append(src)
            cols.append(dst)
            vals.append(c[v])
        self.rows = np.concatenate(rows)
        self.cols = np.concatenate(cols)
        self.vals = np.concatenate(vals)
        self.n = n
        self.build_time = time.perf_counter() - t0

    def node_point(self, k: int) -> np.ndarray:
        i, j = divmod(int(k), self.shape[1])
        return np.array([self.cm.y[i], self.cm.z[j]])

    def _attach(self, p: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray]:
        """Grid nodes within ``reach`` cells of ``p`` joined to it by valid segments, and costs."""
        cm = self.cm
        ny, nz = self.shape
        u = (p[0] - cm.y0) / cm.h
        v = (p[1] - cm.z0) / cm.h
        ks, cs = [], []
        for i in range(max(0, math.floor(u) - reach + 1), min(ny, math.floor(u) + reach + 1)):
            for j in range(max(0, math.floor(v) - reach + 1), min(nz, math.floor(v) + reach + 1)):
                if not cm.node_ok[i, j]:
                    continue
                ok, c = segment_cost(cm, p, [cm.y[i], cm.z[j]])
                if ok:
                    ks.append(i * nz + j)
                    cs.append(c)
        return np.array(ks, int), np.array(cs, float)


def grid_optimum(cm, start, goal, radius: int = 4, graph: GridGraph | None = None,
                 attach: int | None = None) -> ReferenceResult:
    """Optimal cost and path from ``start`` to ``goal`` (m) on the move graph of ``cm``.

    ``start`` and ``goal`` are joined to the grid nodes within ``attach`` cells (default
    ``radius``) by valid straight segments, and to each other when the straight line is valid.
    Raises :class:`InfeasibleError` when no path exists.
    """
    t0 = time.perf_counter()
    g = graph if graph is not None and graph.radius == radius and graph.cm is cm else GridGraph(cm, radius)
    s = np.asarray(start, float)
    q = np.asarray(goal, float)
    reach = attach or max(2, radius)
    ks, cs = g._attach(s, reach)
    kg, cg = g._attach(q, reach)
    S, T = g.n, g.n + 1
    rows = [g.rows, np.full(len(ks), S), kg]
    cols = [g.cols, ks, np.full(len(kg), T)]
    vals = [g.vals, cs, cg]
    ok, c = segment_cost(cm, s, q)
    if ok:
        rows.append(np.array([S]))
        cols.append(np.array([T]))
        vals.append(np.array([c]))
    # Zero costs would be dropped by the sparse matrix: costs are >= length > 0 except for a
    # start equal to a node; nudge those to a tiny positive cost.
    vals = [np.maximum(v, 1e-300) for v in vals]
    A = csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(g.n + 2, g.n + 2))
    dist, pred = dijkstra(A, directed=True, indices=S, return_predecessors=True)
    if not np.isfinite(dist[T]):
        raise InfeasibleError(f"grid reference: no valid path from {list(s)} to {list(q)}")
    path = [q]
    k = pred[T]
    while k != S:
        path.append(g.node_point(k))
        k = pred[k]
    path.append(s)
    return ReferenceResult(float(dist[T]), np.array(path[::-1]), radius, angular_bound(radius),
                           time.perf_counter() - t0)
