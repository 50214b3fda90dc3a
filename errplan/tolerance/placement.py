"""Port placement (tolerance kind ``port_placement``, planar and spatial): where to cut the port so
that a task region is certifiably convergent over as much of it as possible, given how well the
port's position will be known.

A candidate ``c`` is the port's nominal position: the controller's estimate and the reference of
the scenario's ``[uncertainty]`` port box (the true port is anywhere in ``c + box``; without a box
it is ``c``; loads as declared). For each candidate on the candidate grid, ``rho*`` is computed on
the task-region grid exactly as ``errplan fields --metrics rho_star`` computes it for a scenario
with ``[port] position = estimate = c`` and ``[fields] region`` = the task region at the query's
resolution (the compiled kernels, worst case over the error set; P2's flexion controller and
``[effects]`` that move the arm through the fields' numpy path, one ``compute_fields`` per
candidate). Then

- ``covered``: region grid points robustly reachable with ``rho* <= 1 - certify_margin`` (and
  ``rho* < 1``: ``rho* = 1`` means that no gain contracts, never certifiable, as in the planner);
- ``coverage = covered / (all region grid points)``; ``max_rho_star`` the largest ``rho*`` over the
  region's reachable points (NaN, JSON null, where none is reachable);
- ``best``: the largest ``covered``; ties (equal ``covered``) to the smaller ``max_rho_star`` (NaN
  last), then to the first candidate in grid order (C order over the axes).

Grids. The candidate grid starts at the box's low corner: ``lo, lo + spacing, ...`` up to ``hi``
on each axis (a degenerate axis ``lo == hi`` has one value). The region grid is the fields' grid
of a ``[fields] region``: the multiples of the resolution inside the region (so the coverage can
be checked against ``errplan fields`` point for point).

Work. Candidates are independent tasks (:func:`errplan.cluster.map_tasks`: this process, local
worker processes, or a dask cluster; identical numbers either way). The first candidate runs here
and is timed; the others are grouped into tasks of about ``TASK_SECONDS`` (at least ``MIN_TASKS``
tasks), so that a cluster's per-task overhead stays small against the work. What does not change between
candidates is built once and shipped once: the region grid, the error-set samples and, for a URDF
arm, its chain and certified reachability map (the kernels' arrays); a task only swaps the
estimate and the true-port reference in the kernel's arguments.

Refinement (option ``refine``). The coverage is a step function of the port position (it counts
grid points crossing a threshold), so it has no useful gradient and plateaus everywhere. errplan
refines the best grid candidate with a derivative-free compass search on the same lexicographic
objective as the grid (more covered points, then a smaller ``max_rho_star``, which is continuous
and gives the search a direction on a plateau): from the best candidate, poll the neighbours at
step ``spacing / 2`` (the 8 neighbours in the plane; the 6 axis and 8 diagonal neighbours in 3-D),
clipped to the candidate box, in parallel as tasks; move to the best poll if it strictly improves,
else halve the step; ``refine_levels`` halvings. Every poll is an exact evaluation, so the refined
port is never worse than the grid's best; it is a local search (it can miss a better plateau
farther away than a grid cell), and both answers are reported.
"""
from __future__ import annotations

import copy
import itertools
import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..errors import ErrplanError
from .region import point_text, region_text
from .result import Progress

#: the sweep's budget: a candidate grid larger than this is refused before work starts
MAX_CANDIDATES = 10_000
#: region grid points per candidate at most (the fields' own cap)
MAX_REGION_POINTS = 4_000_000
#: memory per region grid point while one candidate is evaluated (coordinates, flags, outputs)
POINT_BYTES = 96
#: refinement: halvings of the poll step (spacing / 2, / 4, / 8) and moves per step at most
REFINE_LEVELS = 3
REFINE_MOVES = 4
#: candidates are grouped into tasks of about this many seconds (measured on the first candidate),
#: keeping at least MIN_TASKS tasks
TASK_SECONDS = 0.2
MIN_TASKS = 16
TIE_BREAK = "most covered region points, then the smaller max_rho_star, then the first candidate in grid order"


