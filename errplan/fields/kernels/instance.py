"""The physics of one error instance: ``M = J Jhat^-1`` of the rigid lever and the flexed shaft, planar
(conformal parts) and spatial, one at a time (:func:`_instance2`, :func:`_instance3`) and straight
shafts in bulk (:func:`_levers2`, :func:`_levers3`), and the cheap exact tests of a tip that fails
(:func:`_corners_out2`, :func:`_lever_out`)."""
from __future__ import annotations

import math

from ...jit import njit
from ...kinematics.urdf.chain import map_geometry, map_state
from ...linalg import inv3
from .reach import _planar_reachable

NEWTON = 8  # Newton iterations of the beam's port-position equation (as kinematics.shaft)
RCOND = 1e-12  # a controller Jacobian with |det| <= RCOND * scale is singular: the tip is invalid


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


# ----------------------------------------------------------------------------- one instance
# Numba increfs the parent of every array view it creates (an atomic operation), so the hot path
# below takes whole arrays and indices and works on scalars: no view per call.
@njit(cache=True, error_model="numpy")
def _flexed_parts2(w0, w1, p0, p1, L, t, a):
    """Conformal parts (mr, mi, nr, ni) of the planar flexed-shaft ``d tip / d w``
    (kinematics.shaft.flexed_jacobian) at constant port and ``t``; ``a`` the port's position along
    the chord."""
    dy, dz = p0 - w0, p1 - w1
    rho = math.sqrt(dy * dy + dz * dz)
    theta = math.atan2(dy, dz)
    b = L - a
    s = t * b * b / 3.0
    phi = theta + math.atan(s)
    u0, u1 = math.sin(theta), math.cos(theta)
    n0, n1 = math.cos(theta), -math.sin(theta)
    q0, q1 = math.cos(phi), -math.sin(phi)
    gg = 1.0 + s * s
    dgg = -(4.0 * t * b / 3.0) * s
    beta_p = -(2.0 * t * b / 3.0) / gg
    a_p = 2.0 * rho / (2.0 * a * gg + a * a * dgg)
    g0 = -n0 / rho - beta_p * a_p * u0
    g1 = -n1 / rho - beta_p * a_p * u1
    j00, j01 = 1.0 + L * q0 * g0, L * q0 * g1
    j10, j11 = L * q1 * g0, 1.0 + L * q1 * g1
    return 0.5 * (j00 + j11), 0.5 * (j10 - j01), 0.5 * (j00 - j11), 0.5 * (j01 + j10)


@njit(cache=True, error_model="numpy")
def _flexed_J3(V, iw, ip, it, L, a, J, S):
    """Spatial flexed shaft ``d tip / d w`` (3 x 3 into ``J``) at constant port ``p = V[ip]`` and constant
    world load ``tvec = V[it]``, wrist ``w = V[iw]`` (docs/physics.md "Flexed shaft in 3-D"; the derivation
    is kinematics.shaft.flexed_jacobian's). ``S`` is a (6, 3, 3) scratch array. Rows of one array, not
    views: a view costs an atomic reference count per call."""
    rho = math.sqrt((V[ip, 0] - V[iw, 0]) ** 2 + (V[ip, 1] - V[iw, 1]) ** 2 + (V[ip, 2] - V[iw, 2]) ** 2)
    for i in range(3):
        S[0, 0, i] = (V[ip, i] - V[iw, i]) / rho  # u
    ut = S[0, 0, 0] * V[it, 0] + S[0, 0, 1] * V[it, 1] + S[0, 0, 2] * V[it, 2]
    for i in range(3):
        S[0, 1, i] = V[it, i] - ut * S[0, 0, i]  # t_perp
    tau = math.sqrt(S[0, 1, 0] ** 2 + S[0, 1, 1] ** 2 + S[0, 1, 2] ** 2)
    for i in range(3):
        S[0, 2, i] = S[0, 1, i] / tau  # n
    for i in range(3):  # Du = d u / d w = -(I - u u^T) / rho
        for j in range(3):
            S[1, i, j] = -((1.0 if i == j else 0.0) - S[0, 0, i] * S[0, 0, j]) / rho
    for j in range(3):  # Dtp = d t_perp / d w = -(u.t) Du - u (t^T Du)
        tDu = V[it, 0] * S[1, 0, j] + V[it, 1] * S[1, 1, j] + V[it, 2] * S[1, 2, j]
        for i in range(3):
            S[2, i, j] = -ut * S[1, i, j] - S[0, 0, i] * tDu
    for j in range(3):  # d tau / d w
        S[4, 0, j] = S[0, 2, 0] * S[2, 0, j] + S[0, 2, 1] * S[2, 1, j] + S[0, 2, 2] * S[2, 2, j]
    for i in range(3):  # Dn
        for j in range(3):
            S[3, i, j] = (S[2, i, j] - S[0, 2, i] * S[4, 0, j]) / tau
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
        v = -sb * S[0, 0, i] + cb * S[0, 2, i]
        for j in range(3):
            dbeta = -beta_a * a_rho * S[0, 0, j] + beta_tau * S[4, 0, j]
            J[i, j] = (1.0 if i == j else 0.0) + L * (v * dbeta + cb * S[1, i, j] + sb * S[3, i, j])


