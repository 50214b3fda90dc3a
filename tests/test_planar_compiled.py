"""The compiled planar kinematics (numba loops in errplan.kinematics.shaft / .arm and the evaluator's true
wrist) against the numpy paths they replaced, kept as references: the same operations in the same order, so
the same values as rounding allows (NaN where NaN, flags and integers exactly), for the batch shapes the
callers use and the edge cases (zero and mixed loads, tips the shaft misses, unreachable wrists, NaN).

Bit-equality between numba's arithmetic and numpy's is not something a platform promises (numpy may use
wide-SIMD trigonometry, or round a complex product twice where the kernel fuses it): the comparisons allow
a few units in the last place (:func:`same`). errplan compares itself bit for bit elsewhere (run to run,
one worker against two, a cluster against a local run)."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from conftest import SCENARIOS
from errplan.api import load_scenario
from errplan.fields import Evaluator
from errplan.kinematics import shaft
from errplan.kinematics.arm import Arm, direction, direction_derivative
from errplan.models import build_arm

L = 0.320
ULPS = 8  # units in the last place of a value (a few roundings apart)
FLOOR_ULPS = 16  # and of the batch's largest magnitude: a value near zero formed by cancellation carries the
#                  rounding of the larger values it came from (2.8e-16 m on a batch of 0.3 m seen on one machine)


def same(a, b) -> bool:
    """Equal as rounding allows: the same shape, dtype and NaN pattern; booleans and integers exactly; floats
    within ``ULPS`` units in the last place of the larger of the two plus ``FLOOR_ULPS`` units of the largest
    finite magnitude in ``b`` (an absolute floor in the values' own unit: metres, radians, 1)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype.kind == "c" and b.dtype.kind == "c":
        return a.shape == b.shape and same(a.real, b.real) and same(a.imag, b.imag)
    if not (a.shape == b.shape and a.dtype == b.dtype):
        return False
    if a.dtype.kind != "f":
        return bool(np.array_equal(a, b))
    nan = np.isnan(b)
    if not np.array_equal(np.isnan(a), nan):
        return False
    fa, fb = a[~nan], b[~nan]
    if not np.array_equal(np.isinf(fa), np.isinf(fb)) or not np.array_equal(fa[np.isinf(fa)], fb[np.isinf(fb)]):
        return False
    fin = np.isfinite(fb)
    fa, fb = fa[fin], fb[fin]
    if fb.size == 0:
        return True
    scale = float(np.max(np.abs(fb)))
    tol = ULPS * np.spacing(np.maximum(np.abs(fa), np.abs(fb))) + FLOOR_ULPS * np.spacing(scale)
    return bool(np.all(np.abs(fa - fb) <= tol))


def test_same_allows_rounding_only():
    """The comparison the tests below use: a few roundings pass, anything larger fails."""
    rng = np.random.default_rng(10)
    x = rng.normal(size=1000) * 0.3
    assert same(x, x.copy()) and same(np.nextafter(x, np.inf), x)
    assert same(x * (1 + 4 * np.finfo(float).eps), x)
    assert not same(x * (1 + 1e-13), x)
    y = x.copy()
    y[7] += 1e-14  # one value off by 50 units of the batch's scale
    assert not same(y, x)
    z = x.copy()
    z[3] = np.nan
    assert not same(z, x) and same(z, z.copy())
    assert not same(x.astype(np.float32), x) and not same(x[:10], x[:11])
    assert same(np.array([True, False]), np.array([True, False])) and not same(np.array([True]), np.array([False]))


@pytest.fixture(scope="module")
def arms():
    sc = load_scenario(SCENARIOS / "beasley2004_port.toml")
    other = Arm((0.05, -0.31), 0.3, 0.25, (0.3, -1.2), (-2.5, 1.5), (-2.5, 2.5), (-3.0, 3.0))
    return [Arm.from_robot(sc.robot), other]


def _shaft_inputs(seed: int, n: int = 4000):
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(n, 2)) * 0.15
    p = rng.normal(size=(n, 2)) * 0.05 + [0.0, 0.16]
    t = rng.normal(size=n) * 30.0
    t[::7] = 0.0  # mixed: some unloaded entries in a loaded batch
    w[5] = np.nan
    t[9] = np.nan
    p[11] = w[11]  # rho = 0
    return w, p, t


