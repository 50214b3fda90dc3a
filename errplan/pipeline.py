"""plan -> gains -> simulate -> record: the tail of ``errplan plan`` and ``errplan demo``.

For every planned query (the plan JSON's ``planned``/``direct`` path objects, docs/interfaces.md):

1. **gains** (:mod:`errplan.gains`): the planned path cut into segments with certified gains, and
   the direct path as ONE segment with its best gain (used only if it is certified; otherwise the
   scenario's ``[controller] gain``, as a user commanding the goal directly would);
2. **simulation** (:mod:`errplan.simulation`): both under the scenario's truth
   (:func:`truth_plant`: true port, ``[effects]``, no sensor noise) and replayed under every
   corner of the error box (true port = estimate + corner offset, corner tip load, with the
   truth's other ``[effects]``: the robot each corner stands for is the true one). Each
   result is the ``R`` object of interfaces.md plus ``max_G_norm`` (the actual ``||G||`` at the
   visited tips under that truth) and ``status``/``converged``;
3. **record** (:mod:`errplan.recording`, optional): one rerun recording of everything.

The command calls :func:`run_pipeline` with the query JSONs and prints :func:`summary_table`.

Spatial scenarios (3-D) run through the same functions: the certificate's physics is a
:class:`errplan.gains.SpatialModel` (built once per run), the truth a :class:`Plant` on the URDF arm
(true port, ``[effects]``, and the error set's smallest load magnitude as a world load along -y,
none for the bundled scenarios), and the corner replays run under every corner of the 3-D port
box (8 truths). Before any work both endpoints of every query are checked: robustly reachable
and ``rho* <= 1 - certify_margin`` (some gain can certify convergence there), else one
:class:`~errplan.errors.InfeasibleError` naming the query, the endpoint and the value.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from .errors import ErrplanError, InfeasibleError
from .errorset import uncovered_effects
from .models import arm_model
from .gains import GainOptions, GainSchedule, SpatialModel, options_from_scenario, schedule_gains, single_segment
from .report import clearance_text, format_table
from .simulation import ControllerModel, Plant, SimResult, g_norm_along, simulate

Progress = Callable[[float, str], None]


def part_progress(progress: Progress | None, lo: float, hi: float) -> Progress | None:
    """``progress`` for one part of a job: its fractions 0..1 mapped to ``lo..hi``."""
    if progress is None:
        return None
    return lambda f, msg="": progress(lo + (hi - lo) * f, msg)
MAX_STEPS = 20000


@dataclass
class Replay:
    """One simulated run of a path under one truth, with the ``||G||`` it met."""

    sim: SimResult
    G_norm: np.ndarray  # (steps,) actual ||G|| at the state each command was issued from
    min_clearance: float | None = None  # m: smallest shaft clearance to [anatomy] along the run (3-D, obstacles)

    def to_json(self) -> dict:
        out = self.sim.to_json()
        out["max_G_norm"] = float(self.G_norm.max()) if len(self.G_norm) else 0.0
        if self.min_clearance is not None:
            out["min_clearance"] = self.min_clearance
        return out


def _clearance(model, plant: Plant, rep: Replay) -> Replay:
    """Set ``rep.min_clearance`` when the scenario has obstacles: the shaft from ``plant``'s true port to
    every visited tip, each step's straight move included (errplan.anatomy)."""
    an = getattr(model, "anatomy", None)
    if an is not None:
        rep.min_clearance = an.run_clearance(plant.true_port, rep.sim.tip)
    return rep


