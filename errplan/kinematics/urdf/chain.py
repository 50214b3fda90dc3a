"""The compiled chain: forward kinematics, Jacobians and inverse kinematics of the wrist (numba kernels
on :class:`~.model.ChainData`), and the reachability answer at a point (:func:`reach_point`: the map,
exact IK in its boundary voxels). Scalar kernels for other compiled code, ``*_many`` loops for arrays."""
from __future__ import annotations

import math
import numpy as np
from ...jit import njit

from .model import IK_TOL, LIMIT_TOL, TWO_PI


# Helpers on tuples of scalars (_mm, _column, _dot) are real calls, not forced inline: LLVM inlines them
# all the same (no arrays, no reference counts), while numba's own inlining typed and lowered a copy at
# each of their call sites in _fkjacz3, _solve and _local3 (about 2 s of the first run's compile). Helpers that
# take the chain or the map (namedtuples of arrays) stay inline: a call would reference-count them.
@njit(cache=True)
def _mm(A, B):
    return (A[0] * B[0] + A[1] * B[3] + A[2] * B[6], A[0] * B[1] + A[1] * B[4] + A[2] * B[7],
            A[0] * B[2] + A[1] * B[5] + A[2] * B[8],
            A[3] * B[0] + A[4] * B[3] + A[5] * B[6], A[3] * B[1] + A[4] * B[4] + A[5] * B[7],
            A[3] * B[2] + A[4] * B[5] + A[5] * B[8],
            A[6] * B[0] + A[7] * B[3] + A[8] * B[6], A[6] * B[1] + A[7] * B[4] + A[8] * B[7],
            A[6] * B[2] + A[7] * B[5] + A[8] * B[8])


@njit(cache=True, inline="always")
def _start(chain):
    T = chain.T
    R = (T[0, 0, 0], T[0, 0, 1], T[0, 0, 2], T[0, 1, 0], T[0, 1, 1], T[0, 1, 2],
         T[0, 2, 0], T[0, 2, 1], T[0, 2, 2])
    p = (T[0, 0, 3], T[0, 1, 3], T[0, 2, 3])
    return R, p


@njit(cache=True, inline="always")
def _advance(chain, i, qi, R, p):
    """Frame (R, p) of joint i (before its motion) -> frame of joint i+1 (or the wrist)."""
    ax, ay, az = chain.axis[i, 0], chain.axis[i, 1], chain.axis[i, 2]
    if chain.jtype[i] == 0:
        c = math.cos(qi)
        s = math.sin(qi)
        v = 1.0 - c
        M = (c + ax * ax * v, ax * ay * v - az * s, ax * az * v + ay * s,
             ay * ax * v + az * s, c + ay * ay * v, ay * az * v - ax * s,
             az * ax * v - ay * s, az * ay * v + ax * s, c + az * az * v)
        R = _mm(R, M)
    else:
        p = (p[0] + (R[0] * ax + R[1] * ay + R[2] * az) * qi,
             p[1] + (R[3] * ax + R[4] * ay + R[5] * az) * qi,
             p[2] + (R[6] * ax + R[7] * ay + R[8] * az) * qi)
    T = chain.T
    k = i + 1
    t0, t1, t2 = T[k, 0, 3], T[k, 1, 3], T[k, 2, 3]
    p = (p[0] + R[0] * t0 + R[1] * t1 + R[2] * t2,
         p[1] + R[3] * t0 + R[4] * t1 + R[5] * t2,
         p[2] + R[6] * t0 + R[7] * t1 + R[8] * t2)
    B = (T[k, 0, 0], T[k, 0, 1], T[k, 0, 2], T[k, 1, 0], T[k, 1, 1], T[k, 1, 2],
         T[k, 2, 0], T[k, 2, 1], T[k, 2, 2])
    return _mm(R, B), p


@njit(cache=True, inline="always")
def _zaxis(chain, i, R):
    ax, ay, az = chain.axis[i, 0], chain.axis[i, 1], chain.axis[i, 2]
    return (R[0] * ax + R[1] * ay + R[2] * az, R[3] * ax + R[4] * ay + R[5] * az,
            R[6] * ax + R[7] * ay + R[8] * az)


@njit(cache=True)
def _column(jt, z, o, w):
    if jt == 0:
        d0, d1, d2 = w[0] - o[0], w[1] - o[1], w[2] - o[2]
        return (z[1] * d2 - z[2] * d1, z[2] * d0 - z[0] * d2, z[0] * d1 - z[1] * d0)
    return z


