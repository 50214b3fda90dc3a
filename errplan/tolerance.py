"""Tolerance-design queries: how much error a task can take (P1 Sec. IV, P2 Sec. IV-B and VI).

Every query answers "the largest error of some kind for which the controller still converges
monotonically" (worst-case ``||G|| < 1``) and returns a plot-ready curve. Four kinds
(``[[tolerance]]`` tables of a scenario, docs/interfaces.md):

``port``
    The largest port error ``e`` (m) such that, for every tip of a rectangular region and every
    true port in ``estimate + S(e)``, the tip is reachable and ``||G||`` at the query's gain is
    below 1. ``S(e)`` is the segment ``{(dy, 0): |dy| <= e}`` (direction ``y``), the segment
    ``{(0, dz): |dz| <= e}`` (``z``) or the disk ``{|d| <= e}`` (``radial``). The controller is
    the scenario's (rigid lever through ``port.estimate``, or P2's flexion model fed by noisy end
    measurements, noise from ``[uncertainty] sensor_noise``).
``tip_load``
    The largest ``T`` (1/m^2) such that a *rigid-lever* controller through ``port.estimate`` keeps
    ``||G|| < 1`` over the region for every lateral tip load ``Ft/EI`` in ``[-T, T]`` (and every
    true port in the optional box ``estimate + port_y x port_z``; without the box the true port is
    ``port.position``).
``insertion_band``
    P2's flexion-model controller (eqs. 4-14) fed by end positions and orientations with bounded
    noise: the worst case of ``||G||`` over the 6-D noise box as a function of insertion depth
    ``r/L``, the band where it stays below 1 and the best depth (P2 Fig. 7). Also the worst-case
    error of the estimated ``Fp/EI`` (P2 Fig. 8) and of the estimated port (P2 Fig. 9).
``tracker_noise``
    The largest tracker position noise ``s`` (m; angle noise ``angle_ratio * s / L`` rad) for
    which the worst-case ``||G||`` stays below 1 over a required insertion band.

Soundness. Each criterion is a worst case over a *nested* family of sets (segments, disks, load
ranges, noise boxes that grow with the error size), hence monotone in the size; the size is found
per tip (or per depth) by bisection, and the answer is the minimum over the region (or band).
The worst case over each set is found by dense sampling plus a local pattern search; for the
6-D noise box, by all 64 vertices plus a pattern search from the worst vertex (``||G||`` is close
to a convex function of small noise, so its maximum sits at a vertex; the tests compare with
scipy multi-start optimisation and 20,000 random draws). Where the box also holds noise vectors
that make P2's estimate degenerate (estimated ``a`` outside ``(0, L)``: a thin interior set the
vertices can miss, with ``||G|| >= 1`` in its limit), the worst case is reported as at least 1.
Region grids are refined (nested, spacing halved) until the answer changes by less than 1%
(reported as ``refinement_change``).

Geometry of the insertion queries (P2 Sec. V, rotational symmetry): the port at the origin, the
tip at ``r * dir(shaft_angle)`` (``shaft_angle = 0``: the port->tip line along the tracker's z
axis), the wrist from the flexed-shaft inverse (``flexed_wrist``). The noise box is aligned with
the tracker axes, so it is *not* rotationally symmetric: ``shaft_angle`` matters (see
notes/readme_tolerance.md).
"""
from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from .errors import ErrplanError, InfeasibleError
from .inputs import memory_budget
from .fields import ErrorSet, Evaluator
from .kinematics.arm import Arm, direction
from .kinematics.shaft import (estimate_from_ends, flexed_end_angles, flexed_geometry, flexed_jacobian,
                               flexed_wrist)
from .metrics import compose_parts, conformal_parts, g_norm_from_parts, inverse_parts

Progress = Callable[[float, str], None]

#: P2 Sec. VI: the Liberty tracker, 0.0021 L position and 0.0026 rad angle (RMS used as bounds).
LIBERTY_ANGLE_RATIO = 0.0026 / 0.0021
#: Relative change of an answer under grid refinement that we accept (the issue's 1%).
REFINE_TOL = 0.01
#: Bisection stops when the bracket is below this fraction of its upper end (or 1e-7 m / 1/m^2).
BISECT_RTOL = 2e-4
HOLDS = ("tip_force", "port_force", "port_deflection")
#: memory (bytes) per region tip while a worst case over an error set is evaluated (measured with
#: tracemalloc at about 350 B for the rigid controller; the flexion controller and the bisection
#: state need more)
TIP_BYTES = 2048
#: memory (bytes) per (depth, noise draw) evaluation of P2's flexion model (measured: about 265 B)
EVAL_BYTES = 512
#: (depth x draw) evaluations per chunk of random noise draws: memory stays flat whatever the
#: number of depths and draws (the maximum over the draws does not depend on the chunking)
EVAL_CHUNK = 2_000_000
NOISE_SAMPLING = ("worst", "random")


