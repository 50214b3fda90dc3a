"""The Python API (issue 17): ``import errplan`` is light and finds the entry points the commands use;
they return the objects the commands' JSON is made from; docs/api.md's worked example runs as printed."""
from __future__ import annotations

import contextlib
import io
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import errplan
from errplan.cli import main

ROOT = Path(__file__).resolve().parents[1]
PORT = ROOT / "scenarios" / "beasley2004_port.toml"
API = ("load_scenario", "compute_fields", "plan", "tolerances", "run_experiment", "calibrate")


def test_import_is_light_and_lists_the_entry_points():
    code = ("import sys, errplan; heavy = [m for m in ('numba', 'pinocchio', 'ompl', 'casadi', 'rerun', 'dask', "
            "'scipy') if m in sys.modules]; print(heavy); print(sorted(set(errplan.__all__) & set(dir(errplan))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.splitlines()
    assert out[0] == "[]"
    listed = eval(out[1])
    assert set(API) <= set(listed)
    for name in API:
        fn = getattr(errplan, name)
        assert callable(fn) and fn.__doc__ and fn.__module__ == "errplan.api", name
    with pytest.raises(AttributeError):
        errplan.no_such_thing  # noqa: B018


def test_bad_input_is_the_commands_error():
    with pytest.raises(errplan.ScenarioError, match="not valid TOML"):
        bad = ROOT / "README.md"
        errplan.load_scenario(bad)


def test_fields_are_the_commands_fields(tmp_path):
    npz = tmp_path / "cli.npz"
    js = tmp_path / "cli.json"
    assert main(["fields", str(PORT), "--out", str(npz), "--resolution", "0.006", "--workers", "1",
                 "--json", str(js)]) == 0
    mf = errplan.compute_fields(PORT, 0.006, workers=1)
    with np.load(npz) as ref:
        for name in ("y", "z", "valid", "G_norm", "phi_hat_max", "phi_max"):
            np.testing.assert_array_equal(ref[name], getattr(mf, name) if name not in "yz" else mf.axes["yz".index(name)])
    assert json.loads(js.read_text())["summary"] == json.loads(json.dumps(mf.summary()))


def test_plan_is_the_commands_plan_json(tmp_path):
    js = tmp_path / "plan.json"
    assert main(["plan", str(PORT), "--query", "N-to-L", "--json", str(js)]) == 0
    cli = json.loads(js.read_text())
    api = json.loads(errplan.report.to_json(errplan.plan(PORT, query="N-to-L").to_json()))
    assert _untimed(api) == _untimed(cli)
    assert api["queries"][0]["gains"] and api["queries"][0]["simulation"]["planned"]["monotonic"] is True


def _untimed(obj):
    """The JSON without wall-clock times (keys ``time*``) and the search's statistics (``search``: a
    loaded machine may stop a search by its time limit a few iterations earlier; N-to-L's optimum is the
    straight line either way)."""
    if isinstance(obj, dict):
        return {k: _untimed(v) for k, v in obj.items() if not k.startswith("time") and k != "search"}
    if isinstance(obj, list):
        return [_untimed(v) for v in obj]
    return obj


def _blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


@pytest.mark.slow
def test_the_worked_example_in_docs_runs_as_printed(tmp_path, monkeypatch):
    text = (ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    blocks = _blocks(text)
    assert blocks, "docs/api.md has no python example"
    (tmp_path / "scenarios").symlink_to(ROOT / "scenarios")
    monkeypatch.chdir(tmp_path)
    for code in blocks:
        expected = [line[3:] for line in code.splitlines() if line.startswith("#> ")]
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            exec(compile(code, "docs/api.md", "exec"), {"__name__": "__docs__"})
        assert out.getvalue().splitlines() == expected
    assert (tmp_path / "fields.npz").is_file()
