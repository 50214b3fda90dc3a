"""Planar and spatial reachability of a tip's wrists: the planar arm's exact test and its
certificate over an error box (:func:`_tip_reach2`), the 3-D certificate from the reachability map
(:func:`_tip_reach`). The lowest layer of the field kernels."""
from __future__ import annotations

import math

import numpy as np

from ...jit import njit
from ...kinematics.compiled import _arc_class
from ...kinematics.urdf.chain import map_geometry, map_state


# ----------------------------------------------------------------------------- planar pieces
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

