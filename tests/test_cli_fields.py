"""``errplan fields SCENARIO --out F.npz [--resolution R] [--rho-star]`` end to end."""
from __future__ import annotations

import json
import subprocess
import sys

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
    r2 = subprocess.run([sys.executable, "-c", "import sys, errplan.kinematics.symbolic; print('casadi' in sys.modules)"],
                        capture_output=True, text=True, timeout=120)
    assert r2.stdout.strip() == "True"


def test_scenario_resolution_is_the_default(tmp_path, capsys):
    path = write_scenario(tmp_path, fields={"resolution": 0.025})
    out = tmp_path / "f.npz"
    assert main(["-q", "fields", str(path), "--out", str(out)]) == 0
    assert MetricField.load(out).resolution == 0.025
    doc = make_scenario_dict()
    assert doc["fields"]["resolution"] == 0.01  # the factory was not mutated
