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
from errplan.metrics import inv2
from errplan.scenario import load_scenario, parse_scenario
from errplan.simulation import ControllerModel, Plant

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
    plant = Plant.from_scenario(sc)
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
    ctrl = ControllerModel.from_scenario(port)
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
    plant = Plant.from_scenario(port)
    r = d.tip - plant.tip(d.q, d.commanded_directions())
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
    r = d.tip - Plant.from_scenario(port).tip(d.q, d.commanded_directions())
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
    u = d.commanded_directions()
    assert np.allclose(u[0], 0) and np.allclose(u[1], [1.0, 0.0])  # b: target - tip(0) = (0.02, 0)


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
