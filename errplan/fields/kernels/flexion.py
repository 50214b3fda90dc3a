"""P2's flexion controller in 3-D, compiled: the motion maps ``M = J Jhat^-1`` of (tip, instance) pairs over
the controller's sensor-noise vectors, and their worst ``||I - k M||`` and ``|phi_max|``.

The true shaft (wrist ``w``, world load ``t``, port ``p``) is the caller's (one per pair, cheap); here, per
pair: the true flexed-shaft Jacobian ``J`` (:func:`errplan.kinematics.shaft.flexed_jacobian`), the end
poses the controller measures (tip, end tangents, :func:`~errplan.kinematics.shaft.flexed_end_directions`),
the true bending plane's normal (:func:`errplan.fields.evaluator.bending_frame`), and per noise vector
(``[delta(3), tilt_w(2), tilt_t(2)]``, :func:`errplan.errorset.spatial_noise_corners`): the noisy
measurements (:func:`~errplan.fields.evaluator.noisy_end_poses`), the fitted bending plane and P2's planar
estimator in it (:func:`~errplan.kinematics.shaft.estimate_from_end_poses`), ``Jhat`` the flexed shaft's
Jacobian at the measured wrist through the estimated port under the estimated load (the lever through the
port estimate where the estimate is unidentifiable), ``M = J Jhat^-1``. Each step is the numpy function's
arithmetic in scalars, in the same order (the numpy path, :meth:`SpatialFlexionEvaluator.parts_numpy
<errplan.fields.evaluator.SpatialFlexionEvaluator.parts_numpy>`, is the reference the tests hold it to).

The noise vectors of a pair run in batches: the distinct chords and tilts once per pair
(:func:`_noise_index`, :func:`_pair_tables`), then blocks of CS vectors through loops without calls or
branches (:func:`_corner_inputs`, :func:`_fast_corners`, :func:`_corner_maps`) that the compiler vectorizes,
the same operations in the same order as the one-vector functions (:func:`_controller_J3`, which still
serves the vectors whose estimate needs the general path): the same numbers to the bit, about four times
faster.

The worst over the noise vectors (:func:`flexion_tips` with ``want_gp``) takes ``||I - k M||`` of each map and
the exact ``|phi_max|`` only where its cheap bound (:func:`errplan.fields.kernels.metrics.phi_bound`'s) could
beat the best exact value so far: the same maximum, a fraction of the exact evaluations.
"""
from __future__ import annotations

import math

import numpy as np

from ...jit import njit
from ...linalg import _smax3, phi_max3
from .instance import NEWTON, _flexed_J3

RCOND_INV = 1e-12  # errplan.metrics.inv's default: a controller Jacobian this close to singular fails the pair

# The vectors of one pair live in rows of one array ``B`` (a view would cost an atomic reference count
# per call, more than the arithmetic here): the true shaft, its measured poses, one noise vector's.
W, P, T, TIP, DW, DT, MB, E1W, E1T, U, N, PT, DWN, DTN, C, F1, F2, NB, PORT, LOAD, EST, CH, R9 = range(23)
ROWS = 23


@njit(cache=True, error_model="numpy")
def _solve_a(rho, L, t):
    """Port position ``a`` along the chord from ``rho^2 = a^2 (1 + (t b^2/3)^2)`` (kinematics.shaft._solve_a)."""
    a = rho
    for _ in range(NEWTON):
        la = L - a
        s = t * la * la / 3.0
        ds = -2.0 * t * la / 3.0
        g = 1.0 + s * s
        a1 = a - (a * a * g - rho * rho) / (2.0 * a * g + 2.0 * a * a * s * ds)
        if a1 == a:  # a fixed point: the remaining steps return it unchanged
            break
        a = a1
    return a


@njit(cache=True, error_model="numpy")
def _geometry3(B, iw, ip, it, L):
    """The 3-D flexed shaft (kinematics.shaft._spatial_geometry) of wrist ``B[iw]``, port ``B[ip]``, world
    load ``B[it]``: ``u``, ``n`` into rows U, N; returns ``(rho, tau, a)`` (the chord's angle from ``u``
    toward ``n`` is ``atan(tau b^2 / 3)``, ``b = L - a``)."""
    d0, d1, d2 = B[ip, 0] - B[iw, 0], B[ip, 1] - B[iw, 1], B[ip, 2] - B[iw, 2]
    rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    u0, u1, u2 = d0 / rho, d1 / rho, d2 / rho
    B[U, 0], B[U, 1], B[U, 2] = u0, u1, u2
    tu = B[it, 0] * u0 + B[it, 1] * u1 + B[it, 2] * u2
    q0, q1, q2 = B[it, 0] - tu * u0, B[it, 1] - tu * u1, B[it, 2] - tu * u2
    tau = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2)
    if tau > 0:
        B[N, 0], B[N, 1], B[N, 2] = q0 / tau, q1 / tau, q2 / tau
        a = _solve_a(rho, L, tau)
    else:
        B[N, 0], B[N, 1], B[N, 2] = 0.0, 0.0, 0.0
        a = rho
    return rho, tau, a


@njit(cache=True, error_model="numpy")
def _lever_rows(B, iw, ip, L, J):
    """Rigid lever ``I - (L/rho)(I - u u^T)`` of wrist ``B[iw]`` through ``B[ip]`` into ``J``."""
    d0, d1, d2 = B[ip, 0] - B[iw, 0], B[ip, 1] - B[iw, 1], B[ip, 2] - B[iw, 2]
    rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    s = L / rho
    for i in range(3):
        ui = (B[ip, i] - B[iw, i]) / rho
        for j in range(3):
            uj = (B[ip, j] - B[iw, j]) / rho
            J[i, j] = (1.0 - s if i == j else 0.0) + s * ui * uj


@njit(cache=True, error_model="numpy")
def _jacobian3(B, iw, ip, it, L, J, S):
    """Flexed-shaft ``d tip / d w`` at constant port and world load (kinematics.shaft.flexed_jacobian in
    3-D) into ``J``; the rigid lever where the load has no part normal to the wrist->port line."""
    rho, tau, a = _geometry3(B, iw, ip, it, L)
    if tau > 0:
        _flexed_J3(B, iw, ip, it, L, a, J, S)
    else:
        _lever_rows(B, iw, ip, L, J)


@njit(cache=True, error_model="numpy")
def _beam_slope(xm, a, L, fp):
    """P2 eq. (2): the beam's slope at ``xm`` (kinematics.shaft.beam_slope)."""
    b = L - a
    mac = (xm - a) ** 2 if xm >= a else 0.0
    return -(fp / 6.0) * (L * b * (1 - b * b / L ** 2 - 3 * xm * xm / L ** 2) + 3 * mac)


