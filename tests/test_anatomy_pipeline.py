"""Anatomy in every step (issue 18's "Done when"), on the bundled PHANToM 1.5 with a sphere and a capsule
that the straight lines of its queries cut:

- fields: the workspace is "reachable (the same scenario without anatomy) and robustly clear" by an
  independent distance (true ports sampled densely in the box, closed-form point/segment distances),
  and the npz's ``clearance`` agrees with it to 1 mm at the 99th percentile;
- planning: every planned path keeps the clearance at every 1 mm sample under every corner of the port
  box (closed-form distances), and costs at most 5 % above the obstacle-aware grid optimum;
- gains: every segment certified, every certified run monotonic under the truth and every corner, each
  run's ``min_clearance`` in the JSON at least the clearance;
- bad anatomy: one line, exit 2, nothing written.
"""
from __future__ import annotations

import itertools
import json
import subprocess
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
SPHERE = ((0.0, 0.0, 0.40), 0.015)
CAPSULE = ((0.0, -0.115, 0.355), (0.0, -0.06, 0.355), 0.006)
CLEARANCE = 0.004
ANATOMY = f"""
[anatomy]
clearance = {CLEARANCE}
[[anatomy.obstacle]]
name = "ball"
shape = "sphere"
center = {list(SPHERE[0])}
radius = {SPHERE[1]}
[[anatomy.obstacle]]
name = "vessel"
shape = "capsule"
a = {list(CAPSULE[0])}
b = {list(CAPSULE[1])}
radius = {CAPSULE[2]}
"""


def _doc(res=0.008, anatomy=True):
    doc = tomllib.loads(PHANTOM.read_text())
    if anatomy:
        doc.update(tomllib.loads(ANATOMY))
    doc["fields"]["resolution"] = res
    return doc


# ----------------------------------------------------------------------------- independent distances
def seg_point(p, a, b):
    """Distance (...,) from points p (..., 3) to segments [a, b] (..., 3) (closed form)."""
    u = b - a
    t = np.clip(np.sum((p - a) * u, -1) / np.maximum(np.sum(u * u, -1), 1e-300), 0, 1)
    return np.linalg.norm(p - (a + t[..., None] * u), axis=-1)


def seg_seg(p0, p1, q0, q1, iters=60):
    """Distance (...,) between segments [p0, p1] and [q0, q1]: the distance of p(s) to segment q is
    convex in s; ternary search on it, each value in closed form."""
    lo = np.zeros(np.broadcast_shapes(p0.shape[:-1], q0.shape[:-1]))
    hi = np.ones_like(lo)
    f = lambda s: seg_point(p0 + s[..., None] * (p1 - p0), q0, q1)  # noqa: E731
    for _ in range(iters):
        m1, m2 = lo + (hi - lo) / 3, hi - (hi - lo) / 3
        left = f(m1) < f(m2)
        hi = np.where(left, m2, hi)
        lo = np.where(left, lo, m1)
    return f(0.5 * (lo + hi))


def shaft_clearance(ports, tips):
    """Clearance (n,) of shafts [port, tip] to the sphere and the capsule, min over ``ports`` (k, 3)."""
    P = ports[:, None, :]
    T = tips[None, :, :]
    ds = seg_point(np.asarray(SPHERE[0]), P, T) - SPHERE[1]
    dc = seg_seg(P, T, np.asarray(CAPSULE[0]), np.asarray(CAPSULE[1])) - CAPSULE[2]
    return np.maximum(np.minimum(ds, dc).min(axis=0), 0.0)


def box_ports(sc, n):
    es = build_arm(sc).errors
    c = es.port_corners()
    axes = [np.linspace(c[:, k].min(), c[:, k].max(), n) for k in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3), c


@pytest.fixture(scope="module")
def world():
    from errplan.fields import compute_fields
    from errplan.planning import plan_scenario
    sc = parse_scenario(_doc(), str(PHANTOM))
    mf = compute_fields(sc, metrics=("G_norm", "phi_hat_max"), rho_star=True)
    sp = plan_scenario(sc, mf)
    return sc, mf, sp


