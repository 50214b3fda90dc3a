"""The 3-D certificate's shortcuts that skip ``||I - k M||`` evaluations by bounds (errplan.gains.physics
grid_top, worst_instances, sym_top_candidates): each against the full computation it replaces (every
value computed, numpy's max / argmax / argpartition / eigvalsh), bit for bit, on random and structured
matrices, with ties and non-finite entries that force the fallbacks."""
from __future__ import annotations

import numpy as np
import pytest

from errplan.gains.certificate import _k_upper_M, _scan_M, _golden, rho_of_k_M
from errplan.gains.physics import (_bisection_order, _grid_top, _scalar_offsets, _worst_instances, gnorm3_grid,
                                   gnorm3_pairs, grid_top, worst_instances)
from errplan.gains.verify import _mask3


def _lever_like(rng, n: int, spread: float = 0.3) -> np.ndarray:
    """``n`` motion-map-like 3 x 3 matrices: rotated ``diag(1, a, a)`` (a lever's axial / lateral
    scaling) plus a small general part, the structure of the certificate's maps."""
    out = np.empty((n, 3, 3))
    for i in range(n):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        a = 1.0 + spread * rng.normal()
        out[i] = q @ np.diag([1.0 + 0.1 * rng.normal(), a, a * (1 + 0.05 * rng.normal())]) @ q.T
        out[i] += 0.05 * rng.normal(size=(3, 3))
    return out


def _full_top(M, kg, top=3):
    """The reference: the whole grid, numpy's max and argpartition (the scan before the bounds)."""
    G = gnorm3_grid(M, kg)
    return G.max(axis=1), np.unique(np.argpartition(-G, top, axis=1)[:, :top].ravel())


@pytest.mark.parametrize("seed,n,eps", [(0, 65, None), (1, 400, None), (2, 2000, None), (3, 1500, 0.003)])
def test_grid_top_equals_full_grid(seed, n, eps):
    rng = np.random.default_rng(seed)
    M = _lever_like(rng, n) if eps is None else _clustered(rng, (n,), eps)
    ku = _k_upper_M(M)
    kg = np.linspace(ku / 81, ku, 81)
    vals, tops = grid_top(M, kg, 3)
    v_ref, idx_ref = _full_top(M, kg)
    assert np.array_equal(vals, v_ref)
    assert np.array_equal(np.unique(tops.ravel()), idx_ref)
    # and the bounds skipped most of the grid (the point of it)
    c, r = np.empty(n), np.empty(n)
    assert _scalar_offsets(M, c, r)
    clear = np.zeros(81, bool)
    evals = _grid_top(M, c, r, kg, *_bisection_order(81), 3, np.empty(81), np.empty((81, 3), np.int64), clear)
    assert clear.all() and evals < 0.5 * 81 * n


def test_grid_top_bound_is_an_upper_bound():
    """``|1 - k c| + |k| r`` (c = tr/3, r = ||M - cI||_2) bounds numpy's SVD norm at every gain, both signs."""
    rng = np.random.default_rng(3)
    M = np.concatenate([_lever_like(rng, 50), rng.normal(size=(50, 3, 3))])
    c, r = np.empty(100), np.empty(100)
    assert _scalar_offsets(M, c, r)
    for k in (-2.0, -0.3, 0.0, 0.4, 1.0, 3.0):
        exact = np.linalg.norm(np.eye(3) - k * M, ord=2, axis=(-2, -1))
        assert np.all(np.abs(1 - k * c) + abs(k) * r >= exact * (1 - 1e-13))


def test_grid_top_ties_and_nan_fall_back_to_the_full_row():
    """Duplicated matrices tie at the top-th value: those gains are computed in full (numpy's own choice
    among the tied); a NaN matrix makes every gain fall back (NaN maxima, as numpy)."""
    rng = np.random.default_rng(4)
    base = _lever_like(rng, 40)
    M = np.concatenate([base, base, base[:5]])          # every matrix at least twice: ties everywhere
    kg = np.linspace(0.05, 1.5, 30)
    vals, tops = grid_top(M, kg, 3)
    v_ref, idx_ref = _full_top(M, kg)
    assert np.array_equal(vals, v_ref) and np.array_equal(np.unique(tops.ravel()), idx_ref)
    c, r = np.empty(len(M)), np.empty(len(M))
    _scalar_offsets(M, c, r)
    clear = np.zeros(30, bool)
    _grid_top(M, c, r, kg, *_bisection_order(30), 3, np.empty(30), np.empty((30, 3), np.int64), clear)
    assert not clear.any()
    Mn = base.copy()
    Mn[7, 1, 2] = np.nan
    vals, tops = grid_top(Mn, kg, 3)
    v_ref, idx_ref = _full_top(Mn, kg)
    assert np.all(np.isnan(vals)) and np.all(np.isnan(v_ref))
    assert np.array_equal(np.unique(tops.ravel()), idx_ref)
    with pytest.raises(ValueError, match="top"):
        grid_top(base[:3], kg, 3)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7, 81])
def test_bisection_order(n):
    order, left, right = _bisection_order(n)
    assert sorted(order.tolist()) == list(range(n))
    pos = {int(j): p for p, j in enumerate(order)}
    for j in order:
        if left[j] >= 0:  # both neighbours visited before it, one on each side
            assert left[j] < j < right[j] and pos[int(left[j])] < pos[int(j)] and pos[int(right[j])] < pos[int(j)]
        else:
            assert j in (0, n - 1)


