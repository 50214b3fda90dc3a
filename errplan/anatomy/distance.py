"""Exact distances between convex hulls of point sets (GJK), and the robust shaft clearance.

Every obstacle is split into convex *pieces*: a piece is the convex hull of up to
:data:`MAX_PIECE` points grown by a radius (a sphere: one point; a capsule: two; a box: eight
corners, radius 0; a mesh: one piece per triangle). The instrument's side of a query is the
*shaft hull*, the convex hull of the port box's corners and one or two tips:

- the union over true ports p of the port box B of the shafts [p, x] is exactly conv(B ∪ {x});
- the union over the tips y of a motion [a, b] of conv(B ∪ {y}) is exactly conv(B ∪ {a, b})
  (a point ``mu y + (1 - mu) p`` with ``y = a + s (b - a)`` is a convex combination of a, b and p,
  and conversely), so a straight motion is checked exactly, in one query, not by sampling.

The distance between two hulls is computed by GJK (Gilbert, Johnson & Keerthi 1988) on the
Minkowski difference, with the closest point of each simplex found by enumerating its faces (at
most 15; the closest point lies in the relative interior of one of them, where the affine
projection of the origin has positive barycentric coordinates): exact up to a tolerance of
:data:`TOL` m. The distance to a piece is the hull distance minus its radius.

Clearance is a minimum over many pieces (a mesh has thousands of triangles); pieces are grouped
into clusters of :data:`CLUSTER` with bounding spheres, and the query's shaft hull is bounded by a
capsule (the segment from the box centre to the tips' midpoint, grown by the box half-diagonal
plus half the motion's length): a cluster or piece whose bounding sphere is farther than the best
distance found so far is skipped, which never changes the result.
"""
from __future__ import annotations

import math

import numpy as np

from ..jit import njit

MAX_PIECE = 8  # points of one convex piece (a box's corners)
MAX_HULL = 10  # points of a shaft hull: 8 box corners and two tips
TOL = 1e-9  # m: GJK's stopping gap (the distance is exact to this)
CLUSTER = 16  # pieces per culling cluster


@njit
def _support(P, n, dx, dy, dz):
    best = -1e300
    k = 0
    for i in range(n):
        s = P[i, 0] * dx + P[i, 1] * dy + P[i, 2] * dz
        if s > best:
            best = s
            k = i
    return k


@njit
def _closest_on_simplex(W, m, out_v, keep, S):
    """Closest point to the origin of conv(W[:m]) (m <= 4). Writes it to ``out_v`` and the
    indices of the face it lies on to ``keep`` (returns their count, 0 when the origin is inside
    a full tetrahedron). ``S``: scratch (a :func:`scratch` array)."""
    best = 1e300
    best_mask = 0
    bv0 = 0.0
    bv1 = 0.0
    bv2 = 0.0
    lam = S[0, 0]
    G = S[1, :3]
    r = S[1, 3]
    mu = S[2, 0]
    idx = keep[4:]
    for mask in range(1, 1 << m):
        k = 0
        for i in range(m):
            if mask & (1 << i):
                idx[k] = i
                k += 1
        # affine projection of the origin onto the points idx[:k]
        i0 = idx[0]
        if k == 1:
            lam[0] = 1.0
        else:
            q = k - 1
            for a in range(q):
                ia = idx[a + 1]
                for c in range(q):
                    ic = idx[c + 1]
                    s = 0.0
                    for t in range(3):
                        s += (W[ia, t] - W[i0, t]) * (W[ic, t] - W[i0, t])
                    G[a, c] = s
                s = 0.0
                for t in range(3):
                    s -= (W[ia, t] - W[i0, t]) * W[i0, t]
                r[a] = s
            # solve G mu = r (q <= 3) by Gaussian elimination with partial pivoting
            scale = 0.0
            for a in range(q):
                scale = max(scale, abs(G[a, a]))
            if scale <= 0.0:
                continue
            ok = True
            for col in range(q):
                piv = col
                for a in range(col + 1, q):
                    if abs(G[a, col]) > abs(G[piv, col]):
                        piv = a
                if abs(G[piv, col]) <= 1e-13 * scale:
                    ok = False
                    break
                if piv != col:
                    for c in range(q):
                        tmp = G[col, c]
                        G[col, c] = G[piv, c]
                        G[piv, c] = tmp
                    tmp = r[col]
                    r[col] = r[piv]
                    r[piv] = tmp
                for a in range(col + 1, q):
                    f = G[a, col] / G[col, col]
                    for c in range(col, q):
                        G[a, c] -= f * G[col, c]
                    r[a] -= f * r[col]
            if not ok:
                continue
            for a in range(q - 1, -1, -1):
                s = r[a]
                for c in range(a + 1, q):
                    s -= G[a, c] * mu[c]
                mu[a] = s / G[a, a]
            s = 0.0
            feasible = True
            for a in range(q):
                lam[a + 1] = mu[a]
                s += mu[a]
                if mu[a] <= 0.0:
                    feasible = False
            lam[0] = 1.0 - s
            if lam[0] <= 0.0 or not feasible:
                continue
        v0 = 0.0
        v1 = 0.0
        v2 = 0.0
        for a in range(k):
            v0 += lam[a] * W[idx[a], 0]
            v1 += lam[a] * W[idx[a], 1]
            v2 += lam[a] * W[idx[a], 2]
        d2 = v0 * v0 + v1 * v1 + v2 * v2
        if d2 < best:
            best = d2
            best_mask = mask
            bv0, bv1, bv2 = v0, v1, v2
    out_v[0], out_v[1], out_v[2] = bv0, bv1, bv2
    n = 0
    for i in range(m):
        if best_mask & (1 << i):
            keep[n] = i
            n += 1
    if n == 4:
        return 0
    return n


