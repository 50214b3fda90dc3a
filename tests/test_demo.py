"""`errplan demo`: the bundled scenarios end to end (fields, plan, gains, simulation, recording): P1's
planar Phantom, the spatial PHANToM 1.5 on its URDF, the abdomen and the several-instrument setup, the plan JSON keys of docs/interfaces.md
(`gains` S objects, `simulation` R objects) in both, every planned segment certified and every corner
replay monotonic, every recording verified, the abdomen's runs clear of its anatomy."""
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
    for q in doc["queries"] + doc["spatial"]["queries"]:
        assert q["name"] in out
    assert "planned" in out and "direct" in out and "recording:" in out
    assert "errplan demo: beasley2004-bounded" in out and "errplan demo: phantom15-spatial" in out
    assert out.count("max ||G||: worst case along the path") == 3  # the same table for each scenario
    assert "errplan demo: abdomen" in out and "min clearance of the shaft" in out
    assert rec.exists() and rec.with_name("errplan-demo-3d.rrd").exists()
    assert rec.with_name("errplan-demo-abdomen.rrd").exists()
    assert doc["spatial"]["dim"] == 3 and len(doc["spatial"]["queries"]) == 3
    assert doc["anatomy"]["scenario"] == "abdomen" and len(doc["anatomy"]["queries"]) == 3


def _all_queries(doc):
    return doc["queries"] + doc["spatial"]["queries"] + doc["anatomy"]["queries"]


def test_demo_json_has_the_interface_keys(demo):
    _, _, _, doc = demo
    assert doc["queries"]
    for q in _all_queries(doc):
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
    for q in _all_queries(doc):
        assert all(s["certified"] and s["certified_G_norm"] < 1 for s in q["gains"]), q["name"]
        sim = q["simulation"]
        assert sim["planned"]["monotonic"] and sim["planned"]["converged"]
        assert sim["planned"]["final_error"] < 1e-5
        c = sim["corners"]
        assert len(c["planned"]) == 8  # every corner of the (dy, dz, t) box; in 3-D of the port box
        assert c["planned_all_monotonic"] and c["planned_all_converged"]
    for q in doc["spatial"]["queries"]:
        assert len(q["start"]) == 3 and all(len(p) == 3 for p in q["planned"]["path"])
        assert len(q["simulation"]["corners"]["instances"][0]["port_offset"]) == 3
    for q in doc["anatomy"]["queries"]:  # issue 18: every planned run keeps the shaft 4 mm clear
        sim = q["simulation"]
        assert not q["direct"]["valid"]  # every straight line cuts an obstacle
        assert sim["planned"]["min_clearance"] >= 0.004
        assert all(r["min_clearance"] >= 0.004 for r in sim["corners"]["planned"])


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


def test_demo_setup_block_chooses_a_triad_and_plans_each_arm(demo):
    """The several-instrument setup (abdomen_triad.toml) closes the demo: its chosen port triad keeps the
    ports apart by the query's port spacing (plain vector algebra on the JSON ports) and is the row the
    block prints; each arm's planned query keeps its shaft the required distance from the held shafts, is
    certified, converges, and the endoscope sees it."""
    import math

    import numpy as np

    _, out, rec, doc = demo
    st = doc["setup"]
    assert st["scenario"] == "abdomen-triad" and "errplan demo: abdomen-triad" in out
    assert out.index("errplan demo: abdomen (") < out.index("errplan demo: abdomen-triad")
    best = st["triads"][0]["best"]
    ports = {k: np.asarray(v, float) for k, v in best["ports"].items()}
    assert set(ports) == {"left", "right", "endoscope"}
    d = [float(np.linalg.norm(ports[a] - ports[b])) for a, b in (("left", "right"), ("left", "endoscope"),
                                                                  ("right", "endoscope"))]
    assert min(d) >= 0.06 - 1e-12 and min(d) == pytest.approx(best["port_spacing_min"], abs=1e-9)
    row = next(ln for ln in out.splitlines() if ln.strip().startswith("1  ["))
    assert "[" + ", ".join(f"{1000 * v:.1f}" for v in ports["left"]) + "]" in row
    assert {q["arm"] for q in st["queries"]} == {"left", "right"}
    for q in st["queries"]:
        assert q["name"] in out
        assert q["min_shaft_clearance"] >= 0.008 and 0.0 <= q["visible"] <= 1.0 and math.isfinite(q["visible"])
        assert q["certified"] and q["converged"]
    assert rec.with_name("errplan-demo-triad.rrd").exists() and rec.with_name("errplan-demo-triad-plan.rrd").exists()


@pytest.mark.parametrize("name", ["errplan-demo.rrd", "errplan-demo-3d.rrd", "errplan-demo-abdomen.rrd",
                                  "errplan-demo-triad.rrd", "errplan-demo-triad-plan.rrd"])
