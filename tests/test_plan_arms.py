"""Planning with the arms outside the body ([setup] arm_clearance; errplan.planning.arm_checks).

Two UR5s (example-robot-data) hold instruments through ports 14 cm apart; the right one waits at rest.
The left instrument's query goes straight up past the place where its wrist links would swing within
``arm_clearance`` of the right arm's: the straight line breaks the clearance, the plan keeps it. The plan
is checked by an independent sampler: tips every 0.25 mm along the planned path, the configuration at
each found from scratch by scipy's least squares on a fresh pinocchio model of the URDF (continued from
the previous tip), and the distance between the arms measured by dense points on the URDF's collision
meshes (trimesh, a k-d tree; tests/test_arm_collision.py's method: never below the true distance, at
most 2 H / sqrt(3) above it)."""
from __future__ import annotations

import json
import math

import numpy as np
import pinocchio as pin
import pytest
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from conftest import SCENARIOS, assert_refused, to_toml
from errplan import api, packages
from errplan.models import arm_model
from errplan.anatomy import setup as geo
from errplan.cli import main

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore

UR5 = "package://ur_description/urdf/ur5_joint_limited_robot.urdf"
JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint"]
CLEARANCE = 0.035  # m, [setup] arm_clearance
START, GOAL = [-0.08, 0.0, 0.29], [-0.08, 0.0, 0.41]


def setup_doc() -> dict:
    """The bundled triad's tables with two UR5s, no anatomy but the held shafts, an endoscope that sees
    the task region, and one left query (see the module docstring)."""
    doc = tomllib.loads((SCENARIOS / "abdomen_triad.toml").read_text())
    doc["anatomy"] = {"clearance": 0.004}
    doc.pop("tolerance")
    for a, sx, rest in zip(doc["arm"], (-1, 1), ([-0.04, 0.02, 0.31], [0.07, 0.06, 0.31])):
        a["robot"] = {"urdf": UR5, "joints": JOINTS, "wrist": "wrist_1_link", "base_position": [sx * 0.5, 0.0, -0.05]}
        a["instrument"] = {"length": 0.30}
        a["rest"] = rest
        a["port"] = {"estimate": [sx * 0.07, 0.0, 0.17], "position": [sx * 0.07 + 0.002, 0.001, 0.171]}
    doc["endoscope"].update(port={"estimate": [-0.06, -0.08, 0.18], "position": [-0.06, -0.08, 0.18]},
                            look_at=[-0.06, 0.0, 0.35], depth=[0.02, 0.25])
    doc["setup"]["arm_clearance"] = CLEARANCE
    doc["fields"] = {"resolution": 0.008, "region": {"x": [-0.11, 0.0], "y": [-0.04, 0.04], "z": [0.27, 0.43]}}
    doc["query"] = [{"name": "up past the right arm", "arm": "left", "start": START, "goal": GOAL}]
    return doc


# ----------------------------------------------------------------------------- the independent sampler
H = 0.004  # m, edge length of the dense surface points (tests/test_arm_collision.py's surfaces_of)
VOXEL = 0.002  # m: of those points one per cube of this side is kept (points on the surfaces, so the distance
#                    is still never below the true one)


