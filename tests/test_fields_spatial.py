"""Spatial worst-case fields against an independent implementation of docs/physics.md "Spatial robots".

The reference here shares no code with the compiled kernels: the true wrist from the port->tip line
(and, under a load, kinematics.shaft.flexed_wrist_plane), reachability by direct inverse kinematics,
the true Jacobian by central differences of the numpy shaft model, the controller's lever Jacobian
written out, ``np.linalg.svd`` for ||G||, a dense search over the sphere for |phi_max|, a dense grid
over the error box followed by Nelder-Mead for the worst case.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import minimize

from errplan.fields import compute_fields
from errplan.kinematics import arm_for
from errplan.kinematics.shaft import flexed_tip, flexed_wrist_plane
from errplan.api import load_scenario

from arms import OMNI, SHARED_ROBOTS, arm_scenario, needs_omni
from errplan.models import build_arm

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = ROOT / "scenarios" / "phantom15_spatial.toml"
PLANAR = ROOT / "scenarios" / "beasley2004_port.toml"


def omni_scenario(tmp_path: Path, extra: str = "", uncertainty: str | None = None) -> Path:
    """The Omni description (arms.OMNI) as a user would describe it (interfaces.md's example); only where that
    folder exists (:data:`arms.needs_omni`)."""
    unc = uncertainty if uncertainty is not None else """
[uncertainty]
port_x = [-0.006, 0.004]
port_y = [-0.005, 0.005]
port_z = [-0.004, 0.006]
samples = 3
"""
    text = f"""
name = "omni"
[robot]
urdf = "{OMNI}"
package_path = ["{SHARED_ROBOTS}"]
joints = ["waist", "shoulder", "elbow"]
wrist = "tip"
base_position = [0.0, 0.0, 0.0]
base_rpy = [1.5707963267948966, 0.0, 3.141592653589793]

[instrument]
length = 0.25

[port]
position = [0.004, 0.052, 0.218]
estimate = [0.0, 0.050, 0.220]

[controller]
gain = 1.0
{unc}
[fields]
resolution = 0.01
region = {{ x = [-0.06, 0.06], y = [-0.06, 0.12], z = [0.30, 0.42] }}
{extra}
"""
    p = tmp_path / "omni.toml"
    p.write_text(text, encoding="utf-8")
    return p


# ----------------------------------------------------------------------------- the reference
def _perp(e1):
    ref = np.eye(3)[np.argmin(np.abs(e1))]
    f1 = np.cross(e1, ref)
    f1 /= np.linalg.norm(f1)
    return f1, np.cross(e1, f1)


def reference_M(sc, x, theta):
    """``M = J Jhat^-1`` of one instance ``theta = (dx, dy, dz, tau, psi)`` at tip ``x``, or None."""
    arm = arm_for(sc.robot)
    L = sc.instrument.length
    est = np.asarray(sc.port.estimate, float)
    p = est + np.asarray(theta[:3]) if sc.uncertainty.declared else np.asarray(sc.port.position, float)
    e = x - p
    r = np.linalg.norm(e)
    if not 1e-9 < r < L:
        return None
    tau = theta[3]
    if tau == 0:
        w, t = x - L * e / r, np.zeros(3)
    else:
        f1, f2 = _perp(e / r)
        w, t = flexed_wrist_plane(x, p, L, tau, math.cos(theta[4]) * f1 + math.sin(theta[4]) * f2)
    q, ok = arm.inverse(w[None])
    if not ok[0]:
        return None
    h = 1e-6
    J = np.stack([(flexed_tip(w + h * c, p, L, t) - flexed_tip(w - h * c, p, L, t)) / (2 * h) for c in np.eye(3)], -1)
    d = est - w
    rho = np.linalg.norm(d)
    u = d / rho
    Jh = np.eye(3) - (L / rho) * (np.eye(3) - np.outer(u, u))
    return J @ np.linalg.inv(Jh)


def g_of(M, k):
    return np.linalg.svd(np.eye(3) - k * M, compute_uv=False)[0]


_SPHERE = None


def phi_of(M):
    """max over unit v of angle(v, M v): dense Fibonacci sphere then a local polish."""
    global _SPHERE
    if _SPHERE is None:
        n = 20000
        i = np.arange(n) + 0.5
        th = np.arccos(1 - 2 * i / n)
        ph = math.pi * (1 + 5**0.5) * i
        _SPHERE = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    V = _SPHERE
    MV = V @ M.T
    ang = np.arccos(np.clip(np.sum(V * MV, -1) / np.linalg.norm(MV, axis=-1), -1, 1))
    v0 = V[np.argmax(ang)]

    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = np.asarray(M, float).tolist()

    def neg(a):  # the angle between v and M v in plain floats (the polish calls it ~100 times per M)
        s0, s1 = math.sin(a[0]), math.sin(a[1])
        v0, v1, v2 = s0 * math.cos(a[1]), s0 * s1, math.cos(a[0])
        w0, w1, w2 = m00 * v0 + m01 * v1 + m02 * v2, m10 * v0 + m11 * v1 + m12 * v2, m20 * v0 + m21 * v1 + m22 * v2
        n = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        if n == 0.0:
            return math.nan
        return -math.acos(min(1.0, max(-1.0, (v0 * w0 + v1 * w1 + v2 * w2) / n)))

    a0 = [math.acos(np.clip(v0[2], -1, 1)), math.atan2(v0[1], v0[0])]
    return max(float(ang.max()), -minimize(neg, a0, method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-12}).fun)


def reference_worst(sc, x, n=5, n_dir=12, phi=False):
    """Worst ||G|| (and |phi_max|) at tip x over the scenario's error set: dense grid + Nelder-Mead."""
    u = sc.uncertainty
    k = sc.controller.gain
    boxes = [u.port_x or (0, 0), u.port_y or (0, 0), u.port_z or (0, 0)]
    tl = u.tip_force_over_ei or (0.0, 0.0)
    axes = [np.linspace(lo, hi, n) if hi > lo else np.array([lo]) for lo, hi in boxes]
    taus = np.linspace(tl[0], tl[1], 3) if tl[1] > tl[0] else np.array([tl[0]])
    dirs = np.arange(n_dir) * 2 * math.pi / n_dir if tl[1] > 0 else np.array([0.0])
    best_g, best_th, best_p = -np.inf, None, -np.inf
    for dx in axes[0]:
        for dy in axes[1]:
            for dz in axes[2]:
                for tau in taus:
                    for psi in (dirs if tau > 0 else [0.0]):
                        th = (dx, dy, dz, tau, psi)
                        M = reference_M(sc, x, th)
                        if M is None:
                            return None
                        g = g_of(M, k)
                        if g > best_g:
                            best_g, best_th = g, th
                        if phi:
                            best_p = max(best_p, phi_of(M))
    lo = np.array([b[0] for b in boxes] + [tl[0]])
    hi = np.array([b[1] for b in boxes] + [tl[1]])

    def neg(z):
        th = np.clip(z[:4], lo, hi)
        M = reference_M(sc, x, (*th, z[4] if len(z) > 4 else 0.0))
        return 0.0 if M is None else -g_of(M, k)

    z0 = np.array(best_th if tl[1] > 0 else best_th[:4])
    res = minimize(neg, z0, method="Nelder-Mead", options={"xatol": 1e-9, "fatol": 1e-12, "maxiter": 2000})
    return max(best_g, -res.fun), best_p


# ----------------------------------------------------------------------------- tests
@pytest.fixture(scope="module")
def phantom():
    return load_scenario(PHANTOM)


def test_phantom_is_spatial(phantom):
    assert phantom.dim == 3
    assert phantom.axes == ("x", "y", "z")


def _sample_tips(mf, n, rng):
    v = np.argwhere(mf.valid)
    pick = v[rng.choice(len(v), min(n, len(v)), replace=False)]
    return pick, np.stack([mf.x[pick[:, 0]], mf.y[pick[:, 1]], mf.z[pick[:, 2]]], -1)


@pytest.mark.slow
def test_spatial_worst_case_matches_independent_reference(phantom):
    """||G|| never below the reference worst case by more than 1e-3 and within 1e-3 of it."""
    sc = phantom
    mf = compute_fields(sc, 0.02, metrics=("G_norm",))
    assert mf.dim == 3 and mf.valid.any()
    rng = np.random.default_rng(3)
    idx, X = _sample_tips(mf, 12, rng)
    for (i, j, l), x in zip(idx, X):
        ref = reference_worst(sc, x, n=3, n_dir=8)
        assert ref is not None, f"tip {x} valid in errplan but not in the reference"
        g = mf.G_norm[i, j, l]
        assert g >= ref[0] - 1e-3 * max(1, ref[0]), (x, g, ref[0])
        assert g <= ref[0] + 1e-3 * max(1, ref[0]), (x, g, ref[0])


@needs_omni
def test_omni_fields_match_reference_with_phi(tmp_path):
    """The Omni description (arms.OMNI), as it is: ||G|| and |phi_max| against the reference."""
    sc = load_scenario(omni_scenario(tmp_path))
    mf = compute_fields(sc, 0.02)
    assert mf.valid.any()
    rng = np.random.default_rng(5)
    idx, X = _sample_tips(mf, 8, rng)
    for (i, j, l), x in zip(idx, X):
        ref = reference_worst(sc, x, n=3, phi=True)
        assert ref is not None
        g, p = mf.G_norm[i, j, l], mf.phi_max[i, j, l]
        assert abs(g - ref[0]) <= 1e-3 * max(1, ref[0]), (x, g, ref[0])
        # the reference's phi is a maximum over its sample grid only: errplan, refined, is never below it
        assert p >= ref[1] - 3e-3, (x, p, ref[1])
        assert p <= ref[1] + 0.05, (x, p, ref[1])


def _unseen_arm(tmp_path, which):
    """The arm model and a scenario writer ``write(port, estimate, body)`` for an arm errplan ships nothing
    for: the toy URDF of tests/test_urdf.py, or a real arm of example-robot-data (tests/arms.py)."""
    if which == "toy":
        from errplan.kinematics.urdf import UrdfArm
        from test_urdf import TOY_BASE, TOY_ROLL, TOY_RPY, toy_scenario, toy_text

        urdf = tmp_path / "toy.urdf"
        urdf.write_text(toy_text(), encoding="utf-8")
        arm = UrdfArm.load(urdf, ["j1", "j2", "j3"], "tool", base_position=TOY_BASE, base_rpy=TOY_RPY,
                           fixed_joints={"roll": TOY_ROLL})
        return arm, 0.25, lambda port, est, body: toy_scenario(tmp_path, port, est, body)
    from errplan.scenario import read_scenario

    # the data only (no reach check): the port is chosen from the arm's wrist cloud below
    arm = arm_for(read_scenario(arm_scenario(tmp_path, which, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])).robot)
    return arm, 0.35, lambda port, est, body: arm_scenario(tmp_path, which, port, est, body, length=0.35)


