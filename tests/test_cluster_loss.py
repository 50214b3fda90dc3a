"""A dask worker SIGKILLed at any moment of a ``--scheduler`` run changes nothing but time.

Real clusters on loopback: a ``distributed.LocalCluster`` (workers under a nanny, which restarts a
killed one) and a bare scheduler with ``dask worker --no-nanny`` processes (a killed worker stays
dead). A worker plugin SIGKILLs its own process at a chosen transition: the shared data arriving from
the scatter, its copy fetched by the other worker, a tile starting, a tile finished. The n-th such event
over the whole cluster is chosen through files created exclusively in ``tmp_path``, so exactly one
worker dies, at the same point of every run. ``map_tasks`` directly, ``errplan fields --scheduler`` and
a port_placement, a triad_placement and a setup_placement query (the tolerance queries share ``map_tasks``)
end with the local run's answer.
"""
from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

from errplan import cluster  # noqa: E402
from errplan.cluster import map_tasks  # noqa: E402
from errplan.errors import ErrplanError  # noqa: E402
from errplan.fields import MetricField  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DASK = Path(sys.executable).with_name("dask")


def _claim(root: str, tag: str) -> int:
    """The index of this event among the events ``tag`` over the whole cluster (0, 1, ...)."""
    i = 0
    while True:
        try:
            os.close(os.open(os.path.join(root, f"{tag}-{i}"), os.O_CREAT | os.O_EXCL))
            return i
        except FileExistsError:
            i += 1


class _Kill(distributed.WorkerPlugin):
    """SIGKILL this worker at the ``nth`` transition to ``state`` of a key starting with ``prefix``
    (counted over the cluster; ``nth = -1``: at every such transition). Each kill leaves a file
    ``killed-<tag>-<pid>`` behind so that a test can check that it happened."""

    def __init__(self, root, triggers):
        self.root = str(root)
        self.triggers = list(triggers)  # (prefix, state, nth)

    def transition(self, key, start, finish, **kwargs):
        k = key if isinstance(key, str) else str(key)
        for j, (prefix, state, nth) in enumerate(self.triggers):
            if finish == state and k.startswith(prefix):
                tag = f"t{j}"
                if nth < 0 or _claim(self.root, tag) == nth:
                    Path(self.root, f"killed-{tag}-{os.getpid()}").touch()
                    os.kill(os.getpid(), signal.SIGKILL)


def _kills(root: Path) -> list[str]:
    return sorted(p.name for p in root.glob("killed-*"))


def _tile(shared, item):
    """A deterministic task with array results, a little slow so that kills land mid-run."""
    time.sleep(0.02)
    x = np.sin(shared["x"] * (item + 1)) * shared["scale"]
    return {"i": item, "x": x, "s": float(np.cumsum(x)[-1])}


def _same_results(a, b):
    assert len(a) == len(b)
    for p, q in zip(a, b):
        assert p["i"] == q["i"]
        assert np.array_equal(p["x"], q["x"])  # bit for bit
        assert p["s"] == q["s"]


SHARED = {"x": np.linspace(0.0, 3.0, 2001), "scale": 1.7}
ITEMS = list(range(24))
# (what, triggers): the data arriving by the scatter (the client's scatter call fails), its copy fetched
# from the first worker by the second, a tile starting (its worker dies while it runs), a tile finished
# (its result and maybe the only copy of the data die before the client fetched them).
PHASES = {
    "scatter": [("dict-", "memory", 0)],
    "copy": [("dict-", "memory", 1)],
    "tile-running": [("_run_remote-", "executing", 3)],
    "tile-finished": [("_run_remote-", "memory", 3)],
}


@pytest.fixture(autouse=True)
def _patient_wait(monkeypatch):
    """A nanny restarts a killed worker, slowly when both cores are busy (the suite's other worker runs
    beside): errplan's wait for a worker is made long here, so that a run the tests kill workers in is
    judged by its answer, not by how fast the machine restarts them. The tests of the wait itself set it."""
    monkeypatch.setattr(cluster, "WORKER_WAIT", 600.0)