# One error instance: ``M = J Jhat^-1`` at tip ``x`` into ``Mb[jm]`` (d x d), :func:`_instance2` in the
# plane, :func:`_instance3` in 3-D; ``(ok, w0, w1, w2)``: ``ok`` False where the shaft does not pass the
# port, the controller's Jacobian is singular or (planar) the arm cannot place the wrist; in 3-D the wrist
# ``w`` is returned and the caller checks its reachability (:func:`reach_point`) unless :func:`_tip_reach`
# certified the tip. ``S`` (8, 3, 3) and ``V`` (9, 3) are scratch (``V`` zeros at first: rows 1, 7, 8 keep
# what :func:`_instance3` reuses between calls).
#
# :func:`_instance3` is the only kernel forced inline: a call would reference-count every array argument,
# which costs more than the arithmetic in the 3-D search (about 10 % of a spatial field without it).
# Every other kernel here was inline too; that doubled the first run's compile for no measurable run time.
# The callers branch on the dimension themselves (``if d == 2: _instance2(...) else: _instance3(...)``
# with ``d`` a constant): numba inlines an ``inline="always"`` function before it prunes the branches of
# the inlined code, so a dispatching ``instance(d, ...)`` forced inline made the planar kernels inline
# (and then drop) the whole 3-D instance at every call site, about 2 s of compile each.
#
# Why the 3-D reachability check is the caller's: an inlined function that takes the chain and the
# reachability map (ten arrays) and uses them behind a branch keeps their reference counts (atomic
# increments) on every call even when the branch is never taken; that doubled the cost of a certified
# tip (benchmarks/fields.py).


@njit(cache=True, error_model="numpy")
def _straight2(x0, x1, e0, e1, r, L):
    """Straight planar shaft at tip x, port->tip vector e (|e| = r): the lever's wrist and J's conformal
    parts (kinematics.shaft.lever_parts): mu = 1 - L/(2 rho), nu = -(L/(2 rho)) n_c^2 with
    n_c = (e_z - i e_y)/r and rho = |p - w| = L - r on the line. ``(w0, w1, m1r, m1i, n1r, n1i)``."""
    ir = 1.0 / r
    w0 = x0 - L * e0 * ir
    w1 = x1 - L * e1 * ir
    h = L / (2.0 * (L - r))
    return w0, w1, 1.0 - h, 0.0, -h * (e1 * e1 - e0 * e0) * ir * ir, 2.0 * h * e0 * e1 * ir * ir


@njit(cache=True, error_model="numpy")
def _est_inverse2(est0, est1, w0, w1, L):
    """The controller's lever through the estimate at wrist w (mu2 real, nu2 = -h2 (d_z - i d_y)^2 /
    rho^2): whether Jhat is regular (|det| > RCOND times its scale) and the conformal parts of Jhat^-1,
    (conj(mu2), -nu2) / det: ``(regular, imr, inr, ini)``."""
    dy, dz = est0 - w0, est1 - w1
    rho2 = dy * dy + dz * dz
    h2 = L / (2.0 * math.sqrt(rho2))
    m2 = 1.0 - h2
    n2r = -h2 * (dz * dz - dy * dy) / rho2
    n2i = 2.0 * h2 * dz * dy / rho2
    nn2 = n2r * n2r + n2i * n2i
    det = m2 * m2 - nn2
    return abs(det) > RCOND * (m2 * m2 + nn2), m2 / det, -n2r / det, -n2i / det


