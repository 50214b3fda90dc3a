"""Several instruments and the endoscope: ``[[arm]]`` scenarios read once into per-arm scenarios, the
setup's geometry (lens, visibility, angles, robust shaft-shaft clearance) against plain vector algebra
and a second distance method, and triad placement against an unpruned brute force."""
from __future__ import annotations

import copy
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from conftest import SCENARIOS, assert_refused, to_toml
from errplan import api
from errplan.anatomy import setup as geo
from errplan.cli import main
from errplan.errors import ScenarioError
from errplan.scenario import read_scenario, read_setup, setup_from_dict
from errplan.models import build_arm

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore

TRIAD = SCENARIOS / "abdomen_triad.toml"


def triad_doc() -> dict:
    """The bundled triad scenario as a document with absolute paths (URDFs, meshes)."""
    doc = tomllib.loads(TRIAD.read_text())
    for a in doc["arm"]:
        a["robot"]["urdf"] = str((SCENARIOS / a["robot"]["urdf"]).resolve())
    for o in doc["anatomy"].get("obstacle", []):
        if "file" in o:
            o["file"] = str((SCENARIOS / o["file"]).resolve())
    return doc


# ----------------------------------------------------------------------------- scenario
def test_one_instrument_scenario_is_the_one_arm_setup():
    for f in ("abdomen.toml", "beasley2004_bounded.toml", "ur5_port.toml"):
        sc = read_scenario(SCENARIOS / f)
        st = read_setup(SCENARIOS / f)
        assert not st.several and st.arm_names == ("arm",) and st.endoscope is None
        assert st.arm(None) == sc and st.arms == (sc,)
        with pytest.raises(ScenarioError, match="one instrument"):
            st.arm("left")


def test_triad_scenario_reads_into_per_arm_scenarios():
    st = api.load_setup(TRIAD)
    assert st.several and st.arm_names == ("left", "right")
    left, right = st.arm("left"), st.arm("right")
    assert left.dim == right.dim == 3
    assert left.robot.base_position != right.robot.base_position
    assert [q.name for q in left.queries] == ["left reach"] and [q.name for q in right.queries] == ["right reach"]
    assert left.anatomy == right.anatomy and left.fields == right.fields and left.planner == right.planner
    assert st.endoscope.fov == pytest.approx(1.22) and st.endoscope.depth == (0.02, 0.2)
    assert st.shaft_clearance == 0.008 and st.arm_clearance is None
    assert [t.kind for t in st.triads] == ["triad_placement"] and not left.tolerances
    assert st.rest("left") == (-0.05, 0.03, 0.32)
    with pytest.raises(ScenarioError, match="2 arms"):
        read_scenario(TRIAD)  # one arm at a time: --arm
    with pytest.raises(ScenarioError, match="--arm middle: expected one of the arms left, right"):
        st.arm("middle")


def _bad(doc_change) -> dict:
    doc = triad_doc()
    doc_change(doc)
    return doc


def _set(path, value):
    def f(doc):
        t = doc
        for k in path[:-1]:
            t = t[k]
        t[path[-1]] = value
    return f


def _del(path):
    def f(doc):
        t = doc
        for k in path[:-1]:
            t = t[k]
        del t[path[-1]]
    return f


