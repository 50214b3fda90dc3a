"""``errplan demo``: the bundled scenarios end to end.

For each scenario: fields (worst case over the error set, with rho*) -> plan every query (OMPL) ->
certified gains (casadi) -> quasi-static simulation under the truth and every corner of the error
box -> one rerun recording and a summary table (planned vs direct).

Without ``--scenario`` the demo runs P1's planar Phantom (``beasley2004_bounded.toml``, recorded to
``--record``, default ``errplan-demo.rrd``) and then the spatial PHANToM 1.5 on its URDF
(``phantom15_spatial.toml``, recorded beside it as ``<stem>-3d.rrd``), then the bundled abdomen
(``abdomen.toml``: the PHANToM among mesh organs, a vessel and the body wall; at its own 8 mm
grid, recorded as ``<stem>-abdomen.rrd``), and last the several-instrument setup
(``abdomen_triad.toml``, :class:`TriadBlock`: its chosen port triad and each arm's queries planned among
the held shafts, recorded as ``<stem>-triad.rrd`` and ``<stem>-triad-plan.rrd``). The PHANToM's spatial fields are
computed at ``SPATIAL_RESOLUTION`` over the scenario's task region (its own 4 mm grid takes about a
minute of CPU) with the metrics the planner and the recording use (G_norm, phi_hat_max, rho_star).
With ``--scenario F`` only that scenario runs (planar or spatial), recorded to ``--record``.
"""
from __future__ import annotations

import contextlib
import json
import os
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

from ..errors import ErrplanError
from ..report import Progress, write_json
from . import warmup

SCENARIOS = Path(__file__).resolve().parents[2] / "scenarios"
BUNDLED = SCENARIOS / "beasley2004_bounded.toml"
BUNDLED_SPATIAL = SCENARIOS / "phantom15_spatial.toml"
BUNDLED_ANATOMY = SCENARIOS / "abdomen.toml"
BUNDLED_TRIAD = SCENARIOS / "abdomen_triad.toml"
#: grid spacing (m) of the demo's spatial fields (the scenario's [fields] resolution is 4 mm)
SPATIAL_RESOLUTION = 0.010
SPATIAL_METRICS = ("G_norm", "phi_hat_max", "rho_star")
#: processes the demo runs its steps in (1: one after another); default: every core
WORKERS_ENV = "ERRPLAN_DEMO_WORKERS"
#: one-process tasks that go on while the demo plans (the rest is paused): one, on the other core. A plan
#: ends at its counted iteration budget (a function of the scenario and the seed), however loaded the
#: machine: the bundled scenarios set no time cap
PLAN_BESIDE = 1
#: a JSON file to write the demo's steps to (scenario, step, start and end s, CPU s): benchmarks/first_run.py
PROFILE_ENV = "ERRPLAN_DEMO_PROFILE"
_STEPS: list[dict] = []


def _cpu() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _own_cpu() -> float:
    t = os.times()
    return t.user + t.system


#: side by side, this process's steps count its own CPU only: the workers' tasks are noted on their own,
#: and a child that ends meanwhile (the first run's warm-up) must not land in whichever step was running
_OWN_ONLY = {"on": False}


@contextlib.contextmanager
def _step(scenario: str, step: str):
    """Note a step of this process (its CPU with that of the worker processes it waited for, or its own
    only when the scenarios run side by side)."""
    clock = _own_cpu if _OWN_ONLY["on"] else _cpu
    c, w = clock(), time.perf_counter()
    try:
        yield
    finally:
        _STEPS.append({"scenario": scenario, "step": step, "process": "main", "start": w,
                       "end": time.perf_counter(), "cpu": clock() - c})


#: the report's name of each noted step (:data:`_STEPS`), in the order the report lists them
_CATEGORY = {"triad": "triad placement", "fields": "fields", "plan": "planning", "queries+record":
             "gains + simulation + recording", "query": "gains + simulation", "record": "recording"}