@njit(cache=True, error_model="numpy")
def _cross_unit(B, ia, ib, io):
    """``B[io] = (B[ia] x B[ib]) / |B[ia] x B[ib]|``; returns ``|B[ia] x B[ib]|``."""
    c0 = B[ia, 1] * B[ib, 2] - B[ia, 2] * B[ib, 1]
    c1 = B[ia, 2] * B[ib, 0] - B[ia, 0] * B[ib, 2]
    c2 = B[ia, 0] * B[ib, 1] - B[ia, 1] * B[ib, 0]
    nn = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    B[io, 0], B[io, 1], B[io, 2] = c0 / nn, c1 / nn, c2 / nn
    return nn


@njit(cache=True, error_model="numpy")
def _perp_rows(B, ie, i1, i2):
    """Rows ``i1``, ``i2``: unit vectors completing unit ``B[ie]`` to a right-handed frame, the reference
    axis that of its least |component| (kernels.instance._perp_basis, kinematics.shaft._chord_frame)."""
    e0, e1, e2 = B[ie, 0], B[ie, 1], B[ie, 2]
    ax, ay, az = abs(e0), abs(e1), abs(e2)
    if ax <= ay and ax <= az:
        r0, r1, r2 = 1.0, 0.0, 0.0
    elif ay <= az:
        r0, r1, r2 = 0.0, 1.0, 0.0
    else:
        r0, r1, r2 = 0.0, 0.0, 1.0
    c0 = e1 * r2 - e2 * r1
    c1 = e2 * r0 - e0 * r2
    c2 = e0 * r1 - e1 * r0
    n = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    f0, f1, f2 = c0 / n, c1 / n, c2 / n
    B[i1, 0], B[i1, 1], B[i1, 2] = f0, f1, f2
    B[i2, 0] = e1 * f2 - e2 * f1
    B[i2, 1] = e2 * f0 - e0 * f2
    B[i2, 2] = e0 * f1 - e1 * f0


@njit(cache=True, error_model="numpy")
def _true_poses(B, L):
    """The true shaft's measured poses and bending frame (kinematics.shaft.flexed_end_directions,
    fields.evaluator.bending_frame) from rows W, P, T: rows TIP, DW, DT (unit end tangents), MB (the
    bending plane's unit normal m) and E1W, E1T (each tangent's tilt axis ``m x d / |m x d|``)."""
    rho, tau, a = _geometry3(B, W, P, T, L)
    b = L - a
    beta = math.atan(tau * b * b / 3.0)
    cb, sb = math.cos(beta), math.sin(beta)
    fp = tau * L / a
    a0 = math.atan(_beam_slope(0.0, a, L, fp))
    aL = math.atan(_beam_slope(L, a, L, fp))
    c0, s0, cL, sL = math.cos(a0), math.sin(a0), math.cos(aL), math.sin(aL)
    for i in range(3):
        ch = cb * B[U, i] + sb * B[N, i]
        v = -sb * B[U, i] + cb * B[N, i]
        B[TIP, i] = B[W, i] + L * ch
        B[DW, i] = c0 * ch + s0 * v
        B[DT, i] = cL * ch + sL * v
    mn = _cross_unit(B, U, N, MB)
    if not mn > 1e-12:  # unbent: the second vector of the chord's frame
        for i in range(3):
            B[CH, i] = (B[TIP, i] - B[W, i]) / L
        if not (math.isfinite(B[CH, 0]) and math.isfinite(B[CH, 1]) and math.isfinite(B[CH, 2])):
            B[CH, 0], B[CH, 1], B[CH, 2] = 0.0, 0.0, 1.0
        _perp_rows(B, CH, R9, MB)
    _cross_unit(B, MB, DW, E1W)
    _cross_unit(B, MB, DT, E1T)


@njit(cache=True, error_model="numpy")
def _tilt(B, id_, z0, z1, ie1, io):
    """``B[io]``: ``B[id_]`` turned by ``|(z0, z1)|`` toward ``z0 e1 + z1 m`` (kinematics.shaft.tilt; ``e1 =
    B[ie1]``, ``m`` the bending normal)."""
    ang = math.sqrt(z0 * z0 + z1 * z1)
    safe = ang if ang > 0 else 1.0
    ca, sa = math.cos(ang), math.sin(ang)
    for i in range(3):
        B[io, i] = ca * B[id_, i] + sa * ((z0 * B[ie1, i] + z1 * B[MB, i]) / safe)


@njit(cache=True, error_model="numpy")
def _tilted(B, Zk, Zv, cnt, slot, id_, z0, z1, ie1, io):
    """:func:`_tilt` through a per-pair table (``slot`` 0 the wrist's, 1 the tip's): a noise set repeats
    each end's few tilts across its corners, the same tilt of the same tangent is computed once."""
    for q in range(cnt[slot]):
        if Zk[slot, q, 0] == z0 and Zk[slot, q, 1] == z1:
            for i in range(3):
                B[io, i] = Zv[slot, q, i]
            return
    _tilt(B, id_, z0, z1, ie1, io)
    q = cnt[slot]
    if q < Zk.shape[1]:
        Zk[slot, q, 0], Zk[slot, q, 1] = z0, z1
        for i in range(3):
            Zv[slot, q, i] = B[io, i]
        cnt[slot] = q + 1


