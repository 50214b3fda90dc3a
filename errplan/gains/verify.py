"""The verification of a certificate, one routine for the plane and 3-D: the worst ``||G||`` over a
segment's ball on a denser sample than the optimiser's, refined by pattern searches, and the nonlinear
one-step replay (:func:`verify_segment`); a lower gain where only the nonlinear step fails (:func:`_lower_gain`)."""
from __future__ import annotations

import math

import numpy as np

from ..fields import Evaluator
from .options import GainOptions
from .physics import SpatialModel, _instance_grid, _is_spatial, _pairs, _worst_g, ball_tips, gnorm3_grid, step_ratio


def _pair_g(ev, k: float, singular: bool):
    """``g(x, th)``: the worst ``||G||`` per (tip, instance) pair (n,), -inf where the truth cannot reach
    the tip, +inf where it can but the controller's Jacobian is singular (or, in 3-D, the ball is not
    singular-free): planar from the conformal parts over the controller's noise corners, 3-D from
    the compiled sigma_max of ``I - k M``."""
    if _is_spatial(ev):
        return lambda x, th: _g3(ev, x, th, k, singular)

    def g(x, th):
        mu, nu, ok = ev.parts(x, th)
        _, reach = ev.true_wrist(x, th)
        return _worst_g(mu, nu, reach, ok, k)

    return g


def _replay_pairs(ev, b: np.ndarray, x: np.ndarray, opts: GainOptions) -> tuple[np.ndarray, np.ndarray]:
    """The (tip, instance) pairs ``(X, TH)`` of the nonlinear one-step replay: every tip of ``x`` but
    the centre ``b`` under every replay instance, the verification grid in the plane, the corner
    instances in 3-D (port corners x {no load, the largest load in 4 directions})."""
    tr = ev.corner_instances() if _is_spatial(ev) else ev.errors.sample_grid(opts.verify_samples)
    x = x[np.linalg.norm(x - b, axis=-1) > 1e-9]
    return np.repeat(x, len(tr), axis=0), np.tile(tr, (len(x), 1))


def verify_segment(ev: Evaluator, start, end, k: float, radius: float, opts: GainOptions) -> dict:
    """Worst ``||G||`` and nonlinear one-step ratio over the ball, denser than the optimiser; one routine
    for the plane and 3-D (``d`` = 2 or 3, tips ``(n, d)``).

    Tips: centre + ``verify_disk`` sunflower (3-D: volume spiral) + ``verify_ring`` boundary points;
    instances: ``verify_samples`` per uncertain axis (3-D: 8 load directions), then a pattern search
    over each tip's worst instance (periodic in the load direction) and over the position of the 8
    worst tips (kept in the ball); the nonlinear step from every tip under the replay instances
    (:func:`_replay_pairs`) and at the refined worst pairs.
    """
    es = ev.errors
    spatial = _is_spatial(ev)
    b = np.asarray(end, float)
    d = len(b)
    singular = spatial and not ev.singular_free(b, radius)
    x = ball_tips(b, radius, opts.verify_disk, opts.verify_ring)
    th = _instance_grid(ev, opts.verify_samples)
    n, m = len(x), len(th)
    if spatial:
        M, ok = ev.maps(x, th)  # (n, m, 3, 3), or (n, m, c, 3, 3) over the flexion controller's noise corners
        G = gnorm3_grid(M, k)[0].reshape(M.shape[:-2])
        G = _mask3(G.max(axis=-1) if G.ndim == 3 else G, ok, singular)
        reach, corners, n_singular = ok, ev.noise_corners, int(ok.sum()) if singular else 0
    else:
        mu, nu, reach, ok = _pairs(ev, x, th)
        G = _worst_g(mu, nu, reach, ok, k)
        corners, n_singular = int(mu.shape[-1]), int((reach & ~ok).sum())
    pair_g = _pair_g(ev, k, singular)
    grid_max = float(G.max())
    j = np.argmax(G, axis=1)
    best = G[np.arange(n), j]
    th_best = th[j].copy()
    # Nonlinear one-step replay from every tip (but the centre) under every replay instance.
    X, TH = _replay_pairs(ev, b, x, opts)
    sr = step_ratio(ev, b, X, TH, k)
    step_max = float(np.nanmax(sr)) if np.any(~np.isnan(sr)) else float("nan")
    # Refine the worst instance of every tip (pattern search over the active axes); in 3-D only from
    # tips some instance reaches with a bounded ||G||.
    step0 = es.spacing(opts.verify_samples)
    dims = np.flatnonzero(es.active)
    live = np.isfinite(best) if spatial else np.ones(n, bool)
    for level in range(1, opts.verify_refine + 1):
        h = step0 / 2 ** level
        for dmn in dims:
            for sgn in (-1.0, 1.0):
                if not live.any():
                    break
                c = _poll(es, th_best[live], dmn, sgn * h[dmn])
                g1 = pair_g(x[live], c)
                upd = g1 > best[live]
                ii = np.flatnonzero(live)[upd]
                best[ii] = g1[upd]
                th_best[ii] = c[upd]
    # Refine the position of the worst tips inside the ball (with their instance).
    top = np.argsort(-best)[:8]
    xt, tt, bt = x[top].copy(), th_best[top].copy(), best[top].copy()
    hx = radius / (math.sqrt if d == 2 else math.cbrt)(opts.verify_disk + 1)
    moves = [sg * e for e in np.eye(d) for sg in (1.0, -1.0)] if d == 2 else np.vstack([np.eye(3), -np.eye(3)])
    for level in range(opts.verify_refine):
        h = hx / 2 ** level
        for dv in moves:
            c = xt + h * dv
            off = c - b
            rr = np.linalg.norm(off, axis=-1)
            c = np.where((rr > radius)[:, None], b + off * (radius / np.maximum(rr, 1e-300))[:, None], c)
            g1 = pair_g(c, tt)
            upd = g1 > bt
            bt[upd] = g1[upd]
            xt[upd] = c[upd]
        for dmn in dims:
            for sgn in (-1.0, 1.0):
                c = _poll(es, tt, dmn, sgn * step0[dmn] / 2 ** (opts.verify_refine + level))
                g1 = pair_g(xt, c)
                upd = g1 > bt
                bt[upd] = g1[upd]
                tt[upd] = c[upd]
    worst = float(max(best.max(), bt.max()))
    iw = int(np.argmax(bt))
    # The nonlinear step at the refined worst pairs too.
    farw = np.linalg.norm(xt - b, axis=-1) > 1e-9
    if np.any(farw):
        sr2 = step_ratio(ev, b, xt[farw], tt[farw], k)
        if np.any(~np.isnan(sr2)):
            step_max = float(np.nanmax(np.concatenate([[step_max] if not math.isnan(step_max) else [], sr2[~np.isnan(sr2)]])))
    if worst == -np.inf:
        worst = float("nan")  # no tip of the ball is reachable: nothing to certify
    return {"G_norm": worst, "grid_G_norm": grid_max, "step_ratio": step_max,
            "worst_tip": xt[iw].tolist(), "worst_theta": tt[iw].tolist(),
            "tips": n, "instances": m, "noise_corners": corners, "pairs": int(reach.sum()),
            "reachable_tip_share": float(reach.any(axis=1).mean()), "singular_pairs": n_singular,
            "step_pairs": int(len(X))}