@dataclass
class QueryRun:
    """Everything the pipeline computed for one query (kept for the recording and the table)."""

    name: str
    start: np.ndarray
    goal: np.ndarray
    planned_path: np.ndarray
    direct_path: np.ndarray
    planned: dict                    # P objects from the planner (cost, length, ...)
    direct: dict
    schedule: GainSchedule
    direct_schedule: GainSchedule
    direct_gain: float
    direct_gain_source: str          # "certified" | "scenario"
    sim_planned: Replay
    sim_direct: Replay
    corners: np.ndarray              # (c, 3) error-set corners theta = (dy, dz, t); 3-D (c, 4) (dx, dy, dz, load)
    corner_planned: list[Replay] = field(default_factory=list)
    corner_direct: list[Replay] = field(default_factory=list)
    #: the truth's [effects] the metrics cannot express (simulated, not covered by the certificate)
    uncovered: list = field(default_factory=list)
    #: the scenario whose truth the paths were simulated on, when not the planned one (``--truth``)
    truth_name: str | None = None

    @property
    def certificate_covers(self) -> bool:
        """The certificate covers the truth simulated: it has no effect the metrics cannot express."""
        return not self.uncovered

    def gains_json(self) -> list[dict]:
        return self.schedule.to_json()

    def simulation_json(self) -> dict:
        out: dict[str, Any] = {"planned": self.sim_planned.to_json(), "direct": self.sim_direct.to_json(),
                               "direct_gain": self.direct_gain, "direct_gain_source": self.direct_gain_source}
        if len(self.corners):
            cp = [r.to_json() for r in self.corner_planned]
            cd = [r.to_json() for r in self.corner_direct]
            d = self.corners.shape[1] - 1
            out["corners"] = {
                "instances": [{"port_offset": [float(v) for v in t[:d]], "tip_force_over_ei": float(t[d])}
                              for t in self.corners],
                "planned": cp, "direct": cd,
                "planned_all_monotonic": all(r["monotonic"] for r in cp),
                "planned_all_converged": all(r["converged"] for r in cp),
                "direct_all_monotonic": all(r["monotonic"] for r in cd),
                "direct_all_converged": all(r["converged"] for r in cd),
            }
        return out

    def extra_json(self) -> dict:
        """The keys the pipeline adds to the query's plan JSON."""
        out = {"gains": self.gains_json(), "simulation": self.simulation_json(),
               "gain_schedule": self.schedule.summary(),
               "direct_gains": self.direct_schedule.to_json(),
               "certificate_covers": self.certificate_covers, "uncovered_effects": list(self.uncovered)}
        if self.truth_name is not None:
            out["truth"] = self.truth_name
        return out


# ----------------------------------------------------------------------------- pieces
def _path_of(p: Any, key: str, dim: int = 2) -> np.ndarray:
    path = np.asarray(p.get("path") if isinstance(p, dict) else getattr(p, "path"), float)
    if path.ndim != 2 or path.shape[1] != dim or len(path) < 2 or not np.all(np.isfinite(path)):
        pts = "[x, y, z]" if dim == 3 else "[y, z]"
        raise ErrplanError(f"{key} path of shape {path.shape}: expected (m >= 2, {dim}) finite {pts} points")
    return path


def truth_plant(sc) -> Plant:
    """The scenario's truth: ``[port] position``, its ``[effects]``, and the tip load of the error
    set closest to 0 (0 when the set allows it; P2's scenarios declare a fixed load there). In 3-D
    that load is a magnitude: a world load of that size along -y (:class:`Plant`)."""
    m = arm_model(sc)
    return m.truth if m is sc else Plant.from_model(m, load=m.truth_load)


def corner_instances(sc) -> np.ndarray:
    """Corners (c, 3) of the scenario's error box as ``(dy, dz, t)`` around its base port. In 3-D:
    the corners (c, 4) of the port box as ``(dx, dy, dz, load)`` with the truth's load magnitude
    (:func:`truth_plant`)."""
    es = arm_model(sc).errors
    if sc.dim == 3:
        ports = es.port_corners() - np.asarray(es.base_port)
        return np.hstack([ports, np.full((len(ports), 1), _truth_load(sc))])
    return es.corners()


def _truth_load(sc) -> float:
    tl = sc.uncertainty.tip_force_over_ei
    return float(np.clip(0.0, tl[0], tl[1])) if tl is not None else 0.0


def corner_plant(sc, theta) -> Plant:
    """The truth at one error-set instance: the corner's true port and tip load, with the truth's
    ``[effects]`` (its geometry, joint offsets, sag, ...; a ``port_offset`` is the corner's port
    itself, so it is not added again)."""
    m = arm_model(sc)
    es = m.errors
    theta = np.asarray(theta, float)
    d = es.dim
    tables = {k: v for k, v in sc.effects.items() if k != "port_offset"}
    return Plant.from_model(m, port=tuple(es.port(theta)), load=float(theta[d]), effects=tables)


def check_truth_pair(sc, truth_sc) -> None:
    """``errplan plan SCENARIO --truth T``: T's robot must be the one SCENARIO's controller commands (the
    same dimension and number of actuated joints), else one error naming both."""
    if truth_sc.dim != sc.dim:
        raise ErrplanError(f"--truth {truth_sc.source}: a {truth_sc.dim}-D scenario for the {sc.dim}-D scenario "
                           f"{sc.source}")
    if sc.dim == 3 and len(truth_sc.robot.joints) != len(sc.robot.joints):
        raise ErrplanError(f"--truth {truth_sc.source}: {len(truth_sc.robot.joints)} actuated joints "
                           f"{list(truth_sc.robot.joints)}; the controller of {sc.source} commands "
                           f"{len(sc.robot.joints)} {list(sc.robot.joints)}")


