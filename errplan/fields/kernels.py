"""Compiled field kernels (numba): the worst case of ``||I - k J Jhat^-1||``, ``|phi_max|`` and
``rho*`` over a bounded error set, tip by tip, for the planar arm (``d = 2``, closed forms through
conformal parts) and for any URDF arm (``d = 3``).

One search serves both dimensions; only the physics of one error instance (:func:`_instance2`, :func:`_instance3`)
branches on ``d``. The search is the method of :mod:`errplan.fields` (the numpy reference in
:mod:`.search`): the error box sampled on a grid, the worst sample refined by a coordinate
pattern search (step halved ``refine`` times, polls a box face clips skipped, further passes while
the worst case still climbs), and a second local maximum of the sample grid refined as well when
it could overtake the first. A tip is valid only if every evaluated instance reaches it.

Straight-shaft (unloaded) instances are also computed in bulk, many per vectorized loop
(:func:`_levers2`, :func:`_levers3`): a tip's samples at once, and, where no load axis is active, the
polls of many tips' worst-||G|| refinements at once (:func:`_pattern_lanes`). Same arithmetic, same
answers to the last bit, a fraction of the time.

Error parameters ``theta``: planar ``(dy, dz, t)`` (port offset, lateral tip load over EI in the
shaft frame, signed); spatial ``(dx, dy, dz, tau, psi)`` (port offset, lateral load magnitude and
its direction angle around the port->tip line, periodic). Compiled once and cached on disk
(``cache=True``): later runs pay no compile cost.
"""
from __future__ import annotations

import math

import numpy as np

from ..jit import copy_function, kernel_array, njit

from ..kinematics.urdf.chain import map_geometry, map_state, reach_boundary
from ..linalg import _smax3, inv3, phi_max3

NEWTON = 8  # Newton iterations of the beam's port-position equation (as kinematics.shaft)
LANE_TIPS = 256  # tips whose worst-||G|| refinements run together (_pattern_lanes): up to twice as many searches
RCOND = 1e-12  # a controller Jacobian with |det| <= RCOND * scale is singular: the tip is invalid


# ----------------------------------------------------------------------------- planar pieces
@njit(cache=True, error_model="numpy")
def _arc_class(x, y, n, cm, sm, chw):
    """Where the angle of the vector ``(x, y)`` (length ``n``) lies against an arc of half-width hw
    around m (``cm, sm = cos m, sin m``, ``chw = cos hw``), without an arctangent: 1 certainly inside,
    0 certainly outside, -1 too close to an end to say. The margin (1e-9 in the cosine, at least
    1e-9 rad in the angle) is far above the rounding of either test and the exact test's 1e-12 rad
    tolerance, so a certain answer is the exact test's answer."""
    cd = x * cm + y * sm
    if cd > (chw + 1e-9) * n:
        return 1
    if cd < (chw - 1e-9) * n:
        return 0
    return -1


@njit(cache=True, error_model="numpy")
def _planar_reachable(arm, w0, w1):
    """Exact reachability of wrist ``[w0, w1]`` by P1's arm (both elbow branches inside the limits).

    ``arm = [base_y, base_z, l1, l2, h1, h2, q1lo, q1hi, q2lo, q2hi, sum_lo, sum_hi, cos h1, sin h1,
    cos h2, sin h2]``; the same arithmetic as :meth:`errplan.kinematics.arm.Arm.reachable`. With the
    ten entries :func:`planar_arm_params` appends (per limit interval of q2, q1 and q1 + q2: cos and
    sin of its middle and cos of its half-width; then 1 where these apply) each angle is first
    placed against its interval by one dot product (:func:`_arc_class`); the arctangents run only for
    a branch that comes within about 1e-9 rad of a limit. Same answers, a fraction of the cost.
    """
    dy = w0 - arm[0]
    dz = w1 - arm[1]
    l1, l2 = arm[2], arm[3]
    c = (dy * dy + dz * dz - l1 * l1 - l2 * l2) / (2.0 * l1 * l2)
    if not (c >= -1.0 and c <= 1.0):
        return False
    sn = math.sqrt(1.0 - c * c)
    ch1, sh1, ch2, sh2 = arm[12], arm[13], arm[14], arm[15]
    fast = arm.shape[0] >= 26 and arm[25] == 1.0
    tol = 1e-12
    for sgn in (1.0, -1.0):
        s_d = sgn * sn
        x2, y2 = c * ch2 + s_d * sh2, s_d * ch2 - c * sh2
        vz, vy = l1 + l2 * c, l2 * s_d
        rz, ry = dz * vz + dy * vy, dy * vz - dz * vy
        x1, y1 = rz * ch1 + ry * sh1, ry * ch1 - rz * sh1
        if fast:
            n2 = math.sqrt(x2 * x2 + y2 * y2)
            k2 = _arc_class(x2, y2, n2, arm[16], arm[17], arm[18])
            if k2 == 0:
                continue
            n1 = math.sqrt(x1 * x1 + y1 * y1)
            k1 = _arc_class(x1, y1, n1, arm[19], arm[20], arm[21])
            if k1 == 0:
                continue
            # q1 + q2 stays inside (-pi, pi) (checked when the entries were made): the angle of the
            # product of the two rotations is the sum itself
            ks = _arc_class(x1 * x2 - y1 * y2, y1 * x2 + x1 * y2, n1 * n2, arm[22], arm[23], arm[24])
            if ks == 0:
                continue
            if k2 == 1 and k1 == 1 and ks == 1:
                return True
        q2 = math.atan2(y2, x2)
        if not (arm[8] - tol <= q2 <= arm[9] + tol):
            continue
        q1 = math.atan2(y1, x1)
        s = q1 + q2
        if (arm[6] - tol <= q1 <= arm[7] + tol and arm[8] - tol <= q2 <= arm[9] + tol
                and arm[10] - tol <= s <= arm[11] + tol):
            return True
    return False


@njit(cache=True, error_model="numpy")
def _cos_beta(rho, l1, l2):
    """cos of the angle at the base between link 1 and the base->wrist line (law of cosines)."""
    return min(1.0, max(-1.0, (rho * rho + l1 * l1 - l2 * l2) / (2.0 * l1 * rho)))


