"""The search of a tip's worst case: the sample grid's tables and local maxima, the coordinate pattern
search (:func:`_pattern`, and :func:`_pattern_lanes` for many tips' straight-shaft refinements at once),
and the golden section over the gain (:func:`_golden_gain`)."""
from __future__ import annotations

import math

import numpy as np

from ...jit import copy_function, njit
from ...kinematics.urdf.chain import map_geometry, map_state, reach_boundary
from .instance import _instance2, _instance3, _levers2, _levers3
from .metrics import _phimax, gval, phi_bound
from .reach import _planar_reachable

LANE_TIPS = 256  # tips whose worst-||G|| refinements run together (_pattern_lanes): up to twice as many searches
_PHI = True  # whether a pattern search computes |phi_max| (_pattern_g: False)


# ----------------------------------------------------------------------------- the search
@njit(cache=True, error_model="numpy", literal_args="d")
def _poll_value(d, which, Mb, Pb, j, k):
    return gval(d, Mb, Pb, j, k) if which == 0 else _phimax(d, Mb, j)


@njit(cache=True, error_model="numpy")
def _sample_table(counts, periodic, na, m, pos, stride, nbr):
    """Once per tile: the per-axis position ``pos[j, ax]`` of every sample (m, na), the strides of
    the flat sample index (na,) and the flat index of each sample's neighbours ``nbr[j, 2 ax + 0/1]``
    one step down/up axis ``ax`` (-1 outside the box or along an axis with one sample), so that the
    tip loop finds local maxima without integer division."""
    s = 1
    for ax in range(na - 1, -1, -1):
        stride[ax] = s
        s *= counts[ax]
    for j in range(m):
        for ax in range(na):
            pos[j, ax] = (j // stride[ax]) % counts[ax]
    for j in range(m):
        for ax in range(na):
            for o in range(2):
                nbr[j, 2 * ax + o] = _neighbour(j, ax, 2 * o - 1, pos, stride, counts, periodic) if counts[ax] > 1 else -1


@njit(cache=True, error_model="numpy")
def _neighbour(j, ax, off, pos, stride, counts, periodic):
    """Flat index of sample ``j`` moved ``off`` steps along axis ``ax``; -1 outside the box."""
    p = pos[j, ax]
    q = p + off
    if periodic[ax]:
        q %= counts[ax]
    elif q < 0 or q >= counts[ax]:
        return -1
    return j + (q - p) * stride[ax]


@njit(cache=True, error_model="numpy")
def _local_max(vals, j, nbr):
    for c in range(nbr.shape[1]):
        q = nbr[j, c]
        if q >= 0 and vals[q] > vals[j]:
            return False
    return True


@njit(cache=True, error_model="numpy")
def _far(j, i, pos, counts, periodic, na):
    """More than one grid step apart along some axis (periodic axes measured around the circle)."""
    for ax in range(na):
        dd = abs(pos[j, ax] - pos[i, ax])
        if periodic[ax]:
            dd = min(dd, counts[ax] - dd)
        if dd > 1:
            return True
    return False


@njit(cache=True, error_model="numpy")
def _peak_raise(vals, j, pos, stride, counts, periodic, na):
    """Estimated gain of refining sample ``j``: per axis the parabola through it and its neighbours
    (one-sided on a face, where only a vertex inside the box counts), summed over the axes."""
    f0 = vals[j]
    out = 0.0
    for ax in range(na):
        s = counts[ax]
        if s < 2:
            continue
        jm = _neighbour(j, ax, -1, pos, stride, counts, periodic)
        jp = _neighbour(j, ax, 1, pos, stride, counts, periodic)
        if s == 2:
            r = abs(f0 - vals[jp if jp >= 0 else jm])
        elif jm >= 0 and jp >= 0:
            fm, fp = vals[jm], vals[jp]
            curv = 2 * f0 - fm - fp
            r = (fp - fm) ** 2 / (8 * curv) if curv > 0 else 0.0
        else:
            inward = 1 if jm < 0 else -1
            j1 = _neighbour(j, ax, inward, pos, stride, counts, periodic)
            j2 = _neighbour(j, ax, 2 * inward, pos, stride, counts, periodic)
            f1, f2 = vals[j1], vals[j2]
            c2 = 0.5 * (f0 - 2 * f1 + f2)
            bb = f0 - f1 + c2
            r = 0.0
            if c2 < 0:
                xv = -bb / (2 * c2)
                if -1 < xv < 0:
                    r = -bb * bb / (4 * c2)
        if not math.isfinite(r):
            return math.inf
        out += max(r, 0.0)
    return out


@njit(cache=True, error_model="numpy")
def _poll_coord(t, step, lo, hi, periodic):
    """A pattern-search poll's coordinate: ``t + step`` wrapped into [lo, hi) on a periodic axis, else
    clipped into [lo, hi]."""
    v = t + step
    if periodic:
        return lo + (v - lo) % (hi - lo)
    return min(max(v, lo), hi)


@njit(cache=True, error_model="numpy")
def _climbing(best, before):
    """A pattern-search pass raised the worst case by more than 1e-7 (relative): another pass follows."""
    return best - before > 1e-7 * max(1.0, abs(best))


@njit(cache=True, error_model="numpy", literal_args="d")
def _pattern(d, which, k, x, th, best, step0, lo, hi, active, periodic, refine, extra, base_port, est, L, arm,
             chain, rmap, M, P1, S, V, cand, known):
    """Coordinate pattern search for the maximum of metric ``which`` (0: ||G|| at gain k, 1: |phi_max|)
    from ``th`` (updated in place) with value ``best``. Returns ``(best, ok)``; ``ok`` is False as
    soon as a polled instance cannot reach the tip (robust validity)."""
    na = th.shape[0]
    geo = map_geometry(rmap)  # the map's fields read once (chain.py: a namedtuple's arrays cost per read)
    mst = rmap.state
    for pass_ in range(1 + extra):
        before = best
        for level in range(1, refine + 1):
            for ax in range(na):
                if not active[ax]:
                    continue
                h = step0[ax] / 2.0 ** level
                for sgn in (-1.0, 1.0):
                    for i in range(na):
                        cand[i] = th[i]
                    v = _poll_coord(th[ax], sgn * h, lo[ax], hi[ax], periodic[ax])
                    if not periodic[ax] and v == th[ax]:
                        continue  # clipped back onto the centre: a worst case on the box face
                    cand[ax] = v
                    if d == 2:  # the branch here, not in an inlined instance(): see instance()
                        ok, w0, w1, w2 = _instance2(x, cand, base_port, est, L, arm, M, 0, S, V, known), 0.0, 0.0, 0.0
                    else:
                        ok, w0, w1, w2 = _instance3(x, cand, base_port, est, L, M, P1, 0, S, V, which == 1)
                    if ok and d == 3 and not known:
                        s_, ix, iy, iz = map_state(geo, mst, w0, w1, w2)
                        ok = s_ == 1 or (s_ == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))
                    if not ok:
                        return best, False
                    if which == 0 and d == 3 and not P1[0, 0] == P1[0, 0] and _gnorm_below(M, 0, k, best):
                        continue  # a loaded instance whose bound cannot raise the worst ||G||
                    if _PHI:
                        if which == 1 and d == 3 and phi_bound(M, 0) <= best:
                            continue  # this instance cannot raise the worst |phi_max|
                        f = _poll_value(d, which, M, P1, 0, k)
                    else:  # the copy without |phi_max| (_pattern_g)
                        f = gval(d, M, P1, 0, k)
                    if f > best:
                        best = f
                        for i in range(na):
                            th[i] = cand[i]
        if not _climbing(best, before):
            break
    return best, True


