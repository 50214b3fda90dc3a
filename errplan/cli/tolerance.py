"""``errplan tolerance SCENARIO [--json F] [--workers N] [--scheduler ADDRESS] [--record F.rrd] [--top N]``:
answer every ``[[tolerance]]`` query of a scenario (planar and spatial).

Prints one table row per query (the answer, where it binds or the best port) and, per
``port_placement`` query, its top candidates; writes ``{"scenario", "source", "tolerances":
[{"name", "kind", ...}]}`` (docs/interfaces.md "tolerance JSON", docs/tolerance.md for every key)
and, with ``--record``, a rerun recording of the placement queries. ``--workers`` and
``--scheduler`` say where the placement candidates run, as for ``errplan fields``. Every option and
every query's sizes are checked before the first query runs; nothing is written when one fails.
"""
from __future__ import annotations

import math

from ..errors import ErrplanError
from ..report import Progress, format_table, write_json


def _mm(p) -> str:
    return "[" + ", ".join(f"{1000 * float(v):.1f}" for v in p) + "]"


def placement_table(r, top: int = 5) -> str:
    """The top ``top`` candidates of a ``port_placement`` result (and the refined port, if any)."""
    d = r.data
    m = d["region_points"]
    rows = []
    for rank, i in enumerate(d["ranking"][:top], 1):
        c = d["candidates"][i]
        rows.append([rank, _mm(c["port"]), 100 * c["coverage"], f"{c['covered']}/{m}", c["reachable"],
                     c["max_rho_star"] if c["max_rho_star"] is not None else math.nan])
    if "refined" in d:
        f = d["refined"]
        rows.append(["refined", _mm(f["port"]), 100 * f["coverage"], f"{f['covered']}/{m}", f["reachable"],
                     f["max_rho_star"] if f["max_rho_star"] is not None else math.nan])
    grid = d["candidate_grid"]
    where = " on the body wall" if grid.get("body_wall") else ""
    title = (f"{r.name}: {grid['count']} candidate ports{where} at {1000 * grid['spacing']:g} mm, task region of {m} "
             f"points at {1000 * d['region_grid']['resolution']:g} mm; covered = "
             + (d["criterion"] if grid.get("body_wall") else
                f"robustly reachable and rho* <= {1 - d['certify_margin']:g}"))
    lines = [format_table(["rank", "port (mm)", "coverage %", "covered", "reachable", "max rho*"], rows, title)]
    lines.append(f"ties: {d['tie_break']}; {d['seconds_per_candidate']:.3g} s per candidate "
                 f"({grid['count']} in {d['sweep_seconds']:.3g} s)")
    if "refined" in d:
        f = d["refined"]
        lines.append(f"refined: {f['evaluations']} more evaluations, {f['moves']} moves, final step "
                     f"{1000 * f['final_step']:g} mm" + ("" if f["improved"] else " (no neighbour did better)"))
    return "\n".join(lines)


def run(args) -> int:
    from ..inputs import check_output
    from .. import api
    from ..tolerance import check_sizes

    if args.workers is not None and args.workers < 1:
        raise ErrplanError(f"--workers {args.workers}: expected a number of worker processes >= 1")
    if args.top < 0:
        raise ErrplanError(f"--top {args.top}: expected a number of candidates >= 0")
    sc = api.load_scenario(args.scenario)
    check_output("--json", args.json)
    record = None
    if args.record:
        check_output("--record", args.record)
        if not any(t.kind == "port_placement" for t in sc.tolerances):
            raise ErrplanError(f"--record {args.record}: {sc.source} has no port_placement query to record")
        from ..recording import record_placement as record
    check_sizes(sc)
    prog = Progress("tolerance", quiet=args.quiet)
    prog.quiet = prog.quiet or not prog.tty  # progress only on a terminal: an error stays the one line on stderr
    with prog.cleared_on_error():
        results = api.tolerances(sc, progress=prog, workers=args.workers, scheduler=args.scheduler)
    prog.done()
    rows = [r.summary_row() + [r.seconds] for r in results]
    print(format_table(["query", "kind", "tolerable", "binding at / best", "note", "s"], rows,
                       f"tolerance-design queries of {sc.name}"))
    for r in results:
        if r.kind in ("port", "tip_load") and not r.data.get("converged", True):
            print(f"warning: {r.name}: halving the grid spacing still changed the answer by "
                  f"{100 * r.data['refinement_change']:.2f}% (> 1%)")
        if r.kind == "port_placement":
            print()
            print(placement_table(r, args.top))
    if record is not None:  # first: the recording is the output most likely to fail, written atomically
        record(args.record, sc, [r for r in results if r.kind == "port_placement"])
    if args.json:
        write_json(args.json, {"scenario": sc.name, "source": sc.source,
                               "tolerances": [r.to_dict() for r in results]})
    if record is not None:
        print(f"recording: {args.record}  (open it with `errplan view {args.record}`)")
    return 0