@pytest.mark.parametrize("which", ["toy", "ur5", "panda"])
def test_unseen_urdf_matches_reference(tmp_path, which):
    """Arms errplan ships nothing for: tests/test_urdf.py's toy (tilted base, a fixed joint with a rotated
    origin, a held roll joint, a prismatic last joint, a side branch off the chain), and two real arms of
    example-robot-data (the joint-limited UR5; the Panda with joint 3 held). The port near the middle of
    the wrist cloud, a 3-D port box. ||G|| and |phi_max| are never below the reference worst case over the
    sampled box, and validity agrees with direct inverse kinematics at every sample tip."""
    arm, L, write = _unseen_arm(tmp_path, which)
    rng = np.random.default_rng(3)
    lim = np.asarray(arm.limits)
    W = arm.forward(lim[:, 0] + rng.random((20000, 3)) * (lim[:, 1] - lim[:, 0]))
    port = W.mean(axis=0) + 0.08 * L * np.array([0.3, -0.5, 0.8])
    est = port + np.array([0.004, -0.002, 0.003])
    d = np.linalg.norm(port - W, axis=1)
    near = (d > 0.24 * L) & (d < 0.76 * L)
    assert near.sum() > 100, near.sum()
    tips = W[near] + L * (port - W[near]) / d[near][:, None]
    lo, hi = np.percentile(tips, 3, axis=0), np.percentile(tips, 97, axis=0)
    region = ", ".join(f"{a} = [{u:.4f}, {v:.4f}]" for a, u, v in zip("xyz", lo, hi))
    res = max(0.006, float(np.max(hi - lo)) / 22)
    toml = write(port, est, f"""[controller]
gain = 0.8
[uncertainty]
port_x = [-0.003, 0.003]
port_y = [-0.002, 0.004]
port_z = [-0.003, 0.002]
samples = 3
[fields]
resolution = {res:.4f}
region = {{ {region} }}
""")
    sc = load_scenario(toml)
    mf = compute_fields(sc, metrics=("G_norm", "phi_max"))
    assert mf.valid.sum() > 200
    P = np.stack(np.meshgrid(*mf.axes, indexing="ij"), -1)
    samples = [np.array([a, b, c, 0.0, 0.0]) for a in (-0.003, 0.0, 0.003) for b in (-0.002, 0.001, 0.004)
               for c in (-0.003, -0.0005, 0.002)]
    idx = np.argwhere(np.ones(mf.valid.shape, bool))
    rng.shuffle(idx)
    compared = 0
    for n, ijk in enumerate(map(tuple, idx[:300])):
        if n >= 100 and compared >= 30:  # enough of both kinds (an arm with a sparse region samples on)
            break
        Ms = [reference_M(sc, P[ijk], th) for th in samples]
        ok = all(M is not None for M in Ms)
        assert ok == bool(mf.valid[ijk]), (P[ijk], ok)
        if ok:
            g = max(g_of(M, sc.controller.gain) for M in Ms)
            assert mf.G_norm[ijk] >= g - 1e-9 * max(1.0, g), (P[ijk], mf.G_norm[ijk], g)
            assert mf.phi_max[ijk] >= max(phi_of(M) for M in Ms) - 1e-6, P[ijk]
            compared += 1
    assert compared >= 30


