"""Fuzz: no input crashes errplan (issue 9).

Mutated inputs are built from every bundled scenario (``scenarios/*.toml``, spatial ones included
as they appear) and from an ``errplan experiment`` CSV:

- scenarios: every leaf key set to NaN, inf and a value of the wrong type; every list one element
  short and one too long, and its first element NaN, inf or text; required keys and tables removed;
  negative, zero and huge values where docs/interfaces.md makes them invalid (or, for sizes such as
  the shaft length, absurd enough that the memory check must refuse them before work starts);
  whole tables of the wrong type; unknown keys; bad ``[effects]``; TOML syntax errors;
- CSV: each column's cells NaN, inf, text, empty and absurd; each column missing; short and long
  rows; header only; an empty file; broken run structure;
- every file: not UTF-8 (binary, UTF-16 with and without a byte-order mark, UTF-32, Latin-1), a
  directory, a missing file, a device, a file larger than the memory budget;
- options: bad seeds, sizes, output paths.

Each case runs through the command that reads it, in-process through :func:`errplan.cli.main`
with stderr captured, and must end with exit code 2, exactly one line on stderr, no traceback, no
Python warning, and nothing written. A handful also run through a real ``python -m errplan``
subprocess, to prove that no traceback reaches a user.
"""
from __future__ import annotations

import copy
import os
import subprocess
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from conftest import SCENARIOS, to_toml
from errplan.cli import main

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore

PORT = SCENARIOS / "beasley2004_port.toml"
BUNDLED = sorted(SCENARIOS.glob("*.toml"))
NAN, INF = float("nan"), float("inf")


# ----------------------------------------------------------------------------- cases
@dataclass
class Case:
    """One bad input: files to write into an empty directory (name -> text or bytes; None makes a
    directory) and the command line (``{d}`` is that directory)."""

    id: str
    files: dict
    argv: list
    env: dict = field(default_factory=dict)


def _abs_paths(doc: dict, src: Path) -> dict:
    """Paths inside a scenario (a URDF, package paths) made absolute, so that the mutated copy
    written elsewhere still finds them."""
    for arm in doc.get("arm") or []:  # several instruments: each [[arm]] holds its own [arm.robot]
        if isinstance(arm, dict) and isinstance(arm.get("robot"), dict):
            _abs_paths({"robot": arm["robot"]}, src)
    robot = doc.get("robot")
    if isinstance(robot, dict):
        if isinstance(robot.get("urdf"), str) and not robot["urdf"].startswith("package://"):
            robot["urdf"] = str((src.parent / robot["urdf"]).resolve())
        if isinstance(robot.get("package_path"), list):
            robot["package_path"] = [str((src.parent / p).resolve()) if isinstance(p, str) else p
                                     for p in robot["package_path"]]
    anatomy = doc.get("anatomy")
    if isinstance(anatomy, dict):  # mesh files of obstacles and of the body wall
        for t in list(anatomy.get("obstacle") or []) + [anatomy.get("body_wall")]:
            if isinstance(t, dict) and isinstance(t.get("file"), str):
                t["file"] = str((src.parent / t["file"]).resolve())
    return doc


def _doc(path: Path) -> dict:
    return _abs_paths(tomllib.loads(path.read_text(encoding="utf-8")), path)


def _leaves(v, path=()):
    if isinstance(v, dict):
        for k, x in v.items():
            yield from _leaves(x, path + (k,))
    elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
        for i, x in enumerate(v):
            yield from _leaves(x, path + (i,))
    else:
        yield path, v


def _set(doc: dict, path: tuple, value) -> dict:
    d = copy.deepcopy(doc)
    t = d
    for k in path[:-1]:
        t = t[k]
    t[path[-1]] = value
    return d


def _delete(doc: dict, path: tuple) -> dict:
    d = copy.deepcopy(doc)
    t = d
    for k in path[:-1]:
        t = t[k]
    del t[path[-1]]
    return d


def _command(path: tuple) -> str:
    """The command that reads this part of a scenario."""
    return {"tolerance": "tolerance", "query": "plan", "planner": "plan"}.get(path[0], "experiment")


def _argv(command: str) -> list:
    return {
        "experiment": ["-q", "experiment", "{d}/s.toml", "--out", "{d}/out.csv", "--starts", "2", "--max-steps", "5"],
        "plan": ["-q", "plan", "{d}/s.toml", "--json", "{d}/out.json", "--record", "{d}/out.rrd", "--time", "0.05"],
        "tolerance": ["-q", "tolerance", "{d}/s.toml", "--json", "{d}/out.json"],
        "fields": ["-q", "fields", "{d}/s.toml", "--out", "{d}/out.npz"],
        "calibrate": ["-q", "calibrate", "{d}/s.toml", str(PORT), "--json", "{d}/out.json"],
    }[command]


def _scenario_case(cid: str, doc_or_text, command: str) -> Case:
    text = doc_or_text if isinstance(doc_or_text, str) else to_toml(doc_or_text)
    return Case(cid, {"s.toml": text}, _argv(command))


def _match(pattern: tuple, path: tuple) -> bool:
    return len(pattern) == len(path) and all(p == "*" or p == k for p, k in zip(pattern, path))


def _kind_of(doc: dict, path: tuple) -> str | None:
    if path[0] == "tolerance" and len(path) > 1:
        return doc["tolerance"][path[1]].get("kind")
    return None


