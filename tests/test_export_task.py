"""From measured data to the plan (docs/physics.md "From measured data to the plan"): the two exports, the
task before and after, ``errplan plan --truth``, corner replays on the truth with its effects, the corrected
URDF's mesh paths and untouched origins, and the one identifiability threshold.

The benches are made by plants errplan's effects did not write: a planar scenario whose ``[robot]``
link lengths differ (the planar arm itself, not ``link_length``) and a PHANToM-like URDF whose elbow origin
was edited by hand (read by pinocchio's model of that file, not through ``joint_geometry``)."""
from __future__ import annotations

import json
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from errplan.api import load_scenario
from errplan.cli import main

ROOT = Path(__file__).resolve().parents[1]
PORT = ROOT / "scenarios" / "beasley2004_port.toml"
SPATIAL = ROOT / "scenarios" / "phantom15_spatial.toml"
URDF = ROOT / "scenarios" / "phantom15.urdf"
#: the candidates of the command-line calibrations here: the geometric group and two physical effects that
#: could absorb part of it (the whole catalogue runs in tests/test_calibration.py)
PLANAR_EFFECTS = "link_length,port_offset,joint_offset"
SPATIAL_EFFECTS = "joint_geometry,port_offset,joint_offset"
MM = 1e-3


def _planar_declared(folder: Path) -> Path:
    """beasley2004_port with one query, a 4 mm grid and a small planning budget."""
    text = PORT.read_text(encoding="utf-8")
    text = text.replace("resolution = 0.002", "resolution = 0.004").replace("iterations = 7500", "iterations = 1200")
    text = text[:text.index("# Across the deep part")]
    assert "resolution = 0.004" in text and "iterations = 1200" in text and text.count("[[query]]") == 1
    p = folder / "declared.toml"
    p.write_text(text, encoding="utf-8")
    return p


@pytest.fixture(scope="module")
def planar(tmp_path_factory):
    """A planar bench whose links are 3 mm longer and 2 mm shorter than declared (the truth scenario's
    own ``link_lengths``), calibrated with both exports and the task."""
    d = tmp_path_factory.mktemp("planar")
    declared = _planar_declared(d)
    text = declared.read_text(encoding="utf-8")
    truth = d / "truth.toml"
    truth.write_text(text.replace("link_lengths = [0.210, 0.210]", "link_lengths = [0.213, 0.208]"), encoding="utf-8")
    assert "0.213, 0.208" in truth.read_text()
    assert main(["-q", "experiment", str(truth), "--out", str(d / "data.csv"), "--seed", "3", "--starts", "4"]) == 0
    (d / "out").mkdir()
    assert main(["-q", "calibrate", str(declared), str(d / "data.csv"), "--json", str(d / "cal.json"), "--folds", "3",
                 "--effects", PLANAR_EFFECTS, "--export-scenario", str(d / "out" / "corrected.toml"),
                 "--export-bench", str(d / "out" / "bench.toml")]) == 0
    return SimpleNamespace(d=d, declared=declared, js=json.loads((d / "cal.json").read_text()),
                           corrected=d / "out" / "corrected.toml", bench=d / "out" / "bench.toml")


def _same_before_as_after(first: dict, again: dict) -> None:
    for k in ("pose_rms", "trajectory_rms"):
        assert abs(first[f"{k}_after"] - again[f"{k}_before"]) < 1e-9, k  # 1e-6 mm
    assert abs(first["fit"]["trajectory_rms_all_steps_after"] - again["fit"]["trajectory_rms_all_steps_before"]) < 1e-9


