"""The arm checks' compiled part: the moving arm at its tips (the wrist on the rigid shaft through the
port, the chain's inverse kinematics), its links' placements, the joint-space samples of a motion and a
conservative broad phase against arms held still (docs/physics.md, "Several instruments and the
endoscope", "Arms outside"). Numba kernels on plain arrays; the exact distances stay coal's
(:mod:`.collision`, which builds these arrays and asks coal about the pairs this part cannot decide).

* :class:`LinkTree`: the arm's joints and collision objects as fixed transforms (pinocchio's kinematic
  tree with every joint off the actuated set at its held value), the objects' bounding spheres and
  bounding capsules in their own frames, and the per-object motion bounds (``reach``);
* :class:`HeldShapes`: the held arms' objects' bounding spheres and capsules in the world;
* :func:`arm_motion`: for a straight tip motion ``a -> b`` (or one tip), the configurations at the tip
  samples (as :meth:`errplan.planning.arm_checks.ArmChecks.motion_configs` finds them), the joint-space
  samples (:func:`.collision.motion_samples`), and per sample the pairs (moving object, held object)
  whose bounding volumes come closer than the clearance. Every other pair of every sample is at least
  that clearance apart: capsules and spheres hold their object (each capsule holds the vertices of its
  triangles, so, being convex, the triangles), and the gap between two bounding volumes is a lower
  bound of the distance of what they hold. Samples are skipped as
  :func:`.collision.clear_along_held` skips them (the clearance is 1-Lipschitz in the links' motion).

Rounding: a pair counts as decided only when its bound exceeds the clearance by :data:`SLACK` (1 nm),
far above the rounding of placements and distances (about 1e-15 m) and far below any figure of the
model, so a pair the exact query would find within the clearance is never decided here.
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
    (capsules sorted by object). Surface points (for the upper bound): ``points`` (k, 3) in their object's
    frame, ``point_start`` (C + 1,) int64 the first of each capsule's piece."""

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
    points: np.ndarray
    point_start: np.ndarray


class HeldShapes(NamedTuple):
    """The held arms' objects (H of them, every held arm's in turn) in the world: ``center`` (H, 3),
    ``radius`` (H,) bounding spheres; capsules ``cap_a``, ``cap_b`` (C, 3), ``cap_r`` (C,), ``cap_start``
    (H + 1,) int64, surface points ``points`` (k, 3) in the world, ``point_start`` (C + 1,) as in
    :class:`LinkTree`."""

    center: np.ndarray
    radius: np.ndarray
    cap_a: np.ndarray
    cap_b: np.ndarray
    cap_r: np.ndarray
    cap_start: np.ndarray
    points: np.ndarray
    point_start: np.ndarray


# ---------------------------------------------------------------------------- placements
@njit(cache=True)
def place_objects(tree, q, P):
    """World placements ``P`` (G, 4, 4) of the objects at actuated joint values ``q`` (n,)."""
    J = tree.jparent.shape[0]
    M = np.empty((J, 4, 4))
    X = np.empty((4, 4))
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
            L = C @ X
        else:
            L = C
        p = tree.jparent[j]
        if p >= 0:
            M[j] = M[p] @ L
        else:
            M[j] = L
    for g in range(tree.gparent.shape[0]):
        p = tree.gparent[g]
        if p >= 0:
            P[g] = tree.base @ (M[p] @ tree.gplace[g])
        else:
            P[g] = tree.base @ tree.gplace[g]


@njit(cache=True)
def _apply(P, x):
    return (P[0, 0] * x[0] + P[0, 1] * x[1] + P[0, 2] * x[2] + P[0, 3],
            P[1, 0] * x[0] + P[1, 1] * x[1] + P[1, 2] * x[2] + P[1, 3],
            P[2, 0] * x[0] + P[2, 1] * x[1] + P[2, 2] * x[2] + P[2, 3])


@njit(cache=True)
def segment_distance(p0, p1, p2, q0, q1, q2, r0, r1, r2, s0, s1, s2):
    """Distance between the segments p -> q and r -> s (Ericson, "Real-Time Collision Detection", 5.1.9)."""
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
    return math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)


