"""The arm checks' compiled part: the moving arm at its tips (the wrist on the rigid shaft through the
port, the chain's inverse kinematics), its links' placements, the joint-space samples of a motion, and a
conservative broad phase and an exact narrow phase against arms held still (docs/physics.md, "Several
instruments and the endoscope", "Arms outside"). Numba kernels on plain arrays (:mod:`.collision` builds
them and asks coal about the few pairs this part leaves: a primitive's piece, or a tie with the clearance).

* :class:`LinkTree`: the arm's joints and collision objects as fixed transforms (pinocchio's kinematic
  tree with every joint off the actuated set at its held value), the objects' bounding spheres, the
  bounding capsules of their mesh pieces, the pieces' triangles (each with a capsule of its own) and their
  hulls' vertices in their own frames, and the per-object motion bounds (``reach``);
* :class:`HeldShapes`: the same of the held arms' objects, in the world;
* :func:`arm_motion`: for a straight tip motion ``a -> b`` (or one tip), the configurations at the tip
  samples (as :meth:`errplan.planning.arm_checks.ArmChecks.motion_configs` finds them), the joint-space
  samples (:func:`.collision.motion_samples`), and per sample and pair of objects (moving, held)
  :func:`pair_bound`: the spheres' gap, the capsules' gaps of their pieces, and for two mesh pieces whose
  capsules come within the clearance :func:`piece_bound`, the exact distance of their triangles
  (:func:`triangle_distance`) where it matters. Coal's mesh query between two pieces (a collision test with
  the clearance as security margin) is also a distance between their triangles (coal's meshes are
  triangle soups), so the answers are coal's.

Before the triangles, per pair of pieces: the two triangles found nearest each other the last time the pair
was looked at (a kept memory, :func:`piece_memory`; at any other state of the arm they are still two
triangles of the pieces, so their distance below the clearance decides "too close" at once), then
:func:`hull_bound`, a support bound on the pieces' convex hulls (the hulls' vertices, precomputed per piece;
a piece lies in its hull, so the hulls' distance bounds the pieces' from below) climbed by Gilbert's
iteration from the pair's last separating direction: it decides most pairs that lie a little above the
clearance with a few passes over a hundred or so vertices, and two support vertices (vertices of the
triangles) closer than the clearance decide the other way. The memory changes no answer, only how soon it
comes.

Pruning in the narrow phase, all conservative: a triangle whose capsule lies the clearance away from the
other piece's capsule cannot come closer (each capsule holds its triangles); the vertices of the triangles
left, projected on a line, bound the pieces' distance from below by the gap of their projections (every
point of a triangle projects between its vertices; on the line between the pieces this is the distance of
two convex pieces, so most pairs of the links' nearly convex pieces are decided by a few hundred dot
products); a pair of triangles whose capsules (or projections on the line between their axes) lie farther
apart than the smallest distance met so far cannot lower it. Three triangles of each side nearest the
other are tried first, so that a pair within the clearance is usually met at once.

Skipping along a motion is per pair of objects: the distance is 1-Lipschitz in the moving object's points,
and :func:`object_travel` bounds how far they move, so a pair found ``e`` above the clearance is not looked
at again until its object has moved ``e`` (:func:`arm_motion`).

Rounding: a pair counts as decided clear only when its bound exceeds the clearance by :data:`SLACK` (1 nm),
and within only when two of its triangles lie closer than the clearance less :data:`SLACK`, far above the
rounding of placements and distances (about 1e-15 m) and far below any figure of the model; a distance
within :data:`SLACK` of the clearance goes to coal.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ...jit import njit
from .chain import ik_near, ik_point

#: m: a bound must exceed the clearance by this much to decide a pair (module docstring)
SLACK = 1e-9

#: status of :func:`arm_motion`: a tip out of reach (or at the port), every pair decided clear, pairs left,
#: a pair certainly closer than the clearance (two of its surface points are)
UNREACHABLE, CLEAR, UNDECIDED, WITHIN = 0, 1, 2, 3


class LinkTree(NamedTuple):
    """One arm for :func:`arm_motion` (plain arrays; built by :meth:`.collision.ArmCollision.link_tree`).

    Joints (J of them, pinocchio's order, parents first): ``jparent`` (J,) int64 the parent joint (-1 the
    world), ``jconst`` (J, 4, 4) the parent joint's frame -> this joint's frame (for an actuated joint
    before its motion; for every other joint with its held motion folded in), ``jact`` (J,) int64 the
    actuated index (-1 for a held joint), ``jkind`` (J,) int64 0 revolute, 1 prismatic, ``jaxis`` (J, 3)
    the unit axis in the joint's frame. Objects (G of them): ``gparent`` (G,) int64 their joint (-1 the
    world), ``gplace`` (G, 4, 4) joint frame -> object frame, ``base`` (4, 4) the arm's base pose,
    ``reach`` (G, n) the motion bounds (:meth:`.collision.ArmCollision.motion_bound`), ``center`` (G, 3) and
    ``radius`` (G,) bounding spheres in the object's frame. Capsules (C of them, several per object):
    ``cap_obj`` (C,) int64 their object, ``cap_a``, ``cap_b`` (C, 3) the ends of the axis segment in the
    object's frame, ``cap_r`` (C,) radii; ``cap_start`` (G + 1,) int64 the first capsule of each object
    (capsules sorted by object). Triangles (the narrow phase): ``tris`` (t, 3, 3) the vertices of every mesh
    piece's triangles in their object's frame, sorted by capsule, ``tri_a``, ``tri_b`` (t, 3) and ``tri_r`` (t,)
    a capsule holding each, ``tri_start`` (C + 1,) int64 the first of each capsule's piece (a primitive's piece has
    none: its pairs go to coal). ``hull`` (v, 3) the vertices of each mesh piece's convex hull in their object's
    frame (every vertex of the piece's triangles lies in their hull), sorted by capsule, ``hull_start`` (C + 1,)
    int64 the first of each (a primitive's piece has none)."""

    jparent: np.ndarray
    jconst: np.ndarray
    jact: np.ndarray
    jkind: np.ndarray
    jaxis: np.ndarray
    gparent: np.ndarray
    gplace: np.ndarray
    base: np.ndarray
    reach: np.ndarray
    center: np.ndarray
    radius: np.ndarray
    cap_a: np.ndarray
    cap_b: np.ndarray
    cap_r: np.ndarray
    cap_start: np.ndarray
    tris: np.ndarray
    tri_a: np.ndarray
    tri_b: np.ndarray
    tri_r: np.ndarray
    tri_start: np.ndarray
    hull: np.ndarray
    hull_start: np.ndarray


class HeldShapes(NamedTuple):
    """The held arms' objects (H of them, every held arm's in turn) in the world: ``center`` (H, 3),
    ``radius`` (H,) bounding spheres; capsules ``cap_a``, ``cap_b`` (C, 3), ``cap_r`` (C,), ``cap_start``
    (H + 1,) int64, triangles ``tris`` (t, 3, 3), their capsules ``tri_a``, ``tri_b`` (t, 3), ``tri_r`` (t,) in the world and
    ``tri_start`` (C + 1,), the pieces' hull vertices ``hull`` (v, 3) in the world and ``hull_start`` (C + 1,) as in
    :class:`LinkTree`."""

    center: np.ndarray
    radius: np.ndarray
    cap_a: np.ndarray
    cap_b: np.ndarray
    cap_r: np.ndarray
    cap_start: np.ndarray
    tris: np.ndarray
    tri_a: np.ndarray
    tri_b: np.ndarray
    tri_r: np.ndarray
    tri_start: np.ndarray
    hull: np.ndarray
    hull_start: np.ndarray


# ---------------------------------------------------------------------------- placements
@njit(cache=True)
def _compose(A, B, C):
    """``C = A @ B`` for homogeneous transforms (4, 4) whose last row is (0, 0, 0, 1), written out (a small
    product in numba goes through a general matrix multiply)."""
    for r in range(3):
        a0, a1, a2 = A[r, 0], A[r, 1], A[r, 2]
        for s in range(4):
            C[r, s] = a0 * B[0, s] + a1 * B[1, s] + a2 * B[2, s]
        C[r, 3] += A[r, 3]
    C[3, 0] = C[3, 1] = C[3, 2] = 0.0
    C[3, 3] = 1.0


@njit(cache=True)
def place_objects(tree, q, P):
    """World placements ``P`` (G, 4, 4) of the objects at actuated joint values ``q`` (n,)."""
    J = tree.jparent.shape[0]
    M = np.empty((J, 4, 4))
    X = np.empty((4, 4))
    L = np.empty((4, 4))
    W = np.empty((4, 4))
    for j in range(J):
        C = tree.jconst[j]
        k = tree.jact[j]
        if k >= 0:  # C @ motion(q_k)
            for r in range(4):
                for s in range(4):
                    X[r, s] = 1.0 if r == s else 0.0
            ax, ay, az = tree.jaxis[j, 0], tree.jaxis[j, 1], tree.jaxis[j, 2]
            if tree.jkind[j] == 0:
                c = math.cos(q[k])
                s_ = math.sin(q[k])
                v = 1.0 - c
                X[0, 0], X[0, 1], X[0, 2] = c + ax * ax * v, ax * ay * v - az * s_, ax * az * v + ay * s_
                X[1, 0], X[1, 1], X[1, 2] = ay * ax * v + az * s_, c + ay * ay * v, ay * az * v - ax * s_
                X[2, 0], X[2, 1], X[2, 2] = az * ax * v - ay * s_, az * ay * v + ax * s_, c + az * az * v
            else:
                X[0, 3], X[1, 3], X[2, 3] = ax * q[k], ay * q[k], az * q[k]
            _compose(C, X, L)
        else:
            L[:] = C
        p = tree.jparent[j]
        if p >= 0:
            _compose(M[p], L, M[j])
        else:
            M[j] = L
    for g in range(tree.gparent.shape[0]):
        p = tree.gparent[g]
        if p >= 0:
            _compose(M[p], tree.gplace[g], W)
            _compose(tree.base, W, P[g])
        else:
            _compose(tree.base, tree.gplace[g], P[g])


@njit(cache=True)
def _apply(P, x):
    return (P[0, 0] * x[0] + P[0, 1] * x[1] + P[0, 2] * x[2] + P[0, 3],
            P[1, 0] * x[0] + P[1, 1] * x[1] + P[1, 2] * x[2] + P[1, 3],
            P[2, 0] * x[0] + P[2, 1] * x[1] + P[2, 2] * x[2] + P[2, 3])


@njit(cache=True)
def segment_distance(p0, p1, p2, q0, q1, q2, r0, r1, r2, s0, s1, s2):
    """Distance between the segments p -> q and r -> s (Ericson, "Real-Time Collision Detection", 5.1.9)."""
    x0, x1, x2 = segment_gap(p0, p1, p2, q0, q1, q2, r0, r1, r2, s0, s1, s2)
    return math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)


@njit(cache=True)
def segment_gap(p0, p1, p2, q0, q1, q2, r0, r1, r2, s0, s1, s2):
    """The vector from the closest point of the segment r -> s to the closest point of p -> q."""
    d10, d11, d12 = q0 - p0, q1 - p1, q2 - p2
    d20, d21, d22 = s0 - r0, s1 - r1, s2 - r2
    e0, e1, e2 = p0 - r0, p1 - r1, p2 - r2
    a = d10 * d10 + d11 * d11 + d12 * d12
    e = d20 * d20 + d21 * d21 + d22 * d22
    f = d20 * e0 + d21 * e1 + d22 * e2
    tiny = 1e-300
    if a <= tiny and e <= tiny:
        s = 0.0
        t = 0.0
    elif a <= tiny:
        s = 0.0
        t = min(max(f / e, 0.0), 1.0)
    else:
        c = d10 * e0 + d11 * e1 + d12 * e2
        if e <= tiny:
            t = 0.0
            s = min(max(-c / a, 0.0), 1.0)
        else:
            b = d10 * d20 + d11 * d21 + d12 * d22
            den = a * e - b * b
            s = min(max((b * f - c * e) / den, 0.0), 1.0) if den > 0.0 else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = min(max(-c / a, 0.0), 1.0)
            elif t > 1.0:
                t = 1.0
                s = min(max((b - c) / a, 0.0), 1.0)
    x0 = p0 + d10 * s - (r0 + d20 * t)
    x1 = p1 + d11 * s - (r1 + d21 * t)
    x2 = p2 + d12 * s - (r2 + d22 * t)
    return x0, x1, x2


@njit(cache=True)
def point_triangle(x0, x1, x2, T):
    """Distance from the point x to the triangle ``T`` (3, 3) (its rows the vertices): Ericson, "Real-Time
    Collision Detection", 5.1.5, the closest point by the point's Voronoi region of the triangle."""
    a0, a1, a2 = T[0, 0], T[0, 1], T[0, 2]
    ab0, ab1, ab2 = T[1, 0] - a0, T[1, 1] - a1, T[1, 2] - a2
    ac0, ac1, ac2 = T[2, 0] - a0, T[2, 1] - a1, T[2, 2] - a2
    ap0, ap1, ap2 = x0 - a0, x1 - a1, x2 - a2
    d1 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2
    d2 = ac0 * ap0 + ac1 * ap1 + ac2 * ap2
    if d1 <= 0.0 and d2 <= 0.0:
        y0, y1, y2 = a0, a1, a2
    else:
        bp0, bp1, bp2 = x0 - T[1, 0], x1 - T[1, 1], x2 - T[1, 2]
        d3 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2
        d4 = ac0 * bp0 + ac1 * bp1 + ac2 * bp2
        cp0, cp1, cp2 = x0 - T[2, 0], x1 - T[2, 1], x2 - T[2, 2]
        d5 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2
        d6 = ac0 * cp0 + ac1 * cp1 + ac2 * cp2
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:
            y0, y1, y2 = T[1, 0], T[1, 1], T[1, 2]
        elif d6 >= 0.0 and d5 <= d6:
            y0, y1, y2 = T[2, 0], T[2, 1], T[2, 2]
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            v = d1 / (d1 - d3)
            y0, y1, y2 = a0 + v * ab0, a1 + v * ab1, a2 + v * ab2
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            w = d2 / (d2 - d6)
            y0, y1, y2 = a0 + w * ac0, a1 + w * ac1, a2 + w * ac2
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            y0 = T[1, 0] + w * (T[2, 0] - T[1, 0])
            y1 = T[1, 1] + w * (T[2, 1] - T[1, 1])
            y2 = T[1, 2] + w * (T[2, 2] - T[1, 2])
        else:
            den = va + vb + vc
            if den > 0.0:
                v = vb / den
                w = vc / den
            else:  # a degenerate triangle: its vertex a (the edges' regions above hold the rest)
                v = 0.0
                w = 0.0
            y0, y1, y2 = a0 + ab0 * v + ac0 * w, a1 + ab1 * v + ac1 * w, a2 + ab2 * v + ac2 * w
    e0, e1, e2 = x0 - y0, x1 - y1, x2 - y2
    return math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)


