"""Symmetric 3x3 eigenproblems: the trigonometric closed form, then deflation (the best-separated
eigenvector by cross products, the other two from the stable 2x2 restriction to its complement)."""
from __future__ import annotations

import math

from .basics import _jit


# ============================================================================ symmetric 3x3 eigen
SQRT3 = math.sqrt(3.0)


@_jit
def _sym3_trig(h00, h01, h02, h11, h12, h22):
    """Trigonometric eigenvalues ``l0 <= l1 <= l2`` of a symmetric 3x3 matrix and
    ``r = det((H - qI)/p) / 2 = cos(3 phi)``: the top eigenvalue is the isolated one (the
    closer pair is the bottom one) when ``r >= 0``."""
    q = (h00 + h11 + h22) / 3.0
    b00 = h00 - q
    b11 = h11 - q
    b22 = h22 - q
    p2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (h01 * h01 + h02 * h02 + h12 * h12)) / 6.0
    if not p2 > 0.0:
        return q, q, q, 1.0
    p = math.sqrt(p2)
    detb = (b00 * (b11 * b22 - h12 * h12) - h01 * (h01 * b22 - h12 * h02)
            + h02 * (h01 * h12 - b11 * h02))
    r = detb / (2.0 * p2 * p)
    if r > 1.0:
        r = 1.0
    elif r < -1.0:
        r = -1.0
    cp = math.cos(math.acos(r) / 3.0)          # phi in [0, pi/3]
    sp = math.sqrt(max(0.0, 1.0 - cp * cp))
    l2 = q + 2.0 * p * cp
    l0 = q - p * (cp + SQRT3 * sp)             # 2 cos(phi + 2pi/3)
    l1 = q - p * (cp - SQRT3 * sp)             # 2 cos(phi - 2pi/3)
    return l0, l1, l2, r


@_jit
def _sym3_eigvals(h00, h01, h02, h11, h12, h22):
    """Eigenvalues ``l0 <= l1 <= l2`` of a symmetric 3x3 matrix, trigonometric closed form
    (accurate to ~1e-8 of the spread at a near-double eigenvalue; see ``_sym3_eigh``)."""
    l0, l1, l2, _r = _sym3_trig(h00, h01, h02, h11, h12, h22)
    return l0, l1, l2


