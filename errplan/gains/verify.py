"""The verification of a certificate, one routine for the plane and 3-D: the worst ``||G||`` over a
segment's ball on a denser sample than the optimiser's, refined by pattern searches, and the nonlinear
one-step replay (:func:`verify_segment`); a lower gain where only the nonlinear step fails (:func:`_lower_gain`)."""
from __future__ import annotations

import math

import numpy as np

from ..fields import Evaluator
from .options import GainOptions
from .physics import (SpatialModel, _instance_grid, _is_spatial, _pairs, _worst_g, ball_tips, gnorm3_pairs,
                      step_ratio, worst_instances)


def _pair_g(ev, k: np.ndarray, singular: np.ndarray):
    """``g(x, th, i)``: the worst ``||G||`` of pairs ``(x[j], th[j])`` (n,) at gains ``k[i]`` (``i`` the
    pairs' segment indices), -inf where the truth cannot reach the tip, +inf where it can but the
    controller's Jacobian is singular (or, in 3-D, the segment's ball is not singular-free, ``singular[i]``):
    planar from the conformal parts over the controller's noise corners, 3-D from the compiled sigma_max
    of ``I - k M``."""
    if _is_spatial(ev):
        return lambda x, th, i: _g3(ev, x, th, k[i], singular[i])

    def g1(x, th, kk):
        mu, nu, ok, reach = ev.parts_tracked(x, th)
        return _worst_g(mu, nu, reach, ok, kk)

    return lambda x, th, i: _per_segment(lambda xs, ts, s: g1(xs, ts, k[s][:, None]), x, th, i)


def _per_segment(f, x: np.ndarray, th: np.ndarray, i: np.ndarray) -> np.ndarray:
    """``f(x, th, s)`` with ``s`` the pairs' segment indices (``i``), the values each segment's pairs get
    on their own: the planar physics (numpy) is elementwise but for one choice per call, the
    straight-shaft fast path when no pair of the call carries a load (the flexed beam's formulas at zero
    load agree only to rounding). So the segments whose pairs carry some load go in one call and those
    whose pairs carry none in another: each pair takes the path it takes when its segment is verified
    alone, in at most two calls."""
    out = np.empty(len(x))
    if not len(x):
        return out
    seg_loaded = np.zeros(int(i.max()) + 1, bool)
    seg_loaded[i[th[:, 2] != 0]] = True
    loaded = seg_loaded[i]
    for sel in (loaded, ~loaded):
        if np.any(sel):
            out[sel] = f(x[sel], th[sel], i[sel])
    return out


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
    return verify_segments(ev, [(start, end, k, radius)], opts)[0]


