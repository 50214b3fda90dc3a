"""Worst-case metric fields over a tip grid and a bounded error set (P1 Sec. IV, P2 Sec. IV-B).

For every tip position ``x`` of a grid and every error instance (true port = estimate + offset,
tip load ``t = Ft/EI``), the *true* configuration is the one that puts the true tip at ``x``
(:func:`errplan.kinematics.shaft.flexed_wrist`), the true Jacobian ``J`` is the flexed-shaft
Jacobian there and the controller's ``Jhat`` comes from its model (rigid lever through the port
estimate, or P2's flexion model fed by the measured end poses, worst case over the corners of the
sensor-noise box). Because ``J Jhat^-1 = J_tw Jhat_tw^-1`` (the arm Jacobian cancels), metrics
depend on the arm only through reachability.

The worst case over the continuous error set is found by sampling it on a grid
(``[uncertainty] samples`` per axis) and refining each tip's worst sample by a local pattern
search (step halved ``REFINE_LEVELS`` times; polls that a box face clips are skipped; up to
``EXTRA_PASSES`` further passes where the worst case still climbs, e.g. along a ridge). Where a
second sampled local maximum could overtake the first after refinement (its value plus twice
its parabolic refinement gain comes within ``SECOND_START`` of the worst), it is refined too.
Checked against an independent dense-sampling implementation (tests/test_fields.py): it never
falls below the dense worst case by more than 1e-3 (relative above 1). A tip is in the workspace
only if it is reachable under every instance evaluated (robust validity).
"""
from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import ErrplanError
from .kinematics.arm import Arm
from .kinematics.shaft import (estimate_from_ends, flexed_end_angles, flexed_jacobian,
                               flexed_tip, flexed_wrist, lever_jacobian, lever_parts, lever_wrist)
from .kinematics.truth import Plant, effect_kwargs
from .metrics import (compose_parts, conformal_parts, g_norm_from_parts, inv2, inverse_parts, phi_hat_max,
                      phi_max_from_parts)

REFINE_LEVELS = 6
_STATS: dict = {}  # diagnostics of the last worst_case call (number of second starts)
EXTRA_PASSES = 2  # further pattern-search passes for worst cases still climbing
SECOND_START = 0.002  # relative margin within which a second local maximum is refined too
Progress = Callable[[float, str], None]


# ----------------------------------------------------------------------------- error set
@dataclass(frozen=True)
class ErrorSet:
    """A box of error parameters ``theta = (dy, dz, t)`` and the controller noise bounds.

    ``port = base_port + [dy, dz]``; ``t`` is the lateral tip load over EI (1/m^2).
    ``noise = (position, angle)`` bounds each measured coordinate of P2's flexion controller.
    """

    base_port: tuple[float, float]
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    noise: tuple[float, float] = (0.0, 0.0)
    samples: int = 5

    @classmethod
    def from_scenario(cls, sc) -> "ErrorSet":
        u = sc.uncertainty
        if u.port_y is None and u.port_z is None:
            base, py, pz = sc.port.position, (0.0, 0.0), (0.0, 0.0)
        else:
            base, py, pz = sc.port.estimate, u.port_y or (0.0, 0.0), u.port_z or (0.0, 0.0)
        tl = u.tip_force_over_ei or (0.0, 0.0)
        noise = (u.sensor_noise.position, u.sensor_noise.angle) if u.sensor_noise else (0.0, 0.0)
        return cls(tuple(base), (py[0], pz[0], tl[0]), (py[1], pz[1], tl[1]), noise, u.samples)

    @property
    def lo_arr(self) -> np.ndarray:
        return np.asarray(self.lo, float)

    @property
    def hi_arr(self) -> np.ndarray:
        return np.asarray(self.hi, float)

    @property
    def active(self) -> np.ndarray:
        """Mask of the uncertain axes (those with a non-degenerate range)."""
        return self.hi_arr > self.lo_arr

    def sample_grid(self, samples: int | None = None) -> np.ndarray:
        """Parameters (n, 3) on a regular grid over the box, ``samples`` per uncertain axis."""
        n = samples or self.samples
        axes = [np.linspace(l, h, n) if h > l else np.array([l]) for l, h in zip(self.lo, self.hi)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)

    def corners(self) -> np.ndarray:
        axes = [(l, h) if h > l else (l,) for l, h in zip(self.lo, self.hi)]
        return np.array(list(itertools.product(*axes)), float)

    def spacing(self, samples: int | None = None) -> np.ndarray:
        n = samples or self.samples
        return (self.hi_arr - self.lo_arr) / (n - 1)

    def port(self, theta: np.ndarray) -> np.ndarray:
        return np.asarray(self.base_port) + theta[..., :2]

    def noise_corners(self) -> np.ndarray:
        """Sensor-noise vectors (c, 6) at the corners of the noise box: [pw(2), pt(2), th_w, th_t]."""
        pos, ang = self.noise
        if pos == 0 and ang == 0:
            return np.zeros((1, 6))
        axes = [(-pos, pos) if pos > 0 else (0.0,)] * 4 + [(-ang, ang) if ang > 0 else (0.0,)] * 2
        return np.array(list(itertools.product(*axes)), float)