def test_robust_workspace_agrees_away_from_boundary(phantom):
    """Validity against direct inverse kinematics at every instance of the reference grid."""
    sc = phantom
    mf = compute_fields(sc, 0.03, metrics=("G_norm",))
    from scipy.ndimage import binary_dilation, binary_erosion

    interior = binary_erosion(mf.valid) | ~binary_dilation(mf.valid)
    rng = np.random.default_rng(0)
    pts = np.argwhere(interior)
    pts = pts[rng.choice(len(pts), min(60, len(pts)), replace=False)]
    corners = [(dx, dy, dz, 0.0, 0.0) for dx in (-0.005, 0.005) for dy in (-0.005, 0.005) for dz in (-0.005, 0.005)]
    for i, j, l in pts:
        x = np.array([mf.x[i], mf.y[j], mf.z[l]])
        ref = all(reference_M(sc, x, th) is not None for th in corners)
        if mf.valid[i, j, l]:
            assert ref, f"{x} valid in errplan, unreachable under a corner instance"
        else:  # invalid away from the boundary: some instance (a corner, or the sampled loads) fails
            loads = [(0, 0, 0, 1.0, psi) for psi in np.arange(8) * math.pi / 4]
            assert not ref or not all(reference_M(sc, x, th) is not None for th in loads), x


