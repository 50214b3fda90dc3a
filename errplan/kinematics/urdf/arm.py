"""A serial arm described by a URDF whose three actuated joints place the wrist: :class:`UrdfArm`, the
URDF twin of the planar :class:`errplan.kinematics.arm.Arm` (same methods, points ``(..., 3)``)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ... import packages
from ...jit import kernel_array
from ...errors import ErrplanError, ScenarioError
from ...scenario import CoupledLimit
from .chain import _fk_many, _ik_many, _jac_many, _reach_many
from .description import read_chain, rpy_matrix
from .model import GRAVITY, ChainData, MapParams, ReachMap
from .reachmap import reach_map_of


class UrdfArm:
    """A serial arm from a URDF whose three actuated joints place the wrist (module docstring).

    Build with :meth:`load` or :meth:`from_robot`. Joint vectors are ``(..., n)`` in the order of
    ``joint_names``; points ``(..., 3)`` world ``[x, y, z]``.
    """

    n: int
    joint_names: tuple[str, ...]
    limits: np.ndarray

    def __init__(self, *, urdf_path: Path, urdf_text: str, model, joint_names, wrist, chain: ChainData,
                 base_position, base_rpy, coupled, fixed_values, package_path, act_ids, qref,
                 segments, map_params: MapParams):
        self.urdf_path = urdf_path
        self.urdf_text = urdf_text
        self.model = model
        self.joint_names = tuple(joint_names)
        self.n = len(self.joint_names)
        self.wrist = wrist
        self.chain = chain
        self.base_position = tuple(base_position)
        self.base_rpy = tuple(base_rpy)
        self.coupled_limits = tuple(coupled)
        self.fixed_joints = dict(fixed_values)
        self.package_path = tuple(package_path)
        self.limits = np.stack([chain.lo[: self.n], chain.hi[: self.n]], axis=-1)
        self.map_params = map_params
        self.map_info: dict = {}
        self._act_ids = act_ids
        self._qref = qref
        self._segments = segments
        self._rmap: ReachMap | None = None
        self._gravity = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_robot(cls, robot, map_params: MapParams | None = None) -> "UrdfArm":
        """From a scenario's ``UrdfRobot`` (attributes as :meth:`load`'s arguments)."""
        return cls.load(robot.urdf, robot.joints, robot.wrist, base_position=robot.base_position,
                        base_rpy=robot.base_rpy, joint_limits=robot.joint_limits,
                        fixed_joints=robot.fixed_joints or {}, coupled_limits=robot.coupled_limits or (),
                        package_path=robot.package_path or (), map_params=map_params)

    @classmethod
    def load(cls, urdf: str | Path, joints: Sequence[str], wrist: str, base_position=(0.0, 0.0, 0.0),
             base_rpy=(0.0, 0.0, 0.0), joint_limits=None, fixed_joints: Mapping[str, float] = {},
             coupled_limits: Sequence[CoupledLimit] = (), package_path: Sequence[str] = (),
             map_params: MapParams | None = None) -> "UrdfArm":
        """Read the URDF and build the chain from the root to the ``wrist`` link.

        Raises :class:`ScenarioError` (one line naming the file and the offending value) for a
        missing or unreadable file, text that is not a URDF, unknown or misplaced joints, a
        missing wrist link, joints that are not revolute/continuous/prismatic, a chain that cannot
        place the wrist in 3-D, and bad limits.
        """
        kwargs, where = read_chain(urdf, joints, wrist, base_position, base_rpy, joint_limits, fixed_joints,
                                   coupled_limits, package_path, map_params)
        arm = cls(**kwargs)
        arm._check_rank(where)
        return arm

    def _check_rank(self, where: str) -> None:
        """One clear error for limits that leave nothing feasible or a chain that cannot move the
        wrist in 3-D (rank-deficient Jacobian at every sampled configuration of the box)."""
        ch = self.chain
        g = [np.linspace(lo, hi, 7) for lo, hi in self.limits]
        Q = np.stack(np.meshgrid(*g, indexing="ij"), axis=-1).reshape(-1, self.n)
        if len(ch.A) == self.n:  # the box alone (A = I): feasible iff every lower limit is below its upper one
            feasible = bool(np.all(ch.lo <= ch.hi))
        elif np.all(self.limits[:, 0] <= self.limits[:, 1]) and np.any(
                np.all((Q @ ch.A.T >= ch.lo) & (Q @ ch.A.T <= ch.hi), axis=1)):
            feasible = True  # a sampled configuration meets every limit: a proof, without the LP
        else:  # coupled limits: a linear program (scipy.optimize costs 0.4 to 4 s to import, so only here)
            from scipy.optimize import linprog

            res = linprog(np.zeros(self.n), A_ub=np.concatenate([ch.A, -ch.A]), b_ub=np.concatenate([ch.hi, -ch.lo]),
                          bounds=[(None, None)] * self.n, method="highs")
            feasible = res.status == 0
        if not feasible:
            raise ScenarioError(f"{where}: the joint limits leave no feasible configuration "
                                f"(box {self.limits.tolist()}, coupled limits "
                                f"{[(list(c.joints), c.lo, c.hi) for c in self.coupled_limits]})")
        rng = np.random.default_rng(0)
        Q = np.concatenate([Q, self.limits[:, 0] + rng.random((200, 3)) * np.ptp(self.limits, axis=1)])
        # pinocchio's Jacobians (about 5 ms for these 543), not the compiled chain's: loading a compiled
        # kernel costs a command 0.2 s, and compiling it on a first run about 10 s, before any work starts
        import pinocchio as pin

        model = self.model
        data = model.createData()
        fid = model.getFrameId(self.wrist)
        cols = [model.joints[j].idx_v for j in self._act_ids]
        J = np.empty((len(Q), 3, self.n))
        for k, q in enumerate(Q):
            J[k] = pin.computeFrameJacobian(model, data, self.pinocchio_configuration(q), fid,
                                            pin.LOCAL_WORLD_ALIGNED)[:3, cols]
        sv = np.linalg.svd(J, compute_uv=False)
        ratio = sv[:, -1] / np.maximum(sv[:, 0], 1e-300)
        if not np.any(ratio > 1e-8):
            raise ScenarioError(f"{where}: joints {list(self.joint_names)} cannot place the wrist '{self.wrist}' in 3-D "
                                "(its Jacobian is rank-deficient at every sampled configuration)")

    # ------------------------------------------------------------------ forward
    def _as_q(self, q) -> tuple[np.ndarray, tuple]:
        q = np.asarray(q, dtype=float)
        if q.shape[-1:] != (self.n,):
            raise ValueError(f"joint vectors must have shape (..., {self.n}), got {q.shape}")
        return kernel_array(q.reshape(-1, self.n)), q.shape[:-1]

    def forward(self, q) -> np.ndarray:
        """Wrist position (..., 3), world frame, for joint values ``q`` (..., n)."""
        Q, lead = self._as_q(q)
        out = np.empty((len(Q), 3))
        _fk_many(self.chain, Q, out)
        return out.reshape(lead + (3,))

    def jacobian(self, q) -> np.ndarray:
        """``d wrist / d q`` (..., 3, n): rows world x, y, z; columns the actuated joints."""
        Q, lead = self._as_q(q)
        out = np.empty((len(Q), 3, 3))
        _jac_many(self.chain, Q, out)
        return out.reshape(lead + (3, 3))

    def chain_points(self, q) -> np.ndarray:
        """World positions (..., k, 3) of the root, the joint origins on the chain and the wrist
        (for drawing the arm as a polyline)."""
        q = np.asarray(q, dtype=float)
        if q.shape[-1:] != (self.n,):
            raise ValueError(f"joint vectors must have shape (..., {self.n}), got {q.shape}")
        lead = q.shape[:-1]
        Q = q.reshape(-1, self.n)
        m = len(Q)
        T = self.chain.T
        pts = [np.broadcast_to(self._segments[0], (m,) + self._segments[0].shape)]
        M = np.broadcast_to(T[0], (m, 4, 4)).copy()
        for i in range(self.n):
            ax = self.chain.axis[i]
            X = np.broadcast_to(np.eye(4), (m, 4, 4)).copy()
            if self.chain.jtype[i] == 0:
                c, s = np.cos(Q[:, i]), np.sin(Q[:, i])
                K = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
                X[:, :3, :3] = (np.eye(3) + s[:, None, None] * K + (1 - c)[:, None, None] * (K @ K))
            else:
                X[:, :3, 3] = Q[:, i, None] * ax
            Mi = M @ X            # child frame of joint i
            local = self._segments[i + 1]
            if len(local):
                pts.append(np.einsum("mij,kj->mki", Mi[:, :3, :3], local) + Mi[:, None, :3, 3])
            M = Mi @ T[i + 1]
        pts.append(M[:, None, :3, 3])  # the wrist origin
        out = np.concatenate(pts, axis=1)
        return out.reshape(lead + out.shape[1:])

    # ------------------------------------------------------------------ limits
    def within_limits(self, q, tol: float = 1e-12) -> np.ndarray:
        """Mask of configurations inside the box and coupled limits (with slack ``tol``)."""
        q = np.asarray(q, dtype=float)
        v = q @ self.chain.A.T
        return np.all((v >= self.chain.lo - tol) & (v <= self.chain.hi + tol), axis=-1)

    def limit_margin(self, q) -> np.ndarray:
        """Smallest distance of ``q`` to any limit row (rad / m); negative outside the limits."""
        q = np.asarray(q, dtype=float)
        v = q @ self.chain.A.T
        return np.minimum(v - self.chain.lo, self.chain.hi - v).min(axis=-1)

    # ------------------------------------------------------------------ reachability and IK
    def kernel(self) -> tuple[ChainData, ReachMap]:
        """``(ChainData, ReachMap)`` for the compiled kernels (the map is built on first use)."""
        return self.chain, self.reach_map()

    def reach_map(self) -> ReachMap:
        """The reachability map: from memory, from the disk cache, or built and cached (:mod:`.reachmap`)."""
        if self._rmap is None:
            self._rmap = reach_map_of(self)
        return self._rmap

    def _points(self, w) -> tuple[np.ndarray, tuple]:
        w = np.asarray(w, dtype=float)
        if w.shape[-1:] != (3,):
            raise ValueError(f"points must have shape (..., 3), got {w.shape}")
        return kernel_array(w.reshape(-1, 3)), w.shape[:-1]

    def reachable(self, w) -> np.ndarray:
        """Mask (...) of wrists ``w`` (..., 3) reachable within all limits (the map, exact IK at its
        boundary; see the module docstring)."""
        W, lead = self._points(w)
        chain, rmap = self.kernel()
        out = np.empty(len(W), np.bool_)
        _reach_many(chain, rmap, W, out)
        return out.reshape(lead)

    def inverse(self, w, near=None) -> tuple[np.ndarray, np.ndarray]:
        """Joint values putting the wrist at ``w`` (..., 3) within all limits, any branch.

        ``near`` (..., n), optional: a configuration tried first as the starting point (keeps a
        trajectory on its branch). Returns ``(q, ok)``: ``q`` (..., n), NaN where unreachable.
        """
        W, lead = self._points(w)
        chain, rmap = self.kernel()
        Q = np.empty((len(W), self.n))
        ok = np.empty(len(W), np.bool_)
        if near is None:
            _ik_many(chain, rmap, W, np.empty((len(W), self.n)), False, Q, ok)
        else:
            N = kernel_array(np.broadcast_to(np.asarray(near, float), lead + (self.n,)).reshape(-1, self.n))
            _ik_many(chain, rmap, W, N, True, Q, ok)
        return Q.reshape(lead + (self.n,)), ok.reshape(lead)

    # ------------------------------------------------------------------ sampling
    def sample_wrists(self, n_per_joint: int = 41) -> np.ndarray:
        """Wrist positions (m, 3) over an ``n_per_joint``^n grid of the joint box, inside all limits."""
        g = [np.linspace(lo, hi, n_per_joint) for lo, hi in self.limits]
        Q = np.stack(np.meshgrid(*g, indexing="ij"), axis=-1).reshape(-1, self.n)
        return self.forward(Q[self.within_limits(Q)])

    def min_distance_to(self, p, n_per_joint: int = 41) -> float:
        """Distance from point ``p`` to the workspace: 0 if reachable, else to the nearest sampled wrist."""
        p = np.asarray(p, dtype=float)
        if bool(self.reachable(p)):
            return 0.0
        w = self.sample_wrists(n_per_joint)
        if len(w) == 0:
            return float("inf")
        return float(np.min(np.linalg.norm(w - p, axis=-1)))

    def nearer_than(self, p, r: float) -> bool:
        """Whether some reachable wrist lies closer than ``r`` to point ``p``. The map answers alone when
        a voxel certified in lies closer than ``r``, or every voxel not certified out lies at least ``r``
        away (about 10 ms, no compiled kernel); otherwise :meth:`min_distance_to` does."""
        rm = self.reach_map()
        p = np.asarray(p, dtype=float)
        d2 = 0.0
        for a in range(3):  # squared distance from p to each voxel's box, axis by axis
            lo = rm.origin[a] + rm.h * np.arange(rm.shape[a])
            da = np.maximum(np.maximum(lo - p[a], p[a] - (lo + rm.h)), 0.0) ** 2
            d2 = d2 + da.reshape([-1 if b == a else 1 for b in range(3)])
        if np.any(d2[rm.state == 1] < r * r):
            return True
        if not np.any(d2[rm.state != 0] < r * r):
            return False
        return self.min_distance_to(p) < r

    # ------------------------------------------------------------------ gravity
    def _gravity_model(self):
        if self._gravity is None:
            import pinocchio as pin
            model = pin.Model(self.model)
            g_world = np.array([0.0, -GRAVITY, 0.0])
            model.gravity.linear = rpy_matrix(self.base_rpy).T @ g_world
            data = model.createData()
            pin.computeSubtreeMasses(model, data)
            for name, jid in zip(self.joint_names, self._act_ids):
                if not data.mass[jid] > 0.0:
                    raise ErrplanError(f"URDF {self.urdf_path}: the links moved by joint '{name}' carry no inertial "
                                       "data (mass 0), so it has no gravity torque; add <inertial> to those links")
            self._gravity = (model, data)
        return self._gravity

    def gravity_torque(self, q) -> np.ndarray:
        """Generalized gravity (..., n) at the actuated joints (N m or N): ``dV/dq`` with world
        gravity 9.81 m/s^2 along -y; held joints at their values, joints off the chain at zero."""
        import pinocchio as pin
        model, data = self._gravity_model()
        Q, lead = self._as_q(q)
        out = np.empty((len(Q), self.n))
        qp = self._qref.copy()
        vidx = [model.joints[j].idx_v for j in self._act_ids]
        for k, qk in enumerate(Q):
            for jid, val in zip(self._act_ids, qk):
                jm = model.joints[jid]
                if jm.nq == 1:
                    qp[jm.idx_q] = val
                else:
                    qp[jm.idx_q], qp[jm.idx_q + 1] = math.cos(val), math.sin(val)
            tau = pin.computeGeneralizedGravity(model, data, qp)
            out[k] = np.asarray(tau)[vidx]
        return out.reshape(lead + (self.n,))

    def pinocchio_configuration(self, q) -> np.ndarray:
        """Pinocchio configuration vector of the whole model for actuated values ``q`` (n,)."""
        qp = self._qref.copy()
        for jid, val in zip(self._act_ids, np.asarray(q, float)):
            jm = self.model.joints[jid]
            if jm.nq == 1:
                qp[jm.idx_q] = val
            else:
                qp[jm.idx_q], qp[jm.idx_q + 1] = math.cos(val), math.sin(val)
        return qp

    # ------------------------------------------------------------------ meshes
    def resolve_uri(self, uri: str) -> Path | None:
        """File for a URDF mesh URI, or None. ``package://NAME/rest`` is looked up in ``package_path``,
        ``$ROS_PACKAGE_PATH`` and the environment's description packages (:mod:`errplan.packages`;
        relative folders against the URDF's); ``file://`` and plain paths are relative to the URDF's folder."""
        if uri.startswith(packages.SCHEME):
            return packages.resolve(uri, packages.search_dirs(self.package_path, self.urdf_path.parent))
        if uri.startswith("file://"):
            uri = uri[len("file://"):]
        if "://" in uri:
            return None
        cand = Path(uri)
        if not cand.is_absolute():
            cand = self.urdf_path.parent / cand
        return cand if cand.is_file() else None
