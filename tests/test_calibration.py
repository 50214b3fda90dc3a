"""Closing the loop (errplan.calibration, `errplan calibrate`).

Bench data carry one catalogue effect (undeclared in the scenario given to calibrate) at bench
sizes (a few mm) with the tracker noise of the scenario: the right effect is selected, its
parameters are recovered within 3 stated sigmas, the held-out trajectory error is cut. Also two
effects at once, noise only (nothing selected), and an effect outside the catalogue (a 1 % tracker
scale error): ``explained: false`` (a link-length error, found by the geometric group
``link_length``: tests/test_geometry_effects.py). The noise floor is checked
against the known tracker sigma, the batched replay against ``simulate``, the CLI's CSV errors
(exit 2, nothing written), the JSON keys of interfaces.md, the recording and the exported scenario
(read back; calibrating against it selects nothing)."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from errplan.calibration import (approach_mask, calibrate, check_against_model, declared_plant, motion_model,
                                 noise_floor, pose_residual, replay, structure_test, to_toml)
from errplan.cli import main
from errplan.effects import predict_tracked
from errplan.errors import DataError
from errplan.experiment import bench_controller, parse_measured_csv, run_experiment
from errplan.api import load_scenario, parse_scenario
from errplan.simulation import Plant, simulate
from errplan.models import build_arm

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore

ROOT = Path(__file__).resolve().parents[1]
#: folds of whole runs for the held-out errors of the in-process calibrations: 3, not the command's default 5
#: (a third fewer fits per candidate, each candidate still held out on runs it was not fitted to); the planar
#: command-line calibrations (cli_run, test_cli_friction_bench_end_to_end) run with the default
FOLDS = 3
PORT = ROOT / "scenarios" / "beasley2004_port.toml"
STARTS = 5

TRUTHS = {
    "port_offset": {"dy": 0.003, "dz": -0.002},
    "joint_offset": {"dq1": 0.003, "dq2": -0.002},
    "tracker_offset": {"by": 0.002, "bz": -0.0015},
    "gravity_sag": {"c1": 0.004, "c2": 0.002, "c3": 0.003},
    "shaft_flexion": {"fy": 2.0, "fz": 1.0},
    "port_friction": {"fa": 0.0015, "fn": 0.001},
}


@pytest.fixture(scope="module")
def port():
    return load_scenario(PORT)


def bench(sc, effects, seed, plant=None):
    return run_experiment(sc.with_(effects=effects), seed=seed, n_starts=STARTS, plant=plant).data


def check_recovery(rep, truth: dict) -> None:
    for e, ps in truth.items():
        for p, v in ps.items():
            got, sig = rep.parameters[e][p], rep.uncertainty[e][p]
            assert sig > 0 and math.isfinite(sig)
            assert abs(got - v) < 3 * sig, f"{e}.{p}: {got:.6g} +- {sig:.3g}, true {v}"


# ----------------------------------------------------------------------------- each effect
# each catalogue effect alone is found on the one-cm bench below (test_each_effect_on_a_one_cm_bench and, for
# port friction, test_cli_friction_bench_end_to_end: the done-means checks, tighter than check_found's, and the
# candidates table of check_candidates); gravity sag on P1's own bench (seeds 11 and 12) is calibrated
# through the command line: cli_run and test_cli_calibrate_finds_the_gravity_sag, with check_found on its JSON
def check_found(js: dict, truth: dict) -> None:
    """One effect on P1's bench, from the calibrate JSON: selected alone and explained, its parameters
    within 3 stated sigmas, the held-out pose error at the noise floor, the trajectory error cut; the
    candidates table: every effect alone, every pair, each geometric group alone, each with a held-out
    error and a score; when a geometric group beats the declared model (a port offset looks like a
    tracker registration), that group with each physical effect too."""
    assert js["selected"] == list(truth) and js["explained"] is True
    for e, ps in truth.items():
        for p, v in ps.items():
            got, sig = js["parameters"][e][p], js["uncertainty"][e][p]
            assert sig > 0 and math.isfinite(sig)
            assert abs(got - v) < 3 * sig, f"{e}.{p}: {got:.6g} +- {sig:.3g}, true {v}"
    assert js["errors_on"] == "validation" and js["validation"]["pose_rms_after"] == js["pose_rms_after"]
    assert js["pose_rms_after"] < 1.1 * js["noise_floor"] < js["pose_rms_before"]
    assert js["trajectory_rms_after"] < 0.8 * js["trajectory_rms_before"]
    check_candidates(js)


def check_candidates(js: dict) -> None:
    """The candidates table of a planar calibrate JSON: every effect alone, every pair, each geometric group
    alone, each with a held-out error and a score; when a geometric group beats the declared model (a port
    offset looks like a tracker registration), that group with each physical effect too."""
    cands = js["candidates"]
    singles = {c["name"] for c in cands if len(c["effects"]) == 1}
    geo = {"link_length", "instrument_length", "tracker_registration", "backlash"}
    assert singles == set(TRUTHS) | geo | {"tracker_latency"}
    phys = [c for c in cands if len(c["effects"]) == 2 and not set(c["effects"]) & geo]
    assert sum("tracker_latency" not in c["effects"] for c in phys) == 15
    # tracker_latency joins the combinations only when it alone beats the declared model
    lat = sum("tracker_latency" in c["effects"] for c in phys)
    assert lat in (0, 6)
    mixed = [c for c in cands if len(c["effects"]) == 2 and set(c["effects"]) & geo]
    assert len(mixed) in (0, 7 if lat else 6) and len({e for c in mixed for e in c["effects"]} & geo) <= 1
    assert all(c["heldout_rms"] is not None and math.isfinite(c["bic"]) for c in cands)


def test_noise_only_selects_nothing(port):
    data = bench(port, {}, 31)
    rep = calibrate(port, data, seed=2, folds=FOLDS)
    assert rep.selected == [] and rep.parameters == {}
    assert rep.explained
    assert rep.fit_errors.pose_after == rep.fit_errors.pose_before
    assert rep.noise.sigma == pytest.approx(port.sensors.tracker_sigma, rel=0.06)
    # the best single effect does not pay for its two parameters
    best = min((c for c in rep.candidates if c.effects), key=lambda c: c.bic)
    none = next(c for c in rep.candidates if not c.effects)
    assert best.bic > none.bic


@dataclass(frozen=True)
class ScaledTracker(Plant):
    """A tracker whose scale is off by ``scale`` about ``centre``: a tip-position-dependent bias."""

    scale: float = 0.0
    centre: tuple = (0.0, 0.30)

    def tip(self, q_enc, u=None):
        t = super().tip(q_enc, u)
        return t + self.scale * (t - np.asarray(self.centre))


# a link-length error (a changed scenario, not the effect) found by the geometric group link_length, and not
# explained by the physical catalogue alone: tests/test_geometry_effects.py
# (test_link_length_found_on_a_bench_with_longer_links)
def test_tracker_scale_error_is_not_explained(port):
    base = Plant.from_model(build_arm(port), noise=True)
    truth = ScaledTracker(**{f: getattr(base, f) for f in base.__dataclass_fields__}, scale=0.015)
    data = bench(port, {}, 42, plant=truth)
    rep = calibrate(port, data, seed=0, folds=FOLDS)
    assert not rep.explained
    assert rep.structure.structured_rms > rep.noise.sigma


# ----------------------------------------------------------------------------- the regime
# A P1-style bench whose controller's port estimate is about 1 cm off the declared port (here
# (+10, +5) mm, 11.2 mm) at gain 0.05 (40 runs from 5 starts, up to 60 steps each): where the
# controller's Jacobian is wrong, the motion a command produces differs from the desired direction
# by up to phi_max, and port friction opposes the motion that happens (docs/physics.md).
ONE_CM_ESTIMATE = (0.010, 0.165)
ONE_CM_TRUTHS = dict(TRUTHS, port_friction={"fa": 0.002, "fn": 0.0012})


def one_cm(sc, estimate=ONE_CM_ESTIMATE, gain=0.05):
    from errplan.scenario import Port

    return sc.with_(port=Port(sc.port.position, tuple(estimate)), controller=replace(sc.controller, gain=gain))


def check_done_json(js: dict, truth: dict) -> None:
    """The issue's "done means", on the calibrate JSON (interfaces.md's keys): exactly the bench's
    effects, each parameter within 2.5 sigma and 25 %, the pose residual within 10 % of the noise
    floor, the replayed trajectory error cut by at least 30 % (held-out validation file), and
    explained."""
    assert sorted(js["selected"]) == sorted(truth), js["selected"]
    for e, ps in truth.items():
        for p, v in ps.items():
            got, sig = js["parameters"][e][p], js["uncertainty"][e][p]
            assert 0 < sig < math.inf
            assert abs(got - v) < 2.5 * sig and abs(got - v) < 0.25 * abs(v), f"{e}.{p}: {got:.6g} +- {sig:.3g}, true {v}"
    assert js["errors_on"] == "validation" and js["validation"]["pose_rms_after"] == js["pose_rms_after"]
    assert js["pose_rms_after"] <= 1.1 * js["noise_floor"] < js["pose_rms_before"]
    assert js["trajectory_rms_after"] <= 0.7 * js["trajectory_rms_before"]
    assert js["explained"] is True


def check_done(rep, truth: dict) -> None:
    """:func:`check_done_json` on a report (the errors on its held-out validation file)."""
    assert rep.validation_errors is rep.errors
    check_done_json(rep.to_json(), truth)


# port friction on this bench (seeds 11 and 12) is calibrated through the command line:
# test_cli_friction_bench_end_to_end, with the same checks on its JSON
@pytest.mark.slow
@pytest.mark.parametrize("effect", [e for e in ONE_CM_TRUTHS if e != "port_friction"])
def test_each_effect_on_a_one_cm_bench(port, effect):
    sc = one_cm(port)
    truth = {effect: ONE_CM_TRUTHS[effect]}
    rep = calibrate(sc, bench(sc, truth, 11), validate=bench(sc, truth, 12), seed=0, folds=FOLDS)
    check_done(rep, truth)
    check_candidates(rep.to_json())


@pytest.mark.parametrize("pair", [
    ("gravity_sag", "port_friction"),
    pytest.param(("port_offset", "port_friction"), marks=pytest.mark.slow),
    pytest.param(("shaft_flexion", "port_friction"), marks=pytest.mark.slow),
    pytest.param(("joint_offset", "tracker_offset"), marks=pytest.mark.slow),
])
def test_two_effects_on_a_one_cm_bench(port, pair):
    """Two effects at once (the first pair: P1's suspects, gravity without compensation and friction at
    the port): the done-means checks, and a single effect cannot explain them: each single predicts the
    held-out runs far worse than the pair."""
    sc = one_cm(port)
    truth = {e: ONE_CM_TRUTHS[e] for e in pair}
    rep = calibrate(sc, bench(sc, truth, 11), validate=bench(sc, truth, 12), seed=1, folds=FOLDS)
    check_done(rep, truth)
    by = {tuple(sorted(c.effects)): c for c in rep.candidates}
    both = by[tuple(sorted(pair))]
    for e in pair:
        assert by[(e,)].heldout_rms > 1.5 * both.heldout_rms, (e, by[(e,)].heldout_rms, both.heldout_rms)


@pytest.mark.slow
@pytest.mark.parametrize("estimate,gain", [((0.0, 0.149), 0.05), ((-0.008, 0.168), 0.3)])
def test_friction_on_other_one_cm_benches(port, estimate, gain):
    """The estimate off along other directions, and a faster gain."""
    sc = one_cm(port, estimate, gain)
    truth = {"port_friction": ONE_CM_TRUTHS["port_friction"]}
    rep = calibrate(sc, bench(sc, truth, 31), validate=bench(sc, truth, 32), seed=0, folds=FOLDS)
    check_done(rep, truth)


@pytest.mark.slow
def test_stated_sigmas_match_the_spread_over_benches(port):
    """The 2.5-sigma criterion is only meaningful if the stated sigmas are honest: over 10 benches
    (different noise seeds) the z-scores of gravity sag + friction have an RMS near 1 (a 5-parameter
    fit has a few % chance of one |z| > 2.5 on any single bench)."""
    from errplan.effects import EffectModel, GravitySag, PortFriction

    sc = one_cm(port)
    truth = {"gravity_sag": ONE_CM_TRUTHS["gravity_sag"], "port_friction": ONE_CM_TRUTHS["port_friction"]}
    tv = np.array([v for ps in truth.values() for v in ps.values()])
    z = []
    for seed in range(100, 110):
        d = bench(sc, truth, seed)
        m = EffectModel([GravitySag(), PortFriction()]).fit(d.q, d.commanded_directions(motion_model(sc)), d.tip,
                                                            declared_plant(sc))
        z.append((m.values_ - tv) / m.sigma_)
    z = np.array(z)
    rms_z = np.sqrt(np.mean(z ** 2, axis=0))
    assert np.all((rms_z > 0.5) & (rms_z < 1.6)), rms_z
    assert np.abs(z).max() < 4.0


def test_noise_only_on_a_one_cm_bench_selects_nothing(port):
    sc = one_cm(port)
    rep = calibrate(sc, bench(sc, {}, 33), seed=0, folds=FOLDS)
    assert rep.selected == [] and rep.explained
    assert rep.noise.sigma == pytest.approx(sc.sensors.tracker_sigma, rel=0.06)


def test_friction_fit_uses_the_motion_not_the_desired_direction(port):
    """On the friction bench the true model fits to the noise with the motion direction (what
    calibrate uses) and not with the desired direction: the fit of friction alone with the old u
    leaves a residual well above the noise floor (what the issue saw: 1.7x)."""
    from errplan.effects import EffectModel, PortFriction

    sc = one_cm(port)
    truth = {"port_friction": ONE_CM_TRUTHS["port_friction"]}
    d = bench(sc, truth, 11)
    base = declared_plant(sc)
    u = d.commanded_directions(motion_model(sc))
    good = EffectModel([PortFriction()]).fit(d.q, u, d.tip, base)
    err = d.target - d.tip
    old = np.zeros_like(u)
    old[1:] = (err / np.linalg.norm(err, axis=1)[:, None])[:-1]
    old[d.step == 0] = 0.0
    bad = EffectModel([PortFriction()]).fit(d.q, old, d.tip, base)
    sigma = sc.sensors.tracker_sigma
    assert math.sqrt(good.rss_ / (2 * d.rows)) == pytest.approx(sigma, rel=0.05)
    assert math.sqrt(bad.rss_ / (2 * d.rows)) > 1.3 * sigma
    assert good.values_ == pytest.approx([0.002, 0.0012], rel=0.02)


def test_cli_friction_bench_end_to_end(tmp_path):
    """errplan experiment + errplan calibrate on files, as in docs/calibration.md's friction example: the
    one-cm bench of test_each_effect_on_a_one_cm_bench with port friction (the same seeds and starts), and
    its checks on the command's JSON."""
    doc = tomllib.loads(PORT.read_text())
    doc["port"]["estimate"] = list(ONE_CM_ESTIMATE)
    doc["controller"]["gain"] = 0.05
    declared = tmp_path / "declared.toml"
    declared.write_text(to_toml(doc))
    doc["effects"] = {"port_friction": dict(ONE_CM_TRUTHS["port_friction"])}
    truth = tmp_path / "truth.toml"
    truth.write_text(to_toml(doc))
    for seed, name in ((11, "bench.csv"), (12, "val.csv")):
        assert main(["-q", "experiment", str(truth), "--out", str(tmp_path / name), "--seed", str(seed),
                     "--starts", str(STARTS)]) == 0
    assert main(["-q", "calibrate", str(declared), str(tmp_path / "bench.csv"), "--validate", str(tmp_path / "val.csv"),
                 "--json", str(tmp_path / "cal.json"), "--no-task"]) == 0
    js = json.loads((tmp_path / "cal.json").read_text())
    check_done_json(js, {"port_friction": ONE_CM_TRUTHS["port_friction"]})
    check_candidates(js)


