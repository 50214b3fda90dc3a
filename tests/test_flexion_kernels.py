"""P2's flexion controller in 3-D, compiled (errplan.fields.kernels.flexion), against the numpy path
(SpatialFlexionEvaluator.parts_numpy through errplan.kinematics.shaft, and the numpy search on it:
NumpyFlexionEvaluator): the same maps, worst cases and fields to 1e-9, on random tips, instances and
noise vectors. "To 1e-9": relative to max(1, |value|), where the controller is not near singular (a
controller Jacobian of condition ~1e6 gives |M| ~ 1e5, whose 9th digit differs between any two orders of
the same arithmetic: there the numpy path is no more exact than that; such pairs are counted, not compared)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from errplan.api import load_scenario
from errplan.fields.compute import numpy_worst_case
from errplan.fields.evaluator import NumpyFlexionEvaluator, SpatialFlexionEvaluator
from errplan.metrics import g_norm, phi_max
from errplan.models import build_arm

ROOT = Path(__file__).resolve().parents[1]
FLEX = ROOT / "scenarios" / "phantom15_flexion.toml"
TOL = 1e-9


def close(a, b) -> bool:
    """Equal to TOL relative to max(1, |b|), NaN where the other is NaN."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return bool(np.array_equal(np.isnan(a), np.isnan(b))
                and np.all(np.abs(a - b)[~np.isnan(b)] <= TOL * np.maximum(1.0, np.abs(b[~np.isnan(b)]))))


@pytest.fixture(scope="module")
def evs():
    sc = load_scenario(FLEX)
    return sc, SpatialFlexionEvaluator.from_model(build_arm(sc)), NumpyFlexionEvaluator.from_model(build_arm(sc))


def _pairs(n, seed, offsets=0.0):
    """Random tips of the widened task region (x, y in [-30, 30] mm, z in [360, 450] mm) and instances
    (port offsets up to ``offsets``, a load of 0 to 4 /m^2 in any direction, some unloaded)."""
    rng = np.random.default_rng(seed)
    x = np.column_stack([rng.uniform(-0.03, 0.03, n), rng.uniform(-0.03, 0.03, n), rng.uniform(0.36, 0.45, n)])
    tau = rng.uniform(0.0, 4.0, n)
    tau[::7] = 0.0
    th = np.column_stack([rng.uniform(-offsets, offsets, (n, 3)), tau, rng.uniform(0, 2 * np.pi, n)])
    return x, th


@pytest.mark.parametrize("seed, offsets", [(0, 0.0), (1, 0.004)])
def test_compiled_maps_equal_the_numpy_path(evs, seed, offsets):
    _, ev, ref = evs
    x, th = _pairs(60, seed, offsets)
    M, _, ok = ev.parts(x, th)
    M0, _, ok0 = ref.parts(x, th)
    assert np.array_equal(ok, ok0) and ok.sum() > 30
    assert M.shape == M0.shape == (60, len(ev.noise), 3, 3)
    assert np.all(np.isnan(M[~ok])) and np.all(np.isfinite(M[ok]))
    assert close(M[ok], M0[ok])


def test_compiled_maps_equal_the_numpy_path_per_tip_noise(evs):
    """Noise vectors per tip (the noise refinement's), inside the set, not only its corners."""
    _, ev, ref = evs
    x, th = _pairs(30, 2)
    half = ev.noise_bounds()
    nz = np.random.default_rng(3).uniform(-1, 1, (30, 14, 7)) * half
    M, _, ok = ev.parts(x, th, nz)
    M0, _, ok0 = ref.parts(x, th, nz)
    assert np.array_equal(ok, ok0) and ok.any()
    assert close(M[ok], M0[ok])


def test_worst_over_the_noise_equals_the_maps_worst(evs):
    """The compiled worst ||G|| and |phi_max| over the corners (bounds prune the exact evaluations) equal the
    plain maximum of errplan.metrics over the numpy maps; with floors, the floor where the worst is not
    above it and the worst where it is."""
    sc, ev, ref = evs
    x, th = _pairs(40, 4)
    k = float(sc.controller.gain)
    g, p, ok = ev.reduced(x, th, k)
    M0, _, ok0 = ref.parts(x, th)
    assert np.array_equal(ok, ok0) and ok.sum() > 20
    g0 = g_norm(M0[ok0], k).max(axis=-1)
    p0 = phi_max(M0[ok0]).max(axis=-1)
    well = np.abs(M0[ok0]).max(axis=(1, 2, 3)) < 1e4  # not a near-singular controller (module docstring)
    assert well.sum() >= 0.8 * len(well)
    assert close(g[ok][well], g0[well]) and close(p[ok][well], p0[well])
    assert np.all(np.isnan(g[~ok])) and np.all(np.isnan(p[~ok]))
    floor_g = np.where(np.arange(40) % 2 == 0, g + 1e-3, g - 1e-3)
    floor_p = np.where(np.arange(40) % 3 == 0, p + 1e-3, p - 1e-3)
    gf, pf, okf = ev.reduced(x, th, k, g_above=floor_g, p_above=floor_p)
    assert np.array_equal(okf, ok)
    assert close(gf[ok], np.where(g > floor_g, g, floor_g)[ok])
    assert close(pf[ok], np.where(p > floor_p, p, floor_p)[ok])
    kk = np.linspace(0.2, 1.2, 40)  # a gain per tip (the rho* certificate's)
    gk, _, _ = ev.reduced(x, th, kk, phi=False)
    assert close(gk[ok][well], g_norm(M0[ok0], kk[ok0][:, None]).max(axis=-1)[well])


