"""Fields on a truth with [effects]: the arm Jacobian no longer cancels (physics.md "Effects")."""
import dataclasses

import numpy as np
import pytest
from scipy.optimize import fsolve

from errplan.fields import Evaluator, compute_fields
from errplan.api import load_scenario
from errplan.simulation import ControllerModel, Plant
from errplan.models import build_arm

SC = load_scenario("scenarios/beasley2004_port.toml")


def test_port_offset_effect_equals_moving_the_true_port():
    a = compute_fields(SC.with_(effects={"port_offset": {"dy": 0.003, "dz": -0.002}}), 0.004)
    b = compute_fields(SC.with_(port=dataclasses.replace(SC.port, position=(0.003, 0.158))), 0.004)
    assert np.array_equal(a.valid, b.valid)
    # The rigid controller runs the compiled kernel, the flexion controller the numpy search: equal to
    # rounding, relative to max(1, ||G||) (||G|| reaches 83 near the port).
    assert np.nanmax(np.abs(a.G_norm - b.G_norm) / np.maximum(1.0, np.abs(b.G_norm))) < 1e-13


def test_general_effect_path_reproduces_the_closed_form_without_effects():
    f = compute_fields(SC, 0.006)
    pts = f.points()[f.valid]
    ev = Evaluator.from_model(build_arm(SC))
    mu, nu, ok = ev.parts(pts, np.zeros(3))
    ev.effects = {"joint_offset": (0.0, 0.0)}  # forces the Newton + finite-difference path
    mu2, nu2, ok2 = ev.parts(pts, np.zeros(3))
    assert np.array_equal(ok, ok2)
    assert np.max(np.abs(mu - mu2)) < 1e-5 and np.max(np.abs(nu - nu2)) < 1e-5


@pytest.mark.parametrize("effects", [
    {"gravity_sag": {"c1": 0.004, "c2": 0.002, "c3": 0.003}},
    {"joint_offset": {"dq1": 0.01, "dq2": -0.02}},
    {"shaft_flexion": {"fy": 2.0, "fz": 1.0}},
])
def test_effect_fields_match_an_independent_solve(effects):
    sc = SC.with_(effects=effects)
    f = compute_fields(sc, 0.01)
    plant, ctl = Plant.from_model(build_arm(sc)), ControllerModel.from_model(build_arm(sc))
    plant0 = Plant.from_model(build_arm(SC))
    P = f.points()
    idx = np.argwhere(f.valid)
    rng = np.random.default_rng(3)
    changed = 0
    for i, j in idx[rng.choice(len(idx), 12, replace=False)]:
        x = P[i, j]
        q = fsolve(lambda q: plant.tip(q) - x, plant0.configuration_for_tip(x), xtol=1e-13)
        assert np.linalg.norm(plant.tip(q) - x) < 1e-9
        h = 1e-6
        J = np.stack([(plant.tip(q + h * e) - plant.tip(q - h * e)) / (2 * h) for e in np.eye(2)], -1)
        G = np.eye(2) - SC.controller.gain * J @ np.linalg.inv(ctl.J_hat(q))
        assert abs(np.linalg.norm(G, 2) - f.G_norm[i, j]) < 1e-4 * max(1.0, f.G_norm[i, j])
        base = np.eye(2) - plant0.true_jacobian(plant0.configuration_for_tip(x)) @ np.linalg.inv(
            ctl.J_hat(plant0.configuration_for_tip(x)))
        changed += abs(np.linalg.norm(base, 2) - f.G_norm[i, j]) > 1e-3
    assert changed > 0  # the effect really enters the field


def test_flexion_controller_on_an_unbent_shaft_falls_back_to_the_lever():
    """P2's model is not identifiable without bending: fields and J_hat use the lever through the
    port estimate there, so the flexion controller's fields equal the rigid controller's."""
    flex = SC.with_(controller=dataclasses.replace(SC.controller, jacobian="flexion"))
    a, b = compute_fields(flex, 0.008), compute_fields(SC, 0.008)
    assert np.array_equal(a.valid, b.valid) and a.valid.any()
    # The rigid controller runs the compiled kernel, the flexion controller the numpy search: equal to
    # rounding, relative to max(1, ||G||) (||G|| reaches 83 near the port).
    assert np.nanmax(np.abs(a.G_norm - b.G_norm) / np.maximum(1.0, np.abs(b.G_norm))) < 1e-13
    plant = Plant.from_model(build_arm(SC))
    q = plant.configuration_for_tip(np.array([0.0, 0.375]))
    J_flex = ControllerModel.from_model(build_arm(flex)).J_hat(q, plant)
    assert np.allclose(J_flex, ControllerModel.from_model(build_arm(SC)).J_hat(q), atol=1e-12)
