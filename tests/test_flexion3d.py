"""P2's flexion controller in 3-D (issue 20; docs/physics.md "P2's flexion controller in 3-D").

Checked against independent things: P2's planar controller (errplan's planar fields and
insertion model) on the plane x = 0 and, for a load in a diagonal direction, the planar controller
with the noise box seen along that direction; finite differences of the flexed shaft for the
out-of-plane entry of the motion map.
"""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from errplan.api import load_scenario
from errplan.fields import ErrorSet, Evaluator, SpatialFlexionEvaluator, compute_fields, worst_case
from errplan.errorset import spatial_noise_corners
from errplan.kinematics import shaft
from errplan.metrics import g_norm
from errplan.tolerance.insertion import InsertionModel, insertion_worst
from errplan.models import build_arm

ROOT = Path(__file__).resolve().parents[1]
FLEX2 = ROOT / "scenarios" / "beasley_howe_flexion.toml"
L = 0.355
POS, ANG = 0.000746, 0.0026  # P2's Liberty tracker


def spatial_flexion_scenario(tmp_path: Path, extra: str = "", unc: str | None = None) -> Path:
    """P2's shaft and tracker on the PHANToM with a waist (scenarios/phantom15.urdf)."""
    unc = unc if unc is not None else """
[uncertainty]
tip_force_over_ei = [3.0, 3.0]
sensor_noise = { position = 0.000746, angle = 0.0026 }
samples = 3
"""
    text = f"""
name = "flex3d"
[robot]
urdf = "{ROOT / 'scenarios' / 'phantom15.urdf'}"
joints = ["waist", "shoulder", "elbow"]
wrist = "wrist"
base_position = [0.0, 0.210, -0.210]
base_rpy = [0.0, 0.0, 0.0]
joint_limits = [[-1.0, 1.0], [-1.9, 1.2], [-0.7, 1.0]]
coupled_limits = [{{ joints = ["shoulder", "elbow"], coeffs = [1.0, 1.0], range = [-0.3, 2.8] }}]
[instrument]
length = 0.355
[port]
position = [0.0, 0.0, 0.160]
estimate = [0.0, 0.0, 0.160]
[controller]
gain = 1.0
jacobian = "flexion"
{unc}
[fields]
resolution = 0.01
region = {{ x = [-0.01, 0.01], y = [-0.01, 0.01], z = [0.40, 0.42] }}
{extra}
"""
    p = tmp_path / "flex3d.toml"
    p.write_text(text, encoding="utf-8")
    return p


def fd_out_of_plane(w, p, t):
    """d tip_x / d w_x of the flexed shaft by central differences (w, p in the plane x = 0)."""
    h = 1e-6
    e = np.array([h, 0.0, 0.0])
    return (shaft.flexed_tip(w + e, p, L, t)[..., 0] - shaft.flexed_tip(w - e, p, L, t)[..., 0]) / (2 * h)


