"""An independent, near-optimal reference for the planner: Dijkstra on the field grid with long moves.

Every claim about the quality of a planned path is a ratio to :func:`grid_optimum`, the exact
shortest path of the same objective ``integral (1 + weight * metric) ds`` over the same usable
region (:class:`errplan.planning.CostMap`: cells whose ``2**d`` corners are usable) among
polylines whose vertices are grid nodes (plus the start and the goal), with moves to every node
``m`` cells away, ``max|m_k| <= radius`` and ``gcd(m) = 1``. Planar: radius 2 gives 16 moves, 3:
32, 4: 48; spatial: radius 2 gives 98, 3: 290, 4: 578. Edges are valid only when every cell they
cross is usable, so the reference path also stays in the region between its vertices. A move lying
in a grid plane (or, in space, along a grid line) borders the cells on both sides; it is valid when
the cells on one side are usable, the same side along the whole move: the reference does not thread
a move through the edges where usable cells only touch diagonally, which the closed-cell validity of
the planner allows but no sampling planner can find.

The implementation shares nothing with the planner's cost code: edge costs here are vectorised
over the grid with Simpson's rule on each piece between grid-plane crossings (exact for the
multilinear interpolant, a polynomial of degree <= 3 along a line inside a cell), and the search
is ``scipy.sparse.csgraph.dijkstra``. Restricting directions to the move set makes the grid
optimum an upper bound of the continuous optimum; in free space the excess is at most
:func:`angular_bound` ``= 1 / cos(rho) - 1`` of the cost, with ``rho`` the largest angular
circumradius of the cones spanned by neighbouring move directions (planar, half the largest gap:
radius 2: 2.7 %, 3: 1.3 %, 4: 0.75 %; spatial: radius 2: 4.9 %, 3: 2.5 %, 4: 1.5 %), and in
practice much smaller (tested by refinement in tests/test_planning.py and
tests/test_planning_spatial.py).
"""
from __future__ import annotations

import functools
import itertools
import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from ..errors import InfeasibleError


@dataclass
class ReferenceResult:
    """The grid optimum of one query.

    Attributes
    ----------
    cost : float
        Optimal cost (m, weighted length) among grid polylines with the move set.
    path : ndarray (n, d)
        The optimal polyline (m) from start to goal.
    radius : int
        Move radius used (see module docstring).
    angular_bound : float
        The largest relative excess of a move-set path over a straight line in the worst direction.
    time : float
        Seconds spent (attachments + search; the graph is built once, :class:`GridGraph`).
    """

    cost: float
    path: np.ndarray
    radius: int
    angular_bound: float
    time: float


def moves(radius: int, dim: int = 2) -> list[tuple[int, ...]]:
    """Primitive moves ``m`` with ``max|m_k| <= radius`` and ``gcd(|m|) = 1``."""
    return [m for m in itertools.product(range(-radius, radius + 1), repeat=dim)
            if any(m) and math.gcd(*(abs(x) for x in m)) == 1]


@functools.lru_cache(maxsize=None)
def angular_bound(radius: int, dim: int = 2) -> float:
    """``1 / cos(rho) - 1``: the largest relative excess, over a straight segment, of the cheapest
    conic combination of move directions (``rho``: the largest angular circumradius of the facets of
    the convex hull of the unit move directions; in the plane, half the largest angular gap)."""
    from scipy.spatial import ConvexHull

    u = np.array(moves(radius, dim), float)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return float(1.0 / np.min(-ConvexHull(u).equations[:, -1]) - 1.0)


def _pieces(m: tuple[int, ...]) -> list[tuple[float, float, tuple[int, ...]]]:
    """Pieces ``(t0, t1, offset)`` of the move ``m`` from a grid node: parameter interval and the
    cell ``node + offset`` it lies in (offset 0 on the axes where ``m`` is 0)."""
    ts = {0.0, 1.0}
    for x in m:
        for k in range(1, abs(x)):
            ts.add(k / abs(x))
    ts = sorted(ts)
    out = []
    for t0, t1 in zip(ts[:-1], ts[1:]):
        if t1 - t0 < 1e-12:
            continue
        tm = 0.5 * (t0 + t1)
        out.append((t0, t1, tuple(math.floor(x * tm) for x in m)))
    return out


def _multilinear(f: np.ndarray, cell: tuple[np.ndarray, ...], loc: tuple[np.ndarray, ...]) -> np.ndarray:
    """Multilinear value of node array ``f`` in cells ``cell`` (index arrays) at local coordinates
    ``loc`` (arrays in [0, 1])."""
    out = 0.0
    for corner in itertools.product((0, 1), repeat=f.ndim):
        w = 1.0
        for c, a in zip(corner, loc):
            w = w * (a if c else 1 - a)
        out = out + w * f[tuple(i + c for i, c in zip(cell, corner))]
    return out