@njit(cache=True, error_model="numpy", literal_args="d")
def _pattern_lanes(d, k, s0, s1, XS, TH, best, known, live, owner, step0, lo, hi, active, periodic, refine, extra,
                   base_port, est, L, arm, chain, rmap, O, okl, want_rho, out_valid, out_g, out_p, out_rho, out_k):
    """:func:`_pattern`'s search for the worst ||G|| (``which`` 0), run for searches ``s0`` to ``s1 - 1`` at once, each
    from its own centre ``TH[:, s]`` (d, ns) with value ``best[s]`` at tip ``XS[:, s]``: every poll of
    the pattern is made for all searches still going by :func:`_levers2`/:func:`_levers3` (vectorized),
    then each search takes it or not exactly as :func:`_pattern` would, so that each ends where it
    would alone, with the same value (in ``best[s]``). Only for straight shafts (no load axis active):
    every poll is a lever. ``live[s]`` ends False if a poll fails (the tip is not robustly valid), as
    :func:`_pattern`'s ``ok``; ``known[s]``: the tip's wrists are certified reachable. Between passes
    the searches that stopped climbing leave the lanes, so a further pass costs only what still climbs.
    ``O``, ``okl``: the kernels' outputs (at least ``s1 - s0`` columns).

    Then the tips' results are completed as :func:`_search` does after its own searches: tip
    ``owner[s]`` gets the worst of its starts (its searches are consecutive), or is invalid if one
    of them failed; rho* is taken against that worst case (:func:`_rho_final`)."""
    na = step0.shape[0]
    ns = s1 - s0
    # working lanes: the searches still going, packed at the front (idx: their search)
    idx = np.arange(s0, s1)
    Xw = np.empty((d, ns))
    Tw = np.empty((d, ns))
    Xp = np.empty((d, ns))  # one poll's tips and instances, packed (its lanes: pq)
    Cp = np.empty((d, ns))
    pq = np.empty(ns, np.int64)
    bw = np.empty(ns)
    bef = np.empty(ns)
    kw = np.empty(ns, np.bool_)
    lw = np.empty(ns, np.bool_)
    for s in range(ns):
        for a in range(d):
            Xw[a, s] = XS[a, s0 + s]
            Tw[a, s] = TH[a, s0 + s]
        bw[s] = best[s0 + s]
        kw[s] = known[s0 + s]
        lw[s] = live[s0 + s]
    nw = ns
    geo = map_geometry(rmap)
    mst = rmap.state
    for pass_ in range(1 + extra):
        for q in range(nw):
            bef[q] = bw[q]
        for level in range(1, refine + 1):
            for ax in range(na):
                if not active[ax]:
                    continue
                h = step0[ax] / 2.0 ** level
                for sgn in (-1.0, 1.0):
                    # the polls to make, packed into the front of Xp, Cp (pq: their lane): not those of a
                    # failed search, nor one clipped back onto its centre (a worst case on the box face),
                    # whose value _pattern would not compute either
                    npk = 0
                    per = periodic[ax]
                    for q in range(nw):
                        t = Tw[ax, q]
                        # (the branch on the axis outside the poll's arithmetic: both ways the same numbers
                        # as _poll_coord's, without the float modulo computed for every lane)
                        if per:
                            v = _poll_coord(t, sgn * h, lo[ax], hi[ax], True)
                        else:
                            v = min(max(t + sgn * h, lo[ax]), hi[ax])
                        if not lw[q] or (not per and v == t):
                            continue
                        for a in range(d):
                            Xp[a, npk] = Xw[a, q]
                            Cp[a, npk] = Tw[a, q]
                        Cp[ax, npk] = v
                        pq[npk] = q
                        npk += 1
                    if d == 2:
                        _levers2(Xp, Cp, npk, base_port, est, L, k, O, okl)
                    else:
                        _levers3(Xp, Cp, npk, base_port, est, L, k, O, okl)
                    for c in range(npk):
                        q = pq[c]
                        v = Cp[ax, c]
                        okj = okl[c]
                        if okj and not kw[q]:
                            if d == 2:
                                okj = _planar_reachable(arm, O[1, c], O[2, c])
                            else:
                                w0, w1, w2 = O[1, c], O[2, c], O[3, c]
                                s_, ix, iy, iz = map_state(geo, mst, w0, w1, w2)
                                okj = s_ == 1 or (s_ == 2 and reach_boundary(chain, rmap, ix, iy, iz, w0, w1, w2))
                        if not okj:
                            lw[q] = False
                            continue
                        if O[0, c] > bw[q]:
                            bw[q] = O[0, c]
                            Tw[ax, q] = v
        # the pass's results; the searches still climbing go on, packed
        m_ = 0
        for q in range(nw):
            o = idx[q]
            best[o] = bw[q]
            live[o] = lw[q]
            if lw[q] and _climbing(bw[q], bef[q]):
                idx[m_] = o
                for a in range(d):
                    Xw[a, m_] = Xw[a, q]
                    Tw[a, m_] = Tw[a, q]
                bw[m_] = bw[q]
                kw[m_] = kw[q]
                lw[m_] = True
                m_ += 1
        nw = m_
        if nw == 0:
            break
    t0 = s0
    while t0 < s1:
        i_ = owner[t0]
        t1 = t0
        ok_ = True
        best_all = -math.inf
        while t1 < s1 and owner[t1] == i_:
            ok_ = ok_ and live[t1]
            best_all = max(best_all, best[t1])
            t1 += 1
        if not ok_:
            out_valid[i_] = False
            out_g[i_] = np.nan
            out_p[i_] = np.nan
            out_rho[i_] = np.nan
            out_k[i_] = np.nan
        elif out_valid[i_]:  # (not when its |phi_max| search failed)
            out_g[i_] = best_all
            if want_rho:
                out_rho[i_], out_k[i_] = _rho_final(best_all, out_rho[i_], out_k[i_], k)
        t0 = t1