@njit(cache=True)
def _fkjacz3(chain, q0, q1, q2):
    """Wrist, the three Jacobian columns and the three world joint axes of a 3-joint chain
    (tuples: no allocation)."""
    R, p = _start(chain)
    z0, o0 = _zaxis(chain, 0, R), p
    R, p = _advance(chain, 0, q0, R, p)
    z1, o1 = _zaxis(chain, 1, R), p
    R, p = _advance(chain, 1, q1, R, p)
    z2, o2 = _zaxis(chain, 2, R), p
    R, p = _advance(chain, 2, q2, R, p)
    return (p, _column(chain.jtype[0], z0, o0, p), _column(chain.jtype[1], z1, o1, p),
            _column(chain.jtype[2], z2, o2, p), z0, z1, z2)


@njit(cache=True)
def _fkjac3(chain, q0, q1, q2):
    """Wrist and the three Jacobian columns of a 3-joint chain."""
    w, c0, c1, c2, z0, z1, z2 = _fkjacz3(chain, q0, q1, q2)
    return w, c0, c1, c2


@njit(cache=True)
def fk_point(chain, q, out3):
    """Wrist position of one configuration ``q`` (n,) into ``out3`` (3,)."""
    R, p = _start(chain)
    for i in range(chain.axis.shape[0]):
        R, p = _advance(chain, i, q[i], R, p)
    out3[0] = p[0]
    out3[1] = p[1]
    out3[2] = p[2]


@njit(cache=True)
def jac_point(chain, q, outJ33):
    """``d wrist / d q`` (3, 3) of one configuration of a 3-joint chain into ``outJ33``."""
    w, c0, c1, c2 = _fkjac3(chain, q[0], q[1], q[2])
    for r in range(3):
        outJ33[r, 0] = c0[r]
        outJ33[r, 1] = c1[r]
        outJ33[r, 2] = c2[r]


@njit(cache=True)
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True, inline="always")
def _box(chain, i, x):
    """Project joint value x into joint i's box (wrap a revolute joint whose range spans 2 pi)."""
    lo = chain.lo[i]
    hi = chain.hi[i]
    if chain.jtype[i] == 0 and hi - lo >= TWO_PI - 1e-9:
        return lo + ((x - lo) % TWO_PI)
    return min(max(x, lo), hi)


@njit(cache=True)
def _rows_in(A, lo, hi, q0, q1, q2, tol):
    """Does q meet every limit row ``lo - tol <= A q <= hi + tol``?"""
    for r in range(A.shape[0]):
        v = A[r, 0] * q0 + A[r, 1] * q1 + A[r, 2] * q2
        if not (v >= lo[r] - tol and v <= hi[r] + tol):
            return False
    return True


@njit(cache=True)
def _rows_ok(chain, q0, q1, q2, tol):
    return _rows_in(chain.A, chain.lo, chain.hi, q0, q1, q2, tol)


@njit(cache=True, inline="always")
def _active(chain, i, qi, gi):
    """Is joint i held at a box limit that the descent direction gi pushes against?"""
    lo = chain.lo[i]
    hi = chain.hi[i]
    if chain.jtype[i] == 0 and hi - lo >= TWO_PI - 1e-9:
        return False
    return (qi <= lo and gi < 0.0) or (qi >= hi and gi > 0.0)


@njit(cache=True)
def _rodrigues(a0, a1, a2, c, s, v0, v1, v2):
    """The vector v turned about the unit axis a by the angle of cosine c and sine s."""
    d = (a0 * v0 + a1 * v1 + a2 * v2) * (1.0 - c)
    return (c * v0 + s * (a1 * v2 - a2 * v1) + d * a0,
            c * v1 + s * (a2 * v0 - a0 * v2) + d * a1,
            c * v2 + s * (a0 * v1 - a1 * v0) + d * a2)


@njit(cache=True, inline="always")
def _screw_move(chain, i, q, c, s, v0, v1, v2):
    """Point v moved by joint i alone (``E_i(q)`` of :attr:`ChainData.screw`): turned about its axis
    (revolute, c and s the cosine and sine of q) or shifted along it (prismatic)."""
    Z = chain.screw
    a0, a1, a2 = Z[i, 0], Z[i, 1], Z[i, 2]
    if chain.jtype[i] == 0:
        o0, o1, o2 = Z[i, 3], Z[i, 4], Z[i, 5]
        r = _rodrigues(a0, a1, a2, c, s, v0 - o0, v1 - o1, v2 - o2)
        return (o0 + r[0], o1 + r[1], o2 + r[2])
    return (v0 + a0 * q, v1 + a1 * q, v2 + a2 * q)


@njit(cache=True)
def _cs(jt, q):
    """Cosine and sine of a joint's angle q (1, 0 for a prismatic joint, ``jt`` 1: it turns nothing)."""
    return (math.cos(q), math.sin(q)) if jt == 0 else (1.0, 0.0)