#: values invalid for these keys by docs/interfaces.md (or absurd sizes the memory check refuses);
#: each entry: pattern -> {kind: value}, value a callable of the original value
_neg = lambda v: [-abs(x) if x else -1.0 for x in v] if isinstance(v, list) else (-abs(v) if v else -1)  # noqa: E731
_zero = lambda v: [0.0] * len(v) if isinstance(v, list) else (0 if isinstance(v, int) else 0.0)  # noqa: E731
_rev = lambda v: [v[1], v[0]] if v[0] != v[1] else [v[0] + 1.0, v[0]]  # noqa: E731  reversed limits
SEMANTIC = {
    ("robot", "base"): {"huge": lambda v: [1e12] * len(v)},
    ("robot", "link_lengths"): {"negative": _neg, "zero": _zero, "huge": lambda v: [1e9] * len(v)},
    ("robot", "joint_sum_limits"): {"reversed": _rev},
    ("instrument", "length"): {"negative": _neg, "zero": _zero, "huge": lambda v: 1e9},
    ("instrument", "flexural_rigidity"): {"negative": _neg, "zero": _zero},
    ("port", "position"): {"huge": lambda v: [1e12] * len(v)},
    ("port", "estimate"): {"huge": lambda v: [1e12] * len(v)},
    ("controller", "gain"): {"negative": _neg, "zero": _zero, "huge": lambda v: 1e12},
    ("uncertainty", "port_y"): {"reversed": _rev},
    ("uncertainty", "port_z"): {"reversed": _rev},
    ("uncertainty", "tip_force_over_ei"): {"reversed": _rev},
    ("uncertainty", "samples"): {"negative": _neg, "zero": _zero, "huge": lambda v: 10**12},
    ("uncertainty", "sensor_noise", "position"): {"negative": _neg},
    ("uncertainty", "sensor_noise", "angle"): {"negative": _neg},
    ("sensors", "tracker_sigma"): {"negative": _neg},
    ("fields", "resolution"): {"negative": _neg, "zero": _zero, "huge": lambda v: 1e9},
    ("planner", "weight"): {"negative": _neg},
    ("planner", "time"): {"negative": _neg, "zero": _zero},
    ("planner", "iterations"): {"negative": _neg, "zero": _zero, "huge": lambda v: 10**12},
    ("planner", "seed"): {"negative": _neg, "huge": lambda v: 2**40},
    ("planner", "certify_margin"): {"negative": _neg, "huge": lambda v: 1e12},
    ("tolerance", "*", "region", "y"): {"reversed": _rev},
    ("tolerance", "*", "region", "z"): {"reversed": _rev},
    ("tolerance", "*", "sensor_noise", "position"): {"negative": _neg},
    ("tolerance", "*", "sensor_noise", "angle"): {"negative": _neg},
    ("tolerance", "*", "draws"): {"negative": _neg, "zero": _zero, "huge": lambda v: 10**12},
    ("tolerance", "*", "samples"): {"negative": _neg, "zero": _zero, "huge": lambda v: 10**12},
    ("tolerance", "*", "seed"): {"negative": _neg, "huge": lambda v: 2**40},
    ("tolerance", "*", "band"): {"negative": _neg, "zero": _zero, "huge": lambda v: [x * 1e12 for x in v]},
    ("tolerance", "*", "port_y"): {"reversed": _rev},
    ("tolerance", "*", "port_z"): {"reversed": _rev},
    # port_placement (issue 12): a reversed (empty) box or region, a spacing or resolution <= 0
    ("tolerance", "*", "region", "x"): {"reversed": _rev},
    ("tolerance", "*", "candidates", "x"): {"reversed": _rev},
    ("tolerance", "*", "candidates", "y"): {"reversed": _rev},
    ("tolerance", "*", "candidates", "z"): {"reversed": _rev},
    ("tolerance", "*", "spacing"): {"negative": _neg, "zero": _zero},
    ("tolerance", "*", "resolution"): {"negative": _neg, "zero": _zero},
    ("tolerance", "*", "certify_margin"): {"negative": _neg, "huge": lambda v: 1e12},
    ("tolerance", "*", "refine_levels"): {"negative": _neg, "huge": lambda v: 10**12},
}
#: keys (and tables) a scenario cannot do without; a callable decides from the tolerance kind
REQUIRED = {
    ("instrument",): True, ("instrument", "length"): True, ("port",): True, ("port", "position"): True,
    ("query", "*", "start"): True, ("query", "*", "goal"): True, ("tolerance", "*", "kind"): True,
    ("tolerance", "*", "region"): lambda kind: kind in ("port", "tip_load", "port_placement"),
    ("tolerance", "*", "candidates"): lambda kind: kind == "port_placement",
    ("tolerance", "*", "spacing"): lambda kind: kind == "port_placement",
    ("tolerance", "*", "sensor_noise"): lambda kind: kind == "insertion_band",
    ("tolerance", "*", "tip_force_over_ei"): lambda kind: kind in ("insertion_band", "tracker_noise"),
    ("tolerance", "*", "band"): lambda kind: kind == "tracker_noise",
}
#: lists whose length is free (no wrong length)
FREE_LENGTH = {("robot", "package_path")}


def _wrong_type(v):
    if isinstance(v, bool):
        return "yes"
    if isinstance(v, (int, float)):
        return "text"
    if isinstance(v, str):
        return 1.5
    if isinstance(v, list):
        return "text"
    return [1, 2]


def _paths_of_tables(doc: dict, path=()):
    """Every table (dict) of the document and its path, arrays of tables included."""
    for k, v in doc.items():
        if isinstance(v, dict):
            yield path + (k,), v
            yield from _paths_of_tables(v, path + (k,))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for i, x in enumerate(v):
                yield path + (k, i), x
                yield from _paths_of_tables(x, path + (k, i))


def scenario_cases(src: Path) -> list[Case]:
    doc = _doc(src)
    stem = src.stem
    out: list[Case] = []

    def add(tag: str, path: tuple, mutated, command: str | None = None) -> None:
        cid = f"{stem}:{'.'.join(map(str, path)) or 'top'}:{tag}"
        out.append(_scenario_case(cid, mutated, command or _command(path or ("top",))))

    for path, v in _leaves(doc):
        add("nan", path, _set(doc, path, NAN))
        add("inf", path, _set(doc, path, INF))
        add("wrong-type", path, _set(doc, path, _wrong_type(v)))
        if isinstance(v, list) and path not in FREE_LENGTH:
            add("short", path, _set(doc, path, v[:-1]))
            add("long", path, _set(doc, path, v + [v[-1]]))
            if v and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
                for tag, x in (("elem-nan", NAN), ("elem-inf", -INF), ("elem-text", "x")):
                    add(tag, path, _set(doc, path, [x] + v[1:]))
        for pattern, kinds in SEMANTIC.items():
            if _match(pattern, path):
                for kind, make in kinds.items():
                    add(kind, path, _set(doc, path, make(v)))
        if path[0] == "tolerance" and path[-1] == "tip_force_over_ei" and _kind_of(doc, path) in (
                "insertion_band", "tracker_noise"):
            add("zero", path, _set(doc, path, 0.0))
    # a region grid no machine holds: 2,000 km wide at the finest spacing the parser accepts
    for i, t in enumerate(doc.get("tolerance", [])):
        if isinstance(t, dict) and t.get("kind") in ("port", "tip_load") and isinstance(t.get("region"), dict):
            d = _set(doc, ("tolerance", i, "region", "y"), [-1e6, 1e6])
            add("huge-grid", ("tolerance", i, "region"), _set(d, ("tolerance", i, "spacing"), 1e-5))
    # port placement: a candidate sweep over the budget, a task-region grid no machine holds
    for i, t in enumerate(doc.get("tolerance", [])):
        if isinstance(t, dict) and t.get("kind") == "port_placement":
            add("tiny-spacing", ("tolerance", i, "spacing"), _set(doc, ("tolerance", i, "spacing"), 1e-9))
            add("tiny-resolution", ("tolerance", i, "resolution"), _set(doc, ("tolerance", i, "resolution"), 1e-9))
    # required keys and tables removed
    for path, v in list(_leaves(doc)) + list(_paths_of_tables(doc)):
        for pattern, need in REQUIRED.items():
            if _match(pattern, path) and (need is True or need(_kind_of(doc, path))):
                add("removed", path, _delete(doc, path))
    # tables of the wrong type, unknown keys
    for key, v in doc.items():
        if isinstance(v, dict) or (isinstance(v, list) and v and isinstance(v[0], dict)):
            add("table-wrong-type", (key,), _set(doc, (key,), 3))
    for path, table in _paths_of_tables(doc):
        if path[-1] in ("region", "sensor_noise") or (path and path[0] == "effects"):
            continue  # inline tables: covered by their keys
        add("unknown-key", path, _set(doc, path + ("bogus_key",), 1.0))
    add("unknown-key", (), _set(doc, ("bogus_table",), {"a": 1}))
    # duplicate query / tolerance names
    for key in ("query", "tolerance"):
        if isinstance(doc.get(key), list) and len(doc[key]) > 1:
            add("duplicate-name", (key, 1, "name"), _set(doc, (key, 1, "name"), doc[key][0]["name"]))
    return out