@njit(cache=True, error_model="numpy")
def _tip_reach2(x, base_port, lo, hi, L, arm):
    """Reachability of every wrist the error set can need at planar tip ``x``, certified at once:
    1 when some elbow branch keeps q2, q1 and q1 + q2 inside their limits, 1e-9 rad clear of them,
    for every wrist in the disc that holds all of them; else 2 (check instance by instance with
    :func:`_planar_reachable`, as before). Then each instance's exact test would say reachable: the
    same answers, without one reachability test per instance.

    The disc: centre the lever wrist through the box centre, radius ``(L / r_min) delta + L atan(t_max
    L^2 / 12)`` as :func:`_tip_reach`. Over it, with d the base->wrist vector (|d| in
    [rho_c - R, rho_c + R]): q2 = s acos(c(|d|)) - h2 (c the elbow's cosine, monotone in |d|),
    q1 = angle(d) - s beta(|d|) - h1 (angle(d) within asin(R / rho_c) of its centre value, beta the
    law-of-cosines angle, its cosine monotone on each side of sqrt(l1^2 - l2^2)), q1 + q2 within the
    sum of the two ranges. Centre values by the exact test's own arctangents (so the same branch of
    the angle), offsets by the monotone end values."""
    if not (arm.shape[0] >= 26 and arm[25] == 1.0):
        return 2
    pc0 = base_port[0] + 0.5 * (lo[0] + hi[0])
    pc1 = base_port[1] + 0.5 * (lo[1] + hi[1])
    delta = 0.5 * math.sqrt((hi[0] - lo[0]) ** 2 + (hi[1] - lo[1]) ** 2)
    e0, e1 = x[0] - pc0, x[1] - pc1
    r = math.sqrt(e0 * e0 + e1 * e1)
    rmin = r - delta
    if not (rmin > 0.0 and r < L):
        return 2
    tmax = max(abs(lo[2]), abs(hi[2])) if lo.shape[0] > 2 else 0.0
    R = L / rmin * delta + L * math.atan(tmax * L * L / 12.0) + 1e-9
    dy = x[0] - L * e0 / r - arm[0]
    dz = x[1] - L * e1 / r - arm[1]
    l1, l2 = arm[2], arm[3]
    rc = math.sqrt(dy * dy + dz * dz)
    if not rc > 2.0 * R:
        return 2
    ra, rb = rc - R, rc + R
    den = 2.0 * l1 * l2
    ca = (ra * ra - l1 * l1 - l2 * l2) / den
    cb = (rb * rb - l1 * l1 - l2 * l2) / den
    cc = (rc * rc - l1 * l1 - l2 * l2) / den
    if not (ca > -1.0 + 1e-9 and cb < 1.0 - 1e-9):
        return 2
    # beta over [ra, rb]: its cosine at the ends and at sqrt(l1^2 - l2^2) when that lies inside
    kb_lo = min(_cos_beta(ra, l1, l2), _cos_beta(rb, l1, l2))
    kb_hi = max(_cos_beta(ra, l1, l2), _cos_beta(rb, l1, l2))
    if l1 > l2:
        rs = math.sqrt(l1 * l1 - l2 * l2)
        if ra < rs < rb:
            kb_lo = min(kb_lo, _cos_beta(rs, l1, l2))
    bc = math.acos(_cos_beta(rc, l1, l2))
    db_lo, db_hi = math.acos(kb_hi) - bc, math.acos(kb_lo) - bc  # beta - beta_c
    gc = math.acos(cc)
    dg_lo, dg_hi = math.acos(cb) - gc, math.acos(ca) - gc  # acos(c) - acos(c_c): c grows with |d|
    dth = math.asin(R / rc)
    sn = math.sqrt(1.0 - cc * cc)
    ch1, sh1, ch2, sh2 = arm[12], arm[13], arm[14], arm[15]
    m = 1e-9
    for sgn in (1.0, -1.0):
        s_d = sgn * sn
        x2, y2 = cc * ch2 + s_d * sh2, s_d * ch2 - cc * sh2
        vz, vy = l1 + l2 * cc, l2 * s_d
        rz, ry = dz * vz + dy * vy, dy * vz - dz * vy
        x1, y1 = rz * ch1 + ry * sh1, ry * ch1 - rz * sh1
        q2 = math.atan2(y2, x2)
        q1 = math.atan2(y1, x1)
        if sgn > 0:
            q2lo, q2hi = q2 + dg_lo, q2 + dg_hi
            q1lo, q1hi = q1 - dth - db_hi, q1 + dth - db_lo
        else:
            q2lo, q2hi = q2 - dg_hi, q2 - dg_lo
            q1lo, q1hi = q1 - dth + db_lo, q1 + dth + db_hi
        if (arm[8] + m <= q2lo and q2hi <= arm[9] - m and arm[6] + m <= q1lo and q1hi <= arm[7] - m
                and arm[10] + m <= q1lo + q2lo and q1hi + q2hi <= arm[11] - m):
            return 1
    return 2


def planar_arm_params(arm) -> np.ndarray:
    """The planar arm as :func:`_planar_reachable` takes it: the sixteen entries it documents, then
    per limit interval [lo, hi] of q2, q1 and q1 + q2 ``cos m, sin m, cos hw`` (m its middle, hw its
    half-width) and a last 1.0 when the arctangent-free test is exact for these limits: every
    interval inside (-pi, pi) by 1e-5 and wider than 2e-3 rad, and q1 + q2 for any q1, q2 within
    their limits inside (-pi, pi) (else 0.0: the arctangents always run)."""
    q1, q2, qs = (tuple(map(float, arm.q1_limits)), tuple(map(float, arm.q2_limits)), tuple(map(float, arm.sum_limits)))
    out = [*arm.base, arm.l1, arm.l2, *arm.home, *q1, *q2, *qs,
           math.cos(arm.home[0]), math.sin(arm.home[0]), math.cos(arm.home[1]), math.sin(arm.home[1])]
    ok = True
    for lo, hi in (q2, q1, qs):
        m, hw = 0.5 * (lo + hi), 0.5 * (hi - lo)
        out += [math.cos(m), math.sin(m), math.cos(hw)]
        ok &= -math.pi + 1e-5 < lo and hi < math.pi - 1e-5 and 1e-3 < hw
    ok &= -math.pi + 1e-5 < q1[0] + q2[0] and q1[1] + q2[1] < math.pi - 1e-5
    out.append(1.0 if ok else 0.0)
    return np.array(out, float)


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
def _flexed_J3(w, p, L, tvec, a, J, S):
    """Spatial flexed shaft ``d tip / d w`` (3 x 3 into ``J``) at constant port ``p`` and constant
    world load ``tvec`` (docs/physics.md "Flexed shaft in 3-D"; the derivation is
    kinematics.shaft.flexed_jacobian's). ``S`` is a (6, 3, 3) scratch array."""
    rho = math.sqrt((p[0] - w[0]) ** 2 + (p[1] - w[1]) ** 2 + (p[2] - w[2]) ** 2)
    for i in range(3):
        S[0, 0, i] = (p[i] - w[i]) / rho  # u
    ut = S[0, 0, 0] * tvec[0] + S[0, 0, 1] * tvec[1] + S[0, 0, 2] * tvec[2]
    for i in range(3):
        S[0, 1, i] = tvec[i] - ut * S[0, 0, i]  # t_perp
    tau = math.sqrt(S[0, 1, 0] ** 2 + S[0, 1, 1] ** 2 + S[0, 1, 2] ** 2)
    for i in range(3):
        S[0, 2, i] = S[0, 1, i] / tau  # n
    for i in range(3):  # Du = d u / d w = -(I - u u^T) / rho
        for j in range(3):
            S[1, i, j] = -((1.0 if i == j else 0.0) - S[0, 0, i] * S[0, 0, j]) / rho
    for j in range(3):  # Dtp = d t_perp / d w = -(u.t) Du - u (t^T Du)
        tDu = tvec[0] * S[1, 0, j] + tvec[1] * S[1, 1, j] + tvec[2] * S[1, 2, j]
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
# certified the tip. ``S`` (8, 3, 3) and ``V`` (8, 3) are scratch.
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
    e1v[0], e1v[1], e1v[2] = e0 / r, e1 / r, e2 / r
    _perp_basis(e1v, f1, f2)
    cp, sp = math.cos(theta[4]), math.sin(theta[4])
    b = _solve_b(r, L, tau)
    a = L - b
    al = math.atan(tau * a * b / 3.0)
    ca, sa = math.cos(al), math.sin(al)
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
    _flexed_J3(w, p, L, tvec, a, J, S)
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


