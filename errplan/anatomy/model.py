"""The anatomy of a scenario built once: convex pieces, meshes, and the robust shaft clearance.

:class:`ShaftClearance` is built from a scenario's ``[anatomy]`` (plain data, :mod:`errplan.scenario`)
and the corners of the port box (the error set's true ports). It answers, for tips ``(..., 3)``:

- :meth:`ShaftClearance.tip` the robust clearance (m): the smallest distance from any obstacle to
  the shaft [p, x] over every true port p of the box, i.e. to conv(box ∪ {x});
- :meth:`ShaftClearance.motion` the same for every tip of straight motions [a, b] (exact:
  conv(box ∪ {a, b})), optionally less a tip-ball radius (a convergence ball around the motion:
  clearance is 1-Lipschitz in the tip, since the hulls of two tips are within Hausdorff distance
  of their separation);
- :meth:`ShaftClearance.inside` whether points are inside (or on) some obstacle.

With ``[anatomy.body_wall]`` the clearance is also at most the tips' depth inside the wall: an
ellipsoid (exact point-to-ellipsoid distance; a motion: the smaller of its ends', exact for a convex
body) or a closed triangle mesh (the distance from the motion's segment to the wall's triangles, by the
same GJK and culling, when its start is inside by the winding number: exact, also when not convex).
:meth:`ShaftClearance.wall_points` spreads candidate ports over either wall.

Distances are exact (GJK on primitives' cores and on every triangle of a mesh, :mod:`.distance`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ScenarioError
from ..jit import kernel_array
from . import distance as _d


@dataclass(frozen=True)
class Surface:
    """One obstacle as a triangle mesh (for drawing and inside tests): name, vertices (n, 3), faces (m, 3)."""

    name: str
    shape: str
    vertices: np.ndarray
    faces: np.ndarray


@dataclass
class ShaftClearance:
    """The obstacles of a scenario as convex pieces, and the port box (corners (nb, 3), m).

    ``required`` is ``[anatomy] clearance`` (m). Arrays are those of :func:`.distance.clearance_batch`.
    """

    required: float
    box: np.ndarray
    pts: np.ndarray
    npts: np.ndarray
    prad: np.ndarray
    pball: np.ndarray
    clusters: np.ndarray
    cball: np.ndarray
    piece_obstacle: np.ndarray  # (n,) index of the obstacle of each piece
    names: tuple[str, ...]
    surfaces: tuple[Surface, ...] = field(default_factory=tuple)
    wall: np.ndarray = field(default_factory=lambda: np.zeros(7))  # body wall (cx, cy, cz, a, b, c, kind)
    _solid: tuple = field(default_factory=tuple)  # per obstacle: ("convex", piece ids) or ("mesh", v, f)
    # a mesh body wall (``wall[6] == 2``): its triangles as pieces (as a mesh obstacle's), and its surface
    wpts: np.ndarray = field(default_factory=lambda: np.zeros((0, _d.MAX_PIECE, 3)))
    wnpts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    wprad: np.ndarray = field(default_factory=lambda: np.zeros(0))
    wpball: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    wclusters: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))
    wcball: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    wall_surface: tuple | None = None  # (vertices (n, 3), faces (m, 3)) of a mesh wall

    @property
    def _wall_args(self) -> tuple:
        return self.wpts, self.wnpts, self.wprad, self.wpball, self.wclusters, self.wcball

    @property
    def mesh_wall(self) -> bool:
        """Whether the body wall is a closed triangle mesh (``[anatomy.body_wall] shape = "mesh"``)."""
        return bool(self.wall[6] > 1.5)

    # ---------------------------------------------------------------- queries
    def _batch(self, a: np.ndarray, b: np.ndarray, extra, stop: float) -> np.ndarray:
        a = np.asarray(a, float)
        b = np.asarray(b, float)
        shape = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
        A = kernel_array(np.broadcast_to(a, shape + (3,)).reshape(-1, 3))  # one specialization of the batch
        B = kernel_array(np.broadcast_to(b, shape + (3,)).reshape(-1, 3))
        E = kernel_array(np.broadcast_to(np.asarray(extra, float), shape).reshape(-1))
        out = np.empty(len(A))
        if len(A) == 0:
            return out.reshape(shape)
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
            raise ValueError("tips must be finite")
        _d.clearance_batch(self.box, A, B, E, self.pts, self.npts, self.prad, self.pball, self.clusters,
                           self.cball, self.wall, float(stop), out, *self._wall_args)
        return np.minimum(out, np.inf).reshape(shape)

    def tip(self, x: np.ndarray) -> np.ndarray:
        """Robust clearance (m, ``inf`` without obstacles) of tips ``x`` (..., 3)."""
        return self._batch(x, x, 0.0, -1.0)

    def motion(self, a: np.ndarray, b: np.ndarray, ball: float | np.ndarray = 0.0) -> np.ndarray:
        """Robust clearance (m) of every tip of the motions [a, b] (..., 3), less ``ball`` (m) (a lower
        bound on the clearance of every tip within ``ball`` of the motion)."""
        return self._batch(a, b, ball, -1.0)

    def tip_clear(self, x: np.ndarray) -> np.ndarray:
        """Whether tips ``x`` (..., 3) are robustly clear (clearance >= required); faster than :meth:`tip`."""
        return self._batch(x, x, 0.0, self.required) >= self.required

    def motion_clear(self, a: np.ndarray, b: np.ndarray, ball: float | np.ndarray = 0.0) -> np.ndarray:
        """Whether every tip of the motions [a, b] (within ``ball`` of them) is robustly clear."""
        return self._batch(a, b, ball, self.required) >= self.required

    def with_box(self, box: np.ndarray) -> "ShaftClearance":
        """The same obstacles for another port box (corners (nb, 3); one point: a known true port)."""
        from dataclasses import replace

        return replace(self, box=np.ascontiguousarray(np.asarray(box, float).reshape(-1, 3)))

    def run_clearance(self, port: np.ndarray, tips: np.ndarray) -> float:
        """Smallest clearance (m) of a simulated run: the shaft from the true ``port`` (3,) through every
        tip it visits (n, 3), each step moving straight (the triangle port-tip-next tip, exact)."""
        tips = np.asarray(tips, float).reshape(-1, 3)
        m = self.with_box(port)
        a, b = (tips[:-1], tips[1:]) if len(tips) > 1 else (tips, tips)
        return float(m.motion(a, b).min())

    def motion_ok(self, ax: float, ay: float, az: float, bx: float, by: float, bz: float) -> bool:
        """Whether every tip of the motion (a, b) is robustly clear: one compiled call (the planner's checks)."""
        return _d.motion_clearance1(self.box, ax, ay, az, bx, by, bz, self.pts, self.npts, self.prad, self.pball,
                                    self.clusters, self.cball, self.wall, self.required,
                                    *self._wall_args) >= self.required

    def checker(self):
        """``ok(ax, ay, az, bx, by, bz) -> bool``: :meth:`motion_ok` with its arrays bound (fewer lookups)."""
        f = _d.motion_clearance1
        box, pts, npts, prad, pball, clusters, cball, wall = (self.box, self.pts, self.npts, self.prad, self.pball,
                                                              self.clusters, self.cball, self.wall)
        req = self.required
        wpts, wnpts, wprad, wpball, wclusters, wcball = self._wall_args

        def ok(ax, ay, az, bx, by, bz):
            return f(box, ax, ay, az, bx, by, bz, pts, npts, prad, pball, clusters, cball, wall, req,
                     wpts, wnpts, wprad, wpball, wclusters, wcball) >= req

        return ok

    @property
    def empty(self) -> bool:
        """No obstacle and no body wall: nothing to check."""
        return len(self.clusters) <= 1 and not self.wall[6] > 0

    def wall_points(self, spacing: float, near: np.ndarray | None = None, radius: float = 0.0) -> np.ndarray:
        """Points (n, 3) of the body wall about ``spacing`` (m) apart along it: a dense deterministic set
        on the surface (about 16 points per ``spacing**2`` of area; the ellipsoid: a Fibonacci set; a
        mesh: :func:`surface_samples`, exactly on its triangles), thinned greedily in its order so that
        kept points are at least ``spacing`` apart (chordal) and every dense point is within ``spacing``
        of one. Deterministic. Empty without a wall. ``near`` (k, 3), ``radius``: only the part of the
        wall within ``radius`` of those points (the dense set is cut before thinning)."""
        if not self.wall[6] > 0:
            return np.zeros((0, 3))
        if self.mesh_wall:
            v, f = self.wall_surface
            tri = v[f]
            area = float(np.sum(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)) / 2)
            n = int(min(max(16 * area / spacing ** 2, 64), 400_000))
            pts = surface_samples(v, f, n)
        else:
            c, r = self.wall[:3], self.wall[3:6]
            a, b, cc = r
            p = 1.6075
            area = 4 * np.pi * (((a * b) ** p + (a * cc) ** p + (b * cc) ** p) / 3) ** (1 / p)
            n = int(min(max(16 * area / spacing ** 2, 64), 400_000))
            i = np.arange(n) + 0.5
            z = 1 - 2 * i / n
            th = np.pi * (1 + 5 ** 0.5) * i
            u = np.stack([np.sqrt(1 - z * z) * np.cos(th), np.sqrt(1 - z * z) * np.sin(th), z], -1)
            pts = c + u * r
        if near is not None:
            near = np.asarray(near, float).reshape(-1, 3)
            keep = np.zeros(len(pts), bool)
            for i0 in range(0, len(pts), 4096):
                dd = np.min(np.sum((pts[i0:i0 + 4096, None, :] - near[None]) ** 2, axis=-1), axis=1)
                keep[i0:i0 + 4096] = dd <= radius * radius
            pts = pts[keep]
        keys = np.floor(pts / spacing).astype(np.int64)
        cells: dict = {}
        kept = []
        for q, key in zip(pts, map(tuple, keys)):
            ok = True
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    for dz in (-1, 0, 1):
                        for j in cells.get((key[0] + dx, key[1] + dy, key[2] + dz), ()):
                            if np.sum((kept[j] - q) ** 2) < spacing * spacing:
                                ok = False
                                break
                        if not ok:
                            break
                    if not ok:
                        break
                if not ok:
                    break
            if ok:
                cells.setdefault(key, []).append(len(kept))
                kept.append(q)
        return np.array(kept).reshape(-1, 3)

    def wall_mesh(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The body wall as a triangle mesh ``(vertices, faces)`` for drawing (the ellipsoid: an
        icosphere scaled; a mesh wall: its surface), or None."""
        if not self.wall[6] > 0:
            return None
        if self.mesh_wall:
            return self.wall_surface
        from .meshes import icosphere

        v, f = icosphere(3)
        return self.wall[:3] + v * self.wall[3:6], f

    def wall_depth(self, p: np.ndarray) -> np.ndarray:
        """Depth (m) of points (..., 3) inside the body wall (> 0 inside; ``inf`` without a wall)."""
        p = np.asarray(p, float)
        if not self.wall[6] > 0:
            return np.full(p.shape[:-1], np.inf)
        flat = p.reshape(-1, 3)
        if self.mesh_wall:
            return np.array([_d.mesh_wall_depth(x, y, z, x, y, z, *self._wall_args, -1.0)
                             for x, y, z in flat]).reshape(p.shape[:-1])
        return np.array([_d.ellipsoid_depth(x, y, z, self.wall) for x, y, z in flat]).reshape(p.shape[:-1])

    def wall_gap(self, p: np.ndarray) -> float:
        """Distance (m) of a point (3,) to the body wall's surface (the ellipsoid: exact inside, outside
        along the ray from the centre, an upper bound that is exact on the surface; a mesh: exact)."""
        p = np.asarray(p, float)
        if self.mesh_wall:
            H = np.zeros((_d.MAX_HULL, 3))
            H[0] = H[1] = p
            return float(_d.shaft_clearance(H, 2, H[0], H[1], np.zeros(2), *self._wall_args, -1.0))
        return _wall_gap(p, self.wall)

    def inside(self, p: np.ndarray) -> np.ndarray:
        """``(...,)`` index of an obstacle containing point ``p`` (..., 3) (on its surface counts), else -1."""
        p = np.asarray(p, float)
        flat = p.reshape(-1, 3)
        out = np.full(len(flat), -1, np.int64)
        for k, solid in enumerate(self._solid):
            if solid[0] == "convex":
                for i, q in enumerate(flat):
                    if out[i] < 0:
                        for pid in solid[1]:
                            if _d.hull_distance(q[None, :].copy(), 1, self.pts[pid], self.npts[pid]) <= self.prad[pid]:
                                out[i] = k
            else:
                w = winding_number(flat, solid[1], solid[2])
                out[(out < 0) & (w > 0.5)] = k
        return out.reshape(p.shape[:-1])


#: m: how far from the body wall a port estimate may lie when the port box is smaller
WALL_TOLERANCE = 0.001


def _wall_gap(p: np.ndarray, wall: np.ndarray) -> float:
    """Distance (m) of a point to the ellipsoid wall's surface (inside: exact; outside: along the ray from
    the centre, an upper bound that is exact on the surface)."""
    d = _d.ellipsoid_depth(float(p[0]), float(p[1]), float(p[2]), wall)
    if d > 0:
        return float(d)
    q = (p - wall[:3]) / wall[3:6]
    r = float(np.linalg.norm(q))
    return float(np.linalg.norm(p - (wall[:3] + q / r * wall[3:6]))) if r > 0 else 0.0


def surface_samples(v: np.ndarray, f: np.ndarray, n: int) -> np.ndarray:
    """``n`` points (n, 3) on the triangle mesh (v, f), deterministic and even in area: point i falls in
    the triangle where ``(i + 0.5) / n`` lands on the cumulative area (systematic sampling), at
    barycentric coordinates from the R2 low-discrepancy sequence (folded into the triangle); the order
    is then a fixed pseudo-random permutation (so that greedy thinning in this order is not biased
    toward the first triangles)."""
    tri = v[f]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area = np.linalg.norm(np.cross(e1, e2), axis=1) / 2
    cdf = np.cumsum(area)
    i = np.arange(n)
    t = np.minimum(np.searchsorted(cdf, (i + 0.5) / n * cdf[-1]), len(f) - 1)
    g = 1.32471795724474602596
    r1 = (0.5 + i / g) % 1.0
    r2 = (0.5 + i / (g * g)) % 1.0
    flip = r1 + r2 > 1
    r1 = np.where(flip, 1 - r1, r1)
    r2 = np.where(flip, 1 - r2, r2)
    pts = tri[t, 0] + r1[:, None] * e1[t] + r2[:, None] * e2[t]
    return pts[np.random.default_rng(0).permutation(n)]


def winding_number(p: np.ndarray, v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Generalized winding number (n,) of points ``p`` (n, 3) for the closed mesh (v, f): 1 inside, 0
    outside (van Oosterom & Strackee's solid angle of each triangle)."""
    out = np.zeros(len(p))
    for i0 in range(0, len(p), 256):
        q = p[i0:i0 + 256, None, None, :]
        a, b, c = (v[f[:, j]][None] - q[:, :, 0] for j in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("...i,...i", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("...i,...i", a, b) * lc + np.einsum("...i,...i", b, c) * la
               + np.einsum("...i,...i", c, a) * lb)
        out[i0:i0 + 256] = np.sum(2 * np.arctan2(det, den), axis=-1) / (4 * np.pi)
    return out


# ----------------------------------------------------------------------------- building
def _sphere_mesh(center, radius, sub=2):
    from .meshes import icosphere

    v, f = icosphere(sub)
    return v * radius + np.asarray(center), f


def _capsule_mesh(a, b, radius, n=16):
    """A capsule surface (for drawing): hemispheres at a, b and the cylinder between."""
    from .meshes import icosphere

    v, f = icosphere(2)
    a, b = np.asarray(a, float), np.asarray(b, float)
    u = b - a
    L = np.linalg.norm(u)
    e = u / L if L > 0 else np.array([0.0, 0.0, 1.0])
    s = v @ e
    # stretch the sphere: points of the upper half go to b, the lower half to a
    out = a + v * radius + np.where(s[:, None] > 0, u, 0.0)
    return out, f


def _box_corners(center, half, rpy):
    from .meshes import rpy_matrix

    R = rpy_matrix(rpy)
    sgn = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    return np.asarray(center, float) + (sgn * np.asarray(half, float)) @ R.T


_BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.int64)