@njit(cache=True)
def sample_pairs(tree, held, P, c, cut, sample, rows, m):
    """The broad phase at one sample (moving objects at world placements ``P`` (G, 4, 4)): per pair of
    objects (moving, held) the spheres' gap, and where it is below ``cut`` the gaps of their capsules; the
    capsule pairs below ``cut`` are appended to ``rows`` (grown as needed) from row ``m`` as ``(sample,
    moving capsule, held capsule)``. Returns ``(d, within, rows, m)``: ``d`` the smallest lower bound over
    the pairs of objects (each the larger of its spheres' and its capsules' gap), ``within`` whether two
    surface points of an undecided pair lie closer than ``c`` (then the rows are incomplete)."""
    G = P.shape[0]
    H = held.radius.shape[0]
    d = np.inf
    for g in range(G):
        c0, c1, c2 = _apply(P[g], tree.center[g])
        rg = tree.radius[g]
        k0, k1 = tree.cap_start[g], tree.cap_start[g + 1]
        wa = np.empty((0, 3))
        wb = np.empty((0, 3))
        for h in range(H):
            x0 = c0 - held.center[h, 0]
            x1 = c1 - held.center[h, 1]
            x2 = c2 - held.center[h, 2]
            sg = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2) - rg - held.radius[h]
            if sg < cut:
                if wa.shape[0] == 0:  # this object's capsules in the world, placed once
                    wa = np.empty((k1 - k0, 3))
                    wb = np.empty((k1 - k0, 3))
                    for k in range(k0, k1):
                        wa[k - k0, 0], wa[k - k0, 1], wa[k - k0, 2] = _apply(P[g], tree.cap_a[k])
                        wb[k - k0, 0], wb[k - k0, 1], wb[k - k0, 2] = _apply(P[g], tree.cap_b[k])
                cg = np.inf
                for k in range(k0, k1):
                    i = k - k0
                    for u in range(held.cap_start[h], held.cap_start[h + 1]):
                        dk = segment_distance(wa[i, 0], wa[i, 1], wa[i, 2], wb[i, 0], wb[i, 1], wb[i, 2],
                                              held.cap_a[u, 0], held.cap_a[u, 1], held.cap_a[u, 2],
                                              held.cap_b[u, 0], held.cap_b[u, 1], held.cap_b[u, 2])
                        dk -= tree.cap_r[k] + held.cap_r[u]
                        if dk < cg:
                            cg = dk
                        if dk < cut:
                            if points_within(tree, held, P[g], k, u, c - SLACK):
                                return dk, True, rows, m
                            if m == rows.shape[0]:
                                grown = np.empty((2 * m + 16, 3), np.int64)
                                grown[:m] = rows[:m]
                                rows = grown
                            rows[m, 0] = sample
                            rows[m, 1] = k
                            rows[m, 2] = u
                            m += 1
                if cg > sg:
                    sg = cg
            if sg < d:
                d = sg
    return d, False, rows, m


@njit(cache=True)
def points_within(tree, held, P, k, u, c):
    """Whether a surface point of moving capsule ``k``'s piece (its object placed by ``P`` (4, 4)) lies closer
    than ``c`` to one of held capsule ``u``'s: then the two pieces do (an upper bound of their distance)."""
    k0, k1 = tree.point_start[k], tree.point_start[k + 1]
    m0, m1 = held.point_start[u], held.point_start[u + 1]
    if k0 == k1 or m0 == m1:
        return False
    c2 = c * c
    for k in range(k0, k1):
        x0, x1, x2 = _apply(P, tree.points[k])
        for m in range(m0, m1):
            y0 = x0 - held.points[m, 0]
            y1 = x1 - held.points[m, 1]
            y2 = x2 - held.points[m, 2]
            if y0 * y0 + y1 * y1 + y2 * y2 < c2:
                return True
    return False


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
def arm_motion(chain, rmap, tree, held, a, b, port, L, ref, tip_step, c):
    """The moving arm's motion ``a -> b`` (a tip when ``a == b``) against the held arms (module docstring).

    Returns ``(status, S, P, pairs)``: ``status`` :data:`UNREACHABLE`, :data:`CLEAR` (every pair of every
    sample decided at least ``c`` apart), :data:`WITHIN` (a pair of some sample certainly closer than ``c``:
    two of its surface points are; the samples after it are not looked at) or :data:`UNDECIDED`; ``S`` (k, n) the joint-space samples; ``P``
    (k, G, 4, 4) the placements of the samples that were placed; ``pairs`` (m, 3) int64 rows (sample, moving
    capsule, held capsule) whose capsules' gap is below ``c + SLACK``, sample by sample: the motion keeps
    the clearance iff no two of those capsules' pieces (their triangles, or the primitive) are closer
    than ``c``."""
    n = chain.axis.shape[0]
    G = tree.gparent.shape[0]
    H = held.radius.shape[0]
    ok, Q = tip_configs(chain, rmap, tree.reach, a, b, port, L, ref, tip_step)
    if not ok:
        return UNREACHABLE, Q, np.empty((0, G, 4, 4)), np.empty((0, 3), np.int64)
    if Q.shape[0] == 1:
        S = Q
        cum = np.zeros(1)
    else:
        S, cum = joint_samples(tree.reach, Q, c)
    k = S.shape[0]
    P = np.empty((k, G, 4, 4))
    if H == 0:
        return CLEAR, S, P, np.empty((0, 3), np.int64)
    cut = c + SLACK
    rows = np.empty((16, 3), np.int64)
    m = 0
    reach_to = -np.inf  # the largest d_i + cum_i - cut: every sample j with cum_j up to it is clear
    for i in range(k):
        if cum[i] <= reach_to:
            continue
        place_objects(tree, S[i], P[i])
        d, within, rows, m = sample_pairs(tree, held, P[i], c, cut, i, rows, m)
        if within:
            return WITHIN, S, P, np.empty((0, 3), np.int64)
        if d >= cut and d + cum[i] - cut > reach_to:
            reach_to = d + cum[i] - cut
    return (UNDECIDED if m else CLEAR), S, P, rows[:m]


def tree_arrays(tree: LinkTree) -> LinkTree:
    """The tree with every array as the kernels take it (C-contiguous, writeable, int64 indices)."""
    return LinkTree(*(np.ascontiguousarray(x, dtype=np.int64 if x.dtype.kind in "iu" else float) for x in tree))


__all__ = ["LinkTree", "HeldShapes", "place_objects", "sample_pairs", "segment_distance", "tip_configs",
           "joint_samples", "object_travel", "arm_motion", "SLACK", "UNREACHABLE", "CLEAR", "UNDECIDED", "WITHIN", "points_within"]
