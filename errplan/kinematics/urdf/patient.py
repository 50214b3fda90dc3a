"""The arms and the patient: how far each link of an arm stays from the patient's body (docs/physics.md
"Where the arms stand: setup placement").

The body is the solid bounded by the body wall: the ellipsoid wall as coal's ``Ellipsoid`` (centre,
semi-axes along x, y, z), a mesh wall as coal's ``Convex`` of the mesh's vertices (its convex hull, a
solid for coal's GJK: a link inside it is at distance <= 0). A link is a collision object of the arm's
:class:`~errplan.kinematics.urdf.collision.ArmCollision` (the URDF's collision geometry placed at the
arm's base pose and configuration); the instrument shaft is not a link (it passes through the port by
design). Distances are coal's exact ones, <= 0 when a link touches or enters the body.

This module and :mod:`errplan.kinematics.urdf.collision` are the two that import coal (the link geometry
is collision's; the body solid is built here).
"""
from __future__ import annotations

import math

import numpy as np

from ...errors import ErrplanError
from .collision import ArmCollision


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


__all__ = ["BodySolid", "link_distances", "patient_clearances", "patient_clear"]
