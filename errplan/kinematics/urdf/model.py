"""The plain data of a URDF chain for the compiled kernels: :class:`ChainData` (the chain as fixed
transforms between the actuated joints), :class:`ReachMap` (the voxel map of the wrist workspace),
:class:`MapParams` (how the map is built), the constants they share and where maps are cached."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

TWO_PI = 2.0 * math.pi
IK_TOL = 1e-10          # |f(q) - w| below this counts as reached (m)
LIMIT_TOL = 1e-12       # slack on the limit rows, as within_limits' default
MAP_VERSION = "reachmap-3"
GRAVITY = 9.81          # m/s^2, along world -y


# ============================================================================ data
class ChainData(NamedTuple):
    """The chain for the kernels (plain arrays).

    ``T`` (n+1, 4, 4): ``T[0]`` world -> frame of joint 0 (base pose and fixed joints folded in),
    ``T[i]`` child frame of joint i-1 -> frame of joint i, ``T[n]`` child frame of joint n-1 ->
    wrist link origin. ``axis`` (n, 3) unit joint axes in their joint frames; ``jtype`` (n,) int64,
    0 revolute, 1 prismatic. Limit rows ``lo <= A q <= hi``: ``A`` (m, n), the first n rows are the
    box limits (identity), then the coupled limits. ``screw`` (n+1, 6): the same chain as a product of
    exponentials, ``f(q) = E_0(q_0) ... E_{n-1}(q_{n-1}) w0``: row i < n holds joint i's world axis and
    a point on it (its frame's origin) at q = 0, row n[:3] the wrist ``w0`` at q = 0 (the inverse
    kinematics' Newton steps use it, :func:`errplan.kinematics.urdf.chain._local3`).
    """

    T: np.ndarray
    axis: np.ndarray
    jtype: np.ndarray
    A: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    screw: np.ndarray


def chain_screws(T: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """:attr:`ChainData.screw` from the fixed transforms ``T`` (n+1, 4, 4) and joint-frame axes (n, 3)."""
    n = axis.shape[0]
    out = np.zeros((n + 1, 6))
    G = np.asarray(T[0], float)
    for i in range(n):
        out[i, :3] = G[:3, :3] @ axis[i]
        out[i, 3:] = G[:3, 3]
        G = G @ T[i + 1]
    out[n, :3] = G[:3, 3]
    return out


class ReachMap(NamedTuple):
    """Voxel map of the wrist workspace (see the module docstring for what each state guarantees).

    Voxel ``(i, j, k)`` is the box ``origin + h * [i, j, k] .. origin + h * [i+1, j+1, k+1]``;
    ``shape`` (3,) int64 the counts, ``state`` (nx, ny, nz) uint8: 0 out, 1 in, 2 boundary.
    ``depth`` (nx, ny, nz) uint8: for an out or in voxel, its chessboard distance in voxels (at most 255)
    to the nearest voxel of the map in another state (255 when there is none); 0 for a boundary voxel.
    So every voxel of the map less than ``depth`` steps away along each axis has the voxel's state: a
    ball's voxels are certified in one lookup (:func:`errplan.fields.kernels._tip_reach`).
    IK seeds live on a coarser grid of ``sub``^3 voxels per seed cell: the seeds of the cell
    ``c = ((i // sub) * cy + j // sub) * cz + k // sub`` (``cy, cz = shape[1:] // sub``) are
    ``seeds[seed_ptr[c]:seed_ptr[c + 1]]`` (rows of n joint values), nearest first; cells with only
    out voxels have none.
    """

    origin: np.ndarray
    h: float
    shape: np.ndarray
    state: np.ndarray
    depth: np.ndarray
    sub: int
    seed_ptr: np.ndarray
    seeds: np.ndarray


@dataclass(frozen=True)
class MapParams:
    """Reachability-map resolution. ``voxels``: seed cells along the workspace's longest extent;
    ``sub``: voxels per seed-cell edge (voxel edge h = extent / (voxels * sub)); ``coarse``: the
    coarse joint cells move the wrist by at most about ``coarse`` seed cells; ``beta``: critical
    cells are refined until their image ball has radius ``<= beta * h``; ``max_depth``: refinement
    levels; ``seeds``: IK seeds kept per seed cell; ``tau``: joint distance (rad or m, max norm)
    under which two seeds count as one branch."""

    voxels: int = 64
    sub: int = 2
    coarse: float = 2.0
    beta: float = 0.5
    max_depth: int = 12
    seeds: int = 6
    tau: float = 0.3



def cache_dir() -> Path:
    """Where reachability maps are cached: ``$ERRPLAN_CACHE_DIR``, else ``~/.cache/errplan``."""
    env = os.environ.get("ERRPLAN_CACHE_DIR")
    return Path(env) if env else Path.home() / ".cache" / "errplan"
