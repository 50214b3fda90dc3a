"""The true robot: the declared arm and shaft plus the effects of docs/physics.md ("Effects a real
bench shows"), each with its fixed parametrization. Used by the worst-case fields (a scenario's
``[effects]`` are part of its truth), the simulator, the bench-run generator and calibration.

One class for both dimensions (docs/physics.md "Spatial robots"): the arm is P1's planar
:class:`~errplan.kinematics.arm.Arm` (points ``[y, z]``, the planar closed forms, unchanged) or a
:class:`~errplan.kinematics.urdf.UrdfArm` (points ``[x, y, z]``). In 3-D the shaft is the lever,
bent by a constant world-frame load when there is one; the effects take their spatial
parametrization (``port_offset`` dx, dy, dz; ``joint_offset`` dq1..dqN; ``tracker_offset`` bx, by,
bz; ``gravity_sag`` c1..cN against the URDF's generalized gravity; ``shaft_flexion`` fx, fy, fz;
``port_friction`` fa, fn with the whole normal part of the motion).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from ..errors import ErrplanError
from ..scenario import joint_geometry_keys
from .arm import Arm, angle_of, direction, direction_derivative
from .shaft import flexed_end_angles, flexed_end_directions, flexed_geometry, flexed_jacobian, flexed_tip, flexed_wrist, lever_wrist

#: a scalar tip load in 3-D is this world direction times the load (docs/pipeline.md): gravity-like
SPATIAL_LOAD_DIRECTION = (0.0, -1.0, 0.0)
#: Newton iterations for the 3-D wrist under a constant world load (quadratic convergence from the lever)
WRIST_NEWTON_ITERS = 12

@dataclass(frozen=True)
class Plant:
    """The true robot: declared arm and shaft plus the effects of docs/physics.md.

    Parameters (SI, the fixed parametrization of physics.md "Effects"): ``port`` the true port
    (before ``port_offset``); ``load`` a lateral tip load over EI in the shaft frame (1/m^2, an
    error-set instance); ``joint_offset`` [dq1, dq2]; ``tracker_offset`` [by, bz];
    ``gravity_sag`` [c1, c2, c3]; ``world_load`` [fy, fz] (shaft_flexion); ``friction`` [fa, fn]
    (port_friction); ``tracker_sigma`` / ``encoder_sigma`` measurement noise (std).

    Spatial (a :class:`~errplan.kinematics.urdf.UrdfArm`): ``port`` and the offsets are 3-vectors,
    ``joint_offset`` and ``gravity_sag`` have one value per actuated joint (the sag is
    ``diag(c) tau_g(q_enc)``), ``world_load`` is [fx, fy, fz], and ``load`` is a world-frame load
    vector over EI (3,) or a number ``t`` meaning ``t * SPATIAL_LOAD_DIRECTION``; the shaft bends
    under the part of the total world load normal to the wrist->port line. Zero planar defaults
    are resized to the arm's dimension, so ``Plant(urdf_arm, L, port)`` is a plant without effects.
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
    link_length: tuple[float, ...] = (0.0, 0.0)
    instrument_length: tuple[float] = (0.0,)
    tracker_rotation: tuple[float, ...] = (0.0,)
    joint_geometry: tuple[float, ...] = ()
    backlash: tuple[float, ...] = (0.0, 0.0)
    #: ``tracker_latency`` tau: the tracked tip of a row is the true tip at the row's time - tau (the
    #: time unit of the rows: seconds, or steps without a time column); see
    #: :func:`errplan.effects.delayed`
    tracker_latency: tuple[float] = (0.0,)
    #: a controller step's duration in tracker_latency's unit: ``[sensors] step_time`` when tau is in
    #: seconds, 1 when it is in steps; a simulation given no times steps by it
    step_duration: float = 1.0

    def __post_init__(self):
        if isinstance(self.arm, Arm):
            sizes = (("link_length", 2), ("instrument_length", 1), ("tracker_rotation", 1), ("joint_geometry", 0),
                     ("backlash", 2), ("tracker_latency", 1))
        else:
            d, n = 3, int(self.arm.n)
            sizes = (("port_offset", d), ("tracker_offset", d), ("world_load", d), ("joint_offset", n),
                     ("gravity_sag", n), ("link_length", 0), ("instrument_length", 1), ("tracker_rotation", 3),
                     ("joint_geometry", 6 * n + 3), ("backlash", n), ("tracker_latency", 1))
        for name, size in sizes:
            v = tuple(float(x) for x in getattr(self, name))
            if name == "joint_geometry" and size and len(v) == size - 3:
                v = v + (0.0, 0.0, 0.0)  # the joints' six each only: the wrist link's origin unmoved
                object.__setattr__(self, name, v)
            if len(v) != size:
                if any(v):
                    raise ErrplanError(f"Plant {name} = {list(v)}: expected {size} values for the "
                                       f"{'planar' if self.dim == 2 else 'spatial'} arm")
                object.__setattr__(self, name, (0.0,) * size)
        if self.length + self.instrument_length[0] <= 0:
            raise ErrplanError(f"Plant instrument_length {self.instrument_length[0]}: the instrument would be "
                               f"{self.length + self.instrument_length[0]:.4g} m long")

    @cached_property
    def true_arm(self):
        """The arm as it is: the declared arm with ``link_length`` (planar) or ``joint_geometry``
        (URDF) applied (:func:`errplan.kinematics.geometry.perturbed_arm`)."""
        from .geometry import perturbed_arm

        return perturbed_arm(self.arm, self.link_length, self.joint_geometry)

    @property
    def true_length(self) -> float:
        """The instrument's true length: declared + ``instrument_length``."""
        return float(self.length + self.instrument_length[0])

    def tracked(self, tip: np.ndarray) -> np.ndarray:
        """What the tracker reads (noise-free) for true tips (..., d): ``R(r) tip + b``
        (``tracker_registration``; ``tracker_offset`` is its ``b`` with ``r = 0``). Planar: ``r`` is the
        rotation about the world x axis, turning ``[y, z]`` to ``[c y - s z, s y + c z]``."""
        tip = np.asarray(tip, float)
        b = np.asarray(self.tracker_offset, float)
        r = np.asarray(self.tracker_rotation, float)
        if not np.any(r):
            return tip + b
        if self.dim == 2:
            c, s = np.cos(r[0]), np.sin(r[0])
            R = np.array([[c, -s], [s, c]])
        else:
            from .geometry import rotation_vector_matrix

            R = rotation_vector_matrix(r)
        return tip @ R.T + b

    @classmethod
    def from_model(cls, m, *, port=None, load=0.0, effects=True, noise: bool = False) -> "Plant":
        """The truth of an arm's model (:class:`errplan.models.ArmModel`, its arm built once):
        ``port.position`` (or ``port``), with the ``[effects]`` (``effects`` True; a mapping: those effect
        tables instead; False: none) and optionally the sensor noise."""
        sc = m.scenario
        tables = sc.effects if effects is True else (effects or {})
        if m.dim == 3:
            kw = effect_kwargs(tables, 3, m.arm.n) if tables else {}
            ld = tuple(float(v) for v in np.broadcast_to(np.asarray(load, float), (3,))) if np.ndim(load) else float(load)
        else:
            kw = effect_kwargs(tables) if tables else {}
            ld = float(load)
        step = getattr(sc.sensors, "step_time", None)
        return cls(m.arm, sc.instrument.length, tuple(sc.port.position if port is None else port), ld,
                   tracker_sigma=sc.sensors.tracker_sigma if noise else 0.0,
                   encoder_sigma=sc.sensors.encoder_sigma if noise else 0.0,
                   step_duration=float(step) if step is not None else 1.0, **kw)

    @property
    def dim(self) -> int:
        """2 for P1's planar arm, 3 for a URDF arm."""
        return 2 if isinstance(self.arm, Arm) else 3

    @property
    def load_vector(self) -> np.ndarray:
        """The instance load as a world vector (3,) (3-D only)."""
        if np.ndim(self.load):
            return np.asarray(self.load, float)
        return float(self.load) * np.asarray(SPATIAL_LOAD_DIRECTION)

    def with_(self, **changes) -> "Plant":
        return replace(self, **changes)

    @property
    def true_port(self) -> np.ndarray:
        return np.asarray(self.port, float) + np.asarray(self.port_offset, float)

    def link_angles_q(self, q_enc: np.ndarray) -> np.ndarray:
        """Joint angles of the links (after joint offset and gravity sag) for encoder angles."""
        q = np.asarray(q_enc, float) + np.asarray(self.joint_offset, float)
        if self.dim == 3:
            if any(self.gravity_sag):  # diag(c) tau_g(q_enc), the URDF's generalized gravity
                q = q - np.asarray(self.gravity_sag, float) * self.arm.gravity_torque(np.asarray(q_enc, float))
            return q
        c1, c2, c3 = self.gravity_sag
        if c1 or c2 or c3:
            a1, a2 = self.arm.link_angles(np.asarray(q_enc, float))
            sag = np.stack([c1 * np.cos(a1) + c2 * np.cos(a2), c3 * np.cos(a2)], axis=-1)
            q = q - sag
        return q

    def wrist(self, q_enc: np.ndarray) -> np.ndarray:
        return self.true_arm.forward(self.link_angles_q(q_enc))

    def shaft_load(self, w: np.ndarray) -> np.ndarray:
        """Lateral load over EI: the instance load plus the world load's component normal to wrist->port.
        In 3-D: the total world load vector (..., 3) (the shaft model takes its normal part)."""
        if self.dim == 3:
            t = self.load_vector + np.asarray(self.world_load, float)
            return np.broadcast_to(t, np.shape(w)).copy()
        t = np.broadcast_to(np.asarray(self.load, float), np.shape(w)[:-1]).copy()
        if any(self.world_load):
            n = direction_derivative(angle_of(self.true_port - w))
            t = t + n @ np.asarray(self.world_load, float)
        return t

    def shaft_reaches(self, w: np.ndarray) -> np.ndarray:
        r = np.linalg.norm(self.true_port - np.asarray(w, float), axis=-1)
        return (r > 1e-9) & (r < self.true_length)

    def declared(self) -> "Plant":
        """The declared model under this plant: its arm, shaft, tip load and ``port`` (the declared
        port position), without any effect and without noise."""
        return Plant(self.arm, self.length, tuple(self.port), self.load)

    def model_tip(self, q: np.ndarray) -> np.ndarray:
        """``x_model(q)`` of docs/physics.md ``port_friction``: the declared model's tip (..., 2) at
        joint angles ``q`` (arm, shaft with the plant's tip load, ``port``; no effects). Friction's
        direction ``u`` is the direction of ``x_model(q + dq) - x_model(q)``."""
        q = np.asarray(q, float)
        w = self.arm.forward(q)
        if self.dim == 3:
            return flexed_tip(w, np.asarray(self.port, float), self.length, self.load_vector)
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
        if self.dim == 3:
            tip = flexed_tip(w, self.true_port, self.true_length, self.shaft_load(w))
            fa, fn = self.friction
            if (fa or fn) and u is not None:
                # s: the shaft axis wrist -> tip (the chord); the normal part is all of u normal to s
                s = (tip - w) / self.true_length
                u = np.asarray(u, float)
                us = np.sum(u * s, axis=-1, keepdims=True)
                tip = tip - (fa * us * s + fn * (u - us * s))
            return tip
        g = flexed_geometry(w, self.true_port, self.true_length, self.shaft_load(w))
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
        """True wrist, tip and end tangents (what P2's flexion controller measures): in the plane the
        tangents' angles (rad), in 3-D their unit directions (..., 3) (docs/physics.md "P2's flexion
        controller in 3-D")."""
        w = self.wrist(q_enc)
        if self.dim == 3:
            tip, dw, dt = flexed_end_directions(w, self.true_port, self.true_length, self.shaft_load(w))
            return w, tip, dw, dt
        tip, thw, tht = flexed_end_angles(w, self.true_port, self.true_length, self.shaft_load(w))
        return w, tip, thw, tht

    def true_jacobian(self, q_enc: np.ndarray) -> np.ndarray:
        """``d tip / d q`` of the truth without friction (..., 2, 2)."""
        q = self.link_angles_q(q_enc)
        w = self.true_arm.forward(q)
        J_tw = flexed_jacobian(w, self.true_port, self.true_length, self.shaft_load(w))
        return J_tw @ self.true_arm.jacobian(q)

    def configuration_for_tip(self, x: np.ndarray) -> np.ndarray:
        """Encoder angles putting the true tip at ``x`` (no effects other than port/load)."""
        x = np.asarray(x, float)
        w = self.true_wrist_for_tip(x) if self.dim == 3 else flexed_wrist(x, self.true_port, self.true_length, self.load)
        q, ok = self.true_arm.inverse(w)
        if not np.all(ok) or not np.all(self.shaft_reaches(w)):
            raise ErrplanError(f"tip {np.round(x, 5).tolist()} is not reachable by the true robot "
                               f"(port {np.round(self.true_port, 5).tolist()}, shaft {self.true_length} m)")
        return q - np.asarray(self.joint_offset)

    def true_wrist_for_tip(self, x: np.ndarray) -> np.ndarray:
        """3-D: the wrist (..., 3) that puts the true tip at ``x`` through the true port under the
        plant's world load (the lever wrist without one; else Newton on ``flexed_tip(w) = x``,
        started at the lever wrist)."""
        x = np.asarray(x, float)
        p = self.true_port
        w = lever_wrist(x, p, self.true_length)
        t = self.shaft_load(w)
        if not np.any(t):
            return w
        for _ in range(WRIST_NEWTON_ITERS):
            f = flexed_tip(w, p, self.true_length, t) - x
            if np.all(np.abs(f) < 1e-13):
                break
            J = flexed_jacobian(w, p, self.true_length, t)
            w = w - np.linalg.solve(J, f[..., None])[..., 0]
        return w


