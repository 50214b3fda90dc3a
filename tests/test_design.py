"""Experiment design (errplan.calibration.design, `errplan experiment --design N`).

The criteria against their textbook formulas, the exchange against brute force over every subset
of a small candidate set, the row budget, the identifiability summary against the correlations a
least-squares fit reports on the same rows (an independent path: SVD of the fit's own Jacobian),
and on P1's scenario: the designed bench separates the effect pairs the default bench confuses,
on the rows a real bench records."""
from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from errplan.calibration.design import (CONFUSED, Objective, _criterion, bench_info, catalogue_model,
                                        design_experiment, pair_correlations, predict_runs, select_runs)
from errplan.cli import main
from errplan.effects import EffectModel, make_effect
from errplan.errors import ErrplanError
from errplan.experiment import choose_starts, run_experiment, target_offsets, truth_plant
from errplan.api import load_scenario

ROOT = Path(__file__).resolve().parents[1]
PORT = ROOT / "scenarios" / "beasley2004_port.toml"


@pytest.fixture(scope="module")
def port():
    return load_scenario(PORT)


def _spd(rng, k, p):
    A = rng.normal(size=(k, 3 * p, p))
    return np.einsum("kri,krj->kij", A, A)


# ----------------------------------------------------------------------------- criteria
def test_criteria_match_their_formulas():
    rng = np.random.default_rng(0)
    Ms = _spd(rng, 7, 5)
    for i, M in enumerate(Ms):
        V = np.linalg.inv(M)
        assert _criterion(Ms, "D")[i] == pytest.approx(math.log(np.linalg.det(M)), rel=1e-10)
        assert _criterion(Ms, "A")[i] == pytest.approx(-math.log(np.trace(V)), rel=1e-10)
        assert _criterion(Ms, "E")[i] == pytest.approx(math.log(np.min(np.linalg.eigvalsh(M))), rel=1e-10)
        assert _criterion(Ms, "G")[i] == pytest.approx(-np.sum(np.log(np.diag(V))), rel=1e-10)
    # G is D plus the log-determinant of the estimates' correlation matrix (Hadamard: G <= D)
    for M in Ms:
        V = np.linalg.inv(M)
        d = np.sqrt(np.diag(V))
        R = V / np.outer(d, d)
        g = _criterion(M[None], "G")[0]
        assert g == pytest.approx(_criterion(M[None], "D")[0] + math.log(np.linalg.det(R)), rel=1e-10)
        assert g <= _criterion(M[None], "D")[0] + 1e-12
    # a singular matrix scores -inf
    S = np.zeros((1, 3, 3))
    S[0, 0, 0] = 1.0
    assert _criterion(S, "D")[0] == -np.inf and _criterion(S, "G")[0] == -np.inf and _criterion(S, "A")[0] == -np.inf
    with pytest.raises(ErrplanError, match="criterion"):
        _criterion(Ms, "X")


def test_pair_correlations_match_direct_inversion():
    rng = np.random.default_rng(1)
    Ms = _spd(rng, 4, 6)
    pairs = [((0, 1), (2, 3, 4)), ((5,), (0,))]
    got = pair_correlations(Ms, pairs)
    for k, M in enumerate(Ms):
        for j, (ia, ib) in enumerate(pairs):
            idx = list(ia) + list(ib)
            C = np.linalg.inv(M[np.ix_(idx, idx)])
            d = np.sqrt(np.diag(C))
            C = C / np.outer(d, d)
            assert got[k, j] == pytest.approx(np.abs(C[:len(ia), len(ia):]).max(), rel=1e-9)


