"""``errplan experiment SCENARIO --out DATA.csv [--seed N] [--starts N] [--max-steps N] [--dwell N]``.

A P1-style bench run (P1 Sec. III-B) on the scenario's truth: the declared model plus its
``[effects]`` and sensor noise. Writes the measured-data CSV of docs/interfaces.md (atomically).
"""
from __future__ import annotations

import numpy as np

from ..errors import ErrplanError
from ..report import format_table


def run(args) -> int:
    from .. import api

    from ..inputs import check_output
    from . import check_seed

    sc = api.load_arm(args.scenario, args.arm)
    out = check_output("--out", args.out)
    check_seed("--seed", args.seed)
    starts = getattr(args, "starts", 8)
    max_steps = getattr(args, "max_steps", 60)
    dwell = getattr(args, "dwell", 10)
    if starts < 1:
        raise ErrplanError(f"--starts {starts}: expected an integer >= 1")
    if max_steps < 1:
        raise ErrplanError(f"--max-steps {max_steps}: expected an integer >= 1")
    if dwell < 0:
        raise ErrplanError(f"--dwell {dwell}: expected an integer >= 0")
    design_n = getattr(args, "design", None)
    design_json = check_output("--design-json", getattr(args, "design_json", None))
    max_rows = getattr(args, "max_rows", None)
    if design_n is not None and design_n < 0:
        raise ErrplanError(f"--design {design_n}: expected a number of runs >= 1 (0: as many as the rows hold)")
    if max_rows is not None and max_rows < 0:
        raise ErrplanError(f"--max-rows {max_rows}: expected an integer >= 0 (0: no limit)")
    design_effects = getattr(args, "design_effects", None)
    if design_n is None and (max_rows is not None or design_json or design_effects is not None):
        raise ErrplanError("--max-rows, --design-json and --design-effects go with --design N")
    if design_effects is not None:
        design_effects = [e.strip() for e in design_effects.split(",")]
    sep_text = str(getattr(args, "separate", "0.94"))
    if sep_text.strip().lower() == "none":
        separate = None
    else:
        try:
            separate = float(sep_text)
        except ValueError:
            separate = float("nan")
        if not 0.0 < separate < 1.0:
            raise ErrplanError(f"--separate {sep_text}: expected a correlation between 0 and 1, or 'none'")
    runs = None
    if design_n is not None:
        from ..calibration.design import design_experiment
        from ..report import Progress, write_json

        prog = Progress("design", quiet=args.quiet)
        prog.quiet = prog.quiet or not prog.tty
        design = design_experiment(sc, design_n or None, max_rows=max_rows, criterion=getattr(args, "criterion", "G"),
                                   separate=separate, effects=design_effects,
                                   seed=args.seed, n_starts=starts, max_steps=max_steps, dwell=dwell, progress=prog)
        prog.done()
        print(design.text())
        print()
        runs = design.runs
    ex = api.run_experiment(sc, args.seed, starts=starts, max_steps=max_steps, dwell=dwell, runs=runs)
    d = ex.data
    ex.data.source = str(out)
    d.write_csv(out)
    if design_n is not None and design_json:
        write_json(design_json, design.to_json())
    rows = []
    for si, s in enumerate(ex.starts):
        ids = [r for r in range(d.runs) if d.run_ids[r].split("-")[0] == str(si)]
        if not ids:
            continue
        per = len(ex.targets[si]) if ex.targets is not None else len(ids)
        steps = [int(np.sum(d.run == r)) - 1 for r in ids]
        final = [float(np.linalg.norm(d.tip[(d.run == r) & d.tracked][-1] - d.target[d.run == r][0]) * 1000)
                 if np.any((d.run == r) & d.tracked) else float("nan") for r in ids]  # the last tracked row
        st = [ex.status[r] for r in ids]
        rows.append(["(" + ", ".join(f"{v * 1000:.1f}" for v in s) + ")", f"{len(ids)}/{per}", int(np.mean(steps)),
                     max(steps), st.count("converged"), max(final)])
    eff = ", ".join(f"{k}({', '.join(f'{p}={v:g}' for p, v in ps.items())})" for k, ps in sc.effects.items()) or "none"
    axes = ", ".join(sc.axes)
    print(format_table([f"start {axes} (mm)", "runs", "mean steps", "max steps", "converged", "max final error (mm)"], rows,
                       f"bench run on {sc.name}: gain {sc.controller.gain:g}, {sc.controller.jacobian} controller, "
                       f"seed {args.seed} -> {out}"))
    print(f"truth: effects {eff}; tracker sigma {sc.sensors.tracker_sigma * 1000:g} mm, encoder sigma "
          f"{sc.sensors.encoder_sigma:g} rad; arrival tolerance {ex.tolerance * 1000:.2f} mm, dwell {ex.dwell} steps")
    print(f"{d.rows} rows, {d.runs} runs")
    se = sc.sensors
    if se.records:  # a bench as it records ([sensors]): say what the file holds besides the clean table
        parts = []
        if se.step_time is not None:
            parts.append(f"a time column (steps of {se.step_time * 1000:g} ms ± {se.step_jitter * 100:g} %)")
        if se.dropout_rate > 0:
            parts.append(f"{d.dropouts} dropout rows (bursts of 1..{se.dropout_burst})")
        if se.outlier_rate > 0:
            parts.append(f"outliers at a rate of {se.outlier_rate:g}, {se.outlier_size[0] * 1000:g}-"
                         f"{se.outlier_size[1] * 1000:g} mm")
        print("recorded as a bench records: " + ", ".join(parts))
    return 0