# ----------------------------------------------------------------------------- pieces
@pytest.mark.parametrize("effect", [None, "gravity_sag", "port_friction"])
def test_noise_floor_estimates_the_tracker_sigma(port, effect):
    """Model-free: from the declared model's residual, even with a large effect in it."""
    truth = {effect: TRUTHS[effect]} if effect else {}
    for sigma in (1e-4, 4e-4):
        sc = port.with_(sensors=replace(port.sensors, tracker_sigma=sigma))
        d = bench(sc, truth, 51)
        base = declared_plant(port)
        u = d.commanded_directions(motion_model(port))
        nf = noise_floor(pose_residual(d, base, u), predict_tracked(base, d.q, u), u)
        assert nf.sigma == pytest.approx(sigma, rel=0.08)


def test_structure_test_sees_a_smooth_field_and_not_noise(port):
    d = bench(port, {}, 52)
    base = declared_plant(port)
    u = d.commanded_directions(motion_model(port))
    x = predict_tracked(base, d.q, u)
    rng = np.random.default_rng(0)
    noise = rng.normal(0, 2e-4, x.shape)
    nf = noise_floor(noise, x, u)
    assert not structure_test(noise, u, nf).structured
    smooth = 4e-4 * np.stack([np.sin(30 * x[:, 0]), np.cos(20 * x[:, 1])], -1)
    st = structure_test(noise + smooth, u, nf)
    assert st.structured and st.structured_rms == pytest.approx(np.sqrt(np.mean((smooth - smooth.mean(0)) ** 2)), rel=0.3)


