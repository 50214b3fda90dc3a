"""Arm checks in the triad search (errplan.tolerance.triad with ``[setup] arm_clearance``; docs/physics.md
"Several instruments and the endoscope").

On the bundled abdomen triad (its PHANToMs given their visual cylinders as collision geometry) and on
the bundled two-UR5 setup with a mesh torso: the branch and bound's triads equal an unpruned brute
force's with the arm checks on, and the best triad's figures equal independent computations: angles by
plain vector algebra and the shaft clearance by SLSQP (test_setup's checks), each arm's configuration by
forward kinematics (the wrist at t - L u), and the arm clearance by sampling: every collision surface read
by trimesh from the URDF, subdivided to edges <= H, placed by pinocchio's link frames and the base pose
written out here (no GeometryModel), compared point to point with a k-d tree. Those points lie on the
surfaces (a cylinder's or sphere's polygon within SAG of it), so that distance is at least the true one
less SAG and at most the true one plus 2H/sqrt(3)."""
from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from conftest import SCENARIOS, assert_refused, to_toml
from errplan import api, packages
from errplan.errors import ErrplanError
from errplan.kinematics import arm_for
from errplan.kinematics.urdf.collision import ArmCollision, clear_of, clearances
from errplan.tolerance import triad as tr
from test_arm_collision import pose, sampled_distance, surfaces_of
from test_setup import _check_figures, triad_doc

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore

UR5_TRIAD = SCENARIOS / "ur5_triad.toml"
H = 0.007  # edge length of the sampled surfaces (m)
SAG = 1e-4  # how far inside a sampled cylinder or sphere its polygon's points may lie (m), bounded below


# ----------------------------------------------------------------------------- scenarios
def phantom_with_collision(d: Path) -> Path:
    """The bundled PHANToM with the visual cylinders and sphere of its moving links as collision geometry
    (its base disc and post left out: abdomen_triad's two bases stand 0.1 m apart, their 0.12 m discs
    would overlap and their posts would set every triad's arm clearance)."""
    text = (SCENARIOS / "phantom15.urdf").read_text()

    def link(m):
        body = m.group(0)
        v = re.search(r"<visual>(.*?)</visual>", body, re.S)
        if 'name="base"' in body or 'name="torso"' in body or v is None:
            return body
        geometry = re.sub(r"<material[^>]*/>", "", v.group(1))
        return body.replace("</link>", "<collision>" + geometry + "</collision></link>")

    p = d / "phantom15_collision.urdf"
    p.write_text(re.sub(r"<link .*?</link>", link, text, flags=re.S))
    return p


def abdomen_arms(d: Path, arm_clearance: float = 0.02) -> Path:
    """abdomen_triad.toml with arm checks on, coarse enough that a brute force takes seconds."""
    doc = triad_doc()
    urdf = str(phantom_with_collision(d))
    for a in doc["arm"]:
        a["robot"]["urdf"] = urdf
    doc["setup"]["arm_clearance"] = arm_clearance
    doc["tolerance"][0].update(spacing=0.08, resolution=0.04)
    p = d / "abdomen_arms.toml"
    p.write_text(to_toml(doc), encoding="utf-8")
    return p


def ur5_doc() -> dict:
    doc = tomllib.loads(UR5_TRIAD.read_text())
    doc["anatomy"]["body_wall"]["file"] = str((SCENARIOS / doc["anatomy"]["body_wall"]["file"]).resolve())
    return doc


def ur5_coarse(d: Path, **setup) -> Path:
    doc = ur5_doc()
    doc["setup"].update(setup)
    doc["tolerance"][0].update(spacing=0.08)
    p = d / "ur5_coarse.toml"
    p.write_text(to_toml(doc), encoding="utf-8")
    return p


# ----------------------------------------------------------------------------- the independent arm clearance
def world_points(arm, q, surfaces) -> np.ndarray:
    data = arm.model.createData()
    pin.framesForwardKinematics(arm.model, data, arm.pinocchio_configuration(np.asarray(q, float)))
    B = pose(list(arm.base_position), list(arm.base_rpy))
    pts = []
    for name, O, _, fine in surfaces:
        M = B @ data.oMf[arm.model.getFrameId(name)].homogeneous @ O
        pts.append(fine @ M[:3, :3].T + M[:3, 3])
    return np.concatenate(pts)