@njit(cache=True, error_model="numpy")
def _compose2(m1r, m1i, n1r, n1i, imr, inr, ini):
    """M = J Jhat^-1 from the conformal parts of J and of Jhat^-1 (mu = mu1 imu + nu1 conj(inu),
    nu = mu1 inu + nu1 conj(imu)): its entries ``(M00, M01, M10, M11)``."""
    mr = m1r * imr + n1r * inr + n1i * ini
    mi = m1i * imr + n1i * inr - n1r * ini
    nr = m1r * inr - m1i * ini + n1r * imr
    ni = m1r * ini + m1i * inr + n1i * imr
    return mr + nr, ni - mi, mi + ni, mr - nr


@njit(cache=True, error_model="numpy")
def _gnorm2(a00, a01, a10, a11, k):
    """||I - k M||_2 of a planar M: |1 - k mu| + k |nu| from its conformal parts."""
    mr = 0.5 * (a00 + a11)
    mi = 0.5 * (a10 - a01)
    nr = 0.5 * (a00 - a11)
    ni = 0.5 * (a01 + a10)
    return math.sqrt((1.0 - k * mr) ** 2 + (k * mi) ** 2) + k * math.sqrt(nr * nr + ni * ni)


@njit(cache=True, error_model="numpy")
def _instance2(x, theta, base_port, est, L, arm, Mb, jm, S, V, known):
    """The planar instance: conformal parts of J and Jhat in real arithmetic (``known``: the tip's
    wrists are certified reachable, :func:`_tip_reach2`)."""
    if True:
        # Conformal parts (errplan.metrics) in real arithmetic: mu = mr + i mi, nu = nr + i ni.
        p0, p1 = base_port[0] + theta[0], base_port[1] + theta[1]
        e0, e1 = x[0] - p0, x[1] - p1
        r = math.sqrt(e0 * e0 + e1 * e1)
        if not (r > 1e-9 and r < L):
            return False
        t = theta[2]
        if t == 0.0:
            w0, w1, m1r, m1i, n1r, n1i = _straight2(x[0], x[1], e0, e1, r, L)
            if not (known or _planar_reachable(arm, w0, w1)):
                return False
        else:
            b = _solve_b(r, L, t)
            a = L - b
            phi = math.atan2(e0, e1) - math.atan(t * a * b / 3.0)
            w0 = x[0] - L * math.sin(phi)
            w1 = x[1] - L * math.cos(phi)
            if not (known or _planar_reachable(arm, w0, w1)):
                return False
            m1r, m1i, n1r, n1i = _flexed_parts2(w0, w1, p0, p1, L, t, a)
        regular, imr, inr, ini = _est_inverse2(est[0], est[1], w0, w1, L)
        if not regular:
            return False
        Mb[jm, 0, 0], Mb[jm, 0, 1], Mb[jm, 1, 0], Mb[jm, 1, 1] = _compose2(m1r, m1i, n1r, n1i, imr, inr, ini)
        return True
    return False


@njit(cache=True, error_model="numpy")
def _lever3(x0, x1, x2, e0, e1, e2, r, est0, est1, est2, L):
    """Straight 3-D shaft at tip x, port->tip vector e (|e| = r) (docs/physics.md "Lever in 3-D"):
    J = I - s P, P = I - u u^T, u = e / r and s = L / (L - r) on the line; Jhat = I - sh Ph through the
    estimate, so Jhat^-1 = I + c Ph with c = sh / (1 - sh) (P is a projector): no inversion. Jhat is
    singular when det(Jhat) = (1 - sh)^2 is below RCOND times its scale ||Jhat||_F^3 ~ (1 + 2 (1 - sh)^2)^1.5.
    ``(regular, w0, w1, w2, u0, u1, u2, v0, v1, v2, s, c, u.v, |u x v|)``."""
    ir = 1.0 / r
    u0, u1, u2 = e0 * ir, e1 * ir, e2 * ir
    w0, w1, w2 = x0 - L * u0, x1 - L * u1, x2 - L * u2
    s_ = L / (L - r)
    d0, d1, d2 = est0 - w0, est1 - w1, est2 - w2
    rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    sh = L / rho
    one = 1.0 - sh
    sc = 1.0 + 2.0 * one * one
    regular = one * one > RCOND * (sc * math.sqrt(sc))  # (a power call would not vectorize in _levers3)
    c = sh / one
    v0, v1, v2 = d0 / rho, d1 / rho, d2 / rho
    uv = u0 * v0 + u1 * v1 + u2 * v2
    n0, n1, n2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
    sv = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    return regular, w0, w1, w2, u0, u1, u2, v0, v1, v2, s_, c, uv, sv


