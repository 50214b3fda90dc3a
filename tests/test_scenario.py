"""Scenario files (docs/interfaces.md): valid files load into frozen objects; every malformed file
raises one ScenarioError that names the key and the value, and the CLI turns it into exit code 2,
one line on stderr and no output file."""
from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import pytest

from conftest import SCENARIOS, make_scenario_dict, to_toml, write_scenario
from errplan.cli import main
from errplan.errors import ErrplanError, ScenarioError
from errplan.scenario import Scenario
from errplan.api import load_scenario, parse_scenario

# (overrides of make_scenario_dict, substrings the message must contain: key, value, reason)
BAD = {
    # wrong types
    "length-string": (dict(instrument={"length": "long"}), ["[instrument] length", "'long'", "a number"]),
    "gain-bool": (dict(controller={"gain": True}), ["[controller] gain", "True", "a number"]),
    "base-short": (dict(robot={"base": [0.1]}), ["[robot] base", "[0.1]", "two numbers"]),
    "links-negative": (dict(robot={"link_lengths": [0.2, -0.1]}), ["[robot] link_lengths", "-0.1", "> 0"]),
    "jacobian-unknown": (dict(controller={"jacobian": "magic"}), ["[controller] jacobian", "'magic'", "rigid"]),
    "gain-zero": (dict(controller={"gain": 0.0}), ["[controller] gain", "0.0", "> 0"]),
    "length-nan": (dict(instrument={"length": math.nan}), ["[instrument] length", "nan", "finite"]),
    "ei-zero": (dict(instrument={"flexural_rigidity": 0.0}), ["[instrument] flexural_rigidity", "0.0", "> 0"]),
    "samples-one": (dict(uncertainty={"samples": 1}), ["[uncertainty] samples", "1", "integer"]),
    "samples-float": (dict(uncertainty={"samples": 2.5}), ["[uncertainty] samples", "2.5", "integer"]),
    "resolution-huge": (dict(fields={"resolution": 1.0}), ["[fields] resolution", "1.0", "grid spacing"]),
    "metric-unknown": (dict(planner={"metric": "speed"}), ["[planner] metric", "'speed'", "phi_hat_max"]),
    "seed-negative": (dict(planner={"seed": -1}), ["[planner] seed", "-1", "integer"]),
    "sigma-negative": (dict(sensors={"tracker_sigma": -0.1}), ["[sensors] tracker_sigma", "-0.1", ">= 0"]),
    "noise-not-table": (dict(uncertainty={"sensor_noise": 0.001}), ["[uncertainty] sensor_noise", "0.001", "table"]),
    "name-int": (dict(name=5), ["name", "5", "string"]),
    "controller-not-table": (dict(controller="x"), ["[controller]", "'x'", "a table"]),
    "effect-param-string": (dict(effects={"gravity_sag": {"c1": "big"}}), ["[effects.gravity_sag] c1", "'big'", "number"]),
    # missing keys
    "no-length": (dict(instrument={"length": None}), ["[instrument] length", "None", "missing"]),
    "no-port-table": (dict(port=None), ["[port]", "None", "missing"]),
    "no-instrument": (dict(instrument=None), ["[instrument]", "None", "missing"]),
    "no-position": (dict(port={"position": None}), ["[port] position", "None", "missing"]),
    "query-no-goal": (dict(query=[{"name": "a", "start": [0.0, 0.4]}]), ["[[query]][0] goal", "None", "missing"]),
    # limits reversed
    "joint-limits-reversed": (dict(robot={"joint_limits": [[1.2, -1.9], [-0.7, 1.0]]}),
                              ["[robot] joint_limits[0]", "[1.2, -1.9]", "reversed"]),
    "sum-limits-reversed": (dict(robot={"joint_sum_limits": [2.8, -0.3]}),
                            ["[robot] joint_sum_limits", "[2.8, -0.3]", "reversed"]),
    "port-box-reversed": (dict(uncertainty={"port_y": [0.01, -0.01]}), ["[uncertainty] port_y", "[0.01, -0.01]", "reversed"]),
    "load-reversed": (dict(uncertainty={"tip_force_over_ei": [3.0, -3.0]}),
                      ["[uncertainty] tip_force_over_ei", "[3.0, -3.0]", "reversed"]),
    # port out of reach
    "port-out-of-reach": (dict(port={"position": [0.0, 2.0]}), ["[port] position", "[0.0, 2.0]", "out of reach"]),
    "estimate-out-of-reach": (dict(port={"estimate": [5.0, 5.0]}), ["[port] estimate", "[5.0, 5.0]", "out of reach"]),
    # unknown keys
    "unknown-top": (dict(colour="red"), ["colour", "'red'", "unknown key"]),
    "unknown-robot": (dict(robot={"wheels": 4}), ["[robot] wheels", "4", "unknown key"]),
    "typo-port": (dict(port={"positon": [0.0, 0.16]}), ["[port] positon", "[0.0, 0.16]", "unknown key"]),
    "unknown-effect": (dict(effects={"wobble": {"x": 1.0}}), ["[effects.wobble]", "'x'", "effect"]),
    "unknown-uncertainty": (dict(uncertainty={"port_x": [0.0, 1.0]}), ["[uncertainty] port_x", "[0.0, 1.0]", "unknown key"]),
}


