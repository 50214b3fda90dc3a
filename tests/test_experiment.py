"""Bench runs (errplan.experiment, `errplan experiment`): P1's starts and targets, the CSV of
interfaces.md (columns, step semantics re-derived from the controller law), determinism from the
seed, the tracker noise it carries, starts on other scenarios, and the robust CSV reader."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from errplan.cli import main
from errplan.errors import DataError, ErrplanError
from errplan.experiment import (COLUMNS, P1_STARTS, choose_starts, parse_measured_csv, read_measured_csv,
                                run_experiment, target_offsets)
from errplan.kinematics.shaft import lever_tip
from errplan.metrics import inv2
from errplan.api import load_scenario, parse_scenario
from errplan.simulation import ControllerModel, Plant
from errplan.models import build_arm

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore

ROOT = Path(__file__).resolve().parents[1]
PORT = ROOT / "scenarios" / "beasley2004_port.toml"


@pytest.fixture(scope="module")
def port():
    return load_scenario(PORT)


@pytest.fixture(scope="module")
def bench(port):
    return run_experiment(port, seed=3, n_starts=4)


def test_targets_are_p1s_eight_at_20mm():
    off = target_offsets()
    assert off.shape == (8, 2)
    assert np.allclose(np.linalg.norm(off, axis=1), 0.020)
    ang = np.degrees(np.arctan2(off[:, 0], off[:, 1])) % 360
    assert np.allclose(np.sort(ang), np.arange(0, 360, 45))
    # P1 Sec. IV names (429, 14) and (401, -14) for the start N = (415, 0) (mm, z first): the diagonals
    n = np.array(P1_STARTS[2]) * 1000
    tg = {tuple(np.round(n + 1000 * o).astype(int)) for o in off}
    assert (14, 429) in tg and (-14, 401) in tg and (0, 435) in tg


def test_p1_starts_come_first_and_extra_starts_spread(port):
    S = choose_starts(port, 8)
    assert np.allclose(S[:3], P1_STARTS)
    d = np.linalg.norm(S[:, None] - S[None], axis=-1) + np.eye(len(S))
    assert len(S) == 8 and d[3:, :].min() > 0.040  # the extra starts keep apart from every other start
    assert np.ptp(S[:, 0]) > 0.15  # spread over y, not only P1's line y = 0


def test_starts_on_a_scenario_without_p1_points():
    doc = tomllib.loads(PORT.read_text())
    doc["port"] = {"position": [0.05, 0.12], "estimate": [0.05, 0.12]}
    doc["instrument"]["length"] = 0.25
    sc = parse_scenario(doc, "shifted")
    S = choose_starts(sc, 5)
    assert 1 <= len(S) <= 5
    plant = Plant.from_model(build_arm(sc))
    for s in S:  # every start and its eight targets reachable by the truth
        for x in np.vstack([s[None], s + target_offsets()]):
            plant.configuration_for_tip(x)
    ex = run_experiment(sc, seed=0, n_starts=5)
    assert ex.data.runs == 8 * len(S)


def test_csv_columns_and_step_semantics(port, bench):
    """Row t+1's encoders read exactly the command q(t) + k Jhat(q(t))^-1 (target - tip(t)) (no encoder noise)."""
    d = bench.data
    text = d.to_csv_text()
    assert text.splitlines()[0] == ",".join(COLUMNS)
    back = parse_measured_csv(text)
    assert back.rows == d.rows and back.runs == d.runs
    assert np.allclose(back.q, d.q, atol=1e-11) and np.allclose(back.tip, d.tip, atol=1e-12)
    ctrl = ControllerModel.from_model(build_arm(port))
    k = port.controller.gain
    assert np.all(d.gain == k)
    i = np.flatnonzero(d.step[1:] > 0)  # rows t with a successor t+1 in the same run
    Jinv, sing = inv2(ctrl.J_hat(d.q[i]))
    assert not np.any(sing)
    cmd = d.q[i] + k * np.einsum("nij,nj->ni", Jinv, d.target[i] - d.tip[i])
    assert np.allclose(d.q[i + 1], cmd, atol=1e-12)
    # every run: one target, steps 0..n-1, starts within noise of a start tip, ends by the cap or dwell rule
    for r in range(d.runs):
        m = d.run == r
        assert np.array_equal(d.step[m], np.arange(m.sum()))
        assert np.ptp(d.target[m], axis=0).max() == 0
        assert m.sum() - 1 <= bench.max_steps
        if bench.status[r] == "converged":
            e = np.linalg.norm(d.tip[m] - d.target[m], axis=1)
            first = int(np.flatnonzero(e < bench.tolerance)[0])
            assert m.sum() - 1 <= first + bench.dwell


