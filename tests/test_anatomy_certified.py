"""Among anatomy, every planned segment is certified: built scenarios whose paths must pass within a few
millimetres of an organ (a sphere, and a convex STL organ written here with trimesh) on the bundled
PHANToM 1.5, and the bundled abdomen.

For every planned segment: certified, the controller's replay monotonic under the truth and every port
corner, and its whole convergence ball clear, checked by an independent sampler (tips sampled in each
ball; for each tip and each corner of the port box the distance from the shaft [port, tip] to the
obstacle: closed form for the sphere, trimesh's closest point on the triangles for the mesh). The plan
costs at most 5 % more than the obstacle-aware grid optimum (at the plain clearance, without the
planner's ball margin). Also: the ball condition (:func:`errplan.gains.certificate.ball_clearance`)
and the halving against brute force, and non-mesh files given as organ meshes.
"""
from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from errplan.api import parse_scenario
from errplan.errors import ScenarioError
from errplan.models import build_arm

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = ROOT / "scenarios" / "phantom15_spatial.toml"
CLEARANCE = 0.003
CLOSE = 0.003  # the paths must pass within CLEARANCE + CLOSE of the obstacle (the test of a close pass)
NODULE = ((0.0, -0.08, 0.35), 0.007)
ORGAN_CENTER, ORGAN_AXES = (0.0, -0.07, 0.37), (0.018, 0.014, 0.010)
CASES = {
    "nodule": ({"x": [-0.08, 0.08], "y": [-0.11, -0.04], "z": [0.32, 0.40]},
               ("past-nodule", [-0.07, -0.08, 0.35], [0.07, -0.08, 0.35])),
    "organ": ({"x": [-0.08, 0.08], "y": [-0.10, -0.03], "z": [0.32, 0.40]},
              ("under-organ", [-0.07, -0.07, 0.37], [0.07, -0.07, 0.37])),
}


def organ_mesh():
    """A convex organ: an icosphere scaled to an ellipsoid's half-axes (trimesh)."""
    import trimesh
    m = trimesh.creation.icosphere(subdivisions=2)
    m.apply_scale(ORGAN_AXES)
    m.apply_translation(ORGAN_CENTER)
    return m


def scenario_doc(kind: str, folder: Path) -> dict:
    doc = tomllib.loads(PHANTOM.read_text())
    doc["robot"]["urdf"] = str(ROOT / "scenarios" / "phantom15.urdf")
    region, (name, start, goal) = CASES[kind]
    doc["fields"].update(resolution=0.004, region=region)
    if kind == "nodule":
        obstacle = {"name": "nodule", "shape": "sphere", "center": list(NODULE[0]), "radius": NODULE[1]}
    else:
        organ_mesh().export(str(folder / "organ.stl"))
        obstacle = {"name": "organ", "shape": "mesh", "file": str(folder / "organ.stl")}
    doc["anatomy"] = {"clearance": CLEARANCE, "obstacle": [obstacle]}
    doc["query"] = [{"name": name, "start": start, "goal": goal}]
    return doc


# ----------------------------------------------------------------------------- independent distances
def seg_point(p, a, b):
    """Distance (...,) from points p (..., 3) to segments [a, b] (..., 3) (closed form)."""
    u = b - a
    t = np.clip(np.sum((p - a) * u, -1) / np.maximum(np.sum(u * u, -1), 1e-300), 0, 1)
    return np.linalg.norm(p - (a + t[..., None] * u), axis=-1)


def mesh_point_distance(mesh, p):
    """Distance (n,) from points p (n, 3) to the closed convex mesh's surface (trimesh's closest point on
    every triangle; no rtree), 0 inside (every face plane's signed distance <= 0)."""
    from trimesh.triangles import closest_point
    tri = np.asarray(mesh.triangles)
    n, f = len(p), len(tri)
    c = closest_point(np.tile(tri, (n, 1, 1)), np.repeat(p, f, axis=0)).reshape(n, f, 3)
    d = np.linalg.norm(c - p[:, None, :], axis=-1).min(axis=1)
    inside = (np.einsum("fk,nk->nf", mesh.face_normals, p) - np.sum(mesh.face_normals * tri[:, 0], -1)).max(1) <= 0
    return np.where(inside, 0.0, d)