def check_arms(st, r):
    """The best triad's arms: configurations by FK, the hard constraint and arm_clearance_min by sampling."""
    b = r["best"]
    n1, n2 = r["instruments"]
    data, X, Q = r["_arrays"]["data"], r["_arrays"]["targets"], r["_arrays"]["arm_q"]
    i1, i2, ie = b["indices"]
    c = data.cov1[i1] & data.cov2[i2] & data.vis[ie]
    assert c.any()
    sampled = []
    for name in (n1, n2):
        sc = st.arm(name)
        arm = arm_for(sc.robot)
        p = np.asarray(b["ports"][name])
        u = (X[c] - p) / np.linalg.norm(X[c] - p, axis=1)[:, None]
        assert np.allclose(arm.forward(Q[name][c]), X[c] - sc.instrument.length * u, atol=1e-6)
        assert np.all(arm.within_limits(Q[name][c]))
        surf = surfaces_of(arm.urdf_path, arm.urdf_path.parent, h=H)
        sampled.append([world_points(arm, q, surf) for q in Q[name][c]])
    d = np.array([sampled_distance(a, b_) for a, b_ in zip(*sampled)])
    assert np.all(d >= st.arm_clearance - SAG)  # the hard constraint, by the second method
    m = b["arm_clearance_min"]
    assert min(d) - 2 * H / math.sqrt(3) - 1e-9 <= m <= min(d) + SAG
    return m


def search_both(st, tol):
    a = tr.triad_placement(st, tol, prune=True)
    b = tr.triad_placement(st, tol, prune=False)
    assert a["search"]["pruned"] > 0 and b["search"]["pruned"] == 0
    assert [t["indices"] for t in [a["best"]] + a["ranked"]] == [t["indices"] for t in [b["best"]] + b["ranked"]]
    for x, y in zip([a["best"]] + a["ranked"], [b["best"]] + b["ranked"]):
        assert x["score"] == pytest.approx(y["score"], abs=1e-12)
        assert x["arm_clearance_min"] == y["arm_clearance_min"]  # None: no target covered
        assert x["arm_clearance_min"] is None or x["arm_clearance_min"] >= st.arm_clearance
    assert a["rejected"]["arm_clearance"] > 0 and b["rejected"]["arm_clearance"] >= a["rejected"]["arm_clearance"]
    assert a["arm_checks"].startswith("on") and a["timing"]["arm_queries"] < b["timing"]["arm_queries"]
    return a, b


# ----------------------------------------------------------------------------- the search against brute force
@pytest.mark.slow
def test_abdomen_arms_pruned_equals_brute_force_and_figures(tmp_path):
    st = api.load_setup(abdomen_arms(tmp_path))
    tol = st.triads[0]
    a, _ = search_both(st, tol)  # some triads rejected for their arms (the PHANToMs' links touch there)
    _check_figures(st, tol, a)
    check_arms(st, a)
    off = tr.triad_placement(dataclasses.replace(st, arm_clearance=None), tol)
    assert off["best"]["arm_clearance_min"] is None and off["rejected"]["arm_clearance"] is None
    assert off["arm_checks"] == "off" and off["timing"]["arm_queries"] == 0


@pytest.mark.slow
def test_ur5_triad_pruned_equals_brute_force_and_figures(tmp_path):
    st = api.load_setup(ur5_coarse(tmp_path))
    assert st.arm("left").anatomy.body_wall.shape == "mesh" and st.arm_clearance == 0.03
    tol = st.triads[0]
    a, _ = search_both(st, tol)
    assert a["rejected"]["arm_clearance"] > a["rejected"]["port_spacing"] + a["rejected"]["shaft_clearance"]
    off = tr.triad_placement(dataclasses.replace(st, arm_clearance=None), tol)  # the arm checks decide
    assert off["best"]["indices"] != a["best"]["indices"] and off["best"]["score"] < a["best"]["score"]
    _check_figures(st, tol, a)
    check_arms(st, a)
    c = tr.triad_placement(st, tol, workers=2)  # tasks in two processes: the same answer and counts
    assert [t["indices"] for t in [c["best"]] + c["ranked"]] == [t["indices"] for t in [a["best"]] + a["ranked"]]
    assert c["rejected"] == a["rejected"] and c["search"]["evaluated"] == a["search"]["evaluated"]