def cpu_by_step(names) -> dict[str, float]:
    """CPU seconds of the noted steps (:data:`_STEPS`: this process's and its workers') of the scenarios
    called ``names``, per step of the report, and ``total``. A step's CPU is its own process's (with the
    worker processes it waited for): the lines of several scenarios run side by side add up, where their
    wall times would overlap."""
    names = set(names)
    out: dict[str, float] = {}
    for e in _STEPS:
        if e["scenario"] in names:
            k = _CATEGORY.get(e["step"].split(" ")[0], e["step"])
            out[k] = out.get(k, 0.0) + e["cpu"]
    order = list(dict.fromkeys(_CATEGORY.values()))
    res = {k: out[k] for k in order if k in out}
    res.update({k: v for k, v in out.items() if k not in res})
    res["total"] = sum(out.values())
    return res


def _cpu_line(cpu: dict[str, float]) -> str:
    parts = ", ".join(f"{k} {v:.1f} s" for k, v in cpu.items() if k != "total")
    return f"time: CPU {parts}; {cpu['total']:.1f} s in all"


def bundled_scenario() -> Path:
    if not BUNDLED.exists():
        raise ErrplanError(f"{BUNDLED}: the bundled demo scenario is missing (pass --scenario FILE)")
    return BUNDLED


def spatial_record_path(rec: Path, tag: str = "3d") -> Path:
    """Where the spatial recording goes beside the planar one: ``<stem>-3d<suffix>`` (``-abdomen`` for the
    anatomy scenario)."""
    return rec.with_name(f"{rec.stem}-{tag}{rec.suffix or '.rrd'}")


def _fields(sc, spatial_demo: bool | str, progress, workers: int | None = None):
    """The scenario's worst-case fields for the demo: planar with rho* at its own grid; the PHANToM at
    ``SPATIAL_RESOLUTION`` (``spatial_demo`` True), the abdomen at its own grid ("own"), with
    ``SPATIAL_METRICS``, on ``workers`` processes (None: every core; the tiles' results are the same)."""
    from ..fields import compute_fields

    # a first run compiles ahead in the background (errplan.cli.warmup); the spatial demo's metrics have no
    # exact |phi_max|, its search is compiled without it
    warmup.wait(_fields_part(sc, spatial_demo))
    if spatial_demo == "plan":  # an arm of the several-instrument setup: the fields `errplan plan` makes, here
        from ..planning.plan import fields_for_planning

        warmup.wait(f"lanes{sc.dim}")  # their error set has no load: the lanes (the arms' tasks would each compile them)

        return fields_for_planning(sc, progress=progress, workers=1)
    if spatial_demo:  # True: the PHANToM at SPATIAL_RESOLUTION; "own": the abdomen at its own resolution
        res = SPATIAL_RESOLUTION if spatial_demo is True else None
        return compute_fields(sc, res, metrics=SPATIAL_METRICS, progress=progress, workers=workers)
    return compute_fields(sc, rho_star=True, progress=progress)


def _fields_part(sc, spatial_demo) -> str:
    return f"fields{sc.dim}{'g' if spatial_demo else ''}"


def _plans(sc, mf) -> list:
    """Every query planned on ``mf`` (with the warm-up paused, as in a later run: the plan is the same either
    way, its budget is counted, but the planner has a core to itself)."""
    from ..planning import plan_scenario

    warmup.wait(f"plan{sc.dim}")
    with warmup.paused():
        return plan_scenario(sc, mf).queries


def _report(sc, path: Path, rec: Path | None, res: dict, spatial_demo, times: dict) -> tuple[str, dict]:
    """The scenario's printed block (table, times, recording) and its JSON document."""
    from ..pipeline import summary_table

    res_note = f" (spatial fields at {SPATIAL_RESOLUTION * 1000:g} mm)" if spatial_demo is True else ""
    lines = [summary_table(res["runs"], f"errplan demo: {sc.name} ({path.name}){res_note}")]
    if times.get("side_by_side"):  # wall intervals overlap with the other scenarios': CPU only
        lines.append(_cpu_line(times["cpu"]) + " (run side by side with the other scenarios: the demo's wall "
                     "time is on its last line)")
    else:
        lines.append(f"time: wall fields {times['fields']:.1f} s, planning {times['plan']:.1f} s, gains + simulation"
                     f"{' + recording' if rec else ''} {times['gains_simulation_record']:.1f} s, total "
                     f"{times['total']:.1f} s")
        lines.append(_cpu_line(times["cpu"]))
    if rec:
        lines.append(f"recording: {rec}  (open it with `errplan view {rec}`)")
    return "\n".join(lines), {"scenario": sc.name, "dim": sc.dim, "queries": res["queries"], "timing_s": times}