# ============================================================================= grids
def candidate_axes(box: dict, spacing: float, axes: tuple[str, ...]) -> list[np.ndarray]:
    """Candidate coordinates per axis: ``lo, lo + spacing, ...`` up to ``hi`` (``lo`` when ``lo == hi``)."""
    out = []
    for a in axes:
        lo, hi = box[a]
        n = int(math.floor((hi - lo) / spacing + 1e-9)) + 1
        out.append(np.round(lo + spacing * np.arange(n), 12))  # 0.17, not 0.16999999999999998
    return out


def candidate_count(box: dict, spacing: float, axes: tuple[str, ...]) -> float:
    """Number of candidates, as a float computed without building anything (a budget check first)."""
    return math.prod(math.floor((box[a][1] - box[a][0]) / spacing + 1e-9) + 1.0 for a in axes)


def _index_range(lo: float, hi: float, res: float) -> tuple[int, int]:
    """The multiples of ``res`` inside [lo, hi] (errplan.fields' grid of a ``[fields] region``)."""
    return math.ceil(lo / res - 1e-9), math.floor(hi / res + 1e-9)


def region_axes_of(region: dict, res: float, axes: tuple[str, ...]) -> list[np.ndarray]:
    """The task-region grid axes (the fields' grid of ``[fields] region`` at resolution ``res``)."""
    return [np.arange(i0, i1 + 1) * res for i0, i1 in (_index_range(*region[a], res) for a in axes)]


def check_placement(sc, o: dict, where: str) -> None:
    """Every size of a ``port_placement`` query checked before any work: the candidate budget, an
    empty region grid, the region grid's memory. One :class:`ErrplanError` naming the key."""
    from ..inputs import check_allocation

    axes = sc.axes
    cand, spacing = o["candidates"], float(o["spacing"])
    if set(cand) != set(axes) or set(o["region"]) != set(axes):
        raise ErrplanError(f"{where}: candidates and region need the axes {', '.join(axes)} of this "
                           f"{sc.dim}-D scenario")
    if not spacing > 0 or not math.isfinite(spacing):
        raise ErrplanError(f"{where} spacing = {spacing!r}: expected a candidate grid spacing > 0 m")
    n = candidate_count(cand, spacing, axes)
    if n > MAX_CANDIDATES:
        raise ErrplanError(f"{where} spacing = {spacing:g}: the candidate box {region_text(cand)} would need "
                           f"{n:.4g} candidates, more than the sweep's budget of {MAX_CANDIDATES:,}: use a larger "
                           "spacing or a smaller box")
    res = float(o.get("resolution") or sc.fields.resolution)
    if not res > 0 or not math.isfinite(res):
        raise ErrplanError(f"{where} resolution = {res!r}: expected a region grid spacing > 0 m")
    counts = []
    for a in axes:
        lo, hi = o["region"][a]
        i0, i1 = _index_range(lo, hi, res)
        if i1 < i0:
            raise ErrplanError(f"{where} region.{a} = {[lo, hi]}: holds no grid point at resolution {res:g} m "
                               "(an empty region: the region grid is the multiples of the resolution inside it)")
        counts.append(i1 - i0 + 1.0)
    m = math.prod(counts)
    check_allocation(f"{where} resolution", res, m, POINT_BYTES, "the task-region grid")
    if m > MAX_REGION_POINTS:
        raise ErrplanError(f"{where} resolution = {res:g}: the task-region grid would have {m:.4g} points "
                           f"(max {MAX_REGION_POINTS:,}): use a coarser resolution or a smaller region")


# ============================================================================= one candidate
@dataclass(frozen=True)
class PlacementJob:
    """What every candidate shares (picklable: shipped once to each cluster worker).

    ``evaluator``: a :class:`errplan.fields.KernelEvaluator` of the scenario (the compiled path: its
    kernel arguments hold the arm's chain and reachability map); ``None`` for the numpy path, which
    runs :func:`errplan.fields.compute_fields` on ``scenario`` per candidate."""

    X: np.ndarray  # (m, d) region grid points, C order over the region axes
    k: float
    bound: float  # 1 - certify_margin
    evaluator: Any = None
    scenario: Any = None
    region: Any = None
    resolution: float = 0.0