@njit(cache=True)
def _crossing(T, U, i, j):
    """Where the edge ``T[i] -> T[j]`` crosses the plane of triangle ``U``, its distance to ``U`` (0 when the
    edge passes through ``U``); inf when the edge lies on one side of the plane or in it."""
    n0 = (U[1, 1] - U[0, 1]) * (U[2, 2] - U[0, 2]) - (U[1, 2] - U[0, 2]) * (U[2, 1] - U[0, 1])
    n1 = (U[1, 2] - U[0, 2]) * (U[2, 0] - U[0, 0]) - (U[1, 0] - U[0, 0]) * (U[2, 2] - U[0, 2])
    n2 = (U[1, 0] - U[0, 0]) * (U[2, 1] - U[0, 1]) - (U[1, 1] - U[0, 1]) * (U[2, 0] - U[0, 0])
    dp = n0 * (T[i, 0] - U[0, 0]) + n1 * (T[i, 1] - U[0, 1]) + n2 * (T[i, 2] - U[0, 2])
    dq = n0 * (T[j, 0] - U[0, 0]) + n1 * (T[j, 1] - U[0, 1]) + n2 * (T[j, 2] - U[0, 2])
    if (dp > 0.0 and dq > 0.0) or (dp < 0.0 and dq < 0.0) or dp == dq:
        return np.inf
    s = dp / (dp - dq)
    return point_triangle(T[i, 0] + s * (T[j, 0] - T[i, 0]), T[i, 1] + s * (T[j, 1] - T[i, 1]),
                          T[i, 2] + s * (T[j, 2] - T[i, 2]), U)


