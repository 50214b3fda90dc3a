"""Anatomy (docs/physics.md "Anatomy (3-D)"): obstacles from a scenario's ``[anatomy]``
(spheres, capsules, boxes, triangle meshes read through trimesh) and the exact robust clearance of
the instrument's shaft to them.

- :mod:`.distance`: compiled GJK between convex hulls of point sets and the culled minimum over pieces;
- :mod:`.meshes`: mesh files through ``trimesh`` (the only module importing it);
- :mod:`.model`: :class:`ShaftClearance` built once per scenario and port box, :func:`build`, :func:`check`.
"""
from .model import ShaftClearance, Surface, build, check, winding_number

__all__ = ["ShaftClearance", "Surface", "build", "check", "winding_number"]
