"""The true robot: the declared arm and shaft plus the effects of docs/physics.md ("Effects a real
bench shows"), each with its fixed parametrization. Used by the worst-case fields (a scenario's
``[effects]`` are part of its truth), the simulator, the bench-run generator and calibration.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import ErrplanError
from .arm import Arm, angle_of, direction, direction_derivative
from .shaft import flexed_end_angles, flexed_geometry, flexed_jacobian, flexed_wrist

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
        t = np.broadcast_to(np.asarray(self.load, float), np.shape(w)[:-1]).copy()
        if any(self.world_load):
            n = direction_derivative(angle_of(self.true_port - w))
            t = t + n @ np.asarray(self.world_load, float)
        return t

    def shaft_reaches(self, w: np.ndarray) -> np.ndarray:
        r = np.linalg.norm(self.true_port - np.asarray(w, float), axis=-1)
        return (r > 1e-9) & (r < self.length)

    def declared(self) -> "Plant":
        """The declared model under this plant: its arm, shaft, tip load and ``port`` (the declared
        port position), without any effect and without noise."""
        return Plant(self.arm, self.length, self.port, self.load)

    def model_tip(self, q: np.ndarray) -> np.ndarray:
        """``x_model(q)`` of docs/physics.md ``port_friction``: the declared model's tip (..., 2) at
        joint angles ``q`` (arm, shaft with the plant's tip load, ``port``; no effects). Friction's
        direction ``u`` is the direction of ``x_model(q + dq) - x_model(q)``."""
        q = np.asarray(q, float)
        w = self.arm.forward(q)
        t = np.broadcast_to(np.asarray(self.load, float), np.shape(w)[:-1])
        return flexed_geometry(w, np.asarray(self.port, float), self.length, t)["tip"]

    def motion_direction(self, q_from: np.ndarray, q_to: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Friction's ``u`` (..., 2) for a joint command from ``q_from`` to ``q_to``: the unit
        direction of ``x_model(q_to) - x_model(q_from)``, or ``u_prev`` where the command produces
        no motion (see :func:`motion_direction`)."""
        return motion_direction(self.model_tip(q_from), self.model_tip(q_to), u_prev)

    def tip(self, q_enc: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """True tip (..., 2) for encoder angles; ``u`` the unit direction of the tip motion the
        last joint command produced under the declared model (:meth:`motion_direction`; port
        friction holds the tip back against it; ``u = 0`` before the first command)."""
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


def motion_direction(x_from: np.ndarray, x_to: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
    """Unit direction (..., 2) of ``x_to - x_from`` (declared-model tips before and after a joint
    command); where the command moves nothing (a zero or non-finite difference), ``u_prev``: u
    keeps its last value (docs/physics.md ``port_friction``)."""
    d = np.asarray(x_to, float) - np.asarray(x_from, float)
    n = np.sqrt(np.sum(d * d, axis=-1, keepdims=True))
    moved = (n > 0) & np.isfinite(n)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(moved, d / np.where(moved, n, 1.0), np.asarray(u_prev, float))


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
