"""Certified per-segment gains (casadi) for a planned tip path: the convergence-ball certificate.

The controller drives the tip through the path's waypoints; on segment ``s`` (from ``a`` to ``b``)
it aims at ``b``. While the error length ``|x - b|`` shrinks, the tip stays inside the ball
``B_s`` of centre ``b`` and radius ``R_s = |b - a| + switch_tolerance`` (the controller switches to
``b`` once it is within ``switch_tolerance`` of ``a``). So the segment converges monotonically
whatever the truth inside the error set is when, at every tip ``x`` of ``B_s`` that the truth
``theta`` can reach, ``||G|| = ||I - k J Jhat^-1|| < 1`` (P1 Sec. II-B, by induction on the steps).

With the conformal parts ``(mu, nu)`` of ``M = J Jhat^-1`` (:mod:`errplan.metrics`),
``||G(k)|| = |1 - k mu| + k |nu|``: convex in ``k``, so ``rho_s(k) = max over (x, theta) in B_s``
is convex too and the gains of all segments are chosen together as one casadi/IPOPT problem:

    minimise   sum_s log(R_s / tol_s) / (-log r_s)          (predicted steps, P1 eq. 6)
               + W sum_s sigma_s                             (gain-change slack)
    subject to r_s >= |1 - k_s mu_i| + k_s |nu_i|            for the sampled pairs i of B_s
               r_s <= 1 - margin                             (every certifiable segment)
               |k_{s+1} - k_s| <= max_gain_change + sigma_s, sigma_s >= 0.

The epigraph constraint is written without a square root (a second-order cone in smooth form):
``(r - k |nu|)^2 >= (1 - k Re mu)^2 + (k Im mu)^2`` and ``r - k |nu| >= 0``. Sampled pairs
that never attain the maximum on a fine numpy grid of ``k`` are pruned before the solve (grids
belong to numpy, optimisation to casadi).

A segment whose ball is too large to certify (sampled ``rho* > 1 - margin``) is halved, up to
``max_depth`` times. After the solve every certificate is verified on a denser sample than the
optimiser used (more tips, boundary ring, more error-set samples, local refinement of the worst
instance and of the worst tip), and the verified worst case is what ``certified_G_norm`` reports.
The verification also replays one controller step from every sampled (tip, instance) pair with
the full nonlinear kinematics (``step_ratio = |x' - b| / |x - b|``): the ``||G||`` argument is
first order, the replay is not. A segment is ``certified`` only if both are below 1; one that no
gain certifies is reported with ``certified = false`` and the reason.

**3-D** (docs/physics.md "Spatial robots"; the same routine, :class:`SpatialModel` for the physics).
Balls are 3-D (centre, a Fibonacci-spiral volume sample, a Fibonacci sphere), the error set is
(port box, lateral load magnitude and direction), ``M = J Jhat^-1`` is 3 x 3 from the compiled
kernels (:class:`errplan.fields.KernelEvaluator`) and ``||G(k)|| = sigma_max(I - k M)``. For a unit
direction ``v``, ``||(I - k M) v||^2 = (1 - k a)^2 + (k b)^2`` with ``a = v.Mv`` and
``b = |Mv - a v|``: the planar cone constraint with ``|nu| = 0``. ``sigma_max`` is the maximum of
these over ``v``, so the casadi problem is the planar one over *cuts* ``(M_i, v)``; it starts with
the right singular vectors at a few gains of the numpy grid and, after each solve, adds the
singular vector of ``I - k_s M_i`` at the solved gain wherever the cuts underestimate the exact
``sigma_max`` (cutting planes, until the cuts are exact at the solution to 1e-9). Pairs are
pruned on a compiled k-grid as in the plane. A ball is only certified when the controller's
Jacobian cannot be singular in it: ``|x - estimate| > 2 delta + L atan(tau_max L^2/12)`` at every
tip (``delta`` the port box's largest distance from the estimate; analytic, see
:meth:`SpatialModel.singular_free`). Sample sizes differ (``GainOptions.for_dim(3)``): 2 samples per
uncertain port/load axis and 8 load directions for the optimiser, 3 and 8 plus the same pattern
searches for the verification; the nonlinear one-step replay runs from every verification tip
under every corner instance (port corners x {no load, the largest load in 4 directions}) and at
the refined worst pairs.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from numba import njit

from .errors import ErrplanError
from .fields import Evaluator
from .kinematics.shaft import flexed_tip, flexed_wrist_plane, lever_jacobian
from .linalg import g_norm3, v_sigma3
from .metrics import inv, inv2, inverse_parts

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


# ----------------------------------------------------------------------------- options / results
@dataclass(frozen=True)
class GainOptions:
    """Settings of the gain schedule (SI).

    ``max_segment``: longest segment the path is cut into before certification (m); bounds the
    jump the quasi-static controller makes per step. ``switch_tolerance``: the controller moves on
    to the next waypoint once within this distance (m); ``tolerance``: final convergence (m).
    ``margin``: certified segments satisfy ``rho_s <= 1 - margin`` in the optimiser.
    ``max_gain_change``: bound on ``|k_{s+1} - k_s|`` (soft, penalised slack).
    Optimiser sample: ``opt_disk`` + ``opt_ring`` tips per ball, ``opt_samples`` per uncertain axis.
    Verification sample: ``verify_disk`` + ``verify_ring`` tips, ``verify_samples`` per axis,
    ``verify_refine`` halvings of the local search over instances and tips.
    """

    margin: float = 0.02
    max_segment: float = 0.02
    switch_tolerance: float = 1e-3
    tolerance: float = 1e-5
    max_gain_change: float = 0.2
    max_depth: int = 6
    min_segment: float = 2e-4
    rounds: int = 4
    opt_disk: int = 40
    opt_ring: int = 24
    opt_samples: int = 3
    verify_disk: int = 200
    verify_ring: int = 72
    verify_samples: int = 6
    verify_refine: int = 4
    slack_weight: float = 1e3

    @classmethod
    def for_dim(cls, dim: int, **overrides) -> "GainOptions":
        """Defaults for the plane (the dataclass defaults) or for 3-D, where balls and error sets
        are larger: fewer tips and samples per axis, the same local refinement."""
        kw = dict(SPATIAL_DEFAULTS) if dim == 3 else {}
        kw.update(overrides)
        return cls(**kw)

    def validate(self) -> "GainOptions":
        for name in ("max_segment", "switch_tolerance", "tolerance", "min_segment"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ErrplanError(f"gain option {name} = {v!r}: expected a length > 0 m")
        if not 0 <= self.margin < 1:
            raise ErrplanError(f"gain option margin = {self.margin!r}: expected a number in [0, 1)")
        if not self.max_gain_change > 0:
            raise ErrplanError(f"gain option max_gain_change = {self.max_gain_change!r}: expected > 0")
        for name in ("opt_samples", "verify_samples"):
            if getattr(self, name) < 2:
                raise ErrplanError(f"gain option {name} = {getattr(self, name)!r}: expected >= 2")
        return self


#: GainOptions defaults in 3-D (GainOptions.for_dim)
SPATIAL_DEFAULTS = {"opt_disk": 30, "opt_ring": 26, "opt_samples": 2,
                    "verify_disk": 90, "verify_ring": 40, "verify_samples": 3}


@dataclass
class Segment:
    """One certified (or not) segment: the controller aims at ``end`` from ``start`` with ``gain``."""

    start: np.ndarray
    end: np.ndarray
    gain: float
    certified_G_norm: float      # verified worst-case ||G|| over the ball and the error set
    step_ratio: float            # verified worst nonlinear one-step ratio |x' - b| / |x - b|
    certified: bool
    radius: float                # ball radius, m
    predicted_G_norm: float      # the optimiser's rho_s at its (coarser) sample
    edge: int                    # index of the path edge this segment belongs to
    depth: int = 0               # halvings applied to reach it
    samples: dict = field(default_factory=dict)
    reason: str = ""

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.end - self.start))

    def to_json(self) -> dict:
        out = {"from": [float(v) for v in self.start], "to": [float(v) for v in self.end],
               "gain": float(self.gain), "certified_G_norm": _finite(self.certified_G_norm),
               "certified": bool(self.certified), "step_ratio": _finite(self.step_ratio),
               "radius": float(self.radius), "predicted_G_norm": _finite(self.predicted_G_norm),
               "edge": int(self.edge), "depth": int(self.depth), "samples": self.samples}
        if not self.certified and out["certified_G_norm"] is not None and out["certified_G_norm"] < 1:
            # ||G|| < 1 over the ball, but a full step leaves the ball (or the workspace): the worst case
            # over every tip the controller can visit is not bounded by it, so it is no certificate
            # (docs/interfaces.md: certified_G_norm < 1 means certified). The ball's value stays here:
            out["ball_G_norm"] = out["certified_G_norm"]
            out["certified_G_norm"] = None
        if self.reason:
            out["reason"] = self.reason
        return out


def _finite(v: float) -> float | None:
    """JSON-safe number: an unbounded worst case is reported as null (never as certified)."""
    return float(v) if math.isfinite(v) else None


@dataclass
class GainSchedule:
    """The segments of one path with their gains and verified certificates."""

    path: np.ndarray
    segments: list[Segment]
    options: GainOptions
    solver: dict = field(default_factory=dict)

    @property
    def certified(self) -> bool:
        return bool(self.segments) and all(s.certified for s in self.segments)

    @property
    def waypoints(self) -> np.ndarray:
        return np.array([s.end for s in self.segments])

    @property
    def gains(self) -> np.ndarray:
        return np.array([s.gain for s in self.segments])

    @property
    def max_certified_G_norm(self) -> float:
        return max((s.certified_G_norm for s in self.segments), default=float("nan"))

    def predicted_steps(self) -> float:
        """Sum over segments of ``log(R / tol) / -log(||G||)`` (inf if a segment is uncertified)."""
        tot = 0.0
        for i, s in enumerate(self.segments):
            tol = self.options.tolerance if i == len(self.segments) - 1 else self.options.switch_tolerance
            if not s.certified_G_norm < 1:
                return float("inf")
            tot += max(math.log(s.radius / tol), 0.0) / max(-math.log(max(s.certified_G_norm, 1e-12)), 1e-12)
        return tot

    def to_json(self) -> list[dict]:
        return [s.to_json() for s in self.segments]

    def summary(self) -> dict:
        return {"segments": len(self.segments), "certified": self.certified,
                "uncertified": sum(not s.certified for s in self.segments),
                "max_certified_G_norm": _finite(self.max_certified_G_norm),
                "max_step_ratio": _finite(max((s.step_ratio for s in self.segments), default=float("nan"))),
                "gain_range": [float(self.gains.min()), float(self.gains.max())] if self.segments else [],
                "predicted_steps": _finite(self.predicted_steps()), "solver": self.solver}


# ----------------------------------------------------------------------------- sampling
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
    _, reach = ev.true_wrist(X, TH)
    mu, nu, ok = ev.parts(X, TH)
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

    def __init__(self, sc):
        from .fields import KernelEvaluator
        from .kinematics import arm_for

        if sc.controller.jacobian != "rigid":
            raise ErrplanError(f"{sc.source}: [controller] jacobian = {sc.controller.jacobian!r}: in 3-D gains are "
                               "certified for the rigid controller only (P2's flexion controller is planar)")
        try:
            self.kev = KernelEvaluator(sc)
        except ErrplanError:
            raise ErrplanError(f"{sc.source}: [effects] {', '.join(sorted(sc.effects))}: gain certificates of a "
                               "spatial truth whose effects move the arm (joint_offset, gravity_sag, shaft_flexion) "
                               "are not supported yet") from None
        self.scenario = sc
        self.errors = self.kev.errors
        self.arm = arm_for(sc.robot)
        self.length = float(sc.instrument.length)
        self.estimate = np.asarray(sc.port.estimate, float)
        es = self.errors
        self.delta = float(np.max(np.linalg.norm(es.port_corners() - self.estimate, axis=-1)))
        tmax = float(max(abs(es.lo[3]), abs(es.hi[3])))
        self.deviation = self.length * math.atan(tmax * self.length ** 2 / 12.0)

    @classmethod
    def from_scenario(cls, sc) -> "SpatialModel":
        return cls(sc)

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

    def singular_free(self, center, radius: float) -> bool:
        """True when the controller's lever Jacobian cannot be singular at any tip of the ball.

        ``Jhat`` is singular where the wrist is ``L`` from the estimate. For a tip ``x`` with true
        port ``p`` (``|p - e| <= delta``) the wrist is within ``L - |x - p| + deviation`` of ``p``
        (lever wrist ``L - r`` from the port; a load moves it by at most ``deviation``), so
        ``|w - e| < L`` whenever ``|x - e| > 2 delta + deviation``.
        """
        c = np.asarray(center, float)
        return bool(np.linalg.norm(c - self.estimate) - radius > 2.0 * self.delta + self.deviation + 1e-6)

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
        """:func:`step_ratio` in 3-D: one controller step on the URDF arm per pair (n,)."""
        x = np.asarray(x, float)
        theta = np.asarray(theta, float)
        b = np.asarray(target, float)
        k = np.broadcast_to(np.asarray(k, float), x.shape[:-1])
        out = np.full(len(x), np.nan)
        if not len(x):
            return out
        p, w, t, reach = self.wrists(x, theta)
        q, okq = self.arm.inverse(np.where(reach[:, None], w, w[reach][0] if reach.any() else 0.0))
        reach &= okq
        idx = np.flatnonzero(reach)
        if not len(idx):
            return out
        w, p, t, q, xx, kk = w[idx], p[idx], t[idx], q[idx], x[idx], k[idx]
        with np.errstate(invalid="ignore", divide="ignore"):
            Jh_inv, sing = inv(lever_jacobian(w, self.estimate, self.length))
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
        out[idx] = np.where(good, ratio, np.inf)
        return out


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
    pulls the shaft out of the port or the controller's Jacobian is singular. In 3-D
    (:class:`SpatialModel`) the same step on the URDF arm.
    """
    if _is_spatial(ev):
        return ev.step_ratio(target, x, theta, k)
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
        ratio = np.linalg.norm(x2 - b, axis=-1) / np.where(e0 > 0, e0, np.nan)[:, None]
    good = ok_lim & ok_shaft & ~sing & ~sing_arm[:, None] & np.isfinite(ratio)
    ratio = np.where(good, ratio, np.inf).max(axis=-1)
    return np.where(reach, ratio, np.nan)