def test_batched_replay_equals_simulate(port):
    """The calibration's replay of every run at once matches simulation.simulate run by run."""
    sc = port.with_(effects={"port_friction": {"fa": 0.001, "fn": 0.0005}, "gravity_sag": {"c1": 0.002, "c2": 0.0, "c3": 0.0}})
    d = bench(sc, sc.effects, 53)
    plant = Plant.from_model(build_arm(sc))
    ctrl = bench_controller(sc)
    pred, alive = replay(d, plant, ctrl)
    for r in range(0, d.runs, 5):
        m = d.run == r
        q0 = d.q[m][0]
        res = simulate(plant, ctrl, q0, d.target[m][:1], d.gain[m][0], tolerance=1e-300, max_steps=int(m.sum()) - 1)
        n = min(len(res.tracked), m.sum())
        assert np.allclose(pred[m][:n], res.tracked[:n], atol=1e-12)


def test_approach_mask():
    text = "run,step,target_y,target_z,gain,q1,q2,tip_y,tip_z\n" + "".join(
        f"a,{i},0,0.34,1,0,0,0,{0.34 - e}\n" for i, e in enumerate([0.02, 0.01, 0.0004, 0.002, 0.0001]))
    d = parse_measured_csv(text)
    m, out = approach_mask(d, 5e-4)
    assert m.tolist() == [False, True, True, False, False] and out.tolist() == [False]
    m, out = approach_mask(d, 1e-6)  # never arrives, never moves away: a slow run, all of it counts
    assert m.tolist() == [False, True, True, True, True] and out.tolist() == [False]
    # 40 mm away after the first command only, then closing in: friction's lag as the tip starts to
    # move (a one-off jump of at most the friction's size), the run converges and counts whole
    lag = text.replace("a,1,0,0.34,1,0,0,0,0.33", "a,1,0,0.34,1,0,0,0,0.30")
    m, out = approach_mask(parse_measured_csv(lag), 1e-6)
    assert m.tolist() == [False, True, True, True, True] and out.tolist() == [False]
    # farther than at the start after a later command: diverged or cycling, left out
    grows = text.replace("a,3,0,0.34,1,0,0,0,0.338", "a,3,0,0.34,1,0,0,0,0.29")
    m, out = approach_mask(parse_measured_csv(grows), 1e-6)
    assert not m.any() and out.tolist() == [True]


