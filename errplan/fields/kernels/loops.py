"""The entry loops Python calls: the worst case of a tile of tips (:func:`worst_case_tile`, compiled
once per dimension and use by :func:`_per_dim`), the lanes that finish its straight-shaft refinements,
and the motion maps of (tip, instance) pairs (:func:`motion_maps`)."""
from __future__ import annotations

import math

import numpy as np

from ...jit import copy_function, kernel_array, njit
from ...kinematics.urdf.chain import map_geometry, map_state, reach_boundary
from .instance import _corners_out2, _instance2, _instance3, _lever_out, _levers2, _levers3
from .metrics import _phimax, gval, phi_bound
from .reach import _planar_reachable, _tip_reach, _tip_reach2
from .search import (LANE_TIPS, _far, _gnorm_below, _golden_gain, _gval_skip, _gval_ub_at, _neighbour, _pattern, _pattern_g, _pattern_lanes, _peak_raise,
                     _rho_final, _sample_table)


def worst_case_tile(X, *args) -> None:
    """Worst case at every tip ``X[i]`` (n, d) over the error set sampled at ``grid`` (m, na); the other
    arguments as :func:`_search`'s.

    Writes ``out_valid`` (robustly reachable), ``out_g`` (worst ||G|| at gain ``k``), ``out_p``
    (worst |phi_max|, if ``want_phi``), ``out_rho``/``out_k`` (rho*, k*, if ``want_rho``; rho*
    certified by a refined worst case at k*, the scenario gain used where it does better).
    One search for both dimensions and both uses; the copy is picked here, in Python, so that a command
    compiles only the search of its own dimension (a compiled dispatch typed both), and without the exact
    |phi_max| unless it asks for it (its search is a fifth of a cold 3-D compile).

    Where the error set is straight shafts only (no load axis active), the search records the starts of
    its worst-||G|| refinements and :func:`_lanes_tile` (an entry of its own per dimension) runs
    them as lanes afterwards (:func:`run_lanes`): a command whose error sets all carry a load never compiles
    the lanes.
    """
    d, n = X.shape[1], X.shape[0]
    lanes = _Lanes(d, n)
    _TILES[d, bool(args[_WANT_PHI])](X, *args, *lanes.bufs)
    if lanes.count[0] > 0:
        run_lanes(lanes, *args)


class _Lanes:
    """The buffers in which a search records its lanes' starts (:func:`_search`, :func:`_lanes_tile`): at
    most two per tip."""

    def __init__(self, d: int, n: int):
        ns = 2 * n
        self.d = d
        self.count = np.zeros(1, np.int64)
        self.bufs = (np.empty((d, ns)), np.empty((d, ns)), np.empty(ns), np.empty(ns, np.bool_),
                     np.empty(ns, np.bool_), np.empty(ns, np.int64), self.count)


def run_lanes(lanes: _Lanes, grid, counts, active, periodic, lo, hi, step0, base_port, est, L, k, arm, chain,
              rmap, refine, extra, second_start, want_phi, want_rho, out_valid, out_g, out_p, out_rho, out_k):
    """The recorded lanes of a tile (:func:`_lanes_tile`), in the copy of its dimension."""
    XS, TH, best, known, live, owner, count = lanes.bufs
    _LANE_TILES[lanes.d](int(count[0]), XS, TH, best, known, live, owner, step0, lo, hi, active, periodic,
                         refine, extra, base_port, est, L, k, arm, chain, rmap, want_rho, out_valid, out_g,
                         out_p, out_rho, out_k)


def load_lanes(d: int, grid, counts, active, *args) -> None:
    """Load (or compile) the lanes of dimension ``d`` now if the error set (``grid``, ``active``: the
    search's arguments) can use them: straight shafts only (:func:`_search`'s ``lanes``). Run on no
    searches, with the search's own arguments (one specialization)."""
    if not (grid.shape[1] > d and (np.any(grid[:, d] != 0.0) or np.any(active[d:]))):
        out = [np.zeros(0, bool)] + [np.zeros(0) for _ in range(4)]
        run_lanes(_Lanes(d, 0), grid, counts, active, *args, *out)