#: the bad inputs of docs/interfaces.md's list (and a few more): change -> words the one line must hold
BAD = {
    "duplicate-arm-name": (_set(("arm", 1, "name"), "left"), ["[[arm]][1] name", "'left'", "used by no other"]),
    "query-without-arm": (_del(("query", 0, "arm")), ["[[query]][0] arm", "required when there are several arms"]),
    "query-unknown-arm": (_set(("query", 0, "arm"), "middle"), ["[[query]][0] arm", "'middle'", "unknown arm"]),
    "rest-unreachable": (_set(("arm", 0, "rest"), [-0.05, 0.03, 0.9]), ["'left' rest", "unreachable"]),
    "rest-not-clear": (_set(("arm", 1, "rest"), [0.018, -0.024, 0.37]), ["'right' rest", "not clear"]),
    "ports-too-close": (_set(("tolerance", 0, "port_spacing"), 0.2), ["apart", "port_spacing = 0.2"]),
    "endoscope-off-wall": (_set(("endoscope", "port"), {"estimate": [0.0, -0.06, 0.25], "position": [0.0, -0.06, 0.25]}),
                           ["[endoscope] port.estimate", "off the wall"]),
    "fov-zero": (_set(("endoscope", "fov"), 0.0), ["[endoscope] fov", "(0, pi)"]),
    "fov-pi": (_set(("endoscope", "fov"), 3.2), ["[endoscope] fov", "(0, pi)"]),
    "depth-decreasing": (_set(("endoscope", "depth"), [0.2, 0.02]), ["[endoscope] depth", "increasing"]),
    "depth-nan": (_set(("endoscope", "depth"), [float("nan"), 0.2]), ["[endoscope] depth", "finite"]),
    "both-robot-and-arms": (_set(("robot",), {"urdf": "x.urdf"}), ["[robot]", "beside [[arm]]"]),
    "arm-unknown-key": (_set(("arm", 0, "wheels"), 4), ["[[arm]][0] wheels", "unknown key"]),
    "arm-robot-unknown-key": (_set(("arm", 1, "robot", "wheels"), 4), ["[[arm]][1] (name 'right') robot.wheels",
                                                                       "unknown key"]),
    "arm-port-missing": (_del(("arm", 0, "port")), ["[[arm]][0] (name 'left') port", "missing"]),
    "setup-unknown-key": (_set(("setup", "gap"), 0.01), ["[setup] gap", "unknown key"]),
    "shaft-clearance-negative": (_set(("setup", "shaft_clearance"), -0.01), ["[setup] shaft_clearance", ">= 0"]),
    "triad-one-instrument": (_set(("tolerance", 0, "instruments"), ["left", "left"]), ["instruments", "two different"]),
    "triad-bad-candidates": (_set(("tolerance", 0, "candidates"), {"left": [[0.0, 0.0, 0.17]]}),
                             ["candidates.right", "missing"]),
    "triad-unknown-key": (_set(("tolerance", 0, "colour"), "red"), ["[[tolerance]][0] colour", "unknown key"]),
    "keep-visible-text": (_set(("endoscope", "keep_visible"), "yes"), ["keep_visible", "true or false"]),
    "endoscope-without-arms": (None, ["[endoscope]", "[[arm]]"]),
    "arm-checks-without-collision-geometry": (_set(("setup", "arm_clearance"), 0.02),
                                              ["[setup] arm_clearance", "no collision geometry"]),
}


@pytest.mark.parametrize("case", sorted(BAD), ids=sorted(BAD))
def test_bad_setup_is_one_line_exit_2_nothing_written(case, tmp_path, capsys):
    change, words = BAD[case]
    if change is None:  # an [endoscope] in a one-instrument scenario
        doc = tomllib.loads((SCENARIOS / "abdomen.toml").read_text())
        doc["robot"]["urdf"] = str((SCENARIOS / "phantom15.urdf").resolve())
        for o in doc["anatomy"]["obstacle"]:
            if "file" in o:
                o["file"] = str((SCENARIOS / o["file"]).resolve())
        doc["endoscope"] = triad_doc()["endoscope"]
    else:
        doc = _bad(change)
    assert_refused(tmp_path, capsys, doc, "tolerance", *words)


def test_unknown_key_names_the_key_not_the_whole_table(tmp_path):
    """Unknown top-level key holding every arm: the message names it and stays short."""
    doc = triad_doc()
    doc["arms"] = doc["arm"]
    with pytest.raises(ScenarioError) as e:
        setup_from_dict(doc, str(tmp_path / "s.toml"))
    msg = str(e.value)
    assert "arms = an array of 2 tables" in msg and "unknown key" in msg and len(msg) < 400, msg


def test_unknown_key_of_a_one_instrument_scenario_unchanged():
    doc = tomllib.loads((SCENARIOS / "beasley2004_port.toml").read_text())
    doc["port"]["positon"] = [0.0, 0.16]
    with pytest.raises(ScenarioError, match=r"\[port\] positon = \[0.0, 0.16\]: expected one of the keys"):
        setup_from_dict(doc)