@njit(cache=True)
def triangle_distance(T, U):
    """Distance between the triangles ``T`` and ``U`` (3, 3) (rows the vertices), 0 where they meet. Two
    triangles that do not meet have a closest pair with a vertex of one or on two edges (the 6 vertex-triangle
    and 9 edge-edge distances); two that meet have an edge of one crossing the other (the crossing's point
    is on both: distance 0). Every term is the distance of two points of the triangles, so none is below
    the true distance, and the smallest is it."""
    best = np.inf
    for i in range(3):
        d = point_triangle(T[i, 0], T[i, 1], T[i, 2], U)
        if d < best:
            best = d
        d = point_triangle(U[i, 0], U[i, 1], U[i, 2], T)
        if d < best:
            best = d
    for i in range(3):
        i2 = (i + 1) % 3
        for j in range(3):
            j2 = (j + 1) % 3
            d = segment_distance(T[i, 0], T[i, 1], T[i, 2], T[i2, 0], T[i2, 1], T[i2, 2],
                                 U[j, 0], U[j, 1], U[j, 2], U[j2, 0], U[j2, 1], U[j2, 2])
            if d < best:
                best = d
    if best > 0.0:
        for i in range(3):
            i2 = (i + 1) % 3
            d = _crossing(T, U, i, i2)
            if d < best:
                best = d
            d = _crossing(U, T, i, i2)
            if d < best:
                best = d
    return best


@njit(cache=True)
def _separation(A, na, U, B, nb, n0, n1, n2):
    """``min_j (U[B[j]] . n) - max_i (A[i] . n)`` over the vertices of the triangles ``A[:na]`` and ``U[B[:nb]]``,
    ``n`` the unit vector along (n0, n1, n2) (A's side first): a lower bound of the distance of the two sets of
    triangles (-inf when n is 0), padded for rounding."""
    nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    if not nn > 0.0:
        return -np.inf
    n0, n1, n2 = n0 / nn, n1 / nn, n2 / nn
    hi = -np.inf
    for i in range(na):
        for v in range(3):
            x = A[i, v, 0] * n0 + A[i, v, 1] * n1 + A[i, v, 2] * n2
            if x > hi:
                hi = x
    lo = np.inf
    for jj in range(nb):
        for v in range(3):
            x = U[B[jj], v, 0] * n0 + U[B[jj], v, 1] * n1 + U[B[jj], v, 2] * n2
            if x < lo:
                lo = x
    return (lo - hi) - 1e-12 * (abs(lo) + abs(hi) + 1.0)