def motion_direction(x_from: np.ndarray, x_to: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
    """Unit direction (..., 2) of ``x_to - x_from`` (declared-model tips before and after a joint
    command); where the command moves nothing (a zero or non-finite difference), ``u_prev``: u
    keeps its last value (docs/physics.md ``port_friction``)."""
    d = np.asarray(x_to, float) - np.asarray(x_from, float)
    n = np.sqrt(np.sum(d * d, axis=-1, keepdims=True))
    moved = (n > 0) & np.isfinite(n)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(moved, d / np.where(moved, n, 1.0), np.asarray(u_prev, float))


def effect_kwargs(effects, dim: int | None = None, n_joints: int | None = None) -> dict:
    """Plant keyword arguments for a mapping ``{effect: {param: value}}`` (physics.md names).

    ``dim`` 3 (or spatial parameter names such as ``dx``, ``bx``, ``fx``, ``dq3``): the spatial
    parametrization, one value per axis or per actuated joint (``n_joints``, default 3)."""
    if dim is None:
        spatial = any(k in ("dx", "bx", "fx", "ry", "rz") or "_" in k
                      or (k[:1] == "b" and k[1:].isdigit() and int(k[1:]) > 2)
                      or (k[:2] == "dq" and k[2:].isdigit() and int(k[2:]) > 2)
                      for p in (effects or {}).values() for k in p)
        dim = 3 if spatial else 2
    if dim == 3:
        n = int(n_joints or 3)
        names = {"port_offset": ("port_offset", ("dx", "dy", "dz")),
                 "joint_offset": ("joint_offset", tuple(f"dq{i + 1}" for i in range(n))),
                 "tracker_offset": ("tracker_offset", ("bx", "by", "bz")),
                 "gravity_sag": ("gravity_sag", tuple(f"c{i + 1}" for i in range(n))),
                 "shaft_flexion": ("world_load", ("fx", "fy", "fz")),
                 "port_friction": ("friction", ("fa", "fn")),
                 "instrument_length": ("instrument_length", ("dL",)),
                 "joint_geometry": ("joint_geometry", joint_geometry_keys(n)),
                 "backlash": ("backlash", tuple(f"b{i + 1}" for i in range(n))),
                 "tracker_latency": ("tracker_latency", ("tau",))}
        out3: dict = {}
        for name, p in (effects or {}).items():
            if name == "tracker_registration":
                out3["tracker_rotation"] = tuple(float(p.get(k, 0.0)) for k in ("rx", "ry", "rz"))
                b = tuple(float(p.get(k, 0.0)) for k in ("bx", "by", "bz"))
                out3["tracker_offset"] = tuple(a + c for a, c in zip(out3.get("tracker_offset", (0.0,) * 3), b))
                continue
            if name not in names:
                raise ErrplanError(f"effect {name!r}: not an effect of docs/physics.md")
            fld, params = names[name]
            v = tuple(float(p.get(k, 0.0)) for k in params)
            if name == "tracker_offset":
                v = tuple(a + c for a, c in zip(out3.get("tracker_offset", (0.0,) * 3), v))
            out3[fld] = v
        return out3
    out: dict = {}
    for name, p in (effects or {}).items():
        if name == "port_offset":
            out["port_offset"] = (p.get("dy", 0.0), p.get("dz", 0.0))
        elif name == "joint_offset":
            out["joint_offset"] = (p.get("dq1", 0.0), p.get("dq2", 0.0))
        elif name == "tracker_offset":
            b = out.get("tracker_offset", (0.0, 0.0))
            out["tracker_offset"] = (b[0] + p.get("by", 0.0), b[1] + p.get("bz", 0.0))
        elif name == "tracker_registration":
            b = out.get("tracker_offset", (0.0, 0.0))
            out["tracker_offset"] = (b[0] + p.get("by", 0.0), b[1] + p.get("bz", 0.0))
            out["tracker_rotation"] = (p.get("rx", 0.0),)
        elif name == "link_length":
            out["link_length"] = (p.get("dl1", 0.0), p.get("dl2", 0.0))
        elif name == "instrument_length":
            out["instrument_length"] = (p.get("dL", 0.0),)
        elif name == "backlash":
            out["backlash"] = (p.get("b1", 0.0), p.get("b2", 0.0))
        elif name == "gravity_sag":
            out["gravity_sag"] = (p.get("c1", 0.0), p.get("c2", 0.0), p.get("c3", 0.0))
        elif name == "shaft_flexion":
            out["world_load"] = (p.get("fy", 0.0), p.get("fz", 0.0))
        elif name == "port_friction":
            out["friction"] = (p.get("fa", 0.0), p.get("fn", 0.0))
        elif name == "tracker_latency":
            out["tracker_latency"] = (p.get("tau", 0.0),)
        else:
            raise ErrplanError(f"effect {name!r}: not an effect of docs/physics.md")
    return out
