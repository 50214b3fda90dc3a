"""The physics a certificate samples: tips of a convergence ball (:func:`ball_tips`), the worst ``||G||``
of (tip, error instance) pairs, the 3-D model (:class:`SpatialModel`: motion maps ``M = J Jhat^-1`` on the
URDF arm from the compiled kernels) and one nonlinear controller step (:func:`step_ratio`)."""
from __future__ import annotations

import math

import numpy as np
from ..jit import njit

from ..errors import ErrplanError
from ..fields import Evaluator
from ..kinematics.shaft import flexed_tip, flexed_wrist_plane, lever_jacobian
from ..linalg import g_norm3, sigma_max3, v_sigma3
from ..linalg.eigen import _sym3_max
from ..metrics import inv, inv2, inverse_parts

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def ball_tips(center, radius: float, n_disk: int, n_ring: int) -> np.ndarray:
    """Tips covering the closed disc: the centre, a sunflower (Vogel) disc and the boundary ring.
    In 3-D (a 3-vector ``center``): the centre, a Fibonacci-spiral volume sample (radius
    ``R ((i + 1/2)/n)^(1/3)``) and a Fibonacci sphere of ``n_ring`` points on the boundary."""
    c = np.asarray(center, float)
    if c.shape[-1] == 3:
        vol = sphere_points(n_disk) * (radius * np.cbrt((np.arange(n_disk) + 0.5) / max(n_disk, 1)))[:, None]
        return np.vstack([c[None], c + vol, c + radius * sphere_points(n_ring)])
    i = np.arange(n_disk)
    r = radius * np.sqrt((i + 0.5) / max(n_disk, 1))
    a = i * GOLDEN_ANGLE
    disk = np.stack([r * np.cos(a), r * np.sin(a)], axis=-1)
    b = 2 * np.pi * np.arange(n_ring) / max(n_ring, 1)
    ring = radius * np.stack([np.cos(b), np.sin(b)], axis=-1)
    return np.vstack([c[None], c + disk, c + ring])


def sphere_points(n: int) -> np.ndarray:
    """``n`` unit vectors (n, 3) spread evenly over the sphere (spherical Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / max(n, 1)
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    a = i * GOLDEN_ANGLE
    return np.stack([r * np.cos(a), r * np.sin(a), z], axis=-1)


def _pairs(ev: Evaluator, x: np.ndarray, th: np.ndarray):
    """Parts over every (tip, instance) pair: mu, nu (n, m, c), reach (n, m), ok (n, m)."""
    n, m = len(x), len(th)
    X = np.repeat(x, m, axis=0)
    TH = np.tile(th, (n, 1))
    mu, nu, ok, reach = ev.parts_tracked(X, TH)  # the ball's tips are tracked tips: the loop's frame
    c = mu.shape[-1]
    return mu.reshape(n, m, c), nu.reshape(n, m, c), reach.reshape(n, m), ok.reshape(n, m)


def _worst_g(mu, nu, reach, ok, k) -> np.ndarray:
    """Worst ||G|| per pair (n, m): -inf where the truth cannot reach the tip, +inf where it can
    but the controller's Jacobian is singular there (an unbounded error, never certified)."""
    g = np.abs(1.0 - k * mu) + k * np.abs(nu)
    g = np.where(np.isfinite(g), g, np.inf).max(axis=-1)
    g = np.where(ok, g, np.inf)
    return np.where(reach, g, -np.inf)


# ----------------------------------------------------------------------------- 3-D physics
@njit(cache=True, error_model="numpy")
def _gnorm_grid(Ms, ks, out):
    """``out[j, i] = ||I - ks[j] Ms[i]||_2`` (3 x 3; NaN for a non-finite ``Ms[i]``)."""
    for j in range(ks.shape[0]):
        for i in range(Ms.shape[0]):
            out[j, i] = g_norm3(Ms[i], ks[j])


#: relative (and absolute) slack on the bound ``|1 - k c| + k r`` before it may skip a pair: the closed-form
#: ``sigma_max`` is exact to ~1e-15 relative, so a skipped pair is far below the kept ones, never tied
_BOUND_SLACK = 1e-9


@njit(cache=True, error_model="numpy")
def _scalar_offsets(Ms, c, r):
    """Per 3 x 3 ``Ms[i]``: ``c[i] = tr(Ms[i]) / 3`` and ``r[i] = ||Ms[i] - c[i] I||_2``, so that at
    every gain ``||I - k Ms[i]||_2 <= |1 - k c[i]| + k r[i]`` (triangle inequality). Returns False when
    some value is not finite (no bound then)."""
    A = np.empty((3, 3))
    for i in range(Ms.shape[0]):
        ci = (Ms[i, 0, 0] + Ms[i, 1, 1] + Ms[i, 2, 2]) / 3.0
        for a in range(3):
            for b in range(3):
                A[a, b] = Ms[i, a, b] - (ci if a == b else 0.0)
        ri = sigma_max3(A)
        if not (math.isfinite(ci) and math.isfinite(ri)):
            return False
        c[i] = ci
        r[i] = ri
    return True


