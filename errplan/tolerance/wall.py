"""Port placement on the body wall (``port_placement`` with ``candidates = "body_wall"``).

The candidates are points of the scenario's ``[anatomy.body_wall]`` (:meth:`errplan.anatomy.ShaftClearance.
wall_points`: a deterministic set with neighbours about ``spacing`` apart along the surface, chordal
distance), kept when the shaft can reach through them (some reachable wrist nearer than the shaft length)
and some task-region point lies within the shaft length. Each is evaluated as in
:mod:`errplan.tolerance.placement` (the candidate is the port estimate and the reference of the
``[uncertainty]`` port box; ``rho*`` on the task-region grid by the compiled kernels), and a region point
counts as covered only when it is robustly reachable, certifiable (``rho* <= 1 - certify_margin`` and < 1)
**and robustly clear** of the anatomy for that candidate's port box (the shaft to every obstacle and the
tip inside the wall, :mod:`errplan.anatomy`). ``best``: most covered points, then the smaller
``max_rho_star``, then the first candidate. Candidates are independent tasks (dask as the grid sweep).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ErrplanError
from .placement import (MAX_CANDIDATES, MIN_TASKS, TASK_SECONDS, TIE_BREAK, PlacementJob, _candidate_item,
                        candidate_fields, check_placement, rank_key, region_axes_of)
from .result import Progress

#: halvings of the wall spacing around the leading candidates
REFINE_LEVELS = 2


@dataclass(frozen=True)
class WallJob:
    """What every wall candidate shares: the placement job, the anatomy and the port box's offsets."""

    base: PlacementJob
    anatomy: Any  # errplan.anatomy.ShaftClearance
    offsets: np.ndarray  # (c, 3) port-box corners less its reference port


def evaluate_wall(job: WallJob, cand) -> tuple[int, int, float, int]:
    """``(covered, reachable, max_rho_star, clear)`` of one wall candidate."""
    valid, rho = candidate_fields(job.base, cand)
    box = np.asarray(cand.base_port, float) + job.offsets
    clear = np.zeros(len(valid), bool)
    if valid.any():
        clear[valid] = job.anatomy.with_box(box).tip_clear(job.base.X[valid])
    ok = valid & clear
    with np.errstate(invalid="ignore"):
        cov = ok & np.isfinite(rho) & (rho <= job.base.bound) & (rho < 1.0)
    reach = int(valid.sum())
    return int(cov.sum()), reach, float(np.max(rho[valid])) if reach else float("nan"), int(ok.sum())


def evaluate_wall_batch(job: WallJob, cands: list) -> list:
    return [evaluate_wall(job, c) for c in cands]


def wall_candidates(sc, model, spacing: float, region: dict, near: np.ndarray | None = None,
                    radius: float = 0.0) -> np.ndarray:
    """The wall points (n, 3) the shaft can reach through, with a task-region point within its length
    (``near``, ``radius``: only those within ``radius`` of the points ``near``)."""
    from ..kinematics import arm_for

    pts = model.wall_points(spacing, near, radius)
    arm = arm_for(sc.robot)
    L = float(sc.instrument.length)
    lo = np.array([region[a][0] for a in sc.axes])
    hi = np.array([region[a][1] for a in sc.axes])
    near = np.linalg.norm(pts - np.clip(pts, lo, hi), axis=1) < L
    pts = pts[near]
    if not len(pts):
        return pts
    # errplan.kinematics' min_distance_to, vectorized: a reachable port, or a sampled wrist within L
    W = arm.sample_wrists(41)
    ok = np.asarray(arm.reachable(pts), bool).reshape(-1)
    for i0 in range(0, len(pts), 64):
        d = np.sqrt(np.min(np.sum((pts[i0:i0 + 64, None, :] - W[None]) ** 2, axis=-1), axis=1))
        ok[i0:i0 + 64] |= d < L
    return pts[ok]


