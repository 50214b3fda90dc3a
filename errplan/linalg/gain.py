"""The best achievable contraction ``rho* = min over k > 0 of max_i ||I - k M_i||`` and its gain."""
from __future__ import annotations

import math

from .basics import _jit, _maxabs3x3
from .eigen import _sym3_eigvals
from .singular import g_norm3


# ============================================================================ best gain
@_jit
def _max_gnorm3(Ms, m, k):
    worst = -1.0
    for i in range(m):
        g = g_norm3(Ms[i], k)
        if g > worst:
            worst = g
    return worst


@_jit
def min_over_gain3(Ms, m, out, iters=60):
    """``rho* = min over k > 0 of max_i ||I - k Ms[i]||_2`` over ``Ms[:m]`` (3x3 each), by golden
    section on the convex ``f(k)`` (``iters`` steps, as the planar ``minimize_gain`` of the
    fields). Writes ``out[0] = rho*``, ``out[1] = k*`` and returns ``rho*``.

    Conventions of the planar search: where no gain contracts (``rho* >= 1``) the result is
    ``rho* = 1`` at ``k* = 0``; this is known up front when some ``M`` turns a motion by more than
    90 deg (``||I - k M|| >= |1 - k v^T M v| > 1`` for every ``k > 0``), and when some ``M`` has a
    non-finite entry: it counts as ``M = 0`` (no motion, ``||I - k 0|| = 1``), as the planar search
    replaces non-finite parts by 0. ``m = 0`` gives ``rho* = 1``, ``k* = 0``.

    The bracket is ``[0, 2 / max_i lambda_max(S_i)]``: beyond it ``||I - k M_i|| >=
    |1 - k v^T M_i v| >= 1`` for the ``v`` maximising ``v^T M_i v``.
    """
    smax = 0.0
    smin = math.inf
    for i in range(m):
        M = Ms[i]
        if math.isnan(_maxabs3x3(M)):
            smin = -1.0  # a non-finite matrix counts as M = 0: f(k) >= 1 for every k
            break
        l0, _l1, l2 = _sym3_eigvals(M[0, 0], 0.5 * (M[0, 1] + M[1, 0]), 0.5 * (M[0, 2] + M[2, 0]),
                                    M[1, 1], 0.5 * (M[1, 2] + M[2, 1]), M[2, 2])
        smax = max(smax, l2)
        smin = min(smin, l0)
    if not (smax > 0.0) or smin < 0.0:
        out[0] = 1.0
        out[1] = 0.0
        return 1.0
    gr = (math.sqrt(5.0) - 1.0) / 2.0
    a = 0.0
    b = 2.0 / smax
    c = b - gr * (b - a)
    d = a + gr * (b - a)
    fc = _max_gnorm3(Ms, m, c)
    fd = _max_gnorm3(Ms, m, d)
    for _ in range(iters):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - gr * (b - a)
            fc = _max_gnorm3(Ms, m, c)
        else:
            a, c, fc = c, d, fd
            d = a + gr * (b - a)
            fd = _max_gnorm3(Ms, m, d)
    k = 0.5 * (a + b)
    rho = _max_gnorm3(Ms, m, k)
    if not rho < 1.0:
        out[0] = 1.0
        out[1] = 0.0
        return 1.0
    out[0] = rho
    out[1] = k
    return rho
