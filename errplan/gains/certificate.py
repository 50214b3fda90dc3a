"""What a ball's sample says about gains: the optimiser's sample of a segment, the worst-case contraction
``rho(k)`` over it, the gains that can certify it (scans on a k-grid) and the pairs that matter (pruning)."""
from __future__ import annotations

import math

import numpy as np

from ..fields import Evaluator
from .options import GainOptions
from .physics import _is_spatial, _pairs, ball_tips, gnorm3_grid, grid_top, sym_top_candidates


def _sample_segment(ev: Evaluator, a, b, radius: float, opts: GainOptions) -> dict:
    """The optimiser's sample of one ball: flattened conformal parts of the reachable pairs
    (3-D: the motion maps ``M`` (p, 3, 3) of the reachable pairs)."""
    x = ball_tips(b, radius, opts.opt_disk, opts.opt_ring)
    if _is_spatial(ev):
        th = ev.instances(opts.opt_samples)
        M, ok = ev.maps(x, th)
        Ms = M[ok].reshape(-1, 3, 3)  # the flexion controller's noise corners flattened too
        singular = 0 if ev.singular_free(b, radius) else int(ok.sum())
        return {"M": Ms, "singular": singular, "tips": len(x), "instances": len(th), "noise_corners": ev.noise_corners,
                "pairs": int(ok.sum())}
    th = ev.errors.sample_grid(opts.opt_samples)
    mu, nu, reach, ok = _pairs(ev, x, th)
    n_reach = int(reach.sum())
    singular = reach & ~ok
    sel = reach & ok
    m = mu[sel].ravel()
    v = nu[sel].ravel()
    fin = np.isfinite(m) & np.isfinite(v)
    return {"mu": m[fin], "nu": v[fin], "singular": int(singular.sum()) + int((~fin).sum()),
            "tips": len(x), "instances": len(th), "noise_corners": int(mu.shape[-1]), "pairs": n_reach}


def rho_of_k(mu: np.ndarray, nu: np.ndarray, k: np.ndarray) -> np.ndarray:
    """``max_i |1 - k mu_i| + k |nu_i|`` for each gain of ``k`` (numpy, for grids and tests)."""
    k = np.atleast_1d(np.asarray(k, float))
    out = np.empty(len(k))
    for j in range(0, len(k), 64):
        kk = k[j:j + 64, None]
        out[j:j + 64] = (np.abs(1.0 - kk * mu[None]) + kk * np.abs(nu[None])).max(axis=1)
    return out


def rho_of_k_M(M: np.ndarray, k) -> np.ndarray:
    """``max_i ||I - k M_i||_2`` for each gain of ``k`` (3 x 3 ``M`` (n, 3, 3), compiled)."""
    return gnorm3_grid(M, k).max(axis=1)


def _rho(smp: dict, k) -> np.ndarray:
    """The sampled worst case ``rho_s(k)`` of a segment's optimiser sample (planar or 3-D)."""
    if "M" in smp:
        return rho_of_k_M(smp["M"], k)
    return rho_of_k(smp["mu"], smp["nu"], k)


def _k_upper_M(M: np.ndarray) -> float:
    """Above ``2 / max_i lambda_max(sym M_i)`` no gain contracts (``|1 - k v.Mv| >= 1``)."""
    if not len(M):
        return 1.0
    S = 0.5 * (M + np.swapaxes(M, -1, -2))
    if np.all(np.isfinite(S)):
        # only the matrices whose closed-form top eigenvalue is within rounding of the largest can hold the
        # largest: LAPACK on those alone (the same values, one matrix at a time)
        S = S[sym_top_candidates(S)]
    lam = np.linalg.eigvalsh(S)[:, -1].max()
    return 2.0 / lam if lam > 0 else 1.0