def mesh_shaft_distance(mesh, ports, tips, need):
    """Distance (n,) from shafts [ports[i], tips[i]] to the convex mesh. A sound lower bound first: the
    distance to any face's half-space (which contains the convex mesh), the smaller of the two ends';
    where that bound is below ``need`` (m), the exact distance by ternary search along the shaft (the
    distance to a convex set is convex along a line), each value by :func:`mesh_point_distance`."""
    nrm = mesh.face_normals
    off = np.sum(nrm * np.asarray(mesh.triangles)[:, 0], -1)
    sd = lambda x: x @ nrm.T - off  # noqa: E731
    lb = np.minimum(sd(ports), sd(tips)).max(axis=1)
    out = lb.copy()
    hard = np.flatnonzero(lb < need)
    if len(hard):
        a, b = ports[hard], tips[hard]
        lo, hi = np.zeros(len(hard)), np.ones(len(hard))
        f = lambda s: mesh_point_distance(mesh, a + s[:, None] * (b - a))  # noqa: E731
        for _ in range(30):
            m1, m2 = lo + (hi - lo) / 3, hi - (hi - lo) / 3
            left = f(m1) < f(m2)
            hi, lo = np.where(left, m2, hi), np.where(left, lo, m1)
        ends = np.minimum(f(np.zeros(len(hard))), f(np.ones(len(hard))))
        # less the search's last interval (the distance is 1-Lipschitz along the shaft): a lower bound still
        out[hard] = np.minimum(f(0.5 * (lo + hi)) - (hi - lo) * np.linalg.norm(b - a, axis=1), ends)
    return out


