"""Certified per-segment gains (errplan.gains): the casadi optimum against a brute-force scan, the
certificates against independent brute force, every bundled plan certified and replayed under every
corner of the error box with a controller loop written here (not errplan.simulation). 3-D: the
cutting-plane casadi optimum against an SVD scan, the cut rows, the kernels' motion maps against numpy,
the 3-D balls; the spatial certificates end to end are in tests/test_pipeline_spatial.py."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from errplan.errors import ErrplanError
from errplan.fields import Evaluator, compute_fields
from errplan.gains.certificate import _sample_segment
from errplan.gains import (GainOptions, ball_tips, cut_path, options_from_scenario, rho_of_k,
                           schedule_gains, single_segment, solve_gains, step_ratio)
from errplan.kinematics.arm import Arm
from errplan.kinematics.shaft import flexed_jacobian, flexed_tip, flexed_wrist, lever_jacobian
from errplan.api import load_scenario
from errplan.scenario import read_scenario
from errplan.models import build_arm

ROOT = Path(__file__).resolve().parents[1]
BOUNDED = ROOT / "scenarios" / "beasley2004_bounded.toml"
PORT = ROOT / "scenarios" / "beasley2004_port.toml"


def _scan_best(mu, nu, n=20001):
    """Brute force: the gain minimising max_i |1 - k mu_i| + k |nu_i| on a fine grid."""
    ku = 2.0 / np.abs(mu).max()
    k = np.linspace(ku / n, ku, n)
    vals = rho_of_k(mu, nu, k)
    j = int(np.argmin(vals))
    return float(k[j]), float(vals[j])


@pytest.mark.parametrize("scenario,a,b", [
    (PORT, (0.0, 0.415), (0.0, 0.396)),        # P1 Fig. 5 error, near N: rho* well above 0
    (PORT, (0.0, 0.339), (0.0, 0.320)),        # near L
    (BOUNDED, (-0.06, 0.40), (-0.04, 0.40)),   # bounded error set, 125 instances x tips
])
def test_casadi_gain_matches_brute_force_scan(scenario, a, b):
    sc = load_scenario(scenario)
    ev = Evaluator.from_model(build_arm(sc))
    opts = options_from_scenario(sc)
    R = float(np.hypot(*np.subtract(b, a))) + opts.switch_tolerance
    smp = _sample_segment(ev, np.array(a), np.array(b), R, opts)
    mu, nu = smp["mu"], smp["nu"]
    k_scan, rho_scan = _scan_best(mu, nu)
    # The full sample (no pruning) given to casadi; the problem's minimum is the smallest rho.
    prob = [{"mu": mu, "nu": nu, "d": R, "tol": opts.tolerance, "k0": 0.5 * k_scan, "rho0": rho_of_k(mu, nu, 0.5 * k_scan)[0]}]
    ks, info = solve_gains(prob, opts)
    assert info["success"], info
    rho_cas = float(rho_of_k(mu, nu, ks[0])[0])
    assert abs(ks[0] - k_scan) < 1e-3
    assert abs(rho_cas - rho_scan) < 1e-3
    assert rho_cas <= rho_scan + 1e-9  # casadi is at least as good as the grid


def test_pruned_joint_problem_matches_per_segment_scan():
    """The schedule's predicted ||G|| (its own sample, after pruning) equals the unpruned scan value at the
    chosen gain, and each gain is within the scan's sublevel set."""
    sc = load_scenario(PORT)
    gs = schedule_gains(sc, np.array([[0.0, 0.415], [0.0, 0.320]]))
    ev = Evaluator.from_model(build_arm(sc))
    for s in gs.segments:
        smp = _sample_segment(ev, s.start, s.end, s.radius, gs.options)
        assert abs(rho_of_k(smp["mu"], smp["nu"], s.gain)[0] - s.predicted_G_norm) < 1e-12
        assert s.predicted_G_norm <= 1 - gs.options.margin + 1e-6
    # bounded gain change between consecutive segments (no slack needed here)
    assert np.all(np.abs(np.diff(gs.gains)) <= gs.options.max_gain_change + 1e-6)
    assert gs.solver["gain_change_slack"] < 1e-6


