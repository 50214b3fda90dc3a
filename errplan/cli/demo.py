"""``errplan demo``: the bundled scenarios end to end.

For each scenario: fields (worst case over the error set, with rho*) -> plan every query (OMPL) ->
certified gains (casadi) -> quasi-static simulation under the truth and every corner of the error
box -> one rerun recording and a summary table (planned vs direct).

Without ``--scenario`` the demo runs P1's planar Phantom (``beasley2004_bounded.toml``, recorded to
``--record``, default ``errplan-demo.rrd``) and then the spatial PHANToM 1.5 on its URDF
(``phantom15_spatial.toml``, recorded beside it as ``<stem>-3d.rrd``), then the bundled abdomen
(``abdomen.toml``: the PHANToM among mesh organs, a vessel and the body wall; at its own 8 mm
grid, recorded as ``<stem>-abdomen.rrd``). The PHANToM's spatial fields are
computed at ``SPATIAL_RESOLUTION`` over the scenario's task region (its own 4 mm grid takes about a
minute of CPU) with the metrics the planner and the recording use (G_norm, phi_hat_max, rho_star).
With ``--scenario F`` only that scenario runs (planar or spatial), recorded to ``--record``.
"""
from __future__ import annotations

import time
from functools import partial
from pathlib import Path

from ..errors import ErrplanError
from ..report import Progress, write_json
from . import warmup

SCENARIOS = Path(__file__).resolve().parents[2] / "scenarios"
BUNDLED = SCENARIOS / "beasley2004_bounded.toml"
BUNDLED_SPATIAL = SCENARIOS / "phantom15_spatial.toml"
BUNDLED_ANATOMY = SCENARIOS / "abdomen.toml"
#: grid spacing (m) of the demo's spatial fields (the scenario's [fields] resolution is 4 mm)
SPATIAL_RESOLUTION = 0.010
SPATIAL_METRICS = ("G_norm", "phi_hat_max", "rho_star")


def bundled_scenario() -> Path:
    if not BUNDLED.exists():
        raise ErrplanError(f"{BUNDLED}: the bundled demo scenario is missing (pass --scenario FILE)")
    return BUNDLED


def spatial_record_path(rec: Path, tag: str = "3d") -> Path:
    """Where the spatial recording goes beside the planar one: ``<stem>-3d<suffix>`` (``-abdomen`` for the
    anatomy scenario)."""
    return rec.with_name(f"{rec.stem}-{tag}{rec.suffix or '.rrd'}")


def run_scenario(sc, path: Path, rec: Path | None, quiet: bool, *, spatial_demo: bool | str = False) -> dict:
    """Fields, plan, gains, simulation and recording of one scenario; prints its table and times.
    Returns the JSON document of the run (``queries`` with the plan JSON keys, ``timing_s``)."""
    from ..fields import compute_fields
    from ..pipeline import run_pipeline, summary_table
    from ..planning import plan_scenario

    t0 = time.perf_counter()
    if not sc.queries:
        raise ErrplanError(f"{path}: the scenario has no [[query]] to plan")
    prog = Progress("fields", quiet=quiet)
    # a first run compiles ahead in the background (errplan.cli.warmup); the spatial demo's metrics have no
    # exact |phi_max|, its search is compiled without it
    warmup.wait(f"fields{sc.dim}{'g' if spatial_demo else ''}")
    if spatial_demo:  # True: the PHANToM at SPATIAL_RESOLUTION; "own": the abdomen at its own resolution
        res = SPATIAL_RESOLUTION if spatial_demo is True else None
        mf = compute_fields(sc, res, metrics=SPATIAL_METRICS, progress=prog, workers=None)
    else:
        mf = compute_fields(sc, rho_star=True, progress=prog)
    prog.done()
    t_fields = time.perf_counter() - t0
    t1 = time.perf_counter()
    warmup.wait(f"plan{sc.dim}")
    with warmup.paused():  # the planner has a time budget: it runs alone, as in a later run
        plans = plan_scenario(sc, mf).queries
    t_plan = time.perf_counter() - t1
    t2 = time.perf_counter()
    prog = Progress("gains+simulation", quiet=quiet)
    warmup.wait(f"gains{sc.dim}")
    res = run_pipeline(sc, plans, mf, record=str(rec) if rec else None, progress=prog)
    prog.done()
    t_pipe = time.perf_counter() - t2
    total = time.perf_counter() - t0
    res_note = f" (spatial fields at {SPATIAL_RESOLUTION * 1000:g} mm)" if spatial_demo is True else ""
    print(summary_table(res["runs"], f"errplan demo: {sc.name} ({path.name}){res_note}"))
    print(f"time: fields {t_fields:.1f} s, planning {t_plan:.1f} s, gains + simulation"
          f"{' + recording' if rec else ''} {t_pipe:.1f} s, total {total:.1f} s")
    if rec:
        print(f"recording: {rec}  (open it with `errplan view {rec}`)")
    return {"scenario": sc.name, "dim": sc.dim, "queries": res["queries"],
            "timing_s": {"fields": t_fields, "plan": t_plan, "gains_simulation_record": t_pipe, "total": total}}