def ball_samples(center, radius, n, rng):
    """The centre, ``n`` uniform tips inside the ball and ``n`` on its sphere (seeded)."""
    u = rng.normal(size=(2 * n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = np.concatenate([radius * rng.random(n) ** (1 / 3), np.full(n, radius)])
    return np.vstack([center, center + u * r[:, None]])


def port_corners(sc):
    return build_arm(sc).errors.port_corners()


# ----------------------------------------------------------------------------- built scenarios
@pytest.fixture(scope="module", params=sorted(CASES))
def built(request, tmp_path_factory):
    from errplan.fields import compute_fields
    from errplan.pipeline import run_pipeline
    from errplan.planning import plan_scenario
    kind = request.param
    folder = tmp_path_factory.mktemp(kind)
    sc = parse_scenario(scenario_doc(kind, folder), str(folder / f"{kind}.toml"))
    mf = compute_fields(sc, metrics=("G_norm", "phi_hat_max"), rho_star=True)
    sp = plan_scenario(sc, mf)
    res = run_pipeline(sc, sp.queries, mf)
    return kind, sc, mf, sp, res


@pytest.mark.slow
def test_path_passes_close_and_near_optimal(built):
    """The query's path must pass within a few mm of the organ (the scenario tests what it claims to),
    and costs at most 5 % above the grid optimum of the plain clearance (no ball margin)."""
    from errplan.planning import CostMap
    from errplan.planning.reference import grid_optimum
    kind, sc, mf, sp, _ = built
    cm = sp.costmap
    assert cm.anatomy_margin > 0
    plain = CostMap(mf, cm.metric, cm.weight, cm.certifiable, cm.certify_margin)
    corners = port_corners(sc)
    mesh = organ_mesh()
    for q in sp.queries:
        path = q.planned.path
        s = np.linspace(0, 1, 40)[:, None]
        pts = np.concatenate([a + s * (b - a) for a, b in zip(path[:-1], path[1:])])
        P, T = np.repeat(corners, len(pts), 0), np.tile(pts, (len(corners), 1))
        if kind == "nodule":
            d = close = seg_point(np.asarray(NODULE[0]), P, T) - NODULE[1]
        else:  # exact below the clearance (a sound lower bound above); exact for the 50 closest by that bound
            d = mesh_shaft_distance(mesh, P, T, need=CLEARANCE)
            idx = np.argsort(d)[:50]
            close = mesh_shaft_distance(mesh, P[idx], T[idx], need=np.inf)
        assert d.min() >= CLEARANCE - 1e-9
        assert close.min() < CLEARANCE + CLOSE, (q.name, close.min())  # within a few mm of the organ
        ref = grid_optimum(plain, q.start, q.goal, radius=3)
        assert q.planned.cost <= 1.05 * ref.cost, (q.name, q.planned.cost, ref.cost)
    # a tip inside the margin (clear of the plain clearance) is refused, and the message says why
    c = np.asarray(NODULE[0] if kind == "nodule" else ORGAN_CENTER)
    lo, hi = c, np.asarray(q.start, float)
    for _ in range(40):  # bisection towards the obstacle to the robust clearance CLEARANCE + margin / 2
        m = 0.5 * (lo + hi)
        lo, hi = (m, hi) if float(cm.anatomy.tip(m)) < CLEARANCE + 0.5 * cm.anatomy_margin else (lo, m)
    msg = cm.explain_point(tuple(hi), "tip")
    assert msg and "plan keeps for its convergence balls" in msg and f"clearance = {CLEARANCE * 1000:.1f} mm" in msg


@pytest.mark.slow
def test_every_segment_certified_monotonic_and_ball_clear(built):
    kind, sc, _, _, res = built
    corners = port_corners(sc)
    mesh = organ_mesh()
    rng = np.random.default_rng(35)
    for q in res["queries"]:
        gains = q["gains"]
        assert gains and all(g["certified"] for g in gains), [g.get("reason") for g in gains]
        sim = q["simulation"]
        assert sim["planned"]["monotonic"] and sim["corners"]["planned_all_monotonic"]
        assert all(r["min_clearance"] >= CLEARANCE for r in sim["corners"]["planned"])
        for g in gains:
            assert g["ball_clearance"] >= CLEARANCE
            tips = ball_samples(np.asarray(g["to"]), g["radius"], 40, rng)
            P, T = np.repeat(corners, len(tips), 0), np.tile(tips, (len(corners), 1))
            if kind == "nodule":
                d = seg_point(np.asarray(NODULE[0]), P, T) - NODULE[1]
            else:  # exact wherever the sound lower bound is below the model's bound (>= the clearance)
                d = mesh_shaft_distance(mesh, P, T, need=g["ball_clearance"] + 1e-6)
            # every sampled tip is clear, and the model's bound is a lower bound of their clearance
            assert d.min() >= CLEARANCE
            assert d.min() >= g["ball_clearance"] - 1e-9
        assert min(g["ball_clearance"] for g in gains) < CLEARANCE + CLOSE  # some ball comes close


@pytest.mark.slow
def test_abdomen_every_segment_certified():
    from errplan.fields import compute_fields
    from errplan.pipeline import run_pipeline
    from errplan.planning import plan_scenario
    abd = ROOT / "scenarios" / "abdomen.toml"
    sc = parse_scenario(tomllib.loads(abd.read_text()), str(abd))
    mf = compute_fields(sc, metrics=("G_norm", "phi_hat_max"), rho_star=True)
    sp = plan_scenario(sc, mf)
    res = run_pipeline(sc, sp.queries, mf, corners=False)
    for q in res["queries"]:
        bad = [g.get("reason") for g in q["gains"] if not g["certified"]]
        assert not bad, (q["name"], bad)
        assert all(g["ball_clearance"] >= sc.anatomy.clearance for g in q["gains"])


# ----------------------------------------------------------------------------- the ball condition
def test_ball_clearance_is_a_lower_bound_for_the_wall_and_obstacles():
    """One function for obstacles and the body wall: its value is at most the clearance of every sampled
    tip of the ball (the model's own tip query, and, for the nodule, the closed form) and equals the
    centre's clearance less the radius."""
    from errplan.fields.compute import anatomy_model
    from errplan.gains.certificate import ball_clearance
    doc = tomllib.loads((ROOT / "scenarios" / "abdomen.toml").read_text())
    sc = parse_scenario(doc, str(ROOT / "scenarios" / "abdomen.toml"))
    model = anatomy_model(sc, build_arm(sc).errors)
    rng = np.random.default_rng(3)
    # inside the task region, and near the body wall's side (x = 0.16 m at z = 0.36)
    centres = np.vstack([rng.uniform([-0.08, -0.08, 0.30], [0.08, 0.08, 0.44], (30, 3)),
                         rng.uniform([0.135, -0.01, 0.35], [0.145, 0.01, 0.37], (10, 3))])
    for i, c in enumerate(centres):
        R = float(rng.uniform(0.001, 0.01))
        b = ball_clearance(model, c, R)
        assert b == pytest.approx(float(model.tip(c)) - R, abs=1e-15)
        tips = ball_samples(c, R, 30, rng)
        assert np.all(model.tip(tips) >= b - 1e-12)
        if i >= 30:  # the wall counts: at most the centre's depth inside it, less the radius
            depth = float(model.wall_depth(c[None])[0])
            assert depth < 0.03 and b <= depth - R + 1e-12
    # the nodule: closed form
    nod = parse_scenario(scenario_doc("nodule", Path("/nonexistent")), str(PHANTOM))
    m2 = anatomy_model(nod, build_arm(nod).errors)
    corners = port_corners(nod)
    for c in rng.uniform([-0.03, -0.10, 0.33], [0.03, -0.06, 0.37], (20, 3)):
        R = 0.003
        tips = ball_samples(c, R, 30, rng)
        P, T = np.repeat(corners, len(tips), 0), np.tile(tips, (len(corners), 1))
        d = np.maximum(seg_point(np.asarray(NODULE[0]), P, T) - NODULE[1], 0.0)
        assert d.min() >= ball_clearance(m2, c, R) - 1e-9


def test_schedule_halves_balls_until_clear():
    """A straight path passing 6.5 mm from the nodule (3 mm required): with the halving every ball is
    clear (checked by the closed form), shorter segments only near the nodule; a path passing at 3.5 mm
    (less than clearance + switch tolerance) cannot be certified there and says why."""
    from errplan.gains import GainOptions, SpatialModel, schedule_gains
    nod = parse_scenario(scenario_doc("nodule", Path("/nonexistent")), str(PHANTOM))
    ev = SpatialModel(nod)
    opts = GainOptions.for_dim(3, verify_disk=30, verify_ring=16, verify_samples=2, verify_refine=1)
    an = ev.anatomy
    # the x offset such that the path's own robust clearance is 6.5 mm (bisection on the model's query)
    y0 = NODULE[0][1] - NODULE[1]

    def path_at(cl):
        lo, hi = 0.0, 0.03
        for _ in range(50):
            m = 0.5 * (lo + hi)
            lo, hi = (lo, m) if float(an.motion(np.array([-0.04, y0 - m, 0.35]), np.array([0.04, y0 - m, 0.35]))) > cl \
                else (m, hi)
        return np.array([[-0.04, y0 - hi, 0.35], [0.04, y0 - hi, 0.35]])

    gs = schedule_gains(ev, path_at(0.0065), opts)
    corners = port_corners(nod)
    lengths = np.array([s.length for s in gs.segments])
    assert lengths.min() < 0.5 * lengths.max()  # halved near the nodule only
    for s in gs.segments:
        assert s.ball_clearance >= CLEARANCE, s.reason
        tips = ball_samples(s.end, s.radius, 30, np.random.default_rng(1))
        P, T = np.repeat(corners, len(tips), 0), np.tile(tips, (len(corners), 1))
        assert (seg_point(np.asarray(NODULE[0]), P, T) - NODULE[1]).min() >= CLEARANCE
    close = schedule_gains(ev, path_at(0.0035), opts)
    bad = [s for s in close.segments if not s.certified]
    assert bad and all("not robustly clear" in s.reason for s in bad)
    assert sum(s.certified for s in close.segments) > 0  # the stretches away from the nodule still certify


# ----------------------------------------------------------------------------- non-mesh organ files
@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply"])
def test_binary_file_as_organ_mesh_is_not_a_mesh(tmp_path, monkeypatch, seed, suffix):
    """Fuzz: random bytes (and random bytes after a plausible start) under each mesh suffix are one
    ScenarioError saying the file is not a mesh, also when trimesh's optional text decoder is absent."""
    from errplan.anatomy.meshes import load_surface
    monkeypatch.setitem(sys.modules, "charset_normalizer", None)  # as on a machine without it
    rng = np.random.default_rng(seed)
    head = [b"", b"solid x\n", b"v 0 0 0\n", b"\x00" * 80][seed % 4]
    f = tmp_path / f"organ{suffix}"
    f.write_bytes(head + rng.bytes(int(rng.integers(1, 5000))))
    with pytest.raises(ScenarioError, match="not a mesh") as e:
        load_surface(str(f), where="[anatomy.obstacle] organ")
    assert "ModuleNotFoundError" not in str(e.value) and str(f) in str(e.value)


def test_text_mesh_in_latin1_needs_a_named_package(tmp_path, monkeypatch):
    """A text mesh the reader must decode with its optional package: a missing package is named plainly;
    with it installed the mesh loads."""
    from errplan.anatomy.meshes import load_surface
    m = organ_mesh()
    f = tmp_path / "organ.obj"
    f.write_bytes(b"# caf\xe9\n" + m.export(file_type="obj").encode())
    v, faces = load_surface(str(f))
    assert len(faces) == len(m.faces)
    monkeypatch.setitem(sys.modules, "charset_normalizer", None)
    with pytest.raises(ScenarioError, match="needs the Python package 'charset_normalizer'"):
        load_surface(str(f))


def test_binary_stl_still_loads(tmp_path):
    from errplan.anatomy.meshes import load_surface
    m = organ_mesh()
    f = tmp_path / "organ.stl"
    m.export(str(f))  # binary STL: header, count, 50 bytes a triangle (may contain control bytes)
    v, faces = load_surface(str(f))
    assert len(faces) == len(m.faces)
    assert np.allclose(np.sort(v, axis=0), np.sort(np.asarray(m.vertices), axis=0), atol=1e-6)
