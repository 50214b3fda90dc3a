"""Arms outside the body (errplan.kinematics.urdf.collision; docs/physics.md "Several instruments and the
endoscope", "Arms outside").

Two UR5s of example-robot-data face each other 1.5 m apart. coal's arm clearance is checked against an
independent distance: the same collision meshes read by trimesh from the URDF's own <collision> elements,
placed by pinocchio's link frames, the base pose and the collision origins written out here (no
GeometryModel), subdivided to edges of at most H and compared point to point with a k-d tree. Those points
lie on the surfaces, so that distance is never below the true one, and every surface point lies within
H/sqrt(3) of one of them, so it exceeds the true one by at most 2H/sqrt(3)."""
from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from scipy.spatial import cKDTree

from errplan import packages
from errplan.errors import ErrplanError
from errplan.kinematics.urdf import MapParams, UrdfArm
from errplan.kinematics.urdf.collision import (ArmCollision, arm_at_tip, arm_clearance, clear_along, closest_pair,
                                              min_clearance_along, motion_samples)

from arms import ARMS, ROOT

UR5 = "package://example-robot-data/robots/ur_description/urdf/ur5_robot.urdf"
JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint"]
BASE_A = dict(base_position=[0.0, 0.0, 0.0], base_rpy=[-math.pi / 2, 0.0, 0.0])      # z of the URDF up (y)
BASE_B = dict(base_position=[1.5, 0.0, 0.0], base_rpy=[-math.pi / 2, math.pi, 0.0])  # the same, turned to face a
H = 0.004  # edge length of the independent method's sampling (m)
CONFIGS = [([0.0, -0.3, 0.3], [0.0, 0.0, 0.0]), ([0.3, -0.5, 0.3], [0.0, 0.0, 0.0]),
           ([0.2, -0.4, 0.5], [-0.1, -0.2, 0.2]), ([0.0, -1.2, 1.0], [0.1, -1.0, 0.8])]


def ur5_path():
    path = packages.resolve_package_uri(UR5)
    assert path is not None, f"{UR5}: example-robot-data is a test dependency"
    return path


def load(**kw) -> UrdfArm:
    return UrdfArm.load(ur5_path(), JOINTS, "wrist_1_link", **kw)


@pytest.fixture(scope="module")
def arms():
    a, b = load(**BASE_A), load(**BASE_B)
    return a, b, ArmCollision.from_arm(a), ArmCollision.from_arm(b)


# ----------------------------------------------------------------------------- the independent distance
def rpy(r, p, y):
    """R = Rz(y) Ry(p) Rx(r), the URDF convention, written out."""
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def pose(xyz, r) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = rpy(*r)
    M[:3, 3] = xyz
    return M


def _floats(elem, key, default="0 0 0"):
    return [float(x) for x in (elem.get(key, default) if elem is not None else default).split()]


@pytest.fixture(scope="module")
def surfaces():
    return surfaces_of(ur5_path())


def surfaces_of(urdf, base_dir=None, h=None):
    """Per collision element of the URDF: (link, origin (4, 4), vertices of the mesh (or primitive), the
    same surface's points subdivided to edges <= ``h`` (default H). Meshes by package:// URI or relative to
    ``base_dir``, scaled as the URDF says; boxes, cylinders and spheres as trimesh builds them."""
    import trimesh

    out = []
    for link in ET.parse(urdf).getroot().iter("link"):
        for c in link.findall("collision"):
            o = c.find("origin")
            O = pose(_floats(o, "xyz"), _floats(o, "rpy"))
            g = c.find("geometry")[0]
            if g.tag == "mesh":
                uri = g.get("filename")
                path = packages.resolve_package_uri(uri) if uri.startswith("package://") else Path(base_dir) / uri
                m = trimesh.load(str(path), force="mesh")
                m.apply_scale(_floats(g, "scale", "1 1 1"))
            elif g.tag == "box":
                m = trimesh.creation.box(extents=_floats(g, "size"))
            elif g.tag == "cylinder":
                m = trimesh.creation.cylinder(radius=float(g.get("radius")), height=float(g.get("length")), sections=48)
            else:
                assert g.tag == "sphere", g.tag
                m = trimesh.creation.icosphere(subdivisions=4, radius=float(g.get("radius")))
            v, _ = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=h or H)
            out.append((link.get("name"), O, np.asarray(m.vertices, float), np.unique(np.asarray(v), axis=0)))
    return out