def effect_cases() -> list[Case]:
    doc = _doc(PORT)
    out = []
    bad = {
        "fa-nan": {"port_friction": {"fa": NAN, "fn": 0.001}},
        "fa-inf": {"port_friction": {"fa": INF, "fn": 0.001}},
        "fa-text": {"port_friction": {"fa": "x", "fn": 0.001}},
        "fa-list": {"port_friction": {"fa": [1.0, 2.0], "fn": 0.001}},
        "unknown-param": {"port_friction": {"fa": 0.001, "fx": 0.001}},
        "unknown-effect": {"wobble": {"a": 1.0}},
        "c1-nan": {"gravity_sag": {"c1": NAN, "c2": 0.0, "c3": 0.0}},
        "dy-inf": {"port_offset": {"dy": -INF, "dz": 0.0}},
    }
    for tag, eff in bad.items():
        d = copy.deepcopy(doc)
        d["effects"] = eff
        out.append(_scenario_case(f"port:effects:{tag}", d, "experiment"))
    d = copy.deepcopy(doc)
    text = to_toml(d) + "\neffects = 3\n"
    out.append(_scenario_case("port:effects:wrong-type", text, "experiment"))
    text = to_toml(d) + "\n[effects]\nport_friction = 2.0\n"
    out.append(_scenario_case("port:effects:effect-not-a-table", text, "experiment"))
    return out


def toml_syntax_cases() -> list[Case]:
    good = PORT.read_text(encoding="utf-8")
    cases = {
        "truncated-mid-array": good[: good.index("[port]") + 22],
        "unclosed-bracket": good.replace("position = [0.0, 0.160]", "position = [0.0, 0.160"),
        "duplicate-key": good.replace("length = 0.320", "length = 0.320\nlength = 0.330"),
        "bare-word": good.replace("gain = 1.0", "gain = one"),
        "deep-nesting": "a = " + "[" * 5000 + "]" * 5000 + "\n" + good,
        "empty": "",
        "comment-only": "# nothing here\n",
        "null-free-garbage": "\u2603" * 100,
    }
    return [_scenario_case(f"toml:{k}", v, cmd) for k, v in cases.items() for cmd in ("experiment",)]


# ----------------------------------------------------------------------------- encodings, files
def _encoding_variants(text: str) -> dict:
    """Bytes that are not UTF-8 text (the UTF-8 byte-order mark is accepted, so it is not here).
    The Latin-1 variant carries an accented letter where it would be valid once decoded (the
    scenario's description, or the CSV's first run id)."""
    accented = (text.replace("P1", "P1 caf\u00e9", 1) if "P1" in text
                else text.replace("\n0-0,", "\n0-0\u00e9,"))
    return {
        "utf16-bom": text.encode("utf-16"),
        "utf16-le-no-bom": text.encode("utf-16-le"),
        "utf16-be-no-bom": text.encode("utf-16-be"),
        "utf32": text.encode("utf-32"),
        "latin1": accented.encode("latin-1"),
        "binary": bytes(range(256)) * 8,
        "elf-header": b"\x7fELF\x02\x01\x01\x00" + bytes(120),
        "invalid-utf8-tail": text.encode("utf-8") + b"\xc3\x28\n",
    }


def file_cases() -> list[Case]:
    out = []
    scen = PORT.read_text(encoding="utf-8")
    for tag, raw in _encoding_variants(scen).items():
        for cmd in ("experiment", "plan", "tolerance", "fields"):
            out.append(Case(f"scenario-file:{tag}:{cmd}", {"s.toml": raw}, _argv(cmd)))
    for cmd in ("experiment", "plan", "tolerance", "calibrate", "fields"):
        out.append(Case(f"scenario-file:directory:{cmd}", {"s.toml": None}, _argv(cmd)))
        out.append(Case(f"scenario-file:missing:{cmd}", {}, _argv(cmd)))
    out.append(Case("scenario-file:device", {}, ["-q", "experiment", "/dev/zero", "--out", "{d}/out.csv"]))
    out.append(Case("scenario-file:over-memory-budget", {"s.toml": scen}, _argv("experiment"),
                    env={"ERRPLAN_MEMORY_BUDGET": "1K"}))
    return out


# ----------------------------------------------------------------------------- CSV
COLUMNS = ("run", "step", "target_y", "target_z", "gain", "q1", "q2", "tip_y", "tip_z")


@pytest.fixture(scope="module")
def base_csv(tmp_path_factory) -> str:
    """A real `errplan experiment` CSV (P1's port scenario, one start: 8 runs)."""
    d = tmp_path_factory.mktemp("fuzzcsv")
    assert main(["-q", "experiment", str(PORT), "--out", str(d / "b.csv"), "--starts", "1", "--max-steps", "8"]) == 0
    return (d / "b.csv").read_text(encoding="utf-8")


def _calibrate_argv(data="{d}/data.csv", extra=()) -> list:
    return ["-q", "calibrate", str(PORT), data, "--json", "{d}/out.json", "--record", "{d}/out.rrd",
            "--export-scenario", "{d}/out.toml", *extra]


def _cell(text: str, column: str, value: str, row: int = 3, whole_run: bool = False) -> str:
    lines = [line.split(",") for line in text.splitlines()]
    j = lines[0].index(column)
    rid = lines[row][0]
    for i, r in enumerate(lines[1:], start=1):
        if i == row or (whole_run and r[0] == rid):
            r[j] = value
    return "\n".join(",".join(r) for r in lines) + "\n"


def _drop_column(text: str, column: str) -> str:
    lines = [line.split(",") for line in text.splitlines()]
    j = lines[0].index(column)
    return "\n".join(",".join(r[:j] + r[j + 1:]) for r in lines) + "\n"


def csv_mutations(text: str) -> dict:
    lines = text.splitlines()
    m = {}
    for c in COLUMNS:
        per_run = c in ("target_y", "target_z", "gain")
        for tag, v in (("nan", "nan"), ("inf", "inf"), ("neg-inf", "-inf"), ("text", "abc"), ("empty", "")):
            if c == "run" and tag in ("nan", "inf", "neg-inf", "text"):
                continue  # any text is a valid run id
            m[f"{c}:{tag}"] = _cell(text, c, v, whole_run=per_run)
        m[f"{c}:missing-column"] = _drop_column(text, c)
    absurd = {"q1": "1e300", "q2": "-1e12", "tip_y": "1e300", "tip_z": "-1e12", "target_y": "1e300",
              "target_z": "1e12", "gain": "-1e300", "step": "1e300"}
    for c, v in absurd.items():
        m[f"{c}:absurd"] = _cell(text, c, v, whole_run=c in ("target_y", "target_z", "gain"))
    m["gain:zero"] = _cell(text, "gain", "0", whole_run=True)
    m["step:negative"] = _cell(text, "step", "-1")
    m["step:fraction"] = _cell(text, "step", "1.5")
    m["step:gap"] = _cell(text, "step", "7")
    m["step:duplicate"] = _cell(text, "step", "1", row=3)
    m["target:changes-in-run"] = _cell(text, "target_y", "0.001")
    m["run:single-step"] = text + "lonely,0,0,0.34,1,0,0,0,0.32\n"
    m["row:short"] = "\n".join(lines[:3] + [",".join(lines[3].split(",")[:-1])] + lines[4:]) + "\n"
    m["row:long"] = "\n".join(lines[:3] + [lines[3] + ",0.5"] + lines[4:]) + "\n"
    m["row:unterminated-quote"] = "\n".join(lines[:3] + ['"' + lines[3]] + lines[4:]) + "\n"
    m["header:only"] = lines[0] + "\n"
    m["header:duplicate-column"] = lines[0] + ",q1\n" + "\n".join(r + ",0" for r in lines[1:]) + "\n"
    m["header:missing"] = "\n".join(lines[1:]) + "\n"
    m["file:empty"] = ""
    m["file:blank-lines"] = "\n\n  \n"
    m["file:a-scenario"] = PORT.read_text(encoding="utf-8")
    return m


