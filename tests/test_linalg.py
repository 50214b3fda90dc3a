"""Compiled small-matrix kernels (errplan.linalg) against numpy and against brute force.

The exact 3-D |phi_max| is checked against an independent dense search of the sphere (a Fibonacci
hemisphere, then Nelder-Mead polishes from the best grid points and from the singular and
eigenvectors of M; Nelder-Mead follows the razor-thin ridges of nearly reversing maps where a
compass search stalls), on 2400 matrices from 14 families, most of them adversarial.
"""
from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from numba import njit

from errplan import linalg as L
from errplan import metrics as m


# ----------------------------------------------------------------------------- reference search
def fib_hemisphere(n: int) -> np.ndarray:
    """Unit vectors of a Fibonacci sphere of ``n`` points with z >= 0 (v and -v give the same
    angle, so a hemisphere covers every direction)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    t = np.pi * (1 + 5 ** 0.5) * i
    V = np.stack([r * np.cos(t), r * np.sin(t), z], -1)
    return np.ascontiguousarray(V[V[:, 2] >= 0])


@njit(cache=True)
def _ang(M, x0, x1, x2):
    y0 = M[0, 0] * x0 + M[0, 1] * x1 + M[0, 2] * x2
    y1 = M[1, 0] * x0 + M[1, 1] * x1 + M[1, 2] * x2
    y2 = M[2, 0] * x0 + M[2, 1] * x1 + M[2, 2] * x2
    c0 = x1 * y2 - x2 * y1
    c1 = x2 * y0 - x0 * y2
    c2 = x0 * y1 - x1 * y0
    return math.atan2(math.sqrt(c0 * c0 + c1 * c1 + c2 * c2), x0 * y0 + x1 * y1 + x2 * y2)


@njit(cache=True)
def _tangent_point(x, e, f, p, q, out):
    for i in range(3):
        out[i] = x[i] + p * e[i] + q * f[i]
    n = math.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2)
    for i in range(3):
        out[i] /= n


@njit(cache=True)
def _nelder_mead(M, x, scale):
    """Maximise the angle over the tangent plane at unit ``x`` (2-D Nelder-Mead); ``x`` is
    replaced by the best point. Returns the best angle."""
    if abs(x[0]) < 0.9:
        e = np.array([0.0, x[2], -x[1]])
    else:
        e = np.array([-x[2], 0.0, x[0]])
    e /= np.sqrt((e * e).sum())
    f = np.array([x[1] * e[2] - x[2] * e[1], x[2] * e[0] - x[0] * e[2], x[0] * e[1] - x[1] * e[0]])
    P = np.array([[0.0, 0.0], [scale, 0.0], [0.0, scale]])
    val = np.empty(3)
    y = np.empty(3)
    for k in range(3):
        _tangent_point(x, e, f, P[k, 0], P[k, 1], y)
        val[k] = _ang(M, y[0], y[1], y[2])
    for _ in range(2000):
        for i in range(2):  # order best first (3 points, insertion sort in place)
            for j in range(2 - i):
                if val[j + 1] > val[j]:
                    val[j], val[j + 1] = val[j + 1], val[j]
                    P[j, 0], P[j + 1, 0] = P[j + 1, 0], P[j, 0]
                    P[j, 1], P[j + 1, 1] = P[j + 1, 1], P[j, 1]
        size = abs(P[1, 0] - P[0, 0]) + abs(P[1, 1] - P[0, 1]) + abs(P[2, 0] - P[0, 0]) + abs(P[2, 1] - P[0, 1])
        if size < 1e-15:
            break
        c0 = 0.5 * (P[0, 0] + P[1, 0])
        c1 = 0.5 * (P[0, 1] + P[1, 1])
        r0, r1 = 2 * c0 - P[2, 0], 2 * c1 - P[2, 1]
        _tangent_point(x, e, f, r0, r1, y)
        vr = _ang(M, y[0], y[1], y[2])
        if vr > val[0]:
            e0, e1 = 3 * c0 - 2 * P[2, 0], 3 * c1 - 2 * P[2, 1]
            _tangent_point(x, e, f, e0, e1, y)
            ve = _ang(M, y[0], y[1], y[2])
            if ve > vr:
                P[2, 0], P[2, 1], val[2] = e0, e1, ve
            else:
                P[2, 0], P[2, 1], val[2] = r0, r1, vr
        elif vr > val[1]:
            P[2, 0], P[2, 1], val[2] = r0, r1, vr
        else:
            k0, k1 = 0.5 * (c0 + P[2, 0]), 0.5 * (c1 + P[2, 1])
            _tangent_point(x, e, f, k0, k1, y)
            vk = _ang(M, y[0], y[1], y[2])
            if vk > val[2]:
                P[2, 0], P[2, 1], val[2] = k0, k1, vk
            else:
                for k in (1, 2):
                    P[k, 0] = 0.5 * (P[0, 0] + P[k, 0])
                    P[k, 1] = 0.5 * (P[0, 1] + P[k, 1])
                    _tangent_point(x, e, f, P[k, 0], P[k, 1], y)
                    val[k] = _ang(M, y[0], y[1], y[2])
    k = np.argmax(val)
    _tangent_point(x, e, f, P[k, 0], P[k, 1], y)
    x[:] = y
    return val[k]


@njit(cache=True)
def _dense_search(Ms, V, seeds, nstart):
    """max over the grid ``V``, then Nelder-Mead (4 restarts, scale / 10 each) from the ``nstart``
    best mutually separated grid points and from ``seeds`` (NaN rows skipped)."""
    n = V.shape[0]
    out = np.empty(Ms.shape[0])
    vals = np.empty(n)
    sep = math.cos(6.0 * math.sqrt(2 * math.pi / n))
    h0 = 3.0 * math.sqrt(2 * math.pi / n)
    starts = np.empty((nstart + seeds.shape[1], 3))
    scales = np.empty(nstart + seeds.shape[1])
    for m_ in range(Ms.shape[0]):
        M = Ms[m_]
        for i in range(n):
            vals[i] = _ang(M, V[i, 0], V[i, 1], V[i, 2])
        order = np.argsort(-vals)
        best = vals[order[0]]
        ns = 0
        for j in range(min(n, 5000)):
            i = order[j]
            ok = True
            for s in range(ns):
                if abs(V[i, 0] * starts[s, 0] + V[i, 1] * starts[s, 1] + V[i, 2] * starts[s, 2]) > sep:
                    ok = False
                    break
            if ok:
                starts[ns] = V[i]
                scales[ns] = h0
                ns += 1
                if ns == nstart:
                    break
        for j in range(seeds.shape[1]):
            if seeds[m_, j, 0] == seeds[m_, j, 0]:
                starts[ns] = seeds[m_, j]
                scales[ns] = 0.05
                ns += 1
        x = np.empty(3)
        for s in range(ns):
            x[:] = starts[s]
            sc = scales[s]
            for _ in range(4):
                best = max(best, _nelder_mead(M, x, sc))
                sc *= 0.1
        out[m_] = best
    return out


def dense_phi_max3(Ms: np.ndarray, npts: int = 25_000, nstart: int = 4) -> np.ndarray:
    """Brute-force ``max over unit v of angle(v, M v)`` for each ``M`` (independent of linalg)."""
    Ms = np.ascontiguousarray(np.asarray(Ms, float).reshape(-1, 3, 3))
    seeds = np.full((len(Ms), 9, 3), np.nan)
    for i, M in enumerate(Ms):
        _, _, Vt = np.linalg.svd(M)
        _w, E = np.linalg.eig(M)
        S = [Vt[j] for j in range(3)]
        for j in range(3):
            for part in (E[:, j].real, E[:, j].imag):
                if np.linalg.norm(part) > 1e-12:
                    S.append(part / np.linalg.norm(part))
        seeds[i, :len(S)] = S
    return _dense_search(Ms, fib_hemisphere(2 * npts), seeds, nstart)  # npts on the hemisphere


# ----------------------------------------------------------------------------- matrix families
def _qr(rng):
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return Q


def _rot(axis, th):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def lever_jacobian3(w, p, length):
    """``d tip / d wrist = I - (L/r)(I - u u^T)`` of the 3-D lever (docs/physics.md)."""
    d = p - w
    r = np.linalg.norm(d)
    u = d / r
    return np.eye(3) - (length / r) * (np.eye(3) - np.outer(u, u))


def families(rng, scale=1) -> dict[str, np.ndarray]:
    def n(k):
        return int(k * scale)

    F = {}
    F["normal"] = rng.normal(size=(n(300), 3, 3))
    F["near_id_0.3"] = np.eye(3) + 0.3 * rng.normal(size=(n(200), 3, 3))
    F["near_id_1e-3"] = np.eye(3) + 1e-3 * rng.normal(size=(n(100), 3, 3))
    F["near_id_1e-6"] = np.eye(3) + 1e-6 * rng.normal(size=(n(100), 3, 3))
    F["near_singular"] = np.array([_qr(rng) @ np.diag([1, rng.uniform(0.05, 1), 10 ** rng.uniform(-7, -3)]) @ _qr(rng)
                                   for _ in range(n(200))])
    out = []
    for _ in range(n(200)):  # a complex pair at arg pi - delta: a direction almost reversed
        dl = 10 ** rng.uniform(-6, -1.5)
        B = np.zeros((3, 3))
        B[:2, :2] = rng.uniform(0.3, 3) * np.array([[np.cos(np.pi - dl), -np.sin(np.pi - dl)],
                                                    [np.sin(np.pi - dl), np.cos(np.pi - dl)]])
        B[2, 2] = rng.uniform(0.05, 3)
        P = np.eye(3) + 0.3 * rng.normal(size=(3, 3))
        out.append(P @ B @ np.linalg.inv(P))
    F["nearly_reversing"] = np.array(out)
    F["rotation_pi/2"] = np.array([_rot(rng.normal(size=3), np.pi / 2 + rng.uniform(-0.05, 0.05))
                                   @ np.diag(rng.uniform(0.3, 2, 3)) for _ in range(n(200))])
    out = []
    for _ in range(n(200)):
        B = np.zeros((3, 3))
        B[:2, :2] = np.eye(2) + 0.5 * rng.normal(size=(2, 2))
        B[2, 2] = rng.uniform(0.1, 3)
        Q = _qr(rng)
        out.append(Q @ B @ Q.T)
    F["block_planar"] = np.array(out)
    out = []
    for _ in range(n(300)):  # P1-sized lever: shaft 0.32 m, port estimate off by up to a few cm
        p = np.array([0.0, 0.16, 0.0])
        w = p + rng.normal(size=3) * 0.1 - np.array([0, 0.12, 0])
        ph = p + rng.normal(size=3) * rng.choice([0.002, 0.02, 0.05])
        out.append(lever_jacobian3(w, p, 0.32) @ np.linalg.inv(lever_jacobian3(w, ph, 0.32)))
    F["lever"] = np.array(out)
    F["scale_1e150"] = rng.normal(size=(n(100), 3, 3)) * 1e150
    F["scale_1e-150"] = (np.eye(3) + 0.5 * rng.normal(size=(n(100), 3, 3))) * 1e-150
    F["orthogonal+1e-7"] = np.array([_qr(rng) + 1e-7 * rng.normal(size=(3, 3)) for _ in range(n(100))])
    F["non_normal"] = np.array([np.triu(rng.normal(size=(3, 3)) * 10 ** rng.uniform(0, 2), 1)
                                + np.diag(rng.uniform(0.1, 1, 3)) for _ in range(n(200))])
    B0 = np.array([[-1.6457, -8.4708, -2.5913], [8.2146, -7.2761, -1.4779], [-4.6366, 2.9221, 0.5569]])
    F["two_maxima"] = np.array([B0 + 0.3 * rng.normal(size=(3, 3)) for _ in range(n(100))])
    return {k: np.ascontiguousarray(v) for k, v in F.items()}


def _phi_p(Ms):
    """``(phi_max3, angle attained by p_phi3 (numpy), p_phi3)``. (Through metrics' loops, which
    live in linalg.py: a cached njit function here would not be recompiled when linalg changes.)"""
    d = m.p_phi(Ms)
    Md = np.einsum("nij,nj->ni", Ms, d)
    attained = np.arctan2(np.linalg.norm(np.cross(d, Md), axis=-1), np.einsum("ni,ni->n", d, Md))
    return m.phi_max(Ms), attained, d


@pytest.fixture(scope="module")
def fam():
    return families(np.random.default_rng(20240607))


# ----------------------------------------------------------------------------- inverses, products
def test_inverses_and_products_vs_numpy():
    rng = np.random.default_rng(1)
    A3 = rng.normal(size=(500, 3, 3))
    A2 = rng.normal(size=(500, 2, 2))
    out3, out2, P = np.empty((3, 3)), np.empty((2, 2)), np.empty((3, 3))
    for A, B in zip(A3, A3[::-1]):
        det = L.inv3(A, out3)
        assert det == pytest.approx(np.linalg.det(A), rel=1e-12, abs=1e-14)
        np.testing.assert_allclose(out3, np.linalg.inv(A), rtol=1e-9, atol=1e-12)
        L.matmul3(A, B, P)
        np.testing.assert_allclose(P, A @ B, rtol=1e-14, atol=1e-14)
    for A in A2:
        det = L.inv2(A, out2)
        assert det == pytest.approx(np.linalg.det(A), rel=1e-12, abs=1e-14)
        np.testing.assert_allclose(out2, np.linalg.inv(A), rtol=1e-9, atol=1e-12)


def test_singular_flags_and_nan_not_inf():
    out = np.empty((3, 3))
    rank2 = np.array([[1.0, 2, 3], [4, 5, 6], [7, 8, 9]])          # exactly singular in exact arithmetic
    zero = np.zeros((3, 3))
    near = np.diag([1.0, 1.0, 1e-13])
    ok = np.diag([1.0, 2.0, 3.0])
    for A, want in ((rank2, True), (zero, True), (near, True), (ok, False), (np.diag([1.0, 1, 1e-9]), False)):
        det = L.inv3(A, out)
        assert L.singular3(A, det, 1e-12) is want
        assert not np.isinf(out).any()
    assert L.inv3(zero, out) == 0.0 and np.isnan(out).all()
    nan = np.full((3, 3), np.nan)
    assert L.singular3(nan, L.inv3(nan, out), 1e-12)
    out2 = np.empty((2, 2))
    S2 = np.array([[1.0, 2.0], [2.0, 4.0]])
    assert L.singular2(S2, L.inv2(S2, out2), 1e-12) and np.isnan(out2).all()
    assert not L.singular2(np.eye(2), L.inv2(np.eye(2), out2), 1e-12)
    # the same test as metrics.inv2 (|det| <= rcond ||A||_F^2)
    rng = np.random.default_rng(2)
    A = rng.normal(size=(300, 2, 2)) * np.stack([np.ones(300), 10 ** rng.uniform(-18, -10, 300)], 1)[:, :, None]
    _, sing = m.inv2(A, 1e-14)
    assert [L.singular2(a, L.inv2(a, out2), 1e-14) for a in A] == sing.tolist() and 0 < sing.sum() < 300


# ----------------------------------------------------------------------------- singular values
def _adversarial_3x3(rng):
    mats = [rng.normal(size=(3, 3)) for _ in range(300)]
    mats += [np.eye(3) + eps * rng.normal(size=(3, 3)) for eps in (1e-3, 1e-8, 1e-13) for _ in range(50)]
    for s in ([1, 1, 1], [2, 2, 1], [2, 1, 1], [1, 1, 1e-9], [3, 3, 0], [1, 0, 0], [1, 1 - 1e-9, 0.5],
              [1, 1 - 1e-15, 0.2], [1e-5, 1e-5, 1]):
        for _ in range(30):
            mats.append(_qr(rng) @ np.diag(s) @ _qr(rng))
    mats += [np.outer(rng.normal(size=3), rng.normal(size=3)) for _ in range(50)]    # rank 1
    mats += [rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-150, 150) for _ in range(100)]
    mats += [np.zeros((3, 3)), np.eye(3), -np.eye(3), np.diag([1e300, 1, 1e-300])]
    return np.array(mats)


def test_sigma_max3_vs_svd_adversarial():
    A = _adversarial_3x3(np.random.default_rng(3))
    got = np.array([L.sigma_max3(a) for a in A])
    want = np.linalg.svd(A, compute_uv=False)[:, 0]
    rel = np.abs(got - want) / np.where(want > 0, want, 1.0)
    assert np.all(np.isfinite(got))
    assert rel.max() < 1e-12, rel.max()


def test_sigma_max2_and_g_norms_vs_svd():
    rng = np.random.default_rng(4)
    A2 = np.concatenate([rng.normal(size=(500, 2, 2)),
                         np.array([_qr(rng)[:2, :2] * 0 + np.eye(2) * c for c in (1.0, 1e-200, 1e200)]),
                         np.array([[[1.0, 1e-9], [0.0, 1.0]], [[1.0, 0.0], [0.0, 1.0 + 1e-12]]])])
    want = np.linalg.svd(A2, compute_uv=False)[:, 0]
    got = np.array([L.sigma_max2(a) for a in A2])
    np.testing.assert_allclose(got, want, rtol=1e-13)
    M3 = np.concatenate([np.eye(3) + 0.3 * rng.normal(size=(300, 3, 3)), rng.normal(size=(300, 3, 3))])
    k = rng.uniform(0.01, 3, len(M3))
    want3 = np.linalg.svd(np.eye(3) - k[:, None, None] * M3, compute_uv=False)[:, 0]
    got3 = np.array([L.g_norm3(a, kk) for a, kk in zip(M3, k)])
    np.testing.assert_allclose(got3, want3, rtol=1e-12)
    M2 = M3[:, :2, :2]
    want2 = np.linalg.svd(np.eye(2) - k[:, None, None] * M2, compute_uv=False)[:, 0]
    np.testing.assert_allclose([L.g_norm2(a, kk) for a, kk in zip(M2, k)], want2, rtol=1e-12)
    # the planar kernel is the metrics closed form
    np.testing.assert_allclose([L.g_norm2(a, kk) for a, kk in zip(M2, k)], m.g_norm(M2, k), rtol=1e-15)


def test_v_sigma3_attains_the_norm():
    A = _adversarial_3x3(np.random.default_rng(5))
    A = A[np.abs(A).max(axis=(1, 2)) < 1e100]
    v = np.empty(3)
    for a in A:
        s = L.v_sigma3(a, v)
        assert np.linalg.norm(v) == pytest.approx(1.0, abs=1e-12)
        want = np.linalg.svd(a, compute_uv=False)[0]
        assert s == pytest.approx(want, rel=1e-12, abs=1e-300)
        assert np.linalg.norm(a @ v) == pytest.approx(want, rel=1e-10, abs=1e-300)


# ----------------------------------------------------------------------------- |phi_max|
def test_phi_max2_kernel_is_the_planar_closed_form():
    rng = np.random.default_rng(6)
    M = np.concatenate([rng.normal(size=(3000, 2, 2)), np.eye(2) + 0.3 * rng.normal(size=(3000, 2, 2)),
                        np.zeros((1, 2, 2)), -np.eye(2)[None]])
    got = np.array([L.phi_max2(a) for a in M])
    # the same formula; numpy's and libm's asin/atan2 differ in the last ulp
    np.testing.assert_allclose(got, m.phi_max(M), rtol=0, atol=1e-14)
    assert np.array_equal(got == np.pi, m.phi_max(M) == np.pi)


@pytest.mark.slow
def test_phi_max3_vs_dense_search(fam):
    """Exact to the brute force on 2400 matrices (14 families), and never above what its own
    direction attains: the value is attained (not too high) and no search finds more (not too low)."""
    report = []
    errs = []
    for name, Ms in fam.items():
        v, attained, _ = _phi_p(Ms)
        ref = dense_phi_max3(Ms)
        err = v - ref
        errs.append(err)
        report.append(f"{name:17s} n={len(Ms):3d}  max|phi - search| = {np.abs(err).max():.1e}  "
                      f"max(phi - attained) = {np.max(v - attained):.1e}")
        assert np.all(np.isfinite(v)), name
        assert np.all(ref <= v + 1e-9), (name, np.max(ref - v))           # the search never finds more
        assert np.all(attained >= v - 1e-9), (name, np.max(v - attained))  # p_phi3 attains the value
    err = np.abs(np.concatenate(errs))
    print("\n" + "\n".join(report) + f"\nall {len(err)}: max |error| {err.max():.2e}, "
          f"99th percentile {np.quantile(err, 0.99):.1e}")
    assert len(err) >= 2000
    assert err.max() < 1e-4                       # the requirement
    assert err.max() < 1e-9                       # and what it achieves (1.0e-12 when written)
    assert np.quantile(err, 0.99) < 1e-12


def test_p_phi3_attains_and_is_unit(fam):
    for name in ("normal", "near_id_0.3", "lever", "nearly_reversing"):
        Ms = fam[name]
        v, attained, d = _phi_p(Ms)
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(attained, v, atol=1e-9)
        np.testing.assert_allclose(m.phi_of_direction(Ms, d), attained, atol=1e-12)


def test_value_bounds_every_direction(fam):
    """No direction turns more than phi_max3 (a cheap global check on random directions)."""
    rng = np.random.default_rng(7)
    X = rng.normal(size=(4000, 3))
    X /= np.linalg.norm(X, axis=1)[:, None]
    for Ms in fam.values():
        v = m.phi_max(Ms)
        Y = np.einsum("nij,sj->nsi", Ms, X)
        ang = np.arctan2(np.linalg.norm(np.cross(X[None], Y), axis=-1), np.einsum("si,nsi->ns", X, Y))
        assert np.all(ang.max(axis=1) <= v + 1e-12)


def _blockdiag(M2, c):
    M = np.zeros((3, 3))
    M[:2, :2] = M2
    M[2, 2] = c
    return M


def test_planar_embedding():
    """blockdiag(M2, c): the third axis maps to c times itself (angle 0). While c does not
    dominate, i.e. c / |M2 p| lies in [tan(pi/4 - phi/2), tan(pi/4 + phi/2)] (p = p_phi(M2),
    phi = phi_max(M2) <= pi/2), the 3-D value is the planar one; beyond, mixing in the axis turns
    motions further (e.g. M2 = I, c = 2: a symmetric map with eigenvalues 1, 2). Obtuse planar
    maps never gain."""
    rng = np.random.default_rng(8)
    checked = 0
    beyond = []
    for M2 in np.concatenate([np.eye(2) + 0.4 * rng.normal(size=(400, 2, 2)), rng.normal(size=(200, 2, 2))]):
        phi2 = float(m.phi_max(M2))
        if phi2 == np.pi:
            continue
        r = np.linalg.norm(M2 @ m.p_phi(M2))
        if phi2 <= np.pi / 2:
            lo, hi = r * np.tan(np.pi / 4 - phi2 / 2), r * np.tan(np.pi / 4 + phi2 / 2)
            cs = [r, lo + (hi - lo) * rng.uniform(0.01, 0.99)]
        else:
            cs = [r * 10 ** rng.uniform(-3, 3)]
        for c in cs:
            Q = _qr(rng)
            for M3 in (_blockdiag(M2, c), Q @ _blockdiag(M2, c) @ Q.T):
                assert L.phi_max3(M3) == pytest.approx(L.phi_max2(M2), abs=1e-11)
                checked += 1
        if phi2 <= np.pi / 2:
            beyond.append(_blockdiag(M2, hi * rng.uniform(1.2, 3)))
            beyond.append(_blockdiag(M2, lo / rng.uniform(1.2, 3)))
    assert checked > 1000
    beyond = np.array(beyond[:200])
    p3 = m.phi_max(beyond)
    p2 = m.phi_max(beyond[:, :2, :2])
    assert np.all(p3 > p2 + 1e-6)
    np.testing.assert_allclose(p3, dense_phi_max3(beyond, npts=20_000), atol=1e-9)
    assert L.phi_max3(_blockdiag(np.eye(2), 2.0)) == pytest.approx(np.arcsin(1 / 3))


def test_invariances(fam):
    """Rotations (R M R^T), positive scale (s M) and inversion (v -> M v is w -> M^-1 w backwards)
    leave |phi_max| unchanged: three different numerical paths to the same number."""
    rng = np.random.default_rng(9)
    Ms = np.concatenate([fam["normal"], fam["near_id_0.3"], fam["lever"], fam["non_normal"][:50],
                         fam["rotation_pi/2"][:50]])
    v = m.phi_max(Ms)
    R = np.array([_qr(rng) for _ in Ms])
    R *= np.sign(np.linalg.det(R))[:, None, None]
    np.testing.assert_allclose(m.phi_max(R @ Ms @ np.swapaxes(R, 1, 2)), v, atol=1e-9)
    s = 10.0 ** rng.uniform(-100, 100, len(Ms))
    np.testing.assert_allclose(m.phi_max(s[:, None, None] * Ms), v, atol=1e-12)
    ok = v < np.pi
    np.testing.assert_allclose(m.phi_max(np.linalg.inv(Ms[ok])), v[ok], atol=1e-8)


def test_reversal_is_pi_exactly():
    """A real eigenvalue <= 0 reverses (or annihilates) a direction: pi exactly, with p_phi3 an
    eigenvector; a complex pair close to the negative axis only comes close to pi."""
    rng = np.random.default_rng(10)
    d = np.empty(3)
    for _ in range(300):
        P = np.eye(3) + 0.5 * rng.normal(size=(3, 3))
        ev = [-rng.uniform(0.01, 2), rng.uniform(-2, 2), rng.uniform(0.1, 2)]   # det of either sign
        M = P @ np.diag(ev) @ np.linalg.inv(P)
        assert L.phi_max3(M) == np.pi
        assert L.p_phi3(M, d) == np.pi
        assert (M @ d) @ d < 0 and np.linalg.norm(np.cross(M @ d, d)) < 1e-6 * np.linalg.norm(M @ d)
        M2 = P @ np.diag([-rng.uniform(0.1, 2), -rng.uniform(0.1, 2), rng.uniform(0.1, 2)]) @ np.linalg.inv(P)
        assert np.linalg.det(M2) > 0 and L.phi_max3(M2) == np.pi    # two negative eigenvalues, det > 0
    for M in (np.zeros((3, 3)), np.diag([1.0, 1.0, 0.0]), np.outer([1.0, 2, 3], [0.5, -1, 2]),
              -np.eye(3), np.diag([1.0, -1e-300, 1.0])):
        assert L.phi_max3(M) == np.pi
    for delta in (1e-2, 1e-4, 1e-6):
        B = _blockdiag(np.array([[np.cos(np.pi - delta), -np.sin(np.pi - delta)],
                                 [np.sin(np.pi - delta), np.cos(np.pi - delta)]]), 1.0)
        assert L.phi_max3(B) == pytest.approx(np.pi - delta, abs=1e-12)


def test_nonfinite_input_gives_nan():
    out = np.empty(3)
    for bad in (np.nan, np.inf, -np.inf):
        M = np.eye(3)
        M[1, 2] = bad
        assert np.isnan(L.phi_max3(M)) and np.isnan(L.sigma_max3(M)) and np.isnan(L.g_norm3(M, 0.5))
        assert np.isnan(L.p_phi3(M, out)) and np.isnan(out).all()
        assert np.isnan(L.v_sigma3(M, out)) and np.isnan(out).all()


# ----------------------------------------------------------------------------- best gain
def _dense_rho(Ms, ks):
    """``max_i ||I - k M_i||`` for each ``k`` (numpy SVD)."""
    G = np.eye(3) - np.asarray(ks, float)[:, None, None, None] * Ms[None]
    return np.linalg.svd(G, compute_uv=False)[..., 0].max(axis=1)


def test_min_over_gain3_vs_dense_gain_search():
    rng = np.random.default_rng(11)
    out = np.empty(2)
    for trial in range(40):
        m_ = rng.integers(1, 9)
        Ms = np.eye(3) + rng.uniform(0.05, 0.5) * rng.normal(size=(m_, 3, 3))
        rho = L.min_over_gain3(Ms, m_, out)
        assert rho == out[0]
        if rho == 1.0:
            assert out[1] == 0.0
            ks = np.linspace(1e-4, 3, 3001)
            assert _dense_rho(Ms, ks).min() >= 1.0 - 1e-12
            continue
        ks = np.linspace(0, 2 * out[1], 4001)
        dense = _dense_rho(Ms, ks).min()
        assert rho <= dense + 1e-12                               # no grid gain does better
        assert rho == pytest.approx(_dense_rho(Ms, [out[1]])[0], abs=1e-14)
        assert dense - rho < 1e-5                                 # the grid is that coarse
        kf = np.linspace(out[1] - 1e-6, out[1] + 1e-6, 201)       # and a fine grid around k*
        assert rho <= _dense_rho(Ms, kf).min() + 1e-12


def test_min_over_gain3_conventions():
    out = np.empty(2)
    R = _rot([0, 0, 1], 2.0)                                   # turns by 115 deg: no gain contracts
    Ms = np.stack([np.eye(3), R])
    assert L.min_over_gain3(Ms, 2, out) == 1.0 and out[1] == 0.0
    Ms = np.stack([np.eye(3) * 2.0, np.full((3, 3), np.nan)])
    assert L.min_over_gain3(Ms, 1, out) == pytest.approx(0.0, abs=1e-12)   # only the first m count
    assert out[1] == pytest.approx(0.5)
    # a non-finite matrix counts as M = 0 (||I - k 0|| = 1), as in the planar search: no gain
    assert L.min_over_gain3(Ms, 2, out) == 1.0 and out[1] == 0.0
    assert L.min_over_gain3(Ms, 0, out) == 1.0 and out[1] == 0.0


# ----------------------------------------------------------------------------- no allocation
def test_kernels_do_not_allocate_per_call(tmp_path):
    """From inside a compiled loop the kernels allocate nothing: the NRT allocation count of a
    loop over 5 matrices equals that over 200 (only the call's own argument wrappers)."""
    code = textwrap.dedent("""
        import numpy as np
        from numba import njit
        from numba.core.runtime import rtsys
        from errplan import linalg as L

        @njit
        def loop(Ms, n, v, inv, g, o2):
            acc = 0.0
            for i in range(n):
                M = Ms[i]
                acc += L.phi_max3(M) + L.g_norm3(M, 0.5) + L.sigma_max3(M) + L.p_phi3(M, v)
                acc += L.v_sigma3(M, v) + L.inv3(M, inv) + L.singular3(M, 1.0, 1e-12)
                acc += L.min_over_gain3(Ms[i:], 3, g) + L.phi_max2(M[:2, :2]) + L.inv2(M[:2, :2], o2)
                acc += L.g_norm2(M[:2, :2], 0.5) + L.sigma_max2(M[:2, :2])
                L.matmul3(M, M, inv)
            return acc

        rng = np.random.default_rng(0)
        Ms = np.concatenate([rng.normal(size=(100, 3, 3)), np.eye(3) + 0.3 * rng.normal(size=(103, 3, 3))])
        args = (np.empty(3), np.empty((3, 3)), np.empty(2), np.empty((2, 2)))
        loop(Ms, 5, *args)
        a0 = rtsys.get_allocation_stats().alloc
        loop(Ms, 5, *args)
        a1 = rtsys.get_allocation_stats().alloc
        loop(Ms, 200, *args)
        a2 = rtsys.get_allocation_stats().alloc
        print(a1 - a0, a2 - a1)
    """)
    env = dict(os.environ, NUMBA_NRT_STATS="1")
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600,
                         check=False)
    assert res.returncode == 0, res.stderr[-2000:]
    few, many = map(int, res.stdout.split())
    assert few == many
