"""`explained` means explained (docs/physics.md "Measured data as a bench records it"): the verdict's four
conditions, the structure test that sees the motion, and lone-row outliers.

The benches: errplan's experiment run noise-free on P1's planar scenario (the closed loop), then the
tracked tips changed in this file, by code errplan does not have: a smooth warp of the tracker's space,
a cubic distortion, a tracker scale error about a point, a late tracker (each row's tip linearly
interpolated in time from its run's rows, tau steps back), marker swaps (lone rows 3-10 mm off), and
the tracker's Gaussian noise added last. Effects outside the catalogue must read "not explained" with
the failed condition named; noise only and an in-catalogue effect must read explained."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from errplan.api import load_scenario
from errplan.calibration import calibrate
from errplan.calibration.driver import _verdict
from errplan.calibration.noise import motion_features, model_steps
from errplan.calibration.outliers import find_outliers, lone_rows, robust_sigma, without_rows
from errplan.experiment import run_experiment
from tests.test_calibration import PORT

SIGMA = 2e-4
FOLDS = 3
STARTS = 4
#: the candidates of the fast cases (the whole catalogue in the slow ones): the physical effects that
#: imitate warps and latencies, and a geometric group
EFFECTS = ["port_offset", "tracker_offset", "gravity_sag", "shaft_flexion", "port_friction", "link_length"]


@pytest.fixture(scope="module")
def sc():
    s = load_scenario(PORT)
    return s.with_(controller=replace(s.controller, gain=0.3))


def clean(sc, seed, effects=None):
    """The noise-free closed loop on the scenario's truth (with ``effects``): tracked tips exact."""
    quiet = sc.with_(sensors=replace(sc.sensors, tracker_sigma=0.0), effects=effects or {})
    return run_experiment(quiet, seed=seed, n_starts=STARTS).data


def noisy(data, tip, seed):
    rng = np.random.default_rng(seed)
    return replace(data, tip=tip + rng.normal(0.0, SIGMA, tip.shape))


def warp(tip, amp, kind):
    c = np.array([0.0, 0.30])
    z = (tip - c) / 0.05
    if kind == "smooth":
        d = np.stack([np.sin(1.3 * z[:, 1] + 0.4 * z[:, 0]), np.cos(1.1 * z[:, 0] - 0.7 * z[:, 1])], -1)
    elif kind == "cubic":
        d = np.stack([z[:, 0] ** 3 - 0.5 * z[:, 1] ** 2 * z[:, 0], z[:, 1] ** 3 + 0.3 * z[:, 0] ** 2 * z[:, 1]], -1)
    else:  # scale about c
        d = z
    return tip + amp * d


def late(data, tau):
    """Each row's tip = the true tip at the row's step - tau, linear between rows, the first row's before."""
    out = data.tip.copy()
    for r in range(data.runs):
        idx = np.flatnonzero(data.run == r)
        s = data.step[idx].astype(float)
        for j in range(data.dim):
            out[idx, j] = np.interp(s - tau, s, data.tip[idx, j])
    return out


@pytest.fixture(scope="module")
def base(sc):
    return clean(sc, 61)


@pytest.fixture(scope="module")
def noise_only(sc, base):
    return calibrate(sc, noisy(base, base.tip, 1), seed=0, folds=FOLDS, effects=EFFECTS)


def test_noise_only_is_explained(noise_only):
    rep = noise_only
    js = rep.to_json()
    assert rep.selected == [] and rep.explained and js["explained"] is True
    assert js["verdict"]["failed"] == [] and js["verdict"]["structure_p"] > 0.05
    assert js["verdict"]["residual_ratio"] < 1.1
    assert rep.noise.sigma == pytest.approx(SIGMA, rel=0.08)
    assert len(js["measured"]["outliers"]) <= 0.002 * rep.fit_errors.rows  # data without outliers list (almost) none
    assert "explained: yes" in rep.text() and "nan" not in rep.text()


@pytest.mark.parametrize("kind,amp", [("smooth", 4e-4), pytest.param("cubic", 1.5e-4, marks=pytest.mark.slow),
                                      pytest.param("scale", 3e-3, marks=pytest.mark.slow)])
def test_a_tracker_warp_is_not_explained(sc, base, kind, amp):
    """A warp of the tracker's space (about 1.5-2x the noise floor left after the catalogue's best)."""
    rep = calibrate(sc, noisy(base, warp(base.tip, amp, kind), 2), seed=0, folds=FOLDS, effects=EFFECTS)
    v = rep.to_json()["verdict"]
    assert not rep.explained and v["failed"], v
    assert "b" in v["failed"] and v["structure_p"] < 1e-3
    assert rep.empirical is not None
    assert "explained: NO — failed: " in rep.text() and "(b) FAILED" in rep.text()