@njit(cache=True)
def _local3(chain, q0, q1, q2, t0, t1, t2):
    """Residual ``t - f(q)`` of target t and the three Jacobian columns of a 3-joint chain, all turned
    back by joint 0's own motion (``E_0(q_0)^-1``, a rotation or a shift). Newton's ``J^T J``, ``J^T r``
    and ``|r|`` are the same in that frame as in the world. The product of exponentials on
    :attr:`ChainData.screw` gets them with five vector rotations, about half the arithmetic of
    :func:`_fkjac3`'s six matrix products. The same chain: tests/test_urdf.py holds it to pinocchio.
    Revolute joint i's column is ``z_i x (f - o_i)``, prismatic ``z_i``, with joint 0's axis and point
    fixed in this frame, joint 1's at their zero-configuration place, joint 2's moved by joint 1."""
    Z = chain.screw
    jt = chain.jtype
    c0, s0 = _cs(jt[0], q0)
    c1, s1 = _cs(jt[1], q1)
    c2, s2 = _cs(jt[2], q2)
    v = _screw_move(chain, 2, q2, c2, s2, Z[3, 0], Z[3, 1], Z[3, 2])
    v = _screw_move(chain, 1, q1, c1, s1, v[0], v[1], v[2])
    if jt[1] == 0:
        z2 = _rodrigues(Z[1, 0], Z[1, 1], Z[1, 2], c1, s1, Z[2, 0], Z[2, 1], Z[2, 2])
    else:
        z2 = (Z[2, 0], Z[2, 1], Z[2, 2])
    o2 = _screw_move(chain, 1, q1, c1, s1, Z[2, 3], Z[2, 4], Z[2, 5])
    if jt[0] == 0:  # the target turned back about joint 0's axis
        u = _rodrigues(Z[0, 0], Z[0, 1], Z[0, 2], c0, -s0, t0 - Z[0, 3], t1 - Z[0, 4], t2 - Z[0, 5])
        u = (u[0] + Z[0, 3], u[1] + Z[0, 4], u[2] + Z[0, 5])
    else:
        u = (t0 - Z[0, 0] * q0, t1 - Z[0, 1] * q0, t2 - Z[0, 2] * q0)
    r = (u[0] - v[0], u[1] - v[1], u[2] - v[2])
    z0 = (Z[0, 0], Z[0, 1], Z[0, 2])
    z1 = (Z[1, 0], Z[1, 1], Z[1, 2])
    return (r, _column(jt[0], z0, (Z[0, 3], Z[0, 4], Z[0, 5]), v),
            _column(jt[1], z1, (Z[1, 3], Z[1, 4], Z[1, 5]), v), _column(jt[2], z2, o2, v))


@njit(cache=True)
def _solve(chain, w0, w1, w2, s0, s1, s2, maxit):
    """Projected Gauss-Newton / Levenberg-Marquardt from seed s within the joint box.

    Joints held at a box limit that the descent pushes against are frozen for the step (active
    set), so a target beyond a limit ends at a stationary point quickly. Returns
    (reached, q0, q1, q2): reached when |f(q) - w| < IK_TOL and every limit row holds. Stops early
    when the residual stops shrinking fast (no solution on this branch).
    """
    q0 = _box(chain, 0, s0)
    q1 = _box(chain, 1, s1)
    q2 = _box(chain, 2, s2)
    r, c0, c1, c2 = _local3(chain, q0, q1, q2, w0, w1, w2)
    r0, r1, r2 = r
    e = r0 * r0 + r1 * r1 + r2 * r2
    tol2 = IK_TOL * IK_TOL
    polish2 = 1e-6 * tol2   # keep going below the tolerance while Newton still improves
    lam = 0.0
    slow = 0
    for _ in range(maxit):
        if e < polish2:
            break
        r = (r0, r1, r2)
        g0, g1, g2 = _dot(c0, r), _dot(c1, r), _dot(c2, r)
        a00, a01, a02 = _dot(c0, c0), _dot(c0, c1), _dot(c0, c2)
        a11, a12, a22 = _dot(c1, c1), _dot(c1, c2), _dot(c2, c2)
        mu = lam * (a00 + a11 + a22) + 1e-30
        b00, b11, b22 = a00 + mu, a11 + mu, a22 + mu
        if _active(chain, 0, q0, g0):
            b00, a01, a02, g0 = 1.0, 0.0, 0.0, 0.0
        if _active(chain, 1, q1, g1):
            b11, a01, a12, g1 = 1.0, 0.0, 0.0, 0.0
        if _active(chain, 2, q2, g2):
            b22, a02, a12, g2 = 1.0, 0.0, 0.0, 0.0
        m00 = b11 * b22 - a12 * a12
        m01 = a02 * a12 - a01 * b22
        m02 = a01 * a12 - a02 * b11
        m11 = b00 * b22 - a02 * a02
        m12 = a01 * a02 - b00 * a12
        m22 = b00 * b11 - a01 * a01
        det = b00 * m00 + a01 * m01 + a02 * m02
        if not (det > 1e-300):
            if e < tol2:
                break
            lam = max(10.0 * lam, 1e-9)
            if lam > 1e4:
                break
            continue
        d0 = (m00 * g0 + m01 * g1 + m02 * g2) / det
        d1 = (m01 * g0 + m11 * g1 + m12 * g2) / det
        d2 = (m02 * g0 + m12 * g1 + m22 * g2) / det
        n0 = _box(chain, 0, q0 + d0)
        n1 = _box(chain, 1, q1 + d1)
        n2 = _box(chain, 2, q2 + d2)
        if n0 == q0 and n1 == q1 and n2 == q2:
            break                               # stationary
        tn, e0, e1, e2 = _local3(chain, n0, n1, n2, w0, w1, w2)
        t0, t1, t2 = tn
        en = t0 * t0 + t1 * t1 + t2 * t2
        if en < e:
            if en > 0.5 * e and en >= tol2:
                slow += 1
            else:
                slow = 0
            q0, q1, q2 = n0, n1, n2
            c0, c1, c2 = e0, e1, e2
            r0, r1, r2, e = t0, t1, t2, en
            lam = 0.1 * lam if lam > 1e-9 else 0.0
            if slow >= 3:
                break
        else:
            if e < tol2:
                break
            lam = max(10.0 * lam, 1e-9)
            if lam > 1e4:
                break
    ok = e < tol2 and _rows_ok(chain, q0, q1, q2, LIMIT_TOL)
    return ok, q0, q1, q2


