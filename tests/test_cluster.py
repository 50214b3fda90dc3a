"""Tiles on local worker processes and on a real dask.distributed cluster give identical arrays."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from errplan.cluster import map_tasks
from errplan.errors import ErrplanError
from errplan.fields import MetricField, compute_fields
from errplan.api import load_scenario

ROOT = Path(__file__).resolve().parents[1]


def _square(shared, item):
    return shared["scale"] * item * item


def test_map_tasks_orders_results_everywhere():
    items = list(range(17))
    want = [3 * i * i for i in items]
    seen = []
    assert map_tasks(_square, {"scale": 3}, items, workers=1, progress=lambda d, n: seen.append((d, n))) == want
    assert seen[-1] == (17, 17)
    assert map_tasks(_square, {"scale": 3}, items, workers=2) == want


def test_bad_workers_and_unreachable_scheduler():
    with pytest.raises(ErrplanError, match="--workers"):
        map_tasks(_square, {"scale": 1}, [1, 2], workers=0)
    with pytest.raises(ErrplanError, match="--scheduler"):
        map_tasks(_square, {"scale": 1}, [1, 2], scheduler="tcp://127.0.0.1:9")


def _same(a: MetricField, b: MetricField):
    assert a.dim == b.dim
    for ax_a, ax_b in zip(a.axes, b.axes):
        np.testing.assert_array_equal(ax_a, ax_b)
    np.testing.assert_array_equal(a.valid, b.valid)
    for name in ("G_norm", "phi_hat_max", "phi_max", "rho_star", "k_star"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y)  # bit for bit


@pytest.mark.slow
def test_local_cluster_identical_to_local_run():
    distributed = pytest.importorskip("distributed")
    planar = load_scenario(ROOT / "scenarios" / "beasley2004_bounded.toml")
    spatial = load_scenario(ROOT / "scenarios" / "phantom15_spatial.toml")
    ref_p = compute_fields(planar, 0.01, rho_star=True, workers=1, tile_points=200)
    ref_s = compute_fields(spatial, 0.03, workers=1, tile_points=100)
    _same(ref_p, compute_fields(planar, 0.01, rho_star=True, workers=2, tile_points=200))
    _same(ref_s, compute_fields(spatial, 0.03, workers=2, tile_points=100))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  host="127.0.0.1") as cluster:
        ticks = []
        got_p = compute_fields(planar, 0.01, rho_star=True, scheduler=cluster.scheduler_address, tile_points=200,
                               progress=lambda f, m: ticks.append(f))
        got_s = compute_fields(spatial, 0.03, scheduler=cluster.scheduler_address, tile_points=100)
    _same(ref_p, got_p)
    _same(ref_s, got_s)
    assert ticks and ticks[-1] == 1.0


def test_cli_workers_give_the_same_npz(tmp_path):
    sc = ROOT / "scenarios" / "beasley2004_bounded.toml"
    outs = []
    for w in ("1", "2"):
        out = tmp_path / f"f{w}.npz"
        r = subprocess.run([sys.executable, "-m", "errplan", "-q", "fields", str(sc), "--out", str(out),
                            "--resolution", "0.008", "--workers", w], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        outs.append(MetricField.load(out))
    _same(*outs)


@pytest.mark.parametrize("bad", [0, -4, 2.5, True, "64"])
def test_a_tile_size_that_is_not_a_positive_count_is_one_clear_error(bad):
    sc = load_scenario(ROOT / "scenarios" / "beasley2004_port.toml")
    with pytest.raises(ErrplanError, match=r"^tile_points = .*: expected a whole number of tips >= 1"):
        compute_fields(sc, 0.01, metrics=("G_norm",), workers=1, tile_points=bad)


def test_tile_sizes_and_the_kernel_loader_change_nothing_but_time(monkeypatch, capsys):
    """The default tiles (about 16 per worker) give the arrays of small explicit tiles; a failure while
    the kernel loads in its thread is raised in the caller, once, not printed by the thread."""
    from errplan.fields import compute

    sc = load_scenario(ROOT / "scenarios" / "beasley2004_port.toml")
    small = compute_fields(sc, 0.01, metrics=("G_norm",), workers=1, tile_points=97)
    auto = compute_fields(sc, 0.01, metrics=("G_norm",), workers=2)
    for a in ("valid", "G_norm"):
        assert np.array_equal(getattr(small, a), getattr(auto, a), equal_nan=True), a

    real = compute.run_tile

    def failing(job, span):
        if span == (0, 1) and len(job.X) == 1:
            raise ValueError("the kernel would not load")
        return real(job, span)

    monkeypatch.setattr(compute, "run_tile", failing)
    with pytest.raises(ValueError, match="would not load"):
        compute_fields(sc, 0.01, metrics=("G_norm",), workers=1)
    assert "Exception in thread" not in capsys.readouterr().err