def test_demo_recording_verifies(demo, name):
    rec = demo[2].with_name(name)
    exe = shutil.which("rerun")
    cmd = [exe] if exe else [sys.executable, "-m", "rerun_cli"]
    p = subprocess.run(cmd + ["rrd", "verify", str(rec)], env=dict(os.environ, CI="1"), capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr


def test_demo_with_a_spatial_scenario_runs_only_that(tmp_path, capsys):
    """`errplan demo --scenario F` runs F alone, planar or spatial, and records it to --record."""
    import json as _json

    from arms import ur5_scenario

    p = ur5_scenario(tmp_path, """
[[query]]
name = "hop"
start = [0.0, 0.0, 0.70]
goal = [0.03, 0.0, 0.70]
""", name="ur5")
    p.write_text(p.read_text().replace("resolution = 0.008", "resolution = 0.016"))  # what is checked is the
    # choice of scenario and its outputs, not the fields' detail
    rec, js = tmp_path / "ur5.rrd", tmp_path / "ur5.json"
    assert main(["--quiet", "demo", "--scenario", str(p), "--record", str(rec), "--json", str(js)]) == 0
    out = capsys.readouterr().out
    assert "errplan demo: ur5" in out and "beasley2004" not in out
    doc = _json.loads(js.read_text())
    assert "spatial" not in doc and doc["dim"] == 3
    assert all(s["certified"] for s in doc["queries"][0]["gains"])
    assert rec.exists() and not rec.with_name("ur5-3d.rrd").exists()


def test_demo_bad_scenario_is_one_clear_error(tmp_path, capsys):
    assert main(["demo", "--scenario", str(tmp_path / "missing.toml"), "--record", str(tmp_path / "x.rrd")]) == 2
    err = capsys.readouterr().err
    assert "missing.toml" in err and err.count("\n") == 1
    assert not (tmp_path / "x.rrd").exists()


def test_side_by_side_prints_what_one_after_another_prints(tmp_path, capsys, monkeypatch):
    """The demo's scenarios run side by side in worker processes (fields, then every query's gains and
    replays as tasks) print the same blocks, in the same order, and return the same documents as one
    after the other in this process (a small UR5 scenario with two queries, another with one)."""
    from arms import ur5_scenario

    from errplan.cli import demo as d

    # the planner stops at its iteration budget, however loaded the machine: its plans are a function of the seed
    p = ur5_scenario(tmp_path, """
[[query]]
name = "hop"
start = [0.0, 0.0, 0.70]
goal = [0.03, 0.0, 0.70]

[[query]]
name = "back"
start = [0.03, 0.0, 0.70]
goal = [0.0, 0.01, 0.70]
""", name="ur5")
    p2 = ur5_scenario(tmp_path, """
[[query]]
name = "side"
start = [0.0, 0.01, 0.70]
goal = [0.03, 0.0, 0.70]
""", name="ur5b")
    for f in (p, p2):
        # small and fast: what is compared is the two ways of running, not the plans' quality (a counted budget
        # of a quarter of BITstar's spatial default)
        text = f.read_text().replace("resolution = 0.008", "resolution = 0.016").replace("weight = 2.0\n",
                                                                               "weight = 2.0\niterations = 1000\n")
        assert "resolution = 0.016" in text and "iterations = 1000" in text
        f.write_text(text)

    def jobs():  # the second one heavier: side by side it starts first, and is still printed second
        return [d.DemoJob(p, record=tmp_path / "a.rrd"), d.DemoJob(p2, record=tmp_path / "b.rrd", weight=2.0)]

    def strip(out):
        return [ln for ln in out.splitlines() if not ln.startswith(("time:", "recording:"))]

    def plain(v):  # the documents without their wall-clock times
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items() if not k.startswith(("time", "timing"))}
        return [plain(x) for x in v] if isinstance(v, list) else v

    one = d.run_jobs(jobs(), True, workers=1)
    out_one = capsys.readouterr().out
    d._STEPS.clear()
    two = d.run_jobs(jobs(), True, workers=2)
    out_two = capsys.readouterr().out
    assert any(e["process"] == "worker" and e["step"] == "query 1" for e in d._STEPS)  # it did run side by side
    assert out_one.index("errplan demo: ur5 ") < out_one.index("errplan demo: ur5b") and "back" in out_one
    assert strip(out_two) == strip(out_one)
    assert plain(two) == plain(one)
    assert (tmp_path / "a.rrd").exists() and (tmp_path / "b.rrd").exists()


def test_a_failing_step_in_a_worker_is_the_one_clear_error(tmp_path):
    """An error of a step run in a worker process reaches the command as itself (ErrplanError: exit 2),
    and no worker is left behind."""
    from errplan.cluster import ForkedTasks
    from errplan.errors import ErrplanError

    tasks = ForkedTasks(2)
    tasks.start("ok", sum, [1, 2])
    tasks.start("bad", _fail, "value 7")
    got = {}
    with pytest.raises(ErrplanError, match="value 7"):
        while True:
            got.update(tasks.collect())
    assert len(tasks) == 0


def _fail(msg):
    from errplan.errors import ErrplanError

    raise ErrplanError(msg)