def test_planar_exports_say_which_model_is_which_and_the_bench_round_trips(planar, tmp_path):
    js = planar.js
    assert js["selected"] == ["link_length"] and js["exported"] == [str(planar.corrected), str(planar.bench)]
    # the corrected robot: controller and truth both have the found links, no effect left for them
    corr = load_scenario(planar.corrected)
    assert corr.robot.link_lengths == pytest.approx((0.213, 0.208), abs=0.05 * MM)
    assert "link_length" not in corr.effects
    # the bench: the declared robot and controller, the fitted links as its truth's effect
    bench, declared = load_scenario(planar.bench), load_scenario(planar.declared)
    for t in ("robot", "instrument", "port", "controller", "uncertainty", "fields", "planner", "queries"):
        assert getattr(bench, t) == getattr(declared, t), t
    assert bench.effects["link_length"]["dl1"] == pytest.approx(0.003, abs=0.05 * MM)
    assert bench.effects["link_length"]["dl2"] == pytest.approx(-0.002, abs=0.05 * MM)
    # the same data on the bench: nothing to add, and "before" there is "after" here
    assert main(["-q", "calibrate", str(planar.bench), str(planar.d / "data.csv"), "--json", str(tmp_path / "again.json"),
                 "--folds", "3", "--effects", PLANAR_EFFECTS, "--no-task"]) == 0
    again = json.loads((tmp_path / "again.json").read_text())
    assert again["selected"] == [] and "task" not in again
    _same_before_as_after(js, again)


def _plan_json(scenario: Path, truth: Path, out: Path) -> dict:
    assert main(["-q", "plan", str(scenario), "--truth", str(truth), "--json", str(out), "--workers", "1"]) == 0
    return json.loads(out.read_text())


def test_the_task_table_is_plan_truth_for_the_same_pair(planar, tmp_path, capsys):
    """The task's before is ``plan DECLARED --truth BENCH``, its after ``plan CORRECTED --truth BENCH``; the
    truth simulated is the bench's: its planned run under the true links, not the declared ones."""
    task = planar.js["task"]
    assert [t["query"] for t in task] == ["N-to-L"]
    for side, scenario in (("before", planar.declared), ("after", planar.corrected)):
        q = _plan_json(scenario, planar.bench, tmp_path / f"{side}.json")["queries"][0]
        sim = q["simulation"]["planned"]
        T = task[0][side]
        assert T == {"max_deviation": sim["max_deviation"], "final_error": sim["final_error"], "steps": sim["steps"],
                     "monotonic": sim["monotonic"], "certified_G_norm": q["gain_schedule"]["max_certified_G_norm"],
                     "certificate_covers": True, "uncovered_effects": []}, side
        assert q["certificate_covers"] is True and q["truth"].endswith("-bench")
    out = capsys.readouterr().out
    assert "(beasley2004-port-bench's, --truth)" in out
    # the bench's truth is not the declared scenario's: the same plan simulated on its own truth differs
    own = json.loads(_plain_plan(planar.declared, tmp_path / "own.json").read_text())["queries"][0]
    assert own["simulation"]["planned"]["max_deviation"] != task[0]["before"]["max_deviation"]


def _plain_plan(scenario: Path, out: Path) -> Path:
    assert main(["-q", "plan", str(scenario), "--json", str(out), "--workers", "1"]) == 0
    return out


def test_bad_export_paths_are_one_error_and_nothing_is_written(planar, tmp_path, capsys):
    data = planar.d / "data.csv"
    cases = [(["--export-bench", str(tmp_path / "no" / "b.toml")], "--export-bench"),
             (["--export-bench", str(tmp_path)], "--export-bench"),
             (["--export-bench", str(tmp_path / "x.toml"), "--export-scenario", str(tmp_path / "x.toml")], "same file")]
    for extra, needle in cases:
        rc = main(["calibrate", str(planar.declared), str(data), "--json", str(tmp_path / "o.json"), *extra])
        err = capsys.readouterr().err
        assert rc == 2 and err.count("\n") == 1 and needle in err, (extra, err)
        assert not any(tmp_path.iterdir()), extra


