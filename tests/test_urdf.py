"""URDF arms (errplan.kinematics.urdf, docs/physics.md "Spatial robots (3-D)").

Forward kinematics and Jacobians are checked against pinocchio, central finite differences and a
hand-written chain of explicit rotation matrices; the PHANToM against P1's planar arm;
reachability against brute-force IK (many seeds) and closed-form IK of the Omni and the PHANToM;
gravity against finite differences of the potential energy (pinocchio's and a hand-written one).
The Omni is read where ERRPLAN_TEST_OMNI_URDF names it (tests/arms.py), never copied into the repository.
"""
from __future__ import annotations

import math
import re
import os
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from numba import njit
from scipy.spatial import cKDTree

from errplan.errors import ErrplanError
from errplan.kinematics import urdf as U
from errplan.kinematics.arm import Arm
from errplan.kinematics.urdf import CoupledLimit, UrdfArm, phantom_urdf

from arms import ARMS, OMNI, SHARED_ROBOTS as ROBOTS, arm_scenario, needs_omni
from errplan import packages

REPO = Path(__file__).resolve().parents[1]
PHANTOM = REPO / "scenarios" / "phantom15.urdf"
JOINTS = ["waist", "shoulder", "elbow"]
OMNI_RPY = (math.pi / 2, 0.0, math.pi)
PHANTOM_BASE = (0.0, 0.210, -0.210)
SUM = CoupledLimit(("shoulder", "elbow"), (1.0, 1.0), -0.3, 2.8)
PLANAR = Arm(base=(0.21, -0.21), l1=0.21, l2=0.21, home=(0.0, -math.pi / 2), q1_limits=(-1.9, 1.2),
             q2_limits=(-0.7, 1.0), sum_limits=(-0.3, 2.8))


#: ERRPLAN_CACHE_DIR as it was before this file's fresh cache directory (None: unset, the default one)
_OUTER_CACHE: list = [None]


@pytest.fixture(scope="module", autouse=True)
def cache_dir(tmp_path_factory):
    """Reachability maps go to a fresh cache directory, never the user's (but see :func:`shared_map`)."""
    old = os.environ.get("ERRPLAN_CACHE_DIR")
    _OUTER_CACHE[0] = old
    path = tmp_path_factory.mktemp("errplan-cache")
    os.environ["ERRPLAN_CACHE_DIR"] = str(path)
    yield path
    if old is None:
        os.environ.pop("ERRPLAN_CACHE_DIR", None)
    else:
        os.environ["ERRPLAN_CACHE_DIR"] = old


def load_omni(**kw):
    if not OMNI.is_file():
        pytest.skip(needs_omni.kwargs["reason"])
    return UrdfArm.load(OMNI, JOINTS, "tip", base_rpy=OMNI_RPY, **kw)


def erd_path(which: str) -> Path:
    """The installed example-robot-data URDF of tests/arms.py's arm ``which``."""
    path = packages.resolve_package_uri(ARMS[which]["urdf"])
    assert path is not None, f"{ARMS[which]['urdf']}: example-robot-data is a test dependency"
    return path


def load_erd(which: str, **kw):
    a = ARMS[which]
    return UrdfArm.load(erd_path(which), a["joints"], a["wrist"], base_rpy=a["base_rpy"],
                        fixed_joints=a["fixed_joints"], **kw)


def load_phantom(**kw):
    return UrdfArm.load(PHANTOM, JOINTS, "wrist", base_position=PHANTOM_BASE, coupled_limits=[SUM], **kw)


@pytest.fixture(scope="module")
def omni():
    return load_omni()


@pytest.fixture(scope="module")
def phantom():
    return load_phantom()


def shared_map(arm):
    """``arm`` with its reachability map read from (or built into) the cache the other test files use,
    not this file's fresh one: the UR5's and the Panda's maps (30 s and 8 s of CPU to build) are then
    built once per machine, not once more per run of this file. Only the Omni's and the PHANToM's maps,
    whose build statistics (``conflicts``) and cache behaviour this file checks, are built fresh here."""
    fresh = os.environ.get("ERRPLAN_CACHE_DIR")
    if _OUTER_CACHE[0] is None:
        os.environ.pop("ERRPLAN_CACHE_DIR", None)
    else:
        os.environ["ERRPLAN_CACHE_DIR"] = _OUTER_CACHE[0]
    try:
        arm.reach_map()
    finally:
        os.environ["ERRPLAN_CACHE_DIR"] = fresh
    return arm


def use_shared_cache(monkeypatch):
    """For one test: maps from the cache :func:`shared_map` uses."""
    if _OUTER_CACHE[0] is None:
        monkeypatch.delenv("ERRPLAN_CACHE_DIR", raising=False)
    else:
        monkeypatch.setenv("ERRPLAN_CACHE_DIR", _OUTER_CACHE[0])


@pytest.fixture(scope="module")
def ur5():
    return shared_map(load_erd("ur5"))


@pytest.fixture(scope="module")
def panda():
    return shared_map(load_erd("panda"))


def random_q(arm, n, seed, feasible=True):
    rng = np.random.default_rng(seed)
    lo, hi = arm.limits[:, 0], arm.limits[:, 1]
    q = lo + rng.random((4 * n if feasible else n, arm.n)) * (hi - lo)
    if feasible:
        q = q[arm.within_limits(q)][:n]
        assert len(q) == n
    return q


def fd_jacobian(f, q, h=1e-6):
    cols = []
    for i in range(q.shape[-1]):
        e = np.zeros(q.shape[-1])
        e[i] = h
        cols.append((f(q + e) - f(q - e)) / (2 * h))
    return np.stack(cols, axis=-1)


# ============================================================================ references
def rpy(r, p, y):
    """URDF rpy: Rz(y) Ry(p) Rx(r), written out."""
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return (np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
            @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]]))