# ----------------------------------------------------------------------------- one segment
def _sample_segment(ev: Evaluator, a, b, radius: float, opts: GainOptions) -> dict:
    """The optimiser's sample of one ball: flattened conformal parts of the reachable pairs
    (3-D: the motion maps ``M`` (p, 3, 3) of the reachable pairs)."""
    x = ball_tips(b, radius, opts.opt_disk, opts.opt_ring)
    if _is_spatial(ev):
        th = ev.instances(opts.opt_samples)
        M, ok = ev.maps(x, th)
        Ms = M[ok]
        singular = 0 if ev.singular_free(b, radius) else int(ok.sum())
        return {"M": Ms, "singular": singular, "tips": len(x), "instances": len(th), "noise_corners": 1,
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
    lam = np.linalg.eigvalsh(0.5 * (M + np.swapaxes(M, -1, -2)))[:, -1].max()
    return 2.0 / lam if lam > 0 else 1.0


def _scan_M(M: np.ndarray, n: int = 81, top: int = 3):
    """3-D :func:`_scan` and :func:`_prune` in one pass: ``(rho*, k*, kg, pruned indices)``. The
    grid's top pairs are kept; the golden-section polish runs on them (the maximum near the grid's
    best gain is theirs), the value at the result on every pair."""
    ku = _k_upper_M(M)
    kg = np.linspace(ku / n, ku, n)
    G = gnorm3_grid(M, kg)                                   # (n, p)
    vals = G.max(axis=1)
    if len(M) <= 64:
        idx = np.arange(len(M))
    else:
        idx = np.unique(np.argpartition(-G, top, axis=1)[:, :top].ravel())
    Mp = M[idx]
    j = int(np.argmin(vals))
    lo, hi = kg[max(j - 1, 0)], kg[min(j + 1, n - 1)]
    gr = (math.sqrt(5) - 1) / 2
    for _ in range(40):
        c, d = hi - gr * (hi - lo), lo + gr * (hi - lo)
        if rho_of_k_M(Mp, c)[0] < rho_of_k_M(Mp, d)[0]:
            hi = d
        else:
            lo = c
    k = 0.5 * (lo + hi)
    return float(rho_of_k_M(M, k)[0]), float(k), kg, idx


def _k_upper(mu: np.ndarray) -> float:
    """Above ``2 / max|mu|`` no gain contracts (|1 - k mu| >= k|mu| - 1 >= 1)."""
    amax = float(np.abs(mu).max()) if len(mu) else 1.0
    return 2.0 / amax if amax > 0 else 10.0


def _scan(mu, nu, n: int = 401) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Best gain on a numpy grid then golden-section polish: (rho*, k*, grid, values)."""
    ku = _k_upper(mu)
    kg = np.linspace(ku / n, ku, n)
    vals = rho_of_k(mu, nu, kg)
    j = int(np.argmin(vals))
    lo, hi = kg[max(j - 1, 0)], kg[min(j + 1, n - 1)]
    gr = (math.sqrt(5) - 1) / 2
    for _ in range(40):
        c, d = hi - gr * (hi - lo), lo + gr * (hi - lo)
        if rho_of_k(mu, nu, c)[0] < rho_of_k(mu, nu, d)[0]:
            hi = d
        else:
            lo = c
    k = 0.5 * (lo + hi)
    return float(rho_of_k(mu, nu, k)[0]), float(k), kg, vals


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


# ----------------------------------------------------------------------------- casadi problem
def solve_gains(samples: list[dict], opts: GainOptions, *, fixed: list[bool] | None = None) -> tuple[np.ndarray, dict]:
    """Choose every segment's gain in one casadi/IPOPT problem (see the module docstring).

    ``samples[s]`` holds the segment's pruned ``mu``/``nu`` (complex) or, in 3-D, its cut ``rows``
    (p, 2) and gain bound ``ku``, and ``d`` (ball radius),
    ``tol`` (its convergence tolerance), ``k0``/``rho0`` (numpy scan); ``fixed[s]`` marks a
    segment no gain certifies: its gain stays at the scan's best and it does not constrain the
    others beyond the (soft) gain-change bound. Returns the gains and a solver report.
    """
    import casadi as ca

    S = len(samples)
    fixed = fixed or [False] * S
    k = ca.SX.sym("k", S)
    r = ca.SX.sym("r", S)
    sig = ca.SX.sym("sigma", max(S - 1, 0))
    g, lbg, ubg = [], [], []
    obj = 0
    lbx_k, ubx_k, lbx_r, ubx_r, x0_k, x0_r = [], [], [], [], [], []
    for s, smp in enumerate(samples):
        if "rows" in smp:  # 3-D cuts (a, b): ||(I - kM) v|| = sqrt((1 - k a)^2 + (k b)^2), |nu| = 0
            rows = smp["rows"]
            A, B, C = ca.DM(rows[:, 0]), ca.DM(rows[:, 1]), ca.DM(np.zeros(len(rows)))
            n = len(rows)
            ku = smp["ku"]
        else:
            mu, nu = smp["mu"], smp["nu"]
            A, B, C = ca.DM(mu.real), ca.DM(mu.imag), ca.DM(np.abs(nu))
            n = len(mu)
            ku = _k_upper(mu)
        slackr = r[s] - k[s] * C
        g += [slackr ** 2 - (1 - k[s] * A) ** 2 - (k[s] * B) ** 2, slackr]
        lbg += [0.0] * (2 * n)
        ubg += [ca.inf] * (2 * n)
        if fixed[s]:
            lbx_k.append(smp["k0"]); ubx_k.append(smp["k0"])
            lbx_r.append(0.0); ubx_r.append(ca.inf)
            obj += 1e-3 * r[s]
        else:
            lbx_k.append(1e-6); ubx_k.append(ku)
            lbx_r.append(1e-6); ubx_r.append(1.0 - opts.margin)
            obj += max(math.log(smp["d"] / smp["tol"]), 1e-3) / (-ca.log(r[s]))
        x0_k.append(smp["k0"])
        x0_r.append(min(smp["rho0"] + 1e-9, 1.0 - opts.margin) if not fixed[s] else smp["rho0"])
    for s in range(S - 1):
        dk = k[s + 1] - k[s]
        g += [dk - sig[s], -dk - sig[s]]
        lbg += [-ca.inf, -ca.inf]
        ubg += [opts.max_gain_change, opts.max_gain_change]
        obj += opts.slack_weight * sig[s]
    x = ca.vertcat(k, r, sig)
    lbx = lbx_k + lbx_r + [0.0] * (S - 1)
    ubx = ubx_k + ubx_r + [ca.inf] * (S - 1)
    x0 = x0_k + x0_r + [max(abs(x0_k[s + 1] - x0_k[s]) - opts.max_gain_change, 0.0) for s in range(S - 1)]
    nlp = {"x": x, "f": obj, "g": ca.vertcat(*[ca.vec(e) for e in g])}
    solver = ca.nlpsol("gains", "ipopt", nlp, {"ipopt.print_level": 0, "print_time": 0, "ipopt.sb": "yes",
                                                "ipopt.tol": 1e-10, "ipopt.max_iter": 500})
    t0 = time.perf_counter()
    sol = solver(x0=x0, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
    stats = solver.stats()
    xs = np.asarray(sol["x"]).ravel()
    ks = xs[:S]
    info = {"solver": "ipopt", "status": stats.get("return_status", "?"), "success": bool(stats.get("success", False)),
            "iterations": int(stats.get("iter_count", -1)), "objective": float(sol["f"]),
            "time_s": time.perf_counter() - t0, "segments": S,
            "constraints": int(sum(len(s["rows"]) if "rows" in s else len(s["mu"]) for s in samples)),
            "gain_change_slack": float(xs[2 * S:].max()) if S > 1 else 0.0}
    if not info["success"] or not np.all(np.isfinite(ks)):
        # Fall back to each segment's own best gain: still verified below, never assumed.
        ks = np.array([s["k0"] for s in samples])
        info["fallback"] = "per-segment scan gains (the joint problem did not solve)"
    return ks, info


# ----------------------------------------------------------------------------- verification
def verify_segment(ev: Evaluator, start, end, k: float, radius: float, opts: GainOptions) -> dict:
    """Worst ``||G||`` and nonlinear one-step ratio over the ball, denser than the optimiser.

    Tips: centre + ``verify_disk`` sunflower + ``verify_ring`` boundary points; instances: a grid
    of ``verify_samples`` per uncertain axis, then a pattern search over the instance of every
    tip (``verify_refine`` halvings) and over the position of the 8 worst tips (kept in the ball).
    3-D: :func:`_verify_spatial`.
    """
    if _is_spatial(ev):
        return _verify_spatial(ev, start, end, k, radius, opts)
    es = ev.errors
    b = np.asarray(end, float)
    x = ball_tips(b, radius, opts.verify_disk, opts.verify_ring)
    th = es.sample_grid(opts.verify_samples)
    mu, nu, reach, ok = _pairs(ev, x, th)
    G = _worst_g(mu, nu, reach, ok, k)                 # (n, m)
    grid_max = float(G.max())
    j = np.argmax(G, axis=1)
    best = G[np.arange(len(x)), j]
    th_best = th[j].copy()
    # Nonlinear one-step replay on the grid pairs.
    n, m = len(x), len(th)
    X = np.repeat(x, m, axis=0)
    TH = np.tile(th, (n, 1))
    far = np.linalg.norm(X - b, axis=-1) > 1e-9
    sr = step_ratio(ev, b, X[far], TH[far], k)
    step_max = float(np.nanmax(sr)) if np.any(np.isfinite(sr) | np.isinf(sr)) else float("nan")
    # Refine the worst instance of every tip (pattern search over the active axes).
    step0 = es.spacing(opts.verify_samples)
    dims = np.flatnonzero(es.active)

    def eval_at(xx, tt):
        mu1, nu1, ok1 = ev.parts(xx, tt)
        _, r1 = ev.true_wrist(xx, tt)
        return _worst_g(mu1, nu1, r1, ok1, k)

    for level in range(1, opts.verify_refine + 1):
        h = step0 / 2 ** level
        for dmn in dims:
            for sgn in (-1.0, 1.0):
                c = th_best.copy()
                c[:, dmn] = np.clip(c[:, dmn] + sgn * h[dmn], es.lo[dmn], es.hi[dmn])
                g1 = eval_at(x, c)
                upd = g1 > best
                best[upd] = g1[upd]
                th_best[upd] = c[upd]
    # Refine the position of the worst tips inside the ball (with their instance).
    top = np.argsort(-best)[:8]
    xt, tt, bt = x[top].copy(), th_best[top].copy(), best[top].copy()
    hx = radius / math.sqrt(opts.verify_disk + 1)
    for level in range(opts.verify_refine):
        h = hx / 2 ** level
        for d in ([h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]):
            c = xt + np.array(d)
            off = c - b
            rr = np.linalg.norm(off, axis=-1)
            c = np.where((rr > radius)[:, None], b + off * (radius / np.maximum(rr, 1e-300))[:, None], c)
            g1 = eval_at(c, tt)
            upd = g1 > bt
            bt[upd] = g1[upd]
            xt[upd] = c[upd]
        for dmn in dims:
            for sgn in (-1.0, 1.0):
                c = tt.copy()
                c[:, dmn] = np.clip(c[:, dmn] + sgn * step0[dmn] / 2 ** (opts.verify_refine + level), es.lo[dmn], es.hi[dmn])
                g1 = eval_at(xt, c)
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
    reach_share = float(reach.any(axis=1).mean())
    if worst == -np.inf:
        worst = float("nan")  # no tip of the ball is reachable: nothing to certify
    return {"G_norm": worst, "grid_G_norm": grid_max, "step_ratio": step_max,
            "worst_tip": xt[iw].tolist(), "worst_theta": tt[iw].tolist(),
            "tips": len(x), "instances": len(th), "noise_corners": int(mu.shape[-1]), "pairs": int(reach.sum()),
            "reachable_tip_share": reach_share, "singular_pairs": int((reach & ~ok).sum())}


def _g3(ev: SpatialModel, x: np.ndarray, th: np.ndarray, k: float, singular: bool) -> np.ndarray:
    """Worst ||G|| per pair (n,) in 3-D: -inf where the truth cannot reach the tip, +inf where it can
    and the ball is not singular-free."""
    M, ok = ev.maps_paired(x, th)
    g = gnorm3_grid(M, k)[0]
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


def _verify_spatial(ev: SpatialModel, start, end, k: float, radius: float, opts: GainOptions) -> dict:
    """:func:`verify_segment` in 3-D: the ball's tips (centre, ``verify_disk`` volume and
    ``verify_ring`` sphere points) under ``verify_samples`` per uncertain axis (8 load directions),
    a pattern search over each tip's worst instance (periodic in the load direction) and over the
    position of the 8 worst tips; the nonlinear step from every tip under every corner instance
    and at the refined worst pairs."""
    es = ev.errors
    b = np.asarray(end, float)
    singular = not ev.singular_free(b, radius)
    x = ball_tips(b, radius, opts.verify_disk, opts.verify_ring)
    th = ev.instances(opts.verify_samples)
    M, ok = ev.maps(x, th)
    n, m = ok.shape
    G = gnorm3_grid(M.reshape(-1, 3, 3), k)[0].reshape(n, m)
    G = np.where(np.isfinite(G), G, np.inf)
    if singular:
        G = np.where(ok, np.inf, G)
    G = np.where(ok, G, -np.inf)
    grid_max = float(G.max())
    j = np.argmax(G, axis=1)
    best = G[np.arange(n), j]
    th_best = th[j].copy()
    # Nonlinear one-step replay from every tip under every corner instance.
    tc = ev.corner_instances()
    far = np.linalg.norm(x - b, axis=-1) > 1e-9
    X = np.repeat(x[far], len(tc), axis=0)
    TH = np.tile(tc, (int(far.sum()), 1))
    sr = ev.step_ratio(b, X, TH, k)
    step_max = float(np.nanmax(sr)) if np.any(~np.isnan(sr)) else float("nan")
    step0 = es.spacing(opts.verify_samples)
    dims = np.flatnonzero(es.active)
    live = np.isfinite(best)  # tips some instance reaches (and not already unbounded)
    for level in range(1, opts.verify_refine + 1):
        h = step0 / 2 ** level
        for dmn in dims:
            for sgn in (-1.0, 1.0):
                if not live.any():
                    break
                c = _poll(es, th_best[live], dmn, sgn * h[dmn])
                g1 = _g3(ev, x[live], c, k, singular)
                upd = g1 > best[live]
                ii = np.flatnonzero(live)[upd]
                best[ii] = g1[upd]
                th_best[ii] = c[upd]
    top = np.argsort(-best)[:8]
    xt, tt, bt = x[top].copy(), th_best[top].copy(), best[top].copy()
    hx = radius / math.cbrt(opts.verify_disk + 1)
    steps = np.vstack([np.eye(3), -np.eye(3)])
    for level in range(opts.verify_refine):
        h = hx / 2 ** level
        for dv in steps:
            c = xt + h * dv
            off = c - b
            rr = np.linalg.norm(off, axis=-1)
            c = np.where((rr > radius)[:, None], b + off * (radius / np.maximum(rr, 1e-300))[:, None], c)
            g1 = _g3(ev, c, tt, k, singular)
            upd = g1 > bt
            bt[upd] = g1[upd]
            xt[upd] = c[upd]
        for dmn in dims:
            for sgn in (-1.0, 1.0):
                c = _poll(es, tt, dmn, sgn * step0[dmn] / 2 ** (opts.verify_refine + level))
                g1 = _g3(ev, xt, c, k, singular)
                upd = g1 > bt
                bt[upd] = g1[upd]
                tt[upd] = c[upd]
    worst = float(max(best.max(), bt.max()))
    iw = int(np.argmax(bt))
    farw = np.linalg.norm(xt - b, axis=-1) > 1e-9
    if np.any(farw):
        sr2 = ev.step_ratio(b, xt[farw], tt[farw], k)
        if np.any(~np.isnan(sr2)):
            step_max = float(np.nanmax(np.concatenate([[step_max] if not math.isnan(step_max) else [], sr2[~np.isnan(sr2)]])))
    if worst == -np.inf:
        worst = float("nan")
    return {"G_norm": worst, "grid_G_norm": grid_max, "step_ratio": step_max,
            "worst_tip": xt[iw].tolist(), "worst_theta": tt[iw].tolist(),
            "tips": len(x), "instances": len(th), "noise_corners": 1, "pairs": int(ok.sum()),
            "reachable_tip_share": float(ok.any(axis=1).mean()),
            "singular_pairs": int(ok.sum()) if singular else 0, "step_pairs": int(len(X))}


def _lower_gain(ev: Evaluator, a, b, k: float, radius: float, opts: GainOptions, factor: float = 0.8,
               tries: int = 12):
    """The largest gain ``k factor^j`` whose nonlinear step ratio (verification grid) is below 1,
    re-verified in full; None if none is found. Smaller steps make the quasi-static step closer to
    its linearisation, at the price of a larger ``||G||`` (closer to 1)."""
    bb = np.asarray(b, float)
    x = ball_tips(bb, radius, opts.verify_disk, opts.verify_ring)
    x = x[np.linalg.norm(x - bb, axis=-1) > 1e-9]
    th = ev.corner_instances() if _is_spatial(ev) else ev.errors.sample_grid(opts.verify_samples)
    X = np.repeat(x, len(th), axis=0)
    TH = np.tile(th, (len(x), 1))
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


# ----------------------------------------------------------------------------- schedule
def cut_path(path: np.ndarray, max_segment: float) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Split every edge of ``path`` (m, 2) into equal pieces no longer than ``max_segment``."""
    path = np.asarray(path, float)
    out = []
    for e in range(len(path) - 1):
        a, b = path[e], path[e + 1]
        L = float(np.linalg.norm(b - a))
        if L <= 1e-12:
            continue
        n = max(1, math.ceil(L / max_segment - 1e-9))
        for i in range(n):
            out.append((a + (b - a) * i / n, a + (b - a) * (i + 1) / n, e))
    return out