@pytest.mark.parametrize("seed", [0, 1])
def test_flexed_shaft_compiled_equals_numpy(seed):
    w, p, t = _shaft_inputs(seed)
    with np.errstate(all="ignore"):
        for tt in (t, np.zeros_like(t), np.float64(4.0), 0.0):
            g, r = shaft.flexed_geometry(w, p, L, tt), shaft._flexed_geometry_numpy(w, p, L, tt)
            assert set(g) == set(r) and all(same(g[k], r[k]) for k in r)
            assert same(shaft.flexed_tip(w, p, L, tt), r["tip"])
            assert same(shaft.flexed_jacobian(w, p, L, tt), shaft._flexed_jacobian2_numpy(w, p, L, tt))
            assert same(shaft.flexed_wrist(w, p, L, tt), shaft._flexed_wrist_numpy(w, p, L, tt))
        # broadcast batches (n, c, 2) against (n, 1, 2) ports and (n, c) loads, and single points
        W = w[:50, None, :] + np.linspace(-0.01, 0.01, 4)[:, None]
        P, T = p[:50, None, :], np.broadcast_to(t[:50, None], (50, 4))
        assert same(shaft.flexed_jacobian(W, P, L, T), shaft._flexed_jacobian2_numpy(W, P, L, T))
        assert same(shaft.flexed_wrist(W, P, L, T), shaft._flexed_wrist_numpy(W, P, L, T))
        for i in (0, 3, 7):
            g, r = shaft.flexed_geometry(w[i], p[i], L, t[i]), shaft._flexed_geometry_numpy(w[i], p[i], L, t[i])
            assert all(same(g[k], r[k]) and type(g[k]) is type(r[k]) for k in r)
        # a load that widens the points' batch keeps numpy's shapes (the reference path)
        g, r = shaft.flexed_geometry(w[0], p[0], L, t[:3]), shaft._flexed_geometry_numpy(w[0], p[0], L, t[:3])
        assert all(same(g[k], r[k]) for k in r)


def test_flexed_shaft_compiled_is_the_beam():
    """Independent of the numpy path: the wrist the compiled inverse returns puts the compiled tip back at
    the target, and the compiled Jacobian is the central difference of the compiled tip."""
    rng = np.random.default_rng(3)
    p = np.array([0.0, 0.16])
    x = p + rng.uniform(0.03, 0.15, 200)[:, None] * direction(rng.uniform(-0.8, 0.8, 200))
    t = rng.uniform(-20.0, 20.0, 200)
    w = shaft.flexed_wrist(x, p, L, t)
    assert np.max(np.abs(shaft.flexed_tip(w, p, L, t) - x)) < 1e-12
    h = 1e-6
    fd = np.stack([(shaft.flexed_tip(w + e, p, L, t) - shaft.flexed_tip(w - e, p, L, t)) / (2 * h)
                   for e in (np.array([h, 0.0]), np.array([0.0, h]))], axis=-1)
    assert np.max(np.abs(shaft.flexed_jacobian(w, p, L, t) - fd)) < 1e-6