@pytest.mark.slow
def test_fields_workspace_is_reachable_and_clear(world):
    from errplan.fields import compute_fields
    sc, mf, _ = world
    sc0 = parse_scenario(_doc(anatomy=False), str(PHANTOM))
    mf0 = compute_fields(sc0, metrics=("G_norm",), rho_star=False)
    P = mf.points().reshape(-1, 3)
    reach = mf0.valid.reshape(-1)
    assert mf.meta["anatomy"]["blocked_points"] > 0
    # clearance is NaN exactly where the tip is unreachable
    assert np.array_equal(np.isfinite(mf.clearance.reshape(-1)), reach)
    rng = np.random.default_rng(5)
    idx = rng.choice(np.flatnonzero(reach), size=min(400, int(reach.sum())), replace=False)
    ports, _ = box_ports(sc, 9)  # 1.25 mm apart
    ind = np.concatenate([shaft_clearance(ports, P[idx[i:i + 50]]) for i in range(0, len(idx), 50)])
    mine = mf.clearance.reshape(-1)[idx]
    assert np.all(mine <= ind + 1e-9)  # exact <= any sample of the error set
    assert np.percentile(ind - mine, 99) <= 0.001
    # the workspace is "reachable and robustly clear" (away from the 1 mm band the sampling cannot decide)
    sure = np.abs(ind - CLEARANCE) > 0.001
    assert np.array_equal(mf.valid.reshape(-1)[idx][sure], (ind >= CLEARANCE)[sure])
    # and every tip the fields keep is reachable
    assert not np.any(mf.valid.reshape(-1) & ~reach)


@pytest.mark.slow
def test_plans_keep_clearance_and_near_optimal(world):
    from errplan.planning.reference import grid_optimum
    sc, mf, sp = world
    _, corners = box_ports(sc, 2)
    cut = 0
    for q in sp.queries:
        path = q.planned.path
        assert q.planned.valid
        pts = [path[:1]]
        for a, b in zip(path[:-1], path[1:]):
            n = max(int(np.ceil(np.linalg.norm(b - a) / 0.001)), 1)
            pts.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
        pts = np.concatenate(pts)
        c = shaft_clearance(corners, pts)
        assert c.min() >= CLEARANCE - 1e-9, q.name
        # the straight line is not clear
        s = np.linspace(0, 1, 400)[:, None]
        line = np.asarray(q.start) + s * (np.asarray(q.goal) - np.asarray(q.start))
        cut += shaft_clearance(corners, line).min() < CLEARANCE
        cm = sp.costmap
        ref = grid_optimum(cm, q.start, q.goal, radius=3)
        assert q.planned.cost <= 1.05 * ref.cost, (q.name, q.planned.cost, ref.cost)
    assert cut >= 2


@pytest.mark.slow
def test_certified_segments_clear_and_monotonic(world):
    from errplan.pipeline import run_pipeline
    sc, mf, sp = world
    res = run_pipeline(sc, sp.queries[:2], mf)
    for q in res["queries"]:
        assert all(g["certified"] for g in q["gains"])
        assert all(g["ball_clearance"] >= CLEARANCE for g in q["gains"])
        sim = q["simulation"]
        assert sim["planned"]["monotonic"] and sim["corners"]["planned_all_monotonic"]
        assert sim["planned"]["min_clearance"] >= CLEARANCE
        assert all(r["min_clearance"] >= CLEARANCE for r in sim["corners"]["planned"])
        assert all("min_clearance" in r for r in sim["corners"]["direct"])


# ----------------------------------------------------------------------------- bad anatomy
def _write(tmp_path, extra):
    text = PHANTOM.read_text().replace('urdf = "phantom15.urdf"', f'urdf = "{ROOT / "scenarios" / "phantom15.urdf"}"')
    p = tmp_path / "s.toml"
    p.write_text(text + extra)
    return p


BAD = {
    "negative radius": ('[anatomy]\n[[anatomy.obstacle]]\nshape = "sphere"\ncenter = [0, 0, 0.4]\nradius = -0.01\n',
                        "radius"),
    "negative clearance": ("[anatomy]\nclearance = -0.001\n", "clearance"),
    "non-finite": ('[anatomy]\n[[anatomy.obstacle]]\nshape = "sphere"\ncenter = [0, nan, 0.4]\nradius = 0.01\n',
                   "finite"),
    "missing mesh": ('[anatomy]\n[[anatomy.obstacle]]\nshape = "mesh"\nfile = "nope.stl"\n', "missing"),
    "empty mesh": ('[anatomy]\n[[anatomy.obstacle]]\nshape = "mesh"\nfile = "empty.stl"\n', "empty"),
    "open mesh": ('[anatomy]\n[[anatomy.obstacle]]\nshape = "mesh"\nfile = "open.stl"\n', "not a closed surface"),
    "start inside": ('[anatomy]\n[[anatomy.obstacle]]\nshape = "sphere"\ncenter = [-0.08, 0.04, 0.40]\n'
                     'radius = 0.01\n', "inside obstacle"),
    "port inside": ('[anatomy]\n[[anatomy.obstacle]]\nshape = "box"\ncenter = [0.0, 0.0, 0.16]\n'
                    'half_extents = [0.01, 0.01, 0.01]\n', "port box touches"),
    "open mesh wall": ('[anatomy]\n[anatomy.body_wall]\nshape = "mesh"\nfile = "open.stl"\n',
                       "open.stl: not a closed surface"),
    "missing mesh wall": ('[anatomy]\n[anatomy.body_wall]\nshape = "mesh"\nfile = "nope.stl"\n', "nope.stl"),
    "planar": None,
}