def rot(axis, a):
    """Rotation by angle a about a unit axis (Rodrigues)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def tf(R=np.eye(3), p=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def pin_world(arm_path, frame, base_position, base_rpy, q, joints=None, held=None):
    """Wrist position and world Jacobian columns from pinocchio: the actuated ``joints`` (default: the
    first 3 of q) at ``q``, the ``held`` joints at their values, every other joint at pinocchio's neutral."""
    model = pin.buildModelFromUrdf(str(arm_path))
    data = model.createData()
    fid = model.getFrameId(frame)
    R = rpy(*base_rpy)
    if joints is None:
        iq = iv = [0, 1, 2]
    else:
        js = [model.joints[model.getJointId(n)] for n in joints]
        iq, iv = [j.idx_q for j in js], [j.idx_v for j in js]
    W, J = [], []
    for qk in q:
        qq = pin.neutral(model)
        for name, v in (held or {}).items():
            qq[model.joints[model.getJointId(name)].idx_q] = v
        qq[iq] = qk
        pin.forwardKinematics(model, data, qq)
        pin.updateFramePlacements(model, data)
        pin.computeJointJacobians(model, data, qq)
        W.append(np.asarray(base_position) + R @ data.oMf[fid].translation)
        Jf = pin.getFrameJacobian(model, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        J.append(R @ np.asarray(Jf)[:3, iv])
    return np.array(W), np.array(J)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def omni_exact(W):
    """Closed-form reachability of the Omni, from its URDF numbers: waist about the root z axis at
    height 0.09; in the torso plane x = 0 a two-link arm from the shoulder at (y, z) = (0, 0.035)
    (link 1 0.134 m at angle 0.23 + q1 from the torso y axis, link 2 0.08 + 0.0525 m at a further
    -2.15 + q2); wrist1 turns about the link-2 axis, so the tip does not move with it."""
    p = W @ rpy(*OMNI_RPY)      # root frame: R^T w
    px, py, pz = p[:, 0], p[:, 1], p[:, 2]
    l1, l2 = 0.134, 0.1325
    lim = np.array([[-0.98, 0.98], [-0.24, 1.57], [-0.2, 1.95]])
    rho = np.hypot(px, py)
    out = np.zeros(len(W), bool)
    for sg in (1.0, -1.0):
        q0 = np.where(rho == 0, 0.0, np.arctan2(-sg * px, sg * py))
        dy, dz = sg * rho, pz - 0.09 - 0.035
        c = (dy * dy + dz * dz - l1 * l1 - l2 * l2) / (2 * l1 * l2)
        for br in (1.0, -1.0):
            a2 = br * np.arccos(np.clip(c, -1, 1))
            a1 = np.arctan2(dz, dy) - np.arctan2(l2 * np.sin(a2), l1 + l2 * np.cos(a2))
            q = np.stack([q0, _wrap(a1 - 0.23), _wrap(a2 + 2.15)], -1)
            out |= (np.abs(c) <= 1) & np.all((q >= lim[:, 0]) & (q <= lim[:, 1]), -1)
    return out


def phantom_exact(W):
    """Closed-form reachability of the PHANToM: the waist turns P1's planar arm about the vertical
    axis through the shoulder; a wrist is reachable if, for a waist angle within its limits, the
    point in the turned plane is reachable by the planar Arm."""
    d = W - np.array(PHANTOM_BASE)
    rho = np.hypot(d[:, 0], d[:, 2])
    out = np.zeros(len(W), bool)
    for sg in (1.0, -1.0):
        psi = np.where(rho == 0, 0.0, np.arctan2(sg * d[:, 0], sg * d[:, 2]))
        planar = np.stack([PHANTOM_BASE[1] + d[:, 1], PHANTOM_BASE[2] + sg * rho], -1)
        out |= (psi >= -1.0) & (psi <= 1.0) & PLANAR.reachable(planar)
    return out


def brute_reachable(arm, W, per_joint=28, k=40, n_random=16, iters=60, seed=0):
    """Brute-force IK: projected Levenberg-Marquardt (numpy) from the k configurations of a
    joint grid whose wrists are nearest to w plus n_random random configurations; reachable when
    a run ends with |f(q) - w| < 1e-9 within all limits."""
    lo, hi = arm.limits[:, 0], arm.limits[:, 1]
    g = [np.linspace(a, b, per_joint) for a, b in arm.limits]
    G = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)
    _, idx = cKDTree(arm.forward(G)).query(W, k=k)
    rng = np.random.default_rng(seed)
    seeds = np.concatenate([G[idx], lo + rng.random((len(W), n_random, 3)) * (hi - lo)], axis=1)
    m = seeds.shape[1]
    Q = seeds.reshape(-1, 3).copy()
    T = np.repeat(W, m, axis=0)
    lam = np.full(len(Q), 1e-9)
    e = np.sum((T - arm.forward(Q)) ** 2, -1)
    active = np.ones(len(Q), bool)
    slow = np.zeros(len(Q), int)
    for _ in range(iters):
        a = np.flatnonzero(active)
        if len(a) == 0:
            break
        q, t = Q[a], T[a]
        r = t - arm.forward(q)
        J = arm.jacobian(q)
        A = np.einsum("kji,kjl->kil", J, J)
        A = A + (lam[a] * np.trace(A, axis1=1, axis2=2))[:, None, None] * np.eye(3)
        dq = np.linalg.solve(A, np.einsum("kji,kj->ki", J, r)[..., None])[..., 0]
        qn = np.clip(q + dq, lo, hi)
        en = np.sum((t - arm.forward(qn)) ** 2, -1)
        acc = en < e[a]
        slow[a] = np.where(en < 0.99 * e[a], 0, slow[a] + 1)     # a rejected or tiny step is slow
        Q[a[acc]] = qn[acc]
        e[a[acc]] = en[acc]
        lam[a] = np.where(acc, np.maximum(lam[a] * 0.1, 1e-12), lam[a] * 10)
        active[a] = (e[a] > 1e-26) & (slow[a] < 6)
        # a point reached by one seed needs no other
        hit = np.zeros(len(W), bool)
        reached = a[e[a] < 1e-18]
        hit[reached[arm.within_limits(Q[reached])] // m] = True
        active &= ~np.repeat(hit, m)
    ok = (np.sqrt(e) < 1e-9) & arm.within_limits(Q)
    return ok.reshape(len(W), m).any(-1)


def map_state(arm, W):
    _, rm = arm.kernel()
    f = np.floor((W - rm.origin) / rm.h).astype(np.int64)
    inside = np.all((f >= 0) & (f < rm.shape), axis=1)
    st = np.zeros(len(W), np.int64)
    st[inside] = rm.state[f[inside, 0], f[inside, 1], f[inside, 2]]
    return st


def near_boundary(exact, W, h):
    """Points whose exact reachability changes within one voxel edge along some axis."""
    base = exact(W)
    out = np.zeros(len(W), bool)
    for d in range(3):
        for s in (-h, h):
            Wd = W.copy()
            Wd[:, d] += s
            out |= exact(Wd) != base
    return out


def workspace_box(arm, margin=0.02):
    S = arm.sample_wrists(25)
    return S.min(0) - margin, S.max(0) + margin


# ============================================================================ the bundled PHANToM
def test_phantom_urdf_file_is_generated():
    assert PHANTOM.read_text(encoding="utf-8") == phantom_urdf()


def test_phantom_matches_planar_arm(phantom):
    rng = np.random.default_rng(1)
    q12 = np.stack([rng.uniform(-2.5, 2.0, 500), rng.uniform(-1.5, 2.0, 500)], -1)
    q = np.concatenate([np.zeros((500, 1)), q12], -1)
    w = phantom.forward(q)
    assert np.allclose(w[:, 0], 0.0, atol=1e-15)
    assert np.allclose(w[:, 1:], PLANAR.forward(q12), rtol=0, atol=1e-15)
    J = phantom.jacobian(q)
    assert np.allclose(J[:, 1:, 1:], PLANAR.jacobian(q12), rtol=0, atol=1e-15)
    assert np.allclose(J[:, 0, 1:], 0.0, atol=1e-15)
    assert np.array_equal(phantom.within_limits(q), PLANAR.within_limits(q12))
    assert np.allclose(phantom.limit_margin(q), np.minimum(PLANAR.limit_margin(q12), 1.0))  # waist 0: 1 rad
    assert np.allclose(phantom.forward([0.0, 0.0, 0.0]), [0.0, 0.0, 0.0], atol=1e-15)  # P1's home
    # the waist turns the plane about the vertical axis through the shoulder
    w1 = phantom.forward(np.concatenate([np.full((500, 1), 0.7), q12], -1))
    d0, d1 = w - PHANTOM_BASE, w1 - PHANTOM_BASE
    assert np.allclose(d1[:, 1], d0[:, 1])
    assert np.allclose(d1[:, [2, 0]], d0[:, [2, 2]] * [math.cos(0.7), math.sin(0.7)], atol=1e-15)
    assert phantom.limits.tolist() == [[-1.0, 1.0], [-1.9, 1.2], [-0.7, 1.0]]


def test_phantom_reachable_at_x0_equals_planar(phantom):
    y, z = np.meshgrid(np.linspace(-0.45, 0.65, 221), np.linspace(-0.65, 0.45, 221), indexing="ij")
    planar = np.stack([y, z], -1).reshape(-1, 2)
    W = np.concatenate([np.zeros((len(planar), 1)), planar], -1)
    got = phantom.reachable(W)
    want = PLANAR.reachable(planar)
    assert want.sum() > 4000
    assert np.array_equal(got, want)


def test_phantom_gravity_torque(phantom):
    model = pin.buildModelFromUrdf(str(PHANTOM))
    data = model.createData()
    model.gravity.linear = np.array([0.0, -9.81, 0.0])   # base_rpy = 0: root frame = world frame
    q = random_q(phantom, 40, 3)
    tau = phantom.gravity_torque(q)
    assert np.all(tau[:, 0] == 0.0)                      # waist: vertical axis
    h = 1e-6
    for qk, tk in zip(q, tau):
        fd = [(pin.computePotentialEnergy(model, data, qk + h * e) - pin.computePotentialEnergy(model, data, qk - h * e))
              / (2 * h) for e in np.eye(3)]
        assert np.allclose(tk, fd, rtol=0, atol=1e-8)
    assert np.all(phantom.gravity_torque([0.0, 0.5, 0.3])[1:] != 0.0)
    # at home the upper arm is horizontal (along +z) and the lower arm hangs: elbow torque 0,
    # shoulder torque = (m1 l1 / 2 + (m2 + m_gimbal) l1) g > 0 (raising the arm raises V)
    m_rod = U.ALUMINIUM_DENSITY * math.pi * U.ROD_RADIUS ** 2 * 0.21
    m_gim = U.ALUMINIUM_DENSITY * 4 / 3 * math.pi * (2 * U.ROD_RADIUS) ** 3
    t0 = phantom.gravity_torque([0.0, 0.0, 0.0])
    assert t0[2] == pytest.approx(0.0, abs=1e-15)
    assert t0[1] == pytest.approx((m_rod * 0.105 + (m_rod + m_gim) * 0.21) * 9.81, rel=1e-9)


# ============================================================================ FK and Jacobian
@pytest.mark.parametrize("which", ["omni", "phantom", "ur5", "panda"])
def test_kernel_fk_and_jacobian_vs_pinocchio_and_fd(which, request):
    """errplan's compiled chain against pinocchio on the same file and against central differences: the
    Omni as it is, the PHANToM errplan writes, and two real arms of example-robot-data (the UR5; the Panda
    with joint 3 held, so the actuated joints are not the first three)."""
    arm = request.getfixturevalue(which)
    if which in ARMS:
        path, frame, joints, held = erd_path(which), ARMS[which]["wrist"], ARMS[which]["joints"], ARMS[which]["fixed_joints"]
    else:
        path, frame = (OMNI, "tip") if which == "omni" else (PHANTOM, "wrist")
        joints, held = None, None
    q = random_q(arm, 200, 2, feasible=False)
    W, J = pin_world(path, frame, arm.base_position, arm.base_rpy, q, joints, held)
    assert np.allclose(arm.forward(q), W, rtol=0, atol=1e-14)
    assert np.allclose(arm.jacobian(q), J, rtol=0, atol=1e-14)
    assert np.allclose(arm.jacobian(q), fd_jacobian(arm.forward, q), rtol=0, atol=1e-9)
    # the single-point kernels called from compiled code
    out, outJ = np.empty(3), np.empty((3, 3))
    chain = arm.chain
    U.fk_point(chain, q[5], out)
    U.jac_point(chain, q[5], outJ)
    assert np.allclose(out, W[5], atol=1e-14) and np.allclose(outJ, J[5], atol=1e-14)
    # batch shapes
    assert arm.forward(q.reshape(10, 20, 3)).shape == (10, 20, 3)
    assert arm.jacobian(q.reshape(10, 20, 3)).shape == (10, 20, 3, 3)


def test_omni_frame_and_chain_points(omni):
    assert omni.joint_names == ("waist", "shoulder", "elbow")
    assert omni.limits.tolist() == [[-0.98, 0.98], [-0.24, 1.57], [-0.2, 1.95]]   # from the URDF
    q = random_q(omni, 50, 4)
    pts = omni.chain_points(q)
    assert np.allclose(pts[:, 0], 0.0)                           # the root at base_position
    assert np.allclose(pts[:, -1], omni.forward(q), atol=1e-15)  # ... to the wrist
    # y is up: the waist joint is 0.09 m above the root, on the vertical axis
    assert np.any(np.all(np.isclose(pts, [0.0, 0.09, 0.0], atol=1e-12), axis=-1), axis=-1).all()
    seg = np.linalg.norm(np.diff(pts, axis=1), axis=-1)
    assert np.allclose(seg, seg[0], atol=1e-12)                   # rigid links keep their lengths
    # wrist1 (held) does not move the tip: the tip lies on its axis
    moved = load_omni(fixed_joints={"wrist1": 1.1})
    assert np.allclose(moved.forward(q), omni.forward(q), atol=1e-15)


TOY = """<?xml version="1.0"?>
<robot name="toy">
  <link name="root"/>
  <link name="l1"><inertial><origin xyz="0.01 0 0.05"/><mass value="0.7"/>
    <inertia ixx="1e-3" ixy="0" ixz="0" iyy="1e-3" iyz="0" izz="1e-3"/></inertial></link>
  <link name="mount"/>
  <link name="l2"><inertial><origin xyz="0.1 0.02 0"/><mass value="0.5"/>
    <inertia ixx="1e-3" ixy="0" ixz="0" iyy="1e-3" iyz="0" izz="1e-3"/></inertial></link>
  <link name="l3"/>
  <link name="l4"><inertial><origin xyz="0.03 0 -0.01"/><mass value="0.3"/>
    <inertia ixx="1e-4" ixy="0" ixz="0" iyy="1e-4" iyz="0" izz="1e-4"/></inertial></link>
  <link name="tool"/>
  <link name="side"><inertial><origin xyz="0 0.04 0"/><mass value="0.2"/>
    <inertia ixx="1e-4" ixy="0" ixz="0" iyy="1e-4" iyz="0" izz="1e-4"/></inertial></link>
  <joint name="j1" type="revolute"><parent link="root"/><child link="l1"/>
    <origin xyz="0.01 0.02 0.10" rpy="0.1 -0.2 0.3"/><axis xyz="0 0 1"/>
    <limit lower="-2.0" upper="2.0" effort="1" velocity="1"/></joint>
  <joint name="mount_fixed" type="fixed"><parent link="l1"/><child link="mount"/>
    <origin xyz="0.05 0 0.02" rpy="0 0.4 0"/></joint>
  <joint name="j2" type="REVOLUTE_TYPE"><parent link="mount"/><child link="l2"/>
    <origin xyz="0 0.03 0.15" rpy="-0.3 0 0.2"/><axis xyz="0 0.6 0.8"/>
    <limit lower="J2_LO" upper="J2_HI" effort="1" velocity="1"/></joint>
  <joint name="roll" type="revolute"><parent link="l2"/><child link="l3"/>
    <origin xyz="0.2 0 0"/><axis xyz="1 0 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j3" type="prismatic"><parent link="l3"/><child link="l4"/>
    <origin xyz="0 0.05 0" rpy="0 0 0.5"/><axis xyz="1 0 0"/>
    <limit lower="0.05" upper="0.25" effort="1" velocity="1"/></joint>
  <joint name="tool_fixed" type="fixed"><parent link="l4"/><child link="tool"/>
    <origin xyz="0.02 0.01 -0.03" rpy="0.2 0.1 0"/></joint>
  <joint name="side_joint" type="revolute"><parent link="l1"/><child link="side"/>
    <origin xyz="0 0 0.03"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
</robot>
"""
TOY_BASE, TOY_RPY, TOY_ROLL = (0.3, -0.1, 0.25), (0.4, -0.7, 1.2), 0.3


def toy_text(j2_type="revolute", j2_lo=-1.5, j2_hi=1.5):
    return TOY.replace("REVOLUTE_TYPE", j2_type).replace("J2_LO", str(j2_lo)).replace("J2_HI", str(j2_hi))


def toy_scenario(folder, port, estimate, body: str = ""):
    """A scenario on the toy URDF (written into ``folder`` beside it): the chain j1, j2, j3 to
    ``tool`` with the roll joint held, a 0.25 m shaft through ``port`` (controller's ``estimate``),
    then ``body`` (further TOML tables). Returns the scenario's path."""
    (folder / "toy.urdf").write_text(toy_text(), encoding="utf-8")
    path = folder / "toy.toml"
    path.write_text(f"""name = "toy"
[robot]
urdf = "toy.urdf"
joints = ["j1", "j2", "j3"]
wrist = "tool"
fixed_joints = {{ roll = {TOY_ROLL} }}
base_position = {list(TOY_BASE)}
base_rpy = {list(TOY_RPY)}
[instrument]
length = 0.25
[port]
position = {[float(v) for v in port]}
estimate = {[float(v) for v in estimate]}
{body}""", encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def toy_path(tmp_path_factory):
    p = tmp_path_factory.mktemp("toy") / "toy.urdf"
    p.write_text(toy_text())
    return p


def load_toy(path, **kw):
    args = dict(base_position=TOY_BASE, base_rpy=TOY_RPY, fixed_joints={"roll": TOY_ROLL})
    args.update(kw)
    return UrdfArm.load(path, ["j1", "j2", "j3"], "tool", **args)


def toy_frames(q):
    """World frames of the toy's links, by explicit matrices."""
    q1, q2, q3 = q
    B = tf(rpy(*TOY_RPY), TOY_BASE)
    l1 = B @ tf(rpy(0.1, -0.2, 0.3), (0.01, 0.02, 0.10)) @ tf(rot([0, 0, 1], q1))
    mount = l1 @ tf(rpy(0, 0.4, 0), (0.05, 0, 0.02))
    l2 = mount @ tf(rpy(-0.3, 0, 0.2), (0, 0.03, 0.15)) @ tf(rot([0, 0.6, 0.8], q2))
    l3 = l2 @ tf(p=(0.2, 0, 0)) @ tf(rot([1, 0, 0], TOY_ROLL))
    l4 = l3 @ tf(rpy(0, 0, 0.5), (0, 0.05, 0)) @ tf(p=(q3, 0, 0))
    tool = l4 @ tf(rpy(0.2, 0.1, 0), (0.02, 0.01, -0.03))
    side = l1 @ tf(p=(0, 0, 0.03))
    return {"l1": l1, "l2": l2, "l4": l4, "tool": tool, "side": side}


def toy_potential(q):
    """V = sum m g . c with world gravity 9.81 along -y (links with inertial data)."""
    F = toy_frames(q)
    V = 0.0
    for link, m, c in [("l1", 0.7, (0.01, 0, 0.05)), ("l2", 0.5, (0.1, 0.02, 0)), ("l4", 0.3, (0.03, 0, -0.01)),
                       ("side", 0.2, (0, 0.04, 0))]:
        V += m * 9.81 * (F[link] @ np.append(c, 1.0))[1]
    return V


def test_hand_written_chain(toy_path):
    arm = load_toy(toy_path)
    rng = np.random.default_rng(7)
    q = np.stack([rng.uniform(-2, 2, 100), rng.uniform(-1.5, 1.5, 100), rng.uniform(0.05, 0.25, 100)], -1)
    want = np.array([toy_frames(qk)["tool"][:3, 3] for qk in q])
    assert np.allclose(arm.forward(q), want, rtol=0, atol=1e-14)
    assert np.allclose(arm.jacobian(q), fd_jacobian(arm.forward, q), rtol=0, atol=1e-9)
    assert arm.chain.jtype.tolist() == [0, 0, 1]
    assert arm.limits.tolist() == [[-2.0, 2.0], [-1.5, 1.5], [0.05, 0.25]]
    pts = arm.chain_points(q[:3])
    assert np.allclose(pts[:, 0], TOY_BASE) and np.allclose(pts[:, -1], want[:3], atol=1e-14)
    for k, qk in enumerate(q[:3]):        # every joint origin on the chain is drawn
        F = toy_frames(qk)
        for p in (F["l1"][:3, 3], F["l2"][:3, 3], (F["l4"] @ tf(p=(-qk[2], 0, 0)))[:3, 3]):
            assert np.min(np.linalg.norm(pts[k] - p, axis=-1)) < 1e-14
    # the held joint's value matters; the off-chain joint does not exist for the wrist
    other = load_toy(toy_path, fixed_joints={"roll": -0.2})
    assert not np.allclose(other.forward(q), arm.forward(q))
    # gravity, with a rotated base and a branch (side) off the chain: dV/dq by finite differences
    tau = arm.gravity_torque(q[:10])
    h = 1e-6
    for qk, tk in zip(q[:10], tau):
        fd = [(toy_potential(qk + h * e) - toy_potential(qk - h * e)) / (2 * h) for e in np.eye(3)]
        assert np.allclose(tk, fd, rtol=0, atol=1e-8)
    # inverse through a prismatic joint and a held joint
    W = arm.forward(q[:200])
    qi, ok = arm.inverse(W)
    assert ok.all() and np.allclose(arm.forward(qi), W, rtol=0, atol=1e-10) and arm.within_limits(qi).all()


def test_continuous_joint_wraps(tmp_path):
    text = toy_text().replace('<joint name="j1" type="revolute">', '<joint name="j1" type="continuous">')
    p = tmp_path / "cont.urdf"
    p.write_text(text)
    arm = load_toy(p)
    assert arm.limits[0].tolist() == [-math.pi, math.pi]
    rng = np.random.default_rng(8)
    q = np.stack([rng.uniform(-math.pi, math.pi, 300), rng.uniform(-1.5, 1.5, 300), rng.uniform(0.05, 0.25, 300)], -1)
    q[:100, 0] = np.where(q[:100, 0] > 0, math.pi - 1e-3 * rng.random(100), -math.pi + 1e-3 * rng.random(100))
    W = arm.forward(q)
    qi, ok = arm.inverse(W)
    assert ok.all() and np.allclose(arm.forward(qi), W, rtol=0, atol=1e-10)
    assert np.all(np.abs(qi[:, 0]) <= math.pi)
    assert arm.reachable(W).all()


# ============================================================================ inverse
@pytest.mark.parametrize("which", ["omni", "phantom", "ur5", "panda"])
def test_inverse_round_trip(which, request):
    arm = request.getfixturevalue(which)
    q = random_q(arm, 1000, 11)
    W = arm.forward(q)
    qi, ok = arm.inverse(W)
    assert ok.all()
    assert np.max(np.linalg.norm(arm.forward(qi) - W, axis=-1)) < 1e-10
    assert arm.within_limits(qi).all()
    # near = the true configuration: the same branch comes back
    qn, okn = arm.inverse(W, near=q)
    assert okn.all() and np.allclose(qn, q, atol=1e-8)
    # unreachable: NaN, not ok
    far = W + 10.0
    qf, okf = arm.inverse(far)
    assert not okf.any() and np.isnan(qf).all()
    qs, oks = arm.inverse(W[0])
    assert qs.shape == (3,) and oks.shape == () and bool(oks)


def test_inverse_finds_the_second_elbow_branch():
    """P1's limits allow one elbow branch only (relative angle q2 - pi/2 < 0). With the elbow
    allowed past straight, wrists that only the branch opposite to the home pose's reaches
    within the limits are found, and so are wrists behind the shoulder (waist turned by pi)."""
    lims = [[-1.0, 4.0], [-1.9, 1.2], [-0.7, 3.0]]
    arm = UrdfArm.load(PHANTOM, JOINTS, "wrist", base_position=PHANTOM_BASE, joint_limits=lims,
                       coupled_limits=[CoupledLimit(("shoulder", "elbow"), (1.0, 1.0), -0.3, 3.5)])
    planar = Arm(base=(0.21, -0.21), l1=0.21, l2=0.21, home=(0.0, -math.pi / 2), q1_limits=(-1.9, 1.2),
                 q2_limits=(-0.7, 3.0), sum_limits=(-0.3, 3.5))
    q = random_q(arm, 20000, 12)
    q[:, 0] = 0.0                               # the plane x = 0: closed-form branches
    q = q[arm.within_limits(q)]
    W = arm.forward(q)
    pref, other, reach = planar.inverse_branches(W[:, 1:])
    only_other = reach & ~planar.within_limits(pref) & planar.within_limits(other)
    assert only_other.sum() > 50
    # waist 0 or pi put the arm in the plane x = 0; the map must find whichever holds
    qi, ok = arm.inverse(W[only_other])
    assert ok.all()
    assert np.allclose(arm.forward(qi), W[only_other], rtol=0, atol=1e-10) and arm.within_limits(qi).all()
    at_zero = np.abs(qi[:, 0]) < 1e-9
    assert at_zero.sum() > 0 and np.allclose(qi[at_zero, 1:], other[only_other][at_zero], atol=1e-8)
    # random configurations over the whole box, all four branches
    q = random_q(arm, 20000, 13)
    W = arm.forward(q)
    qi, ok = arm.inverse(W)
    assert ok.all() and np.max(np.linalg.norm(arm.forward(qi) - W, axis=-1)) < 1e-10
    assert arm.within_limits(qi).all()
    assert np.any(qi[:, 0] > math.pi / 2) and np.any(qi[:, 2] > math.pi / 2)


def test_kernels_from_compiled_code(omni):
    chain, rmap = omni.kernel()

    @njit
    def sweep(chain, rmap, W, q, ok, reach):
        for k in range(W.shape[0]):
            reach[k] = U.reach_point(chain, rmap, W[k, 0], W[k, 1], W[k, 2])
            ok[k] = U.ik_point(chain, rmap, W[k, 0], W[k, 1], W[k, 2], q[k])

    lo, hi = workspace_box(omni)
    W = lo + np.random.default_rng(13).random((3000, 3)) * (hi - lo)
    q, ok, reach = np.empty((3000, 3)), np.empty(3000, bool), np.empty(3000, bool)
    sweep(chain, rmap, W, q, ok, reach)
    assert np.array_equal(reach, omni.reachable(W))
    assert np.array_equal(ok, reach)
    assert np.allclose(omni.forward(q[ok]), W[ok], rtol=0, atol=1e-10)
    assert np.isnan(q[~ok]).all()
    assert not U.reach_point(chain, rmap, np.nan, 0.0, 0.1)


# ============================================================================ reachability
@pytest.mark.parametrize("which", ["omni", "phantom"])
def test_reach_map_guarantees(which, request, capsys):
    """In/out voxels agree with closed-form IK everywhere; boundary voxels (exact IK) too."""
    arm = request.getfixturevalue(which)
    exact = omni_exact if which == "omni" else phantom_exact
    chain, rmap = arm.kernel()
    assert arm.map_info.get("conflicts", 0) == 0
    # every wrist of a feasible configuration (incl. on the limit faces) is in a non-out voxel
    g = [np.linspace(a, b, 41) for a, b in arm.limits]
    Q = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)
    Wq = arm.forward(Q[arm.within_limits(Q)])
    assert np.all(map_state(arm, Wq) != 0)
    rng = np.random.default_rng(21)
    lo, hi = workspace_box(arm)
    W = lo + rng.random((100000, 3)) * (hi - lo)
    got, want, st = arm.reachable(W), exact(W), map_state(arm, W)
    assert want.sum() > 10000
    for s in (0, 1):
        assert np.array_equal(got[st == s], want[st == s]), f"state {s} voxels disagree with closed-form IK"
    # points inside boundary voxels
    B = np.argwhere(rmap.state == 2)
    Wb = rmap.origin + (B[rng.integers(0, len(B), 30000)] + rng.random((30000, 3))) * rmap.h
    gb, eb = arm.reachable(Wb), exact(Wb)
    near = near_boundary(exact, W, rmap.h)
    with capsys.disabled():
        print(f"\n[{which}] reach map: h = {rmap.h * 1e3:.2f} mm, voxels in/out/boundary = "
              f"{(rmap.state == 1).sum()}/{(rmap.state == 0).sum()}/{(rmap.state == 2).sum()}; closed-form IK "
              f"disagreements: {int((got != want).sum())} of {len(W)} random points "
              f"({int((got != want)[near].sum())} of {int(near.sum())} within one voxel of the boundary), "
              f"{int((gb != eb).sum())} of {len(Wb)} points in boundary voxels")
    assert np.array_equal(got, want)
    assert np.array_equal(gb, eb)
    # in voxels: IK succeeds there too
    assert arm.inverse(W[st == 1])[1].all()


@pytest.mark.slow
@pytest.mark.parametrize("which", ["omni", "phantom"])
def test_reachable_vs_brute_force_ik(which, request, capsys):
    arm = request.getfixturevalue(which)
    exact = omni_exact if which == "omni" else phantom_exact
    _, rmap = arm.kernel()
    rng = np.random.default_rng(31)
    lo, hi = workspace_box(arm)
    W = lo + rng.random((20000, 3)) * (hi - lo)
    got, st = arm.reachable(W), map_state(arm, W)
    brute = brute_reachable(arm, W)
    near = near_boundary(exact, W, rmap.h)
    bad = got != brute
    with capsys.disabled():
        print(f"\n[{which}] reachable vs brute-force IK on {len(W)} points: {int(bad.sum())} disagreements; "
              f"{int(bad[st == 2].sum())} of {int((st == 2).sum())} in boundary voxels, "
              f"{int(bad[near].sum())} of {int(near.sum())} within one voxel of the boundary")
    assert not bad[st != 2].any()
    assert bad[st == 2].mean() <= 0.002
    assert bad[near].mean() <= 0.01


# ============================================================================ map cache
def test_map_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("ERRPLAN_CACHE_DIR", str(tmp_path))
    a = load_phantom()
    ra = a.reach_map()
    assert a.map_info["from_cache"] is False
    files = list(tmp_path.glob("reachmap-*.npz"))
    assert len(files) == 1 and not list(tmp_path.glob(".reachmap-*"))   # written atomically
    b = load_phantom()
    rb = b.reach_map()
    assert b.map_info["from_cache"] is True
    for f in U.ReachMap._fields:
        assert np.array_equal(np.asarray(getattr(ra, f)), np.asarray(getattr(rb, f)))
    # a corrupt file is rebuilt, never trusted
    files[0].write_bytes(b"not an npz")
    c = load_phantom()
    rc = c.reach_map()
    assert c.map_info["from_cache"] is False and np.array_equal(rc.state, ra.state)
    # a well-formed file whose content does not match its checksum is rebuilt too
    with np.load(files[0]) as z:
        arrs = {k: z[k] for k in z.files}
    arrs["state"] = np.zeros_like(arrs["state"])
    with open(files[0], "wb") as f:
        np.savez(f, **arrs)
    d = load_phantom()
    assert np.array_equal(d.reach_map().state, ra.state) and d.map_info["from_cache"] is False
    # anything the map depends on changes the key
    e = UrdfArm.load(PHANTOM, JOINTS, "wrist", base_position=PHANTOM_BASE)   # no coupled limit
    e.reach_map()
    assert e.map_info["from_cache"] is False
    assert len(list(tmp_path.glob("reachmap-*.npz"))) == 2


def test_sampling_and_distance(phantom):
    S = phantom.sample_wrists(15)
    assert S.shape[1] == 3 and len(S) > 1000
    assert np.all(phantom.reachable(S) | (map_state(phantom, S) == 2))
    assert phantom.min_distance_to(phantom.forward([0.2, 0.3, 0.1])) == 0.0
    far = np.array([0.0, 2.0, 0.0])
    assert phantom.min_distance_to(far) == pytest.approx(np.min(np.linalg.norm(phantom.sample_wrists() - far, axis=-1)))


@pytest.mark.parametrize("which", ["phantom", "ur5"])
def test_nearer_than_agrees_with_the_sampled_distance(which, request):
    """UrdfArm.nearer_than (the scenario check that the shaft reaches the port; the map's certified
    voxels answer, else the sampled distance): never "no" where a sampled reachable wrist lies within r,
    never "yes" where no point of a non-out voxel does; a wrist's own neighbourhood is near, a point
    10 m off is not."""
    arm = request.getfixturevalue(which)
    _, rm = arm.kernel()
    rng = np.random.default_rng(17)
    lo, hi = workspace_box(arm, margin=0.3)
    S = arm.sample_wrists(41)
    corners = rm.origin + rm.h * np.argwhere(rm.state != 0)
    answers = set()
    for p, r in zip(lo + rng.random((60, 3)) * (hi - lo), rng.uniform(0.005, 0.3, 60)):
        got = arm.nearer_than(p, r)
        answers.add(got)
        if np.min(np.linalg.norm(S - p, axis=-1)) < r:
            assert got
        # the nearest point of any voxel not certified out
        d = np.linalg.norm(np.maximum(np.maximum(corners - p, p - (corners + rm.h)), 0.0), axis=-1)
        if np.min(d) >= r:
            assert not got
    assert answers == {True, False}
    w = arm.forward(random_q(arm, 5, 3))
    for wk in w:
        assert arm.nearer_than(wk + [0.004, 0.0, 0.0], 0.005)
    assert not arm.nearer_than(w[0] + 10.0, 0.3)


def test_resolve_uri(monkeypatch, tmp_path):
    """package:// mesh URIs: package_path (relative to the URDF), then ROS_PACKAGE_PATH, then the
    description packages installed in the environment (example-robot-data's own meshes); a miss is None."""
    monkeypatch.delenv("ROS_PACKAGE_PATH", raising=False)
    pkgs = tmp_path / "pkgs"
    mesh = pkgs / "my_description" / "meshes" / "base.stl"
    mesh.parent.mkdir(parents=True)
    mesh.write_bytes(b"solid x\nendsolid x\n")
    (tmp_path / "toy.urdf").write_text(toy_text(), encoding="utf-8")
    kw = dict(base_position=TOY_BASE, base_rpy=TOY_RPY, fixed_joints={"roll": TOY_ROLL})
    arm = UrdfArm.load(tmp_path / "toy.urdf", ["j1", "j2", "j3"], "tool", **kw)
    uri = "package://my_description/meshes/base.stl"
    assert arm.resolve_uri(uri) is None
    with_path = UrdfArm.load(tmp_path / "toy.urdf", ["j1", "j2", "j3"], "tool", package_path=["pkgs"], **kw)
    assert with_path.resolve_uri(uri) == mesh.resolve()
    assert with_path.resolve_uri("package://my_description/meshes/nope.stl") is None
    # a package_path entry may be the package itself
    itself = UrdfArm.load(tmp_path / "toy.urdf", ["j1", "j2", "j3"], "tool",
                          package_path=[str(pkgs / "my_description")], **kw)
    assert itself.resolve_uri(uri) == mesh.resolve()
    monkeypatch.setenv("ROS_PACKAGE_PATH", os.pathsep.join([str(tmp_path / "nowhere"), str(pkgs)]))
    assert arm.resolve_uri(uri) == mesh.resolve()
    assert arm.resolve_uri("pkgs/my_description/meshes/base.stl") == mesh.resolve()  # relative to the URDF
    assert arm.resolve_uri("file://" + str(mesh)) == mesh.resolve()
    assert arm.resolve_uri("http://example.invalid/x.stl") is None
    # installed packages: example-robot-data's UR5 names its meshes package://example-robot-data/robots/...
    ur5 = load_erd("ur5")
    text = erd_path("ur5").read_text(encoding="utf-8")
    uris = sorted(set(re.findall(r'filename="(package://[^"]+)"', text)))
    assert uris and all(ur5.resolve_uri(u) is not None and ur5.resolve_uri(u).is_file() for u in uris)
    assert ur5.resolve_uri("package://example-robot-data/robots/ur_description/meshes/none.dae") is None
    assert ur5.resolve_uri("package://no_such_description/x.stl") is None


def test_package_uri_in_a_scenario(tmp_path, monkeypatch):
    """A scenario's urdf as package://: found among the installed packages (no path of the machine in the
    file), or in its package_path; a package nowhere is one error naming the URI and where errplan looked."""
    from errplan.api import load_scenario
    monkeypatch.delenv("ROS_PACKAGE_PATH", raising=False)
    use_shared_cache(monkeypatch)   # loading checks the port against the UR5's map: the shared one
    sc = load_scenario(REPO / "scenarios" / "ur5_port.toml")
    assert Path(sc.robot.urdf) == erd_path("ur5")
    (tmp_path / "pkgs" / "toy_description" / "urdf").mkdir(parents=True)
    (tmp_path / "pkgs" / "toy_description" / "urdf" / "toy.urdf").write_text(toy_text(), encoding="utf-8")
    text = toy_scenario(tmp_path, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]).read_text(encoding="utf-8")
    text = text.replace('urdf = "toy.urdf"', 'urdf = "package://toy_description/urdf/toy.urdf"\npackage_path = ["pkgs"]')
    (tmp_path / "pkg.toml").write_text(text, encoding="utf-8")
    from errplan.scenario import read_scenario

    assert Path(read_scenario(tmp_path / "pkg.toml").robot.urdf) == (tmp_path / "pkgs/toy_description/urdf/toy.urdf").resolve()
    (tmp_path / "miss.toml").write_text(text.replace("toy_description/urdf", "missing_description/urdf"),
                                        encoding="utf-8")
    with pytest.raises(ErrplanError) as e:
        read_scenario(tmp_path / "miss.toml")
    msg = str(e.value)
    assert "[robot] urdf" in msg and "package://missing_description/urdf/toy.urdf" in msg and "pkgs" in msg
    assert "\n" not in msg


