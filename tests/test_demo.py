"""`errplan demo`: the bundled scenario end to end (fields, plan, gains, simulation, recording) and the
plan JSON keys of docs/interfaces.md (`gains` S objects, `simulation` R objects)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

from errplan.cli import main

S_KEYS = {"from", "to", "gain", "certified_G_norm"}
R_KEYS = {"steps", "final_error", "max_deviation", "max_phi", "monotonic"}
P_KEYS = {"path", "cost", "length", "max_G_norm", "max_phi_hat_max"}


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    d = tmp_path_factory.mktemp("demo")
    rec, js = d / "errplan-demo.rrd", d / "demo.json"
    cap = {}
    import io
    from contextlib import redirect_stdout

    buf = io.StringIO()
    with redirect_stdout(buf):
        rc = main(["--quiet", "demo", "--record", str(rec), "--json", str(js)])
    cap["stdout"] = buf.getvalue()
    return rc, cap["stdout"], rec, json.loads(js.read_text())


def test_demo_runs_and_prints_the_summary(demo):
    rc, out, rec, doc = demo
    assert rc == 0
    for h in ("query", "path", "cost", "max ||G||", "steps", "monotonic", "certified"):
        assert h in out
    for q in doc["queries"]:
        assert q["name"] in out
    assert "planned" in out and "direct" in out and "recording:" in out
    assert rec.exists()


def test_demo_json_has_the_interface_keys(demo):
    _, _, _, doc = demo
    assert doc["queries"]
    for q in doc["queries"]:
        assert {"name", "start", "goal", "planned", "direct", "gains", "simulation"} <= set(q)
        assert P_KEYS <= set(q["planned"]) and P_KEYS <= set(q["direct"])
        assert q["gains"] and all(S_KEYS <= set(s) for s in q["gains"])
        assert R_KEYS <= set(q["simulation"]["planned"]) and R_KEYS <= set(q["simulation"]["direct"])
        # the segments chain from the planned path's start to its goal
        assert q["gains"][0]["from"] == pytest.approx(q["planned"]["path"][0])
        assert q["gains"][-1]["to"] == pytest.approx(q["planned"]["path"][-1])
        for a, b in zip(q["gains"][:-1], q["gains"][1:]):
            assert a["to"] == pytest.approx(b["from"])


def test_demo_plans_are_certified_and_monotonic_everywhere(demo):
    _, _, _, doc = demo
    for q in doc["queries"]:
        assert all(s["certified"] and s["certified_G_norm"] < 1 for s in q["gains"]), q["name"]
        sim = q["simulation"]
        assert sim["planned"]["monotonic"] and sim["planned"]["converged"]
        assert sim["planned"]["final_error"] < 1e-5
        c = sim["corners"]
        assert len(c["planned"]) == 8  # every corner of the (dy, dz, t) box
        assert c["planned_all_monotonic"] and c["planned_all_converged"]


def test_demo_direct_path_fails_where_its_certificate_does(demo):
    """The long direct move of the demo (one segment across the workspace) has no certifying gain: its
    ball's worst-case ||G|| exceeds 1, and replays under the error-box corners are not all monotonic."""
    _, _, _, doc = demo
    bad = [q for q in doc["queries"] if not q["direct_gains"][0]["certified"]]
    assert bad
    q = max(bad, key=lambda q: q["direct"]["length"])
    s = q["direct_gains"][0]
    assert s["certified_G_norm"] is None or s["certified_G_norm"] >= 1 or s["step_ratio"] is None or s["step_ratio"] >= 1
    assert q["simulation"]["direct_gain_source"] == "scenario"
    assert not q["simulation"]["corners"]["direct_all_monotonic"]


def test_demo_recording_verifies(demo):
    rec = demo[2]
    exe = shutil.which("rerun")
    cmd = [exe] if exe else [sys.executable, "-m", "rerun_cli"]
    p = subprocess.run(cmd + ["rrd", "verify", str(rec)], env=dict(os.environ, CI="1"), capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr


def test_demo_bad_scenario_is_one_clear_error(tmp_path, capsys):
    assert main(["demo", "--scenario", str(tmp_path / "missing.toml"), "--record", str(tmp_path / "x.rrd")]) == 2
    err = capsys.readouterr().err
    assert "missing.toml" in err and err.count("\n") == 1
    assert not (tmp_path / "x.rrd").exists()