@njit(cache=True, error_model="numpy")
def _fro_ub(q, scale):
    """``sqrt(q)`` (``q = ||I - k M||_F^2`` summed as ``3 - 2 k tr M + k^2 ||M||_F^2``) raised over rounding:
    ``1e-13 scale`` (the sum's terms' magnitudes) for its cancellation, then 1e-6 relative + 1e-9 for the
    3 x 3 sigma_max's own rounding."""
    return math.sqrt(max(q, 0.0) + 1e-13 * scale) * (1.0 + 1e-6) + 1e-9


@njit(cache=True, error_model="numpy")
def _gnorm_below(Mb, j, k, thr):
    """True when ``||I - k M||_2`` (``M = Mb[j]``, 3 x 3) is certainly below ``thr``: an upper bound of the
    largest eigenvalue ``lam`` of ``A = G^T G`` (``G = I - k M``), raised as :func:`_fro_ub` raises its own,
    is not above ``thr``. Much tighter than the Frobenius norm, and no trigonometry: from ``min(tr A,
    Gershgorin)`` (both above ``lam``: A is positive semi-definite), Laguerre steps on the characteristic
    cubic ``p(x) = x^3 - c2 x^2 + c1 x - c0`` (all roots real: they go down toward ``lam``), each new point
    kept only where ``p``, ``p'`` and ``p''`` are above 1e-10 of their scale there (then ``p'' > 0``, ``p' > 0``,
    ``p > 0`` on all of ``[x, inf)`` for the computed coefficients and, the margins being far above the
    rounding of the coefficients and of ``p``, for the exact ones: no eigenvalue at or above ``x``). Stops
    as soon as the bound is at or below ``thr`` (True) or no step can be kept (False)."""
    g00, g01, g02 = 1.0 - k * Mb[j, 0, 0], -k * Mb[j, 0, 1], -k * Mb[j, 0, 2]
    g10, g11, g12 = -k * Mb[j, 1, 0], 1.0 - k * Mb[j, 1, 1], -k * Mb[j, 1, 2]
    g20, g21, g22 = -k * Mb[j, 2, 0], -k * Mb[j, 2, 1], 1.0 - k * Mb[j, 2, 2]
    a00 = g00 * g00 + g10 * g10 + g20 * g20
    a11 = g01 * g01 + g11 * g11 + g21 * g21
    a22 = g02 * g02 + g12 * g12 + g22 * g22
    a01 = g00 * g01 + g10 * g11 + g20 * g21
    a02 = g00 * g02 + g10 * g12 + g20 * g22
    a12 = g01 * g02 + g11 * g12 + g21 * g22
    c2 = a00 + a11 + a22
    if not (c2 > 0.0 and c2 < math.inf):
        return False  # (NaN or inf: the exact value decides; 0: G = 0, let it be computed)
    x = min(c2, max(a00 + abs(a01) + abs(a02), max(abs(a01) + a11 + abs(a12), abs(a02) + abs(a12) + a22)))
    ub = _fro_ub(x, c2)
    if ub <= thr:
        return True
    c1 = (a00 * a11 - a01 * a01) + (a00 * a22 - a02 * a02) + (a11 * a22 - a12 * a12)
    c0 = a00 * (a11 * a22 - a12 * a12) - a01 * (a01 * a22 - a12 * a02) + a02 * (a01 * a12 - a11 * a02)
    tol = 1e-10
    p = ((x - c2) * x + c1) * x - c0
    dp = (3.0 * x - 2.0 * c2) * x + c1
    d2p = 6.0 * x - 2.0 * c2
    for it in range(LAGUERRE):
        # x is above every eigenvalue (at first tr A or Gershgorin; later: checked below)
        if not p > 0.0:
            return False  # x is an eigenvalue (to rounding): no step below it can be trusted
        gg = dp / p
        hh = gg * gg - d2p / p
        x1 = x - 3.0 / (gg + math.sqrt(max(2.0 * (3.0 * hh - gg * gg), 0.0)))
        if not x1 < x:
            return False
        # keep x1 only where no eigenvalue can lie at or above it
        sc = max(x1, c2 / 3.0)
        p1 = ((x1 - c2) * x1 + c1) * x1 - c0
        dp1 = (3.0 * x1 - 2.0 * c2) * x1 + c1
        d2p1 = 6.0 * x1 - 2.0 * c2
        if not (p1 > tol * sc * sc * sc and dp1 > tol * sc * sc and d2p1 > tol * sc):
            return False
        x, p, dp, d2p = x1, p1, dp1, d2p1
        if _fro_ub(x, c2) <= thr:
            return True
    return False


