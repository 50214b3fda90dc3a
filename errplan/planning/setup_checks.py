"""The several-instrument checks that need a scenario's models: the figures of a planned path among the
held shafts and the endoscope (:func:`path_figures`), and the planner's visibility check (:func:`view_checker`).
The geometry itself (lens, view cone, angles, exact hull distances) is :mod:`errplan.anatomy.setup`."""
from __future__ import annotations

import math

import numpy as np

from ..anatomy.setup import box_corners, hull_points, optical_axis, resample, shaft_distance, visible
from ..fields.compute import anatomy_model
from ..errorset import error_set


def path_figures(st, name: str, path) -> dict:
    """For a path (n, 3) of arm ``name`` of setup ``st``: ``min_shaft_clearance`` (m, the exact distance
    from the moving shaft conv(box ∪ {a, b}) of every straight piece to every held shaft and the
    endoscope's, each at its rest; None when there is none) and ``visible`` (share of the path's
    points, every 1 mm, the endoscope sees; None without an endoscope)."""
    sc = st.arm(name)
    path = np.asarray(path, float).reshape(-1, 3)
    box = error_set(sc)[0].port_corners()
    held = held_hulls(st, name)
    segs = list(zip(path[:-1], path[1:])) or [(path[0], path[0])]
    dmin = min((shaft_distance(hull_points(box, a, b), H) for a, b in segs for H in held), default=None)
    vis = None
    e = st.endoscope
    if e is not None:
        pe = np.asarray(e.port.estimate, float)
        axis = optical_axis(pe, e.look_at)
        lens = pe + e.insertion * axis
        pts = resample(path)
        vis = float(np.mean(visible(pts, lens, axis, e.fov, e.depth, anatomy_model(st.arm(name)))))
    return {"arm": name, "min_shaft_clearance": dmin, "visible": vis}


def held_hulls(st, name: str) -> list[np.ndarray]:
    """The points (k, 3) whose convex hulls are what arm ``name`` keeps ``shaft_clearance`` from: every held
    shaft conv(box_j ∪ {rest_j}) and the endoscope's conv(box_e ∪ {lens})."""
    return [np.vstack([box_corners(o.center, _Halves(o.half_extents)), np.asarray(o.a, float)[None]])
            for o in st.held_shafts(name)]


def run_shaft_clearance(hulls, port, tips) -> float | None:
    """The smallest exact distance (m) between the shaft of one simulated run and the held hulls
    (:func:`held_hulls`): the shaft pivots at the run's true ``port`` (3,) and its tip moves straight
    between the visited tips (n, 3), so each step sweeps the triangle conv(port, t_k, t_k+1); None
    without any hull."""
    if not hulls:
        return None
    tips = np.asarray(tips, float).reshape(-1, 3)
    port = np.asarray(port, float).reshape(1, 3)
    steps = list(zip(tips[:-1], tips[1:])) or [(tips[0], tips[0])]
    return float(min(shaft_distance(hull_points(port, a, b), H) for a, b in steps for H in hulls))


class _Halves:
    """An uncertainty-like view of a box's half extents (port_x = [-hx, hx], ...)."""

    def __init__(self, h):
        self.port_x, self.port_y, self.port_z = ((-float(v), float(v)) for v in h)


def view_checker(sc):
    """``ok(ax, ay, az, bx, by, bz) -> bool``: every tip of the straight motion a -> b is visible to the
    endoscope ``sc.view``. Exact: the view cone (full angle < pi) cut by the depth slab is convex, so a
    motion is inside when both ends are; the lines of sight of every tip of the motion sweep the
    triangle conv(lens, a, b), so they all clear the obstacles when that triangle keeps a positive
    distance from them (one hull query: the anatomy's obstacles, with the lens as the "port", without
    the held shafts and the wall)."""
    from dataclasses import replace

    e = sc.view
    pe = np.asarray(e.port.estimate, float)
    axis = optical_axis(pe, e.look_at)
    lens = pe + e.insertion * axis
    an = sc.anatomy
    solid = None
    if an is not None:
        an = replace(an, obstacles=tuple(o for o in an.obstacles if o.shape != "shaft"), body_wall=None)
        if an.obstacles:
            solid = replace(anatomy_model(sc.with_(anatomy=an)), wall=np.zeros(7), required=1e-12).with_box(lens)
    clear = solid.checker() if solid is not None else None
    lx, ly, lz = (float(v) for v in lens)
    ux, uy, uz = (float(v) for v in axis)
    near, far = float(e.depth[0]), float(e.depth[1])
    cos_half = math.cos(e.fov / 2.0)

    def cone(x, y, z):
        rx, ry, rz = x - lx, y - ly, z - lz
        d = rx * ux + ry * uy + rz * uz
        return near <= d <= far and d >= cos_half * math.sqrt(rx * rx + ry * ry + rz * rz)

    def ok(ax, ay, az, bx, by, bz):
        if not (cone(ax, ay, az) and cone(bx, by, bz)):
            return False
        return clear is None or clear(ax, ay, az, bx, by, bz)

    return ok
