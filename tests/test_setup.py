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

from conftest import SCENARIOS, to_toml
from errplan import api
from errplan.anatomy import setup as geo
from errplan.cli import main
from errplan.errors import ScenarioError
from errplan.scenario import read_scenario, read_setup, setup_from_dict

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
    p = tmp_path / "s.toml"
    p.write_text(to_toml(doc), encoding="utf-8")
    capsys.readouterr()
    rc = main(["-q", "tolerance", str(p), "--json", str(tmp_path / "out.json")])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, (w, err)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["s.toml"]


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