def _scan_M(M: np.ndarray, n: int = 81, top: int = 3, ku: float | None = None):
    """3-D :func:`_scan` and :func:`_prune` in one pass: ``(rho*, k*, kg, pruned indices)``. The
    grid's top pairs are kept; the golden-section polish (:func:`_golden`) runs on them (the maximum
    near the grid's best gain is theirs), the value at the result on every pair. ``ku``: :func:`_k_upper_M`
    of ``M`` when the caller has it."""
    ku = _k_upper_M(M) if ku is None else ku
    kg = np.linspace(ku / n, ku, n)
    if len(M) <= 64:
        vals = gnorm3_grid(M, kg).max(axis=1)                # (n,)
        idx = np.arange(len(M))
    else:  # the grid's maxima and top pairs with most of the (n, p) grid skipped by bounds (exact)
        vals, tops = grid_top(M, kg, top)
        idx = np.unique(tops.ravel())
    Mp = M[idx]
    k = _golden(lambda q: rho_of_k_M(Mp, q), kg, vals)
    return float(rho_of_k_M(M, k)[0]), float(k), kg, idx


def _k_upper(mu: np.ndarray) -> float:
    """Above ``2 / max|mu|`` no gain contracts (|1 - k mu| >= k|mu| - 1 >= 1)."""
    amax = float(np.abs(mu).max()) if len(mu) else 1.0
    return 2.0 / amax if amax > 0 else 10.0


def _scan(mu, nu, n: int = 401) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Best gain on a numpy grid then golden-section polish (:func:`_golden`): (rho*, k*, grid, values)."""
    ku = _k_upper(mu)
    kg = np.linspace(ku / n, ku, n)
    vals = rho_of_k(mu, nu, kg)
    k = _golden(lambda q: rho_of_k(mu, nu, q), kg, vals)
    return float(rho_of_k(mu, nu, k)[0]), float(k), kg, vals


def _golden(rho, kg: np.ndarray, vals: np.ndarray) -> float:
    """The scans' polish (plane and 3-D): golden-section search of the convex ``rho(k)`` between the
    neighbours of the grid's best gain ``kg[argmin vals]``; ``rho`` takes an array of gains (both
    points of a step in one call)."""
    j = int(np.argmin(vals))
    lo, hi = kg[max(j - 1, 0)], kg[min(j + 1, len(kg) - 1)]
    gr = (math.sqrt(5) - 1) / 2
    for _ in range(40):
        c, d = hi - gr * (hi - lo), lo + gr * (hi - lo)
        rc, rd = rho(np.array([c, d]))
        if rc < rd:
            hi = d
        else:
            lo = c
    return 0.5 * (lo + hi)


def _prune(mu, nu, kg, top: int = 3) -> np.ndarray:
    """Indices of pairs among the ``top`` largest ``||G||`` at some gain of the grid."""
    if len(mu) <= 64:
        return np.arange(len(mu))
    keep = set()
    for j in range(0, len(kg), 32):
        kk = kg[j:j + 32, None]
        g = np.abs(1.0 - kk * mu[None]) + kk * np.abs(nu[None])  # (kb, n)
        idx = np.argpartition(-g, top, axis=1)[:, :top]
        keep.update(idx.ravel().tolist())
    return np.array(sorted(keep))


def ball_clearance(anatomy, center, radius: float) -> float:
    """A lower bound (m) on the robust clearance of every tip of the convergence ball of centre
    ``center`` (3,) and radius ``radius`` (m): the clearance at the centre less the radius.

    ``anatomy`` is the scenario's anatomy model (:class:`errplan.anatomy.ShaftClearance`); its
    distance query ``anatomy.tip(x)`` is the smallest distance, over every true port of the box,
    from the shaft [port, x] to every obstacle, and is also at most the tip's depth inside the body
    wall. That clearance is 1-Lipschitz in the tip (the hulls of the box with two tips are within
    Hausdorff distance of their separation; the depth inside a wall is a distance), hence the bound.
    The ball is clear when the bound is at least ``anatomy.required`` ([anatomy] clearance).

    This is the one ball condition anatomy adds, for every kind of obstacle at once: organs
    (primitives and meshes), vessels, the body wall, and any further convex pieces the model's
    distance query comes to include (e.g. the shafts of the other instruments of a several-instrument
    setup, held fixed while this one moves): they join by entering ``anatomy.tip``, not here.
    """
    return float(anatomy.tip(np.asarray(center, float))) - float(radius)