@njit(cache=True, error_model="numpy")
def _lever_block3(s_, c, uv, sv):
    """The lever's M in reduced form (:func:`gval`): its 2 x 2 block on span{u, v} in the basis (u, e)
    and its value along u x v."""
    oms = 1.0 - s_
    return 1.0 + c * sv * sv, -c * sv * uv, -oms * c * sv * uv, oms * (1.0 + c * uv * uv), oms * (1.0 + c)


@njit(cache=True, error_model="numpy")
def _gval_block(b00, b01, b10, b11, b4, k):
    """``||I - k M||_2`` from the reduced form: ``max(|1 - k b4|, sigma_max(I - k B))``, the 2 x 2 value by
    its conformal parts (|mu| + |nu|)."""
    g00 = 1.0 - k * b00
    g01 = -k * b01
    g10 = -k * b10
    g11 = 1.0 - k * b11
    a = 0.5 * (g00 + g11)
    b = 0.5 * (g10 - g01)
    c = 0.5 * (g00 - g11)
    e = 0.5 * (g01 + g10)
    return max(abs(1.0 - k * b4), math.sqrt(a * a + b * b) + math.sqrt(c * c + e * e))


@njit(cache=True, error_model="numpy", inline="always")
def _instance3(x, theta, base_port, est, L, Mb, Pb, jm, S, V, full):
    """The spatial instance: the 3-D lever in closed form, or the flexed shaft under a load.

    The lever's ``M`` also goes into ``Pb[jm]`` in reduced form (:func:`gval`): ``n = u x v`` is a
    singular vector of ``I - k M`` for every k (``P n = Ph n = n``), so ``I - k M`` splits into
    ``1 - k (1 - s)(1 + c)`` along n and a 2 x 2 block on span{u, v}; in the basis (u, e) of that
    plane (``v = (u.v) u + |u x v| e``) ``P = diag(0, 1)``, ``Ph = w w^T`` with ``w = (-|u x v|, u.v)``,
    so the block of M is ``[[1 + c sv^2, -c sv cu], [-(1 - s) c sv cu, (1 - s)(1 + c cu^2)]]``
    (``cu = u.v``, ``sv = |u x v|``). Under a load ``Pb[jm, 0]`` is NaN (the full 3 x 3 form). The
    lever's full ``M`` is written only with ``full`` (|phi_max| and the motion maps need it; ||G|| at
    any gain needs only ``Pb``)."""
    p0, p1, p2 = base_port[0] + theta[0], base_port[1] + theta[1], base_port[2] + theta[2]
    e0, e1, e2 = x[0] - p0, x[1] - p1, x[2] - p2
    r = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    if not (r > 1e-9 and r < L):
        return False, 0.0, 0.0, 0.0
    tau = theta[3]
    if tau == 0.0:
        regular, w0, w1, w2, u0, u1, u2, v0, v1, v2, s_, c, uv, sv = _lever3(
            x[0], x[1], x[2], e0, e1, e2, r, est[0], est[1], est[2], L)
        if not regular:
            return False, 0.0, 0.0, 0.0
        # M = (I - s P)(I + c Ph) = I + c Ph - s P - s c P Ph, with P Ph = I - u u^T - v v^T + (u.v) u v^T
        sc = s_ * c
        for i in range(3 if full else 0):
            ui = u0 if i == 0 else (u1 if i == 1 else u2)
            vi = v0 if i == 0 else (v1 if i == 1 else v2)
            for j in range(3):
                uj = u0 if j == 0 else (u1 if j == 1 else u2)
                vj = v0 if j == 0 else (v1 if j == 1 else v2)
                dij = 1.0 if i == j else 0.0
                P = dij - ui * uj
                Ph = dij - vi * vj
                PPh = dij - ui * uj - vi * vj + uv * ui * vj
                Mb[jm, i, j] = dij + c * Ph - s_ * P - sc * PPh
        Pb[jm, 0], Pb[jm, 1], Pb[jm, 2], Pb[jm, 3], Pb[jm, 4] = _lever_block3(s_, c, uv, sv)
        return True, w0, w1, w2
    Pb[jm, 0] = math.nan
    # A lateral load: the bending plane holds the port->tip line e1 and e2(psi); in it the planar
    # beam with load tau (docs/physics.md): chord c = cos(alpha) e1 - sin(alpha) e2, wrist x - L c.
    p = V[0]
    w = V[2]
    tvec = V[3]
    e1v = V[4]
    f1 = V[5]
    f2 = V[6]
    p[0], p[1], p[2] = p0, p1, p2
    # The parts that do not depend on the load direction psi are kept in V from the previous loaded
    # instance and reused where their inputs are the same numbers (the sampled directions of one port
    # and load follow each other): the basis from e (V[1]: its key), the beam's b and angle from
    # (r, tau, L) (V[7]: key r, tau, b; V[8]: cos, sin, L). The same arithmetic on the same inputs:
    # the same values. V starts at zero, which no loaded instance matches (r > 0, tau != 0).
    ek = V[1]
    if not (ek[0] == e0 and ek[1] == e1 and ek[2] == e2):
        e1v[0], e1v[1], e1v[2] = e0 / r, e1 / r, e2 / r
        _perp_basis(e1v, f1, f2)
        ek[0], ek[1], ek[2] = e0, e1, e2
    cp, sp = math.cos(theta[4]), math.sin(theta[4])
    bk = V[7]
    ak = V[8]
    if bk[0] == r and bk[1] == tau and ak[2] == L:
        b, ca, sa = bk[2], ak[0], ak[1]
    else:
        b = _solve_b(r, L, tau)
        al = math.atan(tau * (L - b) * b / 3.0)
        ca, sa = math.cos(al), math.sin(al)
        bk[0], bk[1], bk[2] = r, tau, b
        ak[0], ak[1], ak[2] = ca, sa, L
    a = L - b
    for i in range(3):
        w[i] = x[i] - L * (ca * e1v[i] - sa * (cp * f1[i] + sp * f2[i]))
    # world load: tau along the normal of the wrist->port line toward the chord
    rho = math.sqrt((p[0] - w[0]) ** 2 + (p[1] - w[1]) ** 2 + (p[2] - w[2]) ** 2)
    cu = 0.0
    for i in range(3):
        cu += (ca * e1v[i] - sa * (cp * f1[i] + sp * f2[i])) * (p[i] - w[i]) / rho
    nn = 0.0
    for i in range(3):
        ci = ca * e1v[i] - sa * (cp * f1[i] + sp * f2[i])
        tvec[i] = ci - cu * (p[i] - w[i]) / rho
        nn += tvec[i] * tvec[i]
    nn = math.sqrt(nn)
    for i in range(3):
        tvec[i] = tau * tvec[i] / nn
    J = S[5]
    Jh = S[6]
    Jinv = S[7]
    _flexed_J3(V, 2, 0, 3, L, a, J, S)
    _lever_J(w, est, L, Jh)
    det = inv3(Jh, Jinv)
    scale = 0.0
    for i in range(3):
        for j in range(3):
            scale += Jh[i, j] * Jh[i, j]
    if not abs(det) > RCOND * scale ** 1.5:
        return False, 0.0, 0.0, 0.0
    for i in range(3):
        for j in range(3):
            Mb[jm, i, j] = J[i, 0] * Jinv[0, j] + J[i, 1] * Jinv[1, j] + J[i, 2] * Jinv[2, j]
    return True, w[0], w[1], w[2]