def scratch() -> tuple[np.ndarray, np.ndarray]:
    """Work arrays of :func:`hull_distance_s` (float (5, 4, 4), int (8,))."""
    return np.zeros((5, 4, 4)), np.zeros(8, np.int64)


@njit
def hull_distance(P, np_, Q, nq):
    """Distance (m) between conv(P[:np_]) and conv(Q[:nq]) (points (n, 3)); 0 when they meet."""
    S = np.zeros((5, 4, 4))
    keep = np.zeros(8, np.int64)
    return hull_distance_s(P, np_, Q, nq, S, keep)


@njit
def hull_distance_s(P, np_, Q, nq, S, keep):
    """:func:`hull_distance` with caller-owned work arrays ``S``, ``keep`` (:func:`scratch`)."""
    W = S[3, :, :3]
    W2 = S[4, :, :3]
    v = S[2, 1, :3]
    v[0] = P[0, 0] - Q[0, 0]
    v[1] = P[0, 1] - Q[0, 1]
    v[2] = P[0, 2] - Q[0, 2]
    m = 0
    for _ in range(64):
        vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
        if vv <= 1e-30:
            return 0.0
        i = _support(P, np_, -v[0], -v[1], -v[2])
        j = _support(Q, nq, v[0], v[1], v[2])
        w0 = P[i, 0] - Q[j, 0]
        w1 = P[i, 1] - Q[j, 1]
        w2 = P[i, 2] - Q[j, 2]
        vw = v[0] * w0 + v[1] * w1 + v[2] * w2
        nv = math.sqrt(vv)
        if vv - vw <= TOL * nv:  # |v| - v.w/|v| <= TOL: |v| is the distance within TOL
            return nv
        dup = False
        for a in range(m):
            if abs(W[a, 0] - w0) + abs(W[a, 1] - w1) + abs(W[a, 2] - w2) <= 1e-15:
                dup = True
        if dup:
            return nv
        W[m, 0], W[m, 1], W[m, 2] = w0, w1, w2
        m += 1
        n = _closest_on_simplex(W, m, v, keep, S)
        if n == 0:
            return 0.0
        for a in range(n):
            for t in range(3):
                W2[a, t] = W[keep[a], t]
        for a in range(n):
            for t in range(3):
                W[a, t] = W2[a, t]
        m = n
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@njit
def _point_segment(cx, cy, cz, a, b):
    ux, uy, uz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    wx, wy, wz = cx - a[0], cy - a[1], cz - a[2]
    uu = ux * ux + uy * uy + uz * uz
    t = 0.0
    if uu > 0.0:
        t = min(max((wx * ux + wy * uy + wz * uz) / uu, 0.0), 1.0)
    dx, dy, dz = wx - t * ux, wy - t * uy, wz - t * uz
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@njit
def _cone_lb(qx, qy, qz, c0, m, rho, half):
    """A lower bound on the distance from point q to the shaft hull, which lies in the union over
    s in [0, 1] of the balls centred at ``c0 + s (m - c0)`` with radius ``(1 - s) rho + s half``
    (a tapered capsule): the exact minimum over s of ``|q - p(s)| - r(s)`` (convex in s; closed form)."""
    ax, ay, az = m[0] - c0[0], m[1] - c0[1], m[2] - c0[2]
    L = math.sqrt(ax * ax + ay * ay + az * az)
    wx, wy, wz = qx - c0[0], qy - c0[1], qz - c0[2]
    if L <= 1e-12:
        return math.sqrt(wx * wx + wy * wy + wz * wz) - max(rho, half)
    ax, ay, az = ax / L, ay / L, az / L
    u = wx * ax + wy * ay + wz * az
    hx, hy, hz = wx - u * ax, wy - u * ay, wz - u * az
    h = math.sqrt(hx * hx + hy * hy + hz * hz)
    k = (rho - half) / L
    if abs(k) >= 1.0:
        t = 0.0 if k > 0 else L
    else:
        t = u - k * h / math.sqrt(1.0 - k * k)
    t = min(max(t, 0.0), L)
    return math.sqrt((u - t) ** 2 + h * h) - rho + k * t


