"""``errplan tolerance SCENARIO [--json F] [--workers N] [--scheduler ADDRESS] [--record F.rrd] [--top N]
[--arm NAME] [--export-scenario OUT.toml]``: answer every ``[[tolerance]]`` query of a scenario (planar and
spatial; a setup's ``triad_placement`` and ``setup_placement`` queries without ``--arm``; with
``--export-scenario``, the scenario with the best setup's bases and port estimates written for
``errplan plan``).

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
from . import warmup


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


def triad_table(r, top: int = 5) -> str:
    """The best triad and the next ones of a ``triad_placement`` result: ports, score, per-criterion figures."""
    d = r.data
    names = d["instruments"]
    arms = d.get("arm_clearance") is not None  # arm checks on: a column of their figure
    rows = []
    for rank, t in enumerate([d["best"]] + d["ranked"][:max(top - 1, 0)], 1):
        ma = t["manipulation_angle"]
        sc_ = t["shaft_clearance_min"]
        rows.append([rank, _mm(t["ports"][names[0]]), _mm(t["ports"][names[1]]), _mm(t["ports"]["endoscope"]),
                     t["score"], 100 * t["coverage"][names[0]], 100 * t["coverage"][names[1]],
                     100 * t["coverage"]["both"], 100 * t["visible"], math.degrees(ma["mean"]),
                     math.degrees(ma["min"]), math.degrees(t["azimuth_difference_mean"]),
                     1000 * t["port_spacing_min"], math.nan if sc_ is None else 1000 * sc_]
                    + ([math.nan if t["arm_clearance_min"] is None else 1000 * t["arm_clearance_min"]] if arms else []))
    s = d["search"]
    title = (f"{r.name}: {len(d['candidates'][names[0]])} x {len(d['candidates'][names[1]])} x "
             f"{len(d['candidates']['endoscope'])} candidate ports ({names[0]} x {names[1]} x endoscope), "
             f"{d['targets']} targets; score S lower is better")
    lines = [format_table(["rank", f"{names[0]} (mm)", f"{names[1]} (mm)", "endoscope (mm)", "S",
                           f"cov {names[0]} %", f"cov {names[1]} %", "both %", "visible %", "m mean (deg)",
                           "m min (deg)", "|a1-a2| (deg)", "spacing (mm)", "shaft clear (mm)"] + (["arm clear (mm)"] if arms else []), rows, title)]
    rej = d["rejected"]
    lines.append(f"search: {s['method']}, {s['evaluated']:,} of {s['triads']:,} triads evaluated "
                 f"({100 * s['pruned_share']:.1f}% pruned by the lower bound); rejected among them: port spacing "
                 f"{rej['port_spacing']:,}, shaft clearance {rej['shaft_clearance']:,}; arm checks: {d['arm_checks']}")
    return "\n".join(lines)


def setup_table(r, top: int = 5) -> str:
    """A ``setup_placement`` result: the triad's table, then each ranked setup's bases and its smallest
    link-to-body clearance."""
    d = r.data
    names = d["instruments"]
    rows = []
    for rank, t in enumerate([d["best"]] + d["ranked"][:max(top - 1, 0)], 1):
        pc = t.get("patient_clearance_min")
        rows.append([rank] + [f"{_mm(t['bases'][n]['position'])} {[round(v, 3) for v in t['bases'][n]['rpy']]}"
                              for n in names]
                    + [t["score"], math.nan if pc is None else 1000 * pc])
    title = (f"{r.name}: {len(d['bases'][names[0]])} x {len(d['bases'][names[1]])} base candidates "
             f"({names[0]} x {names[1]}); ties: {d['search']['tie_break']}")
    rej = d["rejected"]
    pc = d.get("patient_clearance")
    note = ("patient checks: off" if pc is None else
            f"patient checks: on (patient_clearance {pc:g} m, {rej['patient_clearance']:,} setups rejected)")
    if d["search"]["ties"] > 1:
        note += f"; {d['search']['ties']} setups tied with the best score"
    lines = [triad_table(r, top),
             format_table(["rank", f"{names[0]} base (mm, rpy)", f"{names[1]} base (mm, rpy)", "S",
                           "patient clear (mm)"], rows, title), note]
    return "\n".join(lines)


def _warm_up(args) -> tuple[str, ...]:
    """A first run of a spatial scenario: the fields' search without the exact |phi_max| (what the
    queries' fields and worst cases run; a setup's triad placement its lanes too: its error sets have no
    load) compiled in a second process while this one loads and checks the arms (their reachability
    maps, the anatomy's clearances). The parts started (none with ``--scheduler``, in the plane or where
    the fields take the numpy path)."""
    from ..scenario import read_setup

    st = read_setup(args.scenario)
    first = st.arm(args.arm) if args.arm is not None and args.arm in st.arm_names else st.arms[0]
    part = warmup.fields_part(first, False) if first.dim == 3 and args.scheduler is None else None
    if not part:
        return ()
    parts = (part, "lanes3") if st.several and args.arm is None else (part,)
    warmup.start(parts)
    return parts


def _run_setup(st, args, parts: tuple[str, ...] = ()) -> int:
    from ..inputs import check_output
    from ..tolerance.run import run_setup_query

    if not st.triads:
        raise ErrplanError(f"{st.source}: no triad_placement or setup_placement query: name an arm with --arm NAME "
                           "for its [[tolerance]] queries")
    check_output("--json", args.json)
    check_output("--record", args.record)
    export = getattr(args, "export_scenario", None)
    if export:
        from ..tolerance.setup import check_export

        check_output("--export-scenario", export)
        check_export(export, st.triads)
    prog = Progress("tolerance", quiet=args.quiet)
    prog.quiet = prog.quiet or not prog.tty
    results = []
    with prog.cleared_on_error():
        for p in parts:
            warmup.wait(p)
        for tol in st.triads:
            results.append(run_setup_query(st, tol, prog, workers=args.workers, scheduler=args.scheduler))
    prog.done()
    rows = [r.summary_row() + [r.seconds] for r in results]
    print(format_table(["query", "kind", "answer", "ports", "note", "s"], rows,
                       f"setup queries of {st.name}"))
    for r in results:
        print()
        print(setup_table(r, args.top) if r.kind == "setup_placement" else triad_table(r, args.top))
    if args.record:  # first: the recording is the output most likely to fail, written atomically
        from ..recording.setup import record_triad

        record_triad(args.record, st, results)
    if export:
        from ..calibration.export import to_toml
        from ..report import write_atomic
        from ..scenario import read_document
        from ..tolerance.setup import check_export, export_header, exported_document

        r = check_export(export, results)
        write_atomic(export, to_toml(exported_document(read_document(st.source), st.source, r.data),
                                     export_header(r.name, r.data)))
    if args.json:
        write_json(args.json, {"scenario": st.name, "source": st.source,
                               "tolerances": [r.to_dict() for r in results]})
    if args.record:
        print(f"recording: {args.record}  (open it with `errplan view {args.record}`)")
    if export:
        print(f"scenario: {export}  (the best setup's bases and ports; plan it with `errplan plan {export}`)")
    return 0


def run(args) -> int:
    from ..inputs import check_output
    from .. import api
    from ..tolerance import check_sizes

    if args.workers is not None and args.workers < 1:
        raise ErrplanError(f"--workers {args.workers}: expected a number of worker processes >= 1")
    if args.top < 0:
        raise ErrplanError(f"--top {args.top}: expected a number of candidates >= 0")
    parts = _warm_up(args)
    st = api.load_setup(args.scenario)
    if st.several and args.arm is None:  # the setup's own queries (triad and setup placement)
        return _run_setup(st, args, parts)
    if getattr(args, "export_scenario", None):
        raise ErrplanError(f"--export-scenario {args.export_scenario}: expected a scenario with several arms and a "
                           "setup_placement query (without --arm)")
    sc = st.arm(args.arm)
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
        for p in parts:
            warmup.wait(p)
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