def test_tracked_tip_is_truth_plus_tracker_noise(port, bench):
    d = bench.data
    plant = Plant.from_model(build_arm(port))
    r = d.tip - plant.tip(d.q, d.commanded_directions(plant.declared()))
    sigma = port.sensors.tracker_sigma
    assert np.std(r) == pytest.approx(sigma, rel=0.06)
    assert abs(np.mean(r)) < 4 * sigma / np.sqrt(r.size)


def test_deterministic_from_seed(port):
    a = run_experiment(port, seed=5, n_starts=3).data.to_csv_text()
    b = run_experiment(port, seed=5, n_starts=3).data.to_csv_text()
    c = run_experiment(port, seed=6, n_starts=3).data.to_csv_text()
    assert a == b and a != c


def test_effects_reach_the_data(port):
    """The truth carries the scenario's [effects]: a tracker offset shifts every tracked tip."""
    sc = port.with_(effects={"tracker_offset": {"by": 0.003, "bz": -0.002}})
    d = run_experiment(sc, seed=1, n_starts=2).data
    r = d.tip - Plant.from_model(build_arm(port)).tip(d.q, d.commanded_directions(Plant.from_model(build_arm(port))))
    assert np.allclose(r.mean(axis=0), [0.003, -0.002], atol=4e-5)


def test_flexion_controller_scenario_runs():
    """P2's flexion controller on an unbent shaft falls back to the straight-shaft model (no error)."""
    doc = tomllib.loads(PORT.read_text())
    doc["controller"]["jacobian"] = "flexion"
    sc = parse_scenario(doc, "flexion")
    ex = run_experiment(sc, seed=0, n_starts=2)
    assert ex.data.runs == 16 and "converged" in ex.status


def test_cli_experiment_writes_atomically(tmp_path, capsys):
    out = tmp_path / "bench.csv"
    assert main(["-q", "experiment", str(PORT), "--out", str(out), "--seed", "2", "--starts", "3"]) == 0
    d = read_measured_csv(out)
    assert d.runs == 24 and not (tmp_path / "bench.csv.part").exists()
    assert "24 runs" in capsys.readouterr().out
    assert main(["experiment", str(PORT), "--out", str(tmp_path / "no" / "x.csv")]) == 2
    assert main(["experiment", str(PORT), "--out", str(tmp_path / "y.csv"), "--starts", "0"]) == 2
    assert not (tmp_path / "y.csv").exists()


# ----------------------------------------------------------------------------- CSV reader
GOOD = "run,step,target_y,target_z,gain,q1,q2,tip_y,tip_z\n" \
       "a,0,0,0.34,1,0,0,0.0,0.32\n" \
       "a,1,0,0.34,1,0.02,0.05,0.0,0.335\n" \
       "b,0,0.02,0.32,1,0,0,0.0,0.32\n" \
       "b,1,0.02,0.32,1,0.01,0.0,0.01,0.32\n"


def test_reader_accepts_good_csv_in_any_run_order():
    lines = GOOD.splitlines()
    shuffled = "\n".join([lines[0], lines[4], lines[1], lines[3], lines[2]]) + "\n"
    d = parse_measured_csv(shuffled)
    assert d.run_ids == ["b", "a"] and d.rows == 4
    assert np.array_equal(d.step, [0, 1, 0, 1])
    model = Plant.from_model(build_arm(load_scenario(PORT)), effects=False)
    u = d.commanded_directions(model)
    # b moved from q = (0, 0) to (0.01, 0): u is the direction of the declared model's tip motion,
    # the lever through the declared port (by hand), not the desired direction target - tip = (0.02, 0)
    arm, port = model.arm, np.asarray(model.port)
    x0, x1 = (lever_tip(arm.forward(np.array(q)), port, model.length) for q in ((0.0, 0.0), (0.01, 0.0)))
    assert np.allclose(u[0], 0) and np.allclose(u[1], (x1 - x0) / np.linalg.norm(x1 - x0), atol=1e-12)
    assert abs(u[1] @ [1.0, 0.0]) < 0.999  # not the desired direction


