"""Kinematics (docs/physics.md): the arm, the rigid lever and P2's flexed shaft. Every closed-form
Jacobian is checked against casadi AD (tests/casadi_twins.py) and central finite
differences; every inverse against its forward model; P2's appendix against AD with each
candidate quantity held constant."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import SCENARIOS
from errplan.kinematics import shaft
import casadi_twins as sym
from errplan.kinematics.arm import Arm, angle_of, direction, direction_derivative
from errplan.metrics import conformal_parts
from errplan.api import load_scenario

L = 0.320
PORT = np.array([0.0, 0.160])


@pytest.fixture(scope="module")
def arm():
    return Arm.from_robot(load_scenario(SCENARIOS / "beasley2004_port.toml").robot)


def fd_jacobian(f, x, h=1e-6):
    """Central differences of f (..., 2) -> (..., 2) at x (..., 2): (..., 2, 2)."""
    cols = []
    for i in range(2):
        e = np.zeros(2)
        e[i] = h
        cols.append((f(x + e) - f(x - e)) / (2 * h))
    return np.stack(cols, axis=-1)


def shaft_wrists(n, seed, lo=0.06, hi=0.30, p=PORT):
    """Wrists behind the port (the side away from the patient), at distance lo..hi from it."""
    rng = np.random.default_rng(seed)
    ang = rng.uniform(np.pi - 1.1, np.pi + 1.1, n)
    return p + rng.uniform(lo, hi, n)[:, None] * direction(ang)


# ----------------------------------------------------------------------------- arm
def test_arm_home_pose_and_fk(arm):
    assert np.allclose(arm.forward(np.zeros(2)), [0.0, 0.0], atol=1e-15)  # P1: wrist at origin at home
    q = np.array([0.3, -0.2])
    a1, a2 = 0.3, 0.3 - 0.2 - np.pi / 2
    want = np.array([0.21, -0.21]) + 0.21 * np.array([np.sin(a1), np.cos(a1)]) + 0.21 * np.array([np.sin(a2), np.cos(a2)])
    assert np.allclose(arm.forward(q), want)
    assert np.allclose(sym.arm_forward(arm, q), want)


def test_arm_jacobian_closed_form_vs_casadi_vs_fd(arm):
    rng = np.random.default_rng(0)
    q = np.stack([rng.uniform(-1.9, 1.2, 200), rng.uniform(-0.7, 1.0, 200)], -1)
    J = arm.jacobian(q)
    assert np.allclose(J, sym.arm_jacobian(arm, q), atol=1e-14)
    assert np.allclose(J, fd_jacobian(arm.forward, q), atol=1e-9)


def test_arm_ik_both_branches_and_limits(arm):
    rng = np.random.default_rng(1)
    q = np.stack([rng.uniform(-1.9, 1.2, 2000), rng.uniform(-0.7, 1.0, 2000)], -1)
    q = q[arm.within_limits(q)]
    w = arm.forward(q)
    q_pref, q_other, reach = arm.inverse_branches(w)
    assert reach.all()
    assert np.allclose(arm.forward(q_pref), w, atol=1e-12) and np.allclose(arm.forward(q_other), w, atol=1e-12)
    qi, ok = arm.inverse(w)
    assert ok.all() and np.allclose(arm.forward(qi), w, atol=1e-12)
    assert arm.within_limits(qi).all()
    # inside P1's limits the elbow never flips: the IK returns the very angles (q2 + h2 in (-pi, 0))
    assert np.allclose(qi, q, atol=1e-9)
    assert np.array_equal(arm.reachable(w), ok)


def test_arm_reachable_matches_inverse_everywhere(arm):
    rng = np.random.default_rng(2)
    w = rng.uniform(-0.4, 0.7, (50000, 2))
    _, ok = arm.inverse(w)
    assert np.array_equal(arm.reachable(w), ok)
    assert 0.05 < ok.mean() < 0.6
    # outside the annulus |l1 - l2| <= |w - base| <= l1 + l2: never reachable
    far = np.array([[0.21, -0.21 + 0.43], [0.21, -0.21]])
    assert not arm.reachable(far).any()
    # other home angles and wide limits: the fast mask still equals the IK's
    other = Arm((0.1, -0.2), 0.25, 0.18, (0.4, -2.0), (-2.5, 2.5), (-2.0, 2.9), (-3.0, 3.0))
    _, ok2 = other.inverse(w)
    assert np.array_equal(other.reachable(w), ok2) and ok2.any()


def test_arm_limit_margin(arm):
    q = np.array([[0.0, 0.0], [1.2, -0.5], [1.3, 0.0], [0.0, 1.0], [-0.2, -0.2]])
    margin = arm.limit_margin(q)
    assert margin[0] == pytest.approx(0.3)   # q1 + q2 = 0 is 0.3 above -0.3
    assert margin[1] == pytest.approx(0.0, abs=1e-12)
    assert margin[2] < 0 and not arm.within_limits(q[2])
    assert margin[4] < 0  # q1 + q2 = -0.4 < -0.3
    assert np.array_equal(margin >= -1e-12, arm.within_limits(q))


def test_p1_experiment_points_are_reachable(arm):
    """physics.md: L, M, N and their +-20 mm targets are reachable (elbow solution inside limits)."""
    pts = []
    for z in (0.320, 0.375, 0.415):
        for dy in (-0.02, 0.0, 0.02):
            for dz in (-0.02, 0.0, 0.02):
                pts.append([dy, z + dz])
    w = shaft.lever_wrist(np.array(pts), PORT, L)
    assert arm.reachable(w).all()


# ----------------------------------------------------------------------------- rigid lever
def test_lever_geometry_and_inverse():
    w = shaft_wrists(300, 3)
    tip = shaft.lever_tip(w, PORT, L)
    assert np.allclose(np.linalg.norm(tip - w, axis=-1), L)
    # the port lies on the segment wrist -> tip
    u = (tip - w) / L
    proj = np.einsum("...i,...i->...", PORT - w, u)
    assert np.allclose(w + proj[:, None] * u, PORT, atol=1e-14)
    assert np.allclose(shaft.lever_wrist(tip, PORT, L), w, atol=1e-14)
    assert np.allclose(sym.lever_tip(w, PORT, L), tip, atol=1e-15)


def test_lever_jacobian_closed_form_vs_casadi_vs_fd():
    w = shaft_wrists(300, 4)
    J = shaft.lever_jacobian(w, PORT, L)
    assert np.allclose(J, sym.lever_jacobian(w, PORT, L), atol=1e-12)
    assert np.allclose(J, fd_jacobian(lambda ww: shaft.lever_tip(ww, PORT, L), w), atol=1e-7)
    mu, nu = shaft.lever_parts(w, PORT, L)
    mu_ref, nu_ref = conformal_parts(J)
    assert np.allclose(mu, mu_ref) and np.allclose(nu, nu_ref)
    # singular where the tip reaches the port (|p - w| = L)
    w_sing = PORT + L * direction(np.array(2.8))
    assert abs(np.linalg.det(shaft.lever_jacobian(w_sing, PORT, L))) < 1e-12


# ----------------------------------------------------------------------------- flexed shaft
LOADS = np.array([-5.0, -3.0, -1.0, 0.5, 2.0, 3.0, 5.0])


def test_flexed_geometry_satisfies_p2():
    w = shaft_wrists(7 * 40, 5)
    t = np.repeat(LOADS, 40)
    g = shaft.flexed_geometry(w, PORT, L, t)
    a, b = g["a"], g["b"]
    ym = -t * a * b * b / 3.0                     # eq. (10) with Fp = Ft L / a
    assert np.allclose(g["rho"] ** 2, a * a + ym * ym, rtol=1e-13)   # eq. (18)
    assert np.allclose(g["phi"], g["theta"] - np.arctan(ym / a))      # eq. (7)
    assert np.allclose(np.linalg.norm(g["tip"] - w, axis=-1), L)      # eq. (6)
    # the port is the beam point (a, y_m(a)) of the model frame (eq. 8), and eq. (1) passes there
    fp = t * L / a
    assert np.allclose(shaft.beam_height(a, a, L, fp), ym, rtol=1e-12, atol=1e-16)
    port = w + a[:, None] * direction(g["phi"]) + ym[:, None] * direction_derivative(g["phi"])
    assert np.allclose(port, PORT, atol=1e-13)
    # casadi's rootfinder solves eq. (18) to the same a
    shape = sym.flexed_shape(w, PORT, L, t)
    assert np.allclose(shape[:, 0], a, atol=1e-13) and np.allclose(shape[:, 1], ym, atol=1e-14)


def test_beam_slope_is_derivative_of_height_and_ends_rest():
    a = np.array([0.1, 0.16, 0.25])
    fp = np.array([9.0, -4.0, 2.0])
    for xm in np.linspace(0.01, L - 0.01, 13):
        h = 1e-6
        fd = (shaft.beam_height(xm + h, a, L, fp) - shaft.beam_height(xm - h, a, L, fp)) / (2 * h)
        assert np.allclose(shaft.beam_slope(np.full(3, xm), a, L, fp), fd, atol=1e-8)
    assert np.allclose(shaft.beam_height(np.zeros(3), a, L, fp), 0) and np.allclose(shaft.beam_height(np.full(3, L), a, L, fp), 0, atol=1e-15)


def test_flexed_reduces_to_lever_without_load():
    w = shaft_wrists(100, 6)
    assert np.allclose(shaft.flexed_tip(w, PORT, L, 0.0), shaft.lever_tip(w, PORT, L), atol=1e-15)
    assert np.allclose(shaft.flexed_jacobian(w, PORT, L, 0.0), shaft.lever_jacobian(w, PORT, L), atol=1e-12)


def test_flexed_jacobian_closed_form_vs_casadi_vs_fd():
    w = shaft_wrists(7 * 30, 7)
    t = np.repeat(LOADS, 30)
    J = shaft.flexed_jacobian(w, PORT, L, t)
    J_ad = sym.flexed_jacobian(w, PORT, L, t, hold="tip_force")
    J_fd = fd_jacobian(lambda ww: shaft.flexed_tip(ww, PORT, L, t), w)
    assert np.max(np.abs(J - J_ad)) < 1e-10
    assert np.max(np.abs(J - J_fd)) < 1e-7
    assert np.max(np.abs(J_ad - J_fd)) < 1e-7
    # flexion matters: the flexed Jacobian is not the lever's
    assert np.max(np.abs(J - shaft.lever_jacobian(w, PORT, L))) > 1e-3


def test_flexed_wrist_inverts_flexed_tip():
    rng = np.random.default_rng(8)
    r = rng.uniform(0.03, 0.30, 400)
    x = PORT + r[:, None] * direction(rng.uniform(-1.0, 1.0, 400))
    t = rng.uniform(-5, 5, 400)
    w = shaft.flexed_wrist(x, PORT, L, t)
    assert np.allclose(shaft.flexed_tip(w, PORT, L, t), x, atol=1e-12)
    assert np.allclose(shaft.flexed_wrist(x, PORT, L, 0.0), shaft.lever_wrist(x, PORT, L), atol=1e-15)


def test_estimate_from_ends_recovers_the_model():
    """P2 eqs. (8)-(14): noise-free end poses give back a, Fp/EI, Ft/EI and the port."""
    w = shaft_wrists(6 * 30, 9, lo=0.08, hi=0.26)
    t = np.repeat(np.array([-5.0, -3.0, -1.0, 1.0, 3.0, 5.0]), 30)
    g = shaft.flexed_geometry(w, PORT, L, t)
    tip, thw, tht = shaft.flexed_end_angles(w, PORT, L, t)
    est = shaft.estimate_from_ends(w, tip, thw, tht, L)
    assert np.allclose(est["a"], g["a"], rtol=1e-9)
    assert np.allclose(est["t"], t, rtol=1e-8)
    assert np.allclose(est["fp_over_ei"], t * L / g["a"], rtol=1e-8)
    assert np.allclose(est["port"], PORT, atol=1e-11)
    # no flexion: a is not identifiable -> NaN, never inf
    tip0, thw0, tht0 = shaft.flexed_end_angles(w[:3], PORT, L, 0.0)
    with np.errstate(invalid="ignore"):
        est0 = shaft.estimate_from_ends(w[:3], tip0, thw0, tht0, L)
    for key in ("a", "fp_over_ei", "t", "port", "ym"):
        assert np.isnan(est0[key]).all(), key


def test_hold_variants_agree_at_the_point_and_match_fd():
    """casadi's three forward models pass through the same shape; each AD Jacobian equals the
    central differences of its own forward model, and the three Jacobians differ."""
    w = shaft_wrists(60, 10, lo=0.08, hi=0.25)
    t = np.repeat(np.array([-4.0, 3.0, 6.0]), 20)
    g = shaft.flexed_geometry(w, PORT, L, t)
    loads = {"tip_force": t, "port_force": t * L / g["a"], "port_deflection": -t * g["a"] * g["b"] ** 2 / 3}
    Js = {}
    for hold, load in loads.items():
        assert np.allclose(sym.flexed_tip(w, PORT, L, load, hold), g["tip"], atol=1e-13)
        Js[hold] = sym.flexed_jacobian(w, PORT, L, load, hold)
        fd = fd_jacobian(lambda ww, load=load, hold=hold: sym.flexed_tip(ww, PORT, L, load, hold), w)
        assert np.max(np.abs(Js[hold] - fd)) < 1e-7, hold
    for h1, h2 in (("tip_force", "port_force"), ("tip_force", "port_deflection"), ("port_force", "port_deflection")):
        assert np.max(np.abs(Js[h1] - Js[h2])) > 1e-3, (h1, h2)


# ----------------------------------------------------------------------------- P2's appendix
def _appendix_errors(repaired: bool, angle: str = "port"):
    w = shaft_wrists(240, 11, lo=0.06, hi=0.28)
    t = np.repeat(np.array([-5.0, -3.0, -1.0, 1.0, 3.0, 5.0]), 40)
    g = shaft.flexed_geometry(w, PORT, L, t)
    a = g["a"]
    ym = -t * a * g["b"] ** 2 / 3
    A = sym.p2_appendix_jacobian(w, PORT, L, a, ym, repaired=repaired, angle=angle)
    loads = {"tip_force": t, "port_force": t * L / a, "port_deflection": ym}
    out = {}
    for hold, load in loads.items():
        J = sym.flexed_jacobian(w, PORT, L, load, hold)
        # error relative to the flexion part of the Jacobian (J - I)
        out[hold] = np.linalg.norm(A - J, axis=(-2, -1)) / np.linalg.norm(J - np.eye(2), axis=(-2, -1))
    return out


def test_p2_appendix_repaired_is_the_jacobian_holding_fp_over_ei():
    """P2's appendix, with its two garbled terms repaired (temp2 = 2 (2a - L) temp1 / (a - L),
    temp3 = (3 L a + temp2 y_m / a)(a^2 + y_m^2)), is exactly casadi's AD of the flexed forward
    model with Fp/EI held constant; it is not the Jacobian holding Ft/EI or y_m(a)."""
    err = _appendix_errors(repaired=True)
    assert np.max(err["port_force"]) < 1e-9
    assert np.median(err["tip_force"]) > 5e-3 and np.median(err["port_deflection"]) > 5e-3
    # the printed phi is the port direction angle(p - w), not eq. (7)'s chord angle
    assert np.median(_appendix_errors(repaired=True, angle="chord")["port_force"]) > 5e-3


def test_p2_appendix_as_printed():
    """As printed (dimensionally inconsistent: temp2 - temp1 mixes m^3 and m^2), evaluated in SI,
    the appendix reproduces none of the three Jacobians exactly; it is closest to the one holding
    y_m(a) (temp2 is tiny in metres, leaving -temp1 / (3 L a (a^2 + y_m^2)) = the y_m-held chain
    rule), within 2.1 % of the flexion part J - I, median 0.11 %."""
    err = _appendix_errors(repaired=False)
    assert 1e-5 < np.median(err["port_deflection"]) < 2e-3 and np.max(err["port_deflection"]) < 3e-2
    assert np.median(err["tip_force"]) > 5e-3 and np.median(err["port_force"]) > 5e-3
    assert np.median(err["port_deflection"]) < 0.2 * min(np.median(err["tip_force"]), np.median(err["port_force"]))


def test_fields_use_the_tip_force_hold():
    """errplan's true Jacobian (fields, simulation) holds Ft/EI: the tip load is the external one."""
    w = shaft_wrists(20, 12)
    assert np.allclose(shaft.flexed_jacobian(w, PORT, L, 3.0), sym.flexed_jacobian(w, PORT, L, 3.0, "tip_force"), atol=1e-10)
    assert angle_of(np.array([1.0, 0.0])) == pytest.approx(np.pi / 2)


