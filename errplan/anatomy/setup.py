"""Geometry of a setup with several instruments and an endoscope (docs/physics.md "Several instruments
and the endoscope"): the lens, visibility, the angles at a target, and the robust shaft-shaft clearance.

- The endoscope's optical axis runs from its nominal port ``p_e`` toward ``look_at``; the lens sits
  ``insertion`` along it. A point t is *visible* when its angle to the axis (seen from the lens) is at
  most ``fov / 2``, its depth ``(t - lens) . u`` lies in ``[near, far]``, and the segment lens -> t has a
  positive distance to every obstacle (exact distances of :mod:`.distance`, no margin; the body wall is
  not an obstacle of the line of sight).
- Angles at t (p_1, p_2 nominal instrument ports): the manipulation angle ``m(t)`` between ``t - p_1``
  and ``t - p_2``; the azimuths ``a_i(t)`` between ``t - p_i`` and ``t - lens``; the elevations ``e_i(t)``:
  the angle between the shaft line ``t - p_i`` and the plane normal to the optical axis through t,
  ``asin(|u . (t - p_i)| / |t - p_i|)``.
- Shafts: the union over the true ports of a box B of the shafts [p, x] for every tip x of a set is
  the convex hull conv(B ∪ tips) (physics "Anatomy"); the robust clearance between two shafts is
  the exact distance between two such hulls (GJK, :func:`.distance.hull_distance`). A held instrument
  occupies conv(box_j ∪ {rest_j}); the endoscope conv(box_e ∪ {lens}).
"""
from __future__ import annotations

import itertools
import math

import numpy as np

from ..jit import njit
from . import distance as _d


def box_corners(center, uncertainty) -> np.ndarray:
    """Corners (k, 3) of the port box ``center`` + [port_x] x [port_y] x [port_z] (an axis without an
    interval: no offset), duplicates removed (a point when nothing is uncertain)."""
    c = np.asarray(center, float)
    iv = [getattr(uncertainty, f"port_{a}", None) or (0.0, 0.0) for a in "xyz"]
    out = np.array([c + np.array(o) for o in itertools.product(*iv)])
    return np.unique(np.round(out, 15), axis=0)


def endoscope_box(endo) -> np.ndarray:
    """Corners of the endoscope's port box around its estimate."""
    return box_corners(endo.port.estimate, endo.uncertainty)