def _doc(overrides):
    return make_scenario_dict(**overrides)


@pytest.mark.parametrize("case", sorted(BAD))
def test_malformed_scenario_names_key_and_value(case, tmp_path):
    overrides, needles = BAD[case]
    path = write_scenario(tmp_path, _doc(overrides), name=f"{case}.toml")
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(str(path))
    for needle in needles:
        assert needle in msg, (needle, msg)


def test_bad_toml_missing_file_and_unreadable(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("name = \n[robot\n", encoding="utf-8")
    with pytest.raises(ScenarioError, match=r"broken\.toml: not valid TOML"):
        load_scenario(p)
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario(tmp_path / "nope.toml")
    with pytest.raises(ScenarioError, match="cannot read"):
        load_scenario(tmp_path)  # a directory
    assert issubclass(ScenarioError, ErrplanError)


@pytest.mark.parametrize("case", ["length-string", "joint-limits-reversed", "port-out-of-reach", "unknown-top",
                                  "no-length", "load-reversed"])
def test_cli_bad_scenario_in_process(case, tmp_path, capsys):
    overrides, needles = BAD[case]
    path = write_scenario(tmp_path, _doc(overrides), name=f"{case}.toml")
    out = tmp_path / "x.npz"
    assert main(["fields", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("errplan fields: error: ")
    assert all(n in err[0] for n in needles)
    assert not out.exists() and not (tmp_path / "x.npz.part").exists()


@pytest.mark.parametrize("text", ["name = \n", None])
def test_cli_bad_scenario_subprocess(text, tmp_path):
    """The real command: exit code 2, exactly one line on stderr, nothing written."""
    path = tmp_path / "bad.toml"
    if text is None:  # a well-formed TOML file with a reversed limit
        path.write_text(to_toml(_doc(BAD["sum-limits-reversed"][0])), encoding="utf-8")
    else:
        path.write_text(text, encoding="utf-8")
    out = tmp_path / "x.npz"
    r = subprocess.run([sys.executable, "-m", "errplan", "fields", str(path), "--out", str(out)],
                       capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "bad.toml" in lines[0]
    assert r.stdout == ""
    assert list(tmp_path.iterdir()) == [path]


# ----------------------------------------------------------------------------- valid files
@pytest.mark.parametrize("name", ["beasley2004_port.toml", "beasley2004_bounded.toml"])
def test_bundled_scenarios_load(name):
    sc = load_scenario(SCENARIOS / name)
    assert isinstance(sc, Scenario)
    assert sc.robot.link_lengths == (0.210, 0.210)
    assert sc.instrument.length == pytest.approx(0.320)
    assert sc.port.position == (0.0, 0.160)
    assert sc.source.endswith(name)


def test_p1_values_and_error_set():
    sc = load_scenario(SCENARIOS / "beasley2004_port.toml")
    assert sc.port.estimate == (0.020, 0.170)  # P1 Fig. 5: (+20, +10) mm
    assert sc.controller.gain == 1.0 and sc.controller.jacobian == "rigid"
    assert not sc.uncertainty.declared
    b = load_scenario(SCENARIOS / "beasley2004_bounded.toml")
    assert b.uncertainty.declared
    assert b.uncertainty.port_y == (-0.005, 0.005) and b.uncertainty.tip_force_over_ei == (-1.0, 1.0)


def test_scenario_is_immutable_and_defaults():
    doc = make_scenario_dict(port={"estimate": None}, controller=None, fields=None, planner=None, sensors=None)
    sc = parse_scenario(doc)
    assert sc.port.estimate == sc.port.position  # estimate defaults to the true port
    assert sc.controller.gain == 1.0 and sc.controller.jacobian == "rigid"
    assert sc.fields.resolution == 0.002 and sc.uncertainty.samples == 5
    with pytest.raises(dataclasses.FrozenInstanceError):
        sc.instrument.length = 1.0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        sc.port = None  # type: ignore[misc]
    sc2 = sc.with_(controller=dataclasses.replace(sc.controller, gain=0.5))
    assert sc2.controller.gain == 0.5 and sc.controller.gain == 1.0


def test_integers_are_numbers_and_round_trip(tmp_path):
    doc = make_scenario_dict(instrument={"length": 1}, controller={"gain": 2},
                             uncertainty={"port_y": [-1, 1], "samples": 3},
                             effects={"gravity_sag": {"c1": 0.004}})
    doc["instrument"]["length"] = 0.32
    sc = load_scenario(write_scenario(tmp_path, doc))
    assert sc.controller.gain == 2.0 and isinstance(sc.controller.gain, float)
    assert sc.uncertainty.port_y == (-1.0, 1.0) and sc.uncertainty.samples == 3
    assert sc.effects == {"gravity_sag": {"c1": 0.004, "c2": 0.0, "c3": 0.0}}
