"""Metrics of P1 Sec. II-B: closed forms against numpy's SVD, a dense direction search of eq. (9),
and the properties the papers state (phi_hat_max bounds |phi_max| where ||G|| <= 1, |phi_max| does
not depend on k, v_sigma and p_phi attain their maxima)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from errplan import metrics as m


def dense_phi_max(M: np.ndarray, n: int = 180, stages: int = 7) -> np.ndarray:
    """max over unit v of |angle(v, M v)| by brute force: n directions over [0, pi), then local
    refinement (21 points, step / 10 each stage) around the peaks of |phi| and of +-phi."""
    def phis(s):
        c, sn = np.cos(s), np.sin(s)
        u0 = M[..., 0, 0, None] * c + M[..., 0, 1, None] * sn
        u1 = M[..., 1, 0, None] * c + M[..., 1, 1, None] * sn
        return np.arctan2(c * u1 - sn * u0, c * u0 + sn * u1)

    s = np.linspace(0, np.pi, n, endpoint=False)
    ph = phis(np.broadcast_to(s, M.shape[:-2] + (n,)))
    best = np.abs(ph).max(-1)
    for i in (np.argmax(np.abs(ph), -1), np.argmax(ph, -1), np.argmin(ph, -1)):
        c, h = s[i], np.pi / n
        for _ in range(stages):
            sf = c[..., None] + np.linspace(-h, h, 21)
            pf = np.abs(phis(sf))
            j = np.argmax(pf, -1)
            best = np.maximum(best, np.take_along_axis(pf, j[..., None], -1)[..., 0])
            c, h = np.take_along_axis(sf, j[..., None], -1)[..., 0], h / 10
    return best


@pytest.fixture(scope="module")
def mats():
    rng = np.random.default_rng(20040426)
    M = rng.normal(size=(6000, 2, 2))
    # plus near-identity maps (the realistic motion maps J Jhat^-1) and pure rotations/scalings
    M2 = np.eye(2) + 0.3 * rng.normal(size=(3000, 2, 2))
    ang = rng.uniform(-np.pi, np.pi, 500)
    R = np.stack([np.stack([np.cos(ang), -np.sin(ang)], -1), np.stack([np.sin(ang), np.cos(ang)], -1)], -2)
    return np.concatenate([M, M2, R * rng.uniform(0.2, 3, (500, 1, 1))])


def _nondegenerate(M, rel=1e-3):
    det = np.linalg.det(M)
    return np.abs(det) > rel * np.einsum("...ij,...ij->...", M, M)


def test_phi_max_closed_form_vs_dense_search(mats):
    closed = m.phi_max(mats)
    dense = dense_phi_max(mats)
    ok = _nondegenerate(mats)
    assert ok.mean() > 0.99
    # the search is a lower bound that converges to the closed form
    assert np.all(dense <= closed + 1e-12)
    assert np.max(closed[ok] - dense[ok]) < 1e-6
    # near-degenerate maps (|det| tiny: the reversal peak is razor sharp) still within 1e-4
    assert np.max(closed - dense) < 1e-4
    # both regimes occur: motions that can be reversed (pi) and those that cannot
    assert np.mean(closed == np.pi) > 0.05 and np.mean(closed < np.pi / 2) > 0.3


def test_phi_max_known_cases():
    th = 0.3
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    assert m.phi_max(R) == pytest.approx(th)                       # a rotation turns every motion by th
    assert m.phi_max(np.diag([2.0, 0.5])) == pytest.approx(np.arcsin(0.6))  # asin((a-b)/(a+b))
    assert m.phi_max(np.diag([1.0, -1.0])) == pytest.approx(np.pi)  # a reflection reverses some motion
    assert m.phi_max(np.eye(2) * 3.0) == 0.0
    assert m.phi_max(np.zeros((2, 2))) == np.pi                    # no motion: treated as worst


def test_g_norm_and_spectral_norm_vs_svd(mats):
    rng = np.random.default_rng(1)
    k = rng.uniform(0.01, 3.0, len(mats))
    G = m.G_matrix(mats, k)
    svd = np.linalg.svd(G, compute_uv=False)[..., 0]
    assert np.allclose(m.g_norm(mats, k), svd, rtol=1e-12, atol=1e-12)
    assert np.allclose(np.linalg.norm(G, 2, axis=(-2, -1)), svd)
    assert np.allclose(m.spectral_norm(mats), np.linalg.svd(mats, compute_uv=False)[..., 0], rtol=1e-12)
    mu, nu = m.conformal_parts(mats)
    assert np.allclose(m.g_norm_from_parts(mu, nu, k), svd, rtol=1e-12, atol=1e-12)
    # smallest singular value: ||mu| - |nu||
    assert np.allclose(np.abs(np.abs(mu) - np.abs(nu)), np.linalg.svd(mats, compute_uv=False)[..., 1], atol=1e-12)


def test_parts_algebra(mats):
    A, B = mats[:1000], mats[1000:2000]
    mu1, nu1 = m.conformal_parts(A)
    mu2, nu2 = m.conformal_parts(B)
    mu, nu = m.compose_parts(mu1, nu1, mu2, nu2)
    mu_ref, nu_ref = m.conformal_parts(A @ B)
    assert np.allclose(mu, mu_ref) and np.allclose(nu, nu_ref)
    imu, inu, sing = m.inverse_parts(mu1, nu1)
    assert not sing.any()
    mu_i, nu_i = m.conformal_parts(np.linalg.inv(A))
    assert np.allclose(imu, mu_i) and np.allclose(inu, nu_i)
    inv, sing = m.inv2(A)
    assert np.allclose(inv, np.linalg.inv(A)) and not sing.any()


def test_singular_matrices_give_nan_not_inf():
    S = np.array([[[1.0, 2.0], [2.0, 4.0]], [[0.0, 0.0], [0.0, 0.0]], [[1.0, 0.0], [0.0, 1.0]]])
    inv, sing = m.inv2(S)
    assert sing.tolist() == [True, True, False]
    assert np.isnan(inv[:2]).all() and np.isfinite(inv[2]).all()
    mu, nu = m.conformal_parts(S)
    imu, inu, sing2 = m.inverse_parts(mu, nu)
    assert sing2.tolist() == [True, True, False] and np.isnan(imu[:2]).all()
    M, sing3 = m.motion_map(np.broadcast_to(np.eye(2), S.shape), S)
    assert sing3.tolist() == [True, True, False] and not np.isinf(M).any()


def test_v_sigma_attains_the_norm(mats):
    rng = np.random.default_rng(2)
    G = m.G_matrix(mats, rng.uniform(0.1, 2.0, len(mats)))
    v = m.v_sigma(G)
    assert np.allclose(np.linalg.norm(v, axis=-1), 1.0)
    Gv = np.linalg.norm(np.einsum("...ij,...j->...i", G, v), axis=-1)
    assert np.allclose(Gv, np.linalg.svd(G, compute_uv=False)[..., 0], rtol=1e-10, atol=1e-12)


def test_p_phi_attains_phi_max(mats):
    v = m.p_phi(mats)
    assert np.allclose(np.linalg.norm(v, axis=-1), 1.0)
    got = np.abs(m.phi_of_direction(mats, v))
    want = m.phi_max(mats)
    ok = _nondegenerate(mats)
    assert np.max(np.abs(got - want)[ok]) < 1e-9
    # reversal (phi_max = pi): M p_phi points against p_phi
    rev = ok & (want == np.pi)
    Mv = np.einsum("...ij,...j->...i", mats[rev], v[rev])
    assert rev.sum() > 50 and np.all(np.einsum("...i,...i->...", Mv, v[rev]) < 0)


def test_phi_hat_max_shape():
    g = np.array([0.0, 0.5, 1.0, 1.0 + 1e-12, 2.0, 1e9])
    ph = m.phi_hat_max(g)
    assert ph[0] == 0.0 and ph[1] == pytest.approx(np.arcsin(0.5))
    assert ph[2] == pytest.approx(np.pi / 2) and ph[3] == pytest.approx(np.pi / 2)  # continuous at 1
    assert ph[4] == pytest.approx(np.pi - np.arcsin(0.5))
    assert ph[5] == pytest.approx(np.pi, abs=1e-8)
    assert np.all(np.diff(m.phi_hat_max(np.linspace(0, 50, 5001))) >= 0)  # monotone


mat2 = arrays(np.float64, (2, 2), elements=st.floats(-3, 3, allow_nan=False, allow_infinity=False))


@settings(max_examples=300, deadline=None)
@given(mat2, st.floats(0.01, 3.0))
def test_phi_hat_max_bounds_phi_max_where_contracting(M, k):
    """P1 eq. (10): where ||G|| <= 1, phi_hat_max = asin(||G||) >= |phi_max| (a true bound)."""
    gn = float(m.g_norm(M, k))
    if gn <= 1.0 and abs(np.linalg.det(M)) > 1e-9:
        assert float(m.phi_hat_max(gn)) >= float(m.phi_max(M)) - 1e-12


@settings(max_examples=200, deadline=None)
@given(mat2, st.floats(0.01, 100.0))
def test_phi_max_does_not_depend_on_gain(M, k):
    if abs(np.linalg.det(M)) > 1e-6 * float(np.sum(M * M)):  # away from rank-deficient maps
        assert float(m.phi_max(k * M)) == pytest.approx(float(m.phi_max(M)), abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(mat2)
def test_phi_max_matches_search_property(M):
    if abs(np.linalg.det(M)) > 1e-3 * float(np.sum(M * M)):
        assert float(m.phi_max(M)) == pytest.approx(float(dense_phi_max(M[None])[0]), abs=1e-6)


def test_eq9_as_printed_with_g():
    """P1 eq. (9) literally: |phi_max| = max over unit v of acos(v^T (v - u) / |v - u|), u = G v,
    G = I - k M, on 3600 directions x 3 gains; equals the closed form to the search's resolution
    (1e-4 rad where the peak is smooth, 2e-2 rad at a reversal)."""
    rng = np.random.default_rng(9)
    M = np.eye(2) + 0.4 * rng.normal(size=(300, 2, 2))
    M = M[_nondegenerate(M, 1e-2)]
    s = np.linspace(0, 2 * np.pi, 3600, endpoint=False)
    V = np.stack([np.cos(s), np.sin(s)], -1)
    for k in (0.3, 1.0, 2.5):
        G = m.G_matrix(M, np.full(len(M), k))
        U = np.einsum("nij,sj->nsi", G, V)
        D = V[None] - U
        eq9 = np.arccos(np.clip(np.einsum("si,nsi->ns", V, D) / np.linalg.norm(D, axis=-1), -1, 1)).max(axis=1)
        closed = m.phi_max(M)
        assert np.all(eq9 <= closed + 1e-9)
        smooth = closed < 3.0  # a reversal (pi) is a kink of the angle: first-order search error
        assert smooth.mean() > 0.8 and np.max((closed - eq9)[smooth]) < 1e-4
        assert np.max(closed - eq9) < 2e-2