def world_points(arm: UrdfArm, base: dict, q, surfaces, dense: bool = True) -> np.ndarray:
    data = arm.model.createData()
    pin.framesForwardKinematics(arm.model, data, arm.pinocchio_configuration(np.asarray(q, float)))
    B = pose(base["base_position"], base["base_rpy"])
    pts = []
    for name, O, verts, fine in surfaces:
        M = B @ data.oMf[arm.model.getFrameId(name)].homogeneous @ O
        v = fine if dense else verts
        pts.append(v @ M[:3, :3].T + M[:3, 3])
    return np.concatenate(pts)


def sampled_distance(Pa: np.ndarray, Pb: np.ndarray) -> float:
    """Smallest point-to-point distance between two point sets (a k-d tree; the query limited to the
    points of a within a first upper bound of b's bounding box)."""
    tree = cKDTree(Pb)
    upper = float(tree.query(Pa[::97])[0].min())
    lo, hi = Pb.min(axis=0) - upper, Pb.max(axis=0) + upper
    near = Pa[np.all((Pa >= lo) & (Pa <= hi), axis=1)]
    d = tree.query(near, distance_upper_bound=upper * (1 + 1e-9) + 1e-12)[0]
    return min(upper, float(d.min())) if len(d) else upper


# ----------------------------------------------------------------------------- coal against sampling
def test_coal_clearance_matches_dense_surface_sampling(arms, surfaces):
    a, b, A, B = arms
    seen = []
    for qa, qb in CONFIGS:
        d = arm_clearance(A, qa, B, qb)
        ind = sampled_distance(world_points(a, BASE_A, qa, surfaces), world_points(b, BASE_B, qb, surfaces))
        assert d > 0.0
        assert d <= ind + 1e-9, (qa, qb, d, ind)                       # never above the sampled distance
        assert ind - d <= 2 * H / math.sqrt(3) + 1e-9, (qa, qb, d, ind)  # within the sampling resolution
        seen.append(d)
    assert min(seen) < 0.01 and max(seen) > 0.2  # near contact and far apart both checked


@pytest.mark.slow
def test_ur5_against_a_panda_with_a_held_joint(arms, surfaces):
    """A second setup: the UR5 against a Panda (collision origins off the link frames, boxes on the
    fingers, joint 3 held at 0.3 rad) 1.2 m away, facing it; and the motion bound of that Panda."""
    a, _, A, _ = arms
    spec = ARMS["panda"]
    base = dict(base_position=[1.2, 0.0, 0.0], base_rpy=[-math.pi / 2, math.pi, 0.0])
    panda = UrdfArm.load(packages.resolve_package_uri(spec["urdf"]), spec["joints"], spec["wrist"],
                         fixed_joints=spec["fixed_joints"], **base)
    P = ArmCollision.from_arm(panda)
    psurf = surfaces_of(panda.urdf_path)
    assert any(n.startswith("panda_leftfinger") for n in P.names)
    seen = []
    for qa, qp in (([0.0, -0.5, 0.5], [0.0, 0.5, -1.5]), ([0.1, -0.4, 0.4], [0.2, 1.0, -1.0])):
        d = arm_clearance(A, qa, P, qp)
        ind = sampled_distance(world_points(a, BASE_A, qa, surfaces), world_points(panda, base, qp, psurf))
        assert d <= ind + 1e-9 and ind - d <= 2 * H / math.sqrt(3) + 1e-9, (qa, qp, d, ind)
        seen.append(d)
    assert min(seen) > 0.0
    rng = np.random.default_rng(7)
    for _ in range(10):
        q, dq = rng.uniform(-1.5, 1.5, 3), rng.normal(scale=0.05, size=3)
        P0 = world_points(panda, base, q, psurf, dense=False)
        P1 = world_points(panda, base, q + dq, psurf, dense=False)
        assert np.linalg.norm(P1 - P0, axis=-1).max() <= P.motion_bound(dq) + 1e-12


def test_closest_points_lie_on_the_arms_and_give_the_distance(arms, surfaces):
    a, b, A, B = arms
    qa, qb = CONFIGS[0]
    c = closest_pair(A, qa, B, qb)
    assert np.linalg.norm(c.point_a - c.point_b) == pytest.approx(c.distance, abs=1e-9)
    for arm, base, q, pt in ((a, BASE_A, qa, c.point_a), (b, BASE_B, qb, c.point_b)):
        P = world_points(arm, base, q, surfaces)
        assert cKDTree(P).query(pt)[0] <= H / math.sqrt(3) + 1e-9


