"""The compiled cell walk: validity and exact cost of a straight motion through a grid of cells.

A :class:`~errplan.planning.costmap.CostMap` packs what the walk needs into ONE float64 array
(:func:`pack`), so that a call from Python unboxes a single array plus the motion's coordinates
(about 1 us; OMPL calls it once per motion):

- a header of :data:`HEADER` values: grid origin ``o0, o1, o2`` (m; ``o2`` unused in the plane),
  spacing ``h`` (m), cell counts ``n0, n1, n2`` (``n2 = 1`` in the plane), and ``f_max``, the cost
  per metre charged off the grid;
- per cell (C order over the cell indices), the ``2**d`` coefficients of the multilinear integrand
  in the cell's local coordinates ``a, b (, c)`` in ``[0, 1]``, then 1.0 if the cell is usable
  (else 0.0). Planar: ``f = c0 + ca a + cb b + cab a b``; spatial:
  ``f = c0 + ca a + cb b + cc c + cab a b + cac a c + cbc b c + cabc a b c``.

The walk (Amanatides & Woo) visits the cells the segment passes through, in order. Along the
segment each local coordinate is linear in the motion parameter t, so the integrand is a
polynomial of degree <= d in t inside a cell and is integrated exactly (:func:`walk2`,
:func:`walk3`). Rules shared with the pure-Python :meth:`CostMap.pieces` and the independent
:mod:`errplan.planning.reference`:

- the region is the closed union of the usable cells: a piece of the motion that lies in a grid
  plane (its coordinate on that axis is constant and on a grid line, within 1e-9 cell) touches the
  cells on both sides, and either one makes it usable;
- crossings of two or three grid planes closer than 1e-9 (in units of the motion) are one crossing
  through an edge or a corner: the walk steps on every such axis at once rather than through a
  sliver of a neighbouring cell;
- a motion is valid when every piece of positive length lies in a usable cell.

The planar kernel does the same arithmetic in the same order as errplan's former pure-Python
planar walk; only the segment length (libm's ``hypot`` instead of CPython's) can differ, by one
unit in the last place.
"""
from __future__ import annotations

import math

import numpy as np
from ..jit import njit

HEADER = 8


def pack(origin, h: float, cell_shape, coefs: list[np.ndarray], cell_ok: np.ndarray, f_max: float) -> np.ndarray:
    """The walk's array: header, then per cell its ``2**d`` coefficients and its usable flag."""
    d = len(cell_shape)
    head = np.zeros(HEADER)
    head[:d] = origin
    head[3] = h
    head[4:4 + d] = cell_shape
    if d == 2:
        head[6] = 1
    head[7] = f_max
    body = np.stack([np.asarray(c, float).ravel() for c in coefs] + [cell_ok.ravel().astype(float)], axis=1)
    return np.ascontiguousarray(np.concatenate([head, body.ravel()]))


@njit(cache=True, inline="always", error_model="numpy")
def _axis(u, du):
    """Amanatides-Woo set-up on one axis: starting cell (ties on a grid line go in the motion
    direction), step sign, parameter step per cell, parameter of the first cell boundary, and whether
    the segment runs along a grid line of this axis (no motion on it, on the line: the cell index is
    then the line's)."""
    if du > 0:
        i = math.floor(u + 1e-12)
        return i, 1, 1.0 / du, (i + 1 - u) / du, False
    if du < 0:
        i = math.ceil(u - 1e-12) - 1
        return i, -1, -1.0 / du, (i - u) / du, False
    if abs(u - round(u)) < 1e-9:
        return int(round(u)), 0, math.inf, math.inf, True
    return math.floor(u), 0, math.inf, math.inf, False


@njit(cache=True, inline="always", error_model="numpy")
def _near(u):
    """``(first, count)``: the cells along one axis whose closed interval holds coordinate ``u``
    (two when ``u`` is on a grid line: ``r`` and ``r - 1``)."""
    r = round(u)
    if abs(u - r) < 1e-9:
        return r, 2
    return math.floor(u), 1


@njit(cache=True, error_model="numpy")
def point_ok2(D, y, z):
    """True if ``[y, z]`` lies in a usable cell (closed cells)."""
    h = D[3]
    n0, n1 = int(D[4]), int(D[5])
    i0, ci = _near((y - D[0]) / h)
    j0, cj = _near((z - D[1]) / h)
    for a in range(ci):
        i = i0 - a
        if 0 <= i < n0:
            for b in range(cj):
                j = j0 - b
                if 0 <= j < n1 and D[HEADER + (i * n1 + j) * 5 + 4] != 0.0:
                    return True
    return False


