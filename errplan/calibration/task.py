"""The task before and after calibration (docs/physics.md "From measured data to the plan").

A scenario with ``[[query]]`` tables gets, from ``errplan calibrate``, each query planned on the declared
model and on the corrected one (``--export-scenario``'s robot) and simulated on the fitted truth
(``--export-bench``'s: the declared controller's robot as the fit found it). Both sides run
:func:`plan_on_truth`, the function ``errplan plan SCENARIO --truth T.toml`` runs, so the table's numbers
are that command's for the same pair: the planning budget, seed and field resolution are the scenario's.

Per query and side, :func:`task_figures`: ``max_deviation`` and ``final_error`` (m) of the planned path's
run on the truth, its ``steps`` and ``monotonic``, ``certified_G_norm`` (the worst certified ||G|| over
the path's segments, None when a segment is not certified) and ``certificate_covers`` (false when the
truth has effects the metrics cannot express: :func:`errplan.errorset.uncovered_effects`).
"""
from __future__ import annotations

import math
from contextlib import contextmanager
from pathlib import Path

from ..errors import InfeasibleError

#: the figures of one planned run on the truth, in the order of the table
TASK_KEYS = ("max_deviation", "final_error", "steps", "monotonic", "certified_G_norm", "certificate_covers")


def plan_on_truth(sc, truth_sc=None, *, query: str | None = None, planner: str | None = None,
                  time: float | None = None, seed: int | None = None, iterations: int | None = None,
                  corners: bool = True, workers: int = 1, progress=None, record: str | None = None, plan_fn=None):
    """Plan every query of ``sc`` (or ``query``) on its own fields, certify the gains on its model, and
    simulate the planned and direct paths on ``truth_sc``'s truth (its arm and geometry, port and
    ``[effects]``; default ``sc``'s own): :class:`~errplan.planning.ScenarioPlan` with ``.runs``.

    ``plan_fn(sc, progress)``: the plan itself (``errplan plan`` passes its step-by-step
    :func:`errplan.cli.plan.plan_arm` without the pipeline; the result is the same); default
    :func:`errplan.planning.plan_scenario` with the scenario's budget."""
    from ..pipeline import part_progress as _part
    from ..models import arm_model
    from ..pipeline import check_truth_pair, run_pipeline
    from ..planning import plan_scenario

    sc = arm_model(sc)
    tsc = None if truth_sc is None else arm_model(truth_sc)
    if tsc is not None:
        check_truth_pair(sc, tsc)
    if plan_fn is None:
        plan = plan_scenario(sc, query=query, planner=planner, time=time, seed=seed, iterations=iterations,
                             progress=_part(progress, 0.0, 0.6), workers=workers)
    else:
        plan = plan_fn(sc, _part(progress, 0.0, 0.6))
    res = run_pipeline(sc, plan.queries, plan.costmap.mf, record=record, progress=_part(progress, 0.6, 1.0),
                       corners=corners, workers=workers, truth_sc=tsc)
    plan.runs = res["runs"]
    return plan


def _finite(x):
    return float(x) if x is not None and math.isfinite(x) else None


def task_figures(run) -> dict:
    """T of the calibrate JSON's ``task`` for one :class:`errplan.pipeline.QueryRun`: its planned path
    as simulated on the truth."""
    sim = run.sim_planned.sim
    segs = run.schedule.segments
    cert = run.schedule.max_certified_G_norm if segs and all(s.certified for s in segs) else None
    return {"max_deviation": float(sim.max_deviation), "final_error": float(sim.final_error), "steps": int(sim.steps),
            "monotonic": bool(sim.monotonic), "certified_G_norm": _finite(cert),
            "certificate_covers": bool(run.certificate_covers), "uncovered_effects": list(run.uncovered)}


@contextmanager
def task_scenarios(sc, report):
    """The corrected robot and the fitted bench of a calibration as scenarios (their files in a scratch
    folder for as long as the context lasts): ``(corrected, bench)``, read as ``--export-scenario`` and
    ``--export-bench`` write them (:mod:`errplan.calibration.export`)."""
    import tempfile

    import tomllib

    from ..scenario import scenario_from_dict
    from .export import bench_files, corrected_files

    with tempfile.TemporaryDirectory(prefix="errplan-task-") as tmp:
        tmp = Path(tmp)
        text, extra = corrected_files(sc, report, tmp / "corrected.toml")
        doc = tomllib.loads(text)
        for path, t in extra.items():
            Path(path).write_text(t, encoding="utf-8")
            doc["robot"]["urdf"] = str(Path(path).resolve())
        corrected = scenario_from_dict(doc, str(sc.source))  # other relative paths: the scenario's folder
        bench = scenario_from_dict(tomllib.loads(bench_files(sc, report)), str(sc.source))
        yield corrected, bench


def _side(sc, truth_sc, workers: int, progress) -> dict:
    """``{query name: T}`` of one side; a side that cannot be planned gives every query ``{"error": why}``."""
    try:
        plan = plan_on_truth(sc, truth_sc, corners=False, workers=workers, progress=progress)
    except InfeasibleError as e:
        return {q.name: {"error": str(e)} for q in sc.queries}
    return {r.name: task_figures(r) for r in plan.runs}


def calibration_task(sc, report, *, workers: int = 1, progress=None) -> list[dict]:
    """The calibrate JSON's ``task``: ``[{"query", "before": T, "after": T}]``, each query of ``sc`` planned
    on the declared model (before) and on the corrected one (after), both simulated on the fitted truth
    (:func:`plan_on_truth`, corner replays left out: they do not enter T). [] without queries."""
    from ..pipeline import part_progress as _part

    if not getattr(sc, "queries", None):
        return []
    with task_scenarios(sc, report) as (corrected, bench):
        before = _side(sc, bench, workers, _part(progress, 0.0, 0.5))
        after = _side(corrected, bench, workers, _part(progress, 0.5, 1.0))
    return [{"query": q.name, "before": before.get(q.name), "after": after.get(q.name)} for q in sc.queries]


def task_table(task: list[dict]) -> str:
    """The task before and after as a table (mm for lengths)."""
    from ..report import format_table

    if not task:
        return ""
    rows, notes = [], []
    for t in task:
        for side in ("before", "after"):
            T = t.get(side) or {}
            if "error" in T:
                rows.append([t["query"] if side == "before" else "", side, "-", "-", "-", "-", "-", "-"])
                notes.append(f"{t['query']} {side}: {T['error']}")
                continue
            cg = T.get("certified_G_norm")
            rows.append([t["query"] if side == "before" else "", side, T["max_deviation"] * 1000, T["final_error"] * 1000,
                         T["steps"], "yes" if T["monotonic"] else "NO", "-" if cg is None else f"{cg:.4g}",
                         "yes" if T["certificate_covers"] else "NO"])
            if not T["certificate_covers"] and side == "after":
                notes.append(f"{t['query']}: the certificate does not cover {', '.join(T['uncovered_effects'])} "
                             f"(simulated, not certified)")
    lines = [format_table(["query", "plan on", "max deviation mm", "final error mm", "steps", "monotonic",
                           "certified ||G||", "certificate covers"], rows,
                          "the task before -> after: each query planned on the declared (before) and on the corrected "
                          "model (after), simulated on the fitted truth")]
    lines += notes
    lines.append("the same numbers as `errplan plan SCENARIO --truth BENCH.toml` (BENCH: --export-bench) for the "
                 "declared scenario and for the --export-scenario file")
    return "\n".join(lines)


__all__ = ["TASK_KEYS", "plan_on_truth", "task_figures", "task_scenarios", "calibration_task", "task_table"]