# ----------------------------------------------------------------------------- evaluator
@dataclass
class Evaluator:
    """Metrics of one tip set under error instances: the physics of docs/physics.md, batched."""

    arm: Arm
    length: float
    estimate: tuple[float, float]
    jacobian: str  # "rigid" | "flexion"
    errors: ErrorSet
    effects: dict = field(default_factory=dict)  # Plant keyword arguments of the truth's [effects]

    @classmethod
    def from_scenario(cls, sc) -> "Evaluator":
        kw = {k: v for k, v in effect_kwargs(sc.effects).items()
              if k in JACOBIAN_EFFECTS and any(x != 0 for x in v)}
        errors = ErrorSet.from_scenario(sc)
        if "port_offset" in kw:  # the true port moves: fold it into the error set (fast path kept)
            off = kw.pop("port_offset")
            errors = replace(errors, base_port=(errors.base_port[0] + off[0], errors.base_port[1] + off[1]))
        return cls(Arm.from_robot(sc.robot), sc.instrument.length, tuple(sc.port.estimate),
                   sc.controller.jacobian, errors, kw)

    def true_wrist(self, x: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Wrist putting the true tip at ``x`` and its validity (reachable, shaft through port)."""
        port = self.errors.port(theta)
        t = theta[..., 2]
        d = x - port
        r = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)
        ok_shaft = (r > 1e-9) & (r < self.length)
        if not np.any(t != 0):  # straight shaft: the lever's unique wrist (fast path)
            scale = self.length / np.where(ok_shaft, r, 1.0)
            w = x - scale[..., None] * d
        else:
            xs = np.where(ok_shaft[..., None], x, port + [0.0, 0.5 * self.length])
            w = flexed_wrist(xs, port, self.length, np.where(ok_shaft, t, 0.0))
        ok_arm = self.arm.reachable(np.where(ok_shaft[..., None], w, 0.0))
        return w, ok_shaft & ok_arm

    def controller_parts(self, w: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Conformal parts of the controller's ``Jhat_tw`` at the true wrist: (..., c), c noise
        corners of P2's flexion controller (1 for the rigid lever)."""
        if self.jacobian == "rigid":
            mu, nu = lever_parts(w, np.asarray(self.estimate), self.length)
            return mu[..., None], nu[..., None]
        port = self.errors.port(theta)
        t = theta[..., 2]
        tip, thw, tht = flexed_end_angles(w, port, self.length, t)
        nc = self.errors.noise_corners()  # (c, 6)
        pw = w[..., None, :] + nc[:, 0:2]
        pt = tip[..., None, :] + nc[:, 2:4]
        est = estimate_from_ends(pw, pt, thw[..., None] + nc[:, 4], tht[..., None] + nc[:, 5], self.length)
        with np.errstate(invalid="ignore", divide="ignore"):
            mu, nu = conformal_parts(flexed_jacobian(pw, est["port"], self.length, est["t"]))
        # An unbent shaft (noise-free, zero load) does not identify P2's model: the controller
        # falls back to the lever through the port estimate (as ControllerModel.J_hat does).
        rigid = ~(np.isfinite(mu) & np.isfinite(nu))
        if np.any(rigid):
            mu_l, nu_l = lever_parts(w, np.asarray(self.estimate), self.length)
            mu = np.where(rigid, mu_l[..., None], mu)
            nu = np.where(rigid, nu_l[..., None], nu)
        return mu, nu

    def parts(self, x: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Conformal parts ``(mu, nu)`` of ``M = J Jhat^-1`` (..., c) and validity (...)."""
        if self.effects:
            return self._effect_parts(np.asarray(x, float), np.asarray(theta, float))
        w, ok = self.true_wrist(x, theta)
        wsafe = np.where(ok[..., None], w, np.asarray(self.arm.base))
        port = self.errors.port(theta)
        t = theta[..., 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            if np.any(t != 0):
                mu_j, nu_j = conformal_parts(flexed_jacobian(wsafe, port, self.length, t))
            else:
                mu_j, nu_j = lever_parts(wsafe, port, self.length)
            mu_h, nu_h = self.controller_parts(wsafe, theta)
            imu, inu, singular = inverse_parts(mu_h, nu_h)
            mu, nu = compose_parts(mu_j[..., None], nu_j[..., None], imu, inu)
        bad = singular | ~np.isfinite(mu) | ~np.isfinite(nu)
        # A singular or unidentifiable controller Jacobian is unbounded error: not a valid tip.
        ok = ok & ~np.any(bad, axis=-1)
        return mu, nu, ok


    def plant(self, theta: np.ndarray) -> Plant:
        """The truth of instance(s) ``theta`` with the scenario's effects."""
        return Plant(self.arm, self.length, self.errors.port(theta), theta[..., 2], **self.effects)

    def _effect_parts(self, x: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """General path for a truth with [effects] (joint offsets, gravity sag, world tip load, port
        offset): the arm Jacobian no longer cancels. Encoder angles putting the true tip at ``x``
        by Newton's method on the full forward map, true ``J = d tip/d q_enc`` by central
        differences, ``Jhat`` from the controller model at the encoder angles."""
        theta = np.broadcast_to(theta, x.shape[:-1] + (3,))
        plant = self.plant(theta)
        port = plant.true_port
        d = x - port
        r = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)
        ok = (r > 1e-9) & (r < self.length)
        xs = np.where(ok[..., None], x, port + [0.0, 0.5 * self.length])
        with np.errstate(invalid="ignore", divide="ignore"):
            w0 = flexed_wrist(xs, port, self.length, plant.shaft_load(lever_wrist(xs, port, self.length)))
            q_link, ok_ik = self.arm.inverse(w0)
            ok &= ok_ik
            q = np.where(ok[..., None], q_link - np.asarray(plant.joint_offset), 0.0)
            for _ in range(EFFECT_NEWTON_ITERS):
                f = plant.tip(q) - xs
                J = _fd_jacobian(plant.tip, q)
                Jinv, sing = inv2(J)
                q = q - np.where(sing[..., None], 0.0, np.einsum("...ij,...j->...i", np.nan_to_num(Jinv), f))
            resid = np.linalg.norm(plant.tip(q) - xs, axis=-1)
            ok &= (resid < 1e-10) & self.arm.within_limits(plant.link_angles_q(q))
            ok &= plant.shaft_reaches(plant.wrist(q))
            q = np.where(ok[..., None], q, 0.0)
            J = _fd_jacobian(plant.tip, q)
            Jr = self.arm.jacobian(q)
            if self.jacobian == "rigid":
                Jh = (lever_jacobian(self.arm.forward(q), np.asarray(self.estimate), self.length) @ Jr)[..., None, :, :]
            else:
                w, tip, thw, tht = plant.end_poses(q)
                nc = self.errors.noise_corners()
                pw = w[..., None, :] + nc[:, 0:2]
                est = estimate_from_ends(pw, tip[..., None, :] + nc[:, 2:4], thw[..., None] + nc[:, 4],
                                         tht[..., None] + nc[:, 5], self.length)
                Jh = flexed_jacobian(pw, est["port"], self.length, est["t"]) @ Jr[..., None, :, :]
                lever = lever_jacobian(self.arm.forward(q), np.asarray(self.estimate), self.length) @ Jr
                Jh = np.where(np.all(np.isfinite(Jh), axis=(-2, -1))[..., None, None], Jh, lever[..., None, :, :])
            Jh_inv, singular = inv2(Jh)
            mu, nu = conformal_parts(J[..., None, :, :] @ Jh_inv)
        bad = singular | ~np.isfinite(mu) | ~np.isfinite(nu)
        ok = ok & ~np.any(bad, axis=-1)
        return mu, nu, ok


EFFECT_NEWTON_ITERS = 8
JACOBIAN_EFFECTS = ("port_offset", "joint_offset", "gravity_sag", "world_load")


def _fd_jacobian(f, q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central-difference Jacobian (..., 2, 2) of ``f: (..., 2) -> (..., 2)``."""
    cols = []
    for i in range(2):
        e = np.zeros(2)
        e[i] = h
        cols.append((f(q + e) - f(q - e)) / (2 * h))
    return np.stack(cols, axis=-1)


# ----------------------------------------------------------------------------- field object
@dataclass
class MetricField:
    """Worst-case metric arrays on a regular ``(y, z)`` grid; NaN outside the workspace."""

    y: np.ndarray
    z: np.ndarray
    valid: np.ndarray
    G_norm: np.ndarray
    phi_hat_max: np.ndarray
    phi_max: np.ndarray
    rho_star: np.ndarray | None = None
    k_star: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    @property
    def resolution(self) -> float:
        if "resolution" in self.meta:
            return float(self.meta["resolution"])
        return float(self.y[1] - self.y[0])

    def array(self, name: str) -> np.ndarray:
        a = getattr(self, name, None)
        if a is None:
            raise ErrplanError(f"field {name!r} was not computed (use --rho-star or compute_fields(rho_star=True))")
        return a

    def points(self) -> np.ndarray:
        """Tip positions (ny, nz, 2) of the grid."""
        return np.stack(np.meshgrid(self.y, self.z, indexing="ij"), axis=-1)

    def sample(self, name: str, pts: np.ndarray) -> np.ndarray:
        """Bilinear interpolation of a field at points (..., 2); NaN where a corner is invalid."""
        a = self.array(name)
        pts = np.asarray(pts, float)
        fy = (pts[..., 0] - self.y[0]) / self.resolution
        fz = (pts[..., 1] - self.z[0]) / self.resolution
        i0 = np.floor(fy).astype(int)
        j0 = np.floor(fz).astype(int)
        inside = (i0 >= 0) & (j0 >= 0) & (i0 < len(self.y) - 1) & (j0 < len(self.z) - 1)
        i0c = np.clip(i0, 0, len(self.y) - 2)
        j0c = np.clip(j0, 0, len(self.z) - 2)
        ty, tz = fy - i0c, fz - j0c
        v = ((1 - ty) * (1 - tz) * a[i0c, j0c] + ty * (1 - tz) * a[i0c + 1, j0c]
             + (1 - ty) * tz * a[i0c, j0c + 1] + ty * tz * a[i0c + 1, j0c + 1])
        return np.where(inside, v, np.nan)

    def summary(self) -> dict:
        """Share of the workspace with ||G|| < 1 (and rho* < 1) and max/median of each field."""
        n = int(self.valid.sum())
        out: dict = {"grid": [len(self.y), len(self.z)], "resolution": self.resolution, "valid_points": n,
                     "workspace_area_m2": n * self.resolution**2}
        if n == 0:
            return out
        out["share_G_below_1"] = float(np.mean(self.G_norm[self.valid] < 1.0))
        if self.rho_star is not None:
            out["share_rho_star_below_1"] = float(np.mean(self.rho_star[self.valid] < 1.0))
        for name in ("G_norm", "phi_hat_max", "phi_max", "rho_star", "k_star"):
            a = getattr(self, name)
            if a is not None:
                v = a[self.valid]
                out[name] = {"max": float(v.max()), "median": float(np.median(v)), "min": float(v.min())}
        return out

    # ---------------------------------------------------------------- io
    def save(self, path: str | Path) -> None:
        """Write the npz of docs/interfaces.md (atomically: nothing half-written)."""
        path = Path(path)
        arrays = {"y": self.y, "z": self.z, "valid": self.valid, "G_norm": self.G_norm,
                  "phi_hat_max": self.phi_hat_max, "phi_max": self.phi_max,
                  "meta": np.array(json.dumps(self.meta))}
        if self.rho_star is not None:
            arrays["rho_star"] = self.rho_star
            arrays["k_star"] = self.k_star
        tmp = path.with_name(path.name + ".part")
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path) -> "MetricField":
        with np.load(path) as d:
            meta = json.loads(str(d["meta"])) if "meta" in d else {}
            return cls(d["y"], d["z"], d["valid"].astype(bool), d["G_norm"], d["phi_hat_max"], d["phi_max"],
                       d["rho_star"] if "rho_star" in d else None, d["k_star"] if "k_star" in d else None, meta)


# ----------------------------------------------------------------------------- computation
def _aligned_axis(lo: float, hi: float, res: float) -> np.ndarray:
    i0, i1 = math.floor(lo / res), math.ceil(hi / res)
    return np.arange(i0, i1 + 1) * res


def workspace_bounds(ev: Evaluator) -> tuple[float, float, float, float]:
    """Bounding box (y0, y1, z0, z1) of tips reachable under any corner instance."""
    w = ev.arm.sample_wrists(161)
    tips = []
    for th in ev.errors.corners():
        port = ev.errors.port(th)
        r = np.linalg.norm(port - w, axis=-1)
        ww = w[(r < ev.length) & (r > 1e-6)]
        if len(ww):
            tips.append(flexed_tip(ww, port, ev.length, th[2]))
    if not tips:
        raise ErrplanError("the tip workspace is empty: no reachable wrist puts the shaft through the port")
    t = np.concatenate(tips)
    return float(t[:, 0].min()), float(t[:, 0].max()), float(t[:, 1].min()), float(t[:, 1].max())


def _reduce(mu: np.ndarray, nu: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Worst case over the noise axis (last): ``(||G||, |phi_max|)``."""
    return g_norm_from_parts(mu, nu, k).max(axis=-1), phi_max_from_parts(mu, nu).max(axis=-1)


def _far_mask(es: ErrorSet, samples: int | None) -> np.ndarray:
    """(m, m) mask of sample pairs more than one grid step apart along some axis."""
    n = samples or es.samples
    shape = [n if a else 1 for a in es.active]
    ij = np.stack(np.unravel_index(np.arange(int(np.prod(shape))), shape), axis=-1)
    return np.abs(ij[:, None, :] - ij[None, :, :]).max(axis=-1) > 1


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
        mu, nu, ok = ev.parts(x[sub], th)
        valid[sub[~ok]] = False
        g, p = _reduce(mu, nu, k)
        vals_g[sub, j] = np.where(ok, g, -np.inf)
        vals_p[sub, j] = np.where(ok, p, -np.inf)
        if keep_parts:
            full_mu = np.full((n,) + mu.shape[1:], np.nan, complex)
            full_nu = np.full_like(full_mu, np.nan)
            full_mu[sub], full_nu[sub] = mu, nu
            mus.append(full_mu)
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
        shape = [(samples or es.samples) if a else 1 for a in es.active]
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

    def evaluate(sub, theta, track_g):
        mu, nu, ok = ev.parts(xe[sub], theta)
        ok_e[sub[~ok]] = False
        g, p = _reduce(mu, nu, k)
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
                        moved = np.clip(c[:, dmn] + sgn * h[dmn], lo[dmn], hi[dmn])
                        keep = moved != c[:, dmn]
                        if np.any(keep):
                            c = c[keep].copy()
                            c[:, dmn] = moved[keep]
                            evaluate(rows[keep], c, for_g)

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
        out["nu"] = np.stack(nus, axis=1) if nus else np.zeros((n, 0, 1), complex)
    return out


def minimize_gain(mu: np.ndarray, nu: np.ndarray, iters: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """``rho* = min_k max_i |1 - k mu_i| + k |nu_i|`` per row, by golden section (convex in k).

    ``mu``, ``nu``: (n, m) complex, NaN entries ignored. Returns ``(rho_star, k_star)``; where no
    gain contracts, ``rho* = 1`` at ``k* = 0``.
    """
    mu = np.asarray(mu).reshape(len(mu), -1)
    nu = np.asarray(nu).reshape(len(nu), -1)
    bad = ~np.isfinite(mu) | ~np.isfinite(nu)
    mu = np.where(bad, 0.0, mu)
    nu = np.where(bad, 0.0, nu)
    amax = np.abs(mu).max(axis=1)
    kmax = np.where(amax > 0, 2.0 / np.where(amax > 0, amax, 1.0), 1.0)

    def f(k):
        return (np.abs(1.0 - k[:, None] * mu) + k[:, None] * np.abs(nu)).max(axis=1)

    a = np.zeros(len(mu))
    b = kmax.copy()
    gr = (math.sqrt(5) - 1) / 2
    c = b - gr * (b - a)
    d = a + gr * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(iters):
        left = fc < fd  # the minimum lies in [a, d]
        a, b = np.where(left, a, c), np.where(left, d, b)
        new_x = np.where(left, b - gr * (b - a), a + gr * (b - a))
        f_new = f(new_x)
        c, d, fc, fd = (np.where(left, new_x, d), np.where(left, c, new_x),
                        np.where(left, f_new, fd), np.where(left, fc, f_new))
    k = 0.5 * (a + b)
    rho = f(k)
    none = rho >= 1.0
    return np.where(none, 1.0, rho), np.where(none, 0.0, k)


def compute_fields(sc, resolution: float | None = None, rho_star: bool = False, *,
                   samples: int | None = None, refine: int = REFINE_LEVELS,
                   progress: Progress | None = None) -> MetricField:
    """Worst-case fields of a scenario on its tip grid (docs/interfaces.md "fields npz")."""
    ev = Evaluator.from_scenario(sc)
    res = float(resolution or sc.fields.resolution)
    if res <= 0 or not math.isfinite(res):
        raise ErrplanError(f"resolution = {resolution!r}: expected a grid spacing > 0 m")
    y0, y1, z0, z1 = workspace_bounds(ev)
    y = _aligned_axis(y0 - 2 * res, y1 + 2 * res, res)
    z = _aligned_axis(z0 - 2 * res, z1 + 2 * res, res)
    if len(y) * len(z) > 4_000_000:
        raise ErrplanError(f"resolution = {res}: the grid would have {len(y) * len(z)} points (max 4,000,000)")
    Y, Z = np.meshgrid(y, z, indexing="ij")
    pts = np.stack([Y.ravel(), Z.ravel()], axis=-1)
    # Cheap prefilter: a robustly valid tip is within the shaft length of every port of the box,
    # in particular of its corners (the same strict test true_wrist applies to each instance).
    es = ev.errors
    near = np.ones(len(pts), bool)
    for th in es.corners():
        d = pts - es.port(th)
        near &= np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2) < ev.length
    cand = np.flatnonzero(near)
    k = float(sc.controller.gain)
    wc = worst_case(ev, pts[cand], k, samples=samples, refine=refine, keep_parts=rho_star, progress=progress)
    shape = Y.shape

    def scatter(v, fill=np.nan, dtype=float):
        a = np.full(len(pts), fill, dtype=dtype)
        a[cand] = v
        return a.reshape(shape)

    valid = scatter(wc["valid"], False, bool)
    gn = scatter(wc["G_norm"])
    pm = scatter(wc["phi_max"])
    ph = phi_hat_max(np.where(valid, gn, 1.0))
    ph[~valid] = np.nan
    meta = {"scenario": sc.name, "gain": k, "resolution": res, "jacobian": sc.controller.jacobian,
            "error_set": {"base_port": list(es.base_port), "lo": list(es.lo), "hi": list(es.hi),
                          "noise": list(es.noise), "samples": samples or es.samples, "refine_levels": refine},
            "length": ev.length, "effects": {name: dict(p) for name, p in sc.effects.items()}}
    mf = MetricField(y, z, valid, gn, ph, pm, meta=meta)
    if rho_star:
        if progress:
            progress(1.0, "minimising the worst case over the gain")
        v = wc["valid"]
        mu = wc["mu"][v].reshape(int(v.sum()), -1)
        nu = wc["nu"][v].reshape(int(v.sum()), -1)
        rs, ks = minimize_gain(mu, nu)
        # Certify at k*: the refined worst case over the continuous error set at that gain.
        xs = pts[cand][v]
        rs_ref = _refined_at_gain(ev, xs, ks, samples=samples, refine=refine)
        rs_ref = np.where(ks > 0, np.maximum(rs, rs_ref), 1.0)
        # The scenario gain is a candidate too: rho* never exceeds the refined ||G|| at k.
        g_k = wc["G_norm"][v]
        use_k = g_k < rs_ref
        rs_ref, ks = np.where(use_k, g_k, rs_ref), np.where(use_k, k, ks)
        none = rs_ref >= 1.0  # no certified contraction: rho* = 1 (k -> 0), k* = 0
        rs_ref, ks = np.where(none, 1.0, rs_ref), np.where(none, 0.0, ks)
        rfull = np.full(len(cand), np.nan)
        kfull = np.full(len(cand), np.nan)
        rfull[v] = rs_ref
        kfull[v] = ks
        mf.rho_star = scatter(rfull)
        mf.k_star = scatter(kfull)
    return mf


def _refined_at_gain(ev: Evaluator, x: np.ndarray, k: np.ndarray, *, samples=None, refine=REFINE_LEVELS) -> np.ndarray:
    """Worst ``||G||`` at a per-point gain ``k`` over the error set, with local refinement."""
    es = ev.errors
    grid = es.sample_grid(samples)
    best = np.full(len(x), -np.inf)
    th_best = np.zeros((len(x), 3))
    for th in grid:
        mu, nu, ok = ev.parts(x, th)
        g = g_norm_from_parts(mu, nu, k[:, None]).max(axis=-1)
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
                c[:, dmn] = np.clip(c[:, dmn] + sgn * h[dmn], es.lo[dmn], es.hi[dmn])
                mu, nu, ok = ev.parts(x, c)
                g = np.where(ok, g_norm_from_parts(mu, nu, k[:, None]).max(axis=-1), np.inf)
                upd = g > best
                best[upd] = g[upd]
                th_best[upd] = c[upd]
    return best