@njit(cache=True)
def _pair_separation(T, U, n0, n1, n2):
    """``min (U . n) - max (T . n)`` over the two triangles' vertices, ``n`` a unit vector: a lower bound of
    their distance, padded for rounding."""
    hi = -np.inf
    lo = np.inf
    for v in range(3):
        x = T[v, 0] * n0 + T[v, 1] * n1 + T[v, 2] * n2
        if x > hi:
            hi = x
        y = U[v, 0] * n0 + U[v, 1] * n1 + U[v, 2] * n2
        if y < lo:
            lo = y
    return (lo - hi) - 1e-12 * (abs(lo) + abs(hi) + 1.0)


#: the most steps of :func:`hull_bound` (each one pass over the two pieces' hull vertices)
HULL_STEPS = 12


@njit(cache=True)
def hull_bound(tree, held, Pg, k, u, n0, n1, n2, target):
    """A lower bound of the distance between moving capsule ``k``'s piece (its object placed by ``Pg`` (4, 4))
    and held capsule ``u``'s piece from their hulls' vertices, the direction that gave it, and an upper bound:
    ``(bound, m0, m1, m2, upper)`` (-inf and inf without hulls); ``upper`` the smallest distance of the support
    vertices met (the hulls' vertices are vertices of the pieces' triangles, so the pieces come that close).

    Along a unit direction ``n`` from the moving piece to the held one, the gap of the two pieces'
    projections, ``min (held . n) - max (moving . n)`` (padded for rounding), bounds their distance from
    below; its largest value over ``n`` is the distance of the two hulls. Gilbert's iteration on the hulls'
    difference climbs towards it from ``n``: ``x`` a point of the difference, the support point ``s`` along
    ``x``, ``x`` moved to the point of the segment ``x -> s`` nearest the origin. Stops once the bound reaches
    ``target``, or ``upper`` falls below ``target - 2 SLACK`` (the caller's "closer than" threshold), or after
    :data:`HULL_STEPS` steps (where the hulls come closer than ``target`` the steps go on for a pair of
    support vertices that close). The moving piece's support is taken in its own frame (the direction turned
    back by ``Pg``), so its vertices are not placed."""
    v0, v1 = tree.hull_start[k], tree.hull_start[k + 1]
    w0, w1 = held.hull_start[u], held.hull_start[u + 1]
    best, m0, m1, m2, upper = -np.inf, n0, n1, n2, np.inf
    if v0 == v1 or w0 == w1:
        return best, m0, m1, m2, upper
    x0 = x1 = x2 = 0.0
    for it in range(HULL_STEPS):
        nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if not nn > 0.0:
            break
        n0, n1, n2 = n0 / nn, n1 / nn, n2 / nn
        l0 = Pg[0, 0] * n0 + Pg[1, 0] * n1 + Pg[2, 0] * n2
        l1 = Pg[0, 1] * n0 + Pg[1, 1] * n1 + Pg[2, 1] * n2
        l2 = Pg[0, 2] * n0 + Pg[1, 2] * n1 + Pg[2, 2] * n2
        hi = -np.inf
        ia = v0
        for v in range(v0, v1):
            y = tree.hull[v, 0] * l0 + tree.hull[v, 1] * l1 + tree.hull[v, 2] * l2
            if y > hi:
                hi = y
                ia = v
        hi += Pg[0, 3] * n0 + Pg[1, 3] * n1 + Pg[2, 3] * n2
        lo = np.inf
        ib = w0
        for w in range(w0, w1):
            y = held.hull[w, 0] * n0 + held.hull[w, 1] * n1 + held.hull[w, 2] * n2
            if y < lo:
                lo = y
                ib = w
        gap = (lo - hi) - 1e-12 * (abs(lo) + abs(hi) + 1.0)
        if gap > best:
            best, m0, m1, m2 = gap, n0, n1, n2
            if best >= target:
                break
        p0, p1, p2 = _apply(Pg, tree.hull[ia])
        s0, s1, s2 = held.hull[ib, 0] - p0, held.hull[ib, 1] - p1, held.hull[ib, 2] - p2
        upper = min(upper, math.sqrt(s0 * s0 + s1 * s1 + s2 * s2))
        if it == 0:
            x0, x1, x2 = s0, s1, s2
        else:
            d0, d1, d2 = s0 - x0, s1 - x1, s2 - x2
            dd = d0 * d0 + d1 * d1 + d2 * d2
            if not dd > 0.0:
                break
            t = min(max(-(x0 * d0 + x1 * d1 + x2 * d2) / dd, 0.0), 1.0)
            x0, x1, x2 = x0 + t * d0, x1 + t * d1, x2 + t * d2
        if upper < target - 2.0 * SLACK:  # two vertices of the pieces within: decided the other way
            break
        n0, n1, n2 = x0, x1, x2
    return best, m0, m1, m2, upper


@njit(cache=True)
def piece_bound(tree, held, Pg, k, u, wa, wb, top, low):
    """:func:`cached_piece_bound` without a memory of earlier calls."""
    return cached_piece_bound(tree, held, Pg, k, u, wa, wb, top, low, np.full(2, -1, np.int64), np.zeros(3))