# ----------------------------------------------------------------------------- geometry
def _angle(u, v) -> float:  # plain vector algebra
    u, v = np.asarray(u, float), np.asarray(v, float)
    return math.acos(max(-1.0, min(1.0, float(u @ v) / (np.linalg.norm(u) * np.linalg.norm(v)))))


def test_angles_by_plain_vector_algebra():
    rng = np.random.default_rng(3)
    for _ in range(50):
        t, p1, p2, pe, look = rng.normal(size=(5, 3))
        lens = geo.lens_of(pe, look, 0.3)
        u = (look - pe) / np.linalg.norm(look - pe)
        assert np.allclose(lens, pe + 0.3 * u)
        assert geo.manipulation_angle(t, p1, p2) == pytest.approx(_angle(t - p1, t - p2), abs=1e-9)
        assert geo.azimuth(t, p1, lens) == pytest.approx(_angle(t - p1, t - lens), abs=1e-9)
        # elevation: 90 deg less the angle between the shaft line and the axis
        a = _angle(t - p2, u)
        assert geo.elevation(t, p2, u) == pytest.approx(math.pi / 2 - min(a, math.pi - a), abs=1e-9)


def test_view_cone_and_depth():
    lens, axis = np.zeros(3), np.array([0.0, 0.0, 1.0])
    fov, depth = math.radians(60), (0.02, 0.2)
    pts = np.array([[0, 0, 0.1], [0, 0, 0.01], [0, 0, 0.25], [0.1 * math.tan(math.radians(29)), 0, 0.1],
                    [0.1 * math.tan(math.radians(31)), 0, 0.1], [0, 0, -0.1]])
    assert geo.in_view(pts, lens, axis, fov, depth).tolist() == [True, False, False, True, False, False]


def test_line_of_sight_blocked_by_an_obstacle():
    from errplan.anatomy import build
    from errplan.scenario import Anatomy, Obstacle

    m = build(Anatomy(0.0, (Obstacle("ball", "sphere", center=(0.0, 0.0, 0.1), radius=0.02),)), np.zeros((1, 3)))
    ok = geo.visible(np.array([[0, 0, 0.15], [0.05, 0, 0.15]]), np.zeros(3), np.array([0, 0, 1.0]), 1.5,
                     (0.0, 0.3), m)
    assert ok.tolist() == [False, True]


def _hull_distance_scipy(P, Q) -> float:
    """A second method: min |P^T a - Q^T b| over convex combinations a, b (SLSQP, several starts)."""
    from scipy.optimize import minimize

    n, m = len(P), len(Q)
    best = math.inf
    rng = np.random.default_rng(0)
    def f(x):
        r = x[:n] @ P - x[n:] @ Q
        return float(r @ r), np.concatenate([2 * P @ r, -2 * Q @ r])

    ea, eb = np.r_[np.ones(n), np.zeros(m)], np.r_[np.zeros(n), np.ones(m)]
    cons = [{"type": "eq", "fun": lambda x: ea @ x - 1, "jac": lambda x: ea},
            {"type": "eq", "fun": lambda x: eb @ x - 1, "jac": lambda x: eb}]
    for s in range(3):
        x0 = np.concatenate([rng.dirichlet(np.ones(n)), rng.dirichlet(np.ones(m))])
        r = minimize(f, x0, jac=True, bounds=[(0, 1)] * (n + m), constraints=cons, method="SLSQP",
                     options={"ftol": 1e-18, "maxiter": 1000})
        best = min(best, math.sqrt(max(r.fun, 0.0)))
    return best


