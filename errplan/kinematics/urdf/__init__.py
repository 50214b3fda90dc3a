"""Serial arms described by a URDF (docs/physics.md "Spatial robots (3-D)").

One module per concept, imports pointing down: :mod:`.model` (the plain data: ChainData, ReachMap,
MapParams) <- :mod:`.chain` (compiled FK, Jacobians, IK) <- :mod:`.reachmap` (the reachability map)
<- :mod:`.description` (reading the URDF through pinocchio) <- :mod:`.arm` (:class:`UrdfArm`);
:mod:`.phantom` writes P1's PHANToM 1.5 as a URDF.

:class:`UrdfArm` mirrors the planar :class:`errplan.kinematics.arm.Arm` for any serial chain whose
three actuated ``joints`` place the origin of the ``wrist`` link in 3-D. Points are world
``[x, y, z]`` (y up, z toward the patient); the URDF root sits at ``base_position`` with
orientation ``R = Rz(yaw) Ry(pitch) Rx(roll)`` from ``base_rpy``. Every other joint on the chain
from the root to the wrist is held at its ``fixed_joints`` value (default 0).

Pinocchio parses the URDF (kinematic model only: meshes are never loaded, so missing meshes never
fail kinematics) and is the reference for the compiled kernels. The hot paths are numba kernels on
two namedtuples of plain arrays (:meth:`UrdfArm.kernel`):

* :class:`ChainData`: the chain as fixed transforms between the actuated joints;
* :class:`ReachMap`: a voxel map of the wrist workspace with the guarantees below.

Reachability map
----------------
Let ``Q`` be the feasible joint set (box and coupled limits: a polytope), ``f`` the wrist position
and ``W = f(Q)`` the workspace. Every boundary point of ``W`` is the image of a point of the faces
``dQ`` or of a singular configuration (``det J = 0``): anywhere else the inverse function theorem
makes the image an interior point. Image balls bound where joint-space pieces can go: for a cell
(or a planar patch) with centre ``c`` and half-widths ``e`` along directions ``t_i``::

    f(piece) lies in the ball B(f(c), rho),  rho = sum_i |J(c) t_i| e_i + K (sum_i |t_i| e_i)^2 / 2,

where ``K`` bounds the Lipschitz constant of ``J`` (every second derivative of a serial chain's
wrist is bounded by a distance from the wrist to a joint axis, so ``K`` follows from the link
lengths, :meth:`UrdfArm._lipschitz`). The build

1. covers each face of ``Q`` (both limits of every joint whose range is under 2 pi, both bounds of
   every coupled limit) with planar patches, halving them until ``rho <= beta h`` (``h`` the voxel
   edge), and marks every voxel that meets a patch ball *boundary*;
2. covers ``Q`` with coarse joint cells, halves those that may hold a singular configuration
   (not excluded by Weyl's inequality ``sigma_min(J(c)) > K |e|`` nor by a second-order bound on
   ``det J``, :meth:`UrdfArm._det_bound`) until ``rho <= beta h``, and marks the voxels meeting their
   balls *boundary*; every cell centre that satisfies all limits marks its wrist's voxel *hit*.

So a voxel not marked boundary meets no boundary point of ``W``: it lies entirely inside ``W`` or
entirely outside, and so does any face-connected set of such voxels. A flood fill labels them:

* **out (0)**: connected to the map's border layer, which lies outside the bounding box of all
  coarse-cell balls and so outside ``W``. Guarantee: no point of such a voxel is reachable.
* **in (1)**: connected to a hit voxel. Guarantee: every point of such a voxel is reachable within
  all limits.
* **boundary (2)**: the rest. :func:`reach_point` answers there with exact IK; a point counts as
  reached only when ``|f(q) - w| < 1e-10`` with every limit row holding. Where joints 1 and 2 turn
  about parallel axes (the PHANToM, a UR arm's shoulder lift and elbow) the closed form
  (:func:`chain._ik_parallel`) enumerates every solution and the turns of every joint, and decides
  but within 1e-4 rad (or m) of a limit, 1e-8 m of the workspace's edge, and near singular arms. Elsewhere, and in that margin, :func:`ik_point`'s projected Gauss-Newton runs from the seeds
  of the voxel's seed cell. That answer is as good as the seeds: configurations whose wrist falls
  in the seed cell or its 26 neighbours (patch and cell centres), one per cluster of nearby
  configurations, i.e. one per IK branch. Tests compare both with brute-force IK and the closed
  forms written in the tests.

The soundness of in/out rests on the bounds above (rounding is covered by relative slack); the
build reports ``conflicts`` (an out flood reaching a hit voxel), which must be 0.

The build is deterministic; its result is cached on disk (``$ERRPLAN_CACHE_DIR``, else
``~/.cache/errplan``) under a hash of the chain data (all that the URDF, joints, wrist, base pose,
limits, fixed joints and coupled limits contribute) and the map parameters, written atomically and
verified by a checksum when read (a bad file is rebuilt, never trusted).
"""
from __future__ import annotations

from ...scenario import CoupledLimit
from .arm import UrdfArm
from .description import rpy_matrix
from .chain import fk_point, ik_near, ik_point, jac_point, reach_point
from .model import GRAVITY, IK_TOL, LIMIT_TOL, MAP_VERSION, ChainData, MapParams, ReachMap, cache_dir
from .phantom import ALUMINIUM_DENSITY, PHANTOM_HOME, PHANTOM_LIMITS, PHANTOM_LINKS, PHANTOM_SHOULDER, PHANTOM_SUM_LIMITS, ROD_RADIUS, phantom_urdf

__all__ = ["UrdfArm", "ChainData", "ReachMap", "MapParams", "CoupledLimit", "cache_dir", "fk_point", "jac_point",
           "ik_point", "ik_near", "reach_point", "phantom_urdf", "rpy_matrix", "GRAVITY", "IK_TOL", "LIMIT_TOL", "MAP_VERSION",
           "ALUMINIUM_DENSITY", "ROD_RADIUS", "PHANTOM_HOME", "PHANTOM_LIMITS", "PHANTOM_LINKS", "PHANTOM_SHOULDER",
           "PHANTOM_SUM_LIMITS"]
