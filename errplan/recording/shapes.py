"""Geometry the views draw, computed from errplan's results with numpy (and scikit-image for
isosurfaces): field images placed in metres, workspace edges, field slices and level surfaces."""
from __future__ import annotations

import numpy as np

from ..errors import ErrplanError
from .style import turbo


def field_image(mf, name: str) -> tuple[np.ndarray, list[float], list[float]]:
    """Image (rows = y descending, cols = z ascending; 0 outside), translation and scale."""
    a = getattr(mf, name, None)
    if a is None:
        raise ErrplanError(f"field {name!r} was not computed")
    img = np.where(mf.valid & np.isfinite(a), a, 0.0)[::-1, :].astype(np.float32)
    res = mf.resolution
    # pixel (col j, row i) covers u in [u0 + j res, u0 + (j+1) res]: centred on z[j] and -y[ny-1-i]
    translation = [float(mf.z[0] - res / 2), float(-mf.y[-1] - res / 2), 0.0]
    return img, translation, [res, res, 1.0]


def workspace_edges(mf) -> np.ndarray:
    """Boundary of the valid grid cells as 2-point strips (n, 2, 2) in tip coordinates."""
    v = np.asarray(mf.valid, bool)
    res = mf.resolution
    y, z = mf.y, mf.z
    segs = []
    pad = np.zeros((v.shape[0] + 2, v.shape[1] + 2), bool)
    pad[1:-1, 1:-1] = v
    # edges between (i, j) and (i+1, j) along y: a horizontal (constant-y) edge of the pixel squares
    dy = pad[1:, 1:-1] != pad[:-1, 1:-1]          # (ny+1, nz)
    ii, jj = np.nonzero(dy)
    ye = y[0] + (ii - 0.5) * res
    segs.append(np.stack([np.stack([ye, z[jj] - res / 2], -1), np.stack([ye, z[jj] + res / 2], -1)], 1))
    dz = pad[1:-1, 1:] != pad[1:-1, :-1]          # (ny, nz+1)
    ii, jj = np.nonzero(dz)
    ze = z[0] + (jj - 0.5) * res
    segs.append(np.stack([np.stack([y[ii] - res / 2, ze], -1), np.stack([y[ii] + res / 2, ze], -1)], 1))
    return np.concatenate(segs) if segs else np.zeros((0, 2, 2))


def _merge_edges(edges: np.ndarray) -> list[np.ndarray]:
    """Chain unit cell edges into polylines (fewer, longer strips)."""
    from collections import defaultdict

    key = lambda p: (round(float(p[0]), 9), round(float(p[1]), 9))  # noqa: E731
    adj: dict = defaultdict(list)
    for i, (a, b) in enumerate(edges):
        adj[key(a)].append((i, key(b)))
        adj[key(b)].append((i, key(a)))
    used = np.zeros(len(edges), bool)
    strips = []
    for i in range(len(edges)):
        if used[i]:
            continue
        used[i] = True
        a, b = key(edges[i][0]), key(edges[i][1])
        line = [a, b]
        for direction in (0, 1):
            cur = line[-1] if direction == 0 else line[0]
            while True:
                nxt = next(((j, p) for j, p in adj[cur] if not used[j]), None)
                if nxt is None:
                    break
                used[nxt[0]] = True
                cur = nxt[1]
                if direction == 0:
                    line.append(cur)
                else:
                    line.insert(0, cur)
        strips.append(np.array(line))
    return strips


def slice_mesh(mf, name: str, axis: int, index: int, vrange=(0.0, 1.2)):
    """The field ``name`` on the grid plane ``axis = axes[axis][index]`` as a coloured triangle mesh:
    ``(vertices (n, 3), triangles (t, 3), colours (n, 3))``; a grid cell gets its two triangles only
    where its four corners are in the workspace (valid and finite)."""
    a = np.asarray(mf.array(name), float)
    v = np.asarray(mf.valid, bool) & np.isfinite(a)
    axes = [np.asarray(ax, float) for ax in mf.axes]
    sl = [slice(None)] * 3
    sl[axis] = index
    F, V = a[tuple(sl)], v[tuple(sl)]
    (ia, ib) = [i for i in range(3) if i != axis]
    A, B = np.meshgrid(axes[ia], axes[ib], indexing="ij")
    P = np.zeros(A.shape + (3,))
    P[..., ia], P[..., ib], P[..., axis] = A, B, axes[axis][index]
    na, nb = F.shape
    idx = np.arange(na * nb).reshape(na, nb)
    cell = V[:-1, :-1] & V[1:, :-1] & V[:-1, 1:] & V[1:, 1:]
    i00, i10, i01, i11 = idx[:-1, :-1][cell], idx[1:, :-1][cell], idx[:-1, 1:][cell], idx[1:, 1:][cell]
    tri = np.concatenate([np.stack([i00, i10, i11], -1), np.stack([i00, i11, i01], -1)]).astype(np.uint32)
    col = turbo((np.where(V, F, vrange[0]) - vrange[0]) / (vrange[1] - vrange[0]))
    return P.reshape(-1, 3), tri, col.reshape(-1, 3)


def level_surface(mf, name: str, level: float):
    """The surface ``field = level`` inside the robust workspace (marching cubes, scikit-image):
    ``(vertices (n, 3) in metres, triangles (t, 3), normals (n, 3))``, or None where the field does
    not cross the level there."""
    from skimage.measure import marching_cubes

    a = getattr(mf, name, None)
    if a is None:
        return None
    a = np.asarray(a, float)
    valid = np.asarray(mf.valid, bool) & np.isfinite(a)
    if min(a.shape) < 2 or not valid.any():
        return None
    vals = a[valid]
    if not (vals.min() < level < vals.max()):
        return None
    vol = np.where(valid, a, level)
    h = mf.resolution
    try:
        verts, faces, normals, _ = marching_cubes(vol, level, spacing=(h, h, h), mask=valid)
    except (ValueError, RuntimeError):
        return None
    if not len(faces):
        return None
    origin = np.array([ax[0] for ax in mf.axes], float)
    return verts + origin, faces.astype(np.uint32), normals
