"""The compiled planar kinematics: P1's arm (:class:`errplan.kinematics.arm.Arm`) and P2's flexed shaft
(:mod:`errplan.kinematics.shaft`) as numba loops over a batch.

Each kernel performs the operations of the numpy function it replaces in the same order (IEEE arithmetic,
no fast-math; sin, cos, atan, atan2 and acos are the C library's, as numpy's on this platform), so the
values are the same to the last bit; the numpy functions stay as the references the tests compare against.
Imported on first use by :mod:`.arm` and :mod:`.shaft`, so that importing them does not load numba; the
planar fields kernels take their arc test (:func:`_arc_class`) from here.
"""
from __future__ import annotations

import math

import numpy as np

from numba import types as _types
from numba.core.extending import intrinsic

from ..jit import kernel_array, njit  # noqa: F401  (kernel_array: for .arm and .shaft)
from .newton import NEWTON_ITERS as _NEWTON_ITERS


# ----------------------------------------------------------------------------- the arm
@njit(cache=True, error_model="numpy")
def _arc_class(x, y, n, cm, sm, chw):
    """Where the angle of the vector ``(x, y)`` (length ``n``) lies against an arc of half-width hw
    around m (``cm, sm = cos m, sin m``, ``chw = cos hw``), without an arctangent: 1 certainly inside,
    0 certainly outside, -1 too close to an end to say. The margin (1e-9 in the cosine, at least 1e-9
    rad in the angle) is far above the rounding of either test and the exact test's 1e-12 rad
    tolerance, so a certain answer is the exact test's answer."""
    cd = x * cm + y * sm
    if cd > (chw + 1e-9) * n:
        return 1
    if cd < (chw - 1e-9) * n:
        return 0
    return -1


@njit(cache=True, error_model="numpy")
def _reachable_kernel(W, prm, out):
    """:meth:`Arm.reachable` per wrist ``W[i]`` into ``out[i]``: the answers of :meth:`Arm._reachable_numpy`
    (``prm`` from :meth:`Arm._reach_params`). Each branch's angles are first placed against their limit
    intervals by one dot product each (:func:`_arc_class`, where ``prm[27]`` says it is exact); the
    arctangents, in the reference's operations and order, run only for a branch that comes within about
    1e-9 rad of a limit."""
    by, bz, l1, l2 = prm[0], prm[1], prm[2], prm[3]
    ch1, sh1, ch2, sh2 = prm[4], prm[5], prm[6], prm[7]
    fast = prm[27] == 1.0
    den = 2 * l1 * l2
    for i in range(W.shape[0]):
        dy = W[i, 0] - by
        dz = W[i, 1] - bz
        c = (dy * dy + dz * dz - l1 * l1 - l2 * l2) / den
        res = False
        if c >= -1.0 and c <= 1.0:
            sn = math.sqrt(1.0 - c * c)
            for k in range(2):
                s_d = (1.0 if k == 0 else -1.0) * sn
                y2, x2 = s_d * ch2 - c * sh2, c * ch2 + s_d * sh2
                vz, vy = l1 + l2 * c, l2 * s_d
                rz, ry = dz * vz + dy * vy, dy * vz - dz * vy
                y1, x1 = ry * ch1 - rz * sh1, rz * ch1 + ry * sh1
                if fast:
                    n2 = math.sqrt(x2 * x2 + y2 * y2)
                    k2 = _arc_class(x2, y2, n2, prm[18], prm[19], prm[20])
                    if k2 == 0:
                        continue
                    n1 = math.sqrt(x1 * x1 + y1 * y1)
                    k1 = _arc_class(x1, y1, n1, prm[21], prm[22], prm[23])
                    if k1 == 0:
                        continue
                    # q1 + q2 stays inside (-pi, pi): the angle of the product of the two rotations is the sum
                    ks = _arc_class(x1 * x2 - y1 * y2, y1 * x2 + x1 * y2, n1 * n2, prm[24], prm[25], prm[26])
                    if ks == 0:
                        continue
                    if k2 == 1 and k1 == 1 and ks == 1:
                        res = True
                        break
                q2 = math.atan2(y2, x2)
                q1 = math.atan2(y1, x1)
                s = q1 + q2
                if (q1 >= prm[8] and q1 <= prm[9] and q2 >= prm[10] and q2 <= prm[11]
                        and s >= prm[12] and s <= prm[13]):
                    res = True
                    break
        out[i] = res