CSV_TAGS = list(csv_mutations("\n".join([",".join(COLUMNS)] + [f"r,{i},0,0.34,1,0,0,0,0.32" for i in range(6)])))


# ----------------------------------------------------------------------------- option cases
def option_cases() -> list[Case]:
    scen = {"s.toml": PORT.read_text(encoding="utf-8")}
    exp = ["-q", "experiment", "{d}/s.toml", "--out", "{d}/out.csv"]
    cases = {
        "experiment:seed-negative": exp + ["--seed", "-1"],
        "experiment:seed-huge": exp + ["--seed", str(2**70)],
        "experiment:max-steps-zero": exp + ["--max-steps", "0"],
        "experiment:max-steps-negative": exp + ["--max-steps", "-3"],
        "experiment:max-steps-huge": exp + ["--max-steps", str(10**15)],
        "experiment:dwell-negative": exp + ["--dwell", "-1"],
        "experiment:starts-zero": exp + ["--starts", "0"],
        "experiment:starts-text": exp + ["--starts", "many"],
        "experiment:out-is-a-directory": ["-q", "experiment", "{d}/s.toml", "--out", "{d}"],
        "experiment:out-in-missing-directory": ["-q", "experiment", "{d}/s.toml", "--out", "{d}/no/out.csv"],
        "plan:seed-negative": ["-q", "plan", "{d}/s.toml", "--seed", "-1", "--json", "{d}/out.json"],
        "plan:seed-huge": ["-q", "plan", "{d}/s.toml", "--seed", str(2**40), "--json", "{d}/out.json"],
        "plan:no-such-query": ["-q", "plan", "{d}/s.toml", "--query", "nope", "--json", "{d}/out.json"],
        "plan:no-such-planner": ["-q", "plan", "{d}/s.toml", "--planner", "Nope", "--json", "{d}/out.json"],
        "plan:time-zero": ["-q", "plan", "{d}/s.toml", "--time", "0", "--json", "{d}/out.json"],
        "plan:time-nan": ["-q", "plan", "{d}/s.toml", "--time", "nan", "--json", "{d}/out.json"],
        "plan:iterations-zero": ["-q", "plan", "{d}/s.toml", "--iterations", "0", "--json", "{d}/out.json"],
        "plan:iterations-float": ["-q", "plan", "{d}/s.toml", "--iterations", "2.5", "--json", "{d}/out.json"],
        "plan:json-is-a-directory": ["-q", "plan", "{d}/s.toml", "--json", "{d}"],
        "tolerance:json-in-missing-directory": ["-q", "tolerance", "{d}/s.toml", "--json", "{d}/no/out.json"],
        "tolerance:json-is-a-directory": ["-q", "tolerance", "{d}/s.toml", "--json", "{d}"],
        "view:missing": ["-q", "view", "{d}/none.rrd"],
        "view:directory": ["-q", "view", "{d}"],
        "view:not-a-recording": ["-q", "view", "{d}/s.toml"],
        "command:unknown": ["-q", "frobnicate", "{d}/s.toml"],
        "command:missing-argument": ["-q", "experiment", "{d}/s.toml"],
    }
    return [Case(f"options:{k}", dict(scen), v) for k, v in cases.items()]


def calibrate_option_cases() -> list[Case]:
    return [
        ("folds-one", ["--folds", "1"]), ("folds-negative", ["--folds", "-4"]), ("seed-negative", ["--seed", "-1"]),
        ("seed-huge", ["--seed", str(2**64)]), ("json-is-a-directory", ["--json", "{d}"]),
        ("record-in-missing-directory", ["--record", "{d}/no/x.rrd"]),
        ("export-is-a-directory", ["--export-scenario", "{d}"]),
    ]


_PLANAR_3R = """<?xml version="1.0"?>
<robot name="planar3r">
  <link name="base"/><link name="a"/><link name="b"/><link name="c"/><link name="wrist"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="a"/><origin xyz="0 0 0"/>
    <axis xyz="1 0 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0 0 0.2"/>
    <axis xyz="1 0 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="j3" type="revolute"><parent link="b"/><child link="c"/><origin xyz="0 0 0.2"/>
    <axis xyz="1 0 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="fix" type="fixed"><parent link="c"/><child link="wrist"/><origin xyz="0 0 0.1"/></joint>
</robot>
"""


_BOMB = """<?xml version="1.0"?>
<!DOCTYPE robot [
  <!ENTITY a "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa">
  <!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;"><!ENTITY c "&b;&b;&b;&b;&b;&b;&b;&b;&b;&b;">
  <!ENTITY d "&c;&c;&c;&c;&c;&c;&c;&c;&c;&c;"><!ENTITY e "&d;&d;&d;&d;&d;&d;&d;&d;&d;&d;">
  <!ENTITY f "&e;&e;&e;&e;&e;&e;&e;&e;&e;&e;"><!ENTITY g "&f;&f;&f;&f;&f;&f;&f;&f;&f;&f;">
  <!ENTITY h "&g;&g;&g;&g;&g;&g;&g;&g;&g;&g;"><!ENTITY i "&h;&h;&h;&h;&h;&h;&h;&h;&h;&h;">
]>
<robot name="&i;"><link name="base"/></robot>
"""


def _bad_urdfs(src: str) -> list[tuple[str, str, dict]]:
    """The bundled PHANToM's URDF broken one way at a time: (tag, text, scenario changes)."""
    shoulder_axis = '<axis xyz="-1 0 0"/>'
    elbow_origin = '<origin xyz="0 0 0.21" rpy="1.5707963267948966 0 0"/>'
    assert shoulder_axis in src and elbow_origin in src
    two_parents = '<joint name="extra" type="fixed"><parent link="base"/><child link="lower_arm"/></joint>\n</robot>'
    return [
        ("zero-axis", src.replace(shoulder_axis, '<axis xyz="0 0 0"/>', 1), {}),
        ("nan-axis", src.replace(shoulder_axis, '<axis xyz="nan 0 0"/>', 1), {}),
        ("nan-origin", src.replace(elbow_origin, '<origin xyz="0 nan 0.21" rpy="0 0 0"/>'), {}),
        ("inf-origin", src.replace(elbow_origin, '<origin xyz="0 0 inf" rpy="0 0 0"/>'), {}),
        ("origin-two-numbers", src.replace(elbow_origin, '<origin xyz="0 0.21" rpy="0 0 0"/>'), {}),
        ("origin-not-a-number", src.replace(elbow_origin, '<origin xyz="0 zero 0.21" rpy="0 0 0"/>'), {}),
        ("rpy-missing-number", src.replace(elbow_origin, '<origin xyz="0 0 0.21" rpy="1.57 0"/>'), {}),
        ("origin-overflow", src.replace(elbow_origin, '<origin xyz="0 0 1e400" rpy="0 0 0"/>'), {}),
        ("link-origin-nan", src.replace('<origin xyz="0 -0.105 0" rpy="0 0 0"/>', '<origin xyz="0 nan 0" rpy="0 0 0"/>', 1), {}),
        ("reversed-limits", src.replace('lower="-1.9" upper="1.2"', 'lower="1.2" upper="-1.9"'),
         {"robot.joint_limits": None, "robot.coupled_limits": None}),
        ("nan-limit", src.replace('lower="-1.9" upper="1.2"', 'lower="nan" upper="1.2"'),
         {"robot.joint_limits": None, "robot.coupled_limits": None}),
        ("floating-joint-in-chain", src.replace('<joint name="shoulder" type="revolute">',
                                                '<joint name="shoulder" type="floating">'), {}),
        ("missing-parent-link", src.replace('<parent link="torso"/>', '<parent link="nowhere"/>', 1), {}),
        ("link-with-two-parents", src.replace("</robot>", two_parents), {}),
        ("empty-robot", '<?xml version="1.0"?>\n<robot name="empty"/>\n', {}),
        ("entity-bomb", _BOMB, {}),
        ("binary-bytes-in-xml", src.replace('<robot name="phantom15">', '<robot name="phantom15\x00\x01\x02">'), {}),
    ]