def _scan_M_reference(M, n=81, top=3):
    """``_scan_M`` as it was before the bounds: every gain of the grid, numpy's argpartition."""
    ku = float(2.0 / np.linalg.eigvalsh(0.5 * (M + np.swapaxes(M, -1, -2)))[:, -1].max())
    kg = np.linspace(ku / n, ku, n)
    G = gnorm3_grid(M, kg)
    vals = G.max(axis=1)
    idx = np.arange(len(M)) if len(M) <= 64 else np.unique(np.argpartition(-G, top, axis=1)[:, :top].ravel())
    Mp = M[idx]
    k = _golden(lambda q: rho_of_k_M(Mp, q), kg, vals)
    return float(rho_of_k_M(M, k)[0]), float(k), kg, idx


@pytest.mark.parametrize("seed,n", [(5, 30), (6, 900)])
def test_scan_M_and_k_upper_unchanged(seed, n):
    rng = np.random.default_rng(seed)
    M = _lever_like(rng, n, spread=0.5)
    ref = _scan_M_reference(M)
    new = _scan_M(M)
    assert new[0] == ref[0] and new[1] == ref[1]
    assert np.array_equal(new[2], ref[2]) and np.array_equal(new[3], ref[3])
    # the gain bound: LAPACK on the closed-form candidates only, the same number as on all
    S = 0.5 * (M + np.swapaxes(M, -1, -2))
    lam = np.linalg.eigvalsh(S)[:, -1].max()
    assert _k_upper_M(M) == 2.0 / lam
    M2 = np.concatenate([M, M[:3]])  # a tie for the largest eigenvalue
    assert _k_upper_M(M2) == 2.0 / np.linalg.eigvalsh(0.5 * (M2 + np.swapaxes(M2, -1, -2)))[:, -1].max()


def _worst_reference(M, ok, k, singular):
    """The verification grid before the bounds: every ||I - k M||, masked, numpy max / argmax."""
    g = gnorm3_pairs(M, k).reshape(M.shape[:-2])  # the compiled values (bit for bit), every pair
    G = _mask3(g.max(axis=-1) if g.ndim == 3 else g, ok, singular)
    j = np.argmax(G, axis=1)
    return G[np.arange(len(G)), j], j


def _clustered(rng, shape, eps):
    """Matrices of ``shape`` (n, m, ...): one lever-like matrix per tip, the instances within ``eps`` of it
    (the certificate's maps: an instance moves the port by millimetres), so that many are near the max."""
    base = _lever_like(rng, shape[0])
    return base.reshape((shape[0],) + (1,) * (len(shape) - 1) + (3, 3)) + eps * rng.normal(size=shape + (3, 3))


@pytest.mark.parametrize("corners,eps", [(0, None), (4, None), (0, 0.003), (3, 0.003), (0, 0.0), (2, 0.0)])
def test_worst_instances_equals_masked_argmax(corners, eps):
    rng = np.random.default_rng(7 + corners)
    n, m = 40, 60
    shape = (n, m) + ((corners,) if corners else ())
    if eps is None:
        M = _lever_like(rng, int(np.prod(shape))).reshape(shape + (3, 3))
    elif eps > 0:
        M = _clustered(rng, shape, eps)
    else:  # nearly scalar maps: the bounds are tight, a pair just below the max is skipped or not by a hair
        M = (1 + 0.01 * rng.normal(size=shape))[..., None, None] * np.eye(3) + 1e-7 * rng.normal(size=shape + (3, 3))
    M[:, 10:20] = M[:, 30:40]                       # tied instances: the first index must win
    ok = rng.random((n, m)) > 0.2
    ok[0] = False                                   # a tip no instance reaches: -inf at index 0
    M[~ok] = np.nan
    if corners:
        M[3, 5, 1, 0, 0] = np.nan                   # one corner NaN on a valid pair: +inf
        ok[3, 5] = True
    for k in (0.2, 0.9, 1.7):
        for singular in (False, True):
            best, j = worst_instances(M, ok, k, singular)
            b_ref, j_ref = _worst_reference(M, ok, k, singular)
            assert np.array_equal(best, b_ref) and np.array_equal(j, j_ref)
    if eps is not None:
        return  # instances this close: the bounds cannot skip them (the values above are the test)
    # the bound skipped pairs
    Ms = np.ascontiguousarray(M.reshape(n, m, -1, 3, 3))
    evals = _worst_instances(Ms, ok, 0.9, False, np.empty(n), np.empty(n, np.int64))
    assert evals < 0.8 * ok.sum() * Ms.shape[2]


def test_spatial_step_ratio_rows_independent_of_unreachable_pairs():
    """The 3-D one-step replay inverts only the reachable wrists: a batch mixing pairs the truth cannot
    reach gives each reachable pair the value it gets alone, NaN to the others."""
    from pathlib import Path

    from errplan.api import load_scenario
    from errplan.gains import SpatialModel

    sc = load_scenario(Path(__file__).resolve().parents[1] / "scenarios" / "phantom15_spatial.toml")
    ev = SpatialModel(sc)
    th = ev.corner_instances()
    b = np.array([0.0, 0.0, 0.33])
    rng = np.random.default_rng(11)
    x = b + 0.01 * rng.normal(size=(12, 3))
    x[[2, 7]] = [5.0, 5.0, 5.0]  # far outside the arm's reach
    X, TH = np.repeat(x, len(th), axis=0), np.tile(th, (len(x), 1))
    batch = ev.step_ratio(b, X, TH, 0.8)
    assert np.isnan(batch[2 * len(th):3 * len(th)]).all() and np.isfinite(batch[:len(th)]).any()
    for i in range(0, len(X), 17):
        alone = ev.step_ratio(b, X[i:i + 1], TH[i:i + 1], 0.8)
        assert np.array_equal(alone, batch[i:i + 1], equal_nan=True)