def test_x0_slice_consistent_with_planar_field(tmp_path):
    """Waist at zero, errors in the plane: the x = 0 slice of the 3-D field against P1's planar field.

    In the plane x = 0 G is block diagonal: the planar 2 x 2 block and the out-of-plane entry
    ``1 - k (1 - L/rho) / (1 - L/rho_hat)`` (lever Jacobians: the x axis is normal to the shaft).
    So the 3-D ||G|| equals max(planar ||G||, out-of-plane) and is never below the planar one.
    """
    planar = load_scenario(PLANAR)
    text = PHANTOM.read_text(encoding="utf-8")
    text = text.replace('urdf = "phantom15.urdf"', f'urdf = "{ROOT / "scenarios" / "phantom15.urdf"}"')
    head, _, _ = text.partition("[port]")
    text = head + """[port]
position = [0.0, 0.0, 0.160]
estimate = [0.0, 0.020, 0.170]

[controller]
gain = 1.0

[fields]
resolution = 0.004
region = { x = [0.0, 0.0], y = [-0.1, 0.1], z = [0.3, 0.42] }
"""
    p = tmp_path / "slice.toml"
    p.write_text(text, encoding="utf-8")
    sc = load_scenario(p)
    m3 = compute_fields(sc, 0.004, metrics=("G_norm", "phi_max"))
    m2 = compute_fields(planar, 0.004)
    assert len(m3.x) == 1 and m3.x[0] == 0.0
    iy = np.searchsorted(np.round(m2.y, 9), np.round(m3.y, 9))
    iz = np.searchsorted(np.round(m2.z, 9), np.round(m3.z, 9))
    g2 = m2.G_norm[np.ix_(iy, iz)]
    v2 = m2.valid[np.ix_(iy, iz)]
    g3 = m3.G_norm[0]
    v3 = m3.valid[0]
    assert v3.sum() > 100
    assert np.array_equal(v2, v3), "the x = 0 slice and the plane disagree on reachability"
    both = v2 & v3
    assert np.all(g3[both] >= g2[both] - 1e-12)
    # where does 3-D exceed the plane: exactly where the out-of-plane entry dominates
    Y, Z = np.meshgrid(m3.y, m3.z, indexing="ij")
    x = np.stack([Y, Z], -1)[both]
    L = 0.32
    r = np.linalg.norm(x - np.array([0.0, 0.160]), axis=-1)
    w = x - L * (x - np.array([0.0, 0.160])) / r[:, None]
    rho_hat = np.linalg.norm(np.array([0.020, 0.170]) - w, axis=-1)
    g_out = np.abs(1 - (1 - L / (L - r)) / (1 - L / rho_hat))
    np.testing.assert_allclose(g3[both], np.maximum(g2[both], g_out), rtol=1e-9, atol=1e-12)
    # in-plane |phi_max| (the x axis maps to a positive multiple of itself or reverses it)
    p2 = m2.phi_max[np.ix_(iy, iz)][both]
    p3 = m3.phi_max[0][both]
    assert np.all(p3 >= p2 - 1e-6)