def spatial_robot_cases() -> list[Case]:
    """Bad spatial robots and points (issue 10): each one clear error from ``errplan fields``."""
    urdf_src = (SCENARIOS / "phantom15.urdf").read_text(encoding="utf-8")
    doc = _doc(SCENARIOS / "phantom15_spatial.toml")
    doc.pop("query", None)
    doc.pop("tolerance", None)

    def case(cid, urdf_files, **changes):
        d = copy.deepcopy(doc)
        d["robot"]["urdf"] = "{d}/arm.urdf"
        for path, value in changes.items():
            tbl, key = path.split(".")
            if value is None:
                d[tbl].pop(key, None)
            else:
                d[tbl][key] = value
        files = dict(urdf_files)
        return cid, d, files

    raw = [
        case("urdf-missing", {}),
        case("urdf-not-xml", {"arm.urdf": "this is not xml <robot"}),
        case("urdf-binary", {"arm.urdf": bytes(range(256)) * 4}),
        case("urdf-utf16", {"arm.urdf": urdf_src.encode("utf-16")}),
        case("urdf-not-a-robot", {"arm.urdf": "<?xml version='1.0'?><html><body/></html>"}),
        case("urdf-empty", {"arm.urdf": ""}),
        case("urdf-is-a-directory", {"arm.urdf": None}),
        case("joint-not-in-urdf", {"arm.urdf": urdf_src},
             **{"robot.joints": ["waist", "shoulder", "knee"], "robot.coupled_limits": None}),
        case("joints-two", {"arm.urdf": urdf_src}, **{"robot.joints": ["waist", "shoulder"]}),
        case("joints-repeated", {"arm.urdf": urdf_src}, **{"robot.joints": ["waist", "waist", "elbow"]}),
        case("wrist-link-not-in-urdf", {"arm.urdf": urdf_src}, **{"robot.wrist": "hand"}),
        case("wrist-before-joints", {"arm.urdf": urdf_src}, **{"robot.wrist": "upper_arm"}),
        case("fixed-joint-unknown", {"arm.urdf": urdf_src}, **{"robot.fixed_joints": {"nope": 0.1}}),
        case("planar-3r-cannot-place-wrist", {"arm.urdf": _PLANAR_3R},
             **{"robot.joints": ["j1", "j2", "j3"], "robot.coupled_limits": None}),
        case("port-2-vector", {"arm.urdf": urdf_src}, **{"port.position": [0.0, 0.16]}),
        case("estimate-2-vector", {"arm.urdf": urdf_src}, **{"port.estimate": [0.0, 0.16]}),
        case("port-4-vector", {"arm.urdf": urdf_src}, **{"port.position": [0.0, 0.0, 0.16, 0.0]}),
        case("load-negative", {"arm.urdf": urdf_src}, **{"uncertainty.tip_force_over_ei": [-1.0, 1.0]}),
        case("region-2d", {"arm.urdf": urdf_src}, **{"fields.region": {"y": [-0.1, 0.1], "z": [0.3, 0.4]}}),
        case("region-empty", {"arm.urdf": urdf_src},
             **{"fields.region": {"x": [0.001, 0.002], "y": [0.0, 0.1], "z": [0.3, 0.4]}}),
        # (P2's flexion controller and its sensor noise are spatial too since issue 20: no longer refused)
        case("joint-limits-2-pairs", {"arm.urdf": urdf_src}, **{"robot.joint_limits": [[-1, 1], [-1, 1]]}),
        case("base-rpy-2", {"arm.urdf": urdf_src}, **{"robot.base_rpy": [0.0, 0.0]}),
        # malformed URDFs (issue 17): each one line naming what is wrong
        *[case(f"urdf-{tag}", {"arm.urdf": text}, **changes) for tag, text, changes in _bad_urdfs(urdf_src)],
    ]
    out = []
    for cid, d, files in raw:
        files = {k: v for k, v in files.items()}
        files["s.toml"] = to_toml(d).replace("{d}/arm.urdf", "arm.urdf")
        out.append(Case(f"spatial-robot:{cid}", files, ["-q", "fields", "{d}/s.toml", "--out", "{d}/f.npz"]))
    return out


def placement_cases() -> list[Case]:
    """Bad port-placement queries (issue 12), planar and spatial, each one clear error from
    ``errplan tolerance`` before any candidate runs: a candidate box or region of the wrong
    dimension, a spacing <= 0 or so small that the sweep exceeds the candidate budget, an empty
    region (no grid point at the resolution, or reversed), bad options."""
    out = []
    for src in (SCENARIOS / "beasley2004_bounded.toml", SCENARIOS / "phantom15_placement.toml"):
        if not src.exists():
            continue
        doc = _doc(src)
        doc.pop("query", None)
        tols = [t for t in doc.get("tolerance", []) if t.get("kind") == "port_placement"]
        if not tols:
            continue
        base = copy.deepcopy(tols[0])
        d3 = "x" in base["candidates"]
        good_box = base["candidates"]
        wrong_box = ({"y": good_box["y"], "z": good_box["z"]} if d3 else
                     {"x": [0.0, 0.01], "y": good_box["y"], "z": good_box["z"]})
        wrong_region = ({"y": base["region"]["y"], "z": base["region"]["z"]} if d3 else
                        dict(base["region"], x=[0.0, 0.0]))
        empty = dict(base["region"], z=[base["region"]["z"][0] + 0.0001, base["region"]["z"][0] + 0.0002])
        variants = {
            "candidates-wrong-dimension": {"candidates": wrong_box},
            "candidates-one-axis": {"candidates": {"z": good_box["z"]}},
            "candidates-not-a-table": {"candidates": [0.0, 0.1]},
            "region-wrong-dimension": {"region": wrong_region},
            "spacing-zero": {"spacing": 0.0},
            "spacing-negative": {"spacing": -0.01},
            "spacing-over-budget": {"spacing": 1e-6},
            "spacing-text": {"spacing": "fine"},
            "resolution-over-budget": {"resolution": 1e-7},
            "region-empty-at-resolution": {"region": empty, "resolution": 0.01},
            "region-reversed": {"region": dict(base["region"], y=base["region"]["y"][::-1])},
            "candidates-reversed": {"candidates": dict(good_box, z=good_box["z"][::-1])},
            "certify-margin-one": {"certify_margin": 1.0},
            "refine-not-bool": {"refine": 1},
            "refine-levels-huge": {"refine_levels": 1000},
            "planar-only-key-beside": None,
        }
        for tag, change in variants.items():
            d = copy.deepcopy(doc)
            if change is None:
                if not d3:
                    continue
                d["tolerance"] = [base, {"name": "band", "kind": "insertion_band", "tip_force_over_ei": 3.0,
                                         "sensor_noise": {"position": 0.001, "angle": 0.002},
                                         "hold": "port_force"}]  # the hold variants are planar only
            else:
                d["tolerance"] = [dict(base, **change)]
            out.append(_scenario_case(f"placement:{src.stem}:{tag}", d, "tolerance"))
        d = copy.deepcopy(doc)
        d["tolerance"] = [base]
        text = to_toml(d)
        tol = ["-q", "tolerance", "{d}/s.toml", "--json", "{d}/out.json"]
        for tag, extra in (("workers-zero", ["--workers", "0"]), ("workers-negative", ["--workers", "-2"]),
                           ("record-in-missing-directory", ["--record", "{d}/no/x.rrd"]),
                           ("record-is-a-directory", ["--record", "{d}"]), ("top-negative", ["--top", "-1"])):
            out.append(Case(f"placement:{src.stem}:{tag}", {"s.toml": text}, tol + extra))
    return out