def run_scenario(sc, path: Path, rec: Path | None, quiet: bool, *, spatial_demo: bool | str = False) -> dict:
    """Fields, plan, gains, simulation and recording of one scenario, one step after the other; prints its
    table and times. Returns the JSON document of the run (``queries`` with the plan JSON keys, ``timing_s``)."""
    from ..pipeline import run_pipeline

    t0 = time.perf_counter()
    if not sc.queries:
        raise ErrplanError(f"{path}: the scenario has no [[query]] to plan")
    prog = Progress("fields", quiet=quiet)
    with _step(sc.name, "fields"):
        mf = _fields(sc, spatial_demo, prog)
    prog.done()
    t_fields = time.perf_counter() - t0
    t1 = time.perf_counter()
    with _step(sc.name, "plan"):
        plans = _plans(sc, mf)
    t_plan = time.perf_counter() - t1
    t2 = time.perf_counter()
    prog = Progress("gains+simulation", quiet=quiet)
    warmup.wait(f"gains{sc.dim}")
    with _step(sc.name, "queries+record"):
        res = run_pipeline(sc, plans, mf, record=str(rec) if rec else None, progress=prog)
    prog.done()
    t_pipe = time.perf_counter() - t2
    times = {"fields": t_fields, "plan": t_plan, "gains_simulation_record": t_pipe,
             "total": time.perf_counter() - t0, "cpu": cpu_by_step([sc.name])}
    text, doc = _report(sc, path, rec, res, spatial_demo, times)
    print(text)
    return doc


@dataclass
class DemoJob:
    """One scenario of the demo: its file, how its fields are computed (``spatial_demo``: False planar,
    True the PHANToM at ``SPATIAL_RESOLUTION``, "own" at the scenario's grid), the warm-up part its load
    waits for (a first run: its load calls those kernels, and compiling them here too would only duplicate
    the work), its expected share of the work (``weight``: the heaviest chain starts first when the
    scenarios run side by side) and where it is recorded."""

    path: Path
    spatial_demo: bool | str = False
    load_part: str | None = None
    weight: float = 1.0
    record: Path | None = None
    #: the order of its queries among the others' when side by side (the longest first; default ``weight``)
    query_weight: float | None = None
    sc: object = None
    #: an arm of the several-instrument setup (:class:`TriadBlock`): no block of its own
    hidden: bool = False

    def load(self):
        from ..api import load_scenario
        from ..models import arm_model

        if self.sc is None:
            if self.load_part:
                warmup.wait(self.load_part)
            self.sc = arm_model(load_scenario(self.path))  # built once: every step below takes it
        if not self.sc.queries:
            raise ErrplanError(f"{self.path}: the scenario has no [[query]] to plan")
        return self.sc