def _brute_G(sc, x, theta, k):
    """||I - k J Jhat^-1|| with full 2x2 matrices and numpy's SVD (independent of conformal parts)."""
    es = build_arm(sc).errors
    L = sc.instrument.length
    port = es.port(theta)
    w = flexed_wrist(x, port, L, theta[..., 2])
    J = flexed_jacobian(w, port, L, theta[..., 2])
    Jh = lever_jacobian(w, np.asarray(sc.port.estimate), L)
    G = np.eye(2) - k * J @ np.linalg.inv(Jh)
    return np.linalg.norm(G, ord=2, axis=(-2, -1)), w


def test_certificate_bounds_random_brute_force():
    """Random tips in each certified ball and random instances of the error set (an independent sample):
    the SVD norm never exceeds the reported certified_G_norm (beyond 1e-3: sampling, not a bound)."""
    sc = load_scenario(BOUNDED)
    gs = schedule_gains(sc, np.array([[-0.1, 0.40], [0.0, 0.385], [0.1, 0.40]]))
    assert gs.certified
    arm = Arm.from_robot(sc.robot)
    es = build_arm(sc).errors
    rng = np.random.default_rng(7)
    worst_excess = -1.0
    for s in gs.segments:
        n = 4000
        r = s.radius * np.sqrt(rng.uniform(0, 1, n))
        a = rng.uniform(0, 2 * np.pi, n)
        x = s.end + np.stack([r * np.cos(a), r * np.sin(a)], -1)
        th = rng.uniform(es.lo_arr, es.hi_arr, (n, 3))
        g, w = _brute_G(sc, x, th, s.gain)
        port = es.port(th)
        reach = (np.linalg.norm(w - port, axis=-1) < sc.instrument.length) & arm.reachable(w)
        assert reach.mean() > 0.5
        worst_excess = max(worst_excess, float(np.max(g[reach]) - s.certified_G_norm))
        assert s.certified_G_norm < 1
    assert worst_excess < 1e-3


def test_nonlinear_step_ratio_matches_a_hand_step():
    """step_ratio against one step of the controller written out with matrices."""
    sc = load_scenario(PORT)
    ev = Evaluator.from_model(build_arm(sc))
    arm = Arm.from_robot(sc.robot)
    L = sc.instrument.length
    b = np.array([0.0, 0.40])
    x = np.array([[0.005, 0.41], [-0.01, 0.395]])
    th = np.zeros((2, 3))
    k = 0.6
    got = step_ratio(ev, b, x, th, k)
    port = np.asarray(sc.port.position)
    for i in range(2):
        w = x[i] - L * (x[i] - port) / np.linalg.norm(x[i] - port)
        q, ok = arm.inverse(w)
        Jh = lever_jacobian(arm.forward(q), np.asarray(sc.port.estimate), L) @ arm.jacobian(q)
        q2 = q + k * np.linalg.solve(Jh, b - x[i])
        w2 = arm.forward(q2)
        x2 = w2 + L * (port - w2) / np.linalg.norm(port - w2)
        assert got[i] == pytest.approx(np.linalg.norm(x2 - b) / np.linalg.norm(x[i] - b), rel=1e-9)


def test_verification_is_denser_than_the_optimiser():
    sc = load_scenario(BOUNDED)
    gs = schedule_gains(sc, np.array([[0.0, 0.415], [0.0, 0.375]]))
    for s in gs.segments:
        o, v = s.samples["optimiser"], s.samples["verification"]
        assert v["tips"] > 3 * o["tips"] and v["instances"] > 3 * o["instances"]
        # the refinement only raises the grid's worst case, and not by much (stable under refinement)
        assert v["grid_G_norm"] <= s.certified_G_norm + 1e-12
        assert s.certified_G_norm - v["grid_G_norm"] < 0.02


def test_long_segments_are_halved_until_certified():
    sc = load_scenario(PORT)
    opts = options_from_scenario(sc, max_segment=1.0)
    gs = schedule_gains(sc, np.array([[0.0, 0.415], [0.0, 0.320]]), opts)
    assert len(gs.segments) > 1 and max(s.depth for s in gs.segments) >= 1
    assert gs.certified
    ends = np.array([s.end for s in gs.segments])
    assert np.allclose(ends[-1], [0.0, 0.320]) and np.allclose(gs.segments[0].start, [0.0, 0.415])
    # contiguous, on the line
    for s0, s1 in zip(gs.segments[:-1], gs.segments[1:]):
        assert np.allclose(s0.end, s1.start)