@njit(cache=True, error_model="numpy")
def point_ok3(D, x, y, z):
    """True if ``[x, y, z]`` lies in a usable cell (closed cells)."""
    h = D[3]
    n0, n1, n2 = int(D[4]), int(D[5]), int(D[6])
    i0, ci = _near((x - D[0]) / h)
    j0, cj = _near((y - D[1]) / h)
    k0, ck = _near((z - D[2]) / h)
    for a in range(ci):
        i = i0 - a
        if 0 <= i < n0:
            for b in range(cj):
                j = j0 - b
                if 0 <= j < n1:
                    for c in range(ck):
                        k = k0 - c
                        if 0 <= k < n2 and D[HEADER + ((i * n1 + j) * n2 + k) * 9 + 8] != 0.0:
                            return True
    return False


@njit(cache=True, error_model="numpy")
def walk2(D, ya, za, yb, zb, check, cost):
    """``(ok, cost)`` of the planar motion ``[ya, za] -> [yb, zb]`` (see the module docstring).

    ``check``: stop at the first unusable piece (cost ``inf``). ``cost``: integrate (else 0).
    """
    h = D[3]
    y0, z0 = D[0], D[1]
    nyc, nzc = int(D[4]), int(D[5])
    f_max = D[7]
    u = (ya - y0) / h
    v = (za - z0) / h
    du = (yb - ya) / h
    dv = (zb - za) / h
    length = math.hypot(yb - ya, zb - za)
    i, su, tdu, tu, on_u = _axis(u, du)
    j, sv, tdv, tv, on_v = _axis(v, dv)
    t0 = 0.0
    total = 0.0
    ok = True
    while True:
        t1 = tu if tu < tv else tv
        if t1 > 1.0 - 1e-9:
            t1 = 1.0
        if t1 > t0:
            ci, cj = i, j
            if 0 <= ci < nyc and 0 <= cj < nzc and D[HEADER + (ci * nzc + cj) * 5 + 4] != 0.0:
                good = True
            else:
                good = False
                if on_u and 0 <= i - 1 < nyc and 0 <= cj < nzc and D[HEADER + ((i - 1) * nzc + cj) * 5 + 4] != 0.0:
                    ci, good = i - 1, True
                elif on_v and 0 <= ci < nyc and 0 <= j - 1 < nzc and D[HEADER + (ci * nzc + j - 1) * 5 + 4] != 0.0:
                    cj, good = j - 1, True
                elif (on_u and on_v and 0 <= i - 1 < nyc and 0 <= j - 1 < nzc
                      and D[HEADER + ((i - 1) * nzc + j - 1) * 5 + 4] != 0.0):
                    ci, cj, good = i - 1, j - 1, True
            if not good:
                ok = False
                if check:
                    return False, math.inf
            if cost:
                if 0 <= ci < nyc and 0 <= cj < nzc:
                    k = HEADER + (ci * nzc + cj) * 5
                    a0 = u - ci
                    b0 = v - cj
                    c0, ca, cb, cab = D[k], D[k + 1], D[k + 2], D[k + 3]
                    A = c0 + ca * a0 + cb * b0 + cab * a0 * b0
                    B = ca * du + cb * dv + cab * (a0 * dv + b0 * du)
                    C = cab * du * dv
                    total += (A * (t1 - t0) + 0.5 * B * (t1 * t1 - t0 * t0)
                              + C * (t1 * t1 * t1 - t0 * t0 * t0) / 3.0)
                else:
                    total += f_max * (t1 - t0)
            t0 = t1
        if t1 >= 1.0:
            break
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