def wall_port_placement(sc, spacing: float, region: dict, *, resolution: float | None = None,
                        gain: float | None = None, certify_margin: float | None = None, workers: int | None = 1,
                        scheduler: str | None = None, progress: Progress | None = None,
                        ports: np.ndarray | None = None, refine_levels: int = REFINE_LEVELS) -> dict[str, Any]:
    """Coverage of ``region`` for every candidate port on the body wall and the best one (module
    docstring). ``ports`` (n, 3): evaluate these wall points instead of the spaced set (tests).

    Refinement (``refine_levels`` halvings of the spacing): the wall points of the finer set lying
    within 1.5 coarse spacings of a leading candidate (covering at least the best count less one) are
    evaluated too; the answer is the best of everything evaluated (``wall_refinement`` says how many were
    added and whether the best moved)."""
    from ..cluster import map_tasks
    from ..fields import ErrorSet, KernelEvaluator, error_set
    from ..fields.compute import anatomy_model

    t0 = time.perf_counter()
    where = "port_placement"
    if sc.dim != 3 or sc.anatomy is None or sc.anatomy.body_wall is None:
        raise ErrplanError(f'{where}: candidates = "body_wall" needs a spatial scenario with [anatomy.body_wall]')
    if not spacing > 0 or not math.isfinite(spacing):
        raise ErrplanError(f"{where} spacing = {spacing!r}: expected a spacing > 0 m along the body wall")
    axes = sc.axes
    dummy = {a: (0.0, 0.0) for a in axes}
    check_placement(sc, {"candidates": dummy, "spacing": 1.0, "region": region, "resolution": resolution}, where)
    _, jac_effects = error_set(sc)
    if sc.controller.jacobian != "rigid" or jac_effects:
        raise ErrplanError(f'{where}: candidates = "body_wall" covers the rigid controller without [effects] that '
                           "move the arm (not supported yet otherwise)")
    model = anatomy_model(sc)
    res = float(resolution or sc.fields.resolution)
    k = float(gain if gain is not None else sc.controller.gain)
    margin = float(sc.planner.certify_margin if certify_margin is None else certify_margin)
    bound = 1.0 - margin
    r_axes = region_axes_of(region, res, axes)
    X = np.stack(np.meshgrid(*r_axes, indexing="ij"), axis=-1).reshape(-1, 3)
    ports_given = ports is not None
    if ports is None:
        ports = wall_candidates(sc, model, float(spacing), region)
    ports = np.asarray(ports, float).reshape(-1, 3)
    if len(ports) == 0:
        raise ErrplanError(f"{where}: no point of the body wall at spacing {spacing:g} m lets the shaft reach "
                           "through it toward the region")
    if len(ports) > MAX_CANDIDATES:
        raise ErrplanError(f"{where} spacing = {spacing:g}: {len(ports)} wall candidates, more than the sweep's "
                           f"budget of {MAX_CANDIDATES:,}: use a larger spacing")
    es = ErrorSet.from_tables(sc.port, sc.uncertainty, sc.dim)
    offsets = es.port_corners() - np.asarray(es.base_port, float)
    job = WallJob(PlacementJob(X, k, bound, evaluator=KernelEvaluator(sc)), model, offsets)
    t1 = time.perf_counter()
    t_one = [0.0]

    def run(pts):
        items = [_candidate_item(sc, c) for c in pts]
        out = []
        if not t_one[0] and items:
            t = time.perf_counter()
            out.append(evaluate_wall(job, items[0]))
            t_one[0] = time.perf_counter() - t
            items = items[1:]
        if items:
            per = max(1, min(math.ceil(TASK_SECONDS / max(t_one[0], 1e-6)), math.ceil(len(items) / MIN_TASKS)))
            batches = [items[i:i + per] for i in range(0, len(items), per)]

            def tick(done, total):
                if progress:
                    progress(done / total, f"wall candidate tasks {done}/{total}")

            for part in map_tasks(evaluate_wall_batch, job, batches, workers=workers, scheduler=scheduler,
                                  progress=tick):
                out.extend(part)
        return out

    grid_n = len(ports)
    results = run(ports)
    grid_best = max(range(len(ports)), key=lambda i: (results[i][0], -results[i][2] if math.isfinite(results[i][2])
                                                      else -math.inf, -i))
    h = float(spacing)
    for _ in range(max(int(refine_levels), 0) if ports_given is False else 0):
        top_cov = max(r[0] for r in results)
        lead = ports[[i for i, r in enumerate(results) if r[0] >= top_cov - 1]]
        h /= 2
        fresh = wall_candidates(sc, model, h, region, near=lead, radius=1.5 * 2 * h)
        if len(fresh):
            seen = np.min(np.linalg.norm(fresh[:, None] - ports[None], axis=-1), axis=1) > 1e-9
            fresh = fresh[seen]
        if not len(fresh):
            continue
        results += run(fresh)
        ports = np.vstack([ports, fresh])
    items = ports
    sweep_s = time.perf_counter() - t1
    m = len(X)
    order = sorted(range(len(items)), key=lambda i: rank_key(results[i][0], results[i][2], i))
    ib = order[0]
    cov_b, reach_b, rho_b, clear_b = results[ib]
    return {
        "best": ports[ib].tolist(), "coverage": cov_b / m, "max_rho_star": rho_b, "covered": cov_b,
        "reachable": reach_b, "clear": clear_b, "region_points": m,
        "candidates": [{"port": p.tolist(), "coverage": r[0] / m, "max_rho_star": r[2], "covered": r[0],
                        "reachable": r[1], "clear": r[3]} for p, r in zip(ports, results)],
        "ranking": [int(i) for i in order[:10]],
        "candidate_grid": {"body_wall": True, "spacing": float(spacing), "count": len(items),
                           "distance": "chordal, between neighbouring wall points"},
        "wall_refinement": {"levels": int(refine_levels) if not ports_given else 0, "grid_candidates": grid_n,
                    "added": len(items) - grid_n, "improved": ib != grid_best,
                    "grid_best": ports[grid_best].tolist(), "grid_covered": results[grid_best][0],
                    "port": ports[ib].tolist(), "coverage": cov_b / m, "covered": cov_b, "reachable": reach_b,
                    "max_rho_star": rho_b},
        "region": {a: list(region[a]) for a in axes},
        "region_grid": {"resolution": res, "axes": {a: v.tolist() for a, v in zip(axes, r_axes)}, "points": m},
        "gain": k, "certify_margin": margin,
        "criterion": f"robustly reachable, robustly clear of the anatomy and rho* <= {bound:g} (and < 1)",
        "tie_break": TIE_BREAK, "path": "compiled", "workers": workers, "scheduler": scheduler,
        "seconds_per_candidate": sweep_s / len(items), "sweep_seconds": sweep_s, "seconds": time.perf_counter() - t0,
    }