@njit(cache=True, error_model="numpy")
def _forward_kernel(Q, prm, out):
    """:meth:`Arm.forward` per row of ``Q`` into ``out`` (:meth:`Arm._forward_numpy`'s operations)."""
    l1, l2, h1, h2 = prm[2], prm[3], prm[14], prm[15]
    for i in range(Q.shape[0]):
        a1 = Q[i, 0] + h1
        a2 = a1 + Q[i, 1] + h2
        out[i, 0] = prm[0] + l1 * math.sin(a1) + l2 * math.sin(a2)
        out[i, 1] = prm[1] + l1 * math.cos(a1) + l2 * math.cos(a2)


@njit(cache=True, error_model="numpy")
def _jacobian_kernel(Q, prm, out):
    """:meth:`Arm.jacobian` per row of ``Q`` into ``out`` (n, 2, 2) (:meth:`Arm._jacobian_numpy`'s operations)."""
    l1, l2, h1, h2 = prm[2], prm[3], prm[14], prm[15]
    for i in range(Q.shape[0]):
        a1 = Q[i, 0] + h1
        a2 = a1 + Q[i, 1] + h2
        c1, s1 = math.cos(a1), -math.sin(a1)
        c2, s2 = math.cos(a2), -math.sin(a2)
        out[i, 0, 0] = l1 * c1 + l2 * c2
        out[i, 1, 0] = l1 * s1 + l2 * s2
        out[i, 0, 1] = l2 * c2
        out[i, 1, 1] = l2 * s2