# ============================================================================= result object
@dataclass
class ToleranceResult:
    """One answered query. ``data`` holds the kind's keys of docs/interfaces.md ("tolerance JSON")
    plus the plot-ready ``curve`` and details; :meth:`to_dict` is the JSON entry."""

    name: str
    kind: str
    data: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        out = {"name": self.name, "kind": self.kind}
        out.update(_jsonable(self.data))
        out["seconds"] = round(self.seconds, 3)
        return out

    def summary_row(self) -> list[Any]:
        """``[name, kind, answer, where, note]`` for the command's table."""
        d = self.data
        if self.kind == "port":
            return [self.name, f"port ({d['direction']})", f"{1000 * d['value']:.3f} mm",
                    f"[{d['binding_point'][0]:.4f}, {d['binding_point'][1]:.4f}]", d["binding"]]
        if self.kind == "tip_load":
            return [self.name, "tip_load", f"{d['value']:.4g} 1/m^2",
                    f"[{d['binding_point'][0]:.4f}, {d['binding_point'][1]:.4f}]", d["binding"]]
        if self.kind == "insertion_band":
            band = d["band"]
            b = "none" if band is None else f"{band[0]:.3f} < r/L < {band[1]:.3f}"
            return [self.name, "insertion_band", b, f"best r/L {d['best']:.3f}",
                    f"min worst ||G|| {d['best_G_norm']:.3f}"]
        if self.kind == "tracker_noise":
            return [self.name, "tracker_noise", f"{1000 * d['value']:.4f} mm, {d['angle_value']:.5f} rad",
                    f"r/L {d['binding_r_over_L']:.3f}", f"= {d['value'] / d['length']:.5f} L"]
        return [self.name, self.kind, "", "", ""]  # pragma: no cover


def _jsonable(obj: Any) -> Any:
    """numpy -> JSON types; non-finite floats become ``None`` (JSON null: 'divergent/undefined')."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


# ============================================================================= flexed shaft helpers
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


# ============================================================================= worst case over a box
_UNIT_CORNERS = np.array(list(itertools.product((-1.0, 1.0), repeat=6)))


def box_worst(objective: Callable[[np.ndarray], np.ndarray], half: np.ndarray, *, levels: int = 5,
              sweeps: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Maximum of ``objective`` over the boxes ``[-half, half]`` (one box per row of ``half`` (n, d)).

    ``objective(noise (n, c, d)) -> (n, c)``. Method: every vertex of the box, then a pattern search
    from the worst vertex (steps ``half * 2^-l``, ``l = 0..levels-1``, up to ``sweeps`` accepted
    moves per level, each move the best of the ``2d`` axis steps, clipped to the box). Returns the
    maximum (n,) and its argument (n, d).
    """
    half = np.asarray(half, float)
    n, d = half.shape
    unit = _UNIT_CORNERS if d == 6 else np.array(list(itertools.product((-1.0, 1.0), repeat=d)))
    cand = unit[None, :, :] * half[:, None, :]
    vals = objective(cand)
    i = np.argmax(vals, axis=1)
    best = vals[np.arange(n), i]
    arg = cand[np.arange(n), i]
    steps = np.concatenate([np.eye(d), -np.eye(d)])  # (2d, d)
    active = half.max(axis=1) > 0
    for level in range(levels):
        h = half * 2.0 ** (-level)
        for _ in range(sweeps):
            c = np.clip(arg[:, None, :] + steps[None] * h[:, None, :], -half[:, None, :], half[:, None, :])
            v = objective(c)
            j = np.argmax(v, axis=1)
            vj = v[np.arange(n), j]
            upd = active & (vj > best)
            if not upd.any():
                break
            best = np.where(upd, vj, best)
            arg = np.where(upd[:, None], c[np.arange(n), j], arg)
    return best, arg


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
        from .inputs import check_allocation

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


