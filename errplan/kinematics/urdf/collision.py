"""Arms outside the body: the links of different arms keep a clearance (docs/physics.md, "Several
instruments and the endoscope", "Arms outside").

Each arm's links are the URDF's collision geometry, read by pinocchio into a ``GeometryModel`` (meshes
resolved exactly as the arm resolves them, :meth:`UrdfArm.resolve_uri`) and placed at the arm's base
pose and configuration; distances are coal's (the collision library pinocchio ships): exact
mesh-mesh distances, 0 (or a negative penetration depth for primitive shapes) when two objects touch or
overlap. This is the only module of errplan that imports coal or builds a ``GeometryModel``.

* :class:`ArmCollision` (:meth:`ArmCollision.from_arm`): one arm's collision objects, built once;
* :func:`arm_clearance`: the smallest distance between the objects of two arms at one configuration each;
  :func:`clearances`, the same for a batch of configuration pairs; :func:`clear_of`, its yes/no against
  a required clearance (coal's collision query with a security margin, no distance);
* :func:`min_clearance_along`: the same along a joint-space motion of one arm, sampled densely enough
  that no link point moves more than ``clearance / 2`` between samples; :func:`clear_along`, the
  yes/no of it with fewer distance queries (a motion validity check);
* :class:`HeldArm`, :func:`clearance_to_held`, :func:`within_held`, :func:`clear_along_held`,
  :func:`min_clearance_along_held`: the same against several arms held still, their placements computed
  once (the planner's arm checks, :mod:`errplan.planning.arm_checks`); :func:`within_held` answers "closer
  than c?" by coal's collision test with security margin c, about a hundred times cheaper than a distance;
* :func:`arm_at_tip`: the configuration that puts the instrument tip at ``t`` through port ``p``;
* the arms and the patient (docs/physics.md "Where the arms stand: setup placement"): :class:`BodySolid`,
  the solid bounded by the body wall (the ellipsoid wall as coal's ``Ellipsoid``, a mesh wall as coal's
  ``Convex`` of its vertices: its convex hull, a solid for GJK, so a link inside it is at distance <= 0);
  :func:`link_distances`, :func:`patient_clearances` (exact distances of the links, not the instrument
  shaft, which passes through the port by design) and :func:`patient_clear` (coal's collision test with a
  security margin);
* for the compiled broad and narrow phases (:mod:`.broadphase`): :meth:`ArmCollision.link_tree` (the arm's
  joints and objects as plain arrays), :meth:`ArmCollision.capsules` and :meth:`ArmCollision.pieces` (each
  mesh split into up to :data:`CAPSULE_PIECES` pieces of its triangles, each piece a coal mesh with a
  bounding capsule), :meth:`ArmCollision.piece_triangles` (the pieces' triangles, each with a capsule,
  :func:`triangle_capsules`), :func:`held_shapes`, and
  :func:`first_within` (coal on the pairs of pieces the compiled phases leave undecided: a primitive's).

Configurations are the arm's actuated-joint vectors ``(n,)`` (``UrdfArm``'s order); joints off the
actuated set stay where the arm holds them (``fixed_joints``, else 0).

Pruning: each object carries a bounding sphere (centre of its local bounding box, radius the largest
distance of its vertices, or of the box corners for a primitive, from that centre); a pair whose spheres
lie farther apart than the smallest distance found so far cannot hold the minimum, so pairs are visited
nearest spheres first and the search stops at the first pair whose sphere gap reaches the minimum. The
result is the exact minimum over all pairs while they are clear (and the same on every run: the order is
a stable sort); once a pair touches or overlaps (distance <= 0) the search stops there.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ...errors import ErrplanError
from .arm import UrdfArm
from .broadphase import SLACK, HeldShapes, LinkTree, tree_arrays
from .description import rpy_matrix

KINDS = ("collision", "visual")


@dataclass(frozen=True)
class Closest:
    """The closest pair of two arms' objects: ``distance`` (m, <= 0 when they touch or overlap), the
    objects' names and the nearest points (world, (3,)) on each (where coal reports them)."""

    distance: float
    name_a: str
    name_b: str
    point_a: np.ndarray
    point_b: np.ndarray