# ----------------------------------------------------------------------------- straight shafts in bulk
# The sampled instances of a rigid shaft (no lateral load) at one tip, all at once: one loop over the
# instances' port offsets (structure of arrays: ``G`` (d, n), a row per coordinate) with no branch, which
# LLVM vectorizes (four instances per AVX2 instruction; the scalar helpers it calls, _straight2 ...
# _gval_block, are inlined by LLVM): about 23 ns an instance in 3-D against 125 ns one by one through
# _instance3 and gval. The helpers are those of _instance2 / _instance3 and gval, so the values are the
# same to the last bit. Reachability stays the caller's (a tip's certificate, or the exact test per wrist).


@njit(cache=True, error_model="numpy")
def _levers2(XS, G, n, base_port, est, L, k, O, ok):
    """Planar straight-shaft instances ``j < n``, tip ``XS[:, j]`` and port offset ``G[:, j]``: ``O[0]``
    ||G|| at gain k (:func:`gnorm`), ``O[1:3]`` the wrist, ``O[3:7]`` M (00, 01, 10, 11); ``ok`` the
    shaft reaches the tip through the port and Jhat is regular (:func:`_instance2`'s tests but
    reachability)."""
    b0, b1 = base_port[0], base_port[1]
    for j in range(n):
        x0, x1 = XS[0, j], XS[1, j]
        p0, p1 = b0 + G[0, j], b1 + G[1, j]
        e0, e1 = x0 - p0, x1 - p1
        r = math.sqrt(e0 * e0 + e1 * e1)
        w0, w1, m1r, m1i, n1r, n1i = _straight2(x0, x1, e0, e1, r, L)
        regular, imr, inr, ini = _est_inverse2(est[0], est[1], w0, w1, L)
        ok[j] = (r > 1e-9) & (r < L) & regular
        a00, a01, a10, a11 = _compose2(m1r, m1i, n1r, n1i, imr, inr, ini)
        O[0, j] = _gnorm2(a00, a01, a10, a11, k)
        O[1, j] = w0
        O[2, j] = w1
        O[3, j] = a00
        O[4, j] = a01
        O[5, j] = a10
        O[6, j] = a11


