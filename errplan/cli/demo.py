"""``errplan demo``: the bundled default scenario end to end.

fields (worst case over the error set, with rho*) -> plan every query (OMPL) -> certified gains
(casadi) -> quasi-static simulation under the truth and every corner of the error box -> one rerun
recording (``errplan-demo.rrd``) and a summary table (planned vs direct).
"""
from __future__ import annotations

import time
from pathlib import Path

from ..errors import ErrplanError
from ..report import Progress, write_json

BUNDLED = Path(__file__).resolve().parents[2] / "scenarios" / "beasley2004_bounded.toml"


def bundled_scenario() -> Path:
    if not BUNDLED.exists():
        raise ErrplanError(f"{BUNDLED}: the bundled demo scenario is missing (pass --scenario FILE)")
    return BUNDLED


def run(args) -> int:
    from ..fields import compute_fields
    from ..inputs import check_output
    from ..pipeline import run_pipeline, summary_table
    from ..planning import plan_scenario
    from ..scenario import load_scenario

    t0 = time.perf_counter()
    path = Path(args.scenario) if args.scenario else bundled_scenario()
    sc = load_scenario(path)
    if not sc.queries:
        raise ErrplanError(f"{path}: the scenario has no [[query]] to plan")
    rec = check_output("--record", args.record)
    check_output("--json", args.json)
    quiet = getattr(args, "quiet", False)
    prog = Progress("fields", quiet=quiet)
    mf = compute_fields(sc, rho_star=True, progress=prog)
    prog.done()
    t_fields = time.perf_counter() - t0
    t1 = time.perf_counter()
    plans = plan_scenario(sc, mf).queries
    t_plan = time.perf_counter() - t1
    t2 = time.perf_counter()
    prog = Progress("gains+simulation", quiet=quiet)
    res = run_pipeline(sc, plans, mf, record=str(rec) if rec else None, progress=prog)
    prog.done()
    t_pipe = time.perf_counter() - t2
    doc = {"scenario": sc.name, "queries": res["queries"],
           "timing_s": {"fields": t_fields, "plan": t_plan, "gains_simulation_record": t_pipe,
                        "total": time.perf_counter() - t0}}
    if args.json:
        write_json(args.json, doc)
    print(summary_table(res["runs"], f"errplan demo: {sc.name} ({path.name})"))
    print(f"time: fields {t_fields:.1f} s, planning {t_plan:.1f} s, gains + simulation"
          f"{' + recording' if rec else ''} {t_pipe:.1f} s, total {time.perf_counter() - t0:.1f} s")
    if rec:
        print(f"recording: {rec}  (open it with `errplan view {rec}`)")
    return 0