# ============================================================================= 1-D helpers
def _bisect_vec(fails: Callable[[np.ndarray], np.ndarray], n: int, start: float, cap: float,
                zero_fails: np.ndarray | None = None, abs_tol: float = 1e-7,
                progress: Progress | None = None, label: str = "") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-row largest ``e`` with ``fails(e) == False`` for a monotone criterion.

    ``fails(e (n,)) -> bool (n,)``. Brackets by doubling from ``start`` up to ``cap`` and bisects until
    the bracket is below ``BISECT_RTOL`` of its top (or ``abs_tol``). Rows failing at 0
    (``zero_fails``) get 0. Returns ``(lo, hi, capped)``: ``lo`` passes, ``hi`` fails (``cap`` when
    nothing failed, flagged in ``capped``).
    """
    lo = np.zeros(n)
    hi = np.full(n, start)
    zero = np.zeros(n, bool) if zero_fails is None else zero_fails.copy()
    hi[zero] = 0.0
    searching = ~zero
    capped = np.zeros(n, bool)
    while searching.any():
        f = np.ones(n, bool)
        f[searching] = fails(hi)[searching]
        passed = searching & ~f
        lo[passed] = hi[passed]
        at_cap = passed & (hi >= cap)
        capped |= at_cap
        grow = passed & ~at_cap
        hi[grow] = np.minimum(2.0 * hi[grow], cap)
        searching = grow
    hi[capped] = cap
    todo = ~zero & ~capped
    it = 0
    while True:
        width = hi - lo
        todo &= width > np.maximum(BISECT_RTOL * hi, abs_tol)
        if not todo.any() or it > 60:
            break
        mid = np.where(todo, 0.5 * (lo + hi), lo)
        f = fails(mid)
        lo = np.where(todo & ~f, mid, lo)
        hi = np.where(todo & f, mid, hi)
        it += 1
        if progress:
            progress(min(1.0, it / 14.0), label)
    return lo, hi, capped


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Index ranges [i, j] of the True runs of a boolean vector."""
    out, i = [], None
    for k, m in enumerate(mask):
        if m and i is None:
            i = k
        if not m and i is not None:
            out.append((i, k - 1))
            i = None
    if i is not None:
        out.append((i, len(mask) - 1))
    return out


def _crossing(f: Callable[[float], float], a: float, b: float, iters: int = 50) -> float:
    """A root of ``f(r) - 1`` between ``a`` (f < 1) and ``b`` (f >= 1) by bisection (f may be inf)."""
    for _ in range(iters):
        m = 0.5 * (a + b)
        if f(m) < 1.0:
            a = m
        else:
            b = m
        if abs(b - a) < 1e-7:
            break
    return 0.5 * (a + b)


def _golden_min(f: Callable[[float], float], a: float, b: float, iters: int = 40) -> float:
    gr = (math.sqrt(5) - 1) / 2
    c, d = b - gr * (b - a), a + gr * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(iters):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - gr * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + gr * (b - a)
            fd = f(d)
    return 0.5 * (a + b)


# ============================================================================= insertion band
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
    lo_b, hi_b = band
    if not 0 < lo_b <= hi_b < 1:
        raise ErrplanError(f"band = {list(band)}: expected insertion depths 0 < lo <= hi < 1 (r/L)")
    if samples < 2:
        raise ErrplanError(f"samples = {samples}: expected at least 2 depths")
    if angle_ratio < 0 or not math.isfinite(angle_ratio):
        raise ErrplanError(f"angle_ratio = {angle_ratio!r}: expected a number >= 0")
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


# ============================================================================= region queries
def region_grid(region: dict, spacing: float) -> np.ndarray:
    """Tips (m, 2) on a grid over ``region = {y: [lo, hi], z: [lo, hi]}`` with edges included and
    spacing at most ``spacing``."""
    from .inputs import check_allocation

    n_y, n_z = _grid_size(region, spacing)
    check_allocation("spacing", spacing, n_y * n_z, 2 * 8 * 3, "the region grid")
    axes = []
    for key in ("y", "z"):
        lo, hi = region[key]
        n = 1 if hi == lo else int(math.ceil((hi - lo) / spacing - 1e-9)) + 1
        axes.append(np.linspace(lo, hi, max(n, 1 if hi == lo else 2)))
    Y, Z = np.meshgrid(*axes, indexing="ij")
    return np.stack([Y.ravel(), Z.ravel()], axis=-1)