@pytest.mark.slow
def test_spatial_refinement_is_stable(phantom):
    """Denser sampling of the 3-D error set (3 -> 5 per axis, 8 -> 8 load directions) and more
    refinement levels move the worst case by little: the refinement has found the maximum."""
    coarse = compute_fields(phantom, 0.03, metrics=("G_norm", "phi_max"))
    fine = compute_fields(phantom, 0.03, metrics=("G_norm", "phi_max"), samples=5, refine=9)
    assert np.array_equal(coarse.valid, fine.valid)
    v = coarse.valid
    dg = np.abs(fine.G_norm[v] - coarse.G_norm[v]) / np.maximum(1, fine.G_norm[v])
    dp = np.abs(fine.phi_max[v] - coarse.phi_max[v])
    assert dg.max() < 1e-3, dg.max()
    assert dp.max() < 3e-3, dp.max()
    assert np.median(dg) < 1e-6


def test_phi_bound_is_an_upper_bound():
    """The branch-and-bound of |phi_max| (kernels.phi_bound) never cuts off the exact value."""
    from errplan.fields.kernels import phi_bound, phimax

    rng = np.random.default_rng(11)
    Ms = np.concatenate([np.eye(3) + 0.3 * rng.normal(size=(3000, 3, 3)), rng.normal(size=(1000, 3, 3))])
    ub = np.array([phi_bound(Ms, j) for j in range(len(Ms))])
    ex = np.array([phimax(Ms, j) for j in range(len(Ms))])
    assert np.all(ub >= ex - 1e-12)
    near = ub < math.pi
    assert near.sum() > 2000  # the bound is informative for near-identity motion maps
    assert np.median((ub - ex)[near]) < 0.2


