"""The small pieces every kernel uses: the compile decorator, max-abs scaling, 2x2 and 3x3 inverses with
their singularity test, and the 3x3 product."""
from __future__ import annotations

import math

from ..jit import njit


PI = math.pi
NAN = math.nan


def _jit(f):
    return njit(cache=True, fastmath=False, error_model="numpy")(f)


@_jit
def _maxabs9(a0, a1, a2, a3, a4, a5, a6, a7, a8):
    """max |a_i|, NaN if any entry is NaN or infinite."""
    s = 0.0
    bad = False
    for a in (a0, a1, a2, a3, a4, a5, a6, a7, a8):
        a = abs(a)
        if not a < math.inf:
            bad = True
        elif a > s:
            s = a
    return NAN if bad else s


@_jit
def _maxabs3x3(M):
    return _maxabs9(M[0, 0], M[0, 1], M[0, 2], M[1, 0], M[1, 1], M[1, 2], M[2, 0], M[2, 1], M[2, 2])


# ============================================================================ 2x2 and 3x3 basics
@_jit
def inv2(A, out):
    """``out = A^-1`` of a 2x2 matrix (adjugate / det); returns ``det``. NaN entries if det == 0."""
    a, b, c, d = A[0, 0], A[0, 1], A[1, 0], A[1, 1]
    det = a * d - b * c
    if det == 0.0:
        r = NAN
    else:
        r = 1.0 / det
    out[0, 0] = d * r
    out[0, 1] = -b * r
    out[1, 0] = -c * r
    out[1, 1] = a * r
    return det


@_jit
def inv3(A, out):
    """``out = A^-1`` of a 3x3 matrix (cofactors / det); returns ``det``. NaN entries if det == 0."""
    a00, a01, a02 = A[0, 0], A[0, 1], A[0, 2]
    a10, a11, a12 = A[1, 0], A[1, 1], A[1, 2]
    a20, a21, a22 = A[2, 0], A[2, 1], A[2, 2]
    c00 = a11 * a22 - a12 * a21
    c01 = a12 * a20 - a10 * a22
    c02 = a10 * a21 - a11 * a20
    det = a00 * c00 + a01 * c01 + a02 * c02
    if det == 0.0:
        r = NAN
    else:
        r = 1.0 / det
    out[0, 0] = c00 * r
    out[1, 0] = c01 * r
    out[2, 0] = c02 * r
    out[0, 1] = (a02 * a21 - a01 * a22) * r
    out[1, 1] = (a00 * a22 - a02 * a20) * r
    out[2, 1] = (a01 * a20 - a00 * a21) * r
    out[0, 2] = (a01 * a12 - a02 * a11) * r
    out[1, 2] = (a02 * a10 - a00 * a12) * r
    out[2, 2] = (a00 * a11 - a01 * a10) * r
    return det


@_jit
def singular2(A, det, rcond):
    """True when ``|det| <= rcond * ||A||_F^2`` or ``det`` is not finite (``metrics.inv2``'s test)."""
    f = A[0, 0] * A[0, 0] + A[0, 1] * A[0, 1] + A[1, 0] * A[1, 0] + A[1, 1] * A[1, 1]
    return not abs(det) > rcond * f


@_jit
def singular3(A, det, rcond):
    """True when ``|det| <= rcond * ||A||_F^3`` or ``det`` is not finite.

    ``|det| / ||A||_F^3 = s1 s2 s3 / (s1^2 + s2^2 + s3^2)^1.5`` is at most ``3^-1.5`` and of the
    order of ``s3 s2 / s1^2`` (singular values s1 >= s2 >= s3): a scale-free measure of how close
    ``A`` is to singular, the 3-D analogue of the planar test.
    """
    f = 0.0
    for i in range(3):
        for j in range(3):
            f += A[i, j] * A[i, j]
    return not abs(det) > rcond * f * math.sqrt(f)


@_jit
def matmul3(A, B, out):
    """``out = A @ B`` for 3x3 matrices (``out`` must not alias ``A`` or ``B``)."""
    for i in range(3):
        a0, a1, a2 = A[i, 0], A[i, 1], A[i, 2]
        for j in range(3):
            out[i, j] = a0 * B[0, j] + a1 * B[1, j] + a2 * B[2, j]