def test_x0_plane_fields_equal_the_planar_controller(tmp_path):
    """Motion in the plane x = 0, an in-plane load, in-plane noise: the 3-D worst case over the
    noise set is the planar one composed with the out-of-plane entry. In x = 0 the motion map is
    block diagonal (the planar 2 x 2 block and ``m_xx = J_xx / Jhat_xx``), so the 3-D ||G|| is
    max(planar ||G||, max over corners of |1 - k m_xx|) to 1e-9 relative, and the planar block is
    P2's planar controller itself."""
    sc2 = load_scenario(FLEX2)
    sc3 = load_scenario(spatial_flexion_scenario(tmp_path))
    ev2 = Evaluator.from_model(build_arm(sc2))
    k = 0.8
    # psi = 0 is the in-plane load direction of positive planar t (f1 = e1 x x_hat = dir'(theta))
    es3 = ErrorSet((0.0, 0.0, 0.160), (0.0, 0.0, 0.0, 3.0, 0.0), (0.0, 0.0, 0.0, 3.0, 0.0), (POS, ANG), 3)
    ev3 = SpatialFlexionEvaluator(load_ev_arm(sc3), L, (0.0, 0.0, 0.160), es3,
                                  spatial_noise_corners(POS, ANG, in_plane=True))
    y = np.linspace(-0.03, 0.03, 7)
    z = np.linspace(0.37, 0.45, 9)
    Y, Z = np.meshgrid(y, z, indexing="ij")
    x2 = np.stack([Y.ravel(), Z.ravel()], -1)
    x3 = np.concatenate([np.zeros((len(x2), 1)), x2], -1)
    w2 = worst_case(ev2, x2, k)
    w3 = worst_case(ev3, x3, k)
    assert np.array_equal(w2["valid"], w3["valid"]) and w2["valid"].sum() > 40
    v = w2["valid"]
    # the out-of-plane entry, independently: finite differences of the flexed shaft, the controller's
    # estimate from the planar estimator (the noise corners of the plane)
    w3t, t3, p3, _ = ev3.truth(x3[v], es3.lo_arr)
    Jxx = fd_out_of_plane(w3t, p3, t3)
    tip2, thw, tht = shaft.flexed_end_angles(w3t[:, 1:], p3[:, 1:], L, 3.0)
    nc = ev2.errors.noise_corners()
    pw = w3t[:, None, 1:] + nc[:, 0:2]
    est = shaft.estimate_from_ends(pw, tip2[:, None] + nc[:, 2:4], thw[:, None] + nc[:, 4], tht[:, None] + nc[:, 5], L)
    emb = lambda a: np.concatenate([np.zeros(a.shape[:-1] + (1,)), a], -1)
    load = est["t"][..., None] * emb(shaft.direction_derivative(shaft.angle_of(est["port"] - pw)))
    Jhxx = fd_out_of_plane(emb(pw), emb(est["port"]), load)
    g_out = np.abs(1 - k * Jxx[:, None] / Jhxx).max(axis=1)
    expect = np.maximum(w2["G_norm"][v], g_out)
    np.testing.assert_allclose(w3["G_norm"][v], expect, rtol=1e-9)
    assert np.any(w2["G_norm"][v] > g_out), "the planar block should decide somewhere"
    # the planar block on its own equals the planar controller to 1e-9 relative
    M3, _, ok3 = ev3.parts(x3[v], es3.lo_arr)
    mu, nu, ok2 = ev2.parts(x2[v], ev2.errors.lo_arr)
    G2 = g_norm(np.asarray(_maps_from_parts(mu, nu)), k).max(axis=1)
    G3b = g_norm(M3[:, :, 1:, 1:], k).max(axis=1)
    np.testing.assert_allclose(G3b, G2, rtol=1e-9)
    assert np.all(w3["phi_max"][v] >= w2["phi_max"][v] - 1e-6)


def load_ev_arm(sc):
    from errplan.kinematics import arm_for

    return arm_for(sc.robot)


def _maps_from_parts(mu, nu):
    """2 x 2 maps from conformal parts: M z = mu z + nu conj(z) (z = y + i z)."""
    a, b = mu.real, mu.imag
    c, d = nu.real, nu.imag
    return np.stack([np.stack([a + c, -b + d], -1), np.stack([b + d, a - c], -1)], -2)