def _lanes_tile(ns, XS, TH, best, known, live, owner, step0, lo, hi, active, periodic, refine, extra,
                base_port, est, L, k, arm, chain, rmap, want_rho, out_valid, out_g, out_p, out_rho, out_k):
    """The ``ns`` worst-||G|| refinements a search recorded (:func:`_search`), as lanes
    (:func:`_pattern_lanes`), LANE_TIPS tips at a time (a tip's searches are consecutive and stay in one
    block); compiled once per dimension (:func:`_per_dim`: ``_lanes_tile2``, ``_lanes_tile3``)."""
    d = _D
    O = np.empty((7 if d == 2 else 4, 2 * LANE_TIPS))
    okl = np.empty(2 * LANE_TIPS, np.bool_)
    s0 = 0
    while s0 < ns:
        s1 = s0
        tips = 0
        while s1 < ns and tips < LANE_TIPS:
            i_ = owner[s1]
            while s1 < ns and owner[s1] == i_:
                s1 += 1
            tips += 1
        _pattern_lanes(d, k, s0, s1, XS, TH, best, known, live, owner, step0, lo, hi, active, periodic, refine,
                       extra, base_port, est, L, arm, chain, rmap, O, okl, want_rho, out_valid, out_g, out_p,
                       out_rho, out_k)
        s0 = s1


@njit(cache=True, error_model="numpy", literal_args="d")
def _lazy_g(d, Ms, Pbs, k, vals, kn, j):
    """``vals[j]``, the sample's ||G|| at gain ``k`` (:func:`gval`), computed now if not yet (``kn[j]``)."""
    if not kn[j]:
        vals[j] = gval(d, Ms, Pbs, j, k)
        kn[j] = True
    return vals[j]


@njit(cache=True, error_model="numpy", literal_args="d")
def _g_below(d, Ms, Pbs, k, vals, kn, j, thr):
    """The sample's ||G|| is certainly below ``thr``: its value if known, else its tight bound
    (:func:`_gnorm_below`; a sample not yet computed is a loaded 3-D one)."""
    if kn[j]:
        return vals[j] < thr
    return _gnorm_below(Ms, j, k, thr)


@njit(cache=True, error_model="numpy", literal_args="d")
def _starts_lazy(d, Ms, Pbs, k, vals, kn, m, na, second_start, pos, stride, counts, periodic, nbr, st):
    """The starts of the worst-||G|| refinement, ``st[0]`` the first sample attaining the largest value,
    ``st[1]`` the second start (-1 for none), exactly as :func:`_search` chooses them from every value,
    computing a loaded sample's value (:func:`_lazy_g`) only where a comparison needs it: a sample whose
    bound is below the value it is compared with (:func:`_g_below`) loses that comparison whatever its
    value. False (a value is NaN: the comparisons are then not those of the bounds) and the caller
    chooses from every value."""
    # the worst: a running maximum in index order, a sample that cannot beat it skipped
    jbest = 0
    vb = _lazy_g(d, Ms, Pbs, k, vals, kn, 0)
    for j in range(1, m):
        if _g_below(d, Ms, Pbs, k, vals, kn, j, vb):
            continue
        v = _lazy_g(d, Ms, Pbs, k, vals, kn, j)
        if not v == v:
            return False
        if v > vb:
            jbest, vb = j, v
    if not vb == vb:
        return False
    j2 = -1
    v2 = 0.0
    if second_start > 0 and m > 1:
        for j in range(m):
            if not _far(j, jbest, pos, counts, periodic, na):
                continue
            if j2 >= 0 and _g_below(d, Ms, Pbs, k, vals, kn, j, v2):
                continue
            v = _lazy_g(d, Ms, Pbs, k, vals, kn, j)
            if not v == v:
                return False
            if j2 >= 0 and not v > v2:
                continue
            lm = True  # _local_max: no neighbour above
            for c in range(nbr.shape[1]):
                q = nbr[j, c]
                if q < 0 or _g_below(d, Ms, Pbs, k, vals, kn, q, v):
                    continue
                vq = _lazy_g(d, Ms, Pbs, k, vals, kn, q)
                if not vq == vq:
                    return False
                if vq > v:
                    lm = False
                    break
            if lm:
                j2, v2 = j, v
        if j2 >= 0:
            # the values _peak_raise reads: up to two steps either way along each axis
            for ax in range(na):
                if counts[ax] < 2:
                    continue
                for off in (-2, -1, 1, 2):
                    q = _neighbour(j2, ax, off, pos, stride, counts, periodic)
                    if q >= 0:
                        vq = _lazy_g(d, Ms, Pbs, k, vals, kn, q)
                        if not vq == vq:
                            return False
            if not (v2 + 2.0 * _peak_raise(vals, j2, pos, stride, counts, periodic, na)
                    >= vb - second_start * max(1.0, abs(vb))):
                j2 = -1
    st[0] = jbest
    st[1] = j2
    return True