# The closed form's margins (:func:`_ik_parallel`). It proves a wrist unreachable only where every exact
# solution misses by more than these and the arm is well conditioned there: then a target error of
# IK_TOL moves the solutions by about 1e-5 (rad or m) at most, a tenth of _QGAP, so no configuration
# within the limits comes within IK_TOL of the wrist. Elsewhere Newton (:func:`_ik_seeds`) decides.
_GAP = 1e-8      # m: a height or reach mismatch (100 x IK_TOL)
_QGAP = 1e-4     # rad or m: a solution this close outside a limit row
_SINE = 1e-2     # an elbow's (or joint 0's root's) sine below this: two solutions near their merge
_COND = 0.02     # joint 0's root's slope below 2 % of the lever
_FOLD = 1e-3     # the wrist this close to joint 1's axis (relative to l1 + l2): the shoulder's angle
_TILT = 1e-2     # a prismatic joint 0 this close to normal to the turning joints' axis
_TURNS = 1e3     # rad: a representative q + 2 pi k beyond this is checked (its rounding grows with k)


@njit(cache=True)
def _turn2(x, y, c, s):
    """The plane vector (x, y) turned by the angle of cosine c and sine s."""
    return x * c - y * s, x * s + y * c


@njit(cache=True)
def _wraps(jt, lo, hi, q):
    """The range of k for which a joint's ``q + 2 pi k`` lies within its box [lo, hi] widened by _QGAP
    (one value, k = 0, for a prismatic joint, ``jt`` 1); empty (k1 < k0) when none does. Infinite
    limits give +-1e9."""
    lo = lo - _QGAP
    hi = hi + _QGAP
    if jt != 0:
        return 0, (0 if q >= lo and q <= hi else -1)
    return (int(math.ceil(min(max((lo - q) / TWO_PI, -1e9), 1e9))),
            int(math.floor(min(max((hi - q) / TWO_PI, -1e9), 1e9))))


@njit(cache=True)
def _nearest3(ka, kb):
    """Up to three consecutive turns within [ka, kb] nearest k = 0: the first s, how many n, and the
    offset of the one to try first (k = 0 when it is among them): turn i is ``s + (first + i) % n``."""
    n = kb - ka + 1
    if n <= 0:
        return 0, 0, 0
    s = ka if n <= 3 else min(max(-1, ka), kb - 2)
    n = min(n, 3)
    return s, n, min(max(-s, 0), n - 1)


@njit(cache=True)
def _verified(chain, q0, q1, q2, t0, t1, t2):
    """``|f(q) - t| < IK_TOL`` (ik_point's criterion)."""
    r, c0, c1, c2 = _local3(chain, q0, q1, q2, t0, t1, t2)
    return r[0] * r[0] + r[1] * r[1] + r[2] * r[2] < IK_TOL * IK_TOL