def test_shaft_shaft_distance_against_scipy():
    rng = np.random.default_rng(7)
    box = np.array(list(itertools.product((-0.004, 0.004), repeat=3)))
    for _ in range(4):
        p1, p2 = rng.normal(scale=0.05, size=(2, 3)) + [[0, 0, 0.17]]
        a, b = rng.normal(scale=0.04, size=(2, 3)) + [[0, 0, 0.35]]
        P = geo.hull_points(p1 + box, a, b)
        Q = geo.hull_points(p2 + box, b + rng.normal(scale=0.03, size=3))
        d = geo.shaft_distance(P, Q)
        ref = _hull_distance_scipy(P, Q)
        assert d == pytest.approx(ref, abs=2e-6), (d, ref)
    # batched version equals the single one
    boxes = np.stack([p1 + box, p2 + box])
    tips = rng.normal(scale=0.04, size=(4, 3)) + [0, 0, 0.35]
    others = np.stack([geo.hull_points(p2 + box, b), geo.hull_points(p1 + box, a)])
    D = geo.target_hull_distances(boxes, tips, others)
    for i, j, k in itertools.product(range(2), range(2), range(4)):
        assert D[i, j, k] == pytest.approx(geo.shaft_distance(geo.hull_points(boxes[i], tips[k]), others[j]), abs=1e-12)


# ----------------------------------------------------------------------------- triad placement
from dataclasses import replace as _replace  # noqa: E402

from errplan.tolerance import triad as tr  # noqa: E402


def _random_data(rng, n1, n2, ne, T, keep) -> "tr.TriadData":
    """A random instance of the search (coverage, visibility, angles, distances; ties on purpose)."""
    cov1, cov2, vis = (rng.random((n, T)) < 0.8 for n in (n1, n2, ne))
    q = lambda *s: np.round(rng.random(s), 1)  # noqa: E731 - coarse values make ties
    return tr.TriadData(cov1, cov2, vis, q(n1, n2, T) * 2, q(n1, ne, T), q(n2, ne, T), q(n1, ne, T) * 0.02,
                        q(n2, ne, T) * 0.02, q(n1, n2), q(n1, ne), q(n2, ne), 10.0, 0.26, 0.15, 0.004, keep)


def _brute(data) -> list:
    out = []
    for i1, i2 in itertools.product(range(data.cov1.shape[0]), range(data.cov2.shape[0])):
        for e in range(data.vis.shape[0]):
            c = data.cov1[i1] & data.cov2[i2] & data.vis[e]
            S = np.mean(data.W * (1 - c) + data.mterm[i1, i2] + ((data.A1[i1, e] - data.A2[i2, e]) / data.a_tol) ** 2)
            ok = min(data.d12[i1, i2], data.d1e[i1, e], data.d2e[i2, e]) >= data.port_spacing and not np.any(
                c & ((data.D1[i1, e] < data.shaft_clearance) | (data.D2[i2, e] < data.shaft_clearance)))
            if ok:
                out.append((float(S), i1, i2, e))
    return sorted(out)[:data.keep]


def test_branch_and_bound_equals_brute_force_on_random_instances(monkeypatch):
    monkeypatch.setattr(tr, "BLOCK_PAIRS", 3)  # many blocks and waves
    monkeypatch.setattr(tr, "WAVE_BLOCKS", 2)
    rng = np.random.default_rng(11)
    pruned_any = False
    for _ in range(25):
        data = _random_data(rng, int(rng.integers(2, 7)), int(rng.integers(2, 7)), int(rng.integers(1, 6)),
                            int(rng.integers(3, 9)), int(rng.integers(1, 5)))
        ref = _brute(data)
        got = tr.search(data, prune=True)
        full = tr.search(data, prune=False)
        assert [b[1:] for b in got["best"]] == [b[1:] for b in ref] == [b[1:] for b in full["best"]]
        assert np.allclose([b[0] for b in got["best"]], [b[0] for b in ref])
        assert got["evaluated"] + got["pruned"] == got["triads"] == full["evaluated"]
        pruned_any |= got["pruned"] > 0
        # the bound is admissible: no triad scores below its pair's LB
        for s, i1, i2, e in ref:
            assert s >= tr.lower_bound(data, i1, i2) - 1e-12
    assert pruned_any


def _run(st, tol, **kw):
    return tr.triad_placement(st, tol, **kw)