def test_a_triad_closer_than_arm_clearance_is_rejected(tmp_path):
    """The bundled UR5 setup's chosen triad alone (its ports as the candidate lists): accepted with
    arm_clearance just below its smallest arm clearance, rejected just above it."""
    st = api.load_setup(UR5_TRIAD)
    tol = st.triads[0]
    ports = {"left": [[0.0532, 0.1316, 0.6281]], "right": [[0.1963, 0.1619, 0.7399]],
             "endoscope": [[0.1306, 0.1616, 0.6675]]}
    one = dataclasses.replace(tol, options=dict(tol.options, candidates=ports))
    r = tr.triad_placement(st, one)
    m = r["best"]["arm_clearance_min"]
    assert st.arm_clearance <= m < st.arm_clearance + 0.05
    r2 = tr.triad_placement(dataclasses.replace(st, arm_clearance=m - 0.002), one)
    assert r2["best"]["arm_clearance_min"] == m and r2["rejected"]["arm_clearance"] == 0
    with pytest.raises(ErrplanError, match=r"no triad of the 1 meets the hard constraints .*arm clearance"):
        tr.triad_placement(dataclasses.replace(st, arm_clearance=m + 0.002), one)


# ----------------------------------------------------------------------------- the yes/no against the distance
def test_clear_of_answers_as_the_exact_distance():
    st = api.load_setup(UR5_TRIAD)
    A, B = (ArmCollision.from_arm(arm_for(sc.robot)) for sc in st.arms)
    rng = np.random.default_rng(5)
    lo, hi = np.array([-1.2, -2.6, -0.3]), np.array([1.2, -0.4, 2.6])
    qa, qb = rng.uniform(lo, hi, (81, 3)), rng.uniform(lo, hi, (81, 3))
    qa[0, 1] = np.nan  # an arm that cannot stand there: not clear
    d = clearances(A, qa, B, qb)
    assert np.isnan(d[0]) and np.all(np.isfinite(d[1:]))
    s = np.sort(d[1:])
    for c in (0.01, 0.03, 0.1, float(0.5 * (s[39] + s[40]))):  # the last one splits the sample in halves
        got = clear_of(A, qa, B, qb, c)
        assert not got[0]
        assert np.array_equal(got[1:], d[1:] >= c), c
    assert 0 < np.sum(d[1:] < 0.03) < len(d) - 1  # both answers occur


def test_clear_of_bad_arguments():
    st = api.load_setup(UR5_TRIAD)
    A, B = (ArmCollision.from_arm(arm_for(sc.robot)) for sc in st.arms)
    for c in (0.0, -0.01, math.nan, math.inf):
        with pytest.raises(ErrplanError, match="clearance must be a positive number"):
            clear_of(A, np.zeros((1, 3)), B, np.zeros((1, 3)), c)
    with pytest.raises(ErrplanError, match="configurations"):
        clearances(A, np.zeros((2, 3)), B, np.zeros((3, 3)))


# ----------------------------------------------------------------------------- the bundled setup, bad input
def test_ur5_triad_loads_with_its_rest_arms_clear():
    st = api.load_setup(UR5_TRIAD)
    assert st.arm_names == ("left", "right") and st.arm_clearance == 0.03
    assert st.endoscope is not None and [t.kind for t in st.triads] == ["triad_placement"]
    for name in st.arm_names:  # one query per arm, each valid for its arm
        assert [q.name for q in st.arm(name).queries] == [f"{name} reach"]


def test_rest_arms_closer_than_arm_clearance_is_one_line_exit_2(tmp_path, capsys):
    doc = ur5_doc()
    doc["setup"]["arm_clearance"] = 0.5  # the UR5s at rest are closer than that
    assert_refused(tmp_path, capsys, doc, "tolerance", "'left' rest", "'right' rest", "mm apart",
                   "arm_clearance = 0.5", "rest point not clear")
