"""First run against a later one: the whole `errplan demo` with empty caches, then again warm.

    python benchmarks/first_run.py [--pairs 3] [--scenario F] [--keep DIR]

Each pair: one `errplan demo` process with an empty numba kernel cache and an empty reachability-map
cache (``NUMBA_CACHE_DIR``, ``ERRPLAN_CACHE_DIR`` in a fresh temporary directory: what a fresh install
has), then the same command again on the caches the first one filled. Both are timed whole (wall
clock, interpreter start to exit) with the CPU time of the process and its children, and the
first-run notice's delay (how long after the start its line came on stderr; a warm run prints none). The pairs run one
after the other, so a drift of the machine's speed lands on both halves of a pair alike; the table
gives every pair and the median ratio. The target is a cold run within 1.5 times the warm one, and the
notice within 10 s.

``--scenario F`` runs `errplan demo --scenario F` instead of the bundled scenarios and setup.

``--steps``: every run also writes its steps (``ERRPLAN_DEMO_PROFILE``: scenario, step, process, start,
end, CPU) and the table gives, per run, the CPU of each scenario's steps and the wall time two quiet
cores would need at least for that CPU (:func:`cpu_bound`: the larger of the total CPU over the cores
and the longest scenario's chain of fields, plan, longest query and recording). ``--compare`` runs each
warm demo twice back to back, one step after another (``ERRPLAN_DEMO_WORKERS=1``, as before the demo ran
side by side) and side by side, with the same caches, and prints both.
"""
from __future__ import annotations

import argparse
import json
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


def cpu_bound(prof: dict, cores: int = 2) -> dict:
    """From a demo's steps (``ERRPLAN_DEMO_PROFILE``): CPU seconds per scenario and step kind (fields,
    plan, queries, record; the setup's triad placement counts as fields), the total, and the least wall
    time ``cores`` quiet cores need for it: the larger of total / cores and the longest scenario chain
    (fields, in one process side by side, plan, its longest query, record: the steps that wait for each
    other). One step after another the chain is the sum."""
    per: dict = {}
    for e in prof["steps"]:
        d = per.setdefault(e["scenario"], {"fields": 0.0, "plan": 0.0, "queries": 0.0, "record": 0.0,
                                           "query_max": 0.0})
        if e["step"] == "triad":
            d["fields"] += e["cpu"]
            continue
        kind = "queries" if e["step"].startswith("query") or e["step"] == "queries+record" else e["step"]
        d[kind] += e["cpu"]
        if e["step"].startswith("query"):
            d["query_max"] = max(d["query_max"], e["cpu"])
    total = prof["cpu"]
    if prof.get("workers", 1) <= 1:
        chain = sum(d["fields"] / cores + d["plan"] + d["queries"] + d["record"] for d in per.values())
    else:
        chain = max((d["fields"] + d["plan"] + d["query_max"] + d["record"] for d in per.values()), default=0)
    return {"per": per, "total": total, "bound": max(total / cores, chain), "chain": chain}


def run_demo(cache: Path, work: Path, scenario: str | None, steps: bool = False, workers: int | None = None) -> dict:
    """One `errplan demo` process on the caches in ``cache``: wall and CPU seconds, the compile notice's
    delay (None: no notice); with ``steps`` its steps (:func:`cpu_bound`); ``workers``: ERRPLAN_DEMO_WORKERS."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache / "numba"), ERRPLAN_CACHE_DIR=str(cache / "errplan"),
               CI=os.environ.get("CI", "true"))
    env.pop("ERRPLAN_COMPILE_NOTICE", None)
    prof_path = work / "steps.json"
    if steps:
        env["ERRPLAN_DEMO_PROFILE"] = str(prof_path)
    if workers is not None:
        env["ERRPLAN_DEMO_WORKERS"] = str(workers)
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
    out = {"wall": wall, "cpu": cpu, "notice_s": first.get("t")}
    if steps:
        out["steps"] = cpu_bound(json.loads(prof_path.read_text()))
    return out


def steps_table(label: str, r: dict) -> str:
    b = r["steps"]
    rows = [[label, name, f"{d['fields']:.1f}", f"{d['plan']:.1f}", f"{d['queries']:.1f}",
             f"{d['query_max']:.1f}" if d["query_max"] else "-", f"{d['record']:.1f}"] for name, d in b["per"].items()]
    return (format_table(["run", "scenario", "fields CPU, s", "plan CPU, s", "queries CPU, s", "longest query, s",
                          "record CPU, s"], rows)
            + f"\n{label}: wall {r['wall']:.1f} s, CPU {r['cpu']:.1f} s (all processes), at least "
              f"{b['bound']:.1f} s on 2 quiet cores (chain {b['chain']:.1f} s, CPU / 2 {b['total'] / 2:.1f} s)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, default=3, help="cold + warm pairs (default 3)")
    ap.add_argument("--scenario", default=None, help="one scenario file instead of the bundled ones")
    ap.add_argument("--keep", default=None, help="keep the caches and recordings under this directory")
    ap.add_argument("--steps", action="store_true", help="per-step CPU of every run and its least wall time")
    ap.add_argument("--compare", action="store_true",
                    help="each warm run also one step after another (ERRPLAN_DEMO_WORKERS=1), back to back")
    a = ap.parse_args()
    steps = a.steps or a.compare
    if a.pairs < 1:
        raise SystemExit("--pairs: expected at least 1")
    rows, ratios, notices, details = [], [], [], []
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(a.keep) if a.keep else Path(tmp)
        for i in range(a.pairs):
            cache, work = base / f"pair{i + 1}" / "cache", base / f"pair{i + 1}" / "work"
            work.mkdir(parents=True, exist_ok=True)
            cold = run_demo(cache, work, a.scenario, steps)
            warm = run_demo(cache, work, a.scenario, steps)
            if steps:
                details.append(steps_table(f"pair {i + 1} cold", cold))
                details.append(steps_table(f"pair {i + 1} warm", warm))
            if a.compare:
                seq = run_demo(cache, work, a.scenario, True, workers=1)
                details.append(steps_table(f"pair {i + 1} warm, one step after another", seq))
                print(f"pair {i + 1}: warm one step after another {seq['wall']:.1f} s", file=sys.stderr, flush=True)
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
    for d in details:
        print()
        print(d)
    med = statistics.median(ratios)
    late = [t for t in notices if t is None or t > NOTICE_S]  # a cold run compiles: no notice at all is late
    print()
    print(f"median cold / warm {med:.2f} (target <= {TARGET}: {'met' if med <= TARGET else 'NOT met'}; "
          f"range {min(ratios):.2f} to {max(ratios):.2f}); first-run notice within {NOTICE_S:g} s: "
          f"{'yes' if not late else 'NO'}")
    return 0 if med <= TARGET and not late else 1


if __name__ == "__main__":
    sys.exit(main())