@njit
def shaft_clearance(H, nh, cap_a, cap_b, cap_r, pts, npts, prad, pball, clusters, cball, stop):
    """Smallest distance (m, >= 0) from conv(H[:nh]) to every piece; stops early once it is below
    ``stop`` (then the value is only known to be below ``stop``, and is the distance found so far).

    ``cap_a``, ``cap_b``, ``cap_r`` = (rho, half): a tapered capsule containing the hull (radius rho at
    ``cap_a``, half at ``cap_b``; :func:`_cone_lb`, for culling); ``pts`` (n, 8, 3),
    ``npts`` (n,), ``prad`` (n,): the pieces; ``pball`` (n, 4): each piece's bounding sphere
    (centre, radius incl. ``prad``); ``clusters`` (c + 1,): piece ranges; ``cball`` (c, 4) their spheres.
    """
    nc = len(clusters) - 1
    S = np.zeros((5, 4, 4))
    keep = np.zeros(8, np.int64)
    lb = np.empty(nc)
    for c in range(nc):
        lb[c] = _cone_lb(cball[c, 0], cball[c, 1], cball[c, 2], cap_a, cap_b, cap_r[0], cap_r[1]) - cball[c, 3]
    best = 1e300
    for _ in range(nc):
        # the cluster of smallest bound not yet seen (found by a scan: a sort would add seconds to a first
        # run's compile, and the loop ends after the few clusters whose bound beats the best distance)
        c = 0
        for cc in range(1, nc):
            if lb[cc] < lb[c]:
                c = cc
        if lb[c] >= best:
            break
        lb[c] = np.inf
        for p in range(clusters[c], clusters[c + 1]):
            lp = _cone_lb(pball[p, 0], pball[p, 1], pball[p, 2], cap_a, cap_b, cap_r[0], cap_r[1]) - pball[p, 3]
            if lp >= best:
                continue
            d = hull_distance_s(H, nh, pts[p], npts[p], S, keep) - prad[p]
            if d < best:
                best = d
        if best < stop:
            break
    return max(best, 0.0)


@njit
def winding(px, py, pz, wpts, n):
    """Generalized winding number of point p for the closed mesh whose triangles are ``wpts[:n, :3]``
    (1 inside, 0 outside; van Oosterom & Strackee's solid angle of each triangle)."""
    tot = 0.0
    for t in range(n):
        ax, ay, az = wpts[t, 0, 0] - px, wpts[t, 0, 1] - py, wpts[t, 0, 2] - pz
        bx, by, bz = wpts[t, 1, 0] - px, wpts[t, 1, 1] - py, wpts[t, 1, 2] - pz
        cx, cy, cz = wpts[t, 2, 0] - px, wpts[t, 2, 1] - py, wpts[t, 2, 2] - pz
        la = math.sqrt(ax * ax + ay * ay + az * az)
        lb = math.sqrt(bx * bx + by * by + bz * bz)
        lc = math.sqrt(cx * cx + cy * cy + cz * cz)
        det = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
        den = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (bx * cx + by * cy + bz * cz) * la
               + (cx * ax + cy * ay + cz * az) * lb)
        tot += 2.0 * math.atan2(det, den)
    return tot / (4.0 * math.pi)