def test_touching_and_overlapping_arms_give_nonpositive_clearance(arms, surfaces):
    a, b, A, B = arms
    qa, qb = CONFIGS[0]
    c = closest_pair(A, qa, B, qb)
    gap = c.point_a - c.point_b  # moving arm b by this brings its nearest point onto a's
    for s, expect in ((0.9, "clear"), (1.0, "touch"), (1.02, "overlap")):
        base = dict(BASE_B, base_position=list(np.asarray(BASE_B["base_position"]) + s * gap))
        bs = load(**base)
        d = arm_clearance(A, qa, ArmCollision.from_arm(bs), qb)
        if expect == "clear":
            assert 0.0 < d <= 0.1 * c.distance + 1e-9
            ind = sampled_distance(world_points(a, BASE_A, qa, surfaces), world_points(bs, base, qb, surfaces))
            assert d <= ind + 1e-9 and ind - d <= 2 * H / math.sqrt(3) + 1e-9
        elif expect == "touch":
            assert d <= 1e-9
        else:
            assert d <= 0.0
    # the same configuration for both arms at the same base: every link inside the other
    assert arm_clearance(A, qa, A, qa) <= 0.0


# ----------------------------------------------------------------------------- along a motion
def test_sampler_finds_a_collision_the_endpoints_miss(arms):
    a, b, A, B = arms
    mid = np.array([0.0, -0.15, 0.15])
    qs = np.array([mid - [0.4, 0, 0], mid + [0.4, 0, 0]])
    qb = np.zeros(3)
    ends = [arm_clearance(A, q, B, qb) for q in qs]
    assert min(ends) > 0.05                           # both endpoints well clear
    assert min_clearance_along(A, qs, B, qb, 0.01) <= 0.0
    assert arm_clearance(A, mid, B, qb) <= 0.0        # it is real: the middle of the sweep collides
    # stop_below returns at the first sample below it
    assert min_clearance_along(A, qs, B, qb, 0.01, stop_below=0.03) < 0.03


def test_samples_keep_every_link_point_within_half_the_clearance(arms, surfaces):
    """Between consecutive samples no vertex of any collision mesh (placed here by pinocchio's frames,
    not by the bound) moves more than clearance/2; a rigid motion moves no point of a mesh farther
    than its farthest-moving vertex. And a brute force along the motion is never below the sampler's
    minimum minus clearance/2."""
    a, b, A, B = arms
    rng = np.random.default_rng(3)
    clearance = 0.02
    for _ in range(3):
        qs = rng.uniform(-1.0, 1.0, size=(3, 3))
        S = motion_samples(A, qs, clearance)
        assert np.allclose(S[0], qs[0]) and np.allclose(S[-1], qs[-1])
        P = np.stack([world_points(a, BASE_A, q, surfaces, dense=False) for q in S])
        step = np.linalg.norm(np.diff(P, axis=0), axis=-1).max()
        assert step <= clearance / 2 + 1e-12
        assert step > clearance / 20  # the bound is not wildly loose
    qs = np.array([[-0.6, -0.15, 0.15], [0.5, -0.3, 0.2]])
    found = min_clearance_along(A, qs, B, np.zeros(3), clearance)
    brute = min(arm_clearance(A, q, B, np.zeros(3)) for q in np.linspace(qs[0], qs[1], 121))
    assert brute >= found - clearance / 2
    assert found <= min(arm_clearance(A, q, B, np.zeros(3)) for q in qs)  # its samples include the waypoints


def test_clear_along_answers_as_the_full_sampler(arms):
    """clear_along (skipping samples by the Lipschitz bound) against min_clearance_along over every sample."""
    _, _, A, B = arms
    rng = np.random.default_rng(2)
    answers = []
    for _ in range(5):
        qs, qb = rng.uniform(-1.0, 1.0, size=(2, 3)), rng.uniform(-0.5, 0.5, 3)
        for c in (0.1, 0.25):
            ok = clear_along(A, qs, B, qb, c)
            assert ok == (min_clearance_along(A, qs, B, qb, c) >= c)
            answers.append(ok)
    assert any(answers) and not all(answers)


def test_motion_bound_against_finite_motions(arms, surfaces):
    """The per-joint reach bound holds from random configurations for random joint steps."""
    a, _, A, _ = arms
    rng = np.random.default_rng(5)
    for _ in range(20):
        q = rng.uniform(-3.0, 3.0, 3)
        dq = rng.normal(scale=0.05, size=3)
        P0 = world_points(a, BASE_A, q, surfaces, dense=False)
        P1 = world_points(a, BASE_A, q + dq, surfaces, dense=False)
        assert np.linalg.norm(P1 - P0, axis=-1).max() <= A.motion_bound(dq) + 1e-12