def test_package_uri_search_order(tmp_path, monkeypatch):
    """package://NAME/PATH in a scenario: the scenario's package_path first, then ROS_PACKAGE_PATH, then the
    installed description packages; a package in none of them is one line naming the URI and every folder
    looked in (all three kinds)."""
    from errplan.scenario import read_scenario

    rel = "ur_description/urdf/ur5_joint_limited_robot.urdf"
    copies = {}
    for where in ("mine", "ros"):
        f = tmp_path / where / rel
        f.parent.mkdir(parents=True)
        f.write_bytes(erd_path("ur5").read_bytes())
        copies[where] = f.resolve()
    plain = arm_scenario(tmp_path, "ur5", [0.1, 0.2, 0.6], [0.1, 0.2, 0.6]).read_text(encoding="utf-8")
    assert f'urdf = "package://{rel}"' in plain
    own = tmp_path / "own.toml"
    own.write_text(plain.replace(f'urdf = "package://{rel}"', f'urdf = "package://{rel}"\npackage_path = ["mine"]'),
                   encoding="utf-8")
    plain_path = tmp_path / "ur5.toml"
    monkeypatch.setenv("ROS_PACKAGE_PATH", os.pathsep.join([str(tmp_path / "nowhere"), str(tmp_path / "ros")]))
    assert Path(read_scenario(own).robot.urdf) == copies["mine"]          # package_path before ROS_PACKAGE_PATH
    assert Path(read_scenario(plain_path).robot.urdf) == copies["ros"]    # ROS_PACKAGE_PATH before installed
    monkeypatch.delenv("ROS_PACKAGE_PATH")
    assert Path(read_scenario(plain_path).robot.urdf) == erd_path("ur5")  # installed (example-robot-data)
    assert Path(read_scenario(own).robot.urdf) == copies["mine"]
    monkeypatch.setenv("ROS_PACKAGE_PATH", str(tmp_path / "ros"))
    miss = tmp_path / "miss.toml"
    miss.write_text(own.read_text(encoding="utf-8").replace("package://ur_description/", "package://nobody_description/"),
                    encoding="utf-8")
    with pytest.raises(ErrplanError) as e:
        read_scenario(miss)
    msg = str(e.value)
    assert "\n" not in msg and e.value.__cause__ is None
    assert f"package://nobody_description/{rel.partition('/')[2]}" in msg
    assert str((tmp_path / "mine").resolve()) in msg or str(tmp_path / "mine") in msg
    assert str(tmp_path / "ros") in msg
    assert str(packages.installed_roots()[0]) in msg