def _load_when_compiled(part: str, path: Path):
    """A bundled scenario, loaded once a first run's warm-up has compiled ``part``: its load calls those
    kernels (the arm's kinematics; the anatomy's clearances for its checks), and compiling them here too
    would only duplicate the work."""
    from ..api import load_scenario

    warmup.wait(part)
    return load_scenario(path)


def run(args) -> int:
    from ..inputs import check_output
    from ..api import load_scenario

    t0 = time.perf_counter()
    quiet = getattr(args, "quiet", False)
    if args.scenario:
        path = Path(args.scenario)
        sc = load_scenario(path)
        jobs = [(lambda: sc, path, False)]
        # a first run compiles the planner's (and in 3-D the gains') kernels meanwhile
        if sc.dim == 3:
            warmup.start(("plan3", "gains3") + (("anatomy",) if sc.anatomy is not None else ()))
        else:
            warmup.start(("plan2",))
    else:
        path = bundled_scenario()
        if not BUNDLED_SPATIAL.exists():
            raise ErrplanError(f"{BUNDLED_SPATIAL}: the bundled spatial demo scenario is missing (pass --scenario FILE)")
        # A first run: this process compiles the planar kernels, runs the planar part, then
        # loads the spatial scenario (compiling the reachability map's build, building the map) and runs
        # it; meanwhile a second process compiles what the later parts need, in the order they need it
        # (errplan.cli.warmup): the arm's kinematics first (a few seconds, so that this process finds
        # them), the spatial search (the longest, ready about when this process has built the map), the
        # planner's and the gains' kernels in the order a scenario's steps call them, the anatomy's. The
        # bundled scenarios are loaded when their turn comes.
        warmup.start(("plan2", "arm", "fields3g", "plan3", "gains3", "anatomy"))
        sc = load_scenario(path)
        jobs = [(lambda: sc, path, False),
                (partial(_load_when_compiled, "arm", BUNDLED_SPATIAL), BUNDLED_SPATIAL, True)]
        if BUNDLED_ANATOMY.exists():
            jobs.append((partial(_load_when_compiled, "anatomy", BUNDLED_ANATOMY), BUNDLED_ANATOMY, "own"))
    rec = check_output("--record", args.record)
    check_output("--json", args.json)
    recs = [rec] + [spatial_record_path(rec, tag) if rec else None for tag in ("3d", "abdomen")[:len(jobs) - 1]]
    for r in recs[1:]:
        if r is not None:
            check_output("--record", str(r))
    docs = []
    for i, ((load, p, spatial_demo), r) in enumerate(zip(jobs, recs)):
        if i:
            print()
        docs.append(run_scenario(load(), p, r, quiet, spatial_demo=spatial_demo))
    doc = dict(docs[0])
    if len(docs) > 1:
        doc["spatial"] = docs[1]
    if len(docs) > 2:
        doc["anatomy"] = docs[2]
    doc["total_s"] = time.perf_counter() - t0
    if args.json:
        write_json(args.json, doc)
    if len(docs) > 1:
        print(f"\ndemo total: {doc['total_s']:.1f} s")
    return 0