def check_query_endpoints(sc, name: str, start, goal, model: SpatialModel, margin: float) -> None:
    """3-D: both endpoints robustly reachable and ``rho* <= 1 - margin`` (some gain can certify
    convergence there), else one :class:`InfeasibleError` naming the query, the endpoint and the value."""
    pts = np.array([start, goal], float)
    wc = model.kev.worst_case(pts, float(sc.controller.gain), phi=False, rho=True)
    for i, what in enumerate(("start", "goal")):
        p = [round(float(v), 6) for v in pts[i]]
        if not wc["valid"][i]:
            raise InfeasibleError(f"query {name!r}: {what} {p} is outside the robust workspace: some instance of the "
                                  "error set (true port in the box, tip load) cannot put the tip there")
        if not wc["rho_star"][i] <= 1.0 - margin:
            raise InfeasibleError(f"query {name!r}: {what} {p}: no gain can certify convergence there "
                                  f"(rho* = {wc['rho_star'][i]:.4f} > 1 - certify_margin = {1.0 - margin:g})")


def replay(plant: Plant, controller: ControllerModel, start, waypoints, gains, opts: GainOptions,
           seed: int | None = None) -> Replay:
    """Simulate from the configuration that puts the true tip at ``start``.

    Noise-free, except for P2's flexion controller with bounded sensor noise: then its measured
    end poses get uniform noise inside the bounds, from a generator seeded with ``seed``.
    """
    try:
        q0 = plant.configuration_for_tip(np.asarray(start, float))
    except ErrplanError as e:
        raise ErrplanError(f"cannot simulate from the path's start: {e}") from None
    rng = None
    if controller.jacobian == "flexion" and any(controller.noise):
        rng = np.random.default_rng(0 if seed is None else seed)
    sim = simulate(plant, controller, q0, waypoints, gains, tolerance=opts.tolerance,
                   switch_tolerance=opts.switch_tolerance, max_steps=MAX_STEPS, path_start=start, rng=rng)
    return Replay(sim, g_norm_along(sim, plant, controller))


def run_query(sc, qjson: dict, *, options: GainOptions | None = None, corners: bool = True,
              progress: Progress | None = None, model: SpatialModel | None = None, truth_sc=None) -> QueryRun:
    """Gains and simulations for one query JSON (``name``, ``start``, ``goal``, ``planned``, ``direct``).

    ``truth_sc``: another scenario whose truth (its arm with its geometry, its port, its ``[effects]``)
    the planned and direct paths are simulated on (``errplan plan --truth``); default ``sc``'s own. The
    gains are certified on ``sc``, and the corner replays run under ``sc``'s error set."""
    opts = options or options_from_scenario(sc)
    dim = sc.dim
    name = str(qjson.get("name", "query"))
    start = np.asarray(qjson["start"], float)
    goal = np.asarray(qjson["goal"], float)
    ppath = _path_of(qjson["planned"], f"query {name!r}: planned", dim)
    dpath = _path_of(qjson["direct"], f"query {name!r}: direct", dim) if "direct" in qjson else np.array([start, goal])
    src = sc
    if dim == 3:
        src = model if model is not None else SpatialModel.from_model(arm_model(sc))
        check_query_endpoints(sc, name, ppath[0], ppath[-1], src, opts.margin)
    an_model = src if dim == 3 else None  # its .anatomy: the obstacles, for min_clearance
    if progress:
        progress(0.05, f"{name}: certifying gains")
    sched = schedule_gains(src, ppath, opts)
    dsched = single_segment(src, dpath[0], dpath[-1], opts)
    if dsched.certified:
        kd, src = float(dsched.gains[0]), "certified"
    else:
        kd, src = float(sc.controller.gain), "scenario"
    if progress:
        progress(0.5, f"{name}: simulating")
    ctrl = ControllerModel.from_model(arm_model(sc))
    tsc = sc if truth_sc is None else truth_sc
    truth = truth_plant(tsc)
    seed = int(sc.planner.seed)
    sp = _clearance(an_model, truth, replay(truth, ctrl, ppath[0], sched.waypoints, sched.gains, opts, seed))
    sd = _clearance(an_model, truth, replay(truth, ctrl, dpath[0], dpath[-1:], [kd], opts, seed))
    cs = corner_instances(sc) if corners else np.zeros((0, dim + 1))
    run = QueryRun(name, start, goal, ppath, dpath, dict(qjson["planned"]) if isinstance(qjson["planned"], dict) else {},
                   dict(qjson["direct"]) if isinstance(qjson.get("direct"), dict) else {}, sched, dsched, kd, src,
                   sp, sd, cs, uncovered=uncovered_effects(tsc), truth_name=tsc.name if truth_sc is not None else None)
    for i, th in enumerate(cs):
        pl = corner_plant(sc, th)
        run.corner_planned.append(_clearance(an_model, pl, replay(pl, ctrl, ppath[0], sched.waypoints, sched.gains,
                                                                  opts, seed + 1 + i)))
        run.corner_direct.append(_clearance(an_model, pl, replay(pl, ctrl, dpath[0], dpath[-1:], [kd], opts,
                                                                 seed + 1 + i)))
        if progress:
            progress(0.5 + 0.5 * (i + 1) / len(cs), f"{name}: corner replays")
    return run