def _as_evaluator(src):
    """The physics of a scenario: the planar :class:`Evaluator` or, in 3-D, a :class:`SpatialModel`."""
    if isinstance(src, (Evaluator, SpatialModel)):
        return src
    if getattr(src, "dim", 2) == 3:
        return SpatialModel(src)
    return Evaluator.from_scenario(src)


def _default_options(src) -> GainOptions:
    if isinstance(src, SpatialModel):
        return GainOptions.for_dim(3)
    if isinstance(src, Evaluator):
        return GainOptions()
    return options_from_scenario(src)


def options_from_scenario(sc, **overrides) -> GainOptions:
    kw = {"margin": sc.planner.certify_margin}
    kw.update(overrides)
    return GainOptions.for_dim(getattr(sc, "dim", 2), **kw).validate()


def _initial_cuts(M: np.ndarray, k0: float, ku: float) -> np.ndarray:
    """Cut rows of the pruned pairs at the scan's gain and at 0.8 and 1.25 times it (within ``ku``);
    the cutting-plane loop adds what the solution needs."""
    ks = [k0] + [min(f * k0, ku) for f in (0.8, 1.25)]
    return np.vstack([cut_rows(M, kk) for kk in ks])


def _solve_with_cuts(probs: list[dict], Ms: list, opts: GainOptions, fixed: list[bool],
                     max_rounds: int = 12) -> tuple[np.ndarray, dict]:
    """:func:`solve_gains` with cutting planes for the 3-D segments (``Ms[s]`` their pruned maps,
    None for planar ones): after each solve, add the singular-vector cut at the solved gain for
    every pair whose exact ``||I - k M||`` exceeds the cuts by more than 1e-9; stop when none does."""
    total = 0
    for it in range(max_rounds):
        ks, info = solve_gains(probs, opts, fixed=fixed)
        added = 0
        for s, (pr, M) in enumerate(zip(probs, Ms)):
            if M is None or not len(M) or fixed[s]:
                continue
            kk = float(ks[s])
            exact = gnorm3_grid(M, kk)[0]
            rows = pr["rows"]
            cuts = np.sqrt((1 - kk * rows[:, 0]) ** 2 + (kk * rows[:, 1]) ** 2).max()
            gap = exact.max() - cuts
            if gap > 1e-9:
                hot = exact > cuts + 1e-9
                pr["rows"] = np.vstack([rows, cut_rows(M[hot], kk)])
                added += int(hot.sum())
        total += added
        if not added:
            break
    info["cut_rounds"] = it + 1
    info["cuts_added"] = total
    return ks, info


