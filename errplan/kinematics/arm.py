"""Planar two-link arm (P1 Sec. III-A, docs/physics.md "Robot").

All functions take joint angles ``q`` of shape ``(..., 2)`` (rad) and points of shape
``(..., 2)`` as ``[y, z]`` (m); leading axes are batch axes. The direction of angle ``a`` is
``dir(a) = [sin a, cos a]``; link 1 points along ``a1 = q1 + h1`` and link 2 along
``a2 = a1 + q2 + h2``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def direction(a: np.ndarray) -> np.ndarray:
    """Unit vector ``[sin a, cos a]`` of angle ``a`` (any shape) -> shape ``(..., 2)``."""
    a = np.asarray(a, dtype=float)
    out = np.empty(a.shape + (2,))
    np.sin(a, out=out[..., 0])
    np.cos(a, out=out[..., 1])
    return out


def direction_derivative(a: np.ndarray) -> np.ndarray:
    """``d dir(a) / da = [cos a, -sin a]``: the unit normal on the side of increasing angle."""
    a = np.asarray(a, dtype=float)
    out = np.empty(a.shape + (2,))
    np.cos(a, out=out[..., 0])
    np.sin(a, out=out[..., 1])
    np.negative(out[..., 1], out=out[..., 1])
    return out


def angle_of(v: np.ndarray) -> np.ndarray:
    """Angle ``a`` of a vector ``[y, z]`` in the convention ``dir(a)``: ``atan2(y, z)``."""
    v = np.asarray(v, dtype=float)
    return np.arctan2(v[..., 0], v[..., 1])


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


@dataclass(frozen=True)
class Arm:
    """The planar arm: shoulder ``base`` [y, z], link lengths, home angles and joint limits."""

    base: tuple[float, float]
    l1: float
    l2: float
    home: tuple[float, float]
    q1_limits: tuple[float, float]
    q2_limits: tuple[float, float]
    sum_limits: tuple[float, float]

    @classmethod
    def from_robot(cls, robot) -> "Arm":
        """From a :class:`errplan.scenario.Robot`."""
        (l1, l2), (lim1, lim2) = robot.link_lengths, robot.joint_limits
        return cls(tuple(robot.base), l1, l2, tuple(robot.home_angles), tuple(lim1), tuple(lim2),
                   tuple(robot.joint_sum_limits))

    # ------------------------------------------------------------------ forward
    def link_angles(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Absolute link angles ``(a1, a2)`` for joint angles ``q`` (..., 2)."""
        q = np.asarray(q, dtype=float)
        a1 = q[..., 0] + self.home[0]
        return a1, a1 + q[..., 1] + self.home[1]

    def elbow(self, q: np.ndarray) -> np.ndarray:
        a1, _ = self.link_angles(q)
        return np.asarray(self.base) + self.l1 * direction(a1)

    def forward(self, q: np.ndarray) -> np.ndarray:
        """Wrist position ``w`` (..., 2) for joint angles ``q`` (..., 2). Compiled
        (:func:`.compiled._forward_kernel`), the operations of :meth:`_forward_numpy` (the reference)."""
        q = np.asarray(q, dtype=float)
        if q.shape[-1:] != (2,):
            return self._forward_numpy(q)
        out = np.empty(q.shape)
        k = _compiled()
        k._forward_kernel(k.kernel_array(q).reshape(-1, 2), self._reach_params(), out.reshape(-1, 2))
        return out

    def _forward_numpy(self, q: np.ndarray) -> np.ndarray:
        a1, a2 = self.link_angles(q)
        return np.asarray(self.base) + self.l1 * direction(a1) + self.l2 * direction(a2)

    def forward_from_link_angles(self, a1: np.ndarray, a2: np.ndarray) -> np.ndarray:
        return np.asarray(self.base) + self.l1 * direction(a1) + self.l2 * direction(a2)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """``dw/dq`` of shape (..., 2, 2): rows [y, z], columns [q1, q2]. Compiled
        (:func:`.compiled._jacobian_kernel`), the operations of :meth:`_jacobian_numpy` (the reference)."""
        q = np.asarray(q, dtype=float)
        if q.shape[-1:] != (2,):
            return self._jacobian_numpy(q)
        out = np.empty(q.shape + (2,))
        k = _compiled()
        k._jacobian_kernel(k.kernel_array(q).reshape(-1, 2), self._reach_params(), out.reshape(-1, 2, 2))
        return out

    def _jacobian_numpy(self, q: np.ndarray) -> np.ndarray:
        a1, a2 = self.link_angles(q)
        d1, d2 = direction_derivative(a1), direction_derivative(a2)
        c1 = self.l1 * d1 + self.l2 * d2
        c2 = self.l2 * d2
        return np.stack([c1, c2], axis=-1)

    # ------------------------------------------------------------------ limits
    def within_limits(self, q: np.ndarray, tol: float = 1e-12) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        q1, q2 = q[..., 0], q[..., 1]
        s = q1 + q2
        return ((q1 >= self.q1_limits[0] - tol) & (q1 <= self.q1_limits[1] + tol)
                & (q2 >= self.q2_limits[0] - tol) & (q2 <= self.q2_limits[1] + tol)
                & (s >= self.sum_limits[0] - tol) & (s <= self.sum_limits[1] + tol))

    def limit_margin(self, q: np.ndarray) -> np.ndarray:
        """Smallest distance (rad) of ``q`` to any joint limit; negative outside the limits."""
        q = np.asarray(q, dtype=float)
        q1, q2 = q[..., 0], q[..., 1]
        s = q1 + q2
        return np.minimum.reduce([
            q1 - self.q1_limits[0], self.q1_limits[1] - q1,
            q2 - self.q2_limits[0], self.q2_limits[1] - q2,
            s - self.sum_limits[0], self.sum_limits[1] - s,
        ])

    # ------------------------------------------------------------------ inverse
    def _preferred_sign(self) -> float:
        # The elbow branch of the home pose (relative angle a2 - a1 = h2 at q = 0).
        return -1.0 if np.sin(self.home[1]) < 0 else 1.0

    def _branch(self, d: np.ndarray, c: np.ndarray, sgn: float) -> np.ndarray:
        delta = sgn * np.arccos(np.clip(c, -1.0, 1.0))
        a1 = angle_of(d) - np.arctan2(self.l2 * np.sin(delta), self.l1 + self.l2 * np.cos(delta))
        return np.stack([_wrap(a1 - self.home[0]), _wrap(delta - self.home[1])], axis=-1)

    def _annulus(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d = np.asarray(w, dtype=float) - np.asarray(self.base)
        c = (d[..., 0] ** 2 + d[..., 1] ** 2 - self.l1**2 - self.l2**2) / (2 * self.l1 * self.l2)
        return d, c, (c >= -1.0) & (c <= 1.0)

    def inverse_branches(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Both IK solutions for wrist ``w`` (..., 2).

        Returns ``(q_pref, q_other, reachable)``: the home-pose elbow branch first, the other
        second (each (..., 2), NaN where the wrist is out of the annulus), and the annulus mask.
        """
        d, c, reach = self._annulus(w)
        out = []
        for sgn in (self._preferred_sign(), -self._preferred_sign()):
            q = self._branch(d, c, sgn)
            q[~reach] = np.nan
            out.append(q)
        return out[0], out[1], reach

    def inverse(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joint angles putting the wrist at ``w`` inside the limits.

        Returns ``(q, ok)``: ``q`` (..., 2) is the home-pose elbow branch where it is inside the
        limits, else the other branch where that is, else NaN; ``ok`` marks reachable wrists.
        The second branch is only computed where the first fails. Compiled (:func:`.compiled._inverse_kernel`),
        the operations of :meth:`_inverse_numpy` (the reference).
        """
        w = np.asarray(w, dtype=float)
        if w.shape[-1:] != (2,):
            return self._inverse_numpy(w)
        q = np.empty(w.shape)
        ok = np.empty(w.shape[:-1], bool)
        k = _compiled()
        k._inverse_kernel(k.kernel_array(w).reshape(-1, 2), self._reach_params(), self._preferred_sign(),
                          q.reshape(-1, 2), ok.reshape(-1))
        return q, ok

    def _inverse_numpy(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d, c, reach = self._annulus(w)
        sgn = self._preferred_sign()
        q = self._branch(d, c, sgn)
        ok = reach & self.within_limits(q)
        retry = reach & ~ok
        if np.any(retry):
            qb = self._branch(d[retry], c[retry], -sgn)
            okb = self.within_limits(qb)
            idx = np.flatnonzero(retry.ravel())
            qf = q.reshape(-1, 2)
            qf[idx[okb]] = qb[okb]
            okf = ok.ravel()
            okf[idx[okb]] = True
            ok = okf.reshape(ok.shape)
            q = qf.reshape(q.shape)
        q[~ok] = np.nan
        return q, ok

    def reachable(self, w: np.ndarray) -> np.ndarray:
        """Mask of wrists ``w`` (..., 2) that some IK branch reaches inside the limits.

        Same answer as ``inverse(w)[1]`` without building the angles: both branches' joint angles
        come from complex products (one ``arctan2`` each, already wrapped), the fields' hot path.
        Compiled (:func:`.compiled._reachable_kernel`, an arctangent-free test first where it is certain):
        the answers of :meth:`_reachable_numpy` (the reference).
        """
        w = np.asarray(w, dtype=float)
        if w.shape[-1:] != (2,):
            return self._reachable_numpy(w)
        S = w.shape[:-1]
        out = np.empty(S, bool)
        k = _compiled()
        k._reachable_kernel(k.kernel_array(w).reshape(-1, 2), self._reach_params(), out.reshape(-1))
        return out[()]

    def _reach_params(self) -> np.ndarray:
        """``[base y, base z, l1, l2, cos h1, sin h1, cos h2, sin h2]``, the six limits with the
        tolerance of :meth:`within_limits` (lower - tol, upper + tol for q1, q2, q1 + q2),
        ``[h1, h2, l1**2, l2**2]``; then per limit interval of q2, q1 and q1 + q2 ``cos m, sin m, cos hw`` (m its middle, hw its half-width) and 1.0
        where :func:`_arc_class` decides exactly (every interval inside (-pi, pi) by 1e-5 and wider than
        2e-3 rad, q1 + q2 of any q1, q2 within their limits inside (-pi, pi)), else 0.0."""
        p = self.__dict__.get("_reach_p")
        if p is None:
            tol = 1e-12
            p = np.array([self.base[0], self.base[1], self.l1, self.l2,
                          np.cos(self.home[0]), np.sin(self.home[0]), np.cos(self.home[1]), np.sin(self.home[1]),
                          self.q1_limits[0] - tol, self.q1_limits[1] + tol, self.q2_limits[0] - tol,
                          self.q2_limits[1] + tol, self.sum_limits[0] - tol, self.sum_limits[1] + tol,
                          self.home[0], self.home[1], self.l1**2, self.l2**2], float)
            arcs, fast = [], True
            for lo, hi in (self.q2_limits, self.q1_limits, self.sum_limits):
                m, hw = 0.5 * (lo + hi), 0.5 * (hi - lo)
                arcs += [math.cos(m), math.sin(m), math.cos(hw)]
                fast &= -math.pi + 1e-5 < lo and hi < math.pi - 1e-5 and 1e-3 < hw
            fast &= (-math.pi + 1e-5 < self.q1_limits[0] + self.q2_limits[0]
                     and self.q1_limits[1] + self.q2_limits[1] < math.pi - 1e-5)
            p = np.concatenate([p, arcs, [1.0 if fast else 0.0]])
            object.__setattr__(self, "_reach_p", p)
        return p

    def _reachable_numpy(self, w: np.ndarray) -> np.ndarray:
        """:meth:`reachable` in numpy: the reference of the compiled path."""
        w = np.asarray(w, dtype=float)
        dy = w[..., 0] - self.base[0]
        dz = w[..., 1] - self.base[1]
        l1, l2 = self.l1, self.l2
        c = (dy * dy + dz * dz - l1 * l1 - l2 * l2) / (2 * l1 * l2)
        reach = (c >= -1.0) & (c <= 1.0)
        cc = np.clip(c, -1.0, 1.0)
        sn = np.sqrt(1.0 - cc * cc)
        ch1, sh1 = np.cos(self.home[0]), np.sin(self.home[0])
        ch2, sh2 = np.cos(self.home[1]), np.sin(self.home[1])
        out = np.zeros(c.shape, bool)
        for sgn in (1.0, -1.0):
            s_d = sgn * sn
            # q2 = wrap(delta - h2): angle of e^{i delta} e^{-i h2}
            q2 = np.arctan2(s_d * ch2 - cc * sh2, cc * ch2 + s_d * sh2)
            # q1 = wrap(angle(d) - angle(l1 + l2 e^{i delta}) - h1), with angle(v) = atan2(v_y, v_z)
            vz, vy = l1 + l2 * cc, l2 * s_d
            # d * conj(v) in the (z + i y) plane, then rotated by -h1
            rz, ry = dz * vz + dy * vy, dy * vz - dz * vy
            q1 = np.arctan2(ry * ch1 - rz * sh1, rz * ch1 + ry * sh1)
            out |= self.within_limits(np.stack([q1, q2], axis=-1))
        return reach & out

    # ------------------------------------------------------------------ sampling
    def sample_wrists(self, n: int = 121) -> np.ndarray:
        """Wrist positions (m, 2) over an ``n x n`` grid of the joint box, inside the limits."""
        q1 = np.linspace(*self.q1_limits, n)
        q2 = np.linspace(*self.q2_limits, n)
        Q = np.stack(np.meshgrid(q1, q2, indexing="ij"), axis=-1).reshape(-1, 2)
        Q = Q[self.within_limits(Q)]
        return self.forward(Q)

    def nearer_than(self, p, r: float) -> bool:
        """Whether some reachable wrist (of the sampled joint grid) lies closer than ``r`` to ``p``."""
        return self.min_distance_to(p) < r

    def min_distance_to(self, p, n: int = 121) -> float:
        """Distance from point ``p`` to the nearest reachable wrist (sampled joint grid)."""
        w = self.sample_wrists(n)
        if len(w) == 0:
            return float("inf")
        return float(np.min(np.linalg.norm(w - np.asarray(p, dtype=float), axis=-1)))


def _compiled():
    """The compiled planar kernels (:mod:`errplan.kinematics.compiled`), imported on first use: numba
    loads only for commands that compute."""
    from . import compiled
    return compiled
