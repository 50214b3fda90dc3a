"""The physics of one error instance, batched in numpy: true wrist, true and controller Jacobians,
conformal parts of ``M = J Jhat^-1`` (planar), including P2's flexion controller and a truth with
``[effects]``. The reference the compiled kernels (:mod:`.kernels`) are tested against."""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np

from ..jit import kernel_array, njit
from ..kinematics.arm import Arm
from ..kinematics.compiled import _reachable_kernel, _wrist2_kernel
from ..kinematics.shaft import (estimate_from_ends, flexed_end_angles, flexed_jacobian, flexed_wrist,
                                flexed_wrist_plane, lever_jacobian, lever_parts, lever_wrist)
from ..kinematics.truth import Plant
from ..metrics import conformal_parts, compose_parts, inv, inv2, inverse_parts
from ..errorset import JACOBIAN_EFFECTS, ErrorSet  # noqa: F401  (JACOBIAN_EFFECTS: re-exported by errplan.fields)


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
    def from_model(cls, m) -> "Evaluator":
        """The planar evaluator of an arm's model (:class:`errplan.models.ArmModel`): its arm, the error
        set with ``port_offset`` folded in (fast path kept) and the truth's other Jacobian effects."""
        return cls(m.arm, m.length, m.estimate, m.jacobian, m.true_errors, dict(m.jacobian_effects))

    def true_wrist(self, x: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Wrist putting the true tip at ``x`` and its validity (reachable, shaft through port).

        Compiled in one pass (:func:`_true_wrist2`) where ``x`` and ``theta`` share their batch shape;
        the operations of :meth:`_true_wrist_numpy` (the reference), the same values."""
        port = self.errors.port(theta)
        t = theta[..., 2]
        x = np.asarray(x, float)
        if not (isinstance(self.arm, Arm) and x.shape[-1:] == (2,) and x.shape == port.shape
                and t.shape == x.shape[:-1]):
            return self._true_wrist_numpy(x, theta)
        w = np.empty(x.shape)
        ok = np.empty(x.shape[:-1], bool)
        _true_wrist2(kernel_array(x).reshape(-1, 2), kernel_array(port).reshape(-1, 2), kernel_array(t).reshape(-1),
                     float(self.length), bool(np.any(t != 0)), self.arm._reach_params(), w.reshape(-1, 2),
                     ok.reshape(-1))
        return w, ok

    def _true_wrist_numpy(self, x: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`true_wrist` in numpy: the reference of the compiled path."""
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
        return self.parts_reach(x, theta)[:3]

    def parts_reach(self, x: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`parts` and the truth's reach of :meth:`true_wrist` (...), the true wrist solved once."""
        if self.effects:
            return self._effect_parts(np.asarray(x, float), np.asarray(theta, float))
        w, ok = self.true_wrist(x, theta)
        reach = ok
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
        return mu, nu, ok, reach

    def parts_tracked(self, y: np.ndarray, theta: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`parts_reach` at the tips whose tracked readings are ``y`` (the loop's frame, what a
        gain certificate's ball is drawn in): the true tips ``R^-1 (y - b)`` of a truth with a tracker
        registration, ``y`` itself otherwise."""
        y = np.asarray(y, float)
        if self.effects and "tracker_rotation" in self.effects:
            y = true_tips(self.plant(np.broadcast_to(theta, y.shape[:-1] + (3,))), y)
        return self.parts_reach(y, theta)

    def plant(self, theta: np.ndarray) -> Plant:
        """The truth of instance(s) ``theta`` with the scenario's effects."""
        out = Plant(self.arm, self.length, self.errors.port(theta), theta[..., 2], **self.effects)
        key = (id(self.arm), out.link_length)  # the true arm, built once per arm and link lengths
        kept = self.__dict__.get("_true_arm")
        if kept is None or kept[0] != key:
            kept = self.__dict__["_true_arm"] = (key, out.true_arm)
        out.__dict__["true_arm"] = kept[1]
        return out

    def effect_configuration(self, x: np.ndarray, theta: np.ndarray):
        """The truth of instances ``theta`` putting its true tip at ``x`` (..., 2): ``(plant, q, ok,
        reach)``, ``q`` the encoder angles by Newton's method on the true forward map (started from the
        true arm's inverse of the true shaft's wrist; 0 where ``ok`` is False), ``ok`` where it
        converged inside the limits with the shaft through the true port, ``reach`` the truth's reach
        (the shaft through the true port and the true arm's inverse of its wrist within the limits)."""
        theta = np.broadcast_to(theta, x.shape[:-1] + (3,))
        plant = self.plant(theta)
        port = plant.true_port
        L = plant.true_length
        d = x - port
        r = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)
        ok = (r > 1e-9) & (r < L)
        xs = np.where(ok[..., None], x, port + [0.0, 0.5 * L])
        if self.closed_form:  # the true shaft's wrist, the true arm's inverse: exact, no Newton
            t = np.where(ok, theta[..., 2], 0.0)
            with np.errstate(invalid="ignore", divide="ignore"):
                w = lever_wrist(xs, port, L) if not np.any(t != 0) else flexed_wrist(xs, port, L, t)
                q_link, ok_ik = plant.true_arm.inverse(np.where(ok[..., None], w, 0.0))
            ok &= ok_ik
            q = np.where(ok[..., None], q_link - np.asarray(plant.joint_offset), 0.0)
            return plant, q, ok, ok.copy()
        with np.errstate(invalid="ignore", divide="ignore"):
            w0 = flexed_wrist(xs, port, L, plant.shaft_load(lever_wrist(xs, port, L)))
            q_link, ok_ik = plant.true_arm.inverse(w0)
            ok &= ok_ik
            reach = ok.copy()
            q = np.where(ok[..., None], q_link - np.asarray(plant.joint_offset), 0.0)
            for _ in range(EFFECT_NEWTON_ITERS):
                f = plant.tip(q) - xs
                J = _fd_jacobian(plant.tip, q)
                Jinv, sing = inv2(J)
                q = q - np.where(sing[..., None], 0.0, np.einsum("...ij,...j->...i", np.nan_to_num(Jinv), f))
            resid = np.linalg.norm(plant.tip(q) - xs, axis=-1)
            ok &= (resid < 1e-10) & self.arm.within_limits(plant.link_angles_q(q))
            ok &= plant.shaft_reaches(plant.wrist(q))
        return plant, np.where(ok[..., None], q, 0.0), ok, reach

    @property
    def closed_form(self) -> bool:
        """True when no effect moves the links against the encoders in a way only Newton's method
        solves (``gravity_sag``, a world tip load): the encoder angles are the true arm's inverse of the
        true shaft's wrist, less ``joint_offset``, and ``J`` is exact (:meth:`true_jacobian`)."""
        return not any(k in self.effects for k in ("gravity_sag", "world_load"))

    def true_jacobian(self, plant: Plant, q: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """``J = d tip / d q_enc`` (..., 2, 2) of the truth at encoder angles ``q``: exact where
        :attr:`closed_form` (the true shaft's Jacobian at the true wrist times the true arm's),
        central differences of the true forward map otherwise."""
        if not self.closed_form:
            return _fd_jacobian(plant.tip, q)
        ql = q + np.asarray(plant.joint_offset)
        w = plant.true_arm.forward(ql)
        t = np.broadcast_to(np.asarray(theta, float)[..., 2], w.shape[:-1])
        Jtw = lever_jacobian(w, plant.true_port, plant.true_length) if not np.any(t != 0) else \
            flexed_jacobian(w, plant.true_port, plant.true_length, t)
        return Jtw @ plant.true_arm.jacobian(ql)

    def effect_controller_jacobian(self, plant: Plant, q: np.ndarray) -> np.ndarray:
        """The controller's ``Jhat`` (..., c, 2, 2) at encoder angles ``q``: its (declared) model at the
        same encoder angles, over the flexion controller's noise corners (``c`` = 1 for the lever)."""
        Jr = self.arm.jacobian(q)
        lever = lever_jacobian(self.arm.forward(q), np.asarray(self.estimate), self.length) @ Jr
        if self.jacobian == "rigid":
            return lever[..., None, :, :]
        w, tip, thw, tht = plant.end_poses(q)
        nc = self.errors.noise_corners()
        pw = w[..., None, :] + nc[:, 0:2]
        est = estimate_from_ends(pw, tip[..., None, :] + nc[:, 2:4], thw[..., None] + nc[:, 4],
                                 tht[..., None] + nc[:, 5], self.length)
        Jh = flexed_jacobian(pw, est["port"], self.length, est["t"]) @ Jr[..., None, :, :]
        return np.where(np.all(np.isfinite(Jh), axis=(-2, -1))[..., None, None], Jh, lever[..., None, :, :])

    def _effect_parts(self, x: np.ndarray, theta: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """General path for a truth with [effects] (joint offsets, gravity sag, world tip load, port
        offset, the arm's ``link_length``, ``instrument_length``, a tracker registration's rotation):
        the arm Jacobian no longer cancels. The encoder angles of :meth:`effect_configuration`, true
        ``J = d tip/d q_enc`` by central differences, ``Jhat`` from the controller's (declared) model
        at the same encoder angles (:meth:`effect_controller_jacobian`), and ``M = R J Jhat^-1`` with
        ``R`` the tracker registration's rotation (the loop closes on the tracked tip ``R x + b``).
        Returns the conformal parts ``(mu, nu)`` (..., c), validity and the truth's reach (...)."""
        plant, q, ok, reach = self.effect_configuration(x, theta)
        with np.errstate(invalid="ignore", divide="ignore"):
            J = self.true_jacobian(plant, q, theta)
            R = tracker_rotation_matrix(plant)
            if R is not None:
                J = R @ J
            Jh_inv, singular = inv2(self.effect_controller_jacobian(plant, q))
            mu, nu = conformal_parts(J[..., None, :, :] @ Jh_inv)
        bad = singular | ~np.isfinite(mu) | ~np.isfinite(nu)
        ok = ok & ~np.any(bad, axis=-1)
        return mu, nu, ok, reach

    def effect_step_ratio(self, target, y: np.ndarray, theta: np.ndarray, k) -> np.ndarray:
        """One controller step on the truth with its [effects], per pair, in the loop's frame: ``y``
        (n, 2) and ``target`` the tracked tip and the target (the tracker's frame, ``R x + b``); the
        true tip ``x = R^-1 (y - b)``, the encoder angles putting it there, ``dq = k Jhat^-1 (target -
        y)`` over the controller's noise corners, the true tip after the step and its tracked reading.
        Returns ``|y' - target| / |y - target|`` (n,), worst over the corners; ``nan`` where the truth
        cannot reach ``x``, ``inf`` where the step leaves the limits, pulls the shaft out of the port or
        the controller's Jacobian is singular."""
        y = np.asarray(y, float)
        theta = np.asarray(theta, float)
        b = np.broadcast_to(np.asarray(target, float), y.shape)
        k = np.broadcast_to(np.asarray(k, float), y.shape[:-1])
        plant0 = self.plant(theta)
        x = true_tips(plant0, y)
        plant, q, ok, reach = self.effect_configuration(x, theta)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            Jh_inv, sing = inv2(self.effect_controller_jacobian(plant, q))          # (n, c, 2, 2)
            e = b - y
            dq = k[:, None, None] * np.einsum("ncij,nj->nci", np.nan_to_num(Jh_inv), e)
            q2 = q[:, None, :] + dq
            c = q2.shape[1]
            rep = plant.with_(port=np.repeat(plant.port, c, axis=0), load=np.repeat(plant.load, c, axis=0))
            q2f = q2.reshape(-1, 2)
            ok_lim = self.arm.within_limits(rep.link_angles_q(q2f))
            ok_shaft = rep.shaft_reaches(rep.wrist(q2f))
            y2 = rep.tracked(rep.tip(q2f)).reshape(-1, c, 2)
            e0 = np.linalg.norm(e, axis=-1)
            ratio = np.linalg.norm(y2 - b[:, None, :], axis=-1) / np.where(e0 > 0, e0, np.nan)[:, None]
        good = (ok_lim & ok_shaft).reshape(-1, c) & ~sing & np.isfinite(ratio)
        ratio = np.where(good, ratio, np.inf).max(axis=-1)
        return np.where(ok, ratio, np.where(reach, np.inf, np.nan))


def true_tips(plant: Plant, y: np.ndarray) -> np.ndarray:
    """The true tips (..., d) whose tracked readings are ``y``: ``R^-1 (y - b)`` (the inverse of
    :meth:`Plant.tracked`; ``y - b`` without a rotation, ``y`` itself without a registration)."""
    y = np.asarray(y, float)
    b = np.asarray(plant.tracker_offset, float)
    R = tracker_rotation_matrix(plant)
    z = y - b if np.any(b) else y
    return z if R is None else z @ R


def _with(plant: Plant, **changes) -> Plant:
    """``plant.with_(**changes)`` for ``port`` and ``load`` (one per row), keeping its true arm once built (a
    perturbed URDF arm is built from the URDF's joint origins: once per evaluator, not once per batch). A
    shallow copy: the fields it changes need none of the checks of a new Plant's construction."""
    if set(changes) - {"port", "load"}:
        out = plant.with_(**changes)
        if "true_arm" in plant.__dict__:
            out.__dict__["true_arm"] = plant.__dict__["true_arm"]
        return out
    out = copy.copy(plant)  # the cached true arm comes along in __dict__
    for name, value in changes.items():
        object.__setattr__(out, name, value)
    return out


def tracker_rotation_matrix(plant: Plant) -> np.ndarray | None:
    """The rotation ``R`` (d, d) of the truth's tracker registration (the tracked tip is ``R x + b``),
    or None without one: the loop's matrix is ``G = I - k R J Jhat^-1`` (docs/physics.md "From measured
    data to the plan")."""
    r = np.asarray(plant.tracker_rotation, float)
    if not np.any(r):
        return None
    if plant.dim == 2:
        c, s = math.cos(float(r[0])), math.sin(float(r[0]))
        return np.array([[c, -s], [s, c]])
    from ..kinematics.geometry import rotation_vector_matrix

    return rotation_vector_matrix(r)


EFFECT_NEWTON_ITERS = 8


@njit(cache=True, error_model="numpy")
def _true_wrist2(X, PORT, T, L, anyt, prm, W, OK):
    """:meth:`Evaluator.true_wrist` over a planar batch into ``W`` (n, 2), ``OK`` (n,): the operations of
    :meth:`Evaluator._true_wrist_numpy` (the straight shaft's wrist, or :func:`flexed_wrist` on the tips
    the shaft reaches, the others replaced by a point on the port's line; then :meth:`Arm.reachable`)."""
    n = T.shape[0]
    R = np.empty(n)
    oks = np.empty(n, np.bool_)
    for i in range(n):
        d0, d1 = X[i, 0] - PORT[i, 0], X[i, 1] - PORT[i, 1]
        r = math.sqrt(d0 * d0 + d1 * d1)
        R[i] = r
        oks[i] = (r > 1e-9) and (r < L)
    if not anyt:
        for i in range(n):
            scale = L / (R[i] if oks[i] else 1.0)
            W[i, 0] = X[i, 0] - scale * (X[i, 0] - PORT[i, 0])
            W[i, 1] = X[i, 1] - scale * (X[i, 1] - PORT[i, 1])
    else:
        XS = np.empty((n, 2))
        TS = np.empty(n)
        any_s = False
        h = 0.5 * L
        for i in range(n):
            if oks[i]:
                XS[i, 0], XS[i, 1], TS[i] = X[i, 0], X[i, 1], T[i]
            else:
                XS[i, 0], XS[i, 1], TS[i] = PORT[i, 0] + 0.0, PORT[i, 1] + h, 0.0
            any_s = any_s or TS[i] != 0
        _wrist2_kernel(XS, PORT, L, TS, any_s, W)
    WS = np.empty((n, 2))
    for i in range(n):
        if oks[i]:
            WS[i, 0], WS[i, 1] = W[i, 0], W[i, 1]
        else:
            WS[i, 0], WS[i, 1] = 0.0, 0.0
    _reachable_kernel(WS, prm, OK)
    for i in range(n):
        OK[i] = oks[i] and OK[i]


def _fd_jacobian(f, q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central-difference Jacobian (..., d, n) of ``f: (..., n) -> (..., d)``."""
    cols = []
    n = q.shape[-1]
    for i in range(n):
        e = np.zeros(n)
        e[i] = h
        cols.append((f(q + e) - f(q - e)) / (2 * h))
    return np.stack(cols, axis=-1)




def _perp_basis(e1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors completing unit ``e1`` (..., 3) to a right-handed frame: the convention of the
    compiled kernels (kernels._perp_basis), so ``psi`` means the same direction in both."""
    a = np.abs(e1)
    ref = np.zeros_like(e1)
    first = (a[..., 0] <= a[..., 1]) & (a[..., 0] <= a[..., 2])
    second = ~first & (a[..., 1] <= a[..., 2])
    ref[first, 0] = 1.0
    ref[second, 1] = 1.0
    ref[~first & ~second, 2] = 1.0
    f1 = np.cross(e1, ref)
    f1 /= np.linalg.norm(f1, axis=-1, keepdims=True)
    return f1, np.cross(e1, f1)


@dataclass
class SpatialEffectsEvaluator:
    """3-D truth whose ``[effects]`` change the true Jacobian or the loop's frame (``joint_offset``,
    ``gravity_sag``, ``shaft_flexion``, ``joint_geometry``, ``instrument_length``,
    ``tracker_registration``): ``J Jhat^-1`` no longer reduces to the wrist Jacobians. Per (tip,
    instance): the encoder angles that put the true tip at ``x`` by Newton's method on the true
    forward map (started from the true arm's inverse kinematics of the true shaft's wrist), the true
    ``J = d tip / d q_enc`` by central differences, the controller's (declared)
    ``Jhat = J_lever(w_model(q_enc), estimate) J_arm(q_enc)`` at the same encoder angles, and
    ``M = R J Jhat^-1`` with ``R`` the tracker registration's rotation. A load instance ``(tau, psi)`` is the
    world vector the lever geometry gives it (as in the compiled kernels), added to the truth's
    ``shaft_flexion`` load. Where the truth's links follow the encoders in closed form under the rigid
    controller (:attr:`compiled`) one compiled loop computes ``M`` (:mod:`.kernels.effects`, equal to
    :meth:`numpy_parts`); otherwise numpy, slower (and slower still with ``gravity_sag``, whose
    generalized gravity comes from pinocchio point by point).

    ``parts(x, theta)`` returns ``(M, None, ok)`` with ``M`` (n, 1, 3, 3): the numpy search
    (:mod:`.search`) takes motion maps where the planar evaluator gives conformal parts.
    """

    plant: Plant
    estimate: tuple[float, ...]
    errors: ErrorSet
    jacobian: str = "rigid"

    @classmethod
    def from_model(cls, m) -> "SpatialEffectsEvaluator":
        """From an arm's model: the truth with its ``[effects]`` (``port_offset`` folded into the box's base port)."""
        es = m.true_errors
        effects = {name: p for name, p in m.scenario.effects.items() if name != "port_offset"}
        plant = Plant.from_model(m, port=es.base_port, effects=effects)
        return cls(plant, m.estimate, es, m.jacobian)

    @property
    def noise(self) -> np.ndarray | None:
        """The flexion controller's noise corners (c, 7); None for the rigid controller."""
        return self.errors.noise_corners() if self.jacobian == "flexion" else None

    @property
    def arm(self):
        return self.plant.arm

    @property
    def length(self) -> float:
        return self.plant.length

    def _plant(self, x: np.ndarray, theta: np.ndarray, wrist: bool = False):
        """The truth of instance(s) ``theta`` (n, 5) at tips ``x`` (n, 3): ``(plant, port)`` with one port and
        load vector per row; ``wrist``: also the wrist (n, 3) that puts the true shaft's tip at ``x`` under
        the instance's load alone (the lever's where unloaded; NaN where the shaft cannot reach ``x``)."""
        port = np.asarray(self.errors.base_port) + theta[:, :3]
        tau = theta[:, 3]
        t = np.zeros_like(x)
        bent = tau > 0
        L = self.plant.true_length
        self.plant.true_arm  # built once, kept by every copy (_with)
        w = None
        if wrist:
            with np.errstate(invalid="ignore", divide="ignore"):
                d = x - port
                w = x - L * d / np.linalg.norm(d, axis=-1, keepdims=True)
        if np.any(bent):
            e = x[bent] - port[bent]
            e1 = e / np.linalg.norm(e, axis=-1, keepdims=True)
            f1, f2 = _perp_basis(e1)
            psi = theta[bent, 4][:, None]
            with np.errstate(invalid="ignore", divide="ignore"):
                wb, t[bent] = flexed_wrist_plane(x[bent], port[bent], L, tau[bent], np.cos(psi) * f1 + np.sin(psi) * f2)
            if wrist:
                w[bent] = wb
        pl = _with(self.plant, port=port, load=t)
        return (pl, port, w) if wrist else (pl, port)

    def configuration(self, x: np.ndarray, theta: np.ndarray) -> tuple[Plant, np.ndarray, np.ndarray, np.ndarray]:
        """The truth of instances ``theta`` (n, 5) putting its true tip at ``x`` (n, 3): ``(plant, port, q,
        ok)``, ``q`` the encoder angles by Newton's method on the true forward map (started from the true
        arm's inverse of the true shaft's wrist), ``ok`` where it converged inside the limits with the
        shaft through the true port."""
        x = np.asarray(x, float).reshape(-1, 3)
        theta = np.broadcast_to(np.asarray(theta, float), (len(x), 5))
        plant, port, w_inst = self._plant(x, theta, wrist=True)
        r = np.linalg.norm(x - port, axis=-1)
        ok = (r > 1e-9) & (r < plant.true_length)
        with np.errstate(invalid="ignore", divide="ignore"):
            if any(self.plant.world_load):  # the instance's load and the world's: Newton on the wrist
                w0 = plant.true_wrist_for_tip(np.where(ok[:, None], x, port + [0, 0, 0.5 * self.length]))
            else:  # the instance's load alone: its wrist is exact
                w0 = w_inst
            ok &= np.all(np.isfinite(w0), axis=-1)
            w0 = np.where(ok[:, None], w0, 0.0)
            q_link, ok_ik = plant.true_arm.inverse(w0)
            ok &= ok_ik
            q = np.where(ok[:, None], q_link - np.asarray(plant.joint_offset), 0.0)
            if self.closed_form:  # the true wrist (under the world load) and the true arm's inverse: exact
                return plant, port, q, ok
            for _ in range(EFFECT_NEWTON_ITERS):
                f = plant.tip(q) - x
                J = _fd_jacobian(plant.tip, q)
                step = np.zeros_like(q)
                good = ok & np.all(np.isfinite(J), axis=(-2, -1)) & (np.abs(np.linalg.det(np.where(
                    np.isfinite(J), J, 0.0))) > 1e-14)
                if np.any(good):
                    step[good] = np.linalg.solve(J[good], f[good][..., None])[..., 0]
                q = q - step
            resid = np.linalg.norm(plant.tip(q) - x, axis=-1)
            ok &= (resid < 1e-10) & self.arm.within_limits(plant.link_angles_q(q))
            ok &= plant.shaft_reaches(plant.wrist(q))
        return plant, port, q, ok

    @property
    def closed_form(self) -> bool:
        """True without ``gravity_sag`` (the only effect whose link angles need Newton's method): the
        encoder angles are the true arm's inverse of the true wrist less ``joint_offset`` and ``J`` is
        exact (:meth:`true_jacobian`)."""
        return not any(self.plant.gravity_sag)

    def true_jacobian(self, pl: Plant, q: np.ndarray) -> np.ndarray:
        """``J = d tip / d q_enc`` (n, 3, 3) of the truth ``pl`` (one port and load per row) at encoder
        angles ``q``: the true flexed shaft's Jacobian at the true wrist times the true arm's where
        :attr:`closed_form`, central differences of the true forward map otherwise."""
        if not self.closed_form:
            return _fd_jacobian(pl.tip, q)
        ql = pl.link_angles_q(q)
        w = pl.true_arm.forward(ql)
        return flexed_jacobian(w, pl.true_port, pl.true_length, pl.shaft_load(w)) @ pl.true_arm.jacobian(ql)

    def controller_jacobian_at(self, pl: Plant, q: np.ndarray) -> np.ndarray:
        """The controller's ``Jhat`` (n, c, 3, 3) at encoder angles ``q`` (n, 3) of the truth ``pl`` (one
        port and load per row): the lever through the estimate on the declared arm's wrist, or P2's
        controller fed the true end poses under the noise corners, times the declared arm's Jacobian."""
        L = self.length  # the declared instrument (the controller's)
        lever = lever_jacobian(self.arm.forward(q), np.asarray(self.estimate), L)
        if self.jacobian == "flexion":  # P2's controller in 3-D fed the true end poses + noise corners
            from ..kinematics.shaft import flexion_controller_jacobian

            w, tip, dw, dt = pl.end_poses(q)
            m = bending_frame(w, pl.true_port, pl.true_length, pl.shaft_load(w))
            pw, pt, mw, mt = noisy_end_poses(w, tip, dw, dt, m, self.noise)
            Jtw = flexion_controller_jacobian(pw, pt, mw, mt, L)
            Jtw = np.where(np.all(np.isfinite(Jtw), axis=(-2, -1))[..., None, None], Jtw, lever[:, None])
        else:
            Jtw = lever[:, None]
        return Jtw @ self.arm.jacobian(q)[:, None]  # (n, c, 3, 3)

    @property
    def compiled(self) -> bool:
        """True where :meth:`parts` runs compiled (:func:`errplan.fields.kernels.effects._effects_maps3`):
        :attr:`closed_form`, the rigid controller, no world load, a 3-joint arm."""
        return (self.closed_form and self.jacobian == "rigid" and not any(self.plant.world_load)
                and int(self.arm.n) == 3 and hasattr(self.arm, "kernel"))

    def _kernel_args(self) -> tuple:
        """The compiled path's fixed arguments, built once."""
        kept = self.__dict__.get("_kargs")
        if kept is None:
            from ..jit import kernel_array

            pl = self.plant
            decl, rmap = self.arm.kernel()
            true_arm = pl.true_arm
            refine = true_arm is not self.arm
            R = tracker_rotation_matrix(pl)
            kept = self.__dict__["_kargs"] = (
                kernel_array(np.asarray(self.errors.base_port, float) + np.asarray(pl.port_offset, float)),
                kernel_array(np.asarray(self.estimate, float)), float(self.length), float(pl.true_length),
                decl, rmap, true_arm.chain if refine else decl, bool(refine),
                kernel_array(np.asarray(pl.joint_offset, float)), kernel_array(np.eye(3) if R is None else R))
        return kept

    def parts(self, x: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, None, np.ndarray]:
        x = np.asarray(x, float).reshape(-1, 3)
        n = len(x)
        if self.compiled:
            from ..jit import kernel_array
            from .kernels.effects import _effects_maps3

            bp, est, L, Lt, decl, rmap, tch, refine, off, R = self._kernel_args()
            X = kernel_array(x)
            TH = kernel_array(np.broadcast_to(np.asarray(theta, float), (n, 5)))
            M = np.empty((n, 3, 3))
            ok = np.empty(n, np.bool_)
            _effects_maps3(X, TH, bp, est, L, Lt, decl, rmap, tch, refine, off, R, M, ok)
            return M[:, None], None, ok
        return self.numpy_parts(x, theta)

    def numpy_parts(self, x: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, None, np.ndarray]:
        """:meth:`parts` in numpy (every effect; the compiled path's reference)."""
        x = np.asarray(x, float).reshape(-1, 3)
        n = len(x)
        M = np.full((n, 1 if self.noise is None else len(self.noise), 3, 3), np.nan)
        plant, port, q, ok = self.configuration(x, theta)
        if not np.any(ok):
            return M, None, ok
        with np.errstate(invalid="ignore", divide="ignore"):
            qo = q[ok]
            pl = _with(plant, port=port[ok], load=plant.load_vector[ok])
            J = self.true_jacobian(pl, qo)
            R = tracker_rotation_matrix(plant)
            if R is not None:  # the loop closes on the tracked tip R x + b
                J = R @ J
            Jh = self.controller_jacobian_at(pl, qo)
            det = np.linalg.det(Jh)
            fro = np.sqrt(np.sum(Jh * Jh, axis=(-2, -1)))
            nonsing = np.all(np.abs(det) > 1e-12 * fro**3, axis=-1)
            c = Jh.shape[1]
            Mo = np.full((len(qo), c, 3, 3), np.nan)
            Mo[nonsing] = J[nonsing][:, None] @ np.linalg.inv(Jh[nonsing])
        idx = np.flatnonzero(ok)
        ok[idx[~nonsing]] = False
        M[idx] = Mo
        M[~ok] = np.nan
        return M, None, ok

    def step_ratio(self, target, y: np.ndarray, theta: np.ndarray, k) -> np.ndarray:
        """One controller step on the truth with its [effects], per pair, in the loop's frame (``y`` (n,
        3) the tracked tips, ``target`` (3,) or (n, 3) in the tracker's frame): as
        :meth:`Evaluator.effect_step_ratio`, the worst over the controller's noise corners. ``nan`` where
        the truth cannot put its tip at ``R^-1 (y - b)``, ``inf`` where the step leaves the limits, pulls
        the shaft out of the port or the controller's Jacobian is singular."""
        y = np.asarray(y, float).reshape(-1, 3)
        n = len(y)
        theta = np.broadcast_to(np.asarray(theta, float), (n, 5))
        b = np.broadcast_to(np.asarray(target, float), y.shape)
        k = np.broadcast_to(np.asarray(k, float), (n,))
        out = np.full(n, np.nan)
        x = true_tips(self.plant, y)
        plant, port, q, ok = self.configuration(x, theta)
        if not np.any(ok):
            return out
        i = np.flatnonzero(ok)
        pl = _with(plant, port=port[i], load=plant.load_vector[i])
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            Jh = self.controller_jacobian_at(pl, q[i])                   # (m, c, 3, 3)
            c = Jh.shape[1]
            Jh_inv, sing = inv(Jh)
            e = b[i] - y[i]
            dq = k[i][:, None, None] * np.einsum("ncij,nj->nci", np.nan_to_num(Jh_inv), e)
            q2 = (q[i][:, None, :] + dq).reshape(-1, 3)
            rep = _with(pl, port=np.repeat(pl.port, c, axis=0), load=np.repeat(pl.load_vector, c, axis=0))
            ok_lim = self.arm.within_limits(rep.link_angles_q(q2))
            ok_shaft = rep.shaft_reaches(rep.wrist(q2))
            y2 = rep.tracked(rep.tip(q2)).reshape(-1, c, 3)
            e0 = np.linalg.norm(e, axis=-1)
            ratio = np.linalg.norm(y2 - b[i][:, None, :], axis=-1) / np.where(e0 > 0, e0, np.nan)[:, None]
        good = (ok_lim & ok_shaft).reshape(-1, c) & ~sing & np.isfinite(ratio)
        out[i] = np.where(good, ratio, np.inf).max(axis=-1)
        return out


def bending_frame(w: np.ndarray, port: np.ndarray, L: float, t: np.ndarray) -> np.ndarray:
    """Unit normal (..., 3) of the true shaft's bending plane (wrist->port line and the load's
    normal part); for an unbent shaft the second vector of :func:`_perp_basis` of the chord (in the
    plane x = 0 that is the x axis, so "in-plane" keeps its meaning)."""
    from ..kinematics.shaft import _spatial_geometry

    g = _spatial_geometry(w, port, L, t)
    m = np.cross(g["u"], g["n"])
    mn = np.linalg.norm(m, axis=-1)
    chord = (g["tip"] - w) / L
    _, f2 = _perp_basis(np.where(np.isfinite(chord), chord, [0.0, 0.0, 1.0]))
    bent = mn > 1e-12
    return np.where(bent[..., None], m / np.where(bent, mn, 1.0)[..., None], f2)


def noisy_end_poses(w: np.ndarray, tip: np.ndarray, dw: np.ndarray, dt: np.ndarray, m: np.ndarray,
                    noise: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The 3-D flexion controller's measurements (..., c, 3) under noise vectors ``noise`` (c, 7)
    (:func:`errplan.errorset.spatial_noise_corners`): the chord difference ``delta`` on the
    tip position, each end direction tilted in its frame ``(m x d, m)``, ``m`` the true bending
    plane's normal (..., 3)."""
    from ..kinematics.shaft import tilt

    noise = np.asarray(noise, float)  # (c, 7), or (..., c, 7) per point
    pw = np.broadcast_to(w[..., None, :], np.broadcast_shapes(w.shape[:-1] + (1,), noise.shape[:-1]) + (3,))
    pt = tip[..., None, :] + noise[..., 0:3]
    out = []
    for d, sl in ((dw, slice(3, 5)), (dt, slice(5, 7))):
        e1 = np.cross(m, d)
        e1 = e1 / np.linalg.norm(e1, axis=-1, keepdims=True)
        out.append(tilt(d[..., None, :], noise[..., sl], e1[..., None, :], m[..., None, :]))
    return pw, pt, out[0], out[1]


@dataclass
class SpatialFlexionEvaluator:
    """P2's flexion controller in 3-D (docs/physics.md "P2's flexion controller in 3-D") without
    [effects] that move the arm: ``M = J Jhat^-1 = J_tw Jhat_tw^-1`` (the arm Jacobian cancels, as
    for the rigid controller), per (tip, instance, noise corner).

    Per instance ``theta = (dx, dy, dz, tau, psi)`` the true wrist and world load come from
    :func:`flexed_wrist_plane` (the load direction ``psi`` around the port->tip line, the convention
    of the compiled kernels), the true end poses from :func:`flexed_end_directions`; the controller
    sees them with each noise vector of ``noise`` (c, 7) and builds ``Jhat_tw`` by
    :func:`flexion_controller_jacobian`. Where the estimate is unidentifiable (an unbent shaft, no
    noise) it falls back to the lever through ``estimate``, as the planar controller does.

    ``parts(x, theta)`` returns ``(M, None, ok)``, ``M`` (n, c, 3, 3): the numpy search
    (:mod:`.search`) takes motion maps.
    """

    arm: object
    length: float
    estimate: tuple[float, ...]
    errors: ErrorSet
    noise: np.ndarray = None  # (c, 7); default: errors.noise_corners()
    jacobian: str = "flexion"

    def __post_init__(self):
        if self.noise is None:
            self.noise = self.errors.noise_corners()

    @classmethod
    def from_model(cls, m, noise: np.ndarray | None = None) -> "SpatialFlexionEvaluator":
        """From an arm's model (:class:`errplan.models.ArmModel`); one :class:`ErrplanError` when the
        truth has ``[effects]`` that move the arm."""
        from ..errors import ErrplanError

        es, kw = m.true_errors, m.jacobian_effects
        if kw:
            raise ErrplanError(f"{m.scenario.source}: [effects] {sorted(kw)} with P2's flexion controller in 3-D: not "
                               "supported yet (the 3-D flexion controller runs with a truth whose effects do not "
                               "move the arm)")
        return cls(m.arm, float(m.length), m.estimate, es, noise)

    def truth(self, x: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """True wrist, world load, port (n, 3) and validity (n,) putting the true tip at ``x``."""
        x = np.asarray(x, float).reshape(-1, 3)
        theta = np.broadcast_to(np.asarray(theta, float), (len(x), 5))
        L = self.length
        port = np.asarray(self.errors.base_port, float) + theta[:, :3]
        e = x - port
        r = np.linalg.norm(e, axis=-1)
        ok = (r > 1e-9) & (r < L)
        xs = np.where(ok[:, None], x, port + [0.0, 0.0, 0.5 * L])
        e1 = (xs - port) / np.linalg.norm(xs - port, axis=-1, keepdims=True)
        tau = np.where(ok, theta[:, 3], 0.0)
        w = xs - L * e1
        t = np.zeros_like(x)
        bent = tau > 0
        if np.any(bent):
            f1, f2 = _perp_basis(e1[bent])
            psi = theta[bent, 4][:, None]
            w[bent], t[bent] = flexed_wrist_plane(xs[bent], port[bent], L, tau[bent], np.cos(psi) * f1 + np.sin(psi) * f2)
        ok &= self.arm.reachable(np.where(ok[:, None], w, self.arm.forward(np.zeros(self.arm.n))))
        return w, t, port, ok

    def controller_jacobian(self, w: np.ndarray, t: np.ndarray, port: np.ndarray,
                            noise: np.ndarray | None = None) -> np.ndarray:
        """``Jhat_tw`` (n, c, 3, 3) from the true shaft's end poses under every noise vector
        (``noise`` (c, 7) or per point (n, c, 7); default the corners)."""
        from ..kinematics.shaft import flexed_end_directions, flexion_controller_jacobian

        L = self.length
        tip, dw, dt = flexed_end_directions(w, port, L, t)
        m = bending_frame(w, port, L, t)
        pw, pt, mw, mt = noisy_end_poses(w, tip, dw, dt, m, self.noise if noise is None else noise)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            Jh = flexion_controller_jacobian(pw, pt, mw, mt, L)
        rigid = ~np.all(np.isfinite(Jh), axis=(-2, -1))
        if np.any(rigid):
            lever = lever_jacobian(w, np.asarray(self.estimate, float), L)
            Jh = np.where(rigid[..., None, None], lever[:, None], Jh)
        return Jh

    def _compiled(self, x: np.ndarray, theta: np.ndarray, noise, k, want_M: bool, want_gp: int, gfloor=None,
                  pfloor=None):
        """The compiled controller (:func:`errplan.fields.kernels.flexion.flexion_tips`) on the true shafts
        of :meth:`truth`: ``(M or None, g, p, ok)``."""
        from ..jit import kernel_array
        from .kernels.flexion import flexion_tips

        x = np.asarray(x, float).reshape(-1, 3)
        nz = self.noise if noise is None else np.asarray(noise, float)
        NZ = kernel_array(nz[None] if nz.ndim == 2 else nz)
        n, c = len(x), NZ.shape[1]
        w, t, port, ok = self.truth(x, theta)
        ok = kernel_array(np.asarray(ok, bool))
        M = np.empty((n if want_M or want_gp == 3 else 1, c if want_M else 1, 3, 3))
        g = np.empty(n if want_gp else 1)
        p = np.empty(n if want_gp else 1)
        kk = kernel_array(np.asarray(np.broadcast_to(np.asarray(k, float), (n,)) if np.ndim(k) else [float(k)],
                                     float))
        gf, pf = (np.full(1, -np.inf) if f is None else kernel_array(np.array(np.broadcast_to(f, (n,)), float))
                  for f in (gfloor, pfloor))
        flexion_tips(kernel_array(w), kernel_array(t), kernel_array(port), ok, NZ, np.asarray(self.estimate, float),
                     float(self.length), kk, bool(want_M), int(want_gp), gf, pf, M, g, p)
        return (M if want_M or want_gp == 3 else None), g, p, ok

    def parts(self, x: np.ndarray, theta: np.ndarray, noise: np.ndarray | None = None
              ) -> tuple[np.ndarray, None, np.ndarray]:
        """``(M, None, ok)``: ``M`` (n, c, 3, 3) at tips ``x`` (n, 3) under instances ``theta`` over the
        noise vectors ``noise`` ((c, 7) or per tip (n, c, 7); default the noise set's corners); NaN where
        ``ok`` is False. Compiled (:mod:`errplan.fields.kernels.flexion`); :meth:`parts_numpy` is the
        numpy reference it equals."""
        M, _, _, ok = self._compiled(x, theta, noise, 0.0, True, 0)
        return M, None, ok

    def reduced(self, x: np.ndarray, theta: np.ndarray, k, phi: bool = True, g_above=None, p_above=None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The worst over the noise vectors (the corners) of :meth:`parts`' maps, without forming them in
        Python: ``(||I - k M||, |phi_max|, ok)`` (n,) each (``k`` a number or (n,); ``|phi_max|`` NaN
        without ``phi``; both NaN where ``ok`` is False). ``g_above``, ``p_above`` ((n,) or a number): a
        caller that keeps a worst value only where it exceeds these gets the value itself where it does
        not (``inf``: that value is not computed); the exact norms and angles are then computed only
        where their bounds exceed it. Without them: the worst values."""
        _, g, p, ok = self._compiled(x, theta, None, k, False, 2 if phi else 1, g_above, p_above)
        return g, p, ok

    def worst_corner(self, x: np.ndarray, theta: np.ndarray, k: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The noise corner of largest ``||I - k M||`` at each pair, compiled, without forming the other
        corners' maps in Python: ``(||G||, j, M_j, ok)``, ``j`` (n,) the first corner attaining it
        (``np.argmax`` over :meth:`parts`' corners), ``M_j`` (n, 3, 3) its map; ``||G||`` -inf, ``j`` 0 and
        ``M_j`` NaN where ``ok`` is False."""
        M, g, j, ok = self._compiled(x, theta, None, k, False, 3)
        M = M[:, 0]
        M[~ok] = np.nan
        return np.where(ok, g, -np.inf), np.where(ok, j, 0.0).astype(np.int64), M, ok

    def parts_numpy(self, x: np.ndarray, theta: np.ndarray, noise: np.ndarray | None = None
                    ) -> tuple[np.ndarray, None, np.ndarray]:
        """:meth:`parts` in numpy, step by step through :mod:`errplan.kinematics.shaft`: the reference
        of the compiled controller."""
        from ..kinematics.shaft import flexed_jacobian
        from ..metrics import inv

        x = np.asarray(x, float).reshape(-1, 3)
        nz = self.noise if noise is None else np.asarray(noise, float)
        n, c = len(x), nz.shape[-2]
        M = np.full((n, c, 3, 3), np.nan)
        w, t, port, ok = self.truth(x, theta)
        if not np.any(ok):
            return M, None, ok
        i = np.flatnonzero(ok)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            J = flexed_jacobian(w[i], port[i], self.length, t[i])
            Jh_inv, singular = inv(self.controller_jacobian(w[i], t[i], port[i], nz if nz.ndim == 2 else nz[i]))
            Mi = J[:, None] @ Jh_inv
        bad = np.any(singular | ~np.all(np.isfinite(Mi), axis=(-2, -1)), axis=-1)
        M[i] = Mi
        ok[i[bad]] = False
        M[~ok] = np.nan
        return M, None, ok

    def noise_bounds(self) -> np.ndarray:
        """Half widths (7,) of the noise parameters: ``2 position`` per chord axis, ``angle`` per tilt."""
        pos, ang = self.errors.noise
        return np.array([2 * pos] * 3 + [ang] * 4, float)

    def refine_noise(self, x: np.ndarray, theta: np.ndarray, k: float, *, levels: int = 4, sweeps: int = 2
                     ) -> tuple[np.ndarray, np.ndarray]:
        """The noise refinement of the worst case: from the worst corner at each tip's worst instance
        ``theta`` (n, 5), a pattern search over the noise vector (steps halved per level, each move
        the best of the axis polls, projected back into the set: the chord box, each tilt's disc).
        Returns the refined worst ``(||G||, |phi_max|)`` (n,) at gain ``k`` (never below the
        corners'); still a lower bound of the worst case over the set. Axes the corners keep at zero
        (the in-plane set's out-of-plane ones) stay there."""
        from ..metrics import g_norm, phi_max

        x = np.asarray(x, float).reshape(-1, 3)
        n = len(x)
        best_g, j, Mj, ok = self.worst_corner(x, theta, k)
        best_p = np.where(ok, phi_max(np.where(ok[:, None, None], Mj, np.eye(3))), -np.inf)
        z = self.noise[j].copy()
        half = self.noise_bounds()
        moving = np.flatnonzero(np.any(self.noise != 0, axis=0) & (half > 0))
        if not len(moving) or not np.any(ok):
            return best_g, best_p
        steps = np.concatenate([np.eye(7)[moving], -np.eye(7)[moving]])
        live = ok.copy()
        for level in range(levels):
            h = half * 2.0 ** (-level)
            for _ in range(sweeps):
                c = _project_noise(z[live][:, None, :] + steps[None] * h, half)
                Mc, _, okc = self.parts(x[live], theta[live], c)
                gc = np.where(okc[:, None], g_norm(np.where(okc[:, None, None, None], Mc, 0.0), k), -np.inf)
                jj = np.argmax(gc, axis=1)
                li = np.flatnonzero(live)
                vg = gc[np.arange(len(li)), jj]
                upd = okc & (vg > best_g[li])
                if upd.any():
                    pc = phi_max(Mc[upd].reshape(-1, 3, 3)).reshape(int(upd.sum()), -1).max(axis=1)
                    best_p[li[upd]] = np.maximum(best_p[li[upd]], pc)
                    best_g[li[upd]] = vg[upd]
                    z[li[upd]] = c[upd, jj[upd]]
                else:
                    break
        return best_g, best_p


def _project_noise(z: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Noise vectors (..., 7) back into the set: the chord difference clipped to its box, each tilt
    scaled into its disc of radius ``half[3]``."""
    out = z.copy()
    out[..., 0:3] = np.clip(out[..., 0:3], -half[0:3], half[0:3])
    for sl in (slice(3, 5), slice(5, 7)):
        r = np.linalg.norm(out[..., sl], axis=-1)
        lim = half[sl.start]
        scale = np.where(r > lim, lim / np.where(r > 0, r, 1.0), 1.0)
        out[..., sl] = out[..., sl] * scale[..., None]
    return out


@dataclass
class NumpyFlexionEvaluator(SpatialFlexionEvaluator):
    """P2's controller in 3-D on the numpy path alone (:meth:`SpatialFlexionEvaluator.parts_numpy`, the
    search reducing the maps in numpy): the independent reference of the compiled controller for the tests
    and ``benchmarks/flexion.py``; the same answers, much slower."""

    reduced = None  # the numpy search forms every map (errplan.fields.search._values)

    def worst_corner(self, x: np.ndarray, theta: np.ndarray, k: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`SpatialFlexionEvaluator.worst_corner` from every corner's map in numpy (``np.argmax``)."""
        from ..metrics import g_norm

        M, _, ok = self.parts(x, theta)
        n = len(M)
        g = np.where(ok[:, None], g_norm(np.where(ok[:, None, None, None], M, 0.0), k), -np.inf)
        j = np.argmax(g, axis=1)
        return g[np.arange(n), j], j, M[np.arange(n), j], ok

    def parts(self, x: np.ndarray, theta: np.ndarray, noise: np.ndarray | None = None
              ) -> tuple[np.ndarray, None, np.ndarray]:
        return self.parts_numpy(x, theta, noise)
