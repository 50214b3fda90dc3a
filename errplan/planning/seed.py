"""A coarse global search on the usable cells: the homotopy class a sampling planner can miss.

In space, within a query's budget, OMPL's sampling planners (with errplan's Python objective) draw
a few hundred to a few thousand samples; they miss narrow passages of the usable region, such as a
channel one or two cells wide between a hole and the workspace's edge, and then settle on the far
side of a hole at a few per cent above the optimum, which no local refinement can repair
(benchmarks/planning.py, docs/planning.md). :func:`seed_path` therefore adds one candidate: the
cheapest path through the centres of usable cells, moving to any of the ``3**d - 1`` neighbours
whose straight connection is valid, with the exact segment costs of the cell walk. A diagonal move
between two usable cells that touch only at an edge or a corner passes exactly through it, which
the closed-cell validity allows (the edge's nodes are usable) and which a sampler never hits: the
coarse path finds these passages too. Its cost also bounds the box the OMPL search samples in
(:func:`errplan.planning.plan.search_box`).

The graph (:class:`CellGraph`) is built once per cost map: about 0.1 s for 20 000 usable cells.
"""
from __future__ import annotations

import itertools
import math
import time

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from . import cellwalk


class CellGraph:
    """Usable cells (nodes, at their centres) and their neighbour moves with exact costs."""

    def __init__(self, cm):
        t0 = time.perf_counter()
        ok = cm.cell_ok
        d = ok.ndim
        self.cm = cm
        self.index = np.full(ok.shape, -1, np.int64)
        cells = np.argwhere(ok)
        self.index[ok] = np.arange(len(cells))
        self.centers = np.ascontiguousarray(cm.origin + (cells + 0.5) * cm.h)
        rows, cols = [], []
        for m in itertools.product((-1, 0, 1), repeat=d):
            if not any(m) or next(x for x in m if x) < 0:  # one of each pair +-m
                continue
            lo = [max(0, -x) for x in m]
            hi = [n - max(0, x) for n, x in zip(ok.shape, m)]
            both = ok[tuple(slice(a, b) for a, b in zip(lo, hi))] & ok[tuple(slice(a + x, b + x)
                                                                           for a, b, x in zip(lo, hi, m))]
            rows.append(self.index[tuple(slice(a, b) for a, b in zip(lo, hi))][both])
            cols.append(self.index[tuple(slice(a + x, b + x) for a, b, x in zip(lo, hi, m))][both])
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        cost = cellwalk.walk_many(cm._D, self.centers[rows], self.centers[cols], True)
        keep = np.isfinite(cost)
        an = getattr(cm, "anatomy", None)
        if an is not None:
            # A move between two cell centres is clear when both centres keep the clearance plus half its
            # length (clearance is 1-Lipschitz in the tip): conservative, one query per cell, not per move.
            cc = an.tip(self.centers)
            half = 0.5 * np.linalg.norm(self.centers[rows] - self.centers[cols], axis=1)
            keep &= np.minimum(cc[rows], cc[cols]) >= an.required + half
        n = len(cells)
        self.graph = csr_matrix((np.maximum(cost[keep], 1e-300), (rows[keep], cols[keep])), shape=(n, n))
        self.build_time = time.perf_counter() - t0


def cell_graph(cm) -> CellGraph:
    """The :class:`CellGraph` of ``cm`` (built on first use, then cached on it)."""
    g = getattr(cm, "_cell_graph", None)
    if g is None:
        g = cm._cell_graph = CellGraph(cm)
    return g


def seed_path(cm, start, goal, limit: float = math.inf) -> tuple[np.ndarray, float] | None:
    """The cheapest path ``start -> centre of its cell -> ... -> centre of the goal's cell -> goal``
    on the :class:`CellGraph` of ``cm``, and its exact cost; None when there is none cheaper than
    ``limit`` (m)."""
    g = cell_graph(cm)
    cs, cg = cm._cell_index(start), cm._cell_index(goal)
    if cs is None or cg is None:
        return None
    i, j = int(g.index[cs]), int(g.index[cg])
    s = np.asarray(start, float)
    q = np.asarray(goal, float)
    c_s = cm.motion(s, g.centers[i], check=False)[1]
    c_g = cm.motion(g.centers[j], q, check=False)[1]
    dist, pred = dijkstra(g.graph, directed=False, indices=i, return_predecessors=True,
                          limit=max(limit - c_s - c_g, 0.0) if math.isfinite(limit) else np.inf)
    if not np.isfinite(dist[j]):
        return None
    nodes = [j]
    while nodes[-1] != i:
        nodes.append(int(pred[nodes[-1]]))
    path = np.concatenate([s[None], g.centers[nodes[::-1]], q[None]])
    ok, cost = cm.path_cost(path)
    if not ok or cost >= limit:
        return None
    return path, cost
