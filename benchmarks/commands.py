"""`errplan plan`, `errplan fields` and `errplan tolerance` on both cores, first and later runs, against one core.

    python benchmarks/commands.py [--repeat 1] [--only plan-abdomen,...]

Each case runs one command as a user would, whole (interpreter start to exit: wall clock, and the CPU of
the process and its children), in two ways:

- **both cores** (as shipped): the fields' tiles and the queries' gains and simulations on every core
  (`--workers` default), and on a first run the second process that compiles ahead
  (:mod:`errplan.cli.warmup`);
- **one core** (as before): ``--workers 1`` (``errplan plan``) and ``ERRPLAN_WARMUP=0``: every step and
  every compile in the command's own process (``errplan tolerance`` and ``errplan fields`` keep their
  default workers: only the warm-up differs).

"first run": empty kernel and reachability-map caches (``NUMBA_CACHE_DIR``, ``ERRPLAN_CACHE_DIR`` in a
fresh temporary directory, what a fresh install has); "later run": the caches a first run filled. The
two ways alternate per case, so a drift of the machine's speed lands on both. Every pair of outputs is
compared: the JSONs without their timings (keys naming a time, and the seconds of a tolerance query), the
fields' npz arrays bit for bit.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from errplan.report import format_table  # noqa: E402

SC = ROOT / "scenarios"
#: name -> (command arguments after ``errplan``, output option, output file name, whether it is a first run)
CASES = {
    "plan-abdomen-first": (["plan", str(SC / "abdomen.toml")], "--json", "plan.json", True),
    "fields-abdomen-first": (["fields", str(SC / "abdomen.toml")], "--out", "fields.npz", True),
    "tolerance-placement-first": (["tolerance", str(SC / "phantom15_placement.toml")], "--json", "tolerance.json",
                                  True),
    "plan-abdomen": (["plan", str(SC / "abdomen.toml")], "--json", "plan.json", False),
    "plan-phantom15": (["plan", str(SC / "phantom15_spatial.toml")], "--json", "plan.json", False),
}


def run(args: list[str], cache: Path, work: Path, one_core: bool) -> dict:
    """One command on the caches in ``cache``: wall and CPU seconds."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache / "numba"), ERRPLAN_CACHE_DIR=str(cache / "errplan"),
               CI=os.environ.get("CI", "true"))
    cmd = [sys.executable, "-m", "errplan", "-q", *args]
    if one_core:
        env["ERRPLAN_WARMUP"] = "0"
        if args[0] == "plan":
            cmd += ["--workers", "1"]
    before = os.times()
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=work, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    after = os.times()
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(args)} exited with {r.returncode}: {r.stderr.strip().splitlines()[-1:]}")
    cpu = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    return {"wall": wall, "cpu": cpu}


def _no_times(o):
    if isinstance(o, dict):
        return {k: _no_times(v) for k, v in o.items() if "time" not in k and "seconds" not in k}
    return [_no_times(v) for v in o] if isinstance(o, list) else o


def same(a: Path, b: Path) -> bool:
    """The two outputs agree: plan JSONs without timings, npz arrays bit for bit."""
    if a.suffix == ".json":
        return _no_times(json.loads(a.read_text())) == _no_times(json.loads(b.read_text()))
    x, y = np.load(a), np.load(b)
    return x.files == y.files and all(np.array_equal(x[k], y[k], equal_nan=x[k].dtype.kind == "f") for k in x.files)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=1, help="runs of each case and way (default 1)")
    ap.add_argument("--only", default=None, help=f"comma-separated cases (default all: {', '.join(CASES)})")
    a = ap.parse_args()
    names = a.only.split(",") if a.only else list(CASES)
    bad = [n for n in names if n not in CASES]
    if bad or a.repeat < 1:
        raise SystemExit(f"--only {bad}: expected some of {', '.join(CASES)}" if bad else "--repeat: expected >= 1")
    rows = []
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            args, opt, fname, first = CASES[name]
            warm = {}
            for way in ("both", "one"):  # a later run's caches: filled once per way, before its timed runs
                if not first:
                    w = Path(tmp) / name / f"fill-{way}"
                    w.mkdir(parents=True)
                    run(args + [opt, str(w / fname)], w / "cache", w, way == "one")
                    warm[way] = w / "cache"
            for i in range(a.repeat):
                res, outs = {}, {}
                for way in ("both", "one"):
                    w = Path(tmp) / name / f"{way}{i}"
                    w.mkdir(parents=True)
                    outs[way] = w / fname
                    res[way] = run(args + [opt, str(outs[way])], w / "cache" if first else warm[way], w, way == "one")
                b, o = res["both"], res["one"]
                rows.append([name, "first" if first else "later", f"{b['wall']:.1f}", f"{b['cpu']:.1f}",
                             f"{o['wall']:.1f}", f"{o['cpu']:.1f}", f"{b['wall'] / o['wall']:.2f}",
                             "yes" if same(outs["both"], outs["one"]) else "NO"])
                print(f"{name} {i + 1}: both cores {b['wall']:.1f} s, one core {o['wall']:.1f} s", file=sys.stderr,
                      flush=True)
    print(f"`errplan plan` / `errplan fields` / `errplan tolerance`: {len(os.sched_getaffinity(0))} cores, load average (1 min) "
          f"{load0:.2f} before, {os.getloadavg()[0]:.2f} after")
    print(format_table(["case", "run", "both cores wall, s", "both cores CPU, s", "one core wall, s",
                        "one core CPU, s", "both / one", "same output"], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