def schedule_gains(src, path, options: GainOptions | None = None, *, progress=None) -> GainSchedule:
    """Certified per-segment gains for a tip path (m, 2) under a scenario's error set.

    ``src``: a :class:`errplan.scenario.Scenario` (planar or spatial), an
    :class:`errplan.fields.Evaluator` or a :class:`SpatialModel`; ``path`` (m, d).
    Cuts the path into pieces of at most ``max_segment``, halves the pieces whose ball no sampled
    gain certifies, chooses all gains in one casadi problem, verifies each certificate densely and
    halves (and re-solves) where the verification fails, up to ``rounds`` times.
    """
    ev = _as_evaluator(src)
    opts = (options or _default_options(src)).validate()
    dim = 3 if _is_spatial(ev) else 2
    path = np.atleast_2d(np.asarray(path, float))
    if path.ndim != 2 or path.shape[1] != dim or len(path) < 2 or not np.all(np.isfinite(path)):
        pts = "[x, y, z]" if dim == 3 else "[y, z]"
        raise ErrplanError(f"path of shape {path.shape}: expected (m >= 2, {dim}) finite {pts} points")
    pieces = [(a, b, e, 0) for a, b, e in cut_path(path, opts.max_segment)]
    if not pieces:
        raise ErrplanError("path has zero length: start and goal coincide")
    cache: dict = {}

    def sample(a, b):
        key = (tuple(np.round(a, 12)), tuple(np.round(b, 12)))
        if key not in cache:
            R = float(np.linalg.norm(b - a)) + opts.switch_tolerance
            smp = _sample_segment(ev, a, b, R, opts)
            smp["d"] = R
            if "M" in smp:
                if len(smp["M"]) == 0:
                    smp.update(rho0=float("inf"), k0=1.0, kg=None)
                else:
                    rho0, k0, kg, idx = _scan_M(smp["M"])
                    smp.update(rho0=float("inf") if smp["singular"] else rho0, k0=k0, kg=kg, prune=idx,
                               ku=_k_upper_M(smp["M"]))
            elif len(smp["mu"]) == 0:
                smp.update(rho0=float("inf"), k0=1.0, kg=None, vals=None)
            else:
                rho0, k0, kg, vals = _scan(smp["mu"], smp["nu"])
                if smp["singular"]:
                    rho0 = float("inf")
                smp.update(rho0=rho0, k0=k0, kg=kg)
            cache[key] = smp
        return cache[key]

    def split(piece):
        a, b, e, d = piece
        m = 0.5 * (a + b)
        return [(a, m, e, d + 1), (m, b, e, d + 1)]

    def can_split(piece):
        a, b, _, d = piece
        return d < opts.max_depth and np.linalg.norm(b - a) / 2 >= opts.min_segment

    # 1) halve where the optimiser's own sample shows no certifying gain
    changed = True
    while changed:
        changed = False
        out = []
        for p in pieces:
            smp = sample(p[0], p[1])
            if smp["rho0"] > 1.0 - opts.margin and can_split(p):
                out += split(p)
                changed = True
            else:
                out.append(p)
        pieces = out
    info: dict = {}
    segs: list[Segment] = []
    for rnd in range(opts.rounds):
        smps = [sample(p[0], p[1]) for p in pieces]
        fixed = [not (s["rho0"] <= 1.0 - opts.margin) for s in smps]
        probs = []
        Ms = []
        for i, s in enumerate(smps):
            Ms.append(None)
            if s["kg"] is None:
                probs.append({"mu": np.zeros(0, complex), "nu": np.zeros(0, complex), "d": s["d"],
                              "tol": opts.switch_tolerance, "k0": 1.0, "rho0": 1.0})
                fixed[i] = True
                continue
            if "M" in s:
                M = s["M"][s["prune"]]
                Ms[-1] = M
                probs.append({"rows": _initial_cuts(M, s["k0"], s["ku"]), "ku": s["ku"], "d": s["d"], "k0": s["k0"],
                              "rho0": min(s["rho0"], 10.0),
                              "tol": opts.tolerance if i == len(smps) - 1 else opts.switch_tolerance})
                continue
            idx = _prune(s["mu"], s["nu"], s["kg"])
            probs.append({"mu": s["mu"][idx], "nu": s["nu"][idx], "d": s["d"], "k0": s["k0"],
                          "rho0": min(s["rho0"], 10.0),
                          "tol": opts.tolerance if i == len(smps) - 1 else opts.switch_tolerance})
        if dim == 3:
            ks, info = _solve_with_cuts(probs, Ms, opts, fixed)
        else:
            ks, info = solve_gains(probs, opts, fixed=fixed)
        info["round"] = rnd + 1
        segs = []
        redo = []
        for i, (p, s, kk) in enumerate(zip(pieces, smps, ks)):
            if progress:
                progress((rnd + (i + 1) / len(pieces)) / opts.rounds, "verifying certificates")
            a, b, e, d = p
            v = verify_segment(ev, a, b, float(kk), s["d"], opts)
            pred = float(_rho(s, kk)[0]) if len(s["M"] if "M" in s else s["mu"]) else float("nan")
            if s["singular"]:
                pred = float("inf")
            gn, sr = v["G_norm"], v["step_ratio"]
            if gn < 1.0 and not sr < 1.0 and not can_split(p):
                # ||G|| certifies but a large nonlinear step does not: try smaller gains.
                low = _lower_gain(ev, a, b, float(kk), s["d"], opts)
                if low is not None:
                    kk, v = low
                    gn, sr = v["G_norm"], v["step_ratio"]
                    pred = float(_rho(s, kk)[0])
            cert = bool(gn < 1.0 and sr < 1.0)  # NaN compares False: never certified by default
            reason = ""
            if not cert:
                if math.isnan(gn):
                    reason = "no tip of the ball is reachable under the error set"
                elif v["singular_pairs"] or s["singular"]:
                    reason = "the controller's Jacobian is singular inside the ball"
                elif not gn < 1.0:
                    reason = f"no gain found with worst-case ||G|| < 1 over the ball (best {gn:.3f})"
                elif math.isinf(sr):
                    reason = (f"||G|| = {gn:.3f} < 1, but from some tip of the ball a full step leaves the joint "
                              f"limits or pulls the shaft out of the port (the ball reaches the workspace edge)")
                else:
                    reason = f"||G|| = {gn:.3f} < 1, but a full nonlinear step grows the error (ratio {sr:.3f})"
                if can_split(p):
                    redo.append(i)
            smpinfo = {"optimiser": {k_: s[k_] for k_ in ("tips", "instances", "noise_corners", "pairs")},
                       "verification": {k_: v[k_] for k_ in ("tips", "instances", "noise_corners", "pairs", "grid_G_norm",
                                                              "reachable_tip_share", "worst_tip", "worst_theta")}}
            segs.append(Segment(a.copy(), b.copy(), float(kk), gn, sr, cert, s["d"], pred, e, d, smpinfo, reason))
        if not redo:
            break
        pieces = [q for i, p in enumerate(pieces) for q in (split(p) if i in redo else [p])]
    return GainSchedule(path, segs, opts, info)


def single_segment(src, start, goal, options: GainOptions | None = None) -> GainSchedule:
    """The direct path as ONE segment with its best gain (no cutting, no halving), verified."""
    opts = options or _default_options(src)
    opts = GainOptions(**{**opts.__dict__, "max_segment": 1e9, "max_depth": 0, "rounds": 1}).validate()
    return schedule_gains(src, np.array([start, goal], float), opts)
