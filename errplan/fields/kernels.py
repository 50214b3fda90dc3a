"""Compiled field kernels (numba): the worst case of ``||I - k J Jhat^-1||``, ``|phi_max|`` and
``rho*`` over a bounded error set, tip by tip, for the planar arm (``d = 2``, closed forms through
conformal parts) and for any URDF arm (``d = 3``).

One search serves both dimensions; only the physics of one error instance (:func:`instance`)
branches on ``d``. The search is the method of :mod:`errplan.fields` (the numpy reference in
:mod:`.search`): the error box sampled on a grid, the worst sample refined by a coordinate
pattern search (step halved ``refine`` times, polls a box face clips skipped, further passes while
the worst case still climbs), and a second local maximum of the sample grid refined as well when
it could overtake the first. A tip is valid only if every evaluated instance reaches it.

Error parameters ``theta``: planar ``(dy, dz, t)`` (port offset, lateral tip load over EI in the
shaft frame, signed); spatial ``(dx, dy, dz, tau, psi)`` (port offset, lateral load magnitude and
its direction angle around the port->tip line, periodic). Compiled once and cached on disk
(``cache=True``): later runs pay no compile cost.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..kinematics.urdf import reach_point
from ..linalg import g_norm3, inv3, phi_max3

NEWTON = 8  # Newton iterations of the beam's port-position equation (as kinematics.shaft)
RCOND = 1e-12  # a controller Jacobian with |det| <= RCOND * scale is singular: the tip is invalid


# ----------------------------------------------------------------------------- planar pieces
@njit(cache=True, error_model="numpy")
def _planar_reachable(arm, w0, w1):
    """Exact reachability of wrist ``[w0, w1]`` by P1's arm (both elbow branches inside the limits).

    ``arm = [base_y, base_z, l1, l2, h1, h2, q1lo, q1hi, q2lo, q2hi, sum_lo, sum_hi, cos h1, sin h1,
    cos h2, sin h2]``; the same arithmetic as :meth:`errplan.kinematics.arm.Arm.reachable`.
    """
    dy = w0 - arm[0]
    dz = w1 - arm[1]
    l1, l2 = arm[2], arm[3]
    c = (dy * dy + dz * dz - l1 * l1 - l2 * l2) / (2.0 * l1 * l2)
    if not (c >= -1.0 and c <= 1.0):
        return False
    sn = math.sqrt(1.0 - c * c)
    ch1, sh1, ch2, sh2 = arm[12], arm[13], arm[14], arm[15]
    tol = 1e-12
    for sgn in (1.0, -1.0):
        s_d = sgn * sn
        q2 = math.atan2(s_d * ch2 - c * sh2, c * ch2 + s_d * sh2)
        if not (arm[8] - tol <= q2 <= arm[9] + tol):
            continue
        vz, vy = l1 + l2 * c, l2 * s_d
        rz, ry = dz * vz + dy * vy, dy * vz - dz * vy
        q1 = math.atan2(ry * ch1 - rz * sh1, rz * ch1 + ry * sh1)
        s = q1 + q2
        if (arm[6] - tol <= q1 <= arm[7] + tol and arm[8] - tol <= q2 <= arm[9] + tol
                and arm[10] - tol <= s <= arm[11] + tol):
            return True
    return False


@njit(cache=True, error_model="numpy")
def _solve_b(r, L, t):
    """Tip-side length ``b`` of the flexed shaft from ``r^2 = b^2 (1 + (t a b / 3)^2)``, ``a = L - b``."""
    b = r
    for _ in range(NEWTON):
        a = L - b
        c = t * a * b / 3.0
        h = 1.0 + c * c
        dc = t * (a - b) / 3.0
        f = b * b * h - r * r
        b = b - f / (2.0 * b * h + b * b * 2.0 * c * dc)
    return b


@njit(cache=True, error_model="numpy")
def _lever_J(w, p, L, J):
    """Rigid lever ``d tip / d w = I - (L/rho)(I - u u^T)`` (d x d) into ``J``; returns ``rho``."""
    d = w.shape[0]
    rho2 = 0.0
    for i in range(d):
        rho2 += (p[i] - w[i]) ** 2
    rho = math.sqrt(rho2)
    s = L / rho
    for i in range(d):
        ui = (p[i] - w[i]) / rho
        for j in range(d):
            uj = (p[j] - w[j]) / rho
            J[i, j] = (1.0 - s if i == j else 0.0) + s * ui * uj
    return rho


@njit(cache=True, error_model="numpy")
def _flexed_J2(w, p, L, t, a, J):
    """Planar flexed shaft ``d tip / d w`` at constant port and ``t`` (kinematics.shaft.flexed_jacobian)."""
    dy, dz = p[0] - w[0], p[1] - w[1]
    rho = math.sqrt(dy * dy + dz * dz)
    theta = math.atan2(dy, dz)
    b = L - a
    s = t * b * b / 3.0
    phi = theta + math.atan(s)
    u0, u1 = math.sin(theta), math.cos(theta)
    n0, n1 = math.cos(theta), -math.sin(theta)
    np0, np1 = math.cos(phi), -math.sin(phi)
    gg = 1.0 + s * s
    dgg = -(4.0 * t * b / 3.0) * s
    beta_p = -(2.0 * t * b / 3.0) / gg
    a_p = 2.0 * rho / (2.0 * a * gg + a * a * dgg)
    g0 = -n0 / rho - beta_p * a_p * u0
    g1 = -n1 / rho - beta_p * a_p * u1
    J[0, 0] = 1.0 + L * np0 * g0
    J[0, 1] = L * np0 * g1
    J[1, 0] = L * np1 * g0
    J[1, 1] = 1.0 + L * np1 * g1


# ----------------------------------------------------------------------------- spatial pieces
@njit(cache=True, error_model="numpy")
def _perp_basis(e, f1, f2):
    """Unit vectors ``f1, f2`` completing unit ``e`` to a right-handed frame (continuous away from
    the axis e is nearest to)."""
    ax, ay, az = abs(e[0]), abs(e[1]), abs(e[2])
    if ax <= ay and ax <= az:
        r0, r1, r2 = 1.0, 0.0, 0.0
    elif ay <= az:
        r0, r1, r2 = 0.0, 1.0, 0.0
    else:
        r0, r1, r2 = 0.0, 0.0, 1.0
    c0 = e[1] * r2 - e[2] * r1
    c1 = e[2] * r0 - e[0] * r2
    c2 = e[0] * r1 - e[1] * r0
    n = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    f1[0], f1[1], f1[2] = c0 / n, c1 / n, c2 / n
    f2[0] = e[1] * f1[2] - e[2] * f1[1]
    f2[1] = e[2] * f1[0] - e[0] * f1[2]
    f2[2] = e[0] * f1[1] - e[1] * f1[0]


@njit(cache=True, error_model="numpy")
def _flexed_J3(w, p, L, tvec, a, J, S):
    """Spatial flexed shaft ``d tip / d w`` at constant port and constant world load ``tvec``
    (docs/physics.md "Flexed shaft in 3-D"; derivation in kinematics.shaft.flexed_jacobian).
    ``S`` is a (6, 3, 3) scratch array."""
    rho = 0.0
    for i in range(3):
        rho += (p[i] - w[i]) ** 2
    rho = math.sqrt(rho)
    u = S[0, 0]
    for i in range(3):
        u[i] = (p[i] - w[i]) / rho
    ut = u[0] * tvec[0] + u[1] * tvec[1] + u[2] * tvec[2]
    tp = S[0, 1]
    for i in range(3):
        tp[i] = tvec[i] - ut * u[i]
    tau = math.sqrt(tp[0] ** 2 + tp[1] ** 2 + tp[2] ** 2)
    n = S[0, 2]
    for i in range(3):
        n[i] = tp[i] / tau
    Du = S[1]  # d u / d w = -(I - u u^T) / rho
    for i in range(3):
        for j in range(3):
            Du[i, j] = -((1.0 if i == j else 0.0) - u[i] * u[j]) / rho
    Dtp = S[2]  # d t_perp / d w = -(u.t) Du - u (t^T Du)
    for j in range(3):
        tDu = tvec[0] * Du[0, j] + tvec[1] * Du[1, j] + tvec[2] * Du[2, j]
        for i in range(3):
            Dtp[i, j] = -ut * Du[i, j] - u[i] * tDu
    Dn = S[3]
    dtau = S[4, 0]
    for j in range(3):
        dtau[j] = n[0] * Dtp[0, j] + n[1] * Dtp[1, j] + n[2] * Dtp[2, j]
    for i in range(3):
        for j in range(3):
            Dn[i, j] = (Dtp[i, j] - n[i] * dtau[j]) / tau
    b = L - a
    s = tau * b * b / 3.0
    gg = 1.0 + s * s
    dgg = -(4.0 * tau * b / 3.0) * s
    Fa = 2.0 * a * gg + a * a * dgg
    a_rho = 2.0 * rho / Fa
    a_tau = -(a * a * 2.0 * s * b * b / 3.0) / Fa
    beta = math.atan(s)
    beta_a = -(2.0 * tau * b / 3.0) / gg
    beta_tau = (b * b / 3.0) / gg + beta_a * a_tau
    cb, sb = math.cos(beta), math.sin(beta)
    for i in range(3):
        v = -sb * u[i] + cb * n[i]
        for j in range(3):
            dbeta = beta_a * a_rho * (-u[j]) + beta_tau * dtau[j]
            J[i, j] = (1.0 if i == j else 0.0) + L * (v * dbeta + cb * Du[i, j] + sb * Dn[i, j])


# ----------------------------------------------------------------------------- one instance
@njit(cache=True, error_model="numpy")
def instance(x, theta, base_port, est, L, arm, chain, rmap, M, S, V, reach_known=False):
    """``M = J Jhat^-1`` (d x d, into ``M``) of one error instance at tip ``x``; False where the
    instance cannot reach the tip (shaft not through the port, wrist unreachable) or the
    controller's Jacobian is singular there. ``S`` (8, 3, 3) and ``V`` (8, 3) are scratch.
    ``reach_known``: the caller has certified that every wrist of the error set is reachable
    (:func:`_tip_reach`), so the per-instance check is skipped (3-D)."""
    d = x.shape[0]
    p = V[0]
    e = V[1]
    w = V[2]
    a = 0.0
    r2 = 0.0
    for i in range(d):
        p[i] = base_port[i] + theta[i]
        e[i] = x[i] - p[i]
        r2 += e[i] * e[i]
    r = math.sqrt(r2)
    if not (r > 1e-9 and r < L):
        return False
    J = S[5]
    Jh = S[6]
    if d == 2:
        t = theta[2]
        if t == 0.0:
            # Straight shaft: the lever's wrist, and J, Jhat through their conformal parts
            # (kinematics.shaft.lever_parts): mu = 1 - L/(2 rho), nu = -(L/(2 rho)) n_c^2.
            w0 = x[0] - L * e[0] / r
            w1 = x[1] - L * e[1] / r
            if not _planar_reachable(arm, w0, w1):
                return False
            h = L / (2.0 * (L - r))  # rho = |p - w| = L - r on the line
            nc = complex(e[1], -e[0]) / r
            mu1 = 1.0 - h
            nu1 = -h * nc * nc
        else:
            b = _solve_b(r, L, t)
            a = L - b
            phi = math.atan2(e[0], e[1]) - math.atan(t * a * b / 3.0)
            w0 = x[0] - L * math.sin(phi)
            w1 = x[1] - L * math.cos(phi)
            if not _planar_reachable(arm, w0, w1):
                return False
            w[0], w[1] = w0, w1
            _flexed_J2(w[:2], p[:2], L, t, a, J[:2, :2])
            mu1 = complex(0.5 * (J[0, 0] + J[1, 1]), 0.5 * (J[1, 0] - J[0, 1]))
            nu1 = complex(0.5 * (J[0, 0] - J[1, 1]), 0.5 * (J[0, 1] + J[1, 0]))
        dy, dz = est[0] - w0, est[1] - w1
        rho2 = dy * dy + dz * dz
        rho = math.sqrt(rho2)
        h = L / (2.0 * rho)
        nc = complex(dz, -dy)
        mu2 = 1.0 - h
        nu2 = -h * nc * nc / rho2
        det = mu2.real * mu2.real + mu2.imag * mu2.imag - (nu2.real * nu2.real + nu2.imag * nu2.imag)
        scale = mu2.real * mu2.real + mu2.imag * mu2.imag + nu2.real * nu2.real + nu2.imag * nu2.imag
        if not abs(det) > RCOND * scale:
            return False
        imu = mu2.conjugate() / det
        inu = -nu2 / det
        mu = mu1 * imu + nu1 * inu.conjugate()
        nu = mu1 * inu + nu1 * imu.conjugate()
        M[0, 0] = mu.real + nu.real
        M[1, 1] = mu.real - nu.real
        M[1, 0] = mu.imag + nu.imag
        M[0, 1] = nu.imag - mu.imag
        return True
    # d == 3
    tau = theta[3]
    if tau == 0.0:
        # Straight shaft (docs/physics.md "Lever in 3-D"): J = I - s P, P = I - u u^T, u = e / r and
        # s = L / (L - r) on the line; Jhat = I - sh Ph through the estimate, so
        # Jhat^-1 = I + c Ph with c = sh / (1 - sh) (P is a projector): no inversion.
        for i in range(3):
            w[i] = x[i] - L * e[i] / r
        if not reach_known and not reach_point(chain, rmap, w[0], w[1], w[2]):
            return False
        u0, u1, u2 = e[0] / r, e[1] / r, e[2] / r
        s_ = L / (L - r)
        d0, d1, d2 = est[0] - w[0], est[1] - w[1], est[2] - w[2]
        rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        sh = L / rho
        # det(Jhat) = (1 - sh)^2: singular relative to its scale ||Jhat||_F^3 ~ (1 + 2 (1 - sh)^2)^1.5
        one = 1.0 - sh
        if not one * one > RCOND * (1.0 + 2.0 * one * one) ** 1.5:
            return False
        c = sh / one
        u = V[3]
        v = V[4]
        u[0], u[1], u[2] = u0, u1, u2
        v[0], v[1], v[2] = d0 / rho, d1 / rho, d2 / rho
        P = S[5]
        Ph = S[6]
        for i in range(3):
            for j in range(3):
                dij = 1.0 if i == j else 0.0
                P[i, j] = dij - u[i] * u[j]
                Ph[i, j] = dij - v[i] * v[j]
        # M = (I - s P)(I + c Ph) = I + c Ph - s P - s c P Ph
        sc = s_ * c
        for i in range(3):
            for j in range(3):
                dij = 1.0 if i == j else 0.0
                M[i, j] = (dij + c * Ph[i, j] - s_ * P[i, j]
                           - sc * (P[i, 0] * Ph[0, j] + P[i, 1] * Ph[1, j] + P[i, 2] * Ph[2, j]))
        return True
    # A lateral load: the bending plane holds the port->tip line e1 and e2(psi); in it the planar
    # beam with load tau (docs/physics.md): chord c = cos(alpha) e1 - sin(alpha) e2, wrist x - L c.
    tvec = V[3]
    e1 = V[4]
    f1 = V[5]
    f2 = V[6]
    for i in range(3):
        e1[i] = e[i] / r
    _perp_basis(e1, f1, f2)
    cp, sp = math.cos(theta[4]), math.sin(theta[4])
    b = _solve_b(r, L, tau)
    a = L - b
    al = math.atan(tau * a * b / 3.0)
    ca, sa = math.cos(al), math.sin(al)
    for i in range(3):
        w[i] = x[i] - L * (ca * e1[i] - sa * (cp * f1[i] + sp * f2[i]))
    if not reach_known and not reach_point(chain, rmap, w[0], w[1], w[2]):
        return False
    # world load: tau along the normal of the wrist->port line toward the chord
    rho = 0.0
    for i in range(3):
        rho += (p[i] - w[i]) ** 2
    rho = math.sqrt(rho)
    cu = 0.0
    for i in range(3):
        cu += (ca * e1[i] - sa * (cp * f1[i] + sp * f2[i])) * (p[i] - w[i]) / rho
    nn = 0.0
    for i in range(3):
        ci = ca * e1[i] - sa * (cp * f1[i] + sp * f2[i])
        tvec[i] = ci - cu * (p[i] - w[i]) / rho
        nn += tvec[i] * tvec[i]
    nn = math.sqrt(nn)
    for i in range(3):
        tvec[i] = tau * tvec[i] / nn
    _flexed_J3(w, p, L, tvec, a, J, S)
    _lever_J(w, est, L, Jh)
    Jinv = S[4]
    det = inv3(Jh, Jinv)
    scale = 0.0
    for i in range(3):
        for j in range(3):
            scale += Jh[i, j] * Jh[i, j]
    if not abs(det) > RCOND * scale ** 1.5:
        return False
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for l in range(3):
                acc += J[i, l] * Jinv[l, j]
            M[i, j] = acc
    return True


@njit(cache=True, error_model="numpy")
def _tip_reach(x, base_port, lo, hi, L, rmap):
    """Reachability of every wrist the error set can need at tip ``x`` (3-D), from the map alone:
    1 all certified in, 0 all out (or off the map), 2 unknown (check instance by instance).

    Over the port box (centre ``pc``, half-diagonal ``delta``) the lever wrist
    ``w(p) = x - L (x - p)/|x - p|`` moves by at most ``(L / r_min) delta`` (its Jacobian in p has
    norm L/r), ``r_min = |x - pc| - delta``; a lateral load moves it off the lever wrist by at most
    ``L * atan(tau_max L^2 / 12)`` (the chord turns by ``atan(tau a b / 3)``, ``a b <= L^2 / 4``).
    """
    pc0 = base_port[0] + 0.5 * (lo[0] + hi[0])
    pc1 = base_port[1] + 0.5 * (lo[1] + hi[1])
    pc2 = base_port[2] + 0.5 * (lo[2] + hi[2])
    delta = 0.5 * math.sqrt((hi[0] - lo[0]) ** 2 + (hi[1] - lo[1]) ** 2 + (hi[2] - lo[2]) ** 2)
    e0, e1, e2 = x[0] - pc0, x[1] - pc1, x[2] - pc2
    r = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    rmin = r - delta
    if not (rmin > 0.0 and r < L):
        return 2
    R = L / rmin * delta + L * math.atan(max(abs(lo[3]), abs(hi[3])) * L * L / 12.0) + 1e-9
    w0, w1, w2 = x[0] - L * e0 / r, x[1] - L * e1 / r, x[2] - L * e2 / r
    h = rmap.h
    ilo = np.empty(3, np.int64)
    ihi = np.empty(3, np.int64)
    wc = (w0, w1, w2)
    n = 1
    for a in range(3):
        ilo[a] = int(math.floor((wc[a] - R - rmap.origin[a]) / h))
        ihi[a] = int(math.floor((wc[a] + R - rmap.origin[a]) / h))
        if ihi[a] < 0 or ilo[a] >= rmap.shape[a]:
            return 0  # the whole ball lies off the map: nothing there is reachable
        if ilo[a] < 0 or ihi[a] >= rmap.shape[a]:
            return 2
        n *= ihi[a] - ilo[a] + 1
    if n > 4096:
        return 2
    seen_in = False
    seen_out = False
    for i in range(ilo[0], ihi[0] + 1):
        for j in range(ilo[1], ihi[1] + 1):
            for k in range(ilo[2], ihi[2] + 1):
                st = rmap.state[i, j, k]
                if st == 1:
                    seen_in = True
                elif st == 0:
                    seen_out = True
                else:
                    return 2
                if seen_in and seen_out:
                    return 2
    return 1 if seen_in else 0


# ----------------------------------------------------------------------------- metrics of M
@njit(cache=True, error_model="numpy")
def gnorm(M, k):
    """``||I - k M||_2``: ``|1 - k mu| + k |nu|`` in the plane, the closed-form sigma_max in 3-D."""
    if M.shape[0] == 2:
        mr = 0.5 * (M[0, 0] + M[1, 1])
        mi = 0.5 * (M[1, 0] - M[0, 1])
        nr = 0.5 * (M[0, 0] - M[1, 1])
        ni = 0.5 * (M[0, 1] + M[1, 0])
        return math.sqrt((1.0 - k * mr) ** 2 + (k * mi) ** 2) + k * math.sqrt(nr * nr + ni * ni)
    return g_norm3(M, k)


@njit(cache=True, error_model="numpy")
def phimax(M):
    """Exact ``|phi_max|`` of ``M``: the conformal closed form in the plane, the S^2 method in 3-D."""
    if M.shape[0] == 2:
        mr = 0.5 * (M[0, 0] + M[1, 1])
        mi = 0.5 * (M[1, 0] - M[0, 1])
        amu = math.hypot(mr, mi)
        anu = math.hypot(0.5 * (M[0, 0] - M[1, 1]), 0.5 * (M[0, 1] + M[1, 0]))
        if not amu > 0.0:
            return math.pi
        ratio = anu / amu
        if not ratio < 1.0:
            return math.pi
        return min(math.pi, abs(math.atan2(mi, mr)) + math.asin(ratio))
    return phi_max3(M)


# ----------------------------------------------------------------------------- the search
@njit(cache=True, error_model="numpy")
def _poll_value(which, M, k):
    return gnorm(M, k) if which == 0 else phimax(M)


@njit(cache=True, error_model="numpy")
def _grid_index(j, counts, na, out):
    for ax in range(na - 1, -1, -1):
        out[ax] = j % counts[ax]
        j //= counts[ax]


@njit(cache=True, error_model="numpy")
def _neighbour(j, ax, off, counts, periodic, na):
    """Flat index of sample ``j`` moved ``off`` steps along axis ``ax``; -1 outside the box."""
    stride = 1
    for a2 in range(ax + 1, na):
        stride *= counts[a2]
    pos = (j // stride) % counts[ax]
    q = pos + off
    if periodic[ax]:
        q %= counts[ax]
    elif q < 0 or q >= counts[ax]:
        return -1
    return j + (q - pos) * stride


@njit(cache=True, error_model="numpy")
def _local_max(vals, j, counts, periodic, na):
    for ax in range(na):
        if counts[ax] < 2:
            continue
        for off in (-1, 1):
            q = _neighbour(j, ax, off, counts, periodic, na)
            if q >= 0 and vals[q] > vals[j]:
                return False
    return True


@njit(cache=True, error_model="numpy")
def _far(j, i, counts, periodic, na):
    """More than one grid step apart along some axis (periodic axes measured around the circle)."""
    stride = 1
    for ax in range(na - 1, -1, -1):
        pj = (j // stride) % counts[ax]
        pi = (i // stride) % counts[ax]
        dd = abs(pj - pi)
        if periodic[ax]:
            dd = min(dd, counts[ax] - dd)
        if dd > 1:
            return True
        stride *= counts[ax]
    return False


@njit(cache=True, error_model="numpy")
def _peak_raise(vals, j, counts, periodic, na):
    """Estimated gain of refining sample ``j``: per axis the parabola through it and its neighbours
    (one-sided on a face, where only a vertex inside the box counts), summed over the axes."""
    f0 = vals[j]
    out = 0.0
    for ax in range(na):
        s = counts[ax]
        if s < 2:
            continue
        jm = _neighbour(j, ax, -1, counts, periodic, na)
        jp = _neighbour(j, ax, 1, counts, periodic, na)
        if s == 2:
            r = abs(f0 - vals[jp if jp >= 0 else jm])
        elif jm >= 0 and jp >= 0:
            fm, fp = vals[jm], vals[jp]
            curv = 2 * f0 - fm - fp
            r = (fp - fm) ** 2 / (8 * curv) if curv > 0 else 0.0
        else:
            inward = 1 if jm < 0 else -1
            j1 = _neighbour(j, ax, inward, counts, periodic, na)
            j2 = _neighbour(j, ax, 2 * inward, counts, periodic, na)
            f1, f2 = vals[j1], vals[j2]
            c2 = 0.5 * (f0 - 2 * f1 + f2)
            bb = f0 - f1 + c2
            r = 0.0
            if c2 < 0:
                xv = -bb / (2 * c2)
                if -1 < xv < 0:
                    r = -bb * bb / (4 * c2)
        if not math.isfinite(r):
            return math.inf
        out += max(r, 0.0)
    return out


@njit(cache=True, error_model="numpy")
def _pattern(which, k, x, th, best, step0, lo, hi, active, periodic, refine, extra, base_port, est, L, arm,
             chain, rmap, M, S, V, cand, known):
    """Coordinate pattern search for the maximum of metric ``which`` (0: ||G|| at gain k, 1: |phi_max|)
    from ``th`` (updated in place) with value ``best``. Returns ``(best, ok)``; ``ok`` is False as
    soon as a polled instance cannot reach the tip (robust validity)."""
    na = th.shape[0]
    for pass_ in range(1 + extra):
        before = best
        for level in range(1, refine + 1):
            for ax in range(na):
                if not active[ax]:
                    continue
                h = step0[ax] / 2.0 ** level
                for sgn in (-1.0, 1.0):
                    for i in range(na):
                        cand[i] = th[i]
                    v = th[ax] + sgn * h
                    if periodic[ax]:
                        v = lo[ax] + (v - lo[ax]) % (hi[ax] - lo[ax])
                    else:
                        v = min(max(v, lo[ax]), hi[ax])
                        if v == th[ax]:
                            continue  # clipped back onto the centre: a worst case on the box face
                    cand[ax] = v
                    if not instance(x, cand, base_port, est, L, arm, chain, rmap, M, S, V, known):
                        return best, False
                    f = _poll_value(which, M, k)
                    if f > best:
                        best = f
                        for i in range(na):
                            th[i] = cand[i]
        if not best - before > 1e-7 * max(1.0, abs(best)):
            break
    return best, True


@njit(cache=True, error_model="numpy")
def _golden_gain(Ms, m, iters):
    """``min over k > 0 of max_i ||I - k M_i||`` by golden section (convex in k); ``(rho, k)``,
    ``(1, 0)`` where no gain contracts."""
    amax = 0.0
    for i in range(m):
        s = 0.0
        for a in range(Ms.shape[1]):
            for b in range(Ms.shape[2]):
                s += Ms[i, a, b] ** 2
        amax = max(amax, math.sqrt(s))
    kmax = 2.0 / amax if amax > 0 else 1.0
    gr = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = 0.0, kmax
    c, d = b - gr * (b - a), a + gr * (b - a)

    def f(kk):
        v = 0.0
        for i in range(m):
            v = max(v, gnorm(Ms[i], kk))
        return v

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
    kk = 0.5 * (a + b)
    rho = f(kk)
    if rho >= 1.0:
        return 1.0, 0.0
    return rho, kk


@njit(cache=True, error_model="numpy")
def worst_case_tile(X, grid, counts, active, periodic, lo, hi, step0, base_port, est, L, k, arm, chain, rmap,
                    refine, extra, second_start, want_phi, want_rho,
                    out_valid, out_g, out_p, out_rho, out_k):
    """Worst case at every tip ``X[i]`` (n, d) over the error set sampled at ``grid`` (m, na).

    Writes ``out_valid`` (robustly reachable), ``out_g`` (worst ||G|| at gain ``k``), ``out_p``
    (worst |phi_max|, if ``want_phi``), ``out_rho``/``out_k`` (rho*, k*, if ``want_rho``; rho*
    certified by a refined worst case at k*, the scenario gain used where it does better).
    """
    n, d = X.shape
    m, na = grid.shape
    vals_g = np.empty(m)
    vals_p = np.empty(m)
    Ms = np.empty((m, d, d))
    M = np.empty((d, d))
    S = np.zeros((8, 3, 3))
    V = np.zeros((8, 3))
    th = np.empty(na)
    cand = np.empty(na)
    for ii in range(n):
        x = X[ii]
        ok = True
        known = False
        if d == 3:
            tr = _tip_reach(x, base_port, lo, hi, L, rmap)
            ok = tr != 0
            known = tr == 1
        for j in range(m if ok else 0):
            if not instance(x, grid[j], base_port, est, L, arm, chain, rmap, Ms[j], S, V, known):
                ok = False
                break
            vals_g[j] = gnorm(Ms[j], k)
            vals_p[j] = phimax(Ms[j]) if want_phi else 0.0
        if not ok:
            out_valid[ii] = False
            out_g[ii] = np.nan
            out_p[ii] = np.nan
            out_rho[ii] = np.nan
            out_k[ii] = np.nan
            continue
        results = np.empty(2)
        for which in range(2 if want_phi else 1):
            vals = vals_g if which == 0 else vals_p
            jbest = 0
            for j in range(1, m):
                if vals[j] > vals[jbest]:
                    jbest = j
            # a second start: the best sampled local maximum more than one step from the worst
            j2 = -1
            if second_start > 0 and m > 1:
                for j in range(m):
                    if _far(j, jbest, counts, periodic, na) and _local_max(vals, j, counts, periodic, na):
                        if j2 < 0 or vals[j] > vals[j2]:
                            j2 = j
                if j2 >= 0:
                    v = vals[jbest]
                    if not (vals[j2] + 2.0 * _peak_raise(vals, j2, counts, periodic, na)
                            >= v - second_start * max(1.0, abs(v))):
                        j2 = -1
            best_all = -math.inf
            for start in (jbest, j2):
                if start < 0:
                    continue
                for i in range(na):
                    th[i] = grid[start, i]
                b, ok = _pattern(which, k, x, th, vals[start], step0, lo, hi, active, periodic, refine, extra,
                                 base_port, est, L, arm, chain, rmap, M, S, V, cand, known)
                if not ok:
                    break
                best_all = max(best_all, b)
            if not ok:
                break
            results[which] = best_all
        if not ok:
            out_valid[ii] = False
            out_g[ii] = np.nan
            out_p[ii] = np.nan
            out_rho[ii] = np.nan
            out_k[ii] = np.nan
            continue
        out_valid[ii] = True
        out_g[ii] = results[0]
        out_p[ii] = results[1] if want_phi else np.nan
        if want_rho:
            rs, ks = _golden_gain(Ms, m, 60)
            if ks > 0:
                # certify at k*: the refined worst case over the continuous set at that gain
                jbest = 0
                vbest = -1.0
                for j in range(m):
                    v = gnorm(Ms[j], ks)
                    if v > vbest:
                        vbest, jbest = v, j
                for i in range(na):
                    th[i] = grid[jbest, i]
                ref, ok = _pattern(0, ks, x, th, vbest, step0, lo, hi, active, periodic, refine, extra,
                                   base_port, est, L, arm, chain, rmap, M, S, V, cand, known)
                rs = max(rs, ref) if ok else 1.0
            else:
                rs = 1.0
            if results[0] < rs:  # the scenario gain does better
                rs, ks = results[0], k
            if rs >= 1.0:
                rs, ks = 1.0, 0.0
            out_rho[ii] = rs
            out_k[ii] = ks
        else:
            out_rho[ii] = np.nan
            out_k[ii] = np.nan


@njit(cache=True, error_model="numpy")
def motion_maps(X, TH, base_port, est, L, arm, chain, rmap, out_M, out_ok):
    """``M = J Jhat^-1`` (into ``out_M`` (n, d, d)) and validity (``out_ok`` (n,)) of instance
    ``TH[i]`` at tip ``X[i]``; invalid rows of ``out_M`` are NaN."""
    d = X.shape[1]
    S = np.zeros((8, 3, 3))
    V = np.zeros((8, 3))
    for i in range(X.shape[0]):
        ok = instance(X[i], TH[i], base_port, est, L, arm, chain, rmap, out_M[i], S, V, False)
        out_ok[i] = ok
        if not ok:
            for a in range(d):
                for b in range(d):
                    out_M[i, a, b] = np.nan
