"""``errplan calibrate SCENARIO DATA.csv [--validate VAL.csv] [--json F] [--record F.rrd]
[--export-scenario F.toml] [--export-bench F.toml] [--no-task] [--predictions PRED.csv] [--seed N] [--folds K]``.

Close the loop: residual of the declared model, noise floor, candidate effects fitted and
selected, error before -> after (see :mod:`errplan.calibration`). Every input is checked before
anything is written; outputs are written atomically at the end.

``--export-scenario`` writes the corrected robot (controller and truth both corrected), ``--export-bench``
the bench as it ran (the declared controller, the fitted truth under ``[effects]``;
:mod:`errplan.calibration.export`). A scenario with ``[[query]]`` tables gets the task before and after
(:mod:`errplan.calibration.task`; ``--no-task`` skips its two plans).
"""
from __future__ import annotations

from ..errors import ErrplanError
from ..report import Progress, write_atomic, write_json


def run(args) -> int:
    from .. import api
    from pathlib import Path

    from ..calibration.export import bench_files, corrected_files, predictions_csv
    from ..experiment import read_measured_csv

    from ..inputs import check_output
    from . import check_seed

    sc = api.load_arm(args.scenario, args.arm)
    predictions = getattr(args, "predictions", None)
    bench_path = getattr(args, "export_bench", None)
    outs = (("--json", args.json), ("--record", args.record), ("--export-scenario", args.export_scenario),
            ("--export-bench", bench_path), ("--predictions", predictions))
    for opt, v in outs:
        check_output(opt, v)
    seen: dict = {}
    for opt, v in outs:
        if v is None:
            continue
        key = Path(v).resolve()
        if key in seen:
            raise ErrplanError(f"{opt} {v}: the same file as {seen[key]}")
        seen[key] = f"{opt} {v}"
    if args.export_scenario and sc.dim == 3 and Path(args.export_scenario).with_suffix(".urdf").resolve() in seen:
        u = Path(args.export_scenario).with_suffix(".urdf")
        raise ErrplanError(f"{seen[u.resolve()]}: the file the corrected URDF of --export-scenario {args.export_scenario} "
                           f"would be written to ({u})")
    check_seed("--seed", args.seed)
    folds = getattr(args, "folds", 5)
    if folds < 2:
        raise ErrplanError(f"--folds {folds}: expected an integer >= 2")
    data = read_measured_csv(args.data, sc)
    val = read_measured_csv(args.validate, sc) if args.validate else None
    prog = Progress("calibrate", quiet=args.quiet)
    prog.quiet = prog.quiet or not prog.tty  # progress only on a terminal: an error stays the one line on stderr
    effects = getattr(args, "effects", None)
    effects = [e.strip() for e in effects.split(",")] if effects is not None else None
    report = api.calibrate(sc, data, validate=val, seed=args.seed, folds=folds, progress=prog, effects=effects)
    prog.done()
    toml_text, extra = corrected_files(sc, report, args.export_scenario) if args.export_scenario else (None, {})
    bench_text = bench_files(sc, report) if bench_path else None
    pred_text = predictions_csv(sc, report, val if val is not None else data) if predictions else None
    if sc.queries and not getattr(args, "no_task", False):
        from ..calibration.task import calibration_task

        report.task = calibration_task(sc, report)
    report.exported = ([str(args.export_scenario)] + [str(k) for k in extra] if toml_text is not None else []) + (
        [str(bench_path)] if bench_text is not None else [])
    js = report.to_json()
    if args.record:
        from ..recording import record_calibration

        record_calibration(report, args.record, sc)
    if args.json:
        write_json(args.json, js)
    if toml_text is not None:
        for path, text in extra.items():  # the corrected URDF first: the scenario names it
            write_atomic(path, text)
        write_atomic(args.export_scenario, toml_text)
    if bench_text is not None:
        write_atomic(bench_path, bench_text)
    if pred_text is not None:
        write_atomic(predictions, pred_text)
    print(report.text())
    if report.task:
        from ..calibration.task import task_table

        print()
        print(task_table(report.task))
    written = [x for x in (args.json, args.record, args.export_scenario, *extra, bench_path, predictions) if x]
    if written:
        print("wrote " + ", ".join(written))
    return 0