def _search(X, grid, counts, active, periodic, lo, hi, step0, base_port, est, L, k, arm, chain, rmap,
            refine, extra, second_start, want_phi, want_rho, out_valid, out_g, out_p, out_rho, out_k,
            XS, TH, bestL, knownL, liveL, ownerL, nlanes):
    """The search of :func:`worst_case_tile`; compiled once per dimension and use (:func:`_per_dim`:
    ``_tile2``, ``_tile3`` with |phi_max|, ``_tile2g``, ``_tile3g`` without), ``d``, ``_PHI`` and the pattern
    search ``_PAT`` constants of the module globals there. ``want_phi`` is read in Python (:func:`worst_case_tile` picks the copy).
    ``XS``, ``TH``, ``bestL``, ``knownL``, ``liveL``, ``ownerL`` (room for two per tip, :class:`_Lanes`): where
    the error set is straight shafts only, the starts of the worst-||G|| refinements, left for
    :func:`_lanes_tile`; ``nlanes[0]``: how many."""
    d = _D
    n = X.shape[0]
    m, na = grid.shape
    vals_g = np.empty(m)
    vals_p = np.empty(m)
    Ms = np.empty((m, d, d))
    Pbs = np.empty((m, 5))
    M = np.empty((1, d, d))
    P1 = np.empty((1, 5))
    S = np.zeros((8, 3, 3))
    V = np.zeros((9, 3))
    th = np.empty(na)
    cand = np.empty(na)
    results = np.empty(2)
    idx = np.empty(m, np.int64)
    trM = np.empty(m)  # the sampled M's traces and squared Frobenius norms (_golden_gain, _gval_ub)
    f2M = np.empty(m)
    st = np.empty(2, np.int64)
    kn = np.ones(m, np.bool_)  # vals_g[j] computed (lazy: a loaded 3-D sample's value only where needed)
    lkM = np.empty(m)  # per sampled instance: the last gain of its exact ||G|| and that value (_golden_gain)
    lvM = np.empty(m)
    pos = np.empty((m, na), np.int64)
    stride = np.empty(na, np.int64)
    nbr = np.empty((m, 2 * na), np.int64)
    _sample_table(counts, periodic, na, m, pos, stride, nbr)
    nnb = nbr.shape[1]
    tabfar = m <= 256  # farT[i, j]: sample j more than one step from sample i (_far), once per tile
    farT = np.zeros((m, m) if tabfar else (1, 1), np.bool_)
    for i in range(m if tabfar else 0):
        for j in range(m):
            farT[i, j] = _far(j, i, pos, counts, periodic, na)
    geo = map_geometry(rmap)  # the map's fields read once (chain.py: a namedtuple's arrays cost per read)
    mst = rmap.state
    # 3-D with a load: samples at tau = 0 repeat along the direction axis psi (the last one)
    dup = d == 3 and na == 5 and counts[4] > 1
    full = _PHI or want_rho  # the sampled M themselves (|phi_max|, rho*'s gain bracket), not only ||G||
    # the straight-shaft samples (no load), all at once per tip (_levers2/_levers3): lever[j] their column
    # in G, -1 for a loaded sample; in 3-D only where the search needs no M (``bulk``: _levers3 forms none)
    bulk = d == 2 or not full
    lever = np.full(m, -1, np.int64)
    nl = 0
    for j in range(m):
        if na <= d or grid[j, d] == 0.0:
            lever[j] = nl
            nl += 1
    G = np.empty((d, nl))
    for j in range(m):
        if lever[j] >= 0:
            for a in range(d):
                G[a, lever[j]] = grid[j, a]
    O = np.empty((7 if d == 2 else 4, nl))
    okl = np.empty(nl, np.bool_)
    # The refinement of the worst ||G|| as lanes where every instance the pattern can poll is a straight
    # shaft (no load axis active, none sampled): each tip's searches are recorded here (XS, TH, bestL,
    # knownL, liveL, ownerL; nlanes[0] of them) and run together afterwards, then its results completed
    # (_lanes_tile, an entry of its own: worst_case_tile).
    lanes = nl == m
    for a in range(d, na):
        lanes = lanes and not active[a]
    # planar: the straight samples at the corners of the port box, whose wrists are tested first
    corners = np.empty(m, np.int64)
    nc = 0
    for j in range(m if d == 2 else 0):
        if lever[j] >= 0:
            c_ = True
            for a in range(d):
                c_ = c_ and (pos[j, a] == 0 or pos[j, a] == counts[a] - 1)
            if c_:
                corners[nc] = j
                nc += 1
    corners = corners[:nc]
    # the loaded 3-D samples' ||G|| only where the choice of the starts needs it (_starts_lazy): their full M
    # is there (_instance3 forms it under a load), so is a tight bound of the value (_gnorm_below)
    lazy = d == 3
    XT = np.empty((d, nl))  # the tip, once per sampled straight instance (_levers2/_levers3 take one per lane)
    ns = 0
    for ii in range(n):
        x = X[ii]
        ok = True
        known = False
        nlz = 0  # this tip's loaded samples whose value is not computed yet (lazy)
        if d == 3:
            tr = _tip_reach(x, base_port, lo, hi, L, rmap)
            ok = tr != 0
            known = tr == 1
            if tr == 2:
                ok = not _lever_out(x, grid, base_port, L, rmap)
        else:
            ok = not _corners_out2(x, grid, corners, base_port, L, arm)
            known = ok and _tip_reach2(x, base_port, lo, hi, L, arm) == 1
        if ok and bulk and nl > 0:
            for q in range(nl):
                for a in range(d):
                    XT[a, q] = x[a]
            if d == 2:
                _levers2(XT, G, nl, base_port, est, L, k, O, okl)
            else:
                _levers3(XT, G, nl, base_port, est, L, k, O, okl)
        for j in range(m if ok else 0):
            q = lever[j] if bulk else -1
            if q >= 0:
                okj = okl[q]
                if okj and not known:
                    if d == 2:
                        okj = _planar_reachable(arm, O[1, q], O[2, q])
                    else:
                        w0, w1, w2 = O[1, q], O[2, q], O[3, q]
                        s_, ix, iy, iz = map_state(geo, mst, w0, w1, w2)
                        okj = s_ == 1 or (s_ == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))
                if not okj:
                    ok = False
                    break
                vals_g[j] = O[0, q]
                if d == 2 and full:
                    Ms[j, 0, 0], Ms[j, 0, 1], Ms[j, 1, 0], Ms[j, 1, 1] = O[3, q], O[4, q], O[5, q], O[6, q]
                continue
            if dup and grid[j, 3] == 0.0 and j % counts[4] != 0:
                j0 = j - j % counts[4]  # the same instance: tau = 0 has no direction
                for a in range(d):
                    for b in range(d):
                        Ms[j, a, b] = Ms[j0, a, b]
                for a in range(5):
                    Pbs[j, a] = Pbs[j0, a]
                vals_g[j] = vals_g[j0]
                continue
            if d == 2:
                okj, w0, w1, w2 = _instance2(x, grid[j], base_port, est, L, arm, Ms, j, S, V, known), 0.0, 0.0, 0.0
            else:
                okj, w0, w1, w2 = _instance3(x, grid[j], base_port, est, L, Ms, Pbs, j, S, V, full)
            if okj and d == 3 and not known:
                s_, ix, iy, iz = map_state(geo, mst, w0, w1, w2)
                okj = s_ == 1 or (s_ == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))
            if not okj:
                ok = False
                break
            if lazy and not Pbs[j, 0] == Pbs[j, 0]:
                kn[j] = False  # (a loaded 3-D sample: its ||G|| when a choice below needs it, _lazy_g)
                nlz += 1
                continue
            vals_g[j] = gval(d, Ms, Pbs, j, k)
            kn[j] = True
        if _PHI and ok:
            if d == 2:
                for j in range(m):
                    vals_p[j] = _phimax(d, Ms, j)
            else:
                # branch and bound: exact |phi_max| only where the cheap bound could beat the best
                # exact value so far; elsewhere the bound stands in (never above the best exact)
                for j in range(m):
                    vals_p[j] = phi_bound(Ms, j)
                order = np.argsort(-vals_p)
                best_exact = -1.0
                for q in range(m):
                    j = order[q]
                    if vals_p[j] <= best_exact:
                        vals_p[j] = min(vals_p[j], best_exact)
                        continue
                    vals_p[j] = _phimax(d, Ms, j)
                    best_exact = max(best_exact, vals_p[j])
        for which in range((2 if _PHI else 1) if ok else 0):
            vals = vals_g if which == 0 else vals_p
            # the lazy choice only where a loaded sample's value is still unknown: with every value known
            # (no load in the error set, or none sampled at this tip) the plain choice below is the same
            # and far cheaper (the lazy helpers' calls are not inlined: numba counts references per call)
            if which == 0 and nlz > 0 and _starts_lazy(d, Ms, Pbs, k, vals_g, kn, m, na, second_start, pos,
                                                       stride, counts, periodic, nbr, st):
                jbest, j2 = st[0], st[1]
            else:
                if which == 0 and nlz > 0:  # a NaN value: every value, and the choice as below
                    for j in range(m):
                        if not kn[j]:
                            vals_g[j] = gval(d, Ms, Pbs, j, k)
                            kn[j] = True
                jbest = 0
                for j in range(1, m):
                    if vals[j] > vals[jbest]:
                        jbest = j
                # a second start: the best sampled local maximum more than one step from the worst.
                # :func:`_far`, :func:`_local_max` and :func:`_peak_raise` written out here, on the tile's
                # tables (farT, nbr): per tip, their calls (each with its arrays' reference counts) and
                # branches cost more than the comparisons themselves (about a fifth of a planar search)
                j2 = -1
                if second_start > 0 and m > 1:
                    for j in range(m):
                        if j2 >= 0 and not vals[j] > vals[j2]:  # the cheap comparison first
                            continue
                        if tabfar:
                            if not farT[jbest, j]:
                                continue
                        elif not _far(j, jbest, pos, counts, periodic, na):
                            continue
                        vj = vals[j]
                        lm = True
                        for c in range(nnb):
                            q = nbr[j, c]
                            if q >= 0:
                                lm = lm & (not vals[q] > vj)
                        if lm:
                            j2 = j
                    if j2 >= 0:
                        # _peak_raise(vals, j2, ...): nbr holds its one-step neighbours (-1 outside the box;
                        # an axis of fewer than 2 samples is skipped before they are read)
                        f0 = vals[j2]
                        pr = 0.0
                        for ax in range(na):
                            s_ax = counts[ax]
                            if s_ax < 2:
                                continue
                            jm = nbr[j2, 2 * ax]
                            jp = nbr[j2, 2 * ax + 1]
                            if s_ax == 2:
                                r = abs(f0 - vals[jp if jp >= 0 else jm])
                            elif jm >= 0 and jp >= 0:
                                fm, fp = vals[jm], vals[jp]
                                curv = 2 * f0 - fm - fp
                                r = (fp - fm) ** 2 / (8 * curv) if curv > 0 else 0.0
                            else:
                                # on a face of a non-periodic axis of 3 or more samples: the two inward
                                inward = 1 if jm < 0 else -1
                                j1_ = jp if inward == 1 else jm
                                j2_ = j2 + 2 * inward * stride[ax]
                                f1, f2 = vals[j1_], vals[j2_]
                                c2 = 0.5 * (f0 - 2 * f1 + f2)
                                bb = f0 - f1 + c2
                                r = 0.0
                                if c2 < 0:
                                    xv = -bb / (2 * c2)
                                    if -1 < xv < 0:
                                        r = -bb * bb / (4 * c2)
                            if not math.isfinite(r):
                                pr = math.inf
                                break
                            pr += max(r, 0.0)
                        v = vals[jbest]
                        if not (vals[j2] + 2.0 * pr >= v - second_start * max(1.0, abs(v))):
                            j2 = -1
            best_all = -math.inf
            for start in (jbest, j2):
                if start < 0:
                    continue
                if lanes and which == 0:  # run with the other searches afterwards (_lanes_tile)
                    for a in range(d):
                        XS[a, ns] = x[a]
                        TH[a, ns] = grid[start, a]
                    bestL[ns] = vals[start]
                    knownL[ns] = known
                    liveL[ns] = True
                    ownerL[ns] = ii
                    ns += 1
                    continue
                for i in range(na):
                    th[i] = grid[start, i]
                b, ok = _PAT(d, which, k, x, th, vals[start], step0, lo, hi, active, periodic, refine, extra,
                             base_port, est, L, arm, chain, rmap, M, P1, S, V, cand, known)
                if not ok:
                    break
                best_all = max(best_all, b)
            if not ok:
                break
            results[which] = best_all
        if not ok:
            out_valid[ii] = False
            out_g[ii] = np.nan
            out_p[ii] = np.nan
            out_rho[ii] = np.nan
            out_k[ii] = np.nan
            continue
        out_valid[ii] = True
        out_g[ii] = results[0]
        out_p[ii] = results[1] if _PHI else np.nan
        if want_rho:
            rs, ks = _golden_gain(d, Ms, Pbs, m, 60, k, idx, trM, f2M, vals_g, kn, lkM, lvM)
            if ks > 0:
                # certify at k*: the refined worst case over the continuous set at that gain
                jbest = 0
                vbest = -1.0
                for j in range(m):
                    if _gval_ub_at(d, Pbs, j, ks, trM, f2M, lkM, lvM) <= vbest or (
                            lkM[j] != ks and _gval_skip(d, Ms, Pbs, j, ks, trM, f2M, vbest)):
                        continue  # cannot be the worst (trM, f2M, lkM, lvM: filled by _golden_gain)
                    # the value _golden_gain computed at this gain (the same call), else computed here
                    v = lvM[j] if lkM[j] == ks else gval(d, Ms, Pbs, j, ks)
                    if v > vbest:
                        vbest, jbest = v, j
                for i in range(na):
                    th[i] = grid[jbest, i]
                ref, ok = _PAT(d, 0, ks, x, th, vbest, step0, lo, hi, active, periodic, refine, extra,
                               base_port, est, L, arm, chain, rmap, M, P1, S, V, cand, known)
                rs = max(rs, ref) if ok else 1.0
            else:
                rs = 1.0
            if not lanes:
                rs, ks = _rho_final(results[0], rs, ks, k)
            out_rho[ii] = rs  # with lanes: completed by _lanes_tile, once the worst ||G|| is known
            out_k[ii] = ks
        else:
            out_rho[ii] = np.nan
            out_k[ii] = np.nan
    nlanes[0] = ns