@njit(cache=True)
def cached_piece_bound(tree, held, Pg, k, u, wa, wb, top, low, wit, axis):
    """The distance between moving capsule ``k``'s piece (its object placed by ``Pg`` (4, 4); the capsule's axis
    in the world ``wa -> wb``) and held capsule ``u``'s piece, both meshes, as far as a caller asking "closer
    than ``low``?" needs it: a value below ``low`` is the distance of two of their triangles (so theirs is
    below ``low`` too); any other value is a lower bound of ``min(distance, top)``, and exactly
    ``min(distance, top)`` when below ``low + 2 SLACK``. Each triangle has a capsule of its own (its longest
    edge, the radius the third vertex's distance from it: it holds the triangle); triangles whose capsules
    lie ``top`` from the other piece's capsule cannot come closer; a separating line (module docstring)
    showing at least ``low + 2 SLACK`` decides; else every pair of triangles, but those whose capsules (or
    projections on the line between their axes) lie farther apart than the smallest distance found so far,
    by :func:`triangle_distance`, stopping at the first below ``low``.

    Before all that, the pair's memory of its earlier calls (other states of the same pieces): ``wit`` (2,)
    int64 the moving and held triangles (indices into ``tree.tris``, ``held.tris``; -1 none) nearest each other
    when last measured, tried first (their distance below ``low`` answers at once: a state near contact is
    mostly decided by the pair that decided the one before), and ``axis`` (3,) the direction of the best
    separation found last time, from which :func:`hull_bound` starts (a bound of at least ``low + 2 SLACK``
    answers). Both are updated; neither changes an answer, only how soon it comes."""
    t0, t1 = tree.tri_start[k], tree.tri_start[k + 1]
    h0, h1 = held.tri_start[u], held.tri_start[u + 1]
    rk, ru = tree.cap_r[k], held.cap_r[u]
    ua0, ua1, ua2 = held.cap_a[u, 0], held.cap_a[u, 1], held.cap_a[u, 2]
    ub0, ub1, ub2 = held.cap_b[u, 0], held.cap_b[u, 1], held.cap_b[u, 2]
    if wit[0] >= 0:  # the two triangles nearest each other last time
        T = np.empty((3, 3))
        for v in range(3):
            T[v, 0], T[v, 1], T[v, 2] = _apply(Pg, tree.tris[wit[0], v])
        d = triangle_distance(T, held.tris[wit[1]])
        if d < low:
            return d
    n0, n1, n2 = axis[0], axis[1], axis[2]
    if n0 == 0.0 and n1 == 0.0 and n2 == 0.0:  # none yet: the line between the capsules' axes
        n0, n1, n2 = segment_gap(ua0, ua1, ua2, ub0, ub1, ub2, wa[0], wa[1], wa[2], wb[0], wb[1], wb[2])
    hb, axis[0], axis[1], axis[2], ub = hull_bound(tree, held, Pg, k, u, n0, n1, n2, low + 2.0 * SLACK)
    if hb >= low + 2.0 * SLACK:
        return min(hb, top)
    if ub < low:  # two vertices of the pieces' triangles that close
        return ub
    A = np.empty((t1 - t0, 3, 3))
    aa = np.empty((t1 - t0, 3))
    ab = np.empty((t1 - t0, 3))
    ar = np.empty(t1 - t0)
    ia = np.empty(t1 - t0, np.int64)
    la = np.empty(t1 - t0)
    lb = np.empty(h1 - h0)
    na = 0
    for t in range(t0, t1):
        p0, p1, p2 = _apply(Pg, tree.tri_a[t])
        q0, q1, q2 = _apply(Pg, tree.tri_b[t])
        gap = segment_distance(p0, p1, p2, q0, q1, q2, ua0, ua1, ua2, ub0, ub1, ub2) - tree.tri_r[t] - ru
        if gap >= top:
            continue
        la[na] = gap
        for v in range(3):
            A[na, v, 0], A[na, v, 1], A[na, v, 2] = _apply(Pg, tree.tris[t, v])
        aa[na, 0], aa[na, 1], aa[na, 2] = p0, p1, p2
        ab[na, 0], ab[na, 1], ab[na, 2] = q0, q1, q2
        ar[na] = tree.tri_r[t]
        ia[na] = t
        na += 1
    if na == 0:
        return top
    B = np.empty(h1 - h0, np.int64)
    nb = 0
    for t in range(h0, h1):
        gap = segment_distance(held.tri_a[t, 0], held.tri_a[t, 1], held.tri_a[t, 2], held.tri_b[t, 0], held.tri_b[t, 1],
                               held.tri_b[t, 2], wa[0], wa[1], wa[2], wb[0], wb[1], wb[2]) - held.tri_r[t] - rk
        if gap < top:
            B[nb] = t
            lb[nb] = gap
            nb += 1
    if nb == 0:
        return top
    # a witness first: the few triangles of each side nearest the other side's capsule
    oa = np.argsort(la[:na])
    ob = np.argsort(lb[:nb])
    wi, wj, wd = oa[0], B[ob[0]], np.inf
    for ii in range(min(na, 3)):
        for j0 in range(min(nb, 3)):
            d = triangle_distance(A[oa[ii]], held.tris[B[ob[j0]]])
            if d < wd:
                wi, wj, wd = oa[ii], B[ob[j0]], d
                wit[0], wit[1] = ia[wi], wj
            if d < low:
                return d
    # separating directions: the survivors' vertices projected on a line; every point of a triangle lies
    # between its vertices' projections, so the gap of the projections bounds the distance from below (exact
    # for two convex pieces facing along that line, as the links' pieces mostly do). Tried: the line between
    # the two capsules' axes at their closest points, the line between the survivors' centroids, the line
    # between the axes of the nearest two triangles of the witness pass.
    x0, x1, x2 = segment_gap(ua0, ua1, ua2, ub0, ub1, ub2, wa[0], wa[1], wa[2], wb[0], wb[1], wb[2])
    sep = _separation(A, na, held.tris, B, nb, x0, x1, x2)
    if sep < low + 2.0 * SLACK:
        m0 = m1 = m2 = 0.0
        for i in range(na):
            for v in range(3):
                m0 += A[i, v, 0]
                m1 += A[i, v, 1]
                m2 += A[i, v, 2]
        n0 = n1 = n2 = 0.0
        for jj in range(nb):
            for v in range(3):
                n0 += held.tris[B[jj], v, 0]
                n1 += held.tris[B[jj], v, 1]
                n2 += held.tris[B[jj], v, 2]
        sep = max(sep, _separation(A, na, held.tris, B, nb, n0 / nb - m0 / na, n1 / nb - m1 / na, n2 / nb - m2 / na))
    if sep < low + 2.0 * SLACK:  # the line between the axes of the nearest two triangles met above
        x0, x1, x2 = segment_gap(held.tri_a[wj, 0], held.tri_a[wj, 1], held.tri_a[wj, 2], held.tri_b[wj, 0],
                                 held.tri_b[wj, 1], held.tri_b[wj, 2], aa[wi, 0], aa[wi, 1], aa[wi, 2],
                                 ab[wi, 0], ab[wi, 1], ab[wi, 2])
        sep = max(sep, _separation(A, na, held.tris, B, nb, x0, x1, x2))
    if sep >= low + 2.0 * SLACK:
        return min(sep, top)
    # every pair, nearest triangles first (a pair within the clearance is met early)
    best = top
    for ii in range(na):
        i = oa[ii]
        for j0 in range(nb):
            jj = ob[j0]
            j = B[jj]
            y0, y1, y2 = segment_gap(held.tri_a[j, 0], held.tri_a[j, 1], held.tri_a[j, 2],
                                     held.tri_b[j, 0], held.tri_b[j, 1], held.tri_b[j, 2],
                                     aa[i, 0], aa[i, 1], aa[i, 2], ab[i, 0], ab[i, 1], ab[i, 2])
            ny = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
            if ny - ar[i] - held.tri_r[j] >= best:
                continue
            if ny > 0.0 and _pair_separation(A[i], held.tris[j], y0 / ny, y1 / ny, y2 / ny) >= best:
                continue
            d = triangle_distance(A[i], held.tris[j])
            if d < best:
                best = d
                if d < wd:
                    wd = d
                    wit[0], wit[1] = ia[i], j
                if best < low:
                    return best
    return best