#: the case run as the real console command (a separate process); the others call errplan.cli.main in process
BAD_SUBPROCESS = "negative radius"


@pytest.mark.parametrize("case", [k for k in BAD if BAD[k]])
def test_bad_anatomy_is_one_line_exit_2(tmp_path, case, capsys, monkeypatch):
    from errplan.anatomy.meshes import icosphere, write_surface
    from errplan.cli import main
    v, f = icosphere(1)
    write_surface(tmp_path / "open.stl", v * 0.01 + [0, 0, 0.4], f[:-4])
    (tmp_path / "empty.stl").write_bytes(b"")
    extra, word = BAD[case]
    p = _write(tmp_path, extra)
    out = tmp_path / "f.npz"
    if case == BAD_SUBPROCESS:
        r = subprocess.run([sys.executable, "-m", "errplan", "fields", str(p), "--out", str(out)], capture_output=True,
                           text=True, cwd=tmp_path)
        rc, err = r.returncode, r.stderr
    else:
        monkeypatch.chdir(tmp_path)
        capsys.readouterr()
        rc = main(["fields", str(p), "--out", str(out)])
        err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and word in lines[0], err
    assert not out.exists() and not list(tmp_path.glob("*.part"))


def test_anatomy_is_spatial_only():
    doc = tomllib.loads((ROOT / "scenarios" / "beasley2004_bounded.toml").read_text())
    doc.update(tomllib.loads("[anatomy]\nclearance = 0.001\n"))
    with pytest.raises(ScenarioError, match="planar"):
        parse_scenario(doc, str(ROOT / "scenarios" / "beasley2004_bounded.toml"))


def test_cli_fields_writes_clearance(tmp_path, capsys, monkeypatch):
    from errplan.cli import main
    out = tmp_path / "a.npz"
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    rc = main(["fields", str(ROOT / "scenarios" / "abdomen.toml"), "--out", str(out), "--resolution", "0.012",
               "--workers", "1"])
    r = capsys.readouterr()
    assert rc == 0, r.err
    assert "clearance" in r.out and "not robustly clear" in r.out
    with np.load(out) as d:
        c, v = d["clearance"], d["valid"]
        meta = json.loads(str(d["meta"]))
    assert np.all(c[v] >= meta["anatomy"]["clearance"])
    assert meta["anatomy"]["blocked_points"] == int(np.sum(np.isfinite(c) & (c < meta["anatomy"]["clearance"])))


# ----------------------------------------------------------------------------- port placement on the wall
WALL_REGION = {"x": (-0.03, 0.03), "y": (-0.03, 0.03), "z": (0.36, 0.42)}
WALL_SPACING, WALL_RES = 0.03, 0.015  # 265 wall candidates (510 with refinement), 125 region points
WALL_TOL = """
[[tolerance]]
name = "on the wall"
kind = "port_placement"
candidates = "body_wall"
spacing = 0.02
region = { x = [-0.03, 0.03], y = [-0.03, 0.03], z = [0.36, 0.42] }
resolution = 0.01
"""


@pytest.fixture(scope="module")
def wall_run():
    from errplan.tolerance.wall import wall_port_placement
    abd = ROOT / "scenarios" / "abdomen.toml"
    sc = parse_scenario(tomllib.loads(abd.read_text() + WALL_TOL), str(abd))
    return sc, wall_port_placement(sc, WALL_SPACING, WALL_REGION, resolution=WALL_RES)


