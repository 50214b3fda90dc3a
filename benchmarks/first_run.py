"""First run against a later one (issue 17): the whole `errplan demo` with empty caches, then again warm.

    python benchmarks/first_run.py [--pairs 3] [--scenario F] [--keep DIR]

Each pair: one `errplan demo` process with an empty numba kernel cache and an empty reachability-map
cache (``NUMBA_CACHE_DIR``, ``ERRPLAN_CACHE_DIR`` in a fresh temporary directory: what a fresh install
has), then the same command again on the caches the first one filled. Both are timed whole (wall
clock, interpreter start to exit) with the CPU time of the process and its children, and the
first-run notice's delay (how long after the start its line came on stderr; a warm run prints none). The pairs run one
after the other, so a drift of the machine's speed lands on both halves of a pair alike; the table
gives every pair and the median ratio. The target is a cold run within 1.5 times the warm one, and the
notice within 10 s.

``--scenario F`` runs `errplan demo --scenario F` instead of the three bundled scenarios.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from errplan.report import format_table  # noqa: E402

TARGET = 1.5
NOTICE_S = 10.0


def run_demo(cache: Path, work: Path, scenario: str | None) -> dict:
    """One `errplan demo` process on the caches in ``cache``: wall and CPU seconds, the compile notice's
    delay (None: no notice)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache / "numba"), ERRPLAN_CACHE_DIR=str(cache / "errplan"),
               CI=os.environ.get("CI", "true"))
    env.pop("ERRPLAN_COMPILE_NOTICE", None)
    cmd = [sys.executable, "-m", "errplan", "demo", "--record", str(work / "demo.rrd")]
    if scenario:
        cmd += ["--scenario", str(Path(scenario).resolve())]
    first: dict = {}
    last: dict = {}
    before = os.times()
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=work, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    def read_err():
        for line in proc.stderr:
            if "compiling numerical kernels" in line and not first:
                first["t"] = time.perf_counter() - t0
            last["line"] = line.strip()

    reader = threading.Thread(target=read_err, daemon=True)
    reader.start()
    rc = proc.wait()
    wall = time.perf_counter() - t0
    reader.join()
    after = os.times()
    if rc != 0:
        raise SystemExit(f"errplan demo exited with {rc}: {last.get('line', '')}")
    cpu = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    return {"wall": wall, "cpu": cpu, "notice_s": first.get("t")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, default=3, help="cold + warm pairs (default 3)")
    ap.add_argument("--scenario", default=None, help="one scenario file instead of the bundled three")
    ap.add_argument("--keep", default=None, help="keep the caches and recordings under this directory")
    a = ap.parse_args()
    if a.pairs < 1:
        raise SystemExit("--pairs: expected at least 1")
    rows, ratios, notices = [], [], []
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(a.keep) if a.keep else Path(tmp)
        for i in range(a.pairs):
            cache, work = base / f"pair{i + 1}" / "cache", base / f"pair{i + 1}" / "work"
            work.mkdir(parents=True, exist_ok=True)
            cold = run_demo(cache, work, a.scenario)
            warm = run_demo(cache, work, a.scenario)
            ratio = cold["wall"] / warm["wall"]
            ratios.append(ratio)
            notices.append(cold["notice_s"])
            rows.append([str(i + 1), f"{cold['wall']:.1f}", f"{cold['cpu']:.1f}", f"{warm['wall']:.1f}",
                         f"{warm['cpu']:.1f}", f"{ratio:.2f}",
                         "none" if cold["notice_s"] is None else f"{cold['notice_s']:.1f}",
                         "none" if warm["notice_s"] is None else f"{warm['notice_s']:.1f}"])
            print(f"pair {i + 1}: cold {cold['wall']:.1f} s, warm {warm['wall']:.1f} s, ratio {ratio:.2f}",
                  file=sys.stderr, flush=True)
    print(f"`errplan demo{' --scenario ' + a.scenario if a.scenario else ''}`: {os.cpu_count()} cores, load "
          f"average (1 min) {load0:.2f} before, {os.getloadavg()[0]:.2f} after")
    print()
    print(format_table(["pair", "cold wall, s", "cold CPU, s", "warm wall, s", "warm CPU, s", "cold / warm",
                        "cold: notice after, s", "warm: notice after, s"], rows))
    med = statistics.median(ratios)
    late = [t for t in notices if t is None or t > NOTICE_S]  # a cold run compiles: no notice at all is late
    print()
    print(f"median cold / warm {med:.2f} (target <= {TARGET}: {'met' if med <= TARGET else 'NOT met'}; "
          f"range {min(ratios):.2f} to {max(ratios):.2f}); first-run notice within {NOTICE_S:g} s: "
          f"{'yes' if not late else 'NO'}")
    return 0 if med <= TARGET and not late else 1


if __name__ == "__main__":
    sys.exit(main())