@njit(cache=True)
def pair_bound(tree, held, P, g, h, c, top, sample, rows, m, known, moved, wit, axes):
    """The broad and narrow phases for moving object ``g`` (placed by ``P`` (G, 4, 4)) and held object ``h``:
    ``(bound, within, rows, m)``. ``bound`` is a lower bound of their distance, at least ``min(distance,
    top)`` where every piece pair is a pair of meshes (the larger of the spheres' gap and, per pair of pieces,
    of the capsules' gap and :func:`piece_bound`); ``within`` True when two of their triangles lie closer than
    ``c - SLACK`` (certainly within the clearance; the bound is then that distance). A pair of pieces that
    cannot be decided here (a primitive's piece, whose solid coal measures, or a distance within
    :data:`SLACK` of ``c``) is appended to ``rows`` as ``(sample, moving capsule, held capsule)`` (grown as
    needed) for coal. ``known`` (moving capsules, held capsules): per pair of pieces, a lower bound of their
    distance found before plus how far object ``g`` had moved then; ``moved``, how far it has moved now: a
    pair with ``known - moved >= c + SLACK`` is clear without a look (the distance is 1-Lipschitz in g's
    points), every other pair looked at updates it. ``wit`` (moving capsules, held capsules, 2), ``axes`` (moving
    capsules, held capsules, 3): each pair of pieces' memory (:func:`cached_piece_bound`)."""
    cut = c + SLACK
    c0, c1, c2 = _apply(P[g], tree.center[g])
    x0 = c0 - held.center[h, 0]
    x1 = c1 - held.center[h, 1]
    x2 = c2 - held.center[h, 2]
    sg = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2) - tree.radius[g] - held.radius[h]
    if sg >= top:
        return sg, False, rows, m
    k0, k1 = tree.cap_start[g], tree.cap_start[g + 1]
    wa = np.empty(3)
    wb = np.empty(3)
    cg = np.inf
    for k in range(k0, k1):
        wa[0], wa[1], wa[2] = _apply(P[g], tree.cap_a[k])
        wb[0], wb[1], wb[2] = _apply(P[g], tree.cap_b[k])
        for u in range(held.cap_start[h], held.cap_start[h + 1]):
            dk = known[k, u] - moved
            if dk >= cut:
                if dk < cg:
                    cg = dk
                continue
            dk = segment_distance(wa[0], wa[1], wa[2], wb[0], wb[1], wb[2],
                                  held.cap_a[u, 0], held.cap_a[u, 1], held.cap_a[u, 2],
                                  held.cap_b[u, 0], held.cap_b[u, 1], held.cap_b[u, 2])
            dk -= tree.cap_r[k] + held.cap_r[u]
            if dk < top:
                mesh = tree.tri_start[k + 1] > tree.tri_start[k] and held.tri_start[u + 1] > held.tri_start[u]
                exact = cached_piece_bound(tree, held, P[g], k, u, wa, wb, top, c - SLACK, wit[k, u],
                                           axes[k, u]) if mesh else -np.inf
                if exact < c - SLACK and mesh:
                    return exact, True, rows, m
                if exact > dk:
                    dk = exact
                if dk < cut:  # a primitive's piece, or a tie with the clearance
                    if m == rows.shape[0]:
                        grown = np.empty((2 * m + 16, 3), np.int64)
                        grown[:m] = rows[:m]
                        rows = grown
                    rows[m, 0] = sample
                    rows[m, 1] = k
                    rows[m, 2] = u
                    m += 1
            known[k, u] = dk + moved
            if dk < cg:
                cg = dk
    return max(sg, cg), False, rows, m


# ---------------------------------------------------------------------------- the arm at its tips
@njit(cache=True)
def _wrist(t0, t1, t2, port, L):
    """The wrist of the rigid shaft of length ``L`` from tip t through ``port``; ok False at the port."""
    d0, d1, d2 = t0 - port[0], t1 - port[1], t2 - port[2]
    nd = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if not nd > 0.0:
        return False, 0.0, 0.0, 0.0
    return True, t0 - L * d0 / nd, t1 - L * d1 / nd, t2 - L * d2 / nd


@njit(cache=True)
def _max_reach(reach, q0, q1):
    """``max_g sum_j reach[g, j] |q1_j - q0_j|`` (:meth:`.collision.ArmCollision.motion_bound`)."""
    best = 0.0
    for g in range(reach.shape[0]):
        s = 0.0
        for j in range(reach.shape[1]):
            s += reach[g, j] * abs(q1[j] - q0[j])
        if s > best:
            best = s
    return best


@njit(cache=True)
def tip_configs(chain, rmap, reach, a, b, port, L, ref, tip_step):
    """Configurations (k + 1, n) at the tips ``a + (i / k) (b - a)``, ``k = max(1, ceil(|b - a| /
    tip_step))``, each on the branch of the one before (:meth:`ArmChecks.motion_configs`); with ``a == b``
    the one configuration at ``a`` (1, n). The first from ``ref`` (NaN: none), the others from it; where a
    step jumps branch (a link point moving more than 50 tip steps), redone one by one from the previous
    one. ok False when a tip is out of reach or at the port."""
    n = chain.axis.shape[0]
    single = a[0] == b[0] and a[1] == b[1] and a[2] == b[2]
    q0 = np.empty(n)
    ok, w0, w1, w2 = _wrist(a[0], a[1], a[2], port, L)
    if not ok:
        return False, np.empty((0, n))
    if ref[0] == ref[0]:
        ok = ik_near(chain, rmap, w0, w1, w2, ref, q0)
    else:
        ok = ik_point(chain, rmap, w0, w1, w2, q0)
    if not ok:
        return False, np.empty((0, n))
    if single:
        Q = np.empty((1, n))
        Q[0] = q0
        return True, Q
    e0, e1, e2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    k = max(1, int(math.ceil(math.sqrt(e0 * e0 + e1 * e1 + e2 * e2) / tip_step)))
    W = np.empty((k + 1, 3))
    for i in range(k + 1):
        s = i / k
        ok, W[i, 0], W[i, 1], W[i, 2] = _wrist(a[0] + s * e0, a[1] + s * e1, a[2] + s * e2, port, L)
        if not ok:
            return False, np.empty((0, n))
    Q = np.empty((k + 1, n))
    for i in range(k + 1):
        if not ik_near(chain, rmap, W[i, 0], W[i, 1], W[i, 2], q0, Q[i]):
            return False, np.empty((0, n))
    Q[0] = q0
    bad = -1
    for i in range(k):
        if _max_reach(reach, Q[i], Q[i + 1]) > 50.0 * tip_step:
            bad = i
            break
    if bad >= 0:
        for i in range(bad + 1, k + 1):
            if not ik_near(chain, rmap, W[i, 0], W[i, 1], W[i, 2], Q[i - 1], Q[i]):
                return False, np.empty((0, n))
    return True, Q


