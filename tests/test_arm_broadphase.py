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
from errplan.kinematics.urdf.broadphase import CLEAR, UNDECIDED, UNREACHABLE, WITHIN, arm_check, arm_motion, \
    cached_piece_bound, hull_bound, pack_shapes, piece_bound, piece_memory, place_objects, point_triangle, \
    segment_distance, segment_gap, triangle_distance, unpack_shapes
from errplan.kinematics.urdf.collision import ArmCollision, clearance_to_held, motion_samples, triangle_capsules
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
    partition its triangles; a piece's triangles for the narrow phase are its own (the same vertices)."""
    for geo in (checks.geo, panda):
        obj, A, B, R = geo.capsules()
        pieces = geo.pieces()
        tcap, tris, *_ = geo.piece_triangles()
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
                T = tris[tcap == k]
                if len(T):
                    assert len(T) == pieces[k].num_tris
                    P = np.unique(T.reshape(-1, 3), axis=0)
                    assert len(P) == len(V) and np.allclose(P, np.unique(V, axis=0))


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


def _triangle_points(T, n=40):
    """Points on the triangle T (3, 3): a barycentric grid of n + 1 steps a side (edges and corners included)."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    u, v = i[keep] / n, j[keep] / n
    return T[0] + u[:, None] * (T[1] - T[0]) + v[:, None] * (T[2] - T[0])


def test_triangle_distances_against_dense_sampling():
    """point_triangle and triangle_distance against the distances of dense grids of points on the triangles
    (never below the true distance, at most a grid cell above it); triangles that cross each other, meet at
    a point or lie in one plane; long thin triangles like the UR5 meshes'."""
    rng = np.random.default_rng(8)
    for trial in range(50):
        T = rng.normal(size=(3, 3)) * 0.05
        U = rng.normal(size=(3, 3)) * 0.05 + rng.normal(size=3) * 0.04
        if trial % 5 == 1:  # long and thin
            T[2] = T[0] + 0.98 * (T[1] - T[0]) + 1e-3 * rng.normal(size=3)
        if trial % 5 == 2:  # U pierces T: an edge of U through a point inside T
            x = T[0] + 0.3 * (T[1] - T[0]) + 0.3 * (T[2] - T[0])
            n = np.cross(T[1] - T[0], T[2] - T[0])
            U[0], U[1] = x + 0.02 * n / np.linalg.norm(n), x - 0.03 * n / np.linalg.norm(n)
        if trial % 5 == 3:  # coplanar
            U = T[0] + rng.normal(size=(3, 2)) @ np.stack([T[1] - T[0], T[2] - T[0]]) * 0.8
        X, Y = _triangle_points(T), _triangle_points(U)
        cell = max(np.max(np.linalg.norm(np.diff(T[[0, 1, 2, 0]], axis=0), axis=1)),
                   np.max(np.linalg.norm(np.diff(U[[0, 1, 2, 0]], axis=0), axis=1))) / 40
        brute = np.min(np.linalg.norm(X[:, None] - Y[None], axis=-1))
        d = triangle_distance(T, U)
        assert d <= brute + 1e-12 and brute <= d + 2 * cell, (trial, d, brute)
        if trial % 5 == 2:
            assert d <= 1e-15  # 0 up to the rounding of the crossing point
        for x in rng.normal(size=(3, 3)) * 0.05:
            px = point_triangle(*x, U)
            pb = np.min(np.linalg.norm(Y - x, axis=1))
            assert px <= pb + 1e-12 and pb <= px + cell


def test_triangle_capsules_hold_their_triangles():
    rng = np.random.default_rng(4)
    T = rng.normal(size=(200, 3, 3)) * 0.05
    T[::3, 2] = T[::3, 0] + 0.9 * (T[::3, 1] - T[::3, 0])  # degenerate: flat on an edge
    a, b, r = triangle_capsules(T)
    for k in range(len(T)):
        X = _triangle_points(T[k], 20)
        ab = b[k] - a[k]
        s = np.clip((X - a[k]) @ ab / max(ab @ ab, 1e-300), 0.0, 1.0)
        assert np.linalg.norm(X - (a[k] + s[:, None] * ab), axis=1).max() <= r[k]