@pytest.mark.parametrize("text,needle", [
    ("", "empty"),
    ("run,step,target_y,target_z,gain,q1,q2,tip_y\na,0,0,0,1,0,0,0\n", "missing column(s) tip_z"),
    (GOOD.replace("0.0,0.335", "nan,0.335"), "row 2 column 'tip_y': value 'nan' is not finite"),
    (GOOD.replace("0.02,0.05", "0.02,inf"), "row 2 column 'q2': value 'inf' is not finite"),
    (GOOD.replace("0.02,0.05", "0.02,abc"), "row 2 column 'q2': value 'abc' is not a number"),
    (GOOD.replace("b,1,0.02,0.32,1,0.01", "c,1,0.02,0.32,1,0.01"), "run 'b' has 1 step"),
    (GOOD.replace("a,1,", "a,2,"), "step 1 is missing"),
    (GOOD.replace("a,1,0,0.34", "a,1,0.001,0.34"), "'target_y' changes within the run"),
    (GOOD.replace(",1,0,0,0.0,0.32\na", ",0,0,0,0.0,0.32\na", 1), "'gain'"),
    ("run,step,target_y,target_z,gain,q1,q2,tip_y,tip_z\n", "no data rows"),
    (GOOD.replace("a,0,0,0.34,1,0,0,0.0,0.32", "a,0.5,0,0.34,1,0,0,0.0,0.32"), "not an integer"),
])
def test_reader_names_the_defect(text, needle):
    with pytest.raises(DataError) as e:
        parse_measured_csv(text, "x.csv")
    assert needle in str(e.value)


def test_reader_missing_file(tmp_path):
    with pytest.raises(DataError, match="not found"):
        read_measured_csv(tmp_path / "nope.csv")


def test_run_experiment_rejects_bad_settings(port):
    with pytest.raises(ErrplanError):
        run_experiment(port, max_steps=0)
    with pytest.raises(ErrplanError):
        choose_starts(port, 0)


# ----------------------------------------------------------------------------- friction's direction
def _u_by_hand(model, q_rows: np.ndarray) -> np.ndarray:
    """u for the rows of one run, from the definition: unit x_model(q(t+1)) - x_model(q(t)) with
    x_model the lever through the declared port (computed here with lever_tip, not model_tip);
    0 at step 0; the last value kept when a step moves nothing."""
    x = lever_tip(model.arm.forward(q_rows), np.asarray(model.port), model.length)
    u = np.zeros_like(x)
    for t in range(1, len(x)):
        d = x[t] - x[t - 1]
        n = np.linalg.norm(d)
        u[t] = d / n if n > 0 else u[t - 1]
    return u


def test_u_from_rows_follows_the_definition_step_by_step():
    """u = 0 at step 0, the model motion of each step, the last value kept over a step without motion
    (b's step 2 repeats step 1's encoders), runs kept apart, any row order."""
    text = ("run,step,target_y,target_z,gain,q1,q2,tip_y,tip_z\n"
            "a,0,0,0.34,1,0,0,0,0.32\n"
            "a,1,0,0.34,1,0.02,0.05,0,0.335\n"
            "a,2,0,0.34,1,0.03,0.04,0,0.336\n"
            "b,0,0.02,0.32,1,0.01,0.01,0,0.32\n"
            "b,1,0.02,0.32,1,0.012,0.0,0.01,0.32\n"
            "b,2,0.02,0.32,1,0.012,0.0,0.01,0.32\n"
            "b,3,0.02,0.32,1,0.011,-0.01,0.01,0.32\n")
    model = Plant.from_model(build_arm(load_scenario(PORT)), effects=False)
    d = parse_measured_csv(text)
    u = d.commanded_directions(model)
    for r in range(d.runs):
        m = d.run == r
        assert np.allclose(u[m], _u_by_hand(model, d.q[m]), atol=1e-12)
    assert np.allclose(u[d.step == 0], 0.0)
    b = np.flatnonzero(d.run == 1)
    assert np.array_equal(u[b[2]], u[b[1]]) and not np.allclose(u[b[3]], u[b[1]])
    lines = text.splitlines()
    shuffled = parse_measured_csv("\n".join([lines[0]] + lines[1:][::-1]) + "\n")
    us = shuffled.commanded_directions(model)
    for rid in ("a", "b"):
        assert np.allclose(us[shuffled.run == shuffled.run_ids.index(rid)], u[d.run == d.run_ids.index(rid)], atol=1e-15)


