"""Setup placement (``kind = "setup_placement"``; docs/physics.md "Where the arms stand"): the bases read as
poses or a grid (the grid's rotation against scipy's), bad input one line and exit 2, the search over
(base, port) candidates against an independent brute force (random instances; on a UR5 setup, the triad
search run once per base pair on the scenario with its bases moved), the patient clearance against closed
forms, and the exported scenario planned."""
from __future__ import annotations

import dataclasses
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import SCENARIOS, assert_refused, to_toml
from errplan import api
from errplan.cli import main
from errplan.errors import ErrplanError
from errplan.scenario import setup_from_dict
from errplan.tolerance import triad as tr

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore

UR5_SETUP = SCENARIOS / "ur5_setup.toml"


def setup_doc() -> dict:
    doc = tomllib.loads(UR5_SETUP.read_text())
    doc["anatomy"]["body_wall"]["file"] = str((SCENARIOS / doc["anatomy"]["body_wall"]["file"]).resolve())
    return doc


def _matrix(rpy) -> np.ndarray:  # URDF: R = Rz(yaw) Ry(pitch) Rx(roll), i.e. extrinsic x, y, z
    return Rotation.from_euler("xyz", rpy).as_matrix()


# ----------------------------------------------------------------------------- reading the bases
def test_bases_as_poses_and_as_a_grid():
    st = setup_from_dict(setup_doc(), str(UR5_SETUP))
    (tol,) = st.triads
    assert tol.kind == "setup_placement" and st.patient_clearance == 0.02
    left, right = tol.options["bases"]["left"], tol.options["bases"]["right"]
    assert [p for p, _ in left] == [(-0.30, 0.0, -0.05), (-0.30, 0.0, 0.10), (-0.30, 0.0, 0.25)]
    # the grid: x in {0.30}, z in {-0.05, 0.10, 0.25} (hi inclusive), two yaws: 6 bases, y = 0
    assert len(right) == 6
    assert np.allclose(sorted({p for p, _ in right}), [(0.30, 0.0, z) for z in (-0.05, 0.10, 0.25)], atol=1e-12)
    own = st.arm("right").robot.base_rpy
    for yaw in (0.0, 0.3):
        want = Rotation.from_euler("y", yaw).as_matrix() @ _matrix(own)  # R_y(yaw) R(own rpy)
        got = [r for p, r in right if np.allclose(_matrix(r), want, atol=1e-12)]
        assert len(got) == 3, yaw
    # a grid whose spacing does not divide the range: lo, lo + h, ... up to hi
    doc = setup_doc()
    doc["tolerance"][0]["bases"]["right"] = {"y": 0.0, "x": [0.3, 0.5], "z": [0.0, 0.25], "spacing": 0.1,
                                             "yaw": [-math.pi, 1.0]}
    t = setup_from_dict(doc, str(UR5_SETUP)).triads[0]
    pts = sorted({tuple(np.round(p, 9)) for p, _ in t.options["bases"]["right"]})
    assert pts == sorted((round(x, 9), 0.0, round(z, 9)) for x in (0.3, 0.4, 0.5) for z in (0.0, 0.1, 0.2))
    assert len(t.options["bases"]["right"]) == 18
    # an arm without bases.<arm>: its own base only
    del doc["tolerance"][0]["bases"]["left"]
    t = setup_from_dict(doc, str(UR5_SETUP)).triads[0]
    own_l = st.arm("left").robot
    assert t.options["bases"]["left"] == ((tuple(own_l.base_position), tuple(own_l.base_rpy)),)


def _set(path, value):
    def f(doc):
        d = doc
        for k in path[:-1]:
            d = d[k]
        d[path[-1]] = value
    return f