@njit(cache=True, error_model="numpy")
def _levers3(XS, G, n, base_port, est, L, k, O, ok):
    """Spatial straight-shaft instances ``j < n`` as :func:`_levers2`'s: ``O[0]`` ||G|| at gain k
    (:func:`gval`'s reduced form), ``O[1:4]`` the wrist. The full M is not formed (the search takes
    :func:`_instance3` where it needs M)."""
    b0, b1, b2 = base_port[0], base_port[1], base_port[2]
    for j in range(n):
        x0, x1, x2 = XS[0, j], XS[1, j], XS[2, j]
        p0, p1, p2 = b0 + G[0, j], b1 + G[1, j], b2 + G[2, j]
        e0, e1, e2 = x0 - p0, x1 - p1, x2 - p2
        r = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        regular, w0, w1, w2, u0, u1, u2, v0, v1, v2, s_, c, uv, sv = _lever3(
            x0, x1, x2, e0, e1, e2, r, est[0], est[1], est[2], L)
        ok[j] = (r > 1e-9) & (r < L) & regular
        b00, b01, b10, b11, b4 = _lever_block3(s_, c, uv, sv)
        O[0, j] = _gval_block(b00, b01, b10, b11, b4, k)
        O[1, j] = w0
        O[2, j] = w1
        O[3, j] = w2


@njit(cache=True, error_model="numpy")
def _corners_out2(x, grid, corners, base_port, L, arm):
    """True when one of the planar straight samples ``grid[corners]`` (the port box's corners) certainly
    fails at tip ``x``: the shaft misses the port or the wrist is out of reach (the exact test). The
    tip is then invalid, as the search would find at that sample; the extreme wrists first, before
    anything else is computed (most tips outside the robust workspace fail here)."""
    for c in range(corners.shape[0]):
        j = corners[c]
        e0 = x[0] - (base_port[0] + grid[j, 0])
        e1 = x[1] - (base_port[1] + grid[j, 1])
        r = math.sqrt(e0 * e0 + e1 * e1)
        if not (r > 1e-9 and r < L):
            return True
        w0, w1, _, _, _, _ = _straight2(x[0], x[1], e0, e1, r, L)  # the instance's wrist, to the last bit
        if not _planar_reachable(arm, w0, w1):
            return True
    return False


@njit(cache=True, error_model="numpy")
def _lever_out(x, grid, base_port, L, rmap):
    """True when some unloaded sampled instance (``grid[j, 3] == 0`` or no load axis) certainly fails at
    tip ``x`` (3-D): the shaft misses the port (the instance's own test) or its lever wrist lies off
    the reachability map or in a voxel certified out (:func:`reach_point`'s first answers). The
    cheapest exact test of an uncertified tip, before any instance is computed: the tip is then
    invalid, as the search would find at that instance."""
    na = grid.shape[1]
    geo = map_geometry(rmap)
    mst = rmap.state
    for j in range(grid.shape[0]):
        if na > 3 and grid[j, 3] != 0.0:
            continue
        e0 = x[0] - (base_port[0] + grid[j, 0])
        e1 = x[1] - (base_port[1] + grid[j, 1])
        e2 = x[2] - (base_port[2] + grid[j, 2])
        r = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        if not (r > 1e-9 and r < L):
            return True
        ir = 1.0 / r  # the wrist in _instance3's arithmetic, to the last bit
        u0, u1, u2 = e0 * ir, e1 * ir, e2 * ir
        if map_state(geo, mst, x[0] - L * u0, x[1] - L * u1, x[2] - L * u2)[0] == 0:
            return True
    return False
