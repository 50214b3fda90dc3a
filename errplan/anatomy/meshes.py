"""Triangle meshes from files (STL, OBJ, PLY) through ``trimesh``: the only module importing it.

:func:`load_surface` reads a file, checks that it is a usable closed surface and places it
(``scale``, then ``R(rpy)``, then ``position``); :func:`write_surface` writes one (the bundled
abdomen's organs). A bad file is one :class:`~errplan.errors.ScenarioError` naming the file.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ScenarioError


def rpy_matrix(rpy) -> np.ndarray:
    """URDF rotation ``Rz(yaw) Ry(pitch) Rx(roll)`` (3, 3) of ``rpy`` (rad)."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def load_surface(file: str, scale: float = 1.0, position=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0),
                 where: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (n, 3) m, faces (m, 3) int)`` of the closed surface in ``file``, placed.

    Raises :class:`ScenarioError` (naming ``where`` and the file) when the file is missing or empty,
    cannot be read as a mesh, has no triangle, has a non-finite vertex, or is not a closed surface
    (every edge shared by exactly two triangles, consistently oriented: trimesh's ``is_watertight``
    and ``is_winding_consistent``).
    """
    import trimesh

    path = Path(file)
    if not path.is_file():
        raise ScenarioError(f"{where}: mesh file {path}: missing")
    if path.stat().st_size == 0:
        raise ScenarioError(f"{where}: mesh file {path}: empty (no triangle)")
    try:
        raw = trimesh.load(str(path), force="mesh", process=False)
    except Exception as e:  # any reader failure is one line naming the file
        raise ScenarioError(f"{where}: mesh file {path}: not readable as STL, OBJ or PLY ({type(e).__name__}: {e})")
    v = np.asarray(getattr(raw, "vertices", np.zeros((0, 3))), float)
    f = np.asarray(getattr(raw, "faces", np.zeros((0, 3))), np.int64)
    if len(f) == 0 or len(v) == 0:
        raise ScenarioError(f"{where}: mesh file {path}: empty (no triangle)")
    if not np.all(np.isfinite(v)):
        bad = int(np.sum(~np.all(np.isfinite(v), axis=1)))
        raise ScenarioError(f"{where}: mesh file {path}: {bad} vertex(es) with non-finite coordinates")
    mesh = trimesh.Trimesh(v, f, process=True)
    if len(mesh.faces) == 0:
        raise ScenarioError(f"{where}: mesh file {path}: empty (only degenerate triangles)")
    if not (mesh.is_watertight and mesh.is_winding_consistent):
        raise ScenarioError(f"{where}: mesh file {path}: not a closed surface (some edge is not shared by exactly "
                            "two consistently oriented triangles)")
    R = rpy_matrix(rpy)
    verts = np.asarray(mesh.vertices, float) * float(scale) @ R.T + np.asarray(position, float)
    faces = np.asarray(mesh.faces, np.int64)
    if mesh.volume < 0:  # inward normals: flip, so that the winding number is +1 inside
        faces = faces[:, ::-1].copy()
    return verts, faces


def write_surface(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write a triangle mesh (format from the suffix: .stl, .obj, .ply)."""
    import trimesh

    trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64), process=False).export(str(path))


def icosphere(subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A unit icosphere ``(vertices, faces)`` (trimesh.creation)."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)