@pytest.mark.parametrize("which", sorted(ARMS))
def test_example_robot_data_scenarios(which, tmp_path, monkeypatch):
    """The example-robot-data arms as a user names them, in a scenario (urdf = "package://...", nothing of
    this machine in the file): the scenario's arm against pinocchio's FK on the same file, with the held
    joints at their values, and its Jacobian against central differences."""
    from errplan.kinematics import arm_for
    from errplan.scenario import read_scenario

    monkeypatch.delenv("ROS_PACKAGE_PATH", raising=False)
    path = arm_scenario(tmp_path, which, [0.1, 0.2, 0.6], [0.1, 0.2, 0.6])
    assert "package://" in path.read_text(encoding="utf-8")
    sc = read_scenario(path)
    assert Path(sc.robot.urdf) == erd_path(which)
    arm = arm_for(sc.robot)
    a = ARMS[which]
    assert arm.joint_names == tuple(a["joints"])
    q = random_q(arm, 100, 7, feasible=False)
    W, J = pin_world(erd_path(which), a["wrist"], arm.base_position, arm.base_rpy, q, a["joints"], a["fixed_joints"])
    assert np.allclose(arm.forward(q), W, rtol=0, atol=1e-14)
    assert np.allclose(arm.jacobian(q), J, rtol=0, atol=1e-14)
    assert np.allclose(arm.jacobian(q), fd_jacobian(arm.forward, q), rtol=0, atol=1e-9)