def _check_figures(st, tol, r):
    """The best triad's figures recomputed independently: angles by plain vector algebra, coverage by
    the one-port wall placement, visibility by the cone's definition, the shaft clearance by SLSQP."""
    from errplan.tolerance.wall import wall_port_placement

    b = r["best"]
    n1, n2 = tol.get("instruments")
    p1, p2, pe = (np.asarray(b["ports"][k]) for k in (n1, n2, "endoscope"))
    X = r["_arrays"]["targets"]
    endo = st.endoscope
    u = (np.asarray(endo.look_at) - pe) / np.linalg.norm(np.asarray(endo.look_at) - pe)
    lens = pe + endo.insertion * u
    m = [_angle(t - p1, t - p2) for t in X]
    assert b["manipulation_angle"]["mean"] == pytest.approx(np.mean(m), abs=1e-9)
    assert b["manipulation_angle"]["min"] == pytest.approx(min(m), abs=1e-9)
    assert b["azimuth_difference_mean"] == pytest.approx(
        np.mean([abs(_angle(t - p1, t - lens) - _angle(t - p2, t - lens)) for t in X]), abs=1e-9)
    assert b["port_spacing_min"] == pytest.approx(min(np.linalg.norm(p1 - p2), np.linalg.norm(p1 - pe),
                                                      np.linalg.norm(p2 - pe)), abs=1e-12)
    region, res = tol.get("region"), r["resolution"]
    covs = []
    for n, p in ((n1, p1), (n2, p2)):
        w = wall_port_placement(st.arm(n), 0.05, region, resolution=res, certify_margin=tol.get("certify_margin"),
                                ports=p[None, :])
        assert b["coverage"][n] == pytest.approx(w["coverage"], abs=1e-12)
        covs.append(w["coverage"])
    depth = [(t - lens) @ u for t in X]
    in_cone = [endo.depth[0] <= z <= endo.depth[1] and _angle(t - lens, u) <= endo.fov / 2 for t, z in zip(X, depth)]
    assert b["visible"] <= np.mean(in_cone) + 1e-12  # line of sight can only remove targets
    assert b["coverage"]["both"] <= min(covs) + 1e-12
    # the smallest shaft clearance: its target's distance by a second method
    data = r["_arrays"]["data"]
    i1, i2, ie = b["indices"]
    c = data.cov1[i1] & data.cov2[i2] & data.vis[ie]
    D = np.minimum(data.D1[i1, ie], data.D2[i2, ie])
    k = int(np.flatnonzero(c)[np.argmin(D[c])])
    off_e = geo.endoscope_box(endo) - np.asarray(endo.port.estimate)
    i_near = 0 if data.D1[i1, ie, k] <= data.D2[i2, ie, k] else 1
    arm = st.arm((n1, n2)[i_near])
    es = build_arm(arm).errors
    off_i = es.port_corners() - np.asarray(es.base_port)
    P = np.vstack([(p1, p2)[i_near] + off_i, X[k]])
    Q = np.vstack([pe + off_e, lens])
    assert b["shaft_clearance_min"] == pytest.approx(_hull_distance_scipy(P, Q), abs=2e-6)
    assert b["shaft_clearance_min"] >= st.shaft_clearance


@pytest.mark.slow
def test_triad_bundled_pruned_equals_brute_force_and_figures():
    st = api.load_setup(TRIAD)
    tol = _replace(st.triads[0], options=dict(st.triads[0].options, spacing=0.05))
    a = _run(st, tol, prune=True)
    b = _run(st, tol, prune=False)
    assert a["search"]["pruned"] > 0 and b["search"]["pruned"] == 0
    assert a["best"]["indices"] == b["best"]["indices"] and a["best"]["score"] == pytest.approx(b["best"]["score"])
    assert [t["indices"] for t in a["ranked"]] == [t["indices"] for t in b["ranked"]]
    assert a["best"]["coverage"]["both"] < 1.0  # the region reaches the kidney: coverage matters
    _check_figures(st, tol, a)
    json.dumps(tr_json(st, tol, a), allow_nan=False)


