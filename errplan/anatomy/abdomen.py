"""The bundled abdomen (scenarios/abdomen.toml): organs errplan generates as closed triangle meshes.

Each organ is a smooth, slightly lobed ellipsoid: an icosphere whose vertices are pushed out along
their directions by a fixed low-order harmonic, then scaled to the organ's semi-axes (mm: the files
carry ``scale = 0.001`` in the scenario). Vertex displacement keeps the icosphere's closed,
consistently oriented surface. Deterministic: :func:`write_organs` writes the same bytes each time,
and ``tests/test_anatomy.py`` checks the bundled files against it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .meshes import icosphere, write_surface

#: organ name -> (semi-axes mm, lobe amplitude, lobe orders (azimuth, polar))
ORGANS = {
    "liver": ((32.0, 24.0, 18.0), 0.10, (3, 2)),
    "stomach": ((20.0, 16.0, 12.0), 0.08, (2, 3)),
    "kidney": ((12.0, 9.0, 10.0), 0.12, (1, 2)),
}


def organ_mesh(name: str, subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (n, 3) mm, faces (m, 3))`` of organ ``name`` (centred at the origin)."""
    axes, amp, (ka, kp) = ORGANS[name]
    v, f = icosphere(subdivisions)
    az = np.arctan2(v[:, 1], v[:, 0])
    pol = np.arccos(np.clip(v[:, 2], -1.0, 1.0))
    r = 1.0 + amp * np.cos(ka * az) * np.sin(kp * pol) ** 2
    return np.round(v * r[:, None] * np.asarray(axes), 6), f


def write_organs(folder: str | Path) -> list[Path]:
    """Write every organ of :data:`ORGANS` as ``folder/NAME.stl``; returns the paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for name in ORGANS:
        v, f = organ_mesh(name)
        p = folder / f"{name}.stl"
        write_surface(p, v, f)
        out.append(p)
    return out
