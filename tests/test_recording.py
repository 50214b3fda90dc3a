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
from errplan.scenario import load_scenario

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