@dataclass(frozen=True)
class Candidate:
    """One task: the estimate and the true-port reference (the estimate, plus a ``port_offset``
    effect) of a candidate nominal port, exactly as :func:`errplan.fields.error_set` gives them."""

    port: tuple[float, ...]
    base_port: tuple[float, ...]


def candidate_scenario(sc, c) -> Any:
    """The scenario of candidate ``c``: ``[port] position = estimate = c`` (the true port is
    ``c + box`` with the scenario's box; ``c`` without one)."""
    from ..scenario import Port

    c = tuple(float(v) for v in c)
    return sc.with_(port=Port(c, c))


def _candidate_item(sc, c) -> Candidate:
    from ..fields import error_set

    es, _ = error_set(candidate_scenario(sc, c))
    return Candidate(tuple(float(v) for v in c), tuple(float(v) for v in es.base_port))


def candidate_fields(job: PlacementJob, cand: Candidate) -> tuple[np.ndarray, np.ndarray]:
    """``(valid, rho_star)`` on the region grid (m,) for one candidate."""
    if job.evaluator is not None:
        ev = copy.copy(job.evaluator)  # shallow: the kernel arrays are shared, only two vectors change
        ev._args = dict(job.evaluator._args, base_port=np.asarray(cand.base_port, float),
                        est=np.asarray(cand.port, float))
        ev.estimate = cand.port
        wc = ev.worst_case(job.X, job.k, phi=False, rho=True)
        return np.asarray(wc["valid"], bool), np.asarray(wc["rho_star"], float)
    from ..fields import compute_fields
    from ..scenario import Fields

    sc_c = replace(candidate_scenario(job.scenario, cand.port), fields=Fields(job.resolution, job.region),
                   controller=replace(job.scenario.controller, gain=job.k))
    mf = compute_fields(sc_c, job.resolution, metrics=("rho_star",), workers=1)
    return np.asarray(mf.valid, bool).ravel(), np.asarray(mf.rho_star, float).ravel()


def score(valid: np.ndarray, rho: np.ndarray, bound: float) -> tuple[int, int, float]:
    """``(covered, reachable, max_rho_star)`` of one candidate's region fields."""
    with np.errstate(invalid="ignore"):
        cov = valid & np.isfinite(rho) & (rho <= bound) & (rho < 1.0)
    reach = int(valid.sum())
    return int(cov.sum()), reach, float(np.max(rho[valid])) if reach else float("nan")


def evaluate_candidate(job: PlacementJob, cand: Candidate) -> tuple[int, int, float]:
    """The task run per candidate: ``(covered, reachable, max_rho_star)``."""
    valid, rho = candidate_fields(job, cand)
    return score(valid, rho, job.bound)


def evaluate_batch(job: PlacementJob, cands: list) -> list:
    """One task: a few candidates in a row (tasks of ``TASK_SECONDS`` or so keep a cluster's per-task
    overhead small against the work)."""
    return [evaluate_candidate(job, c) for c in cands]


def run_candidates(job: PlacementJob, items: list, *, workers, scheduler, tick, seconds_each: float | None = None
                   ) -> tuple[list, float]:
    """``evaluate_candidate`` on every item, as tasks of about ``TASK_SECONDS`` each (at least
    ``MIN_TASKS`` tasks when there are that many candidates). Without ``seconds_each`` the first
    candidate is evaluated here and timed. Returns the results in order and the seconds per candidate
    of that first one (or ``seconds_each``)."""
    from ..cluster import map_tasks

    out: list = []
    rest = items
    if seconds_each is None and items:
        t0 = time.perf_counter()
        out.append(evaluate_candidate(job, items[0]))
        seconds_each = time.perf_counter() - t0
        rest = items[1:]
    if rest:
        per = max(1, min(math.ceil(TASK_SECONDS / max(seconds_each or 0.0, 1e-6)), math.ceil(len(rest) / MIN_TASKS)))
        batches = [rest[i:i + per] for i in range(0, len(rest), per)]
        for part in map_tasks(evaluate_batch, job, batches, workers=workers, scheduler=scheduler, progress=tick):
            out.extend(part)
    return out, float(seconds_each or 0.0)


