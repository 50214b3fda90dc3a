"""Worst case over a bounded error set, in numpy: sampling plus a local pattern search with
multi-start (the method of the package docstring), and the best contraction over the gain.
The general path (P2's flexion controller, a truth with ``[effects]``) and the reference
implementation of the compiled kernels."""
from __future__ import annotations

from typing import Callable

import numpy as np

from ..metrics import (g_norm, g_norm_from_parts, min_over_gain, min_over_gain_parts, phi_max,
                       phi_max_from_parts)
from ..errorset import ErrorSet
from .evaluator import Evaluator

REFINE_LEVELS = 6
_STATS: dict = {}  # diagnostics of the last worst_case call (number of second starts)
EXTRA_PASSES = 2  # further pattern-search passes for worst cases still climbing
SECOND_START = 0.002  # relative margin within which a second local maximum is refined too
Progress = Callable[[float, str], None]


def _g_of(mu: np.ndarray, nu, k) -> np.ndarray:
    """``||I - k M||`` from an evaluator's parts: planar conformal parts ``(mu, nu)``, or (``nu is
    None``) the motion maps ``M`` themselves (..., d, d) of a spatial evaluator."""
    return g_norm(mu, k) if nu is None else g_norm_from_parts(mu, nu, k)


def _reduce(mu: np.ndarray, nu, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Worst case over the noise axis (last): ``(||G||, |phi_max|)``."""
    if nu is None:
        return g_norm(mu, k).max(axis=-1), phi_max(mu).max(axis=-1)
    return g_norm_from_parts(mu, nu, k).max(axis=-1), phi_max_from_parts(mu, nu).max(axis=-1)


def _values(ev, x: np.ndarray, th: np.ndarray, k: float, keep: bool, g_above=None, p_above=None):
    """``(mu, nu, ||G||, |phi_max|, ok)`` of an evaluator at tips ``x`` under instance(s) ``th``, the worst
    over a noise axis: from the evaluator's compiled reduction where it has one and the parts are not
    kept (P2's controller in 3-D: :meth:`SpatialFlexionEvaluator.reduced`; ``mu``, ``nu`` None then).
    ``g_above``, ``p_above``: the caller keeps ``||G||``, ``|phi_max|`` only above these values (the
    reduction may return them where it is not; ``inf``: not needed)."""
    red = getattr(ev, "reduced", None)
    if red is not None and not keep:
        g, p, ok = red(x, th, k, g_above=g_above, p_above=p_above)
        return None, None, g, p, ok
    mu, nu, ok = ev.parts(x, th)
    g, p = _reduce(mu, nu, k)
    return mu, nu, g, p, ok


def _far_mask(es: ErrorSet, samples: int | None) -> np.ndarray:
    """(m, m) mask of sample pairs more than one grid step apart along some axis (a periodic axis
    measured around the circle)."""
    shape = [int(c) for c in es.counts(samples)]
    ij = np.stack(np.unravel_index(np.arange(int(np.prod(shape))), shape), axis=-1)
    dd = np.abs(ij[:, None, :] - ij[None, :, :])
    per = es.periodic
    dd[..., per] = np.minimum(dd[..., per], np.asarray(shape)[per] - dd[..., per])
    return dd.max(axis=-1) > 1


def _local_max(vals: np.ndarray, shape: list[int]) -> np.ndarray:
    """Mask (n, m) of samples no lower than their grid neighbours along every axis."""
    n = len(vals)
    v = vals.reshape((n,) + tuple(shape))
    out = np.ones(v.shape, bool)
    for ax, s in enumerate(shape):
        if s < 2:
            continue
        lo = (slice(None),) * (ax + 1) + (slice(0, s - 1),)
        hi = (slice(None),) * (ax + 1) + (slice(1, s),)
        out[lo] &= v[lo] >= v[hi]
        out[hi] &= v[hi] >= v[lo]
    return out.reshape(n, -1)


def _peak_raise(vals: np.ndarray, j: np.ndarray, shape: list[int]) -> np.ndarray:
    """Estimated gain (n,) of refining sample ``j`` (n,) of each row of ``vals`` (n, m): along
    every axis the parabola through the sample and its neighbours (one-sided on a face of the box,
    where only a vertex inside the box counts), summed over the axes."""
    ij = np.stack(np.unravel_index(j, shape), axis=-1)
    strides = np.array([int(np.prod(shape[i + 1:])) for i in range(len(shape))])
    out = np.zeros(len(vals))

    def at(ax, off):
        jj = j + off * strides[ax]
        return np.take_along_axis(vals, np.clip(jj, 0, vals.shape[1] - 1)[:, None], 1)[:, 0]

    f0 = np.take_along_axis(vals, j[:, None], 1)[:, 0]
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        for ax, s in enumerate(shape):
            if s < 2:
                continue
            pos = ij[:, ax]
            if s == 2:
                r = np.abs(f0 - at(ax, np.where(pos == 0, 1, -1)))
            else:
                fm, fp = at(ax, -1), at(ax, 1)
                curv = 2 * f0 - fm - fp  # interior: vertex of the parabola through -1, 0, 1
                r_in = np.where(curv > 0, (fp - fm) ** 2 / (8 * np.where(curv > 0, curv, 1.0)), 0.0)
                inward = np.where(pos == 0, 1, -1)  # faces: parabola through 0, -1, -2 inward
                f1, f2 = at(ax, inward), at(ax, 2 * inward)
                c2 = 0.5 * (f0 - 2 * f1 + f2)
                b = f0 - f1 + c2  # f(x) = f0 + b x + c2 x^2, x counted outward
                cneg = np.where(c2 < 0, c2, -1.0)
                xv = -b / (2 * cneg)
                r_face = np.where((c2 < 0) & (xv < 0) & (xv > -1), -b * b / (4 * cneg), 0.0)
                r = np.where((pos == 0) | (pos == s - 1), r_face, r_in)
            out += np.where(np.isfinite(r), np.maximum(r, 0.0), np.inf)
    return out


def worst_case(ev: Evaluator, x: np.ndarray, k: float, *, samples: int | None = None,
               refine: int = REFINE_LEVELS, keep_parts: bool = False,
               progress: Progress | None = None, second_start: float = SECOND_START,
               chunk: int | None = None) -> dict[str, np.ndarray]:
    """Worst-case ``||G||`` (gain ``k``) and ``|phi_max|`` at tips ``x`` (n, 2).

    The error box is sampled on a grid (``samples`` per uncertain axis), then each tip's worst
    instance is refined by a coordinate pattern search: at level ``l = 1..refine`` every uncertain
    axis is polled at ``+-spacing / 2**l`` around the current worst, which moves to any better
    poll. Polls around the ||G|| worst also update |phi_max|; |phi_max| is polled on its own only
    where its worst instance differs from the ||G|| one. Where the best sample more than one grid
    step away from the worst sample comes within ``second_start`` (relative, of ``max(1, worst)``)
    of it, a second local maximum may win after refinement: it is refined too (multi-start).
    A tip is invalid as soon as any evaluated instance cannot reach it.

    Returns ``valid``, ``G_norm``, ``phi_max``, the worst parameters ``theta_G``/``theta_phi``
    and, with ``keep_parts``, the sampled ``mu``/``nu`` (n, m, c) for gain optimisation.
    """
    x = np.asarray(x, float)
    n = len(x)
    grid = ev.errors.sample_grid(samples)
    step = chunk or max(2000, 6_000_000 // max(len(grid), 1))
    if n > step:
        parts = [worst_case(ev, x[i:i + step], k, samples=samples, refine=refine, keep_parts=keep_parts,
                            second_start=second_start, chunk=step,
                            progress=None if progress is None else
                            (lambda f, m, i=i: progress((i + f * min(step, n - i)) / n, m)))
                 for i in range(0, n, step)]
        return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    es = ev.errors
    m = len(grid)
    valid = np.ones(n, bool)
    vals_g = np.full((n, m), -np.inf)
    vals_p = np.full((n, m), -np.inf)
    mus, nus = [], []
    idx = np.arange(n)
    dims = np.flatnonzero(es.active)
    total = m + 2 * refine * 2 * len(dims)
    done = 0
    for j, th in enumerate(grid):
        sub = idx[valid]
        if len(sub) == 0:
            break
        mu, nu, g, p, ok = _values(ev, x[sub], th, k, keep_parts)
        valid[sub[~ok]] = False
        vals_g[sub, j] = np.where(ok, g, -np.inf)
        vals_p[sub, j] = np.where(ok, p, -np.inf)
        if keep_parts:
            full_mu = np.full((n,) + mu.shape[1:], np.nan, mu.dtype)
            full_mu[sub] = mu
            mus.append(full_mu)
            if nu is not None:
                full_nu = np.full_like(full_mu, np.nan)
                full_nu[sub] = nu
                nus.append(full_nu)
        done += 1
        if progress:
            progress(done / total, "sampling the error set")
    # Starts of the local refinement: each tip's worst sample, plus a second local maximum where
    # one comes close (entries n.. of the extended arrays belong to tips owner[n..]).
    i_g, i_p = vals_g.argmax(axis=1), vals_p.argmax(axis=1)
    owner = idx
    starts_g, starts_p = [i_g], [i_p]
    if m > 1 and second_start > 0 and len(dims):
        far = _far_mask(es, samples)
        shape = [int(c) for c in es.counts(samples)]
        far_g = far[i_g] & _local_max(vals_g, shape)
        far_p = far[i_p] & _local_max(vals_p, shape)
        v_g = np.take_along_axis(vals_g, i_g[:, None], 1)[:, 0]
        v_p = np.take_along_axis(vals_p, i_p[:, None], 1)[:, 0]
        j_g = np.where(far_g, vals_g, -np.inf).argmax(axis=1)
        j_p = np.where(far_p, vals_p, -np.inf).argmax(axis=1)
        w_g = np.take_along_axis(vals_g, j_g[:, None], 1)[:, 0]
        w_p = np.take_along_axis(vals_p, j_p[:, None], 1)[:, 0]
        # A second local maximum is refined too when the sampled value plus twice its estimated
        # refinement gain (parabolic, _peak_raise) comes within second_start * max(1, worst).
        r_g = _peak_raise(vals_g, j_g, shape)
        r_p = _peak_raise(vals_p, j_p, shape)
        with np.errstate(invalid="ignore"):  # -inf entries: tips already invalid
            need_g = w_g + 2.0 * r_g >= v_g - second_start * np.maximum(1.0, np.abs(v_g))
            need_p = w_p + 2.0 * r_p >= v_p - second_start * np.maximum(1.0, np.abs(v_p))
        extra = np.flatnonzero(valid & (need_g | need_p))
        _STATS["second_starts"] = len(extra)
        if len(extra):
            owner = np.concatenate([idx, extra])
            # A metric without a close second maximum follows the other's track (shared polls).
            starts_g.append(np.where(need_g, j_g, j_p)[extra])
            starts_p.append(np.where(need_p, j_p, j_g)[extra])
    s_g, s_p = np.concatenate(starts_g), np.concatenate(starts_p)
    xe = x[owner]
    th_g, th_p = grid[s_g].copy(), grid[s_p].copy()
    best_g = vals_g[owner, s_g]
    best_p = vals_p[owner, s_p]
    ok_e = valid[owner].copy()
    idx_e = np.arange(len(owner))

    # The instances each entry has been evaluated at (its theta's bytes -> whether ||G|| was computed there):
    # a poll landing on one again cannot raise that entry's best (both only grow), so it is skipped (the
    # same search, fewer evaluations). A tip's own entry starts at its best samples, so its samples count;
    # a second start's entry starts below them and does not.
    seen: dict = {}
    for j, th in enumerate(grid):
        key = th.tobytes()
        for i in np.flatnonzero(valid).tolist():
            seen[(i, key)] = True

    def unseen(rows, theta, for_g):
        fresh = np.ones(len(rows), bool)
        for q, (r, t) in enumerate(zip(rows.tolist(), theta)):
            key = (r, t.tobytes())
            had = seen.get(key)
            if had is not None and (had or not for_g):
                fresh[q] = False
            else:
                seen[key] = for_g
        return fresh

    def evaluate(sub, theta, track_g):
        _, _, g, p, ok = _values(ev, xe[sub], theta, k, False, best_g[sub] if track_g else np.inf, best_p[sub])
        ok_e[sub[~ok]] = False
        if track_g:
            upd = ok & (g > best_g[sub])
            best_g[sub[upd]] = g[upd]
            th_g[sub[upd]] = theta[upd]
        upd = ok & (p > best_p[sub])
        best_p[sub[upd]] = p[upd]
        th_p[sub[upd]] = theta[upd]

    # Local refinement (pattern search, step halved each level). Entries that still gained in a
    # pass (a worst on a ridge, which coordinate polls climb slowly) get up to EXTRA_PASSES more.
    step0 = es.spacing(samples)
    lo, hi = es.lo_arr, es.hi_arr
    active = ok_e.copy()
    for pass_ in range(1 + EXTRA_PASSES):
        before_g, before_p = best_g.copy(), best_p.copy()
        for level in range(1, refine + 1):
            h = step0 / 2**level
            for dmn in dims:
                for sgn in (-1.0, 1.0):
                    sub = idx_e[ok_e & active]
                    if len(sub) == 0:
                        break
                    apart = np.any(th_p[sub] != th_g[sub], axis=1)

                    def poll(rows, th_best, for_g):
                        # Polls clipped back onto the centre (a worst on the box face) are skipped.
                        c = th_best[rows]
                        moved = c[:, dmn] + sgn * h[dmn]
                        if es.periodic[dmn]:  # the load direction wraps around
                            moved = lo[dmn] + np.mod(moved - lo[dmn], hi[dmn] - lo[dmn])
                        else:
                            moved = np.clip(moved, lo[dmn], hi[dmn])
                        keep = moved != c[:, dmn]
                        if np.any(keep):
                            c = c[keep].copy()
                            c[:, dmn] = moved[keep]
                            fresh = unseen(rows[keep], c, for_g)
                            if np.any(fresh):
                                evaluate(rows[keep][fresh], c[fresh], for_g)

                    poll(sub, th_g, True)
                    poll(sub[apart & ok_e[sub]], th_p, False)
                    if pass_ == 0:
                        done += 2
                        if progress:
                            progress(done / total, "refining the worst case")
        with np.errstate(invalid="ignore"):
            gain = np.maximum(best_g - before_g, best_p - before_p)
            active = ok_e & (gain > 1e-7 * np.maximum(1.0, np.abs(best_g)))
        if not np.any(active):
            break
    # Back from the extended entries to the tips: worst over the starts, valid under all.
    np.logical_and.at(valid, owner, ok_e)
    out_g, out_p = best_g[:n].copy(), best_p[:n].copy()
    tg, tp = th_g[:n].copy(), th_p[:n].copy()
    ext = np.arange(n, len(owner))  # at most one extra start per tip
    o = owner[ext]
    b = best_g[ext] > out_g[o]
    out_g[o[b]], tg[o[b]] = best_g[ext[b]], th_g[ext[b]]
    b = best_p[ext] > out_p[o]
    out_p[o[b]], tp[o[b]] = best_p[ext[b]], th_p[ext[b]]
    out_g[~valid] = np.nan
    out_p[~valid] = np.nan
    out = {"valid": valid, "G_norm": out_g, "phi_max": out_p, "theta_G": tg, "theta_phi": tp}
    if keep_parts:
        out["mu"] = np.stack(mus, axis=1) if mus else np.zeros((n, 0, 1), complex)
        out["nu"] = np.stack(nus, axis=1) if nus else None  # None: "mu" holds motion maps M
    return out


def minimize_gain(mu: np.ndarray, nu, iters: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """``rho* = min_k max_i |1 - k mu_i| + k |nu_i|`` per row, by golden section (convex in k).

    ``mu``, ``nu``: (n, m) complex, NaN entries ignored. Returns ``(rho_star, k_star)``; where no
    gain contracts, ``rho* = 1`` at ``k* = 0``.
    """
    if nu is None:  # motion maps (n, m, ..., d, d): errplan.metrics.min_over_gain
        M = np.asarray(mu, float)
        d = M.shape[-1]
        M = M.reshape(len(M), -1, d, d)
        bad = ~np.all(np.isfinite(M), axis=(-2, -1))
        M = np.where(bad[..., None, None], 0.0, M)  # a zero map contracts nothing: never the worst
        rho, kk = min_over_gain(M, iters)
        none = ~(rho < 1.0)
        return np.where(none, 1.0, rho), np.where(none, 0.0, kk)
    return min_over_gain_parts(mu, nu, iters)


def _refined_at_gain(ev: Evaluator, x: np.ndarray, k: np.ndarray, *, samples=None, refine=REFINE_LEVELS) -> np.ndarray:
    """Worst ``||G||`` at a per-point gain ``k`` over the error set, with local refinement."""
    es = ev.errors
    grid = es.sample_grid(samples)
    best = np.full(len(x), -np.inf)
    th_best = np.zeros((len(x), len(es.lo)))
    red = getattr(ev, "reduced", None)

    def worst_g(th):
        if red is not None:  # compiled: the worst over the noise axis without forming the maps in Python
            g, _, ok = red(x, th, k, phi=False)
            return g, ok
        mu, nu, ok = ev.parts(x, th)
        return _g_of(mu, nu, k[:, None]).max(axis=-1), ok

    for th in grid:
        g, ok = worst_g(th)
        g = np.where(ok, g, np.inf)
        upd = g > best
        best[upd] = g[upd]
        th_best[upd] = th
    step0 = es.spacing(samples)
    for level in range(1, refine + 1):
        h = step0 / 2**level
        for dmn in np.flatnonzero(es.active):
            for sgn in (-1.0, 1.0):
                c = th_best.copy()
                v = c[:, dmn] + sgn * h[dmn]
                c[:, dmn] = (es.lo[dmn] + np.mod(v - es.lo[dmn], es.hi[dmn] - es.lo[dmn]) if es.periodic[dmn]
                             else np.clip(v, es.lo[dmn], es.hi[dmn]))
                g, ok = worst_g(c)
                g = np.where(ok, g, np.inf)
                upd = g > best
                best[upd] = g[upd]
                th_best[upd] = c[upd]
    return best
