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
