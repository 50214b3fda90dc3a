"""``errplan tolerance SCENARIO [--json F]``: answer every ``[[tolerance]]`` query of a scenario.

Prints one table row per query (the answer, where it binds) and writes
``{"scenario", "tolerances": [{"name", "kind", ...}]}`` (docs/interfaces.md "tolerance JSON",
notes/readme_tolerance.md for every key). Nothing is written when a query fails.
"""
from __future__ import annotations

from ..report import Progress, format_table, write_json


def run(args) -> int:
    from ..inputs import check_output
    from ..scenario import load_scenario
    from ..tolerance import run_all

    sc = load_scenario(args.scenario)
    check_output("--json", args.json)
    prog = Progress("tolerance", quiet=args.quiet)
    prog.quiet = prog.quiet or not prog.tty  # progress only on a terminal: an error stays the one line on stderr
    results = run_all(sc, progress=prog)
    prog.done()
    rows = [r.summary_row() + [r.seconds] for r in results]
    print(format_table(["query", "kind", "tolerable", "binding at / best", "note", "s"], rows,
                       f"tolerance-design queries of {sc.name}"))
    for r in results:
        if r.kind in ("port", "tip_load") and not r.data.get("converged", True):
            print(f"warning: {r.name}: halving the grid spacing still changed the answer by "
                  f"{100 * r.data['refinement_change']:.2f}% (> 1%)")
    if args.json:
        write_json(args.json, {"scenario": sc.name, "source": sc.source,
                               "tolerances": [r.to_dict() for r in results]})
    return 0