@pytest.fixture(scope="module")
def reference():
    return map_tasks(_tile, SHARED, ITEMS, workers=1)


@pytest.fixture(scope="module")
def nanny_cluster():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  host="127.0.0.1") as c:
        yield c


def _dask_worker(address: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "tests"),
                                                       os.environ.get("PYTHONPATH", "")]))
    return subprocess.Popen([str(DASK), "worker", address, "--no-nanny", "--nthreads", "1", "--host", "127.0.0.1",
                             "--no-dashboard"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


@pytest.fixture
def bare_cluster():
    """A scheduler and two ``dask worker --no-nanny`` processes: a killed worker does not come back."""
    with distributed.LocalCluster(n_workers=0, processes=True, dashboard_address=None, host="127.0.0.1") as c:
        procs = [_dask_worker(c.scheduler_address) for _ in range(2)]
        try:
            with distributed.Client(c.scheduler_address) as client:
                client.wait_for_workers(2, timeout=300)
            yield c
        finally:
            for p in procs:
                p.kill()
                p.wait()


def _with_killer(address: str, plugin, run):
    """``run()`` with ``plugin`` on every worker (and every worker that starts meanwhile). The client that
    installs it is closed before the run: errplan's own is the only one while it runs, as in use."""
    with distributed.Client(address) as client:
        client.wait_for_workers(2, timeout=600)  # a nanny restarts a worker killed by the test before (slowly on a busy machine)
        client.register_plugin(plugin, name="errplan-kill")
    try:
        return run()
    finally:
        with distributed.Client(address) as client:
            try:
                client.unregister_worker_plugin("errplan-kill")
            except Exception:  # no worker left to remove it from
                pass


@pytest.mark.parametrize("phase", list(PHASES))
def test_a_worker_killed_under_a_nanny_changes_nothing(nanny_cluster, reference, tmp_path, phase):
    addr = nanny_cluster.scheduler_address
    got = _with_killer(addr, _Kill(tmp_path, PHASES[phase]), lambda: map_tasks(_tile, SHARED, ITEMS, scheduler=addr))
    assert len(_kills(tmp_path)) == 1, "the worker was not killed"
    _same_results(reference, got)


@pytest.mark.parametrize("phase", ["scatter", "tile-running"])
def test_a_worker_killed_for_good_changes_nothing(bare_cluster, reference, tmp_path, phase):
    addr = bare_cluster.scheduler_address
    got = _with_killer(addr, _Kill(tmp_path, PHASES[phase]), lambda: map_tasks(_tile, SHARED, ITEMS, scheduler=addr))
    assert len(_kills(tmp_path)) == 1, "the worker was not killed"
    _same_results(reference, got)
    with distributed.Client(addr) as client:
        assert len(client.nthreads()) == 1  # the run finished on the worker left


def test_a_task_error_is_raised_as_a_local_run_raises_it(nanny_cluster):
    with pytest.raises(ZeroDivisionError):
        map_tasks(_divide, 1.0, [1, 0, 2], scheduler=nanny_cluster.scheduler_address)


def _divide(shared, item):
    return shared / item


def test_no_worker_is_one_clear_error(monkeypatch):
    monkeypatch.setattr(cluster, "WORKER_WAIT", 1.0)
    with distributed.LocalCluster(n_workers=0, processes=True, dashboard_address=None, host="127.0.0.1") as c:
        addr = c.scheduler_address
        with pytest.raises(ErrplanError, match=rf"^--scheduler {addr}: no worker to send the data to \(no worker "
                                               r"for 1 s; 0 of 3 tasks done\)"):
            map_tasks(_divide, 1.0, [1, 2, 3], scheduler=addr)


def test_fields_on_a_scheduler_without_workers_is_one_line_exit_2_and_no_file(monkeypatch, tmp_path, capsys):
    from errplan.cli import main

    monkeypatch.setattr(cluster, "WORKER_WAIT", 1.0)
    out = tmp_path / "f.npz"
    with distributed.LocalCluster(n_workers=0, processes=True, dashboard_address=None, host="127.0.0.1") as c:
        addr = c.scheduler_address
        code = main(["-q", "fields", str(ROOT / "scenarios" / "beasley2004_bounded.toml"), "--out", str(out),
                     "--resolution", "0.01", "--scheduler", addr])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[-1].startswith(f"errplan fields: error: --scheduler {addr}: no worker to send the data to"), err
    assert not out.exists()


def test_every_worker_lost_is_one_clear_error(bare_cluster, tmp_path, monkeypatch):
    """Both workers die (a task kills every worker it starts on) and none comes back."""
    monkeypatch.setattr(cluster, "WORKER_WAIT", 2.0)
    addr = bare_cluster.scheduler_address
    with pytest.raises(ErrplanError, match=rf"^--scheduler {addr}: every worker was lost \(no worker for 2 s; "):
        _with_killer(addr, _Kill(tmp_path, [("_run_remote-", "executing", -1)]),
                     lambda: map_tasks(_tile, SHARED, ITEMS, scheduler=addr))
    assert len(_kills(tmp_path)) == 2


@pytest.mark.slow
def test_fields_cli_with_workers_killed_gives_the_local_npz(tmp_path):
    """``errplan fields --scheduler``: one worker killed while the job's data is scattered, another while
    its (first) tile runs; the npz is the local run's, bit for bit."""
    sc = ROOT / "scenarios" / "phantom15_spatial.toml"
    args = ["--resolution", "0.03"]

    def fields(out, *extra):
        r = subprocess.run([sys.executable, "-m", "errplan", "-q", "fields", str(sc), "--out", str(out), *args, *extra],
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        return MetricField.load(out)

    ref = fields(tmp_path / "local.npz", "--workers", "1")
    marks = tmp_path / "marks"
    marks.mkdir()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  host="127.0.0.1") as c:
        addr = c.scheduler_address
        got = _with_killer(addr, _Kill(marks, [("FieldJob-", "memory", 0), ("_run_remote-", "executing", 0)]),
                           lambda: fields(tmp_path / "dask.npz", "--scheduler", addr))
    kills = _kills(marks)
    assert [k.split("-")[1] for k in kills] == ["t0", "t1"], kills
    for ax_a, ax_b in zip(ref.axes, got.axes):
        np.testing.assert_array_equal(ax_a, ax_b)
    np.testing.assert_array_equal(ref.valid, got.valid)
    for name in ("G_norm", "phi_hat_max", "phi_max"):
        x, y = getattr(ref, name), getattr(got, name)
        assert x is not None and y is not None, name
        np.testing.assert_array_equal(x, y)  # bit for bit


PLACEMENT_DOC = {
    "name": "placement-under-loss",
    "robot": {"base": [0.190, -0.210], "link_lengths": [0.210, 0.200], "home_angles": [0.0, -1.5],
              "joint_limits": [[-1.8, 1.3], [-0.8, 1.1]], "joint_sum_limits": [-0.4, 2.9]},
    "instrument": {"length": 0.300},
    "port": {"position": [0.0, 0.150], "estimate": [0.0, 0.150]},
    "controller": {"gain": 0.9, "jacobian": "rigid"},
    "uncertainty": {"port_y": [-0.004, 0.004], "port_z": [-0.003, 0.003], "tip_force_over_ei": [0.0, 0.6],
                    "samples": 3},
    "tolerance": [{"name": "place", "kind": "port_placement", "candidates": {"y": [0.0, 0.06], "z": [0.15, 0.21]},
                   "spacing": 0.03, "region": {"y": [-0.07, 0.07], "z": [0.36, 0.44]}, "resolution": 0.01}],
}


def test_port_placement_with_workers_killed_gives_the_local_answer(nanny_cluster, tmp_path):
    """``errplan tolerance --scheduler`` (a port_placement query): one worker killed while the job's data
    arrives, another as a batch of candidates starts; the same candidates and best port as a local run."""
    from errplan.api import parse_scenario
    from errplan.tolerance import run_query

    sc = parse_scenario(PLACEMENT_DOC, "<test>")
    ref = run_query(sc, sc.tolerances[0], workers=1)
    addr = nanny_cluster.scheduler_address
    got = _with_killer(addr, _Kill(tmp_path, [("PlacementJob-", "memory", 0), ("_run_remote-", "executing", 0)]),
                       lambda: run_query(sc, sc.tolerances[0], scheduler=addr))
    assert [k.split("-")[1] for k in _kills(tmp_path)] == ["t0", "t1"]
    assert got.data["candidates"] == ref.data["candidates"]
    assert got.data["best"] == ref.data["best"]


def _same_placement(a: dict, b: dict):
    """Two triad or setup answers: the same best and ranked triads, scores and clearances bit for bit."""
    for x, y in zip([a["best"]] + a["ranked"], [b["best"]] + b["ranked"], strict=True):
        assert x["indices"] == y["indices"] and x["score"] == y["score"] and x["ports"] == y["ports"]
        assert x.get("arm_clearance_min") == y.get("arm_clearance_min")
    assert a["rejected"] == b["rejected"]


def _killed_while_placing(cluster_, marks: Path, run):
    """``run(scheduler=...)`` with one worker killed as the first data arrives on a worker (the first
    scatter) and another as the first task starts."""
    addr = cluster_.scheduler_address
    got = _with_killer(addr, _Kill(marks, [("", "memory", 0), ("_run_remote-", "executing", 0)]),
                       lambda: run(scheduler=addr))
    assert [k.split("-")[1] for k in _kills(marks)] == ["t0", "t1"]
    return got


@pytest.mark.slow
def test_triad_placement_with_workers_killed_gives_the_local_answer(nanny_cluster, tmp_path):
    """``errplan tolerance --scheduler`` on a triad_placement query (the bundled abdomen triad, coarse):
    workers killed during the scatter and as a task starts; the local run's triads."""
    from conftest import to_toml
    from test_setup import triad_doc

    from errplan.api import load_setup
    from errplan.tolerance.triad import triad_placement

    doc = triad_doc()
    doc["tolerance"][0].update(spacing=0.08, resolution=0.04)
    path = tmp_path / "triad.toml"
    path.write_text(to_toml(doc), encoding="utf-8")
    st = load_setup(path)
    (tol,) = st.triads
    ref = triad_placement(st, tol, workers=1)
    marks = tmp_path / "marks"
    marks.mkdir()
    got = _killed_while_placing(nanny_cluster, marks, lambda **k: triad_placement(st, tol, **k))
    _same_placement(ref, got)


@pytest.mark.slow
def test_setup_placement_with_workers_killed_gives_the_local_answer(nanny_cluster, tmp_path):
    """The setup search (``kind = "setup_placement"``, the bundled UR5 setup with the first base of each arm
    and a coarse wall) under the same kills: the local run's setups."""
    from conftest import to_toml
    from test_setup_placement import setup_doc

    from errplan.api import load_setup
    from errplan.tolerance.setup import setup_placement

    doc = setup_doc()
    rpy = [-math.pi / 2, 0.0, 0.0]
    doc["tolerance"][0].update(spacing=0.12, bases={"left": [{"position": [-0.30, 0.0, -0.05], "rpy": rpy}],
                                                    "right": [{"position": [0.30, 0.0, 0.10], "rpy": rpy}]})
    path = tmp_path / "setup.toml"
    path.write_text(to_toml(doc), encoding="utf-8")
    st = load_setup(path)
    (tol,) = st.triads
    ref = setup_placement(st, tol, workers=1)
    marks = tmp_path / "marks"
    marks.mkdir()
    got = _killed_while_placing(nanny_cluster, marks, lambda **k: setup_placement(st, tol, **k))
    _same_placement(ref, got)
