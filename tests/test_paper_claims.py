"""The papers' claims, each as an assertion that could fail. Where errplan differs from a paper the
assertion states by how much (docs/papers.md says why).

P1 = Beasley, Howe, Dupont, ICRA 2004 (scenarios/beasley2004_port.toml: port (0, 160) mm, estimate
(20, 170) mm, k = 1). P2 = Beasley & Howe, flexible instruments (L = 0.355 m, Ft/EI = 3 /m^2).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from conftest import SCENARIOS
from errplan.fields import Evaluator, compute_fields, worst_case
from errplan.kinematics.shaft import flexed_jacobian, flexed_tip, flexed_wrist, lever_jacobian, lever_tip, lever_wrist
from errplan.metrics import g_norm, motion_map, phi_max, phi_of_direction
from errplan.api import load_scenario
from errplan.models import build_arm

DEG = np.pi / 180
L_P, M_P, N_P = (0.0, 0.320), (0.0, 0.375), (0.0, 0.415)


@pytest.fixture(scope="module")
def p1():
    return load_scenario(SCENARIOS / "beasley2004_port.toml")


@pytest.fixture(scope="module")
def fig5(p1):
    return compute_fields(p1, 0.002)


# ----------------------------------------------------------------------------- P1 Fig. 5
def test_fig5a_g_norm_above_one_over_a_large_part_below_half_in_the_middle(fig5):
    """'||G|| >= 1 for a large portion of the workspace ... ||G|| <= 0.5 in the middle'.
    errplan: ||G|| >= 1 on 28.5 % of the tip workspace (2 mm grid); every tip within 40 mm of the
    workspace centroid has ||G|| <= 0.467; the median over the workspace is 0.49."""
    v = fig5.valid
    G = fig5.G_norm[v]
    share_ge_1 = np.mean(G >= 1)
    assert 0.2 < share_ge_1 < 0.4
    assert share_ge_1 == pytest.approx(0.285, abs=0.01)
    pts = fig5.points()[v]
    centre = pts.mean(axis=0)
    middle = np.linalg.norm(pts - centre, axis=-1) < 0.04
    assert middle.sum() > 1000
    assert np.max(G[middle]) <= 0.5
    assert np.median(G) < 0.5


def test_fig5_phi_hat_max_bounds_phi_max_where_contracting(fig5):
    """'phi_hat_max is a conservative estimate of |phi_max|' (where ||G|| <= 1, eq. 10 is a bound)."""
    v = fig5.valid & (fig5.G_norm <= 1)
    assert v.sum() > 10000
    assert np.all(fig5.phi_hat_max[v] >= fig5.phi_max[v] - 1e-12)
    # and it is not vacuous: somewhere the bound is tight within 1 degree
    assert np.min(fig5.phi_hat_max[v] - fig5.phi_max[v]) < 1 * DEG


def test_fig5_phi_hat_over_135_roughly_where_phi_over_45(fig5):
    """'the contour beyond which phi_hat_max > 135 deg approximately corresponds to where
    |phi_max| > 45 deg'. errplan: of the tips with phi_hat_max > 135 deg, 99.9 % have
    |phi_max| > 45 deg; the converse is weaker: of the tips with |phi_max| > 45 deg, 64 % have
    phi_hat_max > 135 deg (the rest lie between the two contours, ||G|| in [1, 1.41])."""
    v = fig5.valid
    hi_hat = v & (fig5.phi_hat_max > 135 * DEG)
    hi_phi = v & (fig5.phi_max > 45 * DEG)
    share = np.mean(fig5.phi_max[hi_hat] > 45 * DEG)
    converse = np.mean(fig5.phi_hat_max[hi_phi] > 135 * DEG)
    assert hi_hat.sum() > 1000
    assert share > 0.99
    assert converse == pytest.approx(0.64, abs=0.03)


def test_experiment_points_L_M_N_lie_in_areas_of_increasing_error(fig5):
    """'(0, 320), (0, 375), (0, 415) ... chosen to lie in areas of increasing error'.
    errplan: ||G|| = 0.33, 0.56, 1.29 and |phi_max| = 17.4, 29.7, 64.8 deg."""
    pts = np.array([L_P, M_P, N_P])
    G = fig5.sample("G_norm", pts)
    P = fig5.sample("phi_max", pts)
    H = fig5.sample("phi_hat_max", pts)
    assert np.all(np.isfinite(G))
    assert G[0] < G[1] < G[2] and P[0] < P[1] < P[2] and H[0] < H[1] < H[2]
    assert G[2] > 1 > G[1]  # N, near the workspace edge, is where monotonic convergence is lost
    assert G == pytest.approx([0.33, 0.56, 1.29], abs=0.01)
    assert P / DEG == pytest.approx([17.4, 29.7, 64.8], abs=0.3)


def test_phi_max_does_not_depend_on_gain_but_g_norm_does(p1):
    """'This plot (|phi_max|) is unaffected by changes in the controller's gain'; ||G|| tends to 1 as
    k -> 0 and grows proportionally as k grows."""
    ev = Evaluator.from_model(build_arm(p1))
    x = np.array([L_P, M_P, N_P, (-0.1, 0.3), (0.05, 0.25)])
    w1 = worst_case(ev, x, 1.0)
    for k in (0.01, 0.5, 4.0):
        wk = worst_case(ev, x, k)
        assert np.allclose(wk["phi_max"], w1["phi_max"], atol=1e-12)
    assert np.allclose(worst_case(ev, x, 1e-4)["G_norm"], 1.0, atol=1e-3)
    g8, g16 = worst_case(ev, x, 8.0)["G_norm"], worst_case(ev, x, 16.0)["G_norm"]
    assert np.allclose(g16 / g8, 2.0, rtol=0.1)


# ----------------------------------------------------------------------------- P1 Fig. 7
FIG7 = {"+z": (0.0, 0.01), "-z": (0.0, -0.01), "+y": (0.01, 0.0), "-y": (-0.01, 0.0)}


def _with_estimate(sc, off):
    return sc.with_(port=replace(sc.port, estimate=tuple(np.add(sc.port.position, off))))


@pytest.mark.parametrize("name", sorted(FIG7))
def test_fig7_tips_on_the_line_of_the_port_error(p1, name):
    """'positions along the line of port error do not have errors in motion'. errplan: on the line
    through the true and the estimated port, J and Jhat share their eigenvectors (along and across
    the line), so motions along and across the line are exact (phi = 0) and |phi_max| is smallest
    there in every cross-section of the line; it is not zero (3.6 - 9 deg 100 - 280 mm from the
    port, the two directions are scaled differently) while 40 mm off the line it is 5 - 32 deg."""
    sc = _with_estimate(p1, FIG7[name])
    p = np.asarray(sc.port.position)
    u = np.asarray(FIG7[name]) / 0.01
    n = np.array([u[1], -u[0]])
    ev = Evaluator.from_model(build_arm(sc))
    checked = 0
    for s in np.arange(-0.30, 0.301, 0.02):
        d = np.linspace(-0.04, 0.04, 81)
        x = p + s * u + d[:, None] * n
        wc = worst_case(ev, x, 1.0)
        ok = wc["valid"]
        if not ok[40] or ok.sum() < 60 or abs(s) < 0.1:  # the line in the workspace, off the port
            continue
        checked += 1
        ph = wc["phi_max"]
        assert np.nanargmin(ph) == 40, s              # the minimum across the line is on it
        assert ph[40] < 10 * DEG and ph[40] < 0.75 * np.nanmax(ph)
        # exact motions along and across the line at the on-line tip
        w = lever_wrist(x[40], p, sc.instrument.length)
        M, _ = motion_map(lever_jacobian(w, p, sc.instrument.length),
                          lever_jacobian(w, np.asarray(sc.port.estimate), sc.instrument.length))
        assert abs(phi_of_direction(M, u)) < 1e-9 and abs(phi_of_direction(M, n)) < 1e-9
    assert checked >= 4


def test_fig7_y_port_error_hurts_more_than_z_along_y0(p1):
    """'if positions along y = 0 are the most important ... errors in the y position of the port are
    less tolerable than errors in the z position'. Tips on y = 0, z in [0.30, 0.42] m (L to beyond
    N), 10 mm errors: worst ||G|| 0.88 (y errors) vs 0.21 (z errors), worst |phi_max| 48.6 vs 6.3 deg."""
    x = np.stack([np.zeros(61), np.linspace(0.30, 0.42, 61)], -1)
    worst = {}
    for name, off in FIG7.items():
        wc = worst_case(Evaluator.from_model(build_arm(_with_estimate(p1, off))), x, 1.0)
        assert wc["valid"].all()
        worst[name] = (wc["G_norm"].max(), wc["phi_max"].max())
    gy = max(worst["+y"][0], worst["-y"][0])
    gz = max(worst["+z"][0], worst["-z"][0])
    py = max(worst["+y"][1], worst["-y"][1])
    pz = max(worst["+z"][1], worst["-z"][1])
    assert gy > 3 * gz and py > 5 * pz
    assert gy == pytest.approx(0.877, abs=0.01) and gz == pytest.approx(0.213, abs=0.01)
    assert py / DEG == pytest.approx(48.6, abs=0.5) and pz / DEG == pytest.approx(6.3, abs=0.3)


# ----------------------------------------------------------------------------- P2
ZEUS_L = 0.355
ZEUS_EI = 200e9 * np.pi * (3.35e-3 ** 4 - 1.47e-3 ** 4) / 64   # steel, OD 3.35 mm, ID 1.47 mm


def test_p2_zeus_shaft_deflects_about_15_mm_under_1_newton():
    """'a 1 N force applied to the tip of a cantilevered instrument ... causes a 15 mm tip
    deflection'. errplan's beam with the port at the wrist (a -> 0, the cantilever) under
    Ft/EI = 1 N / EI deflects the tip 12.5 mm from the straight shaft (E = 200 GPa: EI = 1.19 N m^2),
    the textbook F L^3 / (3 EI) = 12.53 mm: 16.5 % below P2's 15 mm (within 20 %)."""
    cantilever = 1.0 * ZEUS_L**3 / (3 * ZEUS_EI)
    assert cantilever == pytest.approx(0.01253, abs=1e-4)
    port = np.array([0.0, 0.0])
    w = port - np.array([0.0, 1e-4])           # the port 0.1 mm from the wrist
    t = 1.0 / ZEUS_EI
    deflection = np.linalg.norm(flexed_tip(w, port, ZEUS_L, t) - lever_tip(w, port, ZEUS_L))
    assert deflection == pytest.approx(cantilever, rel=2e-3)
    assert abs(deflection - 0.015) / 0.015 < 0.20
    assert (deflection - 0.015) / 0.015 == pytest.approx(-0.166, abs=0.01)


