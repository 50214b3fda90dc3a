"""Arms outside the body in planning: with ``[setup] arm_clearance``, the moving arm's links keep that
distance from every other arm's links (docs/physics.md, "Several instruments and the endoscope", "Arms
outside"), in OMPL's validity and motion checks and in the refinement, as the anatomy and the held shafts
are kept clear.

The model (:class:`ArmChecks`, built once per plan from the scenario :meth:`errplan.scenario.Setup.moving`
gives, :attr:`errplan.scenario.Scenario.held_arms`):

* every other arm is held with its tip at its ``rest`` point through its port estimate: its configuration
  (:func:`~errplan.kinematics.urdf.collision.arm_at_tip`) and its links' placements are computed once
  (:class:`~errplan.kinematics.urdf.collision.HeldArm`);
* the moving arm at tip ``t`` is the inverse kinematics that puts its wrist on the rigid shaft from ``t``
  through its port estimate (``arm_at_tip``), started from the arm's configuration at its own rest tip
  (:attr:`reference`): one branch of the inverse kinematics over the whole task region, so that a tip's
  verdict does not depend on which solution a solver happened to reach;
* a tip is valid when that configuration exists and its links are at least ``arm_clearance`` from every
  held arm's (coal's exact mesh distances);
* a straight tip motion ``a -> b`` is valid when the arm's joint-space motion through the configurations
  of the tips ``a + s (b - a)``, sampled every ``tip_step`` (1 mm) along ``a -> b`` (each found from the
  previous one, one branch along the motion), keeps that clearance at every sample of
  :func:`~errplan.kinematics.urdf.collision.motion_samples` (no point of a link moves more than
  ``arm_clearance / 2`` between two samples of the piecewise-straight joint-space motion through those
  configurations), with :func:`~errplan.kinematics.urdf.collision.clear_along_held`'s exact skipping.

What that guarantees, and what it approximates. Along the sampled joint-space polyline every
configuration is at least ``arm_clearance / 2`` clear (clearance is 1-Lipschitz in the links' motion and
no link point moves more than ``arm_clearance / 2`` between samples), and every sample, among them the
arm at every tip of the 1 mm tip samples, is at least ``arm_clearance`` clear. The arm's true motion
between two tip samples is the inverse kinematics of the tips in between, not the straight joint-space
line between the two configurations: the two differ by the curvature of the inverse kinematics over 1 mm
of tip motion (second order in the step: a few micrometres of link motion for a UR5 away from its
singularities), which this check does not bound. The ``arm_clearance`` itself is the margin; the
independent test samples the tips four times finer, solves the inverse kinematics from scratch and
measures with a second distance method.

The planner's hot path (:meth:`ArmChecks.point_ok`, :meth:`ArmChecks.motion_ok`; ``compiled`` True) takes
the six plain floats of a motion to one compiled call
(:func:`~errplan.kinematics.urdf.broadphase.arm_check`, :func:`~errplan.kinematics.urdf.broadphase.arm_motion`
on the arms' shapes packed in two buffers): the wrists on the shaft, the inverse kinematics
at every tip sample (the same branch rules as :meth:`ArmChecks.motion_configs`), the joint-space samples,
the links' placements, a conservative broad phase against the held arms (per object a bounding sphere,
then the capsules of its mesh pieces) and an exact narrow phase on the pairs of mesh pieces it leaves (the
pair's nearest triangles of the check before, a support bound on the pieces' convex hulls, then the distance
of their triangles, pruned by the triangles' capsules and by projections on separating lines; the checks keep
each pair's nearest triangles and separating direction from one check to the next, which changes no answer);
along a motion a pair of objects is looked at again only once its object may have moved as far as it was
found above the clearance. Only the pairs a primitive's piece takes part in (or whose distance ties with the
clearance within 1 nm) go to coal (:func:`~errplan.kinematics.urdf.collision.first_within`): at a tip its
collision test with the clearance as security margin; along a motion its exact distance, so that the later
samples of the same two pieces are skipped while their link has moved less than that distance above the
clearance. The answers are the Python check's (:meth:`ArmChecks.point_ok_exact`, :meth:`ArmChecks.motion_ok_exact`, kept
as the reference; tests/test_arm_broadphase.py compares them, and both with coal's distance); the
reported clearances (:meth:`ArmChecks.path_clearance`, :meth:`ArmChecks.rest_clearance`) stay coal's exact
distances computed as before.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ErrplanError
from ..kinematics import arm_for
from ..jit import kernel_array
from ..kinematics.urdf.broadphase import CLEAR, UNDECIDED, arm_check, object_travel, pack_shapes, piece_memory
from ..kinematics.urdf.collision import (ArmCollision, HeldArm, arm_at_tip, clear_along_held, clearance_to_held,
                                         first_within, held_objects, held_shapes, min_clearance_along_held,
                                         within_held)

#: m: the spacing of the tip samples along a straight motion (each one inverse kinematics solve)
TIP_STEP = 0.001


@dataclass
class ArmChecks:
    """The moving arm's links against the held arms' (module docstring). Build with :meth:`from_model`.

    ``arm`` (the moving ``UrdfArm``), ``geo`` (its :class:`ArmCollision`), ``port`` (3,) its port
    estimate, ``length`` its shaft, ``held`` (:class:`HeldArm` per other arm, named), ``clearance`` (m),
    ``tip_step`` (m)."""

    arm: object
    geo: ArmCollision
    port: np.ndarray
    length: float
    held: tuple
    clearance: float
    reference: np.ndarray | None = None
    tip_step: float = TIP_STEP
    compiled: bool = True

    def __getstate__(self):
        state = dict(self.__dict__)
        state.pop("_kargs", None)  # coal's transforms: rebuilt on first use
        state.pop("_memory", None)
        state.pop("_packed", None)
        return state

    @classmethod
    def from_model(cls, m) -> "ArmChecks | None":
        """The checks of the moving arm's model (:class:`errplan.models.ArmModel`: its kinematics, and
        ``held_arms`` of its scenario, set by :meth:`errplan.scenario.Setup.moving`); None without
        ``[setup] arm_clearance``."""
        sc = m.scenario
        spec = sc.held_arms
        if spec is None:
            return None
        arm = m.arm
        geo = ArmCollision.from_arm(arm)
        held = []
        for name, robot, port, length, rest in spec.arms:
            other = arm_for(robot)
            try:
                q = arm_at_tip(other, rest, port, length)
            except ErrplanError as err:
                raise ErrplanError(f"{sc.source}: [[arm]] {name!r} rest = {list(rest)}: {err}") from None
            held.append(HeldArm(ArmCollision.from_arm(other), q, name))
        port, length = np.asarray(sc.port.estimate, float), float(sc.instrument.length)
        ref = None
        if spec.rest is not None:
            try:
                ref = arm_at_tip(arm, spec.rest, port, length)
            except ErrplanError as err:
                raise ErrplanError(f"{sc.source}: the moving arm's rest = {list(spec.rest)}: {err}") from None
        return cls(arm, geo, port, length, tuple(held), float(spec.clearance), ref)

    # ------------------------------------------------------------------ configurations
    def wrists(self, tips: np.ndarray) -> np.ndarray | None:
        """Wrist points (k, 3) of the rigid shaft from each tip through the port; None when a tip is at the port."""
        d = tips - self.port
        nd = np.linalg.norm(d, axis=1)
        if not np.all(nd > 0.0):
            return None
        return tips - self.length * d / nd[:, None]

    def config(self, t, near=None) -> np.ndarray | None:
        """The configuration (n,) at tip ``t`` (:func:`arm_at_tip`, started from ``near``, by default
        :attr:`reference`), None when out of reach."""
        try:
            return arm_at_tip(self.arm, t, self.port, self.length, near=self.reference if near is None else near)
        except ErrplanError:
            return None

    def motion_configs(self, a, b) -> np.ndarray | None:
        """Configurations (k, n) at the tips ``a + s (b - a)``, ``s`` every :attr:`tip_step` of the motion
        (both ends included), each on the branch of the one before; None when a tip is out of reach."""
        a = np.asarray(a, float)
        b = np.asarray(b, float)
        k = max(1, math.ceil(float(np.linalg.norm(b - a)) / self.tip_step))
        tips = a + (np.arange(k + 1)[:, None] / k) * (b - a)
        W = self.wrists(tips)
        q0 = self.config(a)
        if W is None or q0 is None:
            return None
        Q, ok = self.arm.inverse(W, near=q0)
        if not bool(np.all(ok)):
            return None
        Q[0] = q0
        # one branch: a step between neighbouring tips moves a link point by far more than the tip when the
        # start from q0 converged to another branch; redo from there, each from the previous one
        jump = self.geo.reach @ np.abs(np.diff(Q, axis=0)).T
        bad = np.flatnonzero(np.max(jump, axis=0) > 50.0 * self.tip_step) if len(Q) > 1 else []
        if len(bad):
            for i in range(int(bad[0]) + 1, len(Q)):
                q, ok1 = self.arm.inverse(W[i], near=Q[i - 1])
                if not bool(ok1):
                    return None
                Q[i] = q
        return Q

    # ------------------------------------------------------------------ checks
    def _kernel_args(self) -> tuple:
        """What :func:`~errplan.kinematics.urdf.broadphase.arm_motion` takes besides the motion, and the
        held objects for coal (built on first use)."""
        args = self.__dict__.get("_kargs")
        if args is None:
            chain, rmap = self.arm.kernel()
            ref = np.full(self.arm.n, np.nan) if self.reference is None else np.asarray(self.reference, float)
            tree, held = self.geo.link_tree(), held_shapes(self.held)
            args = self.__dict__["_kargs"] = (
                (chain, rmap, tree, held),
                (kernel_array(np.array(self.port, float)), float(self.length), kernel_array(ref.copy()),
                 float(self.tip_step), float(self.clearance)),
                held_objects(self.held))
            # each pair of pieces' witness triangles and separating direction, from check to check
            self.__dict__["_memory"] = piece_memory(tree, held)
            self.__dict__["_packed"] = pack_shapes(tree, held)  # one call takes two buffers, not some 35 arrays
        return args

    def compiled_ok(self, ax: float, ay: float, az: float, bx: float, by: float, bz: float) -> bool:
        """:meth:`motion_ok_exact` (:meth:`point_ok_exact` when ``a == b``) by the compiled broad phase
        (module docstring): the same samples, coal's collision test only on the pairs of objects whose
        bounding volumes come closer than the clearance."""
        (chain, rmap, tree, _), (port, length, ref, step, c), objects = self._kernel_args()
        a = np.array((ax, ay, az))
        b = a if ax == bx and ay == by and az == bz else np.array((bx, by, bz))
        status, S, P, rows = arm_check(chain, rmap, *self._packed, a, b, port, length, ref, step, c, *self._memory)
        if status == UNDECIDED:
            travel = object_travel(tree.reach, S) if len(S) > 1 else None  # a motion: exact distances, skipping
            return first_within(self.geo, P, objects, rows, c, travel) < 0
        return status == CLEAR  # else out of reach, or two surface points closer than the clearance

    def point_ok(self, x: float, y: float, z: float) -> bool:
        """The arm at tip ``(x, y, z)`` exists and keeps the clearance (module docstring)."""
        if self.compiled:
            return self.compiled_ok(x, y, z, x, y, z)
        return self.point_ok_exact(x, y, z)

    def motion_ok(self, ax: float, ay: float, az: float, bx: float, by: float, bz: float) -> bool:
        """Every sample of the motion ``a -> b`` keeps the clearance (module docstring)."""
        if self.compiled:
            return self.compiled_ok(ax, ay, az, bx, by, bz)
        return self.motion_ok_exact(ax, ay, az, bx, by, bz)

    def point_ok_exact(self, x: float, y: float, z: float) -> bool:
        """:meth:`point_ok` in Python: the placements by pinocchio, every pair whose bounding spheres come
        closer than the clearance asked to coal (the reference of the compiled check)."""
        q = self.config((x, y, z))
        return q is not None and not within_held(self.geo, q, self.held, self.clearance)

    def motion_ok_exact(self, ax: float, ay: float, az: float, bx: float, by: float, bz: float) -> bool:
        """:meth:`motion_ok` in Python (:meth:`point_ok_exact`'s way), the reference of the compiled check."""
        if ax == bx and ay == by and az == bz:
            return self.point_ok_exact(ax, ay, az)
        Q = self.motion_configs((ax, ay, az), (bx, by, bz))
        return Q is not None and clear_along_held(self.geo, Q, self.held, self.clearance)

    def path_clearance(self, path) -> float:
        """The smallest clearance (m) between the moving arm along the path (n, 3), sampled as the motion
        check samples it, and every held arm; NaN where a tip is out of reach."""
        path = np.asarray(path, float).reshape(-1, 3)
        best = math.inf
        pieces = list(zip(path[:-1], path[1:])) or [(path[0], path[0])]
        for a, b in pieces:
            Q = self.motion_configs(a, b)
            if Q is None:
                return math.nan
            best = min(best, min_clearance_along_held(self.geo, Q, self.held, self.clearance))
        return float(best)

    def rest_clearance(self) -> float:
        """The smallest clearance (m) between the held arms themselves (each pair at rest); inf with one."""
        from ..kinematics.urdf.collision import arm_clearance

        best = math.inf
        for i, h in enumerate(self.held):
            for g in self.held[i + 1:]:
                best = min(best, arm_clearance(h.geo, h.q, g.geo, g.q))
        return best


def attach(cm, checks: ArmChecks | None):
    """Keep the moving arm's links clear of the held arms' in every check of the cost map ``cm`` (its
    point, motion, planner and refinement checks, beside the anatomy's and the view's): the arm check
    comes last, as the dearest. Sets ``cm.arm_checks``; returns ``cm``."""
    cm.arm_checks = checks
    if checks is None:
        return cm
    if cm.dim != 3:
        raise ErrplanError("arm checks are spatial: the cost map is planar")
    if checks.compiled:  # compile (a first run) or load the kernel now, not inside a search's time budget
        checks.compiled_ok(*checks.port, *checks.port)
    return cm.and_clear(checks.motion_ok)


def path_clear(cm, path) -> bool:
    """Whether every straight piece of ``path`` (n, 3) passes the arm checks of ``cm`` (True without any):
    the straight line and the coarse cell-graph path are candidates the planner's checks never saw."""
    checks = getattr(cm, "arm_checks", None)
    if checks is None:
        return True
    P = [[float(v) for v in p] for p in np.asarray(path, float).reshape(-1, 3)]
    return all(checks.motion_ok(*a, *b) for a, b in zip(P[:-1], P[1:])) if len(P) > 1 else checks.point_ok(*P[0])


def explain_point(cm, p, what: str = "point") -> str | None:
    """One line when tip ``p`` fails the arm checks of ``cm`` (out of the moving arm's reach on the rigid
    shaft, or its links closer than ``arm_clearance`` to a held arm's), else None."""
    checks = getattr(cm, "arm_checks", None)
    if checks is None:
        return None
    x = [float(v) for v in p]
    if len(x) != 3 or not all(math.isfinite(v) for v in x):
        return None  # the cost map's own explanation names it
    q = checks.config(x)
    if q is None:
        return None  # out of reach: the fields' robust workspace says so
    fmt = "[" + ", ".join(f"{v:.4f}" for v in x) + "]"
    for h in checks.held:
        d = clearance_to_held(checks.geo, q, (h,))
        if d < checks.clearance:
            return (f"{what} {fmt} m: the arm's links come {d * 1000:.1f} mm from arm {h.name!r} held at rest, "
                    f"less than [setup] arm_clearance = {checks.clearance * 1000:g} mm")
    return None