@njit
def mesh_wall_depth(ax, ay, az, bx, by, bz, wpts, wnpts, wprad, wpball, wclusters, wcball, stop):
    """Depth (m) of every point of the segment [a, b] inside the closed mesh body wall (its triangles
    as pieces, ``wpts`` ...): the distance from the segment to the surface when ``a`` is inside (the
    segment then stays inside up to that distance: exact, also for a wall that is not convex), -1 when
    ``a`` is outside; 0 when the segment touches the surface. Once the distance is below ``stop`` the
    value is only known to be below ``stop`` (and the inside test is skipped)."""
    H = np.zeros((MAX_HULL, 3))
    H[0, 0], H[0, 1], H[0, 2] = ax, ay, az
    H[1, 0], H[1, 1], H[1, 2] = bx, by, bz
    rr = np.zeros(2)
    d = shaft_clearance(H, 2, H[0], H[1], rr, wpts, wnpts, wprad, wpball, wclusters, wcball, stop)
    if d <= 0.0 or d < stop:
        return d
    if winding(ax, ay, az, wpts, wpts.shape[0]) < 0.5:
        return -1.0
    return d


@njit
def clearance_batch(box, tips_a, tips_b, extra, pts, npts, prad, pball, clusters, cball, wall, stop, out,
                    wpts, wnpts, wprad, wpball, wclusters, wcball):
    """:func:`shaft_clearance` of the hulls conv(box ∪ {a_i, b_i}) (``box`` (nb, 3) corners;
    ``tips_a``, ``tips_b`` (n, 3); a == b for a single tip), and, when ``wall[6] > 0``, the depth of
    the tips inside the body wall: ``wall[6] == 1`` the ellipsoid ``wall`` (:func:`ellipsoid_depth`;
    along a motion the smaller of its ends', exact since the set of points at least that deep in a
    convex body is convex), ``wall[6] == 2`` the closed mesh whose triangles are the pieces ``wpts`` ...
    (:func:`mesh_wall_depth`: the distance of the motion's segment to the surface, exact), minus
    ``extra[i]`` (a tip ball's radius, by the 1-Lipschitz bound), into ``out`` (n,)."""
    nb = box.shape[0]
    H = np.zeros((MAX_HULL, 3))
    c0 = np.zeros(3)
    for i in range(nb):
        for t in range(3):
            H[i, t] = box[i, t]
            c0[t] += box[i, t] / nb
    rho = 0.0
    for i in range(nb):
        dx, dy, dz = box[i, 0] - c0[0], box[i, 1] - c0[1], box[i, 2] - c0[2]
        rho = max(rho, math.sqrt(dx * dx + dy * dy + dz * dz))
    mid = np.zeros(3)
    rr = np.zeros(2)
    rr[0] = rho
    for i in range(tips_a.shape[0]):
        half = 0.0
        for t in range(3):
            H[nb, t] = tips_a[i, t]
            H[nb + 1, t] = tips_b[i, t]
            mid[t] = 0.5 * (tips_a[i, t] + tips_b[i, t])
            half += (tips_b[i, t] - tips_a[i, t]) ** 2
        half = 0.5 * math.sqrt(half)
        rr[1] = half
        d = 1e300
        if wall[6] > 1.5:
            d = mesh_wall_depth(tips_a[i, 0], tips_a[i, 1], tips_a[i, 2], tips_b[i, 0], tips_b[i, 1], tips_b[i, 2],
                                wpts, wnpts, wprad, wpball, wclusters, wcball, stop + extra[i])
        elif wall[6] > 0.0:
            d = min(ellipsoid_depth(tips_a[i, 0], tips_a[i, 1], tips_a[i, 2], wall),
                    ellipsoid_depth(tips_b[i, 0], tips_b[i, 1], tips_b[i, 2], wall))
        if len(clusters) > 1 and d > stop + extra[i]:
            d = min(d, shaft_clearance(H, nb + 2, c0, mid, rr, pts, npts, prad, pball, clusters, cball,
                                       stop + extra[i]))
        out[i] = max(d - extra[i], 0.0)