def tr_json(st, tol, data):
    from errplan.tolerance.result import ToleranceResult

    d = ToleranceResult(tol.name, tol.kind, data).to_dict()
    assert {"best", "ranked", "candidates", "targets", "rejected"} <= set(d)
    assert set(d["best"]) >= {"ports", "score", "coverage", "visible", "manipulation_angle", "azimuth_difference_mean",
                              "port_spacing_min", "shaft_clearance_min", "arm_clearance_min"}
    return d


def _second_setup(d: Path) -> Path:
    """Two UR5s (example-robot-data) instead of PHANToMs, a mesh body wall, two obstacles."""
    from errplan.anatomy.meshes import icosphere, write_surface

    v, f = icosphere(3)
    write_surface(d / "wall.stl", v * [160, 140, 200], f)
    doc = triad_doc()
    doc["anatomy"]["body_wall"] = {"shape": "mesh", "file": str(d / "wall.stl"), "scale": 0.001,
                                   "position": [0.0, 0.0, 0.36]}
    doc["anatomy"]["obstacle"] = [o for o in doc["anatomy"]["obstacle"] if o["name"] in ("kidney", "vessel")]
    for a, sx in zip(doc["arm"], (-1, 1)):
        a["robot"] = {"urdf": "package://ur_description/urdf/ur5_joint_limited_robot.urdf",
                      "joints": ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint"], "wrist": "wrist_1_link",
                      "base_position": [sx * 0.35, 0.0, -0.05]}
        a["instrument"] = {"length": 0.30}
        a["rest"] = [sx * 0.04, 0.02, 0.31]
    doc["query"] = [dict(q, start=[q["start"][0], q["start"][1], 0.31]) for q in doc["query"]]
    doc["tolerance"][0].update(spacing=0.06, region={"x": [-0.04, 0.04], "y": [-0.04, 0.04], "z": [0.30, 0.36]},
                               resolution=0.02)
    p = d / "ur5_triad.toml"
    p.write_text(to_toml(doc), encoding="utf-8")
    return p


@pytest.mark.slow
def test_triad_second_setup_pruned_equals_brute_force_and_workers(tmp_path):
    st = api.load_setup(_second_setup(tmp_path))
    assert st.arm("left").anatomy.body_wall.shape == "mesh"
    tol = st.triads[0]
    a = _run(st, tol, prune=True, workers=1)
    b = _run(st, tol, prune=False, workers=1)
    c = _run(st, tol, prune=True, workers=2)
    assert a["search"]["pruned"] > 0
    for x in (b, c):
        assert a["best"]["indices"] == x["best"]["indices"]
        assert [t["indices"] for t in a["ranked"]] == [t["indices"] for t in x["ranked"]]
    assert a["search"]["evaluated"] == c["search"]["evaluated"] and a["rejected"] == c["rejected"]
    _check_figures(st, tol, a)


@pytest.mark.slow
def test_tolerance_command_on_the_triad(tmp_path, capsys):
    out = tmp_path / "t.json"
    doc = triad_doc()
    doc["tolerance"][0]["spacing"] = 0.06  # fewer candidates: the command, not the search, is tested here
    src = tmp_path / "s.toml"
    src.write_text(to_toml(doc), encoding="utf-8")
    assert main(["-q", "tolerance", str(src), "--json", str(out), "--workers", "1", "--top", "3"]) == 0
    text = capsys.readouterr().out
    assert "triad_placement" in text and "branch and bound" in text
    d = json.loads(out.read_text())["tolerances"][0]
    assert d["kind"] == "triad_placement" and set(d["best"]["ports"]) == {"left", "right", "endoscope"}
    assert d["targets"] == 125 and len(d["ranked"]) == 5


