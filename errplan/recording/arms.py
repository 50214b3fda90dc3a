"""An arm's collision (or visual) geometry in a recording, at one configuration: one ``Mesh3D`` per object,
from :class:`errplan.kinematics.urdf.collision.ArmCollision` (the same objects the arm checks use), so
several arms can be drawn by calling :func:`log_arm_geometry` once per arm."""
from __future__ import annotations

import numpy as np

from . import sdk


def log_arm_geometry(rec, entity: str, geometry, q, color=None, static: bool = False) -> list[str]:
    """Log every object of ``geometry`` (an ``ArmCollision``) at actuated joint values ``q`` as a
    ``Mesh3D`` under ``entity/<object name>`` in recording stream ``rec``; ``color`` an RGB(A) triple (0-255)
    or None; ``static`` logs them as static (no time). Returns the entity paths logged."""
    rr = sdk.rerun()
    paths = []
    for name, v, f in geometry.triangle_meshes(np.asarray(q, float)):
        path = f"{entity.rstrip('/')}/{name}"
        kw = {} if color is None else {"albedo_factor": list(color)}
        rec.log(path, rr.Mesh3D(vertex_positions=v.astype(np.float32), triangle_indices=f.astype(np.uint32), **kw),
                static=static)
        paths.append(path)
    return paths