LAGUERRE = 3  # Laguerre steps of _gnorm_below at most


@njit(cache=True, error_model="numpy", literal_args="d")
def _gval_ub(d, Pb, j, k, tr, f2):
    """A cheap upper bound of :func:`gval` of instance ``j`` at gain ``k`` where its value costs a 3 x 3
    sigma_max (a loaded 3-D instance, ``Pb[j, 0]`` NaN): the Frobenius norm ``sqrt(3 - 2 k tr(M) + k^2
    ||M||_F^2)`` from ``tr[j]``, ``f2[j]``, raised by 1e-6 (relative) + 1e-9 over the rounding of both;
    inf where the value is cheap (the plane, the 3-D lever: no bound needed). A sample whose bound
    cannot beat the running maximum is skipped: the maximum, and which sample attains it, do not change."""
    if d == 2:
        return math.inf
    if Pb[j, 0] == Pb[j, 0]:
        return math.inf
    return _fro_ub(3.0 - 2.0 * k * tr[j] + k * k * f2[j], 3.0 + 2.0 * k * abs(tr[j]) + k * k * f2[j])


@njit(cache=True, error_model="numpy", literal_args="d")
def _gval_ub_at(d, Pb, j, k, tr, f2, lk, lv):
    """:func:`_gval_ub`, or a tighter bound from the exact value ``lv[j]`` of the same instance at gain
    ``lk[j]``: ``||I - k M|| <= ||I - lk M|| + |k - lk| ||M||_2`` and ``||M||_2 <= ||M||_F = sqrt(f2[j])``,
    raised as :func:`_fro_ub` raises its bound (1e-6 relative + 1e-9) over the rounding of both values.
    The smaller of the two; inf where :func:`_gval_ub` is (no bound needed)."""
    ub = _gval_ub(d, Pb, j, k, tr, f2)
    if ub == math.inf:
        return ub
    lip = (lv[j] + abs(k - lk[j]) * math.sqrt(f2[j])) * (1.0 + 1e-6) + 1e-9
    if lip < ub:  # (False where lv[j] is NaN: the Frobenius bound stands)
        return lip
    return ub