class FreshArm:
    """A UR5 of the setup from a fresh pinocchio model of its URDF (no errplan code): the wrist by forward
    kinematics, the configuration at a tip by scipy's least squares, the collision meshes as dense points."""

    def __init__(self, robot: dict, port, length: float, surfaces):
        self.path = str(packages.resolve_package_uri(robot["urdf"]))
        self.model = pin.buildModelFromUrdf(self.path)
        self.data = self.model.createData()
        self.base = np.asarray(robot["base_position"], float)  # base_rpy 0
        self.idx = [self.model.joints[self.model.getJointId(j)].idx_q for j in JOINTS]
        self.lo = self.model.lowerPositionLimit[self.idx]
        self.hi = self.model.upperPositionLimit[self.idx]
        self.wrist = self.model.getFrameId("wrist_1_link")
        self.port, self.length = np.asarray(port, float), float(length)
        self.parts = []  # (link, origin, points thinned to one per VOXEL cube, their centre and radius)
        for link, O, _, fine in surfaces:
            _, keep = np.unique(np.floor(fine / VOXEL).astype(np.int64), axis=0, return_index=True)
            P = fine[np.sort(keep)]
            c = 0.5 * (P.min(axis=0) + P.max(axis=0))
            self.parts.append((link, O, P, c, float(np.max(np.linalg.norm(P - c, axis=1)))))

    def _q(self, q3):
        q = pin.neutral(self.model)
        q[self.idx] = q3
        return q

    def fk(self, q3) -> np.ndarray:
        pin.framesForwardKinematics(self.model, self.data, self._q(q3))
        return self.base + self.data.oMf[self.wrist].translation

    def at_tip(self, t, x0) -> np.ndarray:
        d = np.asarray(t, float) - self.port
        w = t - self.length * d / np.linalg.norm(d)
        r = least_squares(lambda q: self.fk(q) - w, np.clip(x0, self.lo, self.hi), bounds=(self.lo, self.hi),
                          xtol=1e-14, ftol=1e-14, gtol=1e-14)
        assert np.linalg.norm(self.fk(r.x) - w) < 1e-7, (t, r.x)
        return r.x

    def links(self, q3) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per collision element: its placed world transform (4, 4) and local dense points."""
        pin.framesForwardKinematics(self.model, self.data, self._q(q3))
        out = []
        for link, O, P, c, r in self.parts:
            M = self.data.oMf[self.model.getFrameId(link)].homogeneous @ O
            M[:3, 3] += self.base
            out.append((M, P, c, r))
        return out


class HeldPoints:
    """The held arm's dense points per element, a k-d tree and a bounding sphere each (built once)."""

    def __init__(self, links):
        self.parts = []
        for M, P, c, r in links:
            self.parts.append((cKDTree(P @ M[:3, :3].T + M[:3, 3]), M[:3, :3] @ c + M[:3, 3], r))

    def distance(self, links, below: float = math.inf) -> float:
        """Smallest point-to-point distance from the moving arm's elements, or ``below`` when that is smaller
        (then exactly ``below``): a pair whose spheres (exact for the point sets) lie farther apart than the
        best so far is skipped, and so is a moving point farther than that from the held element's sphere."""
        best = below
        moving = [(M, P, M[:3, :3] @ c + M[:3, 3], r) for M, P, c, r in links]
        pairs = sorted((np.linalg.norm(ca - cb) - ra - rb, i, j) for i, (_, _, ca, ra) in enumerate(moving)
                       for j, (_, cb, rb) in enumerate(self.parts))
        placed = {}
        for gap, i, j in pairs[:3]:  # a first upper bound from a few points of the nearest pairs
            M, P = moving[i][:2]
            best = min(best, float(self.parts[j][0].query(P[::50] @ M[:3, :3].T + M[:3, 3])[0].min()))
        for gap, i, j in pairs:
            if gap >= best:
                break
            if i not in placed:
                M, fine = moving[i][:2]
                placed[i] = fine @ M[:3, :3].T + M[:3, 3]
            tree, cb, rb = self.parts[j]
            P = placed[i]
            P = P[np.einsum("ij,ij->i", P - cb, P - cb) < (best + rb) ** 2]  # the others lie >= best away
            if len(P):
                best = min(best, float(tree.query(P, distance_upper_bound=best)[0].min()))
        return best


def arm_distance(st, tips) -> tuple[float, int]:
    """Over the tips (k, 3) of the left arm: the smallest dense-point distance between the left arm
    (configuration from the previous tip's, least squares) and the right arm held at its rest, and its tip's
    index. Exact: every tip's distance is measured, only below the smallest so far (a first pass over every
    16th tip finds a small one early, so that most pairs of elements are skipped)."""
    left, held, q0 = _independent(st)
    q = q0(tips[0])
    qs = []
    for t in tips:
        q = left.at_tip(t, q)
        qs.append(q)
    best, arg = math.inf, -1
    for i in list(range(0, len(qs), 16)) + [i for i in range(len(qs)) if i % 16]:
        d = held.distance(left.links(qs[i]), below=best)
        if d < best:
            best, arg = d, i
    return best, arg


_CACHE: dict = {}