@pytest.mark.slow
def test_fields_per_arm(tmp_path, capsys):
    out = tmp_path / "F.npz"
    assert main(["-q", "fields", str(TRIAD), "--out", str(out), "--resolution", "0.03", "--workers", "1"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["F.left.npz", "F.right.npz"]
    left = np.load(tmp_path / "F.left.npz")
    right = np.load(tmp_path / "F.right.npz")
    assert left["valid"].shape == right["valid"].shape and not np.array_equal(left["valid"], right["valid"])
    # --arm: the arm's own scenario, as a one-instrument file of the same tables would give
    one = tmp_path / "one.npz"
    assert main(["-q", "fields", str(TRIAD), "--arm", "right", "--out", str(one), "--resolution", "0.03",
                 "--workers", "1"]) == 0
    assert np.array_equal(np.load(one)["valid"], right["valid"])


# ----------------------------------------------------------------------------- planning among the others
def _seg_seg(p0, p1, q0, q1) -> float:
    """Exact distance between segments [p0, p1] and [q0, q1]: the interior critical point when it lies in
    the parameter square, else the smallest of the four endpoint-to-segment distances."""
    def pt_seg(x, a, b):
        ab = b - a
        t = 0.0 if ab @ ab == 0 else min(max((x - a) @ ab / (ab @ ab), 0.0), 1.0)
        return float(np.linalg.norm(a + t * ab - x))

    u, v, w = p1 - p0, q1 - q0, p0 - q0
    a, b, c, d, e = u @ u, u @ v, v @ v, u @ w, v @ w
    den = a * c - b * b
    best = min(pt_seg(p0, q0, q1), pt_seg(p1, q0, q1), pt_seg(q0, p0, p1), pt_seg(q1, p0, p1))
    if den > 1e-18:
        s, t = (b * e - c * d) / den, (a * e - b * d) / den
        if 0 <= s <= 1 and 0 <= t <= 1:
            best = min(best, float(np.linalg.norm(p0 + s * u - q0 - t * v)))
    return best


@pytest.mark.slow
def test_plan_keeps_the_held_shafts_clear_and_the_tip_visible(tmp_path, capsys):
    """A left-arm query whose straight line takes the shaft through the held right shaft: the plan goes
    around; every 1 mm sample keeps shaft_clearance under every corner of both port boxes (and from the
    endoscope), every sample is visible, every segment is certified and the replays are monotonic."""
    doc = triad_doc()
    doc["query"] = [{"name": "cross", "arm": "left", "start": [0.02, 0.0, 0.32], "goal": [0.06, 0.05, 0.32]}]
    src = tmp_path / "s.toml"
    src.write_text(to_toml(doc), encoding="utf-8")
    out = tmp_path / "p.json"
    assert main(["-q", "plan", str(src), "--json", str(out), "--iterations", "5625"]) == 0
    q = json.loads(out.read_text())["queries"][0]
    assert q["arm"] == "left" and not q["direct"]["valid"] and q["planned"]["valid"]
    st = api.load_setup(src)
    left, right = st.arm("left"), st.arm("right")
    e = st.endoscope
    corners = lambda sc: geo.box_corners(sc.port.estimate, sc.uncertainty)  # noqa: E731
    ci, cj, ce = corners(left), corners(right), geo.endoscope_box(e)
    u = (np.asarray(e.look_at) - np.asarray(e.port.estimate))
    u /= np.linalg.norm(u)
    lens = np.asarray(e.port.estimate) + e.insertion * u
    rest = np.asarray(st.rest("right"))
    X = geo.resample(np.asarray(q["planned"]["path"]), 0.001)
    worst = min(min(_seg_seg(a, x, b, rest) for a in ci for b in cj) for x in X)
    worst_e = min(min(_seg_seg(a, x, b, lens) for a in ci for b in ce) for x in X)
    assert min(worst, worst_e) >= st.shaft_clearance - 1e-9, (worst, worst_e)
    assert q["min_shaft_clearance"] <= min(worst, worst_e) + 1e-9  # the hull distance bounds every pair of shafts
    # visible: in the cone and depth range by plain vector algebra (line of sight: the anatomy's distances)
    for x in X:
        r = x - lens
        assert e.depth[0] <= r @ u <= e.depth[1] and _angle(r, u) <= e.fov / 2 + 1e-12
    assert q["visible"] == 1.0
    assert all(g["certified"] for g in q["gains"])
    assert q["simulation"]["planned"]["monotonic"] and q["simulation"]["corners"]["planned_all_monotonic"]