class ArmCollision:
    """One arm's collision objects (module docstring). Build with :meth:`from_arm`.

    Attributes: ``arm`` (the :class:`UrdfArm`), ``geometry_model`` (pinocchio's ``GeometryModel``),
    ``names`` (one per object), ``base`` (4, 4) the arm's base pose (URDF root -> world),
    ``reach`` (objects, n): ``reach[g, j]`` bounds how far a point of object ``g`` moves per unit of
    actuated joint ``j`` (:meth:`motion_bound`).
    """

    def __init__(self, arm: UrdfArm, geometry_model, kind: str):
        import pinocchio as pin

        self.arm = arm
        self.kind = kind
        self.geometry_model = geometry_model
        self.names = tuple(g.name for g in geometry_model.geometryObjects)
        self._geoms = [g.geometry for g in geometry_model.geometryObjects]
        self._data = arm.model.createData()
        self._gdata = pin.GeometryData(geometry_model)
        B = np.eye(4)
        B[:3, :3] = rpy_matrix(arm.base_rpy)
        B[:3, 3] = arm.base_position
        self.base = B
        hulls = [_hull_points(g) for g in self._geoms]
        self._hulls = hulls
        self._center = np.array([0.5 * (h.min(axis=0) + h.max(axis=0)) for h in hulls])
        self._radius = np.array([float(np.max(np.linalg.norm(h - c, axis=1))) for h, c in zip(hulls, self._center)])
        self.reach = self._reach_bounds()

    def __reduce__(self):
        """Pickled as its arm and kind (pinocchio's GeometryData does not pickle): a dask worker rebuilds
        the same objects from the same URDF (about 30 ms for a UR5)."""
        return (type(self).from_arm, (self.arm, self.kind))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_arm(cls, arm: UrdfArm, kind: str = "collision") -> "ArmCollision":
        """The arm's ``collision`` (default) or ``visual`` geometry as pinocchio reads it from the arm's URDF,
        every mesh URI resolved by :meth:`UrdfArm.resolve_uri`, placed at the arm's base pose.

        Raises :class:`ErrplanError` naming the URDF when it has no such geometry, and naming the URI of
        a mesh that cannot be found or read.
        """
        import pinocchio as pin

        if kind not in KINDS:
            raise ErrplanError(f"geometry kind must be one of {list(KINDS)}, got {kind!r}")
        where = str(arm.urdf_path)
        root = ET.fromstring(arm.urdf_text)
        count = 0
        for link in root.iter("link"):
            for elem in link.findall(kind):
                geom = elem.find("geometry")
                if geom is None or len(geom) == 0:
                    continue
                count += 1
                for mesh in geom.iter("mesh"):
                    uri = mesh.get("filename", "")
                    path = arm.resolve_uri(uri)
                    if path is None:
                        raise ErrplanError(f"URDF {where}: {kind} mesh '{uri}' of link '{link.get('name')}' "
                                           "was not found (package_path, ROS_PACKAGE_PATH, installed description "
                                           "packages, the URDF's folder)")
                    mesh.set("filename", str(path))
        if count == 0:
            raise ErrplanError(f"URDF {where} has no {kind} geometry; arm checks need it")
        text = ET.tostring(root, encoding="unicode")
        gtype = pin.GeometryType.COLLISION if kind == "collision" else pin.GeometryType.VISUAL
        try:
            gm = pin.buildGeomFromUrdfString(arm.model, text, gtype)
        except Exception as exc:  # pinocchio/assimp: ValueError, RuntimeError on an unreadable mesh
            reason = " ".join(str(exc).split())[:300] or type(exc).__name__
            raise ErrplanError(f"URDF {where}: its {kind} geometry cannot be read ({reason})") from None
        if gm.ngeoms == 0:
            raise ErrplanError(f"URDF {where} has no {kind} geometry; arm checks need it")
        return cls(arm, gm, kind)

    def _reach_bounds(self) -> np.ndarray:
        """``reach[g, j]``: for a revolute actuated joint j upstream of object g, a bound on the distance
        of any point of g from a point of j's axis (the joint frame's origin), valid at EVERY
        configuration; 1 for a prismatic one; 0 when j does not move g.

        Why configuration-free: let ``a_1 < ... < a_m`` be the actuated joints upstream of g (root to
        g). Between two consecutive ones only held joints lie, so the origin of ``a_{l+1}`` is fixed in
        the child frame of ``a_l``; that frame turns about an axis through its own origin (revolute) or
        moves with it (prismatic), so ``|o_{a_l} - o_{a_{l+1}}|`` never changes, nor the distance of a
        point of g from ``o_{a_m}``. By the triangle inequality every point x of g has
        ``|x - o_{a_i}| <= sum_{l=i}^{m-1} |o_{a_l} - o_{a_{l+1}}| + max_x |x - o_{a_m}|``, all measured at
        one configuration (the arm's reference). Points of g are within the convex hull of its vertices
        (the corners of its bounding box for a primitive), so the maximum is over those points."""
        import pinocchio as pin

        arm, model, data = self.arm, self.arm.model, self._data
        q0 = arm.pinocchio_configuration(np.zeros(arm.n))
        pin.forwardKinematics(model, data, q0)
        pin.updateGeometryPlacements(model, data, self.geometry_model, self._gdata)
        act = list(arm._act_ids)
        prismatic = [_is_prismatic(model.joints[j]) for j in act]
        reach = np.zeros((len(self._geoms), arm.n))
        for g, obj in enumerate(self.geometry_model.geometryObjects):
            ups = []
            jid = obj.parentJoint
            while jid != 0:
                if jid in act:
                    ups.append(act.index(jid))
                jid = model.parents[jid]
            ups.reverse()  # root to object
            if not ups:
                continue
            M = self._gdata.oMg[g].homogeneous
            pts = self._hulls[g] @ M[:3, :3].T + M[:3, 3]
            origin = [np.asarray(data.oMi[act[i]].translation) for i in ups]
            r = float(np.max(np.linalg.norm(pts - origin[-1], axis=1)))
            for k in range(len(ups) - 1, -1, -1):
                reach[g, ups[k]] = 1.0 if prismatic[ups[k]] else r
                if k:
                    r += float(np.linalg.norm(origin[k] - origin[k - 1]))
        return reach

    # ------------------------------------------------------------------ placements
    def _check_q(self, q, what: str = "q") -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if q.shape != (self.arm.n,):
            raise ErrplanError(f"{what} must be {self.arm.n} joint values of {self.arm.urdf_path.name}, got shape {q.shape}")
        if not np.all(np.isfinite(q)):
            raise ErrplanError(f"{what} must be finite joint values, got {q.tolist()}")
        return q

    def placements(self, q) -> np.ndarray:
        """World placements (objects, 4, 4) of the objects at actuated joint values ``q`` (n,)."""
        import pinocchio as pin

        q = self._check_q(q)
        pin.forwardKinematics(self.arm.model, self._data, self.arm.pinocchio_configuration(q))
        pin.updateGeometryPlacements(self.arm.model, self._data, self.geometry_model, self._gdata)
        return np.array([self.base @ M.homogeneous for M in self._gdata.oMg])

    def motion_bound(self, dq) -> float:
        """Bound (m) on how far any point of any object moves along the straight joint-space motion
        ``q -> q + dq``, from any ``q``: ``max_g sum_j |dq_j| reach[g, j]``.

        Along ``q(s) = q + s dq`` a point x of object g moves with velocity
        ``sum_j (w_j x (x - o_j)) dq_j`` (revolute; ``dq_j`` times a unit axis for a prismatic joint), the
        geometric Jacobian's columns, so its speed is at most ``sum_j |dq_j| |x - o_j|`` and its
        displacement, the integral over s in [0, 1], at most ``sum_j |dq_j| reach[g, j]``
        (:meth:`_reach_bounds`: ``|x - o_j|`` bounded at every configuration)."""
        dq = np.abs(np.asarray(dq, dtype=float))
        return float(np.max(self.reach @ dq)) if len(self.reach) else 0.0

    # ------------------------------------------------------------------ the compiled broad phase
    def link_tree(self) -> LinkTree:
        """The arm's joints and objects as plain arrays for the compiled broad phase
        (:class:`~.broadphase.LinkTree`): pinocchio's kinematic tree with every joint off the actuated set
        at its held value, each actuated joint's axis read from pinocchio's own motion of it, the objects'
        bounding spheres and capsules (:meth:`capsules`), :attr:`reach`. Built once."""
        tree = getattr(self, "_tree", None)
        if tree is not None:
            return tree
        import pinocchio as pin

        arm, model = self.arm, self.arm.model
        data = model.createData()
        act = list(arm._act_ids)
        pin.forwardKinematics(model, data, arm.pinocchio_configuration(np.zeros(arm.n)))
        J = model.njoints - 1
        jparent = np.array([model.parents[j] - 1 for j in range(1, model.njoints)], np.int64)
        jconst = np.array([data.liMi[j].homogeneous for j in range(1, model.njoints)]).reshape(J, 4, 4)
        jact = np.full(J, -1, np.int64)
        jkind = np.zeros(J, np.int64)
        jaxis = np.zeros((J, 3))
        for k, j in enumerate(act):
            C = model.jointPlacements[j].homogeneous
            unit = np.zeros(arm.n)
            unit[k] = 1.0
            pin.forwardKinematics(model, data, arm.pinocchio_configuration(unit))
            X = np.linalg.solve(C, data.liMi[j].homogeneous)  # the joint's own motion at q_k = 1
            jact[j - 1] = k
            jconst[j - 1] = C
            if _is_prismatic(model.joints[j]):
                jkind[j - 1] = 1
                jaxis[j - 1] = X[:3, 3]
            else:
                jaxis[j - 1] = np.asarray(pin.log3(X[:3, :3]), float)  # angle 1 rad about the unit axis
        objs = self.geometry_model.geometryObjects
        gparent = np.array([o.parentJoint - 1 for o in objs], np.int64)
        gplace = np.array([o.placement.homogeneous for o in objs]).reshape(len(objs), 4, 4)
        caps = self.capsules()
        start = np.searchsorted(caps[0], np.arange(len(objs) + 1), side="left").astype(np.int64)
        tcap, tris, ta, tb, tr = self.piece_triangles()
        tstart = np.searchsorted(tcap, np.arange(len(caps[0]) + 1), side="left").astype(np.int64)
        hcap, hull = self.piece_hulls()
        hstart = np.searchsorted(hcap, np.arange(len(caps[0]) + 1), side="left").astype(np.int64)
        self._tree = tree_arrays(LinkTree(jparent, jconst, jact, jkind, jaxis, gparent, gplace, self.base, self.reach,
                                          self._center, self._radius, caps[1], caps[2], caps[3], start, tris, ta, tb,
                                          tr, tstart, hull, hstart))
        return self._tree

    def capsules(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Bounding capsules of the objects, in each object's frame: ``(object (C,) int, a (C, 3), b (C, 3),
        radius (C,))``, sorted by object. A mesh is split along its principal axis into up to
        :data:`CAPSULE_PIECES` groups of triangles (by their centroids), each group bounded by one capsule
        holding its triangles' vertices (so, being convex, its triangles) (:func:`_object_capsules`). A
        primitive gets one capsule holding the corners of its bounding box. Built once."""
        caps = getattr(self, "_capsules", None)
        if caps is None:
            obj, A, B, R, pieces = [], [], [], [], []
            for g, geom in enumerate(self._geoms):
                groups = _object_capsules(geom, self._hulls[g])
                for a, b, r, tris in groups:
                    obj.append(g)
                    A.append(a)
                    B.append(b)
                    R.append(r)
                    pieces.append(geom if len(groups) == 1 else _sub_mesh(geom, tris))
            caps = self._capsules = (np.array(obj, np.int64), np.array(A, float).reshape(-1, 3),
                                     np.array(B, float).reshape(-1, 3), np.array(R, float))
            self._pieces = pieces
        return caps

    def pieces(self) -> list:
        """One coal geometry per capsule of :meth:`capsules`, in the object's frame: the object itself where
        it has one capsule, else the mesh of that capsule's triangles (the pieces of an object partition its
        triangles, so two objects come closer than ``c`` iff two of their pieces do)."""
        self.capsules()
        return self._pieces

    def piece_triangles(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The triangles of every mesh piece (:meth:`pieces`), in its object's frame, for the compiled narrow
        phase: ``(capsule (t,) int, vertices (t, 3, 3), a (t, 3), b (t, 3), radius (t,))``, sorted by capsule,
        with a capsule holding each triangle (:func:`triangle_capsules`). A primitive's piece has none. Built
        once."""
        out = getattr(self, "_piece_tris", None)
        if out is None:
            self.capsules()
            cap, T = [], []
            for k, piece in enumerate(self._pieces):
                V, F = _mesh_of(piece)
                if F is None:
                    continue
                cap += [k] * len(F)
                T.append(V[F])
            T = np.concatenate(T) if T else np.zeros((0, 3, 3))
            out = self._piece_tris = (np.array(cap, np.int64), T, *triangle_capsules(T))
        return out

    def piece_hulls(self) -> tuple[np.ndarray, np.ndarray]:
        """The vertices of each mesh piece's convex hull (:meth:`piece_triangles`), in its object's frame, for
        the narrow phase's support bounds: ``(capsule (v,) int, vertices (v, 3))``, sorted by capsule; the
        largest projection of a piece's triangles on any line is that of one of these. A piece whose points
        span no volume keeps all its distinct vertices. Built once."""
        out = getattr(self, "_piece_hulls", None)
        if out is None:
            from scipy.spatial import ConvexHull, QhullError

            tcap, tris = self.piece_triangles()[:2]
            cap, V = [], [np.zeros((0, 3))]
            for k in np.unique(tcap):
                X = np.unique(tris[tcap == k].reshape(-1, 3), axis=0)
                try:
                    X = X[np.sort(ConvexHull(X).vertices)]
                except (QhullError, ValueError):  # flat or too few points: every vertex
                    pass
                cap += [int(k)] * len(X)
                V.append(X)
            out = self._piece_hulls = (np.array(cap, np.int64), np.concatenate(V))
        return out

    # ------------------------------------------------------------------ triangle meshes (for drawing)
    def local_meshes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each object as a triangle mesh in its own frame: ``(vertices (k, 3), faces (m, 3))``. Meshes as
        coal holds them (pinocchio scaled them on loading); a convex primitive (box, sphere, cylinder,
        capsule, cone, convex) as the convex hull of points on its surface. Built once."""
        if getattr(self, "_local_meshes", None) is None:
            self._local_meshes = [_triangles(g, name) for g, name in zip(self._geoms, self.names)]
        return self._local_meshes

    def triangle_meshes(self, q) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """``(name, world vertices (k, 3), faces (m, 3))`` of every object at joint values ``q`` (n,)."""
        P = self.placements(q)
        return [(name, v @ M[:3, :3].T + M[:3, 3], f)
                for name, (v, f), M in zip(self.names, self.local_meshes(), P)]


# ============================================================================ distances
def _hull_points(geom) -> np.ndarray:
    """Points (k, 3), in the object's frame, whose convex hull holds the object: a mesh's vertices, else
    the corners of its local bounding box."""
    verts = getattr(geom, "vertices", None)
    if callable(verts):
        v = np.asarray(verts(), dtype=float)
        if v.ndim == 2 and len(v):
            return v
    geom.computeLocalAABB()
    lo, hi = np.asarray(geom.aabb_local.min_, float), np.asarray(geom.aabb_local.max_, float)
    return np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def _triangles(geom, name: str) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`ArmCollision.local_meshes` for one coal geometry."""
    verts = getattr(geom, "vertices", None)
    if callable(verts) and hasattr(geom, "tri_indices"):
        v = np.asarray(verts(), dtype=float)
        tri = geom.tri_indices
        f = np.array([[t[0], t[1], t[2]] for t in (tri(i) for i in range(geom.num_tris))], dtype=np.int64)
        return v, f.reshape(-1, 3)
    kind = type(geom).__name__
    ring = np.linspace(0.0, 2.0 * math.pi, 24, endpoint=False)
    if kind == "Box":
        h = np.asarray(geom.halfSide, float)
        pts = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * h
    elif kind in ("Sphere", "Capsule"):
        r = float(geom.radius)
        el = np.linspace(-math.pi / 2, math.pi / 2, 13)
        pts = np.array([[math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)] for e in el for a in ring]) * r
        if kind == "Capsule":
            hl = float(geom.halfLength)
            pts = np.concatenate([pts[pts[:, 2] >= 0] + [0, 0, hl], pts[pts[:, 2] <= 0] - [0, 0, hl]])
    elif kind in ("Cylinder", "Cone"):
        r, hl = float(geom.radius), float(geom.halfLength)
        circle = np.stack([r * np.cos(ring), r * np.sin(ring)], axis=1)
        top = np.concatenate([circle, np.full((len(ring), 1), hl)], axis=1) if kind == "Cylinder" else np.array([[0.0, 0.0, hl]])
        pts = np.concatenate([top, np.concatenate([circle, np.full((len(ring), 1), -hl)], axis=1)])
    elif hasattr(geom, "points") and hasattr(geom, "num_points"):
        pts = np.array([np.asarray(geom.points(i), float) for i in range(geom.num_points)])
    else:
        raise ErrplanError(f"object '{name}': cannot draw a {kind} as triangles")
    from scipy.spatial import ConvexHull

    hull = ConvexHull(pts)
    return pts, np.asarray(hull.simplices, np.int64)


