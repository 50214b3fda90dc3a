"""The first run's background warm-up (errplan.cli.warmup): it reports each part it has done, a part that
fails is reported done too (the command then compiles it itself), and it starts nothing when turned off."""
from __future__ import annotations

import subprocess
import sys

from errplan.cli import warmup


def test_the_warm_up_process_reports_each_part_in_order(tmp_path):
    status = tmp_path / "status.txt"
    r = subprocess.run([sys.executable, "-m", "errplan.cli.warmup", str(status), "plan2", "no-such-part"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    lines = status.read_text(encoding="utf-8").splitlines()
    assert [ln.split()[0] for ln in lines] == ["plan2", "no-such-part"]
    assert all(float(ln.split()[1]) >= 0 for ln in lines)


def test_a_planner_kernel_compiled_by_the_warm_up_is_in_the_disk_cache(tmp_path):
    from errplan.jit import cached
    from errplan.planning import cellwalk

    subprocess.run([sys.executable, "-m", "errplan.cli.warmup", str(tmp_path / "s"), "plan3"], check=True,
                   capture_output=True, timeout=600)
    assert cached(cellwalk.walk3)
    assert not warmup._cold(["plan3"])


def test_turned_off_or_warm_it_starts_nothing_and_waits_for_nothing(monkeypatch):
    monkeypatch.setenv(warmup.ENV, "0")
    assert warmup.start(["plan2"]) is False
    assert warmup._STATE["proc"] is None
    warmup.wait("plan2", timeout=0.0)  # returns at once
    with warmup.paused():
        pass
    monkeypatch.setenv(warmup.ENV, "1")
    subprocess.run([sys.executable, "-m", "errplan.cli.warmup", "/dev/null", "plan2"], check=True, timeout=600)
    assert warmup.start(["plan2"]) is False  # the cache is warm: nothing to do


def test_the_anatomy_part_compiles_the_clearance_kernels_a_scenario_calls(tmp_path):
    """The part's placeholder anatomy calls the kernels with the argument types a scenario's checks, the
    planner and the replays pass (one specialization each, so the run loads them instead of compiling)."""
    from errplan.anatomy import distance

    subprocess.run([sys.executable, "-m", "errplan.cli.warmup", str(tmp_path / "s"), "anatomy"], check=True,
                   capture_output=True, timeout=900)
    assert not warmup._cold(["anatomy"])
    warmup._anatomy()  # in this process: loaded from the cache, one signature each
    assert len(distance.clearance_batch.signatures) == 1
    assert len(distance.motion_clearance1.signatures) == 1


def test_the_urdf_part_compiles_what_loading_a_spatial_scenario_compiles(tmp_path):
    """After the part, loading a URDF scenario (its arm's kinematics, its reachability map's build) and
    the arm's vectorized calls, broadcast arguments included, compile nothing: one specialization each."""
    import numpy as np

    from conftest import SCENARIOS
    from errplan.kinematics import arm_for
    from errplan.kinematics.urdf import chain, reachmap

    subprocess.run([sys.executable, "-m", "errplan.cli.warmup", str(tmp_path / "s"), "urdf"], check=True,
                   capture_output=True, timeout=900)
    assert not warmup._cold(["urdf"])
    from errplan.api import load_scenario

    arm = arm_for(load_scenario(SCENARIOS / "phantom15_spatial.toml").robot)
    q = np.broadcast_to(np.zeros(arm.n), (4, arm.n))  # read-only views
    w = arm.forward(q)
    arm.jacobian(q), arm.reachable(np.broadcast_to(w[0], (3, 3))), arm.inverse(w), arm.inverse(w, near=q[0])
    reachmap.build_map(arm)  # built here (not read from the cache, whatever this process loaded before)
    warmup._urdf()
    for f in (chain._fk_many, chain._jac_many, chain._reach_many, chain._ik_many, reachmap._coarse_bbox,
              reachmap._build_map):
        assert len(f.signatures) == 1, (f, f.signatures)


def test_the_arm_part_compiles_the_kinematics_a_spatial_scenario_calls(tmp_path):
    """A first demo's warm-up starts with the arm's kinematics (errplan.cli.demo), so that the command,
    loading the spatial scenario, compiles only the reachability map's build: after the part, the PHANToM's
    forward kinematics, Jacobians, reachability test and map bounding box have the placeholder's types
    (one specialization each)."""
    import numpy as np

    from conftest import SCENARIOS
    from errplan.kinematics import arm_for
    from errplan.kinematics.urdf import chain, reachmap

    subprocess.run([sys.executable, "-m", "errplan.cli.warmup", str(tmp_path / "s"), "arm"], check=True,
                   capture_output=True, timeout=900)
    assert not warmup._cold(["arm"])
    from errplan.api import load_scenario

    arm = arm_for(load_scenario(SCENARIOS / "phantom15_spatial.toml").robot)
    q = np.zeros((4, arm.n))
    w = arm.forward(q)
    arm.jacobian(q), arm.reachable(w)
    reachmap.build_map(arm)  # its coarse bounding box too
    warmup._arm()
    for f in (chain._fk_many, chain._jac_many, chain._reach_many, reachmap._coarse_bbox):
        assert len(f.signatures) == 1, (f, f.signatures)


def test_the_lanes_part_compiles_what_a_port_box_field_runs():
    """The ``lanes2`` part's placeholder arguments have the types a field of a pure port box passes: after
    both, the lanes' entry has one specialization (the command loads what the part compiled)."""
    from conftest import SCENARIOS
    from errplan.api import compute_fields, load_scenario
    from errplan.fields import kernels

    warmup._lanes(2)
    f = compute_fields(load_scenario(SCENARIOS / "beasley2004_port.toml"), 0.01, metrics=("G_norm",), workers=1)
    assert f.valid.sum() > 100
    assert len(kernels._LANE_TILES[2].signatures) == 1


def test_the_gains_parts_compile_what_the_gains_and_replays_call():
    """The ``gains2`` and ``gains3`` parts run their kernels with the argument types the gains, the
    certificates and the replays pass (C arrays; the bounded scan, the worst instances and the top
    eigenvalue candidates on matrices, not an empty batch that returns before them): after a planar
    evaluator's true wrists and a 3-D certificate's scans, each entry has one specialization (a demo's
    workers load what the warm-up compiled instead of compiling it each)."""
    import numpy as np

    from conftest import SCENARIOS
    from errplan.api import load_scenario
    from errplan.fields import evaluator
    from errplan.gains import physics
    from errplan.kinematics import compiled
    from errplan.models import arm_model

    warmup._gains2()
    warmup._gains3()
    ev = evaluator.Evaluator.from_model(arm_model(load_scenario(SCENARIOS / "beasley2004_bounded.toml")))
    rng = np.random.default_rng(3)
    x = np.array([0.0, 0.4]) + 0.01 * rng.standard_normal((6, 2))  # about the scenario's query tips
    theta = np.concatenate([0.002 * rng.standard_normal((6, 2)), np.full((6, 1), 0.01)], axis=1)
    w, ok = ev.true_wrist(x, theta)
    assert ok.any() and np.isfinite(w[ok]).all()
    M = np.eye(3) + 0.05 * rng.standard_normal((12, 3, 3))
    physics.grid_top(M, np.linspace(0.2, 1.2, 9), 3)
    physics.worst_instances(M.reshape(2, 3, 2, 3, 3), np.ones((2, 3), bool), 0.8, False)
    physics.sym_top_candidates(M + M.transpose(0, 2, 1))
    for f in (evaluator._true_wrist2, compiled._wrist2_kernel, compiled._reachable_kernel, physics._grid_top,
              physics._worst_instances, physics._sym_top):
        assert len(f.signatures) == 1, (f, f.signatures)


def test_plan_fields_and_tolerance_start_the_warm_up_before_loading_the_arm(monkeypatch, tmp_path):
    """A first `errplan plan` of a spatial scenario compiles the fields' search, the planner's and the
    gains' kernels in the second process from the start, while it loads and checks the arm (the map's
    build, the anatomy's clearances); a planar one the planner's and the gains' only (no map to build:
    the command compiles its search itself). A first `errplan fields` or `errplan tolerance` of a spatial
    scenario: its search."""
    from conftest import SCENARIOS
    from errplan import api
    from errplan.cli import main
    from errplan.errors import ScenarioError

    calls = []
    monkeypatch.setattr(warmup, "start", lambda parts: calls.append(("start", tuple(parts))) or False)

    def stop_here(path):
        calls.append(("load", str(path)))
        raise ScenarioError("stop here")

    monkeypatch.setattr(api, "load_setup", stop_here)
    assert main(["plan", str(SCENARIOS / "abdomen.toml")]) == 2
    assert main(["plan", str(SCENARIOS / "beasley2004_bounded.toml")]) == 2
    assert [c[0] for c in calls] == ["start", "load", "start", "load"]
    assert calls[0][1] == ("fields3g", "plan3", "gains3")
    assert calls[2][1] == ("plan2", "gains2")
    # `errplan fields`: the spatial search (with the exact |phi_max| by default, without it when not asked
    # for), none for the plane, a flexion controller (the numpy path) or a dask scheduler (remote workers)
    calls.clear()
    out = str(tmp_path / "unused.npz")
    assert main(["fields", str(SCENARIOS / "abdomen.toml"), "--out", out]) == 2
    assert main(["fields", str(SCENARIOS / "abdomen.toml"), "--out", out, "--metrics", "G_norm"]) == 2
    assert main(["fields", str(SCENARIOS / "beasley2004_bounded.toml"), "--out", out]) == 2
    assert main(["fields", str(SCENARIOS / "phantom15_flexion.toml"), "--out", out]) == 2
    assert main(["fields", str(SCENARIOS / "abdomen.toml"), "--out", out, "--scheduler", "tcp://nowhere:1"]) == 2
    assert calls == [("start", ("fields3",)), ("load", str(SCENARIOS / "abdomen.toml")),
                     ("start", ("fields3g",)), ("load", str(SCENARIOS / "abdomen.toml"))] + [
        ("load", str(SCENARIOS / f)) for f in ("beasley2004_bounded.toml", "phantom15_flexion.toml", "abdomen.toml")]
    # `errplan tolerance`: the search without |phi_max| (and a setup's triad placement its lanes), none in
    # the plane
    calls.clear()
    assert main(["tolerance", str(SCENARIOS / "phantom15_placement.toml")]) == 2
    assert main(["tolerance", str(SCENARIOS / "abdomen_triad.toml")]) == 2
    assert main(["tolerance", str(SCENARIOS / "beasley2004_port.toml")]) == 2
    assert [c[1] for c in calls if c[0] == "start"] == [("fields3g",), ("fields3g", "lanes3")]
    assert [c[0] for c in calls] == ["start", "load", "start", "load", "load"]