def test_p2_rigid_lever_motion_error_grows_with_insertion_depth():
    """'the motion error for the rigid instrument Jacobian is proportional to the insertion depth'
    (J = flexed truth, Jhat = the lever through the true port, k = 1, L = 0.355 m, Ft/EI = 3).
    errplan: ||G|| = 0.252 r/L within 1.8 % for r/L in [0.05, 0.95] (about (2/3) (Ft/EI) L r), and
    the Zeus tip-position error (Fig. 6) grows from 0.1 mm to 40 mm."""
    t = 3.0
    p = np.array([0.0, 0.16])
    rl = np.linspace(0.05, 0.95, 19)
    for ang in (0.0, 0.5, -1.0):
        x = p + (rl * ZEUS_L)[:, None] * np.array([np.sin(ang), np.cos(ang)])
        w = flexed_wrist(x, p, ZEUS_L, t)
        M, sing = motion_map(flexed_jacobian(w, p, ZEUS_L, t), lever_jacobian(w, p, ZEUS_L))
        assert not sing.any()
        G = g_norm(M, 1.0)
        assert np.all(np.diff(G) > 0) and np.all(np.diff(phi_max(M)) > 0)
        slope = G / rl
        assert np.allclose(slope, 0.252, rtol=0.02)
        assert np.allclose(slope, 2 / 3 * t * ZEUS_L**2, rtol=0.02)
        tip_err = np.linalg.norm(lever_tip(w, p, ZEUS_L) - x, axis=-1)
        assert np.all(np.diff(tip_err) > 0)
        assert tip_err[0] < 0.0002 and 0.035 < tip_err[-1] < 0.045
    # without load the lever is exact
    w0 = flexed_wrist(x, p, ZEUS_L, 0.0)
    M0, _ = motion_map(flexed_jacobian(w0, p, ZEUS_L, 0.0), lever_jacobian(w0, p, ZEUS_L))
    assert np.allclose(g_norm(M0, 1.0), 0.0, atol=1e-12)
