"""Largest singular values and ``||I - k M||_2`` of 2x2 and 3x3 matrices in closed form, and the right
singular vector of the largest one."""
from __future__ import annotations

import math

from .basics import NAN, _jit, _maxabs3x3, _maxabs9
from .eigen import _sym3_eigh, _sym3_max


# ============================================================================ singular values
@_jit
def _smax2(a, b, c, d):
    """Largest singular value of [[a, b], [c, d]]: |mu| + |nu| (conformal parts)."""
    return math.hypot(0.5 * (a + d), 0.5 * (c - b)) + math.hypot(0.5 * (a - d), 0.5 * (b + c))


@_jit
def sigma_max2(A):
    """Largest singular value of a 2x2 matrix.

    Closed form ``sqrt((f + sqrt(f^2 - 4 det^2)) / 2)``, ``f = ||A||_F^2``, evaluated as
    ``|mu| + |nu|`` (the same number: ``|mu|^2 + |nu|^2 = f / 2``, ``|mu|^2 - |nu|^2 = det``)
    because ``f^2 - 4 det^2`` cancels catastrophically when the singular values are close.
    """
    return _smax2(A[0, 0], A[0, 1], A[1, 0], A[1, 1])


@_jit
def _gram(g00, g01, g02, g10, g11, g12, g20, g21, g22):
    """The six distinct entries ``(a00, a01, a02, a11, a12, a22)`` of ``G^T G``."""
    return (g00 * g00 + g10 * g10 + g20 * g20, g00 * g01 + g10 * g11 + g20 * g21, g00 * g02 + g10 * g12 + g20 * g22,
            g01 * g01 + g11 * g11 + g21 * g21, g01 * g02 + g11 * g12 + g21 * g22, g02 * g02 + g12 * g12 + g22 * g22)


@_jit
def _smax3(g00, g01, g02, g10, g11, g12, g20, g21, g22):
    s = _maxabs9(g00, g01, g02, g10, g11, g12, g20, g21, g22)
    if not s > 0.0:
        return 0.0 if s == 0.0 else NAN
    r = 1.0 / s
    g00 *= r
    g01 *= r
    g02 *= r
    g10 *= r
    g11 *= r
    g12 *= r
    g20 *= r
    g21 *= r
    g22 *= r
    a00, a01, a02, a11, a12, a22 = _gram(g00, g01, g02, g10, g11, g12, g20, g21, g22)
    lam = _sym3_max(a00, a01, a02, a11, a12, a22)
    return s * math.sqrt(max(lam, 0.0))


@_jit
def sigma_max3(A):
    """Largest singular value of a 3x3 matrix: ``sqrt(lambda_max(A^T A))`` in closed form
    (trigonometric eigenvalues of the characteristic cubic of ``A^T A``, deflation when the top
    two are close). Relative error ~1e-15; NaN for a non-finite input."""
    return _smax3(A[0, 0], A[0, 1], A[0, 2], A[1, 0], A[1, 1], A[1, 2], A[2, 0], A[2, 1], A[2, 2])


@_jit
def g_norm2(M, k):
    """``||I - k M||_2`` of a 2x2 ``M`` (``|1 - k mu| + k |nu|`` for ``k >= 0``)."""
    return _smax2(1.0 - k * M[0, 0], -k * M[0, 1], -k * M[1, 0], 1.0 - k * M[1, 1])


@_jit
def g_norm3(M, k):
    """``||I - k M||_2`` of a 3x3 ``M``, formed in registers."""
    return _smax3(1.0 - k * M[0, 0], -k * M[0, 1], -k * M[0, 2],
                  -k * M[1, 0], 1.0 - k * M[1, 1], -k * M[1, 2],
                  -k * M[2, 0], -k * M[2, 1], 1.0 - k * M[2, 2])


@_jit
def v_sigma3(G, out3):
    """Right singular vector (unit, up to sign) of ``G`` for its largest singular value, written
    into ``out3``; returns that singular value. NaN vector and value for a non-finite ``G``."""
    s = _maxabs3x3(G)
    if math.isnan(s):
        out3[0] = out3[1] = out3[2] = NAN
        return NAN
    if s == 0.0:
        out3[0], out3[1], out3[2] = 1.0, 0.0, 0.0
        return 0.0
    r = 1.0 / s
    g00, g01, g02 = G[0, 0] * r, G[0, 1] * r, G[0, 2] * r
    g10, g11, g12 = G[1, 0] * r, G[1, 1] * r, G[1, 2] * r
    g20, g21, g22 = G[2, 0] * r, G[2, 1] * r, G[2, 2] * r
    a00, a01, a02, a11, a12, a22 = _gram(g00, g01, g02, g10, g11, g12, g20, g21, g22)
    e = _sym3_eigh(a00, a01, a02, a11, a12, a22)
    out3[0], out3[1], out3[2] = e[9], e[10], e[11]
    return s * math.sqrt(max(e[2], 0.0))
