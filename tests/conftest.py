"""Shared fixtures: a valid scenario as a dict (P1's setup), a TOML writer, scenario files.

``make_scenario_dict(**tables)`` returns a fresh document; each keyword replaces or merges one
top-level entry: ``port={"estimate": [0.0, 0.16]}`` merges into ``[port]``, a value ``None``
deletes a key (``controller={"gain": None}``) or a whole table (``uncertainty=None``).
``write_scenario(tmp_path, doc=None, name=..., **tables)`` writes it as TOML and returns the path.
"""
from __future__ import annotations

import copy
import math
import os
from pathlib import Path

import pytest

# The first-run compile notice (errplan.jit) is a line on stderr; tests that count stderr lines see only
# errors. tests/test_jit.py turns it back on in its own processes.
os.environ["ERRPLAN_COMPILE_NOTICE"] = "0"

#: compiled once before the tests, in two processes at once (errplan.cli.warmup), when the kernel cache is
#: cold (a fresh clone): otherwise both test workers would compile the same kernels side by side
_PRECOMPILE = (("anatomy", "fields3", "gains3", "gains2", "plan2", "plan3", "lanes2"), ("urdf", "fields3g", "fields2", "lanes3"))


def pytest_configure(config):
    if hasattr(config, "workerinput") or os.environ.get("ERRPLAN_TEST_PRECOMPILE", "1") == "0":
        return  # an xdist worker: the controller did it
    import subprocess
    import sys
    import tempfile
    import time

    from errplan.cli import warmup

    if not warmup._cold([p for group in _PRECOMPILE for p in group]):
        return
    sys.stderr.write("errplan tests: compiling the numerical kernels once for this machine (1 to 2 min)\n")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        procs = [subprocess.Popen([sys.executable, "-m", "errplan.cli.warmup", os.path.join(tmp, f"s{i}"), *group],
                                  stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                 for i, group in enumerate(_PRECOMPILE)]
        for proc in procs:
            proc.wait()
    sys.stderr.write(f"errplan tests: kernels compiled in {time.perf_counter() - t0:.0f} s\n")

#: the test files with the most CPU, largest first: run first, so that with ``--dist loadfile`` the files
#: left at the end, when one worker may wait for the other, are the short ones (the rest keep their order).
#: xdist dispatches the files in this order only with ``--no-loadscope-reorder`` (pyproject's addopts):
#: by default it sorts them by their number of tests, which sends the long files of few tests last.
#: The order is measured: CPU of one process per file (``-n 0``, kernels precompiled, the first compile of
#: the arm checks counted where it falls): calibration 470 s, setup_placement 147, geometry_effects 146,
#: cluster_loss 132, arm_broadphase 111 (26 of them compiling), urdf 78, flexion3d about 76, demo 67,
#: design, fields_spatial and tolerance 65 each, fuzz 55, fields 47, planning about 46, anatomy_certified 41,
#: planning_spatial 30, plan_arms and placement under 30.
HEAVY_FIRST = ("test_calibration", "test_setup_placement", "test_geometry_effects", "test_cluster_loss",
               "test_arm_broadphase", "test_urdf", "test_flexion3d", "test_anatomy_pipeline", "test_demo",
               "test_design", "test_fields_spatial", "test_tolerance", "test_fuzz", "test_fields", "test_planning",
               "test_anatomy_certified", "test_planning_spatial", "test_jit", "test_setup", "test_linalg",
               "test_triad_arms", "test_plan_arms", "test_placement")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    items[:] = sorted(items, key=lambda it: rank.get(it.path.stem, len(rank)))  # stable: order within a file kept


BASE_DOC = {
    "name": "test-p1",
    "description": "P1 planar Phantom, port estimate off by (+20, +10) mm",
    "robot": {
        "base": [0.210, -0.210],
        "link_lengths": [0.210, 0.210],
        "home_angles": [0.0, -math.pi / 2],
        "joint_limits": [[-1.9, 1.2], [-0.7, 1.0]],
        "joint_sum_limits": [-0.3, 2.8],
    },
    "instrument": {"length": 0.320, "flexural_rigidity": 0.60},
    "port": {"position": [0.0, 0.160], "estimate": [0.020, 0.170]},
    "controller": {"gain": 1.0, "jacobian": "rigid"},
    "sensors": {"tracker_sigma": 0.0002},
    "fields": {"resolution": 0.01},
    "planner": {"metric": "phi_hat_max", "weight": 1.0, "planner": "RRTstar", "iterations": 187, "seed": 1},
    "query": [{"name": "N-to-L", "start": [0.0, 0.415], "goal": [0.0, 0.320]}],
}


def make_scenario_dict(**tables) -> dict:
    doc = copy.deepcopy(BASE_DOC)
    for key, val in tables.items():
        if val is None:
            doc.pop(key, None)
        elif isinstance(val, dict) and isinstance(doc.get(key), dict):
            for k, v in val.items():
                if v is None:
                    doc[key].pop(k, None)
                else:
                    doc[key][k] = copy.deepcopy(v)
        else:
            doc[key] = copy.deepcopy(val)
    return doc


# ----------------------------------------------------------------------------- TOML writer
# Deliberately not errplan.calibration.to_toml: tests must also write *malformed* scenarios
# (nan, inf, wrong types) that errplan's own writer refuses.
def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_value(x)}" for k, x in v.items()) + " }"
    if hasattr(v, "item"):  # numpy scalar
        return _value(v.item())
    raise TypeError(f"cannot write {v!r} as TOML")