@njit(cache=True, error_model="numpy")
def _tip_reach(x, base_port, lo, hi, L, rmap):
    """Reachability of every wrist the error set can need at tip ``x`` (3-D), from the map alone:
    1 all certified in, 0 all out (or off the map), 2 unknown (check instance by instance).

    Over the port box (centre ``pc``, half-diagonal ``delta``) the lever wrist
    ``w(p) = x - L (x - p)/|x - p|`` moves by at most ``(L / r_min) delta`` (its Jacobian in p has
    norm L/r), ``r_min = |x - pc| - delta``; a lateral load moves it off the lever wrist by at most
    ``L * atan(tau_max L^2 / 12)`` (the chord turns by ``atan(tau a b / 3)``, ``a b <= L^2 / 4``).
    The voxels of the ball's bounding cube are certified at once when the map's ``depth`` at the
    voxel of its centre exceeds the cube's reach from it; else one by one (up to 4096 of them).
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
    geo = map_geometry(rmap)
    o0, o1, o2, h, s0, s1, s2 = geo
    mst = rmap.state
    # the voxel index ranges in scalars (no per-tip allocation)
    i0 = int(math.floor((w0 - R - o0) / h))
    i1 = int(math.floor((w0 + R - o0) / h))
    j0 = int(math.floor((w1 - R - o1) / h))
    j1 = int(math.floor((w1 + R - o1) / h))
    k0 = int(math.floor((w2 - R - o2) / h))
    k1 = int(math.floor((w2 + R - o2) / h))
    # axis by axis: the whole ball off the map (nothing there is reachable), else partly off
    if i1 < 0 or i0 >= s0:
        return 0
    if i0 < 0 or i1 >= s0:
        return 2
    if j1 < 0 or j0 >= s1:
        return 0
    if j0 < 0 or j1 >= s1:
        return 2
    if k1 < 0 or k0 >= s2:
        return 0
    if k0 < 0 or k1 >= s2:
        return 2
    # the voxel of w (inside the cube, so on the map) and its depth (ReachMap.depth): a cube within that
    # many steps of it is all of its state
    st, ci, cj, ck = map_state(geo, mst, w0, w1, w2)
    if ci < 0 or st == 2:
        return 2
    reach = max(max(ci - i0, i1 - ci), max(max(cj - j0, j1 - cj), max(ck - k0, k1 - ck)))
    if reach < rmap.depth[ci, cj, ck]:
        return 1 if st == 1 else 0
    if (i1 - i0 + 1) * (j1 - j0 + 1) * (k1 - k0 + 1) > 4096:
        return 2
    seen_in = False
    seen_out = False
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            for k in range(k0, k1 + 1):
                st = mst[i, j, k]
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
@njit(cache=True, error_model="numpy", literal_args="d")
def gnorm(d, Mb, j, k):
    """``||I - k M||_2`` of ``M = Mb[j]``: ``|1 - k mu| + k |nu|`` in the plane, the closed-form
    sigma_max in 3-D. ``d`` (2 or 3) is a compile-time constant in the search: one branch is compiled."""
    if d == 2:
        return _gnorm2(Mb[j, 0, 0], Mb[j, 0, 1], Mb[j, 1, 0], Mb[j, 1, 1], k)
    return _smax3(1.0 - k * Mb[j, 0, 0], -k * Mb[j, 0, 1], -k * Mb[j, 0, 2],
                  -k * Mb[j, 1, 0], 1.0 - k * Mb[j, 1, 1], -k * Mb[j, 1, 2],
                  -k * Mb[j, 2, 0], -k * Mb[j, 2, 1], 1.0 - k * Mb[j, 2, 2])


@njit(cache=True, error_model="numpy", literal_args="d")
def gval(d, Mb, Pb, j, k):
    """``||I - k M||_2`` of instance ``j`` as :func:`gnorm`, from the reduced form in ``Pb[j]`` where
    :func:`_instance3` left one (the 3-D lever): ``max(|1 - k Pb[j, 4]|, sigma_max(I - k B))`` with
    ``B = [[Pb[j, 0], Pb[j, 1]], [Pb[j, 2], Pb[j, 3]]]``, the 2 x 2 value by its conformal parts
    (``|mu| + |nu|``): no eigenvalue cubic, no trigonometry."""
    if d == 2:
        return gnorm(2, Mb, j, k)
    b00 = Pb[j, 0]
    if not b00 == b00:
        return gnorm(3, Mb, j, k)
    return _gval_block(b00, Pb[j, 1], Pb[j, 2], Pb[j, 3], Pb[j, 4], k)


@njit(cache=True, error_model="numpy")
def phimax(Mb, j):
    """Exact ``|phi_max|`` of ``M = Mb[j]`` (d x d, either d); the search calls :func:`_phimax`."""
    if Mb.shape[1] == 2:
        return _phimax(2, Mb, j)
    return _phimax(3, Mb, j)


@njit(cache=True, error_model="numpy", literal_args="d")
def _phimax(d, Mb, j):
    """Exact ``|phi_max|`` of ``M = Mb[j]``: the conformal closed form in the plane, the S^2 method
    of errplan.linalg in 3-D (``d`` as :func:`gnorm`'s)."""
    if d == 2:
        mr = 0.5 * (Mb[j, 0, 0] + Mb[j, 1, 1])
        mi = 0.5 * (Mb[j, 1, 0] - Mb[j, 0, 1])
        amu = math.sqrt(mr * mr + mi * mi)
        anu = math.sqrt((0.5 * (Mb[j, 0, 0] - Mb[j, 1, 1])) ** 2 + (0.5 * (Mb[j, 0, 1] + Mb[j, 1, 0])) ** 2)
        if not amu > 0.0:
            return math.pi
        ratio = anu / amu
        if not ratio < 1.0:
            return math.pi
        return min(math.pi, abs(math.atan2(mi, mr)) + math.asin(ratio))
    return phi_max3(Mb[j])


@njit(cache=True, error_model="numpy")
def phi_bound(Mb, j):
    """A cheap upper bound of ``|phi_max|`` of ``M = Mb[j]`` (3-D): for any k > 0 the actual motion
    k M v lies in the ball of radius ||I - k M|| |v| around v, so the angle is at most
    asin(||I - k M||) when that is below 1 (P1 eq. 10). k = tr(M) / ||M||_F^2 (the Frobenius-best
    gain); pi when no bound below pi follows."""
    tr = Mb[j, 0, 0] + Mb[j, 1, 1] + Mb[j, 2, 2]
    f = 0.0
    for a in range(3):
        for b in range(3):
            f += Mb[j, a, b] * Mb[j, a, b]
    if not (tr > 0.0 and f > 0.0):
        return math.pi
    g = gnorm(3, Mb, j, tr / f)
    return math.asin(g) if g < 1.0 else math.pi


# ----------------------------------------------------------------------------- the search
@njit(cache=True, error_model="numpy", literal_args="d")
def _poll_value(d, which, Mb, Pb, j, k):
    return gval(d, Mb, Pb, j, k) if which == 0 else _phimax(d, Mb, j)


@njit(cache=True, error_model="numpy")
def _sample_table(counts, periodic, na, m, pos, stride, nbr):
    """Once per tile: the per-axis position ``pos[j, ax]`` of every sample (m, na), the strides of
    the flat sample index (na,) and the flat index of each sample's neighbours ``nbr[j, 2 ax + 0/1]``
    one step down/up axis ``ax`` (-1 outside the box or along an axis with one sample), so that the
    tip loop finds local maxima without integer division."""
    s = 1
    for ax in range(na - 1, -1, -1):
        stride[ax] = s
        s *= counts[ax]
    for j in range(m):
        for ax in range(na):
            pos[j, ax] = (j // stride[ax]) % counts[ax]
    for j in range(m):
        for ax in range(na):
            for o in range(2):
                nbr[j, 2 * ax + o] = _neighbour(j, ax, 2 * o - 1, pos, stride, counts, periodic) if counts[ax] > 1 else -1


@njit(cache=True, error_model="numpy")
def _neighbour(j, ax, off, pos, stride, counts, periodic):
    """Flat index of sample ``j`` moved ``off`` steps along axis ``ax``; -1 outside the box."""
    p = pos[j, ax]
    q = p + off
    if periodic[ax]:
        q %= counts[ax]
    elif q < 0 or q >= counts[ax]:
        return -1
    return j + (q - p) * stride[ax]


@njit(cache=True, error_model="numpy")
def _local_max(vals, j, nbr):
    for c in range(nbr.shape[1]):
        q = nbr[j, c]
        if q >= 0 and vals[q] > vals[j]:
            return False
    return True


@njit(cache=True, error_model="numpy")
def _far(j, i, pos, counts, periodic, na):
    """More than one grid step apart along some axis (periodic axes measured around the circle)."""
    for ax in range(na):
        dd = abs(pos[j, ax] - pos[i, ax])
        if periodic[ax]:
            dd = min(dd, counts[ax] - dd)
        if dd > 1:
            return True
    return False


@njit(cache=True, error_model="numpy")
def _peak_raise(vals, j, pos, stride, counts, periodic, na):
    """Estimated gain of refining sample ``j``: per axis the parabola through it and its neighbours
    (one-sided on a face, where only a vertex inside the box counts), summed over the axes."""
    f0 = vals[j]
    out = 0.0
    for ax in range(na):
        s = counts[ax]
        if s < 2:
            continue
        jm = _neighbour(j, ax, -1, pos, stride, counts, periodic)
        jp = _neighbour(j, ax, 1, pos, stride, counts, periodic)
        if s == 2:
            r = abs(f0 - vals[jp if jp >= 0 else jm])
        elif jm >= 0 and jp >= 0:
            fm, fp = vals[jm], vals[jp]
            curv = 2 * f0 - fm - fp
            r = (fp - fm) ** 2 / (8 * curv) if curv > 0 else 0.0
        else:
            inward = 1 if jm < 0 else -1
            j1 = _neighbour(j, ax, inward, pos, stride, counts, periodic)
            j2 = _neighbour(j, ax, 2 * inward, pos, stride, counts, periodic)
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
def _poll_coord(t, step, lo, hi, periodic):
    """A pattern-search poll's coordinate: ``t + step`` wrapped into [lo, hi) on a periodic axis, else
    clipped into [lo, hi]."""
    v = t + step
    if periodic:
        return lo + (v - lo) % (hi - lo)
    return min(max(v, lo), hi)


@njit(cache=True, error_model="numpy")
def _climbing(best, before):
    """A pattern-search pass raised the worst case by more than 1e-7 (relative): another pass follows."""
    return best - before > 1e-7 * max(1.0, abs(best))


@njit(cache=True, error_model="numpy", literal_args="d")
def _pattern(d, which, k, x, th, best, step0, lo, hi, active, periodic, refine, extra, base_port, est, L, arm,
             chain, rmap, M, P1, S, V, cand, known):
    """Coordinate pattern search for the maximum of metric ``which`` (0: ||G|| at gain k, 1: |phi_max|)
    from ``th`` (updated in place) with value ``best``. Returns ``(best, ok)``; ``ok`` is False as
    soon as a polled instance cannot reach the tip (robust validity)."""
    na = th.shape[0]
    geo = map_geometry(rmap)  # the map's fields read once (chain.py: a namedtuple's arrays cost per read)
    mst = rmap.state
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
                    v = _poll_coord(th[ax], sgn * h, lo[ax], hi[ax], periodic[ax])
                    if not periodic[ax] and v == th[ax]:
                        continue  # clipped back onto the centre: a worst case on the box face
                    cand[ax] = v
                    if d == 2:  # the branch here, not in an inlined instance(): see instance()
                        ok, w0, w1, w2 = _instance2(x, cand, base_port, est, L, arm, M, 0, S, V, known), 0.0, 0.0, 0.0
                    else:
                        ok, w0, w1, w2 = _instance3(x, cand, base_port, est, L, M, P1, 0, S, V, which == 1)
                    if ok and d == 3 and not known:
                        s_, ix, iy, iz = map_state(geo, mst, w0, w1, w2)
                        ok = s_ == 1 or (s_ == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))
                    if not ok:
                        return best, False
                    if _PHI:
                        if which == 1 and d == 3 and phi_bound(M, 0) <= best:
                            continue  # this instance cannot raise the worst |phi_max|
                        f = _poll_value(d, which, M, P1, 0, k)
                    else:  # the copy without |phi_max| (_pattern_g)
                        f = gval(d, M, P1, 0, k)
                    if f > best:
                        best = f
                        for i in range(na):
                            th[i] = cand[i]
        if not _climbing(best, before):
            break
    return best, True


@njit(cache=True, error_model="numpy", literal_args="d")
def _pattern_lanes(d, k, s0, s1, XS, TH, best, known, live, owner, step0, lo, hi, active, periodic, refine, extra,
                   base_port, est, L, arm, chain, rmap, O, okl, want_rho, out_valid, out_g, out_p, out_rho, out_k):
    """:func:`_pattern`'s search for the worst ||G|| (``which`` 0), run for searches ``s0`` to ``s1 - 1`` at once, each
    from its own centre ``TH[:, s]`` (d, ns) with value ``best[s]`` at tip ``XS[:, s]``: every poll of
    the pattern is made for all searches still going by :func:`_levers2`/:func:`_levers3` (vectorized),
    then each search takes it or not exactly as :func:`_pattern` would, so that each ends where it
    would alone, with the same value (in ``best[s]``). Only for straight shafts (no load axis active):
    every poll is a lever. ``live[s]`` ends False if a poll fails (the tip is not robustly valid), as
    :func:`_pattern`'s ``ok``; ``known[s]``: the tip's wrists are certified reachable. Between passes
    the searches that stopped climbing leave the lanes, so a further pass costs only what still climbs.
    ``O``, ``okl``: the kernels' outputs (at least ``s1 - s0`` columns).

    Then the tips' results are completed as :func:`_search` does after its own searches: tip
    ``owner[s]`` gets the worst of its starts (its searches are consecutive), or is invalid if one
    of them failed; rho* is taken against that worst case (:func:`_rho_final`)."""
    na = step0.shape[0]
    ns = s1 - s0
    # working lanes: the searches still going, packed at the front (idx: their search)
    idx = np.arange(s0, s1)
    Xw = np.empty((d, ns))
    Tw = np.empty((d, ns))
    Cw = np.empty((d, ns))
    bw = np.empty(ns)
    bef = np.empty(ns)
    kw = np.empty(ns, np.bool_)
    lw = np.empty(ns, np.bool_)
    for s in range(ns):
        for a in range(d):
            Xw[a, s] = XS[a, s0 + s]
            Tw[a, s] = TH[a, s0 + s]
            Cw[a, s] = TH[a, s0 + s]
        bw[s] = best[s0 + s]
        kw[s] = known[s0 + s]
        lw[s] = live[s0 + s]
    nw = ns
    geo = map_geometry(rmap)
    mst = rmap.state
    for pass_ in range(1 + extra):
        for q in range(nw):
            bef[q] = bw[q]
        for level in range(1, refine + 1):
            for ax in range(na):
                if not active[ax]:
                    continue
                h = step0[ax] / 2.0 ** level
                for sgn in (-1.0, 1.0):
                    for q in range(nw):
                        Cw[ax, q] = _poll_coord(Tw[ax, q], sgn * h, lo[ax], hi[ax], periodic[ax])
                    if d == 2:
                        _levers2(Xw, Cw, nw, base_port, est, L, k, O, okl)
                    else:
                        _levers3(Xw, Cw, nw, base_port, est, L, k, O, okl)
                    for q in range(nw):
                        v = Cw[ax, q]
                        Cw[ax, q] = Tw[ax, q]
                        if not lw[q] or (not periodic[ax] and v == Tw[ax, q]):
                            continue  # failed, or clipped back onto the centre (a worst case on the box face)
                        okj = okl[q]
                        if okj and not kw[q]:
                            if d == 2:
                                okj = _planar_reachable(arm, O[1, q], O[2, q])
                            else:
                                w0, w1, w2 = O[1, q], O[2, q], O[3, q]
                                s_, ix, iy, iz = map_state(geo, mst, w0, w1, w2)
                                okj = s_ == 1 or (s_ == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))
                        if not okj:
                            lw[q] = False
                            continue
                        if O[0, q] > bw[q]:
                            bw[q] = O[0, q]
                            Tw[ax, q] = v
                            Cw[ax, q] = v
        # the pass's results; the searches still climbing go on, packed
        m_ = 0
        for q in range(nw):
            o = idx[q]
            best[o] = bw[q]
            live[o] = lw[q]
            if lw[q] and _climbing(bw[q], bef[q]):
                idx[m_] = o
                for a in range(d):
                    Xw[a, m_] = Xw[a, q]
                    Tw[a, m_] = Tw[a, q]
                    Cw[a, m_] = Tw[a, q]
                bw[m_] = bw[q]
                kw[m_] = kw[q]
                lw[m_] = True
                m_ += 1
        nw = m_
        if nw == 0:
            break
    t0 = s0
    while t0 < s1:
        i_ = owner[t0]
        t1 = t0
        ok_ = True
        best_all = -math.inf
        while t1 < s1 and owner[t1] == i_:
            ok_ = ok_ and live[t1]
            best_all = max(best_all, best[t1])
            t1 += 1
        if not ok_:
            out_valid[i_] = False
            out_g[i_] = np.nan
            out_p[i_] = np.nan
            out_rho[i_] = np.nan
            out_k[i_] = np.nan
        elif out_valid[i_]:  # (not when its |phi_max| search failed)
            out_g[i_] = best_all
            if want_rho:
                out_rho[i_], out_k[i_] = _rho_final(best_all, out_rho[i_], out_k[i_], k)
        t0 = t1