@pytest.mark.slow
def test_wall_candidates_are_on_the_wall_and_spaced(wall_run):
    sc, r = wall_run
    c, rad = np.array(sc.anatomy.body_wall.center), np.array(sc.anatomy.body_wall.radii)
    P = np.array([x["port"] for x in r["candidates"]])
    assert np.allclose(np.sum(((P - c) / rad) ** 2, axis=1), 1.0, atol=1e-9)
    g = P[:r["wall_refinement"]["grid_candidates"]]  # the spaced set; refinement adds finer points after it
    d = np.linalg.norm(g[:, None] - g[None], axis=-1) + np.eye(len(g))
    assert d.min() >= WALL_SPACING - 1e-12
    assert r["wall_refinement"]["added"] > 0 and r["covered"] >= r["wall_refinement"]["grid_covered"]
    assert r["best"] in [x["port"] for x in r["candidates"]]
    # the best is the largest coverage (then the smaller max rho*)
    assert r["covered"] == max(x["covered"] for x in r["candidates"])
    assert 0 < r["coverage"] <= 1 and r["covered"] <= r["clear"] <= r["reachable"]


@pytest.mark.slow
def test_wall_coverage_counts_only_clear_points(wall_run):
    """Independently: the best candidate's covered points are reachable and certifiable (the plain
    box-candidate placement at that port), and robustly clear (the fields' clearance of a scenario whose
    port is that candidate)."""
    from dataclasses import replace
    from errplan.fields.compute import anatomy_model
    from errplan.scenario import Port
    from errplan.tolerance.placement import port_placement
    sc, r = wall_run
    b = tuple(r["best"])
    box = {a: (v, v) for a, v in zip("xyz", b)}
    plain = port_placement(sc, box, 0.01, WALL_REGION, resolution=WALL_RES, keep_arrays=True)
    A = plain["_arrays"]
    ok = A["best_valid"] & (A["best_rho_star"] <= A["bound"]) & (A["best_rho_star"] < 1)
    m = anatomy_model(replace(sc, port=Port(b, b)))
    clear = m.tip(A["region_points"]) >= sc.anatomy.clearance
    assert int(np.sum(ok & clear)) == r["covered"]
    assert int(np.sum(ok)) >= r["covered"]


@pytest.mark.slow
def test_cli_tolerance_body_wall(tmp_path, capsys, monkeypatch):
    from errplan.cli import main
    abd = ROOT / "scenarios" / "abdomen.toml"
    import shutil
    shutil.copytree(ROOT / "scenarios" / "abdomen", tmp_path / "abdomen")
    shutil.copy(ROOT / "scenarios" / "phantom15.urdf", tmp_path)
    (tmp_path / "w.toml").write_text(abd.read_text() + WALL_TOL.replace("spacing = 0.02", "spacing = 0.04")
                                            .replace("resolution = 0.01", "resolution = 0.02"))
    js = tmp_path / "t.json"
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    rc = main(["tolerance", str(tmp_path / "w.toml"), "--json", str(js), "--workers", "1"])
    assert rc == 0, capsys.readouterr().err
    t = json.loads(js.read_text())["tolerances"][0]
    assert t["kind"] == "port_placement" and len(t["best"]) == 3 and t["candidate_grid"]["body_wall"]
@pytest.mark.slow
def test_wall_brute_force_finds_none_better(wall_run):
    """A denser set of wall points (a third of the spacing, another lattice than the refinement's halvings)
    near every candidate within 2 covered points of the best: none covers more."""
    from errplan.fields.compute import anatomy_model
    from errplan.tolerance.wall import wall_candidates, wall_port_placement
    sc, r = wall_run
    m = anatomy_model(sc)
    top = np.array([x["port"] for x in r["candidates"] if x["covered"] >= r["covered"] - 2])
    dense = wall_candidates(sc, m, WALL_SPACING / 3, WALL_REGION, near=top, radius=WALL_SPACING)
    rd = wall_port_placement(sc, WALL_SPACING / 3, WALL_REGION, resolution=WALL_RES, ports=dense)
    assert len(rd["candidates"]) > len(top)
    assert rd["covered"] <= r["covered"]


# ----------------------------------------------------------------------------- a mesh body wall
ELLIPSOID_WALL = """shape = "ellipsoid"                        # the inner surface of the insufflated abdomen
center = [0.0, 0.0, 0.36]
radii = [0.16, 0.14, 0.20]"""


