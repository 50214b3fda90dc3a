"""``errplan calibrate SCENARIO DATA.csv [--validate VAL.csv] [--json F] [--record F.rrd]
[--export-scenario F.toml] [--predictions PRED.csv] [--seed N] [--folds K]``.

Close the loop: residual of the declared model, noise floor, candidate effects fitted and
selected, error before -> after (see :mod:`errplan.calibration`). Every input is checked before
anything is written; outputs are written atomically at the end.
"""
from __future__ import annotations

from ..errors import ErrplanError
from ..report import Progress, write_atomic, write_json


def run(args) -> int:
    from .. import api
    from ..calibration.export import corrected_files, predictions_csv
    from ..experiment import read_measured_csv

    from ..inputs import check_output
    from . import check_seed

    sc = api.load_arm(args.scenario, args.arm)
    predictions = getattr(args, "predictions", None)
    for opt, v in (("--json", args.json), ("--record", args.record), ("--export-scenario", args.export_scenario),
                   ("--predictions", predictions)):
        check_output(opt, v)
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
    pred_text = predictions_csv(sc, report, val if val is not None else data) if predictions else None
    js = report.to_json()
    js["exported"] = ([str(args.export_scenario)] + [str(k) for k in extra]) if toml_text is not None else []
    if args.record:
        from ..recording import record_calibration

        record_calibration(report, args.record, sc)
    if args.json:
        write_json(args.json, js)
    if toml_text is not None:
        for path, text in extra.items():  # the corrected URDF first: the scenario names it
            write_atomic(path, text)
        write_atomic(args.export_scenario, toml_text)
    if pred_text is not None:
        write_atomic(predictions, pred_text)
    print(report.text())
    written = [x for x in (args.json, args.record, args.export_scenario, *extra, predictions) if x]
    if written:
        print("wrote " + ", ".join(written))
    return 0