@njit(cache=True, error_model="numpy", literal_args="d")
def _gval_skip(d, Ms, Pb, j, k, tr, f2, thr):
    """True when :func:`gval` of instance ``j`` at gain ``k`` is certainly below ``thr`` (> 0): the cheap
    Frobenius bound (:func:`_gval_ub`) first, then the tight one (:func:`_gnorm_below`) for a loaded 3-D
    instance. A skipped instance cannot change a running maximum, nor which instance attains it."""
    if not thr > 0.0:
        return False
    if _gval_ub(d, Pb, j, k, tr, f2) <= thr:
        return True
    return d == 3 and not Pb[j, 0] == Pb[j, 0] and _gnorm_below(Ms, j, k, thr)


@njit(cache=True, error_model="numpy", literal_args="d")
def _golden(d, Ms, Pb, idx, na_, kmax, iters, tr, f2):
    """``min over k in [0, kmax] of max_{i in idx[:na_]} ||I - k Ms[i]||`` by golden section (convex in k).
    ``tr``, ``f2``: the instances' trace and squared Frobenius norm (:func:`_gval_ub`: an instance whose
    bound is not above the running maximum is not evaluated, the maximum is the same)."""
    gr = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = 0.0, kmax
    c, e = b - gr * (b - a), a + gr * (b - a)
    fc = 0.0
    fd = 0.0
    for q in range(na_):
        if not _gval_skip(d, Ms, Pb, idx[q], c, tr, f2, fc):
            fc = max(fc, gval(d, Ms, Pb, idx[q], c))
        if not _gval_skip(d, Ms, Pb, idx[q], e, tr, f2, fd):
            fd = max(fd, gval(d, Ms, Pb, idx[q], e))
    for _ in range(iters):
        if fc < fd:
            b, e, fd = e, c, fc
            c = b - gr * (b - a)
            fc = 0.0
            for q in range(na_):
                if not _gval_skip(d, Ms, Pb, idx[q], c, tr, f2, fc):
                    fc = max(fc, gval(d, Ms, Pb, idx[q], c))
        else:
            a, c, fc = c, e, fd
            e = a + gr * (b - a)
            fd = 0.0
            for q in range(na_):
                if not _gval_skip(d, Ms, Pb, idx[q], e, tr, f2, fd):
                    fd = max(fd, gval(d, Ms, Pb, idx[q], e))
    return 0.5 * (a + b)


