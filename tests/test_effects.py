"""The effect library (errplan.effects): each class means what docs/physics.md says (checked with
independent formulas), effects add up, the least-squares fit recovers noise-free parameters
exactly, the stated uncertainty matches the closed form and a Monte Carlo spread, and
unidentifiable combinations are flagged."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from errplan.effects import (CATALOGUE, EFFECTS, EffectModel, GravitySag, JointOffset, PortFriction, PortOffset,
                             ShaftFlexion, TrackerOffset, make_effect, predict_tracked)
from errplan.errors import ErrplanError
from errplan.kinematics.shaft import flexed_tip, lever_tip
from errplan.scenario import EFFECT_PARAMS
from errplan.api import load_scenario
from errplan.simulation import Plant
from errplan.models import build_arm

ROOT = Path(__file__).resolve().parents[1]
PORT = ROOT / "scenarios" / "beasley2004_port.toml"


@pytest.fixture(scope="module")
def base():
    return Plant.from_model(build_arm(load_scenario(PORT)), effects=False)


@pytest.fixture(scope="module")
def rows(base):
    """Encoder angles over a patch of the workspace and random commanded directions."""
    rng = np.random.default_rng(0)
    tips = np.stack(np.meshgrid(np.linspace(-0.06, 0.06, 9), np.linspace(0.30, 0.42, 9)), -1).reshape(-1, 2)
    q = np.array([base.configuration_for_tip(x) for x in tips])
    a = rng.uniform(0, 2 * np.pi, len(q))
    u = np.stack([np.sin(a), np.cos(a)], -1)
    return q, u


def test_catalogue_matches_physics_md():
    from errplan.effects import GEOMETRY

    # tracker_latency: a physical effect of the catalogue (docs/physics.md "Measured data as a bench
    # records it"), its row of EFFECT_PARAMS after the geometry's
    assert [c.name for c in CATALOGUE + GEOMETRY if c.name != "joint_geometry"] == [
        n for n in EFFECT_PARAMS if n not in ("joint_geometry", "backlash", "tracker_latency")][:6] + [
        "tracker_latency"] + [n for n in EFFECT_PARAMS if n not in ("joint_geometry", "backlash", "tracker_latency")][6:]
    for c in CATALOGUE + GEOMETRY[:1] + GEOMETRY[2:]:
        assert c.params == EFFECT_PARAMS[c.name]
        assert len(c.units) == len(c.params) == len(c.default_scales)
        e = c()
        assert e.n_params == len(c.params) and e.scales == c.default_scales
    with pytest.raises(ErrplanError, match="not an effect"):
        make_effect("wobble")
    with pytest.raises(ErrplanError):
        PortOffset(scales=(1.0, -1.0))


def test_port_offset_moves_the_port(base, rows):
    q, u = rows
    p = PortOffset().apply(base, [0.003, -0.002])
    w = base.arm.forward(q)
    want = lever_tip(w, np.asarray(base.port) + [0.003, -0.002], base.length)
    assert np.allclose(predict_tracked(p, q, u), want, atol=1e-12)


def test_joint_offset_adds_to_encoders(base, rows):
    q, u = rows
    p = JointOffset().apply(base, [0.004, -0.003])
    want = lever_tip(base.arm.forward(q + [0.004, -0.003]), np.asarray(base.port), base.length)
    assert np.allclose(predict_tracked(p, q, u), want, atol=1e-12)


def test_tracker_offset_shifts_readings(base, rows):
    q, u = rows
    p = TrackerOffset().apply(base, [0.002, 0.001])
    assert np.allclose(predict_tracked(p, q, u) - predict_tracked(base, q, u), [0.002, 0.001], atol=1e-15)


def test_gravity_sag_formula(base, rows):
    q, u = rows
    c1, c2, c3 = 0.004, 0.002, 0.003
    p = GravitySag().apply(base, [c1, c2, c3])
    h1, h2 = base.arm.home
    a1 = q[:, 0] + h1
    a2 = a1 + q[:, 1] + h2
    qs = q - np.stack([c1 * np.cos(a1) + c2 * np.cos(a2), c3 * np.cos(a2)], -1)
    # wrist from the link angles by hand (physics.md "Robot")
    b = np.asarray(base.arm.base)
    s1 = qs[:, 0] + h1
    s2 = s1 + qs[:, 1] + h2
    w = b + base.arm.l1 * np.stack([np.sin(s1), np.cos(s1)], -1) + base.arm.l2 * np.stack([np.sin(s2), np.cos(s2)], -1)
    assert np.allclose(predict_tracked(p, q, u), lever_tip(w, np.asarray(base.port), base.length), atol=1e-12)


def test_shaft_flexion_uses_the_normal_component(base, rows):
    q, u = rows
    f = np.array([2.0, 1.0])
    p = ShaftFlexion().apply(base, f)
    w = base.arm.forward(q)
    d = np.asarray(base.port) - w
    th = np.arctan2(d[:, 0], d[:, 1])
    n = np.stack([np.cos(th), -np.sin(th)], -1)  # dir'(theta), the side of increasing angle
    t = n @ f
    assert np.allclose(predict_tracked(p, q, u), flexed_tip(w, np.asarray(base.port), base.length, t), atol=1e-12)
    # a load along the shaft bends nothing
    p_axial = ShaftFlexion().apply(base, [0.0, 0.0])
    assert np.allclose(predict_tracked(p_axial, q, u), predict_tracked(base, q, u))


def test_port_friction_holds_the_tip_back(base, rows):
    q, u = rows
    fa, fn = 0.0015, 0.001
    p = PortFriction().apply(base, [fa, fn])
    w = base.arm.forward(q)
    tip0 = lever_tip(w, np.asarray(base.port), base.length)
    s = (tip0 - w) / np.linalg.norm(tip0 - w, axis=1)[:, None]
    n = np.stack([s[:, 1], -s[:, 0]], -1)
    want = tip0 - fa * np.sum(u * s, 1)[:, None] * s - fn * np.sum(u * n, 1)[:, None] * n
    assert np.allclose(predict_tracked(p, q, u), want, atol=1e-12)
    # no command (u = 0, step 0): no friction
    assert np.allclose(predict_tracked(p, q, np.zeros_like(u)), tip0, atol=1e-15)


#: the catalogue's effects of the pose alone (tracker_latency needs runs and times: tests/test_bench_data.py)
POSE_EFFECTS = [c for c in CATALOGUE if c.name != "tracker_latency"]


@pytest.mark.parametrize("cls", POSE_EFFECTS)
def test_effects_are_additive(base, rows, cls):
    q, u = rows
    e = cls()
    a = np.array(e.default_scales) * 1.5
    b = np.array(e.default_scales) * -0.7
    twice = e.apply(e.apply(base, a), b)
    once = e.apply(base, a + b)
    assert np.allclose(e.values_of(twice), a + b)
    assert np.allclose(predict_tracked(twice, q, u), predict_tracked(once, q, u), atol=1e-14)


@pytest.mark.parametrize("cls", POSE_EFFECTS)
def test_fit_recovers_noise_free_parameters(base, rows, cls):
    q, u = rows
    e = cls()
    true = np.array(e.default_scales) * np.linspace(2.5, -1.5, e.n_params)
    data = predict_tracked(e.apply(base, true), q, u)
    got = cls().fit(q, u, data, base)
    assert np.allclose(got.values_, true, rtol=1e-6, atol=1e-9 * max(e.default_scales))
    assert got.model_.rss_ < 1e-20 and got.model_.identifiable_


def test_uncertainty_of_a_linear_effect_is_the_closed_form(base, rows):
    """Tracker offset is linear: each coordinate is a mean of n readings, sigma = s / sqrt(n)."""
    q, u = rows
    rng = np.random.default_rng(1)
    sig = 2e-4
    data = predict_tracked(TrackerOffset().apply(base, [1e-3, -2e-3]), q, u) + rng.normal(0, sig, (len(q), 2))
    m = EffectModel([TrackerOffset()]).fit(q, u, data, base)
    r = data - predict_tracked(base, q, u)
    assert np.allclose(m.values_, r.mean(axis=0), atol=1e-12)
    s = np.sqrt(m.rss_ / (2 * len(q) - 2))
    assert np.allclose(m.sigma_, s / np.sqrt(len(q)), rtol=1e-6)


def test_uncertainty_matches_monte_carlo(base, rows):
    """Gravity sag (nonlinear, correlated parameters): the spread of fits over noise draws agrees
    with the stated s^2 (J^T J)^-1 within 25 %."""
    q, u = rows
    true = np.array([0.004, 0.002, 0.003])
    clean = predict_tracked(GravitySag().apply(base, true), q, u)
    rng = np.random.default_rng(2)
    est, sig = [], []
    for _ in range(40):
        m = EffectModel([GravitySag()]).fit(q, u, clean + rng.normal(0, 2e-4, clean.shape), base)
        est.append(m.values_)
        sig.append(m.sigma_)
    est = np.array(est)
    assert np.allclose(est.mean(axis=0), true, atol=3 * np.mean(sig, axis=0) / np.sqrt(40) + 1e-7)
    assert np.allclose(est.std(axis=0, ddof=1), np.mean(sig, axis=0), rtol=0.25)


def test_unidentifiable_combinations_are_flagged(base, rows):
    q, u = rows
    data = predict_tracked(base, q, u)
    # one configuration only: a port offset and a tracker offset do the same thing
    one_q, one_u = np.repeat(q[:1], 30, 0), np.repeat(u[:1], 30, 0)
    m = EffectModel([PortOffset(), TrackerOffset()]).fit(one_q, one_u, np.repeat(data[:1], 30, 0), base)
    assert not m.identifiable_ and ("condition" in m.why_ or "correlate" in m.why_)
    # no commanded motion at all: nothing depends on friction
    m = EffectModel([PortFriction()]).fit(q, np.zeros_like(u), data, base)
    assert not m.identifiable_ and "no data depend on" in m.why_
    # a well-spread patch identifies every pair
    for a, b in [(PortOffset, TrackerOffset), (GravitySag, PortFriction), (JointOffset, TrackerOffset)]:
        assert EffectModel([a(), b()]).fit(q, u, data, base).identifiable_


def test_model_structure(base):
    m = EffectModel([GravitySag(), PortFriction()])
    assert m.label == "gravity_sag+port_friction" and m.n_params == 5
    assert m.param_labels == ["gravity_sag.c1", "gravity_sag.c2", "gravity_sag.c3", "port_friction.fa", "port_friction.fn"]
    p = m.plant(base, [1e-3, 2e-3, 3e-3, 4e-3, 5e-3])
    assert p.gravity_sag == (1e-3, 2e-3, 3e-3) and p.friction == (4e-3, 5e-3)
    assert m.parameters([1e-3, 2e-3, 3e-3, 4e-3, 5e-3])["port_friction"] == {"fa": 4e-3, "fn": 5e-3}
    assert EffectModel().label == "none"
    with pytest.raises(ErrplanError, match="twice"):
        EffectModel([GravitySag(), GravitySag()])
    assert set(EFFECTS) == set(EFFECT_PARAMS)