# ============================================================================ bad input
def write(tmp_path, text, name="r.urdf"):
    p = tmp_path / name
    p.write_text(text)
    return p


LIM = '<limit lower="-1" upper="1" effort="1" velocity="1"/>'
PLANAR3 = f"""<robot name="planar3"><link name="a"/><link name="b"/><link name="c"/><link name="d"/>
<joint name="p1" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>{LIM}</joint>
<joint name="p2" type="revolute"><parent link="b"/><child link="c"/><origin xyz="0.1 0 0"/><axis xyz="0 0 1"/>{LIM}</joint>
<joint name="p3" type="revolute"><parent link="c"/><child link="d"/><origin xyz="0.1 0 0"/><axis xyz="0 0 1"/>{LIM}</joint>
</robot>"""


@pytest.mark.parametrize("case, pattern", [
    ("missing", r".*nope\.urdf: URDF file not found"),
    ("directory", r"is a directory"),
    ("not_xml", r"r\.urdf is not XML"),
    ("not_urdf", r"r\.urdf is not a URDF: its root element is <foo>"),
    ("invalid_urdf", r"r\.urdf is not a valid URDF: .*does not specify limits"),
    ("unknown_joint", r"toy\.urdf: joint 'jx' is not in the URDF"),
    ("off_chain", r"toy\.urdf: joint 'side_joint' is not on the chain from the root link 'root' to the wrist link 'tool'"),
    ("no_wrist", r"toy\.urdf: wrist link 'hand' is not in the URDF"),
    ("fixed_actuated", r"toy\.urdf: joint 'mount_fixed' is fixed"),
    ("floating", r"r\.urdf: joint 'j2' on the chain to 'tool' is (freeflyer|floating)"),
    ("two_joints", r"toy\.urdf: 2 actuated joint\(s\) \['j1', 'j2'\] cannot place the wrist in 3-D"),
    ("planar", r"r\.urdf: joints \['p1', 'p2', 'p3'\] cannot place the wrist 'd' in 3-D"),
    ("order", r"toy\.urdf: joints \['j2', 'j1', 'j3'\] must be listed from the root to the wrist"),
    ("fixed_off_chain", r"toy\.urdf: fixed_joints names 'side_joint', which is not a movable joint on the chain"),
    ("fixed_actuated_name", r"toy\.urdf: fixed_joints names 'j1', which is an actuated joint"),
    ("fixed_nan", r"toy\.urdf: fixed_joints value of 'roll' must be a finite number"),
    ("limits_reversed", r"toy\.urdf: joint_limits for 'j2' are reversed: \[1\.0, -1\.0\]"),
    ("limits_shape", r"toy\.urdf: joint_limits must be 3 finite pairs"),
    ("urdf_limits_reversed", r"r\.urdf: joint 'j2' has reversed limits in the URDF: lower 1\.5 > upper -1\.5"),
    ("coupled_reversed", r"toy\.urdf: coupled limit \['j1', 'j2'\] bounds are reversed: \[1\.0, -1\.0\]"),
    ("coupled_unknown", r"toy\.urdf: coupled limit \['j1', 'roll'\] names 'roll', which is not an actuated joint"),
    ("base_rpy", r"toy\.urdf: base_rpy must be 3 finite numbers"),
    ("empty", r"toy\.urdf: the joint limits leave no feasible configuration"),
])
def test_bad_input(case, pattern, tmp_path, toy_path, capfd):
    j = ["j1", "j2", "j3"]
    calls = {
        "missing": lambda: UrdfArm.load(tmp_path / "nope.urdf", j, "tool"),
        "directory": lambda: UrdfArm.load(tmp_path, j, "tool"),
        "not_xml": lambda: UrdfArm.load(write(tmp_path, "robot: {not xml"), j, "tool"),
        "not_urdf": lambda: UrdfArm.load(write(tmp_path, "<foo><bar/></foo>"), j, "tool"),
        "invalid_urdf": lambda: UrdfArm.load(write(tmp_path, TOY.replace(
            '<limit lower="J2_LO" upper="J2_HI" effort="1" velocity="1"/>', "").replace("REVOLUTE_TYPE", "revolute")), j, "tool"),
        "unknown_joint": lambda: UrdfArm.load(toy_path, ["j1", "jx", "j3"], "tool"),
        "off_chain": lambda: UrdfArm.load(toy_path, ["j1", "side_joint", "j3"], "tool"),
        "no_wrist": lambda: UrdfArm.load(toy_path, j, "hand"),
        "fixed_actuated": lambda: UrdfArm.load(toy_path, ["j1", "mount_fixed", "j3"], "tool"),
        "floating": lambda: UrdfArm.load(write(tmp_path, toy_text(j2_type="floating")), ["j1", "roll", "j3"], "tool"),
        "two_joints": lambda: UrdfArm.load(toy_path, ["j1", "j2"], "tool"),
        "planar": lambda: UrdfArm.load(write(tmp_path, PLANAR3), ["p1", "p2", "p3"], "d"),
        "order": lambda: UrdfArm.load(toy_path, ["j2", "j1", "j3"], "tool"),
        "fixed_off_chain": lambda: load_toy(toy_path, fixed_joints={"side_joint": 0.1}),
        "fixed_actuated_name": lambda: load_toy(toy_path, fixed_joints={"j1": 0.1}),
        "fixed_nan": lambda: load_toy(toy_path, fixed_joints={"roll": float("nan")}),
        "limits_reversed": lambda: load_toy(toy_path, joint_limits=[[-1, 1], [1, -1], [0.1, 0.2]]),
        "limits_shape": lambda: load_toy(toy_path, joint_limits=[[-1, 1], [0.1, 0.2]]),
        "urdf_limits_reversed": lambda: load_toy(write(tmp_path, toy_text(j2_lo=1.5, j2_hi=-1.5))),
        "coupled_reversed": lambda: load_toy(toy_path, coupled_limits=[CoupledLimit(("j1", "j2"), (1.0, 1.0), 1.0, -1.0)]),
        "coupled_unknown": lambda: load_toy(toy_path, coupled_limits=[CoupledLimit(("j1", "roll"), (1.0, 1.0), -1.0, 1.0)]),
        "base_rpy": lambda: load_toy(toy_path, base_rpy=(0.0, 1.0)),
        "empty": lambda: load_toy(toy_path, coupled_limits=[CoupledLimit(("j1", "j2"), (1.0, 1.0), 5.0, 6.0)]),
    }
    with pytest.raises(ErrplanError, match=pattern) as info:
        calls[case]()
    msg = str(info.value)
    assert "\n" not in msg
    assert info.value.__cause__ is None
    assert capfd.readouterr().err == ""          # nothing from urdfdom/pinocchio leaks to stderr