def rank_key(covered: int, max_rho: float, index: int = 0) -> tuple:
    """Sort key of the objective: most covered, then the smaller max rho* (NaN last), then index."""
    return (-covered, max_rho if math.isfinite(max_rho) else math.inf, index)


# ============================================================================= the query
def port_placement(sc, candidates: dict, spacing: float, region: dict, *, resolution: float | None = None,
                   gain: float | None = None, certify_margin: float | None = None, refine: bool = False,
                   refine_levels: int = REFINE_LEVELS, workers: int | None = 1, scheduler: str | None = None,
                   progress: Progress | None = None, keep_arrays: bool = True) -> dict[str, Any]:
    """Coverage of the task ``region`` for every nominal port on the candidate grid, the best port,
    and optionally a refined best port (see the module docstring for every definition).

    Returns the JSON keys of docs/interfaces.md (``best``, ``coverage``, ``max_rho_star``,
    ``candidates``) plus ``covered``, ``reachable``, ``region_points``, the grids, ``refined``
    (with ``refine``) and timing; with ``keep_arrays`` also ``_arrays`` (numpy arrays for the
    recording: coverage over the candidate grid, the best candidate's region fields)."""
    from ..fields import KernelEvaluator, error_set

    t0 = time.perf_counter()
    where = "port_placement"
    o = {"candidates": candidates, "spacing": spacing, "region": region, "resolution": resolution}
    check_placement(sc, o, where)
    axes = sc.axes
    res = float(resolution or sc.fields.resolution)
    k = float(gain if gain is not None else sc.controller.gain)
    margin = float(sc.planner.certify_margin if certify_margin is None else certify_margin)
    if not 0 <= margin < 1:
        raise ErrplanError(f"certify_margin = {margin!r}: expected a number in [0, 1)")
    bound = 1.0 - margin
    c_axes = candidate_axes(candidates, float(spacing), axes)
    r_axes = region_axes_of(region, res, axes)
    X = np.stack(np.meshgrid(*r_axes, indexing="ij"), axis=-1).reshape(-1, sc.dim)
    ports = np.stack(np.meshgrid(*c_axes, indexing="ij"), axis=-1).reshape(-1, sc.dim)
    _, jac_effects = error_set(sc)
    compiled = sc.controller.jacobian == "rigid" and not jac_effects
    if compiled:
        job = PlacementJob(X, k, bound, evaluator=KernelEvaluator(sc))
    else:  # P2's flexion controller, or [effects] that move the arm: the fields' numpy path
        job = PlacementJob(X, k, bound, scenario=sc, region={a: tuple(region[a]) for a in axes}, resolution=res)
    items = [_candidate_item(sc, c) for c in ports]

    def tick(done, total, what="candidate tasks"):
        if progress:
            progress(done / total, f"{what} {done}/{total}")

    t_sweep = time.perf_counter()
    results, t_one = run_candidates(job, items, workers=workers, scheduler=scheduler, tick=tick)
    sweep_s = time.perf_counter() - t_sweep
    m = len(X)
    order = sorted(range(len(items)), key=lambda i: rank_key(results[i][0], results[i][2], i))
    ib = order[0]
    cov_b, reach_b, rho_b = results[ib]
    out: dict[str, Any] = {
        "best": ports[ib].tolist(), "coverage": cov_b / m, "max_rho_star": rho_b, "covered": cov_b,
        "reachable": reach_b, "region_points": m,
        "candidates": [{"port": p.tolist(), "coverage": r[0] / m, "max_rho_star": r[2], "covered": r[0],
                        "reachable": r[1]} for p, r in zip(ports, results)],
        "ranking": [int(i) for i in order[:10]],
        "candidate_grid": {"box": {a: list(candidates[a]) for a in axes}, "spacing": float(spacing),
                           "axes": {a: v.tolist() for a, v in zip(axes, c_axes)}, "count": len(items)},
        "region": {a: list(region[a]) for a in axes},
        "region_grid": {"resolution": res, "axes": {a: v.tolist() for a, v in zip(axes, r_axes)}, "points": m},
        "gain": k, "certify_margin": margin, "criterion": f"robustly reachable and rho* <= {bound:g} (and < 1)",
        "tie_break": TIE_BREAK, "path": "compiled" if compiled else "numpy",
        "workers": workers, "scheduler": scheduler,
        "sweep_seconds": sweep_s, "seconds_per_candidate": sweep_s / len(items),
    }
    if refine:
        out["refined"] = _refine(job, sc, ports[ib], (cov_b, reach_b, rho_b), candidates, float(spacing),
                                 int(refine_levels), workers, scheduler, tick, t_one)
    if keep_arrays:
        shape = tuple(len(a) for a in c_axes)
        valid_b, rho_best = candidate_fields(job, items[ib])
        arrays = {"candidate_axes": c_axes, "region_axes": r_axes,
                  "coverage": np.array([r[0] / m for r in results]).reshape(shape),
                  "max_rho_star": np.array([r[2] for r in results]).reshape(shape),
                  "best_valid": valid_b, "best_rho_star": rho_best, "region_points": X, "bound": bound}
        if refine and out["refined"]["improved"]:
            vr, rr_ = candidate_fields(job, _candidate_item(sc, out["refined"]["port"]))
            arrays.update(refined_valid=vr, refined_rho_star=rr_)
        out["_arrays"] = arrays
    out["seconds"] = time.perf_counter() - t0
    return out