def _g3(ev: SpatialModel, x: np.ndarray, th: np.ndarray, k: float, singular: bool) -> np.ndarray:
    """Worst ||G|| per pair (n,) in 3-D: -inf where the truth cannot reach the tip, +inf where it can
    and the ball is not singular-free."""
    M, ok = ev.maps_paired(x, th)
    g = gnorm3_grid(M, k)[0].reshape(M.shape[:-2])
    return _mask3(g.max(axis=-1) if g.ndim == 2 else g, ok, singular)


def _mask3(g: np.ndarray, ok: np.ndarray, singular: bool) -> np.ndarray:
    """3-D ``||G||`` values ``g`` of pairs (any shape, as ``ok``) for the verification: +inf where not
    finite or (``singular``: the ball is not singular-free) wherever the pair is valid, -inf where the
    truth cannot reach the tip."""
    g = np.where(np.isfinite(g), g, np.inf)
    if singular:
        g = np.where(ok, np.inf, g)
    return np.where(ok, g, -np.inf)


def _poll(es, th: np.ndarray, dim: int, h: float) -> np.ndarray:
    """``th`` moved by ``h`` along error axis ``dim``: clipped to the box, wrapped on a periodic axis."""
    c = th.copy()
    if es.periodic[dim]:
        span = es.hi[dim] - es.lo[dim]
        c[:, dim] = es.lo[dim] + np.mod(c[:, dim] + h - es.lo[dim], span)
    else:
        c[:, dim] = np.clip(c[:, dim] + h, es.lo[dim], es.hi[dim])
    return c


def _lower_gain(ev: Evaluator, a, b, k: float, radius: float, opts: GainOptions, factor: float = 0.8,
               tries: int = 12):
    """The largest gain ``k factor^j`` whose nonlinear step ratio (verification grid) is below 1,
    re-verified in full; None if none is found. Smaller steps make the quasi-static step closer to
    its linearisation, at the price of a larger ``||G||`` (closer to 1)."""
    bb = np.asarray(b, float)
    X, TH = _replay_pairs(ev, bb, ball_tips(bb, radius, opts.verify_disk, opts.verify_ring), opts)
    for j in range(1, tries + 1):
        kj = k * factor ** j
        sr = step_ratio(ev, bb, X, TH, kj)
        if not np.nanmax(sr) < 1.0:
            continue
        v = verify_segment(ev, a, b, kj, radius, opts)
        if v["G_norm"] < 1.0 and v["step_ratio"] < 1.0:
            return kj, v
        if not v["G_norm"] < 1.0:
            return None  # smaller gains only bring ||G|| closer to (and past) 1
    return None