def motion_maps(X, TH, base_port, est, L, arm, chain, rmap, out_M, out_ok) -> None:
    """``M = J Jhat^-1`` (into ``out_M`` (n, d, d)) and validity (``out_ok`` (n,)) of instance
    ``TH[i]`` at tip ``X[i]``; invalid rows of ``out_M`` are NaN. The dimension is picked in Python.
    Read-only inputs (broadcast views) are copied: numba types a read-only array apart, and one
    specialization (one compile) serves every caller."""
    X, TH = kernel_array(X), kernel_array(TH)
    (_maps2 if X.shape[1] == 2 else _maps3)(X, TH, base_port, est, L, arm, chain, rmap, out_M, out_ok)


def _motion_maps(X, TH, base_port, est, L, arm, chain, rmap, out_M, out_ok):
    """:func:`motion_maps`' loop; compiled once per dimension (``_maps2``, ``_maps3``) as :func:`_search`."""
    d = _D
    S = np.zeros((8, 3, 3))
    V = np.zeros((9, 3))
    Pb = np.empty((X.shape[0], 5))
    geo = map_geometry(rmap)
    mst = rmap.state
    for i in range(X.shape[0]):
        if d == 2:
            ok, w0, w1, w2 = _instance2(X[i], TH[i], base_port, est, L, arm, out_M, i, S, V, False), 0.0, 0.0, 0.0
        else:
            ok, w0, w1, w2 = _instance3(X[i], TH[i], base_port, est, L, out_M, Pb, i, S, V, True)
        if ok and d == 3:
            s_, ix, iy, iz = map_state(geo, mst, w0, w1, w2)
            ok = s_ == 1 or (s_ == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))
        out_ok[i] = ok
        if not ok:
            for a in range(d):
                for b in range(d):
                    out_M[i, a, b] = np.nan