@njit(cache=True, error_model="numpy", literal_args="d")
def _golden(d, Ms, Pb, idx, na_, kmax, iters):
    """``min over k in [0, kmax] of max_{i in idx[:na_]} ||I - k Ms[i]||`` by golden section (convex in k)."""
    gr = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = 0.0, kmax
    c, e = b - gr * (b - a), a + gr * (b - a)
    fc = 0.0
    fd = 0.0
    for q in range(na_):
        fc = max(fc, gval(d, Ms, Pb, idx[q], c))
        fd = max(fd, gval(d, Ms, Pb, idx[q], e))
    for _ in range(iters):
        if fc < fd:
            b, e, fd = e, c, fc
            c = b - gr * (b - a)
            fc = 0.0
            for q in range(na_):
                fc = max(fc, gval(d, Ms, Pb, idx[q], c))
        else:
            a, c, fc = c, e, fd
            e = a + gr * (b - a)
            fd = 0.0
            for q in range(na_):
                fd = max(fd, gval(d, Ms, Pb, idx[q], e))
    return 0.5 * (a + b)


@njit(cache=True, error_model="numpy", literal_args="d")
def _golden_gain(d, Ms, Pb, m, iters, k0, idx):
    """``min over k > 0 of max_i ||I - k M_i||`` over the m sampled instances; ``(rho, k)``,
    ``(1, 0)`` where no gain contracts.

    Cutting planes: golden section over an active set of instances (first the worst at the
    scenario gain ``k0``), then every instance is checked at the minimiser and the worst one
    joins the set, until none exceeds the active maximum. At the end the maximum over all
    instances at k equals the active minimum, so k minimises the full maximum (each function is
    convex in k, so is their maximum). ``idx`` is (m,) int scratch."""
    amax = 0.0
    for i in range(m):
        s = 0.0
        for a in range(Ms.shape[1]):
            for b in range(Ms.shape[2]):
                s += Ms[i, a, b] ** 2
        amax = max(amax, math.sqrt(s))
    kmax = 2.0 / amax if amax > 0 else 1.0
    jw, vw = 0, -1.0
    for i in range(m):
        v = gval(d, Ms, Pb, i, k0)
        if v > vw:
            jw, vw = i, v
    idx[0] = jw
    n_act = 1
    kk = 0.0
    rho = 1.0
    while True:
        kk = _golden(d, Ms, Pb, idx, n_act, kmax, iters)
        act = 0.0
        for q in range(n_act):
            act = max(act, gval(d, Ms, Pb, idx[q], kk))
        jw, vw = -1, act
        for i in range(m):
            v = gval(d, Ms, Pb, i, kk)
            if v > vw * (1.0 + 1e-13) + 1e-15:
                jw, vw = i, v
        rho = vw
        if jw < 0 or n_act >= m:
            break
        idx[n_act] = jw
        n_act += 1
    if rho >= 1.0:
        return 1.0, 0.0
    return rho, kk