def test_uncertified_segment_is_reported_as_such():
    """A single 200 mm segment across the bounded workspace: no gain certifies its ball; the output says so."""
    sc = load_scenario(BOUNDED)
    d = single_segment(sc, (-0.1, 0.40), (0.1, 0.40))
    s = d.segments[0]
    assert not s.certified and not d.certified
    assert s.reason
    assert not (s.certified_G_norm < 1 and s.step_ratio < 1)
    js = s.to_json()
    assert js["certified"] is False and "reason" in js
    assert d.predicted_steps() == math.inf


def test_cut_path_and_ball_sampling():
    pieces = cut_path(np.array([[0, 0], [0, 0.05], [0.01, 0.05]]), 0.02)
    assert len(pieces) == 3 + 1
    assert all(np.linalg.norm(b - a) <= 0.02 + 1e-12 for a, b, _ in pieces)
    x = ball_tips([0.0, 0.3], 0.01, 100, 20)
    d = np.linalg.norm(x - [0.0, 0.3], axis=-1)
    assert d.max() == pytest.approx(0.01) and d.min() == 0.0 and np.sum(np.isclose(d, 0.01)) >= 20


def test_bad_input():
    sc = load_scenario(PORT)
    with pytest.raises(ErrplanError, match="path"):
        schedule_gains(sc, np.array([[0.0, 0.4]]))
    with pytest.raises(ErrplanError, match="zero length"):
        schedule_gains(sc, np.array([[0.0, 0.4], [0.0, 0.4]]))
    with pytest.raises(ErrplanError, match="max_segment"):
        GainOptions(max_segment=0.0).validate()
    with pytest.raises(ErrplanError, match="margin"):
        GainOptions(margin=1.5).validate()


# ----------------------------------------------------------------------------- bundled plans
def _bundled_plans():
    from errplan import planning

    out = []
    for path in sorted((ROOT / "scenarios").glob("*.toml")):
        if "[[arm]]" in path.read_text():
            continue  # several arms (spatial): tests/test_setup.py
        data = read_scenario(path)  # plain data: a spatial scenario's robot is not built to be skipped
        if not data.queries or data.dim != 2:
            continue  # the spatial ones: tests/test_pipeline_spatial.py (coarser fields, 3-D replays)
        sc = load_scenario(path)
        for qp in planning.plan_scenario(sc, compute_fields(sc, rho_star=True)).queries:
            out.append((sc, qp.name, np.asarray(qp.planned.path, float)))
    return out


@pytest.fixture(scope="module")
def bundled():
    plans = _bundled_plans()
    return [(sc, name, path, schedule_gains(sc, path)) for sc, name, path in plans]


def _replay(sc, theta, start, waypoints, gains, tol_switch, tol_final, max_steps=5000):
    """An independent quasi-static controller loop (P1 eq. 1-5) for the rigid lever controller:
    the truth is the flexed shaft through port = estimate + (dy, dz) under tip load t."""
    arm = Arm.from_robot(sc.robot)
    es = build_arm(sc).errors
    L = sc.instrument.length
    port, t = es.port(theta), theta[2]
    q, ok = arm.inverse(flexed_wrist(np.asarray(start, float), port, L, t))
    assert ok
    x = flexed_tip(arm.forward(q), port, L, t)
    steps = 0
    for i, (b, k) in enumerate(zip(waypoints, gains)):
        tol = tol_final if i == len(waypoints) - 1 else tol_switch
        e_prev = np.linalg.norm(b - x)
        while np.linalg.norm(b - x) >= tol:
            w = arm.forward(q)
            Jh = lever_jacobian(w, np.asarray(sc.port.estimate), L) @ arm.jacobian(q)
            q = q + k * np.linalg.solve(Jh, b - x)
            assert arm.within_limits(q), "left the joint limits"
            x = flexed_tip(arm.forward(q), port, L, t)
            e = np.linalg.norm(b - x)
            if e > e_prev * (1 + 1e-9):
                return False, steps
            e_prev = e
            steps += 1
            if steps > max_steps:
                return False, steps
    return True, steps


def test_every_bundled_segment_certified(bundled):
    assert bundled
    for sc, name, path, gs in bundled:
        assert gs.certified, (sc.name, name, [s.reason for s in gs.segments if not s.certified])
        for s in gs.segments:
            assert s.certified_G_norm < 1 and s.step_ratio < 1
            js = s.to_json()
            assert set(js) >= {"from", "to", "gain", "certified_G_norm"} and js["certified"] is True
        # the segments cover the planned polyline from start to goal
        assert np.allclose(gs.segments[0].start, path[0]) and np.allclose(gs.segments[-1].end, path[-1])