def test_arm_compiled_equals_numpy(arms):
    rng = np.random.default_rng(4)
    for arm in arms:
        W = rng.normal(size=(20000, 2)) * 0.4 + np.asarray(arm.base)
        W[3] = np.nan
        Q = rng.uniform(-4.0, 4.0, size=(20000, 2))
        r = arm.reachable(W)
        assert same(r, arm._reachable_numpy(W)) and 0.05 < r.mean() < 0.95
        q, ok = arm.inverse(W)
        qr, okr = arm._inverse_numpy(W)
        assert same(q, qr) and same(ok, okr) and same(ok, r)
        assert same(arm.forward(Q), arm._forward_numpy(Q))
        assert same(arm.jacobian(Q), arm._jacobian_numpy(Q))
        Q3 = Q[:60].reshape(5, 12, 2)
        assert same(arm.forward(Q3), arm._forward_numpy(Q3)) and same(arm.jacobian(Q3), arm._jacobian_numpy(Q3))
        assert same(arm.reachable(W[:60].reshape(5, 12, 2)), arm._reachable_numpy(W[:60].reshape(5, 12, 2)))
        for i in range(8):
            assert same(arm.reachable(W[i]), arm._reachable_numpy(W[i]))
            assert all(same(a, b) for a, b in zip(arm.inverse(W[i]), arm._inverse_numpy(W[i])))
            assert same(arm.forward(Q[i]), arm._forward_numpy(Q[i]))
        # independent: the inverse's angles put the wrist back where it was
        assert np.max(np.abs(arm.forward(q[ok]) - W[ok])) < 1e-12
        # wrists whose joint angles sit on a limit, or just inside or outside it (the arctangent-free
        # test's uncertain band and the 1e-12 rad tolerance)
        eps = np.array([-1e-7, -1e-9, -2e-12, -5e-13, 0.0, 5e-13, 2e-12, 1e-9, 1e-7])
        Qb = []
        for j, lim in ((0, arm.q1_limits), (1, arm.q2_limits)):
            for v in lim:
                lo, hi = [arm.q1_limits[0], arm.q2_limits[0]], [arm.q1_limits[1], arm.q2_limits[1]]
                q = rng.uniform(lo, hi, (len(eps), 2))
                q[:, j] = v + eps
                Qb.append(q)
        for v in arm.sum_limits:  # on the q1 + q2 limits
            q1 = rng.uniform(*arm.q1_limits, len(eps))
            Qb.append(np.stack([q1, v - q1 + eps], axis=-1))
        Wb = arm.forward(np.concatenate(Qb))
        assert same(arm.reachable(Wb), arm._reachable_numpy(Wb))
        assert all(same(a, b) for a, b in zip(arm.inverse(Wb), arm._inverse_numpy(Wb)))
    assert arms[0]._reach_params()[27] == 1.0 and arms[1]._reach_params()[27] == 0.0  # both paths run


def test_direction_values():
    a = np.random.default_rng(5).uniform(-7, 7, (3, 4))
    assert same(direction(a), np.stack([np.sin(a), np.cos(a)], axis=-1))
    assert same(direction_derivative(a), np.stack([np.cos(a), -np.sin(a)], axis=-1))
    assert same(direction(0.3), np.array([np.sin(0.3), np.cos(0.3)]))


def test_true_wrist_compiled_equals_numpy():
    sc = load_scenario(SCENARIOS / "beasley2004_bounded.toml")
    ev = Evaluator.from_model(build_arm(sc))
    rng = np.random.default_rng(6)
    th = ev.errors.sample_grid(5)
    n = 6000
    theta = th[rng.integers(0, len(th), n)]
    x = np.asarray(ev.errors.base_port)[None] + rng.normal(size=(n, 2)) * 0.1
    x[7] = ev.errors.port(theta[7])  # the shaft misses the tip (r = 0)
    for T in (theta, theta * [1.0, 1.0, 0.0], theta * [1.0, 1.0, 1e-3]):
        w, ok = ev.true_wrist(x, T)
        wr, okr = ev._true_wrist_numpy(x, T)
        assert same(w, wr) and same(ok, okr) and 0.05 < ok.mean() < 0.95