@njit(cache=True, error_model="numpy")
def _wrap1(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


@njit(cache=True, error_model="numpy")
def _inverse_kernel(W, prm, sgn, Q, ok):
    """:meth:`Arm.inverse` per wrist ``W[i]`` into ``Q[i]``, ``ok[i]`` (:meth:`Arm._inverse_numpy`'s
    operations: the preferred branch ``sgn``, else the other one, inside the limits; NaN elsewhere)."""
    l1, l2, h1, h2 = prm[2], prm[3], prm[14], prm[15]
    for i in range(W.shape[0]):
        dy = W[i, 0] - prm[0]
        dz = W[i, 1] - prm[1]
        c = (dy * dy + dz * dz - prm[16] - prm[17]) / (2 * l1 * l2)
        good = False
        q1 = q2 = math.nan
        if c >= -1.0 and c <= 1.0:
            ad = math.atan2(dy, dz)
            ac = math.acos(min(max(c, -1.0), 1.0))
            for k in range(2):
                delta = (sgn if k == 0 else -sgn) * ac
                a1 = ad - math.atan2(l2 * math.sin(delta), l1 + l2 * math.cos(delta))
                q1 = _wrap1(a1 - h1)
                q2 = _wrap1(delta - h2)
                s = q1 + q2
                if (q1 >= prm[8] and q1 <= prm[9] and q2 >= prm[10] and q2 <= prm[11]
                        and s >= prm[12] and s <= prm[13]):
                    good = True
                    break
        ok[i] = good
        if good:
            Q[i, 0], Q[i, 1] = q1, q2
        else:
            Q[i, 0], Q[i, 1] = math.nan, math.nan


# ----------------------------------------------------------------------------- the flexed shaft
# The Newton iterations run an iteration at a time over the whole batch (a loop without calls, which LLVM
# vectorizes); the trigonometry in a separate loop.
@njit(cache=True, error_model="numpy")
def _newton_a2(R, L, T, X):
    """:func:`_solve_a` over a batch into ``X`` (:func:`_solve_length` with its ``s(a)``, the same
    operations). An iteration at a time over the whole batch: a loop without calls, which LLVM
    vectorizes (one element at a time the divisions' latency would dominate)."""
    n = R.shape[0]
    for i in range(n):
        X[i] = R[i]
    for _ in range(_NEWTON_ITERS):
        for i in range(n):
            x, t, rho = X[i], T[i], R[i]
            la = L - x
            s = t * (la * la) / 3.0
            ds = -2.0 * t * la / 3.0
            g = 1.0 + s * s
            X[i] = x - (x * x * g - rho * rho) / (2.0 * x * g + 2.0 * x * x * s * ds)


@njit(cache=True, error_model="numpy")
def _newton_b2(R, L, T, X):
    """:func:`_solve_b` over a batch into ``X`` (:func:`_solve_length` with its ``s(b)``), as :func:`_newton_a2`."""
    n = R.shape[0]
    for i in range(n):
        X[i] = R[i]
    for _ in range(_NEWTON_ITERS):
        for i in range(n):
            x, t, r = X[i], T[i], R[i]
            s = t * (L - x) * x / 3.0
            ds = t * (L - 2.0 * x) / 3.0
            g = 1.0 + s * s
            X[i] = x - (x * x * g - r * r) / (2.0 * x * g + 2.0 * x * x * s * ds)


@njit(cache=True, error_model="numpy")
def _geometry2_batch(W, P, L, T, anyt, O):
    """``O[0:5]`` = rho, theta, a, b, phi of a planar batch (:func:`_flexed_geometry_numpy`)."""
    n = T.shape[0]
    for i in range(n):
        d0, d1 = P[i, 0] - W[i, 0], P[i, 1] - W[i, 1]
        O[0, i] = math.sqrt(d0 * d0 + d1 * d1)
    if anyt:
        _newton_a2(O[0], L, T, O[2])
    else:
        for i in range(n):
            O[2, i] = O[0, i] + 0.0 * T[i]
    for i in range(n):
        O[3, i] = L - O[2, i]
    for i in range(n):
        b = O[3, i]
        O[1, i] = math.atan2(P[i, 0] - W[i, 0], P[i, 1] - W[i, 1])
        O[4, i] = O[1, i] + math.atan(T[i] * b * b / 3.0)


@njit(cache=True, error_model="numpy")
def _geometry2_kernel(W, P, L, T, anyt, O):
    """:func:`flexed_geometry` over a planar batch into ``O`` (7, n): rho, theta, a, b, phi, tip y, tip z."""
    _geometry2_batch(W, P, L, T, anyt, O)
    for i in range(T.shape[0]):
        phi = O[4, i]
        O[5, i] = W[i, 0] + L * math.sin(phi)
        O[6, i] = W[i, 1] + L * math.cos(phi)


@njit(cache=True, error_model="numpy")
def _jacobian2_kernel(W, P, L, T, anyt, J):
    """:func:`flexed_jacobian` over a planar batch into ``J`` (n, 2, 2) (:func:`_flexed_jacobian2_numpy`)."""
    n = T.shape[0]
    O = np.empty((5, n))
    _geometry2_batch(W, P, L, T, anyt, O)
    for i in range(n):
        t = T[i]
        rho, theta, a, b, phi = O[0, i], O[1, i], O[2, i], O[3, i], O[4, i]
        st, ct = math.sin(theta), math.cos(theta)
        u0, u1 = st, ct
        n0, n1 = ct, -st
        q0, q1 = math.cos(phi), -math.sin(phi)
        s = t * b * b / 3.0
        gg = 1.0 + s * s
        dgg = -(4.0 * t * b / 3.0) * s
        beta_p = -(2.0 * t * b / 3.0) / gg
        a_p = 2.0 * rho / (2.0 * a * gg + a * a * dgg)
        c = beta_p * a_p
        g0 = -n0 / rho - c * u0
        g1 = -n1 / rho - c * u1
        J[i, 0, 0] = 1.0 + L * (q0 * g0)
        J[i, 0, 1] = 0.0 + L * (q0 * g1)
        J[i, 1, 0] = 0.0 + L * (q1 * g0)
        J[i, 1, 1] = 1.0 + L * (q1 * g1)


@njit(cache=True, error_model="numpy")
def _wrist2_kernel(X, P, L, T, anyt, O):
    """:func:`flexed_wrist` over a planar batch into ``O`` (n, 2) (:func:`_flexed_wrist_numpy`)."""
    n = T.shape[0]
    R = np.empty(n)
    for i in range(n):
        d0, d1 = X[i, 0] - P[i, 0], X[i, 1] - P[i, 1]
        R[i] = math.sqrt(d0 * d0 + d1 * d1)
    if not anyt:
        for i in range(n):
            r, t = R[i], T[i]
            O[i, 0] = X[i, 0] - L * (X[i, 0] - P[i, 0]) / r + 0.0 * t
            O[i, 1] = X[i, 1] - L * (X[i, 1] - P[i, 1]) / r + 0.0 * t
        return
    B = np.empty(n)
    _newton_b2(R, L, T, B)
    for i in range(n):
        x0, x1 = X[i, 0], X[i, 1]
        t, b = T[i], B[i]
        a = L - b
        phi = math.atan2(x0 - P[i, 0], x1 - P[i, 1]) - math.atan(t * a * b / 3.0)
        O[i, 0] = x0 - L * math.sin(phi)
        O[i, 1] = x1 - L * math.cos(phi)



# ----------------------------------------------------------------------------- 2 x 2 inverses
@njit(cache=True, error_model="numpy")
def _inv2_kernel(A, rcond, out, singular):
    """:func:`errplan.metrics.inv2` per matrix ``A[i]`` into ``out[i]``, ``singular[i]``: its operations in the
    same order (``||A||_F^2`` summed as numpy's einsum sums a C-contiguous 2 x 2 block)."""
    for i in range(A.shape[0]):
        a, b, c, d = A[i, 0, 0], A[i, 0, 1], A[i, 1, 0], A[i, 1, 1]
        det = a * d - b * c
        scale = (a * a + c * c) + (b * b + d * d)
        sing = not (abs(det) > rcond * scale)
        singular[i] = sing
        if sing:
            out[i, 0, 0] = out[i, 0, 1] = out[i, 1, 0] = out[i, 1, 1] = math.nan
        else:
            out[i, 0, 0] = d / det
            out[i, 1, 1] = a / det
            out[i, 0, 1] = -b / det
            out[i, 1, 0] = -c / det



# ----------------------------------------------------------------------------- complex parts
@intrinsic
def _fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (LLVM's ``fma``): how numpy's complex loops form a product on this
    platform (re = fma(ar, br, -(ai bi)), im = fma(ar, bi, ai br)), checked bit for bit by the tests."""
    sig = _types.float64(_types.float64, _types.float64, _types.float64)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return sig, codegen


@njit(cache=True, error_model="numpy")
def _lever_parts_kernel(W, P, L, mu, nu):
    """:func:`errplan.kinematics.shaft.lever_parts` per wrist ``W[i]`` (port ``P[i]``, or ``P[0]`` for all)
    into ``mu[i]`` and ``nu[i]`` (real, imaginary): numpy's operations in its order, complex products as
    its loops form them (:func:`_fma`), the division by the real ``rho^2`` as Smith's (times its inverse)."""
    one = P.shape[0] == 1
    for i in range(W.shape[0]):
        j = 0 if one else i
        dy = P[j, 0] - W[i, 0]
        dz = P[j, 1] - W[i, 1]
        rho2 = dy * dy + dz * dz
        rho = math.sqrt(rho2)
        t1r = _fma(0.0, dy, -0.0)  # 1j * dy
        t1i = _fma(0.0, 0.0, dy)
        zr = dz - t1r  # dz - 1j * dy
        zi = 0.0 - t1i
        sr = _fma(zr, zr, -(zi * zi))  # ** 2
        si = _fma(zr, zi, zi * zr)
        scl = 1.0 / rho2  # / rho2
        h = L / (2.0 * rho)
        mu[i] = 1.0 - h
        nu[i, 0] = -h * (sr * scl)
        nu[i, 1] = -h * (si * scl)



@njit(cache=True, error_model="numpy")
def _smith_real(a, b, c):
    """``(a + i b) / c`` for a real ``c`` as numpy divides complex numbers (Smith's method, ``c + 0i``)."""
    rat = 0.0 / c
    scl = 1.0 / (c + 0.0 * rat)
    return (a + b * rat) * scl, (b - a * rat) * scl


@njit(cache=True, error_model="numpy")
def _inverse_parts_kernel(MU, NU, real_mu, rcond, IMU, INU, singular):
    """:func:`errplan.metrics.inverse_parts` per element: ``MU`` (n, 2) (real, imaginary; imaginary 0 and
    ``real_mu`` when numpy's mu is real), ``NU`` (n, 2), into ``IMU`` (n, 2), ``INU`` (n, 2), ``singular``;
    numpy's operations, its complex products as fused multiply-adds (:func:`_fma`)."""
    for i in range(MU.shape[0]):
        mr, mi, nr, ni = MU[i, 0], MU[i, 1], NU[i, 0], NU[i, 1]
        if real_mu:
            mm = mr * mr
        else:
            mm = _fma(mr, mr, -(mi * -mi))
        nn = _fma(nr, nr, -(ni * -ni))
        det = mm - nn
        scale = mm + nn
        sing = not (abs(det) > rcond * scale)
        singular[i] = sing
        safe = math.nan if sing else det
        if real_mu:
            IMU[i, 0], IMU[i, 1] = mr / safe, 0.0
        else:
            IMU[i, 0], IMU[i, 1] = _smith_real(mr, -mi, safe)
        INU[i, 0], INU[i, 1] = _smith_real(-nr, -ni, safe)