def test_diagonal_load_sees_the_noise_box_diagonal(tmp_path):
    """Shaft along z, load toward (x + y)/sqrt(2): rotating the world by 45 deg about z is P2's
    planar problem whose normal axis sees both position axes: position half width sqrt(2) p
    normal to the shaft, p along it. The 3-D worst over the noise set's corners equals the
    planar worst over that box (an independent check of the 3-D noise set and of the bending
    plane estimate), and exceeds the in-plane load's (itself at least the planar worst case)."""
    sc3 = load_scenario(spatial_flexion_scenario(tmp_path))
    ev = SpatialFlexionEvaluator.from_model(build_arm(sc3))
    m = InsertionModel(L, 3.0, 1.0)
    for rl in (0.66, 0.72, 0.8):
        x = np.array([[0.0, 0.0, 0.160 + rl * L]])
        gs = [g_norm(ev.parts(x, np.array([0, 0, 0, 3.0, psi]))[0], 1.0).max() for psi in (0.0, math.pi / 4)]
        p2 = POS * math.sqrt(2)
        ref = insertion_worst(m, np.array([rl]), POS, ANG, half=np.array([[p2, POS, p2, POS, ANG, ANG]]))[0]
        ref0 = insertion_worst(m, np.array([rl]), POS, ANG)[0]
        assert gs[1] == pytest.approx(ref, rel=1e-6)
        assert gs[0] >= ref0 * (1 - 1e-9)  # the in-plane load: the planar worst, or more (out-of-plane noise)
        assert gs[1] > gs[0]


def test_spatial_flexion_fields_run_and_say_lower_bound(tmp_path):
    """errplan fields on a spatial flexion scenario: the numpy search over loads in every direction
    normal to the shaft and the noise set's corners; the npz metadata says the noise worst case
    is a lower bound."""
    sc = load_scenario(spatial_flexion_scenario(tmp_path))
    m = compute_fields(sc, metrics=("G_norm", "phi_max"))
    assert m.valid.all() and m.G_norm.shape == (3, 3, 3)
    assert np.all(np.isfinite(m.G_norm)) and np.all(m.G_norm > 1.0)  # the Liberty bounds in 3-D: no band here
    assert "lower bound" in m.meta["noise_worst_case"]
    # symmetric in x -> -x (the PHANToM's waist, an axis-aligned noise set)
    np.testing.assert_allclose(m.G_norm, m.G_norm[::-1], rtol=1e-9)