@njit(cache=True, error_model="numpy")
def _rho_final(g, rs, ks, k):
    """rho* and k* from the certified golden-section pair ``(rs, ks)`` and the worst ||G|| ``g`` at the
    scenario gain ``k`` (used where it does better); ``(1, 0)`` where no gain contracts."""
    if g < rs:
        rs, ks = g, k
    if rs >= 1.0:
        rs, ks = 1.0, 0.0
    return rs, ks


def worst_case_tile(X, *args) -> None:
    """Worst case at every tip ``X[i]`` (n, d) over the error set sampled at ``grid`` (m, na); the other
    arguments as :func:`_search`'s.

    Writes ``out_valid`` (robustly reachable), ``out_g`` (worst ||G|| at gain ``k``), ``out_p``
    (worst |phi_max|, if ``want_phi``), ``out_rho``/``out_k`` (rho*, k*, if ``want_rho``; rho*
    certified by a refined worst case at k*, the scenario gain used where it does better).
    One search for both dimensions and both uses; the copy is picked here, in Python, so that a command
    compiles only the search of its own dimension (a compiled dispatch typed both), and without the exact
    |phi_max| unless it asks for it (its search is a fifth of a cold 3-D compile).

    Where the error set is straight shafts only (no load axis active), the search records the starts of
    its worst-||G|| refinements and :func:`_lanes_tile` (an entry of its own per dimension) runs
    them as lanes afterwards (:func:`run_lanes`): a command whose error sets all carry a load never compiles
    the lanes.
    """
    d, n = X.shape[1], X.shape[0]
    lanes = _Lanes(d, n)
    _TILES[d, bool(args[_WANT_PHI])](X, *args, *lanes.bufs)
    if lanes.count[0] > 0:
        run_lanes(lanes, *args)