@dataclass
class TriadBlock:
    """The several-instrument setup of the demo (``abdomen_triad.toml``): its ``triad_placement`` queries
    (:func:`errplan.tolerance.run.run_setup_query`, one process) and each arm's queries planned among the
    held shafts as ``errplan plan`` plans them (:meth:`errplan.scenario.Setup.moving`: the arm's fields as
    :func:`errplan.planning.plan.fields_for_planning` makes them, its plan, gains and replays), one short
    block (:func:`_triad_report`) and two recordings: ``record`` (the chosen triad,
    :func:`errplan.recording.setup.record_triad`) and ``<stem>-plan`` beside it (the arms' planned motions,
    :func:`errplan.recording.setup.record_setup_plan`). The arms are :class:`DemoJob` s with ``hidden``."""

    path: Path
    record: Path | None = None
    st: object = None
    #: (arm name, its DemoJob) of every arm with queries
    arms: list = field(default_factory=list)

    def load(self):
        from ..api import load_setup

        if self.st is None:
            st = load_setup(self.path)
            if not st.several or not st.triads:
                raise ErrplanError(f"{self.path}: the demo's setup needs several [[arm]] tables and a "
                                   "triad_placement [[tolerance]] query")
            self.st = st
            moving = [(n, st.moving(n)) for n in st.arm_names]
            self.arms = [(n, DemoJob(self.path, "plan", "anatomy", weight=0.5, sc=sc, hidden=True))
                         for n, sc in moving if sc.queries]
        return self.st

    def plan_record(self) -> Path | None:
        return None if self.record is None else self.record.with_name(f"{self.record.stem}-plan{self.record.suffix}")


def _triad_task(st) -> list:
    """The setup's ``triad_placement`` results, one process."""
    from ..tolerance.run import run_setup_query

    return [run_setup_query(st, tol, workers=1) for tol in st.triads]


def _triad_report(tb: TriadBlock, results: list, arm_runs: list, times: dict) -> tuple[str, dict]:
    """The setup's printed block and JSON document: the chosen triad of each ``triad_placement`` query
    (:func:`errplan.cli.tolerance.triad_table`, its best row) and per planned query its arm, the smallest
    distance of its shaft to the held shafts, the share the endoscope sees
    (:func:`errplan.planning.setup_checks.path_figures`), whether its gains are certified and its replays
    converge. ``arm_runs``: (arm name, plans, runs) per arm. Writes the recordings."""
    from ..planning.setup_checks import path_figures
    from ..report import format_table
    from .tolerance import triad_table

    st = tb.st
    lines = [f"errplan demo: {st.name} ({tb.path.name}): the chosen port triad, then every query planned among "
             "the held shafts"]
    for r in results:
        lines.append(triad_table(r, 1))
    rows, qdocs = [], []
    for n, plans, runs in arm_runs:
        for qp, run in zip(plans, runs):
            fig = path_figures(st, n, qp.planned.path)
            ms, vis = fig["min_shaft_clearance"], fig["visible"]
            reps = run.corner_planned
            cost = qp.planned.cost
            rows.append([run.name, n, float("nan") if cost is None else float(cost), 1000 * float(qp.planned.length),
                         float("nan") if ms is None else 1000 * ms, float("nan") if vis is None else 100 * vis,
                         "yes" if run.schedule.certified else "NO", "yes" if run.sim_planned.sim.converged else "NO",
                         f"{sum(x.sim.converged for x in reps)}/{len(reps)}" if reps else "-"])
            qdocs.append({"name": run.name, **fig, "certified": bool(run.schedule.certified),
                          "converged": bool(run.sim_planned.sim.converged)})
    lines.append(format_table(["query", "arm", "cost (m)", "length (mm)", "min shaft clearance (mm)", "visible %",
                               "certified", "converged", "corners converged"], rows,
                              f"planned paths of {st.name} (required shaft clearance "
                              f"{st.shaft_clearance * 1000:g} mm)"))
    if times.get("side_by_side"):
        lines.append(_cpu_line(times["cpu"]) + " (the placement and the arms run side by side with the other "
                     "scenarios: the demo's wall time is on its last line)")
    else:
        lines.append(f"time: wall triad placement {times['triad']:.1f} s, arms' fields + plans + gains + simulation "
                     f"{times['arms']:.1f} s, total {times['total']:.1f} s")
        lines.append(_cpu_line(times["cpu"]))
    if tb.record:
        from ..recording.setup import record_setup_plan, record_triad
        from types import SimpleNamespace

        record_triad(tb.record, st, results)
        pr = tb.plan_record()
        record_setup_plan(pr, st, [(n, None, SimpleNamespace(queries=plans)) for n, plans, _ in arm_runs])
        lines.append(f"recording: {tb.record} (triad) and {pr} (planned motions)  (open them with `errplan view`)")
    doc = {"scenario": st.name, "triads": [{"name": r.name, "best": r.data["best"]} for r in results],
           "queries": qdocs, "timing_s": times}
    return "\n".join(lines), doc