# ----------------------------------------------------------------------------- gains and replays
def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _fd(f, x, h=1e-6):
    return np.stack([(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(len(x))], axis=-1)


def independent_replay(arm, L, port, t_world, q0, waypoints, gains, pos, ang, rng, steps=60):
    """A simulator sharing no controller code with errplan.simulation: the true tip from the arm's
    forward kinematics and the 3-D flexed shaft under a constant world load; the controller's
    measurements with uniform noise (positions per coordinate, directions tilted inside the cone),
    P2's estimate, ``Jhat = d tip/d w`` by central differences of the flexed shaft through the
    estimated port with the estimated load, times the arm's Jacobian by central differences.
    Returns the distances to the active target before each command, per segment."""
    q = np.array(q0, float)
    out = []
    for b, k in zip(waypoints, gains):
        errs = []
        for _ in range(steps):
            w = arm.forward(q)
            tip, dw, dt = shaft.flexed_end_directions(w, port, L, t_world)
            e = b - tip
            errs.append(float(np.linalg.norm(e)))
            if errs[-1] < 1e-7:
                break
            pw = w + rng.uniform(-pos, pos, 3)
            pt = tip + rng.uniform(-pos, pos, 3)
            meas = []
            for d in (dw, dt):
                f1 = _unit(np.cross(d, [1.0, 0.0, 0.0]))
                f2 = np.cross(d, f1)
                r, a = ang * math.sqrt(rng.uniform()), rng.uniform(0, 2 * math.pi)
                meas.append(_unit(math.cos(r) * d + math.sin(r) * (math.cos(a) * f1 + math.sin(a) * f2)))
            est = shaft.estimate_from_end_poses(pw, pt, meas[0], meas[1], L)
            Jtw = _fd(lambda ww: shaft.flexed_tip(ww, est["port"], L, est["load"]), pw)
            Jarm = _fd(arm.forward, q)
            q = q + k * np.linalg.solve(Jtw @ Jarm, e)
        out.append(np.array(errs))
    return out


@pytest.mark.slow
def test_certified_3d_flexion_segments_replay_monotonic(tmp_path):
    """A certified gain schedule of P2's flexion controller in 3-D (loads of 2.5-3.5 /m^2 in any
    direction normal to the shaft, the Liberty noise set) replays monotonic in an independent
    simulator under random load truths and random noise inside the set; the direct segment at the
    scenario's gain 1 (uncertified here: ||G|| > 1) is not what is replayed."""
    from errplan.gains import schedule_gains
    from errplan.gains.options import GainOptions
    from errplan.gains.physics import SpatialModel
    from errplan.kinematics import arm_for

    sc = load_scenario(spatial_flexion_scenario(tmp_path, unc="""
[uncertainty]
tip_force_over_ei = [2.5, 3.5]
sensor_noise = { position = 0.000746, angle = 0.0026 }
samples = 2
"""))
    model = SpatialModel(sc)
    opts = GainOptions.for_dim(3, verify_disk=20, verify_ring=12, opt_disk=10, opt_ring=8)
    path = np.array([[0.0, 0.0, 0.160 + 0.70 * L], [0.006, 0.003, 0.160 + 0.72 * L], [0.010, -0.002, 0.160 + 0.74 * L]])
    sched = schedule_gains(model, path, opts)
    assert sched.certified
    segs = sched.segments
    assert all(s.certified_G_norm < 1.0 for s in segs)
    arm = arm_for(sc.robot)
    port = np.array([0.0, 0.0, 0.160])
    rng = np.random.default_rng(5)
    for trial in range(6):
        # a random load truth of magnitude in the set, normal to the shaft at the start
        x0 = path[0]
        u = _unit(x0 - port)
        v = rng.normal(size=3)
        t_world = rng.uniform(2.5, 3.5) * _unit(v - (v @ u) * u)
        e1 = _unit(x0 - port)
        w0 = None
        # the wrist putting the tip at the start under that load: Newton on the forward model
        w0 = x0 - L * e1
        for _ in range(30):
            w0 = w0 - np.linalg.solve(_fd(lambda ww: shaft.flexed_tip(ww, port, L, t_world), w0),
                                      shaft.flexed_tip(w0, port, L, t_world) - x0)
        q0, ok = arm.inverse(w0[None])
        assert ok[0]
        errs = independent_replay(arm, L, port, t_world, q0[0], sched.waypoints, sched.gains, POS, ANG, rng)
        for seg_errs in errs:
            assert np.all(np.diff(seg_errs) <= 1e-12), (trial, seg_errs)
            assert seg_errs[-1] < 1e-6 or len(seg_errs) == 60


def test_simulation_runs_the_3d_flexion_controller_on_the_urdf_arm(tmp_path):
    """errplan.simulation with P2's controller in 3-D: noise-free, its Jhat is the flexed shaft's
    through the true port with the load's normal part, so at k = 1 it converges in a few steps; with the
    Liberty noise at the gain k = 0.75 (rho* < 1 there) the run still converges monotonically."""
    from errplan.simulation import ControllerModel, Plant, simulate

    sc = load_scenario(spatial_flexion_scenario(tmp_path))
    ctrl = ControllerModel.from_model(build_arm(sc))
    assert ctrl.jacobian == "flexion" and ctrl.dim == 3 and ctrl.noise == (POS, ANG)
    # a load normal to the shaft along z: (0, -3, 0); at the start the truth's J equals Jhat
    plant = Plant.from_model(build_arm(sc), load=3.0)
    start = np.array([0.0, 0.0, 0.160 + 0.70 * L])
    goal = np.array([0.008, -0.004, 0.160 + 0.73 * L])
    q0 = plant.configuration_for_tip(start)
    w, tip, dw, dt = plant.end_poses(q0)
    assert np.allclose(tip, start, atol=1e-12)
    Jh = ControllerModel(ctrl.arm, L, ctrl.port_estimate, "flexion").J_hat(q0, plant)
    port = np.array([0.0, 0.0, 0.160])
    u = _unit(port - w)
    t = np.array([0.0, -3.0, 0.0])
    t_perp = t - (t @ u) * u  # the estimate holds the load's normal part (the truth's axial part turns in)
    np.testing.assert_allclose(Jh, shaft.flexed_jacobian(w, port, L, t_perp) @ ctrl.arm.jacobian(q0), atol=1e-7)
    assert np.max(np.abs(Jh - plant.true_jacobian(q0))) > 1e-4
    quiet = ControllerModel(ctrl.arm, L, ctrl.port_estimate, "flexion")
    r = simulate(plant, quiet, q0, goal[None], [1.0], tolerance=1e-9)
    assert r.converged and r.steps <= 6
    r = simulate(plant, ctrl, q0, goal[None], [0.75], tolerance=1e-6, rng=np.random.default_rng(3))
    assert r.converged and r.monotonic


# ----------------------------------------------------------------------------- tolerance queries
def test_3d_insertion_band_in_plane_equals_planar():
    """The 3-D insertion band restricted to the plane x = 0 (in-plane load, in-plane noise) is P2's
    planar band to 1e-4 r/L, and its best worst case the planar one."""
    from errplan.tolerance import insertion_band, spatial_insertion_band

    b2 = insertion_band(L, 3.0, POS, ANG, extras=False)
    b3 = spatial_insertion_band(L, 3.0, POS, ANG, samples=25, in_plane=True)
    assert b3["lower_bound"] is True and b3["in_plane"] is True
    assert b2["band"] is not None and b3["band"] is not None
    assert np.allclose(b3["band"], b2["band"], atol=1e-4)
    assert b3["best_G_norm"] == pytest.approx(b2["best_G_norm"], rel=1e-6)


def test_3d_insertion_band_inside_the_planar_band():
    """P2's shaft and Liberty tracker with loads in every direction normal to the shaft: at k = 0.8
    the 3-D band is non-empty and inside the planar band (the 3-D noise set holds the planar one;
    a diagonal load sees the box's diagonal); at P2's k = 1 it is empty (the worst case over the 3-D
    set stays above 1 at every depth)."""
    from errplan.tolerance import insertion_band, spatial_insertion_band

    b2 = insertion_band(L, 3.0, POS, ANG, gain=0.8, extras=False)
    b3 = spatial_insertion_band(L, 3.0, POS, ANG, gain=0.8, samples=17)
    assert b3["band"] is not None
    assert b2["band"][0] < b3["band"][0] < b3["band"][1] < b2["band"][1]
    assert b3["band"][0] == pytest.approx(0.617, abs=2e-3) and b3["band"][1] == pytest.approx(0.832, abs=2e-3)
    # the 3-D worst case is never below the planar one near the band (far from it, near a degenerate
    # estimate, both searches find local maxima in the thousands)
    g2 = insertion_band(L, 3.0, POS, ANG, gain=0.8, samples=17, extras=False)["worst_G_norm"]["G_norm"]
    near = g2 < 2.0
    assert near.sum() >= 8
    assert np.all(b3["worst_G_norm"]["G_norm"][near] >= g2[near] * (1 - 1e-9))
    # P2's k = 1: above 1 at every depth of the planar band's neighbourhood (the bundled scenario's
    # full k = 1 band query, in the slow test below, finds none)
    from errplan.tolerance import SpatialInsertionModel

    g1 = SpatialInsertionModel(L, 3.0, 1.0).worst(np.linspace(0.5, 0.9, 9), POS, ANG)[0]
    assert np.all(g1 > 1.2)


def test_3d_tracker_noise_in_plane_equals_planar_and_full_set_needs_less():
    """tracker_noise in 3-D: restricted to the plane it is the planar answer (bisection tolerance);
    over the full 3-D set the tolerable noise is smaller."""
    from errplan.tolerance import spatial_tracker_noise, tracker_noise

    band = (0.66, 0.76)
    t2 = tracker_noise(L, 3.0, band, samples=3)
    t3p = spatial_tracker_noise(L, 3.0, band, samples=3, in_plane=True)
    t3 = spatial_tracker_noise(L, 3.0, band, samples=3)
    assert t3p["value"] == pytest.approx(t2["value"], rel=2e-3)
    assert t3["value"] < t3p["value"] and t3["lower_bound"]


@pytest.mark.slow
def test_bundled_spatial_flexion_scenario_tolerances(tmp_path):
    """scenarios/phantom15_flexion.toml through ``errplan tolerance``: no band at k = 1, the band
    0.617-0.832 at k = 0.8, each marked as a lower-bound search."""
    import json

    from errplan.cli import main

    out = tmp_path / "t.json"
    assert main(["-q", "tolerance", str(ROOT / "scenarios" / "phantom15_flexion.toml"), "--json", str(out)]) == 0
    t = {d["name"]: d for d in json.loads(out.read_text())["tolerances"]}
    assert t["liberty band 3-D, k = 1"]["band"] is None
    assert np.allclose(t["liberty band 3-D, k = 0.8"]["band"], [0.617, 0.832], atol=2e-3)
    assert all(d["lower_bound"] for d in t.values())
    assert 0.000746 < t["tracker for 0.65-0.80, 3-D"]["value"] < 0.001


@pytest.mark.slow
def test_experiment_and_calibrate_with_the_3d_flexion_controller(tmp_path):
    """``errplan experiment`` on a 3-D bench run by P2's flexion controller whose truth bends more
    than the declared shaft (a world load over EI on top of the declared one: the declared EI is
    wrong), then ``errplan calibrate`` against the declared scenario: the load is found as
    ``shaft_flexion`` with its three components, and the residual is explained."""
    import json

    from errplan.cli import main

    text = (ROOT / "scenarios" / "phantom15_flexion.toml").read_text(encoding="utf-8")
    text = text.replace('urdf = "phantom15.urdf"', f'urdf = "{ROOT / "scenarios" / "phantom15.urdf"}"')
    declared = tmp_path / "declared.toml"
    declared.write_text(text, encoding="utf-8")
    truth = tmp_path / "truth.toml"
    truth.write_text(text + "\n[effects.shaft_flexion]\nfx = 1.5\nfy = -1.0\nfz = 0.0\n", encoding="utf-8")
    data = tmp_path / "bench.csv"
    assert main(["-q", "experiment", str(truth), "--out", str(data), "--starts", "3", "--seed", "2"]) == 0
    out = tmp_path / "cal.json"
    # three folds of runs for the held-out errors (the default's five: tests/test_calibration.py's command line)
    assert main(["-q", "calibrate", str(declared), str(data), "--json", str(out), "--folds", "3", "--no-task"]) == 0
    rep = json.loads(out.read_text())
    assert rep["selected"] == ["shaft_flexion"] and rep["explained"] and rep["selection"]["folds"] == 3
    p = rep["parameters"]["shaft_flexion"]
    assert p["fx"] == pytest.approx(1.5, abs=0.05) and p["fy"] == pytest.approx(-1.0, abs=0.05)
    assert abs(p["fz"]) < 0.1
    assert rep["pose_rms_after"] < 0.2 * rep["pose_rms_before"]


def test_noise_refinement_reaches_a_dense_search(tmp_path):
    """The fields' refinement over the 3-D noise set (pattern search from the worst corner) is never
    below the corners and reaches the maximum of a dense grid over the set (chord box 7^3 x each
    tilt on 9 points of its disc) to 1e-6 relative, at loads in and off the tracker's axes."""
    import itertools

    sc = load_scenario(spatial_flexion_scenario(tmp_path))
    ev = SpatialFlexionEvaluator.from_model(build_arm(sc))
    k = 0.8
    x = np.array([[0.004, -0.003, 0.160 + 0.72 * L]])
    half = ev.noise_bounds()
    dvals = np.linspace(-half[0], half[0], 7)
    disc = [(0.0, 0.0)] + [(ANG * math.cos(a), ANG * math.sin(a)) for a in np.arange(8) * math.pi / 4]
    dense = np.array([(*d, *tw, *tt) for d in itertools.product(dvals, repeat=3) for tw in disc for tt in disc])
    for psi in (0.0, 0.6, math.pi / 4):
        th = np.array([[0.0, 0.0, 0.0, 3.0, psi]])
        Mc, _, ok = ev.parts(x, th)
        g_corners = g_norm(Mc, k).max()
        g_ref, _ = ev.refine_noise(x, th, k)
        Md, _, _ = ev.parts(x, th, dense)
        g_dense = g_norm(Md, k).max()
        assert g_ref[0] >= g_corners
        assert g_ref[0] >= g_dense * (1 - 1e-6)


def test_effects_path_runs_the_3d_flexion_controller(tmp_path):
    """A truth with [effects] that move the arm takes the general path (Newton on the full forward
    map, FD true Jacobian, the controller at the encoder angles); with effects of zero size it gives
    the flexion evaluator's maps (to the FD error), and noise-free its ||G|| is |1 - k| up to the
    load's axial part."""
    from dataclasses import replace as dc_replace

    from errplan.fields.evaluator import SpatialEffectsEvaluator

    sc = load_scenario(spatial_flexion_scenario(tmp_path))
    ev = SpatialEffectsEvaluator.from_model(build_arm(sc.with_(effects={"joint_offset": {"dq1": 0.0, "dq2": 0.0, "dq3": 0.0}})))
    fe = SpatialFlexionEvaluator.from_model(build_arm(sc))
    assert ev.jacobian == "flexion" and ev.noise.shape == fe.noise.shape
    x = np.array([[0.003, 0.002, 0.41], [0.0, -0.004, 0.40]])
    for psi in (0.0, 1.0):
        th = np.array([0.0, 0.0, 0.0, 3.0, psi])
        M1, _, ok1 = ev.parts(x, th)
        M2, _, ok2 = fe.parts(x, th)
        assert ok1.all() and ok2.all()
        np.testing.assert_allclose(M1, M2, atol=1e-8)
    ev.errors = dc_replace(ev.errors, noise=(0.0, 0.0))
    M0, _, _ = ev.parts(x, np.array([0.0, 0.0, 0.0, 3.0, 0.5]))
    assert np.allclose(g_norm(M0, 0.8), 0.2, atol=0.01)


def test_region_queries_take_the_3d_flexion_controller(tmp_path):
    """The port query's physics in 3-D runs P2's controller (worst over its noise corners, the
    sensor noise kept), tip_load stays the rigid lever's by definition, and a load range that
    reaches 0 is refused for the flexion controller (no flexion: nothing to identify)."""
    from errplan.errors import ErrplanError
    from errplan.tolerance import port_tolerance
    from errplan.tolerance.region import _SpatialPhysics

    sc = load_scenario(spatial_flexion_scenario(tmp_path))
    base = (0.002, -0.001, 0.161)
    phys = _SpatialPhysics(sc, base, "flexion")
    x = np.array([[0.003, 0.002, 0.41], [0.0, -0.004, 0.40]])
    th = np.array([[0.001, 0.0, -0.002, 3.0, 0.3], [0.0, 0.002, 0.0, 3.0, 2.0]])
    g, ok = phys.g(x, th, 0.8)
    fe = SpatialFlexionEvaluator.from_model(build_arm(sc))  # true port = estimate + offset: shift the offsets
    M, _, ok2 = fe.parts(x, th + np.array([*np.subtract(base, sc.port.estimate), 0.0, 0.0]))
    assert ok.all() and ok2.all()
    np.testing.assert_allclose(g, g_norm(M, 0.8).max(axis=1), rtol=1e-12)
    assert len(fe.noise) > 1 and phys.fev.errors.noise == (POS, ANG)
    assert _SpatialPhysics(sc, base).fev is None  # the rigid lever (tip_load)
    with pytest.raises(ErrplanError, match="flexion"):
        port_tolerance(sc, {"x": (0.0, 0.0), "y": (0.0, 0.0), "z": (0.41, 0.41)}, "x", tip_force_over_ei=[0.0, 3.0])