#: scenarios with several arms get their own cases (tests/test_setup.py, setup_cases below): the per-leaf
#: mutations here run through one-instrument commands
ONE_ARM = [f for f in BUNDLED if "[[arm]]" not in f.read_text(encoding="utf-8")]
SCENARIO_CASES = [c for f in ONE_ARM for c in scenario_cases(f)]


def setup_cases() -> list[Case]:
    """The keys of a scenario with several arms (``[[arm]]``, ``[endoscope]``, ``[setup]``, query ``arm``,
    ``triad_placement``): NaN, inf, wrong types, wrong lengths, through the commands that read them, and
    ``--arm`` naming no arm."""
    src = SCENARIOS / "abdomen_triad.toml"
    if not src.exists():
        return []
    doc = _doc(src)
    muts = {
        "endoscope.fov:nan": (("endoscope", "fov"), NAN), "endoscope.insertion:inf": (("endoscope", "insertion"), INF),
        "endoscope.depth:text": (("endoscope", "depth"), ["near", 0.2]),
        "endoscope.look_at:short": (("endoscope", "look_at"), [0.0, 0.0]),
        "endoscope.look_at:at-port": (("endoscope", "look_at"), list(doc["endoscope"]["port"]["estimate"])),
        "endoscope.port:text": (("endoscope", "port"), "wall"),
        "endoscope.uncertainty.port_x:reversed": (("endoscope", "uncertainty", "port_x"), [0.003, -0.003]),
        "setup.shaft_clearance:text": (("setup", "shaft_clearance"), "wide"),
        "setup.arm_clearance:zero": (("setup", "arm_clearance"), 0.0),
        "arm.0.rest:nan": (("arm", 0, "rest"), [NAN, 0.0, 0.3]), "arm.1.rest:short": (("arm", 1, "rest"), [0.0, 0.3]),
        "arm.0.name:empty": (("arm", 0, "name"), ""), "arm:table": (("arm",), {"name": "left"}),
        "arm.1.instrument.length:negative": (("arm", 1, "instrument", "length"), -0.3),
        "query.0.arm:number": (("query", 0, "arm"), 1),
        "tolerance.0.instruments:text": (("tolerance", 0, "instruments"), "left"),
        "tolerance.0.coverage_weight:negative": (("tolerance", 0, "coverage_weight"), -1.0),
        "tolerance.0.port_spacing:inf": (("tolerance", 0, "port_spacing"), INF),
        "tolerance.0.candidates:text": (("tolerance", 0, "candidates"), "wall"),
        "tolerance.0.manipulation_angle:pi": (("tolerance", 0, "manipulation_angle"), 3.5),
        "tolerance.0.resolution:tiny": (("tolerance", 0, "resolution"), 1e-9),
    }
    out = []
    for tag, (path, value) in muts.items():
        cmd = "tolerance" if path[0] == "tolerance" else ("plan" if path[0] == "query" else "fields")
        argv = _argv(cmd) + (["--arm", "left"] if cmd != "tolerance" else [])
        out.append(Case(f"abdomen_triad:{tag}", {"s.toml": to_toml(_set(doc, path, value))}, argv))
    text = to_toml(doc)
    for cmd in ("fields", "plan", "experiment", "tolerance", "calibrate"):
        out.append(Case(f"abdomen_triad:arm-unknown:{cmd}", {"s.toml": text}, _argv(cmd) + ["--arm", "middle"]))
    out.append(Case("abdomen_triad:no-arm:experiment", {"s.toml": text}, _argv("experiment")))
    out.append(Case("abdomen_triad:record-triad-is-a-directory", {"s.toml": text}, _argv("tolerance") + ["--record", "{d}"]))
    out.append(Case("abdomen_triad:record-plan-is-a-directory", {"s.toml": text}, _argv("plan") + ["--record", "{d}"]))
    port = _doc(PORT)
    out.append(Case("beasley2004_port:arm-on-one-instrument", {"s.toml": to_toml(port)}, _argv("fields") + ["--arm", "left"]))
    return out
OTHER_CASES = (effect_cases() + toml_syntax_cases() + file_cases() + option_cases() + spatial_robot_cases()
               + placement_cases() + setup_cases())
CASES = SCENARIO_CASES + OTHER_CASES


# ----------------------------------------------------------------------------- running
def _materialise(case: Case, d: Path) -> list[str]:
    for name, content in case.files.items():
        p = d / name
        if content is None:
            p.mkdir()
        elif isinstance(content, bytes):
            p.write_bytes(content)
        else:
            p.write_text(content, encoding="utf-8")
    return sorted(case.files)


def _argv_in(argv: list, d: Path) -> list:
    return [a.replace("{d}", str(d)) for a in argv]


def run_in_process(argv: list, capsys, monkeypatch=None, env=None) -> tuple[int, str, list]:
    if env and monkeypatch is not None:
        for k, v in env.items():
            monkeypatch.setenv(k, v)
    capsys.readouterr()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            rc = main(argv)
        except SystemExit as e:  # argparse usage errors exit directly (one line, code 2)
            rc = e.code
    _, err = capsys.readouterr()
    return rc, err, [str(w.message) for w in caught]


def assert_rejected(rc, err: str, warns: list, d: Path, inputs: list) -> None:
    assert rc == 2, f"exit code {rc}; stderr: {err!r}"
    assert "Traceback" not in err, err
    assert err.endswith("\n") and err.count("\n") == 1, f"not exactly one line on stderr: {err!r}"
    assert err.strip(), "an empty error line"
    assert not warns, f"Python warnings escaped: {warns}"
    left = sorted(p.name for p in d.iterdir())
    assert left == sorted(inputs), f"written: {sorted(set(left) - set(inputs))}"


