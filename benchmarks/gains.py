"""Benchmark of the gain schedule and the demo pipeline: time per step, and what the joint casadi
problem buys over choosing each segment's gain alone.

    python benchmarks/gains.py            # every bundled scenario with queries, planned paths
    python benchmarks/gains.py --demo     # also time `errplan demo` (fields, plan, pipeline) in-process

Spatial scenarios are planned on the demo's fields (errplan.cli.demo: SPATIAL_RESOLUTION, the metrics
the planner needs); their casadi column adds the cutting-plane rounds (3-D: sigma_max is the
maximum of cuts over directions, see errplan.gains).

Columns: segments; casadi solve time and total schedule time (sampling, solve, dense verification);
max certified ||G|| (verified); predicted steps (sum over segments of log(R/tol)/-log ||G||) for the
joint solution and for each segment's own best gain (numpy scan, no gain-change bound) with the
largest gain jump of each; simulated steps under the truth.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from errplan import planning  # noqa: E402
from errplan.fields import Evaluator, compute_fields  # noqa: E402
from errplan.cli.demo import SPATIAL_METRICS, SPATIAL_RESOLUTION  # noqa: E402
from errplan.gains import SpatialModel, schedule_gains  # noqa: E402
from errplan.gains.certificate import _sample_segment, _scan, _scan_M  # noqa: E402
from errplan.pipeline import replay, truth_plant  # noqa: E402
from errplan.report import format_table  # noqa: E402
from errplan.api import load_scenario  # noqa: E402
from errplan.simulation import ControllerModel  # noqa: E402
from errplan.models import build_arm


def predicted_steps(radii, rhos, tols):
    return sum(max(math.log(r / t), 0) / -math.log(max(p, 1e-12)) if p < 1 else math.inf
               for r, p, t in zip(radii, rhos, tols))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demo", action="store_true", help="also time the demo pipeline")
    args = ap.parse_args()
    rows = []
    for path in sorted((ROOT / "scenarios").glob("*.toml")):
        sc = build_arm(load_scenario(path))  # each arm built once, for every step below
        if not sc.queries:
            continue
        if sc.dim == 3:
            ev = SpatialModel.from_model(sc)
            mf = compute_fields(sc, SPATIAL_RESOLUTION, metrics=SPATIAL_METRICS, workers=None)
        else:
            ev = Evaluator.from_model(sc)
            mf = compute_fields(sc, rho_star=True)
        for qp in planning.plan_scenario(sc, mf).queries:
            t0 = time.perf_counter()
            gs = schedule_gains(ev if sc.dim == 3 else sc, np.asarray(qp.planned.path, float))
            t_sched = time.perf_counter() - t0
            segs = gs.segments
            tols = [gs.options.switch_tolerance] * (len(segs) - 1) + [gs.options.tolerance]
            radii = [s.radius for s in segs]
            joint = predicted_steps(radii, [s.predicted_G_norm for s in segs], tols)
            own = []
            for s in segs:
                smp = _sample_segment(ev, s.start, s.end, s.radius, gs.options)
                own.append(_scan_M(smp["M"])[:2] if sc.dim == 3 else _scan(smp["mu"], smp["nu"]))
            alone = predicted_steps(radii, [o[0] for o in own], tols)
            jump_joint = float(np.max(np.abs(np.diff(gs.gains)))) if len(segs) > 1 else 0.0
            jump_alone = float(np.max(np.abs(np.diff([o[1] for o in own])))) if len(segs) > 1 else 0.0
            sim = replay(truth_plant(sc), ControllerModel.from_model(sc), qp.planned.path[0], gs.waypoints,
                         gs.gains, gs.options, sc.planner.seed)
            cas = f"{gs.solver.get('time_s', float('nan')):.4f}"
            if sc.dim == 3:
                cas += f" ({gs.solver.get('cut_rounds', 1)} rounds)"
            rows.append([sc.name, qp.name, len(segs), cas, t_sched,
                         gs.max_certified_G_norm, joint, jump_joint, alone, jump_alone, sim.sim.steps])
    print(format_table(["scenario", "query", "segments", "casadi s", "schedule s", "max cert ||G||",
                        "pred. steps joint", "max |dk| joint", "pred. steps alone", "max |dk| alone",
                        "sim steps"], rows, "gain schedules of the bundled plans"))
    if args.demo:
        import io
        from contextlib import redirect_stdout

        from errplan.cli import main as cli_main

        buf = io.StringIO()
        t0 = time.perf_counter()
        with redirect_stdout(buf):
            cli_main(["--quiet", "demo", "--record", "/tmp/errplan-bench-demo.rrd"])
        wall = time.perf_counter() - t0
        lines = [ln for ln in buf.getvalue().splitlines() if ln.startswith("time:")]
        print(f"\nerrplan demo: {wall:.1f} s wall in-process, planar then spatial:")
        for ln in lines:
            print("  " + ln)
    return 0


if __name__ == "__main__":
    sys.exit(main())
