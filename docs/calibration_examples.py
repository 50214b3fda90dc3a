"""Every printed output on docs/calibration.md, made by today's code.

Each example is a block of the page between ``<!-- output: NAME -->`` and ``<!-- /output -->``: the
commands (``$ errplan ...``, run in a scratch directory through :func:`errplan.cli.main`, so exactly
what a user would type and see) and what they print. Some benches are files a bench records rather
than ones ``errplan experiment`` writes: the script makes them from an experiment's CSV by the
Python functions below (named in the page), as a user would from their own tracker's log.

    python docs/calibration_examples.py            # rewrite every block of the page
    python docs/calibration_examples.py NAME ...   # only these
    python docs/calibration_examples.py --check    # exit 1 naming the blocks that are stale

tests/test_calibration_docs.py runs ``--check`` on the light blocks (the rest marked slow).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import re
import shlex
import sys
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "calibration.md"
PORT = ROOT / "scenarios" / "beasley2004_port.toml"


# ----------------------------------------------------------------------------- the benches' files
def scenario_with(path: Path, out: Path, *, name: str | None = None, effects: dict | None = None,
                  estimate=None, gain=None) -> None:
    """``out``: the scenario at ``path`` with a new name, ``[effects]``, port estimate or gain."""
    try:
        import tomllib
    except ModuleNotFoundError:  # pragma: no cover
        import tomli as tomllib  # type: ignore
    from errplan.calibration import to_toml

    doc = tomllib.loads(path.read_text())
    if name:
        doc["name"] = name
    if effects is not None:
        doc["effects"] = effects
    if estimate is not None:
        doc["port"]["estimate"] = list(estimate)
    if gain is not None:
        doc["controller"]["gain"] = gain
    out.write_text(to_toml(doc))


def with_outliers(src: Path, dst: Path, rate: float = 0.005, lo: float = 0.003, hi: float = 0.010, seed: int = 5) -> None:
    """A tracker that swaps markers now and then: ``rate`` of the rows (at least 5) thrown ``lo``-``hi``
    m off in a random direction; the rest as recorded."""
    from errplan.api import load_scenario
    from errplan.experiment import read_measured_csv

    d = read_measured_csv(src, load_scenario(PORT))
    rng = np.random.default_rng(seed)
    k = max(5, round(rate * d.rows))
    rows = rng.choice(d.rows, k, replace=False)
    v = rng.normal(size=(k, d.dim))
    tip = d.tip.copy()
    tip[rows] += v / np.linalg.norm(v, axis=1)[:, None] * rng.uniform(lo, hi, k)[:, None]
    replace(d, tip=tip).write_csv(dst)


def with_warp(src: Path, dst: Path, amp: float = 4e-4) -> None:
    """A tracker whose space is warped smoothly (up to ``amp`` m per coordinate, about (0, 0.30) m):
    ``tip + amp [sin(1.3 z' + 0.4 y'), cos(1.1 y' - 0.7 z')]``, y', z' the tip's offsets over 50 mm."""
    from errplan.api import load_scenario
    from errplan.experiment import read_measured_csv

    d = read_measured_csv(src, load_scenario(PORT))
    z = (d.tip - np.array([0.0, 0.30])) / 0.05
    w = np.stack([np.sin(1.3 * z[:, 1] + 0.4 * z[:, 0]), np.cos(1.1 * z[:, 0] - 0.7 * z[:, 1])], -1)
    replace(d, tip=d.tip + amp * w).write_csv(dst)


# ----------------------------------------------------------------------------- examples
@dataclass
class Example:
    name: str
    #: writes the example's input files into the scratch directory
    setup: Callable[[Path], None]
    #: the commands, as typed (``errplan`` ... or ``python -c`` lines are not allowed: only errplan)
    commands: list[str]
    #: heavy (minutes of CPU): checked only by the slow test
    slow: bool = True
    #: commands run first and not shown (their output is not on the page)
    hidden: tuple[str, ...] = ()


def _gravity_setup(tmp: Path) -> None:
    scenario_with(PORT, tmp / "bench_truth.toml", name="beasley2004-port-bench",
                  effects={"gravity_sag": {"c1": 0.004, "c2": 0.002, "c3": 0.003}})