def _arm_run(job: DemoJob, quiet: bool) -> tuple[list, list]:
    """An arm of the setup one step after another: fields, plan, gains and replays; (plans, runs)."""
    from ..pipeline import run_pipeline

    sc = job.load()
    with _step(sc.name, "fields"):
        mf = _fields(sc, job.spatial_demo, Progress(f"fields ({sc.name})", quiet=quiet))
    with _step(sc.name, "plan"):
        plans = _plans(sc, mf)
    warmup.wait(f"gains{sc.dim}")
    with _step(sc.name, "queries+record"):
        res = run_pipeline(sc, plans, mf)
    return plans, res["runs"]


def _run_triad(tb: TriadBlock, quiet: bool) -> dict:
    """The setup's block one step after another (prints it)."""
    t0 = time.perf_counter()
    with _step(tb.st.name, "triad"):
        results = _triad_task(tb.st)
    t1 = time.perf_counter()
    arm_runs = [(n, *_arm_run(job, quiet)) for n, job in tb.arms]
    t2 = time.perf_counter()
    times = {"triad": t1 - t0, "arms": t2 - t1, "total": t2 - t0,
             "cpu": cpu_by_step([tb.st.name] + [job.sc.name for _, job in tb.arms])}
    with _step(tb.st.name, "record"):
        text, doc = _triad_report(tb, results, arm_runs, times)
    print(text)
    return doc


def demo_workers() -> int:
    """Processes the demo runs its steps in: ``ERRPLAN_DEMO_WORKERS`` (1: one step after another, in this
    process), else every core this process may use."""
    from ..cluster import default_workers

    v = os.environ.get(WORKERS_ENV, "").strip()
    if not v:
        return default_workers()
    try:
        n = int(v)
    except ValueError:
        n = 0
    if n < 1:
        raise ErrplanError(f"{WORKERS_ENV} = {v!r}: expected a number of processes >= 1")
    return n


def run_jobs(jobs: list[DemoJob], quiet: bool, workers: int = 1, triad: TriadBlock | None = None) -> list[dict]:
    """Every scenario of ``jobs``, its block printed in the jobs' order (a blank line between blocks), then
    the several-instrument setup's block (``triad``, optional); returns their JSON documents (the setup's
    last). ``workers`` 1: one scenario after the other in this process (:func:`run_scenario`,
    :func:`_run_triad`); more: side by side (:func:`_run_side_by_side`), the same blocks."""
    if workers <= 1:
        docs = []
        for i, job in enumerate(jobs):
            if i:
                print()
            docs.append(run_scenario(job.load(), job.path, job.record, quiet, spatial_demo=job.spatial_demo))
        if triad is not None:
            triad.load()
            if jobs:
                print()
            docs.append(_run_triad(triad, quiet))
        return docs
    return _run_side_by_side(jobs, quiet, workers, triad)


def _fields_task(sc, spatial_demo, quiet: bool):
    """A scenario's fields in a worker process, its tiles one after another (one process: the other
    core has the demo's other steps)."""
    prog = Progress(f"fields ({sc.name})", quiet=quiet)
    mf = _fields(sc, spatial_demo, prog, workers=1)
    prog.done()
    return mf