class _Lanes:
    """The buffers in which a search records its lanes' starts (:func:`_search`, :func:`_lanes_tile`): at
    most two per tip."""

    def __init__(self, d: int, n: int):
        ns = 2 * n
        self.d = d
        self.count = np.zeros(1, np.int64)
        self.bufs = (np.empty((d, ns)), np.empty((d, ns)), np.empty(ns), np.empty(ns, np.bool_),
                     np.empty(ns, np.bool_), np.empty(ns, np.int64), self.count)


def run_lanes(lanes: _Lanes, grid, counts, active, periodic, lo, hi, step0, base_port, est, L, k, arm, chain,
              rmap, refine, extra, second_start, want_phi, want_rho, out_valid, out_g, out_p, out_rho, out_k):
    """The recorded lanes of a tile (:func:`_lanes_tile`), in the copy of its dimension."""
    XS, TH, best, known, live, owner, count = lanes.bufs
    _LANE_TILES[lanes.d](int(count[0]), XS, TH, best, known, live, owner, step0, lo, hi, active, periodic,
                         refine, extra, base_port, est, L, k, arm, chain, rmap, want_rho, out_valid, out_g,
                         out_p, out_rho, out_k)


def load_lanes(d: int, grid, counts, active, *args) -> None:
    """Load (or compile) the lanes of dimension ``d`` now if the error set (``grid``, ``active``: the
    search's arguments) can use them: straight shafts only (:func:`_search`'s ``lanes``). Run on no
    searches, with the search's own arguments (one specialization)."""
    if not (grid.shape[1] > d and (np.any(grid[:, d] != 0.0) or np.any(active[d:]))):
        out = [np.zeros(0, bool)] + [np.zeros(0) for _ in range(4)]
        run_lanes(_Lanes(d, 0), grid, counts, active, *args, *out)


def _lanes_tile(ns, XS, TH, best, known, live, owner, step0, lo, hi, active, periodic, refine, extra,
                base_port, est, L, k, arm, chain, rmap, want_rho, out_valid, out_g, out_p, out_rho, out_k):
    """The ``ns`` worst-||G|| refinements a search recorded (:func:`_search`), as lanes
    (:func:`_pattern_lanes`), LANE_TIPS tips at a time (a tip's searches are consecutive and stay in one
    block); compiled once per dimension (:func:`_per_dim`: ``_lanes_tile2``, ``_lanes_tile3``)."""
    d = _D
    O = np.empty((7 if d == 2 else 4, 2 * LANE_TIPS))
    okl = np.empty(2 * LANE_TIPS, np.bool_)
    s0 = 0
    while s0 < ns:
        s1 = s0
        tips = 0
        while s1 < ns and tips < LANE_TIPS:
            i_ = owner[s1]
            while s1 < ns and owner[s1] == i_:
                s1 += 1
            tips += 1
        _pattern_lanes(d, k, s0, s1, XS, TH, best, known, live, owner, step0, lo, hi, active, periodic, refine,
                       extra, base_port, est, L, arm, chain, rmap, O, okl, want_rho, out_valid, out_g, out_p,
                       out_rho, out_k)
        s0 = s1


