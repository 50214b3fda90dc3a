"""Anatomy benchmark (issue 18): what the obstacle checks cost, and how the geometry library was chosen.

    python benchmarks/anatomy.py [--tips 2000] [--skip-pipeline]

1. **Candidates for the robust clearance** of a tip (the distance from every obstacle to the shaft hull
   conv(port box ∪ {tip}), docs/physics.md "Anatomy"), on the bundled abdomen's obstacles (three organ
   meshes of 320 triangles, a capsule) and ``--tips`` random tips of its task region, microseconds per tip:
   - errplan's compiled GJK (errplan.anatomy.distance: clusters of 16 triangles culled by bounding spheres);
   - python-fcl 0.7: a ``Convex`` of the hull's 9 points (faces from scipy's ConvexHull) against a
     ``BVHModel`` per mesh and a ``Capsule``, ``fcl.distance`` per pair;
   - trimesh's proximity (``closest_point``, point to mesh): it cannot take a hull, so the shaft is
     sampled (8 corner ports x 64 points, i.e. about 5 mm apart: not exact, a lower bound on its cost).
   The values of fcl and GJK are compared (max difference).
2. **Overhead on the bundled abdomen** (scenarios/abdomen.toml at its 8 mm resolution): the fields and
   the planner with and without [anatomy] (same scenario, the table removed; each timed after a warm-up
   run), and the anatomy pass alone.
"""
from __future__ import annotations

import argparse
import itertools
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
ABDOMEN = ROOT / "scenarios" / "abdomen.toml"


def candidates(n_tips: int) -> list[tuple[str, float, str]]:
    import fcl
    import trimesh
    from scipy.spatial import ConvexHull

    from errplan.api import load_scenario
    from errplan.fields.compute import anatomy_model

    sc = load_scenario(ABDOMEN)
    m = anatomy_model(sc)
    m_obs = m.with_box(m.box)
    m_obs.wall = np.zeros(7)  # obstacles only: what the libraries are compared on
    rng = np.random.default_rng(0)
    reg = sc.fields.region
    tips = rng.uniform([reg[a][0] for a in "xyz"], [reg[a][1] for a in "xyz"], size=(n_tips, 3))
    m_obs.tip(tips[:5])
    t = time.perf_counter()
    mine = m_obs.tip(tips)
    t_mine = (time.perf_counter() - t) / n_tips * 1e6
    # fcl
    objs = []
    for s in m.surfaces:
        if s.shape == "mesh":
            bvh = fcl.BVHModel()
            bvh.beginModel(len(s.vertices), len(s.faces))
            bvh.addSubModel(s.vertices, s.faces)
            bvh.endModel()
            objs.append(fcl.CollisionObject(bvh, fcl.Transform()))
    for o in sc.anatomy.obstacles:
        if o.shape == "capsule":
            a, b = np.asarray(o.a), np.asarray(o.b)
            L = float(np.linalg.norm(b - a))
            z = (b - a) / L
            x = np.cross(z, [1.0, 0, 0]) if abs(z[0]) < 0.9 else np.cross(z, [0, 1.0, 0])
            x /= np.linalg.norm(x)
            R = np.column_stack([x, np.cross(z, x), z])
            objs.append(("capsule", fcl.CollisionObject(fcl.Capsule(o.radius, L), fcl.Transform(R, (a + b) / 2))))
    objs = [o if isinstance(o, tuple) else ("mesh", o) for o in objs]
    box = m.box
    req = fcl.DistanceRequest(enable_nearest_points=False)
    t = time.perf_counter()
    vals = []
    for x in tips:
        P = np.vstack([box, x])
        h = ConvexHull(P)
        used = np.unique(h.simplices)
        remap = -np.ones(len(P), int)
        remap[used] = np.arange(len(used))
        faces = remap[h.simplices]
        flat = np.hstack([np.full((len(faces), 1), 3), faces]).ravel()
        cv = fcl.CollisionObject(fcl.Convex(P[used], len(faces), flat), fcl.Transform())
        d = min(fcl.distance(cv, o, req, fcl.DistanceResult()) for _, o in objs)
        vals.append(max(d, 0.0))
    t_fcl = (time.perf_counter() - t) / n_tips * 1e6
    diff = float(np.max(np.abs(np.array(vals) - mine)))
    # trimesh proximity on sampled shafts (meshes only)
    meshes = [trimesh.Trimesh(s.vertices, s.faces) for s in m.surfaces if s.shape == "mesh"]
    k = min(n_tips, 200)
    s = np.linspace(0, 1, 64)[:, None]
    t = time.perf_counter()
    try:
        for x in tips[:k]:
            pts = (box[:, None, :] * (1 - s) + x * s).reshape(-1, 3)
            for tm in meshes:
                trimesh.proximity.closest_point(tm, pts)
        t_tm, note = (time.perf_counter() - t) / k * 1e6, "sampled (5 mm), meshes only"
    except ImportError as e:  # trimesh's proximity needs rtree
        t_tm, note = float("nan"), f"not available here: {e}"
    return [("errplan GJK (compiled, exact)", t_mine, "reference"),
            ("python-fcl Convex vs BVH/Capsule", t_fcl, f"max |fcl - GJK| = {diff * 1000:.4f} mm"),
            ("trimesh closest_point, sampled shaft", t_tm, note)]


