"""Serial arms described by a URDF (docs/physics.md "Spatial robots (3-D)").

:class:`UrdfArm` mirrors the planar :class:`errplan.kinematics.arm.Arm` for any serial chain whose
three actuated ``joints`` place the origin of the ``wrist`` link in 3-D. Points are world
``[x, y, z]`` (y up, z toward the patient); the URDF root sits at ``base_position`` with
orientation ``R = Rz(yaw) Ry(pitch) Rx(roll)`` from ``base_rpy``. Every other joint on the chain
from the root to the wrist is held at its ``fixed_joints`` value (default 0).

Pinocchio parses the URDF (kinematic model only: meshes are never loaded, so missing meshes never
fail kinematics) and is the reference for the compiled kernels. The hot paths are numba kernels on
two namedtuples of plain arrays (:meth:`UrdfArm.kernel`):

* :class:`ChainData`: the chain as fixed transforms between the actuated joints;
* :class:`ReachMap`: a voxel map of the wrist workspace with the guarantees below.

Reachability map
----------------
Let ``Q`` be the feasible joint set (box and coupled limits: a polytope), ``f`` the wrist position
and ``W = f(Q)`` the workspace. Every boundary point of ``W`` is the image of a point of the faces
``dQ`` or of a singular configuration (``det J = 0``): anywhere else the inverse function theorem
makes the image an interior point. Image balls bound where joint-space pieces can go: for a cell
(or a planar patch) with centre ``c`` and half-widths ``e`` along directions ``t_i``::

    f(piece) lies in the ball B(f(c), rho),  rho = sum_i |J(c) t_i| e_i + K (sum_i |t_i| e_i)^2 / 2,

where ``K`` bounds the Lipschitz constant of ``J`` (every second derivative of a serial chain's
wrist is bounded by a distance from the wrist to a joint axis, so ``K`` follows from the link
lengths, :meth:`UrdfArm._lipschitz`). The build

1. covers each face of ``Q`` (both limits of every joint whose range is under 2 pi, both bounds of
   every coupled limit) with planar patches, halving them until ``rho <= beta h`` (``h`` the voxel
   edge), and marks every voxel that meets a patch ball *boundary*;
2. covers ``Q`` with coarse joint cells, halves those that may hold a singular configuration
   (not excluded by Weyl's inequality ``sigma_min(J(c)) > K |e|`` nor by a second-order bound on
   ``det J``, :meth:`UrdfArm._det_bound`) until ``rho <= beta h``, and marks the voxels meeting their
   balls *boundary*; every cell centre that satisfies all limits marks its wrist's voxel *hit*.

So a voxel not marked boundary meets no boundary point of ``W``: it lies entirely inside ``W`` or
entirely outside, and so does any face-connected set of such voxels. A flood fill labels them:

* **out (0)**: connected to the map's border layer, which lies outside the bounding box of all
  coarse-cell balls and so outside ``W``. Guarantee: no point of such a voxel is reachable.
* **in (1)**: connected to a hit voxel. Guarantee: every point of such a voxel is reachable within
  all limits.
* **boundary (2)**: the rest. :func:`reach_point` answers there with exact IK (:func:`ik_point`:
  projected Gauss-Newton from the seeds of the voxel's seed cell; a point counts as reached only
  when ``|f(q) - w| < 1e-10`` with every limit row holding). That answer is as good as the seeds:
  configurations whose wrist falls in the seed cell or its 26 neighbours (patch and cell centres),
  one per cluster of nearby configurations, i.e. one per IK branch. Tests compare it with
  brute-force and closed-form IK.

The soundness of in/out rests on the bounds above (rounding is covered by relative slack); the
build reports ``conflicts`` (an out flood reaching a hit voxel), which must be 0.

The build is deterministic; its result is cached on disk (``$ERRPLAN_CACHE_DIR``, else
``~/.cache/errplan``) under a hash of the chain data (all that the URDF, joints, wrist, base pose,
limits, fixed joints and coupled limits contribute) and the map parameters, written atomically and
verified by a checksum when read (a bad file is rebuilt, never trusted).
"""
from __future__ import annotations

import contextlib
import hashlib
import math
import os
import re
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, NamedTuple, Sequence

import numpy as np
from numba import njit

from ..errors import ErrplanError, ScenarioError
from .. import packages
from ..inputs import read_bytes
from ..scenario import CoupledLimit

TWO_PI = 2.0 * math.pi
IK_TOL = 1e-10          # |f(q) - w| below this counts as reached (m)
LIMIT_TOL = 1e-12       # slack on the limit rows, as within_limits' default
MAP_VERSION = "reachmap-2"
GRAVITY = 9.81          # m/s^2, along world -y


# ============================================================================ data
class ChainData(NamedTuple):
    """The chain for the kernels (plain arrays).

    ``T`` (n+1, 4, 4): ``T[0]`` world -> frame of joint 0 (base pose and fixed joints folded in),
    ``T[i]`` child frame of joint i-1 -> frame of joint i, ``T[n]`` child frame of joint n-1 ->
    wrist link origin. ``axis`` (n, 3) unit joint axes in their joint frames; ``jtype`` (n,) int64,
    0 revolute, 1 prismatic. Limit rows ``lo <= A q <= hi``: ``A`` (m, n), the first n rows are the
    box limits (identity), then the coupled limits.
    """

    T: np.ndarray
    axis: np.ndarray
    jtype: np.ndarray
    A: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


class ReachMap(NamedTuple):
    """Voxel map of the wrist workspace (see the module docstring for what each state guarantees).

    Voxel ``(i, j, k)`` is the box ``origin + h * [i, j, k] .. origin + h * [i+1, j+1, k+1]``;
    ``shape`` (3,) int64 the counts, ``state`` (nx, ny, nz) uint8: 0 out, 1 in, 2 boundary.
    IK seeds live on a coarser grid of ``sub``^3 voxels per seed cell: the seeds of the cell
    ``c = ((i // sub) * cy + j // sub) * cz + k // sub`` (``cy, cz = shape[1:] // sub``) are
    ``seeds[seed_ptr[c]:seed_ptr[c + 1]]`` (rows of n joint values), nearest first; cells with only
    out voxels have none.
    """

    origin: np.ndarray
    h: float
    shape: np.ndarray
    state: np.ndarray
    sub: int
    seed_ptr: np.ndarray
    seeds: np.ndarray


@dataclass(frozen=True)
class MapParams:
    """Reachability-map resolution. ``voxels``: seed cells along the workspace's longest extent;
    ``sub``: voxels per seed-cell edge (voxel edge h = extent / (voxels * sub)); ``coarse``: the
    coarse joint cells move the wrist by at most about ``coarse`` seed cells; ``beta``: critical
    cells are refined until their image ball has radius ``<= beta * h``; ``max_depth``: refinement
    levels; ``seeds``: IK seeds kept per seed cell; ``tau``: joint distance (rad or m, max norm)
    under which two seeds count as one branch."""

    voxels: int = 64
    sub: int = 2
    coarse: float = 2.0
    beta: float = 0.5
    max_depth: int = 12
    seeds: int = 6
    tau: float = 0.3


# ============================================================================ compiled kernels
@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
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
def _rows_ok(chain, q0, q1, q2, tol):
    A = chain.A
    for r in range(A.shape[0]):
        v = A[r, 0] * q0 + A[r, 1] * q1 + A[r, 2] * q2
        if not (v >= chain.lo[r] - tol and v <= chain.hi[r] + tol):
            return False
    return True


@njit(cache=True, inline="always")
def _active(chain, i, qi, gi):
    """Is joint i held at a box limit that the descent direction gi pushes against?"""
    lo = chain.lo[i]
    hi = chain.hi[i]
    if chain.jtype[i] == 0 and hi - lo >= TWO_PI - 1e-9:
        return False
    return (qi <= lo and gi < 0.0) or (qi >= hi and gi > 0.0)


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
    w, c0, c1, c2 = _fkjac3(chain, q0, q1, q2)
    r0, r1, r2 = w0 - w[0], w1 - w[1], w2 - w[2]
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
        wn, e0, e1, e2 = _fkjac3(chain, n0, n1, n2)
        t0, t1, t2 = w0 - wn[0], w1 - wn[1], w2 - wn[2]
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