# ----------------------------------------------------------------------------- errors and determinism
def test_urdf_without_collision_geometry_is_one_clear_error():
    urdf = ROOT / "scenarios" / "phantom15.urdf"
    arm = UrdfArm.load(urdf, ["waist", "shoulder", "elbow"], "wrist")
    with pytest.raises(ErrplanError, match=r"phantom15\.urdf has no collision geometry; arm checks need it"):
        ArmCollision.from_arm(arm)


def test_missing_mesh_names_its_uri(tmp_path):
    text = ur5_path().read_text().replace("collision/forearm.stl", "collision/no-such-forearm.stl")
    path = tmp_path / "ur5_broken.urdf"
    path.write_text(text)
    arm = UrdfArm.load(path, JOINTS, "wrist_1_link")
    with pytest.raises(ErrplanError, match=r"no-such-forearm\.stl.*forearm_link.*not found"):
        ArmCollision.from_arm(arm)
    (tmp_path / "bad.stl").write_text("not a mesh\n")  # there, but unreadable: the error names it
    path.write_text(text.replace("package://example-robot-data/robots/ur_description/meshes/ur5/collision/"
                                 "no-such-forearm.stl", "bad.stl"))
    with pytest.raises(ErrplanError, match=r"ur5_broken\.urdf: its collision geometry cannot be read .*bad\.stl"):
        ArmCollision.from_arm(UrdfArm.load(path, JOINTS, "wrist_1_link"))


def test_bad_arguments_are_errors(arms):
    _, _, A, B = arms
    with pytest.raises(ErrplanError, match="3 joint values"):
        arm_clearance(A, [0.0, 0.0], B, [0.0, 0.0, 0.0])
    with pytest.raises(ErrplanError, match="finite"):
        arm_clearance(A, [0.0, math.nan, 0.0], B, [0.0, 0.0, 0.0])
    for c in (0.0, -0.01, math.inf, math.nan, "1"):
        with pytest.raises(ErrplanError, match="clearance must be a positive number"):
            min_clearance_along(A, np.zeros((2, 3)), B, np.zeros(3), c)
    with pytest.raises(ErrplanError, match=r"shape \(m, 3\)"):
        min_clearance_along(A, np.zeros(3), B, np.zeros(3), 0.01)
    with pytest.raises(ErrplanError, match="geometry kind"):
        ArmCollision.from_arm(A.arm, kind="inertial")


def test_deterministic(arms):
    """Two builds, and a pickled copy (as a dask worker receives it), give the same numbers."""
    import pickle

    a, b, A, B = arms
    A2, B2 = ArmCollision.from_arm(a), pickle.loads(pickle.dumps(B))
    assert B2.names == B.names and np.array_equal(B2.base, B.base)
    for qa, qb in CONFIGS:
        assert arm_clearance(A, qa, B, qb) == arm_clearance(A2, qa, B2, qb)
    qs = np.array([[-0.6, -0.15, 0.15], [0.5, -0.3, 0.2]])
    assert min_clearance_along(A, qs, B, np.zeros(3), 0.02) == min_clearance_along(A2, qs, B2, np.zeros(3), 0.02)
    assert np.array_equal(A.reach, A2.reach)


# ----------------------------------------------------------------------------- the arm at a tip
@pytest.fixture(scope="module")
def narrow_arm(tmp_path_factory):
    """A UR5 with a narrow joint box and a coarse map: its reachability map builds in about a second,
    in a fresh cache directory (never the user's)."""
    old = os.environ.get("ERRPLAN_CACHE_DIR")
    os.environ["ERRPLAN_CACHE_DIR"] = str(tmp_path_factory.mktemp("errplan-cache"))
    try:
        arm = load(**BASE_A, joint_limits=[[-1.0, 1.0], [-2.5, -0.6], [0.3, 2.5]], map_params=MapParams(voxels=24))
        arm.reach_map()
        yield arm
    finally:
        if old is None:
            os.environ.pop("ERRPLAN_CACHE_DIR", None)
        else:
            os.environ["ERRPLAN_CACHE_DIR"] = old