@njit(cache=True, error_model="numpy")
def _controller_J3(B, NZ, zi, j, L, Jh, S, Zk, Zv, cnt, last):
    """``Jhat_tw`` of P2's controller in 3-D (kinematics.shaft.flexion_controller_jacobian) fed the true
    poses (:func:`_true_poses`) under noise vector ``NZ[zi, j]``, into ``Jh``: the bending plane fitted to
    the measured tangents (kinematics.shaft.bending_plane), P2's planar estimator in its coordinates
    (kinematics.shaft.estimate_from_ends), the flexed shaft's Jacobian at the measured wrist through the
    estimated port under the estimated load; the lever through the port estimate where that is not finite.

    The estimate is :func:`_estimate`'s shortcut where it is well conditioned, else the numpy path's
    operations. The tilted tangents (:func:`_tilted`) and the chord's frame (``last``: the previous noise vector's chord difference, NaN
    for none) are reused where the noise vector repeats them."""
    d0, d1, d2 = NZ[zi, j, 0], NZ[zi, j, 1], NZ[zi, j, 2]
    if not (d0 == last[0] and d1 == last[1] and d2 == last[2]):
        last[0], last[1], last[2] = d0, d1, d2
        for i in range(3):
            B[PT, i] = B[TIP, i] + NZ[zi, j, i]
        c0, c1, c2 = B[PT, 0] - B[W, 0], B[PT, 1] - B[W, 1], B[PT, 2] - B[W, 2]
        r = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        last[3] = r
        B[C, 0], B[C, 1], B[C, 2] = c0 / r, c1 / r, c2 / r
        _perp_rows(B, C, F1, F2)
    r = last[3]
    _tilted(B, Zk, Zv, cnt, 0, DW, NZ[zi, j, 3], NZ[zi, j, 4], E1W, DWN)
    _tilted(B, Zk, Zv, cnt, 1, DT, NZ[zi, j, 5], NZ[zi, j, 6], E1T, DTN)
    xw = B[DWN, 0] * B[F1, 0] + B[DWN, 1] * B[F1, 1] + B[DWN, 2] * B[F1, 2]
    yw = B[DWN, 0] * B[F2, 0] + B[DWN, 1] * B[F2, 1] + B[DWN, 2] * B[F2, 2]
    xt = B[DTN, 0] * B[F1, 0] + B[DTN, 1] * B[F1, 1] + B[DTN, 2] * B[F1, 2]
    yt = B[DTN, 0] * B[F2, 0] + B[DTN, 1] * B[F2, 1] + B[DTN, 2] * B[F2, 2]
    a, te = _estimate(B, r, xw, yw, xt, yt, L, True)
    solved = False
    if a == -1.0:  # ill-conditioned for the shortcuts: the numpy path's operations
        a, te = _estimate(B, r, xw, yw, xt, yt, L, False)
    elif 0.0 < a < L and 0.0 < abs(te) * L * L < 1.5:
        # The shaft through the estimated port under the estimated load is P2's beam of the plane: its
        # port sits at ``a`` along the chord. The numpy path solves for it again from |port - w| by Newton
        # from that distance: with ``a`` on the shaft and |te| L^2 / 3 < 1/2 the equation has that one root
        # (it is increasing in ``a``), which Newton returns to rounding; the residual confirms it.
        r2 = (B[PORT, 0] - B[W, 0]) ** 2 + (B[PORT, 1] - B[W, 1]) ** 2 + (B[PORT, 2] - B[W, 2]) ** 2
        sb = abs(te) * (L - a) ** 2 / 3.0
        if abs(a * a * (1.0 + sb * sb) - r2) <= 1e-12 * r2:
            _estimated_J3(B, a, te, math.sqrt(r2), L, Jh)
            solved = True
    if not solved:
        _jacobian3(B, W, PORT, LOAD, L, Jh, S)
    for i in range(3):
        for j_ in range(3):
            if not math.isfinite(Jh[i, j_]):
                _lever_rows(B, W, EST, L, Jh)
                return


@njit(cache=True, error_model="numpy")
def _estimated_J3(B, a, te, rho, L, Jh):
    """The flexed shaft's ``d tip / d w`` (kinematics.shaft.flexed_jacobian in 3-D) at the measured wrist
    through the estimated port (rows W, PORT; ``rho = |port - w|``, the port at ``a`` along the chord) under
    the estimated load ``te`` along the plane's normal ``n_u`` of the wrist->port line (row LOAD), into
    ``Jh``. The load is normal to the line (``u.t = 0``) and its part normal to it does not turn with the
    wrist's distance (``d tau / d w = 0``), so the general Jacobian (kernels.instance._flexed_J3) reduces to
    ``I - (L cb / rho)(I - u u^T) + (L sb / rho) u n^T - L beta_a a_rho v u^T`` (``n = sign(te) n_u``,
    ``v = -sb u + cb n``, ``cb + i sb = (1 + i s) / sqrt(1 + s^2)``, ``s = |te| b^2 / 3``): equal to
    rounding."""
    tau = abs(te)
    b = L - a
    s = tau * b * b / 3.0
    gg = 1.0 + s * s
    dgg = -(4.0 * tau * b / 3.0) * s
    a_rho = 2.0 * rho / (2.0 * a * gg + a * a * dgg)
    beta_a = -(2.0 * tau * b / 3.0) / gg
    q = 1.0 / math.sqrt(gg)
    cb, sb = q, s * q
    u0, u1, u2 = (B[PORT, 0] - B[W, 0]) / rho, (B[PORT, 1] - B[W, 1]) / rho, (B[PORT, 2] - B[W, 2]) / rho
    n0, n1, n2 = B[LOAD, 0] / tau, B[LOAD, 1] / tau, B[LOAD, 2] / tau  # sign(te) n_u
    c1 = L * cb / rho
    c2 = L * sb / rho
    c3 = L * beta_a * a_rho
    for i in range(3):
        ui = u0 if i == 0 else (u1 if i == 1 else u2)
        ni = n0 if i == 0 else (n1 if i == 1 else n2)
        vi = -sb * ui + cb * ni
        for j in range(3):
            uj = u0 if j == 0 else (u1 if j == 1 else u2)
            nj = n0 if j == 0 else (n1 if j == 1 else n2)
            dij = 1.0 if i == j else 0.0
            Jh[i, j] = dij - c1 * (dij - ui * uj) + c2 * ui * nj - c3 * vi * uj