def segment_cost(cm, p, q) -> tuple[bool, float]:
    """Validity and cost of the straight segment ``p -> q`` (m, d-vectors) on ``cm`` by Simpson's
    rule on each piece between grid-plane crossings (independent of :meth:`CostMap.segment`)."""
    p = np.asarray(p, float)
    q = np.asarray(q, float)
    d = len(p)
    h = cm.h
    u0 = (p - cm.origin) / h
    dv = (q - p) / h
    ts = [0.0, 1.0]
    for ax in range(d):
        if abs(dv[ax]) > 1e-15:
            lo, hi = sorted((u0[ax], u0[ax] + dv[ax]))
            ks = np.arange(math.ceil(lo), math.floor(hi) + 1)
            ts.extend(((ks - u0[ax]) / dv[ax]).tolist())
    t = np.unique(np.clip(ts, 0.0, 1.0))
    t0, t1 = t[:-1], t[1:]
    keep = t1 - t0 > 1e-9
    t0, t1 = t0[keep], t1[keep]
    if len(t0) == 0:
        t0, t1 = np.array([0.0]), np.array([1.0])
    tm = 0.5 * (t0 + t1)
    um = u0 + tm[:, None] * dv
    cell = [np.floor(um[:, ax]).astype(int) for ax in range(d)]
    # A piece lying in a grid plane touches the cells on both sides of it.
    on_plane = [abs(dv[ax]) < 1e-15 and abs(u0[ax] - round(u0[ax])) < 1e-9 for ax in range(d)]
    for ax in range(d):
        if on_plane[ax]:
            cell[ax][:] = round(u0[ax])
    shape = cm.cell_ok.shape

    def usable(idx):
        inside = np.ones(len(idx[0]), bool)
        for ax in range(d):
            inside &= (idx[ax] >= 0) & (idx[ax] < shape[ax])
        out = np.zeros(len(idx[0]), bool)
        out[inside] = cm.cell_ok[tuple(i[inside] for i in idx)]
        return out

    good = np.zeros(len(t0), bool)
    for off in itertools.product(*[(0, 1) if on_plane[ax] else (0,) for ax in range(d)]):
        good |= usable([cell[ax] - off[ax] for ax in range(d)])
    if not bool(good.all()):
        return False, math.inf
    # Evaluate in a cell that exists (in a grid plane the interpolant is the same on both sides).
    cell = [np.clip(cell[ax], 0, shape[ax] - 1) for ax in range(d)]
    f = cm.integrand
    length = float(np.linalg.norm(q - p))
    total = 0.0
    for tt, w in ((t0, 1.0), (tm, 4.0), (t1, 1.0)):
        uu = u0 + tt[:, None] * dv
        total = total + w * _multilinear(f, tuple(cell), tuple(uu[:, ax] - cell[ax] for ax in range(d)))
    return True, float(np.sum(total * (t1 - t0)) / 6.0 * length)