# ----------------------------------------------------------------------------- pipeline: corners and --truth
def _query_json(sc) -> dict:
    q = sc.queries[0]
    mid = (np.asarray(q.start) + np.asarray(q.goal)) / 2 + np.array([0.01, 0.0])
    return {"name": q.name, "start": list(q.start), "goal": list(q.goal), "planned": {"path": [list(q.start), mid.tolist(),
                                                                                             list(q.goal)]}}


def test_corner_replays_run_on_the_truth_with_its_effects(tmp_path):
    """Without an [uncertainty] table the error set is the one instance "true port = position": its corner
    replay is the truth's own run, effects included, and differs from the declared robot's."""
    from errplan.pipeline import replay, run_query, truth_plant
    from errplan.gains import options_from_scenario
    from errplan.simulation import ControllerModel
    from errplan.models import arm_model

    declared = load_scenario(_planar_declared(tmp_path))
    truth = declared.with_(effects={"link_length": {"dl1": 0.003, "dl2": -0.002}})
    qj = _query_json(declared)
    r_true = run_query(truth, qj)
    r_decl = run_query(declared, qj)
    assert len(r_true.corner_planned) == 1
    # an independent replay on the truth: the plant built from the scenario with longer links, not the effect
    from errplan.scenario import Robot

    rb = declared.robot
    longer = declared.with_(robot=Robot(rb.base, (0.213, 0.208), rb.home_angles, rb.joint_limits, rb.joint_sum_limits))
    opts = options_from_scenario(declared)
    ref = replay(truth_plant(longer), ControllerModel.from_model(arm_model(declared)), r_true.planned_path[0],
                 r_true.schedule.waypoints, r_true.schedule.gains, opts, int(declared.planner.seed) + 1)
    corner = r_true.corner_planned[0].sim
    assert corner.steps == ref.sim.steps and np.max(np.abs(corner.tip - ref.sim.tip)) < 1e-12
    assert np.max(np.abs(corner.tip - r_true.sim_planned.sim.tip)) < 1e-12
    dec = r_decl.corner_planned[0].sim
    assert dec.steps != corner.steps or np.max(np.abs(dec.tip[: min(len(dec.tip), len(corner.tip))]
                                                      - corner.tip[: min(len(dec.tip), len(corner.tip))])) > 1e-4


def test_a_truth_with_an_effect_the_metrics_cannot_express_is_not_covered(tmp_path):
    """--truth with backlash: simulated on that truth (its run differs), and the plan says the certificate
    does not cover it (JSON and text)."""
    from errplan.pipeline import run_pipeline, summary_table

    declared = load_scenario(_planar_declared(tmp_path))
    truth = declared.with_(effects={"backlash": {"b1": 0.004, "b2": 0.003}})
    qj = _query_json(declared)
    own = run_pipeline(declared, [qj], corners=False)
    res = run_pipeline(declared, [qj], corners=False, truth_sc=truth)
    q = res["queries"][0]
    assert own["queries"][0]["certificate_covers"] is True and own["queries"][0]["uncovered_effects"] == []
    assert q["certificate_covers"] is False and q["uncovered_effects"] == ["backlash"] and q["truth"] == truth.name
    a, b = own["runs"][0].sim_planned.sim, res["runs"][0].sim_planned.sim
    assert a.steps != b.steps or np.max(np.abs(a.tip[:len(b.tip)] - b.tip[:len(a.tip)])) > 1e-6
    text = summary_table(res["runs"])
    assert "does not cover backlash" in text
    zero = declared.with_(effects={"backlash": {"b1": 0.0, "b2": 0.0}})
    assert run_pipeline(declared, [qj], corners=False, truth_sc=zero)["queries"][0]["certificate_covers"] is True