def _as_query_json(q: Any) -> dict:
    if isinstance(q, dict):
        return q
    if hasattr(q, "to_json"):
        return q.to_json()
    raise ErrplanError(f"query plan of type {type(q).__name__}: expected a dict or an object with to_json()")


def run_pipeline(sc, query_plans, fields=None, *, record: str | None = None, progress: Progress | None = None,
                 options: GainOptions | None = None, corners: bool = True, workers: int = 1, truth_sc=None) -> dict:
    """Add ``gains`` and ``simulation`` to every query's plan JSON; optionally write a recording.

    ``query_plans``: the planner's per-query results (objects with ``to_json()`` and an ``extra``
    dict, or the query dicts of the plan JSON). Where an object has an ``extra`` dict the new
    keys are put there too, so its own ``to_json()`` carries them. ``fields``: the
    :class:`~errplan.fields.MetricField` the plan used (needed only for the recording).
    Returns ``{"queries": [...], "runs": [QueryRun...]}``; ``runs`` is for
    :func:`summary_table` and the recording (not JSON).

    The queries are independent: :func:`query_jobs` and :func:`finish_pipeline` are the two halves
    around them, for a caller that runs the :func:`run_query` calls elsewhere (``errplan demo`` runs
    them in worker processes); the result is the same. ``workers`` > 1: the queries run that many at a
    time in forked processes (:class:`errplan.cluster.ForkedTasks`; each has the models and the kernels
    this process holds), the progress reported as each one ends; the same result. ``truth_sc``: simulate
    the planned and direct paths on another scenario's truth (:func:`run_query`).
    """
    opts = options or options_from_scenario(sc)
    if truth_sc is not None:
        check_truth_pair(sc, truth_sc)
    plans = list(query_plans)
    model, qjs = query_jobs(sc, plans)
    if workers > 1 and len(qjs) > 1:
        return finish_pipeline(sc, plans, _forked_queries(sc, qjs, opts, corners, model, workers, progress, truth_sc), fields,
                               record=record)
    runs = []
    for i, qj in enumerate(qjs):

        def sub(f, msg, i=i):
            if progress:
                progress((i + f) / max(len(plans), 1), msg)

        runs.append(run_query(sc, qj, options=opts, corners=corners, progress=sub, model=model, truth_sc=truth_sc))
    return finish_pipeline(sc, plans, runs, fields, record=record)


def _forked_queries(sc, qjs: list[dict], opts: GainOptions, corners: bool, model, workers: int,
                    progress: Progress | None, truth_sc=None) -> list[QueryRun]:
    """:func:`run_query` of every query JSON in ``qjs``, at most ``workers`` at a time in forked processes,
    started in order; their runs in the order of ``qjs``."""
    from functools import partial

    from .cluster import ForkedTasks

    tasks = ForkedTasks(min(workers, len(qjs)))
    runs: list = [None] * len(qjs)
    nxt = done = 0
    try:
        while done < len(qjs):
            while tasks.free > 0 and nxt < len(qjs):
                tasks.start(nxt, partial(run_query, options=opts, corners=corners, model=model, truth_sc=truth_sc), sc, qjs[nxt],
                            light=True)
                nxt += 1
            for i, run in tasks.collect():
                runs[i] = run
                done += 1
                if progress:
                    progress(done / len(qjs), f"{run.name} done")
    finally:
        tasks.close()
    return runs


def query_jobs(sc, query_plans) -> tuple[SpatialModel | None, list[dict]]:
    """The scenario's certificate physics (3-D: one :class:`SpatialModel` for every query; planar:
    None) and the query JSONs :func:`run_query` takes, one per plan."""
    model = SpatialModel.from_model(arm_model(sc)) if sc.dim == 3 else None
    return model, [dict(_as_query_json(q)) for q in query_plans]