@njit(cache=True)
def _try_limits(chain, A, lo, hi, jt, q0, q1, q2, t0, t1, t2, verify):
    """Joint values q (mod 2 pi for revolute joints) of an exact solution of f(q) = t: is one of their
    representatives within every limit row (``A``, ``lo``, ``hi``, joint types ``jt``: the chain's, read
    once by the caller)? Returns (status, q0, q1, q2): 1 yes (that representative), 0 no, by more than
    _QGAP, -1 nearer than that. A representative moved onto a box limit, or any with ``verify`` (the
    solution came from a clamped equation), counts only with ``|f(q) - t| < IK_TOL`` (ik_point's
    criterion); an exact one within the limits is a solution to rounding."""
    k0a, k0b = _wraps(jt[0], lo[0], hi[0], q0)
    k1a, k1b = _wraps(jt[1], lo[1], hi[1], q1)
    k2a, k2b = _wraps(jt[2], lo[2], hi[2], q2)
    s0, n0, f0 = _nearest3(k0a, k0b)
    s1, n1, f1 = _nearest3(k1a, k1b)
    s2, n2, f2 = _nearest3(k2a, k2b)
    # more turns within a box than tried: with coupled rows, one of the others might meet them
    near = A.shape[0] > 3 and (k0b - k0a > 2 or k1b - k1a > 2 or k2b - k2a > 2)
    for c in range(n0 * n1 * n2):  # the representatives, at most 3 per joint, nearest the found angle
        a0 = q0 + TWO_PI * (s0 + (f0 + c // (n1 * n2)) % n0) if jt[0] == 0 else q0
        a1 = q1 + TWO_PI * (s1 + (f1 + c // n2) % n1)
        a2 = q2 + TWO_PI * (s2 + (f2 + c) % n2)
        b0 = min(max(a0, lo[0]), hi[0])
        b1 = min(max(a1, lo[1]), hi[1])
        b2 = min(max(a2, lo[2]), hi[2])
        exact = b0 == a0 and b1 == a1 and b2 == a2
        if _rows_in(A, lo, hi, b0, b1, b2, LIMIT_TOL):
            if exact and not verify and max(abs(a0), max(abs(a1), abs(a2))) <= _TURNS:
                return 1, b0, b1, b2
            if _verified(chain, b0, b1, b2, t0, t1, t2):
                return 1, b0, b1, b2
            near = True  # moved onto a limit, or a clamped equation: not proved either way
        elif not exact or _rows_in(A, lo, hi, b0, b1, b2, LIMIT_TOL + _QGAP):
            near = True
    return (-1 if near else 0), 0.0, 0.0, 0.0


@njit(cache=True)
def _ik_parallel(chain, t0, t1, t2):
    """Closed-form inverse kinematics of a 3-joint chain whose joints 1 and 2 turn about parallel axes
    (the PHANToM's shoulder and elbow, a UR arm's shoulder lift and elbow): those two move the wrist in a
    plane normal to their axis ``a``, so joint 0 alone must bring the target to the wrist's height
    along ``a`` (``A cos q0 + B sin q0 = D`` for a revolute joint 0, linear for a prismatic one), and in
    that plane joints 1 and 2 are a two-link arm (the law of cosines, two elbows). Every exact solution
    is tried against the limits (:func:`_try_limits`), each joint's as soon as it is known.

    Returns (status, q0, q1, q2): 1 reachable (a configuration within every limit, ``|f(q) - t| <
    IK_TOL``), 0 unreachable (every exact solution misses the target's height or reach by more than
    _GAP, or a limit by more than _QGAP, where the arm is well conditioned: no configuration within
    the limits comes within IK_TOL of it), -1 not decided here (another chain; an elbow nearly
    straight or folded, a wrist near joint 1's axis, joint 0 ill-conditioned, a solution within the
    margins; coupled limits over more turns than tried: Newton decides)."""
    Z = chain.screw
    jt = chain.jtype
    if Z.shape[0] != 4 or jt[1] != 0 or jt[2] != 0:
        return -1, 0.0, 0.0, 0.0
    a0, a1, a2 = Z[1, 0], Z[1, 1], Z[1, 2]
    cab = a0 * Z[2, 0] + a1 * Z[2, 1] + a2 * Z[2, 2]
    if abs(cab) < 1.0 - 1e-12:
        return -1, 0.0, 0.0, 0.0
    s2 = 1.0 if cab > 0.0 else -1.0
    # the plane's basis e, f = a x e (a turn by theta about a maps (x, y) to _turn2(x, y, cos, sin))
    if abs(a0) <= abs(a1) and abs(a0) <= abs(a2):
        e0, e1, e2 = 0.0, a2, -a1          # a x (1, 0, 0)
    elif abs(a1) <= abs(a2):
        e0, e1, e2 = -a2, 0.0, a0          # a x (0, 1, 0)
    else:
        e0, e1, e2 = a1, -a0, 0.0          # a x (0, 0, 1)
    en = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    e0, e1, e2 = e0 / en, e1 / en, e2 / en
    f0, f1, f2 = a1 * e2 - a2 * e1, a2 * e0 - a0 * e2, a0 * e1 - a1 * e0
    p0, p1, p2 = Z[1, 3], Z[1, 4], Z[1, 5]                       # on joint 1's axis
    v0, v1, v2 = Z[2, 3] - p0, Z[2, 4] - p1, Z[2, 5] - p2        # to joint 2's axis
    w0, w1, w2 = Z[3, 0] - Z[2, 3], Z[3, 1] - Z[2, 4], Z[3, 2] - Z[2, 5]  # on to the wrist
    hgt = a0 * (Z[3, 0] - p0) + a1 * (Z[3, 1] - p1) + a2 * (Z[3, 2] - p2)
    x1, y1 = e0 * v0 + e1 * v1 + e2 * v2, f0 * v0 + f1 * v1 + f2 * v2
    x2, y2 = e0 * w0 + e1 * w1 + e2 * w2, f0 * w0 + f1 * w1 + f2 * w2
    l1 = math.sqrt(x1 * x1 + y1 * y1)
    l2 = math.sqrt(x2 * x2 + y2 * y2)
    if l1 < 1e-9 or l2 < 1e-9:
        return -1, 0.0, 0.0, 0.0
    b0, b1, b2 = Z[0, 0], Z[0, 1], Z[0, 2]
    o0, o1, o2 = Z[0, 3], Z[0, 4], Z[0, 5]
    ab = a0 * b0 + a1 * b1 + a2 * b2
    A_, lo_, hi_ = chain.A, chain.lo, chain.hi
    near = False
    # joint 0's candidates: cosine and sine of q0 = phi -+ dl (revolute), or its one value (prismatic)
    nq = 1
    ca = sa = cb = sb = 0.0
    qp = 0.0
    if jt[0] == 0:
        d0, d1, d2 = t0 - o0, t1 - o1, t2 - o2
        bd = b0 * d0 + b1 * d1 + b2 * d2
        A = a0 * d0 + a1 * d1 + a2 * d2 - ab * bd
        B = -(a0 * (b1 * d2 - b2 * d1) + a1 * (b2 * d0 - b0 * d2) + a2 * (b0 * d1 - b1 * d0))
        D = hgt + a0 * (p0 - o0) + a1 * (p1 - o1) + a2 * (p2 - o2) - ab * bd
        R = math.sqrt(A * A + B * B)
        lever = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) + l1 + l2
        if R < 1e-9 * lever:
            return -1, 0.0, 0.0, 0.0          # the target on joint 0's axis, or joint 0 parallel to a
        if abs(D) - R > _GAP:
            return 0, 0.0, 0.0, 0.0           # no turn of joint 0 brings the target to the wrist's height
        c = min(max(D / R, -1.0), 1.0)
        sd = math.sqrt(max(0.0, 1.0 - c * c))
        if sd < _SINE or R * sd < _COND * lever:
            near = True
        cp, sp = A / R, B / R
        ca, sa = cp * c + sp * sd, sp * c - cp * sd
        cb, sb = cp * c - sp * sd, sp * c + cp * sd
        nq = 2 if sd > 0.0 else 1
    else:
        if abs(ab) < 1e-6:
            return -1, 0.0, 0.0, 0.0
        near = abs(ab) < _TILT
        qp = (a0 * (t0 - p0) + a1 * (t1 - p1) + a2 * (t2 - p2) - hgt) / ab
    # the elbow's cosine and sine of psi: dot cos(theta) - cr sin(theta) = l1 l2 cos(theta - psi)
    cps, sps = (x1 * x2 + y1 * y2) / (l1 * l2), -(x1 * y2 - y1 * x2) / (l1 * l2)
    for iq in range(nq):
        if jt[0] == 0:
            c0, s0 = (ca, sa) if iq == 0 else (cb, sb)
            q0 = math.atan2(s0, c0)
        else:
            c0, s0 = 1.0, 0.0
            q0 = qp
        k0, k1 = _wraps(jt[0], lo_[0], hi_[0], q0)
        if k1 < k0:
            continue
        # the target turned back by joint 0 (as _local3), relative to joint 1's axis, in the plane
        if jt[0] == 0:
            u = _rodrigues(b0, b1, b2, c0, -s0, t0 - o0, t1 - o1, t2 - o2)
            u0, u1, u2 = u[0] + o0 - p0, u[1] + o1 - p1, u[2] + o2 - p2
        else:
            u0, u1, u2 = t0 - b0 * q0 - p0, t1 - b1 * q0 - p1, t2 - b2 * q0 - p2
        px, py = e0 * u0 + e1 * u1 + e2 * u2, f0 * u0 + f1 * u1 + f2 * u2
        rp = math.sqrt(px * px + py * py)
        if rp > l1 + l2 + _GAP or rp < abs(l1 - l2) - _GAP:
            continue                          # beyond the two links' reach (with the margin)
        E = 0.5 * (rp * rp - l1 * l1 - l2 * l2) / (l1 * l2)
        E = min(max(E, -1.0), 1.0)
        se = math.sqrt(max(0.0, 1.0 - E * E))
        nearq = near or se < _SINE or rp < _FOLD * (l1 + l2)
        near = nearq  # an ill-conditioned elbow or shoulder: undecided unless a configuration checks out
        for ie in range(2 if se > 0.0 else 1):
            sg = -1.0 if ie == 0 else 1.0    # theta = psi -+ acos(E)
            ct, stt = cps * E - sg * sps * se, sps * E + sg * cps * se
            q2 = s2 * math.atan2(stt, ct)
            k0, k1 = _wraps(jt[2], lo_[2], hi_[2], q2)
            if k1 < k0:
                continue
            wx, wy = _turn2(x2, y2, ct, stt)
            wx, wy = wx + x1, wy + y1
            if wx * wx + wy * wy < 1e-18:
                near = True                   # the wrist on joint 1's axis: any shoulder angle
                continue
            q1 = math.atan2(wx * py - wy * px, wx * px + wy * py)
            st, r0, r1, r2 = _try_limits(chain, A_, lo_, hi_, jt, q0, q1, q2, t0, t1, t2, nearq)
            if st == 1:
                return 1, r0, r1, r2
            if st == -1:
                near = True
    return (-1 if near else 0), 0.0, 0.0, 0.0


# Compiled code pays for each read of an array field of a namedtuple (``rmap.state``, ``chain.lo``): a
# reference count up and down, about 5 ns, which nothing hoists out of a loop. The map's helpers read
# each field once; loops over many points read the fields before the loop and call the scalar forms
# (:func:`_voxel`).
@njit(cache=True)
def _voxel(o0, o1, o2, h, n0, n1, n2, w0, w1, w2):
    """Voxel (ix, iy, iz) of w on a map of origin o, spacing h and n voxels per axis; ix = -1 outside
    the map (NaN is outside)."""
    fx = (w0 - o0) / h
    fy = (w1 - o1) / h
    fz = (w2 - o2) / h
    if not (fx >= 0.0 and fx < n0 and fy >= 0.0 and fy < n1 and fz >= 0.0 and fz < n2):
        return -1, 0, 0
    return int(fx), int(fy), int(fz)


@njit(cache=True, inline="always")
def map_geometry(rmap):
    """The map's origin, spacing and voxel counts as a tuple of scalars, for :func:`map_state` (read
    once, before a loop over many points)."""
    o = rmap.origin
    n = rmap.shape
    return o[0], o[1], o[2], rmap.h, n[0], n[1], n[2]


@njit(cache=True)
def map_state(geo, state, w0, w1, w2):
    """(s, ix, iy, iz): the state of w's voxel (ix, iy, iz) on the map of geometry ``geo``
    (:func:`map_geometry`) and states ``state``; off the map (NaN is off the map) s = 0 and ix = -1.
    The loops' form of :func:`reach_point`::

        s, ix, iy, iz = map_state(geo, state, w0, w1, w2)
        ok = s == 1 or (s == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))
    """
    ix, iy, iz = _voxel(geo[0], geo[1], geo[2], geo[3], geo[4], geo[5], geo[6], w0, w1, w2)
    if ix < 0:
        return 0, -1, 0, 0
    return state[ix, iy, iz], ix, iy, iz


@njit(cache=True)
def _ik_seeds(chain, rmap, c, w0, w1, w2):
    S = rmap.seeds
    for k in range(rmap.seed_ptr[c], rmap.seed_ptr[c + 1]):
        ok, q0, q1, q2 = _solve(chain, w0, w1, w2, S[k, 0], S[k, 1], S[k, 2], 60)
        if ok:
            return True, q0, q1, q2
    return False, 0.0, 0.0, 0.0


@njit(cache=True)
def _ik_voxel(chain, rmap, ix, iy, iz, w0, w1, w2):
    """IK from the seed cell's seeds; in a certified-in voxel also from the neighbour cells'."""
    sub = rmap.sub
    cx, cy, cz = rmap.shape[0] // sub, rmap.shape[1] // sub, rmap.shape[2] // sub
    jx, jy, jz = ix // sub, iy // sub, iz // sub
    ok, q0, q1, q2 = _ik_seeds(chain, rmap, (jx * cy + jy) * cz + jz, w0, w1, w2)
    if ok or rmap.state[ix, iy, iz] != 1:
        return ok, q0, q1, q2
    for dx in range(-1, 2):
        for dy in range(-1, 2):
            for dz in range(-1, 2):
                kx, ky, kz = jx + dx, jy + dy, jz + dz
                if (dx == 0 and dy == 0 and dz == 0) or kx < 0 or ky < 0 or kz < 0 \
                        or kx >= cx or ky >= cy or kz >= cz:
                    continue
                ok, q0, q1, q2 = _ik_seeds(chain, rmap, (kx * cy + ky) * cz + kz, w0, w1, w2)
                if ok:
                    return ok, q0, q1, q2
    return False, 0.0, 0.0, 0.0


@njit(cache=True)
def ik_point(chain, rmap, w0, w1, w2, qout):
    """Exact IK within all limits for wrist (w0, w1, w2) into ``qout`` (3,); returns success.

    Damped Newton from the seeds of the wrist's seed cell (any branch), then the closed form
    (:func:`_ik_parallel`, where the chain has one) for a configuration the seeds' branches miss, so
    that it succeeds wherever :func:`reach_point` says reachable; success only if ``|f(q) - w| <
    1e-10`` and every limit row holds. ``qout`` is NaN on failure. A point in a certified-out voxel
    fails at once.
    """
    s, ix, iy, iz = map_state(map_geometry(rmap), rmap.state, w0, w1, w2)
    ok = False
    q0 = q1 = q2 = 0.0
    if s != 0:
        ok, q0, q1, q2 = _ik_voxel(chain, rmap, ix, iy, iz, w0, w1, w2)
        if not ok:  # a configuration the seeds' branches miss (reach_point's closed form finds it)
            st, q0, q1, q2 = _ik_parallel(chain, w0, w1, w2)
            ok = st == 1
    if ok:
        qout[0], qout[1], qout[2] = q0, q1, q2
    else:
        qout[0] = qout[1] = qout[2] = np.nan
    return ok


@njit(cache=True)
def ik_near(chain, rmap, w0, w1, w2, near, qout):
    """:func:`ik_point` trying the configuration ``near`` (3,) first (stays on its branch)."""
    if near[0] == near[0] and near[1] == near[1] and near[2] == near[2]:
        ok, q0, q1, q2 = _solve(chain, w0, w1, w2, near[0], near[1], near[2], 60)
        if ok:
            qout[0], qout[1], qout[2] = q0, q1, q2
            return True
    return ik_point(chain, rmap, w0, w1, w2, qout)


@njit(cache=True)
def reach_point(chain, rmap, w0, w1, w2):
    """Is wrist (w0, w1, w2) reachable within all limits? O(1) in certified voxels, exact IK
    (:func:`ik_point`'s criterion) in boundary voxels (:func:`reach_boundary`). NaN is not reachable.
    Loops over many points read the map once and use :func:`map_state` and :func:`reach_boundary`
    (:func:`_reach_many`): a call reads every field of ``chain`` and ``rmap``."""
    s, ix, iy, iz = map_state(map_geometry(rmap), rmap.state, w0, w1, w2)
    return s == 1 or (s == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))


@njit(cache=True)
def reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2):
    """:func:`reach_point` in a boundary voxel (ix, iy, iz): the closed form where it decides, else
    Newton from the seed cell's seeds."""
    st = _ik_parallel(chain, w0, w1, w2)[0]
    if st >= 0:
        return st == 1
    sub = rmap.sub
    n = rmap.shape
    c = ((ix // sub) * (n[1] // sub) + iy // sub) * (n[2] // sub) + iz // sub
    return _ik_seeds(chain, rmap, c, w0, w1, w2)[0]


# ---------------------------------------------------------------------------- vectorised loops
@njit(cache=True)
def _fk_many(chain, Q, out):
    for k in range(Q.shape[0]):
        fk_point(chain, Q[k], out[k])


@njit(cache=True)
def _jac_many(chain, Q, out):
    for k in range(Q.shape[0]):
        jac_point(chain, Q[k], out[k])


@njit(cache=True)
def _reach_many(chain, rmap, Wp, out):
    geo = map_geometry(rmap)
    mst = rmap.state
    for k in range(Wp.shape[0]):
        w0, w1, w2 = Wp[k, 0], Wp[k, 1], Wp[k, 2]
        s, ix, iy, iz = map_state(geo, mst, w0, w1, w2)
        out[k] = s == 1 or (s == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))


@njit(cache=True)
def _ik_many(chain, rmap, Wp, near, use_near, Q, ok):
    for k in range(Wp.shape[0]):
        if use_near:
            ok[k] = ik_near(chain, rmap, Wp[k, 0], Wp[k, 1], Wp[k, 2], near[k], Q[k])
        else:
            ok[k] = ik_point(chain, rmap, Wp[k, 0], Wp[k, 1], Wp[k, 2], Q[k])


# ---------------------------------------------------------------------------- map build