_D = 0  # the dimension of a kernel made by _per_dim (there a constant of its own globals)
_PHI = True  # whether a search copy computes |phi_max| (_pattern_g and _per_dim(..., phi=False): False)


def _per_dim(f, d: int, phi: bool = True):
    """``f`` compiled for dimension ``d``: a copy of the function whose globals hold ``_D = d``, so that
    ``d = _D`` is a compile-time constant (numba freezes global numbers): the branches of the other
    dimension are pruned, callees taking ``d`` get the literal. An entry compiled straight from Python,
    not a wrapper passing ``literally(d)`` to a kernel with ``d`` an argument: such a wrapper linked and
    optimized the whole search a second time (about 4 s of a cold 3-D compile, 3 s of a planar one)."""
    g = copy_function(f, f"{f.__name__}{d}{'' if phi else 'g'}", _D=d, _PHI=phi, _PAT=_pattern if phi else _pattern_g)
    return njit(cache=True, error_model="numpy")(g)


_PAT = _pattern  # the pattern search a search copy calls (_per_dim: _pattern_g in the copies without |phi_max|)
_tile2, _tile3 = _per_dim(_search, 2), _per_dim(_search, 3)
_tile2g, _tile3g = _per_dim(_search, 2, phi=False), _per_dim(_search, 3, phi=False)
_TILES = {(2, True): _tile2, (3, True): _tile3, (2, False): _tile2g, (3, False): _tile3g}
_LANE_TILES = {2: _per_dim(_lanes_tile, 2), 3: _per_dim(_lanes_tile, 3)}
_WANT_PHI = _search.__code__.co_varnames.index("want_phi") - 1  # its place in worst_case_tile's *args
_maps2, _maps3 = _per_dim(_motion_maps, 2), _per_dim(_motion_maps, 3)