def test_arm_at_tip_puts_the_wrist_on_the_rigid_shaft(narrow_arm):
    arm = narrow_arm
    L = 0.35
    for q0, direction in (([0.2, -1.5, 1.4], [0.3, -1.0, 0.2]), ([-0.4, -1.2, 1.0], [0.0, -1.0, -0.3])):
        w = arm.forward(np.array(q0))
        u = np.asarray(direction) / np.linalg.norm(direction)
        tip = w + L * u                      # a shaft of length L from the wrist along u
        port = w + 0.2 * u                   # the port somewhere on it
        q = arm_at_tip(arm, tip, port, L)
        assert arm.within_limits(q)
        assert np.allclose(arm.forward(q), tip - L * (tip - port) / np.linalg.norm(tip - port), atol=1e-9)
    with pytest.raises(ErrplanError, match="out of reach"):
        arm_at_tip(arm, [5.0, 5.0, 5.0], [5.0, 5.1, 5.0], L)
    with pytest.raises(ErrplanError, match="at the port"):
        arm_at_tip(arm, [0.3, 0.5, 0.1], [0.3, 0.5, 0.1], L)
    with pytest.raises(ErrplanError, match="shaft length"):
        arm_at_tip(arm, [0.3, 0.5, 0.1], [0.3, 0.6, 0.1], -0.1)


# ----------------------------------------------------------------------------- drawing the arms
def test_triangle_meshes_are_the_placed_collision_meshes(arms, surfaces):
    """Every vertex of every object drawn lies on a vertex of the same mesh placed here independently."""
    a, _, A, _ = arms
    q = np.array([0.3, -0.7, 0.9])
    data = a.model.createData()
    pin.framesForwardKinematics(a.model, data, a.pinocchio_configuration(q))
    Bm = pose(BASE_A["base_position"], BASE_A["base_rpy"])
    meshes = A.triangle_meshes(q)
    assert [m[0] for m in meshes] == list(A.names) and len(meshes) == len(surfaces) == 8
    for (name, v, f), (link, O, verts, _) in zip(meshes, surfaces):
        assert name.startswith(link)
        M = Bm @ data.oMf[a.model.getFrameId(link)].homogeneous @ O
        mine = verts @ M[:3, :3].T + M[:3, 3]
        assert cKDTree(mine).query(v)[0].max() < 1e-6, name
        assert f.min() >= 0 and f.max() < len(v) and len(f) >= 12


def test_recording_holds_every_object_of_both_arms(arms, tmp_path):
    import rerun.chunk as rrc

    from errplan.recording import sdk
    from errplan.recording.arms import log_arm_geometry

    _, _, A, B = arms
    path = tmp_path / "arms.rrd"
    logged = []

    def log(rec, rr):
        logged.extend(log_arm_geometry(rec, "world/arms/a", A, CONFIGS[0][0], color=(200, 80, 80)))
        logged.extend(log_arm_geometry(rec, "world/arms/b", B, CONFIGS[0][1], static=True))

    sdk.write(path, "errplan-test", "arms", None, log)
    visual = ArmCollision.from_arm(A.arm, kind="visual")  # the visual meshes draw too
    assert len(visual.names) == 7 and all(len(f) for _, _, f in visual.triangle_meshes(CONFIGS[0][0]))
    assert path.exists() and not path.with_name(path.name + ".part").exists()
    rows = {}
    for chunk in rrc.RrdReader(path).stream().to_chunks():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    want = {f"/world/arms/{arm}/{n}" for arm, geo in (("a", A), ("b", B)) for n in geo.names}
    assert want == {"/" + p for p in logged}
    assert want <= set(rows) and all(rows[e] == 1 for e in want)


def test_pruned_search_equals_every_pair(arms):
    """The sphere-pruned search against coal over all 64 pairs, no pruning (seeded configurations, some
    of them touching)."""
    import coal

    _, _, A, B = arms
    rng = np.random.default_rng(11)
    Q = np.concatenate([rng.uniform(-1.2, 1.2, size=(12, 2, 3)), [[[0.0, -0.15, 0.15], [0.0, 0.0, 0.0]]]])
    signs = []
    for qa, qb in Q:
        Pa, Pb = A.placements(qa), B.placements(qb)
        Ta = [coal.Transform3s(M[:3, :3], M[:3, 3]) for M in Pa]
        Tb = [coal.Transform3s(M[:3, :3], M[:3, 3]) for M in Pb]
        every = min(coal.distance(oa.geometry, ta, ob.geometry, tb, coal.DistanceRequest(), coal.DistanceResult())
                    for oa, ta in zip(A.geometry_model.geometryObjects, Ta)
                    for ob, tb in zip(B.geometry_model.geometryObjects, Tb))
        d = arm_clearance(A, qa, B, qb)
        if every > 0:
            assert d == every
        else:
            assert d <= 0
        signs.append(every > 0)
    assert any(signs) and not all(signs)