def test_gravity_without_inertial_data(omni):
    with pytest.raises(ErrplanError, match=r"omni\.urdf: the links moved by joint 'waist' carry no inertial data"):
        omni.gravity_torque([0.0, 0.0, 0.0])


def test_from_robot():
    class Robot:
        urdf = str(PHANTOM)
        joints = tuple(JOINTS)
        wrist = "wrist"
        base_position = PHANTOM_BASE
        base_rpy = (0.0, 0.0, 0.0)
        joint_limits = ((-1.0, 1.0), (-1.9, 1.2), (-0.7, 1.0))
        fixed_joints = {}
        coupled_limits = (SUM,)
        package_path = ()

    arm = UrdfArm.from_robot(Robot())
    ref = load_phantom()
    q = random_q(ref, 50, 41)
    assert np.array_equal(arm.forward(q), ref.forward(q))
    assert np.array_equal(arm.chain.A, ref.chain.A) and np.array_equal(arm.chain.lo, ref.chain.lo)
    assert arm.chain.A.tolist()[-1] == [0.0, 1.0, 1.0] and arm.chain.lo[-1] == -0.3 and arm.chain.hi[-1] == 2.8


def test_seed_lists_keep_every_seed_nearest_first_ties_in_found_order():
    """The reachability map's seed lists (numpy, out of the build kernel) against a plain loop: per cell,
    exactly its ``fcnt`` seeds, sorted by distance, equal distances in the order they were found."""
    from errplan.kinematics.urdf.reachmap import _seed_lists

    rng = np.random.default_rng(3)
    ncel, S2 = 200, 8
    fd = rng.normal(size=(ncel, S2, 3))
    fdist = rng.integers(0, 4, size=(ncel, S2)).astype(np.float32)  # many ties
    fcnt = rng.integers(0, S2 + 1, size=ncel)
    fdist[np.arange(S2) >= fcnt[:, None]] = -1.0  # stale values past the count must be ignored
    ptr, seeds = _seed_lists(fd, fdist, fcnt)
    pos = 0
    for c in range(ncel):
        ref = [fd[c, k] for k in sorted(range(fcnt[c]), key=lambda k: (fdist[c, k], k))]
        assert ptr[c] == pos and ptr[c + 1] == pos + fcnt[c]
        assert np.array_equal(seeds[pos:pos + fcnt[c]], np.reshape(ref, (-1, 3)))
        pos += fcnt[c]
    assert len(seeds) == pos == fcnt.sum() and seeds.flags.c_contiguous


