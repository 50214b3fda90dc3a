"""rerun recordings (errplan.recording): `rerun rrd verify` passes, the file reads back with
rerun.chunk.RrdReader with every entity and the right number of rows, field images are placed in
metres, and `errplan view` refuses a missing file."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from errplan.cli import main
from errplan.errors import ErrplanError
from errplan.fields import compute_fields
from errplan.pipeline import run_pipeline
from errplan.recording import entity_name, field_image, uv, workspace_edges
from errplan.api import load_scenario

ROOT = Path(__file__).resolve().parents[1]
PORT = ROOT / "scenarios" / "beasley2004_port.toml"


def _rerun_cmd() -> list[str]:
    exe = shutil.which("rerun")
    return [exe] if exe else [sys.executable, "-m", "rerun_cli"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    sc = load_scenario(PORT)
    mf = compute_fields(sc, resolution=0.004, rho_star=True)
    queries = [
        {"name": "N-to-L", "start": [0.0, 0.415], "goal": [0.0, 0.320],
         "planned": {"path": [[0.0, 0.415], [0.01, 0.37], [0.0, 0.320]], "cost": 0.2, "length": 0.1, "max_G_norm": 1.2},
         "direct": {"path": [[0.0, 0.415], [0.0, 0.320]], "cost": 0.2, "length": 0.095, "max_G_norm": 1.3}},
        {"name": "short hop/2", "start": [0.0, 0.34], "goal": [0.01, 0.35],
         "planned": {"path": [[0.0, 0.34], [0.01, 0.35]]}, "direct": {"path": [[0.0, 0.34], [0.01, 0.35]]}},
    ]
    path = tmp_path_factory.mktemp("rec") / "plan.rrd"
    res = run_pipeline(sc, queries, mf, record=str(path))
    return sc, mf, res, path


def test_rrd_verify_passes(recorded):
    *_, path = recorded
    assert path.exists() and not path.with_name(path.name + ".part").exists()
    env = dict(os.environ, CI="1")
    p = subprocess.run(_rerun_cmd() + ["rrd", "verify", str(path)], env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr


def test_read_back_every_entity_with_its_rows(recorded):
    import rerun.chunk as rrc

    sc, mf, res, path = recorded
    rows: Counter = Counter()
    timelines: dict = {}
    for chunk in rrc.RrdReader(path).stream().to_chunks():
        rows[chunk.entity_path] += chunk.num_rows
        timelines.setdefault(chunk.entity_path, set()).update(chunk.timeline_names)
    runs = res["runs"]
    assert [r.name for r in runs] == ["N-to-L", "short hop/2"]
    for r in runs:
        q = entity_name(r.name)
        assert "/" not in q
        for kind, rep in (("planned", r.sim_planned), ("direct", r.sim_direct)):
            n = rep.sim.steps + 1  # states 0..steps, one row each on the step timeline
            assert rows[f"/plane/{q}/sim/{kind}/tip"] == n
            assert rows[f"/series/{q}/{kind}/error"] == n + 1  # + the static series style
            assert rows[f"/series/{q}/{kind}/phi"] == n + 1
            assert "step" in timelines[f"/plane/{q}/sim/{kind}/tip"]
            assert rows[f"/plane/{q}/sim/{kind}/trajectory"] == 1
        nseg = len(r.schedule.segments)
        assert nseg >= (5 if r.name == "N-to-L" else 1)  # the polyline is cut into <= 20 mm pieces
        assert rows[f"/gains/{q}/gain"] == nseg + 1
        assert "segment" in timelines[f"/gains/{q}/gain"]
        for e in ("planned", "direct", "segments", "corners/planned", "corners/direct"):
            assert rows[f"/plane/{q}/{e}"] == 1, e
    for e in ("G_norm", "phi_hat_max", "rho_star"):
        assert rows[f"/plane/fields/{e}"] == 2  # placement transform + depth image
    for e in ("/plane/workspace", "/plane/port/true", "/plane/port/estimate", "/summary"):
        assert rows[e] == 1
    # and the file carries the blueprint
    assert rrc.RrdReader(path).blueprints()


def test_field_image_is_placed_in_metres():
    sc = load_scenario(PORT)
    mf = compute_fields(sc, resolution=0.005)
    img, tr, scale = field_image(mf, "G_norm")
    assert img.shape == (len(mf.y), len(mf.z))
    res = mf.resolution
    # pixel (col j, row i) centre -> (u, v) = (z_j, -y_{ny-1-i}) and carries field[ny-1-i, j]
    for i, j in [(0, 0), (5, 17), (len(mf.y) - 1, len(mf.z) - 1)]:
        u = tr[0] + scale[0] * (j + 0.5)
        v = tr[1] + scale[1] * (i + 0.5)
        iy = len(mf.y) - 1 - i
        assert np.allclose(uv([mf.y[iy], mf.z[j]]), [u, v])
        want = mf.G_norm[iy, j] if mf.valid[iy, j] else 0.0
        assert img[i, j] == pytest.approx(want, rel=1e-6)
    assert scale[0] == scale[1] == res and np.all(np.isfinite(img))


def test_workspace_edges_of_a_single_cell():
    class F:
        y = np.array([0.0, 0.1, 0.2])
        z = np.array([1.0, 1.1, 1.2])
        valid = np.zeros((3, 3), bool)
        resolution = 0.1

    F.valid[1, 1] = True
    e = workspace_edges(F)
    assert e.shape == (4, 2, 2)
    assert np.allclose(np.sort(e.reshape(-1, 2)[:, 0]), [0.05] * 4 + [0.15] * 4)
    assert np.allclose(np.sort(e.reshape(-1, 2)[:, 1]), [1.05] * 4 + [1.15] * 4)


def test_view_refuses_a_missing_or_foreign_file(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nope.rrd")]) == 2
    assert "recording not found" in capsys.readouterr().err
    bad = tmp_path / "bad.rrd"
    bad.write_text("hello")
    assert main(["view", str(bad)]) == 2
    assert "not a rerun recording" in capsys.readouterr().err


def test_view_spawns_rerun_with_ci_set(recorded, monkeypatch):
    from errplan.cli import view

    *_, path = recorded
    seen = {}

    def fake_call(cmd, env=None):
        seen["cmd"], seen["env"] = cmd, env
        return 0

    monkeypatch.setattr(view.subprocess, "call", fake_call)
    monkeypatch.setenv("DISPLAY", ":0")
    assert main(["view", str(path)]) == 0
    assert seen["cmd"][-1] == str(path) and seen["env"]["CI"] == "1" and "--web-viewer" not in seen["cmd"]
    assert main(["view", "--web", str(path)]) == 0
    assert seen["cmd"][-2:] == ["--web-viewer", str(path)] and seen["env"]["CI"] == "1"


def test_view_without_display_suggests_the_web_viewer(recorded, monkeypatch, capsys):
    import sys as _sys

    *_, path = recorded
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if not _sys.platform.startswith("linux"):
        pytest.skip("display detection is Linux-only")
    assert main(["view", str(path)]) == 2
    assert "--web" in capsys.readouterr().err


def test_record_into_missing_directory_is_refused(recorded, tmp_path):
    from errplan.recording import record_plan

    sc, mf, res, _ = recorded
    with pytest.raises(ErrplanError, match="does not exist"):
        record_plan(tmp_path / "no" / "x.rrd", sc, mf, res["runs"])


# ----------------------------------------------------------------------------- 3-D helpers
def test_turbo_colormap_runs_from_blue_to_red():
    """The polynomial fit of Turbo: dark blue at 0, cyan at 1/4, green-yellow at 1/2, orange at 3/4, dark red
    at 1 (the dominant channel at each), clipped outside [0, 1]."""
    from errplan.recording import turbo

    c = turbo([0.0, 0.25, 0.5, 0.75, 1.0]).astype(int)
    assert c[0].max() < 60                                           # near black (dark blue)
    assert c[1, 2] > 200 and c[1, 1] > 150 and c[1, 0] < 80           # cyan
    assert c[2, 1] > 230 and c[2, 2] < 120                            # green-yellow
    assert c[3, 0] > 230 and 80 < c[3, 1] < 180 and c[3, 2] < 60      # orange
    assert c[4, 0] > 100 and c[4, 1] < 40 and c[4, 2] < 40            # dark red
    assert np.array_equal(turbo([-1.0, 2.0]), turbo([0.0, 1.0]))


def test_level_surface_of_an_analytic_field():
    """Marching cubes on |x - c| / R over a 3-D grid: the surface at level 1 is the sphere of radius R
    (to the grid's linear interpolation), and a tip outside the workspace cuts it away."""
    from errplan.recording import level_surface, slice_mesh

    class F:
        pass

    h = 0.005
    ax = np.arange(-0.05, 0.0501, h)
    X, Y, Z = np.meshgrid(ax, ax, ax + 0.3, indexing="ij")
    f = F()
    f.axes = (ax, ax, ax + 0.3)
    f.resolution = h
    c, R = np.array([0.0, 0.0, 0.3]), 0.03
    f.G_norm = np.sqrt(X ** 2 + Y ** 2 + (Z - 0.3) ** 2) / R
    f.valid = np.ones(X.shape, bool)
    V, T, N = level_surface(f, "G_norm", 1.0)
    r = np.linalg.norm(V - c, axis=-1)
    assert len(T) > 100 and np.abs(r - R).max() < 0.3 * h
    f.valid = X < 0.0  # half the grid outside the workspace: no vertex beyond it
    V2, _, _ = level_surface(f, "G_norm", 1.0)
    assert V2[:, 0].max() <= 1e-12 and len(V2) < len(V)
    f.array = lambda name: getattr(f, name)
    P, T, C = slice_mesh(f, "G_norm", 1, 10)  # the plane y = ax[10] = 0
    assert np.allclose(P[:, 1], ax[10]) and P.shape == (len(ax) ** 2, 3)
    assert np.all(P[np.unique(T), 0] <= 1e-12)  # triangles only where all corners are valid