BAD = {
    "empty-list": (_set(("tolerance", 0, "bases", "left"), []), ["bases.left", "non-empty list"]),
    "grid-no-point": (_set(("tolerance", 0, "bases", "right", "x"), [0.5, 0.3]), ["bases.right", "at least one point"]),
    "grid-no-yaw": (_set(("tolerance", 0, "bases", "right", "yaw"), []), ["bases.right", "at least one point"]),
    "yaw-outside": (_set(("tolerance", 0, "bases", "right", "yaw"), [0.0, 3.5]), ["bases.right.yaw = 3.5",
                                                                                 "[-pi, pi]"]),
    "spacing-zero": (_set(("tolerance", 0, "bases", "right", "spacing"), 0.0), ["bases.right.spacing", "> 0"]),
    "grid-unknown-key": (_set(("tolerance", 0, "bases", "right", "pitch"), 0.1), ["bases.right.pitch",
                                                                                   "unknown key"]),
    "pose-without-position": (_set(("tolerance", 0, "bases", "left"), [{"rpy": [0.0, 0.0, 0.0]}]),
                              ["bases.left[0].position", "missing"]),
    "bases-of-no-instrument": (_set(("tolerance", 0, "bases", "camera"), []), ["bases.camera", "unknown key"]),
    "bases-not-a-table": (_set(("tolerance", 0, "bases"), 3), ["bases", "base candidates per instrument arm"]),
    "patient-negative": (_set(("setup", "patient_clearance"), -0.01), ["[setup] patient_clearance", ">= 0"]),
    "base-inside-body": (_set(("tolerance", 0, "bases", "left"), [{"position": [0.0, 0.1, 0.78],
                                                                   "rpy": [-1.5707963267948966, 0.0, 0.0]}]),
                         ["bases.left[0].position", "inside the body wall"]),
}


@pytest.mark.parametrize("case", sorted(BAD), ids=sorted(BAD))
def test_bad_setup_placement_is_one_line_exit_2_nothing_written(case, tmp_path, capsys):
    change, words = BAD[case]
    doc = setup_doc()
    change(doc)
    assert_refused(tmp_path, capsys, doc, "tolerance", *words)


