"""Speed of P2's flexion controller in 3-D: the compiled controller against the numpy path, same answers.

    python benchmarks/flexion.py [--every 16] [--task-res 0.002]

(a) The 3-D flexion field of scenarios/phantom15_flexion.toml over the widened region (x, y in [-30, 30] mm,
    z in [360, 450] mm at 5 mm: 3,211 tips), metrics G_norm, phi_hat_max, phi_max (the default), one
    worker, in process: CPU time (user + sys of this process, ``time.process_time``) and wall time per tip
    of the compiled controller (errplan.fields.kernels.flexion, every tip) and of the numpy path
    (NumpyFlexionEvaluator: the same search on errplan.kinematics.shaft in numpy) on every ``--every``-th
    tip (the numpy path takes about 80 ms of CPU per tip: all of them would take minutes), and the largest
    difference of the two on those tips (valid flags, ||G||, |phi_max|).
(b) A field over P2's task region (the scenario's [fields] region) at ``--task-res`` (2 mm), compiled, with
    its time (``compute_fields``, one worker, the first compile excluded: a warm-up field runs first).
Both paths compute the same worst case tile by tile (errplan.fields.compute.numpy_worst_case); the numbers
are measured in this one run, back to back, on this machine.
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from errplan.models import build_arm

REPO = Path(__file__).resolve().parents[1]
FLEX = REPO / "scenarios" / "phantom15_flexion.toml"


def widened_tips() -> np.ndarray:
    """x, y in [-30, 30] mm, z in [360, 450] mm at 5 mm (3,211 tips)."""
    ax = [np.arange(-6, 7) * 0.005, np.arange(-6, 7) * 0.005, np.arange(72, 91) * 0.005]
    return np.stack(np.meshgrid(*ax, indexing="ij"), axis=-1).reshape(-1, 3)


def timed(f):
    c0, w0 = time.process_time(), time.perf_counter()
    out = f()
    return out, time.process_time() - c0, time.perf_counter() - w0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--every", type=int, default=16, help="the numpy path on every n-th tip (default 16)")
    ap.add_argument("--task-res", type=float, default=0.002, help="resolution of the task-region field (m)")
    a = ap.parse_args()

    from errplan.api import load_scenario
    from errplan.fields import compute_fields
    from errplan.fields.compute import numpy_worst_case
    from errplan.fields.evaluator import NumpyFlexionEvaluator, SpatialFlexionEvaluator

    sc = load_scenario(FLEX)
    k = float(sc.controller.gain)
    ev = SpatialFlexionEvaluator.from_model(build_arm(sc))
    ref = NumpyFlexionEvaluator.from_model(build_arm(sc))
    X = widened_tips()
    load0 = os.getloadavg()[0]
    numpy_worst_case(ev, X[:2], k)  # load (or compile) the kernels outside the measurement
    pairs = [0]
    compiled = ev._compiled

    def counted(x, theta, noise, *args, **kw):  # (tip, instance) pairs the compiled controller evaluates
        pairs[0] += len(np.asarray(x).reshape(-1, 3)) * (1 if noise is None else 0)
        return compiled(x, theta, noise, *args, **kw)

    ev._compiled = counted
    kern, c_k, w_k = timed(lambda: numpy_worst_case(ev, X, k))
    ev._compiled = compiled
    sub = np.arange(0, len(X), a.every)
    nump, c_n, w_n = timed(lambda: numpy_worst_case(ref, X[sub], k))
    same = np.array_equal(kern["valid"][sub], nump["valid"])
    v = nump["valid"]
    diff = max(float(np.max(np.abs(kern[key][sub][v] - nump[key][v]), initial=0.0)) for key in ("G_norm", "phi_max"))

    compute_fields(sc, 0.006, workers=1)  # warm: the field's own kernels loaded
    f, c_f, w_f = timed(lambda: compute_fields(sc, a.task_res, workers=1))
    n_task = int(np.prod(f.valid.shape))

    print(f"{os.cpu_count()} cores, load average (1 min) {load0:.2f} before, {os.getloadavg()[0]:.2f} after")
    print()
    print("| 3-D flexion field, widened region (3,211 tips, 5 mm) | tips timed | valid | CPU per tip (ms) | wall per tip (ms) |")
    print("|---|---|---|---|---|")
    print(f"| numpy path (every {a.every}th tip) | {len(sub)} | {int(v.sum())} | {c_n / len(sub) * 1e3:.2f} | {w_n / len(sub) * 1e3:.2f} |")
    print(f"| compiled controller (every tip) | {len(X)} | {int(kern['valid'].sum())} | {c_k / len(X) * 1e3:.2f} | {w_k / len(X) * 1e3:.2f} |")
    print()
    maps = pairs[0] * len(ev.noise)
    print(f"compiled: {pairs[0] / len(X):.1f} (tip, instance) evaluations per tip over the {len(ev.noise)} noise "
          f"corners; {c_k / maps * 1e9:.0f} ns of CPU per corner map (the compiled field's whole CPU time, the "
          f"noise refinement's few polls included, over those maps)")
    print(f"CPU per tip, numpy / compiled: {(c_n / len(sub)) / (c_k / len(X)):.1f}x; same valid flags on the "
          f"numpy tips: {same}; largest |difference| of G_norm, phi_max there: {diff:.1e}")
    print(f"2 mm-class field over P2's task region ({a.task_res * 1e3:g} mm, {n_task} tips, {int(f.valid.sum())} valid): "
          f"{c_f:.1f} s CPU, {w_f:.1f} s wall (one worker)")
    return 0 if same and diff < 1e-9 else 1


if __name__ == "__main__":
    raise SystemExit(main())