@njit(cache=True, error_model="numpy")
def _estimate(B, r, xw, yw, xt, yt, L, fast):
    """The fitted bending plane's normal (row NB) and P2's estimator in the plane (kinematics.shaft.
    bending_plane, estimate_from_ends, estimate_from_end_poses): the estimated port and load into rows
    PORT, LOAD; returns ``(a, te)`` (the port's position along the chord, the signed load).

    ``fast``: the trigonometry reduced to ratios (``tan(atan2(y, x)) = y / x``, cos and sin of an
    ``atan2`` and of its half angle from the same sides), equal to the numpy path's to a few units in
    the last place; returns ``(-1, nan)`` (nothing written) where the estimate would amplify those
    (end slopes whose difference ``den`` is below 1e-4: near an unidentifiable estimate the numpy path's
    own result follows its rounding, and only its own operations in its order reproduce it). Without
    ``fast``: the numpy path's operations in its order, trigonometry included."""
    s11 = xw * xw + xt * xt
    s22 = yw * yw + yt * yt
    s12 = xw * yw + xt * yt
    if fast:
        # psi = atan2(2 s12, s11 - s22) / 2 in (-pi/2, pi/2]: cos psi >= 0, from the double angle's sides
        y2, x2 = 2.0 * s12, s11 - s22
        h2 = math.sqrt(y2 * y2 + x2 * x2)
        if not (h2 > 0.0 and r > 0.0 and r < math.inf):
            return -1.0, math.nan
        c2 = x2 / h2
        if c2 >= 0.0:
            cp = math.sqrt(0.5 * (1.0 + c2))
            sp = y2 / h2 / (2.0 * cp)
        else:
            sp = math.copysign(math.sqrt(0.5 * (1.0 - c2)), y2)
            cp = y2 / h2 / (2.0 * sp)
    else:
        psi = 0.5 * math.atan2(2.0 * s12, s11 - s22)
        cp, sp = math.cos(psi), math.sin(psi)
    n0, n1, n2 = cp * B[F1, 0] + sp * B[F2, 0], cp * B[F1, 1] + sp * B[F2, 1], cp * B[F1, 2] + sp * B[F2, 2]
    yw_ = B[DWN, 0] * n0 + B[DWN, 1] * n1 + B[DWN, 2] * n2
    xw_ = B[DWN, 0] * B[C, 0] + B[DWN, 1] * B[C, 1] + B[DWN, 2] * B[C, 2]
    yt_ = B[DTN, 0] * n0 + B[DTN, 1] * n1 + B[DTN, 2] * n2
    xt_ = B[DTN, 0] * B[C, 0] + B[DTN, 1] * B[C, 1] + B[DTN, 2] * B[C, 2]
    # P2 eqs. (8)-(14) in the plane's coordinates: wrist at the origin, tip at (0, r): the chord's angle
    # atan2(0, r) is 0.0 exactly for r > 0 (its sine 0.0, cosine 1.0)
    phi = 0.0 if r > 0.0 else math.atan2(0.0, r)
    sphi, cphi = (0.0, 1.0) if r > 0.0 else (math.sin(phi), math.cos(phi))
    if fast:
        if not (xw_ > 0.0 and xt_ > 0.0):
            return -1.0, math.nan
        s0 = yw_ / xw_
        sL = yt_ / xt_
    else:
        s0 = math.tan(math.atan2(yw_, xw_) - phi)
        sL = math.tan(math.atan2(yt_, xt_) - phi)
    den = sL - s0
    if fast and not abs(den) > 1e-4:
        return -1.0, math.nan
    a = L * (2 * sL + s0) / den
    if not (math.isfinite(a) and den != 0):
        a = math.nan
    fp = 2 * (s0 - sL) / (a * (a - L))
    if not math.isfinite(fp):
        fp = math.nan
    ym = -fp * a * a * (a - L) ** 2 / (3 * L)
    p20 = 0.0 + a * sphi + ym * cphi
    p21 = 0.0 + a * cphi + ym * -sphi
    te = fp * a / L
    if fast:
        hp = math.sqrt(p20 * p20 + p21 * p21)
        if not (hp > 0.0 and hp < math.inf):
            return -1.0, math.nan
        ct, st = p21 / hp, p20 / hp
    else:
        thp = math.atan2(p20, p21)
        ct, st = math.cos(thp), math.sin(thp)
    B[NB, 0], B[NB, 1], B[NB, 2] = n0, n1, n2
    for i in range(3):
        B[PORT, i] = B[W, i] + p20 * B[NB, i] + p21 * B[C, i]
        B[LOAD, i] = te * (ct * B[NB, i] - st * B[C, i])
    return a, te


# The noise vectors of one pair run in blocks of CS: a block's quantities live in rows of one flat array
# ``Z`` (row ``r`` of corner ``j`` at ``Z[r * CS + j]``). The stride being a constant, the compiler sees
# that the batched stages' reads and writes do not overlap and vectorizes their loops over the corners.
CS = 64
ZR, ZXW, ZYW, ZXT, ZYT, ZC, ZF1, ZF2, ZDW, ZDT = 0, 1, 2, 3, 4, 5, 8, 11, 14, 17  # the measurements
ZJ = 20  # Jhat, 9 rows (row-major)
ZFL = 29  # 1.0 where _fast_corners computed Jhat
ZM = 30  # M = J Jhat^-1, 9 rows
ZBAD = 39  # 1.0 where Jhat is singular or M not finite
ZGB = 40  # _gnorm_bound of M at the pair's gain
ZPB = 41  # the ||G|| bound inside _phi_bound (2.0 where that returns pi without one)
ZROWS = 42


@njit(cache=True, error_model="numpy")
def _noise_index(NZ, zi, c, ids, reps, nrep):
    """The distinct chord differences (slot 0, ``NZ[zi, j, 0:3]``), wrist tilts (slot 1, ``3:5``) and tip tilts
    (slot 2, ``5:7``) of the noise vectors: ``ids[slot, j]`` the one vector ``j`` has, ``reps[slot, q]`` a
    vector with the ``q``-th, ``nrep[slot]`` how many (a noise set repeats each across its corners)."""
    for slot in range(3):
        lo = 0 if slot == 0 else (3 if slot == 1 else 5)
        hi = 3 if slot == 0 else (5 if slot == 1 else 7)
        m = 0
        for j in range(c):
            found = -1
            for q in range(m):
                r = reps[slot, q]
                same = True
                for a_ in range(lo, hi):
                    same = same and NZ[zi, r, a_] == NZ[zi, j, a_]
                if same:
                    found = q
                    break
            if found < 0:
                reps[slot, m] = j
                found = m
                m += 1
            ids[slot, j] = found
        nrep[slot] = m


@njit(cache=True, error_model="numpy")
def _pair_tables(B, NZ, zi, reps, nrep, CT, TW, TT):
    """Per distinct chord difference ``q`` the measured chord's length and frame (``CT[q]``: r, C, F1, F2)
    and per distinct tilt each end's tilted tangent (``TW[q]``, ``TT[q]``), as :func:`_controller_J3`
    computes them (the true poses of rows W, TIP, DW, DT, E1W, E1T, MB)."""
    for q in range(nrep[0]):
        j = reps[0, q]
        for i in range(3):
            B[PT, i] = B[TIP, i] + NZ[zi, j, i]
        c0, c1, c2 = B[PT, 0] - B[W, 0], B[PT, 1] - B[W, 1], B[PT, 2] - B[W, 2]
        r = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        B[C, 0], B[C, 1], B[C, 2] = c0 / r, c1 / r, c2 / r
        _perp_rows(B, C, F1, F2)
        CT[q, 0] = r
        for i in range(3):
            CT[q, 1 + i] = B[C, i]
            CT[q, 4 + i] = B[F1, i]
            CT[q, 7 + i] = B[F2, i]
    for q in range(nrep[1]):
        j = reps[1, q]
        _tilt(B, DW, NZ[zi, j, 3], NZ[zi, j, 4], E1W, DWN)
        for i in range(3):
            TW[q, i] = B[DWN, i]
    for q in range(nrep[2]):
        j = reps[2, q]
        _tilt(B, DT, NZ[zi, j, 5], NZ[zi, j, 6], E1T, DTN)
        for i in range(3):
            TT[q, i] = B[DTN, i]