def finish_pipeline(sc, query_plans, runs: list[QueryRun], fields=None, *, record: str | None = None) -> dict:
    """The pipeline's result from the :func:`run_query` runs of ``query_plans`` (in order): the new keys
    added to every query JSON (and to a plan object's ``extra``), the recording written."""
    out = []
    for q, run in zip(query_plans, runs):
        qj = dict(_as_query_json(q))
        extra = run.extra_json()
        qj.update(extra)
        if hasattr(q, "extra") and isinstance(getattr(q, "extra"), dict):
            q.extra.update(extra)
        out.append(qj)
    if record:
        from .recording import record_plan

        if fields is None:
            raise ErrplanError("--record needs the fields the plan used")
        record_plan(record, sc, fields, runs)
    return {"queries": out, "runs": list(runs)}


# ----------------------------------------------------------------------------- table
def _fmt_bool(v: bool) -> str:
    return "yes" if v else "NO"


def _num(v) -> float:
    """A table cell from a JSON number (None: not defined, e.g. a path leaving the workspace)."""
    return float("nan") if v is None else float(v)


def summary_rows(runs: list[QueryRun]) -> list[list]:
    rows = []
    for r in runs:
        for kind in ("planned", "direct"):
            P = r.planned if kind == "planned" else r.direct
            sched = r.schedule if kind == "planned" else r.direct_schedule
            sim = r.sim_planned if kind == "planned" else r.sim_direct
            reps = r.corner_planned if kind == "planned" else r.corner_direct
            gains = sched.gains if kind == "planned" else np.array([r.direct_gain])
            cert_g = sched.max_certified_G_norm
            rows.append([
                r.name, kind, _num(P.get("cost")), _num(P.get("length")), _num(P.get("max_G_norm")), len(sched.segments),
                f"{gains.min():.3g}" if gains.min() == gains.max() else f"{gains.min():.3g}-{gains.max():.3g}",
                cert_g if math.isfinite(cert_g) else float("nan"),
                _fmt_bool(sched.certified), sim.sim.steps, _fmt_bool(sim.sim.converged), _fmt_bool(sim.sim.monotonic),
                f"{sum(x.sim.monotonic for x in reps)}/{len(reps)}" if reps else "-",
                f"{sum(x.sim.converged for x in reps)}/{len(reps)}" if reps else "-",
                max((x.sim.steps for x in reps), default=0),
            ])
    return rows


SUMMARY_HEADERS = ["query", "path", "cost", "length m", "max ||G||", "segments", "gain", "certified ||G||",
                   "certified", "steps", "converged", "monotonic", "corners monotonic", "corners converged", "corner steps max"]


def summary_table(runs: list[QueryRun], title: str | None = None) -> str:
    """Planned vs direct per query: cost, max ||G|| along the path (fields), certificate, simulation."""
    lines = [format_table(SUMMARY_HEADERS, summary_rows(runs), title)]
    for r in runs:
        for kind, sched in (("planned", r.schedule), ("direct", r.direct_schedule)):
            bad = [s for s in sched.segments if not s.certified]
            if bad:
                lines.append(f"{r.name} {kind}: {len(bad)} of {len(sched.segments)} segment(s) not certified: {bad[0].reason}"
                             + (f"; simulated with the scenario gain {r.direct_gain:g}" if kind == "direct" else ""))
    for r in runs:
        if r.uncovered:
            lines.append(f"{r.name}: the certificate does not cover {', '.join(r.uncovered)} in the truth simulated "
                         f"(the metrics cannot express them): simulated, not certified")
    for r in runs:
        if r.sim_planned.min_clearance is None:
            continue
        parts = []
        for kind, rep, reps in (("planned", r.sim_planned, r.corner_planned), ("direct", r.sim_direct, r.corner_direct)):
            parts.append(clearance_text(kind, rep.min_clearance, rep.sim.status, rep.sim.steps,
                                        [(x.min_clearance, x.sim.status) for x in reps]))
        lines.append(f"{r.name} min clearance of the shaft (anatomy): " + ", ".join(parts))
    lines.append("max ||G||: worst case along the path at the scenario gain (fields); certified ||G||: verified "
                 "worst case over every segment's convergence ball at the chosen gain; steps/converged/monotonic: "
                 "simulated under the scenario's truth" + (f" ({', '.join(sorted({r.truth_name for r in runs if r.truth_name}))}'s, "
                                                  "--truth)" if any(r.truth_name for r in runs) else "")
                 + "; corners: replays under every corner of the error box, with the truth's [effects].")
    return "\n".join(lines)
