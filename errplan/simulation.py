"""Quasi-static simulation of the inverse-Jacobian controller (P1 eqs. 1-5, P2 eq. 4).

At each step the controller reads the tracked tip ``x`` and the encoder angles ``q`` and commands
``q + k Jhat(q)^-1 (x_d - x)``; quasi-statically the joints reach the command before the next
step. ``Jhat`` comes from the controller's *model* (:class:`ControllerModel`: rigid lever through
the port estimate, or P2's flexion model fed by measured end poses); the motion comes from the
*truth* (:class:`Plant`: true port, tip load, and any effects of docs/physics.md).

This module imports neither ompl nor casadi nor rerun.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .errors import ErrplanError
from .kinematics.arm import Arm, angle_of, direction, direction_derivative
from .kinematics.shaft import (estimate_from_ends, flexed_end_angles, flexed_geometry, flexed_jacobian,
                               flexed_wrist, lever_jacobian)
from .metrics import inv2


# ----------------------------------------------------------------------------- truth
@dataclass(frozen=True)
class Plant:
    """The true robot: declared arm and shaft plus the effects of docs/physics.md.

    Parameters (SI, the fixed parametrization of physics.md "Effects"): ``port`` the true port
    (before ``port_offset``); ``load`` a lateral tip load over EI in the shaft frame (1/m^2, an
    error-set instance); ``joint_offset`` [dq1, dq2]; ``tracker_offset`` [by, bz];
    ``gravity_sag`` [c1, c2, c3]; ``world_load`` [fy, fz] (shaft_flexion); ``friction`` [fa, fn]
    (port_friction); ``tracker_sigma`` / ``encoder_sigma`` measurement noise (std).
    """

    arm: Arm
    length: float
    port: tuple[float, float]
    load: float = 0.0
    port_offset: tuple[float, float] = (0.0, 0.0)
    joint_offset: tuple[float, float] = (0.0, 0.0)
    tracker_offset: tuple[float, float] = (0.0, 0.0)
    gravity_sag: tuple[float, float, float] = (0.0, 0.0, 0.0)
    world_load: tuple[float, float] = (0.0, 0.0)
    friction: tuple[float, float] = (0.0, 0.0)
    tracker_sigma: float = 0.0
    encoder_sigma: float = 0.0

    @classmethod
    def from_scenario(cls, sc, *, port=None, load: float = 0.0, effects: bool = True, noise: bool = False) -> "Plant":
        """The scenario's truth (``port.position``), optionally with its ``[effects]`` and sensor noise."""
        kw = effect_kwargs(sc.effects) if effects else {}
        return cls(Arm.from_robot(sc.robot), sc.instrument.length,
                   tuple(sc.port.position if port is None else port), float(load),
                   tracker_sigma=sc.sensors.tracker_sigma if noise else 0.0,
                   encoder_sigma=sc.sensors.encoder_sigma if noise else 0.0, **kw)

    def with_(self, **changes) -> "Plant":
        return replace(self, **changes)

    @property
    def true_port(self) -> np.ndarray:
        return np.asarray(self.port, float) + np.asarray(self.port_offset, float)

    def link_angles_q(self, q_enc: np.ndarray) -> np.ndarray:
        """Joint angles of the links (after joint offset and gravity sag) for encoder angles."""
        q = np.asarray(q_enc, float) + np.asarray(self.joint_offset, float)
        c1, c2, c3 = self.gravity_sag
        if c1 or c2 or c3:
            a1, a2 = self.arm.link_angles(np.asarray(q_enc, float))
            sag = np.stack([c1 * np.cos(a1) + c2 * np.cos(a2), c3 * np.cos(a2)], axis=-1)
            q = q - sag
        return q

    def wrist(self, q_enc: np.ndarray) -> np.ndarray:
        return self.arm.forward(self.link_angles_q(q_enc))

    def shaft_load(self, w: np.ndarray) -> np.ndarray:
        """Lateral load over EI: the instance load plus the world load's component normal to wrist->port."""
        t = np.full(np.shape(w)[:-1], float(self.load))
        if any(self.world_load):
            n = direction_derivative(angle_of(self.true_port - w))
            t = t + n @ np.asarray(self.world_load, float)
        return t

    def shaft_reaches(self, w: np.ndarray) -> np.ndarray:
        r = np.linalg.norm(self.true_port - np.asarray(w, float), axis=-1)
        return (r > 1e-9) & (r < self.length)

    def tip(self, q_enc: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """True tip (..., 2) for encoder angles; ``u`` the unit commanded tip-motion direction
        (port friction holds the tip back against it)."""
        w = self.wrist(q_enc)
        g = flexed_geometry(w, self.true_port, self.length, self.shaft_load(w))
        tip = g["tip"]
        fa, fn = self.friction
        if (fa or fn) and u is not None:
            s = direction(g["phi"])
            n = direction_derivative(g["phi"])
            u = np.asarray(u, float)
            us = np.sum(u * s, axis=-1, keepdims=True)
            un = np.sum(u * n, axis=-1, keepdims=True)
            tip = tip - (fa * us * s + fn * un * n)
        return tip

    def end_poses(self, q_enc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """True wrist, tip and end tangent angles (what P2's flexion controller measures)."""
        w = self.wrist(q_enc)
        tip, thw, tht = flexed_end_angles(w, self.true_port, self.length, self.shaft_load(w))
        return w, tip, thw, tht

    def true_jacobian(self, q_enc: np.ndarray) -> np.ndarray:
        """``d tip / d q`` of the truth without friction (..., 2, 2)."""
        q = self.link_angles_q(q_enc)
        w = self.arm.forward(q)
        J_tw = flexed_jacobian(w, self.true_port, self.length, self.shaft_load(w))
        return J_tw @ self.arm.jacobian(q)

    def configuration_for_tip(self, x: np.ndarray) -> np.ndarray:
        """Encoder angles putting the true tip at ``x`` (no effects other than port/load)."""
        x = np.asarray(x, float)
        w = flexed_wrist(x, self.true_port, self.length, self.load)
        q, ok = self.arm.inverse(w)
        if not np.all(ok) or not np.all(self.shaft_reaches(w)):
            raise ErrplanError(f"tip {np.round(x, 5).tolist()} is not reachable by the true robot "
                               f"(port {np.round(self.true_port, 5).tolist()}, shaft {self.length} m)")
        return q - np.asarray(self.joint_offset)


def effect_kwargs(effects) -> dict:
    """Plant keyword arguments for a mapping ``{effect: {param: value}}`` (physics.md names)."""
    out: dict = {}
    for name, p in (effects or {}).items():
        if name == "port_offset":
            out["port_offset"] = (p.get("dy", 0.0), p.get("dz", 0.0))
        elif name == "joint_offset":
            out["joint_offset"] = (p.get("dq1", 0.0), p.get("dq2", 0.0))
        elif name == "tracker_offset":
            out["tracker_offset"] = (p.get("by", 0.0), p.get("bz", 0.0))
        elif name == "gravity_sag":
            out["gravity_sag"] = (p.get("c1", 0.0), p.get("c2", 0.0), p.get("c3", 0.0))
        elif name == "shaft_flexion":
            out["world_load"] = (p.get("fy", 0.0), p.get("fz", 0.0))
        elif name == "port_friction":
            out["friction"] = (p.get("fa", 0.0), p.get("fn", 0.0))
        else:
            raise ErrplanError(f"effect {name!r}: not an effect of docs/physics.md")
    return out


# ----------------------------------------------------------------------------- controller
@dataclass(frozen=True)
class ControllerModel:
    """The controller's model: the declared arm and shaft, the port estimate, and ``jacobian``
    ("rigid": lever through ``port_estimate``; "flexion": P2's model fed measured end poses)."""

    arm: Arm
    length: float
    port_estimate: tuple[float, float]
    jacobian: str = "rigid"
    noise: tuple[float, float] = (0.0, 0.0)  # flexion: uniform bounds on (position, angle)

    @classmethod
    def from_scenario(cls, sc) -> "ControllerModel":
        n = sc.uncertainty.sensor_noise
        return cls(Arm.from_robot(sc.robot), sc.instrument.length, tuple(sc.port.estimate),
                   sc.controller.jacobian, (n.position, n.angle) if n else (0.0, 0.0))

    def model_tip(self, q: np.ndarray) -> np.ndarray:
        """Tip the model predicts for encoder angles (rigid lever through the estimate)."""
        from .kinematics.shaft import lever_tip

        return lever_tip(self.arm.forward(q), np.asarray(self.port_estimate), self.length)

    def J_hat(self, q: np.ndarray, plant: Plant | None = None, rng: np.random.Generator | None = None) -> np.ndarray:
        """``Jhat(q)`` (..., 2, 2), tip w.r.t. joints."""
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
            thw = thw + rng.uniform(-ang, ang, np.shape(thw))
            tht = tht + rng.uniform(-ang, ang, np.shape(tht))
        est = estimate_from_ends(w, tip, thw, tht, self.length)
        if not np.all(np.isfinite(est["t"])):
            raise ErrplanError("flexion controller: the end poses do not identify the flexion model (no bending)")
        return flexed_jacobian(w, est["port"], self.length, est["t"]) @ Jr


# ----------------------------------------------------------------------------- results
@dataclass
class SimResult:
    """One simulated run. Arrays have one row per step (step 0 is the state before the first command)."""

    q: np.ndarray          # (n, 2) encoder angles
    tip: np.ndarray        # (n, 2) true tip
    tracked: np.ndarray    # (n, 2) tracked tip
    target: np.ndarray     # (n, 2) active target when this state was read
    segment: np.ndarray    # (n,) index of the active segment
    gain: np.ndarray       # (n,) gain applied from this state
    path: np.ndarray       # (m, 2) the intended path (start, segment ends...)
    converged: bool
    status: str            # "converged" | "max_steps" | "left_workspace"
    tolerance: float

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
        cross = desired[:, 0] * actual[:, 1] - desired[:, 1] * actual[:, 0]
        dot = np.sum(desired * actual, axis=-1)
        moving = (np.linalg.norm(actual, axis=-1) > 1e-12) & (np.linalg.norm(desired, axis=-1) > 1e-12)
        return np.where(moving, np.abs(np.arctan2(cross, dot)), 0.0)

    @property
    def max_phi(self) -> float:
        p = self.phi
        return float(p.max()) if len(p) else 0.0

    @property
    def monotonic(self) -> bool:
        """The distance to the active target never grew (within a numerical slack)."""
        e = self.errors
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
    """Distance (n,) from points (n, 2) to a polyline (m, 2)."""
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


def simulate(plant: Plant, controller: ControllerModel, q0: np.ndarray, waypoints, gains, *,
             tolerance: float = 1e-5, max_steps: int = 2000, rng: np.random.Generator | None = None,
             path_start=None, switch_tolerance: float | None = None) -> SimResult:
    """Drive the tip through ``waypoints`` (m, 2) with per-segment ``gains`` (m,).

    The controller aims at waypoint ``i`` until the tracked tip is within ``tolerance`` of it, then
    switches to the next (``switch_tolerance``, default ``tolerance``, for the intermediate
    waypoints; ``tolerance`` for the last one). ``rng`` adds the plant's measurement noise (None: noise-free).
    Stops early (status ``left_workspace``) if a command leaves the joint limits or pulls the
    shaft out of the port; ``max_steps`` bounds the total number of commands.
    """
    wp = np.atleast_2d(np.asarray(waypoints, float))
    gains = np.broadcast_to(np.asarray(gains, float), (len(wp),))
    if np.any(~np.isfinite(gains)) or np.any(gains <= 0):
        raise ErrplanError(f"gains {gains.tolist()}: expected finite numbers > 0")
    switch_tol = float(tolerance if switch_tolerance is None else switch_tolerance)
    if not (tolerance > 0 and switch_tol > 0 and np.isfinite(tolerance) and np.isfinite(switch_tol)):
        raise ErrplanError(f"tolerance {tolerance!r} / switch_tolerance {switch_tolerance!r}: expected lengths > 0 m")
    q = np.asarray(q0, float).copy()
    if not plant.arm.within_limits(plant.link_angles_q(q)):
        raise ErrplanError(f"start configuration {q.tolist()} is outside the joint limits")
    u = np.zeros(2)
    q_true = q.copy()  # the joints' commanded (reached) angles; q holds the encoder reading
    tip = plant.tip(q_true, u)
    Q, T, X, TG, SEG, K = [], [], [], [], [], []
    seg = 0
    status = "max_steps"
    for _ in range(max_steps + 1):
        tracked = tip + np.asarray(plant.tracker_offset)
        if rng is not None and plant.tracker_sigma > 0:
            tracked = tracked + rng.normal(0.0, plant.tracker_sigma, 2)
        # switch targets on convergence
        while seg < len(wp) - 1 and np.linalg.norm(wp[seg] - tracked) < switch_tol:
            seg += 1
        Q.append(q.copy()); T.append(tip.copy()); X.append(tracked.copy())
        TG.append(wp[seg].copy()); SEG.append(seg); K.append(gains[seg])
        err = wp[seg] - tracked
        if seg == len(wp) - 1 and np.linalg.norm(err) < tolerance:
            status = "converged"
            break
        if len(Q) > max_steps:
            break
        Jh = controller.J_hat(q, plant if controller.jacobian == "rigid" else plant_at(plant, q_true), rng)
        Jinv, singular = inv2(Jh)
        if singular:
            status = "left_workspace"
            break
        dq = gains[seg] * (Jinv @ err)
        q_new = q + dq
        if rng is not None and plant.encoder_sigma > 0:
            q_read = q_new + rng.normal(0.0, plant.encoder_sigma, 2)
        else:
            q_read = q_new
        n = np.linalg.norm(err)
        if n > 0:
            u = err / n  # commanded tip motion under the declared model: k Jhat Jhat^-1 err
        w = plant.wrist(q_new)
        if not plant.arm.within_limits(plant.link_angles_q(q_new)) or not plant.shaft_reaches(w):
            status = "left_workspace"
            break
        q, q_true = q_read, q_new
        tip = plant.tip(q_true, u)
    start = np.asarray(path_start if path_start is not None else T[0], float)
    return SimResult(np.array(Q), np.array(T), np.array(X), np.array(TG), np.array(SEG), np.array(K),
                     np.vstack([start[None], wp]), status == "converged", status, tolerance)


def g_norm_along(result: SimResult, plant: Plant, controller: ControllerModel) -> np.ndarray:
    """Actual ``||G|| = ||I - k J Jhat^-1||`` (steps,) at each state a command was issued from.

    ``J`` is the plant's true Jacobian at the encoder angles (no friction), ``Jhat`` the
    controller's (flexion: noise-free end poses). Useful beside :attr:`SimResult.monotonic`:
    to first order the error length can only grow at a step where this exceeds 1.
    """
    from .metrics import spectral_norm

    n = result.steps
    if n == 0:
        return np.zeros(0)
    q = result.q[:n]
    J = plant.true_jacobian(q)
    if controller.jacobian == "rigid":
        Jh = controller.J_hat(q)
    else:
        Jh = np.stack([controller.J_hat(qi, plant_at(plant, qi)) for qi in q])
    Jinv, singular = inv2(Jh)
    G = np.eye(2) - result.gain[:n, None, None] * (J @ Jinv)
    g = spectral_norm(G)
    return np.where(singular | ~np.isfinite(g), np.inf, g)