@njit(cache=True, error_model="numpy")
def _insert_top(v, i, bv, bi, nb, cap):
    """Insert value ``v`` (index ``i``) into the descending list ``bv``/``bi`` of ``nb`` entries, kept to
    its ``cap`` largest; returns the new length."""
    if nb == cap and not v > bv[cap - 1]:
        return nb
    pos = nb if nb < cap else cap - 1
    while pos > 0 and bv[pos - 1] < v:
        bv[pos] = bv[pos - 1]
        bi[pos] = bi[pos - 1]
        pos -= 1
    bv[pos] = v
    bi[pos] = i
    return nb + 1 if nb < cap else nb


@njit(cache=True, error_model="numpy")
def _grid_top(Ms, c, r, ks, order, left, right, top, vals, tops, clear):
    """For each gain ``ks[j]``: ``vals[j] = max_i ||I - ks[j] Ms[i]||_2`` and ``tops[j]`` the indices of
    its ``top`` largest values (any order), the numbers of the full grid (:func:`_gnorm_grid`), but
    ``||I - k M_i||`` evaluated only where an upper bound of it reaches the ``top``-th largest value found
    so far; a pair skipped is strictly below it. The gains are visited in ``order``; ``left[j]`` and
    ``right[j]`` are gains visited before ``j`` on either side (-1 for none). The bound of pair ``i``:
    ``|1 - k c_i| + |k| r_i`` (:func:`_scalar_offsets`) and, between two visited gains, the chord of the
    pair's values (or bounds) there (``||I - k M||`` is convex in ``k``), with :data:`_BOUND_SLACK`. The
    seeds: the top pairs of the neighbour gains and the pairs of largest bound. ``clear[j]`` is False
    where the ``top``-th largest value is tied with the next or some value is NaN (the set is then not
    determined by the values: the caller recomputes that gain in full). Returns the number of
    ``||I - k M||`` evaluated."""
    p = Ms.shape[0]
    nk = ks.shape[0]
    cap = top + 1
    bv = np.empty(cap)
    bi = np.empty(cap, np.int64)
    uv = np.empty(cap)
    ui = np.empty(cap, np.int64)
    topx = np.full((nk, cap), -1, np.int64)
    seen = np.full(p, -1, np.int64)
    U = np.empty((nk, p))
    seeds = np.empty(3 * cap, np.int64)
    evals = 0
    for j in order:
        k = ks[j]
        l, h = left[j], right[j]
        u = U[j]
        nu = 0
        if l >= 0 and h >= 0:
            w = (k - ks[l]) / (ks[h] - ks[l])
        for i in range(p):
            ub = abs(1.0 - k * c[i]) + abs(k) * r[i]
            if l >= 0 and h >= 0:
                ch = U[l, i] + w * (U[h, i] - U[l, i])
                if ch < ub:
                    ub = ch
            u[i] = ub * (1.0 + _BOUND_SLACK) + _BOUND_SLACK
            nu = _insert_top(u[i], i, uv, ui, nu, cap)
        ns = 0
        for nbr in (l, h):
            if nbr >= 0:
                for t in range(cap):
                    if topx[nbr, t] >= 0:
                        seeds[ns] = topx[nbr, t]
                        ns += 1
        for t in range(nu):
            seeds[ns] = ui[t]
            ns += 1
        nb = 0
        nan = False
        for s in range(ns + p):
            i = seeds[s] if s < ns else s - ns
            if seen[i] == j or (s >= ns and nb >= top and u[i] < bv[top - 1]):
                continue
            seen[i] = j
            g = g_norm3(Ms[i], k)
            evals += 1
            if math.isnan(g):
                nan = True
            else:
                u[i] = g
                nb = _insert_top(g, i, bv, bi, nb, cap)
        vals[j] = bv[0] if nb > 0 else np.nan
        for t in range(nb):
            topx[j, t] = bi[t]
        for t in range(top):
            tops[j, t] = bi[t] if t < nb else -1
        clear[j] = (not nan) and nb >= top and (nb < cap or bv[top - 1] > bv[top])
    return evals