# ----------------------------------------------------------------------------- selection
@pytest.mark.parametrize("seed", range(4))
def test_exchange_finds_the_brute_force_optimum(seed):
    """12 candidate runs of 3 parameters, each a block of a few rows: the greedy + exchange design
    of 4 runs within a row budget against every feasible subset."""
    rng = np.random.default_rng(seed)
    R, p, n = 12, 3, 4
    blocks = _spd(rng, R, p) * rng.uniform(0.2, 2.0, R)[:, None, None]
    rows = rng.integers(3, 9, R)
    budget = int(np.sort(rows)[:n].sum() + 6)
    for crit in ("D", "G"):
        best = -np.inf
        for sub in itertools.combinations(range(R), n):
            if rows[list(sub)].sum() <= budget:
                best = max(best, _criterion(blocks[list(sub)].sum(0)[None], crit)[0])
        ch = select_runs(blocks, rows, n, max_rows=budget, objective=crit)
        assert len(set(ch.tolist())) == n and rows[ch].sum() <= budget
        got = _criterion(blocks[ch].sum(0)[None], crit)[0]
        # efficiency: exp((got - best) / p) is the per-parameter ratio of the confidence volumes
        assert math.exp((got - best) / p) > 0.98, (crit, got, best)


def test_row_budget_and_fill():
    rng = np.random.default_rng(5)
    blocks = _spd(rng, 30, 4)
    rows = rng.integers(5, 20, 30)
    ch = select_runs(blocks, rows, None, max_rows=100, objective="G")
    assert rows[ch].sum() <= 100
    free = np.setdiff1d(np.arange(30), ch)
    assert np.all(rows[free] > 100 - rows[ch].sum())  # filled: no other run fits
    with pytest.raises(ErrplanError, match="shortest"):
        select_runs(blocks, rows, 25, max_rows=50)
    with pytest.raises(ErrplanError, match="only 30 candidate runs"):
        select_runs(blocks, rows, 31)


def test_separation_penalty_is_zero_below_the_target():
    rng = np.random.default_rng(2)
    Ms = _spd(rng, 5, 4)
    pairs = (((0, 1), (2, 3)),)
    rho = pair_correlations(Ms, list(pairs))[:, 0]
    obj = Objective("D", pairs, separate=0.9999999)
    assert np.allclose(obj(Ms), _criterion(Ms, "D"))
    target = float(np.median(rho))
    pen = Objective("D", pairs, separate=target, weight=1.0)(Ms) - _criterion(Ms, "D")
    want = np.minimum(0.0, np.log1p(-rho ** 2) - math.log1p(-target ** 2))
    assert np.allclose(pen, want)


# ----------------------------------------------------------------------------- on P1's scenario
def _default_runs(sc, n_starts=3):
    S = choose_starts(sc, n_starts)
    offs = target_offsets()
    return np.stack([np.repeat(S, len(offs), axis=0), (S[:, None] + offs[None]).reshape(-1, 2)], axis=1)


def test_bench_info_agrees_with_a_least_squares_fit(port):
    """The summary's correlations are those EffectModel reports when it fits the pair on the same
    rows (its own Jacobian at its own solution, through an SVD)."""
    data, _ = predict_runs(port, _default_runs(port))
    info = bench_info(port, data)
    base = truth_plant(port, effects=True, noise=False)
    u = data.commanded_directions(truth_plant(port, effects=False, noise=False))
    for a, b in (("joint_offset", "gravity_sag"), ("port_offset", "shaft_flexion"), ("tracker_offset", "port_friction")):
        m = EffectModel([make_effect(a), make_effect(b)]).fit(data.q, u, data.tip + 1e-6 * np.cos(np.arange(data.rows))[:, None],
                                                              base)
        na = m.effects[0].n_params
        cross = np.abs(m.correlation_[:na, na:]).max()
        assert info.pair_correlation(a, b) == pytest.approx(cross, abs=2e-3)
    # the condition number is that of the column-normalised Jacobian
    J = _rows_jacobian(port, data).reshape(-1, info.p)
    Jn = J / np.linalg.norm(J, axis=0)
    sv = np.linalg.svd(Jn, compute_uv=False)
    assert info.condition() == pytest.approx(sv[0] / sv[-1], rel=1e-6)


def _rows_jacobian(sc, data):
    from errplan.calibration.design import row_jacobian

    return row_jacobian(sc, data, catalogue_model(sc))


def test_predicted_rows_are_the_noise_free_bench(port):
    runs = _default_runs(port, 2)
    data, kept = predict_runs(port, runs)
    ex = run_experiment(port, plant=truth_plant(port, noise=False), runs=runs,
                        tolerance=max(5e-4, 3 * port.sensors.tracker_sigma))
    assert kept.tolist() == list(range(len(runs))) and data.rows == ex.data.rows
    assert np.allclose(data.q, ex.data.q, atol=1e-12) and np.allclose(data.tip, ex.data.tip, atol=1e-12)