@njit(cache=True)
def joint_samples(reach, Q, c):
    """:func:`.collision.motion_samples` of the waypoints ``Q`` (m, n): the piecewise-straight joint-space
    motion split so that no point moves more than ``c / 2`` between two samples; and ``cum`` (k,), the
    bound on how far a point moves from the first sample to each."""
    m, n = Q.shape
    steps = np.empty(max(m - 1, 0), np.int64)
    total = 1
    for i in range(m - 1):
        st = max(1, int(math.ceil(_max_reach(reach, Q[i], Q[i + 1]) / (0.5 * c) * (1.0 + 1e-12))))
        steps[i] = st
        total += st
    S = np.empty((total, n))
    S[0] = Q[0]
    r = 1
    for i in range(m - 1):
        st = steps[i]
        for j in range(1, st + 1):
            s = j / st
            for u in range(n):
                S[r, u] = Q[i, u] + s * (Q[i + 1, u] - Q[i, u])
            r += 1
    cum = np.zeros(total)
    for i in range(1, total):
        cum[i] = cum[i - 1] + _max_reach(reach, S[i - 1], S[i])
    return S, cum


@njit(cache=True)
def object_travel(reach, S):
    """``T[i, g]`` (k, G): the bound on how far a point of object ``g`` moves from the first sample of ``S``
    (k, n) to sample ``i`` along the straight joint-space steps between them (``reach[g] . |dq|`` summed)."""
    k, n = S.shape
    G = reach.shape[0]
    T = np.zeros((k, G))
    for i in range(1, k):
        for g in range(G):
            s = 0.0
            for j in range(n):
                s += reach[g, j] * abs(S[i, j] - S[i - 1, j])
            T[i, g] = T[i - 1, g] + s
    return T


@njit(cache=True)
def _nearest_first(gaps, cut):
    """The indices of ``gaps`` below ``cut``, smallest first (ties in index order): an insertion sort, as
    there are a few."""
    idx = np.empty(gaps.shape[0], np.int64)
    n = 0
    for i in range(gaps.shape[0]):
        if gaps[i] < cut:
            j = n
            while j > 0 and gaps[idx[j - 1]] > gaps[i]:
                idx[j] = idx[j - 1]
                j -= 1
            idx[j] = i
            n += 1
    return idx[:n]


@njit(cache=True)
def arm_motion(chain, rmap, tree, held, a, b, port, L, ref, tip_step, c, memory=None):
    """The moving arm's motion ``a -> b`` (a tip when ``a == b``) against the held arms (module docstring).

    Returns ``(status, S, P, pairs)``: ``status`` :data:`UNREACHABLE`, :data:`CLEAR` (every pair of every
    sample decided at least ``c`` apart), :data:`WITHIN` (two triangles of some sample closer than ``c``: the
    samples after it are not looked at) or :data:`UNDECIDED`; ``S`` (k, n) the joint-space samples; ``P``
    (k, G, 4, 4) the placements of the samples that were placed; ``pairs`` (m, 3) int64 rows (sample, moving
    capsule, held capsule) that only coal can decide (:func:`pair_bound`), sample by sample: the motion keeps
    the clearance iff no two of those capsules' pieces are closer than ``c``.

    Skipping, per pair of objects (moving g, held h): the bound of :func:`pair_bound` at sample s less how far
    g's points may have moved since (:func:`object_travel`) is a lower bound of their distance at every later
    sample (the distance is 1-Lipschitz in g's points); while it is at least the clearance the pair is not
    looked at, and a sample none of whose pairs is looked at is not placed; the same per pair of their mesh
    pieces inside :func:`pair_bound`.

    ``memory``: :func:`piece_memory`'s arrays, each pair of pieces' witness triangles and separating direction
    from the calls before (kept by the caller from call to call; None: none kept)."""
    n = chain.axis.shape[0]
    G = tree.gparent.shape[0]
    H = held.radius.shape[0]
    ok, Q = tip_configs(chain, rmap, tree.reach, a, b, port, L, ref, tip_step)
    if not ok:
        return UNREACHABLE, Q, np.empty((0, G, 4, 4)), np.empty((0, 3), np.int64)
    if Q.shape[0] == 1:
        S = Q
    else:
        S, _ = joint_samples(tree.reach, Q, c)
    k = S.shape[0]
    P = np.empty((k, G, 4, 4))
    if H == 0:
        return CLEAR, S, P, np.empty((0, 3), np.int64)
    cut = c + SLACK
    travel = object_travel(tree.reach, S)
    known = np.full((G, H), -np.inf)  # per pair: its bound plus its object's travel at the sample it was found
    pieces = np.full((tree.cap_r.shape[0], held.cap_r.shape[0]), -np.inf)  # the same per pair of pieces
    if memory is None:
        wit = np.full((tree.cap_r.shape[0], held.cap_r.shape[0], 2), -1, np.int64)
        axes = np.zeros((tree.cap_r.shape[0], held.cap_r.shape[0], 3))
    else:
        wit, axes = memory
    rows = np.empty((16, 3), np.int64)
    m = 0
    order = np.arange(G * H)
    for i in range(k):
        placed = False
        if k == 1:  # one state: the pairs of objects whose spheres come within the clearance, nearest first
            # (a state within the clearance ends early; the other pairs are clear)
            place_objects(tree, S[i], P[i])
            placed = True
            gaps = np.empty(G * H)
            for g in range(G):
                c0, c1, c2 = _apply(P[i, g], tree.center[g])
                for h in range(H):
                    x0, x1, x2 = c0 - held.center[h, 0], c1 - held.center[h, 1], c2 - held.center[h, 2]
                    gaps[g * H + h] = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2) - tree.radius[g] - held.radius[h]
            order = _nearest_first(gaps, cut)
        for gh in order:
            g, h = gh // H, gh % H
            if known[g, h] - travel[i, g] >= cut:
                continue
            if not placed:
                place_objects(tree, S[i], P[i])
                placed = True
            d, within, rows, m = pair_bound(tree, held, P[i], g, h, c, cut, i, rows, m, pieces, travel[i, g], wit,
                                            axes)
            if within:
                return WITHIN, S, P, np.empty((0, 3), np.int64)
            known[g, h] = d + travel[i, g]
    return (UNDECIDED if m else CLEAR), S, P, rows[:m]