def _friction_setup(tmp: Path) -> None:
    scenario_with(PORT, tmp / "declared.toml", name="friction-declared", estimate=(0.010, 0.165), gain=0.05)
    scenario_with(tmp / "declared.toml", tmp / "bench_friction.toml", name="friction-bench",
                  effects={"port_friction": {"fa": 0.002, "fn": 0.0012}})


def _links_setup(tmp: Path) -> None:
    scenario_with(PORT, tmp / "truth.toml", effects={"link_length": {"dl1": 0.003, "dl2": -0.002}})


def _recorded_setup(tmp: Path) -> None:
    from errplan.cli import main

    scenario_with(PORT, tmp / "truth.toml", name="port-bench", effects={"port_offset": {"dy": 0.003, "dz": -0.002}})
    with contextlib.redirect_stdout(io.StringIO()):
        main(["-q", "experiment", str(tmp / "truth.toml"), "--out", str(tmp / "clean.csv"), "--seed", "3",
              "--starts", "4"])
    with_outliers(tmp / "clean.csv", tmp / "recorded.csv")


def _warp_setup(tmp: Path) -> None:
    from errplan.cli import main

    with contextlib.redirect_stdout(io.StringIO()):
        for seed, name in (("3", "clean.csv"), ("4", "clean_val.csv")):
            main(["-q", "experiment", str(PORT), "--out", str(tmp / name), "--seed", seed, "--starts", "4"])
    with_warp(tmp / "clean.csv", tmp / "warped.csv")
    with_warp(tmp / "clean_val.csv", tmp / "warped_val.csv")


def _spatial_setup(tmp: Path) -> None:
    import shutil

    src = ROOT / "scenarios" / "phantom15_spatial.toml"
    shutil.copy(ROOT / "scenarios" / "phantom15.urdf", tmp / "phantom15.urdf")
    scenario_with(src, tmp / "declared.toml", name="phantom15-declared", estimate=(0.008, 0.004, 0.168), gain=0.3)
    scenario_with(tmp / "declared.toml", tmp / "bench_truth.toml", name="phantom15-bench",
                  effects={"joint_offset": {"dq1": 0.003, "dq2": -0.002, "dq3": 0.002},
                           "gravity_sag": {"c1": 0.0, "c2": 0.05, "c3": 0.08}})


EXAMPLES = [
    Example("gravity", _gravity_setup, [
        "errplan experiment bench_truth.toml --out bench.csv --seed 1",
        "errplan -q experiment bench_truth.toml --out bench_val.csv --seed 2",
        "errplan -q calibrate scenarios/beasley2004_port.toml bench.csv --validate bench_val.csv "
        "--json cal.json --export-scenario corrected.toml",
    ]),
    Example("gravity-corrected", _gravity_setup, [
        "errplan -q calibrate corrected.toml bench_val.csv",
    ], hidden=(
        "errplan -q experiment bench_truth.toml --out bench.csv --seed 1",
        "errplan -q experiment bench_truth.toml --out bench_val.csv --seed 2",
        "errplan -q calibrate scenarios/beasley2004_port.toml bench.csv --validate bench_val.csv "
        "--export-scenario corrected.toml",
    )),
    Example("friction", _friction_setup, [
        "errplan experiment bench_friction.toml --out friction.csv --seed 1 --starts 5",
        "errplan -q experiment bench_friction.toml --out friction_val.csv --seed 2 --starts 5",
        "errplan -q calibrate declared.toml friction.csv --validate friction_val.csv --json fcal.json "
        "--export-scenario fcorrected.toml",
    ]),
    Example("link-length", _links_setup, [
        "errplan -q experiment truth.toml --out d.csv --seed 1 --starts 5",
        "errplan -q experiment truth.toml --out v.csv --seed 2 --starts 3",
        "errplan -q calibrate scenarios/beasley2004_port.toml d.csv --validate v.csv --json c.json "
        "--export-scenario fixed.toml --predictions p.csv",
    ]),
    Example("spatial", _spatial_setup, [
        "errplan -q experiment bench_truth.toml --out bench.csv --seed 1",
        "errplan -q experiment bench_truth.toml --out val.csv --seed 2",
        "errplan -q calibrate declared.toml bench.csv --validate val.csv --json cal.json --export-scenario corrected.toml "
        "--no-task",
    ]),
    Example("recorded", _recorded_setup, [
        "errplan -q calibrate scenarios/beasley2004_port.toml recorded.csv --json rec.json",
    ]),
    Example("warp", _warp_setup, [
        "errplan -q calibrate scenarios/beasley2004_port.toml warped.csv --validate warped_val.csv",
    ]),
]
BY_NAME = {e.name: e for e in EXAMPLES}