def _pristine_loads(src: Path, tmp: Path) -> str | None:
    """None if the bundled scenario, written back the way the mutations are, loads; else why not."""
    from errplan.api import load_setup

    p = tmp / f"pristine-{src.stem}.toml"
    p.write_text(to_toml(_doc(src)), encoding="utf-8")
    try:
        load_setup(p)
    except Exception as e:  # noqa: BLE001 - reported by the test below
        return f"{type(e).__name__}: {e}"
    return None


@pytest.mark.parametrize("src", BUNDLED, ids=[p.stem for p in BUNDLED])
def test_bundled_scenarios_load_as_written(src, tmp_path):
    """The mutations are meaningful only if the unmutated document, written by the same writer, loads."""
    assert _pristine_loads(src, tmp_path) is None


_PRISTINE_CACHE: dict[str, str | None] = {}


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_fuzz_case_exits_2_with_one_line(case, tmp_path_factory, capsys, monkeypatch):
    stem = case.id.split(":")[0]
    src = SCENARIOS / f"{stem}.toml"
    if src.exists():
        if stem not in _PRISTINE_CACHE:
            _PRISTINE_CACHE[stem] = _pristine_loads(src, tmp_path_factory.mktemp("pristine"))
        if _PRISTINE_CACHE[stem] is not None:
            pytest.skip(f"{src.name} itself does not load yet ({_PRISTINE_CACHE[stem]})")
    d = tmp_path_factory.mktemp("case")
    inputs = _materialise(case, d)
    rc, err, warns = run_in_process(_argv_in(case.argv, d), capsys, monkeypatch, case.env)
    assert_rejected(rc, err, warns, d, inputs)


@pytest.mark.parametrize("tag", CSV_TAGS)
def test_fuzz_csv_exits_2_with_one_line(tag, base_csv, tmp_path, capsys):
    text = csv_mutations(base_csv)[tag]
    (tmp_path / "data.csv").write_text(text, encoding="utf-8")
    rc, err, warns = run_in_process(_argv_in(_calibrate_argv(), tmp_path), capsys)
    assert_rejected(rc, err, warns, tmp_path, ["data.csv"])


@pytest.mark.parametrize("tag", list(_encoding_variants("x")) + ["directory", "missing"])
def test_fuzz_csv_file_exits_2_with_one_line(tag, base_csv, tmp_path, capsys):
    if tag == "directory":
        (tmp_path / "data.csv").mkdir()
    elif tag != "missing":
        (tmp_path / "data.csv").write_bytes(_encoding_variants(base_csv)[tag])
    rc, err, warns = run_in_process(_argv_in(_calibrate_argv(), tmp_path), capsys)
    assert_rejected(rc, err, warns, tmp_path, [] if tag == "missing" else ["data.csv"])


@pytest.mark.parametrize("tag", ["nan", "binary", "missing", "header-only"])
def test_fuzz_validation_csv_exits_2_with_one_line(tag, base_csv, tmp_path, capsys):
    (tmp_path / "data.csv").write_text(base_csv, encoding="utf-8")
    files = ["data.csv"]
    if tag == "nan":
        (tmp_path / "val.csv").write_text(_cell(base_csv, "tip_z", "nan"), encoding="utf-8")
    elif tag == "binary":
        (tmp_path / "val.csv").write_bytes(bytes(range(256)))
    elif tag == "header-only":
        (tmp_path / "val.csv").write_text(base_csv.splitlines()[0] + "\n", encoding="utf-8")
    if tag != "missing":
        files.append("val.csv")
    rc, err, warns = run_in_process(_argv_in(_calibrate_argv(extra=["--validate", "{d}/val.csv"]), tmp_path), capsys)
    assert_rejected(rc, err, warns, tmp_path, files)


@pytest.mark.parametrize("tag,extra", calibrate_option_cases(), ids=[t for t, _ in calibrate_option_cases()])
def test_fuzz_calibrate_options_exit_2_with_one_line(tag, extra, base_csv, tmp_path, capsys):
    (tmp_path / "data.csv").write_text(base_csv, encoding="utf-8")
    argv = ["-q", "calibrate", str(PORT), "{d}/data.csv", *extra]
    rc, err, warns = run_in_process(_argv_in(argv, tmp_path), capsys)
    assert_rejected(rc, err, warns, tmp_path, ["data.csv"])


def test_fuzz_has_at_least_150_cases():
    n = len(CASES) + len(CSV_TAGS) + len(_encoding_variants("x")) + 2 + 4 + len(calibrate_option_cases())
    assert n >= 150, n


def test_memory_messages_name_the_key_the_value_and_the_memory(tmp_path, capsys):
    """The issue's crash: an absurd shaft length is one clear error naming the key, the value and
    the memory it would need (here through `errplan experiment`; `errplan fields` is the fields
    package's to check)."""
    doc = _doc(PORT)
    doc["instrument"]["length"] = 1e9
    (tmp_path / "s.toml").write_text(to_toml(doc), encoding="utf-8")
    rc, err, warns = run_in_process(_argv_in(_argv("experiment"), tmp_path), capsys)
    assert_rejected(rc, err, warns, tmp_path, ["s.toml"])
    assert "[instrument] length = 1e+09" in err and "would need" in err and "iB" in err


# ----------------------------------------------------------------------------- real subprocesses
SUBPROCESS = [
    ("utf16-scenario", {"s.toml": PORT.read_text(encoding="utf-8").encode("utf-16")}, _argv("fields")),
    ("binary-scenario", {"s.toml": bytes(range(256)) * 4}, _argv("experiment")),
    ("huge-length", {"s.toml": PORT.read_text(encoding="utf-8").replace("length = 0.320", "length = 1e9")},
     _argv("experiment")),
    ("nan-csv", {"s.toml": PORT.read_text(encoding="utf-8"),
                 "data.csv": ",".join(COLUMNS) + "\na,0,0,0.34,1,0,0,nan,0.32\na,1,0,0.34,1,0,0,0,0.33\n"},
     ["-q", "calibrate", "{d}/s.toml", "{d}/data.csv", "--json", "{d}/out.json"]),
    ("directory-csv", {"s.toml": PORT.read_text(encoding="utf-8"), "data.csv": None},
     ["-q", "calibrate", "{d}/s.toml", "{d}/data.csv"]),
    ("bad-option", {"s.toml": PORT.read_text(encoding="utf-8")},
     ["-q", "experiment", "{d}/s.toml", "--out", "{d}/o.csv", "--seed", "-5"]),
]


@pytest.mark.parametrize("tag,files,argv", SUBPROCESS, ids=[s[0] for s in SUBPROCESS])
def test_fuzz_real_subprocess_shows_no_traceback(tag, files, argv, tmp_path):
    inputs = _materialise(Case(tag, files, argv), tmp_path)
    env = {k: v for k, v in os.environ.items() if k != "ERRPLAN_TRACEBACK"}
    p = subprocess.run([sys.executable, "-m", "errplan", *_argv_in(argv, tmp_path)], capture_output=True, text=True,
                       env=env, timeout=120)
    assert_rejected(p.returncode, p.stderr, [], tmp_path, inputs)
    assert p.stderr.startswith("errplan ")