@njit(cache=True, error_model="numpy")
def _corner_inputs(ids, j0, nb, CT, TW, TT, Z):
    """Per noise vector ``j0 + jj`` (``jj < nb``) its chord's length and frame and its tilted tangents (from
    :func:`_pair_tables`) and their projections ``xw, yw, xt, yt`` on the chord frame (the operations of
    :func:`_controller_J3`), into column ``jj`` of the block ``Z``."""
    for jj in range(nb):
        j = j0 + jj
        q, u, v = ids[0, j], ids[1, j], ids[2, j]
        f10, f11, f12 = CT[q, 4], CT[q, 5], CT[q, 6]
        f20, f21, f22 = CT[q, 7], CT[q, 8], CT[q, 9]
        w0, w1, w2 = TW[u, 0], TW[u, 1], TW[u, 2]
        t0, t1, t2 = TT[v, 0], TT[v, 1], TT[v, 2]
        Z[ZR * CS + jj] = CT[q, 0]
        Z[ZXW * CS + jj] = w0 * f10 + w1 * f11 + w2 * f12
        Z[ZYW * CS + jj] = w0 * f20 + w1 * f21 + w2 * f22
        Z[ZXT * CS + jj] = t0 * f10 + t1 * f11 + t2 * f12
        Z[ZYT * CS + jj] = t0 * f20 + t1 * f21 + t2 * f22
        Z[ZC * CS + jj], Z[(ZC + 1) * CS + jj], Z[(ZC + 2) * CS + jj] = CT[q, 1], CT[q, 2], CT[q, 3]
        Z[ZF1 * CS + jj], Z[(ZF1 + 1) * CS + jj], Z[(ZF1 + 2) * CS + jj] = f10, f11, f12
        Z[ZF2 * CS + jj], Z[(ZF2 + 1) * CS + jj], Z[(ZF2 + 2) * CS + jj] = f20, f21, f22
        Z[ZDW * CS + jj], Z[(ZDW + 1) * CS + jj], Z[(ZDW + 2) * CS + jj] = w0, w1, w2
        Z[ZDT * CS + jj], Z[(ZDT + 1) * CS + jj], Z[(ZDT + 2) * CS + jj] = t0, t1, t2


@njit(cache=True, error_model="numpy")
def _fast_corners(Z, nb, w0, w1, w2, L):
    """The controller's ``Jhat`` of every noise vector of the block ``Z`` (``nb`` of them) whose estimate takes
    the shortcuts (:func:`_estimate` with ``fast``, then :func:`_estimated_J3`, finite) into rows ZJ, and
    row ZFL 1.0 there, 0.0 where :func:`_controller_J3` must run instead. The same operations in the same
    order as those two functions (the same numbers to the bit), written as one loop over the noise
    vectors without calls, early returns or branches: the compiler vectorizes it, and the vectors' long
    chains of divisions and square roots overlap instead of waiting on each other."""
    for j in range(nb):
        r = Z[(ZR) * CS + j]
        xw, yw, xt, yt = Z[(ZXW) * CS + j], Z[(ZYW) * CS + j], Z[(ZXT) * CS + j], Z[(ZYT) * CS + j]
        s11 = xw * xw + xt * xt
        s22 = yw * yw + yt * yt
        s12 = xw * yw + xt * yt
        y2, x2 = 2.0 * s12, s11 - s22
        h2 = math.sqrt(y2 * y2 + x2 * x2)
        ok = (h2 > 0.0) & (r > 0.0) & (r < math.inf)
        c2 = x2 / h2
        # _estimate's two branches as selects: 1 - c2 == 1 + |c2| exactly for c2 < 0
        pos = c2 >= 0.0
        sq = math.sqrt(0.5 * (1.0 + abs(c2)))
        first = sq if pos else math.copysign(sq, y2)
        other = y2 / h2 / (2.0 * first)
        cp = sq if pos else other
        sp = other if pos else first
        n0 = cp * Z[(ZF1) * CS + j] + sp * Z[(ZF2) * CS + j]
        n1 = cp * Z[(ZF1 + 1) * CS + j] + sp * Z[(ZF2 + 1) * CS + j]
        n2 = cp * Z[(ZF1 + 2) * CS + j] + sp * Z[(ZF2 + 2) * CS + j]
        e0, e1, e2 = Z[(ZC) * CS + j], Z[(ZC + 1) * CS + j], Z[(ZC + 2) * CS + j]
        yw_ = Z[(ZDW) * CS + j] * n0 + Z[(ZDW + 1) * CS + j] * n1 + Z[(ZDW + 2) * CS + j] * n2
        xw_ = Z[(ZDW) * CS + j] * e0 + Z[(ZDW + 1) * CS + j] * e1 + Z[(ZDW + 2) * CS + j] * e2
        yt_ = Z[(ZDT) * CS + j] * n0 + Z[(ZDT + 1) * CS + j] * n1 + Z[(ZDT + 2) * CS + j] * n2
        xt_ = Z[(ZDT) * CS + j] * e0 + Z[(ZDT + 1) * CS + j] * e1 + Z[(ZDT + 2) * CS + j] * e2
        sphi, cphi = 0.0, 1.0  # r > 0 where ok
        ok = ok & (xw_ > 0.0) & (xt_ > 0.0)
        s0 = yw_ / xw_
        sL = yt_ / xt_
        den = sL - s0
        ok = ok & (abs(den) > 1e-4)
        a = L * (2 * sL + s0) / den
        a = a if (math.isfinite(a) & (den != 0)) else math.nan
        fp = 2 * (s0 - sL) / (a * (a - L))
        fp = fp if math.isfinite(fp) else math.nan
        ym = -fp * a * a * (a - L) ** 2 / (3 * L)
        p20 = 0.0 + a * sphi + ym * cphi
        p21 = 0.0 + a * cphi + ym * -sphi
        te = fp * a / L
        hp = math.sqrt(p20 * p20 + p21 * p21)
        ok = ok & (hp > 0.0) & (hp < math.inf)
        ct, st = p21 / hp, p20 / hp
        po0 = w0 + p20 * n0 + p21 * e0
        po1 = w1 + p20 * n1 + p21 * e1
        po2 = w2 + p20 * n2 + p21 * e2
        t0 = te * (ct * n0 - st * e0)
        t1 = te * (ct * n1 - st * e1)
        t2 = te * (ct * n2 - st * e2)
        ok = ok & (0.0 < a) & (a < L) & (0.0 < abs(te) * L * L) & (abs(te) * L * L < 1.5)
        r2 = (po0 - w0) ** 2 + (po1 - w1) ** 2 + (po2 - w2) ** 2
        sb_ = abs(te) * (L - a) ** 2 / 3.0
        ok = ok & (abs(a * a * (1.0 + sb_ * sb_) - r2) <= 1e-12 * r2)
        # _estimated_J3(B, a, te, sqrt(r2), L, Jh)
        rho = math.sqrt(r2)
        tau = abs(te)
        b = L - a
        s = tau * b * b / 3.0
        gg = 1.0 + s * s
        dgg = -(4.0 * tau * b / 3.0) * s
        a_rho = 2.0 * rho / (2.0 * a * gg + a * a * dgg)
        beta_a = -(2.0 * tau * b / 3.0) / gg
        q = 1.0 / math.sqrt(gg)
        cb, sb = q, s * q
        u0, u1, u2 = (po0 - w0) / rho, (po1 - w1) / rho, (po2 - w2) / rho
        n0, n1, n2 = t0 / tau, t1 / tau, t2 / tau
        c1 = L * cb / rho
        c2 = L * sb / rho
        c3 = L * beta_a * a_rho
        v0 = -sb * u0 + cb * n0
        v1 = -sb * u1 + cb * n1
        v2 = -sb * u2 + cb * n2
        h0 = 1.0 - c1 * (1.0 - u0 * u0) + c2 * u0 * n0 - c3 * v0 * u0
        h1 = 0.0 - c1 * (0.0 - u0 * u1) + c2 * u0 * n1 - c3 * v0 * u1
        h2_ = 0.0 - c1 * (0.0 - u0 * u2) + c2 * u0 * n2 - c3 * v0 * u2
        h3 = 0.0 - c1 * (0.0 - u1 * u0) + c2 * u1 * n0 - c3 * v1 * u0
        h4 = 1.0 - c1 * (1.0 - u1 * u1) + c2 * u1 * n1 - c3 * v1 * u1
        h5 = 0.0 - c1 * (0.0 - u1 * u2) + c2 * u1 * n2 - c3 * v1 * u2
        h6 = 0.0 - c1 * (0.0 - u2 * u0) + c2 * u2 * n0 - c3 * v2 * u0
        h7 = 0.0 - c1 * (0.0 - u2 * u1) + c2 * u2 * n1 - c3 * v2 * u1
        h8 = 1.0 - c1 * (1.0 - u2 * u2) + c2 * u2 * n2 - c3 * v2 * u2
        Z[(ZJ + 0) * CS + j], Z[(ZJ + 1) * CS + j], Z[(ZJ + 2) * CS + j] = h0, h1, h2_
        Z[(ZJ + 3) * CS + j], Z[(ZJ + 4) * CS + j], Z[(ZJ + 5) * CS + j] = h3, h4, h5
        Z[(ZJ + 6) * CS + j], Z[(ZJ + 7) * CS + j], Z[(ZJ + 8) * CS + j] = h6, h7, h8
        ok = (ok & math.isfinite(h0) & math.isfinite(h1) & math.isfinite(h2_) & math.isfinite(h3) & math.isfinite(h4)
              & math.isfinite(h5) & math.isfinite(h6) & math.isfinite(h7) & math.isfinite(h8))
        Z[ZFL * CS + j] = 1.0 if ok else 0.0


