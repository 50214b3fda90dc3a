"""Quasi-static simulation of the inverse-Jacobian controller (P1 eqs. 1-5, P2 eq. 4).

At each step the controller reads the tracked tip ``x`` and the encoder angles ``q`` and commands
``q + k Jhat(q)^-1 (x_d - x)``; quasi-statically the joints reach the command before the next
step. ``Jhat`` comes from the controller's *model* (:class:`ControllerModel`: rigid lever through
the port estimate, or P2's flexion model fed by measured end poses); the motion comes from the
*truth* (:class:`Plant`: true port, tip load, and any effects of docs/physics.md).

Planar and spatial with the same code (docs/physics.md "Spatial robots"): points, motions and
Jacobians are ``(..., d)`` / ``(..., d, d)`` with ``d`` the plant's dimension; in 3-D the arm is
the scenario's URDF arm and the controller the rigid lever through the port estimate or P2's
flexion controller in 3-D (end positions and directions, the bending plane estimated from them).

This module imports neither ompl nor casadi nor rerun.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import ErrplanError
from .kinematics.arm import Arm
from .kinematics.shaft import estimate_from_ends, flexed_jacobian, flexion_controller_jacobian, lever_jacobian, tilt
from .kinematics.truth import Plant, effect_kwargs

__all__ = ["Plant", "effect_kwargs", "ControllerModel", "SimResult", "simulate", "distance_to_polyline",
           "g_norm_along"]
from .metrics import inv, spectral_norm


# ----------------------------------------------------------------------------- controller
@dataclass(frozen=True)
class ControllerModel:
    """The controller's model: the declared arm and shaft, the port estimate, and ``jacobian``
    ("rigid": lever through ``port_estimate``; "flexion": P2's model fed measured end poses)."""

    arm: Arm  # or a UrdfArm (3-D)
    length: float
    port_estimate: tuple[float, ...]
    jacobian: str = "rigid"
    noise: tuple[float, float] = (0.0, 0.0)  # flexion: uniform bounds on (position, angle)

    @classmethod
    def from_model(cls, m) -> "ControllerModel":
        """The controller of an arm's model (:class:`errplan.models.ArmModel`): its arm, shaft length,
        port estimate, Jacobian model and noise bounds."""
        return cls(m.arm, m.length, m.estimate, m.jacobian, m.noise)

    @property
    def dim(self) -> int:
        return len(self.port_estimate)

    def model_tip(self, q: np.ndarray) -> np.ndarray:
        """Tip the model predicts for encoder angles (rigid lever through the estimate)."""
        from .kinematics.shaft import lever_tip

        return lever_tip(self.arm.forward(q), np.asarray(self.port_estimate), self.length)

    def J_hat(self, q: np.ndarray, plant: Plant | None = None, rng: np.random.Generator | None = None) -> np.ndarray:
        """``Jhat(q)`` (..., d, d), tip w.r.t. joints."""
        q = np.asarray(q, float)
        Jr = self.arm.jacobian(q)
        if self.jacobian == "rigid":
            return lever_jacobian(self.arm.forward(q), np.asarray(self.port_estimate), self.length) @ Jr
        if plant is None:
            raise ErrplanError("the flexion controller needs measured end poses (a plant)")
        w, tip, thw, tht = plant.end_poses(q)
        if rng is not None and any(self.noise):
            pos, ang = self.noise
            w = w + rng.uniform(-pos, pos, np.shape(w))
            tip = tip + rng.uniform(-pos, pos, np.shape(tip))
            if self.dim == 3:  # directions: tilted by an angle uniform in the disk of radius ang
                thw, tht = (_random_tilt(d, ang, rng) for d in (thw, tht))
            else:
                thw = thw + rng.uniform(-ang, ang, np.shape(thw))
                tht = tht + rng.uniform(-ang, ang, np.shape(tht))
        with np.errstate(invalid="ignore", divide="ignore"):
            if self.dim == 3:  # thw, tht: the end directions (P2's controller in the estimated plane)
                J_tw = flexion_controller_jacobian(w, tip, thw, tht, self.length)
            else:
                est = estimate_from_ends(w, tip, thw, tht, self.length)
                J_tw = flexed_jacobian(w, est["port"], self.length, est["t"])
        # A shaft that does not bend (equal end slopes) does not identify P2's model: the
        # controller falls back to the straight-shaft model, the lever through the port estimate.
        rigid = ~np.all(np.isfinite(J_tw), axis=(-2, -1))
        if np.any(rigid):
            lever = lever_jacobian(self.arm.forward(q), np.asarray(self.port_estimate), self.length)
            J_tw = np.where(rigid[..., None, None], lever, J_tw)
        return J_tw @ Jr


def _random_tilt(d: np.ndarray, angle: float, rng: np.random.Generator) -> np.ndarray:
    """Unit directions ``d`` (..., 3) tilted by a random angular error uniform in the disk of radius
    ``angle`` (rad) around each: the 3-D reading of "direction noise bounded by an angle"."""
    d = np.asarray(d, float)
    n = d / np.linalg.norm(d, axis=-1, keepdims=True)
    ref = np.where((np.abs(n[..., 0]) < 0.9)[..., None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    e1 = np.cross(n, ref)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(n, e1)
    r = angle * np.sqrt(rng.uniform(0.0, 1.0, n.shape[:-1]))
    a = rng.uniform(0.0, 2 * np.pi, n.shape[:-1])
    return tilt(n, np.stack([r * np.cos(a), r * np.sin(a)], axis=-1), e1, e2)


# ----------------------------------------------------------------------------- results
@dataclass
class SimResult:
    """One simulated run. Arrays have one row per step (step 0 is the state before the first command)."""

    q: np.ndarray          # (n, joints) encoder angles
    tip: np.ndarray        # (n, d) true tip
    tracked: np.ndarray    # (n, d) tracked tip
    target: np.ndarray     # (n, d) active target when this state was read
    segment: np.ndarray    # (n,) index of the active segment
    gain: np.ndarray       # (n,) gain applied from this state
    path: np.ndarray       # (m, d) the intended path (start, segment ends...)
    converged: bool
    status: str            # "converged" | "max_steps" | "left_workspace"
    tolerance: float
    #: (n, d) what a noise-free, undelayed tracker reads of the true tip (``Plant.tracked``: ``R tip + b``
    #: with a tracker registration or offset, else the true tip): the tip the loop closes on, whose distance
    #: to the target the gain certificate bounds (:attr:`monotonic`). None: the true tip.
    loop: np.ndarray | None = None

    @property
    def steps(self) -> int:
        """Commands issued."""
        return len(self.q) - 1

    @property
    def errors(self) -> np.ndarray:
        """Distance from the true tip to the active target at each step (m)."""
        return np.linalg.norm(self.target - self.tip, axis=-1)

    @property
    def final_error(self) -> float:
        return float(np.linalg.norm(self.path[-1] - self.tip[-1]))

    @property
    def phi(self) -> np.ndarray:
        """Angle (rad) between each commanded (desired) motion and the actual motion, per step."""
        desired = self.target[:-1] - self.tracked[:-1]
        actual = self.tip[1:] - self.tip[:-1]
        if desired.shape[-1] == 2:
            cross = desired[:, 0] * actual[:, 1] - desired[:, 1] * actual[:, 0]
        else:
            cross = np.linalg.norm(np.cross(desired, actual), axis=-1)
        dot = np.sum(desired * actual, axis=-1)
        moving = (np.linalg.norm(actual, axis=-1) > 1e-12) & (np.linalg.norm(desired, axis=-1) > 1e-12)
        return np.where(moving, np.abs(np.arctan2(cross, dot)), 0.0)

    @property
    def max_phi(self) -> float:
        p = self.phi
        return float(p.max()) if len(p) else 0.0

    @property
    def loop_errors(self) -> np.ndarray:
        """Distance from the loop's tip (:attr:`loop`: the noise-free tracked tip) to the active target (m)."""
        x = self.tip if self.loop is None else self.loop
        return np.linalg.norm(self.target - x, axis=-1)

    @property
    def monotonic(self) -> bool:
        """The distance to the active target never grew (within a numerical slack), measured where the
        loop closes: on the noise-free tracked tip (:attr:`loop`), which with a tracker registration is
        ``R tip + b``, not the true tip; the certificate's ``||G|| < 1`` bounds exactly this distance. Without a
        registration or offset it is the true tip's distance."""
        e = self.loop_errors
        same = self.segment[1:] == self.segment[:-1]
        return bool(np.all(e[1:][same] <= e[:-1][same] * (1 + 1e-9) + 1e-12))

    @property
    def max_deviation(self) -> float:
        """Largest distance of the true tip from the intended polyline (m)."""
        return float(np.max(distance_to_polyline(self.tip, self.path))) if len(self.tip) else 0.0

    def to_json(self) -> dict:
        return {"steps": self.steps, "final_error": self.final_error, "max_deviation": self.max_deviation,
                "max_phi": self.max_phi, "monotonic": self.monotonic, "status": self.status,
                "converged": self.converged}


def distance_to_polyline(pts: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Distance (n,) from points (n, d) to a polyline (m, d)."""
    pts = np.asarray(pts, float)
    path = np.asarray(path, float)
    if len(path) == 1:
        return np.linalg.norm(pts - path[0], axis=-1)
    a, b = path[:-1], path[1:]
    ab = b - a
    L2 = np.maximum(np.sum(ab * ab, axis=-1), 1e-300)
    t = np.clip(np.einsum("nmi,mi->nm", pts[:, None, :] - a[None], ab) / L2, 0.0, 1.0)
    proj = a[None] + t[..., None] * ab[None]
    return np.min(np.linalg.norm(pts[:, None, :] - proj, axis=-1), axis=1)


# ----------------------------------------------------------------------------- simulate
def plant_at(plant: Plant, q_true: np.ndarray):
    """A view of the plant whose end poses are those at the true joint angles (flexion sensing)."""

    class _AtTrue:
        def end_poses(self, _q):
            return plant.end_poses(q_true)

    return _AtTrue()


def delayed_tip(times, tips, tau: float):
    """``tracker_latency`` (docs/physics.md): the true tip at ``times[-1] - tau`` from the steps so far
    (``times`` increasing scalars, ``tips`` arrays (..., d) at them), linear in time between two
    steps, the first step's before it (:func:`errplan.effects.delayed` for recorded rows)."""
    s = times[-1] - tau
    if s <= times[0]:
        return tips[0]
    k = len(times) - 1
    while times[k - 1] > s:
        k -= 1
    t0, t1 = times[k - 1], times[k]
    w = (s - t0) / (t1 - t0) if t1 > t0 else 1.0
    return tips[k - 1] + min(max(w, 0.0), 1.0) * (tips[k] - tips[k - 1])


def simulate(plant: Plant, controller: ControllerModel, q0: np.ndarray, waypoints, gains, *,
             tolerance: float = 1e-5, max_steps: int = 2000, rng: np.random.Generator | None = None,
             path_start=None, switch_tolerance: float | None = None, model: Plant | None = None,
             times=None, lost=None, glitch=None) -> SimResult:
    """Drive the tip through ``waypoints`` (m, d) with per-segment ``gains`` (m,).

    The controller aims at waypoint ``i`` until the tracked tip is within ``tolerance`` of it, then
    switches to the next (``switch_tolerance``, default ``tolerance``, for the intermediate
    waypoints; ``tolerance`` for the last one). ``rng`` adds the plant's measurement noise (None: noise-free).
    Stops early (status ``left_workspace``) if a command leaves the joint limits or pulls the
    shaft out of the port; ``max_steps`` bounds the total number of commands.

    Port friction (docs/physics.md): the state after a command holds the tip back against ``u``,
    the unit direction of ``x_model(q + dq) - x_model(q)`` — the motion the command produces
    under the declared ``model`` (default ``plant.declared()``: the plant's arm, shaft, tip load
    and declared port, no effects), ``q`` the encoder reading the command started from. ``u``
    keeps its last value when a command produces no motion; the state before the first command
    has ``u = 0``. (errplan used to take ``u`` as the desired direction ``target - tracked tip``.
    That was wrong wherever the controller's Jacobian is wrong: friction opposes the motion that
    happens, and the two directions differ by up to phi_max.)

    A bench as it records (docs/physics.md "Measured data as a bench records it"): the plant's
    ``tracker_latency`` tau makes the tracker read the true tip at the step's time - tau (linear in
    time between steps, :func:`delayed_tip`); ``times`` (max_steps + 1,) the steps' times in tau's
    unit (default: the step index times the plant's ``step_duration``). ``lost`` (max_steps + 1,) bool: the tracker sees nothing at
    that step (a dropout: the result's ``tracked`` is NaN there and the controller reads the last
    tracked tip, zero-order hold; before the first tracked step it commands nothing). ``glitch``
    (max_steps + 1, d): added to the tracker's reading (outliers; the controller reads them too).
    """
    from .inputs import check_allocation
    wp = np.atleast_2d(np.asarray(waypoints, float))
    gains = np.broadcast_to(np.asarray(gains, float), (len(wp),))
    if np.any(~np.isfinite(gains)) or np.any(gains <= 0):
        raise ErrplanError(f"gains {gains.tolist()}: expected finite numbers > 0")
    switch_tol = float(tolerance if switch_tolerance is None else switch_tolerance)
    if not (tolerance > 0 and switch_tol > 0 and np.isfinite(tolerance) and np.isfinite(switch_tol)):
        raise ErrplanError(f"tolerance {tolerance!r} / switch_tolerance {switch_tolerance!r}: expected lengths > 0 m")
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 0:
        raise ErrplanError(f"max_steps {max_steps!r}: expected an integer >= 0")
    # per step: the state lists (q, tip, tracked, target, segment, gain) and the final arrays
    check_allocation("max_steps", max_steps, max_steps + 1, 768, "the simulated run")
    model = plant.declared() if model is None else model
    q = np.asarray(q0, float).copy()
    if not plant.arm.within_limits(plant.link_angles_q(q)):
        raise ErrplanError(f"start configuration {q.tolist()} is outside the joint limits")
    d = len(np.asarray(plant.port))
    if wp.shape[-1] != d:
        raise ErrplanError(f"waypoints of shape {wp.shape}: expected (m, {d}) points of the plant's space")
    u = np.zeros(d)
    q_true = q.copy()  # the joints' commanded (reached) angles; q holds the encoder reading
    b = np.asarray(getattr(plant, "backlash", ()), float)
    play = b.size > 0 and bool(np.any(b))
    theta = q_true.copy()  # the links behind the play (docs/physics.md backlash): mid-band at the start
    tip = plant.tip(q_true, u)
    Q, T, X, TG, SEG, K, L = [], [], [], [], [], [], []
    seg = 0
    status = "max_steps"
    tau = float(np.asarray(getattr(plant, "tracker_latency", (0.0,)) or (0.0,), float)[0])
    hist_t: list = []
    hist_x: list = []
    held = None  # the last tracked tip the controller read (dropouts: zero-order hold)
    for k in range(max_steps + 1):
        if tau:
            hist_t.append(float(times[k]) if times is not None else k * float(getattr(plant, "step_duration", 1.0)))
            hist_x.append(tip.copy())
            tracked = plant.tracked(delayed_tip(hist_t, hist_x, tau))
        else:
            tracked = plant.tracked(tip)
        if rng is not None and plant.tracker_sigma > 0:
            tracked = tracked + rng.normal(0.0, plant.tracker_sigma, d)
        if glitch is not None:
            tracked = tracked + glitch[k]
        if lost is not None and lost[k]:
            reading, tracked = held, np.full(d, np.nan)
        else:
            reading = held = tracked
        # switch targets on convergence
        while reading is not None and seg < len(wp) - 1 and np.linalg.norm(wp[seg] - reading) < switch_tol:
            seg += 1
        Q.append(q.copy()); T.append(tip.copy()); X.append(tracked.copy()); L.append(plant.tracked(tip))
        TG.append(wp[seg].copy()); SEG.append(seg); K.append(gains[seg])
        err = wp[seg] - reading if reading is not None else np.zeros(d)  # nothing tracked yet: no command
        if reading is not None and seg == len(wp) - 1 and np.linalg.norm(err) < tolerance:
            status = "converged"
            break
        if len(Q) > max_steps:
            break
        Jh = controller.J_hat(q, plant if controller.jacobian == "rigid" else plant_at(plant, q_true), rng)
        Jinv, singular = inv(Jh)
        if singular:
            status = "left_workspace"
            break
        dq = gains[seg] * (Jinv @ err)
        q_new = q + dq
        if rng is not None and plant.encoder_sigma > 0:
            q_read = q_new + rng.normal(0.0, plant.encoder_sigma, q_new.shape)
        else:
            q_read = q_new
        # the motion this command produces under the declared model (friction opposes it)
        u = model.motion_direction(q, q_new, u)
        w = plant.wrist(q_new)
        if not plant.arm.within_limits(plant.link_angles_q(q_new)) or not plant.shaft_reaches(w):
            status = "left_workspace"
            break
        q, q_true = q_read, q_new
        if play:
            theta = np.clip(theta, q_true - b, q_true + b)
        tip = plant.tip(theta if play else q_true, u)
    start = np.asarray(path_start if path_start is not None else T[0], float)
    return SimResult(np.array(Q), np.array(T), np.array(X), np.array(TG), np.array(SEG), np.array(K),
                     np.vstack([start[None], wp]), status == "converged", status, tolerance, np.array(L))


def g_norm_along(result: SimResult, plant: Plant, controller: ControllerModel) -> np.ndarray:
    """Actual ``||G|| = ||I - k J Jhat^-1||`` (steps,) at each state a command was issued from.

    ``J`` is the plant's true Jacobian at the encoder angles (no friction), ``Jhat`` the
    controller's (flexion: noise-free end poses). Useful beside :attr:`SimResult.monotonic`:
    to first order the error length can only grow at a step where this exceeds 1.
    """
    n = result.steps
    if n == 0:
        return np.zeros(0)
    q = result.q[:n]
    J = plant.true_jacobian(q)
    if controller.jacobian == "rigid":
        Jh = controller.J_hat(q)
    else:
        Jh = np.stack([controller.J_hat(qi, plant_at(plant, qi)) for qi in q])
    Jinv, singular = inv(Jh)
    d = J.shape[-1]
    G = np.eye(d) - result.gain[:n, None, None] * (J @ Jinv)
    g = spectral_norm(G)
    return np.where(singular | ~np.isfinite(g), np.inf, g)