FRICTION = {"port_friction": {"fa": 0.002, "fn": 0.0012}}


def _one_cm_bench(port, effects, **kw):
    """The issue's regime: the controller's port estimate about 11 mm off the declared port, gain 0.05."""
    from dataclasses import replace

    from errplan.scenario import Port

    sc = port.with_(port=Port(port.port.position, (0.010, 0.165)), controller=replace(port.controller, gain=0.05))
    return sc, sc.with_(effects=effects, **kw)


def test_bench_simulation_and_rows_agree_on_friction_exactly(port):
    """Noise-free friction bench: every tracked tip equals the truth at the encoder angles with u
    recovered from the rows under the declared model, to rounding (the bench, ``simulate`` and the
    data agree on which command each row's friction comes from). The desired direction misses."""
    from dataclasses import replace

    sc, truth_sc = _one_cm_bench(port, FRICTION)
    truth_sc = truth_sc.with_(sensors=replace(truth_sc.sensors, tracker_sigma=0.0))
    d = run_experiment(truth_sc, seed=0, n_starts=3).data
    truth = Plant.from_model(build_arm(truth_sc))
    model = Plant.from_model(build_arm(sc), effects=False)
    u = d.commanded_directions(model)
    for r in range(0, d.runs, 3):  # the definition, by hand
        m = d.run == r
        assert np.allclose(u[m], _u_by_hand(model, d.q[m]), atol=1e-12)
    assert np.max(np.abs(d.tip - truth.tip(d.q, u))) < 1e-12
    # through the CSV (12 significant digits) the same to ~1e-9 m
    back = parse_measured_csv(d.to_csv_text())
    assert np.max(np.abs(back.tip - truth.tip(back.q, back.commanded_directions(model)))) < 1e-8
    # the desired direction (target - tip of the previous row) is a different, wrong u: mm-size misfit
    err = d.target - d.tip
    want = np.zeros_like(u)
    want[1:] = (err / np.linalg.norm(err, axis=1)[:, None])[:-1]
    want[d.step == 0] = 0.0
    miss = np.abs(d.tip - truth.tip(d.q, want))
    assert np.sqrt(np.mean(miss ** 2)) > 1e-4
    ang = np.degrees(np.arccos(np.clip(np.sum(u * want, axis=1), -1, 1)))[d.step > 0]
    assert np.median(ang) > 3 and ang.max() > 20  # the two directions differ by up to phi_max


def test_bench_friction_residual_is_the_tracker_noise(port):
    """The issue's numbers: on the ~1 cm bench the true model's pose residual with this u is the
    tracker noise (0.2 mm); with the desired direction it is well above it."""
    sc, truth_sc = _one_cm_bench(port, FRICTION)
    d = run_experiment(truth_sc, seed=11, n_starts=5).data
    truth = Plant.from_model(build_arm(truth_sc))
    u = d.commanded_directions(Plant.from_model(build_arm(sc), effects=False))
    r = d.tip - truth.tip(d.q, u)
    assert np.sqrt(np.mean(r ** 2)) == pytest.approx(sc.sensors.tracker_sigma, rel=0.05)
    err = d.target - d.tip
    want = np.zeros_like(u)
    want[1:] = (err / np.linalg.norm(err, axis=1)[:, None])[:-1]
    want[d.step == 0] = 0.0
    r_old = d.tip - truth.tip(d.q, want)
    assert np.sqrt(np.mean(r_old ** 2)) > 1.4 * sc.sensors.tracker_sigma