def test_bundled_plans_converge_monotonically_under_every_corner(bundled):
    """Replay each rigid-controller plan with its gains under every corner of the port-error box (and tip
    load) with the loop above: every run converges, the distance to the active target never grows."""
    n = 0
    for sc, name, path, gs in bundled:
        if sc.controller.jacobian != "rigid":
            continue  # P2's flexion controller is replayed by tests/test_simulation.py (needs noise)
        es = build_arm(sc).errors
        for theta in es.corners():
            ok, steps = _replay(sc, theta, path[0], gs.waypoints, gs.gains, gs.options.switch_tolerance,
                                gs.options.tolerance)
            assert ok, (sc.name, name, theta.tolist(), steps)
            n += 1
    assert n >= 9  # 8 corners of the bounded box x its queries + the port scenario


# ----------------------------------------------------------------------------- 3-D
PHANTOM = ROOT / "scenarios" / "phantom15_spatial.toml"


def _svd_rho(M, k):
    """max_i ||I - k M_i||_2 by numpy's SVD (independent of the compiled closed form)."""
    k = np.atleast_1d(k)
    G = np.eye(3)[None, None] - k[:, None, None, None] * M[None]
    return np.linalg.norm(G, ord=2, axis=(-2, -1)).max(axis=1)


def test_spatial_ball_tips_cover_the_ball():
    from errplan.gains import sphere_points

    c = np.array([0.01, -0.02, 0.35])
    x = ball_tips(c, 0.02, 90, 40)
    d = np.linalg.norm(x - c, axis=-1)
    assert x.shape == (131, 3) and d.min() == 0.0 and d.max() == pytest.approx(0.02)
    assert np.sum(np.isclose(d, 0.02)) == 40
    # the volume points are spread evenly: mean radius of a uniform ball is 3/4 R
    assert d[1:91].mean() == pytest.approx(0.75 * 0.02, rel=0.03)
    u = sphere_points(400)
    assert np.allclose(np.linalg.norm(u, axis=-1), 1.0) and np.linalg.norm(u.mean(axis=0)) < 0.01


def test_cut_rows_are_exact_in_their_direction():
    """||(I - kM) v||^2 = (1 - k a)^2 + (k b)^2 with v the top right singular vector: the cut equals
    sigma_max at the gain it was taken at and never exceeds it elsewhere."""
    from errplan.gains import cut_rows, gnorm3_grid

    rng = np.random.default_rng(3)
    M = np.eye(3) + 0.4 * rng.normal(size=(50, 3, 3))
    for k in (0.3, 0.9, 1.4):
        rows = cut_rows(M, k)
        cut = np.sqrt((1 - k * rows[:, 0]) ** 2 + (k * rows[:, 1]) ** 2)
        exact = np.linalg.norm(np.eye(3) - k * M, ord=2, axis=(-2, -1))
        assert np.allclose(cut, exact, rtol=1e-10)
        assert np.allclose(gnorm3_grid(M, k)[0], exact, rtol=1e-10)
        for k2 in (0.1, 0.6, 2.0):
            assert np.all(np.sqrt((1 - k2 * rows[:, 0]) ** 2 + (k2 * rows[:, 1]) ** 2)
                          <= np.linalg.norm(np.eye(3) - k2 * M, ord=2, axis=(-2, -1)) + 1e-12)


@pytest.mark.parametrize("a,b", [((0.0, 0.0, 0.40), (0.0, 0.0, 0.38)),          # on the port axis, deep
                                 ((-0.06, 0.03, 0.36), (-0.045, 0.035, 0.37))])  # off axis