def test_data_from_another_scenario_is_refused(port):
    doc = tomllib.loads(PORT.read_text())
    doc["port"] = {"position": [0.0, 0.45], "estimate": [0.0, 0.45]}
    short = parse_scenario(doc, "far port")
    d = bench(port, {}, 54)
    with pytest.raises(DataError, match="row"):
        check_against_model(d, declared_plant(short))


def test_tiny_data_still_calibrates(port):
    text = ("run,step,target_y,target_z,gain,q1,q2,tip_y,tip_z\n"
            "a,0,0,0.34,1,0,0,0.0001,0.3201\n"
            "a,1,0,0.34,1,0.02,0.05,-0.0065,0.3371\n"
            "b,0,0.02,0.32,1,0,0,-0.0001,0.3199\n"
            "b,1,0.02,0.32,1,0.05,0.02,0.0151,0.3221\n")
    rep = calibrate(port, parse_measured_csv(text), seed=0)
    json.dumps(rep.to_json(), allow_nan=False)


def test_toml_writer_round_trips_every_bundled_scenario():
    for f in sorted((ROOT / "scenarios").glob("*.toml")):
        doc = tomllib.loads(f.read_text())
        assert tomllib.loads(to_toml(doc, "header\nline")) == doc
    odd = {"name": 'q"uote\\ \n', "a": {"b": {"c": [1, 2.5, True]}, "d": 1}, "t": [{"x": {"y": [1.0]}, "z": "w"}]}
    assert tomllib.loads(to_toml(odd)) == odd


# ----------------------------------------------------------------------------- CLI
@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("cal")
    sc_text = PORT.read_text() + "\n[effects.gravity_sag]\nc1 = 0.004\nc2 = 0.002\nc3 = 0.003\n"
    truth = d / "truth.toml"
    truth.write_text(sc_text)
    # the bench of test_each_catalogue_effect_is_found: bench(port, truth, 11) and bench(port, truth, 12)
    assert main(["-q", "experiment", str(truth), "--out", str(d / "data.csv"), "--seed", "11", "--starts", str(STARTS)]) == 0
    assert main(["-q", "experiment", str(truth), "--out", str(d / "val.csv"), "--seed", "12", "--starts", str(STARTS)]) == 0
    rc = main(["-q", "calibrate", str(PORT), str(d / "data.csv"), "--validate", str(d / "val.csv"),
               "--json", str(d / "cal.json"), "--record", str(d / "cal.rrd"), "--export-scenario", str(d / "fixed.toml"),
               "--no-task"])
    return rc, d


def test_cli_calibrate_outputs(cli_run, capsys):
    rc, d = cli_run
    assert rc == 0
    js = json.loads((d / "cal.json").read_text())
    for k in ("selected", "explained", "parameters", "noise_floor", "pose_rms_before", "pose_rms_after",
              "trajectory_rms_before", "trajectory_rms_after", "candidates"):
        assert k in js, k
    assert js["selected"] == ["gravity_sag"] and js["explained"] is True
    assert js["errors_on"] == "validation" and js["validation"]["rows"] > 0
    for c in js["candidates"]:
        assert {"effects", "parameters", "uncertainty", "heldout_rms", "bic", "score", "identifiable", "selectable"} <= set(c)
    assert js["pose_rms_after"] < 0.1 * js["pose_rms_before"]
    # the exported scenario reads back with the found effect, and otherwise equals the original
    fixed = load_scenario(d / "fixed.toml")
    orig = load_scenario(PORT)
    assert set(fixed.effects) == {"gravity_sag"}
    assert fixed.effects["gravity_sag"] == pytest.approx(js["parameters"]["gravity_sag"])
    for t in ("robot", "instrument", "port", "controller", "sensors", "fields", "planner", "queries", "tolerances"):
        assert getattr(fixed, t) == getattr(orig, t), t
    # no temporary files left
    assert not list(d.glob("*.part"))