# ---------------------------------------------------------------------------- one call per check
#: the number of dimensions of each field of :class:`LinkTree` and of :class:`HeldShapes`, negative for int64
_TREE_DIMS = (-1, 3, -1, -1, 2, -1, 3, 2, 2, 2, 1, 2, 2, 1, -1, 3, 2, 2, 1, -1, 2, -1)
_HELD_DIMS = (2, 1, 2, 2, 1, -1, 3, 2, 2, 1, -1, 2, -1)
_HEAD = 5  # per field: its offset in its buffer, then its shape (up to 4 dimensions)


def pack_shapes(tree: LinkTree, held: HeldShapes) -> tuple[np.ndarray, np.ndarray]:
    """The tree's and the held shapes' arrays in two buffers, ``(floats, ints)``, for :func:`arm_check`: a
    compiled call spends about a quarter of a microsecond taking each array it is given, and the two hold
    some 35. ``ints`` begins with a header of :data:`_HEAD` int64 per field (its offset in its buffer, its
    shape)."""
    fields = tuple(tree) + tuple(held)
    dims = _TREE_DIMS + _HELD_DIMS
    head = np.zeros(_HEAD * len(fields), np.int64)
    floats, ints, nf, ni = [], [], 0, len(head)
    for i, (x, d) in enumerate(zip(fields, dims)):
        x = np.ascontiguousarray(x, dtype=np.int64 if d < 0 else float)
        if x.ndim != abs(d):
            raise ValueError(f"field {i} of the shapes has {x.ndim} dimensions, not {abs(d)}")
        head[_HEAD * i + 1:_HEAD * i + 1 + x.ndim] = x.shape
        if d < 0:
            head[_HEAD * i] = ni
            ints.append(x.ravel())
            ni += x.size
        else:
            head[_HEAD * i] = nf
            floats.append(x.ravel())
            nf += x.size
    return np.concatenate(floats), np.concatenate([head] + ints)


@njit(cache=True)
def _f1(F, I, i):
    o = I[_HEAD * i]
    return F[o:o + I[_HEAD * i + 1]]


@njit(cache=True)
def _f2(F, I, i):
    o, a, b = I[_HEAD * i], I[_HEAD * i + 1], I[_HEAD * i + 2]
    return F[o:o + a * b].reshape((a, b))


@njit(cache=True)
def _f3(F, I, i):
    o, a, b, c = I[_HEAD * i], I[_HEAD * i + 1], I[_HEAD * i + 2], I[_HEAD * i + 3]
    return F[o:o + a * b * c].reshape((a, b, c))


@njit(cache=True)
def _i1(I, i):
    o = I[_HEAD * i]
    return I[o:o + I[_HEAD * i + 1]]


@njit(cache=True)
def unpack_shapes(F, I):
    """:func:`pack_shapes`' buffers back to ``(LinkTree, HeldShapes)`` (views, no copies)."""
    tree = LinkTree(_i1(I, 0), _f3(F, I, 1), _i1(I, 2), _i1(I, 3), _f2(F, I, 4), _i1(I, 5), _f3(F, I, 6),
                    _f2(F, I, 7), _f2(F, I, 8), _f2(F, I, 9), _f1(F, I, 10), _f2(F, I, 11), _f2(F, I, 12),
                    _f1(F, I, 13), _i1(I, 14), _f3(F, I, 15), _f2(F, I, 16), _f2(F, I, 17), _f1(F, I, 18),
                    _i1(I, 19), _f2(F, I, 20), _i1(I, 21))
    held = HeldShapes(_f2(F, I, 22), _f1(F, I, 23), _f2(F, I, 24), _f2(F, I, 25), _f1(F, I, 26), _i1(I, 27),
                      _f3(F, I, 28), _f2(F, I, 29), _f2(F, I, 30), _f1(F, I, 31), _i1(I, 32), _f2(F, I, 33),
                      _i1(I, 34))
    return tree, held


@njit(cache=True)
def arm_check(chain, rmap, F, I, a, b, port, L, ref, tip_step, c, wit, axes):
    """:func:`arm_motion` with the tree and the held shapes packed by :func:`pack_shapes` and the memory
    :func:`piece_memory`'s ``(wit, axes)``: the planner's per-check call, with a few arrays to take instead of
    some forty."""
    tree, held = unpack_shapes(F, I)
    return arm_motion(chain, rmap, tree, held, a, b, port, L, ref, tip_step, c, (wit, axes))


def piece_memory(tree: LinkTree, held: HeldShapes) -> tuple[np.ndarray, np.ndarray]:
    """Empty memories of every pair of pieces for :func:`arm_motion`: witnesses (moving capsules, held capsules,
    2) int64 all -1, directions (moving capsules, held capsules, 3) all 0."""
    shape = (tree.cap_r.shape[0], held.cap_r.shape[0])
    return np.full(shape + (2,), -1, np.int64), np.zeros(shape + (3,))


def tree_arrays(tree: LinkTree) -> LinkTree:
    """The tree with every array as the kernels take it (C-contiguous, writeable, int64 indices)."""
    return LinkTree(*(np.ascontiguousarray(x, dtype=np.int64 if x.dtype.kind in "iu" else float) for x in tree))


__all__ = ["LinkTree", "HeldShapes", "place_objects", "pair_bound", "piece_bound", "cached_piece_bound",
           "hull_bound", "piece_memory", "pack_shapes", "unpack_shapes", "arm_check", "triangle_distance", "point_triangle",
           "segment_distance", "tip_configs", "joint_samples", "object_travel", "arm_motion", "SLACK", "UNREACHABLE",
           "CLEAR", "UNDECIDED", "WITHIN"]
