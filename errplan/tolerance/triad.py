"""Triad placement (tolerance kind ``triad_placement``): the ports of two instruments and an endoscope,
chosen together (docs/physics.md "Several instruments and the endoscope").

Candidates. Per instrument arm, the body-wall points its shaft reaches through toward the task region
(:func:`errplan.tolerance.wall.wall_candidates`, as ``port_placement`` on the wall), or the points the
query lists; per endoscope, the wall points within ``insertion + far`` of the task region box (or the
listed ones). Per instrument candidate, the per-target coverage: robustly reachable, robustly clear of
the anatomy and certifiable (rho* <= 1 - certify_margin and < 1) for that candidate's port box, the
evaluation of ``port_placement`` on the wall (:func:`errplan.tolerance.wall.evaluate_wall`'s fields and
clearance, kept per target); candidates are independent tasks (:func:`errplan.cluster.map_tasks`).
Per endoscope candidate, the per-target visibility (:mod:`errplan.anatomy.setup`).

Score of a triad (p1, p2, pe), lower is better, over the targets T::

    S = (1/|T|) sum_t [ W (1 - c(t)) + ((m(t) - m*)/m_tol)^2 + ((a1(t) - a2(t))/a_tol)^2 ]

with c(t) = cov1(t) and cov2(t) and vis(t). Hard constraints: every pair of ports at least
``port_spacing`` apart; the endoscope's robust shaft conv(box_e ∪ {lens}) at least ``shaft_clearance``
from each instrument's robust shaft conv(box_i ∪ {t}) at every covered target (exact convex
distances); with ``[setup] arm_clearance`` (arm checks on), the two instrument arms at least that far
apart at every covered target.

Arm checks. At target t each instrument arm stands at the inverse kinematics that puts its wrist at
``t - L (t - p)/|t - p|`` (p its nominal candidate port; the compiled :meth:`UrdfArm.inverse`, the same
branch every run); the arm clearance is the smallest coal distance over the pairs of collision objects
of the two arms (:mod:`errplan.kinematics.urdf.collision`; the endoscope has no arm). A triad is
rejected when some covered target has an arm clearance below ``arm_clearance`` (or an arm that cannot
stand there). Configurations are computed once per (instrument candidate, target) and only for the
candidates a wave evaluates, at the targets that candidate covers; coal is queried once per
(instrument pair, target), only for the pairs a wave evaluates, at the targets both instruments cover,
and only when the two instrument ports are at least ``port_spacing`` apart (otherwise every triad of
the pair is rejected for spacing; its triads do not count under ``arm_clearance``); the queries run as
tasks (:func:`errplan.cluster.map_tasks`) and their results are kept for the rest of the search. A
query answers yes or no (coal's collision query with a security margin of ``arm_clearance``:
:func:`errplan.kinematics.urdf.collision.clear_of`; pairs of links whose bounding spheres lie
``arm_clearance`` apart are never queried); the figures' ``arm_clearance_min`` (the smallest over the
covered targets) is the exact clearance (coal's distance), queried for the reported triads only.

Search (branch and bound; exact). For an instrument pair (p1, p2) let

    LB(p1, p2) = (1/|T|) sum_t [ W (1 - cov1(t) cov2(t)) + ((m(t) - m*)/m_tol)^2 ].

For every endoscope port pe, c(t) <= cov1(t) cov2(t), so W (1 - c(t)) >= W (1 - cov1(t) cov2(t)), and
the azimuth term is >= 0; m(t) does not depend on pe. Hence S(p1, p2, pe) >= LB(p1, p2) for every pe:
LB is an admissible lower bound. It does not look at the hard constraints, so it stays admissible with
the arm checks on: they only remove triads from the feasible set (never change a score), so the
``keep``-th best feasible S can only rise and a pair pruned by LB > that S still holds no triad that
could enter the list. Pairs are visited in increasing LB (ties by index) in blocks; the
search keeps the ``keep`` best feasible triads found so far (ordered by (S, i1, i2, ie)); a pair whose LB
is greater than the ``keep``-th best S cannot enter the list (every one of its triads has S >= LB > that
S), and since the pairs come in increasing LB, once a block's smallest LB exceeds it so do all later
blocks: the search stops. Ties (LB equal to the threshold) are evaluated, so the kept list, best
first, is exactly the brute force's (``prune=False`` evaluates every triad; the tests compare).
Blocks run as tasks in waves of a fixed number of blocks; the threshold is updated between waves only,
so the pruned share does not depend on the number of workers either.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..anatomy import setup as geo
from ..errors import ErrplanError
from .placement import MAX_CANDIDATES, MIN_TASKS, TASK_SECONDS, PlacementJob, _candidate_item, candidate_fields, \
    check_placement, region_axes_of
from .result import Progress

#: instrument pairs per task, and tasks per wave of the branch and bound
BLOCK_PAIRS = 64
#: per-target values held for the search (angles, distances): about 8 bytes each
MAX_TRIAD_CELLS = 60_000_000
WAVE_BLOCKS = 4


# ============================================================================= per-candidate data
@dataclass(frozen=True)
class CoverJob:
    """What every instrument candidate of one arm shares (as :class:`errplan.tolerance.wall.WallJob`)."""

    base: PlacementJob
    anatomy: Any  # errplan.anatomy.ShaftClearance or None
    offsets: np.ndarray  # (c, 3) port-box corners less the reference port


def cover(job: CoverJob, cand) -> np.ndarray:
    """Per target (T,): robustly reachable, robustly clear and certifiable (rho* <= bound and < 1)."""
    valid, rho = candidate_fields(job.base, cand)
    ok = np.asarray(valid, bool).copy()
    if job.anatomy is not None and ok.any():
        box = np.asarray(cand.base_port, float) + job.offsets
        ok[ok] = job.anatomy.with_box(box).tip_clear(job.base.X[ok])
    with np.errstate(invalid="ignore"):
        return ok & np.isfinite(rho) & (rho <= job.base.bound) & (rho < 1.0)


def cover_batch(job: CoverJob, cands: list) -> list:
    return [np.packbits(cover(job, c)) for c in cands]


def distance_rows(shared, rows) -> np.ndarray:
    """One task: (len(rows), E, T) exact shaft distances of instrument candidates ``rows``."""
    boxes, X, hull_e = shared
    return geo.target_hull_distances(boxes[rows], X, hull_e)


def arm_rows(shared, item) -> np.ndarray:
    """One task: (k,) whether the two instrument arms ``shared = (ArmCollision, ArmCollision,
    arm_clearance)`` keep ``arm_clearance`` at configuration pairs ``item = (Q1 (k, n1), Q2 (k, n2))``
    (False where an arm cannot stand)."""
    from ..kinematics.urdf.collision import clear_of

    return clear_of(shared[0], item[0], shared[1], item[1], shared[2])


def _endoscope_candidates(model, endo, spacing: float, region: dict) -> np.ndarray:
    pts = model.wall_points(spacing)
    lo = np.array([region[a][0] for a in "xyz"])
    hi = np.array([region[a][1] for a in "xyz"])
    reach = endo.insertion + endo.depth[1]
    return pts[np.linalg.norm(pts - np.clip(pts, lo, hi), axis=1) <= reach]


# ============================================================================= triads
@dataclass(frozen=True)
class TriadData:
    """Everything a triad's score needs, per candidate (shipped once to every worker)."""

    cov1: np.ndarray  # (N1, T) bool
    cov2: np.ndarray  # (N2, T)
    vis: np.ndarray  # (E, T)
    mterm: np.ndarray  # (N1, N2, T) ((m - m*)/m_tol)^2
    A1: np.ndarray  # (N1, E, T) azimuths
    A2: np.ndarray  # (N2, E, T)
    D1: np.ndarray  # (N1, E, T) robust shaft distance instrument 1 - endoscope
    D2: np.ndarray
    d12: np.ndarray  # (N1, N2) port distances
    d1e: np.ndarray  # (N1, E)
    d2e: np.ndarray  # (N2, E)
    W: float
    a_tol: float
    port_spacing: float
    shaft_clearance: float
    keep: int
    #: (N1, N2, T) bool, the arms at least arm_clearance apart per instrument pair and target (arm checks
    #: on; else None): True where not both instruments cover the target or the pair is not checked,
    #: False where an arm cannot stand
    arm: np.ndarray | None = None
    arm_clearance: float | None = None
    arm_done: np.ndarray | None = None  # (N1, N2) bool: the pairs whose ``arm`` row is computed