def overhead() -> list[tuple[str, float, float]]:
    from errplan.api import parse_scenario
    from errplan.fields import compute_fields
    from errplan.fields.compute import anatomy_model
    from errplan.planning import plan_scenario

    doc = tomllib.loads(ABDOMEN.read_text())
    rows = []
    times = {}
    for label, d in (("with", doc), ("without", {k: v for k, v in doc.items() if k != "anatomy"})):
        sc = parse_scenario(d, str(ABDOMEN))
        compute_fields(sc, 0.02, metrics=("G_norm", "phi_hat_max"), rho_star=True)  # warm: kernels loaded
        t = time.perf_counter()
        mf = compute_fields(sc, metrics=("G_norm", "phi_hat_max"), rho_star=True, workers=1)
        tf = time.perf_counter() - t
        plan_scenario(sc, mf)  # warm: every kernel compiled or loaded before the timed run
        t = time.perf_counter()
        plan_scenario(sc, mf)
        tp = time.perf_counter() - t
        times[label] = (tf, tp)
        if label == "with":
            model = anatomy_model(sc)
            P = mf.points().reshape(-1, 3)
            reach = np.isfinite(mf.clearance.reshape(-1))
            t = time.perf_counter()
            model.tip(P[reach])
            times["pass"] = time.perf_counter() - t
    rows.append(("fields (s)", times["without"][0], times["with"][0]))
    rows.append(("planner, 3 queries (s)", times["without"][1], times["with"][1]))
    rows.append(("anatomy pass of the fields (s)", 0.0, times["pass"]))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tips", type=int, default=2000)
    ap.add_argument("--skip-pipeline", action="store_true")
    a = ap.parse_args(argv)
    print(f"robust clearance of one tip, bundled abdomen ({a.tips} tips)")
    print(f"{'method':40s} {'us/tip':>10s}  note")
    for name, us, note in candidates(a.tips):
        print(f"{name:40s} {us:10.1f}  {note}")
    if not a.skip_pipeline:
        print("\noverhead of [anatomy] on scenarios/abdomen.toml (8 mm, 1 worker)")
        print(f"{'step':32s} {'without':>9s} {'with':>9s} {'added':>7s}")
        for name, w0, w1 in overhead():
            add = f"{(w1 - w0) / w0 * 100:6.1f}%" if w0 > 0 else ""
            print(f"{name:32s} {w0:9.2f} {w1:9.2f} {add:>7s}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