def _run_side_by_side(jobs: list[DemoJob], quiet: bool, slots: int, triad: TriadBlock | None = None) -> list[dict]:
    """The scenarios' steps spread over ``slots`` worker processes (:class:`errplan.cluster.ForkedTasks`,
    forked: each step has the models and kernels this process holds), with the same results and the same
    printed blocks, in the same order, as :func:`run_scenario` one after the other.

    Each scenario's fields are one task (the spatial fields with tile workers of their own); its plan
    runs here with every task paused (``PLAN_BESIDE``: the planner gets a core of its own; its counted budget
    makes the plan the same as one step after another); then each query's gains, simulation and corner
    replays (:func:`errplan.pipeline.run_query`) is a task; its recording and its block are made here
    once all its queries are back. Fields first (the heaviest scenario's first, or with a first run's
    warm-up the jobs' order, the order the warm-up compiles in), then the queries, the heaviest
    scenario's first; a step whose kernels the warm-up still compiles waits for them. The setup
    (``triad``): its triad placement is one task among the fields, each of its arms a scenario without a
    block of its own; its block comes last, once the placement and every arm are back.
    """
    from ..cluster import ForkedTasks
    from ..pipeline import finish_pipeline, query_jobs, run_query
    from ..gains import options_from_scenario

    n_shown = len(jobs)
    tstate = {"t0": None, "results": None, "text": None, "doc": None}
    arm_idx: list[int] = []
    if triad is not None:
        triad.load()
        jobs = list(jobs)
        arm_idx = list(range(len(jobs), len(jobs) + len(triad.arms)))
        jobs.extend(job for _, job in triad.arms)
    n = len(jobs)
    # the setup's triad placement: unit -1 (a task among the fields), weighed between the planar and the
    # spatial scenario (a few seconds of one process)
    units = list(range(n)) + ([-1] if triad is not None else [])
    weight = {i: (jobs[i].weight if i >= 0 else 1.5) for i in units}
    order = units if warmup.active() else sorted(units, key=lambda i: -weight[i])
    rank = {i: r for r, i in enumerate(order)}
    qorder = sorted(range(n), key=lambda i: -(jobs[i].weight if jobs[i].query_weight is None else jobs[i].query_weight))
    qrank = {i: r for r, i in enumerate(qorder)}
    state = [{"runs": None, "text": None, "doc": None} for _ in jobs]
    pending: list[tuple] = [(0, rank[i], 0, i) for i in order]  # (kind 0 fields / 1 query, rank, query, job)
    tasks = ForkedTasks(slots)
    printed = 0
    noted = [0]
    _OWN_ONLY["on"] = True

    def note_workers() -> None:
        """The workers' finished tasks into :data:`_STEPS` (their CPU for the blocks' lines)."""
        for e in tasks.log[noted[0]:]:
            kind, i, q = e["key"]
            _STEPS.append({"scenario": jobs[i].sc.name if i >= 0 else triad.st.name,
                           "step": "triad" if i < 0 else "fields" if kind == 0 else f"query {q}",
                           "process": "worker", "start": e["start"], "end": e["end"], "cpu": e["cpu"]})
        noted[0] = len(tasks.log)

    def startable(item) -> bool:
        kind, _, _, i = item
        if kind:
            return True
        if i < 0:  # the triad placement: the anatomy's clearances, each candidate's fields (no load: lanes)
            return warmup.ready("anatomy") and warmup.ready("lanes3")
        job = jobs[i]
        if job.sc is None and job.load_part and not warmup.ready(job.load_part):
            return False
        sc = job.load()
        return warmup.ready(_fields_part(sc, job.spatial_demo)) and (
            job.spatial_demo != "plan" or warmup.ready(f"lanes{sc.dim}"))

    def on_fields(i: int, mf) -> None:
        job, s = jobs[i], state[i]
        sc = job.sc
        s["mf"], s["t_fields"] = mf, time.perf_counter() - s["t0"]
        t1 = time.perf_counter()
        with tasks.limited(PLAN_BESIDE), _step(sc.name, "plan"):
            s["plans"] = _plans(sc, mf)
        s["t_plan_end"] = time.perf_counter()
        s["t_plan"] = s["t_plan_end"] - t1
        warmup.wait(f"gains{sc.dim}")
        if sc.dim == 3:  # what every query calls, loaded once here rather than in each worker
            warmup.load_here(("fields3g", "gains3"))
        s["model"], s["qjs"] = query_jobs(sc, s["plans"])
        s["opts"] = options_from_scenario(sc)
        s["runs"] = [None] * len(s["qjs"])
        s["prog"] = Progress(f"gains+simulation ({sc.name})", quiet=quiet)
        pending.extend((1, qrank[i], q, i) for q in range(len(s["qjs"])))

    def on_query(i: int, q: int, run) -> None:
        job, s = jobs[i], state[i]
        s["runs"][q] = run
        left = sum(r is None for r in s["runs"])
        s["prog"](1.0 - left / len(s["runs"]), f"{run.name} done")
        if left:
            return
        if job.hidden:  # an arm of the setup: its figures go into the setup's block
            s["prog"].done()
            s["text"], s["end"] = "", time.perf_counter()
            return
        with _step(job.sc.name, "record"):
            res = finish_pipeline(job.sc, s["plans"], s["runs"], s["mf"],
                                  record=str(job.record) if job.record else None)
        s["prog"].done()
        end = time.perf_counter()
        note_workers()
        times = {"fields": s["t_fields"], "plan": s["t_plan"], "gains_simulation_record": end - s["t_plan_end"],
                 "total": end - s["t0"], "side_by_side": True, "cpu": cpu_by_step([job.sc.name])}
        s["text"], s["doc"] = _report(job.sc, job.path, job.record, res, job.spatial_demo, times)

    def triad_block() -> None:
        if tstate["results"] is None or any(state[j]["text"] is None for j in arm_idx):
            return
        t1 = min(state[j]["t0"] for j in arm_idx) if arm_idx else tstate["t_end"]
        end = time.perf_counter()
        note_workers()
        times = {"triad": tstate["t_end"] - tstate["t0"], "arms": max([state[j]["end"] for j in arm_idx] or [t1]) - t1,
                 "total": end - min(t1, tstate["t0"]), "side_by_side": True,
                 "cpu": cpu_by_step([triad.st.name] + [jobs[j].sc.name for j in arm_idx])}
        with _step(triad.st.name, "record"):
            tstate["text"], tstate["doc"] = _triad_report(
                triad, tstate["results"], [(nm, state[j]["plans"], state[j]["runs"])
                                           for (nm, _), j in zip(triad.arms, arm_idx)], times)

    try:
        while printed < n_shown or (triad is not None and tstate["doc"] is None):
            pending.sort()
            blocked = False
            while tasks.free > 0 and pending:
                item = next((it for it in pending if startable(it)), None)
                if item is None:
                    blocked = True
                    break
                pending.remove(item)
                kind, _, q, i = item
                job, s = (jobs[i], state[i]) if i >= 0 else (None, None)
                if kind == 0 and i < 0:
                    tstate["t0"] = time.perf_counter()
                    tasks.start((0, i, 0), _triad_task, triad.st, light=True)
                elif kind == 0:
                    s["t0"] = time.perf_counter()
                    tasks.start((0, i, 0), _fields_task, job.sc, job.spatial_demo, quiet, light=True)
                else:
                    tasks.start((1, i, q), partial(run_query, options=s["opts"], model=s["model"]), job.sc,
                                s["qjs"][q], light=True)
            if not len(tasks):
                if not pending:
                    raise RuntimeError("errplan demo: nothing left to run for a scenario not yet reported")
                time.sleep(0.05)  # waiting for the warm-up
                continue
            for (kind, i, q), res in tasks.collect(0.05 if blocked else None):
                if kind == 0 and i < 0:
                    tstate["results"], tstate["t_end"] = res, time.perf_counter()
                elif kind == 0:
                    on_fields(i, res)
                else:
                    on_query(i, q, res)
            while printed < n_shown and state[printed]["text"] is not None:
                if printed:
                    print()
                print(state[printed]["text"], flush=True)
                printed += 1
            if triad is not None and printed == n_shown and tstate["doc"] is None:
                triad_block()
                if tstate["doc"] is not None:
                    if n_shown:
                        print()
                    print(tstate["text"], flush=True)
    finally:
        tasks.close()
        note_workers()
        _OWN_ONLY["on"] = False
    return [s["doc"] for s in state[:n_shown]] + ([tstate["doc"]] if triad is not None else [])