@njit(cache=True, error_model="numpy")
def _corner_maps(Z, nb, J, k):
    """``M = J Jhat^-1`` of every noise vector of the block ``Z`` (``Jhat`` in rows ZJ; errplan.linalg.inv3's
    cofactors and the product's operations in their order) into rows ZM; row ZBAD 1.0 where ``Jhat`` is
    singular (errplan.linalg.singular3 at RCOND_INV) or ``M`` not finite; the bounds of :func:`_gnorm_bound`
    at gain ``k`` (row ZGB) and inside :func:`_phi_bound` (row ZPB), the same operations. One loop over
    the noise vectors, vectorized as :func:`_fast_corners`."""
    j00, j01, j02 = J[0, 0], J[0, 1], J[0, 2]
    j10, j11, j12 = J[1, 0], J[1, 1], J[1, 2]
    j20, j21, j22 = J[2, 0], J[2, 1], J[2, 2]
    for j in range(nb):
        a00, a01, a02 = Z[(ZJ + 0) * CS + j], Z[(ZJ + 1) * CS + j], Z[(ZJ + 2) * CS + j]
        a10, a11, a12 = Z[(ZJ + 3) * CS + j], Z[(ZJ + 4) * CS + j], Z[(ZJ + 5) * CS + j]
        a20, a21, a22 = Z[(ZJ + 6) * CS + j], Z[(ZJ + 7) * CS + j], Z[(ZJ + 8) * CS + j]
        c00 = a11 * a22 - a12 * a21
        c01 = a12 * a20 - a10 * a22
        c02 = a10 * a21 - a11 * a20
        det = a00 * c00 + a01 * c01 + a02 * c02
        r = math.nan if det == 0.0 else 1.0 / det
        i00 = c00 * r
        i10 = c01 * r
        i20 = c02 * r
        i01 = (a02 * a21 - a01 * a22) * r
        i11 = (a00 * a22 - a02 * a20) * r
        i21 = (a01 * a20 - a00 * a21) * r
        i02 = (a01 * a12 - a02 * a11) * r
        i12 = (a02 * a10 - a00 * a12) * r
        i22 = (a00 * a11 - a01 * a10) * r
        f = _sumsq9(a00, a01, a02, a10, a11, a12, a20, a21, a22)
        sing = not abs(det) > RCOND_INV * f * math.sqrt(f)
        m00 = j00 * i00 + j01 * i10 + j02 * i20
        m01 = j00 * i01 + j01 * i11 + j02 * i21
        m02 = j00 * i02 + j01 * i12 + j02 * i22
        m10 = j10 * i00 + j11 * i10 + j12 * i20
        m11 = j10 * i01 + j11 * i11 + j12 * i21
        m12 = j10 * i02 + j11 * i12 + j12 * i22
        m20 = j20 * i00 + j21 * i10 + j22 * i20
        m21 = j20 * i01 + j21 * i11 + j22 * i21
        m22 = j20 * i02 + j21 * i12 + j22 * i22
        Z[ZM * CS + j], Z[(ZM + 1) * CS + j], Z[(ZM + 2) * CS + j] = m00, m01, m02
        Z[(ZM + 3) * CS + j], Z[(ZM + 4) * CS + j], Z[(ZM + 5) * CS + j] = m10, m11, m12
        Z[(ZM + 6) * CS + j], Z[(ZM + 7) * CS + j], Z[(ZM + 8) * CS + j] = m20, m21, m22
        fin = (math.isfinite(m00) & math.isfinite(m01) & math.isfinite(m02) & math.isfinite(m10)
               & math.isfinite(m11) & math.isfinite(m12) & math.isfinite(m20) & math.isfinite(m21)
               & math.isfinite(m22))
        Z[ZBAD * CS + j] = 1.0 if (sing | (not fin)) else 0.0
        Z[ZGB * CS + j] = _gbound9(m00, m01, m02, m10, m11, m12, m20, m21, m22, k)
        tr = m00 + m11 + m22
        f = _sumsq9(m00, m01, m02, m10, m11, m12, m20, m21, m22)
        pb = _gbound9(m00, m01, m02, m10, m11, m12, m20, m21, m22, tr / f)
        Z[ZPB * CS + j] = pb if ((tr > 0.0) & (f > 0.0)) else 2.0