# ----------------------------------------------------------------------------- errplan.inputs
def test_check_allocation_names_key_value_and_memory(monkeypatch):
    from errplan.errors import ErrplanError
    from errplan.inputs import check_allocation, human_bytes, memory_budget

    monkeypatch.setenv("ERRPLAN_MEMORY_BUDGET", "1G")
    assert memory_budget() == 2**30
    check_allocation("k", 1, 2**27, 8)  # exactly the budget: fine
    with pytest.raises(ErrplanError) as e:
        check_allocation("[instrument] length", 1e9, 832818038773, 8, "a grid axis")
    msg = str(e.value)
    assert msg.startswith("[instrument] length = 1e+09: a grid axis would need 6.1 TiB") and "\n" not in msg
    for bad in (float("nan"), float("inf"), -1, 10**400):
        with pytest.raises(ErrplanError, match="k = 3"):
            check_allocation("k", 3, bad, 8)
    assert human_bytes(6.06 * 2**40) == "6.1 TiB" and human_bytes(512) == "512 B" and human_bytes(1536) == "1.5 KiB"
    monkeypatch.setenv("ERRPLAN_MEMORY_BUDGET", "lots")
    with pytest.raises(ErrplanError, match="ERRPLAN_MEMORY_BUDGET"):
        memory_budget()


def test_memory_budget_is_a_fraction_of_what_is_available(monkeypatch):
    import errplan.inputs as inputs

    monkeypatch.delenv("ERRPLAN_MEMORY_BUDGET", raising=False)
    avail = inputs.available_memory()
    assert avail > 0 and inputs.memory_budget() == int(inputs.BUDGET_FRACTION * avail)
    # read once per process: a later change of the system's numbers does not move it
    assert inputs.available_memory() == avail
    # unreadable system numbers: the fallback constant
    monkeypatch.setattr(inputs, "_available", None)
    monkeypatch.setattr(inputs, "_meminfo_available", lambda: None)
    monkeypatch.setattr(inputs, "_cgroup_available", lambda: None)
    monkeypatch.setattr(inputs.os, "sysconf", lambda name: (_ for _ in ()).throw(ValueError(name)))
    assert inputs.available_memory() == inputs.FALLBACK_AVAILABLE
    monkeypatch.setattr(inputs, "_available", avail)


def test_read_text_accepts_utf8_and_its_bom_and_names_every_other_problem(tmp_path):
    from errplan.errors import DataError, ScenarioError
    from errplan.inputs import read_text

    p = tmp_path / "a.toml"
    p.write_bytes(b"\xef\xbb\xbfname = \"caf\xc3\xa9\"\n")
    assert read_text(p) == 'name = "caf\u00e9"\n'
    cases = {
        "utf-16": ("\u00e9t\u00e9".encode("utf-16"), "UTF-16 text"),
        "utf-16-nobom": ("name = 1\n".encode("utf-16-le"), "UTF-16 text without a byte-order mark"),
        "utf-32": ("name = 1\n".encode("utf-32"), "UTF-32"),
        "binary": (bytes(range(256)), "binary file"),
        "latin-1": (b"name = 'caf\xe9'\n", "not UTF-8 text (byte 0xe9 at offset 11, line 1)"),
    }
    for tag, (raw, needle) in cases.items():
        p.write_bytes(raw)
        with pytest.raises(ScenarioError) as e:
            read_text(p)
        assert needle in str(e.value) and str(p) in str(e.value), (tag, str(e.value))
    with pytest.raises(DataError, match="data file not found"):
        read_text(tmp_path / "none.csv", "data file")
    with pytest.raises(DataError, match="it is a directory"):
        read_text(tmp_path, "data file")


# ----------------------------------------------------------------------------- spatial CSV (issue 13)
SPATIAL = SCENARIOS / "phantom15_spatial.toml"
COLUMNS_3D = ("run", "step", "target_x", "target_y", "target_z", "gain", "q1", "q2", "q3", "tip_x", "tip_y", "tip_z")


def spatial_csv_cases() -> dict:
    """Bad measured data for a spatial scenario (PHANToM with a waist: 3 joints, [x, y, z]) and a 3-D
    file for a planar one: each is one clear error naming what is wrong, before any physics."""
    good = [f"r,{i},0.02,0,0.32,1,0,0,0,0.0001,0.0002,0.32" for i in range(6)]
    head = ",".join(COLUMNS_3D)
    planar_head = ",".join(COLUMNS)
    four = head.replace("q3,", "q3,q4,")
    return {
        # (scenario, text, what the message must name)
        "joints:two-for-three": (SPATIAL, head.replace(",q3", "") + "\n" + "\n".join(
            ",".join(r.split(",")[:8] + r.split(",")[9:]) for r in good) + "\n", "q3"),
        "joints:four-for-three": (SPATIAL, four + "\n" + "\n".join(
            ",".join(r.split(",")[:9] + ["0"] + r.split(",")[9:]) for r in good) + "\n", "q4"),
        "columns:planar-file": (SPATIAL, planar_head + "\n" + "\n".join(
            f"r,{i},0,0.34,1,0,0,0,0.32" for i in range(6)) + "\n", "planar columns"),
        "columns:spatial-file-for-planar": (PORT, head + "\n" + "\n".join(good) + "\n", "spatial columns"),
        "columns:x-missing": (SPATIAL, head.replace("tip_x,", "") + "\n" + "\n".join(
            ",".join(r.split(",")[:9] + r.split(",")[10:]) for r in good) + "\n", "tip_x"),
        "cell:nan-tip": (SPATIAL, head + "\n" + "\n".join(good[:2] + [good[2].replace(",0.32", ",nan")] + good[3:])
                         + "\n", "nan"),
        "cell:nan-q3": (SPATIAL, head + "\n" + "\n".join(
            good[:2] + [",".join(good[2].split(",")[:8] + ["nan"] + good[2].split(",")[9:])] + good[3:]) + "\n", "q3"),
        "cell:inf-target-x": (SPATIAL, head + "\n" + "\n".join(
            ",".join(["r", str(i), "inf"] + r.split(",")[3:]) for i, r in enumerate(good)) + "\n", "target_x"),
        "cell:text-gain": (SPATIAL, head + "\n" + "\n".join(good[:1] + [good[1].replace(",1,0,0,0,", ",fast,0,0,0,")]
                                                             + good[2:]) + "\n", "gain"),
        "target:x-changes-in-run": (SPATIAL, head + "\n" + "\n".join(
            good[:3] + [good[3].replace("r,3,0.02,", "r,3,0.03,")] + good[4:]) + "\n", "target_x"),
        "row:short": (SPATIAL, head + "\n" + "\n".join(good[:3] + [good[3].rsplit(",", 1)[0]] + good[4:]) + "\n",
                      "values"),
    }


@pytest.mark.parametrize("tag", list(spatial_csv_cases()))
def test_fuzz_spatial_csv_exits_2_with_one_line(tag, tmp_path, capsys):
    scenario, text, needle = spatial_csv_cases()[tag]
    (tmp_path / "data.csv").write_text(text, encoding="utf-8")
    argv = ["-q", "calibrate", str(scenario), "{d}/data.csv", "--json", "{d}/out.json", "--export-scenario",
            "{d}/out.toml"]
    rc, err, warns = run_in_process(_argv_in(argv, tmp_path), capsys)
    assert_rejected(rc, err, warns, tmp_path, ["data.csv"])
    assert needle in err, err
