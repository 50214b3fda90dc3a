"""``errplan fields SCENARIO --out F.npz [--resolution R] [--rho-star]`` end to end."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import SCENARIOS, make_scenario_dict, write_scenario
from errplan.cli import main
from errplan.fields import MetricField


def test_fields_command_writes_npz_and_table(tmp_path, capsys):
    out = tmp_path / "f.npz"
    js = tmp_path / "f.json"
    rc = main(["-q", "fields", str(SCENARIOS / "beasley2004_port.toml"), "--out", str(out), "--resolution", "0.01",
               "--json", str(js)])
    assert rc == 0
    text = capsys.readouterr().out
    mf = MetricField.load(out)
    assert mf.resolution == 0.01 and mf.rho_star is None
    share = np.mean(mf.G_norm[mf.valid] < 1)
    assert f"{100 * share:.1f}%" in text
    for name in ("G_norm", "phi_hat_max", "phi_max"):
        assert name in text
    assert "rho*" not in text
    summary = json.loads(js.read_text())["summary"]
    assert summary["valid_points"] == int(mf.valid.sum())
    assert summary["G_norm"]["max"] == pytest.approx(np.nanmax(mf.G_norm))


def test_fields_command_rho_star_and_samples(tmp_path, capsys):
    out = tmp_path / "r.npz"
    rc = main(["-q", "fields", str(SCENARIOS / "beasley2004_bounded.toml"), "--out", str(out), "--resolution", "0.02",
               "--rho-star", "--samples", "3"])
    assert rc == 0
    text = capsys.readouterr().out
    with np.load(out) as d:
        assert {"rho_star", "k_star"} <= set(d.files)
        v = d["valid"]
        share = np.mean(d["rho_star"][v] < 1)
        assert json.loads(str(d["meta"]))["error_set"]["samples"] == 3
    assert f"share with rho* < 1 (some gain certifies monotonic convergence): {100 * share:.1f}%" in text


def test_fields_command_subprocess_success(tmp_path):
    """The real console entry (python -m errplan): exit 0, a table on stdout, the npz written."""
    out = tmp_path / "f.npz"
    r = subprocess.run([sys.executable, "-m", "errplan", "fields", str(SCENARIOS / "beasley2004_port.toml"),
                        "--out", str(out), "--resolution", "0.01"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "share with worst-case ||G|| < 1" in r.stdout
    assert out.exists() and not (tmp_path / "f.npz.part").exists()


def test_program_exit_after_ompl_prints_nothing(tmp_path):
    """The errplan program skips the final garbage collection (errplan.cli.entry) only while OMPL is not
    loaded: OMPL's bindings print a page of "leaked" warnings at exit for objects left uncollected, which
    every `errplan plan` and `errplan demo` printed for a while. The real exit path of a command that
    returns, with OMPL loaded as a planning command loads it: nothing on stderr."""
    out = tmp_path / "f.npz"
    code = ("import sys; import ompl.base, ompl.geometric; from errplan.cli import entry; "
            f"sys.argv = ['errplan', 'fields', {str(SCENARIOS / 'beasley2004_port.toml')!r}, '--out', "
            f"{str(out)!r}, '--resolution', '0.01']; entry()")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, ERRPLAN_COMPILE_NOTICE="0"))
    assert r.returncode == 0 and out.exists(), r.stderr[:500]
    assert "leaked" not in r.stderr, r.stderr[:500]


@pytest.mark.parametrize("args,needle", [
    (["--out", "{tmp}/no/such/dir/f.npz"], "does not exist"),
    (["--out", "{tmp}/f.npz", "--samples", "1"], "--samples 1"),
])
def test_fields_command_bad_options(args, needle, tmp_path, capsys):
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    rc = main(["fields", str(SCENARIOS / "beasley2004_port.toml")] + args)
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]
    assert not (tmp_path / "f.npz").exists()


def test_fields_command_bad_resolution_is_rejected_by_argparse(capsys):
    with pytest.raises(SystemExit) as e:
        main(["fields", str(SCENARIOS / "beasley2004_port.toml"), "--out", "x.npz", "--resolution", "-1"])
    assert e.value.code == 2


def test_fields_command_missing_scenario(tmp_path, capsys):
    rc = main(["fields", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "f.npz")])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.toml" in err[0] and "not found" in err[0]
    assert list(tmp_path.iterdir()) == []


def test_fields_command_empty_workspace(tmp_path, capsys):
    """An error set so large that no tip is reachable under every instance: one clear error."""
    path = write_scenario(tmp_path, uncertainty={"port_y": [-0.15, 0.15], "port_z": [-0.15, 0.15], "samples": 2})
    rc = main(["fields", str(path), "--out", str(tmp_path / "f.npz"), "--resolution", "0.02"])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no tip" in err[0]
    assert not (tmp_path / "f.npz").exists()


def test_fields_start_up_does_not_import_ompl_casadi_rerun(tmp_path):
    """physics of speed: `errplan fields` never pays for ompl, casadi or rerun."""
    out = tmp_path / "f.npz"
    code = (
        "import sys\n"
        "from errplan.cli import main\n"
        "import errplan.cli.fields\n"
        f"rc = main(['-q', 'fields', {str(SCENARIOS / 'beasley2004_port.toml')!r}, '--out', {str(out)!r},"
        " '--resolution', '0.02', '--rho-star'])\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('ompl', 'casadi', 'rerun', 'rerun_sdk'))\n"
        "print(rc, bad)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "0 []"
    assert out.exists()
    # the check can fail: importing the casadi twins does load casadi
    r2 = subprocess.run([sys.executable, "-c", "import sys, errplan.gains, casadi_twins; print('casadi' in sys.modules)"],
                        capture_output=True, text=True, timeout=120, cwd=Path(__file__).parent)
    assert r2.stdout.strip() == "True"


def test_scenario_resolution_is_the_default(tmp_path, capsys):
    path = write_scenario(tmp_path, fields={"resolution": 0.025})
    out = tmp_path / "f.npz"
    assert main(["-q", "fields", str(path), "--out", str(out)]) == 0
    assert MetricField.load(out).resolution == 0.025
    doc = make_scenario_dict()
    assert doc["fields"]["resolution"] == 0.01  # the factory was not mutated


# ----------------------------------------------------------------------------- spatial
def test_spatial_fields_command_writes_3d_npz(tmp_path, capsys):
    out = tmp_path / "s.npz"
    js = tmp_path / "s.json"
    rc = main(["-q", "fields", str(SCENARIOS / "phantom15_spatial.toml"), "--out", str(out), "--resolution", "0.03",
               "--metrics", "G_norm,rho_star", "--workers", "1", "--json", str(js)])
    assert rc == 0
    text = capsys.readouterr().out
    with np.load(out) as d:
        assert {"x", "y", "z", "valid", "G_norm", "rho_star", "k_star"} <= set(d.files)
        assert "phi_max" not in d.files and "phi_hat_max" not in d.files
        assert d["valid"].shape == (len(d["x"]), len(d["y"]), len(d["z"]))
        assert d["G_norm"].shape == d["valid"].shape
        assert np.all(np.isnan(d["G_norm"][~d["valid"]])) and np.all(np.isfinite(d["G_norm"][d["valid"]]))
        # the region of the scenario: x in [-0.12, 0.12] on multiples of 0.03
        np.testing.assert_allclose(d["x"], np.arange(-4, 5) * 0.03)
    mf = MetricField.load(out)
    assert mf.dim == 3 and mf.phi_max is None
    assert np.all(mf.rho_star[mf.valid] <= mf.G_norm[mf.valid] + 1e-12)  # rho* never above ||G|| at k
    assert "G_norm" in text and "rho_star" in text and "cm^3" in text and "phi_max" not in text
    assert json.loads(js.read_text())["summary"]["grid"] == list(mf.valid.shape)


def test_metrics_option_rejects_unknown_names(tmp_path, capsys):
    out = tmp_path / "x.npz"
    rc = main(["-q", "fields", str(SCENARIOS / "beasley2004_port.toml"), "--out", str(out), "--metrics", "G_norm,foo"])
    assert rc == 2 and not out.exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--metrics" in err[0] and "foo" in err[0]


def test_planar_region_limits_the_grid(tmp_path):
    d = make_scenario_dict()
    d["fields"] = {"resolution": 0.01, "region": {"y": [-0.05, 0.05], "z": [0.30, 0.40]}}
    path = write_scenario(tmp_path, d)
    out = tmp_path / "r.npz"
    assert main(["-q", "fields", str(path), "--out", str(out)]) == 0
    mf = MetricField.load(out)
    np.testing.assert_allclose(mf.y, np.arange(-5, 6) * 0.01, atol=1e-12)
    np.testing.assert_allclose(mf.z, np.arange(30, 41) * 0.01, atol=1e-12)