def test_cli_calibrate_finds_the_gravity_sag(cli_run):
    """test_each_catalogue_effect_is_found's checks for the gravity sag, on the command's JSON."""
    rc, d = cli_run
    assert rc == 0
    check_found(json.loads((d / "cal.json").read_text()), {"gravity_sag": TRUTHS["gravity_sag"]})


def test_cli_calibrate_against_the_corrected_model_selects_nothing(cli_run, tmp_path):
    _, d = cli_run
    assert main(["-q", "calibrate", str(d / "fixed.toml"), str(d / "data.csv"), "--json", str(tmp_path / "again.json"),
                 "--no-task"]) == 0
    js = json.loads((tmp_path / "again.json").read_text())
    assert js["selected"] == [] and js["explained"] is True


def test_cli_recording_reads_back(cli_run):
    import os
    import shutil
    import subprocess
    import sys

    import rerun.chunk as rrc

    _, d = cli_run
    path = d / "cal.rrd"
    exe = shutil.which("rerun")
    cmd = [exe] if exe else [sys.executable, "-m", "rerun_cli"]
    p = subprocess.run(cmd + ["rrd", "verify", str(path)], env=dict(os.environ, CI="1"), capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    ents = {c.entity_path for c in rrc.RrdReader(path).stream().to_chunks()}
    for e in ("/plane/residual/before", "/plane/residual/after", "/plane/residual_map/before",
              "/plane/residual_map/after", "/plane/replay/measured", "/plane/replay/after", "/summary"):
        assert e in ents, e


BAD_CSV = {
    "missing_column": ("run,step,target_y,target_z,gain,q1,q2,tip_y\na,0,0,0.34,1,0,0,0\n", "tip_z"),
    "nan": ("run,step,target_y,target_z,gain,q1,q2,tip_y,tip_z\na,0,0,0.34,1,0,0,0,0.32\na,1,0,0.34,1,0,nan,0,0.33\n",
            "row 2 column 'q2': value 'nan'"),
    "text": ("run,step,target_y,target_z,gain,q1,q2,tip_y,tip_z\na,0,0,0.34,1,0,0,0,0.32\na,1,0,0.34,1,0,0,x1,0.33\n",
             "row 2 column 'tip_y': value 'x1'"),
    "empty": ("", "empty"),
    "short_run": ("run,step,target_y,target_z,gain,q1,q2,tip_y,tip_z\na,0,0,0.34,1,0,0,0,0.32\n", "run 'a' has 1 step"),
}


@pytest.mark.parametrize("case", list(BAD_CSV))
def test_cli_csv_errors_exit_2_and_write_nothing(tmp_path, capsys, case):
    text, needle = BAD_CSV[case]
    bad = tmp_path / "bad.csv"
    bad.write_text(text)
    outs = [tmp_path / "o.json", tmp_path / "o.rrd", tmp_path / "o.toml"]
    rc = main(["calibrate", str(PORT), str(bad), "--json", str(outs[0]), "--record", str(outs[1]),
               "--export-scenario", str(outs[2])])
    err = capsys.readouterr().err
    assert rc == 2 and needle in err and err.count("\n") == 1
    assert not any(p.exists() for p in outs) and not list(tmp_path.glob("*.part"))


def test_cli_bad_validation_file_and_output_dir(tmp_path, capsys, cli_run):
    _, d = cli_run
    assert main(["calibrate", str(PORT), str(d / "data.csv"), "--validate", str(tmp_path / "none.csv"),
                 "--json", str(tmp_path / "o.json")]) == 2
    assert "not found" in capsys.readouterr().err and not (tmp_path / "o.json").exists()
    assert main(["calibrate", str(PORT), str(d / "data.csv"), "--json", str(tmp_path / "no" / "o.json")]) == 2
    assert main(["calibrate", str(PORT), str(d / "data.csv"), "--folds", "1"]) == 2


def test_a_declared_effect_is_corrected_not_replaced(port):
    """The scenario declares part of the gravity sag: the report gives the bench's values (declared +
    fitted) and the exported effects equal them."""
    truth = {"gravity_sag": TRUTHS["gravity_sag"]}
    data = bench(port, truth, 61)
    declared = port.with_(effects={"gravity_sag": {"c1": 0.002, "c2": 0.002, "c3": 0.0}})
    rep = calibrate(declared, data, seed=0, folds=FOLDS)
    assert rep.selected == ["gravity_sag"]
    check_recovery(rep, truth)
    assert rep.fitted["gravity_sag"]["c3"] == pytest.approx(rep.parameters["gravity_sag"]["c3"])
    assert rep.fitted["gravity_sag"]["c1"] == pytest.approx(rep.parameters["gravity_sag"]["c1"] - 0.002)
    assert rep.effects_table() == rep.parameters


# ----------------------------------------------------------------------------- spatial (issue 13)
# The bundled PHANToM with a waist (3-D, a URDF with inertial data, the waist a vertical axis) as a
# bench: its controller's port estimate (8, 4, 8) mm off the declared port at gain 0.3, so that the
# paths take several steps and the replayed trajectory has something to follow; SPATIAL_STARTS starts x 14
# targets. The truths use the spatial parametrisation of docs/physics.md.
SPATIAL = ROOT / "scenarios" / "phantom15_spatial.toml"
SPATIAL_GRAVITY = {"gravity_sag": {"c2": 0.05, "c3": 0.08}}
SPATIAL_TRUTHS = {
    "port_offset": {"dx": 0.002, "dy": 0.003, "dz": -0.002},
    "joint_offset": {"dq1": 0.003, "dq2": -0.002, "dq3": 0.002},
    "tracker_offset": {"bx": 0.001, "by": 0.002, "bz": -0.0015},
    "gravity_sag": SPATIAL_GRAVITY["gravity_sag"],
    "shaft_flexion": {"fx": 1.0, "fy": 2.0, "fz": 0.5},
    "port_friction": {"fa": 0.0015, "fn": 0.001},
}


@pytest.fixture(scope="module")
def spatial():
    from errplan.scenario import Port

    sc = load_scenario(SPATIAL)
    return sc.with_(port=Port(sc.port.position, (0.008, 0.004, 0.168)), controller=replace(sc.controller, gain=0.3))


#: starts of the spatial bench (x 14 targets): each effect found within 2.5 sigma and 25 % on 3 as on 4 (the
#: shaft-length error needs 4 for its structured residual to stand above the noise floor)
SPATIAL_STARTS = 3


def spatial_bench(sc, effects, seed, plant=None, starts=SPATIAL_STARTS):
    return run_experiment(sc.with_(effects=effects), seed=seed, n_starts=starts, plant=plant).data


def _spatial_effects():
    # gravity sag on this bench (the same seeds and starts) is calibrated through the command line:
    # test_cli_spatial_calibration_end_to_end, with the same checks on its JSON
    for e in SPATIAL_TRUTHS:
        if e != "gravity_sag":
            yield e if e == "port_friction" else pytest.param(e, marks=pytest.mark.slow)


@pytest.mark.parametrize("effect", list(_spatial_effects()))
def test_each_spatial_effect_is_found(spatial, effect):
    truth = {effect: SPATIAL_TRUTHS[effect]}
    data, val = spatial_bench(spatial, truth, 13), spatial_bench(spatial, truth, 14)
    assert data.dim == 3 and data.n_joints == 3
    rep = calibrate(spatial, data, validate=val, seed=0, folds=FOLDS)
    check_done(rep, truth)


def test_two_spatial_effects_at_once(spatial):
    truth = {"gravity_sag": SPATIAL_TRUTHS["gravity_sag"], "port_friction": {"fa": 0.001, "fn": 0.0008}}
    rep = calibrate(spatial, spatial_bench(spatial, truth, 21), validate=spatial_bench(spatial, truth, 22), seed=1,
                    folds=FOLDS)
    check_done(rep, truth)


def test_spatial_noise_only_selects_nothing(spatial):
    rep = calibrate(spatial, spatial_bench(spatial, {}, 31), seed=2, folds=FOLDS)
    assert rep.selected == [] and rep.explained
    assert rep.noise.sigma == pytest.approx(spatial.sensors.tracker_sigma, rel=0.08)


@pytest.mark.slow
def test_spatial_shaft_length_error_is_not_explained_by_the_physical_catalogue(spatial):
    """The shaft 4 mm longer than declared is in no physical effect (instrument_length finds it:
    tests/test_geometry_effects.py)."""
    from errplan.experiment import truth_plant

    plant = truth_plant(spatial).with_(length=spatial.instrument.length + 0.004)
    rep = calibrate(spatial, spatial_bench(spatial, {}, 41, plant=plant, starts=4), seed=0, folds=FOLDS,
                    effects=list(SPATIAL_TRUTHS))
    assert not rep.explained and rep.structure.p_value < 1e-3 and rep.structure.structured_rms > rep.noise.sigma
    assert rep.to_json()["explained"] is False


def test_spatial_noise_floor_and_csv_round_trip(spatial, tmp_path):
    from errplan.experiment import csv_columns, read_measured_csv

    truth = {"joint_offset": SPATIAL_TRUTHS["joint_offset"]}
    data = spatial_bench(spatial, truth, 5)
    p = tmp_path / "b.csv"
    data.write_csv(p)
    assert p.read_text().splitlines()[0] == ",".join(csv_columns(3, 3))
    back = read_measured_csv(p, spatial)
    assert back.rows == data.rows and np.allclose(back.q, data.q, atol=1e-11) and np.allclose(back.tip, data.tip, atol=1e-12)
    base = declared_plant(spatial)
    u = data.commanded_directions(motion_model(spatial))
    r = pose_residual(data, base, u)
    nf = noise_floor(r, predict_tracked(base, data.q, u), u)
    assert nf.sigma == pytest.approx(spatial.sensors.tracker_sigma, rel=0.08)
    with pytest.raises(DataError, match="spatial columns"):  # a planar scenario refuses the 3-D file
        read_measured_csv(p, load_scenario(PORT))


def test_spatial_batched_replay_equals_simulate(spatial):
    """The calibration's replay of every run at once matches simulation.simulate run by run (3-D)."""
    sc = spatial.with_(effects={"gravity_sag": SPATIAL_TRUTHS["gravity_sag"]})
    truth = Plant.from_model(build_arm(sc), effects=True, noise=False)
    data = run_experiment(sc, plant=truth, n_starts=1).data
    ctrl = bench_controller(sc)
    pred, alive = replay(data, truth, ctrl, motion_model(sc))
    assert np.all(alive)
    assert np.max(np.abs(pred - data.tip)) < 1e-9


def test_calibrate_on_a_urdf_without_inertial_data(tmp_path, capsys):
    """A URDF without inertial data (the UR5 of example-robot-data with its inertial elements removed, as
    many a user's description is, the Omni's for one): no generalized gravity. The default catalogue
    leaves gravity sag out and says so; asking for it is one clear error."""
    import re
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from arms import UR5_ESTIMATE, UR5_PORT, arm_scenario
    from errplan.packages import resolve_package_uri

    text = resolve_package_uri("package://ur_description/urdf/ur5_joint_limited_robot.urdf").read_text()
    bare = re.sub(r"<inertial>.*?</inertial>", "", text, flags=re.S)
    assert "<inertial>" in text and "<inertial>" not in bare
    (tmp_path / "ur5_bare.urdf").write_text(bare, encoding="utf-8")
    omni = arm_scenario(tmp_path, "ur5", UR5_PORT, UR5_ESTIMATE, "[controller]\ngain = 0.5\n", name="bare")
    omni.write_text(omni.read_text().replace("package://ur_description/urdf/ur5_joint_limited_robot.urdf",
                                             "ur5_bare.urdf"), encoding="utf-8")
    sc = load_scenario(omni)
    sc = sc.with_(controller=replace(sc.controller, gain=0.5))
    data = run_experiment(sc.with_(effects={"tracker_offset": {"bx": 0.001, "by": 0.0, "bz": 0.0}}), seed=1,
                          n_starts=2).data
    rep = calibrate(sc, data, seed=0, folds=FOLDS)
    assert rep.selected == ["tracker_offset"]
    assert "gravity_sag" not in {e for c in rep.candidates for e in c.effects}
    assert any("inertial" in s for s in rep.skipped) and "not tried: gravity_sag" in rep.text()
    from errplan.errors import ErrplanError

    with pytest.raises(ErrplanError, match="inertial"):
        calibrate(sc, data, effects=["gravity_sag"])
    p = tmp_path / "omni.csv"
    data.write_csv(p)
    assert main(["-q", "calibrate", str(omni), str(p), "--effects", "gravity_sag,tracker_offset"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "inertial" in err


def spatial_bench_files(d: Path, effects: str = "") -> tuple[Path, Path]:
    """The spatial bench as files: the declared scenario and the bench's truth (declared + effects)."""
    text = SPATIAL.read_text(encoding="utf-8")
    text = text.replace('urdf = "phantom15.urdf"', f'urdf = "{ROOT / "scenarios" / "phantom15.urdf"}"')
    text = text.replace("estimate = [0.0, 0.0, 0.160]", "estimate = [0.008, 0.004, 0.168]")
    text = text.replace("gain = 1.0", "gain = 0.3")
    assert "0.008, 0.004, 0.168" in text and "gain = 0.3" in text
    declared, truth = d / "declared.toml", d / "truth.toml"
    declared.write_text(text, encoding="utf-8")
    # [effects] before the arrays of tables
    i = text.index("[[query]]")
    truth.write_text(text[:i] + effects + "\n" + text[i:], encoding="utf-8")
    return declared, truth


@pytest.mark.slow
def test_cli_spatial_calibration_end_to_end(tmp_path, capsys):
    """errplan experiment + errplan calibrate on 3-D files (the spatial bench of
    test_each_spatial_effect_is_found with the gravity sag: the same seeds and starts, and its checks):
    the JSON, the 3-D recording (robot, residual arrows before and after, replays), the corrected
    scenario (reads back; calibrating against it selects nothing)."""
    import rerun.chunk as rrc

    declared, truth = spatial_bench_files(tmp_path, "[effects.gravity_sag]\nc2 = 0.05\nc3 = 0.08\n")
    for name, seed in (("data.csv", "13"), ("val.csv", "14")):
        assert main(["-q", "experiment", str(truth), "--out", str(tmp_path / name), "--seed", seed,
                     "--starts", str(SPATIAL_STARTS)]) == 0
    assert (tmp_path / "data.csv").read_text().splitlines()[0].startswith("run,step,target_x,target_y,target_z,gain,q1,q2,q3")
    capsys.readouterr()
    assert main(["-q", "calibrate", str(declared), str(tmp_path / "data.csv"), "--validate", str(tmp_path / "val.csv"),
                 "--json", str(tmp_path / "cal.json"), "--record", str(tmp_path / "cal.rrd"),
                 "--export-scenario", str(tmp_path / "fixed.toml"), "--folds", str(FOLDS), "--no-task"]) == 0
    out = capsys.readouterr().out
    assert "not identifiable" in out and "identifiability of the catalogue on these rows" in out
    js = json.loads((tmp_path / "cal.json").read_text())
    assert js["selected"] == ["gravity_sag"] and js["explained"] is True and js["selection"]["folds"] == FOLDS
    check_done_json(js, {"gravity_sag": SPATIAL_TRUTHS["gravity_sag"]})
    # the waist turns about the vertical: its generalized gravity is identically zero, so c1 is
    # reported as not identifiable, not as a number
    assert js["parameters"]["gravity_sag"]["c1"] is None and js["uncertainty"]["gravity_sag"]["c1"] is None
    assert "c1" in js["not_identifiable"]["gravity_sag"] and "waist" in js["not_identifiable_why"]["gravity_sag.c1"]
    assert js["parameters"]["gravity_sag"]["c2"] == pytest.approx(0.05, rel=0.05)
    assert js["trajectory_rms_after"] < 0.7 * js["trajectory_rms_before"]
    assert js["identifiability"]["confused_pairs"]
    ents = {c.entity_path for c in rrc.RrdReader(tmp_path / "cal.rrd").stream().to_chunks()}
    for e in ("/world/residual/before", "/world/residual/after", "/world/residual_map/after", "/world/replay/measured",
              "/world/replay/after", "/world/robot/links", "/world/port/true", "/summary"):
        assert e in ents, e
    # the corrected scenario holds the identifiable parameters and reads back
    assert set(tomllib.loads((tmp_path / "fixed.toml").read_text())["effects"]["gravity_sag"]) == {"c2", "c3"}
    fixed = load_scenario(tmp_path / "fixed.toml")
    assert fixed.dim == 3 and set(fixed.effects["gravity_sag"]) == {"c1", "c2", "c3"}
    assert fixed.effects["gravity_sag"]["c1"] == 0.0
    assert main(["-q", "calibrate", str(tmp_path / "fixed.toml"), str(tmp_path / "val.csv"), "--json",
                 str(tmp_path / "again.json"), "--folds", str(FOLDS), "--no-task"]) == 0
    assert json.loads((tmp_path / "again.json").read_text())["selected"] == []


def test_a_correlated_pair_that_fits_best_is_selected_with_a_warning():
    """Selection: a candidate flagged only for correlation wins when both its BIC and its held-out
    error beat every identifiable candidate; otherwise the identifiable one stays."""
    from errplan.calibration import Candidate, select
    from errplan.effects import EffectModel, make_effect

    def cand(names, bic, ho, ok, weak=False):
        m = EffectModel([make_effect(n) for n in names])
        m.why_ = "" if ok else "joint_offset.dq1 and gravity_sag.c1 correlate +0.9990"
        return Candidate(m, 0.0, bic, ho, ok, weak=weak)

    def cands(pair_bic, pair_ho):
        return {(): cand([], 0.0, 1.0, True), ("joint_offset",): cand(["joint_offset"], -100.0, 0.5, True),
                ("gravity_sag",): cand(["gravity_sag"], -90.0, 0.6, True),
                ("joint_offset", "tracker_offset"): cand(["joint_offset", "tracker_offset"], -150.0, 0.3, True),
                ("joint_offset", "gravity_sag"): cand(["joint_offset", "gravity_sag"], pair_bic, pair_ho, False, True)}

    c = cands(-200.0, 0.2)
    chosen = select(c)
    assert chosen.effects == ["joint_offset", "gravity_sag"] and "poorly identifiable" in chosen.note
    assert select(cands(-200.0, 0.35)).effects == ["joint_offset", "tracker_offset"]  # predicts worse: no
    assert select(cands(-120.0, 0.2)).effects == ["joint_offset", "tracker_offset"]   # BIC worse: no
    c = cands(-200.0, 0.2)
    c[("joint_offset", "gravity_sag")].weak = False                                   # truly singular: never
    assert select(c).effects == ["joint_offset", "tracker_offset"]


@pytest.mark.slow
def test_spatial_pair_the_default_bench_confuses_is_still_found(spatial):
    """joint offset and gravity sag correlate at 0.998 on the spatial bench (as at 0.999 on the default
    bench's 8 starts): calibrate selects both (the best fit and prediction), recovers them within 2.5 sigma
    and 25 %, and warns."""
    truth = {"joint_offset": SPATIAL_TRUTHS["joint_offset"], "gravity_sag": SPATIAL_TRUTHS["gravity_sag"]}
    rep = calibrate(spatial, spatial_bench(spatial, truth, 11), validate=spatial_bench(spatial, truth, 12), seed=0, folds=FOLDS)
    assert rep.bench["confused_pairs"]["joint_offset+gravity_sag"] > 0.995
    check_done(rep, truth)
    assert "warning" in rep.text() and "--design" in rep.text()


@pytest.mark.slow
def test_runs_through_the_port_neighbourhood_are_left_out_not_fatal(tmp_path):
    """A URDF errplan ships nothing for (tests/test_urdf.py's toy, prismatic last joint) with a large
    gravity sag: some bench runs drive the wrist within millimetres of the port, where the lever's
    tip direction is undefined and a tracked tip can lie farther than the shaft from the model's.
    Those runs are left out, each with its reason in the report and the JSON; the rest still finds
    the sag, within 2.5 sigma and 25 %. A corrupted tip in a run that stays away from the port is
    still one error."""
    from test_urdf import toy_scenario

    port = (0.547, 0.0409, 0.6555)
    sc = load_scenario(toy_scenario(tmp_path, port, port, "[controller]\ngain = 0.5\n[sensors]\ntracker_sigma = 0.0002\n"))
    truth = {"gravity_sag": {"c1": 0.05, "c2": 0.05, "c3": 0.001}}
    data = run_experiment(sc.with_(effects=truth), seed=11).data
    rep = calibrate(sc, data, seed=0, folds=FOLDS)
    # the sag is deliberately far beyond a plausible one (more than 20 mrad at the joints' RMS gravity torque):
    # the verdict says so, condition (c) alone, while the residual is at the noise floor without structure
    assert rep.selected == ["gravity_sag"] and not rep.explained and rep.verdict["failed"] == ["c"], rep.verdict
    assert {"gravity_sag.c1", "gravity_sag.c2"} <= set(rep.verdict["implausible"]), rep.verdict
    for p, v in truth["gravity_sag"].items():
        got, sig = rep.parameters["gravity_sag"][p], rep.uncertainty["gravity_sag"][p]
        assert abs(got - v) < 2.5 * sig and abs(got - v) < 0.25 * v, (p, got, sig)
    assert 0 < len(rep.left_out) <= 0.2 * data.runs
    assert all("left out" in s and "port" in s for s in rep.left_out)
    assert rep.fit_errors.runs == data.runs - len(rep.left_out)
    js = rep.to_json()
    assert js["runs_left_out"] == rep.left_out
    assert rep.left_out[0] in rep.text()
    # a tracked tip thrown far off in a run whose wrist stays away from the port is bad data
    from errplan.calibration.residual import DEGENERATE_RHO

    base = declared_plant(sc)
    rho = np.linalg.norm(base.wrist(data.q) - np.asarray(base.true_port), axis=-1)
    far = next(r for r in range(data.runs) if rho[data.run == r].min() > DEGENERATE_RHO)
    i = int(np.flatnonzero(data.run == far)[2])
    data.tip[i] = data.tip[i] + np.array([0.0, 0.4, 0.0])
    with pytest.raises(DataError, match="more than the shaft length"):
        calibrate(sc, data, seed=0)