def _near_piece_pairs(tree, held, P, c):
    """``(capsules' gap, moving object, moving capsule, held capsule, capsule axis ends in the world)`` of every
    pair of mesh pieces whose capsules come within 15 mm of the clearance ``c``, the moving arm placed by ``P``."""
    near = []
    for k in range(len(tree.cap_r)):
        g = int(np.searchsorted(tree.cap_start, k, side="right") - 1)
        M = P[g]
        wa, wb = M[:3, :3] @ tree.cap_a[k] + M[:3, 3], M[:3, :3] @ tree.cap_b[k] + M[:3, 3]
        for u in range(len(held.cap_r)):
            gap = segment_distance(*wa, *wb, *held.cap_a[u], *held.cap_b[u]) - tree.cap_r[k] - held.cap_r[u]
            if gap < c + 0.015 and tree.tri_start[k] < tree.tri_start[k + 1] and held.tri_start[u] < held.tri_start[u + 1]:
                near.append((gap, g, k, u, wa, wb))
    return near


def test_piece_distances_as_coal(checks):
    """The narrow phase on two mesh pieces, at random placements of the moving arm near the held one, against
    coal's exact distance between the same pieces: below the clearance (less 1 nm) it returns the distance of
    two of their triangles (never below coal's), else a lower bound of min(distance, top); either way the
    decision is coal's (many pairs within 10 mm of the clearance)."""
    import coal

    (chain, rmap, tree, held), (port, length, ref, step, c), objects = checks._kernel_args()
    pieces = checks.geo.pieces()
    rng = np.random.default_rng(21)
    P = np.empty((len(tree.gparent), 4, 4))
    seen = 0
    for _ in range(40):
        t = LO + rng.random(3) * (HI - LO)
        q = checks.config(t)
        if q is None:
            continue
        place_objects(tree, q, P)
        near = _near_piece_pairs(tree, held, P, c)
        for i in rng.permutation(len(near))[:12]:
            _, g, k, u, wa, wb = near[i]
            M = P[g]
            hg, hT = objects[u]
            T = coal.Transform3s(np.ascontiguousarray(M[:3, :3]), np.ascontiguousarray(M[:3, 3]))
            exact = coal.distance(pieces[k], T, hg, hT, coal.DistanceRequest(), coal.DistanceResult())
            for top in (c + 1e-9, 1.5 * c):  # a state's question, a motion's
                d = piece_bound(tree, held, M, k, u, wa, wb, top, c - 1e-9)
                if d < c - 1e-9:  # a witness: two triangles that close
                    assert exact <= d + 1e-12
                else:  # a lower bound of min(distance, top)
                    assert d <= min(exact, top) + 1e-9
                if abs(exact - c) > 1e-9:
                    assert (d < c) == (exact < c), (d, exact)
            seen += abs(exact - c) < 0.01
    assert seen > 15


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
    assert seen > 15


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
    joint-space sample, coal's collision test); both outcomes of the compiled phases are met (the UR5's meshes
    leave nothing to coal: UNDECIDED only for a primitive's piece)."""
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
    assert {CLEAR, WITHIN} <= seen and 0.2 < np.mean(answers) < 0.9


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


def test_piece_hulls_hold_their_pieces(checks, panda):
    """Each mesh piece's hull vertices are vertices of its triangles, and along any direction the largest
    projection of the piece's vertices is one of its hull vertices' (so a support bound on the hull vertices
    bounds the triangles); the held arms' hull vertices are their pieces' placed in the world."""
    rng = np.random.default_rng(5)
    n = rng.normal(size=(300, 3))
    n /= np.linalg.norm(n, axis=1)[:, None]
    fewer = 0
    for geo in (checks.geo, panda):
        tcap, tris, *_ = geo.piece_triangles()
        hcap, hull = geo.piece_hulls()
        assert np.array_equal(np.unique(hcap), np.unique(tcap))
        for k in np.unique(tcap):
            V = np.unique(tris[tcap == k].reshape(-1, 3), axis=0)
            Hk = hull[hcap == k]
            assert all(np.any(np.all(V == h, axis=1)) for h in Hk)
            assert np.max(np.abs((V @ n.T).max(axis=0) - (Hk @ n.T).max(axis=0))) <= 1e-12
            fewer += len(Hk) < len(V)
    assert fewer > 20  # hulls do drop vertices
    (_, _, tree, held), _, _ = checks._kernel_args()
    h = checks.held[0]
    obj = h.geo.capsules()[0]
    hcap, hull = h.geo.piece_hulls()
    for k in range(len(obj)):
        M = h.P[obj[k]]
        assert np.allclose(held.hull[held.hull_start[k]:held.hull_start[k + 1]], hull[hcap == k] @ M[:3, :3].T + M[:3, 3],
                           rtol=0, atol=1e-14)