@njit(cache=True, error_model="numpy", literal_args="d")
def _golden_gain(d, Ms, Pb, m, iters, k0, idx, tr, f2, v0, kn, lk, lv):
    """``min over k > 0 of max_i ||I - k M_i||`` over the m sampled instances; ``(rho, k)``,
    ``(1, 0)`` where no gain contracts.

    Cutting planes: golden section over an active set of instances (first the worst at the
    scenario gain ``k0``), then every instance is checked at the minimiser and the worst one
    joins the set, until none exceeds the active maximum. At the end the maximum over all
    instances at k equals the active minimum, so k minimises the full maximum (each function is
    convex in k, so is their maximum). ``idx`` is (m,) int scratch; ``tr``, ``f2`` (m,) float scratch,
    filled here with the instances' trace and squared Frobenius norm (:func:`_gval_ub`: instances
    that cannot change a maximum are not evaluated). ``v0``: the instances' ``||I - k0 M||`` (:func:`gval`'s,
    the search's sampled values: not computed again) where ``kn`` (the others are below the largest); ``lk``, ``lv`` (m,) float scratch: per instance the
    last gain at which its exact value was computed and that value (:func:`_gval_ub_at`'s tighter bound
    skips more of the checks; the caller reads the values at the returned gain from there)."""
    amax = 0.0
    for i in range(m):
        s = 0.0
        t = 0.0
        for a in range(Ms.shape[1]):
            t += Ms[i, a, a]
            for b in range(Ms.shape[2]):
                s += Ms[i, a, b] ** 2
        tr[i] = t
        f2[i] = s
        amax = max(amax, math.sqrt(s))
    kmax = 2.0 / amax if amax > 0 else 1.0
    jw, vw = 0, -1.0
    for i in range(m):
        if not kn[i]:
            lk[i] = math.nan
            continue
        v = v0[i]
        lk[i] = k0
        lv[i] = v
        if v > vw:
            jw, vw = i, v
    idx[0] = jw
    n_act = 1
    kk = 0.0
    rho = 1.0
    while True:
        kk = _golden(d, Ms, Pb, idx, n_act, kmax, iters, tr, f2)
        act = 0.0
        for q in range(n_act):
            i = idx[q]
            if not lk[i] == kk:
                lk[i] = kk
                lv[i] = gval(d, Ms, Pb, i, kk)
            act = max(act, lv[i])
        jw, vw = -1, act
        for i in range(m):
            thr = vw * (1.0 + 1e-13) + 1e-15
            if lk[i] == kk:
                v = lv[i]  # (an active instance: its value at kk above)
            else:
                if _gval_ub_at(d, Pb, i, kk, tr, f2, lk, lv) <= thr or _gval_skip(d, Ms, Pb, i, kk, tr, f2, thr):
                    continue
                v = gval(d, Ms, Pb, i, kk)
                lk[i] = kk
                lv[i] = v
            if v > thr:
                jw, vw = i, v
        rho = vw
        if jw < 0 or n_act >= m:
            break
        idx[n_act] = jw
        n_act += 1
    if rho >= 1.0:
        return 1.0, 0.0
    return rho, kk


@njit(cache=True, error_model="numpy")
def _rho_final(g, rs, ks, k):
    """rho* and k* from the certified golden-section pair ``(rs, ks)`` and the worst ||G|| ``g`` at the
    scenario gain ``k`` (used where it does better); ``(1, 0)`` where no gain contracts."""
    if g < rs:
        rs, ks = g, k
    if rs >= 1.0:
        rs, ks = 1.0, 0.0
    return rs, ks


#: the pattern search without |phi_max| (``which`` is 0): the search copies without it call this one
_pattern_g = njit(cache=True, error_model="numpy", literal_args="d")(
    copy_function(_pattern.py_func, "_pattern_g", _PHI=False))