@njit(cache=True, error_model="numpy", inline="always")
def _sumsq9(a00, a01, a02, a10, a11, a12, a20, a21, a22):
    """The squared Frobenius norm of a 3 x 3 matrix given by its entries, summed in one fixed order (row by
    row; inlined, so the figures are those of the sums written out in place)."""
    f = 0.0
    f += a00 * a00
    f += a01 * a01
    f += a02 * a02
    f += a10 * a10
    f += a11 * a11
    f += a12 * a12
    f += a20 * a20
    f += a21 * a21
    f += a22 * a22
    return f


@njit(cache=True, error_model="numpy")
def _gbound9(m00, m01, m02, m10, m11, m12, m20, m21, m22, k):
    """:func:`_gnorm_bound` of the map with entries ``m..``: the Gershgorin bound of ``G^T G``, widened."""
    g00, g01, g02 = 1.0 - k * m00, -k * m01, -k * m02
    g10, g11, g12 = -k * m10, 1.0 - k * m11, -k * m12
    g20, g21, g22 = -k * m20, -k * m21, 1.0 - k * m22
    a00 = g00 * g00 + g10 * g10 + g20 * g20
    a11 = g01 * g01 + g11 * g11 + g21 * g21
    a22 = g02 * g02 + g12 * g12 + g22 * g22
    a01 = abs(g00 * g01 + g10 * g11 + g20 * g21)
    a02 = abs(g00 * g02 + g10 * g12 + g20 * g22)
    a12 = abs(g01 * g02 + g11 * g12 + g21 * g22)
    r = max(a00 + a01 + a02, max(a01 + a11 + a12, a02 + a12 + a22))
    return math.sqrt(r) * (1.0 + 1e-12)


@njit(cache=True, error_model="numpy")
def _gnorm(Ms, j, k):
    """``||I - k Ms[j]||_2`` (errplan.linalg.g_norm3's arithmetic, without a view)."""
    return _smax3(1.0 - k * Ms[j, 0, 0], -k * Ms[j, 0, 1], -k * Ms[j, 0, 2],
                  -k * Ms[j, 1, 0], 1.0 - k * Ms[j, 1, 1], -k * Ms[j, 1, 2],
                  -k * Ms[j, 2, 0], -k * Ms[j, 2, 1], 1.0 - k * Ms[j, 2, 2])


@njit(cache=True, error_model="numpy")
def _gnorm_bound(Ms, j, k):
    """An upper bound of ``||I - k Ms[j]||_2``: the square root of the largest Gershgorin row sum of
    ``G^T G`` (its largest eigenvalue is at most that), widened by 1e-12 against rounding (:func:`_gbound9`).
    Tight where ``G^T G`` is nearly diagonal, as near a good controller."""
    return _gbound9(Ms[j, 0, 0], Ms[j, 0, 1], Ms[j, 0, 2], Ms[j, 1, 0], Ms[j, 1, 1], Ms[j, 1, 2],
                    Ms[j, 2, 0], Ms[j, 2, 1], Ms[j, 2, 2], k)


@njit(cache=True, error_model="numpy")
def _g_worst(Ms, c, k, bound, floor):
    """``max_j ||I - k Ms[j]||`` over ``j < c``, exact (errplan.linalg's closed form) only where the bound
    ``bound[j]`` (:func:`_gnorm_bound`'s, at ``k``) could beat the best so far; ``floor`` where that maximum
    is not above it. The bound is never below the norm, so the result is the maximum whatever the order."""
    top = 0
    for j in range(c):
        if bound[j] > bound[top]:
            top = j
    best = floor
    if bound[top] > best:
        best = max(best, _gnorm(Ms, top, k))
    for j in range(c):
        if j != top and bound[j] > best:
            best = max(best, _gnorm(Ms, j, k))
    return best


@njit(cache=True, error_model="numpy")
def _phi_bound(Ms, j, tight):
    """An upper bound of ``|phi_max|`` of ``Ms[j]`` (kernels.metrics.phi_bound's argument): ``asin`` of a
    bound of ``||I - k M||`` at ``k = tr(M) / ||M||_F^2`` below 1 (:func:`_gnorm_bound`, or with ``tight``
    the exact norm), else pi."""
    tr = Ms[j, 0, 0] + Ms[j, 1, 1] + Ms[j, 2, 2]
    f = 0.0
    for a_ in range(3):
        for b_ in range(3):
            f += Ms[j, a_, b_] * Ms[j, a_, b_]
    if not (tr > 0.0 and f > 0.0):
        return math.pi
    gb = _gnorm(Ms, j, tr / f) * (1.0 + 1e-12) if tight else _gnorm_bound(Ms, j, tr / f)
    return math.asin(gb) if gb < 1.0 else math.pi


@njit(cache=True, error_model="numpy")
def _phi_worst(Ms, c, pb, floor):
    """``max_j phi_max3(Ms[j])`` over ``j < c``, exact where a bound (:func:`_phi_bound`'s, the cheap one first
    from its norm bound ``pb[j]``, then the tight one) could beat the best exact value so far; ``floor``
    where that maximum is not above ``floor`` (a caller that keeps only a value above its best)."""
    top = 0
    for j in range(c):  # asin is increasing: the largest norm bound gives the largest angle bound
        if pb[j] > pb[top]:
            top = j
    best = floor
    for q in range(-1, c):
        j = top if q < 0 else q
        if q >= 0 and j == top:
            continue
        # pb[j] below sin(best) by more than rounding: asin(pb[j]) < best, the cheap bound fails (no asin)
        if 0.0 <= best < 1.5 and pb[j] < math.sin(best) * (1.0 - 1e-9):
            continue
        if not (math.asin(pb[j]) if pb[j] < 1.0 else math.pi) > best:
            continue
        if not _phi_bound(Ms, j, True) > best:
            continue
        best = max(best, phi_max3(Ms[j]))
    return best