@njit
def motion_clearance1(box, ax, ay, az, bx, by, bz, pts, npts, prad, pball, clusters, cball, wall, stop,
                      wpts, wnpts, wprad, wpball, wclusters, wcball):
    """:func:`clearance_batch` of one motion [a, b] given by its coordinates (a scalar call for the
    planner's validity checks: one dispatch, no array built in Python)."""
    A = np.empty((1, 3))
    B = np.empty((1, 3))
    A[0, 0], A[0, 1], A[0, 2] = ax, ay, az
    B[0, 0], B[0, 1], B[0, 2] = bx, by, bz
    out = np.empty(1)
    clearance_batch(box, A, B, np.zeros(1), pts, npts, prad, pball, clusters, cball, wall, stop, out,
                    wpts, wnpts, wprad, wpball, wclusters, wcball)
    return out[0]


@njit
def ellipsoid_depth(px, py, pz, wall):
    """Signed distance (m) of a point inside the ellipsoid ``wall`` = (cx, cy, cz, a, b, c, ...)
    (axis-aligned semi-axes) to its surface: > 0 inside, <= 0 outside (then ``-(F - 1)`` scaled, only
    its sign is used). Exact inside (Eberly's root of ``sum (e_i y_i / (t + e_i^2))^2 = 1`` on
    ``t in (-e_min^2, 0]`` by bisection, with the degenerate case of a point on the smallest axis'
    plane)."""
    y = np.empty(3)
    e = np.empty(3)
    y[0], y[1], y[2] = abs(px - wall[0]), abs(py - wall[1]), abs(pz - wall[2])
    e[0], e[1], e[2] = wall[3], wall[4], wall[5]
    f0 = 0.0
    for i in range(3):
        f0 += (y[i] / e[i]) ** 2
    if f0 >= 1.0:
        return -(math.sqrt(f0) - 1.0) * min(e[0], min(e[1], e[2]))  # outside: a negative number
    # the smallest semi-axis
    k = 0
    for i in range(1, 3):
        if e[i] < e[k]:
            k = i
    ek2 = e[k] * e[k]
    best = 1e300
    # candidate 1: the regular root t in (-ek^2, 0]
    lo = -ek2
    hi = 0.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid <= lo or mid >= hi:
            break
        f = 0.0
        for i in range(3):
            den = mid + e[i] * e[i]
            f += (e[i] * y[i] / den) ** 2
        if f > 1.0:
            lo = mid
        else:
            hi = mid
    t = 0.5 * (lo + hi)
    d2 = 0.0
    s1 = 0.0
    ok = True
    for i in range(3):
        den = t + e[i] * e[i]
        if den <= 0.0:
            ok = False
            break
        x = e[i] * e[i] * y[i] / den
        d2 += (x - y[i]) ** 2
        s1 += (x / e[i]) ** 2
    if ok and abs(s1 - 1.0) <= 1e-6:  # no root in (-ek^2, 0] (a point on the smallest axis' plane): not a surface point
        best = math.sqrt(d2)
    # candidate 2 (degenerate): t = -ek^2, x_k from the surface equation
    s = 0.0
    d2 = 0.0
    ok = True
    for i in range(3):
        if i == k:
            continue
        den = e[i] * e[i] - ek2
        if den <= 0.0:
            ok = False
            break
        x = e[i] * e[i] * y[i] / den
        s += (x / e[i]) ** 2
        d2 += (x - y[i]) ** 2
    if ok and s <= 1.0:
        xk = e[k] * math.sqrt(1.0 - s)
        d2 += (xk - y[k]) ** 2
        best = min(best, math.sqrt(d2))
    # candidate 3: straight along the smallest axis (always a surface point: an upper bound)
    s = 0.0
    for i in range(3):
        if i != k:
            s += (y[i] / e[i]) ** 2
    best = min(best, e[k] * math.sqrt(max(1.0 - s, 0.0)) - y[k])
    return best