def _run(cmd: str, tmp: Path) -> str:
    from errplan.cli import main

    argv = shlex.split(cmd)
    assert argv[0] == "errplan", cmd
    args = [str(ROOT / a) if a.startswith("scenarios/") else a for a in argv[1:]]
    out, err = io.StringIO(), io.StringIO()
    cwd = os.getcwd()
    os.chdir(tmp)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main(args)
    finally:
        os.chdir(cwd)
    if rc != 0:
        raise RuntimeError(f"{cmd}: exit {rc}: {err.getvalue()}")
    return out.getvalue()


def _wrap(cmd: str, width: int = 100) -> str:
    """``$ cmd`` wrapped at spaces with ``\\`` continuations, as the page shows long commands."""
    words, lines, cur = cmd.split(" "), [], "$"
    for w in words:
        if len(cur) + 1 + len(w) > width and cur not in ("$", "     "):
            lines.append(cur + " \\")
            cur = "     "
        cur += " " + w
    lines.append(cur)
    return "\n".join(lines)


def render(ex: Example) -> str:
    """The block's text: each command and what it printed."""
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        ex.setup(tmp)
        for cmd in ex.hidden:
            _run(cmd, tmp)
        parts = []
        for cmd in ex.commands:
            parts.append(_wrap(cmd))
            out = _run(cmd, tmp).rstrip("\n")
            if out:
                parts.append(out)
    return "\n".join(parts)


BLOCK = re.compile(r"(<!-- output: (?P<name>[\w-]+) -->\n```\n)(?P<body>(?:(?!<!-- /?output).)*?)(\n```\n<!-- /output -->)",
                   re.S)


def blocks(page: str) -> dict[str, str]:
    return {m.group("name"): m.group("body") for m in BLOCK.finditer(page)}


def update(page: str, outputs: dict[str, str]) -> str:
    return BLOCK.sub(lambda m: m.group(1) + outputs.get(m.group("name"), m.group("body")) + m.group(4), page)


def stale(names=None) -> list[str]:
    """The names of the page's blocks (``names``: only these) whose text is not what the code prints."""
    page = PAGE.read_text()
    have = blocks(page)
    out = []
    for ex in EXAMPLES:
        if names is not None and ex.name not in names:
            continue
        if ex.name not in have or have[ex.name] != render(ex):
            out.append(ex.name)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", help=f"examples (default: all): {', '.join(BY_NAME)}")
    ap.add_argument("--check", action="store_true", help="compare, do not write; exit 1 if a block is stale")
    a = ap.parse_args(argv)
    bad = [n for n in a.names if n not in BY_NAME]
    if bad:
        ap.error(f"unknown example(s) {', '.join(bad)}: expected {', '.join(BY_NAME)}")
    names = a.names or list(BY_NAME)
    if a.check:
        s = stale(names)
        if s:
            print("stale output blocks in docs/calibration.md: " + ", ".join(s) + " (python docs/calibration_examples.py "
                  + " ".join(s) + ")")
            return 1
        return 0
    page = PAGE.read_text()
    have = blocks(page)
    missing = [n for n in names if n not in have]
    if missing:
        print("no block for: " + ", ".join(missing) + " (add <!-- output: NAME --> ... <!-- /output --> to the page)")
    for n in names:
        if n in have:  # each block written as soon as it is made (the page read again: one block at a time)
            out = render(BY_NAME[n])
            PAGE.write_text(update(PAGE.read_text(), {n: out}))
            print(f"updated: {n}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
