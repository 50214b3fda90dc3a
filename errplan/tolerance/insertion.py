"""P2's flexion-model controller at insertion depths (P2 Secs. IV-B, V, VI): ``insertion_band``
(P2 Fig. 7, with the Fig. 8/9 curves) and ``tracker_noise``.

Geometry (P2 Sec. V, rotational symmetry): the port at the origin, the tip at
``r * dir(shaft_angle)`` (``shaft_angle = 0``: the port->tip line along the tracker's z axis), the
wrist from the flexed-shaft inverse (``flexed_wrist``). The noise box is aligned with the tracker
axes, so it is *not* rotationally symmetric: ``shaft_angle`` matters (docs/tolerance.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ErrplanError
from ..kinematics.arm import direction
from ..kinematics.shaft import (estimate_from_ends, flexed_end_angles, flexed_geometry, flexed_jacobian,
                                flexed_wrist)
from ..metrics import compose_parts, conformal_parts, g_norm_from_parts, inverse_parts
from .result import Progress
from .search import _bisect_vec, _crossing, _golden_min, _runs, box_worst, pattern_search

#: P2 Sec. VI: the Liberty tracker, 0.0021 L position and 0.0026 rad angle (RMS used as bounds).
LIBERTY_ANGLE_RATIO = 0.0026 / 0.0021
HOLDS = ("tip_force", "port_force", "port_deflection")
#: memory (bytes) per (depth, noise draw) evaluation of P2's flexion model (measured: about 265 B)
EVAL_BYTES = 512
#: (depth x draw) evaluations per chunk of random noise draws: memory stays flat whatever the
#: number of depths and draws (the maximum over the draws does not depend on the chunking)
EVAL_CHUNK = 2_000_000
NOISE_SAMPLING = ("worst", "random")


def flexed_jacobian_hold(w: np.ndarray, p: np.ndarray, L: float, t, hold: str = "tip_force") -> np.ndarray:
    """``d tip / d w`` (..., 2, 2) of the flexed shaft, port fixed, holding one load quantity.

    ``hold = "tip_force"`` holds ``Ft/EI = t`` (errplan's convention, :func:`flexed_jacobian`);
    ``"port_force"`` holds ``Fp/EI = t L / a``; ``"port_deflection"`` holds ``y_m(a) = -t a b^2/3``,
    each at its value in the current configuration. With ``s(a) = tan`` of the chord-to-port angle
    (``t b^2/3``, ``c a b^2/(3L)`` or ``-d/a``), ``rho^2 = a^2 (1 + s^2)`` and
    ``phi = theta + atan s``: ``J = I + L n_phi grad(phi)^T``,
    ``grad(phi) = -n_theta/rho - s'/(1+s^2) * rho/(a(1+s^2) + a^2 s s') * u_theta``.
    """
    if hold == "tip_force":
        return flexed_jacobian(w, p, L, t)
    if hold not in HOLDS:
        raise ErrplanError(f"hold = {hold!r}: expected one of {', '.join(HOLDS)}")
    g = flexed_geometry(w, p, L, t)
    t = np.asarray(t, float)
    rho, a, b, theta = g["rho"], g["a"], g["b"], g["theta"]
    if hold == "port_force":
        c = t * L / a
        s = c * a * b * b / (3 * L)
        ds = c * (b * b - 2 * a * b) / (3 * L)
    else:
        d = -t * a * b * b / 3.0
        s = -d / a
        ds = d / (a * a)
    gg = 1.0 + s * s
    a_p = rho / (a * gg + a * a * s * ds)
    beta_p = ds / gg
    u = direction(theta)
    n = np.stack([np.cos(theta), -np.sin(theta)], axis=-1)
    n_phi = np.stack([np.cos(g["phi"]), -np.sin(g["phi"])], axis=-1)
    grad_phi = -n / rho[..., None] - (beta_p * a_p)[..., None] * u
    eye = np.broadcast_to(np.eye(2), grad_phi.shape[:-1] + (2, 2))
    return eye + L * n_phi[..., :, None] * grad_phi[..., None, :]


@dataclass
class InsertionModel:
    """P2's flexion-model controller at insertion depths ``r/L`` (vectorised over depths).

    ``states`` hold, per depth, the true wrist/tip, the true end angles, the true Jacobian's
    conformal parts and the true model parameters (``a``, ``Fp/EI``).
    """

    length: float
    tip_load: float
    gain: float
    hold: str = "tip_force"
    shaft_angle: float = 0.0

    def __post_init__(self):
        if not self.length > 0 or not math.isfinite(self.length):
            raise ErrplanError(f"length = {self.length!r}: expected a shaft length > 0 m")
        if self.tip_load == 0 or not math.isfinite(self.tip_load):
            raise ErrplanError(f"tip_force_over_ei = {self.tip_load!r}: P2's flexion controller needs a non-zero "
                               "tip load (without flexion the end slopes coincide and the port is not identifiable)")
        if self.hold not in HOLDS:
            raise ErrplanError(f"hold = {self.hold!r}: expected one of {', '.join(HOLDS)}")

    def state(self, rl: np.ndarray) -> dict[str, np.ndarray]:
        rl = np.asarray(rl, float)
        if np.any(rl <= 0) or np.any(rl >= 1):
            raise ErrplanError(f"insertion depth r/L = {rl.min():g}..{rl.max():g}: expected values in (0, 1)")
        L, t = self.length, self.tip_load
        p = np.zeros(rl.shape + (2,))
        x = (rl * L)[..., None] * direction(np.full(rl.shape, self.shaft_angle))
        w = flexed_wrist(x, p, L, np.full(rl.shape, t))
        tip, thw, tht = flexed_end_angles(w, p, L, np.full(rl.shape, t))
        a = flexed_geometry(w, p, L, np.full(rl.shape, t))["a"]
        with np.errstate(invalid="ignore", divide="ignore"):
            mu, nu = conformal_parts(flexed_jacobian_hold(w, p, L, np.full(rl.shape, t), self.hold))
        return {"rl": rl, "w": w, "tip": tip, "thw": thw, "tht": tht, "port": p, "a": a,
                "fp": t * L / a, "mu": mu, "nu": nu}

    def estimates(self, st: dict, noise: np.ndarray) -> dict[str, np.ndarray]:
        """P2 eqs. 8-14 fed the true end measurements plus ``noise`` (n, c, 6) =
        ``[wrist y, wrist z, tip y, tip z, wrist angle, tip angle]``. Returns the estimates (n, c)."""
        pw = st["w"][:, None, :] + noise[..., 0:2]
        pt = st["tip"][:, None, :] + noise[..., 2:4]
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            est = estimate_from_ends(pw, pt, st["thw"][:, None] + noise[..., 4], st["tht"][:, None] + noise[..., 5],
                                     self.length)
        est["pw"] = pw
        return est

    def g_norm(self, st: dict, noise: np.ndarray) -> np.ndarray:
        """Worst ``||I - k J Jhat^-1||`` per (depth, noise vector) (n, c); ``inf`` where the
        controller's model is unidentifiable or singular (a certainly non-certifiable instance)."""
        est = self.estimates(st, noise)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            Jh = flexed_jacobian_hold(est["pw"], est["port"], self.length, est["t"], self.hold)
            mu_h, nu_h = conformal_parts(Jh)
            imu, inu, singular = inverse_parts(mu_h, nu_h)
            mu, nu = compose_parts(st["mu"][:, None], st["nu"][:, None], imu, inu)
            g = g_norm_from_parts(mu, nu, self.gain)
        return np.where(singular | ~np.isfinite(g), np.inf, g)

    def worst_g(self, st: dict, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Worst ``||G||`` over the noise boxes ``[-half, half]`` (n, 6) and a mask of the depths
        whose box reaches a degenerate model (estimated ``a`` outside ``(0, L)``: the estimated port
        at or behind the wrist or the tip, where ``Jhat`` is singular and ``||G|| >= 1`` in the
        limit). The vertices can miss such a thin interior set, so there the worst case is raised
        to at least 1 (sound for the criterion ``||G|| < 1``)."""
        g = box_worst(lambda nz: self.g_norm(st, nz), half)[0]
        amax = box_worst(lambda nz: self._a(st, nz), half)[0]
        amin = -box_worst(lambda nz: -self._a(st, nz), half)[0]
        degenerate = ~((amin > 0) & (amax < self.length))
        return np.where(degenerate, np.maximum(g, 1.0), g), degenerate

    def _a(self, st: dict, noise: np.ndarray) -> np.ndarray:
        a = self.estimates(st, noise)["a"]
        return np.where(np.isfinite(a), a, np.inf)

    def fp_error(self, st: dict, noise: np.ndarray) -> np.ndarray:
        """Relative error ``|Fp/EI_hat / Fp/EI - 1|`` of the estimated normalised port force (P2 Fig. 8)."""
        est = self.estimates(st, noise)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            e = np.abs(est["fp_over_ei"] / st["fp"][:, None] - 1.0)
        return np.where(np.isfinite(e), e, np.inf)

    def port_error(self, st: dict, noise: np.ndarray) -> np.ndarray:
        """Distance (m) between the estimated and the true port (P2 Fig. 9)."""
        est = self.estimates(st, noise)
        e = np.linalg.norm(est["port"] - st["port"][:, None, :], axis=-1)
        return np.where(np.isfinite(e), e, np.inf)



def noise_half_widths(n: int, position: float, angle: float) -> np.ndarray:
    """Half widths (n, 6) of the noise box ``[pw(2), pt(2), th_w, th_t]``."""
    return np.tile(np.array([position] * 4 + [angle] * 2, float), (n, 1))


def random_noise(draws: int, position: float, angle: float, seed: int) -> np.ndarray:
    """``draws`` noise vectors uniform in the box (P2 Sec. IV-B: uniform along each sensor axis)."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, (draws, 6)) * np.array([position] * 4 + [angle] * 2)


def insertion_worst(model: InsertionModel, rl: np.ndarray, position: float, angle: float, *,
                    what: str = "G", sampling: str = "worst", draws: int = 10000, seed: int = 0,
                    half: np.ndarray | None = None) -> np.ndarray:
    """Worst value over the noise box at depths ``rl`` (n,): ``what`` = ``"G"`` (``||G||``),
    ``"fp"`` (relative ``Fp/EI`` error) or ``"port"`` (port error, m).

    ``sampling = "worst"``: vertices + pattern search (:func:`box_worst`); ``"random"``: the max over
    ``draws`` uniform draws (the same draws at every depth), a Monte Carlo reading of P2 Sec. IV-B.
    ``half`` overrides the box half widths per depth (n, 6).
    """
    rl = np.atleast_1d(np.asarray(rl, float))
    st = model.state(rl)
    fn = {"G": model.g_norm, "fp": model.fp_error, "port": model.port_error}[what]
    if sampling == "random":
        from ..inputs import check_allocation

        check_allocation("draws", draws, draws, 6 * 8, "the noise draws")
        step = int(min(2000, max(1, EVAL_CHUNK // max(len(rl), 1))))
        check_allocation("samples", len(rl), len(rl) * step, EVAL_BYTES, "the noise evaluations")
        nz = random_noise(draws, position, angle, seed)
        out = np.full(len(rl), -np.inf)
        for c0 in range(0, draws, step):
            chunk = np.broadcast_to(nz[c0:c0 + step], (len(rl),) + nz[c0:c0 + step].shape)
            out = np.maximum(out, fn(st, chunk).max(axis=1))
        return out
    if sampling != "worst":
        raise ErrplanError(f"noise_sampling = {sampling!r}: expected one of {', '.join(NOISE_SAMPLING)}")
    if half is None:
        half = noise_half_widths(len(rl), position, angle)
    if what == "G":
        return model.worst_g(st, half)[0]
    return box_worst(lambda nz: fn(st, nz), half)[0]


# ============================================================================= insertion band
def _band_of_curve(rl: np.ndarray, g: np.ndarray, f) -> tuple[list | None, list, float, float]:
    """Band, intervals, best depth and its worst ``||G||`` from the worst-case curve ``g`` on depths
    ``rl`` and the worst case ``f(r)`` at one depth (planar or 3-D): every run of ``g < 1`` with its
    edges bisected, the best depth by golden section around the curve's minimum (kept only if it
    improves on the grid), the band the run holding the minimum (``None`` if none)."""
    i = int(np.argmin(g))
    lo_b, hi_b = rl[max(i - 1, 0)], rl[min(i + 1, len(rl) - 1)]
    best = _golden_min(f, lo_b, hi_b) if hi_b > lo_b else float(rl[i])
    best_g = f(best)
    if best_g > g[i]:
        best, best_g = float(rl[i]), float(g[i])
    below = g < 1.0
    intervals = []
    for a, b in _runs(below):
        lo = rl[a] if a == 0 else _crossing(f, rl[a], rl[a - 1])
        hi = rl[b] if b == len(rl) - 1 else _crossing(f, rl[b], rl[b + 1])
        intervals.append([float(lo), float(hi)])
    band = None
    for (a, b), iv in zip(_runs(below), intervals):
        if a <= i <= b:
            band = iv
    return band, intervals, float(best), float(best_g)


def insertion_band(length: float, tip_load: float, position: float, angle: float, *, gain: float = 1.0,
                   samples: int = 193, hold: str = "tip_force", shaft_angle: float = 0.0,
                   sampling: str = "worst", draws: int = 10000, seed: int = 0, extras: bool = True,
                   progress: Progress | None = None) -> dict[str, Any]:
    """The insertion-depth band of P2's flexion controller under a bounded noise box (P2 Fig. 7).

    ``position`` (m) and ``angle`` (rad) bound each measured coordinate. The worst ``||G||`` is
    evaluated on ``samples`` depths ``r/L`` in [0.02, 0.98]; the band edges are refined by bisection
    between grid points and the best depth by golden section. Returns ``band`` ([lo, hi] r/L, the run
    of ``||G|| < 1`` holding the best depth, ``None`` if there is none), ``intervals`` (every such
    run), ``best``, ``best_G_norm``, ``worst_G_norm`` (the curve) and, with ``extras``, the worst-case
    ``fp_over_ei_error`` and ``port_error`` curves (P2 Figs. 8 and 9).
    """
    if samples < 5:
        raise ErrplanError(f"samples = {samples}: expected at least 5 insertion depths")
    if position < 0 or angle < 0 or not (math.isfinite(position) and math.isfinite(angle)):
        raise ErrplanError(f"sensor_noise = ({position!r}, {angle!r}): expected bounds >= 0")
    model = InsertionModel(length, tip_load, gain, hold, shaft_angle)
    kw = dict(sampling=sampling, draws=draws, seed=seed)
    rl = np.linspace(0.02, 0.98, samples)
    if sampling == "worst":
        g, degenerate = model.worst_g(model.state(rl), noise_half_widths(len(rl), position, angle))
    else:
        g, degenerate = insertion_worst(model, rl, position, angle, **kw), np.zeros(len(rl), bool)
    if progress:
        progress(0.5, "insertion band")

    def f(r: float) -> float:
        return float(insertion_worst(model, np.array([r]), position, angle, **kw)[0])

    band, intervals, best, best_g = _band_of_curve(rl, g, f)
    out: dict[str, Any] = {
        "band": band, "intervals": intervals, "best": float(best), "best_G_norm": float(best_g),
        "worst_G_norm": {"r_over_L": rl, "G_norm": g, "degenerate_model": degenerate},
        "length": length, "tip_force_over_ei": tip_load, "gain": gain,
        "sensor_noise": {"position": position, "angle": angle},
        "noise_sampling": sampling, "hold": hold, "shaft_angle": shaft_angle, "samples": samples,
    }
    if sampling == "random":
        out["draws"], out["seed"] = draws, seed
    if extras:
        out["fp_over_ei_error"] = {"r_over_L": rl, "relative_error": insertion_worst(model, rl, position, angle,
                                                                                     what="fp", **kw)}
        out["port_error"] = {"r_over_L": rl, "error": insertion_worst(model, rl, position, angle, what="port", **kw)}
    if progress:
        progress(1.0, "insertion band")
    return out


# ============================================================================= tracker noise
def _check_noise_query(band, samples: int, angle_ratio: float) -> tuple[float, float]:
    """The arguments of a tracker-noise query (plane or 3-D), checked; returns the band's ends."""
    lo_b, hi_b = band
    if not 0 < lo_b <= hi_b < 1:
        raise ErrplanError(f"band = {list(band)}: expected insertion depths 0 < lo <= hi < 1 (r/L)")
    if samples < 2:
        raise ErrplanError(f"samples = {samples}: expected at least 2 depths")
    if angle_ratio < 0 or not math.isfinite(angle_ratio):
        raise ErrplanError(f"angle_ratio = {angle_ratio!r}: expected a number >= 0")
    return lo_b, hi_b


def tracker_noise(length: float, tip_load: float, band: tuple[float, float], *, gain: float = 1.0,
                  angle_ratio: float = LIBERTY_ANGLE_RATIO, samples: int = 41, hold: str = "tip_force",
                  shaft_angle: float = 0.0, progress: Progress | None = None) -> dict[str, Any]:
    """Largest tracker noise keeping P2's flexion controller monotonic over an insertion band.

    The noise box has position half width ``s`` (m) on the four position coordinates and angle half
    width ``angle_ratio * s / L`` (rad) on the two angles. For each of ``samples`` depths in
    ``band`` (edges included) the largest ``s`` with worst ``||G|| < 1`` is found by bisection (the
    worst case over nested boxes is monotone in ``s``); ``value`` is the minimum over the band and
    ``binding_r_over_L`` where it is reached. ``curve`` gives the largest noise per depth.
    """
    lo_b, hi_b = _check_noise_query(band, samples, angle_ratio)
    model = InsertionModel(length, tip_load, gain, hold, shaft_angle)
    rl = np.linspace(lo_b, hi_b, samples) if hi_b > lo_b else np.array([lo_b])
    st = model.state(rl)
    unit = np.array([1.0] * 4 + [angle_ratio / length] * 2)
    g0 = model.g_norm(st, np.zeros((len(rl), 1, 6)))[:, 0]

    def fails(s: np.ndarray) -> np.ndarray:
        return model.worst_g(st, s[:, None] * unit[None, :])[0] >= 1.0

    lo, hi, capped = _bisect_vec(fails, len(rl), 1e-5 * length, 0.05 * length, zero_fails=g0 >= 1.0,
                                 abs_tol=1e-10, progress=progress, label="tracker noise")
    j = int(np.argmin(lo))
    s = float(lo[j])
    g_at = model.worst_g(st, np.full((len(rl), 1), s) * unit[None, :])[0]
    return {
        "value": s, "angle_value": s * angle_ratio / length, "binding_r_over_L": float(rl[j]),
        "band": [lo_b, hi_b], "length": length, "tip_force_over_ei": tip_load, "gain": gain,
        "angle_ratio": angle_ratio, "hold": hold, "shaft_angle": shaft_angle, "samples": samples,
        "capped": bool(capped[j]),
        "curve": {"r_over_L": rl, "max_position_noise": lo, "G_norm_at_value": g_at},
    }


# ============================================================================= 3-D
#: load directions sampled around the shaft before the refinement (3-D insertion depths)
LOAD_DIRECTIONS = 16
#: depths per chunk of the 3-D corner evaluation (memory: depths x directions x corners maps)
DEPTH_CHUNK = 8


@dataclass
class SpatialInsertionModel:
    """P2's flexion controller in 3-D at insertion depths ``r/L`` (docs/physics.md "P2's flexion
    controller in 3-D"): the port at the origin, the tip at ``r s`` (``s`` the unit port->tip
    direction, the tracker's z axis by default), a lateral load of magnitude ``tip_load`` in any
    direction ``psi`` normal to the shaft (angle around ``s`` in the fields' frame,
    :func:`errplan.fields.evaluator._perp_basis`), the sensor-noise set of the tracker: each
    measured position within ``position`` per world coordinate, each end direction within ``angle``.

    A noise vector ``z`` (7) is ``[delta(3), tilt_w(2), tilt_t(2)]``: the chord difference of the two
    position errors (in ``[-2p, 2p]^3``; the controller's Jhat depends on the positions only through
    the chord) and each end's tilt in its frame ``(m x d, m)``, ``m`` the true bending plane's normal
    (a disc of radius ``angle``). ``in_plane``: the load in the plane of ``s`` and ``f1`` only
    (``psi = 0``) and the noise of that plane only: with ``s`` in the plane x = 0 this is P2's planar
    problem of :class:`InsertionModel`.
    """

    length: float
    tip_load: float
    gain: float
    shaft_direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    in_plane: bool = False

    def __post_init__(self):
        if not self.length > 0 or not math.isfinite(self.length):
            raise ErrplanError(f"length = {self.length!r}: expected a shaft length > 0 m")
        if not self.tip_load > 0 or not math.isfinite(self.tip_load):
            raise ErrplanError(f"tip_force_over_ei = {self.tip_load!r}: expected a lateral load magnitude > 0 "
                               "(1/m^2) in a spatial scenario: P2's flexion controller needs flexion")
        s = np.asarray(self.shaft_direction, float)
        if s.shape != (3,) or not np.all(np.isfinite(s)) or np.linalg.norm(s) == 0:
            raise ErrplanError(f"shaft_direction = {list(self.shaft_direction)!r}: expected a non-zero 3-vector")

    @property
    def s(self) -> np.ndarray:
        s = np.asarray(self.shaft_direction, float)
        return s / np.linalg.norm(s)

    def half(self, position: float, angle: float) -> np.ndarray:
        """Bounds (8,) of the search parameters ``[delta(3), tilt_w(2), tilt_t(2), psi]`` (psi: the
        sampling step of the load direction)."""
        return np.array([2 * position] * 3 + [angle] * 4 + [2 * math.pi / LOAD_DIRECTIONS], float)

    def g_norm(self, rl: np.ndarray, par: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``||I - k J Jhat^-1||`` and the estimated ``a`` for depths ``rl`` (n,) under parameters
        ``par`` (n, c, 8) = ``[noise(7), psi]``; ``inf`` where Jhat is singular or unidentifiable."""
        from ..fields.evaluator import _perp_basis, bending_frame
        from ..kinematics.shaft import (estimate_from_end_poses, flexed_end_directions, flexed_jacobian,
                                        flexed_wrist_plane, tilt)
        from ..metrics import g_norm, inv

        L = self.length
        n, c = par.shape[:2]
        s = self.s
        f1, f2 = _perp_basis(s[None])
        psi = par[..., 7]
        e2 = np.cos(psi)[..., None] * f1[0] + np.sin(psi)[..., None] * f2[0]
        x = np.broadcast_to((np.asarray(rl, float) * L)[:, None, None] * s, (n, c, 3))
        p = np.zeros((n, c, 3))
        tau = np.full((n, c), float(self.tip_load))
        w, t = flexed_wrist_plane(x, p, L, tau, e2)
        J = flexed_jacobian(w, p, L, t)
        tip, dw, dt = flexed_end_directions(w, p, L, t)
        m = bending_frame(w, p, L, t)
        meas = []
        for d, sl in ((dw, slice(3, 5)), (dt, slice(5, 7))):
            e1 = np.cross(m, d)
            e1 = e1 / np.linalg.norm(e1, axis=-1, keepdims=True)
            meas.append(tilt(d, par[..., sl], e1, m))
        pt = tip + par[..., 0:3]
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            est = estimate_from_end_poses(w, pt, meas[0], meas[1], L)
            Jh = flexed_jacobian(w, est["port"], L, est["load"])
            Jh_inv, singular = inv(np.where(np.isfinite(Jh), Jh, 0.0))
            g = g_norm(J @ Jh_inv, self.gain)
        bad = singular | ~np.all(np.isfinite(Jh), axis=(-2, -1)) | ~np.isfinite(g)
        return np.where(bad, np.inf, g), np.where(np.isfinite(est["a"]), est["a"], np.inf)

    def candidates(self, position: float, angle: float) -> np.ndarray:
        """Starting parameters (c, 8): the noise set's corners (:func:`spatial_noise_corners`) at
        ``LOAD_DIRECTIONS`` load directions (``psi = 0`` only when ``in_plane``)."""
        from ..errorset import spatial_noise_corners

        nz = spatial_noise_corners(position, angle, in_plane=self.in_plane)
        psis = [0.0] if self.in_plane else [2 * math.pi * i / LOAD_DIRECTIONS for i in range(LOAD_DIRECTIONS)]
        return np.array([[*z, ps] for ps in psis for z in nz], float)

    def _project(self, par: np.ndarray, half: np.ndarray) -> np.ndarray:
        """Back into the set: ``delta`` clipped to its box, each tilt scaled into its disc, psi wrapped."""
        out = par.copy()
        out[..., 0:3] = np.clip(out[..., 0:3], -half[..., 0:3], half[..., 0:3])
        for sl in (slice(3, 5), slice(5, 7)):
            r = np.linalg.norm(out[..., sl], axis=-1)
            lim = half[..., sl.start]
            scale = np.where(r > lim, lim / np.where(r > 0, r, 1.0), 1.0)
            out[..., sl] = out[..., sl] * scale[..., None]
        out[..., 7] = np.mod(out[..., 7], 2 * math.pi)
        return out

    def worst(self, rl: np.ndarray, position, angle, *, levels: int = 5, sweeps: int = 3
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Worst ``||G||`` (n,) over the load directions and the noise set at depths ``rl`` (n,):
        the corners at every sampled direction, then a pattern search from the worst (steps halved
        per level, each move the best of the 16 axis polls, projected back into the set). The
        result is a lower bound of the worst case (the set is searched, not bounded). ``position``
        and ``angle`` may be arrays (n,) (the tracker-noise search). Returns ``(g, degenerate,
        argument)``; ``degenerate`` marks depths where some evaluated noise puts the estimated port
        outside ``(0, L)`` (Jhat degenerate: the worst case is raised to at least 1 there, as in the plane)."""
        rl = np.atleast_1d(np.asarray(rl, float))
        n = len(rl)
        pos = np.broadcast_to(np.asarray(position, float), (n,))
        ang = np.broadcast_to(np.asarray(angle, float), (n,))
        g = np.empty(n)
        arg = np.empty((n, 8))
        amin, amax = np.full(n, np.inf), np.full(n, -np.inf)
        for i in range(n):  # corners: per depth (their count depends on which bounds are zero)
            cand = self.candidates(float(pos[i]), float(ang[i]))
            v, a = self.g_norm(rl[i:i + 1], cand[None])
            j = int(np.argmax(v[0]))
            g[i], arg[i] = v[0, j], cand[j]
            amin[i], amax[i] = min(amin[i], a.min()), max(amax[i], a.max())
        half = np.stack([self.half(float(p_), float(a_)) for p_, a_ in zip(pos, ang)])
        steps = np.concatenate([np.eye(8), -np.eye(8)])
        if self.in_plane:  # only the plane's parameters move: delta_y, delta_z, the e1 tilts
            keep = np.zeros(8, bool)
            keep[[1, 2, 3, 5]] = True
            steps = steps[np.tile(keep, 2)]

        def objective(c):
            v, a = self.g_norm(rl, c)
            amin[:] = np.minimum(amin, a.min(axis=1))
            amax[:] = np.maximum(amax, np.where(np.isfinite(a), a, -np.inf).max(axis=1))
            return v

        g, arg = pattern_search(objective, g, arg, half, steps=steps, active=np.isfinite(g),
                                project=lambda c: self._project(c, half[:, None, :]), levels=levels,
                                sweeps=sweeps)
        degenerate = ~((amin > 0) & (amax < self.length))
        return np.where(degenerate, np.maximum(g, 1.0), g), degenerate, arg


def spatial_insertion_band(length: float, tip_load: float, position: float, angle: float, *, gain: float = 1.0,
                           samples: int = 97, shaft_direction=(0.0, 0.0, 1.0), in_plane: bool = False,
                           progress: Progress | None = None) -> dict[str, Any]:
    """The insertion-depth band of P2's flexion controller in 3-D (:class:`SpatialInsertionModel`):
    the depths ``r/L`` where the worst ``||G||`` over loads of magnitude ``tip_load`` in every
    direction normal to the shaft and over the tracker's 3-D noise set stays below 1.

    Same keys as :func:`insertion_band` (``band``, ``intervals``, ``best``, ``best_G_norm``,
    ``worst_G_norm``) plus ``lower_bound`` (true: the worst case is searched over the set, corners
    and a pattern search, not bounded; the band found can only be too wide), ``shaft_direction``
    and ``worst_load_direction`` (the psi of each depth's worst). Band edges are refined by
    bisection, the best depth by golden section, as in the plane.
    """
    if samples < 5:
        raise ErrplanError(f"samples = {samples}: expected at least 5 insertion depths")
    if position < 0 or angle < 0 or not (math.isfinite(position) and math.isfinite(angle)):
        raise ErrplanError(f"sensor_noise = ({position!r}, {angle!r}): expected bounds >= 0")
    model = SpatialInsertionModel(length, tip_load, gain, tuple(float(v) for v in shaft_direction), in_plane)
    rl = np.linspace(0.02, 0.98, samples)
    g, degenerate, arg = model.worst(rl, position, angle)
    if progress:
        progress(0.5, "insertion band (3-D)")

    def f(r: float) -> float:
        return float(model.worst(np.array([r]), position, angle)[0][0])

    band, intervals, best, best_g = _band_of_curve(rl, g, f)
    if progress:
        progress(1.0, "insertion band (3-D)")
    return {
        "band": band, "intervals": intervals, "best": float(best), "best_G_norm": float(best_g),
        "worst_G_norm": {"r_over_L": rl, "G_norm": g, "degenerate_model": degenerate},
        "worst_load_direction": {"r_over_L": rl, "psi": arg[:, 7]},
        "length": length, "tip_force_over_ei": tip_load, "gain": gain,
        "sensor_noise": {"position": position, "angle": angle}, "noise_sampling": "worst",
        "samples": samples, "shaft_direction": [float(v) for v in model.s], "in_plane": in_plane,
        "lower_bound": True,
        "method": ("worst over loads in every direction normal to the shaft and the 3-D noise set: corners (chord "
                   "differences at -2p, 0, 2p per axis x end tilts at 4 azimuths x 16 load directions) and a pattern "
                   "search from the worst; a lower bound of the true worst case"),
    }


def spatial_tracker_noise(length: float, tip_load: float, band: tuple[float, float], *, gain: float = 1.0,
                          angle_ratio: float = LIBERTY_ANGLE_RATIO, samples: int = 21,
                          shaft_direction=(0.0, 0.0, 1.0), in_plane: bool = False,
                          progress: Progress | None = None) -> dict[str, Any]:
    """The largest tracker noise keeping P2's flexion controller in 3-D monotonic over an insertion
    band (:func:`tracker_noise` in 3-D): position bound ``s`` per coordinate, direction bound
    ``angle_ratio * s / L``; the worst case per depth from :meth:`SpatialInsertionModel.worst`
    (a lower bound, so the noise found can only be too large: ``lower_bound`` says so)."""
    lo_b, hi_b = _check_noise_query(band, samples, angle_ratio)
    model = SpatialInsertionModel(length, tip_load, gain, tuple(float(v) for v in shaft_direction), in_plane)
    rl = np.linspace(lo_b, hi_b, samples) if hi_b > lo_b else np.array([lo_b])
    g0 = model.worst(rl, 0.0, 0.0, levels=0)[0]

    def fails(s: np.ndarray) -> np.ndarray:
        return model.worst(rl, s, s * angle_ratio / length)[0] >= 1.0

    lo, hi, capped = _bisect_vec(fails, len(rl), 1e-5 * length, 0.05 * length, zero_fails=g0 >= 1.0,
                                 abs_tol=1e-10, progress=progress, label="tracker noise (3-D)")
    j = int(np.argmin(lo))
    s = float(lo[j])
    g_at = model.worst(rl, np.full(len(rl), s), np.full(len(rl), s * angle_ratio / length))[0]
    return {
        "value": s, "angle_value": s * angle_ratio / length, "binding_r_over_L": float(rl[j]),
        "band": [lo_b, hi_b], "length": length, "tip_force_over_ei": tip_load, "gain": gain,
        "angle_ratio": angle_ratio, "samples": samples, "capped": bool(capped[j]),
        "shaft_direction": [float(v) for v in model.s], "in_plane": in_plane, "lower_bound": True,
        "curve": {"r_over_L": rl, "max_position_noise": lo, "G_norm_at_value": g_at},
    }
