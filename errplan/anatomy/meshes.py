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
    why = _not_a_mesh(path)
    if why:
        raise ScenarioError(f"{where}: mesh file {path}: not a mesh ({why})")
    try:
        raw = trimesh.load(str(path), force="mesh", process=False)
    except ModuleNotFoundError as e:  # a reader's optional package: say which, not a traceback's last line
        raise ScenarioError(f"{where}: mesh file {path}: reading it needs the Python package {e.name!r}, which is not "
                            f"installed (pip install {e.name})")
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


#: bytes that never occur in a text mesh (ASCII STL, OBJ, ASCII PLY): controls other than tab, LF, FF, CR
_BINARY = bytes(c for c in range(32) if c not in (9, 10, 12, 13))


def _not_a_mesh(path: Path) -> str | None:
    """Why ``path`` cannot be a mesh file, or None: a binary STL is an 80-byte header, a triangle count
    ``n`` (uint32) and ``50 n`` bytes; a PLY starts with ``ply``; anything else must be text (ASCII STL,
    OBJ), so a file with NUL bytes or other controls in its first 64 KiB is none of them."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(65536)
    if size >= 84 and size == 84 + 50 * int.from_bytes(head[80:84], "little"):
        return None  # binary STL
    if head[:3] == b"ply":
        return None
    ctrl = sum(head.count(bytes([c])) for c in _BINARY)
    if ctrl:
        n = int.from_bytes(head[80:84], "little") if size >= 84 else None
        stl = (f"a binary STL of {n} triangles would have {84 + 50 * n} bytes, this file has {size}" if n is not None
               else f"a binary STL has at least 84 bytes, this file has {size}")
        return (f"a binary file ({ctrl} control byte(s) in its first {len(head)}) that is not a binary STL ({stl}) "
                "nor a PLY, and STL/OBJ/PLY text has no such bytes")
    return None


def write_surface(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write a triangle mesh (format from the suffix: .stl, .obj, .ply)."""
    import trimesh

    trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64), process=False).export(str(path))


def icosphere(subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A unit icosphere ``(vertices, faces)`` (trimesh.creation)."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)