def to_toml(doc: dict) -> str:
    """TOML text of a scenario document (scalars first, then tables, then arrays of tables)."""
    lines = []
    tables, arrays = [], []
    for k, v in doc.items():
        if isinstance(v, dict):
            tables.append((k, v))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            arrays.append((k, v))
        else:
            lines.append(f"{k} = {_value(v)}")

    for k, t in tables:
        if k == "effects":  # [effects.NAME] sub-tables
            for name, params in t.items():
                lines.append(f"\n[effects.{name}]")
                lines.extend(f"{p} = {_value(x)}" for p, x in params.items())
        else:  # nested dicts (sensor_noise, region) become inline tables
            lines.append(f"\n[{k}]")
            lines.extend(f"{kk} = {_value(x)}" for kk, x in t.items())
    for k, arr in arrays:
        for t in arr:
            lines.append(f"\n[[{k}]]")
            lines.extend(f"{kk} = {_value(x)}" for kk, x in t.items())
    return "\n".join(lines) + "\n"


def write_scenario(tmp_path: Path, doc: dict | None = None, name: str = "scenario.toml", **tables) -> Path:
    """Write ``doc`` (default: :func:`make_scenario_dict` with ``tables``) to ``tmp_path/name``."""
    if doc is None:
        doc = make_scenario_dict(**tables)
    elif tables:
        raise TypeError("give either doc or table overrides")
    path = Path(tmp_path) / name
    path.write_text(to_toml(doc), encoding="utf-8")
    return path


@pytest.fixture
def scenario_dict():
    """The factory :func:`make_scenario_dict`."""
    return make_scenario_dict


@pytest.fixture
def scenario_file(tmp_path):
    """``scenario_file(doc=None, name="scenario.toml", **tables) -> Path`` in ``tmp_path``."""
    return lambda doc=None, name="scenario.toml", **tables: write_scenario(tmp_path, doc, name, **tables)


REPO = Path(__file__).resolve().parents[1]
SCENARIOS = REPO / "scenarios"


def assert_refused(tmp_path: Path, capsys, doc: dict, command: str, *words: str) -> str:
    """Write ``doc`` to ``tmp_path/s.toml``, run ``errplan -q COMMAND s.toml --json out.json`` and check the
    bad-input contract: exit code 2, one line on stderr holding every one of ``words``, no traceback, and
    nothing written beside the scenario. Returns the line."""
    from errplan.cli import main

    p = tmp_path / "s.toml"
    p.write_text(to_toml(doc), encoding="utf-8")
    capsys.readouterr()
    rc = main(["-q", command, str(p), "--json", str(tmp_path / "out.json")])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, (w, err)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["s.toml"]
    return err
