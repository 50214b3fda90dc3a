"""The shortcuts of the compiled field kernels (issue 21) against the long way, exactly where it matters.

- The 3-D lever's ||I - kM|| from its reduced form (a 2 x 2 block on span{u, v} and the value along
  u x v) equals the closed-form 3 x 3 value and numpy's SVD, at any gain, also for u and v nearly
  parallel or equal.
- A planar tip certified reachable at once (``_tip_reach2``) has every wrist the error set can need
  reachable by the exact per-instance test and by ``Arm.reachable``: sampled port offsets and loads,
  the box corners included.
- The search compiled without the exact |phi_max| (issue 17: the planner's and the demo's fields) gives
  bit for bit the ``||G||``, rho*, k* and validity of the search with it, planar and spatial.
"""
from __future__ import annotations

import numpy as np

from conftest import SCENARIOS
import pytest

from errplan.api import compute_fields, load_scenario
from errplan.fields.errorset import error_set
from errplan.fields.kernels import _instance3, _planar_reachable, _tip_reach2, gnorm, gval, planar_arm_params
from errplan.kinematics import arm_for


def test_lever_reduced_norm_equals_the_full_form():
    rng = np.random.default_rng(21)
    L = 0.32
    est = np.array([0.0, 0.0, 0.16])
    Mb = np.empty((1, 3, 3))
    Pb = np.empty((1, 5))
    S = np.zeros((8, 3, 3))
    V = np.zeros((8, 3))
    checked = 0
    for i in range(3000):
        x = est + np.array([0.0, 0.0, 0.15]) + rng.uniform(-0.1, 0.1, 3)
        # port offsets from none (u = v exactly) to 1e-9 m to 1 cm
        scale = 0.0 if i % 10 == 0 else 10.0 ** rng.uniform(-9, -2)
        theta = np.concatenate([rng.uniform(-1, 1, 3) * scale, [0.0, 0.0]])
        ok, *_ = _instance3(x, theta, est, est, L, Mb, Pb, 0, S, V, True)
        if not ok:
            continue
        M = Mb[0]
        for k in (0.0, 0.3, 1.0, 1.7):
            full = gnorm(3, Mb, 0, k)
            red = gval(3, Mb, Pb, 0, k)
            svd = np.linalg.norm(np.eye(3) - k * M, 2)
            assert abs(red - full) <= 1e-12 * max(1.0, full), (x, theta, k, red, full)
            assert abs(red - svd) <= 1e-12 * max(1.0, svd), (x, theta, k, red, svd)
        checked += 1
    assert checked > 2000


def test_planar_tip_certificate_implies_every_wrist_reachable():
    sc = load_scenario(SCENARIOS / "beasley2004_bounded.toml")
    es, _ = error_set(sc)
    arm = arm_for(sc.robot)
    p = planar_arm_params(arm)
    assert p[25] == 1.0  # the arctangent-free limits apply to P1's arm
    L = float(sc.instrument.length)
    lo, hi, base = es.lo_arr, es.hi_arr, np.asarray(es.base_port, float)
    rng = np.random.default_rng(7)
    # tips over the workspace's bounding box
    tips = base + np.column_stack([rng.uniform(-0.3, 0.3, 4000), rng.uniform(-0.05, 0.3, 4000)])
    cert = np.array([_tip_reach2(t, base, lo, hi, L, p) for t in tips])
    assert (cert == 1).sum() > 200 and (cert == 2).sum() > 200
    corners = np.array([[a, b] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])])
    for t in tips[cert == 1]:
        offs = np.vstack([corners, rng.uniform(lo[:2], hi[:2], (12, 2))])
        loads = [lo[2], hi[2], 0.0, rng.uniform(lo[2], hi[2])] if len(lo) > 2 else [0.0]
        wrists = []
        for o in offs:
            port = base + o
            e = t - port
            r = np.hypot(*e)
            for tl in loads:
                if tl == 0.0:
                    wrists.append(t - L * e / r)
                    continue
                # the flexed shaft's wrist (the kernel's arithmetic): chord turned by atan(t a b / 3)
                from errplan.fields.kernels import _solve_b

                b = _solve_b(r, L, tl)
                phi = np.arctan2(e[0], e[1]) - np.arctan(tl * (L - b) * b / 3.0)
                wrists.append(t - L * np.array([np.sin(phi), np.cos(phi)]))
        wrists = np.array(wrists)
        assert all(_planar_reachable(p, w[0], w[1]) for w in wrists), t
        assert arm.reachable(wrists).all(), t


@pytest.mark.parametrize("name, res", [("beasley2004_bounded.toml", 0.01), ("phantom15_spatial.toml", 0.016)])
def test_the_search_without_phi_max_is_the_search_with_it(name, res):
    from errplan.fields import kernels

    sc = load_scenario(SCENARIOS / name)
    without = compute_fields(sc, res, metrics=("G_norm", "rho_star"), workers=1)
    with_phi = compute_fields(sc, res, metrics=("G_norm", "phi_max", "rho_star"), workers=1)
    assert without.phi_max is None and np.isfinite(with_phi.phi_max[with_phi.valid]).all()
    assert with_phi.valid.sum() > 100
    for a in ("valid", "G_norm", "rho_star", "k_star"):
        assert np.array_equal(getattr(without, a), getattr(with_phi, a), equal_nan=a != "valid"), a
    d = sc.dim
    assert kernels._TILES[d, False] is not kernels._TILES[d, True]
    assert kernels._TILES[d, False].signatures and kernels._TILES[d, True].signatures  # both copies ran