#: the most capsules one object's triangles are split into (:meth:`ArmCollision.capsules`)
CAPSULE_PIECES = 8


def bounding_capsule(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """A capsule ``(a, b, r)`` holding every point (k, 3): its axis along the points' principal direction
    through the middle of their extent across it, the radius their largest distance from that line, the
    segment as short as that radius allows; then the radius is the largest exact distance of a point from
    the segment (rounding included), so every point lies inside."""
    X = np.asarray(points, float)
    m = X.mean(axis=0)
    _, _, Vt = np.linalg.svd(X - m, full_matrices=False) if len(X) > 1 else (None, None, np.eye(3))
    u = Vt[0] / np.linalg.norm(Vt[0])
    E = np.linalg.svd(np.eye(3) - np.outer(u, u))[0][:, :2]  # two unit vectors across u
    Y = (X - m) @ E
    m = m + E @ (0.5 * (Y.min(axis=0) + Y.max(axis=0)))
    t = (X - m) @ u
    rad = np.linalg.norm((X - m) - t[:, None] * u, axis=1)
    R = float(rad.max())
    h = np.sqrt(np.maximum(R * R - rad * rad, 0.0))
    hi, lo = float(np.max(t - h)), float(np.min(t + h))
    if lo > hi:
        lo = hi = 0.5 * (lo + hi)
    a, b = m + lo * u, m + hi * u
    ab = b - a
    L2 = float(ab @ ab)
    s = np.clip(((X - a) @ ab) / L2, 0.0, 1.0) if L2 > 0.0 else np.zeros(len(X))
    r = float(np.max(np.linalg.norm(X - (a + s[:, None] * ab), axis=1)))
    return a, b, r * (1.0 + 1e-12) + 1e-12


def triangle_capsules(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A capsule ``(a (t, 3), b (t, 3), r (t,))`` holding each triangle of ``T`` (t, 3, 3): its axis the
    triangle's longest edge, its radius the third vertex's distance from that edge (so it holds the three
    vertices and, being convex, the triangle), padded for rounding."""
    T = np.asarray(T, float).reshape(-1, 3, 3)
    E = np.stack([np.linalg.norm(T[:, (i + 1) % 3] - T[:, i], axis=1) for i in range(3)], axis=1)
    i = np.argmax(E, axis=1) if len(T) else np.zeros(0, np.int64)
    rows = np.arange(len(T))
    a, b, x = T[rows, i], T[rows, (i + 1) % 3], T[rows, (i + 2) % 3]
    ab = b - a
    L2 = np.einsum("ij,ij->i", ab, ab)
    s = np.clip(np.einsum("ij,ij->i", x - a, ab) / np.where(L2 > 0.0, L2, 1.0), 0.0, 1.0)
    r = np.linalg.norm(x - (a + s[:, None] * ab), axis=1)
    return a, b, r * (1.0 + 1e-12) + 1e-12


def _object_capsules(geom, hull: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """:meth:`ArmCollision.capsules` of one object (``hull``: :func:`_hull_points`) as ``(a, b, r, triangles)``
    (the triangle indices of the capsule's piece, None for a primitive): a mesh's triangles split in two
    along a group's principal axis (at the median of their centroids), the largest capsule first, up to
    :data:`CAPSULE_PIECES` groups (smaller pieces: tighter bounds, and cheaper exact queries)."""
    V, F = _mesh_of(geom)
    if F is None:
        return [bounding_capsule(hull) + (None,)]

    def vol(cap):
        a, b, r = cap
        return math.pi * r * r * float(np.linalg.norm(b - a)) + 4.0 / 3.0 * math.pi * r ** 3

    groups = [(np.arange(len(F)), bounding_capsule(V[np.unique(F)]))]
    cent = V[F].mean(axis=1)
    while len(groups) < CAPSULE_PIECES:
        order = sorted(range(len(groups)), key=lambda i: -vol(groups[i][1]))
        for i in order:
            idx, cap = groups[i]
            if len(idx) < 4:
                continue
            C = cent[idx]
            u = np.linalg.svd(C - C.mean(axis=0), full_matrices=False)[2][0]
            t = C @ u
            cut = np.median(t)
            left, right = idx[t <= cut], idx[t > cut]
            if not len(left) or not len(right):
                continue
            cl, cr = bounding_capsule(V[np.unique(F[left])]), bounding_capsule(V[np.unique(F[right])])
            groups[i:i + 1] = [(left, cl), (right, cr)]
            break
        else:
            break
    return [cap + (idx,) for idx, cap in groups]


def _sub_mesh(geom, tris: np.ndarray):
    """A coal mesh of the triangles ``tris`` (indices) of the mesh ``geom``, in the same frame."""
    import coal

    V, F = _mesh_of(geom)
    F = F[tris]
    used, inv = np.unique(F, return_inverse=True)
    m = coal.BVHModelOBBRSS()
    m.beginModel(len(F), len(used))
    m.addVertices(np.ascontiguousarray(V[used]))
    m.addTriangles(np.ascontiguousarray(inv.reshape(-1, 3), dtype=np.int64))
    m.endModel()
    return m


def _mesh_of(geom) -> tuple[np.ndarray | None, np.ndarray | None]:
    """A triangle mesh's vertices (k, 3) and faces (m, 3) in its own frame, ``(None, None)`` for a primitive."""
    verts = getattr(geom, "vertices", None)
    if not (callable(verts) and hasattr(geom, "tri_indices") and getattr(geom, "num_tris", 0) > 0):
        return None, None
    V = np.asarray(verts(), float)
    tri = geom.tri_indices
    F = np.array([[t[0], t[1], t[2]] for t in (tri(i) for i in range(geom.num_tris))], np.int64).reshape(-1, 3)
    return V, F


def _is_prismatic(joint) -> bool:
    return "Prismatic" in joint.shortname() or "JointModelP" in joint.shortname()


def _transforms(P: np.ndarray):
    import coal

    return [coal.Transform3s(np.ascontiguousarray(M[:3, :3]), np.ascontiguousarray(M[:3, 3])) for M in P]


def _closest(a: ArmCollision, Pa: np.ndarray, b: ArmCollision, Pb: np.ndarray, best: float = math.inf,
             Ta=None, Tb=None) -> tuple[float, tuple | None]:
    """The smallest coal distance over the pairs (object of a at Pa, object of b at Pb) that is below
    ``best``: ``(distance, (i, j, point_a, point_b))``, or ``(best, None)`` when none is (module
    docstring: sphere pruning keeps the exact minimum)."""
    import coal

    ca = np.einsum("gij,gj->gi", Pa[:, :3, :3], a._center) + Pa[:, :3, 3]
    cb = np.einsum("gij,gj->gi", Pb[:, :3, :3], b._center) + Pb[:, :3, 3]
    lower = np.linalg.norm(ca[:, None] - cb[None], axis=-1) - a._radius[:, None] - b._radius[None]
    order = np.argsort(lower, axis=None, kind="stable")
    if not len(order) or lower.flat[order[0]] >= best:
        return best, None
    Ta = _transforms(Pa) if Ta is None else Ta
    Tb = _transforms(Pb) if Tb is None else Tb
    req = coal.DistanceRequest()
    found = None
    nb = len(b._geoms)
    for k in order:
        if lower.flat[k] >= best:
            break
        i, j = divmod(int(k), nb)
        res = coal.DistanceResult()
        d = float(coal.distance(a._geoms[i], Ta[i], b._geoms[j], Tb[j], req, res))
        if not math.isfinite(d):
            raise ErrplanError(f"coal returned a non-finite distance ({d}) between '{a.names[i]}' and '{b.names[j]}'")
        if d < best:
            best = d
            found = (i, j, np.array(res.getNearestPoint1(), float), np.array(res.getNearestPoint2(), float))
            if best <= 0.0:
                break
    return best, found


def closest_pair(geo_a: ArmCollision, q_a, geo_b: ArmCollision, q_b) -> Closest:
    """The closest pair of objects of two arms at configurations ``q_a``, ``q_b`` (:class:`Closest`)."""
    d, found = _closest(geo_a, geo_a.placements(q_a), geo_b, geo_b.placements(q_b))
    if found is None:  # only when an arm has no objects, which from_arm refuses
        raise ErrplanError("arm_clearance needs two arms with collision objects")
    i, j, pa, pb = found
    return Closest(d, geo_a.names[i], geo_b.names[j], pa, pb)


def arm_clearance(geo_a: ArmCollision, q_a, geo_b: ArmCollision, q_b) -> float:
    """The smallest coal distance (m) over all pairs (object of arm a, object of arm b) at actuated joint
    values ``q_a`` and ``q_b``; <= 0 when they touch or overlap (then the value of the first such pair
    found: 0 for meshes, coal's signed penetration for primitives; depths are not compared)."""
    return closest_pair(geo_a, q_a, geo_b, q_b).distance


def _pairs_of(geo_a: ArmCollision, qs_a, geo_b: ArmCollision, qs_b) -> tuple[np.ndarray, np.ndarray, dict]:
    qs_a, qs_b = np.asarray(qs_a, float), np.asarray(qs_b, float)
    if qs_a.ndim != 2 or qs_a.shape != (len(qs_b), geo_a.arm.n) or qs_b.shape[1:] != (geo_b.arm.n,):
        raise ErrplanError(f"qs_a and qs_b must be configurations (k, {geo_a.arm.n}) and (k, {geo_b.arm.n}), "
                           f"got shapes {qs_a.shape} and {qs_b.shape}")
    return qs_a, qs_b, {}


def _placed(cache: dict, geo: ArmCollision, q: np.ndarray):
    key = (id(geo), q.tobytes())
    if key not in cache:
        P = geo.placements(q)
        cache[key] = (P, _transforms(P))
    return cache[key]


def clearances(geo_a: ArmCollision, qs_a, geo_b: ArmCollision, qs_b) -> np.ndarray:
    """:func:`arm_clearance` of every pair of configurations ``(qs_a[k], qs_b[k])`` (k,) ((k, n) each); NaN
    where either configuration holds a NaN (an arm that cannot stand there). Each distinct configuration
    is placed once (a batch shares them: the same candidate port and target recur over many pairs)."""
    qs_a, qs_b, cache = _pairs_of(geo_a, qs_a, geo_b, qs_b)

    out = np.full(len(qs_a), np.nan)
    for k, (qa, qb) in enumerate(zip(qs_a, qs_b)):
        if not (np.all(np.isfinite(qa)) and np.all(np.isfinite(qb))):
            continue
        Pa, Ta = _placed(cache, geo_a, qa)
        Pb, Tb = _placed(cache, geo_b, qb)
        out[k], _ = _closest(geo_a, Pa, geo_b, Pb, Ta=Ta, Tb=Tb)
    return out


def clear_of(geo_a: ArmCollision, qs_a, geo_b: ArmCollision, qs_b, clearance: float) -> np.ndarray:
    """Whether ``arm_clearance >= clearance`` for every pair of configurations ``(qs_a[k], qs_b[k])``: (k,)
    bool, False where either configuration holds a NaN (an arm that cannot stand there). A yes/no needs no
    distance: coal's collision query with ``security_margin = clearance`` (two objects "collide" when
    they are closer than it; it stops at the first such triangle pair), asked only for the pairs of
    objects whose bounding spheres lie less than ``clearance`` apart (the others cannot be closer). On
    the UR5's meshes about 20 times faster than :func:`clearances`; the tests compare the two."""
    c = float(clearance)
    if not (math.isfinite(c) and c > 0.0):
        raise ErrplanError(f"clearance must be a positive number (m), got {clearance!r}")
    qs_a, qs_b, cache = _pairs_of(geo_a, qs_a, geo_b, qs_b)
    held: dict = {}
    out = np.zeros(len(qs_a), bool)
    for k, (qa, qb) in enumerate(zip(qs_a, qs_b)):
        if not (np.all(np.isfinite(qa)) and np.all(np.isfinite(qb))):
            continue
        Pa, _ = _placed(cache, geo_a, qa)
        hb = held.get(qb.tobytes())
        if hb is None:
            hb = held[qb.tobytes()] = HeldArm(geo_b, qb)
        out[k] = not _any_within(geo_a, Pa, (hb,), c)
    return out


def motion_samples(geo: ArmCollision, qs, clearance: float) -> np.ndarray:
    """Configurations (k, n) along the piecewise-straight joint-space motion through ``qs`` (m, n), the
    waypoints included, so that no point of any object moves more than ``clearance / 2`` between two
    consecutive ones (:meth:`ArmCollision.motion_bound` per segment, split into equal steps)."""
    c = float(clearance) if isinstance(clearance, (int, float, np.floating, np.integer)) else math.nan
    if not (math.isfinite(c) and c > 0.0):
        raise ErrplanError(f"clearance must be a positive number (m), got {clearance!r}")
    qs = np.asarray(qs, dtype=float)
    n = geo.arm.n
    if qs.ndim != 2 or qs.shape[1] != n or len(qs) == 0:
        raise ErrplanError(f"qs must be configurations of shape (m, {n}), got shape {qs.shape}")
    if not np.all(np.isfinite(qs)):
        raise ErrplanError("qs must be finite joint values (a NaN is an unreachable configuration)")
    out = [qs[:1]]
    for q0, q1 in zip(qs[:-1], qs[1:]):
        steps = max(1, math.ceil(geo.motion_bound(q1 - q0) / (0.5 * c) * (1.0 + 1e-12)))
        s = np.arange(1, steps + 1)[:, None] / steps
        out.append(q0 + s * (q1 - q0))
    return np.concatenate(out)


def min_clearance_along(geo_a: ArmCollision, qs_a, geo_b: ArmCollision, q_b, clearance: float,
                        stop_below: float | None = None) -> float:
    """The smallest clearance (m) between arm a moving through configurations ``qs_a`` (m, n) (straight
    segments in joint space) and arm b held at ``q_b``, over :func:`motion_samples`: no point of arm a
    moves more than ``clearance / 2`` between two samples, so if every sample is at least ``clearance``
    clear, every configuration of the motion is at least ``clearance / 2`` clear (the true minimum along
    the motion is never below the returned value minus ``clearance / 2``).

    ``stop_below``: return as soon as a sample below it is found (that sample's clearance; a validity
    check needs no more). Arm b's placements are computed once; samples whose spheres cannot beat the
    minimum so far are skipped (the result is the exact minimum over the samples)."""
    samples = motion_samples(geo_a, qs_a, clearance)
    Pb = geo_b.placements(geo_b._check_q(q_b, "q_b"))
    Tb = _transforms(Pb)
    best = math.inf
    for q in samples:
        best, _ = _closest(geo_a, geo_a.placements(q), geo_b, Pb, best, Tb=Tb)
        if stop_below is not None and best < stop_below:
            break
    return float(best)


def clear_along(geo_a: ArmCollision, qs_a, geo_b: ArmCollision, q_b, clearance: float) -> bool:
    """Whether every sample of :func:`motion_samples` (arm a through ``qs_a``, arm b held at ``q_b``) is at
    least ``clearance`` clear: the same answer as ``min_clearance_along(...) >= clearance``, with fewer
    distance queries (a motion validity check).

    Skipping is exact: the clearance is 1-Lipschitz in the motion of arm a's points (moving every point
    of one set by at most e changes the distance between the sets by at most e), and between samples i
    and j no point moves more than the sum ``E(i, j)`` of the per-step bounds
    (:meth:`ArmCollision.motion_bound`). So after an exact clearance ``d_i >= clearance`` at sample i,
    every sample j with ``E(i, j) <= d_i - clearance`` is at least ``clearance`` clear and is skipped."""
    samples = motion_samples(geo_a, qs_a, clearance)
    c = float(clearance)
    steps = np.max(geo_a.reach @ np.abs(np.diff(samples, axis=0)).T, axis=0) if len(samples) > 1 else np.zeros(0)
    cum = np.concatenate([[0.0], np.cumsum(steps)])
    Pb = geo_b.placements(geo_b._check_q(q_b, "q_b"))
    Tb = _transforms(Pb)
    i = 0
    while i < len(samples):
        d, _ = _closest(geo_a, geo_a.placements(samples[i]), geo_b, Pb, math.inf, Tb=Tb)
        if d < c:
            return False
        i = max(i + 1, int(np.searchsorted(cum, cum[i] + (d - c), side="right")))
    return True


# ============================================================================ against arms held still
class HeldArm:
    """An arm held at one configuration ``q`` (n,): its objects' placements, coal transforms and bounding
    spheres in the world, computed once (a planner checks a moving arm against it thousands of times)."""

    def __init__(self, geo: ArmCollision, q, name: str = ""):
        self.geo = geo
        self.name = name
        self.q = geo._check_q(q, "q_held")
        self.P = geo.placements(self.q)
        self.T = _transforms(self.P)
        self.centers = np.einsum("gij,gj->gi", self.P[:, :3, :3], geo._center) + self.P[:, :3, 3]


def held_shapes(held: Sequence[HeldArm]) -> HeldShapes:
    """The held arms' objects (every held arm's in turn) for the compiled broad phase: their bounding
    spheres and capsules (:meth:`ArmCollision.capsules`), their pieces' triangles and hull vertices placed in
    the world (:class:`~.broadphase.HeldShapes`)."""
    centers, radius, A, B, R, start = [np.zeros((0, 3))], [np.zeros(0)], [np.zeros((0, 3))], [np.zeros((0, 3))], \
        [np.zeros(0)], [0]
    X, XA, XB, XR, tstart = [np.zeros((0, 3, 3))], [np.zeros((0, 3))], [np.zeros((0, 3))], [np.zeros(0)], [0]
    V, vstart = [np.zeros((0, 3))], [0]
    for h in held:
        obj, a, b, r = h.geo.capsules()
        tcap, tris, ta, tb, tr = h.geo.piece_triangles()
        hcap, hull = h.geo.piece_hulls()
        centers.append(h.centers)
        radius.append(h.geo._radius)
        for g in range(len(h.geo._geoms)):
            M = h.P[g]
            sel = obj == g
            A.append(a[sel] @ M[:3, :3].T + M[:3, 3])
            B.append(b[sel] @ M[:3, :3].T + M[:3, 3])
            R.append(r[sel])
            start.append(start[-1] + int(np.count_nonzero(sel)))
            for k in np.flatnonzero(sel):
                mine = tcap == k
                X.append(tris[mine] @ M[:3, :3].T + M[:3, 3])
                XA.append(ta[mine] @ M[:3, :3].T + M[:3, 3])
                XB.append(tb[mine] @ M[:3, :3].T + M[:3, 3])
                XR.append(tr[mine] * (1.0 + 1e-12) + 1e-12)  # the rounding of the placement
                tstart.append(tstart[-1] + int(np.count_nonzero(mine)))
                mine = hcap == k
                V.append(hull[mine] @ M[:3, :3].T + M[:3, 3])
                vstart.append(vstart[-1] + int(np.count_nonzero(mine)))
    arrays = [np.ascontiguousarray(np.concatenate(x), float) for x in (centers, radius, A, B, R)]
    tri = [np.ascontiguousarray(np.concatenate(x), float) for x in (X, XA, XB, XR)]
    return HeldShapes(*arrays, np.array(start, np.int64), *tri, np.array(tstart, np.int64),
                      np.ascontiguousarray(np.concatenate(V), float), np.array(vstart, np.int64))


def held_objects(held: Sequence[HeldArm]) -> list:
    """``(coal geometry, coal transform)`` of every held arm's pieces (:meth:`ArmCollision.pieces`), in
    :func:`held_shapes`' order of capsules."""
    out = []
    for h in held:
        obj = h.geo.capsules()[0]
        out += [(piece, h.T[int(g)]) for piece, g in zip(h.geo.pieces(), obj)]
    return out


def first_within(geo: ArmCollision, P: np.ndarray, objects: Sequence, rows: np.ndarray, clearance: float,
                 travel: np.ndarray | None = None) -> int:
    """The first row ``(sample, piece of geo, held piece)`` of ``rows`` (m, 3) whose two pieces
    (:meth:`ArmCollision.pieces`) lie closer than ``clearance``, the moving piece's object placed at
    ``P[sample, object]`` ((k, G, 4, 4), the compiled broad phase's placements) and the held piece as
    ``objects`` (:func:`held_objects`) holds it; -1 when none does.

    Without ``travel``, coal's collision test with security margin ``clearance`` (as :func:`within_held`).
    With ``travel`` (k, G) (:func:`~.broadphase.object_travel`: how far a point of each object may have moved
    from the first sample), coal's exact distance ``d``, and a later row of the same two pieces is skipped
    while its object has moved at most ``d - clearance`` since (the distance is 1-Lipschitz in the moving
    piece's points, :func:`clear_along`'s argument): a motion asks coal once per pair of pieces and stretch
    of motion rather than once per sample."""
    import coal

    if not len(rows):
        return -1
    c = float(clearance)
    req = coal.CollisionRequest()
    req.security_margin = c
    req.enable_contact = False
    dreq = coal.DistanceRequest()
    placed: dict = {}
    known: dict = {}
    pieces = geo.pieces()
    owner = geo.capsules()[0]
    for r, (s, p, k) in enumerate(rows.tolist()):
        g = int(owner[p])
        if travel is not None:
            seen = known.get((p, k))
            if seen is not None and seen[1] - (travel[s, g] - travel[seen[0], g]) >= c + SLACK:
                continue
        T = placed.get((s, g))
        if T is None:
            M = P[s, g]
            T = placed[(s, g)] = coal.Transform3s(np.ascontiguousarray(M[:3, :3]), np.ascontiguousarray(M[:3, 3]))
        hg, hT = objects[k]
        if travel is None:
            if coal.collide(pieces[p], T, hg, hT, req, coal.CollisionResult()):
                return r
            continue
        d = float(coal.distance(pieces[p], T, hg, hT, dreq, coal.DistanceResult()))
        if not d >= c:
            return r
        known[(p, k)] = (s, d)
    return -1


def _lower_bound(geo: ArmCollision, P: np.ndarray, held: Sequence[HeldArm]) -> float:
    """The smallest bounding-sphere gap between arm ``geo`` at placements ``P`` and the held arms: a lower
    bound of their clearance (every point of an object lies in its sphere)."""
    ca = np.einsum("gij,gj->gi", P[:, :3, :3], geo._center) + P[:, :3, 3]
    lb = math.inf
    for h in held:
        gap = np.linalg.norm(ca[:, None] - h.centers[None], axis=-1) - geo._radius[:, None] - h.geo._radius[None]
        lb = min(lb, float(gap.min()))
    return lb


def _any_within(geo: ArmCollision, P: np.ndarray, held: Sequence[HeldArm], c: float) -> bool:
    """Whether some object of arm ``geo`` at placements ``P`` lies closer than ``c`` to an object of a held
    arm: coal's collision test with security margin ``c`` (exact, and about a hundred times cheaper than a
    mesh-mesh distance), on the pairs whose bounding spheres lie closer than ``c``, nearest first."""
    import coal

    ca = np.einsum("gij,gj->gi", P[:, :3, :3], geo._center) + P[:, :3, 3]
    req = coal.CollisionRequest()
    req.security_margin = float(c)
    req.enable_contact = False
    Ta = None
    for h in held:
        gap = np.linalg.norm(ca[:, None] - h.centers[None], axis=-1) - geo._radius[:, None] - h.geo._radius[None]
        order = np.argsort(gap, axis=None, kind="stable")
        nb = len(h.geo._geoms)
        for k in order:
            if gap.flat[k] >= c:
                break
            if Ta is None:
                Ta = _transforms(P)
            i, j = divmod(int(k), nb)
            if coal.collide(geo._geoms[i], Ta[i], h.geo._geoms[j], h.T[j], req, coal.CollisionResult()):
                return True
    return False


def within_held(geo: ArmCollision, q, held: Sequence[HeldArm], clearance: float) -> bool:
    """Whether arm ``geo`` at actuated joint values ``q`` comes closer than ``clearance`` to a held arm (the
    yes/no of :func:`clearance_to_held` below ``clearance``, by coal's collision test with that security
    margin)."""
    return _any_within(geo, geo.placements(q), held, clearance)


def clearance_to_held(geo: ArmCollision, q, held: Sequence[HeldArm], below: float = math.inf) -> float:
    """The smallest coal distance (m) between arm ``geo`` at actuated joint values ``q`` and every held arm
    (:func:`arm_clearance` against each); with ``below``, the exact value only when it is below ``below``,
    else ``below`` itself (a yes/no check needs no more: pairs whose spheres lie ``below`` apart are
    never queried)."""
    P = geo.placements(q)
    Ta = None
    best = float(below)
    for h in held:
        if Ta is None:
            Ta = _transforms(P)
        best, _ = _closest(geo, P, h.geo, h.P, best, Ta=Ta, Tb=h.T)
        if best <= 0.0:
            break
    return best


def clear_along_held(geo: ArmCollision, qs, held: Sequence[HeldArm], clearance: float) -> bool:
    """Whether every sample of :func:`motion_samples` (arm ``geo`` through ``qs`` (m, n)) is at least
    ``clearance`` clear of every held arm: :func:`clear_along` against several arms held still, with their
    placements computed once (:class:`HeldArm`). Skipping is :func:`clear_along`'s (exact): after a sample
    at least ``d >= clearance`` clear, the samples to which no point moves more than ``d - clearance`` are
    clear too; here ``d`` is the bounding-sphere gap (a lower bound of the clearance, no coal query). Where
    the spheres come closer than ``clearance``, the sample is decided by coal's collision test with
    security margin ``clearance`` (:func:`within_held`) and the next sample is taken."""
    if not held:
        return True
    samples = motion_samples(geo, qs, clearance)
    c = float(clearance)
    steps = np.max(geo.reach @ np.abs(np.diff(samples, axis=0)).T, axis=0) if len(samples) > 1 else np.zeros(0)
    cum = np.concatenate([[0.0], np.cumsum(steps)])
    i = 0
    while i < len(samples):
        P = geo.placements(samples[i])
        d = _lower_bound(geo, P, held)
        if d < c:
            if _any_within(geo, P, held, c):
                return False
            i += 1
            continue
        i = max(i + 1, int(np.searchsorted(cum, cum[i] + (d - c), side="right")))
    return True


def min_clearance_along_held(geo: ArmCollision, qs, held: Sequence[HeldArm], clearance: float) -> float:
    """The smallest clearance (m) over the samples of :func:`motion_samples` (arm ``geo`` through ``qs``)
    to every held arm (:func:`min_clearance_along` against several held arms); inf without any."""
    samples = motion_samples(geo, qs, clearance)
    best = math.inf
    for q in samples:
        P = geo.placements(q)
        if _lower_bound(geo, P, held) >= best:
            continue
        Ta = _transforms(P)
        for h in held:
            best, _ = _closest(geo, P, h.geo, h.P, best, Ta=Ta, Tb=h.T)
    return float(best)


# ============================================================================ the arm at a tip
def arm_at_tip(arm: UrdfArm, tip, port, length: float, near=None) -> np.ndarray:
    """Actuated joint values (n,) putting the wrist at ``t - L (t - p) / |t - p|``: the rigid shaft of
    length ``L`` through port ``p`` with its tip at ``t`` (physics.md, "Definitions the figures use").
    ``near``: a configuration tried first (keeps a branch). Raises :class:`ErrplanError` when the tip
    is at the port or that wrist is out of the arm's reach."""
    t = np.asarray(tip, dtype=float)
    p = np.asarray(port, dtype=float)
    if t.shape != (3,) or p.shape != (3,) or not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
        raise ErrplanError(f"tip and port must be finite points [x, y, z], got {np.asarray(tip).tolist()} "
                           f"and {np.asarray(port).tolist()}")
    L = float(length)
    if not (math.isfinite(L) and L > 0.0):
        raise ErrplanError(f"shaft length must be a positive number (m), got {length!r}")
    d = t - p
    nd = float(np.linalg.norm(d))
    if nd == 0.0:
        raise ErrplanError(f"tip {t.tolist()} is at the port: the shaft has no direction")
    w = t - L * d / nd
    q, ok = arm.inverse(w, near=near)
    if not bool(ok):
        raise ErrplanError(f"tip {t.tolist()} through port {p.tolist()} needs the wrist at "
                           f"{np.round(w, 6).tolist()}, out of reach of {arm.urdf_path.name}")
    return np.asarray(q, float)




# ----------------------------------------------------------------------------- the arms and the patient
class BodySolid:
    """The patient's body as one coal shape in the world frame. Build with :meth:`ellipsoid` or
    :meth:`hull`; pickled as its defining data (coal objects do not pickle)."""

    def __init__(self, kind: str, data: tuple):
        import coal

        self.kind = kind
        self.data = data
        if kind == "ellipsoid":
            center, radii = (np.asarray(x, float) for x in data)
            if center.shape != (3,) or radii.shape != (3,) or not np.all(radii > 0) or not np.all(np.isfinite(center)):
                raise ErrplanError(f"body solid: an ellipsoid needs a finite centre and 3 semi-axes > 0, got "
                                   f"{center.tolist()} and {radii.tolist()}")
            self.shape = coal.Ellipsoid(*(float(r) for r in radii))
            self.transform = coal.Transform3s(np.eye(3), center)
            self.center = center
        elif kind == "hull":
            pts = np.asarray(data[0], float)
            if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 4 or not np.all(np.isfinite(pts)):
                raise ErrplanError(f"body solid: a convex hull needs at least 4 finite points (k, 3), got shape "
                                   f"{pts.shape}")
            self.center = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
            local = [np.ascontiguousarray(p - self.center) for p in pts]
            self.shape = coal.Convex.convexHull(local, False, None)
            self.transform = coal.Transform3s(np.eye(3), self.center)
        else:
            raise ErrplanError(f"body solid: kind must be 'ellipsoid' or 'hull', got {kind!r}")

    @classmethod
    def ellipsoid(cls, center, radii) -> "BodySolid":
        return cls("ellipsoid", (tuple(map(float, center)), tuple(map(float, radii))))

    @classmethod
    def hull(cls, vertices) -> "BodySolid":
        return cls("hull", (np.asarray(vertices, float),))

    def __reduce__(self):
        return (BodySolid, (self.kind, self.data))


def link_distances(geo: ArmCollision, q, body: BodySolid) -> np.ndarray:
    """(objects,) coal's distance of every link of the arm at actuated joint values ``q`` (n,) to ``body``."""
    import coal

    P = geo.placements(q)
    req = coal.DistanceRequest()
    out = np.empty(len(P))
    for i, (g, M) in enumerate(zip(geo.geometry_model.geometryObjects, P)):
        T = coal.Transform3s(np.ascontiguousarray(M[:3, :3]), np.ascontiguousarray(M[:3, 3]))
        res = coal.DistanceResult()
        d = float(coal.distance(g.geometry, T, body.shape, body.transform, req, res))
        if not math.isfinite(d):
            raise ErrplanError(f"coal returned a non-finite distance ({d}) between link object '{g.name}' and the body")
        out[i] = d
    return out


def patient_clearances(geo: ArmCollision, qs, body: BodySolid) -> np.ndarray:
    """(k,) the smallest link-to-body distance of the arm at each configuration ``qs[k]`` ((k, n)); NaN where a
    configuration holds a NaN (an arm that cannot stand there)."""
    qs = np.asarray(qs, float)
    if qs.ndim != 2 or qs.shape[1] != geo.arm.n:
        raise ErrplanError(f"configurations must be (k, {geo.arm.n}), got shape {qs.shape}")
    out = np.full(len(qs), np.nan)
    for k, q in enumerate(qs):
        if np.all(np.isfinite(q)):
            out[k] = float(np.min(link_distances(geo, q, body)))
    return out


def patient_clear(geo: ArmCollision, qs, body: BodySolid, clearance: float) -> np.ndarray:
    """(k,) whether every link keeps ``clearance`` from ``body`` at each configuration ``qs[k]``; False where a
    configuration holds a NaN. A yes/no needs no distance: coal's collision query with ``security_margin =
    clearance`` per link (a link "collides" when it is closer than that), stopping at the first link that
    does; about ten times cheaper than :func:`patient_clearances` on the UR5's meshes (the tests compare)."""
    import coal

    c = float(clearance)
    if not (math.isfinite(c) and c >= 0.0):
        raise ErrplanError(f"patient clearance must be a number >= 0 (m), got {clearance!r}")
    qs = np.asarray(qs, float)
    if qs.ndim != 2 or qs.shape[1] != geo.arm.n:
        raise ErrplanError(f"configurations must be (k, {geo.arm.n}), got shape {qs.shape}")
    req = coal.CollisionRequest()
    req.security_margin = c
    objs = geo.geometry_model.geometryObjects
    out = np.zeros(len(qs), bool)
    for k, q in enumerate(qs):
        if not np.all(np.isfinite(q)):
            continue
        ok = True
        for g, M in zip(objs, geo.placements(q)):
            T = coal.Transform3s(np.ascontiguousarray(M[:3, :3]), np.ascontiguousarray(M[:3, 3]))
            if coal.collide(g.geometry, T, body.shape, body.transform, req, coal.CollisionResult()):
                ok = False
                break
        out[k] = ok
    return out


__all__ = ["ArmCollision", "Closest", "arm_clearance", "clearances", "clear_of", "closest_pair", "min_clearance_along",
           "clear_along", "motion_samples", "arm_at_tip", "HeldArm", "clearance_to_held", "within_held", "clear_along_held",
           "min_clearance_along_held", "held_shapes", "held_objects", "first_within", "bounding_capsule", "triangle_capsules",
           "CAPSULE_PIECES", "BodySolid", "link_distances", "patient_clearances", "patient_clear"]