def _bisection_order(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices ``0..n-1`` in the order ``0, n-1``, then midpoints of visited neighbours, with each one's
    visited neighbours ``(order, left, right)`` (-1 for none)."""
    left = np.full(n, -1, np.int64)
    right = np.full(n, -1, np.int64)
    order = [0] + ([n - 1] if n > 1 else [])
    stack = [(0, n - 1)] if n > 2 else []
    while stack:
        nxt = []
        for lo, hi in stack:
            m = (lo + hi) // 2
            order.append(m)
            left[m], right[m] = lo, hi
            nxt += [iv for iv in ((lo, m), (m, hi)) if iv[1] - iv[0] > 1]
        stack = nxt
    return np.array(order, np.int64), left, right


@njit(cache=True, error_model="numpy")
def _sym_top(Ms, out):
    """``out[i]``: the largest eigenvalue of ``(Ms[i] + Ms[i]^T) / 2`` in closed form (a few ulps of its norm)."""
    for i in range(Ms.shape[0]):
        out[i] = _sym3_max(Ms[i, 0, 0], 0.5 * (Ms[i, 0, 1] + Ms[i, 1, 0]), 0.5 * (Ms[i, 0, 2] + Ms[i, 2, 0]),
                           Ms[i, 1, 1], 0.5 * (Ms[i, 1, 2] + Ms[i, 2, 1]), Ms[i, 2, 2])


def sym_top_candidates(S: np.ndarray) -> np.ndarray:
    """Indices of the symmetric 3 x 3 matrices ``S`` (n, 3, 3), all finite, that may hold the largest
    eigenvalue of them all: those whose closed-form top eigenvalue (:func:`_sym_top`) is within
    :data:`_BOUND_SLACK` of the largest entry's scale of the largest one."""
    S = np.ascontiguousarray(S, float)
    lam = np.empty(len(S))
    _sym_top(S, lam)
    tol = _BOUND_SLACK * (3.0 * float(np.abs(S).max()) + 1e-300)
    return np.flatnonzero(lam >= lam.max() - tol)


@njit(cache=True, error_model="numpy")
def _gnorm_bound(A, k):
    """An upper bound of ``||I - k A||_2`` (3 x 3 ``A``; NaN if ``A`` has a NaN): the least of
    ``|1 - k c| + |k| ||A - c I||_F`` (``c = tr(A) / 3``) and ``||I - k A||_F``."""
    c = (A[0, 0] + A[1, 1] + A[2, 2]) / 3.0
    f = 0.0
    fg = 0.0
    for a in range(3):
        for b in range(3):
            e = A[a, b] - (c if a == b else 0.0)
            f += e * e
            g = (1.0 if a == b else 0.0) - k * A[a, b]
            fg += g * g
    u = abs(1.0 - k * c) + abs(k) * math.sqrt(f)
    u3 = math.sqrt(fg)
    if math.isnan(u) or math.isnan(u3):
        return np.nan
    return min(u, u3)


@njit(cache=True, error_model="numpy")
def _worst_instances(Ms, ok, k, singular, best, jbest):
    """Per tip ``t`` of ``Ms`` (n, m, c, 3, 3) (instances, noise corners) and validity ``ok`` (n, m):
    ``best[t] = max_j g[t, j]`` and ``jbest[t]`` its first index (``np.argmax``), where ``g`` is the
    verification's masked ``||G||`` (:func:`errplan.gains.verify._mask3` of the largest
    ``||I - k M||_2`` over the corners, NaN if any is): -inf where not ``ok``, +inf where ``ok`` and
    ``singular`` or not finite. The instance of largest bound (:func:`_gnorm_bound`, with
    :data:`_BOUND_SLACK`) is evaluated first; then, in order, a pair whose bound is below the largest
    value so far is not evaluated: it cannot be the maximum nor its first index. Returns the number of
    ``||I - k M||`` evaluated."""
    n, m, nc = Ms.shape[0], Ms.shape[1], Ms.shape[2]
    evals = 0
    u = np.empty(m)
    vals = np.empty(m)
    for t in range(n):
        js = -1
        us = -np.inf
        for j in range(m):
            if not ok[t, j]:
                u[j] = -np.inf
                vals[j] = -np.inf
                continue
            if singular:
                u[j] = np.inf
                vals[j] = np.inf
                continue
            ub = -np.inf
            for q in range(nc):
                b = _gnorm_bound(Ms[t, j, q], k)
                if math.isnan(b):
                    ub = np.inf  # no bound: evaluate
                    break
                if b > ub:
                    ub = b
            u[j] = ub * (1.0 + _BOUND_SLACK) + _BOUND_SLACK
            vals[j] = np.nan  # not evaluated yet
            if u[j] > us:
                us = u[j]
                js = j
        bv = -np.inf  # the largest value evaluated so far
        for s in range(-1, m):
            j = js if s < 0 else s
            if j < 0 or not math.isnan(vals[j]) or u[j] < bv:
                continue
            v = -np.inf
            for q in range(nc):
                g = g_norm3(Ms[t, j, q], k)
                evals += 1
                if math.isnan(g):
                    v = np.nan
                    break
                if g > v:
                    v = g
            vals[j] = v if math.isfinite(v) else np.inf
            if vals[j] > bv:
                bv = vals[j]
        # the maximum and its first index over the evaluated values (the others are below it)
        bv = -np.inf
        bj = 0
        for j in range(m):
            if not math.isnan(vals[j]) and vals[j] > bv:
                bv = vals[j]
                bj = j
        best[t] = bv
        jbest[t] = bj
    return evals


def worst_instances(M: np.ndarray, ok: np.ndarray, k: float, singular: bool) -> tuple[np.ndarray, np.ndarray]:
    """``(best, jbest)`` (n,) of the masked worst ``||G||`` over the instances of each tip: ``M`` (n, m, 3, 3)
    or (n, m, c, 3, 3) over noise corners, ``ok`` (n, m); see :func:`_worst_instances`. The values and
    indices of ``G.max(axis=1)``, ``G.argmax(axis=1)`` for ``G = _mask3(max_c ||I - k M||, ok, singular)``."""
    n, m = ok.shape
    Ms = np.ascontiguousarray(np.asarray(M, float).reshape(n, m, -1, 3, 3))
    best = np.empty(n)
    jbest = np.empty(n, np.int64)
    _worst_instances(Ms, np.ascontiguousarray(ok, bool), float(k), bool(singular), best, jbest)
    return best, jbest


def grid_top(M: np.ndarray, k: np.ndarray, top: int) -> tuple[np.ndarray, np.ndarray]:
    """``vals`` (len(k),) and ``tops`` (len(k), top) for 3 x 3 ``M`` (n, 3, 3), ``n > top``: with
    ``G = gnorm3_grid(M, k)``, ``vals = G.max(axis=1)`` and the rows of ``tops`` the index sets of
    ``np.argpartition(-G, top, axis=1)[:, :top]``, with most of ``G`` skipped by bounds
    (:func:`_grid_top`); a gain whose set the values do not determine (a tie at the ``top``-th value,
    a NaN) is computed in full as that expression."""
    M = np.ascontiguousarray(np.asarray(M, float).reshape(-1, 3, 3))
    k = np.ascontiguousarray(np.atleast_1d(np.asarray(k, float)))
    if len(M) <= top:
        raise ValueError(f"grid_top: {len(M)} matrices, at most top = {top}")
    c, r = np.empty(len(M)), np.empty(len(M))
    vals = np.empty(len(k))
    tops = np.empty((len(k), top), np.int64)
    clear = np.zeros(len(k), bool)
    if _scalar_offsets(M, c, r) and np.all(np.isfinite(k)):
        _grid_top(M, c, r, k, *_bisection_order(len(k)), top, vals, tops, clear)
    for j in np.flatnonzero(~clear):
        G = gnorm3_grid(M, k[j])
        vals[j] = G.max(axis=1)[0]
        tops[j] = np.argpartition(-G, top, axis=1)[0, :top]
    return vals, tops


@njit(cache=True, error_model="numpy")
def _vsigma_rows(Ms, k, out):
    """Cut rows ``(a, b)`` (n, 2) of the right singular vector ``v`` of ``I - k Ms[i]``:
    ``a = v.Mv``, ``b = |Mv - a v|``, so that ``||(I - kM) v||^2 = (1 - k a)^2 + (k b)^2``."""
    G = np.empty((3, 3))
    v = np.empty(3)
    for i in range(Ms.shape[0]):
        for r in range(3):
            for c in range(3):
                G[r, c] = (1.0 if r == c else 0.0) - k * Ms[i, r, c]
        v_sigma3(G, v)
        a = 0.0
        for r in range(3):
            a += v[r] * (Ms[i, r, 0] * v[0] + Ms[i, r, 1] * v[1] + Ms[i, r, 2] * v[2])
        b2 = 0.0
        for r in range(3):
            m = Ms[i, r, 0] * v[0] + Ms[i, r, 1] * v[1] + Ms[i, r, 2] * v[2] - a * v[r]
            b2 += m * m
        out[i, 0] = a
        out[i, 1] = math.sqrt(b2)


@njit(cache=True, error_model="numpy")
def _gnorm_pairs(Ms, ks, out):
    """``out[i] = ||I - ks[i] Ms[i]||_2`` (3 x 3; NaN for a non-finite ``Ms[i]``)."""
    for i in range(Ms.shape[0]):
        out[i] = g_norm3(Ms[i], ks[i])


def gnorm3_pairs(M: np.ndarray, k) -> np.ndarray:
    """``||I - k_i M_i||_2`` (n,) for 3 x 3 matrices ``M`` (n, 3, 3) each with its gain ``k_i`` (``k``
    a scalar or (n,)), compiled: the same values as :func:`gnorm3_grid` one gain at a time."""
    M = np.ascontiguousarray(np.asarray(M, float).reshape(-1, 3, 3))
    k = np.ascontiguousarray(np.broadcast_to(np.asarray(k, float), (len(M),)))
    out = np.empty(len(M))
    _gnorm_pairs(M, k, out)
    return out


def gnorm3_grid(M: np.ndarray, k) -> np.ndarray:
    """``||I - k_j M_i||_2`` (len(k), n) for 3 x 3 matrices ``M`` (n, 3, 3), compiled."""
    k = np.atleast_1d(np.asarray(k, float))
    M = np.ascontiguousarray(np.asarray(M, float).reshape(-1, 3, 3))
    out = np.empty((len(k), len(M)))
    _gnorm_grid(M, np.ascontiguousarray(k), out)
    return out


def cut_rows(M: np.ndarray, k: float) -> np.ndarray:
    """Rows (n, 2) ``(a, b)`` of the cuts at gain ``k`` (see :func:`_vsigma_rows`)."""
    M = np.ascontiguousarray(np.asarray(M, float).reshape(-1, 3, 3))
    out = np.empty((len(M), 2))
    _vsigma_rows(M, float(k), out)
    return out


def perp_basis(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The field kernels' frame around unit vectors ``e`` (..., 3): ``f1 = e x r / |e x r|`` with
    ``r`` the axis of the smallest ``|e_i|`` (first of equals), ``f2 = e x f1``. The load direction
    ``psi`` of an error instance is the angle of ``e2 = cos(psi) f1 + sin(psi) f2``."""
    e = np.asarray(e, float)
    a = np.abs(e)
    axis = np.where((a[..., 0] <= a[..., 1]) & (a[..., 0] <= a[..., 2]), 0, np.where(a[..., 1] <= a[..., 2], 1, 2))
    r = np.eye(3)[axis]
    c = np.cross(e, r)
    f1 = c / np.linalg.norm(c, axis=-1, keepdims=True)
    return f1, np.cross(e, f1)


class SpatialModel:
    """The certificate's physics in 3-D: the scenario's rigid controller and error set through the
    compiled kernels (``M`` and validity per (tip, instance) pair), the true wrist and world load
    of an instance, and the nonlinear one-step replay on the URDF arm.

    Error instances are ``theta = (dx, dy, dz, tau, psi)`` (:class:`errplan.fields.ErrorSet`); at
    ``tau = 0`` the direction is irrelevant and :meth:`instances` keeps one.
    """

    dim = 3

    def __init__(self, m):
        from ..fields import KernelEvaluator
        from ..models import arm_model

        sc = m = arm_model(m)  # an errplan.models.ArmModel (a scenario is built into one)
        self.jacobian = sc.controller.jacobian
        if m.jacobian_effects:  # the truth's [effects] change J, Jhat or the loop's frame: the general path
            self.kev = EffectsKernel(sc)
        else:
            self.kev = KernelEvaluator(sc) if self.jacobian == "rigid" else FlexionKernel(sc)
        self.scenario = sc
        self.errors = self.kev.errors
        self.arm = m.arm
        self.length = float(sc.instrument.length)
        self.estimate = np.asarray(sc.port.estimate, float)
        es = self.errors
        self.delta = float(np.max(np.linalg.norm(es.port_corners() - self.estimate, axis=-1)))
        tmax = float(max(abs(es.lo[3]), abs(es.hi[3])))
        self.deviation = self.length * math.atan(tmax * self.length ** 2 / 12.0)
        self.anatomy = m.anatomy_model  # [anatomy] obstacles (errplan.anatomy.ShaftClearance) or None, built once

    @classmethod
    def from_model(cls, m) -> "SpatialModel":
        """The certificate's physics of an arm's model (:class:`errplan.models.ArmModel`)."""
        return cls(m)

    def instances(self, samples: int) -> np.ndarray:
        """The error set's grid with ``samples`` per axis (8 load directions), one row per distinct
        instance (a zero load keeps one direction)."""
        th = self.errors.sample_grid(samples)
        keep = (th[:, 3] != 0.0) | (th[:, 4] == self.errors.lo[4])
        return th[keep]

    def corner_instances(self) -> np.ndarray:
        """Port-box corners x {no (smallest) load, the largest load in 4 directions}."""
        es = self.errors
        ports = es.port_corners() - np.asarray(es.base_port)
        rows = [[*p, es.lo[3], es.lo[4]] for p in ports]
        if es.hi[3] > es.lo[3]:
            rows += [[*p, es.hi[3], psi] for p in ports for psi in (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi)]
        return np.array(rows, float)

    @property
    def noise_corners(self) -> int:
        """Noise corners per (tip, instance) pair: 1 for the rigid controller."""
        return 1 if self.jacobian == "rigid" else len(self.kev.fev.noise)

    def singular_free(self, center, radius: float) -> bool:
        """True when the controller's lever Jacobian cannot be singular at any tip of the ball.

        ``Jhat`` is singular where the wrist is ``L`` from the estimate. For a tip ``x`` with true
        port ``p`` (``|p - e| <= delta``) the wrist is within ``L - |x - p| + deviation`` of ``p``
        (lever wrist ``L - r`` from the port; a load moves it by at most ``deviation``), so
        ``|w - e| < L`` whenever ``|x - e| > 2 delta + deviation``.
        """
        c = np.asarray(center, float)
        if isinstance(self.kev, EffectsKernel):
            return self.kev.singular_free(c, radius, self)
        if self.jacobian == "flexion":
            return self._flexion_singular_free(c, radius)
        return bool(np.linalg.norm(c - self.estimate) - radius > 2.0 * self.delta + self.deviation + 1e-6)

    def _flexion_singular_free(self, c: np.ndarray, radius: float) -> bool:
        """P2's flexion controller: ``Jhat_tw`` is the flexed shaft's through the *estimated* port,
        singular where the tip reaches that port. The estimated port is within ``e_p`` of the true
        one, ``e_p`` the largest estimated-port error over the noise corners at the ball's centre
        under the corner instances (sampled, doubled for the ball): the ball is called singular-free
        when it keeps ``delta + deviation + 2 e_p`` from every true port of the box. Unlike the
        rigid case this margin is sampled, not proven."""
        from ..kinematics.shaft import estimate_from_end_poses, flexed_end_directions
        from ..fields.evaluator import bending_frame, noisy_end_poses

        base = np.asarray(self.errors.base_port, float)
        th = self.corner_instances()
        x = np.repeat(c[None], len(th), axis=0)
        fev = self.kev.fev
        w, t, p, ok = fev.truth(x, th)
        if not np.any(ok):
            return False
        w, t, p = w[ok], t[ok], p[ok]
        tip, dw, dt = flexed_end_directions(w, p, self.length, t)
        pw, pt, mw, mt = noisy_end_poses(w, tip, dw, dt, bending_frame(w, p, self.length, t), fev.noise)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            est = estimate_from_end_poses(pw, pt, mw, mt, self.length)
            ep = np.linalg.norm(est["port"] - p[:, None, :], axis=-1)
        if not np.all(np.isfinite(ep)):
            return False
        far = float(np.linalg.norm(c - base)) - radius
        return bool(far > self.delta + self.deviation + 2.0 * float(ep.max()) + 1e-6)

    def maps(self, x: np.ndarray, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``M`` (n, m, 3, 3) and validity (n, m) of every (tip, instance) pair."""
        return self.kev.motion_maps(np.asarray(x, float)[:, None, :], np.asarray(th, float)[None, :, :])

    def maps_paired(self, x: np.ndarray, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``M`` (n, 3, 3) and validity (n,) of pairs ``(x[i], th[i])``."""
        return self.kev.motion_maps(np.asarray(x, float), np.asarray(th, float))

    def wrists(self, x: np.ndarray, th: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """True port, wrist, world load (each (n, 3)) and reach (n,) of pairs ``(x[i], th[i])``: the
        lever wrist, or the bent shaft's (``kinematics.shaft.flexed_wrist_plane`` with the kernels'
        load direction, :func:`perp_basis`); reach = shaft through the port and wrist reachable."""
        x = np.asarray(x, float)
        th = np.asarray(th, float)
        L = self.length
        p = self.errors.port(th)
        e = x - p
        r = np.linalg.norm(e, axis=-1)
        ok = (r > 1e-9) & (r < L)
        e1 = np.where(ok[:, None], e, [0.0, 0.0, 1.0]) / np.where(ok, r, 1.0)[:, None]
        tau = th[:, 3]
        w = x - L * e1
        t = np.zeros_like(x)
        bent = ok & (tau != 0.0)
        if np.any(bent):
            f1, f2 = perp_basis(e1[bent])
            ps = th[bent, 4]
            e2 = np.cos(ps)[:, None] * f1 + np.sin(ps)[:, None] * f2
            wb, tb = flexed_wrist_plane(x[bent], p[bent], L, tau[bent], e2)
            w[bent], t[bent] = wb, tb
        reach = ok.copy()
        if np.any(ok):
            reach[ok] = self.arm.reachable(w[ok])
        return p, w, t, reach

    def step_ratio(self, target, x: np.ndarray, theta: np.ndarray, k) -> np.ndarray:
        """:func:`step_ratio` in 3-D: one controller step on the URDF arm per pair (n,); ``target`` (3,)
        or one per pair (n, 3)."""
        x = np.asarray(x, float)
        theta = np.asarray(theta, float)
        b = np.asarray(target, float)
        k = np.broadcast_to(np.asarray(k, float), x.shape[:-1])
        out = np.full(len(x), np.nan)
        if not len(x):
            return out
        if isinstance(self.kev, EffectsKernel):  # the truth's [effects]: the general path, in the loop's frame
            return self.kev.fev.step_ratio(b, x, theta, k)
        p, w, t, reach = self.wrists(x, theta)
        ir = np.flatnonzero(reach)  # the arm's inverse of the reachable wrists only (row by row: the same q)
        q = np.full((len(x), self.arm.n), np.nan)
        okq = np.zeros(len(x), bool)
        if len(ir):
            q[ir], okq[ir] = self.arm.inverse(w[ir])
        reach &= okq
        idx = np.flatnonzero(reach)
        if not len(idx):
            return out
        b = np.broadcast_to(b, x.shape)[idx]  # one target, or one per pair
        w, p, t, q, xx, kk = w[idx], p[idx], t[idx], q[idx], x[idx], k[idx]
        if self.jacobian == "flexion":  # the worst over the controller's noise corners: one row per corner
            Jh = self.kev.fev.controller_jacobian(w, t, p)  # (n, c, 3, 3)
            c = Jh.shape[1]
            rep = lambda a: np.repeat(a, c, axis=0)
            w, p, t, q, xx, kk, b = rep(w), rep(p), rep(t), rep(q), rep(xx), rep(kk), rep(b)
            Jh = Jh.reshape(-1, 3, 3)
        else:
            c = 1
            Jh = lever_jacobian(w, self.estimate, self.length)
        with np.errstate(invalid="ignore", divide="ignore"):
            Jh_inv, sing = inv(Jh)
            Ja_inv, sing_arm = inv(self.arm.jacobian(q))
            e = b - xx
            dw = kk[:, None] * np.einsum("nij,nj->ni", np.nan_to_num(Jh_inv), e)
            q2 = q + np.einsum("nij,nj->ni", np.nan_to_num(Ja_inv), dw)
            ok_lim = self.arm.within_limits(q2)
            w2 = self.arm.forward(q2)
            r2 = np.linalg.norm(w2 - p, axis=-1)
            ok_shaft = (r2 > 1e-9) & (r2 < self.length)
            w2s = np.where(ok_shaft[:, None], w2, p - 0.5 * self.length * (xx - p) / np.linalg.norm(xx - p, axis=-1)[:, None])
            x2 = flexed_tip(w2s, p, self.length, t)
            e0 = np.linalg.norm(e, axis=-1)
            ratio = np.linalg.norm(x2 - b, axis=-1) / np.where(e0 > 0, e0, np.nan)
        good = ok_lim & ok_shaft & ~sing & ~sing_arm & np.isfinite(ratio)
        out[idx] = np.where(good, ratio, np.inf).reshape(len(idx), c).max(axis=1)
        return out


class FlexionKernel:
    """P2's flexion controller in 3-D behind the interface :class:`SpatialModel` takes from the
    compiled :class:`errplan.fields.KernelEvaluator`: ``motion_maps`` (with a noise-corner axis) and
    ``worst_case``, both from :class:`errplan.fields.SpatialFlexionEvaluator` (compiled physics,
    :mod:`errplan.fields.kernels.flexion`)."""

    def __init__(self, sc):
        from ..fields import SpatialFlexionEvaluator

        self.scenario = sc
        self.fev = SpatialFlexionEvaluator.from_model(sc)
        self.errors = self.fev.errors

    def motion_maps(self, x: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M, ok)`` for tips ``x`` (..., 3) under instances ``theta`` (..., 5), broadcast together:
        ``M`` (..., c, 3, 3) over the noise corners, NaN where ``ok`` is False."""
        x = np.asarray(x, float)
        theta = np.asarray(theta, float)
        shape = np.broadcast_shapes(x.shape[:-1], theta.shape[:-1])
        X = np.broadcast_to(x, shape + (3,)).reshape(-1, 3)
        TH = np.broadcast_to(theta, shape + theta.shape[-1:]).reshape(-1, theta.shape[-1])
        M, _, ok = self.fev.parts(X, TH)
        return M.reshape(shape + M.shape[1:]), ok.reshape(shape)

    def worst_case(self, x: np.ndarray, k: float, *, phi: bool = True, rho: bool = False,
                   refine: int | None = None, samples: int | None = None) -> dict[str, np.ndarray]:
        from ..fields.compute import numpy_worst_case
        from ..fields.search import REFINE_LEVELS

        return numpy_worst_case(self.fev, np.asarray(x, float).reshape(-1, 3), k, samples=samples,
                                refine=REFINE_LEVELS if refine is None else refine, rho=rho)


class EffectsKernel:
    """A spatial truth whose ``[effects]`` change the true Jacobian, the controller's or the loop's frame
    (``joint_geometry``, ``instrument_length``, ``tracker_registration``, ``joint_offset``,
    ``gravity_sag``, ``shaft_flexion``) behind the interface :class:`SpatialModel` takes from the compiled
    :class:`errplan.fields.KernelEvaluator`: ``motion_maps`` and ``worst_case`` from
    :class:`errplan.fields.evaluator.SpatialEffectsEvaluator` (``M = R J Jhat^-1`` with the truth's ``J`` and
    the declared controller's ``Jhat`` at the same encoder angles). A certificate's tips are tracked tips
    (the loop's frame, ``R x + b``): they are mapped to the true tips before the physics."""

    def __init__(self, sc):
        from ..fields.evaluator import SpatialEffectsEvaluator

        self.scenario = sc
        self.fev = SpatialEffectsEvaluator.from_model(sc)
        self.errors = self.fev.errors

    def true_tips(self, y: np.ndarray) -> np.ndarray:
        from ..fields.evaluator import true_tips

        return true_tips(self.fev.plant, y)

    def motion_maps(self, x: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M, ok)`` for tracked tips ``x`` (..., 3) under instances ``theta`` (..., 5), broadcast together:
        ``M`` (..., 3, 3) for the rigid controller, (..., c, 3, 3) over the flexion controller's noise
        corners; NaN where ``ok`` is False."""
        x = np.asarray(x, float)
        theta = np.asarray(theta, float)
        shape = np.broadcast_shapes(x.shape[:-1], theta.shape[:-1])
        X = self.true_tips(np.broadcast_to(x, shape + (3,)).reshape(-1, 3))
        TH = np.broadcast_to(theta, shape + theta.shape[-1:]).reshape(-1, theta.shape[-1])
        M, _, ok = self.fev.parts(X, TH)
        if self.fev.noise is None:
            M = M[:, 0]
        return M.reshape(shape + M.shape[1:]), ok.reshape(shape)

    def worst_case(self, x: np.ndarray, k: float, *, phi: bool = True, rho: bool = False,
                   refine: int | None = None, samples: int | None = None) -> dict[str, np.ndarray]:
        from ..fields.compute import numpy_worst_case
        from ..fields.search import REFINE_LEVELS

        return numpy_worst_case(self.fev, self.true_tips(np.asarray(x, float).reshape(-1, 3)), k, samples=samples,
                                refine=REFINE_LEVELS if refine is None else refine, rho=rho)

    def singular_free(self, c: np.ndarray, radius: float, model: "SpatialModel") -> bool:
        """True when the controller's ``Jhat`` cannot be singular in the ball (the lever bound of
        :meth:`SpatialModel.singular_free` widened by how far the declared wrist lies from the true one at
        the same encoder angles, sampled at the ball's centre and boundary under the corner instances and
        doubled, and by a longer true instrument). P2's controller: the sampled margin of its estimate as
        well. Like the flexion controller's, sampled, not proven."""
        fev = self.fev
        th = model.corner_instances()
        pts = np.vstack([c[None], c + radius * sphere_points(14)])
        X = self.true_tips(np.repeat(pts, len(th), axis=0))
        TH = np.tile(th, (len(pts), 1))
        plant, port, q, ok = fev.configuration(X, TH)
        if not np.any(ok):
            return False
        qo = q[ok]
        gap = float(np.max(np.linalg.norm(fev.arm.forward(qo) - plant.wrist(qo), axis=-1)))
        longer = max(0.0, fev.plant.true_length - fev.length)
        if model.jacobian == "flexion":
            return False  # no margin for P2's estimate on a truth whose arm differs: not certified
        ce = float(np.linalg.norm(self.true_tips(c) - model.estimate))
        return bool(ce - radius > 2.0 * model.delta + model.deviation + 2.0 * gap + longer + 1e-6)


def _is_spatial(ev) -> bool:
    return isinstance(ev, SpatialModel)


def _instance_grid(ev, samples: int) -> np.ndarray:
    return ev.instances(samples) if _is_spatial(ev) else ev.errors.sample_grid(samples)


# ----------------------------------------------------------------------------- nonlinear step
def step_ratio(ev: Evaluator, target, x: np.ndarray, theta: np.ndarray, k) -> np.ndarray:
    """One quasi-static controller step with the full nonlinear kinematics, per pair.

    The truth ``theta`` puts the tip at ``x`` (the configuration is the arm's inverse of the true
    wrist, as :meth:`errplan.simulation.Plant.configuration_for_tip`); the controller commands
    ``dq = k Jarm^-1 Jhat_tw^-1 (b - x)`` and the true tip moves to ``x'`` (flexed shaft, true
    port and load). Returns ``|x' - b| / |x - b|`` (n,) worst over the controller's noise corners;
    ``nan`` where the truth cannot reach ``x`` and ``inf`` where the step leaves the joint limits,
    pulls the shaft out of the port or the controller's Jacobian is singular. ``target`` (d,) or one
    per pair (n, d). In 3-D
    (:class:`SpatialModel`) the same step on the URDF arm.
    """
    if _is_spatial(ev):
        return ev.step_ratio(target, x, theta, k)
    if ev.effects:  # the truth's [effects] (geometry, offsets, sag, load, registration): the general path
        return ev.effect_step_ratio(target, x, theta, k)
    x = np.asarray(x, float)
    theta = np.asarray(theta, float)
    b = np.asarray(target, float)
    k = np.broadcast_to(np.asarray(k, float), x.shape[:-1])
    w, reach = ev.true_wrist(x, theta)
    q, okq = ev.arm.inverse(np.where(reach[..., None], w, 0.0))
    reach = reach & okq
    wsafe = np.where(reach[..., None], w, np.asarray(ev.arm.base))
    qsafe = np.where(reach[..., None], q, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mu_h, nu_h = ev.controller_parts(wsafe, theta)        # (n, c)
        imu, inu, sing = inverse_parts(mu_h, nu_h)
        e = b - x
        z = e[..., 0] + 1j * e[..., 1]
        dwc = k[..., None] * (imu * z[..., None] + inu * np.conj(z[..., None]))  # (n, c)
        dw = np.stack([dwc.real, dwc.imag], axis=-1)          # (n, c, 2)
        Jinv, sing_arm = inv2(ev.arm.jacobian(qsafe))
        dq = np.einsum("nij,ncj->nci", Jinv, dw)
        q2 = qsafe[:, None, :] + dq
        ok_lim = ev.arm.within_limits(q2)
        w2 = ev.arm.forward(q2)
        port = ev.errors.port(theta)[:, None, :]
        r = np.linalg.norm(w2 - port, axis=-1)
        ok_shaft = (r > 1e-9) & (r < ev.length)
        t = np.broadcast_to(theta[:, None, 2], r.shape)
        w2s = np.where(ok_shaft[..., None], w2, port + [0.0, -0.5 * ev.length])
        x2 = flexed_tip(w2s, np.broadcast_to(port, w2s.shape), ev.length, t)
        e0 = np.linalg.norm(e, axis=-1)
        ratio = np.linalg.norm(x2 - (b[:, None, :] if b.ndim == 2 else b), axis=-1) / np.where(e0 > 0, e0, np.nan)[:, None]
    good = ok_lim & ok_shaft & ~sing & ~sing_arm[:, None] & np.isfinite(ratio)
    ratio = np.where(good, ratio, np.inf).max(axis=-1)
    return np.where(reach, ratio, np.nan)