def _mesh_wall_abdomen(tmp_path, z=0.36):
    """The bundled abdomen with its ellipsoid wall as a triangulated ellipsoid (icosphere(3) scaled: its
    vertices on the ellipsoid, the port (0, 0, 0.16) one of them) centred at height ``z``."""
    from errplan.anatomy.meshes import icosphere, write_surface
    v, f = icosphere(3)
    write_surface(tmp_path / "wall.stl", v * [160.0, 140.0, 200.0], f)
    abd = ROOT / "scenarios" / "abdomen.toml"
    text = abd.read_text()
    assert ELLIPSOID_WALL in text
    return text.replace(ELLIPSOID_WALL, f'shape = "mesh"\nfile = "{tmp_path / "wall.stl"}"\nscale = 0.001\n'
                                        f"position = [0.0, 0.0, {z}]")


def test_mesh_wall_placement_matches_the_ellipsoid(tmp_path):
    """Port placement on a mesh wall (a triangulated ellipsoid) finds the analytic ellipsoid's coverage
    and a best port within one spacing of its best; the candidates lie on the mesh, spacing apart."""
    from errplan.tolerance.wall import wall_port_placement
    abd = ROOT / "scenarios" / "abdomen.toml"
    runs = []
    for text in (abd.read_text(), _mesh_wall_abdomen(tmp_path)):
        sc = parse_scenario(tomllib.loads(text), str(abd))
        runs.append((sc, wall_port_placement(sc, 0.04, WALL_REGION, resolution=0.02, refine_levels=0)))
    (_, el), (sc, me) = runs
    assert me["region_points"] == el["region_points"] and me["covered"] > 0
    assert abs(me["covered"] - el["covered"]) <= 1
    assert np.linalg.norm(np.subtract(me["best"], el["best"])) <= 0.04
    from errplan.fields.compute import anatomy_model
    m = anatomy_model(sc)
    assert m.mesh_wall
    P = np.array([c["port"] for c in me["candidates"]])
    assert max(m.wall_gap(p) for p in P) < 1e-9
    assert (np.linalg.norm(P[:, None] - P[None], axis=-1) + np.eye(len(P))).min() >= 0.04 - 1e-12


def test_port_off_the_mesh_wall_is_refused(tmp_path):
    abd = ROOT / "scenarios" / "abdomen.toml"
    parse_scenario(tomllib.loads(_mesh_wall_abdomen(tmp_path)), str(abd))  # on the wall: accepted
    with pytest.raises(ScenarioError, match="from the body wall"):
        parse_scenario(tomllib.loads(_mesh_wall_abdomen(tmp_path, z=0.37)), str(abd))
    text = _mesh_wall_abdomen(tmp_path).replace("start = [-0.08, 0.04, 0.40]", "start = [-0.08, 0.04, 0.58]")
    with pytest.raises(ScenarioError, match="outside the body wall"):
        parse_scenario(tomllib.loads(text), str(abd))


def test_record_wall_placement_reads_back(tmp_path):
    """`errplan tolerance --record` of a body-wall placement (errplan.recording.record_placement, as the
    CLI calls it) on the mesh wall: the wall, the obstacles, the candidates coloured by coverage, the
    best port and the region read back; `rerun rrd verify` passes."""
    import os
    import shutil
    import rerun.chunk as rrc
    from errplan.recording import record_placement
    from errplan.tolerance.result import ToleranceResult
    from errplan.tolerance.wall import wall_port_placement
    abd = ROOT / "scenarios" / "abdomen.toml"
    sc = parse_scenario(tomllib.loads(_mesh_wall_abdomen(tmp_path)), str(abd))
    d = wall_port_placement(sc, 0.05, WALL_REGION, resolution=0.03, refine_levels=0)
    path = tmp_path / "w.rrd"
    record_placement(path, sc, [ToleranceResult("on the wall", "port_placement", d, 0.0)])
    rows = {}
    for ch in rrc.RrdReader(path).stream().to_chunks():
        rows[ch.entity_path] = rows.get(ch.entity_path, 0) + ch.num_rows
    base = "/placement/on_the_wall/space"
    for e in ("anatomy/body_wall", "anatomy/stomach", "anatomy/liver", "anatomy/kidney", "anatomy/vessel",
              "candidates", "best", "region"):
        assert rows.get(f"{base}/{e}") == 1, (e, rows)
    assert rows["/placement/on_the_wall/summary"] == 1 and rrc.RrdReader(path).blueprints()
    exe = shutil.which("rerun")
    cmd = [exe] if exe else [sys.executable, "-m", "rerun_cli"]
    v = subprocess.run(cmd + ["rrd", "verify", str(path)], env=dict(os.environ, CI="1"), capture_output=True,
                       text=True, timeout=120)
    assert v.returncode == 0, v.stdout + v.stderr