def test_hull_bound_and_remembered_pieces_as_coal(checks):
    """At random placements of the moving arm near the held one, per pair of mesh pieces within 15 mm of the
    clearance, against coal's exact distance: hull_bound's lower bound never exceeds it and its upper bound
    never falls below it, and most pairs clear of the clearance by 2 mm are decided by the hulls alone; and
    cached_piece_bound with one memory shared by every pair and state (each state met twice, in two orders,
    so that the memory holds other states' witnesses and directions) decides as coal and returns, below the
    clearance, the distance of two triangles (never below coal's)."""
    import coal

    (chain, rmap, tree, held), (port, length, ref, step, c), objects = checks._kernel_args()
    pieces = checks.geo.pieces()
    rng = np.random.default_rng(33)
    P = np.empty((len(tree.gparent), 4, 4))
    cases = []
    while len(cases) < 60 or sum(x[-1] < c for x in cases) < 15:
        t = LO + rng.random(3) * (HI - LO)
        q = checks.config(t)
        if q is None:
            continue
        place_objects(tree, q, P)
        near = sorted(_near_piece_pairs(tree, held, P, c), key=lambda x: x[0])
        for i in [0, 1] + list(2 + rng.permutation(max(len(near) - 2, 0))[:2]):  # the nearest two, two others
            if i >= len(near):
                continue
            _, g, k, u, wa, wb = near[i]
            M = P[g].copy()
            hg, hT = objects[u]
            T = coal.Transform3s(np.ascontiguousarray(M[:3, :3]), np.ascontiguousarray(M[:3, 3]))
            exact = coal.distance(pieces[k], T, hg, hT, coal.DistanceRequest(), coal.DistanceResult())
            cases.append((M, k, u, wa, wb, exact))
    decided = far = 0
    for M, k, u, wa, wb, exact in cases:
        n = segment_gap(*held.cap_a[u], *held.cap_b[u], *wa, *wb)
        lo, *_, up = hull_bound(tree, held, M, k, u, *n, np.inf)
        assert lo <= exact + 1e-12 and up >= exact - 1e-12, (lo, exact, up)
        if exact > c + 0.002:
            far += 1
            decided += hull_bound(tree, held, M, k, u, *n, c + 1e-9)[0] >= c + 1e-9
    assert far > 10 and decided >= 0.7 * far, (decided, far)
    wit, axes = piece_memory(tree, held)
    seen = 0
    for order in (range(len(cases)), reversed(range(len(cases)))):
        for i in order:
            M, k, u, wa, wb, exact = cases[i]
            d = cached_piece_bound(tree, held, M, k, u, wa, wb, c + 1e-9, c - 1e-9, wit[k, u], axes[k, u])
            if d < c - 1e-9:
                assert exact <= d + 1e-12
            else:
                assert d <= min(exact, c + 1e-9) + 1e-9
            if abs(exact - c) > 1e-9:
                assert (d < c) == (exact < c), (d, exact)
            seen += exact < c
    assert 10 < seen < 2 * len(cases) - 10  # both answers met


def test_packed_shapes_are_the_shapes_and_answer_alike(checks):
    """pack_shapes / unpack_shapes give back every array of the tree and the held shapes (dtype, shape,
    values), and arm_check (packed, with a memory) answers as arm_motion (unpacked, without one) on tips
    and motions."""
    (chain, rmap, tree, held), (port, length, ref, step, c), _ = checks._kernel_args()
    F, I = pack_shapes(tree, held)
    t2, h2 = unpack_shapes(F, I)
    for x, y in zip(tuple(tree) + tuple(held), tuple(t2) + tuple(h2)):
        assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y)
    wit, axes = piece_memory(tree, held)
    rng = np.random.default_rng(9)
    seen = set()
    for _ in range(60):
        a = LO + rng.random(3) * (HI - LO)
        b = a if rng.random() < 0.5 else a + rng.normal(size=3) * 0.01
        st, S, _, rows = arm_check(chain, rmap, F, I, a, b, port, length, ref, step, c, wit, axes)
        st0, S0, _, rows0 = arm_motion(chain, rmap, tree, held, a, b, port, length, ref, step, c)
        assert st == st0 and np.array_equal(S, S0) and np.array_equal(rows, rows0)
        seen.add(int(st))
    assert {CLEAR, WITHIN} <= seen
