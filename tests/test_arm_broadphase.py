"""The arm checks' compiled part (errplan.kinematics.urdf.broadphase, errplan.planning.arm_checks): the link
placements against pinocchio's, the bounding capsules against every vertex they must hold, the segment
distance against dense sampling, the compiled tip configurations and joint-space samples against the Python
ones, and the decisions of the compiled check against coal's exact distance (states) and against the
Python check it replaces (motions), on random states and motions of tests/test_plan_arms.py's two UR5s
(arms whose links come within the clearance and out of it across the region)."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from arms import ARMS
from errplan import packages
from errplan.kinematics.urdf import UrdfArm
from errplan.kinematics.urdf.broadphase import CLEAR, UNDECIDED, UNREACHABLE, WITHIN, arm_motion, place_objects, \
    segment_distance
from errplan.kinematics.urdf.collision import ArmCollision, clearance_to_held, motion_samples
from errplan.models import arm_model
from errplan.planning.arm_checks import ArmChecks
from test_plan_arms import CLEARANCE, api_setup, setup_doc

LO, HI = np.array([-0.11, -0.04, 0.27]), np.array([0.0, 0.04, 0.43])  # the setup's task region (its fields)


@pytest.fixture(scope="module")
def checks():
    return ArmChecks.from_model(arm_model(api_setup(setup_doc()).moving("left")))


@pytest.fixture(scope="module")
def panda():
    a = ARMS["panda"]
    arm = UrdfArm.load(packages.resolve_package_uri(a["urdf"]), a["joints"], a["wrist"], base_position=[0.1, -0.2, 0.3],
                       base_rpy=a["base_rpy"], fixed_joints=a["fixed_joints"])
    return ArmCollision.from_arm(arm)


def test_link_tree_places_objects_as_pinocchio(checks, panda):
    """Compiled placements of every collision object (a UR5; a Panda with a held joint off the chain and
    objects past the wrist) equal pinocchio's within rounding."""
    rng = np.random.default_rng(3)
    for geo in (checks.geo, panda):
        tree = geo.link_tree()
        lim = geo.arm.limits
        P = np.empty((len(geo.names), 4, 4))
        for _ in range(40):
            q = lim[:, 0] + rng.random(geo.arm.n) * (lim[:, 1] - lim[:, 0])
            place_objects(tree, q, P)
            assert np.allclose(P, geo.placements(q), rtol=0, atol=1e-12)


def test_capsules_hold_every_vertex_of_their_piece(checks, panda):
    """Each capsule holds every vertex of its piece (so, being convex, its triangles); the pieces of an object
    partition its triangles; a piece's surface points are its vertices."""
    for geo in (checks.geo, panda):
        obj, A, B, R = geo.capsules()
        pieces = geo.pieces()
        pcap, pts = geo.surface_points()
        for g, geom in enumerate(geo._geoms):
            ks = np.flatnonzero(obj == g)
            assert len(ks) >= 1
            if len(ks) > 1:
                assert sum(p.num_tris for p in (pieces[k] for k in ks)) == geom.num_tris
            for k in ks:
                V = np.asarray(pieces[k].vertices(), float) if hasattr(pieces[k], "num_vertices") else geo._hulls[g]
                ab = B[k] - A[k]
                s = np.clip((V - A[k]) @ ab / max(ab @ ab, 1e-300), 0.0, 1.0)
                dist = np.linalg.norm(V - (A[k] + s[:, None] * ab), axis=1)
                assert dist.max() <= R[k]
                assert dist.max() > 0.5 * R[k]  # and not grossly larger than needed
                P = pts[pcap == k]
                if len(P):
                    assert len(P) == len(V) and np.allclose(np.sort(P, axis=0), np.sort(V, axis=0))