def _independent(st):
    """The fresh arms (built once per test session), the held arm's points, and the starting guess of the
    least squares at a first tip: errplan's configuration there, only to pick the planner's branch."""
    if st.source not in _CACHE:
        from test_arm_collision import surfaces_of

        from errplan.planning.arm_checks import ArmChecks

        doc = setup_doc()
        surf = surfaces_of(packages.resolve_package_uri(UR5))
        left, right = (FreshArm(a["robot"], a["port"]["estimate"], a["instrument"]["length"], surf)
                       for a in doc["arm"])
        checks = ArmChecks.from_model(arm_model(st.moving("left")))
        q_right = right.at_tip(np.asarray(st.rest("right")), checks.held[0].q)
        _CACHE[st.source] = (left, HeldPoints(right.links(q_right)), checks.config)
    return _CACHE[st.source]


def _seg_seg(p0, p1, q0, q1) -> float:
    from test_setup import _seg_seg as f

    return f(p0, p1, q0, q1)


@pytest.mark.slow
def test_plan_keeps_the_arms_clear(tmp_path):
    """The straight line brings the arms within arm_clearance, the plan keeps it at every sample of the
    independent sampler; shafts clear at every 1 mm sample under every corner of both port boxes; every tip
    visible; every segment certified and every replay monotonic; the JSON's figures agree."""
    src = tmp_path / "s.toml"
    src.write_text(to_toml(setup_doc()), encoding="utf-8")
    out = tmp_path / "p.json"
    assert main(["-q", "plan", str(src), "--json", str(out), "--iterations", "300"]) == 0
    q = json.loads(out.read_text())["queries"][0]
    st = api.load_setup(src)
    # arms: every 0.25 mm of the planned path (the planner checks every 1 mm), none of the straight line's
    X = geo.resample(np.asarray(q["planned"]["path"]), 0.00025)
    d, i = arm_distance(st, X)
    assert d >= CLEARANCE - 1e-4, (d, X[i])
    slack = 2 * H / math.sqrt(3) + math.sqrt(3) * VOXEL  # how far above the true distance the points may lie
    assert q["min_arm_clearance"] >= CLEARANCE and abs(q["min_arm_clearance"] - d) <= slack
    direct, _ = arm_distance(st, geo.resample(np.array([START, GOAL]), 0.001))
    assert direct < CLEARANCE - 0.005  # the straight line would break it: the test can fail
    # shafts: every corner of the moving box against every corner of the held box (and the endoscope's)
    left, right, e = st.arm("left"), st.arm("right"), st.endoscope
    ci = geo.box_corners(left.port.estimate, left.uncertainty)
    cj = geo.box_corners(right.port.estimate, right.uncertainty)
    ce = geo.endoscope_box(e)
    u = np.asarray(e.look_at) - np.asarray(e.port.estimate)
    u /= np.linalg.norm(u)
    lens = np.asarray(e.port.estimate) + e.insertion * u
    rest = np.asarray(st.rest("right"))
    X1 = geo.resample(np.asarray(q["planned"]["path"]), 0.001)
    worst = min(min(_seg_seg(a, x, b, rest) for a in ci for b in cj) for x in X1)
    worst_e = min(min(_seg_seg(a, x, b, lens) for a in ci for b in ce) for x in X1)
    assert min(worst, worst_e) >= st.shaft_clearance
    assert q["min_shaft_clearance_path"] <= min(worst, worst_e) + 1e-9
    # the replays' shaft clearances: per run, their minimum, and the query's figure the smallest of all
    sim = q["simulation"]
    reps = [sim["planned"]["min_shaft_clearance"]] + [c["min_shaft_clearance"] for c in sim["corners"]["planned"]]
    assert len(reps) == 9 and q["min_shaft_clearance_replays"] == min(reps)
    assert q["min_shaft_clearance"] == min(q["min_shaft_clearance_path"], min(reps)) >= st.shaft_clearance
    # visible (cone and depth by plain vector algebra), certified, monotonic
    for x in X1:
        r = x - lens
        assert e.depth[0] <= r @ u <= e.depth[1] and r @ u >= math.cos(e.fov / 2) * np.linalg.norm(r) - 1e-12
    assert q["visible"] == 1.0
    assert all(g["certified"] for g in q["gains"])
    assert sim["planned"]["monotonic"] and sim["corners"]["planned_all_monotonic"]