@njit(cache=True, inline="always")
def _locate(rmap, w0, w1, w2):
    """Voxel (ix, iy, iz) of w; ix = -1 outside the map (NaN is outside)."""
    h = rmap.h
    fx = (w0 - rmap.origin[0]) / h
    fy = (w1 - rmap.origin[1]) / h
    fz = (w2 - rmap.origin[2]) / h
    if not (fx >= 0.0 and fx < rmap.shape[0] and fy >= 0.0 and fy < rmap.shape[1]
            and fz >= 0.0 and fz < rmap.shape[2]):
        return -1, 0, 0
    return int(fx), int(fy), int(fz)


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

    Damped Newton from the seeds of the wrist's seed cell (any branch); success only if
    ``|f(q) - w| < 1e-10`` and every limit row holds. ``qout`` is NaN on failure. A point in a
    certified-out voxel fails at once.
    """
    ix, iy, iz = _locate(rmap, w0, w1, w2)
    ok = False
    q0 = q1 = q2 = 0.0
    if ix >= 0 and rmap.state[ix, iy, iz] != 0:
        ok, q0, q1, q2 = _ik_voxel(chain, rmap, ix, iy, iz, w0, w1, w2)
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
    (:func:`ik_point`'s criterion) in boundary voxels. NaN is not reachable."""
    ix, iy, iz = _locate(rmap, w0, w1, w2)
    if ix < 0:
        return False
    s = rmap.state[ix, iy, iz]
    if s == 0:
        return False
    if s == 1:
        return True
    sub = rmap.sub
    c = ((ix // sub) * (rmap.shape[1] // sub) + iy // sub) * (rmap.shape[2] // sub) + iz // sub
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
    for k in range(Wp.shape[0]):
        out[k] = reach_point(chain, rmap, Wp[k, 0], Wp[k, 1], Wp[k, 2])


@njit(cache=True)
def _ik_many(chain, rmap, Wp, near, use_near, Q, ok):
    for k in range(Wp.shape[0]):
        if use_near:
            ok[k] = ik_near(chain, rmap, Wp[k, 0], Wp[k, 1], Wp[k, 2], near[k], Q[k])
        else:
            ok[k] = ik_point(chain, rmap, Wp[k, 0], Wp[k, 1], Wp[k, 2], Q[k])


# ---------------------------------------------------------------------------- map build
@njit(cache=True, inline="always")
def _smin3(c0, c1, c2):
    """Smallest singular value of the 3x3 matrix with columns c0, c1, c2."""
    a00, a01, a02 = _dot(c0, c0), _dot(c0, c1), _dot(c0, c2)
    a11, a12, a22 = _dot(c1, c1), _dot(c1, c2), _dot(c2, c2)
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    if p1 == 0.0:
        lmin = min(a00, min(a11, a22))
    else:
        p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
        p = math.sqrt(p2 / 6.0)
        b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
        b01, b02, b12 = a01 / p, a02 / p, a12 / p
        detb = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
        r = min(1.0, max(-1.0, detb / 2.0))
        phi = math.acos(r) / 3.0
        lmin = q + 2.0 * p * math.cos(phi + TWO_PI / 3.0)
    return math.sqrt(max(lmin, 0.0))


@njit(cache=True, inline="always")
def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@njit(cache=True, inline="always")
def _det(a, b, c):
    return _dot(a, _cross(b, c))


@njit(cache=True, inline="always")
def _djac(jt, j, k, zj, zk, Jj, Jk):
    """d J_j / d q_k of a serial chain (jt: joint types)."""
    if jt[j] == 0:
        if k < j:
            if jt[k] == 0:
                return _cross(zk, Jj)
            return (0.0, 0.0, 0.0)
        return _cross(zj, Jk)
    if k < j and jt[k] == 0:
        return _cross(zk, zj)
    return (0.0, 0.0, 0.0)


@njit(cache=True)
def _nonsingular(chain, c0, c1, c2, z0, z1, z2, e0, e1, e2, M2):
    """True if det J cannot vanish on the cell (second-order Taylor bound, M2 bounds d2 det)."""
    jt = chain.jtype
    d = _det(c0, c1, c2)
    g = 0.0
    for k in range(3):
        zk = z0 if k == 0 else (z1 if k == 1 else z2)
        Jk = c0 if k == 0 else (c1 if k == 1 else c2)
        ek = e0 if k == 0 else (e1 if k == 1 else e2)
        g += abs(_det(_djac(jt, 0, k, z0, zk, c0, Jk), c1, c2)
                 + _det(c0, _djac(jt, 1, k, z1, zk, c1, Jk), c2)
                 + _det(c0, c1, _djac(jt, 2, k, z2, zk, c2, Jk))) * ek
    quad = 0.5 * (M2[0, 0] * e0 * e0 + M2[1, 1] * e1 * e1 + M2[2, 2] * e2 * e2
                  + 2.0 * (M2[0, 1] * e0 * e1 + M2[0, 2] * e0 * e2 + M2[1, 2] * e1 * e2))
    return abs(d) > (g + quad) * (1.0 + 1e-9) + 1e-18


@njit(cache=True)
def _cell_feasible(chain, c0, c1, c2, e0, e1, e2):
    """Can the cell (centre c, half-widths e) meet Q? False only if a limit row fails on all of it."""
    A = chain.A
    for r in range(A.shape[0]):
        m = A[r, 0] * c0 + A[r, 1] * c1 + A[r, 2] * c2
        s = abs(A[r, 0]) * e0 + abs(A[r, 1]) * e1 + abs(A[r, 2]) * e2
        lo = chain.lo[r]
        hi = chain.hi[r]
        slack = 1e-9 * (1.0 + abs(lo) + abs(hi) + s)
        if m + s < lo - slack or m - s > hi + slack:
            return False
    return True


@njit(cache=True)
def _coarse_bbox(chain, K, jlo, djoint, ncell):
    """Bounding box of the image balls of all feasible coarse cells, and the largest ball."""
    bmin = np.full(3, np.inf)
    bmax = np.full(3, -np.inf)
    e0, e1, e2 = 0.5 * djoint[0], 0.5 * djoint[1], 0.5 * djoint[2]
    q2term = 0.5 * K * (e0 * e0 + e1 * e1 + e2 * e2)
    rmax = 0.0
    for i in range(ncell[0]):
        c0 = jlo[0] + (i + 0.5) * djoint[0]
        for j in range(ncell[1]):
            c1 = jlo[1] + (j + 0.5) * djoint[1]
            for k in range(ncell[2]):
                c2 = jlo[2] + (k + 0.5) * djoint[2]
                if not _cell_feasible(chain, c0, c1, c2, e0, e1, e2):
                    continue
                w, a, b, c = _fkjac3(chain, c0, c1, c2)
                rho = (math.sqrt(_dot(a, a)) * e0 + math.sqrt(_dot(b, b)) * e1
                       + math.sqrt(_dot(c, c)) * e2 + q2term) * (1.0 + 1e-9) + 1e-12
                rmax = max(rmax, rho)
                for d in range(3):
                    bmin[d] = min(bmin[d], w[d] - rho)
                    bmax[d] = max(bmax[d], w[d] + rho)
    return bmin, bmax, rmax


@njit(cache=True)
def _add_seed(sd, sdist, scnt, v, q0, q1, q2, dist, tau):
    S = sd.shape[1]
    n = scnt[v]
    for k in range(n):
        if (abs(sd[v, k, 0] - q0) < tau and abs(sd[v, k, 1] - q1) < tau
                and abs(sd[v, k, 2] - q2) < tau):
            if dist < sdist[v, k]:
                sd[v, k, 0], sd[v, k, 1], sd[v, k, 2] = q0, q1, q2
                sdist[v, k] = dist
            return
    if n < S:
        sd[v, n, 0], sd[v, n, 1], sd[v, n, 2] = q0, q1, q2
        sdist[v, n] = dist
        scnt[v] = n + 1
        return
    worst = 0
    for k in range(1, S):
        if sdist[v, k] > sdist[v, worst]:
            worst = k
    if dist < sdist[v, worst]:
        sd[v, worst, 0], sd[v, worst, 1], sd[v, worst, 2] = q0, q1, q2
        sdist[v, worst] = dist


@njit(cache=True, inline="always")
def _neighbour6(ix, iy, iz, d):
    if d == 0:
        return ix - 1, iy, iz
    if d == 1:
        return ix + 1, iy, iz
    if d == 2:
        return ix, iy - 1, iz
    if d == 3:
        return ix, iy + 1, iz
    if d == 4:
        return ix, iy, iz - 1
    return ix, iy, iz + 1


@njit(cache=True)
def _mark_ball(bnd, w, rho, origin, h, nx, ny, nz):
    """Flag every voxel that meets the ball B(w, rho)."""
    lo0 = max(0, int(math.floor((w[0] - rho - origin[0]) / h)))
    hi0 = min(nx - 1, int(math.floor((w[0] + rho - origin[0]) / h)))
    lo1 = max(0, int(math.floor((w[1] - rho - origin[1]) / h)))
    hi1 = min(ny - 1, int(math.floor((w[1] + rho - origin[1]) / h)))
    lo2 = max(0, int(math.floor((w[2] - rho - origin[2]) / h)))
    hi2 = min(nz - 1, int(math.floor((w[2] + rho - origin[2]) / h)))
    r2 = rho * rho
    for ix in range(lo0, hi0 + 1):
        x0 = origin[0] + ix * h
        dx = max(0.0, max(x0 - w[0], w[0] - x0 - h))
        for iy in range(lo1, hi1 + 1):
            y0 = origin[1] + iy * h
            dy = max(0.0, max(y0 - w[1], w[1] - y0 - h))
            for iz in range(lo2, hi2 + 1):
                z0 = origin[2] + iz * h
                dz = max(0.0, max(z0 - w[2], w[2] - z0 - h))
                if dx * dx + dy * dy + dz * dz <= r2:
                    bnd[(ix * ny + iy) * nz + iz] = 1


@njit(cache=True)
def _seed_at(chain, sd, sdist, scnt, fx, fy, fz, sub, cy, cz, c0, c1, c2, tau):
    """Offer configuration c (projected into the box) as a seed of the cell holding voxel coords f."""
    jx, jy, jz = int(fx) // sub, int(fy) // sub, int(fz) // sub
    ux = fx / sub - jx - 0.5
    uy = fy / sub - jy - 0.5
    uz = fz / sub - jz - 0.5
    _add_seed(sd, sdist, scnt, (jx * cy + jy) * cz + jz, _box(chain, 0, c0), _box(chain, 1, c1),
              _box(chain, 2, c2), ux * ux + uy * uy + uz * uz, tau)


@njit(cache=True)
def _build_map(chain, K, M2, jlo, djoint, ncell, faces, origin, h, shape, sub, beta, max_depth, S, tau):
    """Classify the voxels and collect IK seeds (see the module docstring).

    Returns state (nx, ny, nz) uint8, seed_ptr, seeds, stats (int64: leaves, critical leaves,
    conflicts, seed cells without seeds).
    """
    nx, ny, nz = shape[0], shape[1], shape[2]
    nvox = nx * ny * nz
    cx, cy, cz = nx // sub, ny // sub, nz // sub
    ncel = cx * cy * cz
    bnd = np.zeros(nvox, np.uint8)
    hit = np.zeros(nvox, np.uint8)
    sd = np.zeros((ncel, S, 3), np.float64)
    sdist = np.full((ncel, S), np.inf, np.float32)
    scnt = np.zeros(ncel, np.int64)
    cap = 8 * (max_depth + 2)
    st = np.empty((cap, 6))
    sdep = np.empty(cap, np.int64)
    n_leaf = 0
    n_crit = 0
    for i in range(ncell[0]):
        for j in range(ncell[1]):
            for k in range(ncell[2]):
                st[0, 0] = jlo[0] + (i + 0.5) * djoint[0]
                st[0, 1] = jlo[1] + (j + 0.5) * djoint[1]
                st[0, 2] = jlo[2] + (k + 0.5) * djoint[2]
                st[0, 3] = 0.5 * djoint[0]
                st[0, 4] = 0.5 * djoint[1]
                st[0, 5] = 0.5 * djoint[2]
                sdep[0] = 0
                top = 1
                while top > 0:
                    top -= 1
                    c0, c1, c2 = st[top, 0], st[top, 1], st[top, 2]
                    e0, e1, e2 = st[top, 3], st[top, 4], st[top, 5]
                    dep = sdep[top]
                    if not _cell_feasible(chain, c0, c1, c2, e0, e1, e2):
                        continue
                    w, a, b, c, z0, z1, z2 = _fkjacz3(chain, c0, c1, c2)
                    ee = e0 * e0 + e1 * e1 + e2 * e2
                    rho = (math.sqrt(_dot(a, a)) * e0 + math.sqrt(_dot(b, b)) * e1
                           + math.sqrt(_dot(c, c)) * e2 + 0.5 * K * ee) * (1.0 + 1e-9) + 1e-12
                    # may the cell hold a singular configuration? (Weyl on sigma_min, then det J)
                    crit = False
                    if _smin3(a, b, c) <= K * math.sqrt(ee) * (1.0 + 1e-9) + 1e-9:
                        crit = not _nonsingular(chain, a, b, c, z0, z1, z2, e0, e1, e2, M2)
                    if crit and rho > beta * h and dep < max_depth:
                        for s0 in (-0.5, 0.5):
                            for s1 in (-0.5, 0.5):
                                for s2 in (-0.5, 0.5):
                                    st[top, 0] = c0 + s0 * e0
                                    st[top, 1] = c1 + s1 * e1
                                    st[top, 2] = c2 + s2 * e2
                                    st[top, 3] = 0.5 * e0
                                    st[top, 4] = 0.5 * e1
                                    st[top, 5] = 0.5 * e2
                                    sdep[top] = dep + 1
                                    top += 1
                        continue
                    n_leaf += 1
                    if crit:
                        n_crit += 1
                        _mark_ball(bnd, w, rho, origin, h, nx, ny, nz)
                    fx = (w[0] - origin[0]) / h
                    fy = (w[1] - origin[1]) / h
                    fz = (w[2] - origin[2]) / h
                    if fx >= 0.0 and fx < nx and fy >= 0.0 and fy < ny and fz >= 0.0 and fz < nz:
                        if _rows_ok(chain, c0, c1, c2, 0.0):
                            hit[(int(fx) * ny + int(fy)) * nz + int(fz)] = 1
                        _seed_at(chain, sd, sdist, scnt, fx, fy, fz, sub, cy, cz, c0, c1, c2, tau)
    # ---- the faces of Q (box faces of joints that do not wrap, coupled-limit planes), as
    # patches q = c + u t1 + v t2 refined (2-D) until their image ball has radius <= beta h
    n_face = 0
    pst = np.empty((4 * max_depth + 8, 5))
    A = chain.A
    for f in range(faces.shape[0]):
        pst[0, 0] = 0.5 * (faces[f, 9] + faces[f, 10])
        pst[0, 1] = 0.5 * (faces[f, 11] + faces[f, 12])
        pst[0, 2] = 0.5 * (faces[f, 10] - faces[f, 9])
        pst[0, 3] = 0.5 * (faces[f, 12] - faces[f, 11])
        pst[0, 4] = 0
        top = 1
        while top > 0:
            top -= 1
            u, v, eu, ev, dep = pst[top, 0], pst[top, 1], pst[top, 2], pst[top, 3], pst[top, 4]
            c0 = faces[f, 0] + u * faces[f, 3] + v * faces[f, 6]
            c1 = faces[f, 1] + u * faces[f, 4] + v * faces[f, 7]
            c2 = faces[f, 2] + u * faces[f, 5] + v * faces[f, 8]
            t1 = (faces[f, 3], faces[f, 4], faces[f, 5])
            t2 = (faces[f, 6], faces[f, 7], faces[f, 8])
            feas = True
            for r in range(A.shape[0]):
                m = A[r, 0] * c0 + A[r, 1] * c1 + A[r, 2] * c2
                sr = abs(A[r, 0] * t1[0] + A[r, 1] * t1[1] + A[r, 2] * t1[2]) * eu \
                    + abs(A[r, 0] * t2[0] + A[r, 1] * t2[1] + A[r, 2] * t2[2]) * ev
                slack = 1e-9 * (1.0 + abs(chain.lo[r]) + abs(chain.hi[r]) + sr)
                if m + sr < chain.lo[r] - slack or m - sr > chain.hi[r] + slack:
                    feas = False
                    break
            if not feas:
                continue
            w, a, b, c = _fkjac3(chain, c0, c1, c2)
            j1 = (a[0] * t1[0] + b[0] * t1[1] + c[0] * t1[2], a[1] * t1[0] + b[1] * t1[1] + c[1] * t1[2],
                  a[2] * t1[0] + b[2] * t1[1] + c[2] * t1[2])
            j2 = (a[0] * t2[0] + b[0] * t2[1] + c[0] * t2[2], a[1] * t2[0] + b[1] * t2[1] + c[1] * t2[2],
                  a[2] * t2[0] + b[2] * t2[1] + c[2] * t2[2])
            s1 = math.sqrt(_dot(j1, j1)) * eu
            s2 = math.sqrt(_dot(j2, j2)) * ev
            dq = math.sqrt(_dot(t1, t1)) * eu + math.sqrt(_dot(t2, t2)) * ev
            rho = (s1 + s2 + 0.5 * K * dq * dq) * (1.0 + 1e-9) + 1e-12
            if rho > beta * h and dep < 2 * max_depth:
                # halve the side that contributes more to rho (linear and quadratic terms)
                if s1 + 0.5 * K * dq * math.sqrt(_dot(t1, t1)) * eu >= s2 + 0.5 * K * dq * math.sqrt(_dot(t2, t2)) * ev:
                    for sg in (-0.5, 0.5):
                        pst[top, 0], pst[top, 1] = u + sg * eu, v
                        pst[top, 2], pst[top, 3], pst[top, 4] = 0.5 * eu, ev, dep + 1
                        top += 1
                else:
                    for sg in (-0.5, 0.5):
                        pst[top, 0], pst[top, 1] = u, v + sg * ev
                        pst[top, 2], pst[top, 3], pst[top, 4] = eu, 0.5 * ev, dep + 1
                        top += 1
                continue
            n_face += 1
            _mark_ball(bnd, w, rho, origin, h, nx, ny, nz)
            fx = (w[0] - origin[0]) / h
            fy = (w[1] - origin[1]) / h
            fz = (w[2] - origin[2]) / h
            if fx >= 0.0 and fx < nx and fy >= 0.0 and fy < ny and fz >= 0.0 and fz < nz:
                _seed_at(chain, sd, sdist, scnt, fx, fy, fz, sub, cy, cz, c0, c1, c2, tau)
    # ---- flood fill of the non-boundary voxels: out from the border layer, in from the hits
    lab = np.zeros(nvox, np.uint8)   # 0 unknown, 1 out, 2 in
    queue = np.empty(nvox, np.int64)
    conflicts = 0
    for pas in range(2):
        qh = 0
        qt = 0
        for v in range(nvox):
            if bnd[v] or lab[v]:
                continue
            iz = v % nz
            iy = (v // nz) % ny
            ix = v // (ny * nz)
            if pas == 0:
                start = ix == 0 or iy == 0 or iz == 0 or ix == nx - 1 or iy == ny - 1 or iz == nz - 1
            else:
                start = hit[v] == 1
            if start:
                lab[v] = 1 + pas
                queue[qt] = v
                qt += 1
        while qh < qt:
            v = queue[qh]
            qh += 1
            if pas == 0 and hit[v]:
                conflicts += 1
            iz = v % nz
            iy = (v // nz) % ny
            ix = v // (ny * nz)
            for d in range(6):
                jx, jy, jz = _neighbour6(ix, iy, iz, d)
                if jx < 0 or jy < 0 or jz < 0 or jx >= nx or jy >= ny or jz >= nz:
                    continue
                u = (jx * ny + jy) * nz + jz
                if bnd[u] or lab[u]:
                    continue
                lab[u] = 1 + pas
                queue[qt] = u
                qt += 1
    state = np.empty(nvox, np.uint8)
    cflag = np.zeros(ncel, np.uint8)   # 0 only out voxels, 1 some in, 2 some boundary
    for v in range(nvox):
        if bnd[v]:
            s = 2
        elif lab[v] == 1:
            s = 0
        elif lab[v] == 2:
            s = 1
        else:
            s = 2
        state[v] = s
        iz = v % nz
        iy = (v // nz) % ny
        ix = v // (ny * nz)
        c = ((ix // sub) * cy + iy // sub) * cz + iz // sub
        if s > cflag[c]:
            cflag[c] = s
    # ---- seeds: cells with boundary voxels take their own and their 26 neighbours' (one per
    # branch), cells with in voxels their own, else their neighbours'; any still without seeds
    # get the nearest cell's.
    S2 = S + 2
    fd = np.zeros((ncel, S2, 3), np.float64)
    fdist = np.full((ncel, S2), np.inf, np.float32)
    fcnt = np.zeros(ncel, np.int64)
    for c in range(ncel):
        if cflag[c] == 0:
            continue
        for k in range(scnt[c]):
            _add_seed(fd, fdist, fcnt, c, sd[c, k, 0], sd[c, k, 1], sd[c, k, 2], sdist[c, k], tau)
        if cflag[c] == 1 and fcnt[c] > 0:
            continue
        kz = c % cz
        ky = (c // cz) % cy
        kx = c // (cy * cz)
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    jx, jy, jz = kx + dx, ky + dy, kz + dz
                    if jx < 0 or jy < 0 or jz < 0 or jx >= cx or jy >= cy or jz >= cz:
                        continue
                    u = (jx * cy + jy) * cz + jz
                    if u == c:
                        continue
                    off = float(dx * dx + dy * dy + dz * dz)
                    for k in range(scnt[u]):
                        _add_seed(fd, fdist, fcnt, c, sd[u, k, 0], sd[u, k, 1], sd[u, k, 2],
                                  sdist[u, k] + off, tau)
    qh = 0
    qt = 0
    cq = np.empty(ncel, np.int64)
    for c in range(ncel):
        if cflag[c] != 0 and fcnt[c] > 0:
            cq[qt] = c
            qt += 1
    while qh < qt:
        c = cq[qh]
        qh += 1
        kz = c % cz
        ky = (c // cz) % cy
        kx = c // (cy * cz)
        for d in range(6):
            jx, jy, jz = _neighbour6(kx, ky, kz, d)
            if jx < 0 or jy < 0 or jz < 0 or jx >= cx or jy >= cy or jz >= cz:
                continue
            u = (jx * cy + jy) * cz + jz
            if cflag[u] == 0 or fcnt[u] > 0:
                continue
            for k in range(fcnt[c]):
                fd[u, k] = fd[c, k]
                fdist[u, k] = fdist[c, k] + 1.0
            fcnt[u] = fcnt[c]
            cq[qt] = u
            qt += 1
    seedless = 0
    total = 0
    for c in range(ncel):
        if cflag[c] != 0:
            total += fcnt[c]
            if fcnt[c] == 0:
                seedless += 1
    seed_ptr = np.zeros(ncel + 1, np.int64)
    seeds = np.empty((total, 3))
    pos = 0
    for c in range(ncel):
        seed_ptr[c] = pos
        if cflag[c] == 0:
            continue
        n = fcnt[c]
        order = np.argsort(fdist[c, :n])
        for k in range(n):
            seeds[pos] = fd[c, order[k]]
            pos += 1
    seed_ptr[ncel] = pos
    stats = np.array([n_leaf, n_crit, conflicts, seedless, n_face], np.int64)
    return state.reshape((nx, ny, nz)), seed_ptr, seeds, stats


# ============================================================================ helpers
def _rpy_matrix(rpy) -> np.ndarray:
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _se3(M) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(M.rotation)
    T[:3, 3] = np.asarray(M.translation)
    return T


@contextlib.contextmanager
def _captured_stderr():
    """Capture what C++ libraries (urdfdom) print on file descriptor 2; yields a callable giving it."""
    buf = tempfile.TemporaryFile(mode="w+b")
    saved = None
    try:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(buf.fileno(), 2)
    except OSError:  # no usable fd 2: nothing to capture
        saved = None
    text: list[str] = []
    try:
        yield lambda: "".join(text)
    finally:
        if saved is not None:
            os.dup2(saved, 2)
            os.close(saved)
        buf.seek(0)
        text.append(buf.read().decode("utf-8", "replace"))
        buf.close()


def _urdfdom_reason(log: str) -> str:
    for line in log.splitlines():
        line = line.strip()
        if line.startswith("Error:"):
            return line[len("Error:"):].strip()
    return ""


def _joint_kind(shortname: str) -> str:
    if re.search(r"RevoluteUnbounded|JointModelRUB[XYZ]$", shortname):
        return "continuous"
    if re.search(r"Revolute|JointModelR[XYZ]$", shortname):
        return "revolute"
    if re.search(r"Prismatic|JointModelP[XYZ]$", shortname):
        return "prismatic"
    return re.sub(r"^JointModel", "", shortname).lower()


def _finite_tuple(value, n: int, what: str, where: str) -> tuple[float, ...]:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ScenarioError(f"{where}: {what} must be {n} numbers, got {value!r}") from None
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ScenarioError(f"{where}: {what} must be {n} finite numbers, got {value!r}")
    return tuple(float(v) for v in arr)


def cache_dir() -> Path:
    """Where reachability maps are cached: ``$ERRPLAN_CACHE_DIR``, else ``~/.cache/errplan``."""
    env = os.environ.get("ERRPLAN_CACHE_DIR")
    return Path(env) if env else Path.home() / ".cache" / "errplan"


# ============================================================================ the arm
def _check_tree(root, where: str) -> None:
    """What urdfdom and pinocchio let through or report misleadingly: a link with two parent joints (a URDF
    is a tree) and a movable joint whose axis is not a direction. One :class:`ScenarioError` each."""
    parents: dict[str, list[str]] = {}
    for j in root.iter("joint"):
        name = j.get("name", "?")
        child = j.find("child")
        if child is not None and child.get("link"):
            parents.setdefault(child.get("link"), []).append(name)
        axis = j.find("axis")
        if axis is None or j.get("type") in ("fixed", "floating"):
            continue
        try:
            xyz = [float(v) for v in (axis.get("xyz") or "1 0 0").split()]
        except ValueError:
            continue  # urdfdom names the bad number
        if len(xyz) == 3 and all(math.isfinite(v) for v in xyz) and math.hypot(*xyz) < 1e-12:
            raise ScenarioError(f"{where}: joint '{name}' has a zero axis (xyz = \"{axis.get('xyz')}\"): "
                                "expected a direction")
    for link, js in parents.items():
        if len(js) > 1:
            raise ScenarioError(f"{where}: link '{link}' has {len(js)} parent joints ({', '.join(js)}): a URDF is a "
                                "tree, each link the child of one joint")


class UrdfArm:
    """A serial arm from a URDF whose three actuated joints place the wrist (module docstring).

    Build with :meth:`load` or :meth:`from_robot`. Joint vectors are ``(..., n)`` in the order of
    ``joint_names``; points ``(..., 3)`` world ``[x, y, z]``.
    """

    n: int
    joint_names: tuple[str, ...]
    limits: np.ndarray

    def __init__(self, *, urdf_path: Path, urdf_text: str, model, joint_names, wrist, chain: ChainData,
                 base_position, base_rpy, coupled, fixed_values, package_path, act_ids, qref,
                 segments, map_params: MapParams):
        self.urdf_path = urdf_path
        self.urdf_text = urdf_text
        self.model = model
        self.joint_names = tuple(joint_names)
        self.n = len(self.joint_names)
        self.wrist = wrist
        self.chain = chain
        self.base_position = tuple(base_position)
        self.base_rpy = tuple(base_rpy)
        self.coupled_limits = tuple(coupled)
        self.fixed_joints = dict(fixed_values)
        self.package_path = tuple(package_path)
        self.limits = np.stack([chain.lo[: self.n], chain.hi[: self.n]], axis=-1)
        self.map_params = map_params
        self.map_info: dict = {}
        self._act_ids = act_ids
        self._qref = qref
        self._segments = segments
        self._rmap: ReachMap | None = None
        self._gravity = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_robot(cls, robot, map_params: MapParams | None = None) -> "UrdfArm":
        """From a scenario's ``UrdfRobot`` (attributes as :meth:`load`'s arguments)."""
        return cls.load(robot.urdf, robot.joints, robot.wrist, base_position=robot.base_position,
                        base_rpy=robot.base_rpy, joint_limits=robot.joint_limits,
                        fixed_joints=robot.fixed_joints or {}, coupled_limits=robot.coupled_limits or (),
                        package_path=robot.package_path or (), map_params=map_params)

    @classmethod
    def load(cls, urdf: str | Path, joints: Sequence[str], wrist: str, base_position=(0.0, 0.0, 0.0),
             base_rpy=(0.0, 0.0, 0.0), joint_limits=None, fixed_joints: Mapping[str, float] = {},
             coupled_limits: Sequence[CoupledLimit] = (), package_path: Sequence[str] = (),
             map_params: MapParams | None = None) -> "UrdfArm":
        """Read the URDF and build the chain from the root to the ``wrist`` link.

        Raises :class:`ScenarioError` (one line naming the file and the offending value) for a
        missing or unreadable file, text that is not a URDF, unknown or misplaced joints, a
        missing wrist link, joints that are not revolute/continuous/prismatic, a chain that cannot
        place the wrist in 3-D, and bad limits.
        """
        import pinocchio as pin

        path = Path(urdf)
        where = str(path)
        raw = read_bytes(path, "URDF file", ScenarioError)
        try:
            root = ET.fromstring(raw)
        except ET.ParseError as exc:
            raise ScenarioError(f"URDF {where} is not XML ({exc})") from None
        if root.tag != "robot":
            raise ScenarioError(f"URDF {where} is not a URDF: its root element is <{root.tag}>, expected <robot>")
        _check_tree(root, where)
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise ScenarioError(f"URDF {where} is not UTF-8 text") from None
        with _captured_stderr() as log:
            try:
                model = pin.buildModelFromXML(text)
                err = None
            except Exception as exc:  # pinocchio/urdfdom: ValueError, RuntimeError
                err = exc
        if err is not None:
            reason = _urdfdom_reason(log()) or str(err).splitlines()[0]
            raise ScenarioError(f"URDF {where} is not a valid URDF: {reason}")

        # ---- names
        joints = [joints] if isinstance(joints, str) else list(joints)
        if not all(isinstance(j, str) for j in joints):
            raise ScenarioError(f"{where}: joints must be joint names, got {joints!r}")
        if not isinstance(wrist, str):
            raise ScenarioError(f"{where}: wrist must be a link name, got {wrist!r}")
        body_frames = {f.name: k for k, f in enumerate(model.frames) if f.type == pin.FrameType.BODY}
        fixed_frames = {f.name for f in model.frames if f.type == pin.FrameType.FIXED_JOINT}
        if wrist not in body_frames:
            raise ScenarioError(f"{where}: wrist link '{wrist}' is not in the URDF "
                                f"(links: {', '.join(sorted(body_frames))})")
        jnames = list(model.names)
        all_joint_names = sorted(set(jnames[1:]) | (fixed_frames - {"universe"}))
        for j in joints:
            if j in fixed_frames:
                raise ScenarioError(f"{where}: joint '{j}' is fixed; actuated joints must be revolute, "
                                    "continuous or prismatic")
            if j not in jnames[1:]:
                raise ScenarioError(f"{where}: joint '{j}' is not in the URDF (joints: {', '.join(all_joint_names)})")
        if len(set(joints)) != len(joints):
            raise ScenarioError(f"{where}: joints {joints} name a joint twice")
        wf = model.frames[body_frames[wrist]]
        chain_ids: list[int] = []
        jid = wf.parentJoint
        while jid != 0:
            chain_ids.append(jid)
            jid = model.parents[jid]
        chain_ids.reverse()
        chain_names = [jnames[i] for i in chain_ids]
        root_name = model.frames[1].name if len(model.frames) > 1 else "root"
        for j in joints:
            if j not in chain_names:
                raise ScenarioError(f"{where}: joint '{j}' is not on the chain from the root link '{root_name}' "
                                    f"to the wrist link '{wrist}' (that chain: {', '.join(chain_names) or 'none'})")
        for jid in chain_ids:
            kind = _joint_kind(model.joints[jid].shortname())
            if kind not in ("revolute", "continuous", "prismatic"):
                raise ScenarioError(f"{where}: joint '{jnames[jid]}' on the chain to '{wrist}' is {kind}; "
                                    "only revolute, continuous, prismatic and fixed joints can be on it")
        order = [chain_names.index(j) for j in joints]
        if order != sorted(order):
            raise ScenarioError(f"{where}: joints {joints} must be listed from the root to the wrist "
                                f"({', '.join(c for c in chain_names if c in joints)})")
        if len(joints) != 3:
            raise ScenarioError(f"{where}: {len(joints)} actuated joint(s) {joints} cannot place the wrist in 3-D; "
                                "exactly 3 are needed")
        fixed_joints = dict(fixed_joints or {})
        held = {}
        for name, val in fixed_joints.items():
            if name in joints:
                raise ScenarioError(f"{where}: fixed_joints names '{name}', which is an actuated joint")
            if name not in chain_names:
                raise ScenarioError(f"{where}: fixed_joints names '{name}', which is not a movable joint on the chain "
                                    f"from '{root_name}' to '{wrist}' ({', '.join(c for c in chain_names if c not in joints) or 'none'})")
            try:
                v = float(val)
            except (TypeError, ValueError):
                v = float("nan")
            if not math.isfinite(v):
                raise ScenarioError(f"{where}: fixed_joints value of '{name}' must be a finite number, got {val!r}")
            held[name] = v
        held_all = {name: held.get(name, 0.0) for name in chain_names if name not in joints}
        base_position = _finite_tuple(base_position, 3, "base_position", where)
        base_rpy = _finite_tuple(base_rpy, 3, "base_rpy", where)
        act_ids = [model.getJointId(j) for j in joints]
        kinds = [_joint_kind(model.joints[i].shortname()) for i in act_ids]

        # ---- limits
        if joint_limits is None:
            lims = []
            for j, jid, kind in zip(joints, act_ids, kinds):
                if kind == "continuous":
                    lims.append((-math.pi, math.pi))
                    continue
                iq = model.joints[jid].idx_q
                lo, hi = float(model.lowerPositionLimit[iq]), float(model.upperPositionLimit[iq])
                if not (math.isfinite(lo) and math.isfinite(hi)):
                    raise ScenarioError(f"{where}: joint '{j}' has no finite limits in the URDF; give joint_limits")
                if lo > hi:
                    raise ScenarioError(f"{where}: joint '{j}' has reversed limits in the URDF: lower {lo} > upper {hi}")
                if lo == hi:
                    raise ScenarioError(f"{where}: joint '{j}' has an empty range in the URDF: lower = upper = {lo}")
                lims.append((lo, hi))
        else:
            try:
                arr = np.asarray(joint_limits, dtype=float)
            except (TypeError, ValueError):
                raise ScenarioError(f"{where}: joint_limits must be {len(joints)} pairs [lo, hi], got {joint_limits!r}") from None
            if arr.shape != (len(joints), 2) or not np.all(np.isfinite(arr)):
                raise ScenarioError(f"{where}: joint_limits must be {len(joints)} finite pairs [lo, hi], got {joint_limits!r}")
            for j, (lo, hi) in zip(joints, arr):
                if lo > hi:
                    raise ScenarioError(f"{where}: joint_limits for '{j}' are reversed: [{lo}, {hi}]")
                if lo == hi:
                    raise ScenarioError(f"{where}: joint_limits for '{j}' are an empty range: [{lo}, {hi}]")
            lims = [(float(a), float(b)) for a, b in arr]
        rows = [np.eye(len(joints))[i] for i in range(len(joints))]
        lo_r = [a for a, _ in lims]
        hi_r = [b for _, b in lims]
        coupled = []
        for cl in coupled_limits or ():
            cj = tuple(getattr(cl, "joints", ()))
            cc = tuple(getattr(cl, "coeffs", ()))
            desc = f"coupled limit {list(cj)}"
            if len(cj) == 0 or len(cj) != len(cc):
                raise ScenarioError(f"{where}: {desc} needs one coefficient per joint, got coeffs {list(cc)}")
            row = np.zeros(len(joints))
            for name, coef in zip(cj, cc):
                if name not in joints:
                    raise ScenarioError(f"{where}: {desc} names '{name}', which is not an actuated joint {joints}")
                try:
                    c = float(coef)
                except (TypeError, ValueError):
                    c = float("nan")
                if not math.isfinite(c):
                    raise ScenarioError(f"{where}: {desc} has a bad coefficient {coef!r}")
                row[joints.index(name)] += c
            try:
                lo, hi = float(cl.lo), float(cl.hi)
            except (TypeError, ValueError):
                lo = hi = float("nan")
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise ScenarioError(f"{where}: {desc} bounds must be finite numbers, got [{cl.lo!r}, {cl.hi!r}]")
            if lo > hi:
                raise ScenarioError(f"{where}: {desc} bounds are reversed: [{lo}, {hi}]")
            if not np.any(row):
                raise ScenarioError(f"{where}: {desc} has all-zero coefficients")
            rows.append(row)
            lo_r.append(lo)
            hi_r.append(hi)
            coupled.append(CoupledLimit(cj, tuple(float(c) for c in cc), lo, hi))

        # ---- reference configuration: actuated 0, held joints at their values
        qref = pin.neutral(model)

        def set_joint(q, jid, val):
            jm = model.joints[jid]
            if jm.nq == 1:
                q[jm.idx_q] = val
            else:  # continuous: (cos, sin)
                q[jm.idx_q], q[jm.idx_q + 1] = math.cos(val), math.sin(val)

        for name, val in held_all.items():
            set_joint(qref, model.getJointId(name), val)
        data = model.createData()
        pin.forwardKinematics(model, data, qref)
        pin.updateFramePlacements(model, data)
        pin.computeJointJacobians(model, data, qref)
        B = np.eye(4)
        B[:3, :3] = _rpy_matrix(base_rpy)
        B[:3, 3] = base_position
        oMi = [_se3(data.oMi[i]) for i in act_ids]
        T = np.empty((4, 4, 4))
        T[0] = B @ oMi[0]
        for i in range(1, 3):
            T[i] = np.linalg.solve(oMi[i - 1], oMi[i])
        T[3] = np.linalg.solve(oMi[2], _se3(data.oMf[body_frames[wrist]]))
        axes = np.empty((3, 3))
        jtype = np.empty(3, np.int64)
        for k, (jid, kind) in enumerate(zip(act_ids, kinds)):
            S = np.asarray(pin.getJointJacobian(model, data, jid, pin.ReferenceFrame.LOCAL))[:, model.joints[jid].idx_v]
            if kind == "prismatic":
                ax, jtype[k] = S[:3], 1
            else:
                ax, jtype[k] = S[3:], 0
            axes[k] = ax / np.linalg.norm(ax)
        chain = ChainData(np.ascontiguousarray(T), axes, jtype, np.ascontiguousarray(np.array(rows, float)),
                          np.array(lo_r, float), np.array(hi_r, float))

        # ---- drawing points (joint and fixed-joint origins on the chain), per moving segment
        path_frames = []
        fid = body_frames[wrist]
        while fid != 0:
            f = model.frames[fid]
            if f.type in (pin.FrameType.JOINT, pin.FrameType.FIXED_JOINT):
                path_frames.append(fid)
            fid = f.parentFrame
        path_frames.reverse()
        n_before = {jid: sum(1 for a in act_ids if a in chain_ids[: chain_ids.index(jid)]) for jid in chain_ids}
        n_before[0] = 0
        segments: list[list[np.ndarray]] = [[np.array(base_position)]] + [[] for _ in range(3)]
        for fid in path_frames:
            f = model.frames[fid]
            pj = f.parentJoint
            s = n_before[pj] + (1 if f.type == pin.FrameType.FIXED_JOINT and pj in act_ids else 0)
            pos = np.append(np.asarray(data.oMf[fid].translation), 1.0)
            local = (B @ pos)[:3] if s == 0 else np.linalg.solve(oMi[s - 1], pos)[:3]
            if not any(np.allclose(x, local, rtol=0, atol=1e-12) for x in segments[s]):
                segments[s].append(local)
        segments[3] = [x for x in segments[3] if not np.allclose(x, T[3][:3, 3], rtol=0, atol=1e-12)]

        arm = cls(urdf_path=path.resolve(), urdf_text=text, model=model, joint_names=joints, wrist=wrist,
                  chain=chain, base_position=base_position, base_rpy=base_rpy, coupled=coupled,
                  fixed_values=held, package_path=[str(p) for p in (package_path or ())], act_ids=act_ids,
                  qref=qref, segments=[np.array(s).reshape(-1, 3) for s in segments],
                  map_params=map_params or MapParams())
        arm._check_rank(where)
        return arm

    def _check_rank(self, where: str) -> None:
        """One clear error for limits that leave nothing feasible or a chain that cannot move the
        wrist in 3-D (rank-deficient Jacobian at every sampled configuration of the box)."""
        ch = self.chain
        if len(ch.A) == self.n:  # the box alone (A = I): feasible iff every lower limit is below its upper one
            feasible = bool(np.all(ch.lo <= ch.hi))
        else:  # coupled limits: a linear program (scipy.optimize costs 0.4 s to import, so only here)
            from scipy.optimize import linprog

            res = linprog(np.zeros(self.n), A_ub=np.concatenate([ch.A, -ch.A]), b_ub=np.concatenate([ch.hi, -ch.lo]),
                          bounds=[(None, None)] * self.n, method="highs")
            feasible = res.status == 0
        if not feasible:
            raise ScenarioError(f"{where}: the joint limits leave no feasible configuration "
                                f"(box {self.limits.tolist()}, coupled limits "
                                f"{[(list(c.joints), c.lo, c.hi) for c in self.coupled_limits]})")
        g = [np.linspace(lo, hi, 7) for lo, hi in self.limits]
        Q = np.stack(np.meshgrid(*g, indexing="ij"), axis=-1).reshape(-1, 3)
        rng = np.random.default_rng(0)
        Q = np.concatenate([Q, self.limits[:, 0] + rng.random((200, 3)) * np.ptp(self.limits, axis=1)])
        sv = np.linalg.svd(self.jacobian(Q), compute_uv=False)
        ratio = sv[:, -1] / np.maximum(sv[:, 0], 1e-300)
        if not np.any(ratio > 1e-8):
            raise ScenarioError(f"{where}: joints {list(self.joint_names)} cannot place the wrist '{self.wrist}' in 3-D "
                                "(its Jacobian is rank-deficient at every sampled configuration)")

    # ------------------------------------------------------------------ forward
    def _as_q(self, q) -> tuple[np.ndarray, tuple]:
        q = np.asarray(q, dtype=float)
        if q.shape[-1:] != (self.n,):
            raise ValueError(f"joint vectors must have shape (..., {self.n}), got {q.shape}")
        return np.ascontiguousarray(q.reshape(-1, self.n)), q.shape[:-1]

    def forward(self, q) -> np.ndarray:
        """Wrist position (..., 3), world frame, for joint values ``q`` (..., n)."""
        Q, lead = self._as_q(q)
        out = np.empty((len(Q), 3))
        _fk_many(self.chain, Q, out)
        return out.reshape(lead + (3,))

    def jacobian(self, q) -> np.ndarray:
        """``d wrist / d q`` (..., 3, n): rows world x, y, z; columns the actuated joints."""
        Q, lead = self._as_q(q)
        out = np.empty((len(Q), 3, 3))
        _jac_many(self.chain, Q, out)
        return out.reshape(lead + (3, 3))

    def chain_points(self, q) -> np.ndarray:
        """World positions (..., k, 3) of the root, the joint origins on the chain and the wrist
        (for drawing the arm as a polyline)."""
        q = np.asarray(q, dtype=float)
        if q.shape[-1:] != (self.n,):
            raise ValueError(f"joint vectors must have shape (..., {self.n}), got {q.shape}")
        lead = q.shape[:-1]
        Q = q.reshape(-1, self.n)
        m = len(Q)
        T = self.chain.T
        pts = [np.broadcast_to(self._segments[0], (m,) + self._segments[0].shape)]
        M = np.broadcast_to(T[0], (m, 4, 4)).copy()
        for i in range(self.n):
            ax = self.chain.axis[i]
            X = np.broadcast_to(np.eye(4), (m, 4, 4)).copy()
            if self.chain.jtype[i] == 0:
                c, s = np.cos(Q[:, i]), np.sin(Q[:, i])
                K = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
                X[:, :3, :3] = (np.eye(3) + s[:, None, None] * K + (1 - c)[:, None, None] * (K @ K))
            else:
                X[:, :3, 3] = Q[:, i, None] * ax
            Mi = M @ X            # child frame of joint i
            local = self._segments[i + 1]
            if len(local):
                pts.append(np.einsum("mij,kj->mki", Mi[:, :3, :3], local) + Mi[:, None, :3, 3])
            M = Mi @ T[i + 1]
        pts.append(M[:, None, :3, 3])  # the wrist origin
        out = np.concatenate(pts, axis=1)
        return out.reshape(lead + out.shape[1:])

    # ------------------------------------------------------------------ limits
    def within_limits(self, q, tol: float = 1e-12) -> np.ndarray:
        """Mask of configurations inside the box and coupled limits (with slack ``tol``)."""
        q = np.asarray(q, dtype=float)
        v = q @ self.chain.A.T
        return np.all((v >= self.chain.lo - tol) & (v <= self.chain.hi + tol), axis=-1)

    def limit_margin(self, q) -> np.ndarray:
        """Smallest distance of ``q`` to any limit row (rad / m); negative outside the limits."""
        q = np.asarray(q, dtype=float)
        v = q @ self.chain.A.T
        return np.minimum(v - self.chain.lo, self.chain.hi - v).min(axis=-1)

    # ------------------------------------------------------------------ reachability and IK
    def kernel(self) -> tuple[ChainData, ReachMap]:
        """``(ChainData, ReachMap)`` for the compiled kernels (the map is built on first use)."""
        return self.chain, self.reach_map()

    def _cache_key(self) -> str:
        h = hashlib.sha256()
        h.update(MAP_VERSION.encode())
        for arr in self.chain:
            a = np.ascontiguousarray(arr)
            h.update(str(a.dtype).encode() + str(a.shape).encode())
            h.update(a.tobytes())
        h.update(repr(self.map_params).encode())
        return h.hexdigest()

    @staticmethod
    def _digest(arrays) -> str:
        h = hashlib.sha256()
        for a in arrays:
            a = np.ascontiguousarray(a)
            h.update(str(a.dtype).encode() + str(a.shape).encode())
            h.update(a.tobytes())
        return h.hexdigest()

    def reach_map(self) -> ReachMap:
        """The reachability map: from memory, from the disk cache, or built (and cached)."""
        if self._rmap is not None:
            return self._rmap
        key = self._cache_key()
        path = cache_dir() / f"reachmap-{key[:40]}.npz"
        t0 = time.perf_counter()
        rmap = self._read_cache(path, key)
        if rmap is not None:
            self.map_info.update(from_cache=True, seconds=time.perf_counter() - t0, cache_file=str(path))
        else:
            rmap = self._build_map()
            self.map_info.update(from_cache=False, seconds=time.perf_counter() - t0)
            self._write_cache(path, key, rmap)
        st = rmap.state
        self.map_info.update(h=rmap.h, shape=tuple(int(v) for v in rmap.shape), n_out=int((st == 0).sum()),
                             n_in=int((st == 1).sum()), n_boundary=int((st == 2).sum()),
                             n_seeds=int(len(rmap.seeds)))
        self._rmap = rmap
        return rmap

    def _read_cache(self, path: Path, key: str) -> ReachMap | None:
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["key"]) != key:
                    return None
                arrs = [np.array(z[f]) for f in ReachMap._fields]
                if str(z["digest"]) != self._digest(arrs):
                    return None
        except Exception:  # missing, truncated, not an npz, wrong fields: rebuild
            return None
        origin, h, shape, state, sub, seed_ptr, seeds = arrs
        shape = shape.astype(np.int64)
        if (origin.shape != (3,) or h.shape != () or sub.shape != () or shape.shape != (3,)
                or state.dtype != np.uint8 or state.shape != tuple(shape) or int(sub) < 1
                or np.any(shape % int(sub)) or seed_ptr.shape != (int(np.prod(shape // int(sub))) + 1,)
                or seeds.ndim != 2 or seeds.shape[1] != self.n or seed_ptr[-1] != len(seeds)
                or np.any(np.diff(seed_ptr) < 0) or seed_ptr[0] != 0 or not np.isfinite(h) or h <= 0):
            return None
        return ReachMap(origin.astype(float), float(h), shape, np.ascontiguousarray(state), int(sub),
                        seed_ptr.astype(np.int64), np.ascontiguousarray(seeds, dtype=float))

    def _write_cache(self, path: Path, key: str, rmap: ReachMap) -> None:
        arrs = {f: np.asarray(getattr(rmap, f)) for f in ReachMap._fields}
        digest = self._digest([arrs[f] for f in ReachMap._fields])
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".reachmap-", suffix=".npz", dir=path.parent)
            try:
                with os.fdopen(fd, "wb") as f:
                    np.savez(f, key=np.array(key), digest=np.array(digest), **arrs)
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, path)
            except BaseException:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
                raise
        except OSError:  # an unwritable cache only costs a rebuild next time
            pass

    def _lipschitz(self) -> tuple[float, np.ndarray]:
        """K (bound on ||J(q) - J(q')|| / |q - q'|) and per-joint bounds on |J_i|."""
        ch, n = self.chain, self.n
        t = np.linalg.norm(ch.T[:, :3, 3], axis=1)
        pr = np.where(ch.jtype == 1, np.maximum(np.abs(ch.lo[:n]), np.abs(ch.hi[:n])), 0.0)
        R = np.array([t[j + 1:].sum() + pr[j + 1:].sum() for j in range(n)])
        b = np.zeros((n, n))
        for i in range(n):
            for k in range(n):
                a, c = min(i, k), max(i, k)
                if ch.jtype[a] == 0 and ch.jtype[c] == 0:
                    b[i, k] = R[c]
                elif ch.jtype[a] == 0 and ch.jtype[c] == 1:
                    b[i, k] = 1.0
        L = np.where(ch.jtype == 0, R, 1.0)
        return float(np.sqrt((b * b).sum())), L

    def _faces(self, wrap) -> np.ndarray:
        """The faces of Q as planar patches (f, 13): point c, tangents t1, t2 (joint space) and the
        ranges [u0, u1, v0, v1] of q = c + u t1 + v t2 that cover the face."""
        ch, n = self.chain, self.n
        out = []
        for r in range(ch.A.shape[0]):
            row = ch.A[r]
            if r < n and wrap[r]:
                continue
            d = int(np.argmax(np.abs(row)))
            a, b = [i for i in range(n) if i != d]
            for bound in (ch.lo[r], ch.hi[r]):
                c = np.zeros(n)
                c[d] = bound / row[d]
                t1 = np.zeros(n)
                t1[a], t1[d] = 1.0, -row[a] / row[d]
                t2 = np.zeros(n)
                t2[b], t2[d] = 1.0, -row[b] / row[d]
                out.append(np.concatenate([c, t1, t2, [ch.lo[a], ch.hi[a], ch.lo[b], ch.hi[b]]]))
        return np.array(out, float).reshape(-1, 13)

    def _det_bound(self) -> np.ndarray:
        """M (n, n): |d2 det J / dq_k dq_l| <= M[k, l] everywhere.

        Bounds for a serial chain: |J_j| <= L_j; |dJ_j/dq_k| <= b[j, k]; |d2 J_j/dq_k dq_l| <=
        R_max(j,k,l) (all revolute) or 1 (a prismatic joint involved): every derivative of a
        revolute chain rotates a vector about a unit axis, a prismatic one swaps a lever arm for
        a unit axis.
        """
        ch, n = self.chain, self.n
        t = np.linalg.norm(ch.T[:, :3, 3], axis=1)
        pr = np.where(ch.jtype == 1, np.maximum(np.abs(ch.lo[:n]), np.abs(ch.hi[:n])), 0.0)
        R = np.array([t[j + 1:].sum() + pr[j + 1:].sum() for j in range(n)])
        rev = ch.jtype == 0
        L = np.where(rev, R, 1.0)
        b = np.where(rev[:, None] & rev[None, :], R[np.maximum.outer(np.arange(n), np.arange(n))], 1.0)
        M = np.zeros((n, n))
        for k in range(n):
            for kk in range(n):
                tot = 0.0
                for j in range(n):
                    others = [m for m in range(n) if m != j]
                    # both derivatives on column j, or one on column j and one on column m
                    b3 = R[max(j, k, kk)] if (rev[j] and rev[k] and rev[kk]) else 1.0
                    tot += b3 * np.prod(L[others])
                    for m in others:
                        third = [x for x in range(n) if x not in (j, m)][0]
                        tot += b[j, k] * b[m, kk] * L[third]
                M[k, kk] = tot
        return M

    def _build_map(self) -> ReachMap:
        p = self.map_params
        ch = self.chain
        K, _ = self._lipschitz()
        jlo, jhi = self.limits[:, 0].copy(), self.limits[:, 1].copy()
        wrap = np.array([ch.jtype[i] == 0 and jhi[i] - jlo[i] >= TWO_PI - 1e-9 for i in range(self.n)])
        # a first look at the workspace: extent (-> voxel size) and per-joint wrist speed
        g = [np.linspace(lo, hi, 13) for lo, hi in self.limits]
        Qs = np.stack(np.meshgrid(*g, indexing="ij"), axis=-1).reshape(-1, 3)
        Qs = Qs[self.within_limits(Qs)]
        Ws = self.forward(Qs)
        H = float(np.ptp(Ws, axis=0).max()) / p.voxels
        h = H / p.sub
        speed = np.linalg.norm(self.jacobian(Qs), axis=1).max(axis=0) * 1.05 + 1e-9
        ncell = np.maximum(1, np.ceil((jhi - jlo) * speed / (p.coarse * H))).astype(np.int64)
        djoint = (jhi - jlo) / ncell
        bmin, bmax, _ = _coarse_bbox(ch, K, jlo, djoint, ncell)
        cshape = np.ceil((bmax - bmin) / H).astype(np.int64) + 2
        origin = 0.5 * (bmin + bmax) - 0.5 * H * cshape      # >= half a seed cell of margin
        shape = cshape * p.sub
        state, seed_ptr, seeds, stats = _build_map(ch, K, self._det_bound(), jlo, djoint, ncell,
                                                   self._faces(wrap), origin, h, shape, p.sub,
                                                   p.beta, p.max_depth, p.seeds, p.tau)
        self.map_info.update(K=K, coarse_cells=int(np.prod(ncell)), leaves=int(stats[0]),
                             singular_leaves=int(stats[1]), face_patches=int(stats[4]), conflicts=int(stats[2]), seedless=int(stats[3]))
        return ReachMap(origin, h, shape, state, int(p.sub), seed_ptr, seeds)

    def _points(self, w) -> tuple[np.ndarray, tuple]:
        w = np.asarray(w, dtype=float)
        if w.shape[-1:] != (3,):
            raise ValueError(f"points must have shape (..., 3), got {w.shape}")
        return np.ascontiguousarray(w.reshape(-1, 3)), w.shape[:-1]

    def reachable(self, w) -> np.ndarray:
        """Mask (...) of wrists ``w`` (..., 3) reachable within all limits (the map, exact IK at its
        boundary; see the module docstring)."""
        W, lead = self._points(w)
        chain, rmap = self.kernel()
        out = np.empty(len(W), np.bool_)
        _reach_many(chain, rmap, W, out)
        return out.reshape(lead)

    def inverse(self, w, near=None) -> tuple[np.ndarray, np.ndarray]:
        """Joint values putting the wrist at ``w`` (..., 3) within all limits, any branch.

        ``near`` (..., n), optional: a configuration tried first as the starting point (keeps a
        trajectory on its branch). Returns ``(q, ok)``: ``q`` (..., n), NaN where unreachable.
        """
        W, lead = self._points(w)
        chain, rmap = self.kernel()
        Q = np.empty((len(W), self.n))
        ok = np.empty(len(W), np.bool_)
        if near is None:
            _ik_many(chain, rmap, W, np.empty((len(W), self.n)), False, Q, ok)
        else:
            N = np.ascontiguousarray(np.broadcast_to(np.asarray(near, float), lead + (self.n,)).reshape(-1, self.n))
            _ik_many(chain, rmap, W, N, True, Q, ok)
        return Q.reshape(lead + (self.n,)), ok.reshape(lead)

    # ------------------------------------------------------------------ sampling
    def sample_wrists(self, n_per_joint: int = 41) -> np.ndarray:
        """Wrist positions (m, 3) over an ``n_per_joint``^n grid of the joint box, inside all limits."""
        g = [np.linspace(lo, hi, n_per_joint) for lo, hi in self.limits]
        Q = np.stack(np.meshgrid(*g, indexing="ij"), axis=-1).reshape(-1, self.n)
        return self.forward(Q[self.within_limits(Q)])

    def min_distance_to(self, p, n_per_joint: int = 41) -> float:
        """Distance from point ``p`` to the workspace: 0 if reachable, else to the nearest sampled wrist."""
        p = np.asarray(p, dtype=float)
        if bool(self.reachable(p)):
            return 0.0
        w = self.sample_wrists(n_per_joint)
        if len(w) == 0:
            return float("inf")
        return float(np.min(np.linalg.norm(w - p, axis=-1)))

    # ------------------------------------------------------------------ gravity
    def _gravity_model(self):
        if self._gravity is None:
            import pinocchio as pin
            model = pin.Model(self.model)
            g_world = np.array([0.0, -GRAVITY, 0.0])
            model.gravity.linear = _rpy_matrix(self.base_rpy).T @ g_world
            data = model.createData()
            pin.computeSubtreeMasses(model, data)
            for name, jid in zip(self.joint_names, self._act_ids):
                if not data.mass[jid] > 0.0:
                    raise ErrplanError(f"URDF {self.urdf_path}: the links moved by joint '{name}' carry no inertial "
                                       "data (mass 0), so it has no gravity torque; add <inertial> to those links")
            self._gravity = (model, data)
        return self._gravity

    def gravity_torque(self, q) -> np.ndarray:
        """Generalized gravity (..., n) at the actuated joints (N m or N): ``dV/dq`` with world
        gravity 9.81 m/s^2 along -y; held joints at their values, joints off the chain at zero."""
        import pinocchio as pin
        model, data = self._gravity_model()
        Q, lead = self._as_q(q)
        out = np.empty((len(Q), self.n))
        qp = self._qref.copy()
        vidx = [model.joints[j].idx_v for j in self._act_ids]
        for k, qk in enumerate(Q):
            for jid, val in zip(self._act_ids, qk):
                jm = model.joints[jid]
                if jm.nq == 1:
                    qp[jm.idx_q] = val
                else:
                    qp[jm.idx_q], qp[jm.idx_q + 1] = math.cos(val), math.sin(val)
            tau = pin.computeGeneralizedGravity(model, data, qp)
            out[k] = np.asarray(tau)[vidx]
        return out.reshape(lead + (self.n,))

    def pinocchio_configuration(self, q) -> np.ndarray:
        """Pinocchio configuration vector of the whole model for actuated values ``q`` (n,)."""
        qp = self._qref.copy()
        for jid, val in zip(self._act_ids, np.asarray(q, float)):
            jm = self.model.joints[jid]
            if jm.nq == 1:
                qp[jm.idx_q] = val
            else:
                qp[jm.idx_q], qp[jm.idx_q + 1] = math.cos(val), math.sin(val)
        return qp

    # ------------------------------------------------------------------ meshes
    def resolve_uri(self, uri: str) -> Path | None:
        """File for a URDF mesh URI, or None. ``package://NAME/rest`` is looked up in ``package_path``,
        ``$ROS_PACKAGE_PATH`` and the environment's description packages (:mod:`errplan.packages`;
        relative folders against the URDF's); ``file://`` and plain paths are relative to the URDF's folder."""
        if uri.startswith(packages.SCHEME):
            return packages.resolve(uri, packages.search_dirs(self.package_path, self.urdf_path.parent))
        if uri.startswith("file://"):
            uri = uri[len("file://"):]
        if "://" in uri:
            return None
        cand = Path(uri)
        if not cand.is_absolute():
            cand = self.urdf_path.parent / cand
        return cand if cand.is_file() else None


# ============================================================================ the PHANToM 1.5
PHANTOM_SHOULDER = (0.210, -0.210)      # P1's planar base [y, z], m
PHANTOM_LINKS = (0.210, 0.210)          # l1, l2, m
PHANTOM_HOME = (0.0, -math.pi / 2)      # h1, h2, rad
PHANTOM_LIMITS = {"waist": (-1.0, 1.0), "shoulder": (-1.9, 1.2), "elbow": (-0.7, 1.0)}
PHANTOM_SUM_LIMITS = (-0.3, 2.8)        # shoulder + elbow (a coupled limit in the scenario)
ALUMINIUM_DENSITY = 2700.0              # kg/m^3
ROD_RADIUS = 0.005                      # m: the links are modelled as solid aluminium rods


def phantom_urdf() -> str:
    """URDF text of P1's PHANToM 1.5 in 3-D (scenarios/phantom15.urdf is this text).

    The root link ``base`` is placed at the shoulder (scenario base_position = [0, 0.210, -0.210],
    base_rpy = 0). ``waist`` turns about the vertical +y axis; ``shoulder`` and ``elbow`` turn
    about -x, so increasing angles rotate +z toward +y as in P1's plane. Link 1 lies along +z of
    ``upper_arm``; the elbow origin carries the home angle h2 as a roll of -h2 about x, and link 2
    lies along +z of ``lower_arm``. With waist = 0 the wrist is [0, planar y, planar z].
    """
    l1, l2 = PHANTOM_LINKS
    h1, h2 = PHANTOM_HOME
    if h1 != 0.0:
        raise AssertionError("the URDF puts link 1 along +z at q1 = 0 (h1 = 0)")
    rho, r = ALUMINIUM_DENSITY, ROD_RADIUS

    def f(x: float) -> str:       # kinematic numbers: exact
        return repr(float(x))

    def g(x: float) -> str:       # inertial data and decoration: 12 significant digits
        return repr(float(format(float(x), ".12g")))

    def rod(length: float) -> str:
        # a solid aluminium rod of radius r along the link frame's +z, from 0 to length
        m = rho * math.pi * r * r * length
        ixx = m * (3 * r * r + length * length) / 12.0
        izz = m * r * r / 2.0
        return (f'    <inertial>\n'
                f'      <!-- solid aluminium rod, radius {g(r)} m, length {f(length)} m -->\n'
                f'      <origin xyz="0 0 {g(length / 2)}" rpy="0 0 0"/>\n'
                f'      <mass value="{g(m)}"/>\n'
                f'      <inertia ixx="{g(ixx)}" ixy="0" ixz="0" iyy="{g(ixx)}" iyz="0" izz="{g(izz)}"/>\n'
                f'    </inertial>\n'
                f'    <visual>\n'
                f'      <origin xyz="0 0 {g(length / 2)}" rpy="0 0 0"/>\n'
                f'      <geometry><cylinder radius="{g(r)}" length="{f(length)}"/></geometry>\n'
                f'      <material name="aluminium"/>\n'
                f'    </visual>\n')

    def limit(name: str) -> str:
        lo, hi = PHANTOM_LIMITS[name]
        return f'    <limit lower="{f(lo)}" upper="{f(hi)}" effort="10.0" velocity="10.0"/>\n'

    # torso: a vertical aluminium post (radius 2 r, 0.1 m) below the shoulder; base: a disc
    post_len, post_r = 0.1, 2 * r
    m_post = rho * math.pi * post_r ** 2 * post_len
    i_post = m_post * (3 * post_r ** 2 + post_len ** 2) / 12.0
    disc_r, disc_t = 0.06, 0.01
    m_disc = rho * math.pi * disc_r ** 2 * disc_t
    # wrist: the gimbal, an aluminium sphere of radius 2 r centred on the pivot
    gim_r = 2 * r
    m_gim = rho * 4.0 / 3.0 * math.pi * gim_r ** 3
    i_gim = 0.4 * m_gim * gim_r ** 2
    half_pi = f(math.pi / 2)
    return (
        '<?xml version="1.0" encoding="utf-8"?>\n'
        '<!-- P1\'s PHANToM 1.5 in 3-D, generated by errplan.kinematics.urdf.phantom_urdf(); do not edit.\n'
        f'     Shoulder at the root (place the root at [0, {f(PHANTOM_SHOULDER[0])}, {f(PHANTOM_SHOULDER[1])}]),\n'
        f'     l1 = {f(l1)} m, l2 = {f(l2)} m, home angles [{f(h1)}, {f(h2)}]; waist about +y (vertical),\n'
        '     shoulder and elbow about -x. Inertial data: links as solid aluminium rods\n'
        f'     ({g(rho)} kg/m^3, radius {g(r)} m), a vertical post for the torso, a disc for the base and\n'
        '     a sphere for the gimbal at the wrist pivot; visuals are cylinders (no mesh files). -->\n'
        '<robot name="phantom15">\n'
        '  <material name="aluminium"><color rgba="0.75 0.75 0.78 1.0"/></material>\n'
        '  <material name="dark"><color rgba="0.2 0.2 0.22 1.0"/></material>\n'
        '  <link name="base">\n'
        '    <inertial>\n'
        f'      <!-- aluminium disc, radius {g(disc_r)} m, thickness {g(disc_t)} m -->\n'
        f'      <origin xyz="0 {g(-post_len - disc_t / 2)} 0" rpy="0 0 0"/>\n'
        f'      <mass value="{g(m_disc)}"/>\n'
        f'      <inertia ixx="{g(m_disc * (3 * disc_r ** 2 + disc_t ** 2) / 12)}" ixy="0" ixz="0" '
        f'iyy="{g(m_disc * disc_r ** 2 / 2)}" iyz="0" izz="{g(m_disc * (3 * disc_r ** 2 + disc_t ** 2) / 12)}"/>\n'
        '    </inertial>\n'
        '    <visual>\n'
        f'      <origin xyz="0 {g(-post_len - disc_t / 2)} 0" rpy="{half_pi} 0 0"/>\n'
        f'      <geometry><cylinder radius="{g(disc_r)}" length="{g(disc_t)}"/></geometry>\n'
        '      <material name="dark"/>\n'
        '    </visual>\n'
        '  </link>\n'
        '  <link name="torso">\n'
        '    <inertial>\n'
        f'      <!-- vertical aluminium post, radius {g(post_r)} m, length {g(post_len)} m -->\n'
        f'      <origin xyz="0 {g(-post_len / 2)} 0" rpy="0 0 0"/>\n'
        f'      <mass value="{g(m_post)}"/>\n'
        f'      <inertia ixx="{g(i_post)}" ixy="0" ixz="0" iyy="{g(m_post * post_r ** 2 / 2)}" iyz="0" izz="{g(i_post)}"/>\n'
        '    </inertial>\n'
        '    <visual>\n'
        f'      <origin xyz="0 {g(-post_len / 2)} 0" rpy="{half_pi} 0 0"/>\n'
        f'      <geometry><cylinder radius="{g(post_r)}" length="{g(post_len)}"/></geometry>\n'
        '      <material name="dark"/>\n'
        '    </visual>\n'
        '  </link>\n'
        '  <link name="upper_arm">\n' + rod(l1) + '  </link>\n'
        '  <link name="lower_arm">\n' + rod(l2) + '  </link>\n'
        '  <link name="wrist">\n'
        '    <inertial>\n'
        f'      <!-- the gimbal: aluminium sphere, radius {g(gim_r)} m, centred on the pivot -->\n'
        '      <origin xyz="0 0 0" rpy="0 0 0"/>\n'
        f'      <mass value="{g(m_gim)}"/>\n'
        f'      <inertia ixx="{g(i_gim)}" ixy="0" ixz="0" iyy="{g(i_gim)}" iyz="0" izz="{g(i_gim)}"/>\n'
        '    </inertial>\n'
        '    <visual>\n'
        '      <origin xyz="0 0 0" rpy="0 0 0"/>\n'
        f'      <geometry><sphere radius="{g(gim_r)}"/></geometry>\n'
        '      <material name="dark"/>\n'
        '    </visual>\n'
        '  </link>\n'
        '  <joint name="waist" type="revolute">\n'
        '    <parent link="base"/>\n'
        '    <child link="torso"/>\n'
        '    <origin xyz="0 0 0" rpy="0 0 0"/>\n'
        '    <axis xyz="0 1 0"/>\n' + limit("waist") +
        '  </joint>\n'
        '  <joint name="shoulder" type="revolute">\n'
        '    <parent link="torso"/>\n'
        '    <child link="upper_arm"/>\n'
        '    <origin xyz="0 0 0" rpy="0 0 0"/>\n'
        '    <axis xyz="-1 0 0"/>\n' + limit("shoulder") +
        '  </joint>\n'
        '  <joint name="elbow" type="revolute">\n'
        '    <parent link="upper_arm"/>\n'
        '    <child link="lower_arm"/>\n'
        f'    <origin xyz="0 0 {f(l1)}" rpy="{f(-h2)} 0 0"/>\n'
        '    <axis xyz="-1 0 0"/>\n' + limit("elbow") +
        '  </joint>\n'
        '  <joint name="wrist_pivot" type="fixed">\n'
        '    <parent link="lower_arm"/>\n'
        '    <child link="wrist"/>\n'
        f'    <origin xyz="0 0 {f(l2)}" rpy="0 0 0"/>\n'
        '  </joint>\n'
        '</robot>\n'
    )
