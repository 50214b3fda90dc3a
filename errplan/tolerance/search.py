"""Search helpers shared by the tolerance queries: per-row bisection of a monotone criterion, the
worst case over a box (vertices + pattern search), runs, a root and a minimum in 1-D."""
from __future__ import annotations

import itertools
import math
from typing import Callable

import numpy as np

from .result import Progress

#: Bisection stops when the bracket is below this fraction of its upper end (or 1e-7 m / 1/m^2).
BISECT_RTOL = 2e-4


_UNIT_CORNERS = np.array(list(itertools.product((-1.0, 1.0), repeat=6)))


def box_worst(objective: Callable[[np.ndarray], np.ndarray], half: np.ndarray, *, levels: int = 5,
              sweeps: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Maximum of ``objective`` over the boxes ``[-half, half]`` (one box per row of ``half`` (n, d)).

    ``objective(noise (n, c, d)) -> (n, c)``. Method: every vertex of the box, then a pattern search
    from the worst vertex (steps ``half * 2^-l``, ``l = 0..levels-1``, up to ``sweeps`` accepted
    moves per level, each move the best of the ``2d`` axis steps, clipped to the box). Returns the
    maximum (n,) and its argument (n, d).
    """
    half = np.asarray(half, float)
    n, d = half.shape
    unit = _UNIT_CORNERS if d == 6 else np.array(list(itertools.product((-1.0, 1.0), repeat=d)))
    cand = unit[None, :, :] * half[:, None, :]
    vals = objective(cand)
    i = np.argmax(vals, axis=1)
    best = vals[np.arange(n), i]
    arg = cand[np.arange(n), i]
    return pattern_search(objective, best, arg, half, levels=levels, sweeps=sweeps)


def pattern_search(objective: Callable[[np.ndarray], np.ndarray], best: np.ndarray, arg: np.ndarray,
                   half: np.ndarray, *, steps: np.ndarray | None = None,
                   project: Callable[[np.ndarray], np.ndarray] | None = None,
                   active: np.ndarray | None = None, levels: int = 5, sweeps: int = 3
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Raise ``best`` (n,) at ``arg`` (n, d) by a pattern search: at level ``l`` the steps are
    ``steps * half * 2^-l`` (``steps`` (m, d), by default the ``2d`` axis steps), each candidate is
    put back into the set by ``project`` (by default clipped to ``[-half, half]``), and each row moves
    to its best candidate while that raises its value (up to ``sweeps`` moves per level). Rows not
    ``active`` (by default: a box of zero size) keep their start. ``objective(c (n, m, d)) -> (n, m)``.
    Returns the maximum found (n,) and its argument (n, d)."""
    n, d = arg.shape
    if steps is None:
        steps = np.concatenate([np.eye(d), -np.eye(d)])
    if project is None:
        def project(c):
            return np.clip(c, -half[:, None, :], half[:, None, :])
    if active is None:
        active = half.max(axis=1) > 0
    for level in range(levels):
        h = half * 2.0 ** (-level)
        for _ in range(sweeps):
            c = project(arg[:, None, :] + steps[None] * h[:, None, :])
            v = objective(c)
            j = np.argmax(v, axis=1)
            vj = v[np.arange(n), j]
            upd = active & (vj > best)
            if not upd.any():
                break
            best = np.where(upd, vj, best)
            arg = np.where(upd[:, None], c[np.arange(n), j], arg)
    return best, arg


def _bisect_vec(fails: Callable[[np.ndarray], np.ndarray], n: int, start: float, cap: float,
                zero_fails: np.ndarray | None = None, abs_tol: float = 1e-7,
                progress: Progress | None = None, label: str = "") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-row largest ``e`` with ``fails(e) == False`` for a monotone criterion.

    ``fails(e (n,)) -> bool (n,)``. Brackets by doubling from ``start`` up to ``cap`` and bisects until
    the bracket is below ``BISECT_RTOL`` of its top (or ``abs_tol``). Rows failing at 0
    (``zero_fails``) get 0. Returns ``(lo, hi, capped)``: ``lo`` passes, ``hi`` fails (``cap`` when
    nothing failed, flagged in ``capped``).
    """
    lo = np.zeros(n)
    hi = np.full(n, start)
    zero = np.zeros(n, bool) if zero_fails is None else zero_fails.copy()
    hi[zero] = 0.0
    searching = ~zero
    capped = np.zeros(n, bool)
    while searching.any():
        f = np.ones(n, bool)
        f[searching] = fails(hi)[searching]
        passed = searching & ~f
        lo[passed] = hi[passed]
        at_cap = passed & (hi >= cap)
        capped |= at_cap
        grow = passed & ~at_cap
        hi[grow] = np.minimum(2.0 * hi[grow], cap)
        searching = grow
    hi[capped] = cap
    todo = ~zero & ~capped
    it = 0
    while True:
        width = hi - lo
        todo &= width > np.maximum(BISECT_RTOL * hi, abs_tol)
        if not todo.any() or it > 60:
            break
        mid = np.where(todo, 0.5 * (lo + hi), lo)
        f = fails(mid)
        lo = np.where(todo & ~f, mid, lo)
        hi = np.where(todo & f, mid, hi)
        it += 1
        if progress:
            progress(min(1.0, it / 14.0), label)
    return lo, hi, capped


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Index ranges [i, j] of the True runs of a boolean vector."""
    out, i = [], None
    for k, m in enumerate(mask):
        if m and i is None:
            i = k
        if not m and i is not None:
            out.append((i, k - 1))
            i = None
    if i is not None:
        out.append((i, len(mask) - 1))
    return out


def _crossing(f: Callable[[float], float], a: float, b: float, iters: int = 50) -> float:
    """A root of ``f(r) - 1`` between ``a`` (f < 1) and ``b`` (f >= 1) by bisection (f may be inf)."""
    for _ in range(iters):
        m = 0.5 * (a + b)
        if f(m) < 1.0:
            a = m
        else:
            b = m
        if abs(b - a) < 1e-7:
            break
    return 0.5 * (a + b)


def _golden_min(f: Callable[[float], float], a: float, b: float, iters: int = 40) -> float:
    gr = (math.sqrt(5) - 1) / 2
    c, d = b - gr * (b - a), a + gr * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(iters):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - gr * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + gr * (b - a)
            fd = f(d)
    return 0.5 * (a + b)
