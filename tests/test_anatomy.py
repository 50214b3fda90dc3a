"""Anatomy (issue 18): the exact robust shaft clearance against brute force, mesh checks, scenario keys."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from errplan.anatomy import build, winding_number
from errplan.anatomy import distance as D
from errplan.anatomy.meshes import icosphere, write_surface
from errplan.errors import ScenarioError
from errplan.scenario import Anatomy, BodyWall, Obstacle


# ----------------------------------------------------------------------------- brute force
def point_triangle(p, a, b, c):
    """Exact distance (n,) from points p (n, 3) to the triangle abc (Ericson's region tests, vectorized
    by checking the interior projection and the three edges)."""
    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n)
    d_plane = (p - a) @ n
    q = p - d_plane[:, None] * n
    # barycentric inside test of the projection
    def same_side(e0, e1):
        return np.cross(e1 - e0, q - e0) @ n >= 0
    inside = same_side(a, b) & same_side(b, c) & same_side(c, a)
    best = np.where(inside, np.abs(d_plane), np.inf)
    for e0, e1 in ((a, b), (b, c), (c, a)):
        best = np.minimum(best, point_segment(p, e0, e1))
    return best


def point_segment(p, a, b):
    u = b - a
    t = np.clip((p - a) @ u / max(u @ u, 1e-300), 0, 1)
    return np.linalg.norm(p - (a + t[:, None] * u), axis=1)


def point_box(p, center, half, R):
    q = (p - center) @ R  # box frame
    out = np.maximum(np.abs(q) - half, 0.0)
    return np.linalg.norm(out, axis=1)


def brute_clearance(anat, box_lo, box_hi, tip, n_port=5, n_seg=400, meshes=None):
    """min over sampled true ports (n_port^3 grid of the box) and sampled shaft points of the exact
    point-to-obstacle distance: an upper bound on the true clearance, within the sampling gap."""
    axes = [np.linspace(l, h, n_port) for l, h in zip(box_lo, box_hi)]
    ports = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    s = np.linspace(0, 1, n_seg)
    pts = (ports[:, None, :] * (1 - s[:, None]) + tip * s[:, None]).reshape(-1, 3)
    best = np.inf
    from errplan.anatomy.meshes import rpy_matrix
    for o in anat.obstacles:
        if o.shape == "sphere":
            d = np.linalg.norm(pts - np.asarray(o.center), axis=1) - o.radius
        elif o.shape == "capsule":
            d = point_segment(pts, np.asarray(o.a), np.asarray(o.b)) - o.radius
        elif o.shape == "box":
            d = point_box(pts, np.asarray(o.center), np.asarray(o.half_extents), rpy_matrix(o.rpy))
        else:
            best = min(best, _mesh_min_distance(pts, *meshes[o.name], shafts=(ports, tip, s)))
            continue
        best = min(best, float(np.maximum(d, 0).min()))
    return best


def _mesh_min_distance(pts, v, f, shafts, m=16):
    """min over pts (the shafts' samples) of the exact distance to the solid bounded by the closed mesh
    (v, f): 0 if a sample is inside, else the smallest point-triangle distance. Exact, only pruned.
    Inside: a shaft's sample is inside when the port is (winding number) xor an odd number of the shaft's
    crossings of the surface (Möller-Trumbore) lie before it. Distance: every triangle is covered by
    barycentric samples m to an edge, so a point's distance to the nearest sample overestimates its
    distance to the surface by at most h (the longest edge / m); only points whose sample distance is
    within h of the smallest one can hold the minimum, and they are measured exactly."""
    from scipy.spatial import cKDTree
    ports, tip, s = shafts
    tri = v[f]
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    dirs = tip - ports  # (P, 3)
    pv = np.cross(dirs[:, None], e2[None])  # (P, T, 3)
    det = np.einsum("ptk,tk->pt", pv, e1)
    ok = np.abs(det) > 1e-300
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tv = ports[:, None] - a[None]
    u = np.einsum("ptk,ptk->pt", tv, pv) * inv
    qv = np.cross(tv, e1[None])
    w = np.einsum("pk,ptk->pt", dirs, qv) * inv
    t = np.einsum("tk,ptk->pt", e2, qv) * inv
    hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t >= 0) & (t <= 1)
    crossings = np.sum(hit[:, :, None] & (t[:, :, None] <= s[None, None, :]), axis=1)  # (P, S)
    start_in = winding_number(ports, v, f) > 0.5
    if np.any(start_in[:, None] ^ (crossings % 2 == 1)):
        return 0.0
    i, j = np.mgrid[0:m + 1, 0:m + 1]
    keep = i + j <= m
    w = np.stack([i[keep], j[keep], m - i[keep] - j[keep]], 1) / m  # barycentric weights
    samples = np.einsum("sk,tkd->tsd", w, tri).reshape(-1, 3)
    h = max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max() / m, 1e-12)
    tree = cKDTree(samples)
    c = samples.mean(axis=0)
    lb = np.linalg.norm(pts - c, axis=1) - np.linalg.norm(samples - c, axis=1).max()  # <= distance to a sample
    near = np.argsort(lb)[:256]
    ub = tree.query(pts[near])[0].min()  # a sample distance reached
    maybe = pts[lb <= ub + h]
    dv = tree.query(maybe, distance_upper_bound=(ub + h) * (1 + 1e-12) + 1e-15)[0]
    cand = maybe[dv <= dv.min() + h]
    return float(np.min([point_triangle(cand, *t) for t in tri]))


def test_gjk_matches_closed_forms():
    rng = np.random.default_rng(3)
    for _ in range(200):
        a, b, p = rng.normal(size=(3, 3))
        P = np.zeros((10, 3)); P[0] = p
        Q = np.zeros((8, 3)); Q[:2] = a, b
        assert D.hull_distance(P, 1, Q, 2) == pytest.approx(point_segment(p[None], a, b)[0], abs=1e-8)
        tri = rng.normal(size=(3, 3))
        Q[:3] = tri
        assert D.hull_distance(P, 1, Q, 3) == pytest.approx(point_triangle(p[None], *tri)[0], abs=1e-8)


def test_gjk_segment_segment_and_overlap():
    P = np.zeros((10, 3)); Q = np.zeros((8, 3))
    P[:2] = [[-1, 0, 0], [1, 0, 0]]
    Q[:2] = [[0, -1, 0.3], [0, 1, 0.3]]
    assert D.hull_distance(P, 2, Q, 2) == pytest.approx(0.3, abs=1e-9)
    Q[:2] = [[0, -1, 0.0], [0, 1, 0.0]]  # crossing segments
    assert D.hull_distance(P, 2, Q, 2) == pytest.approx(0.0, abs=1e-9)
    box = np.array(list(itertools.product((-1, 1), repeat=3)), float)
    P[:8] = box; Q[0] = [0.2, 0.1, -0.3]
    assert D.hull_distance(P, 8, Q, 1) == 0.0  # a point inside a cube


@pytest.fixture(scope="module")
def organ(tmp_path_factory):
    d = tmp_path_factory.mktemp("anat")
    v, f = icosphere(1)
    v = v * np.array([20.0, 12.0, 15.0])  # mm
    write_surface(d / "organ.stl", v, f)
    return d / "organ.stl"


def _anat(organ):
    from errplan.anatomy.meshes import load_surface
    obs = (Obstacle("ball", "sphere", center=(0.02, 0.0, 0.30), radius=0.012),
           Obstacle("vessel", "capsule", a=(-0.05, 0.03, 0.33), b=(0.05, 0.035, 0.34), radius=0.006),
           Obstacle("block", "box", center=(-0.04, -0.04, 0.31), half_extents=(0.01, 0.02, 0.008), rpy=(0.3, 0.2, 0.5)),
           Obstacle("organ", "mesh", file=str(organ), scale=0.001, position=(0.0, -0.02, 0.38), rpy=(0.1, 0.4, -0.2)))
    anat = Anatomy(0.004, obs)
    mesh = load_surface(str(organ), 0.001, (0.0, -0.02, 0.38), (0.1, 0.4, -0.2))
    return anat, {"organ": mesh}


@pytest.mark.parametrize("n_tips", [12, pytest.param(30, marks=pytest.mark.slow)])
def test_robust_clearance_against_brute_force(organ, n_tips):
    anat, meshes = _anat(organ)
    lo, hi = np.array([-0.005, -0.005, 0.195]), np.array([0.005, 0.004, 0.203])
    box = np.array(list(itertools.product(*zip(lo, hi))), float)
    m = build(anat, box)
    rng = np.random.default_rng(7)
    tips = rng.uniform([-0.06, -0.06, 0.27], [0.06, 0.06, 0.42], size=(n_tips, 3))
    exact = m.tip(tips)
    for x, c in zip(tips, exact):
        b = brute_clearance(anat, lo, hi, x, meshes=meshes)
        # brute force samples the shaft set: never below the exact value, and above it by at most
        # the sampling gap (port grid spacing 2.5 mm / 2 along each axis, shaft steps 0.4 mm)
        assert c <= b + 1e-9
        assert b - c <= 0.0035
    # a point strictly inside the sphere and one inside the mesh: clearance 0
    assert m.tip(np.array([0.02, 0.0, 0.30])) == 0.0
    assert m.tip(np.array([0.0, -0.02, 0.38])) == 0.0
    assert list(m.inside(np.array([[0.02, 0.0, 0.30], [0.0, -0.02, 0.38], [0.0, 0.0, 0.25]]))) == [0, 3, -1]


def test_motion_clearance_is_the_worst_tip(organ):
    """conv(box ∪ {a, b}) is the union of the tips' hulls: the motion's clearance is the minimum
    of the tips' clearances along it (dense sampling), never more."""
    anat, _ = _anat(organ)
    box = np.array(list(itertools.product((-0.004, 0.004), (-0.004, 0.004), (0.196, 0.204))), float)
    m = build(anat, box)
    rng = np.random.default_rng(11)
    for _ in range(20):
        a, b = rng.uniform([-0.06, -0.06, 0.27], [0.06, 0.06, 0.42], size=(2, 3))
        s = np.linspace(0, 1, 2001)[:, None]
        along = m.tip(a + s * (b - a)).min()
        mo = float(m.motion(a, b))
        assert mo <= along + 1e-9
        assert along - mo <= 1e-6 + 0.5 * np.linalg.norm(b - a) / 2000
        assert float(m.motion(a, b, ball=0.002)) == pytest.approx(max(mo - 0.002, 0.0), abs=1e-12)
    # tip_clear agrees with tip() >= required (it may stop early)
    tips = rng.uniform([-0.06, -0.06, 0.27], [0.06, 0.06, 0.42], size=(300, 3))
    assert np.array_equal(m.tip_clear(tips), m.tip(tips) >= anat.clearance)


def test_bad_meshes(tmp_path, organ):
    from errplan.anatomy.meshes import load_surface
    (tmp_path / "empty.stl").write_bytes(b"")
    with pytest.raises(ScenarioError, match="empty"):
        load_surface(str(tmp_path / "empty.stl"))
    v, f = icosphere(1)
    write_surface(tmp_path / "open.stl", v, f[:-3])
    with pytest.raises(ScenarioError, match="not a closed surface"):
        load_surface(str(tmp_path / "open.stl"))
    lines = [f"v {a} {b} {c}" for a, b, c in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    lines[0] = "v nan 0 0"
    (tmp_path / "nan.obj").write_text("\n".join(lines) + "\n")
    with pytest.raises(ScenarioError, match="non-finite"):
        load_surface(str(tmp_path / "nan.obj"))
    with pytest.raises(ScenarioError, match="missing"):
        load_surface(str(tmp_path / "none.ply"))


def test_ellipsoid_wall_depth_against_dense_surface():
    from errplan.anatomy.distance import ellipsoid_depth
    rng = np.random.default_rng(1)
    wall = np.array([0.01, -0.02, 0.3, 0.15, 0.12, 0.2, 1.0])
    u = rng.normal(size=(300000, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    S = wall[:3] + u * wall[3:6]
    pts = [wall[:3], wall[:3] + [0.05, 0, 0], wall[:3] + [0, 0.05, 0.0]]
    pts += [wall[:3] + [0.05, 0, -0.06], wall[:3] + [0, 0, -0.06]]  # on the smallest axis' plane (y): no regular root
    pts += list(wall[:3] + rng.uniform(-0.6, 0.6, (60, 3)) * wall[3:6])
    for p in pts:
        d = ellipsoid_depth(*p, wall)
        b = np.linalg.norm(S - p, axis=1).min()
        assert d <= b + 1e-9
        assert b - d <= 0.0006  # the surface sample's spacing
    assert ellipsoid_depth(0.01, -0.02, 0.51, wall) < 0  # outside


def test_body_wall_in_clearance():
    wall_anat = Anatomy(0.004, (), BodyWall("ellipsoid", center=(0.0, 0.0, 0.3), radii=(0.1, 0.1, 0.14)))
    m = build(wall_anat, np.array([[0.0, 0.0, 0.16]]))
    assert float(m.tip(np.array([0.0, 0.0, 0.3]))) == pytest.approx(0.1, abs=1e-9)
    assert float(m.tip(np.array([0.0, 0.0, 0.5]))) == 0.0
    # a motion between two deep points stays deep (convex wall): the smaller end's depth
    assert float(m.motion(np.array([0.0, 0.0, 0.3]), np.array([0.05, 0.0, 0.3]))) == pytest.approx(0.05, abs=1e-9)


def _mesh_wall(tmp_path, center=(0.0, 0.0, 0.3), radii=(0.1, 0.1, 0.14), sub=3):
    """A closed mesh wall: an icosphere scaled to the ellipsoid (its vertices on the ellipsoid), in mm."""
    v, f = icosphere(sub)
    write_surface(tmp_path / "wall.stl", v * np.asarray(radii) * 1000, f)
    return BodyWall("mesh", file=str(tmp_path / "wall.stl"), scale=0.001, position=tuple(center), rpy=(0.0, 0.0, 0.0))


def test_mesh_body_wall_against_the_ellipsoid_and_brute_force(tmp_path):
    """A triangulated ellipsoid as the wall: tips' depths agree with the analytic ellipsoid within the
    triangulation's chord error, a motion's depth is the smallest over its dense samples (exact, the
    segment's distance to the surface), tips outside have clearance 0, the checker refuses a motion
    leaving the wall, and the wall points lie on the mesh, spacing apart."""
    c, r = np.array([0.0, 0.0, 0.3]), np.array([0.1, 0.1, 0.14])
    port = np.array([[0.0, 0.0, 0.16]])
    me = build(Anatomy(0.004, (), _mesh_wall(tmp_path, c, r, sub=2)), port)
    el = build(Anatomy(0.004, (), BodyWall("ellipsoid", center=tuple(c), radii=tuple(r))), port)
    assert me.mesh_wall and not el.mesh_wall and me.wall_mesh()[1].shape == (320, 3)
    rng = np.random.default_rng(3)
    x = c + rng.uniform(-1.15, 1.15, (400, 3)) * r
    a, b = me.tip(x), el.tip(x)
    chord = 0.004  # icosphere(2) scaled: its triangles lie within ~3 mm inside the ellipsoid
    assert np.all(np.abs(a - b) <= chord)
    assert np.all(a[el.wall_depth(x) < -chord] == 0) and np.all(a[me.wall_depth(x) < 0] == 0)
    v, f = me.wall_mesh()
    for p0, p1 in ((c + [0.0, 0.0, -0.05], c + [0.05, 0.02, 0.0]), (c + [0.06, 0.0, 0.0], c + [0.0, 0.0, 0.1])):
        got = float(me.motion(p0, p1))
        s = np.linspace(0, 1, 201)[:, None]
        seg = p0 * (1 - s) + p1 * s
        brute = float(np.min([point_triangle(seg, *v[t]) for t in f]))
        assert got == pytest.approx(brute, abs=2e-4)  # the segment's sampling gap
    ok = me.checker()
    assert ok(*c, *(c + [0.0, 0.0, 0.05])) and not ok(*c, *(c + [0.0, 0.0, 0.2]))
    assert me.wall_gap(np.array([0.0, 0.0, 0.16])) < 1e-12 and me.wall_gap(c) > 0.09
    P = me.wall_points(0.03)
    assert len(P) > 20 and max(me.wall_gap(p) for p in P) < 1e-9
    d = np.linalg.norm(P[:, None] - P[None], axis=-1) + np.eye(len(P))
    assert d.min() >= 0.03 - 1e-12
    assert np.array_equal(P, me.wall_points(0.03))  # deterministic


# ----------------------------------------------------------------------------- the bundled abdomen
ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]
ABDOMEN = ROOT / "scenarios" / "abdomen.toml"


def test_bundled_organs_are_the_generators(tmp_path):
    from errplan.anatomy.abdomen import ORGANS, write_organs
    for p in write_organs(tmp_path):
        assert p.read_bytes() == (ROOT / "scenarios" / "abdomen" / p.name).read_bytes()
    assert len(ORGANS) == 3


def test_bundled_abdomen_loads_and_its_straight_lines_are_blocked():
    from errplan.api import load_scenario
    from errplan.fields.compute import anatomy_model
    sc = load_scenario(ABDOMEN)
    m = anatomy_model(sc)
    assert m.wall[6] > 0 and len(m.surfaces) == 4
    for q in sc.queries:
        assert float(m.motion(np.asarray(q.start), np.asarray(q.goal))) < sc.anatomy.clearance, q.name
        assert float(m.tip(np.asarray(q.start))) >= sc.anatomy.clearance
        assert float(m.tip(np.asarray(q.goal))) >= sc.anatomy.clearance


@pytest.mark.parametrize("change, word", [
    (("radii = [0.16, 0.14, 0.20]", "radii = [0.16, 0.14, 0.25]"), "from the body wall"),
    (("start = [-0.08, 0.04, 0.40]", "start = [-0.08, 0.04, 0.58]"), "outside the body wall"),
    (('shape = "ellipsoid"', 'shape = "ellipsoid"\nbogus = 1'), "unknown key"),
])
def test_bad_body_wall(tmp_path, change, word):
    import shutil
    from errplan.api import load_scenario
    shutil.copytree(ROOT / "scenarios" / "abdomen", tmp_path / "abdomen")
    shutil.copy(ROOT / "scenarios" / "phantom15.urdf", tmp_path)
    text = ABDOMEN.read_text()
    assert change[0] in text
    (tmp_path / "a.toml").write_text(text.replace(change[0], change[1]))
    with pytest.raises(ScenarioError, match=word):
        load_scenario(tmp_path / "a.toml")


def test_culling_changes_nothing(organ):
    """The cluster and piece culling (tapered-capsule lower bounds) returns the minimum over every piece."""
    anat, _ = _anat(organ)
    box = np.array(list(itertools.product((-0.005, 0.005), (-0.004, 0.004), (0.195, 0.203))), float)
    m = build(anat, box)
    rng = np.random.default_rng(2)
    a = rng.uniform([-0.07, -0.07, 0.26], [0.07, 0.07, 0.44], size=(40, 3))
    b = a + rng.normal(scale=0.01, size=a.shape) * (rng.uniform(size=(40, 1)) < 0.5)
    got = m.motion(a, b)
    for x, y, g in zip(a, b, got):
        H = np.zeros((10, 3))
        H[:8], H[8], H[9] = box, x, y
        full = min(D.hull_distance(H, 10, m.pts[p], m.npts[p]) - m.prad[p] for p in range(len(m.pts)))
        assert g == pytest.approx(max(full, 0.0), abs=1e-12)