def test_spatial_casadi_gain_matches_svd_scan(a, b):
    """The cutting-plane casadi problem on a 3-D segment's pruned optimiser sample: the same gain and
    worst case over the WHOLE sample as a brute-force scan of numpy SVD norms (201 gains, then 2,001
    between the neighbours of the best)."""
    from errplan.gains import SpatialModel
    from errplan.gains.certificate import _k_upper_M, _scan_M
    from errplan.gains.solve import _initial_cuts, _solve_with_cuts

    sc = load_scenario(PHANTOM)
    ev = SpatialModel(sc)
    opts = options_from_scenario(sc)
    R = float(np.linalg.norm(np.subtract(b, a))) + opts.switch_tolerance
    smp = _sample_segment(ev, np.array(a), np.array(b), R, opts)
    M = smp["M"]
    assert smp["singular"] == 0 and len(M) > 500
    ku = _k_upper_M(M)
    kg = np.linspace(ku / 201, ku, 201)
    G = np.concatenate([np.linalg.norm(np.eye(3) - kk * M, ord=2, axis=(-2, -1))[None] for kk in kg])  # (201, p)
    j = int(np.argmin(G.max(axis=1)))
    lo, hi = kg[max(j - 1, 0)], kg[min(j + 1, 200)]
    # the fine scan between the neighbours of the coarse minimum, on the pairs near the top there
    near = np.unique(np.argsort(-G[[max(j - 1, 0), j, min(j + 1, 200)]], axis=1)[:, :40])
    kf = np.linspace(lo, hi, 2001)
    vals = _svd_rho(M[near], kf)
    i = int(np.argmin(vals))
    k_scan, rho_scan = kf[i], float(_svd_rho(M, kf[i])[0])
    # the schedule's own pruning (top pairs on the compiled k-grid), started away from the optimum
    idx = _scan_M(M)[3]
    assert len(idx) < len(M) / 5
    Mp = M[idx]
    prob = [{"rows": _initial_cuts(Mp, 0.5 * k_scan, ku), "ku": ku, "d": R, "tol": opts.tolerance,
             "k0": 0.5 * k_scan, "rho0": float(_svd_rho(M, 0.5 * k_scan)[0])}]
    ks, info = _solve_with_cuts(prob, [Mp], opts, [False])
    assert info["success"], info
    rho_cas = float(_svd_rho(M, ks[0])[0])
    assert abs(ks[0] - k_scan) < 2e-3 and abs(rho_cas - rho_scan) < 1e-5
    assert rho_cas <= rho_scan + 1e-9
    assert info["cut_rounds"] >= 1


def test_spatial_motion_maps_match_numpy_physics():
    """The compiled kernels' M = J Jhat^-1 at (tip, instance) pairs against the numpy shaft model at the
    wrist and load SpatialModel.wrists derives (central differences of flexed_tip for J)."""
    from errplan.gains import SpatialModel
    from errplan.kinematics.shaft import flexed_tip as ftip

    sc = load_scenario(PHANTOM)
    ev = SpatialModel(sc)
    rng = np.random.default_rng(11)
    x = np.array([0.0, 0.0, 0.36]) + rng.uniform(-0.05, 0.05, (40, 3))
    th = ev.instances(3)[rng.integers(0, len(ev.instances(3)), 40)]
    M, ok = ev.maps_paired(x, th)
    p, w, t, reach = ev.wrists(x, th)
    assert np.array_equal(ok, reach) and ok.mean() > 0.8
    L = ev.length
    assert np.allclose(ftip(w, p, L, t)[ok], x[ok], atol=1e-12)
    h = 1e-6
    for i in np.flatnonzero(ok):
        J = np.stack([(ftip(w[i] + h * e, p[i], L, t[i]) - ftip(w[i] - h * e, p[i], L, t[i])) / (2 * h)
                      for e in np.eye(3)], axis=-1)
        d = ev.estimate - w[i]
        r = np.linalg.norm(d)
        Jh = np.eye(3) - (L / r) * (np.eye(3) - np.outer(d, d) / r ** 2)
        assert np.allclose(M[i], J @ np.linalg.inv(Jh), atol=2e-7)


def test_spatial_step_ratio_matches_a_hand_step():
    """SpatialModel.step_ratio against one controller step written with pinocchio (FK and frame Jacobian
    of the wrist) and the straight shaft."""
    import pinocchio as pin
    from errplan.gains import SpatialModel

    sc = load_scenario(PHANTOM)
    ev = SpatialModel(sc)
    arm = ev.arm
    model = pin.buildModelFromUrdf(str(arm.urdf_path))
    data = model.createData()
    fid = model.getFrameId(sc.robot.wrist)
    L = ev.length
    b = np.array([0.01, 0.0, 0.37])
    x = np.array([[0.02, 0.01, 0.38], [-0.005, -0.01, 0.36]])
    th = np.array([[0.005, -0.005, 0.005, 0.0, 0.0], [-0.005, 0.0, 0.005, 0.0, 0.0]])
    k = 0.8
    got = ev.step_ratio(b, x, th, k)
    R = np.eye(3)  # base_rpy = 0 for the bundled PHANToM
    base = np.asarray(sc.robot.base_position)

    def fk(q):
        pin.framesForwardKinematics(model, data, q)
        return base + R @ data.oMf[fid].translation

    def jac(q):
        pin.computeJointJacobians(model, data, q)
        pin.framesForwardKinematics(model, data, q)
        return R @ pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)[:3, :3]

    for i in range(2):
        port = np.asarray(sc.port.estimate) + th[i, :3]
        w = x[i] - L * (x[i] - port) / np.linalg.norm(x[i] - port)
        q, ok = arm.inverse(w)
        assert ok and np.allclose(fk(q), w, atol=1e-9)
        d = np.asarray(sc.port.estimate) - w
        r = np.linalg.norm(d)
        Jh = (np.eye(3) - (L / r) * (np.eye(3) - np.outer(d, d) / r ** 2)) @ jac(q)
        q2 = q + k * np.linalg.solve(Jh, b - x[i])
        w2 = fk(q2)
        x2 = w2 + L * (port - w2) / np.linalg.norm(port - w2)
        assert got[i] == pytest.approx(np.linalg.norm(x2 - b) / np.linalg.norm(x[i] - b), rel=1e-8)