def _morton_order(c: np.ndarray) -> np.ndarray:
    lo, hi = c.min(axis=0), c.max(axis=0)
    q = ((c - lo) / np.maximum(hi - lo, 1e-12) * 1023).astype(np.int64)
    code = np.zeros(len(c), np.int64)
    for bit in range(10):
        for ax in range(3):
            code |= ((q[:, ax] >> bit) & 1) << (3 * bit + ax)
    return np.argsort(code, kind="stable")


def _ball(points: np.ndarray, r: float = 0.0) -> np.ndarray:
    c = points.mean(axis=0)
    return np.array([*c, np.sqrt(np.max(np.sum((points - c) ** 2, axis=1))) + r])


def build(anatomy, box: np.ndarray, where: str = "[anatomy]") -> ShaftClearance:
    """The :class:`ShaftClearance` of ``anatomy`` (a :class:`errplan.scenario.Anatomy`) for the port
    box with corners ``box`` (nb, 3) (one point when the port is certain). Loads the meshes (one
    clear :class:`ScenarioError` for a bad file)."""
    from .meshes import load_surface

    box = np.ascontiguousarray(np.asarray(box, float).reshape(-1, 3))
    pts, npts, prad, pball, owner = [], [], [], [], []
    clusters = [0]
    cball = []
    surfaces, solids = [], []
    for k, o in enumerate(anatomy.obstacles if anatomy else ()):
        first = len(pts)
        if o.shape == "mesh":
            v, f = load_surface(o.file, o.scale, o.position, o.rpy, where=f"[[anatomy.obstacle]] {o.name!r}")
            tri = v[f]  # (m, 3, 3)
            order = _morton_order(tri.mean(axis=1))
            tri = tri[order]
            for t in tri:
                P = np.zeros((_d.MAX_PIECE, 3))
                P[:3] = t
                pts.append(P)
                npts.append(3)
                prad.append(0.0)
                pball.append(_ball(t))
                owner.append(k)
            for s in range(0, len(tri), _d.CLUSTER):
                clusters.append(first + min(s + _d.CLUSTER, len(tri)))
                cball.append(_ball(tri[s:s + _d.CLUSTER].reshape(-1, 3)))
            surfaces.append(Surface(o.name, o.shape, v, f))
            solids.append(("mesh", v, f))
            continue
        if o.shape == "shaft":  # a held shaft conv(box ∪ {tip}): the box and 12 tetrahedra (triangle, tip)
            corners = _box_corners(o.center, o.half_extents, (0.0, 0.0, 0.0))
            tip = np.asarray(o.a, float)
            cores = [corners] + [np.vstack([corners[f], tip]) for f in _BOX_FACES]
            for core in cores:
                P = np.zeros((_d.MAX_PIECE, 3))
                P[:len(core)] = core
                pts.append(P)
                npts.append(len(core))
                prad.append(o.radius)
                pball.append(_ball(core, o.radius))
                owner.append(k)
            clusters.append(first + len(cores))
            cball.append(_ball(np.vstack([corners, tip]), o.radius))
            surfaces.append(Surface(o.name, o.shape, np.vstack([corners, tip]), _BOX_FACES))
            solids.append(("convex", list(range(first, first + len(cores)))))
            continue
        if o.shape == "sphere":
            core, r = np.array([o.center], float), o.radius
            sv, sf = _sphere_mesh(o.center, o.radius)
        elif o.shape == "capsule":
            core, r = np.array([o.a, o.b], float), o.radius
            sv, sf = _capsule_mesh(o.a, o.b, o.radius)
        else:  # box
            core, r = _box_corners(o.center, o.half_extents, o.rpy), 0.0
            sv, sf = core, _BOX_FACES
        P = np.zeros((_d.MAX_PIECE, 3))
        P[:len(core)] = core
        pts.append(P)
        npts.append(len(core))
        prad.append(r)
        pball.append(_ball(core, r))
        owner.append(k)
        clusters.append(first + 1)
        cball.append(pball[-1])
        surfaces.append(Surface(o.name, o.shape, sv, sf))
        solids.append(("convex", [first]))
    n = len(pts)
    wall = np.zeros(7)
    bw = anatomy.body_wall if anatomy else None
    wk: dict = {}
    if bw is not None and bw.shape == "mesh":
        wv, wf = load_surface(bw.file, bw.scale, bw.position, bw.rpy, where="[anatomy.body_wall]")
        tri = wv[wf][_morton_order(wv[wf].mean(axis=1))]
        wpts = np.zeros((len(tri), _d.MAX_PIECE, 3))
        wpts[:, :3] = tri
        starts = list(range(0, len(tri), _d.CLUSTER))
        lo, hi = wv.min(axis=0), wv.max(axis=0)
        wall = np.array([*((lo + hi) / 2), *((hi - lo) / 2), 2.0], float)  # centre, half extents, kind 2
        wk = dict(wpts=np.ascontiguousarray(wpts), wnpts=np.full(len(tri), 3, np.int64), wprad=np.zeros(len(tri)),
                  wpball=np.ascontiguousarray(np.array([_ball(t) for t in tri], float).reshape(-1, 4)),
                  wclusters=np.array([0] + [min(s + _d.CLUSTER, len(tri)) for s in starts], np.int64),
                  wcball=np.ascontiguousarray(np.array([_ball(tri[s:s + _d.CLUSTER].reshape(-1, 3)) for s in starts],
                                                       float).reshape(-1, 4)),
                  wall_surface=(wv, wf))
    elif bw is not None:
        wall = np.array([*bw.center, *bw.radii, 1.0], float)
    return ShaftClearance(**wk,
        wall=wall, required=float(anatomy.clearance) if anatomy else 0.0, box=box,
        pts=np.ascontiguousarray(np.array(pts, float).reshape(n, _d.MAX_PIECE, 3)),
        npts=np.array(npts, np.int64), prad=np.array(prad, float),
        pball=np.ascontiguousarray(np.array(pball, float).reshape(n, 4)),
        clusters=np.array(clusters, np.int64), cball=np.ascontiguousarray(np.array(cball, float).reshape(-1, 4)),
        piece_obstacle=np.array(owner, np.int64), names=tuple(o.name for o in (anatomy.obstacles if anatomy else ())),
        surfaces=tuple(surfaces), _solid=tuple(solids))