def test_batched_corners_are_the_one_corner_kernel_bit_for_bit(evs):
    """The kernel runs the noise vectors in vectorized blocks; per vector it must do what the one-vector
    functions do (fields.kernels.flexion._controller_J3, errplan.linalg.inv3, the product), operation for
    operation: the same maps to the bit, on pairs whose vectors take the shortcut estimate, the general
    one, or both (low loads)."""
    from numba import njit

    import errplan.fields.kernels.flexion as F
    from errplan.linalg import inv3

    @njit(error_model="numpy")
    def one_by_one(Wt, Tt, Pt, ok, NZ, est, L, out):
        c = NZ.shape[1]
        S = np.zeros((8, 3, 3))
        B = np.zeros((F.ROWS, 3))
        J, Jh, Ji = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        Zk, Zv = np.empty((2, 16, 2)), np.empty((2, 16, 3))
        cnt, last = np.zeros(2, np.int64), np.empty(4)
        for a_ in range(3):
            B[F.EST, a_] = est[a_]
        for i in range(Wt.shape[0]):
            if not ok[i]:
                continue
            for a_ in range(3):
                B[F.W, a_], B[F.T, a_], B[F.P, a_] = Wt[i, a_], Tt[i, a_], Pt[i, a_]
            F._jacobian3(B, F.W, F.P, F.T, L, J, S)
            F._true_poses(B, L)
            cnt[0] = cnt[1] = 0
            last[0] = np.nan
            for j in range(c):
                F._controller_J3(B, NZ, 0, j, L, Jh, S, Zk, Zv, cnt, last)
                inv3(Jh, Ji)
                for a_ in range(3):
                    for b_ in range(3):
                        out[i, j, a_, b_] = J[a_, 0] * Ji[0, b_] + J[a_, 1] * Ji[1, b_] + J[a_, 2] * Ji[2, b_]

    _, ev, _ = evs
    x, th = _pairs(40, 7, 0.004)
    M, _, ok = ev.parts(x, th)
    w, t, port, ok_t = ev.truth(x, th)
    M1 = np.full_like(M, np.nan)
    one_by_one(w, t, port, ok, np.ascontiguousarray(ev.noise[None]), np.asarray(ev.estimate, float),
               float(ev.length), M1)
    assert ok.sum() > 20
    assert np.array_equal(M[ok], M1[ok])


def test_worst_corner_equals_the_numpy_argmax(evs):
    """The compiled worst corner (bounds prune the exact norms; the noise refinement's start) is numpy's
    argmax over every corner's ||G|| (the first of equal ones), with its norm and map; invalid pairs as the
    numpy path's. The noise set's 432 corners run in several blocks of the kernel, the last one partial."""
    sc, ev, ref = evs
    x, th = _pairs(40, 6, 0.004)
    k = float(sc.controller.gain)
    g, j, Mj, ok = ev.worst_corner(x, th, k)
    g0, j0, Mj0, ok0 = ref.worst_corner(x, th, k)
    assert np.array_equal(ok, ok0) and ok.sum() > 20 and len(ev.noise) % 64 != 0
    well = np.abs(Mj0[ok]).max(axis=(1, 2)) < 1e4
    assert np.array_equal(j[ok][well], j0[ok][well])
    assert close(g[ok], g0[ok]) and close(Mj[ok][well], Mj0[ok][well])
    assert np.all(g[~ok] == -np.inf) and np.all(np.isnan(Mj[~ok]))
    assert np.unique(j[ok]).size > 1  # not one corner everywhere


@pytest.mark.slow
def test_worst_case_fields_equal_the_numpy_search(evs):
    """The whole worst case of a field tile (sampling, pattern search, noise refinement, rho*) on the
    compiled controller equals the numpy path's to 1e-9."""
    sc, ev, ref = evs
    rng = np.random.default_rng(5)
    x = np.column_stack([rng.uniform(-0.03, 0.03, 5), rng.uniform(-0.03, 0.03, 5), rng.uniform(0.36, 0.45, 5)])
    k = float(sc.controller.gain)
    for rho in (False, True):
        a = numpy_worst_case(ev, x, k, rho=rho)
        b = numpy_worst_case(ref, x, k, rho=rho)
        assert np.array_equal(a["valid"], b["valid"]) and a["valid"].sum() >= 3
        for key in ("G_norm", "phi_max") + (("rho_star", "k_star") if rho else ()):
            assert close(a[key], b[key]), key
