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
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # hypothesis draws extreme entries
        det = np.linalg.det(M)
    if abs(det) > 1e-6 * float(np.sum(M * M)):  # away from rank-deficient maps
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


# ----------------------------------------------------------------------------- 3-D (d = 3)
def _rot3(axis, th):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


@pytest.fixture(scope="module")
def mats3():
    rng = np.random.default_rng(3003)
    return np.concatenate([rng.normal(size=(400, 3, 3)), np.eye(3) + 0.3 * rng.normal(size=(600, 3, 3))])


@pytest.mark.parametrize("batch", [(), (5,), (4, 6)])
def test_3d_batch_shapes(batch):
    rng = np.random.default_rng(len(batch))
    M = np.eye(3) + 0.3 * rng.normal(size=batch + (3, 3))
    k = rng.uniform(0.2, 1.5, size=batch)
    v = rng.normal(size=batch + (3,))
    assert m.phi_max(M).shape == batch
    assert m.g_norm(M, k).shape == batch and m.g_norm(M, 0.7).shape == batch
    assert m.spectral_norm(M).shape == batch
    assert m.p_phi(M).shape == batch + (3,) and m.v_sigma(m.G_matrix(M, k)).shape == batch + (3,)
    assert m.G_matrix(M, k).shape == batch + (3, 3)
    assert m.phi_of_direction(M, v).shape == batch
    inv, sing = m.inv(M)
    assert inv.shape == batch + (3, 3) and sing.shape == batch
    Mm, sing = m.motion_map(M, M)
    assert Mm.shape == batch + (3, 3) and sing.shape == batch
    np.testing.assert_allclose(Mm, np.broadcast_to(np.eye(3), Mm.shape), atol=1e-12)
    rho, ks = m.min_over_gain(np.stack([M, M @ M], axis=-3))
    assert rho.shape == batch and ks.shape == batch
    # every batch element equals the unbatched call
    flat = M.reshape(-1, 3, 3)
    np.testing.assert_array_equal(m.phi_max(M).reshape(-1), [m.phi_max(a) for a in flat])
    np.testing.assert_array_equal(m.g_norm(M, k).reshape(-1), [m.g_norm(a, kk) for a, kk in zip(flat, k.reshape(-1))])