def check(sc, box: np.ndarray, model: ShaftClearance | None = None) -> ShaftClearance:
    """Build the anatomy of ``sc`` and check it against the port and the queries: one
    :class:`ScenarioError` when the port box touches an obstacle, a query's start or goal is
    inside one or outside the body wall, or the port estimate is not on the body wall (within the
    port box's half-diagonal, at least :data:`WALL_TOLERANCE`)."""
    m = model or build(sc.anatomy, box)
    src = sc.source
    if m.wall[6] > 0:
        est = np.asarray(sc.port.estimate, float)
        c = m.box.mean(axis=0)
        tol = max(WALL_TOLERANCE, float(np.max(np.linalg.norm(m.box - c, axis=1))))
        gap = m.wall_gap(est)
        if gap > tol:
            raise ScenarioError(f"{src}: [port] estimate = {list(map(float, est))}: {gap * 1000:.1f} mm from the body "
                                f"wall (more than {tol * 1000:.1f} mm): expected a port on [anatomy.body_wall]")
        for q in sc.queries:
            for what, p in (("start", q.start), ("goal", q.goal)):
                if not float(m.wall_depth(np.asarray(p, float))) > 0:
                    raise ScenarioError(f"{src}: [[query]] {q.name!r} {what} = {list(p)}: outside the body wall: "
                                        "expected a tip inside [anatomy.body_wall]")
    if len(m.clusters) <= 1:
        return m
    from dataclasses import replace

    c0 = m.box.mean(axis=0)
    hull = replace(m, wall=np.zeros(7)).motion(c0, c0)  # the box alone: conv(box ∪ {centre}) = conv(box)
    ins = m.inside(np.vstack([m.box, c0]))
    if float(hull) <= 0.0 or np.any(ins >= 0):
        k = int(np.max(ins)) if np.any(ins >= 0) else int(m.piece_obstacle[0])
        raise ScenarioError(f"{src}: [port] {list(map(float, c0))}: the port box touches an obstacle of [anatomy] "
                            f"({m.names[k]!r}): expected a port outside every obstacle")
    for q in sc.queries:
        for what, p in (("start", q.start), ("goal", q.goal)):
            k = int(m.inside(np.asarray(p, float)))
            if k >= 0:
                raise ScenarioError(f"{src}: [[query]] {q.name!r} {what} = {list(p)}: inside obstacle {m.names[k]!r} "
                                    "of [anatomy]: expected a tip outside every obstacle")
    return m