def test_export_without_a_setup_query_is_one_line_exit_2(tmp_path, capsys):
    doc = tomllib.loads((SCENARIOS / "ur5_triad.toml").read_text())
    doc["anatomy"]["body_wall"]["file"] = str((SCENARIOS / doc["anatomy"]["body_wall"]["file"]).resolve())
    p = tmp_path / "s.toml"
    p.write_text(to_toml(doc), encoding="utf-8")
    capsys.readouterr()
    rc = main(["-q", "tolerance", str(p), "--export-scenario", str(tmp_path / "out.toml")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "--export-scenario" in err and "setup_placement" in err, err
    assert sorted(x.name for x in tmp_path.iterdir()) == ["s.toml"]


# ----------------------------------------------------------------------------- the search on random instances
def _random_setup(rng, b1, b2, p1, p2, ne, T, keep, checks: bool) -> "tr.TriadData":
    """A random search instance whose instrument candidates are (base, port) pairs, base-major: the
    per-port arrays are the triad's, coverage and the arm/patient checks per candidate (coarse values: ties
    across bases on purpose)."""
    n1, n2 = b1 * p1, b2 * p2
    q = lambda *s: np.round(rng.random(s), 1)  # noqa: E731
    cov1, cov2 = rng.random((n1, T)) < 0.8, rng.random((n2, T)) < 0.8
    cov1[p1:2 * p1] = cov1[:p1] if b1 > 1 else cov1[p1:2 * p1]  # a second base covering as the first: ties
    vis = rng.random((ne, T)) < 0.85
    kw = {}
    if checks:
        arm = rng.random((n1, n2, T)) < 0.97
        kw = dict(arm=arm, arm_clearance=0.03, arm_done=np.ones((n1, n2), bool),
                  patient1=rng.random((n1, T)) < 0.95, patient2=rng.random((n2, T)) < 0.95,
                  patient_rest1=rng.random(n1) < 0.9, patient_rest2=rng.random(n2) < 0.9,
                  arm_rest=rng.random((n1, n2)) < 0.9)
    return tr.TriadData(cov1, cov2, vis, q(p1, p2, T) * 2, q(p1, ne, T), q(p2, ne, T), q(p1, ne, T) * 0.02,
                        q(p2, ne, T) * 0.02, q(p1, p2), q(p1, ne), q(p2, ne), 10.0, 0.26, 0.15, 0.004, keep,
                        port1=np.tile(np.arange(p1), b1), port2=np.tile(np.arange(p2), b2), **kw)


def _brute_setups(data, b1, b2, p1, p2) -> tuple[list, dict]:
    """Every (base, port) x (base, port) x endoscope port, scored and checked by the formulas of
    docs/physics.md (no TriadData index maps: bases and ports looped explicitly)."""
    out, rej = [], dict.fromkeys(tr.REJECTIONS, 0)
    ne = data.vis.shape[0]
    for (a1, j1), (a2, j2), e in itertools.product(itertools.product(range(b1), range(p1)),
                                                   itertools.product(range(b2), range(p2)), range(ne)):
        i1, i2 = a1 * p1 + j1, a2 * p2 + j2
        c = data.cov1[i1] & data.cov2[i2] & data.vis[e]
        S = np.mean(data.W * (1 - c) + data.mterm[j1, j2] + ((data.A1[j1, e] - data.A2[j2, e]) / data.a_tol) ** 2)
        sp = min(data.d12[j1, j2], data.d1e[j1, e], data.d2e[j2, e]) >= data.port_spacing
        sh = not np.any(c & ((data.D1[j1, e] < data.shaft_clearance) | (data.D2[j2, e] < data.shaft_clearance)))
        am = pt = True
        if data.arm is not None:
            am = not np.any(c & ~data.arm[i1, i2]) and bool(data.arm_rest[i1, i2])
            pt = (not np.any(c & ~(data.patient1[i1] & data.patient2[i2])) and bool(data.patient_rest1[i1])
                  and bool(data.patient_rest2[i2]))
        for k, ok in zip(tr.REJECTIONS, (sp, sh, am, pt)):
            rej[k] += not ok
        if sp and sh and am and pt:
            out.append((float(S), i1, i2, e))
    return sorted(out)[:data.keep], rej


def test_setup_search_equals_brute_force_on_random_instances(monkeypatch):
    monkeypatch.setattr(tr, "BLOCK_PAIRS", 3)  # many blocks and waves
    monkeypatch.setattr(tr, "WAVE_BLOCKS", 2)
    rng = np.random.default_rng(46)
    pruned_any = rejected_any = False
    for k in range(30):
        b1, b2, p1, p2 = (int(rng.integers(1, 4)) for _ in range(4))
        shape = (b1, b2, p1, p2)
        data = _random_setup(rng, *shape, int(rng.integers(1, 5)), int(rng.integers(3, 8)), int(rng.integers(1, 5)),
                             checks=k % 3 != 0)
        ref, rej = _brute_setups(data, *shape)
        got = tr.search(data, prune=True)
        full = tr.search(data, prune=False)
        assert [b[1:] for b in got["best"]] == [b[1:] for b in ref] == [b[1:] for b in full["best"]]
        assert np.allclose([b[0] for b in got["best"]], [b[0] for b in ref], atol=1e-12)
        assert full["rejected"] == rej
        assert got["evaluated"] + got["pruned"] == got["triads"] == full["evaluated"]
        pruned_any |= got["pruned"] > 0
        rejected_any |= rej["patient_clearance"] > 0 and rej["arm_clearance"] > 0
        for s, i1, i2, e in ref:  # the bound stays admissible with the bases
            assert s >= tr.lower_bound(data, i1, i2) - 1e-12
    assert pruned_any and rejected_any


# ----------------------------------------------------------------------------- the patient's clearance
def test_reach_map_moved_with_the_base_answers_as_the_arm():
    """A moved arm's map is its first base's translated: every wrist of a configuration within limits is
    reachable, and the answers are the first arm's at the points moved back."""
    from errplan.kinematics import arm_for
    from errplan.kinematics.urdf.reachmap import base_offset, share_translated

    st = api.load_setup(UR5_SETUP)
    sc = st.arm("right")
    a0 = arm_for(sc.robot)
    moved = tr._moved(sc, ((0.41, -0.02, 0.33), sc.robot.base_rpy)).robot
    a1 = type(a0).from_robot(moved)  # a fresh arm, no map yet
    assert np.allclose(base_offset(a1, a0), np.array(moved.base_position) - np.array(sc.robot.base_position))
    assert share_translated(a1, a0) and a1.map_info["translated_from"] == tuple(sc.robot.base_position)
    turned = type(a0).from_robot(tr._moved(sc, ((0.3, 0.0, 0.1), (-math.pi / 2, 0.2, 0.0))).robot)
    assert base_offset(turned, a0) is None and not share_translated(turned, a0)  # a rotation: its own map
    rng = np.random.default_rng(3)
    q = rng.uniform(a1.limits[:, 0], a1.limits[:, 1], (400, 3))
    q = q[a1.within_limits(q)]
    assert np.all(a1.reachable(a1.forward(q)))
    W = rng.uniform(-1.0, 1.0, (2000, 3)) + np.array(moved.base_position)
    delta = np.array(moved.base_position) - np.array(sc.robot.base_position)
    r = a1.reachable(W)
    assert np.array_equal(r, a0.reachable(W - delta)) and 0.1 < r.mean() < 0.9


def _spherical_links(tmp_path: Path) -> Path:
    """A two-joint arm whose links are a sphere and a box (primitives: closed-form distances)."""
    p = tmp_path / "prims.urdf"
    p.write_text("""<robot name="prims">
  <link name="base"/>
  <link name="l1"><collision><origin xyz="0.1 0 0.2"/><geometry><sphere radius="0.05"/></geometry></collision></link>
  <link name="l2"><collision><origin xyz="0.15 0 0"/><geometry><box size="0.1 0.04 0.04"/></geometry></collision></link>
  <link name="l3"/>
  <link name="tip"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0 0 0.3"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/><origin xyz="0.3 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="f" type="fixed"><parent link="l3"/><child link="tip"/><origin xyz="0.2 0 0"/></joint>
</robot>""")
    return p


def _box_distance(p, lo, hi) -> float:
    return float(np.linalg.norm(np.maximum(0.0, np.maximum(lo - p, p - hi))))


def test_patient_distances_against_closed_forms(tmp_path):
    """The sphere link's distance to a spherical body is |c - c_b| - r - r_b; to a box body (the convex
    hull of its corners) the point-to-box distance less r. patient_clear answers as the distances do."""
    from errplan.kinematics.urdf import UrdfArm
    from errplan.kinematics.urdf.collision import ArmCollision
    from errplan.kinematics.urdf.collision import BodySolid, link_distances, patient_clear, patient_clearances

    arm = UrdfArm.load(_spherical_links(tmp_path), ["j1", "j2", "j3"], "tip", base_position=[0.1, -0.2, 0.05],
                       base_rpy=[0.3, -0.2, 0.5])
    geo = ArmCollision.from_arm(arm)
    assert geo.names[0].startswith("l1")
    sphere_c, sphere_r = np.array([0.6, 0.1, 0.3]), 0.12
    lo, hi = np.array([-0.5, -0.4, -0.6]), np.array([-0.3, -0.1, -0.35])
    corners = np.array(list(itertools.product(*zip(lo, hi))))
    bodies = [BodySolid.ellipsoid(sphere_c, [sphere_r] * 3), BodySolid.hull(corners)]
    rng = np.random.default_rng(7)
    qs = rng.uniform(-2.5, 2.5, (25, 3))
    for body, dist in zip(bodies, (lambda c: float(np.linalg.norm(c - sphere_c)) - sphere_r,
                                   lambda c: _box_distance(c, lo, hi))):
        got = []
        for q in qs:
            P = geo.placements(q)
            c = P[0, :3, 3]  # the sphere link's centre, world
            d = link_distances(geo, q, body)
            assert d[0] == pytest.approx(dist(c) - 0.05, abs=1e-5)  # coal's GJK tolerance (about 1e-6 m)
            got.append(d.min())
        got = np.array(got)
        assert np.allclose(patient_clearances(geo, qs, body), got, atol=1e-12)
        g = np.sort(got)
        k = int(np.argmax(np.diff(g)))  # the widest gap between two distances: a threshold far from both
        assert g[k + 1] - g[k] > 1e-3
        for c in (0.0, 0.05, float(0.5 * (g[k] + g[k + 1]))):
            assert np.array_equal(patient_clear(geo, qs, body, c), got >= c), c
        assert 0 < np.sum(got >= 0.5 * (g[k] + g[k + 1])) < len(got)
    qn = qs.copy()
    qn[0, 1] = np.nan  # an arm that cannot stand there: no distance, not clear
    assert np.isnan(patient_clearances(geo, qn, bodies[0])[0]) and not patient_clear(geo, qn, bodies[0], 0.0)[0]
    # pickled as data (a worker rebuilds the coal shape)
    import pickle

    b2 = pickle.loads(pickle.dumps(bodies[1]))
    assert link_distances(geo, qs[3], b2) == pytest.approx(link_distances(geo, qs[3], bodies[1]), abs=1e-12)


@pytest.mark.slow
def test_patient_distances_of_the_ur5_against_surface_sampling():
    """The UR5's links (meshes) against the torso's convex hull: coal's distance within the sampling's
    bounds of the nearest sampled link point's distance to the hull (scipy's hull: the point's signed
    distance is the largest of its facet planes' when outside, exact to the nearest facet region below)."""
    from scipy.spatial import ConvexHull

    from errplan.kinematics import arm_for
    from errplan.kinematics.urdf.collision import ArmCollision
    from errplan.kinematics.urdf.collision import patient_clearances
    from errplan.tolerance.setup import body_solid
    import trimesh

    from test_arm_collision import sampled_distance, surfaces_of, world_points

    st = api.load_setup(UR5_SETUP)
    sc = st.arm("left")
    body, model = body_solid(sc)
    hull = ConvexHull(model.wall_surface[0])
    arm = arm_for(sc.robot)
    geo = ArmCollision.from_arm(arm)
    H = 0.01
    surf = surfaces_of(arm.urdf_path, arm.urdf_path.parent, h=H)
    hv, _ = trimesh.remesh.subdivide_to_size(hull.points, hull.simplices, max_edge=H)  # the hull's surface
    base = dict(base_position=list(arm.base_position), base_rpy=list(arm.base_rpy))
    qs = np.array([[0.2, -1.4, 1.1], [-0.3, -1.8, 1.6]])
    d = patient_clearances(geo, qs, body)
    for q, dq in zip(qs, d):
        pts = world_points(arm, base, q, surf)
        plane = pts @ hull.equations[:, :3].T + hull.equations[:, 3]  # signed distances to the facet planes
        lower = plane.max(axis=1)  # <= each point's distance to the hull
        assert np.all(lower > 0) and dq > 0  # these configurations stand outside the body
        # coal's distance: at least the planes' bound less the link sampling, at most the sampled surfaces'
        assert lower.min() - 2 * H / math.sqrt(3) - 1e-9 <= dq <= sampled_distance(pts, np.asarray(hv)) + 1e-9


# ----------------------------------------------------------------------------- against the triad per base pair
def _unseen(tmp_path: Path) -> Path:
    """The UR5 setup made different: an obstacle under the task region, two listed bases per arm (the base
    decides coverage and clearances), a coarser wall, no patient checks (the triad knows none)."""
    doc = setup_doc()
    del doc["setup"]["patient_clearance"]
    doc["anatomy"]["obstacle"] = [{"name": "vessel", "shape": "sphere", "center": [0.02, 0.03, 0.70],
                                   "radius": 0.015}]
    rpy = [-math.pi / 2, 0.0, 0.0]
    t = doc["tolerance"][0]
    t.update(spacing=0.12, bases={"left": [{"position": [-0.30, 0.0, -0.05], "rpy": rpy},
                                           {"position": [-0.36, 0.02, 0.25], "rpy": rpy}],
                                  "right": [{"position": [0.30, 0.0, 0.10], "rpy": [-math.pi / 2, 0.3, 0.0]},
                                            {"position": [0.34, 0.0, 0.25], "rpy": rpy}]})
    p = tmp_path / "unseen.toml"
    p.write_text(to_toml(doc), encoding="utf-8")
    return p


@pytest.mark.slow
def test_setup_equals_the_triad_brute_force_per_base_pair(tmp_path):
    """The setup search (pruned, and unpruned) against an independent brute force: for every base pair, the
    triad placement (itself equal to its brute force) of the scenario with the two arms' bases moved there,
    over the same port candidates, unpruned, every feasible triad kept; ties by the smallest arm clearance
    over the covered targets and at rest, the rest clearance by the arms put at rest independently."""
    from errplan.kinematics import arm_for
    from errplan.kinematics.urdf.collision import ArmCollision, arm_at_tip, arm_clearance
    from errplan.scenario import Tolerance
    from errplan.tolerance.setup import setup_placement

    st = api.load_setup(_unseen(tmp_path))
    (tol,) = st.triads
    a = setup_placement(st, tol)
    b = setup_placement(st, tol, prune=False)
    assert a["search"]["pruned"] > 0 and b["search"]["pruned"] == 0
    assert a["best"]["indices"] == b["best"]["indices"] and a["best"]["score"] == b["best"]["score"]
    n1, n2 = tol.options["instruments"]
    bases = tol.options["bases"]
    opts = {k: v for k, v in tol.options.items() if k != "bases"}
    opts["candidates"] = {r: tuple(map(tuple, a["candidates"][r])) for r in (n1, n2, "endoscope")}
    one = Tolerance("per base pair", "triad_placement", opts)
    ref, counts = [], dict.fromkeys(("port_spacing", "shaft_clearance", "arm_clearance"), 0)
    rejected_at_rest = 0
    K = 200  # the triads with their figures per base pair (every feasible one is listed below, by score)
    for (j1, p1), (j2, p2) in itertools.product(enumerate(bases[n1]), enumerate(bases[n2])):
        arms = [tr._moved(sc, p1 if n == n1 else p2) for n, sc in zip(st.arm_names, st.arms)]
        st2 = dataclasses.replace(st, arms=tuple(arms))
        t = tr.triad_placement(st2, one, prune=False, keep=K)
        for k in counts:
            counts[k] += t["rejected"][k]
        # every feasible triad of this base pair: the triad's own unpruned search again, on its arrays (the
        # unpruned run filled every pair's distances), with no limit; its first K are the triad's answer
        d = t["_arrays"]["data"]
        every = tr.search(dataclasses.replace(d, keep=10 ** 6), prune=False)
        shown = [t["best"]] + t["ranked"]
        assert [e["indices"] for e in shown] == [list(b[1:]) for b in every["best"][:K]]
        assert all(every["rejected"][k] == t["rejected"][k] for k in counts)
        figs = {tuple(e["indices"]): e for e in shown}  # the figures (clearances, coverage) of the first K
        cand = t["candidates"]
        listed = []
        for s, i1, i2, ie in every["best"]:
            q1, q2 = d.ports(i1, i2)
            listed.append(figs.get((i1, i2, ie)) or {"score": s, "ports": {n1: cand[n1][q1], n2: cand[n2][q2],
                                                                           "endoscope": cand["endoscope"][ie]}})
        geo = {n: ArmCollision.from_arm(arm_for(s.robot)) for n, s in zip(st.arm_names, arms)}
        at_rest = {}  # the rest clearance of an instrument port pair (triads differ by the endoscope's too)
        for e in listed:
            key = tuple(tuple(e["ports"][n]) for n in (n1, n2))
            if key not in at_rest:
                try:  # the arms at rest, each put there independently
                    qr = [arm_at_tip(geo[n].arm, st.rest(n), e["ports"][n], st.arm(n).instrument.length)
                          for n in (n1, n2)]
                    at_rest[key] = arm_clearance(geo[n1], qr[0], geo[n2], qr[1])
                except ErrplanError:  # an arm that cannot stand at rest: rejected
                    at_rest[key] = None
            rest = at_rest[key]
            if rest is None:
                rejected_at_rest += 1
                continue
            if rest < st.arm_clearance:  # the arms at rest too close: rejected (the triad does not know rest)
                rejected_at_rest += 1
                continue
            ref.append((e["score"], rest, (j1, j2), e))
    data = a["_arrays"]["data"]
    P = len(a["candidates"][n1])
    assert not np.array_equal(data.cov1[:P], data.cov1[P:2 * P])  # the base decides coverage of some port
    s0 = min(r[0] for r in ref)
    tied = [r for r in ref if r[0] <= s0 + 1e-9]
    assert all("arm_clearance_min" in r[3] for r in tied), "a tie beyond the first K of its base pair: raise K"
    best = max(tied, key=lambda r: min(r[1], math.inf if r[3]["arm_clearance_min"] is None
                                       else r[3]["arm_clearance_min"]))
    got = a["best"]
    assert got["score"] == pytest.approx(best[0], abs=1e-6)
    assert got["base_indices"] == list(best[2]) and got["ports"] == best[3]["ports"]
    assert got["bases"][n1]["position"] == list(bases[n1][best[2][0]][0])
    for k in ("coverage", "visible"):
        assert got[k] == pytest.approx(best[3][k], abs=1e-12)
    assert got["arm_clearance_min"] == pytest.approx(best[3]["arm_clearance_min"], abs=1e-5)
    assert got["shaft_clearance_min"] == pytest.approx(best[3]["shaft_clearance_min"], abs=1e-9)
    assert a["search"]["ties"] == len(tied)
    # the unpruned setup search rejects as the triads do, base pair by base pair (and more for the arms: at rest)
    assert rejected_at_rest > 0
    assert b["rejected"]["port_spacing"] == counts["port_spacing"]
    assert b["rejected"]["shaft_clearance"] == counts["shaft_clearance"]
    assert b["rejected"]["arm_clearance"] >= counts["arm_clearance"] + rejected_at_rest
    assert b["rejected"]["patient_clearance"] is None
    # the next best: the same scores as the brute force's next ones
    want = sorted(r[0] for r in ref)[:len(a["ranked"]) + 1]
    assert [x["score"] for x in [a["best"]] + a["ranked"]] == pytest.approx(want, abs=1e-9)
    # two worker processes: the same answer and counts
    c = setup_placement(st, tol, workers=2)
    assert c["best"]["indices"] == a["best"]["indices"] and c["rejected"] == a["rejected"]


# ----------------------------------------------------------------------------- the command, the export, the plan
@pytest.mark.slow
def test_tolerance_exports_the_best_setup_and_plan_certifies_it(tmp_path, capsys):
    """``errplan tolerance --json --record --export-scenario`` on a small setup, then ``errplan plan`` on the
    exported file: the chosen bases and ports are in it, and every query's planned path is certified."""
    doc = setup_doc()
    # the plan's fields on a coarser grid and a smaller counted planner budget: what is checked is that the
    # exported scenario plans and every planned segment is certified, not the plan's cost
    doc["fields"]["resolution"] = 0.02
    doc["planner"]["iterations"] = 300
    t = doc["tolerance"][0]
    rpy = [-math.pi / 2, 0.0, 0.0]
    t.update(spacing=0.12, bases={"left": [{"position": [-0.30, 0.0, -0.05], "rpy": rpy},
                                           {"position": [-0.30, 0.0, 0.25], "rpy": rpy}],
                                  "right": {"y": 0.0, "x": [0.30, 0.30], "z": [0.10, 0.25], "spacing": 0.15}})
    src = tmp_path / "s.toml"
    src.write_text(to_toml(doc), encoding="utf-8")
    out, rrd, exp = tmp_path / "t.json", tmp_path / "t.rrd", tmp_path / "best.toml"
    assert main(["-q", "tolerance", str(src), "--json", str(out), "--record", str(rrd), "--export-scenario",
                 str(exp), "--workers", "1"]) == 0
    text = capsys.readouterr().out
    assert "setup_placement" in text and "left base (mm, rpy)" in text and "patient checks: on" in text
    r = json.loads(out.read_text())["tolerances"][0]
    b = r["best"]
    assert r["kind"] == "setup_placement" and len(r["bases"]["left"]) == 2 and len(r["bases"]["right"]) == 2
    assert b["patient_clearance_min"] >= 0.02 and b["arm_clearance_min"] >= 0.03
    assert r["rejected"]["patient_clearance"] >= 0 and set(b["bases"]) == {"left", "right"}
    assert all(e["score"] >= b["score"] for e in r["ranked"])
    from test_recording_setup import _read

    _, cols = _read(rrd)
    base = "/world/triad/bases_and_triad_around_the_task_region"
    for n in ("left", "right"):  # the candidate bases, the chosen one, the arm drawn at it
        assert np.allclose(cols[f"{base}/bases/candidates/{n}"]["positions"][0],
                           [c["position"] for c in r["bases"][n]], atol=1e-6)
        assert np.allclose(cols[f"{base}/bases/chosen/{n}"]["positions"][0], [b["bases"][n]["position"]], atol=1e-6)
        assert any(k.startswith(f"/world/arms/{n}_at_rest/") for k in cols), sorted(cols)[:20]
    v = np.fmin(np.array(b["patient_clearance_targets"]["left"], float),
                np.array(b["patient_clearance_targets"]["right"], float))
    got = [x[0] if isinstance(x, list) else x for x in cols[f"{base}/patient_clearance"]["scalars"] if x is not None]
    assert np.allclose(got, 1000 * v[np.isfinite(v)], atol=1e-6) and min(got) >= 20.0 - 1e-6
    st = api.load_setup(exp)
    for n in ("left", "right"):
        sc = st.arm(n)
        assert list(sc.robot.base_position) == pytest.approx(b["bases"][n]["position"], abs=1e-12)
        assert list(sc.robot.base_rpy) == pytest.approx(b["bases"][n]["rpy"], abs=1e-12)
        assert list(sc.port.estimate) == pytest.approx(b["ports"][n], abs=1e-12)
    assert list(st.endoscope.port.estimate) == pytest.approx(b["ports"]["endoscope"], abs=1e-12)
    plan = tmp_path / "p.json"
    assert main(["-q", "plan", str(exp), "--json", str(plan), "--workers", "1"]) == 0
    qs = json.loads(plan.read_text())["queries"]
    assert {q["arm"] for q in qs} == {"left", "right"}
    for q in qs:
        assert q["planned"]["valid"] and q["gains"] and all(g["certified"] for g in q["gains"]), q["name"]