def test_a_late_tracker_is_structure_that_follows_the_motion(sc, base):
    """A tracker 1.5 steps late: without tracker_latency among the candidates the residual follows the
    motion; the structure test's motion features see it (the local pose polynomials do not), and the
    persistent residual of a run's fast first rows is not taken for outliers."""
    rep = calibrate(sc, noisy(base, late(base, 1.5), 3), seed=0, folds=FOLDS, effects=EFFECTS)
    v = rep.to_json()["verdict"]
    assert not rep.explained and "b" in v["failed"]
    st = rep.structure
    assert st.models["global"]["p_value"] < 1e-6
    assert len(rep.outliers) <= 0.002 * rep.fit_errors.rows


def test_an_in_catalogue_effect_is_explained(sc):
    truth = {"port_offset": {"dy": 0.003, "dz": -0.002}}
    d = clean(sc, 62, truth)
    rep = calibrate(sc, noisy(d, d.tip, 4), seed=0, folds=FOLDS, effects=EFFECTS)
    assert rep.selected == ["port_offset"] and rep.explained, rep.to_json()["verdict"]
    assert rep.parameters["port_offset"]["dy"] == pytest.approx(0.003, abs=3e-4)


def test_outliers_are_found_and_do_not_inflate_the_noise_floor(sc, base):
    """0.5 % of the rows 3-10 mm off in a random direction (marker swaps): at least 90 % listed, at most
    1 % false, the noise floor within 15 % of the tracker's sigma (the same rows' floor is 0.35 mm and
    more with them in)."""
    rng = np.random.default_rng(7)
    n = base.rows
    k = max(6, round(0.005 * n))  # 0.5 % of the rows, at least 6
    rows = np.sort(rng.choice(n, k, replace=False))
    tip = noisy(base, base.tip, 5).tip
    dirs = rng.normal(size=(k, 2))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    tip[rows] += dirs * rng.uniform(0.003, 0.010, k)[:, None]
    rep = calibrate(sc, replace(base, tip=tip), seed=0, folds=FOLDS, effects=EFFECTS)
    listed = {(o["run"], o["step"]) for o in rep.to_json()["measured"]["outliers"]}
    true = {(base.run_ids[base.run[i]], int(base.step[i])) for i in rows}
    assert len(listed & true) >= 0.9 * len(true)
    assert len(listed - true) <= 0.01 * n
    assert rep.noise.sigma == pytest.approx(SIGMA, rel=0.15)
    assert rep.selected == [] and rep.explained
    for o in rep.to_json()["measured"]["outliers"]:
        assert 0.0025 < o["size"] < 0.011
    assert "outliers in" in rep.text()


# ----------------------------------------------------------------------------- pieces
def test_lone_rows_and_persistent_residuals():
    rng = np.random.default_rng(0)
    run = np.repeat(np.arange(10), 30)
    res = rng.normal(0, 1.0, (300, 2))
    res[45] += [12.0, 0.0]              # alone: an outlier
    res[100:104] += [0.0, 10.0]         # four rows in a row: structure, not outliers
    res[200] += [9.0, 0.0]              # beside a row 6 sigmas off: not alone
    res[201] += [6.0, 0.0]
    tracked = np.ones(300, bool)
    tracked[46] = False                  # a dropout beside the outlier: its tracked neighbour is the next one
    out = lone_rows(res, run, tracked)
    assert np.flatnonzero(out).tolist() == [45]
    assert robust_sigma(res) == pytest.approx([1.0, 1.0], rel=0.15)


def test_find_outliers_refits_without_them():
    """A smooth field plus noise plus lone spikes: the spikes are found however the field pulls a first
    fit, and nothing else."""
    rng = np.random.default_rng(1)
    n = 1200
    run = np.repeat(np.arange(40), 30)
    x = rng.uniform(-0.05, 0.05, (n, 2)) + [0.0, 0.3]
    u = np.zeros((n, 2))
    r = 1e-3 * np.stack([np.sin(40 * x[:, 0]), np.cos(30 * x[:, 1])], -1) + rng.normal(0, 2e-4, (n, 2))
    spikes = rng.choice(n, 8, replace=False)
    r[spikes] += 5e-3
    out = find_outliers(r, x, u, run, np.ones(n, bool))
    assert set(np.flatnonzero(out)) == set(spikes)