def _neighbours(d: int) -> np.ndarray:
    """Poll directions: every neighbour in the plane (8); the 6 axis and 8 diagonal ones in 3-D."""
    if d == 2:
        return np.array([v for v in itertools.product((-1.0, 0.0, 1.0), repeat=2) if any(v)])
    ax = np.concatenate([np.eye(3), -np.eye(3)])
    diag = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))
    return np.concatenate([ax, diag])


def _refine(job, sc, c0, s0, box, spacing, levels, workers, scheduler, tick, t_one) -> dict[str, Any]:
    """Compass search from the best grid candidate on the lexicographic objective (module docstring)."""
    axes = sc.axes
    lo = np.array([box[a][0] for a in axes])
    hi = np.array([box[a][1] for a in axes])
    dirs = _neighbours(sc.dim)
    c = np.asarray(c0, float)
    cov, reach, rho = s0
    seen = {tuple(np.round(c, 12))}
    evals, moves, h = 0, 0, spacing / 2.0
    trail = [c.tolist()]
    for level in range(max(0, levels)):
        for _ in range(REFINE_MOVES):
            polls = []
            for v in dirs:
                p = np.round(np.clip(c + h * v, lo, hi), 12)  # as the candidate grid rounds
                key = tuple(np.round(p, 12))
                if key not in seen:
                    seen.add(key)
                    polls.append(p)
            if not polls:
                break
            items = [_candidate_item(sc, p) for p in polls]
            res, _ = run_candidates(job, items, workers=workers, scheduler=scheduler, seconds_each=t_one,
                                    tick=lambda d_, t_: tick(d_, t_, f"refinement step {h * 1000:.3g} mm:"))
            evals += len(polls)
            j = min(range(len(polls)), key=lambda i: rank_key(res[i][0], res[i][2], i))
            if rank_key(res[j][0], res[j][2]) < rank_key(cov, rho) and (
                    res[j][0] > cov or not math.isfinite(rho) or res[j][2] < rho - 1e-12):
                c = polls[j]
                cov, reach, rho = res[j]
                moves += 1
                trail.append(c.tolist())
            else:
                break
        h /= 2.0
    m = len(job.X)
    return {"port": c.tolist(), "coverage": cov / m, "max_rho_star": rho, "covered": cov, "reachable": reach,
            "improved": bool(moves > 0), "evaluations": evals, "moves": moves, "levels": levels,
            "initial_step": spacing / 2.0, "final_step": spacing / 2.0 ** max(levels, 0),
            "trail": trail, "method": "compass search on (covered, -max_rho_star) inside the candidate box"}


def describe(data: dict) -> str:
    """One line naming the best port, for messages."""
    return (f"best port {point_text(data['best'])}: coverage {100 * data['coverage']:.1f}% "
            f"({data['covered']} of {data['region_points']} region points)")