def _search(X, grid, counts, active, periodic, lo, hi, step0, base_port, est, L, k, arm, chain, rmap,
            refine, extra, second_start, want_phi, want_rho, out_valid, out_g, out_p, out_rho, out_k,
            XS, TH, bestL, knownL, liveL, ownerL, nlanes):
    """The search of :func:`worst_case_tile`; compiled once per dimension and use (:func:`_per_dim`:
    ``_tile2``, ``_tile3`` with |phi_max|, ``_tile2g``, ``_tile3g`` without), ``d``, ``_PHI`` and the pattern
    search ``_PAT`` constants of the module globals there. ``want_phi`` is read in Python (:func:`worst_case_tile` picks the copy).
    ``XS``, ``TH``, ``bestL``, ``knownL``, ``liveL``, ``ownerL`` (room for two per tip, :class:`_Lanes`): where
    the error set is straight shafts only, the starts of the worst-||G|| refinements, left for
    :func:`_lanes_tile`; ``nlanes[0]``: how many."""
    d = _D
    n = X.shape[0]
    m, na = grid.shape
    vals_g = np.empty(m)
    vals_p = np.empty(m)
    Ms = np.empty((m, d, d))
    Pbs = np.empty((m, 5))
    M = np.empty((1, d, d))
    P1 = np.empty((1, 5))
    S = np.zeros((8, 3, 3))
    V = np.zeros((8, 3))
    th = np.empty(na)
    cand = np.empty(na)
    results = np.empty(2)
    idx = np.empty(m, np.int64)
    pos = np.empty((m, na), np.int64)
    stride = np.empty(na, np.int64)
    nbr = np.empty((m, 2 * na), np.int64)
    _sample_table(counts, periodic, na, m, pos, stride, nbr)
    geo = map_geometry(rmap)  # the map's fields read once (chain.py: a namedtuple's arrays cost per read)
    mst = rmap.state
    # 3-D with a load: samples at tau = 0 repeat along the direction axis psi (the last one)
    dup = d == 3 and na == 5 and counts[4] > 1
    full = _PHI or want_rho  # the sampled M themselves (|phi_max|, rho*'s gain bracket), not only ||G||
    # the straight-shaft samples (no load), all at once per tip (_levers2/_levers3): lever[j] their column
    # in G, -1 for a loaded sample; in 3-D only where the search needs no M (``bulk``: _levers3 forms none)
    bulk = d == 2 or not full
    lever = np.full(m, -1, np.int64)
    nl = 0
    for j in range(m):
        if na <= d or grid[j, d] == 0.0:
            lever[j] = nl
            nl += 1
    G = np.empty((d, nl))
    for j in range(m):
        if lever[j] >= 0:
            for a in range(d):
                G[a, lever[j]] = grid[j, a]
    O = np.empty((7 if d == 2 else 4, nl))
    okl = np.empty(nl, np.bool_)
    # The refinement of the worst ||G|| as lanes where every instance the pattern can poll is a straight
    # shaft (no load axis active, none sampled): each tip's searches are recorded here (XS, TH, bestL,
    # knownL, liveL, ownerL; nlanes[0] of them) and run together afterwards, then its results completed
    # (_lanes_tile, an entry of its own: worst_case_tile).
    lanes = nl == m
    for a in range(d, na):
        lanes = lanes and not active[a]
    # planar: the straight samples at the corners of the port box, whose wrists are tested first
    corners = np.empty(m, np.int64)
    nc = 0
    for j in range(m if d == 2 else 0):
        if lever[j] >= 0:
            c_ = True
            for a in range(d):
                c_ = c_ and (pos[j, a] == 0 or pos[j, a] == counts[a] - 1)
            if c_:
                corners[nc] = j
                nc += 1
    corners = corners[:nc]
    XT = np.empty((d, nl))  # the tip, once per sampled straight instance (_levers2/_levers3 take one per lane)
    ns = 0
    for ii in range(n):
        x = X[ii]
        ok = True
        known = False
        if d == 3:
            tr = _tip_reach(x, base_port, lo, hi, L, rmap)
            ok = tr != 0
            known = tr == 1
            if tr == 2:
                ok = not _lever_out(x, grid, base_port, L, rmap)
        else:
            ok = not _corners_out2(x, grid, corners, base_port, L, arm)
            known = ok and _tip_reach2(x, base_port, lo, hi, L, arm) == 1
        if ok and bulk and nl > 0:
            for q in range(nl):
                for a in range(d):
                    XT[a, q] = x[a]
            if d == 2:
                _levers2(XT, G, nl, base_port, est, L, k, O, okl)
            else:
                _levers3(XT, G, nl, base_port, est, L, k, O, okl)
        for j in range(m if ok else 0):
            q = lever[j] if bulk else -1
            if q >= 0:
                okj = okl[q]
                if okj and not known:
                    if d == 2:
                        okj = _planar_reachable(arm, O[1, q], O[2, q])
                    else:
                        w0, w1, w2 = O[1, q], O[2, q], O[3, q]
                        s_, ix, iy, iz = map_state(geo, mst, w0, w1, w2)
                        okj = s_ == 1 or (s_ == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))
                if not okj:
                    ok = False
                    break
                vals_g[j] = O[0, q]
                if d == 2 and full:
                    Ms[j, 0, 0], Ms[j, 0, 1], Ms[j, 1, 0], Ms[j, 1, 1] = O[3, q], O[4, q], O[5, q], O[6, q]
                continue
            if dup and grid[j, 3] == 0.0 and j % counts[4] != 0:
                j0 = j - j % counts[4]  # the same instance: tau = 0 has no direction
                for a in range(d):
                    for b in range(d):
                        Ms[j, a, b] = Ms[j0, a, b]
                for a in range(5):
                    Pbs[j, a] = Pbs[j0, a]
                vals_g[j] = vals_g[j0]
                continue
            if d == 2:
                okj, w0, w1, w2 = _instance2(x, grid[j], base_port, est, L, arm, Ms, j, S, V, known), 0.0, 0.0, 0.0
            else:
                okj, w0, w1, w2 = _instance3(x, grid[j], base_port, est, L, Ms, Pbs, j, S, V, full)
            if okj and d == 3 and not known:
                s_, ix, iy, iz = map_state(geo, mst, w0, w1, w2)
                okj = s_ == 1 or (s_ == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))
            if not okj:
                ok = False
                break
            vals_g[j] = gval(d, Ms, Pbs, j, k)
        if _PHI and ok:
            if d == 2:
                for j in range(m):
                    vals_p[j] = _phimax(d, Ms, j)
            else:
                # branch and bound: exact |phi_max| only where the cheap bound could beat the best
                # exact value so far; elsewhere the bound stands in (never above the best exact)
                for j in range(m):
                    vals_p[j] = phi_bound(Ms, j)
                order = np.argsort(-vals_p)
                best_exact = -1.0
                for q in range(m):
                    j = order[q]
                    if vals_p[j] <= best_exact:
                        vals_p[j] = min(vals_p[j], best_exact)
                        continue
                    vals_p[j] = _phimax(d, Ms, j)
                    best_exact = max(best_exact, vals_p[j])
        for which in range((2 if _PHI else 1) if ok else 0):
            vals = vals_g if which == 0 else vals_p
            jbest = 0
            for j in range(1, m):
                if vals[j] > vals[jbest]:
                    jbest = j
            # a second start: the best sampled local maximum more than one step from the worst
            j2 = -1
            if second_start > 0 and m > 1:
                for j in range(m):  # the cheap comparison first
                    if (j2 < 0 or vals[j] > vals[j2]) and _far(j, jbest, pos, counts, periodic, na) \
                            and _local_max(vals, j, nbr):
                        j2 = j
                if j2 >= 0:
                    v = vals[jbest]
                    if not (vals[j2] + 2.0 * _peak_raise(vals, j2, pos, stride, counts, periodic, na)
                            >= v - second_start * max(1.0, abs(v))):
                        j2 = -1
            best_all = -math.inf
            for start in (jbest, j2):
                if start < 0:
                    continue
                if lanes and which == 0:  # run with the other searches afterwards (_lanes_tile)
                    for a in range(d):
                        XS[a, ns] = x[a]
                        TH[a, ns] = grid[start, a]
                    bestL[ns] = vals[start]
                    knownL[ns] = known
                    liveL[ns] = True
                    ownerL[ns] = ii
                    ns += 1
                    continue
                for i in range(na):
                    th[i] = grid[start, i]
                b, ok = _PAT(d, which, k, x, th, vals[start], step0, lo, hi, active, periodic, refine, extra,
                             base_port, est, L, arm, chain, rmap, M, P1, S, V, cand, known)
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
        out_p[ii] = results[1] if _PHI else np.nan
        if want_rho:
            rs, ks = _golden_gain(d, Ms, Pbs, m, 60, k, idx)
            if ks > 0:
                # certify at k*: the refined worst case over the continuous set at that gain
                jbest = 0
                vbest = -1.0
                for j in range(m):
                    v = gval(d, Ms, Pbs, j, ks)
                    if v > vbest:
                        vbest, jbest = v, j
                for i in range(na):
                    th[i] = grid[jbest, i]
                ref, ok = _PAT(d, 0, ks, x, th, vbest, step0, lo, hi, active, periodic, refine, extra,
                               base_port, est, L, arm, chain, rmap, M, P1, S, V, cand, known)
                rs = max(rs, ref) if ok else 1.0
            else:
                rs = 1.0
            if not lanes:
                rs, ks = _rho_final(results[0], rs, ks, k)
            out_rho[ii] = rs  # with lanes: completed by _lanes_tile, once the worst ||G|| is known
            out_k[ii] = ks
        else:
            out_rho[ii] = np.nan
            out_k[ii] = np.nan
    nlanes[0] = ns