def verify_segments(ev: Evaluator, segments, opts: GainOptions) -> list[dict]:
    """:func:`verify_segment` of every ``(start, end, k, radius)`` of ``segments`` at once: the segments'
    tips and pairs go through the kernels together (one call per pattern-search move for all of them),
    each segment's search its own (pairs are independent: the same values as one segment at a time)."""
    if not len(segments):
        return []
    es = ev.errors
    spatial = _is_spatial(ev)
    S = len(segments)
    B = np.array([np.asarray(sg[1], float) for sg in segments])          # (S, d)
    K = np.array([float(sg[2]) for sg in segments])
    R = np.array([float(sg[3]) for sg in segments])
    d = B.shape[1]
    sing = np.array([bool(spatial and not ev.singular_free(B[i], R[i])) for i in range(S)])
    xs = [ball_tips(B[i], R[i], opts.verify_disk, opts.verify_ring) for i in range(S)]
    n = len(xs[0])
    x = np.concatenate(xs)                                               # (S n, d)
    seg = np.repeat(np.arange(S), n)                                     # segment of each tip
    th = _instance_grid(ev, opts.verify_samples)
    m = len(th)
    # The grid: one call per segment (n m pairs each: large enough, and the maps of one segment at a time
    # stay small in memory); of it, each tip's worst instance (value and first index)
    best = np.empty(S * n)
    j = np.empty(S * n, np.int64)
    reach = np.empty((S * n, m), bool)
    n_sing = np.zeros(S, np.int64)
    for i in range(S):
        rows = slice(i * n, (i + 1) * n)
        if spatial:
            M, ok = ev.maps(xs[i], th)  # (n, m, 3, 3), or (n, m, c, 3, 3) over the flexion controller's noise corners
            best[rows], j[rows] = worst_instances(M, ok, K[i], sing[i])  # compiled, most pairs skipped by a bound
            reach[rows] = ok
            n_sing[i] = int(ok.sum()) if sing[i] else 0
        else:
            mu, nu, rch, ok = _pairs(ev, xs[i], th)
            G = _worst_g(mu, nu, rch, ok, K[i])
            j[rows] = np.argmax(G, axis=1)
            best[rows] = G[np.arange(n), j[rows]]
            reach[rows] = rch
            n_sing[i] = int((rch & ~ok).sum())
            corners = int(mu.shape[-1])
    if spatial:
        corners = ev.noise_corners
    pair_g = _pair_g(ev, K, sing)
    grid_max = best.reshape(S, n).max(axis=1)
    th_best = th[j].copy()
    # Nonlinear one-step replay from every tip (but the centre) under every replay instance.
    rp = [_replay_pairs(ev, B[i], xs[i], opts) for i in range(S)]
    nrp = np.array([len(X) for X, _ in rp])
    rseg = np.repeat(np.arange(S), nrp)
    sr = step_ratio(ev, B[rseg], np.concatenate([X for X, _ in rp]), np.concatenate([T for _, T in rp]), K[rseg])
    step_max = []
    for part in np.split(sr, np.cumsum(nrp)[:-1]):
        step_max.append(float(np.nanmax(part)) if np.any(~np.isnan(part)) else float("nan"))
    # Refine the worst instance of every tip (pattern search over the active axes); in 3-D only from
    # tips some instance reaches with a bounded ||G||.
    step0 = es.spacing(opts.verify_samples)
    dims = np.flatnonzero(es.active)
    live = np.isfinite(best) if spatial else np.ones(S * n, bool)
    il = np.flatnonzero(live)
    for level in range(1, opts.verify_refine + 1):
        h = step0 / 2 ** level
        for dmn in dims:
            for sgn in (-1.0, 1.0):
                if not len(il):
                    break
                c = _poll(es, th_best[il], dmn, sgn * h[dmn])
                g1 = pair_g(x[il], c, seg[il])
                upd = g1 > best[il]
                ii = il[upd]
                best[ii] = g1[upd]
                th_best[ii] = c[upd]
    # Refine the position of the worst tips inside the ball (with their instance).
    top = np.concatenate([i * n + np.argsort(-best[i * n:(i + 1) * n])[:8] for i in range(S)])
    tseg = seg[top]
    xt, tt, bt = x[top].copy(), th_best[top].copy(), best[top].copy()
    hx = R / (math.sqrt if d == 2 else math.cbrt)(opts.verify_disk + 1)   # (S,)
    moves = [sg * e for e in np.eye(d) for sg in (1.0, -1.0)] if d == 2 else np.vstack([np.eye(3), -np.eye(3)])
    bt_, rt = B[tseg], R[tseg]
    for level in range(opts.verify_refine):
        h = (hx / 2 ** level)[tseg][:, None]
        for dv in moves:
            c = xt + h * dv
            off = c - bt_
            rr = np.linalg.norm(off, axis=-1)
            c = np.where((rr > rt)[:, None], bt_ + off * (rt / np.maximum(rr, 1e-300))[:, None], c)
            g1 = pair_g(c, tt, tseg)
            upd = g1 > bt
            bt[upd] = g1[upd]
            xt[upd] = c[upd]
        for dmn in dims:
            for sgn in (-1.0, 1.0):
                c = _poll(es, tt, dmn, sgn * step0[dmn] / 2 ** (opts.verify_refine + level))
                g1 = pair_g(xt, c, tseg)
                upd = g1 > bt
                bt[upd] = g1[upd]
                tt[upd] = c[upd]
    # The nonlinear step at the refined worst pairs too.
    farw = np.linalg.norm(xt - bt_, axis=-1) > 1e-9
    sr2 = np.full(len(xt), np.nan)
    if np.any(farw):
        fi = np.flatnonzero(farw)
        if spatial:  # compiled physics, pair by pair: all segments at once
            sr2[fi] = step_ratio(ev, bt_[fi], xt[fi], tt[fi], K[tseg[fi]])
        else:
            sr2[fi] = _per_segment(lambda xs, ts, s: step_ratio(ev, B[s], xs, ts, K[s]), xt[fi], tt[fi], tseg[fi])
    out = []
    reach_s = reach.reshape(S, n, m)
    nt = min(8, n)  # refined tips per segment
    for i in range(S):
        sl = slice(i * nt, (i + 1) * nt)
        bti, xti, tti = bt[sl], xt[sl], tt[sl]
        smax = step_max[i]
        s2 = sr2[sl][farw[sl]]
        if np.any(~np.isnan(s2)):
            smax = float(np.nanmax(np.concatenate([[smax] if not math.isnan(smax) else [], s2[~np.isnan(s2)]])))
        worst = float(max(best[i * n:(i + 1) * n].max(), bti.max()))
        iw = int(np.argmax(bti))
        if worst == -np.inf:
            worst = float("nan")  # no tip of the ball is reachable: nothing to certify
        out.append({"G_norm": worst, "grid_G_norm": float(grid_max[i]), "step_ratio": smax,
                    "worst_tip": xti[iw].tolist(), "worst_theta": tti[iw].tolist(),
                    "tips": n, "instances": m, "noise_corners": corners, "pairs": int(reach_s[i].sum()),
                    "reachable_tip_share": float(reach_s[i].any(axis=1).mean()), "singular_pairs": int(n_sing[i]),
                    "step_pairs": int(nrp[i])})
    return out


def _g3(ev: SpatialModel, x: np.ndarray, th: np.ndarray, k, singular) -> np.ndarray:
    """Worst ||G|| per pair (n,) in 3-D at gains ``k`` (scalar or (n,)): -inf where the truth cannot
    reach the tip, +inf where it can and the ball is not singular-free (``singular``, scalar or (n,))."""
    M, ok = ev.maps_paired(x, th)
    kk = np.broadcast_to(np.reshape(k, np.shape(k) + (1,) * (M.ndim - 3)), M.shape[:-2])
    g = gnorm3_pairs(M, kk.ravel()).reshape(M.shape[:-2])
    return _mask3(g.max(axis=-1) if g.ndim == 2 else g, ok, singular)


def _mask3(g: np.ndarray, ok: np.ndarray, singular) -> np.ndarray:
    """3-D ``||G||`` values ``g`` of pairs (any shape, as ``ok``) for the verification: +inf where not
    finite or (``singular``: the ball is not singular-free; a bool or an array broadcasting with ``ok``)
    wherever the pair is valid, -inf where the truth cannot reach the tip."""
    g = np.where(np.isfinite(g), g, np.inf)
    g = np.where(ok & singular, np.inf, g)
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