def _edge_arrays(cm, m: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Validity and cost (node shape) of the move ``m`` from every node (vectorised with shifted
    slices: for one move and one parameter t, every node has the same local coordinates)."""
    f = cm.integrand
    d = f.ndim
    N = f.shape
    valid = np.zeros(N, bool)
    cost = np.zeros(N)
    lo = [max(0, -x) for x in m]
    hi = [min(n, n - x) for n, x in zip(N, m)]
    if any(a >= b for a, b in zip(lo, hi)):
        return valid, cost
    # Padded copies so that slices one cell beyond the grid exist (never valid, weight-0 values).
    cellP = np.pad(cm.cell_ok, [(1, 2)] * d, constant_values=False)
    fP = np.pad(f, [(1, 1)] * d, mode="edge")

    def sl(arr, off):  # arr[n + off] for the nodes n of the move, in the padded frame
        return arr[tuple(slice(a + o + 1, b + o + 1) for a, b, o in zip(lo, hi, off))]

    v = np.ones(tuple(b - a for a, b in zip(lo, hi)), bool)
    c = np.zeros(v.shape)
    length = math.sqrt(sum(x * x for x in m)) * cm.h
    pieces = _pieces(m)
    # A move lying in grid planes borders the cells on either side of them: it is valid when the
    # cells on one side (the same side for all its pieces) are usable.
    v = np.zeros(v.shape, bool)
    for alt in itertools.product(*[(0, -1) if x == 0 else (0,) for x in m]):
        va = np.ones(v.shape, bool)
        for _, _, off in pieces:
            va &= sl(cellP, tuple(o + a for o, a in zip(off, alt)))
        v |= va
    for t0, t1, off in pieces:
        s = 0.0
        for tt, w in ((t0, 1.0), (0.5 * (t0 + t1), 4.0), (t1, 1.0)):
            loc = [x * tt - o for x, o in zip(m, off)]
            val = 0.0
            for corner in itertools.product((0, 1), repeat=d):
                wc = 1.0
                for cc, a in zip(corner, loc):
                    wc *= a if cc else 1 - a
                if wc != 0.0:
                    val = val + wc * sl(fP, tuple(o + cc for o, cc in zip(off, corner)))
            s = s + w * val
        c += s * (t1 - t0) / 6.0 * length
    region = tuple(slice(a, b) for a, b in zip(lo, hi))
    valid[region] = v
    cost[region] = c
    return valid, cost


class GridGraph:
    """The move graph of a :class:`~errplan.planning.CostMap` (built once, reused per query)."""

    def __init__(self, cm, radius: int = 4):
        t0 = time.perf_counter()
        self.cm = cm
        self.radius = int(radius)
        self.shape = tuple(cm.integrand.shape)
        self.dim = len(self.shape)
        n = int(np.prod(self.shape))
        strides = np.cumprod((self.shape[1:] + (1,))[::-1])[::-1]
        rows, cols, vals = [], [], []
        for m in moves(self.radius, self.dim):
            v, c = _edge_arrays(cm, m)
            src = np.flatnonzero(v).astype(np.int32)
            rows.append(src)
            cols.append(src + np.int32(int(np.dot(m, strides))))
            vals.append(c.ravel()[src])
        rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
        # Zero costs would be dropped: costs are >= length > 0, but keep them positive anyway.
        np.maximum(vals, 1e-300, out=vals)
        A = csr_matrix((vals, (rows, cols)), shape=(n, n))
        self.indptr, self.indices, self.data = A.indptr, A.indices, A.data
        self.n = n
        self.edges = len(self.data)
        self.build_time = time.perf_counter() - t0

    def node_point(self, k: int) -> np.ndarray:
        idx = np.unravel_index(int(k), self.shape)
        return np.array([ax[i] for ax, i in zip(self.cm.axes, idx)])

    def _attach(self, p: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray]:
        """Grid nodes within ``reach`` cells of ``p`` joined to it by valid segments, and costs."""
        cm = self.cm
        base = [math.floor((p[k] - cm.origin[k]) / cm.h) for k in range(self.dim)]
        ranges = [range(max(0, b - reach + 1), min(n, b + reach + 1)) for b, n in zip(base, self.shape)]
        ks, cs = [], []
        for idx in itertools.product(*ranges):
            if not cm.node_ok[idx]:
                continue
            ok, c = segment_cost(cm, p, [ax[i] for ax, i in zip(cm.axes, idx)])
            if ok:
                ks.append(int(np.ravel_multi_index(idx, self.shape)))
                cs.append(c)
        return np.array(ks, int), np.array(cs, float)


def grid_optimum(cm, start, goal, radius: int = 4, graph: GridGraph | None = None,
                 attach: int | None = None) -> ReferenceResult:
    """Optimal cost and path from ``start`` to ``goal`` (m, d-vectors) on the move graph of ``cm``.

    ``start`` and ``goal`` are joined to the grid nodes within ``attach`` cells (default
    ``radius``, at least 2) by valid straight segments, and to each other when the straight line
    is valid. Raises :class:`InfeasibleError` when no path exists.
    """
    t0 = time.perf_counter()
    g = graph if graph is not None and graph.radius == radius and graph.cm is cm else GridGraph(cm, radius)
    s = np.asarray(start, float)
    q = np.asarray(goal, float)
    reach = attach or max(2, radius)
    ks, cs = g._attach(s, reach)
    kg, cg = g._attach(q, reach)
    # The start is one more node (index n) with edges to ks; the goal is reached from kg
    # (costs are symmetric), so only the start's row is added to the graph.
    S = g.n
    A = csr_matrix((np.concatenate([g.data, np.maximum(cs, 1e-300)]),
                    np.concatenate([g.indices, ks.astype(g.indices.dtype)]),
                    np.concatenate([g.indptr, [g.indptr[-1] + len(ks)]])), shape=(g.n + 1, g.n + 1))
    dist, pred = dijkstra(A, directed=True, indices=S, return_predecessors=True)
    best, via = math.inf, None
    if len(kg):
        tot = dist[kg] + cg
        j = int(np.argmin(tot))
        best, via = float(tot[j]), int(kg[j])
    ok, c = segment_cost(cm, s, q)
    if ok and c <= best:
        best, via = c, None
    if not math.isfinite(best):
        raise InfeasibleError(f"grid reference: no valid path from {list(s)} to {list(q)}")
    path = [q]
    k = via
    while k is not None and k != S:
        path.append(g.node_point(k))
        k = int(pred[k])
    path.append(s)
    return ReferenceResult(best, np.array(path[::-1]), radius, angular_bound(radius, g.dim),
                           time.perf_counter() - t0)