def test_without_rows_keeps_every_array_aligned(base):
    drop = np.zeros(base.rows, bool)
    drop[[3, 50]] = True
    d = without_rows(base, drop)
    assert d.rows == base.rows - 2 and d.runs == base.runs
    assert np.array_equal(d.q, base.q[~drop]) and np.array_equal(d.step, base.step[~drop])


def test_motion_features_are_the_model_steps_over_their_durations():
    x = np.array([[0.0, 0.0], [1.0, 0.0], [3.0, 1.0], [5.0, 5.0], [6.0, 5.0]])
    run = np.array([0, 0, 0, 1, 1])
    s = model_steps(x, run)
    assert s.tolist() == [[0, 0], [1, 0], [2, 1], [0, 0], [1, 0]]
    t = np.array([0.0, 0.5, 1.5, 7.0, 7.25])
    assert motion_features(s, run, t).tolist() == [[0, 0], [2, 0], [2, 1], [0, 0], [4, 0]]
    assert motion_features(s, run).tolist() == s.tolist()


def test_each_condition_of_the_verdict_can_fail(noise_only):
    """(a)-(d) on the noise-only report's pieces, one changed at a time; each alone makes it not explained."""
    from errplan.effects import EffectModel, PortOffset

    rep = noise_only
    r1, sigma, st = rep.residual_after, rep.noise.sigma, rep.structure
    ok = _verdict(r1, sigma, st, rep.model, None, False)
    assert ok["failed"] == []
    assert _verdict(1.3 * r1, sigma, st, rep.model, None, False)["failed"] == ["a"]
    assert _verdict(r1, sigma, replace(st, structured=True), rep.model, None, False)["failed"] == ["b"]
    m = EffectModel([PortOffset()])
    m.values_ = np.array([0.03, 0.0])   # a 30 mm port offset: beyond the plausible 20 mm
    v = _verdict(r1, sigma, st, m, None, True)
    assert v["failed"] == ["c"] and v["implausible"] == ["port_offset.dy"]
    e = rep.fit_errors
    assert _verdict(r1, sigma, st, rep.model, e, False)["failed"] == []          # nothing selected: after == before
    assert _verdict(r1, sigma, st, rep.model, e, True)["failed"] == ["d"]        # selected, yet no better
    worse = replace(e, pose_before=3 * sigma, pose_after=1.4 * sigma)
    assert _verdict(r1, sigma, st, rep.model, worse, True)["failed"] == ["d"]    # better, but not at the floor
    good = replace(e, pose_before=3 * sigma, pose_after=1.05 * sigma)
    assert _verdict(r1, sigma, st, rep.model, good, True)["failed"] == []
    assert math.isclose(_verdict(r1, sigma, st, rep.model, good, True)["validation_ratio"], 1.05)


@pytest.mark.slow
def test_a_cubic_tracker_distortion_on_the_phantom_is_not_explained():
    """The issue's first bench in kind: a PHANToM-like spatial arm, a cubic distortion of the tracker's
    space about 1.7 noise floors, and joint_geometry among the candidates (it absorbed part of it)."""
    from tests.test_calibration import SPATIAL
    from errplan.scenario import Port

    s = load_scenario(SPATIAL)
    s = s.with_(port=Port(s.port.position, (0.008, 0.004, 0.168)), controller=replace(s.controller, gain=0.3))
    quiet = s.with_(sensors=replace(s.sensors, tracker_sigma=0.0))
    d = run_experiment(quiet, seed=63, n_starts=3).data
    c = d.tip.mean(axis=0)
    z = (d.tip - c) / (d.tip.max(axis=0) - d.tip.min(axis=0)) * 2
    cub = np.stack([z[:, 0] ** 3 + z[:, 1] ** 2 * z[:, 0], z[:, 1] ** 3 - z[:, 2] ** 2 * z[:, 1],
                    z[:, 2] ** 3 + z[:, 0] ** 2 * z[:, 2]], -1)
    cub *= 1.4 * SIGMA / np.sqrt(np.mean(cub ** 2))
    rep = calibrate(s, noisy(d, d.tip + cub, 6), seed=0, folds=FOLDS,
                    effects=["joint_geometry", "gravity_sag", "shaft_flexion", "port_offset"])
    v = rep.to_json()["verdict"]
    assert not rep.explained and "b" in v["failed"], v