def test_segment_distance_against_dense_sampling():
    rng = np.random.default_rng(5)
    t = np.linspace(0.0, 1.0, 401)
    for _ in range(60):
        p, q, r, s = rng.normal(size=(4, 3)) * 0.1
        if rng.random() < 0.2:
            q = p + 1e-3 * rng.normal(size=3)  # nearly a point
        if rng.random() < 0.2:
            s = r + (q - p) * 0.7  # parallel
        d = segment_distance(*p, *q, *r, *s)
        X = p + t[:, None] * (q - p)
        Y = r + t[:, None] * (s - r)
        brute = np.min(np.linalg.norm(X[:, None] - Y[None], axis=-1))
        step = max(np.linalg.norm(q - p), np.linalg.norm(s - r)) / 400
        assert d <= brute + 1e-12 and brute <= d + step


def test_compiled_tips_and_samples_as_the_python_ones(checks):
    """The compiled configurations at the tip samples and the joint-space samples equal ArmChecks.motion_configs
    and motion_samples (same branch, same count) within the inverse kinematics' tolerance."""
    (chain, rmap, tree, held), (port, length, ref, step, c), _ = checks._kernel_args()
    rng = np.random.default_rng(11)
    seen = 0
    for _ in range(40):
        a = LO + rng.random(3) * (HI - LO)
        b = a + rng.normal(size=3) * 0.015
        Q = checks.motion_configs(a, b)
        st, S, _, _ = arm_motion(chain, rmap, tree, held._replace(radius=held.radius[:0], cap_start=held.cap_start[:1]),
                                 a, b, port, length, ref, step, c)
        if Q is None:
            assert st == UNREACHABLE
            continue
        seen += 1
        ref_S = motion_samples(checks.geo, Q, c)
        assert st == CLEAR and S.shape == ref_S.shape
        assert np.allclose(S, ref_S, rtol=0, atol=1e-8)
    assert seen > 20


@pytest.mark.slow
def test_state_decisions_as_the_python_check_and_coal_distance(checks):
    """10,000 random tips: the compiled check answers as the Python one (pinocchio's placements, coal's
    collision test on every pair whose bounding spheres come within the clearance); on every tenth, as coal's
    exact distance says (kept iff the configuration exists and the distance is at least the clearance)."""
    rng = np.random.default_rng(2024)
    tips = LO + rng.random((10_000, 3)) * (HI - LO)
    answers = []
    for i, t in enumerate(tips):
        new = checks.point_ok(*t)
        assert new == checks.point_ok_exact(*t), t.tolist()
        answers.append(new)
        if i % 10 == 0:
            q = checks.config(t)
            if q is None:
                assert not new
                continue
            d = clearance_to_held(checks.geo, q, checks.held, below=CLEARANCE + 1e-3)
            if abs(d - CLEARANCE) > 1e-9:
                assert new == (d >= CLEARANCE), (t.tolist(), d)
    assert 1000 < sum(answers) < 9000  # both answers met often


@pytest.mark.slow
def test_motion_decisions_as_the_python_check(checks):
    """Random straight motions of up to 3 cm: the compiled motion check answers as the Python one (every
    joint-space sample, coal's collision test); every broad-phase outcome is met."""
    rng = np.random.default_rng(77)
    seen = set()
    (chain, rmap, tree, held), (port, length, ref, step, c), _ = checks._kernel_args()
    answers = []
    for _ in range(240):
        a = LO + rng.random(3) * (HI - LO)
        d = rng.normal(size=3)
        b = a + d / np.linalg.norm(d) * 0.03 * rng.random()
        seen.add(int(arm_motion(chain, rmap, tree, held, a, b, port, length, ref, step, c)[0]))
        new = checks.motion_ok(*a, *b)
        assert new == checks.motion_ok_exact(*a, *b), (a.tolist(), b.tolist())
        answers.append(new)
    assert {CLEAR, WITHIN, UNDECIDED} <= seen and 0.2 < np.mean(answers) < 0.9


def test_checks_pickle_and_the_flag_selects_the_python_check(checks):
    checks.point_ok(-0.05, 0.0, 0.3)
    again = pickle.loads(pickle.dumps(checks))
    assert "_kargs" not in again.__dict__
    t = (-0.08, 0.0, 0.35)
    assert again.point_ok(*t) == checks.point_ok(*t)
    slow = pickle.loads(pickle.dumps(checks))
    slow.compiled = False
    calls = []
    slow.point_ok_exact = lambda *p: calls.append(p) or True
    assert slow.point_ok(*t) and calls == [t]