def test_bench_size_is_checked_before_running(port, capsys, tmp_path):
    """An absurd --max-steps or shaft length: one error naming the value and the memory, nothing written."""
    with pytest.raises(ErrplanError, match=r"--max-steps = 100000000000: .* would need .*iB"):
        run_experiment(port, max_steps=10**11, n_starts=2)
    doc = tomllib.loads(PORT.read_text())
    doc["instrument"]["length"] = 1e9
    long = parse_scenario(doc, "long")
    with pytest.raises(ErrplanError, match=r"\[instrument\] length = 1e\+09: the bench's start search .* would need"):
        choose_starts(long, 8)
    out = tmp_path / "x.csv"
    assert main(["experiment", str(PORT), "--out", str(out), "--max-steps", str(10**11)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--max-steps" in err and "iB" in err and not out.exists()


# ----------------------------------------------------------------------------- spatial (issue 13)
SPATIAL = ROOT / "scenarios" / "phantom15_spatial.toml"


@pytest.fixture(scope="module")
def spatial_bench():
    sc = load_scenario(SPATIAL).with_(effects={"joint_offset": {"dq1": 0.002, "dq2": 0.0, "dq3": -0.001}})
    return sc, run_experiment(sc, seed=4, n_starts=3)


def test_spatial_targets_are_the_fourteen_of_interfaces_md():
    off = target_offsets(dim=3)
    assert off.shape == (14, 3)
    assert np.allclose(np.linalg.norm(off, axis=1), 0.020)
    assert {tuple(np.sign(o).astype(int)) for o in off[6:]} == {(a, b, c) for a in (1, -1) for b in (1, -1)
                                                               for c in (1, -1)}
    axes = {tuple(np.round(o / 0.020).astype(int)) for o in off[:6]}
    assert axes == {tuple(v) for v in np.vstack([np.eye(3), -np.eye(3)]).astype(int)}


def test_spatial_bench_rows_and_noise(spatial_bench):
    sc, ex = spatial_bench
    d = ex.data
    assert d.dim == 3 and d.n_joints == 3 and d.runs == 14 * len(ex.starts)
    # P1's starts in the plane x = 0 come first
    assert np.allclose(ex.starts[0], [0.0, 0.0, 0.320])
    text = d.to_csv_text()
    assert text.splitlines()[0] == "run,step,target_x,target_y,target_z,gain,q1,q2,q3,tip_x,tip_y,tip_z"
    back = parse_measured_csv(text, dim=3, n_joints=3)
    assert np.allclose(back.q, d.q, atol=1e-11) and np.array_equal(back.step, d.step)
    # tracked tip = the truth's tip (with the scenario's joint offset) + the tracker's noise
    plant = Plant.from_model(build_arm(sc))
    r = d.tip - plant.tip(d.q, d.commanded_directions(plant.declared()))
    assert np.std(r) == pytest.approx(sc.sensors.tracker_sigma, rel=0.06)
    # every run: the encoders at step t+1 read the command of step t (the 3-D controller law)
    ctrl = ControllerModel.from_model(build_arm(sc))
    for rid in range(0, d.runs, 5):
        m = d.run == rid
        q, tip, tg = d.q[m], d.tip[m], d.target[m][0]
        Jh = ctrl.J_hat(q[:-1])
        dq = sc.controller.gain * np.linalg.solve(Jh, (tg - tip[:-1])[..., None])[..., 0]
        assert np.allclose(q[1:], q[:-1] + dq, atol=1e-10)


def test_cli_experiment_on_a_spatial_scenario(tmp_path, capsys):
    out = tmp_path / "b.csv"
    assert main(["experiment", str(SPATIAL), "--out", str(out), "--starts", "1", "--max-steps", "6"]) == 0
    text = capsys.readouterr().out
    assert "start x, y, z (mm)" in text and "14/14" in text
    assert out.read_text().splitlines()[0].startswith("run,step,target_x")