def test_spatial_singular_free_balls():
    """Near the port the controller's lever can be singular: such balls are refused (never certified)."""
    from errplan.gains import SpatialModel

    sc = load_scenario(PHANTOM)
    ev = SpatialModel(sc)
    est = np.asarray(sc.port.estimate)
    assert ev.singular_free(est + [0, 0, 0.2], 0.02)
    assert not ev.singular_free(est + [0, 0, 0.02], 0.005)
    gs = single_segment(ev, est + [0.0, 0.0, 0.03], est + [0.0, 0.0, 0.02])
    s = gs.segments[0]
    assert not s.certified and "singular" in s.reason


def test_spatial_bad_path_shape():
    from errplan.gains import SpatialModel

    ev = SpatialModel(load_scenario(PHANTOM))
    with pytest.raises(ErrplanError, match=r"\(m >= 2, 3\)"):
        schedule_gains(ev, np.array([[0.0, 0.35], [0.01, 0.36]]))


def test_gnorm3_pairs_match_numpy_svd_and_the_grid():
    """Per-pair gains: ||I - k_i M_i|| against numpy's SVD norm, and bit for bit the grid kernel's value
    at the same gain (the verification batches pairs of segments with different gains)."""
    from errplan.gains import gnorm3_grid
    from errplan.gains.physics import gnorm3_pairs

    rng = np.random.default_rng(5)
    M = np.eye(3) + 0.5 * rng.normal(size=(40, 3, 3))
    k = rng.uniform(0.1, 1.5, 40)
    exact = np.linalg.norm(np.eye(3) - k[:, None, None] * M, ord=2, axis=(-2, -1))
    g = gnorm3_pairs(M, k)
    assert np.allclose(g, exact, rtol=1e-10)
    assert np.array_equal(g, np.array([gnorm3_grid(M[i:i + 1], k[i])[0, 0] for i in range(40)]))
    M[3, 1, 2] = np.nan
    assert np.isnan(gnorm3_pairs(M, k)[3]) and np.isfinite(np.delete(gnorm3_pairs(M, k), 3)).all()


@pytest.mark.parametrize("spatial", [False, True])
def test_verification_of_a_round_equals_one_segment_at_a_time(spatial):
    """verify_segments (all segments' pairs through the kernels together, each with its own gain) gives
    exactly the dicts of verify_segment called on each segment alone."""
    from errplan.gains.schedule import _as_evaluator
    from errplan.gains.verify import verify_segment, verify_segments

    sc = load_scenario(PHANTOM if spatial else BOUNDED)
    ev = _as_evaluator(sc)
    opts = options_from_scenario(sc)
    if spatial:
        opts = GainOptions(**{**opts.__dict__, "verify_disk": 30, "verify_ring": 12, "verify_refine": 2}).validate()
        path = np.array([[-0.06, 0.03, 0.36], [0.02, -0.01, 0.40]])
    else:
        path = np.array([[-0.06, 0.40], [0.0, 0.37]])
    pieces = cut_path(path, opts.max_segment)[:3]
    segs = [(a, b, 0.5 + 0.2 * i, float(np.linalg.norm(b - a)) + opts.switch_tolerance)
            for i, (a, b, _) in enumerate(pieces)]
    assert len(segs) == 3
    batch = verify_segments(ev, segs, opts)
    alone = [verify_segment(ev, *s, opts) for s in segs]
    assert json.dumps(batch) == json.dumps(alone)  # exact floats (repr), NaN included
    assert len({v["G_norm"] for v in batch}) == 3  # three different segments and gains