@njit(cache=True, error_model="numpy")
def _g_argmax(Ms, c, k, bound):
    """``(max_j ||I - k Ms[j]||, j)`` over ``j < c``, ``j`` the first corner attaining it (numpy's argmax),
    exact only where the bound ``bound[j]`` (:func:`_gnorm_bound`'s, widened: above the norm, so a corner
    that ties the maximum is evaluated too) could reach the best so far."""
    top = 0
    for j in range(c):
        if bound[j] > bound[top]:
            top = j
    best = _gnorm(Ms, top, k)
    jb = top
    for j in range(c):
        if j != top and bound[j] >= best:
            v = _gnorm(Ms, j, k)
            if v > best or (v == best and j < jb):
                best, jb = v, j
    return best, jb


@njit(cache=True, error_model="numpy")
def flexion_tips(Wt, Tt, Pt, ok, NZ, est, L, k, want_M, want_gp, gfloor, pfloor, out_M, out_g, out_p):
    """Per pair ``i`` (true wrist ``Wt[i]``, world load ``Tt[i]``, port ``Pt[i]``; ``ok[i]`` its truth is
    valid, cleared here where some noise vector gives a singular or non-finite ``M``): ``M = J Jhat^-1``
    over the noise vectors ``NZ`` ((1, c, 7) shared or (n, c, 7) per pair) into ``out_M[i]`` (``want_M``;
    NaN for an invalid pair), the worst ``||I - k[i] M||`` over them (``k`` (1,) or (n,)) into ``out_g[i]``
    (``want_gp`` 1 or 2) and the worst ``|phi_max|`` into ``out_p[i]`` (``want_gp`` 2); NaN for an invalid
    pair. ``want_gp`` 3: the worst corner of a valid pair instead, its norm into ``out_g[i]``, its index (the
    first attaining it) into ``out_p[i]`` and its map into ``out_M[i, 0]`` (untouched for an invalid pair).
    ``gfloor``, ``pfloor`` ((n,), or (1,) for all): a caller that keeps a worst value only where it
    exceeds these gets the floor itself where it does not (-inf: always the worst; inf: not computed), and
    the exact norms and angles are computed only where their bounds exceed the best so far."""
    n = Wt.shape[0]
    c = NZ.shape[1]
    S = np.zeros((8, 3, 3))
    B = np.zeros((ROWS, 3))
    J = np.empty((3, 3))
    Jh = np.empty((3, 3))
    Ms = np.empty((c, 3, 3))
    Zk = np.empty((2, 16, 2))
    Zv = np.empty((2, 16, 3))
    cnt = np.zeros(2, np.int64)
    last = np.empty(4)
    Z = np.empty(ZROWS * CS)
    gb = np.empty(c)
    pb = np.empty(c)
    ids = np.empty((3, c), np.int64)
    reps = np.empty((3, c), np.int64)
    nrep = np.zeros(3, np.int64)
    CT = np.empty((c, 10))
    TW = np.empty((c, 3))
    TT = np.empty((c, 3))
    if NZ.shape[0] == 1:
        _noise_index(NZ, 0, c, ids, reps, nrep)
    for i in range(3):
        B[EST, i] = est[i]
    for i in range(n):
        good = ok[i]
        if good:
            for a_ in range(3):
                B[W, a_], B[T, a_], B[P, a_] = Wt[i, a_], Tt[i, a_], Pt[i, a_]
            _jacobian3(B, W, P, T, L, J, S)
            _true_poses(B, L)
            zi = i if NZ.shape[0] > 1 else 0
            ki = k[i] if k.shape[0] > 1 else k[0]
            cnt[0] = cnt[1] = 0
            last[0] = math.nan
            if NZ.shape[0] > 1:
                _noise_index(NZ, zi, c, ids, reps, nrep)
            _pair_tables(B, NZ, zi, reps, nrep, CT, TW, TT)
            for j0 in range(0, c, CS):
                nb = min(CS, c - j0)
                _corner_inputs(ids, j0, nb, CT, TW, TT, Z)
                _fast_corners(Z, nb, B[W, 0], B[W, 1], B[W, 2], L)
                for jj in range(nb):
                    if Z[ZFL * CS + jj] == 0.0:  # the general estimate (_controller_J3 from this vector's chord)
                        last[0] = math.nan
                        _controller_J3(B, NZ, zi, j0 + jj, L, Jh, S, Zk, Zv, cnt, last)
                        for a_ in range(3):
                            for b_ in range(3):
                                Z[(ZJ + 3 * a_ + b_) * CS + jj] = Jh[a_, b_]
                _corner_maps(Z, nb, J, ki)
                for jj in range(nb):
                    if Z[ZBAD * CS + jj] != 0.0:  # a singular Jhat or a non-finite M: the pair is not valid
                        good = False
                        break
                    j = j0 + jj
                    for a_ in range(3):
                        for b_ in range(3):
                            Ms[j, a_, b_] = Z[(ZM + 3 * a_ + b_) * CS + jj]
                    gb[j] = Z[ZGB * CS + jj]
                    pb[j] = Z[ZPB * CS + jj]
                if not good:
                    break
        ok[i] = good
        if want_M:
            for j in range(c):
                for a_ in range(3):
                    for b_ in range(3):
                        out_M[i, j, a_, b_] = Ms[j, a_, b_] if good else math.nan
        if want_gp > 0:
            if not good:
                out_g[i] = math.nan
                out_p[i] = math.nan
                continue
            ki = k[i] if k.shape[0] > 1 else k[0]
            if want_gp == 3:  # the worst corner: its norm, index and map
                g_, jb = _g_argmax(Ms, c, ki, gb)
                out_g[i], out_p[i] = g_, float(jb)
                for a_ in range(3):
                    for b_ in range(3):
                        out_M[i, 0, a_, b_] = Ms[jb, a_, b_]
                continue
            gf = gfloor[i] if gfloor.shape[0] > 1 else gfloor[0]
            out_g[i] = _g_worst(Ms, c, ki, gb, gf) if gf < math.inf else gf
            pf = pfloor[i] if pfloor.shape[0] > 1 else pfloor[0]
            out_p[i] = _phi_worst(Ms, c, pb, pf) if want_gp == 2 else math.nan
