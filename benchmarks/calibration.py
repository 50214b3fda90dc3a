"""Benchmark of `errplan calibrate`: time against data size, and what it finds per effect.

    python benchmarks/calibration.py            # timing (1k, 2k, 4k rows) + quality per effect
    python benchmarks/calibration.py --quick    # timing only
    python benchmarks/calibration.py --design   # experiment design only (planar and spatial)

Timing: bench data on P1's scenario (beasley2004_port.toml, gain 1) with gravity sag undeclared,
more starts for more rows; the whole `calibrate` (noise floor, 22-26 candidates each fitted on all
rows and refitted on 5 folds, selection, structure test, trajectory replays) in-process, best of
one run after a warm-up import. Quality: for each catalogue effect at bench size (and for two
effects, noise only and a 4 mm link-2 length error outside the catalogue) the selection, each
parameter's estimate against the truth in stated sigmas, and the held-out errors before -> after.

Design: the default bench (8 starts x P1's targets) against a designed one with the same number of
rows (``errplan experiment --design``): largest correlations and condition numbers predicted for
all catalogue parameters, the criteria compared, then real benches (the same truth, default vs
designed runs) calibrated against the declared scenario: what is selected and the recovered
parameters' stated sigmas.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from errplan.calibration import calibrate  # noqa: E402
from errplan.experiment import run_experiment  # noqa: E402
from errplan.report import format_table  # noqa: E402
from errplan.scenario import Robot, load_scenario  # noqa: E402
from errplan.simulation import Plant  # noqa: E402

PORT = ROOT / "scenarios" / "beasley2004_port.toml"
GRAVITY = {"gravity_sag": {"c1": 0.004, "c2": 0.002, "c3": 0.003}}
CASES = [
    ("port_offset", {"port_offset": {"dy": 0.003, "dz": -0.002}}),
    ("joint_offset", {"joint_offset": {"dq1": 0.003, "dq2": -0.002}}),
    ("tracker_offset", {"tracker_offset": {"by": 0.002, "bz": -0.0015}}),
    ("gravity_sag", GRAVITY),
    ("shaft_flexion", {"shaft_flexion": {"fy": 2.0, "fz": 1.0}}),
    ("port_friction", {"port_friction": {"fa": 0.0015, "fn": 0.001}}),
    ("gravity+friction", {**GRAVITY, "port_friction": {"fa": 0.001, "fn": 0.0008}}),
    ("noise only", {}),
    ("link 2 +4 mm (outside)", None),
]


def timing(sc) -> None:
    truth = sc.with_(effects=GRAVITY)
    rows = []
    for starts, dwell in ((8, 10), (16, 10), (22, 16)):
        d = run_experiment(truth, seed=1, n_starts=starts, dwell=dwell).data
        t0 = time.perf_counter()
        rep = calibrate(sc, d, seed=0)
        dt = time.perf_counter() - t0
        rows.append([d.rows, d.runs, len(rep.candidates), ", ".join(rep.selected) or "none", dt])
    print(format_table(["rows", "runs", "candidates", "selected", "calibrate s"], rows,
                       "calibrate time against data size (P1 scenario, gravity sag undeclared)"))


def quality(sc) -> None:
    rows, prow = [], []
    for name, eff in CASES:
        if eff is None:
            r = sc.robot
            wrong = sc.with_(robot=Robot(r.base, (r.link_lengths[0], r.link_lengths[1] + 0.004), r.home_angles,
                                         r.joint_limits, r.joint_sum_limits))
            plant = Plant.from_scenario(wrong, noise=True)
            data = run_experiment(sc, seed=11, plant=plant).data
            val = run_experiment(sc, seed=12, plant=plant).data
            eff = {}
        else:
            data = run_experiment(sc.with_(effects=eff), seed=11).data
            val = run_experiment(sc.with_(effects=eff), seed=12).data
        rep = calibrate(sc, data, validate=val, seed=0)
        e = rep.errors
        rows.append([name, ", ".join(rep.selected) or "none", "yes" if rep.explained else "NO", rep.noise.sigma * 1e3,
                     e.pose_before * 1e3, e.pose_after * 1e3, e.trajectory_before * 1e3, e.trajectory_after * 1e3])
        for ef, ps in rep.parameters.items():
            for p, v in ps.items():
                true = eff.get(ef, {}).get(p, 0.0)
                s = rep.uncertainty[ef][p]
                f = 1.0 if ef == "shaft_flexion" else 1e3
                prow.append([name, f"{ef}.{p}", true * f, v * f, s * f, (v - true) / s])
    print(format_table(["truth", "selected", "explained", "noise mm", "pose before", "pose after", "traj before",
                        "traj after"], rows,
                       "per effect (P1 scenario, 8 starts, held-out validation run; errors in mm, RMS per coordinate)"))
    print()
    print(format_table(["truth", "parameter", "true", "estimate", "sigma", "z"], prow,
                       "parameters (mm, mrad or 1/m^2): estimate - true in stated sigmas"))


DESIGN_TRUTHS = [
    ("joint_offset + gravity_sag", {"joint_offset": {"dq1": 0.003, "dq2": -0.002}, **GRAVITY}),
    ("port_offset + shaft_flexion", {"port_offset": {"dy": 0.003, "dz": -0.002}, "shaft_flexion": {"fy": 2.0, "fz": 1.0}}),
    ("gravity_sag", GRAVITY),
    ("port_offset", {"port_offset": {"dy": 0.003, "dz": -0.002}}),
    ("shaft_flexion", {"shaft_flexion": {"fy": 2.0, "fz": 1.0}}),
    ("joint_offset", {"joint_offset": {"dq1": 0.003, "dq2": -0.002}}),
]


def design(sc, truths=DESIGN_TRUTHS, label="P1 scenario") -> None:
    import numpy as np

    from errplan.calibration.design import CRITERIA, design_experiment

    t0 = time.perf_counter()
    dz = design_experiment(sc, None)
    t_design = time.perf_counter() - t0
    print(dz.text().split("\n\npredicted")[0])
    print(f"design time {t_design:.1f} s ({dz.candidates} candidate runs); predicted mean sigma ratio (all parameters "
          f"fitted together) {dz.sigma_ratio():.2f}")
    print()
    crow = []
    for c in CRITERIA:
        for sep in (None, 0.94):
            d = dz if (c == "G" and sep == 0.94) else design_experiment(sc, None, criterion=c, separate=sep)
            conf = [f"{a}+{b} {c1:.3f}" for a, b, c0, c1 in d.confused()]
            crow.append([c, "-" if sep is None else f"< {sep:g}", d.designed.runs, d.designed.rows,
                         d.designed.largest_correlation()[0], d.designed.condition(), "; ".join(conf),
                         d.sigma_ratio()])
    print(format_table(["criterion", "pairs", "runs", "rows", "largest corr", "cond", "confused pairs (designed)",
                        "sigma ratio"], crow, f"design criteria compared ({label}, predicted)"))
    print()
    rows, ratios = [], []
    for name, eff in truths:
        truth = sc.with_(effects=eff)
        out = {}
        for bench, runs in (("default", None), ("designed", dz.runs)):
            data = run_experiment(truth, seed=11, runs=runs).data
            rep = calibrate(sc, data, seed=0)
            out[bench] = rep
        r0, r1 = out["default"], out["designed"]
        for ef, ps in eff.items():
            for p_, v in ps.items():
                s0 = r0.uncertainty.get(ef, {}).get(p_) if ef in r0.parameters else None
                s1 = r1.uncertainty.get(ef, {}).get(p_) if ef in r1.parameters else None
                e0 = r0.parameters.get(ef, {}).get(p_)
                e1 = r1.parameters.get(ef, {}).get(p_)
                ratio = s1 / s0 if s0 and s1 else float("nan")
                if np.isfinite(ratio):
                    ratios.append(ratio)
                f = 1.0 if ef == "shaft_flexion" else 1e3
                rows.append([name, f"{ef}.{p_}", v * f,
                             f"{e0 * f:.4g} ± {s0 * f:.3g}" if s0 else "not selected",
                             f"{e1 * f:.4g} ± {s1 * f:.3g}" if s1 else "not selected", ratio])
        rows.append([name, "selected", "", ", ".join(r0.selected) or "none", ", ".join(r1.selected) or "none",
                     f"rows {r0.fit_errors.rows} / {r1.fit_errors.rows}"])
    print(format_table(["truth", "parameter", "true", "default bench", "designed bench", "sigma ratio"], rows,
                       f"calibration on real benches ({label}; mm, mrad or 1/m^2; same seed)"))
    print(f"mean sigma ratio designed / default over the recovered parameters: {np.mean(ratios):.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="timing only")
    ap.add_argument("--design", action="store_true", help="experiment design only")
    args = ap.parse_args()
    sc = load_scenario(PORT)
    if args.design:
        design(sc)
        return 0
    calibrate(sc, run_experiment(sc, seed=0, n_starts=2).data)  # warm-up: imports, caches
    timing(sc)
    if not args.quick:
        print()
        quality(sc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