def optical_axis(port, look_at) -> np.ndarray:
    """Unit vector(s) (..., 3) from ``port`` toward ``look_at``."""
    v = np.asarray(look_at, float) - np.asarray(port, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def lens_of(port, look_at, insertion: float) -> np.ndarray:
    """The lens (..., 3): ``insertion`` along the optical axis from the nominal ``port``."""
    return np.asarray(port, float) + float(insertion) * optical_axis(port, look_at)


def angle_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle (rad) between vectors (..., 3), by atan2(|u x v|, u . v) (accurate near 0 and pi)."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.sum(u * v, axis=-1))


def unit(v: np.ndarray) -> np.ndarray:
    """Vectors (..., 3) scaled to length 1."""
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def unit_angles(U: np.ndarray, V: np.ndarray) -> np.ndarray:
    """(n, m, T): the angles between the unit vectors U (n, T, 3) and V (m, T, 3) per target (arccos of
    the dot product, clipped: accurate to about 1e-8 rad at 0 and pi, exact to rounding elsewhere)."""
    return np.arccos(np.clip(np.einsum("itk,jtk->ijt", U, V, optimize=True), -1.0, 1.0))


def manipulation_angle(t, p1, p2) -> np.ndarray:
    """m(t): the angle at the targets t (..., 3) between t - p1 and t - p2."""
    t = np.asarray(t, float)
    return angle_between(t - np.asarray(p1, float), t - np.asarray(p2, float))


def azimuth(t, p, lens) -> np.ndarray:
    """a_i(t): the angle between t - p and t - lens."""
    t = np.asarray(t, float)
    return angle_between(t - np.asarray(p, float), t - np.asarray(lens, float))


def elevation(t, p, axis) -> np.ndarray:
    """e_i(t): the angle between the shaft line t - p and the plane normal to ``axis`` (unit) through t."""
    d = np.asarray(t, float) - np.asarray(p, float)
    s = np.abs(np.sum(d * np.asarray(axis, float), axis=-1)) / np.linalg.norm(d, axis=-1)
    return np.arcsin(np.clip(s, 0.0, 1.0))


def in_view(t, lens, axis, fov: float, depth: tuple[float, float]) -> np.ndarray:
    """Whether targets t (..., 3) lie in the cone of full angle ``fov`` around ``axis`` from ``lens`` and
    at a depth (along the axis) in ``depth`` = (near, far)."""
    r = np.asarray(t, float) - np.asarray(lens, float)
    z = np.sum(r * np.asarray(axis, float), axis=-1)
    ang = angle_between(r, np.broadcast_to(np.asarray(axis, float), r.shape))
    return (z >= depth[0]) & (z <= depth[1]) & (ang <= fov / 2.0)


def line_of_sight(model, lens, t) -> np.ndarray:
    """Whether the segments lens -> t (..., 3) keep a positive distance to every obstacle of ``model``
    (a :class:`.model.ShaftClearance`; None: nothing blocks)."""
    t = np.asarray(t, float)
    if model is None or len(model.clusters) <= 1:
        return np.ones(t.shape[:-1], bool)
    from dataclasses import replace

    m = replace(model, wall=np.zeros(7)).with_box(np.asarray(lens, float).reshape(1, 3))
    return m.tip(t) > 0.0


def visible(t, lens, axis, fov: float, depth, model) -> np.ndarray:
    """Visibility of targets t (..., 3): in the view cone and depth range, and in line of sight."""
    t = np.asarray(t, float)
    ok = in_view(t, lens, axis, fov, depth)
    if ok.any():
        flat = ok.reshape(-1)
        tf = t.reshape(-1, 3)
        flat[flat] = line_of_sight(model, lens, tf[flat])
        ok = flat.reshape(ok.shape)
    return ok


def hull_points(box: np.ndarray, *tips) -> np.ndarray:
    """The points (k, 3) whose convex hull is the robust shaft: the port box's corners and the tips."""
    parts = [np.asarray(box, float).reshape(-1, 3)] + [np.asarray(x, float).reshape(-1, 3) for x in tips]
    P = np.ascontiguousarray(np.vstack(parts))
    if len(P) > 16:
        raise ValueError(f"a shaft hull of {len(P)} points (at most 16)")
    return P


def shaft_distance(P: np.ndarray, Q: np.ndarray) -> float:
    """Exact distance (m) between conv(P) and conv(Q) (points (n, 3), (m, 3)); 0 when they meet."""
    P = np.ascontiguousarray(np.asarray(P, float).reshape(-1, 3))
    Q = np.ascontiguousarray(np.asarray(Q, float).reshape(-1, 3))
    return float(_d.hull_distance(P, len(P), Q, len(Q)))


@njit
def _target_hull_distances(boxes, nb, tips, others, no, out):  # pragma: no cover - compiled
    """out[i, j, k] = dist(conv(boxes[i][:nb] ∪ {tips[k]}), conv(others[j][:no]))."""
    P = np.zeros((nb + 1, 3))
    for i in range(boxes.shape[0]):
        for a in range(nb):
            for c in range(3):
                P[a, c] = boxes[i, a, c]
        for k in range(tips.shape[0]):
            for c in range(3):
                P[nb, c] = tips[k, c]
            for j in range(others.shape[0]):
                out[i, j, k] = _d.hull_distance(P, nb + 1, others[j], no)


def target_hull_distances(boxes: np.ndarray, tips: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(n, m, T): the exact distance between the robust shaft conv(boxes[i] ∪ {tips[k]}) and the convex
    hulls ``others[j]`` (for the endoscope: its box corners and lens). ``boxes`` (n, nb, 3), ``tips``
    (T, 3), ``others`` (m, no, 3)."""
    boxes = np.ascontiguousarray(np.asarray(boxes, float))
    tips = np.ascontiguousarray(np.asarray(tips, float).reshape(-1, 3))
    others = np.ascontiguousarray(np.asarray(others, float))
    out = np.empty((boxes.shape[0], others.shape[0], len(tips)))
    if out.size:
        _target_hull_distances(boxes, boxes.shape[1], tips, others, others.shape[1], out)
    return out


def degrees(x) -> float:
    return float(math.degrees(x))


def resample(path: np.ndarray, step: float = 0.001) -> np.ndarray:
    """Points of a polyline (n, 3) every ``step`` m or closer (its vertices kept)."""
    path = np.asarray(path, float).reshape(-1, 3)
    out = [path[:1]]
    for a, b in zip(path[:-1], path[1:]):
        k = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + (b - a) * (np.arange(1, k + 1) / k)[:, None])
    return np.vstack(out)