@dataclass
class _OffsetSet:
    """A nested family of error sets ``theta(e) = (dy, dz, t)`` parametrised by a size ``e``.

    ``shape``: ``"y"`` / ``"z"`` (segment ``[-e, e]`` along that axis), ``"radial"`` (disk radius
    ``e``), ``"load"`` (tip load ``t in [-e, e]`` with a fixed port box). The set is parametrised by
    ``q`` in a unit box; ``theta(q, e)`` maps it.
    """

    shape: str
    t_range: tuple[float, float] = (0.0, 0.0)
    box_y: tuple[float, float] = (0.0, 0.0)
    box_z: tuple[float, float] = (0.0, 0.0)

    def unit_samples(self) -> np.ndarray:
        t = np.linspace(0, 1, 5) if self.t_range[1] > self.t_range[0] else np.array([0.0])
        if self.shape in ("y", "z"):
            grid = [np.linspace(-1, 1, 9), t]
        elif self.shape == "radial":
            grid = [np.linspace(0, 1, 4), np.arange(24) / 24.0, t]
        else:  # load
            by = np.linspace(0, 1, 3) if self.box_y[1] > self.box_y[0] else np.array([0.0])
            bz = np.linspace(0, 1, 3) if self.box_z[1] > self.box_z[0] else np.array([0.0])
            grid = [np.linspace(-1, 1, 9), by, bz]
        q = np.stack(np.meshgrid(*grid, indexing="ij"), axis=-1).reshape(-1, len(grid))
        if self.shape == "radial":  # the centre once per load sample
            q = np.concatenate([q[q[:, 0] > 0], np.stack([np.zeros_like(t), np.zeros_like(t), t], axis=-1)])
        return q

    def steps(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Initial pattern steps, lower and upper bounds of ``q`` (the angle of a disk wraps)."""
        if self.shape in ("y", "z"):
            return np.array([0.25, 0.25]), np.array([-1.0, 0.0]), np.array([1.0, 1.0])
        if self.shape == "radial":
            return np.array([1 / 6, 1 / 48, 0.25]), np.array([0.0, -np.inf, 0.0]), np.array([1.0, np.inf, 1.0])
        return np.array([0.25, 0.25, 0.25]), np.array([-1.0, 0.0, 0.0]), np.array([1.0, 1.0, 1.0])

    def active(self) -> np.ndarray:
        t_on = self.t_range[1] > self.t_range[0]
        if self.shape in ("y", "z"):
            return np.array([True, t_on])
        if self.shape == "radial":
            return np.array([True, True, t_on])
        return np.array([True, self.box_y[1] > self.box_y[0], self.box_z[1] > self.box_z[0]])

    def theta(self, q: np.ndarray, e: np.ndarray) -> np.ndarray:
        """``theta`` (..., 3) for ``q`` (..., k) and sizes ``e`` (...)."""
        t0, t1 = self.t_range
        if self.shape in ("y", "z"):
            d = e * q[..., 0]
            t = t0 + (t1 - t0) * q[..., 1]
            z0 = np.zeros_like(d)
            return np.stack([d, z0, t] if self.shape == "y" else [z0, d, t], axis=-1)
        if self.shape == "radial":
            ang = 2 * np.pi * q[..., 1]
            rad = e * q[..., 0]
            t = t0 + (t1 - t0) * q[..., 2]
            return np.stack([rad * np.sin(ang), rad * np.cos(ang), t], axis=-1)
        dy = self.box_y[0] + (self.box_y[1] - self.box_y[0]) * q[..., 1]
        dz = self.box_z[0] + (self.box_z[1] - self.box_z[0]) * q[..., 2]
        return np.stack([dy, dz, e * q[..., 0]], axis=-1)


def _set_worst(ev: Evaluator, x: np.ndarray, oset: _OffsetSet, e: np.ndarray, k: float,
               levels: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Worst ``||G||`` over ``oset(e_i)`` at tips ``x_i`` (n,), validity (every evaluated instance
    reachable and the controller model regular) and reachability alone (n,)."""
    n = len(x)
    Q = oset.unit_samples()
    best = np.full(n, -np.inf)
    qbest = np.zeros((n, Q.shape[1]))
    valid = np.ones(n, bool)
    reach = np.ones(n, bool)

    def evaluate(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        th = oset.theta(q, e)
        mu, nu, ok = ev.parts(x, th)
        _, okr = ev.true_wrist(x, th)
        g = g_norm_from_parts(mu, nu, k).max(axis=-1)
        return np.where(ok, g, np.inf), okr

    for q in Q:
        g, okr = evaluate(np.broadcast_to(q, (n, len(q))))
        reach &= okr
        valid &= np.isfinite(g)
        upd = g > best
        best[upd] = g[upd]
        qbest[upd] = q
    step0, qlo, qhi = oset.steps()
    act = oset.active()
    for level in range(levels):
        h = step0 * 2.0 ** (-level)
        for dim in np.flatnonzero(act):
            for sgn in (-1.0, 1.0):
                c = qbest.copy()
                c[:, dim] = np.clip(c[:, dim] + sgn * h[dim], qlo[dim], qhi[dim])
                g, okr = evaluate(c)
                reach &= okr
                valid &= np.isfinite(g)
                upd = g > best
                best[upd] = g[upd]
                qbest[upd] = c[upd]
    return best, valid, reach


def _grid_size(region: dict, spacing: float) -> tuple[float, float]:
    """:func:`_grid_counts` as floats, computed without building anything (a size check first)."""
    out = []
    for key in ("y", "z"):
        lo, hi = region[key]
        out.append(1.0 if hi == lo else max(2.0, math.ceil((hi - lo) / spacing - 1e-9) + 1.0))
    return out[0], out[1]


def _grid_counts(region: dict, spacing: float) -> tuple[int, int]:
    out = []
    for key in ("y", "z"):
        lo, hi = region[key]
        out.append(1 if hi == lo else max(2, int(math.ceil((hi - lo) / spacing - 1e-9)) + 1))
    return out[0], out[1]


def _grid(region: dict, counts: tuple[int, int]) -> np.ndarray:
    axes = [np.linspace(region[key][0], region[key][1], n) for key, n in zip(("y", "z"), counts)]
    Y, Z = np.meshgrid(*axes, indexing="ij")
    return np.stack([Y.ravel(), Z.ravel()], axis=-1)


def _region_tolerance(ev: Evaluator, region: dict, oset: _OffsetSet, k: float, *, cap: float, start: float,
                      unit: str, spacing: float | None, label: str, progress: Progress | None = None
                      ) -> dict[str, Any]:
    """Largest size with ``||G|| < 1`` and reachability over a region: per-tip bisection on an
    initial grid, then nested refinements (each halves the spacing, keeping the old tips) until the
    answer changes by less than ``REFINE_TOL``. A refinement only bisects the new tips that fail at
    the current answer (the others cannot lower the minimum), so it costs about one evaluation."""
    from .inputs import check_allocation

    ext = max(region["y"][1] - region["y"][0], region["z"][1] - region["z"][0])
    h = float(spacing) if spacing else ext / 8.0
    n_y, n_z = _grid_size(region, min(h, ext) if ext > 0 else 1.0)
    key, value = ("spacing", h) if spacing else ("region", f"{{y = {list(region['y'])}, z = {list(region['z'])}}}")
    check_allocation(key, value, n_y * n_z, TIP_BYTES,
                     f"the region grid ({n_y:.3g} x {n_z:.3g} tips at {min(h, ext) if ext > 0 else 0.0:g} m)")
    counts = _grid_counts(region, min(h, ext) if ext > 0 else 1.0)
    x = _grid(region, counts)
    g0, ok0, r0 = _set_worst(ev, x, oset, np.zeros(len(x)), k)
    where = f"region = {{y = {list(region['y'])}, z = {list(region['z'])}}}"
    if not r0.all():
        bad = x[~r0][0]
        raise InfeasibleError(f"{where}: the tip [{bad[0]:.4f}, {bad[1]:.4f}] is outside the workspace even without "
                              f"error ({int((~r0).sum())} of {len(x)} grid tips unreachable)")
    if not ok0.all():
        bad = x[~ok0][0]
        raise InfeasibleError(f"{where}: the controller's model is singular or unidentifiable at "
                              f"[{bad[0]:.4f}, {bad[1]:.4f}] even without error")

    def fails_at(xs: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        def fails(e: np.ndarray) -> np.ndarray:
            g, ok, _ = _set_worst(ev, xs, oset, e, k)
            return ~ok | (g >= 1.0)
        return fails

    lo, hi, capped = _bisect_vec(fails_at(x), len(x), start, cap, zero_fails=g0 >= 1.0, progress=progress,
                                 label=label)
    j = int(np.argmin(lo))
    best = {"value": float(lo[j]), "upper": float(hi[j]), "point": x[j], "zero": bool(g0[j] >= 1.0),
            "capped": bool(capped[j])}
    per_tip = {"points": x, unit: lo}
    x0 = x
    change, refinements = (0.0 if ext == 0 else None), 0
    while ext > 0 and refinements < 6 and best["value"] > 0 and not best["capped"]:
        fine = tuple(2 * n - 1 if n > 1 else 1 for n in counts)
        if float(fine[0]) * fine[1] * TIP_BYTES > memory_budget():
            break  # the machine cannot hold a finer grid: the answer stays unconverged (reported)
        xf = _grid(region, fine)
        old = np.zeros(fine, bool)
        old[:: (2 if fine[0] > 1 else 1), :: (2 if fine[1] > 1 else 1)] = True
        xn = xf[~old.ravel()]
        v = best["value"]
        fails = fails_at(xn)
        f_new = fails(np.full(len(xn), v))
        new_value = v
        if f_new.any():
            xs = xn[f_new]
            g0n, _, r0n = _set_worst(ev, xs, oset, np.zeros(len(xs)), k)
            if not r0n.all():
                bad = xs[~r0n][0]
                raise InfeasibleError(f"{where}: the tip [{bad[0]:.4f}, {bad[1]:.4f}] is outside the workspace even "
                                      "without error")
            lo_n, hi_n, _ = _bisect_vec(fails_at(xs), len(xs), v, v, zero_fails=g0n >= 1.0)
            jn = int(np.argmin(lo_n))
            if lo_n[jn] < v:
                new_value = float(lo_n[jn])
                best = {"value": new_value, "upper": float(hi_n[jn]), "point": xs[jn], "zero": bool(g0n[jn] >= 1.0),
                        "capped": False}
        change = (v - new_value) / v
        counts, x = fine, xf
        refinements += 1
        if change < REFINE_TOL:
            break
    # why the binding tip fails just above the answer
    xb = best["point"][None, :]
    gb, okb, rb = _set_worst(ev, xb, oset, np.array([best["upper"]]), k)
    reason = ("G_norm" if best["zero"] else "capped" if best["capped"] else
              "reachability" if not rb[0] else "singular" if not okb[0] else "G_norm")
    # plot-ready curve: size vs max over the region of the worst ||G|| (and whether every tip is
    # valid), on the initial grid plus the binding tip
    top = best["value"] if best["capped"] else max(2.0 * best["value"], start)
    sizes = np.linspace(0.0, top, 41)
    gmax, allok = [], []
    xc = np.concatenate([x0, xb])
    for e in sizes:
        g, ok, _ = _set_worst(ev, xc, oset, np.full(len(xc), e), k)
        gmax.append(float(np.max(g[ok])) if ok.any() else float("nan"))
        allok.append(bool(ok.all()))
    return {"value": best["value"], "upper": best["upper"], "binding_point": best["point"], "binding": reason,
            "tips": len(x), "spacing": _spacing(region, counts), "refinements": refinements,
            "refinement_change": change, "converged": bool(change is not None and change < REFINE_TOL),
            "curve": {unit: sizes, "max_G_norm": gmax, "all_valid": allok}, "per_tip_map": per_tip}


def _spacing(region: dict, counts: tuple[int, int]) -> float:
    s = [(region[key][1] - region[key][0]) / (n - 1) for key, n in zip(("y", "z"), counts) if n > 1]
    return float(max(s)) if s else 0.0


def _evaluator(sc, jacobian: str, base_port, t_range=(0.0, 0.0)) -> Evaluator:
    u = sc.uncertainty
    noise = (u.sensor_noise.position, u.sensor_noise.angle) if (u.sensor_noise and jacobian == "flexion") else (0.0, 0.0)
    es = ErrorSet(tuple(base_port), (0.0, 0.0, t_range[0]), (0.0, 0.0, t_range[1]), noise, 5)
    return Evaluator(Arm.from_robot(sc.robot), sc.instrument.length, tuple(sc.port.estimate), jacobian, es)


def _load_range(v, default) -> tuple[float, float]:
    if v is None:
        return default
    if isinstance(v, (tuple, list)):
        return (float(v[0]), float(v[1]))
    return (float(v), float(v))


def port_tolerance(sc, region: dict, direction_: str = "radial", *, gain: float | None = None,
                   tip_force_over_ei=None, spacing: float | None = None,
                   progress: Progress | None = None) -> dict[str, Any]:
    """Largest port error (m) in ``direction_`` keeping the region reachable and worst ``||G|| < 1``.

    The true port ranges over ``port.estimate + S(e)`` (see the module docstring); the tip load is
    ``tip_force_over_ei`` (a number: that load; a pair: the worst case over the range; default the
    scenario's ``[uncertainty] tip_force_over_ei`` range, else 0). Returns ``value``, ``binding_point``,
    ``binding`` (``"G_norm"`` or ``"reachability"``), the grid used and the curve ``error`` vs
    ``max_G_norm``.
    """
    if direction_ not in ("y", "z", "radial"):
        raise ErrplanError(f"direction = {direction_!r}: expected \"y\", \"z\" or \"radial\"")
    k = float(gain if gain is not None else sc.controller.gain)
    t_range = _load_range(tip_force_over_ei, sc.uncertainty.tip_force_over_ei or (0.0, 0.0))
    if sc.controller.jacobian == "flexion" and t_range[0] <= 0 <= t_range[1]:
        raise ErrplanError(f"tip_force_over_ei = {list(t_range)}: P2's flexion controller cannot identify its model "
                           "without flexion; give a non-zero tip load (or a range that excludes 0)")
    ev = _evaluator(sc, sc.controller.jacobian, sc.port.estimate, t_range)
    oset = _OffsetSet(direction_, t_range)
    res = _region_tolerance(ev, region, oset, k, cap=sc.instrument.length, start=0.001, unit="error",
                            spacing=spacing, label="port tolerance", progress=progress)
    return {"value": res["value"], "binding_point": res["binding_point"], "binding": res["binding"],
            "direction": direction_, "gain": k, "tip_force_over_ei": list(t_range), "region": region,
            "controller": sc.controller.jacobian, "grid": {"tips": res["tips"], "spacing": res["spacing"]},
            "refinement_change": res["refinement_change"], "converged": res["converged"],
            "bracket": [res["value"], res["upper"]], "curve": res["curve"], "per_tip": res["per_tip_map"]}


def tip_load_tolerance(sc, region: dict, *, gain: float | None = None, port_y=None, port_z=None,
                       spacing: float | None = None, progress: Progress | None = None) -> dict[str, Any]:
    """Largest ``T`` (1/m^2) such that the rigid-lever controller through ``port.estimate`` keeps
    worst ``||G|| < 1`` and the region reachable for every tip load in ``[-T, T]`` (and every true
    port in ``estimate + port_y x port_z`` when given; else the true port is ``port.position``)."""
    k = float(gain if gain is not None else sc.controller.gain)
    if port_y is None and port_z is None:
        base, by, bz = sc.port.position, (0.0, 0.0), (0.0, 0.0)
    else:
        base, by, bz = sc.port.estimate, tuple(port_y or (0.0, 0.0)), tuple(port_z or (0.0, 0.0))
    ev = _evaluator(sc, "rigid", base)
    oset = _OffsetSet("load", box_y=by, box_z=bz)
    res = _region_tolerance(ev, region, oset, k, cap=1000.0, start=0.5, unit="tip_force_over_ei",
                            spacing=spacing, label="tip-load tolerance", progress=progress)
    return {"value": res["value"], "binding_point": res["binding_point"], "binding": res["binding"],
            "gain": k, "region": region, "controller": "rigid", "true_port": list(base),
            "port_y": list(by), "port_z": list(bz),
            "grid": {"tips": res["tips"], "spacing": res["spacing"]},
            "refinement_change": res["refinement_change"], "converged": res["converged"],
            "bracket": [res["value"], res["upper"]], "curve": res["curve"], "per_tip": res["per_tip_map"]}


# ============================================================================= dispatch
def run_query(sc, tol, progress: Progress | None = None) -> ToleranceResult:
    """Answer one :class:`errplan.scenario.Tolerance` of scenario ``sc``."""
    t0 = time.perf_counter()
    o = tol.options
    gain = o.get("gain", sc.controller.gain)
    where = f"[[tolerance]] {tol.name!r}"
    try:
        if tol.kind == "port":
            data = port_tolerance(sc, o["region"], o.get("direction", "radial"), gain=gain,
                                  tip_force_over_ei=o.get("tip_force_over_ei"), spacing=o.get("spacing"),
                                  progress=progress)
        elif tol.kind == "tip_load":
            data = tip_load_tolerance(sc, o["region"], gain=gain, port_y=o.get("port_y"), port_z=o.get("port_z"),
                                      spacing=o.get("spacing"), progress=progress)
        elif tol.kind == "insertion_band":
            sn = o["sensor_noise"]
            data = insertion_band(o.get("length", sc.instrument.length), _tip_load(o, where), sn.position, sn.angle,
                                  gain=gain, samples=o.get("samples", 193), hold=o.get("hold", "tip_force"),
                                  shaft_angle=o.get("shaft_angle", 0.0), sampling=o.get("noise_sampling", "worst"),
                                  draws=o.get("draws", 10000), seed=o.get("seed", sc.planner.seed), progress=progress)
        elif tol.kind == "tracker_noise":
            data = tracker_noise(o.get("length", sc.instrument.length), _tip_load(o, where), o["band"], gain=gain,
                                 angle_ratio=o.get("angle_ratio", LIBERTY_ANGLE_RATIO), samples=o.get("samples", 41),
                                 hold=o.get("hold", "tip_force"), shaft_angle=o.get("shaft_angle", 0.0),
                                 progress=progress)
        else:  # pragma: no cover - the scenario parser rejects other kinds
            raise ErrplanError(f"{where}: unknown kind {tol.kind!r}")
    except ErrplanError as e:
        msg = str(e)
        raise type(e)(msg if msg.startswith(where) else f"{where}: {msg}") from None
    return ToleranceResult(tol.name, tol.kind, data, time.perf_counter() - t0)


def _tip_load(o: dict, where: str) -> float:
    t = o.get("tip_force_over_ei")
    if t is None:
        raise ErrplanError(f"{where}: tip_force_over_ei is required (P2's flexion controller needs a tip load)")
    if isinstance(t, (tuple, list)):
        raise ErrplanError(f"{where}: tip_force_over_ei = {list(t)}: expected one number for this kind")
    return float(t)


def check_sizes(sc) -> None:
    """Every size a scenario's ``[[tolerance]]`` queries will allocate, checked against the memory
    budget before any query runs (:func:`errplan.inputs.check_allocation`): the region grids of
    ``port`` and ``tip_load`` queries (from ``region`` and ``spacing``), and the noise evaluations
    of ``insertion_band`` queries (``samples`` x ``draws``)."""
    from .inputs import check_allocation

    for tol in sc.tolerances:
        o = tol.options
        where = f"[[tolerance]] {tol.name!r}"
        region = o.get("region")
        if tol.kind in ("port", "tip_load") and region is not None:
            ext = max(region["y"][1] - region["y"][0], region["z"][1] - region["z"][0])
            h = float(o["spacing"]) if o.get("spacing") else ext / 8.0
            n_y, n_z = _grid_size(region, min(h, ext) if ext > 0 else 1.0)
            key, value = ((f"{where} spacing", h) if o.get("spacing") else
                          (f"{where} region", f"{{y = {list(region['y'])}, z = {list(region['z'])}}}"))
            check_allocation(key, value, n_y * n_z, TIP_BYTES, f"the region grid ({n_y:.3g} x {n_z:.3g} tips)")
        if tol.kind == "insertion_band" and o.get("noise_sampling") == "random":
            draws = o.get("draws", 10000)
            check_allocation(f"{where} draws", draws, draws, 6 * 8, "the noise draws")


def run_all(sc, progress: Progress | None = None) -> list[ToleranceResult]:
    """Answer every ``[[tolerance]]`` query of ``sc`` in order."""
    if not sc.tolerances:
        raise ErrplanError(f"{sc.source}: the scenario has no [[tolerance]] queries")
    check_sizes(sc)  # every query's grid before the first query starts
    out = []
    for i, tol in enumerate(sc.tolerances):
        def sub(f, msg, i=i, tol=tol):
            progress((i + min(max(f, 0.0), 1.0)) / len(sc.tolerances), f"{tol.name}: {msg}")

        out.append(run_query(sc, tol, sub if progress else None))
    return out