def test_the_maps_depth_is_the_chessboard_distance_to_another_state_by_brute_force():
    """ReachMap.depth against a brute-force search on random voxel states (blobs of in and out with a
    boundary between): every out or in voxel's depth is the smallest chessboard distance to a voxel of
    another state, so that a cube of half-width below it holds only its state; 0 on the boundary."""
    from errplan.kinematics.urdf.reachmap import state_depth

    rng = np.random.default_rng(7)
    for shape in [(9, 7, 5), (6, 6, 6), (12, 3, 4)]:
        raw = rng.random(shape)
        state = np.where(raw < 0.45, 0, np.where(raw > 0.6, 1, 2)).astype(np.uint8)
        state[: shape[0] // 2] = 1  # a larger in region, so that depths above 1 occur
        state[shape[0] // 2, : shape[1] // 2] = 0
        depth = state_depth(state)
        idx = np.argwhere(np.ones(shape, bool))
        for v in idx:
            s = state[tuple(v)]
            other = idx[state.reshape(-1) != s]
            want = 0 if s == 2 else (255 if not len(other) else int(np.abs(other - v).max(axis=1).min()))
            assert depth[tuple(v)] == want, (shape, tuple(v), s, depth[tuple(v)], want)
    assert state_depth(np.ones((3, 4, 5), np.uint8)).min() == 255  # all in: nothing else in the map


@pytest.mark.parametrize("which", ["phantom", "ur5", "panda", "toy", "toy_p1", "toy_p0"])
def test_the_iks_newton_frame_is_the_chain_turned_back_by_joint_0(which, request, toy_path, tmp_path):
    """The inverse kinematics' Newton steps take the residual and the Jacobian from the product of
    exponentials (chain._local3), in the frame turned back by joint 0's own motion. Against pinocchio's
    world wrist and Jacobian at random configurations and targets: the same |t - f(q)|, J^T J and
    J^T (t - f(q)), and the frame's residual turned forward again is t - f(q) (the toy arm has a
    prismatic joint, a held joint and a rotated base; its variants make joint 1, then joint 0, prismatic
    too)."""
    from errplan.kinematics.urdf.chain import _local3

    if which.startswith("toy"):
        path = toy_path
        if which != "toy":
            text = toy_text("prismatic", -0.1, 0.2)
            if which == "toy_p0":
                text = text.replace('<joint name="j1" type="revolute">', '<joint name="j1" type="prismatic">')
            path = tmp_path / f"{which}.urdf"
            path.write_text(text)
        arm = load_toy(path)
        assert list(arm.chain.jtype) == {"toy": [0, 0, 1], "toy_p1": [0, 1, 1], "toy_p0": [1, 1, 1]}[which]
        frame, joints, held = "tool", ["j1", "j2", "j3"], {"roll": TOY_ROLL}
    else:
        arm = request.getfixturevalue(which)
        if which in ARMS:
            path, frame, joints, held = erd_path(which), ARMS[which]["wrist"], ARMS[which]["joints"], ARMS[which]["fixed_joints"]
        else:
            path, frame, joints, held = PHANTOM, "wrist", None, None
    q = random_q(arm, 100, 11, feasible=False)
    W, J = pin_world(path, frame, arm.base_position, arm.base_rpy, q, joints, held)
    rng = np.random.default_rng(5)
    T = W + rng.normal(scale=0.05, size=W.shape)
    z0, o0 = arm.chain.screw[0, :3], arm.chain.screw[0, 3:]
    for qk, tk, wk, jk in zip(q, T, W, J):
        r, c0, c1, c2 = _local3(arm.chain, qk[0], qk[1], qk[2], tk[0], tk[1], tk[2])
        r, Jl = np.array(r), np.array([c0, c1, c2]).T
        rw = tk - wk
        assert abs(np.linalg.norm(r) - np.linalg.norm(rw)) <= 1e-14
        assert np.allclose(Jl.T @ Jl, jk.T @ jk, rtol=0, atol=1e-13)
        assert np.allclose(Jl.T @ r, jk.T @ rw, rtol=0, atol=1e-13)
        R0 = rot(z0, qk[0]) if arm.chain.jtype[0] == 0 else np.eye(3)
        assert np.allclose(R0 @ r, rw, rtol=0, atol=1e-14) and np.allclose(R0 @ Jl, jk, rtol=0, atol=1e-14)


def test_a_tips_map_certificate_is_the_voxel_by_voxel_answer():
    """_tip_reach's one-lookup certificate (ReachMap.depth) against the answer read voxel by voxel in
    Python: on random maps of in, out and boundary blobs, for random tips, port boxes and loads whose
    wrist-ball cubes hold up to a few hundred voxels, the same 1 (all in), 0 (all out) or 2."""
    from errplan.fields.kernels import _tip_reach
    from errplan.kinematics.urdf.model import ReachMap
    from errplan.kinematics.urdf.reachmap import state_depth

    rng = np.random.default_rng(21)
    shape = (24, 22, 20)
    h = 0.01
    origin = np.array([-0.12, -0.11, -0.10])
    seen = {0: 0, 1: 0, 2: 0}
    for trial in range(6):
        # smooth random field: blobs of in (high), out (low), a boundary band between
        f = rng.normal(size=shape)
        for ax in range(3):
            for _ in range(3):
                f = (f + np.roll(f, 1, axis=ax) + np.roll(f, -1, axis=ax)) / 3.0
        state = np.where(f > 0.04, 1, np.where(f < -0.04, 0, 2)).astype(np.uint8)
        state[:9] = 1  # a large in region and a large out one: depths well above 1
        state[-9:] = 0
        depth = state_depth(state)
        rmap = ReachMap(origin, h, np.array(shape, np.int64), state, depth, 1, np.zeros(2, np.int64),
                        np.zeros((1, 3)))
        L = 0.3
        for _ in range(2500):
            half = rng.uniform(0.0, 0.004, 3)
            lo = np.array([-half[0], -half[1], -half[2], 0.0, 0.0])
            hi = np.array([half[0], half[1], half[2], rng.choice([0.0, 0.3]), 2 * np.pi])
            base_port = rng.uniform(-0.05, 0.05, 3) + np.array([0.0, 0.0, 0.2])
            x = base_port + rng.normal(size=3) * 0.06
            got = _tip_reach(x, base_port, lo, hi, L, rmap)
            # the same arithmetic, then every voxel of the cube read (as before the depth lookup)
            pc = base_port + 0.5 * (lo[:3] + hi[:3])
            delta = 0.5 * math.sqrt((hi[0] - lo[0]) ** 2 + (hi[1] - lo[1]) ** 2 + (hi[2] - lo[2]) ** 2)
            e = x - pc
            r = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
            rmin = r - delta
            if not (rmin > 0.0 and r < L):
                assert got == 2
                continue
            R = L / rmin * delta + L * math.atan(max(abs(lo[3]), abs(hi[3])) * L * L / 12.0) + 1e-9
            w = [x[i] - L * e[i] / r for i in range(3)]
            span = [(int(math.floor((w[i] - R - origin[i]) / h)), int(math.floor((w[i] + R - origin[i]) / h)))
                    for i in range(3)]
            off = None  # axis by axis: the whole ball off the map (0: nothing there is reachable), else partly (2)
            for (a, b), n in zip(span, shape):
                if b < 0 or a >= n:
                    off = 0
                    break
                if a < 0 or b >= n:
                    off = 2
                    break
            if off is not None:
                assert got == off
                continue
            cube = state[span[0][0]:span[0][1] + 1, span[1][0]:span[1][1] + 1, span[2][0]:span[2][1] + 1]
            assert cube.size <= 4096
            want = 1 if (cube == 1).all() else (0 if (cube == 0).all() else 2)
            assert got == want, (trial, x, got, want)
            seen[want] += 1
    assert min(seen.values()) > 100, seen  # every answer occurs often


# ============================================================================ closed-form IK
LIFT = """<?xml version="1.0"?>
<robot name="lift">
  <link name="base"/><link name="carriage"/><link name="upper"/><link name="fore"/><link name="tool"/>
  <joint name="lift" type="prismatic"><parent link="base"/><child link="carriage"/>
    <origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 0.6 0.8"/><limit lower="0" upper="0.3" effort="1" velocity="1"/></joint>
  <joint name="shoulder" type="revolute"><parent link="carriage"/><child link="upper"/>
    <origin xyz="0.02 0 0.05" rpy="0.3 0 0.2"/><axis xyz="1 0 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="fore"/>
    <origin xyz="0 0.25 0.01" rpy="0 0 0"/><axis xyz="-1 0 0"/><limit lower="-2.5" upper="2.5" effort="1" velocity="1"/></joint>
  <joint name="tool_fix" type="fixed"><parent link="fore"/><child link="tool"/><origin xyz="0.03 0.2 0"/></joint>
</robot>
"""


@njit
def _closed_many(chain, W, st, Q):
    for k in range(W.shape[0]):
        s, q0, q1, q2 = U.chain._ik_parallel(chain, W[k, 0], W[k, 1], W[k, 2])
        st[k] = s
        Q[k, 0], Q[k, 1], Q[k, 2] = q0, q1, q2


@pytest.mark.parametrize("which", ["phantom", "phantom_cont", "ur5", "lift"])
def test_closed_form_ik_of_parallel_shoulder_and_elbow(which, request, tmp_path):
    """chain._ik_parallel (reach_point's answer in boundary voxels where it decides) on chains whose
    joints 1 and 2 turn about parallel axes: the PHANToM (a coupled limit), the PHANToM with a
    continuous waist, the UR5 (every range 4 pi: several turns of each joint), and a hand-written arm
    with a prismatic joint 0 and antiparallel joint axes. Every wrist of a feasible configuration is
    found, at a configuration within the limits that reaches it to 1e-10; on points in and around the
    map's boundary voxels, every "unreachable" is unreachable for brute-force IK (many seeds) and
    every "reachable" is a checked configuration; it leaves at most 2 % to Newton."""
    if which == "phantom":
        arm = request.getfixturevalue("phantom")
    elif which == "phantom_cont":
        p = tmp_path / "cont.urdf"
        p.write_text(PHANTOM.read_text().replace('<joint name="waist" type="revolute">',
                                                 '<joint name="waist" type="continuous">'))
        arm = UrdfArm.load(p, JOINTS, "wrist", base_position=PHANTOM_BASE, coupled_limits=[SUM])
        assert arm.limits[0].tolist() == [-math.pi, math.pi]
    elif which == "ur5":
        arm = request.getfixturevalue("ur5")
    else:
        p = tmp_path / "lift.urdf"
        p.write_text(LIFT)
        arm = UrdfArm.load(p, ["lift", "shoulder", "elbow"], "tool")
        assert list(arm.chain.jtype) == [1, 0, 0]
    chain, rmap = arm.kernel()

    def solve(W):
        st, Q = np.empty(len(W), np.int64), np.empty((len(W), 3))
        _closed_many(chain, np.ascontiguousarray(W), st, Q)
        return st, Q

    q = random_q(arm, 3000, 41)
    W = arm.forward(q)
    st, Q = solve(W)
    assert (st != 0).all() and (st == 1).mean() >= 0.98
    ok = st == 1
    assert arm.within_limits(Q[ok]).all()
    assert np.max(np.linalg.norm(arm.forward(Q[ok]) - W[ok], axis=-1)) < 1e-10
    # every branch: with the limits a small window around a random configuration (joint angles anywhere
    # on the circle), the one solution there is found (either root of joint 0, either elbow, any turn)
    rng = np.random.default_rng(43)
    lo0, hi0 = arm.limits[:, 0], arm.limits[:, 1]
    span = np.where(arm.chain.jtype == 0, [-4.0, -4.0, -4.0], lo0), np.where(arm.chain.jtype == 0, 4.0, hi0)
    found = 0
    for qc in span[0] + rng.random((400, 3)) * (span[1] - span[0]):
        win = chain._replace(A=np.eye(3), lo=qc - 0.01, hi=qc + 0.01)
        w = arm.forward(qc)[None]
        st, Q = np.empty(1, np.int64), np.empty((1, 3))
        _closed_many(win, w, st, Q)
        if st[0] == 1:
            found += 1
            assert np.all(np.abs(Q[0] - qc) <= 0.01) and np.linalg.norm(arm.forward(Q[0]) - w[0]) < 1e-10
        else:
            assert st[0] == -1  # never "unreachable"
    assert found >= 0.98 * 400
    # points in and near the boundary voxels: the hard ones
    rng = np.random.default_rng(42)
    B = np.argwhere(rmap.state == 2)
    Wb = rmap.origin + (B[rng.integers(0, len(B), 1500)] + rng.random((1500, 3)) * 1.4 - 0.2) * rmap.h
    st, Q = solve(Wb)
    assert (st == 1).sum() > 100 and (st == 0).sum() > 100 and (st == -1).mean() <= 0.02
    ok = st == 1
    assert arm.within_limits(Q[ok]).all()
    assert np.max(np.linalg.norm(arm.forward(Q[ok]) - Wb[ok], axis=-1)) < 1e-10
    assert not brute_reachable(arm, Wb[st == 0]).any()
    # and reach_point answers by it (Newton where it does not decide): the same on every point
    assert np.array_equal(arm.reachable(Wb)[st >= 0], st[st >= 0] == 1)


def test_closed_form_ik_leaves_other_chains_to_newton(panda, toy_path):
    """Chains without parallel joints 1 and 2 (the Panda's shoulder joints, the toy arm) are not this
    closed form's: it returns -1 everywhere, and reach_point's Newton answers as before."""
    for arm in (panda, load_toy(toy_path)):
        chain, _ = arm.kernel()
        W = arm.forward(random_q(arm, 50, 3))
        st, Q = np.empty(len(W), np.int64), np.empty((len(W), 3))
        _closed_many(chain, W, st, Q)
        assert (st == -1).all()
        assert arm.reachable(W).all()


def _two_link_chain(l1, l2, lo, hi, A=None, axis0=(0.0, 0.0, 1.0), jt0=0, shoulder=0.0):
    """ChainData of joint 0 about (or along) axis0, then two parallel joints about y, links along x."""
    from errplan.kinematics.urdf.model import ChainData, chain_screws

    T = np.tile(np.eye(4), (4, 1, 1))
    T[1, 0, 3], T[2, 0, 3], T[3, 0, 3] = shoulder, l1, l2
    axis = np.array([axis0, [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    A = np.eye(3) if A is None else np.asarray(A, float)
    return ChainData(T, axis, np.array([jt0, 0, 0], np.int64), A, np.array(lo, float), np.array(hi, float),
                     chain_screws(T, axis))


def _fk(chain, q):
    out = np.empty(3)
    U.chain.fk_point(chain, np.asarray(q, float), out)
    return out


def test_closed_form_ik_never_proves_unreachable_what_a_limit_configuration_reaches():
    """The review's cases (each returned 0, or a wrong configuration, before the margins were scaled):
    - a coupled row met only on turns beyond the first three of a 4 pi box: found, or left to Newton;
    - an elbow nearly straight, its limit 2e-7 to 1e-6 rad past the exact solution; a nearly folded
      elbow with the shoulder's limit 3e-7 past it; a prismatic joint 0 tilted 1e-4 rad off the
      normal, its limit 1e-6 m past: configurations within the limits reach to 1e-10 m, so never 0;
    - huge or infinite limits: a configuration near the principal turn, checked to reach."""
    P = 4 * math.pi
    ch = _two_link_chain(0.1, 0.08, [-P, -P, -P, 9.0], [P, P, P, 10.0], A=np.vstack([np.eye(3), [[0, 1, 1]]]))
    q = np.array([0.5, 8.9, 0.6])
    st, *qf = U.chain._ik_parallel(ch, *_fk(ch, q))
    assert st != 0
    if st == 1:
        assert 9.0 <= qf[1] + qf[2] <= 10.0 and np.linalg.norm(_fk(ch, qf) - _fk(ch, q)) < 1e-10
    l = 0.1
    th = math.acos(1 - 2e-6)
    t = _fk(_two_link_chain(l, l, [-3] * 3, [3] * 3), [0.3, 0.2, th])
    for dq in (2e-7, 5e-7, 1e-6):
        assert U.chain._ik_parallel(_two_link_chain(l, l, [-3, -3, th + dq], [3, 3, 3]), *t)[0] != 0
    rp = 2e-4
    thf = math.acos((rp ** 2 - 2 * l * l) / (2 * l * l))
    t = _fk(_two_link_chain(l, l, [-3] * 3, [3, 3, 3.2], shoulder=0.3), [0.3, 0.5, thf])
    assert U.chain._ik_parallel(_two_link_chain(l, l, [-3, 0.5 + 3e-7, 0.0], [3, 3, 3.2], shoulder=0.3), *t)[0] != 0
    # a straight elbow of short links whose limit lies past _QGAP: both elbows fail the limit's quick test,
    # yet the elbow held at its limit reaches to 5e-11 m (the ill-conditioned elbow must leave it to Newton)
    short = _two_link_chain(0.005, 0.005, [-3, -3, 2e-4], [3, 3, 3])
    t = _fk(short, [0.3, 0.2, 0.0])
    assert np.linalg.norm(_fk(short, [0.3, 0.2 - 1e-4, 2e-4]) - t) < 1e-10
    assert U.chain._ik_parallel(short, *t)[0] != 0
    eps = 1e-4
    tilt = _two_link_chain(l, l, [0.0, -3, -3], [1.0, 3, 3], axis0=(math.cos(eps), math.sin(eps), 0.0), jt0=1)
    q = np.array([0.0, 0.4, -0.8])
    t = _fk(tilt, q) + [0.0, -5e-11, 0.0]
    assert np.linalg.norm(_fk(tilt, q) - t) < 1e-10 and U.chain._ik_parallel(tilt, *t)[0] != 0
    q = np.array([0.5, 0.4, 0.6])
    for L in (1e10, 1e16, np.inf):
        ch = _two_link_chain(0.1, 0.08, [-L] * 3, [L] * 3)
        st, *qf = U.chain._ik_parallel(ch, *_fk(ch, q))
        assert st == 1 and np.all(np.abs(qf) <= math.pi + 1e-12)
        assert np.linalg.norm(_fk(ch, qf) - _fk(ch, q)) < 1e-10