def test_3d_norms_inverse_and_vectors_vs_numpy(mats3):
    rng = np.random.default_rng(5)
    k = rng.uniform(0.01, 3.0, len(mats3))
    G = m.G_matrix(mats3, k)
    np.testing.assert_array_equal(G, np.eye(3) - k[:, None, None] * mats3)
    svd = np.linalg.svd(G, compute_uv=False)[:, 0]
    np.testing.assert_allclose(m.g_norm(mats3, k), svd, rtol=1e-12)
    np.testing.assert_allclose(m.spectral_norm(mats3), np.linalg.svd(mats3, compute_uv=False)[:, 0], rtol=1e-12)
    inv, sing = m.inv(mats3)
    assert not sing.any()
    np.testing.assert_allclose(inv, np.linalg.inv(mats3), rtol=1e-9, atol=1e-11)
    vs = m.v_sigma(G)
    np.testing.assert_allclose(np.linalg.norm(vs, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(np.einsum("nij,nj->ni", G, vs), axis=-1), svd, rtol=1e-10)
    # phi_of_direction in 3-D: the unsigned angle between v and M v
    v = rng.normal(size=(len(mats3), 3))
    Mv = np.einsum("nij,nj->ni", mats3, v)
    cosang = np.einsum("ni,ni->n", v, Mv) / np.linalg.norm(v, axis=-1) / np.linalg.norm(Mv, axis=-1)
    np.testing.assert_allclose(m.phi_of_direction(mats3, v), np.arccos(np.clip(cosang, -1, 1)), atol=1e-7)


def test_3d_singular_inverse_masks_nan_not_inf():
    S = np.array([np.diag([1.0, 2.0, 0.0]), np.zeros((3, 3)), np.outer([1.0, 2, 3], [1.0, 0, 1]),
                  np.diag([1.0, 1.0, 1e-14]), np.eye(3), np.full((3, 3), np.nan)])
    inv, sing = m.inv(S)
    assert sing.tolist() == [True, True, True, True, False, True]
    assert np.isnan(inv[sing]).all() and np.isfinite(inv[~sing]).all() and not np.isinf(inv).any()
    M, sing2 = m.motion_map(np.broadcast_to(np.eye(3), S.shape), S)
    assert sing2.tolist() == sing.tolist() and not np.isinf(M).any() and np.isnan(M[sing]).all()
    # the threshold is relative: |det| <= rcond ||A||_F^3, so scale does not matter
    A = np.diag([1.0, 1.0, 1e-9])
    assert not m.inv(A)[1] and not m.inv(1e-100 * A)[1] and m.inv(A, rcond=1e-8)[1]
    # metrics of singular and non-finite maps: pi for an annihilated motion, NaN for NaN
    assert m.phi_max(np.diag([1.0, 1.0, 0.0])) == np.pi
    bad = np.eye(3)
    bad[0, 1] = np.nan
    assert np.isnan(m.phi_max(bad)) and np.isnan(m.g_norm(bad, 0.5)) and np.isnan(m.p_phi(bad)).all()


def test_3d_phi_max_known_cases():
    th = 0.3
    assert m.phi_max(_rot3([1, 2, 3], th)) == pytest.approx(th, abs=1e-12)   # a rotation turns every motion by <= th
    assert m.phi_max(np.diag([2.0, 0.5, 1.0])) == pytest.approx(np.arcsin(0.6), abs=1e-12)  # extreme eigenvalues
    assert m.phi_max(np.diag([1.0, 1.0, -1.0])) == np.pi                      # a reflection reverses a motion
    assert m.phi_max(np.eye(3) * 3.0) == 0.0
    assert m.phi_max(np.zeros((3, 3))) == np.pi
    # a 2x2 block with the third axis mapped to 1 x itself keeps the planar value
    M2 = np.array([[1.1, -0.3], [0.2, 0.9]])
    M3 = np.eye(3)
    M3[:2, :2] = M2
    assert m.phi_max(M3) == pytest.approx(float(m.phi_max(M2)), abs=1e-12)


def test_3d_phi_max_vs_direction_search(mats3):
    """phi_max is attained by p_phi and no direction of a dense sphere sample exceeds it."""
    v = m.phi_max(mats3)
    p = m.p_phi(mats3)
    np.testing.assert_allclose(np.linalg.norm(p, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(m.phi_of_direction(mats3, p), v, atol=1e-9)
    rng = np.random.default_rng(6)
    X = rng.normal(size=(20000, 3))
    X /= np.linalg.norm(X, axis=-1)[:, None]
    for M, val in zip(mats3[::10], v[::10]):
        ang = m.phi_of_direction(np.broadcast_to(M, (len(X), 3, 3)), X)
        assert ang.max() <= val + 1e-12
        if val < 3.0:  # a smooth peak: 20000 random directions come close (a reversal is a cone)
            assert val - ang.max() < 0.05


def test_3d_phi_max_does_not_depend_on_gain_and_bounds(mats3):
    rng = np.random.default_rng(7)
    v = m.phi_max(mats3)
    for k in (0.01, 0.5, 7.0):
        np.testing.assert_allclose(m.phi_max(k * mats3), v, atol=1e-12)
    # P1 eq. (10) in 3-D: where ||G|| <= 1, asin(||G||) >= |phi_max| (u = Gv lies in a ball of
    # radius ||G|| around v, so k M v = v - u makes an angle <= asin(||G||) with v)
    k = rng.uniform(0.05, 2.0, len(mats3))
    gn = m.g_norm(mats3, k)
    c = gn <= 1.0
    assert c.sum() > 100
    assert np.all(m.phi_hat_max(gn[c]) >= v[c] - 1e-12)


def test_3d_lever_motion_maps():
    """M = J Jhat^-1 of the 3-D lever (docs/physics.md): with the estimate on the true port
    M = I (no error); the axis normal to both shafts is a common eigenvector of M and M^T, so M
    is block diagonal in (n, plane) and phi_max is that of the in-plane 2x2 block unless the
    normal gain dominates."""
    def lever(w, p, L):
        d = p - w
        r = np.linalg.norm(d)
        u = d / r
        return np.eye(3) - (L / r) * (np.eye(3) - np.outer(u, u))

    rng = np.random.default_rng(8)
    w = np.array([0.02, -0.05, -0.03])
    p = np.array([0.0, 0.16, 0.0])
    J = lever(w, p, 0.32)
    assert m.phi_max(m.motion_map(J, J)[0]) == pytest.approx(0.0, abs=1e-7)
    checked = 0
    for _ in range(50):
        ph = p + rng.normal(size=3) * 0.01
        M, sing = m.motion_map(J, lever(w, ph, 0.32))
        assert not sing
        u, uh = (p - w) / np.linalg.norm(p - w), (ph - w) / np.linalg.norm(ph - w)
        n = np.cross(u, uh)
        n /= np.linalg.norm(n)
        e1 = u
        e2 = np.cross(n, e1)
        B = np.stack([e1, e2, n])                  # rows: in-plane basis, then the normal
        Mb = B @ M @ B.T
        assert np.abs(Mb[2, :2]).max() < 1e-12 and np.abs(Mb[:2, 2]).max() < 1e-12
        phi2, phi3 = float(m.phi_max(Mb[:2, :2])), float(m.phi_max(M))
        assert phi3 >= phi2 - 1e-12
        r2 = np.linalg.norm(Mb[:2, :2] @ m.p_phi(Mb[:2, :2]))
        if phi2 < np.pi / 2 and np.tan(np.pi / 4 - phi2 / 2) * r2 < Mb[2, 2] < np.tan(np.pi / 4 + phi2 / 2) * r2:
            assert phi3 == pytest.approx(phi2, abs=1e-10)
            checked += 1
    assert checked > 10


def _dense_min_over_gain(Ms, ks):
    d = Ms.shape[-1]
    G = np.eye(d) - ks[:, None, None, None] * Ms[None]
    f = np.linalg.svd(G, compute_uv=False)[..., 0].max(axis=1)
    return f.min(), ks[np.argmin(f)]


@pytest.mark.parametrize("d", [2, 3])
def test_min_over_gain_vs_dense_search(d):
    rng = np.random.default_rng(10 + d)
    stacks = np.eye(d) + rng.uniform(0.05, 0.35, (30, 1, 1, 1)) * rng.normal(size=(30, 5, d, d))
    rho, ks = m.min_over_gain(stacks)
    for S, r, k in zip(stacks, rho, ks):
        if r == 1.0:
            assert k == 0.0
            assert _dense_min_over_gain(S, np.linspace(1e-3, 4, 2000))[0] >= 1.0 - 1e-12
            continue
        dense, kd = _dense_min_over_gain(S, np.linspace(0, 2 * k, 4001))
        assert r <= dense + 1e-12 and dense - r < 1e-5
        assert abs(kd - k) < 0.01 * k + 1e-3
    assert (rho < 1).sum() > 10


def test_min_over_gain_planar_is_the_fields_search():
    """d = 2 runs the same golden section on the closed form as the planar fields search
    (errplan.fields minimize_gain): same numbers, same conventions."""
    rng = np.random.default_rng(12)
    stacks = np.eye(2) + 0.4 * rng.normal(size=(50, 7, 2, 2))
    stacks[3, 2] = np.nan                                     # counts as M = 0: rho* = 1
    stacks[4] = np.array([[np.cos(2.0), -np.sin(2.0)], [np.sin(2.0), np.cos(2.0)]])  # 115 deg: none
    rho, ks = m.min_over_gain(stacks)
    mu, nu = m.conformal_parts(stacks)
    assert rho[4] == 1.0 and ks[4] == 0.0 and np.isfinite(rho).all()
    assert rho[3] == 1.0 and ks[3] == 0.0
    emb3 = np.zeros((2, 3, 3, 3))
    emb3[:] = np.eye(3)
    emb3[1, 1, 0, 0] = np.nan
    r3, k3 = m.min_over_gain(emb3)
    assert r3[0] == pytest.approx(0.0, abs=1e-12) and r3[1] == 1.0 and k3[1] == 0.0
    try:
        from errplan.fields.search import minimize_gain
    except ImportError:  # the fields package moved: the dense check above still holds
        pytest.skip("errplan.fields.search.minimize_gain not found")
    r2, k2 = minimize_gain(mu, nu)
    np.testing.assert_array_equal(rho, r2)
    np.testing.assert_array_equal(ks, k2)
    # and the 3-D kernel on the embedded stacks (third axis = 1, never the worst) agrees
    emb = np.zeros(stacks.shape[:-2] + (3, 3))
    emb[..., :2, :2] = stacks
    emb[..., 2, 2] = 1.0
    r3, _k3 = m.min_over_gain(emb)
    ok = rho < 1
    np.testing.assert_allclose(r3[ok], rho[ok], atol=1e-9)


def test_shape_errors_are_clear():
    with pytest.raises(ValueError, match="d = 2 or 3"):
        m.phi_max(np.eye(4))
    with pytest.raises(ValueError, match="d = 2 or 3"):
        m.g_norm(np.ones(3), 1.0)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        m.phi_of_direction(np.eye(3), np.ones(2))
    with pytest.raises(ValueError, match="2x2"):
        m.conformal_parts(np.eye(3))
    with pytest.raises(ValueError, match="inv2"):
        m.inv2(np.eye(3))
    with pytest.raises(ValueError, match="m, 3, 3"):
        m.min_over_gain(np.eye(3))