@pytest.mark.slow
def test_designed_bench_separates_what_the_default_confuses(port):
    dz = design_experiment(port, None)
    assert dz.designed.rows <= dz.default.rows
    conf = dz.confused()
    assert {(a, b) for a, b, *_ in conf} >= {("joint_offset", "gravity_sag"), ("port_offset", "shaft_flexion")}
    assert all(c1 < CONFUSED for *_, c1 in conf)
    assert dz.designed.condition() < dz.default.condition()
    # the rows a real bench records with these runs (noise, the truth's own arrivals)
    real = run_experiment(port, seed=3, runs=dz.runs).data
    ref = run_experiment(port, seed=3).data
    info, info0 = bench_info(port, real), bench_info(port, ref)
    for a, b, *_ in conf:
        assert info0.pair_correlation(a, b) > CONFUSED > info.pair_correlation(a, b)
    js = dz.to_json()
    assert js["confused_pairs"] and len(js["runs"]) == len(dz.runs) and js["designed"]["rows"] == dz.designed.rows


@pytest.mark.slow
def test_cli_experiment_design(tmp_path, capsys):
    out, js = tmp_path / "d.csv", tmp_path / "d.json"
    assert main(["-q", "experiment", str(PORT), "--out", str(out), "--design", "30", "--max-rows", "520",
                 "--design-json", str(js)]) == 0
    text = capsys.readouterr().out
    assert "experiment design for" in text and "confused" in text
    d = json.loads(js.read_text())
    assert len(d["runs"]) == 30 and d["designed"]["rows"] <= 520
    assert out.exists() and out.read_text().count("\n") > 300


@pytest.mark.parametrize("extra,needle", [
    (["--design", "-1"], "--design -1"),
    (["--max-rows", "100"], "go with --design"),
    (["--design", "5", "--max-rows", "-1"], "--max-rows -1"),
    (["--design", "5", "--criterion", "Q"], "invalid choice"),
    (["--design", "5", "--separate", "1.5"], "--separate 1.5"),
    (["--design", "5", "--separate", "tight"], "--separate tight"),
])
def test_cli_design_options_exit_2(tmp_path, capsys, extra, needle):
    out = tmp_path / "d.csv"
    try:
        rc = main(["-q", "experiment", str(PORT), "--out", str(out), *extra])
    except SystemExit as e:  # argparse's own usage errors
        rc = e.code
    assert rc == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err and not out.exists()


@pytest.mark.slow
def test_spatial_design_separates_what_the_default_confuses():
    """3-D (the PHANToM with a waist): the default bench (8 starts x 14 targets) confuses joint offset
    with gravity sag and port offset with shaft flexion beyond 0.998; the designed bench, with the
    same rows, separates every confused pair, on the rows a real bench records too; the waist's
    gravity parameter (identically zero sensitivity) is not among the designed parameters."""
    sc = load_scenario(ROOT / "scenarios" / "phantom15_spatial.toml")
    dz = design_experiment(sc, None)
    assert "gravity_sag.c1" not in dz.default.labels and "gravity_sag.c2" in dz.default.labels
    assert dz.designed.rows <= dz.default.rows and dz.runs.shape[1:] == (2, 3)
    conf = {(a, b) for a, b, *_ in dz.confused()}
    assert {("joint_offset", "gravity_sag"), ("port_offset", "shaft_flexion")} <= conf
    assert all(c1 < CONFUSED for *_, c1 in dz.confused())
    real = run_experiment(sc, seed=3, runs=dz.runs).data
    info = bench_info(sc, real)
    for a, b in conf:
        assert info.pair_correlation(a, b) < CONFUSED, (a, b)


# ----------------------------------------------------------------------------- geometry and backlash
GEOMETRIC = ["link_length", "instrument_length", "tracker_registration"]