def lower_bound(data: TriadData, i1: int, i2: int) -> float:
    """LB(p1, p2): admissible for every endoscope port (module docstring)."""
    both = data.cov1[i1] & data.cov2[i2]
    return float(np.mean(data.W * (1.0 - both) + data.mterm[i1, i2]))


def lower_bounds(data: TriadData) -> np.ndarray:
    """(N1, N2): :func:`lower_bound` of every pair at once."""
    T = data.cov1.shape[1]
    both = data.cov1.astype(np.float64) @ data.cov2.astype(np.float64).T / T
    return data.W * (1.0 - both) + np.mean(data.mterm, axis=-1)


def pair_scores(data: TriadData, i1: int, i2: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For pair (i1, i2) and every endoscope candidate: ``(S (E,), spacing_ok (E,), shaft_ok (E,),
    arm_ok (E,))`` (arm_ok all true when the arm checks are off)."""
    c = data.cov1[i1][None, :] & data.cov2[i2][None, :] & data.vis  # (E, T)
    az = ((data.A1[i1] - data.A2[i2]) / data.a_tol) ** 2
    S = np.mean(data.W * (1.0 - c) + data.mterm[i1, i2][None, :] + az, axis=1)
    sp = (data.d12[i1, i2] >= data.port_spacing) & (data.d1e[i1] >= data.port_spacing) & (
        data.d2e[i2] >= data.port_spacing)
    if np.isnan(data.D1[i1]).any() or np.isnan(data.D2[i2]).any():  # pragma: no cover - search's ensure
        raise RuntimeError(f"triad search: shaft distances of pair {(i1, i2)} not computed")
    bad = c & ((data.D1[i1] < data.shaft_clearance) | (data.D2[i2] < data.shaft_clearance))
    if data.arm is None:
        arm_ok = np.ones(len(S), bool)
    else:
        if not data.arm_done[i1, i2]:  # pragma: no cover - search's ensure
            raise RuntimeError(f"triad search: arm clearances of pair {(i1, i2)} not computed")
        arm_ok = ~np.any(c & ~data.arm[i1, i2][None, :], axis=1)
    return S, sp, ~np.any(bad, axis=1), arm_ok


def evaluate_block(data: TriadData, item) -> dict:
    """One task: the pairs of a block whose LB does not exceed ``threshold``; their best ``keep``
    feasible triads ``(S, i1, i2, ie)``, rejection counts, evaluated and pruned triad counts."""
    pairs, lbs, threshold = item
    E = data.vis.shape[0]
    best: list = []
    rej = {"port_spacing": 0, "shaft_clearance": 0, "arm_clearance": 0}
    evaluated = pruned = 0
    for (i1, i2), lb in zip(pairs, lbs):
        if lb > threshold:
            pruned += E
            continue
        S, sp, sh, am = pair_scores(data, i1, i2)
        evaluated += E
        rej["port_spacing"] += int(np.sum(~sp))
        rej["shaft_clearance"] += int(np.sum(~sh))
        rej["arm_clearance"] += int(np.sum(~am))
        ok = np.flatnonzero(sp & sh & am)
        for e in ok[np.argsort(S[ok], kind="stable")][:data.keep]:
            best.append((float(S[e]), int(i1), int(i2), int(e)))
    best.sort()
    return {"best": best[:data.keep], "rejected": rej, "evaluated": evaluated, "pruned": pruned}


def search(data: TriadData, *, prune: bool = True, workers: int | None = 1, scheduler: str | None = None,
           progress=None, ensure=None) -> dict:
    """The ``keep`` best feasible triads, by branch and bound (``prune``) or brute force. ``ensure(rows1,
    rows2, pairs)``, called before each wave, fills the rows of ``data.D1``/``data.D2`` (instrument
    candidates) and, with the arm checks on, the pairs of ``data.arm`` the wave evaluates (shaft distances
    and arm clearances are computed only where the search needs them)."""
    from ..cluster import map_tasks

    N1, N2, E = data.cov1.shape[0], data.cov2.shape[0], data.vis.shape[0]
    lbs = lower_bounds(data)
    order = sorted(((float(lbs[i, j]), i, j) for i in range(N1) for j in range(N2)))
    blocks = [order[k:k + BLOCK_PAIRS] for k in range(0, len(order), BLOCK_PAIRS)]
    best: list = []
    rej = {"port_spacing": 0, "shaft_clearance": 0, "arm_clearance": 0}
    evaluated = pruned = 0
    waves = 0
    k = 0
    while k < len(blocks):
        threshold = best[data.keep - 1][0] if (prune and len(best) >= data.keep) else math.inf
        wave = blocks[k:k + WAVE_BLOCKS]
        k += len(wave)
        if prune and wave[0][0][0] > threshold:  # every later pair has an LB at least this one's
            pruned += sum(len(b) for b in blocks[k - len(wave):]) * E
            break
        items = [([(i, j) for _, i, j in b], [lb for lb, _, _ in b], threshold) for b in wave]
        if ensure is not None:  # the distances of the instrument candidates this wave evaluates
            need = [(i, j) for b in wave for lb, i, j in b if lb <= threshold]
            ensure(sorted({i for i, _ in need}), sorted({j for _, j in need}), need)
        waves += 1
        for r in map_tasks(evaluate_block, data, items, workers=workers, scheduler=scheduler):
            best = sorted(best + r["best"])[:data.keep]
            for key in rej:
                rej[key] += r["rejected"][key]
            evaluated += r["evaluated"]
            pruned += r["pruned"]
        if progress:
            progress(min(k / len(blocks), 1.0), f"triad blocks {k}/{len(blocks)}")
    return {"best": best, "rejected": rej, "evaluated": evaluated, "pruned": pruned, "waves": waves,
            "triads": N1 * N2 * E, "pairs": N1 * N2, "lower_bounds": lbs}


# ============================================================================= the query
def _role_points(st, o, role, sc_for_wall, model, spacing, region) -> np.ndarray:
    cand = o["candidates"]
    if cand != "body_wall":
        return np.asarray(cand[role], float).reshape(-1, 3)
    if role == "endoscope":
        return _endoscope_candidates(model, st.endoscope, spacing, region)
    from .wall import wall_candidates

    return wall_candidates(sc_for_wall, model, spacing, region)


def triad_placement(st, tol, *, workers: int | None = 1, scheduler: str | None = None,
                    progress: Progress | None = None, prune: bool = True, keep: int = 6) -> dict[str, Any]:
    """Answer a ``triad_placement`` query of setup ``st`` (:class:`errplan.scenario.Setup`): the best
    triad and the next ``keep - 1`` (module docstring), with the JSON keys of docs/interfaces.md."""
    from ..cluster import map_tasks
    from ..fields import ErrorSet, KernelEvaluator, error_set
    from ..fields.compute import anatomy_model

    t0 = time.perf_counter()
    o = tol.options
    where = "triad_placement"
    n1, n2 = o["instruments"]
    sc1, sc2 = st.arm(n1), st.arm(n2)
    endo = st.endoscope
    if endo is None:
        raise ErrplanError(f"{where}: needs an [endoscope] table")
    region = o["region"]
    res = float(o.get("resolution") or sc1.fields.resolution)
    check_placement(sc1, {"candidates": {a: (0.0, 0.0) for a in "xyz"}, "spacing": 1.0, "region": region,
                          "resolution": res}, where)
    r_axes = region_axes_of(region, res, "xyz")
    X = np.stack(np.meshgrid(*r_axes, indexing="ij"), axis=-1).reshape(-1, 3)
    T = len(X)
    bound = 1.0 - float(o["certify_margin"])
    spacing = float(o["spacing"])
    roles = {}
    jobs = {}
    models = {}
    for name, sc in ((n1, sc1), (n2, sc2)):
        _, jac_effects = error_set(sc)
        if sc.controller.jacobian != "rigid" or jac_effects:
            raise ErrplanError(f"{where}: arm {name!r}: the triad covers the rigid controller without [effects] that "
                               "move the arm (not supported yet otherwise)")
        es = ErrorSet.from_tables(sc.port, sc.uncertainty, sc.dim)
        model = anatomy_model(sc, es)
        if o["candidates"] == "body_wall" and (model is None or not model.wall[6] > 0):
            raise ErrplanError(f'{where}: candidates = "body_wall" needs [anatomy.body_wall]')
        models[name] = model
        roles[name] = _role_points(st, o, name, sc, model, spacing, region)
        k = float(o.get("gain", sc.controller.gain))
        jobs[name] = CoverJob(PlacementJob(X, k, bound, evaluator=KernelEvaluator(sc)), model,
                              es.port_corners() - np.asarray(es.base_port, float))
    model_e = models[n1]
    roles["endoscope"] = _role_points(st, o, "endoscope", sc1, model_e, spacing, region)
    for r, pts in roles.items():
        if len(pts) == 0:
            raise ErrplanError(f"{where}: no candidate port for {r!r} (at spacing {spacing:g} m on the body wall)")
        if len(pts) > MAX_CANDIDATES:
            raise ErrplanError(f"{where} spacing = {spacing:g}: {len(pts)} candidates for {r!r}, more than the "
                               f"budget of {MAX_CANDIDATES:,}: use a larger spacing")
    n_a, n_b, n_e = len(roles[n1]), len(roles[n2]), len(roles["endoscope"])
    cells = (n_a * n_b + (n_a + n_b) * n_e * 2) * T
    if cells > MAX_TRIAD_CELLS:
        raise ErrplanError(f"{where} spacing = {spacing:g}: {n_a} x {n_b} x {n_e} candidate ports over {T} targets "
                           f"would need {cells:.3g} per-target values (max {MAX_TRIAD_CELLS:,}): use a larger spacing "
                           "or resolution")
    t1 = time.perf_counter()
    covs = {}
    for name, sc in ((n1, sc1), (n2, sc2)):
        items = [_candidate_item(sc, c) for c in roles[name]]
        per = max(1, math.ceil(len(items) / max(MIN_TASKS, 1)))
        batches = [items[i:i + per] for i in range(0, len(items), per)]

        def tick(done, total, name=name):
            if progress:
                progress(0.5 * done / total, f"{name} candidates {done}/{total}")

        packed = []
        for part in map_tasks(cover_batch, jobs[name], batches, workers=workers, scheduler=scheduler, progress=tick):
            packed.extend(part)
        covs[name] = np.array([np.unpackbits(p, count=T).astype(bool) for p in packed]).reshape(len(items), T)
    cover_s = time.perf_counter() - t1
    # endoscope: lens, axis, visibility; hull points conv(box_e ∪ {lens})
    P1, P2, PE = roles[n1], roles[n2], roles["endoscope"]
    axes_e = geo.optical_axis(PE, np.asarray(endo.look_at, float)[None, :])
    lens = PE + endo.insertion * axes_e
    vis = np.array([geo.visible(X, lens[i], axes_e[i], endo.fov, endo.depth, model_e) for i in range(len(PE))])
    off_e = geo.endoscope_box(endo) - np.asarray(endo.port.estimate, float)
    hull_e = np.concatenate([PE[:, None, :] + off_e[None], lens[:, None, :]], axis=1)
    boxes = {name: roles[name][:, None, :] + jobs[name].offsets[None] for name in (n1, n2)}
    D1 = np.full((len(P1), len(PE), T), np.nan)
    D2 = np.full((len(P2), len(PE), T), np.nan)
    done = {n1: np.zeros(len(P1), bool), n2: np.zeros(len(P2), bool)}
    dist_t = [0.0, 0]

    def ensure(rows1, rows2):
        """Exact shaft distances of these instrument candidates to every endoscope candidate, per target
        (tasks of a few candidates each)."""
        t = time.perf_counter()
        for name, D, rows in ((n1, D1, rows1), (n2, D2, rows2)):
            rows = [r for r in rows if not done[name][r]]
            if not rows:
                continue
            per = max(1, math.ceil(len(rows) / max(MIN_TASKS, 1)))
            chunks = [rows[i:i + per] for i in range(0, len(rows), per)]
            parts = map_tasks(distance_rows, (boxes[name], X, hull_e), chunks, workers=workers, scheduler=scheduler)
            for ch, part in zip(chunks, parts):
                D[ch] = part
                done[name][ch] = True
            dist_t[1] += len(rows)
        dist_t[0] += time.perf_counter() - t
    arm_c = st.arm_clearance
    arm_t = [0.0, 0, 0]  # seconds, pairs checked, coal queries (pair x target)
    ARM = arm_done = None
    if arm_c is not None:
        from ..kinematics import arm_for
        from ..kinematics.urdf.collision import ArmCollision

        kin, geos = {}, {}
        for name, sc in ((n1, sc1), (n2, sc2)):
            kin[name] = arm_for(sc.robot)
            try:
                geos[name] = ArmCollision.from_arm(kin[name])
            except ErrplanError as err:
                raise ErrplanError(f"{where}: [setup] arm_clearance = {arm_c:g}: arm {name!r}: {err}") from None
        Pc = {n1: P1, n2: P2}
        Qc = {name: np.full((len(Pc[name]), T, kin[name].n), np.nan) for name in (n1, n2)}
        qdone = {name: np.zeros(len(Pc[name]), bool) for name in (n1, n2)}
        ARM = np.ones((len(P1), len(P2), T), bool)
        arm_done = np.zeros((len(P1), len(P2)), bool)
        d12 = np.linalg.norm(P1[:, None] - P2[None], axis=-1)

        def configs(name, rows):
            """Each arm at the targets its candidates ``rows`` cover: the wrist at t - L (t - p)/|t - p|."""
            rows = [r for r in rows if not qdone[name][r]]
            if not rows:
                return
            cov = covs[name][rows]  # (r, T)
            u = geo.unit(X[None] - Pc[name][rows][:, None])
            W = X[None] - float(st.arm(name).instrument.length) * u
            q, ok = kin[name].inverse(W[cov])
            Qr = np.full((len(rows), T, kin[name].n), np.nan)
            Qr[cov] = np.where(np.asarray(ok, bool)[:, None], q, np.nan)
            Qc[name][rows] = Qr
            qdone[name][rows] = True

    def ensure_arms(pairs):
        """Arm clearances of the instrument pairs ``pairs`` at the targets both cover (module docstring)."""
        t = time.perf_counter()
        todo = sorted({(i, j) for i, j in pairs if not arm_done[i, j]})
        check = [(i, j) for i, j in todo if d12[i, j] >= float(o["port_spacing"])]
        configs(n1, sorted({i for i, _ in check}))
        configs(n2, sorted({j for _, j in check}))
        where_t = [(i, j, np.flatnonzero(covs[n1][i] & covs[n2][j])) for i, j in check]
        where_t = [w for w in where_t if len(w[2])]
        total = sum(len(w[2]) for w in where_t)
        if total:
            per = max(1, math.ceil(total / max(MIN_TASKS, 1)))
            chunks, cur, size = [], [], 0
            for w in where_t:
                cur.append(w)
                size += len(w[2])
                if size >= per:
                    chunks.append(cur)
                    cur, size = [], 0
            if cur:
                chunks.append(cur)
            items = [(np.concatenate([Qc[n1][i, tt] for i, _, tt in ch]),
                      np.concatenate([Qc[n2][j, tt] for _, j, tt in ch])) for ch in chunks]
            parts = map_tasks(arm_rows, (geos[n1], geos[n2], float(arm_c)), items, workers=workers,
                              scheduler=scheduler)
            for ch, part in zip(chunks, parts):
                k = 0
                for i, j, tt in ch:
                    ARM[i, j, tt] = part[k:k + len(tt)]
                    k += len(tt)
        for i, j in todo:
            arm_done[i, j] = True
        arm_t[0] += time.perf_counter() - t
        arm_t[1] += len(check)
        arm_t[2] += total

    def ensure_all(rows1, rows2, pairs):
        ensure(rows1, rows2)
        if arm_c is not None:
            ensure_arms(pairs)

    mstar, mtol = float(o["manipulation_angle"]), float(o["manipulation_tolerance"])
    U1, U2, UE = (geo.unit(X[None] - P[:, None]) for P in (P1, P2, lens))  # (N, T, 3) unit vectors p -> t
    M = geo.unit_angles(U1, U2)  # (N1, N2, T): m(t)
    A1 = geo.unit_angles(U1, UE)  # (N1, E, T): a_1(t)
    A2 = geo.unit_angles(U2, UE)
    data = TriadData(covs[n1], covs[n2], vis, ((M - mstar) / mtol) ** 2, A1, A2, D1, D2,
                     np.linalg.norm(P1[:, None] - P2[None], axis=-1), np.linalg.norm(P1[:, None] - PE[None], axis=-1),
                     np.linalg.norm(P2[:, None] - PE[None], axis=-1), float(o["coverage_weight"]),
                     float(o["azimuth_tolerance"]), float(o["port_spacing"]), float(st.shaft_clearance), int(keep),
                     ARM, None if arm_c is None else float(arm_c), arm_done)
    t3 = time.perf_counter()
    found = search(data, prune=prune, workers=workers, scheduler=scheduler,
                   progress=(lambda f, m: progress(0.5 + 0.5 * f, m)) if progress else None, ensure=ensure_all)
    search_s = time.perf_counter() - t3 - dist_t[0] - arm_t[0]
    dist_s = dist_t[0]

    exact = {}

    def exact_arm(i1, i2) -> np.ndarray:
        """(T,) the exact arm clearances of a reported pair at the targets both instruments cover (the
        search keeps only whether they are at least arm_clearance)."""
        from ..kinematics.urdf.collision import clearances

        if (i1, i2) not in exact:
            tt = np.flatnonzero(covs[n1][i1] & covs[n2][i2])
            row = np.full(T, np.inf)
            row[tt] = clearances(geos[n1], Qc[n1][i1, tt], geos[n2], Qc[n2][i2, tt])
            exact[(i1, i2)] = row
        return exact[(i1, i2)]

    def figures(s, i1, i2, ie) -> dict:
        c = data.cov1[i1] & data.cov2[i2] & data.vis[ie]
        m = M[i1, i2]
        cl = np.minimum(D1[i1, ie], D2[i2, ie])[c]
        ac = exact_arm(i1, i2)[c] if ARM is not None else np.zeros(0)
        return {"ports": {n1: P1[i1].tolist(), n2: P2[i2].tolist(), "endoscope": PE[ie].tolist()}, "score": s,
                "coverage": {n1: float(np.mean(data.cov1[i1])), n2: float(np.mean(data.cov2[i2])),
                             "both": float(np.mean(c))},
                "visible": float(np.mean(data.vis[ie])),
                "manipulation_angle": {"mean": float(np.mean(m)), "min": float(np.min(m)), "max": float(np.max(m))},
                "azimuth_difference_mean": float(np.mean(np.abs(A1[i1, ie] - A2[i2, ie]))),
                "port_spacing_min": float(min(data.d12[i1, i2], data.d1e[i1, ie], data.d2e[i2, ie])),
                "shaft_clearance_min": float(cl.min()) if len(cl) else None,
                "arm_clearance_min": float(ac.min()) if len(ac) else None, "indices": [int(i1), int(i2), int(ie)]}

    if not found["best"]:
        arms = "" if arm_c is None else f", arm clearance {arm_c:g} m"
        raise ErrplanError(f"{where}: no triad of the {found['triads']} meets the hard constraints (port spacing "
                           f"{o['port_spacing']:g} m, shaft clearance {st.shaft_clearance:g} m{arms} at covered "
                           "targets)")
    ranked = [figures(*b) for b in found["best"]]
    return {
        "best": ranked[0], "ranked": ranked[1:],
        "candidates": {n1: P1.tolist(), n2: P2.tolist(), "endoscope": PE.tolist()},
        "targets": T,
        "rejected": dict(found["rejected"], arm_clearance=found["rejected"]["arm_clearance"] if arm_c is not None
                         else None),
        "search": {"triads": found["triads"], "pairs": found["pairs"], "evaluated": found["evaluated"],
                   "pruned": found["pruned"], "pruned_share": found["pruned"] / max(found["triads"], 1),
                   "waves": found["waves"], "method": "branch and bound" if prune else "brute force",
                   "rejected_over": "the evaluated triads" if arm_c is None else
                   "the evaluated triads (arm_clearance: those whose instrument ports meet port_spacing)"},
        "instruments": [n1, n2], "region": {a: list(region[a]) for a in "xyz"}, "resolution": res,
        "weights": {"coverage_weight": data.W, "manipulation_angle": mstar, "manipulation_tolerance": mtol,
                    "azimuth_tolerance": data.a_tol},
        "port_spacing": data.port_spacing, "shaft_clearance": data.shaft_clearance,
        "arm_checks": "off" if arm_c is None else (f"on (arm_clearance {arm_c:g} m, "
                                                   f"{found['rejected']['arm_clearance']:,} triads rejected)"),
        "arm_clearance": None if arm_c is None else float(arm_c),
        "workers": workers, "scheduler": scheduler,
        "timing": {"coverage_s": cover_s, "distances_s": dist_s, "search_s": search_s,
                   "distance_rows": dist_t[1], "distance_rows_of": len(P1) + len(P2),
                   "arm_s": arm_t[0], "arm_pairs": arm_t[1], "arm_queries": arm_t[2]},
        "_arrays": {"targets": X, "lens": lens, "data": data,
                    # the best triad's arms per target (T, n) (NaN where not computed; arm checks on)
                    "arm_q": None if arm_c is None else {n1: Qc[n1][found["best"][0][1]],
                                                         n2: Qc[n2][found["best"][0][2]]}},
        "seconds": time.perf_counter() - t0,
    }