@njit(cache=True, error_model="numpy")
def walk3(D, xa, ya, za, xb, yb, zb, check, cost):
    """``(ok, cost)`` of the spatial motion ``[xa, ya, za] -> [xb, yb, zb]`` (module docstring).

    Inside a cell the trilinear integrand is a cubic of the motion parameter, integrated exactly.
    """
    h = D[3]
    n0, n1, n2 = int(D[4]), int(D[5]), int(D[6])
    f_max = D[7]
    u = (xa - D[0]) / h
    v = (ya - D[1]) / h
    w = (za - D[2]) / h
    du = (xb - xa) / h
    dv = (yb - ya) / h
    dw = (zb - za) / h
    length = math.sqrt((xb - xa) ** 2 + (yb - ya) ** 2 + (zb - za) ** 2)
    i, si, tdi, ti, on_i = _axis(u, du)
    j, sj, tdj, tj, on_j = _axis(v, dv)
    k, sk, tdk, tk, on_k = _axis(w, dw)
    t0 = 0.0
    total = 0.0
    ok = True
    while True:
        t1 = ti
        if tj < t1:
            t1 = tj
        if tk < t1:
            t1 = tk
        tm = t1
        if t1 > 1.0 - 1e-9:
            t1 = 1.0
        if t1 > t0:
            # The cell of this piece, or (on grid planes) any usable cell on the other side.
            ci, cj, ck = i, j, k
            good = False
            for m in range(8):
                oi = m & 1
                oj = (m >> 1) & 1
                ok_ = (m >> 2) & 1
                if (oi and not on_i) or (oj and not on_j) or (ok_ and not on_k):
                    continue
                a, b, c = i - oi, j - oj, k - ok_
                if 0 <= a < n0 and 0 <= b < n1 and 0 <= c < n2 and D[HEADER + ((a * n1 + b) * n2 + c) * 9 + 8] != 0.0:
                    ci, cj, ck = a, b, c
                    good = True
                    break
            if not good:
                ok = False
                if check:
                    return False, math.inf
            if cost:
                if 0 <= ci < n0 and 0 <= cj < n1 and 0 <= ck < n2:
                    q = HEADER + ((ci * n1 + cj) * n2 + ck) * 9
                    a0 = u - ci
                    b0 = v - cj
                    g0 = w - ck
                    c0, ca, cb, cc = D[q], D[q + 1], D[q + 2], D[q + 3]
                    cab, cac, cbc, cabc = D[q + 4], D[q + 5], D[q + 6], D[q + 7]
                    # f(t) = A + B t + C t^2 + E t^3 along the motion inside this cell
                    A = (c0 + ca * a0 + cb * b0 + cc * g0 + cab * a0 * b0 + cac * a0 * g0 + cbc * b0 * g0
                         + cabc * a0 * b0 * g0)
                    B = (ca * du + cb * dv + cc * dw + cab * (a0 * dv + b0 * du) + cac * (a0 * dw + g0 * du)
                         + cbc * (b0 * dw + g0 * dv) + cabc * (a0 * b0 * dw + a0 * g0 * dv + b0 * g0 * du))
                    C = (cab * du * dv + cac * du * dw + cbc * dv * dw
                         + cabc * (a0 * dv * dw + b0 * du * dw + g0 * du * dv))
                    E = cabc * du * dv * dw
                    t02, t12 = t0 * t0, t1 * t1
                    total += (A * (t1 - t0) + 0.5 * B * (t12 - t02) + C * (t12 * t1 - t02 * t0) / 3.0
                              + 0.25 * E * (t12 * t12 - t02 * t02))
                else:
                    total += f_max * (t1 - t0)
            t0 = t1
        if t1 >= 1.0:
            break
        # Step every axis whose crossing is (within 1e-9) the next one: through an edge or a corner.
        if ti - tm < 1e-9:
            i += si
            ti += tdi
        if tj - tm < 1e-9:
            j += sj
            tj += tdj
        if tk - tm < 1e-9:
            k += sk
            tk += tdk
    return ok, total * length


@njit(cache=True, error_model="numpy")
def path_cost2(D, pts):
    """``(valid, cost)`` of a planar polyline (n, 2): every segment walked without early stop."""
    ok = True
    total = 0.0
    for m in range(pts.shape[0] - 1):
        o, c = walk2(D, pts[m, 0], pts[m, 1], pts[m + 1, 0], pts[m + 1, 1], False, True)
        ok = ok and o
        total += c
    return ok, total


@njit(cache=True, error_model="numpy")
def path_cost3(D, pts):
    """``(valid, cost)`` of a spatial polyline (n, 3)."""
    ok = True
    total = 0.0
    for m in range(pts.shape[0] - 1):
        o, c = walk3(D, pts[m, 0], pts[m, 1], pts[m, 2], pts[m + 1, 0], pts[m + 1, 1], pts[m + 1, 2], False, True)
        ok = ok and o
        total += c
    return ok, total


def walk_many(D, A, B, check):
    """Costs of the motions ``A[i] -> B[i]`` (arrays (n, d)); with ``check``, ``inf`` for the
    invalid ones. The dimension is picked here: a command compiles the walk of its own dimension."""
    return (_walk_many2 if A.shape[1] == 2 else _walk_many3)(D, A, B, check)


@njit(cache=True, error_model="numpy")
def _walk_many2(D, A, B, check):
    out = np.empty(A.shape[0])
    for m in range(A.shape[0]):
        out[m] = walk2(D, A[m, 0], A[m, 1], B[m, 0], B[m, 1], check, True)[1]
    return out


@njit(cache=True, error_model="numpy")
def _walk_many3(D, A, B, check):
    out = np.empty(A.shape[0])
    for m in range(A.shape[0]):
        out[m] = walk3(D, A[m, 0], A[m, 1], A[m, 2], B[m, 0], B[m, 1], B[m, 2], check, True)[1]
    return out