def motion_maps(X, TH, base_port, est, L, arm, chain, rmap, out_M, out_ok) -> None:
    """``M = J Jhat^-1`` (into ``out_M`` (n, d, d)) and validity (``out_ok`` (n,)) of instance
    ``TH[i]`` at tip ``X[i]``; invalid rows of ``out_M`` are NaN. The dimension is picked in Python.
    Read-only inputs (broadcast views) are copied: numba types a read-only array apart, and one
    specialization (one compile) serves every caller."""
    X, TH = kernel_array(X), kernel_array(TH)
    (_maps2 if X.shape[1] == 2 else _maps3)(X, TH, base_port, est, L, arm, chain, rmap, out_M, out_ok)


def _motion_maps(X, TH, base_port, est, L, arm, chain, rmap, out_M, out_ok):
    """:func:`motion_maps`' loop; compiled once per dimension (``_maps2``, ``_maps3``) as :func:`_search`."""
    d = _D
    S = np.zeros((8, 3, 3))
    V = np.zeros((8, 3))
    Pb = np.empty((X.shape[0], 5))
    geo = map_geometry(rmap)
    mst = rmap.state
    for i in range(X.shape[0]):
        if d == 2:
            ok, w0, w1, w2 = _instance2(X[i], TH[i], base_port, est, L, arm, out_M, i, S, V, False), 0.0, 0.0, 0.0
        else:
            ok, w0, w1, w2 = _instance3(X[i], TH[i], base_port, est, L, out_M, Pb, i, S, V, True)
        if ok and d == 3:
            s_, ix, iy, iz = map_state(geo, mst, w0, w1, w2)
            ok = s_ == 1 or (s_ == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))
        out_ok[i] = ok
        if not ok:
            for a in range(d):
                for b in range(d):
                    out_M[i, a, b] = np.nan


_D = 0  # the dimension of a kernel made by _per_dim (there a constant of its own globals)
_PHI = True  # whether a search copy computes |phi_max| (_pattern_g and _per_dim(..., phi=False): False)


def _per_dim(f, d: int, phi: bool = True):
    """``f`` compiled for dimension ``d``: a copy of the function whose globals hold ``_D = d``, so that
    ``d = _D`` is a compile-time constant (numba freezes global numbers): the branches of the other
    dimension are pruned, callees taking ``d`` get the literal. An entry compiled straight from Python,
    not a wrapper passing ``literally(d)`` to a kernel with ``d`` an argument: such a wrapper linked and
    optimized the whole search a second time (about 4 s of a cold 3-D compile, 3 s of a planar one)."""
    g = copy_function(f, f"{f.__name__}{d}{'' if phi else 'g'}", _D=d, _PHI=phi, _PAT=_pattern if phi else _pattern_g)
    return njit(cache=True, error_model="numpy")(g)


#: the pattern search without |phi_max| (``which`` is 0): the search copies without it call this one
_pattern_g = njit(cache=True, error_model="numpy", literal_args="d")(
    copy_function(_pattern.py_func, "_pattern_g", _PHI=False))
_PAT = _pattern  # the pattern search a search copy calls (_per_dim: _pattern_g in the copies without |phi_max|)
_tile2, _tile3 = _per_dim(_search, 2), _per_dim(_search, 3)
_tile2g, _tile3g = _per_dim(_search, 2, phi=False), _per_dim(_search, 3, phi=False)
_TILES = {(2, True): _tile2, (3, True): _tile3, (2, False): _tile2g, (3, False): _tile3g}
_LANE_TILES = {2: _per_dim(_lanes_tile, 2), 3: _per_dim(_lanes_tile, 3)}
_WANT_PHI = _search.__code__.co_varnames.index("want_phi") - 1  # its place in worst_case_tile's *args
_maps2, _maps3 = _per_dim(_motion_maps, 2), _per_dim(_motion_maps, 3)
