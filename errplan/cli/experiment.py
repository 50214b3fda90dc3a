"""``errplan experiment SCENARIO --out DATA.csv [--seed N] [--starts N] [--max-steps N] [--dwell N]``.

A P1-style bench run (P1 Sec. III-B) on the scenario's truth: the declared model plus its
``[effects]`` and sensor noise. Writes the measured-data CSV of docs/interfaces.md (atomically).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ErrplanError
from ..report import format_table


def run(args) -> int:
    from ..experiment import run_experiment
    from ..scenario import load_scenario

    from ..inputs import check_output
    from . import check_seed

    sc = load_scenario(args.scenario)
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
    ex = run_experiment(sc, args.seed, n_starts=starts, max_steps=max_steps, dwell=dwell)
    d = ex.data
    ex.data.source = str(out)
    d.write_csv(out)
    rows = []
    per = 8
    for si, s in enumerate(ex.starts):
        ids = [r for r in range(d.runs) if d.run_ids[r].split("-")[0] == str(si)]
        if not ids:
            continue
        steps = [int(np.sum(d.run == r)) - 1 for r in ids]
        final = [float(np.linalg.norm(d.tip[d.run == r][-1] - d.target[d.run == r][0]) * 1000) for r in ids]
        st = [ex.status[r] for r in ids]
        rows.append([f"({s[0] * 1000:.1f}, {s[1] * 1000:.1f})", f"{len(ids)}/{per}", int(np.mean(steps)), max(steps),
                     st.count("converged"), max(final)])
    eff = ", ".join(f"{k}({', '.join(f'{p}={v:g}' for p, v in ps.items())})" for k, ps in sc.effects.items()) or "none"
    print(format_table(["start y, z (mm)", "runs", "mean steps", "max steps", "converged", "max final error (mm)"], rows,
                       f"bench run on {sc.name}: gain {sc.controller.gain:g}, {sc.controller.jacobian} controller, "
                       f"seed {args.seed} -> {out}"))
    print(f"truth: effects {eff}; tracker sigma {sc.sensors.tracker_sigma * 1000:g} mm, encoder sigma "
          f"{sc.sensors.encoder_sigma:g} rad; arrival tolerance {ex.tolerance * 1000:.2f} mm, dwell {ex.dwell} steps")
    print(f"{d.rows} rows, {d.runs} runs")
    return 0