def test_importing_the_kinematics_does_not_load_numba():
    """The compiled kernels load on first use: a command that only reads a scenario starts without numba."""
    code = ("import sys, errplan.kinematics.arm, errplan.kinematics.shaft, errplan.kinematics.truth, errplan.metrics\n"
            "assert 'numba' not in sys.modules\nprint('ok')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_inv2_compiled_equals_numpy():
    from errplan.metrics import _inv2_numpy, inv2

    rng = np.random.default_rng(7)
    buf = rng.normal(size=40_000) * rng.lognormal(size=40_000)
    for n in (1, 3, 8, 33, 5000):
        for off in (0, 1, 3):  # contiguous at several alignments
            A = buf[off:off + 4 * n].reshape(n, 2, 2).copy() if off == 0 else buf[off:off + 4 * n].reshape(n, 2, 2)
            A[0] = [[1.0, 2.0], [2.0, 4.0]]  # singular
            with np.errstate(all="ignore"):
                assert all(same(a, b) for a, b in zip(inv2(A), _inv2_numpy(A)))
    A = buf[:8].reshape(2, 2, 2)
    assert all(same(a, b) for a, b in zip(inv2(A[0]), _inv2_numpy(A[0])))  # one matrix
    B = buf[:240].reshape(3, 4, 5, 2, 2)
    assert all(same(a, b) for a, b in zip(inv2(B), _inv2_numpy(B)))
    inv, sing = inv2(B)  # independent: the inverse times the matrix, where it is well conditioned
    good = np.linalg.cond(B) < 1e6
    assert good.sum() > 30 and np.allclose((inv @ B)[good], np.eye(2), atol=1e-8)


def test_lever_parts_compiled_equals_numpy():
    """The lever's conformal parts: numpy's complex products in the kernel, equal as rounding allows."""
    rng = np.random.default_rng(8)
    w = rng.normal(size=(20_000, 2)) * 0.2
    p = rng.normal(size=(20_000, 2)) * 0.05
    w[3] = p[3]  # rho = 0
    w[4] = np.nan
    with np.errstate(all="ignore"):
        for n in (1, 2, 5, 17, 20_000):
            for pp in (p[:n], p[0]):
                a, b = shaft.lever_parts(w[:n], pp, L), shaft._lever_parts_numpy(w[:n], pp, L)
                assert all(same(x, y) for x, y in zip(a, b))
        a, b = shaft.lever_parts(w[0], p[0], L), shaft._lever_parts_numpy(w[0], p[0], L)
        assert all(same(x, y) and type(x) is type(y) for x, y in zip(a, b))
        W = w[:60].reshape(3, 20, 2)
        assert all(same(x, y) for x, y in zip(shaft.lever_parts(W, p[0], L), shaft._lever_parts_numpy(W, p[0], L)))
    # independent: the parts rebuild the lever's Jacobian (errplan.metrics' convention)
    from errplan.metrics import conformal_parts

    mu, nu = shaft.lever_parts(w[5:50], p[5:50], L)
    mu_j, nu_j = conformal_parts(shaft.lever_jacobian(w[5:50], p[5:50], L))
    assert np.allclose(mu, mu_j, atol=1e-12, rtol=1e-12) and np.allclose(nu, nu_j, atol=1e-12, rtol=1e-12)


def test_inverse_parts_compiled_equals_numpy():
    from errplan.metrics import _inverse_parts_numpy, compose_parts, inverse_parts

    rng = np.random.default_rng(9)
    n = 20_000
    mr, mi, nr, ni = (rng.normal(size=(n // 4, 4)) * rng.lognormal(size=(n // 4, 4)) for _ in range(4))
    nr[0, 0], ni[0, 0], mi[0, 0] = mr[0, 0], 0.0, 0.0  # |mu| = |nu|: singular
    mr[1, 1] = np.nan
    with np.errstate(all="ignore"):
        for mu in (mr, mr + 1j * mi):
            for sl in (np.s_[:], np.s_[:1, :1], np.s_[:3]):
                a = inverse_parts(mu[sl], (nr + 1j * ni)[sl])
                b = _inverse_parts_numpy(mu[sl], (nr + 1j * ni)[sl])
                assert all(same(x, y) for x, y in zip(a, b))
            assert a[2][0, 0] and not a[2][2:].all()
        # independent: composed with the matrix's own parts, the inverse's parts give the identity (mu 1, nu 0)
        mu, nu = (mr + 1j * mi)[2:], (nr + 1j * ni)[2:]
        imu, inu, sing = inverse_parts(mu, nu)
        cm, cn = compose_parts(mu, nu, imu, inu)
        good = ~sing & (np.abs(np.abs(mu) ** 2 - np.abs(nu) ** 2) > 1e-3 * (np.abs(mu) ** 2 + np.abs(nu) ** 2))
        assert good.sum() > 1000 and np.allclose(cm[good], 1.0, atol=1e-9) and np.allclose(cn[good], 0.0, atol=1e-9)