@pytest.mark.slow
def test_phi_with_load_disc_matches_reference(phantom):
    """Worst |phi_max| over the port box and the load disc against the dense reference."""
    mf = compute_fields(phantom, 0.04, metrics=("G_norm", "phi_max"))
    rng = np.random.default_rng(8)
    idx, X = _sample_tips(mf, 3, rng)
    for (i, j, l), x in zip(idx, X):
        ref = reference_worst(phantom, x, n=3, n_dir=8, phi=True)
        p = mf.phi_max[i, j, l]
        assert p >= ref[1] - 3e-3, (x, p, ref[1])
        assert p <= ref[1] + 0.05, (x, p, ref[1])


def _phantom_with(tmp_path, effects: str, load: bool = True) -> Path:
    text = PHANTOM.read_text(encoding="utf-8").split("[[query]]")[0]
    text = text.replace('urdf = "phantom15.urdf"', f'urdf = "{ROOT / "scenarios" / "phantom15.urdf"}"')
    if not load:
        text = text.replace("tip_force_over_ei = [0.0, 1.0]", "")
    p = tmp_path / "eff.toml"
    p.write_text(text + effects, encoding="utf-8")
    return p


@pytest.mark.slow
def test_spatial_effects_that_move_the_arm_are_honoured(tmp_path):
    """[effects] joint_offset (and gravity_sag, shaft_flexion) run the numpy path (Newton on the
    full forward map, Jacobians by differences): with a vanishing effect it reproduces the compiled
    kernel; a real joint offset changes the field, and matches a direct evaluation at a tip."""
    plain = load_scenario(_phantom_with(tmp_path, "", load=False))
    tiny = load_scenario(_phantom_with(tmp_path, "\n[effects.joint_offset]\ndq1 = 1e-12\ndq2 = 0.0\ndq3 = 0.0\n", False))
    real = load_scenario(_phantom_with(tmp_path, "\n[effects.joint_offset]\ndq1 = 0.0\ndq2 = 0.02\ndq3 = -0.02\n", False))
    a = compute_fields(plain, 0.05, metrics=("G_norm",))
    b = compute_fields(tiny, 0.05, metrics=("G_norm",))
    assert a.valid.sum() > 20 and np.array_equal(a.valid, b.valid)
    v = a.valid
    assert np.max(np.abs(a.G_norm[v] - b.G_norm[v])) < 1e-6
    c = compute_fields(real, 0.05, metrics=("G_norm",))
    both = v & c.valid
    assert np.median(np.abs(c.G_norm[both] - a.G_norm[both])) > 1e-3
    # direct check at one tip: the true tip map through pinocchio-free FK, J by differences
    from errplan.kinematics.truth import Plant

    i, j, l = np.argwhere(both)[0]
    x = np.array([c.x[i], c.y[j], c.z[l]])
    worst = 0.0
    for dx in (-0.005, 0.005):
        for dy in (-0.005, 0.005):
            for dz in (-0.005, 0.005):
                plant = Plant.from_model(build_arm(real), port=np.add(real.port.estimate, (dx, dy, dz)))
                q = plant.configuration_for_tip(x)
                from scipy.optimize import fsolve

                q = fsolve(lambda qq: plant.tip(qq) - x, q, xtol=1e-12)
                h = 1e-6
                J = np.stack([(plant.tip(q + h * e) - plant.tip(q - h * e)) / (2 * h) for e in np.eye(3)], -1)
                arm = plant.arm
                d = np.asarray(real.port.estimate) - arm.forward(q)
                rho = np.linalg.norm(d)
                u = d / rho
                Jh = (np.eye(3) - (0.32 / rho) * (np.eye(3) - np.outer(u, u))) @ arm.jacobian(q)
                worst = max(worst, np.linalg.svd(np.eye(3) - J @ np.linalg.inv(Jh), compute_uv=False)[0])
    assert c.G_norm[i, j, l] >= worst - 1e-6  # the corners are instances of the box: never below