def run(args) -> int:
    from ..inputs import check_output
    from ..api import load_scenario
    from ..models import arm_model

    t0 = time.perf_counter()
    quiet = getattr(args, "quiet", False)
    workers = demo_workers()
    if args.scenario:
        path = Path(args.scenario)
        sc = arm_model(load_scenario(path))
        jobs = [DemoJob(path, sc=sc)]
        # a first run compiles the planner's (and in 3-D the gains') kernels meanwhile
        if sc.dim == 3:
            warmup.start(("plan3", "gains3") + (("anatomy",) if sc.anatomy is not None else ()))
        else:
            warmup.start(("plan2", "gains2"))
    else:
        path = bundled_scenario()
        if not BUNDLED_SPATIAL.exists():
            raise ErrplanError(f"{BUNDLED_SPATIAL}: the bundled spatial demo scenario is missing (pass --scenario FILE)")
        # A first run: this process compiles the planar kernels, runs the planar part, then
        # loads the spatial scenario (compiling the reachability map's build, building the map) and runs
        # it; meanwhile a second process compiles what the later parts need, in the order they need it
        # (errplan.cli.warmup): the arm's kinematics first (a few seconds, so that this process finds
        # them), the spatial search (the longest, ready about when this process has built the map), the
        # planner's and the gains' kernels in the order a scenario's steps call them, the anatomy's, the lanes the setup's arms take. The
        # bundled scenarios are loaded when their turn comes. Their weights, side by side: the planar
        # fields first (loaded already and short: they run while this process loads the abdomen, and the
        # planar plan and queries, the demo's longest, come early), then the abdomen's (the longest), the
        # PHANToM's, the setup's triad placement and its arms'; the queries the longest first.
        warmup.start(("plan2", "gains2", "arm", "fields3g", "plan3", "gains3", "anatomy", "lanes3"))
        jobs = [DemoJob(path, weight=3.5, query_weight=3.0, sc=arm_model(load_scenario(path))),
                DemoJob(BUNDLED_SPATIAL, True, "arm", weight=2.0, query_weight=1.5)]
        if BUNDLED_ANATOMY.exists():
            jobs.append(DemoJob(BUNDLED_ANATOMY, "own", "anatomy", weight=3.0, query_weight=2.0))
    # the several-instrument setup after the scenarios (with --scenario: none)
    triad = TriadBlock(BUNDLED_TRIAD) if not args.scenario and BUNDLED_TRIAD.exists() else None
    rec = check_output("--record", args.record)
    check_output("--json", args.json)
    recs = [rec] + [spatial_record_path(rec, tag) if rec else None for tag in ("3d", "abdomen")[:len(jobs) - 1]]
    for r in recs[1:]:
        if r is not None:
            check_output("--record", str(r))
    for job, r in zip(jobs, recs):
        job.record = r
    if triad is not None and rec:
        triad.record = spatial_record_path(rec, "triad")
        for r in (triad.record, triad.plan_record()):
            check_output("--record", str(r))
    docs = run_jobs(jobs, quiet, workers, triad)
    doc = dict(docs[0])
    if len(jobs) > 1:
        doc["spatial"] = docs[1]
    if len(jobs) > 2:
        doc["anatomy"] = docs[2]
    if triad is not None:
        doc["setup"] = docs[-1]
    doc["total_s"] = time.perf_counter() - t0
    cpu = _cpu()
    doc["cpu_s"] = cpu
    if args.json:
        write_json(args.json, doc)
    prof = os.environ.get(PROFILE_ENV)
    if prof:
        with open(prof, "w", encoding="utf-8") as f:
            json.dump({"workers": workers, "wall": doc["total_s"], "cpu": _cpu(),
                       "steps": [dict(e, start=e["start"] - t0, end=e["end"] - t0) for e in _STEPS]}, f, indent=1)
    steps = sum(e["cpu"] for e in _STEPS)
    compiled = " and a first run's compiling ahead" if warmup._STATE["proc"] is not None else ""
    print(f"\ndemo total: wall {doc['total_s']:.1f} s, CPU {cpu:.1f} s (this process and the processes it ran; "
          f"the steps above {steps:.1f} s of it, the rest loading the scenarios{compiled})")
    return 0