# ----------------------------------------------------------------------------- P2's controller in 3-D
def spatial_shafts(n, seed, L=0.355):
    """Wrists, ports and world loads (normal part up to 5 1/m^2, any direction) in 3-D."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.05, 0.05, (n, 3)) + [0.0, 0.0, 0.2]
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    w = p - rng.uniform(0.08, 0.27, n)[:, None] * (v + [0.0, 0.0, 2.0]) / np.linalg.norm(v + [0.0, 0.0, 2.0], axis=-1,
                                                                                            keepdims=True)
    t = rng.uniform(-5, 5, (n, 3))
    return w, p, t


def fd3(f, x, h=1e-6):
    return np.stack([(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)


def test_flexed_jacobian_3d_closed_form_vs_casadi_vs_fd():
    """docs/physics.md "P2's flexion controller in 3-D": d tip/d w with the port and the world load
    vector held, closed form against casadi AD (an independent 3-D model) and central differences."""
    L3 = 0.355
    w, p, t = spatial_shafts(60, 21)
    tip = shaft.flexed_tip(w, p, L3, t)
    assert np.allclose(tip, sym.flexed_tip_3d(w, p, L3, t), atol=1e-12)
    J = shaft.flexed_jacobian(w, p, L3, t)
    J_ad = sym.flexed_jacobian_3d(w, p, L3, t)
    J_fd = fd3(lambda ww: shaft.flexed_tip(ww, p, L3, t), w)
    assert np.max(np.abs(J - J_ad)) < 1e-10
    assert np.max(np.abs(J - J_fd)) < 1e-7
    assert np.max(np.abs(J - shaft.lever_jacobian(w, p, L3))) > 1e-3


def test_estimate_from_end_poses_recovers_the_3d_model():
    """Noise-free end poses of a shaft bent in any plane give back the port and the load's
    normal part (the estimator's bending plane is the true one); the flexed shaft through the
    estimate reproduces the measured tip and the controller's Jacobian is the true one of the
    normal load."""
    L3 = 0.355
    w, p, t = spatial_shafts(80, 22)
    tip, dw, dt = shaft.flexed_end_directions(w, p, L3, t)
    assert np.allclose(np.linalg.norm(dw, axis=-1), 1) and np.allclose(np.linalg.norm(dt, axis=-1), 1)
    est = shaft.estimate_from_end_poses(w, tip, dw, dt, L3)
    u = (p - w) / np.linalg.norm(p - w, axis=-1, keepdims=True)
    tperp = t - np.sum(t * u, axis=-1, keepdims=True) * u
    assert np.allclose(est["port"], p, atol=1e-10)
    assert np.allclose(est["load"], tperp, atol=1e-7)
    assert np.allclose(shaft.flexed_tip(w, est["port"], L3, est["load"]), tip, atol=1e-12)
    Jh = shaft.flexion_controller_jacobian(w, tip, dw, dt, L3)
    # the estimate holds the load's normal part; the truth's axial part turns with the shaft
    assert np.allclose(Jh, shaft.flexed_jacobian(w, p, L3, tperp), atol=1e-7)
    # unbent: the tangents are the chord, nothing identifies a (NaN, as in the plane)
    tip0, dw0, dt0 = shaft.flexed_end_directions(w[:4], p[:4], L3, 0.0 * t[:4])
    with np.errstate(invalid="ignore", divide="ignore"):
        est0 = shaft.estimate_from_end_poses(w[:4], tip0, dw0, dt0, L3)
    assert np.isnan(est0["a"]).all() and np.isnan(est0["port"]).all()


def test_flexion_controller_in_plane_x0_equals_planar():
    """On the plane x = 0 with in-plane loads and in-plane noise the 3-D flexion controller (end
    directions, estimated plane, estimate, Jhat) equals P2's planar one to 1e-9 relative."""
    L3 = 0.355
    rng = np.random.default_rng(23)
    w2 = shaft_wrists(120, 24, lo=0.08, hi=0.26)
    t2 = rng.uniform(-5, 5, 120)
    nz = rng.uniform(-1, 1, (120, 6)) * np.array([7e-4] * 4 + [2.6e-3] * 2)
    emb = lambda v: np.concatenate([np.zeros(v.shape[:-1] + (1,)), v], axis=-1)
    tip2, thw, tht = shaft.flexed_end_angles(w2, PORT, L3, t2)
    tip3, dw3, dt3 = shaft.flexed_end_directions(emb(w2), emb(PORT), L3, emb(t2[:, None] * direction_derivative(
        angle_of(PORT - w2))))
    assert np.allclose(tip3, emb(tip2), atol=1e-14)
    assert np.allclose(dw3, emb(direction(thw)), atol=1e-14) and np.allclose(dt3, emb(direction(tht)), atol=1e-14)
    pw, pt = w2 + nz[:, 0:2], tip2 + nz[:, 2:4]
    aw, at = thw + nz[:, 4], tht + nz[:, 5]
    e2 = shaft.estimate_from_ends(pw, pt, aw, at, L3)
    J2 = shaft.flexed_jacobian(pw, e2["port"], L3, e2["t"])
    e3 = shaft.estimate_from_end_poses(emb(pw), emb(pt), emb(direction(aw)), emb(direction(at)), L3)
    J3 = shaft.flexion_controller_jacobian(emb(pw), emb(pt), emb(direction(aw)), emb(direction(at)), L3)
    assert np.allclose(e3["port"], emb(e2["port"]), rtol=0, atol=1e-12)
    assert np.max(np.abs(J3[:, 1:, 1:] - J2) / np.abs(J2).max(axis=(-2, -1))[:, None, None]) < 1e-9
    assert np.all(J3[:, 0, 1:] == 0) and np.all(J3[:, 1:, 0] == 0)
    # the same function in the plane is the planar estimator
    e2b = shaft.estimate_from_end_poses(pw, pt, direction(aw), direction(at), L3)
    assert np.allclose(e2b["load"], e2["t"], rtol=1e-12)
    # out-of-plane noise tilts the estimated plane: the 3-D Jacobian leaves the plane
    J3o = shaft.flexion_controller_jacobian(emb(pw), emb(pt) + [[3e-4, 0, 0]],
                                            shaft.tilt(emb(direction(aw)), np.array([0.0, 2e-3]),
                                                       np.array([1.0, 0, 0]), emb(direction_derivative(aw))),
                                            emb(direction(at)), L3)
    assert np.max(np.abs(J3o[:, 0, 1:])) > 1e-4


def test_spatial_flexed_tip_of_one_point_is_the_vectorized_one_bit_for_bit():
    """``flexed_tip`` of one wrist, port and load (plain floats: a simulation step's call) gives the bits
    of the vectorized model, for loads normal, oblique, axial (no bend) and zero, wrists far from and at
    the port (numpy's nan there, no exception)."""
    import warnings

    rng = np.random.default_rng(4)
    n = 3000
    W = rng.normal(0.0, 0.15, (n, 3))
    P = rng.normal(0.0, 0.05, (n, 3))
    T = rng.normal(0.0, 1.5, (n, 3))
    T[::5] = 0.0
    T[1::7] = 2.0 * (P - W)[1::7]  # along the shaft: no bend
    P[::97] = W[::97]  # the wrist at the port
    L = 0.32
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ref = shaft._spatial_geometry(W, P, L, T)["tip"]
        one = np.array([shaft.flexed_tip(W[i], P[i], L, T[i]) for i in range(n)])
    assert np.isnan(ref[::97]).all()
    assert np.array_equal(one, ref, equal_nan=True)