def test_design_for_the_geometric_groups_beats_the_default_bench(port):
    """``--design-effects``: on one start (8 runs) the default bench confuses the instrument length with
    the tracker's offset along the shaft and the link lengths with both (correlations > 0.95); the
    designed bench, within the same rows, separates them and lowers the condition number by more than
    ten. On the rows a real bench records (noise, the truth's own arrivals) a least-squares fit of the
    three groups (scipy's Jacobian, not the design's) finds the truth with sigmas several times smaller."""
    dz = design_experiment(port, None, effects=GEOMETRIC, n_starts=1)
    assert dz.designed.rows <= dz.default.rows and dz.meta["rank"] == {"default": 6, "designed": 6}
    assert {(a, b) for a, b, *_ in dz.confused()} >= {("instrument_length", "tracker_registration")}
    assert all(c1 < CONFUSED for *_, c1 in dz.confused())
    assert dz.designed.condition() < 0.1 * dz.default.condition()
    assert "6 parameters of link_length, instrument_length, tracker_registration" in dz.text()
    truth = {"link_length": {"dl1": 0.002, "dl2": -0.001}, "instrument_length": {"dL": 0.003},
             "tracker_registration": {"rx": 0.004, "by": 0.0005, "bz": -0.001}}
    want = np.array([0.002, -0.001, 0.003, 0.004, 0.0005, -0.001])
    sc = port.with_(effects=truth)
    sig = []
    for data in (run_experiment(sc, seed=5, runs=dz.runs).data, run_experiment(sc, seed=5, n_starts=1).data):
        m = catalogue_model(port, GEOMETRIC)
        m.fit(data.q, np.zeros_like(data.tip), data.tip, truth_plant(port, effects=False, noise=False))
        assert not m.held_labels
        assert np.all(np.abs(m.values_ - want) < 4.5 * m.sigma_), (m.values_, m.sigma_)
        sig.append(m.sigma_)
    assert np.all(sig[0] < 0.5 * sig[1]), sig


def test_backlash_is_designed_with_its_one_sided_sensitivity(port):
    """Backlash is even in its half-width, so its central difference at 0 vanishes; the design's
    regressor uses the one-sided one: the tip's lag under a small play (the design's step, 1 µrad, on
    one joint; checked against the plant with that play, row by row)."""
    from errplan.calibration import declared_plant, motion_model
    from errplan.calibration.design import row_jacobian
    from errplan.effects import predict_tracked

    runs = np.stack([np.repeat(choose_starts(port, 1), 8, axis=0),
                     choose_starts(port, 1) + target_offsets(dim=2)], axis=1)
    data, _ = predict_runs(port, runs)
    m = catalogue_model(port, ["backlash"])
    J = row_jacobian(port, data, m)
    assert np.count_nonzero(np.abs(J) > 0) > data.rows  # not the vanishing central difference
    base = declared_plant(port)
    u = data.commanded_directions(motion_model(port))
    b = m.fd_step * m.scales[0]
    lag = (predict_tracked(base.with_(backlash=(b, 0.0)), data.q, u, data.run)
           - predict_tracked(base, data.q, u, data.run)) / (b / m.scales[0])
    assert np.allclose(J[..., 0], lag, rtol=1e-9, atol=1e-12) and np.max(np.abs(lag)) > 0
    with pytest.raises(ErrplanError, match="--effects joint_geometry"):
        catalogue_model(port, ["joint_geometry"])


def test_cli_design_for_backlash(tmp_path, capsys):
    out, js = tmp_path / "d.csv", tmp_path / "d.json"
    assert main(["-q", "experiment", str(PORT), "--out", str(out), "--design", "0", "--starts", "1",
                 "--design-effects", "backlash", "--design-json", str(js)]) == 0
    text = capsys.readouterr().out
    assert "2 parameters of backlash" in text and "default bench 2 of 2, designed 2 of 2" in text
    d = json.loads(js.read_text())
    assert d["effects"] == ["backlash"] and d["rank"]["designed"] == 2 and out.exists()
    assert d["designed"]["condition_number"] is not None
    bad = tmp_path / "bad.csv"
    assert main(["-q", "experiment", str(PORT), "--out", str(bad), "--design", "5", "--design-effects",
                 "backlash,wobble"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "wobble" in err and not bad.exists()