@_jit
def _cross_null(r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """Unit vector orthogonal to the rows (a null vector of a rank-2 matrix): the largest of the
    three row cross products. ``(0, 0, 0)`` if all rows are zero-ish (rank < 2)."""
    x0 = r01 * r12 - r02 * r11
    x1 = r02 * r10 - r00 * r12
    x2 = r00 * r11 - r01 * r10
    n0 = x0 * x0 + x1 * x1 + x2 * x2
    y0 = r01 * r22 - r02 * r21
    y1 = r02 * r20 - r00 * r22
    y2 = r00 * r21 - r01 * r20
    n1 = y0 * y0 + y1 * y1 + y2 * y2
    z0 = r11 * r22 - r12 * r21
    z1 = r12 * r20 - r10 * r22
    z2 = r10 * r21 - r11 * r20
    n2 = z0 * z0 + z1 * z1 + z2 * z2
    if n0 >= n1 and n0 >= n2:
        n = n0
    elif n1 >= n2:
        x0, x1, x2, n = y0, y1, y2, n1
    else:
        x0, x1, x2, n = z0, z1, z2, n2
    if not n > 0.0:
        return 0.0, 0.0, 0.0
    n = 1.0 / math.sqrt(n)
    return x0 * n, x1 * n, x2 * n


@_jit
def _complement(e0, e1, e2):
    """Orthonormal ``u, v`` spanning the plane orthogonal to the unit vector ``e`` (u x v = e)."""
    a0, a1, a2 = abs(e0), abs(e1), abs(e2)
    if a0 <= a1 and a0 <= a2:      # u = e x (1, 0, 0)
        u0, u1, u2 = 0.0, e2, -e1
    elif a1 <= a2:                 # u = e x (0, 1, 0)
        u0, u1, u2 = -e2, 0.0, e0
    else:                          # u = e x (0, 0, 1)
        u0, u1, u2 = e1, -e0, 0.0
    n = 1.0 / math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    u0 *= n
    u1 *= n
    u2 *= n
    v0 = e1 * u2 - e2 * u1
    v1 = e2 * u0 - e0 * u2
    v2 = e0 * u1 - e1 * u0
    return u0, u1, u2, v0, v1, v2


@_jit
def _qform(h00, h01, h02, h11, h12, h22, x0, x1, x2, y0, y1, y2):
    """``x^T H y`` for symmetric ``H``."""
    return (x0 * (h00 * y0 + h01 * y1 + h02 * y2) + x1 * (h01 * y0 + h11 * y1 + h12 * y2)
            + x2 * (h02 * y0 + h12 * y1 + h22 * y2))


@_jit
def _eig2(a, b, c):
    """Eigen-decomposition of the symmetric ``[[a, b], [b, c]]``: ``(m, r, cs, sn)`` with the
    eigenvalues ``m -+ r`` and ``(cs, sn)`` the unit eigenvector of ``m + r`` (stable closed form:
    ``(r + d, b) ~ (b, r - d)``, ``d = (a - c) / 2``, whichever is better conditioned)."""
    m = 0.5 * (a + c)
    d = 0.5 * (a - c)
    r = math.sqrt(d * d + b * b)
    if d >= 0.0:
        cs, sn = r + d, b
    else:
        cs, sn = b, r - d
    n = cs * cs + sn * sn
    if n > 0.0:
        n = 1.0 / math.sqrt(n)
        return m, r, cs * n, sn * n
    return m, r, 1.0, 0.0


@_jit
def _sym2_in_plane(h00, h01, h02, h11, h12, h22, u0, u1, u2, v0, v1, v2):
    """Eigen-decomposition of the restriction of ``H`` to the orthonormal pair ``(u, v)``:
    ``(lo, hi, lo-vector (3), hi-vector (3))``, stable closed form (no trigonometry)."""
    w0 = h00 * u0 + h01 * u1 + h02 * u2
    w1 = h01 * u0 + h11 * u1 + h12 * u2
    w2 = h02 * u0 + h12 * u1 + h22 * u2
    huu = u0 * w0 + u1 * w1 + u2 * w2
    huv = v0 * w0 + v1 * w1 + v2 * w2
    hvv = _qform(h00, h01, h02, h11, h12, h22, v0, v1, v2, v0, v1, v2)
    m, rr, c, s = _eig2(huu, huv, hvv)
    return (m - rr, m + rr, c * v0 - s * u0, c * v1 - s * u1, c * v2 - s * u2,
            c * u0 + s * v0, c * u1 + s * v1, c * u2 + s * v2)


@_jit
def _sym3_eigh(h00, h01, h02, h11, h12, h22):
    """Eigen-decomposition of a symmetric 3x3 matrix: ``(l0, l1, l2, x0 (3), x1 (3), x2 (3))``,
    ``l0 <= l1 <= l2`` and orthonormal eigenvectors.

    Trigonometric eigenvalues, then the eigenvector of the isolated end eigenvalue (the top one if
    ``r >= 0``, else the bottom one; its gap is at least half the spread) from cross products, its
    Rayleigh quotient, and the other two from the 2x2 restriction to the orthogonal complement.
    Eigenvalue errors are a few ulps of ``||H||`` also for (near-)double eigenvalues, where the
    bare trigonometric formula loses half the digits.
    """
    l0, l1, l2, r = _sym3_trig(h00, h01, h02, h11, h12, h22)
    if not l2 - l0 > 0.0:
        return l0, l1, l2, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
    top = r >= 0.0
    lam = l2 if top else l0
    e0, e1, e2 = _cross_null(h00 - lam, h01, h02, h01, h11 - lam, h12, h02, h12, h22 - lam)
    if e0 == 0.0 and e1 == 0.0 and e2 == 0.0:
        return l0, l1, l2, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
    le = _qform(h00, h01, h02, h11, h12, h22, e0, e1, e2, e0, e1, e2)
    u0, u1, u2, v0, v1, v2 = _complement(e0, e1, e2)
    a, b, lo0, lo1, lo2, hi0, hi1, hi2 = _sym2_in_plane(h00, h01, h02, h11, h12, h22,
                                                        u0, u1, u2, v0, v1, v2)
    if top:
        if b > le:  # rounding only (near-triple eigenvalue): keep the order
            b, le = le, b
            hi0, hi1, hi2, e0, e1, e2 = e0, e1, e2, hi0, hi1, hi2
        return a, b, le, lo0, lo1, lo2, hi0, hi1, hi2, e0, e1, e2
    if a < le:
        a, le = le, a
        lo0, lo1, lo2, e0, e1, e2 = e0, e1, e2, lo0, lo1, lo2
    return le, a, b, e0, e1, e2, lo0, lo1, lo2, hi0, hi1, hi2


@_jit
def _sym3_top(h00, h01, h02, h11, h12, h22):
    """Largest eigenvalue and a unit eigenvector ``(l2, x0, x1, x2)`` of a symmetric 3x3 matrix:
    cross products when the top eigenvalue is the isolated one (``r >= 0``), ``_sym3_eigh``
    otherwise."""
    l0, _l1, l2, r = _sym3_trig(h00, h01, h02, h11, h12, h22)
    if r >= 0.0 and l2 - l0 > 0.0:
        e0, e1, e2 = _cross_null(h00 - l2, h01, h02, h01, h11 - l2, h12, h02, h12, h22 - l2)
        if not (e0 == 0.0 and e1 == 0.0 and e2 == 0.0):
            return _qform(h00, h01, h02, h11, h12, h22, e0, e1, e2, e0, e1, e2), e0, e1, e2
    e = _sym3_eigh(h00, h01, h02, h11, h12, h22)
    return e[2], e[9], e[10], e[11]


@_jit
def _sym3_max(h00, h01, h02, h11, h12, h22):
    """Largest eigenvalue of a symmetric 3x3 matrix to a few ulps of ``||H||``."""
    l0, _l1, l2, r = _sym3_trig(h00, h01, h02, h11, h12, h22)
    if r > -0.99:
        return l2  # the trigonometric top eigenvalue is accurate unless the top pair is double
    # near-double top pair: deflate the isolated smallest eigenvalue, 2x2 closed form for the rest
    e0, e1, e2 = _cross_null(h00 - l0, h01, h02, h01, h11 - l0, h12, h02, h12, h22 - l0)
    if e0 == 0.0 and e1 == 0.0 and e2 == 0.0:
        return l2
    u0, u1, u2, v0, v1, v2 = _complement(e0, e1, e2)
    return _sym2_in_plane(h00, h01, h02, h11, h12, h22, u0, u1, u2, v0, v1, v2)[1]