def test_replay_shaft_clearance_against_segment_distances():
    """A run's shaft sweeps the triangles conv(port, t_k, t_k+1): its distance to a held hull is at most the
    distance of every shaft position port -> t_k (plain segment algebra) and at least that minus the
    farthest a point of a triangle lies from its two segments (half a step)."""
    from errplan.planning.setup_checks import run_shaft_clearance

    rng = np.random.default_rng(3)
    port = np.array([0.0, 0.0, 0.17])
    tips = np.array([0.0, 0.0, 0.32]) + np.cumsum(rng.normal(0, 0.002, (40, 3)), axis=0)
    held = np.array([[0.03, 0.01, 0.17], [0.02, 0.0, 0.31]])  # a held shaft through a point port: a segment
    d = run_shaft_clearance([held], port, tips)
    segs = min(_seg_seg(port, t, held[0], held[1]) for t in tips)
    step = float(np.max(np.linalg.norm(np.diff(tips, axis=0), axis=1)))
    assert segs - step / 2 - 1e-12 <= d <= segs + 1e-12
    assert run_shaft_clearance([], port, tips) is None


def test_arm_checks_on_a_urdf_without_collision_geometry_is_one_line_exit_2(tmp_path, capsys):
    from test_setup import triad_doc

    doc = triad_doc()  # two PHANToMs: their URDF has no collision geometry
    doc["setup"]["arm_clearance"] = 0.02
    assert_refused(tmp_path, capsys, doc, "plan", "[setup] arm_clearance", "no collision geometry")


def test_a_start_too_near_the_held_arm_is_one_line_exit_2(tmp_path, capsys):
    doc = setup_doc()
    doc["query"][0]["start"] = [-0.10, 0.0, 0.34]
    assert_refused(tmp_path, capsys, doc, "plan", "start", "arm 'right' held at rest", "[setup] arm_clearance = 35 mm")


def test_held_arm_checks_against_coal_distances():
    """within_held (coal's collision test with a security margin) against the distance, and
    clear_along_held (sphere skipping) against the minimum over every sample, on the setup's two UR5s."""
    from errplan.kinematics.urdf.collision import (clear_along, clear_along_held, clearance_to_held,
                                                  min_clearance_along, min_clearance_along_held, within_held)
    from errplan.planning.arm_checks import ArmChecks

    doc = setup_doc()
    st = api_setup(doc)
    ch = ArmChecks.from_model(arm_model(st.moving("left")))
    h = ch.held[0]
    rng = np.random.default_rng(7)
    lo, hi = np.array([-0.11, -0.04, 0.27]), np.array([0.0, 0.04, 0.43])
    seen = []
    for a, b in zip(lo + rng.random((10, 3)) * (hi - lo), lo + rng.random((10, 3)) * (hi - lo)):
        b = a + 0.2 * (b - a)  # moves of up to about 3 cm
        qa = ch.config(a)
        d = clearance_to_held(ch.geo, qa, ch.held)
        seen.append(d)
        for c in (0.01, CLEARANCE, 0.06):
            if abs(d - c) > 1e-6:
                assert within_held(ch.geo, qa, ch.held, c) == (d < c), (a, d, c)
        Q = ch.motion_configs(a, b)
        for c in (CLEARANCE,):
            full = min_clearance_along_held(ch.geo, Q, ch.held, c)
            assert full == pytest.approx(min_clearance_along(ch.geo, Q, h.geo, h.q, c), abs=1e-12)
            assert clear_along_held(ch.geo, Q, ch.held, c) == (full >= c) == clear_along(ch.geo, Q, h.geo, h.q, c)
    assert min(seen) < 0.02 and max(seen) > 0.06  # near and far apart both met


def api_setup(doc, tmp=None):
    import tempfile
    from pathlib import Path

    d = Path(tempfile.mkdtemp())
    p = d / "s.toml"
    p.write_text(to_toml(doc), encoding="utf-8")
    return api.load_setup(p)