def test_plan_truth_refuses_another_robot(tmp_path, capsys):
    declared = _planar_declared(tmp_path)
    rc = main(["-q", "plan", str(declared), "--truth", str(SPATIAL)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "--truth" in err and "3-D" in err
    rc = main(["-q", "plan", str(declared), "--truth", str(tmp_path / "none.toml")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "--truth" in err and "not found" in err


# ----------------------------------------------------------------------------- the URDF bench and the corrected URDF
def _joint_origin_tags(text: str) -> dict[str, str]:
    out = {}
    for m in re.finditer(r"<joint\b[^>]*\bname\s*=\s*\"([^\"]+)\"[^>]*\btype\s*=.*?</joint>", text, flags=re.S):
        o = re.search(r"<origin\b[^>]*/>", m.group(0))
        out[m.group(1)] = o.group(0) if o else None
    return out


ELBOW_DECLARED = '<origin xyz="0 0 0.21" rpy="1.5707963267948966 0 0"/>'


@pytest.fixture(scope="module")
def spatial(tmp_path_factory):
    """The PHANToM-like arm whose upper arm is 3 mm longer: the truth's URDF edited by hand."""
    d = tmp_path_factory.mktemp("spatial")
    text = URDF.read_text(encoding="utf-8")
    assert text.count(ELBOW_DECLARED) == 1
    (d / "robot").mkdir()
    (d / "robot" / "declared.urdf").write_text(text, encoding="utf-8")
    (d / "robot" / "true.urdf").write_text(text.replace(ELBOW_DECLARED, ELBOW_DECLARED.replace("0.21", "0.213")),
                                           encoding="utf-8")
    sc = SPATIAL.read_text(encoding="utf-8").replace('urdf = "phantom15.urdf"', 'urdf = "robot/declared.urdf"')
    assert "robot/declared.urdf" in sc
    (d / "declared.toml").write_text(sc, encoding="utf-8")
    (d / "truth.toml").write_text(sc.replace("robot/declared.urdf", "robot/true.urdf"), encoding="utf-8")
    assert main(["-q", "experiment", str(d / "truth.toml"), "--out", str(d / "data.csv"), "--seed", "5",
                 "--starts", "3"]) == 0
    (d / "out").mkdir()
    assert main(["-q", "calibrate", str(d / "declared.toml"), str(d / "data.csv"), "--json", str(d / "cal.json"),
                 "--folds", "3", "--effects", SPATIAL_EFFECTS, "--no-task",
                 "--export-scenario", str(d / "out" / "fixed.toml"), "--export-bench", str(d / "out" / "bench.toml")]) == 0
    return SimpleNamespace(d=d, js=json.loads((d / "cal.json").read_text()))


def test_urdf_bench_round_trips_and_the_corrected_urdf_is_the_true_one(spatial, tmp_path):
    import pinocchio as pin

    d, js = spatial.d, spatial.js
    assert js["selected"] == ["joint_geometry"]
    assert js["exported"] == [str(d / "out" / "fixed.toml"), str(d / "out" / "fixed.urdf"), str(d / "out" / "bench.toml")]
    bench = load_scenario(d / "out" / "bench.toml")
    assert Path(bench.robot.urdf).resolve() == (d / "robot" / "declared.urdf").resolve()
    assert "joint_geometry" in bench.effects
    assert main(["-q", "calibrate", str(d / "out" / "bench.toml"), str(d / "data.csv"), "--json",
                 str(tmp_path / "again.json"), "--folds", "3", "--effects", SPATIAL_EFFECTS, "--no-task"]) == 0
    again = json.loads((tmp_path / "again.json").read_text())
    assert again["selected"] == []
    _same_before_as_after(js, again)
    # the corrected URDF: pinocchio reads it as it reads the true one (the elbow 3 mm further), and every
    # origin the fit left alone is the source's text, character for character
    src = (d / "robot" / "declared.urdf").read_text()
    fixed = (d / "out" / "fixed.urdf").read_text()
    models = [pin.buildModelFromXML(t) for t in (fixed, (d / "robot" / "true.urdf").read_text())]
    datas = [m.createData() for m in models]
    rng = np.random.default_rng(1)
    for _ in range(5):
        q = rng.uniform(-0.5, 0.5, models[0].nq)
        for m, dd in zip(models, datas):
            pin.forwardKinematics(m, dd, q)
        a, b = (dd.oMi[m.getJointId("elbow")].translation for m, dd in zip(models, datas))
        assert np.max(np.abs(a - b)) < 0.05 * MM
    fitted = {k for k in js["parameters"]["joint_geometry"]}
    joints = ("waist", "shoulder", "elbow")
    moved = {joints[int(k.split("_")[1]) - 1] for k in fitted if int(k.split("_")[1]) <= 3}
    before, after = _joint_origin_tags(src), _joint_origin_tags(fixed)
    for name, tag in before.items():
        if name not in moved:
            assert after[name] == tag, name
    assert "elbow" in moved and after["elbow"] != before["elbow"]
    # only origins changed: the text outside them is the source's
    strip = lambda t: re.sub(r"<origin\b[^>]*/>", "", t)  # noqa: E731
    assert strip(fixed) == strip(src)


def test_an_untouched_rotation_keeps_its_text():
    """A joint only moved keeps its rpy as written (a pitch of pi/2 is not rewritten through roll-pitch-yaw)."""
    from errplan.kinematics.geometry import corrected_urdf_text

    text = ('<robot name="r"><link name="a"/><link name="b"/><link name="c"/>'
            '<joint name="j1" type="revolute"><parent link="a"/><child link="b"/>'
            '<origin xyz="0 0 0.1" rpy="0 1.5708 0"/><axis xyz="0 0 1"/></joint>'
            '<joint name="j2" type="revolute"><parent link="b"/><child link="c"/>'
            '<origin rpy="0.0 0.0 0.0" xyz="0.0 -0.1197 0.425"/><axis xyz="0 0 1"/></joint></robot>')
    g = np.zeros(12)
    g[2] = 0.003   # dz_1: moved only
    g[11] = 0.01   # rz_2: turned only
    out = corrected_urdf_text(text, ["j1", "j2"], g)
    assert 'rpy="0 1.5708 0"' in out and 'xyz="0 0 0.103"' in out
    assert 'xyz="0.0 -0.1197 0.425"' in out and 'rpy="0 -0 0.01"' in out.replace("0.0100000000000", "0.01")


def test_ur5_export_finds_its_meshes_from_a_new_folder(tmp_path):
    """A UR5 description whose meshes are named relative to its URDF (``../meshes/...``), exported to another
    folder: the corrected URDF's mesh paths resolve there and the arm checks' collision geometry loads
    from it; the same text with the paths left as they were does not."""
    from errplan.calibration.export import corrected_files
    from errplan.errors import ErrplanError
    from errplan.kinematics.urdf import UrdfArm
    from errplan.kinematics.urdf.collision import ArmCollision
    from errplan.packages import resolve_package_uri

    src = resolve_package_uri("package://ur_description/urdf/ur5_joint_limited_robot.urdf")
    prefix = "package://example-robot-data/robots/ur_description/meshes/"
    text = src.read_text()
    assert text.count(prefix) == 14
    (tmp_path / "ur5" / "urdf").mkdir(parents=True)
    (tmp_path / "ur5" / "meshes").symlink_to(src.parents[1] / "meshes", target_is_directory=True)
    (tmp_path / "ur5" / "urdf" / "ur5.urdf").write_text(text.replace(prefix, "../meshes/"))
    sc_text = (ROOT / "scenarios" / "ur5_port.toml").read_text().replace(
        'urdf = "package://ur_description/urdf/ur5_joint_limited_robot.urdf"', 'urdf = "ur5/urdf/ur5.urdf"')
    (tmp_path / "ur5.toml").write_text(sc_text)
    sc = load_scenario(tmp_path / "ur5.toml")
    r = sc.robot
    jg = {"dz_3": 0.003}
    # the rows a bench ran: configurations whose wrist is within the shaft of the port (the export's read-back)
    declared_arm = UrdfArm.from_robot(r)
    lim = np.asarray(declared_arm.limits)
    q = lim[:, 0] + np.random.default_rng(2).random((4000, 3)) * (lim[:, 1] - lim[:, 0])
    near = np.linalg.norm(declared_arm.forward(q) - np.asarray(sc.port.position), axis=-1) < 0.3
    assert near.sum() > 10
    rep = SimpleNamespace(effects_table=lambda: {"joint_geometry": dict(jg)}, selected=["joint_geometry"],
                          data_source="bench.csv", explained=True, noise=SimpleNamespace(sigma=2e-4),
                          fit_errors=SimpleNamespace(pose_before=3e-3, pose_after=2e-4), data=SimpleNamespace(q=q[near]))
    out = tmp_path / "elsewhere" / "fixed.toml"
    out.parent.mkdir()
    toml_text, extra = corrected_files(sc, rep, out)
    (urdf_path, urdf_text), = extra.items()
    Path(urdf_path).write_text(urdf_text)
    out.write_text(toml_text)
    assert urdf_text.count("../meshes/") == 0 and urdf_text.count("../ur5/meshes/") == 14
    fixed = load_scenario(out)
    arm = UrdfArm.from_robot(fixed.robot)
    geo = ArmCollision.from_arm(arm)
    ref = ArmCollision.from_arm(UrdfArm.from_robot(r))
    assert geo.geometry_model.ngeoms == ref.geometry_model.ngeoms > 0
    q = np.array([[0.1, -0.4, 0.6]])
    assert np.max(np.abs(arm.forward(q) - UrdfArm.from_robot(r).forward(q))) > 1e-3  # the corrected arm is not the source
    # the same corrected text with its mesh paths as in the source does not find them from the new folder
    (out.parent / "stale.urdf").write_text(urdf_text.replace("../ur5/meshes/", "../meshes/"))
    stale = UrdfArm.load(out.parent / "stale.urdf", r.joints, r.wrist, base_position=r.base_position, base_rpy=r.base_rpy)
    with pytest.raises(ErrplanError, match="not found"):
        ArmCollision.from_arm(stale)


# ----------------------------------------------------------------------------- the identifiability threshold
def test_one_condition_threshold_flags_a_poorly_identifiable_geometric_group():
    """tracker_registration (a geometric group: QR picks its parameters) on tips clustered far from the world
    origin: the rotation shows almost as a translation. QR keeps it (its pivot is above 1e-6 of the first),
    but its condition number exceeds MAX_CONDITION, so it is flagged as not identifiable; on tips spread over
    the workspace it is identifiable. The candidates table and the docs name the same number."""
    from errplan.effects import MAX_CONDITION, EffectModel, make_effect
    from errplan.experiment import truth_plant

    sc = load_scenario(PORT)
    base = truth_plant(sc, effects=False, noise=False)
    rng = np.random.default_rng(0)
    true = base.with_(tracker_rotation=(0.004,), tracker_offset=(0.001, -0.002))

    def fit(spread: float):
        q = np.array([0.2, 0.1]) + rng.uniform(-spread, spread, (60, 2))
        u = np.zeros((60, 2))
        tip = true.tracked(true.tip(q, u)) + rng.normal(0.0, 1e-6, (60, 2))
        return EffectModel([make_effect("tracker_registration")]).fit(q, u, tip, base)

    tight, wide = fit(2e-4), fit(0.3)
    assert tight.n_free == 3 and tight.condition_ > MAX_CONDITION and not tight.identifiable_
    assert f"condition number {tight.condition_:.3g} > {MAX_CONDITION:g}" in tight.why_
    assert wide.condition_ < MAX_CONDITION and wide.identifiable_
    docs = (ROOT / "docs" / "calibration.md").read_text(encoding="utf-8")
    assert f"condition number > {MAX_CONDITION:g}" in docs
