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

Setups (:func:`place` with bases; :mod:`errplan.tolerance.setup`). An instrument candidate is then a (base,
port) pair, base-major; the per-port arrays (angles, shaft distances, port distances) stay per port and
:class:`TriadData` maps each candidate to its port row; coverage, the arms' configurations and the arm and
patient checks are per candidate. Two more hard constraints, both only removing setups (LB stays
admissible): the arms at rest at least ``arm_clearance`` apart (asked first, per pair the search evaluates;
the targets only for pairs clear at rest) and, with a patient clearance, every link of each arm that far
from the body at the covered targets and at rest (per candidate, before the search).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
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
#: the hard constraints a triad (or setup) is rejected for, counted separately
REJECTIONS = ("port_spacing", "shaft_clearance", "arm_clearance", "patient_clearance")


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


def cover_base_batch(jobs, item) -> list:
    """One task: ``item = (base index, candidates)``, covered by that base's job of ``jobs``."""
    b, cands = item
    return cover_batch(jobs[b], cands)


def distance_rows(shared, rows) -> np.ndarray:
    """One task: (len(rows), E, T) exact shaft distances of instrument candidates ``rows``."""
    boxes, X, hull_e = shared
    return geo.target_hull_distances(boxes[rows], X, hull_e)


def arm_rows(shared, item) -> np.ndarray:
    """One task: (k,) whether the two instrument arms keep ``arm_clearance`` at configuration pairs; ``shared
    = (ArmCollisions of arm 1 per base, ArmCollisions of arm 2 per base, arm_clearance)``, ``item`` a list of
    ``(base 1, base 2, Q1 (k, n1), Q2 (k, n2))`` (False where an arm cannot stand), concatenated."""
    from ..kinematics.urdf.collision import clear_of

    g1, g2, c = shared
    parts = [clear_of(g1[b1], Q1, g2[b2], Q2, c) for b1, b2, Q1, Q2 in item]
    return np.concatenate(parts) if parts else np.zeros(0, bool)


def patient_rows(shared, item) -> np.ndarray:
    """One task: (k,) whether one arm's links keep the patient clearance at configurations ``Q``; ``shared =
    (ArmCollisions per base, BodySolid, patient_clearance)``, ``item = (base, Q (k, n))`` (False where the arm
    cannot stand)."""
    from ..kinematics.urdf.collision import patient_clear

    geos, body, c = shared
    b, Q = item
    return patient_clear(geos[b], Q, body, c)


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
    #: setup placement: each instrument candidate's port row (N1,), (N2,) in the per-port arrays (mterm, A, D,
    #: d); None: the candidates are the ports
    port1: np.ndarray | None = None
    port2: np.ndarray | None = None
    #: setup placement with [setup] patient_clearance: (N, T) bool, the arm's links keep it from the body at t
    #: (False where the arm cannot stand), and (N,) at rest; None: no patient checks
    patient1: np.ndarray | None = None
    patient2: np.ndarray | None = None
    patient_rest1: np.ndarray | None = None
    patient_rest2: np.ndarray | None = None
    #: setup placement with arm checks: (N1, N2) bool, the two arms at rest keep arm_clearance (rows of
    #: ``arm_done`` pairs); None: not checked
    arm_rest: np.ndarray | None = None

    def ports(self, i1: int, i2: int) -> tuple[int, int]:
        """The port rows of instrument candidates (i1, i2)."""
        return (int(self.port1[i1]) if self.port1 is not None else i1,
                int(self.port2[i2]) if self.port2 is not None else i2)


def lower_bound(data: TriadData, i1: int, i2: int) -> float:
    """LB(p1, p2): admissible for every endoscope port (module docstring)."""
    both = data.cov1[i1] & data.cov2[i2]
    return float(np.mean(data.W * (1.0 - both) + data.mterm[data.ports(i1, i2)]))


def lower_bounds(data: TriadData) -> np.ndarray:
    """(N1, N2): :func:`lower_bound` of every pair at once."""
    T = data.cov1.shape[1]
    both = data.cov1.astype(np.float64) @ data.cov2.astype(np.float64).T / T
    m = np.mean(data.mterm, axis=-1)
    if data.port1 is not None:
        m = m[np.ix_(data.port1, data.port2)]
    return data.W * (1.0 - both) + m


def pair_scores(data: TriadData, i1: int, i2: int) -> tuple[np.ndarray, ...]:
    """For pair (i1, i2) and every endoscope candidate: ``(S (E,), spacing_ok (E,), shaft_ok (E,),
    arm_ok (E,), patient_ok (E,))`` (arm_ok, patient_ok all true when those checks are off)."""
    j1, j2 = data.ports(i1, i2)
    c = data.cov1[i1][None, :] & data.cov2[i2][None, :] & data.vis  # (E, T)
    az = ((data.A1[j1] - data.A2[j2]) / data.a_tol) ** 2
    S = np.mean(data.W * (1.0 - c) + data.mterm[j1, j2][None, :] + az, axis=1)
    sp = (data.d12[j1, j2] >= data.port_spacing) & (data.d1e[j1] >= data.port_spacing) & (
        data.d2e[j2] >= data.port_spacing)
    if np.isnan(data.D1[j1]).any() or np.isnan(data.D2[j2]).any():  # pragma: no cover - search's ensure
        raise RuntimeError(f"triad search: shaft distances of pair {(i1, i2)} not computed")
    bad = c & ((data.D1[j1] < data.shaft_clearance) | (data.D2[j2] < data.shaft_clearance))
    if data.arm is None:
        arm_ok = np.ones(len(S), bool)
    else:
        if not data.arm_done[i1, i2]:  # pragma: no cover - search's ensure
            raise RuntimeError(f"triad search: arm clearances of pair {(i1, i2)} not computed")
        arm_ok = ~np.any(c & ~data.arm[i1, i2][None, :], axis=1)
        if data.arm_rest is not None:
            arm_ok &= bool(data.arm_rest[i1, i2])
    if data.patient1 is None:
        pt_ok = np.ones(len(S), bool)
    else:
        both = data.patient1[i1] & data.patient2[i2]
        pt_ok = ~np.any(c & ~both[None, :], axis=1) & bool(data.patient_rest1[i1] and data.patient_rest2[i2])
    return S, sp, ~np.any(bad, axis=1), arm_ok, pt_ok


def evaluate_block(data: TriadData, item) -> dict:
    """One task: the pairs of a block whose LB does not exceed ``threshold``; their best ``keep``
    feasible triads ``(S, i1, i2, ie)``, rejection counts, evaluated and pruned triad counts."""
    pairs, lbs, threshold = item
    E = data.vis.shape[0]
    best: list = []
    rej = dict.fromkeys(REJECTIONS, 0)
    evaluated = pruned = 0
    for (i1, i2), lb in zip(pairs, lbs):
        if lb > threshold:
            pruned += E
            continue
        S, sp, sh, am, pt = pair_scores(data, i1, i2)
        evaluated += E
        rej["port_spacing"] += int(np.sum(~sp))
        rej["shaft_clearance"] += int(np.sum(~sh))
        rej["arm_clearance"] += int(np.sum(~am))
        rej["patient_clearance"] += int(np.sum(~pt))
        ok = np.flatnonzero(sp & sh & am & pt)
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
    rej = dict.fromkeys(REJECTIONS, 0)
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
    return place(st, tol, None, workers=workers, scheduler=scheduler, progress=progress, prune=prune, keep=keep)


def _moved(sc, pose):
    """Scenario ``sc`` with its arm's base at ``pose = (position, rpy)``."""
    return sc.with_(robot=replace(sc.robot, base_position=tuple(pose[0]), base_rpy=tuple(pose[1])))


def _share_maps(scenarios, done: list) -> None:
    """Each arm of ``scenarios`` (one per base) takes the reachability map of an arm in ``done`` that differs
    from it only by the base's position, moved with the base (:func:`errplan.kinematics.urdf.reachmap.
    share_translated`), instead of building its own; then joins ``done``."""
    from ..kinematics import arm_for
    from ..kinematics.urdf.reachmap import share_translated

    for s_b in scenarios:
        a = arm_for(s_b.robot)
        for src in done:
            if share_translated(a, src):
                break
        done.append(a)


def _union(parts: list) -> np.ndarray:
    """The rows of the arrays ``parts`` once each, in order of first appearance."""
    seen, out = set(), []
    for P in parts:
        for p in np.asarray(P, float).reshape(-1, 3):
            key = tuple(p.tolist())
            if key not in seen:
                seen.add(key)
                out.append(p)
    return np.array(out, float).reshape(-1, 3)


def place(st, tol, bases: dict | None, *, workers: int | None = 1, scheduler: str | None = None,
          progress: Progress | None = None, prune: bool = True, keep: int = 6, patient=None) -> dict[str, Any]:
    """The triad search over instrument candidates. ``bases`` None: each arm at its own base, the
    candidates are the ports (``triad_placement``). Else ``{arm: ((position, rpy), ...)}``: an instrument
    candidate is a (base, port) pair, base-major (:mod:`errplan.tolerance.setup`), the arms also checked at
    rest (with ``arm_clearance``) and against ``patient`` (``(BodySolid, patient_clearance)``, or None)."""
    from ..cluster import map_tasks
    from ..fields import ErrorSet, KernelEvaluator, error_set
    from ..fields.compute import anatomy_model
    from ..models import build_arm

    t0 = time.perf_counter()
    o = tol.options
    setup = bases is not None
    where = tol.kind if setup else "triad_placement"
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
    shared_arms: list = []  # the arms whose reachability maps the moved ones take (setup placement)
    jobs = {}  # per arm, per base
    models = {}
    scs = {}  # per arm, per base: the arm's scenario with its base there
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
        scs[name] = [sc] if not setup else [build_arm(_moved(sc, b), name).scenario for b in bases[name]]
        if setup:
            _share_maps(scs[name], shared_arms)
        roles[name] = (_union([_role_points(st, o, name, s_b, model, spacing, region) for s_b in scs[name]]) if setup
                       else _role_points(st, o, name, sc, model, spacing, region))
        k = float(o.get("gain", sc.controller.gain))
        off = es.port_corners() - np.asarray(es.base_port, float)
        jobs[name] = [CoverJob(PlacementJob(X, k, bound, evaluator=KernelEvaluator(s_b)), model, off)
                      for s_b in scs[name]]
    model_e = models[n1]
    roles["endoscope"] = _role_points(st, o, "endoscope", sc1, model_e, spacing, region)
    for r, pts in roles.items():
        if len(pts) == 0:
            raise ErrplanError(f"{where}: no candidate port for {r!r} (at spacing {spacing:g} m on the body wall)")
        if len(pts) > MAX_CANDIDATES:
            raise ErrplanError(f"{where} spacing = {spacing:g}: {len(pts)} candidates for {r!r}, more than the "
                               f"budget of {MAX_CANDIDATES:,}: use a larger spacing")
    n_a, n_b, n_e = len(roles[n1]), len(roles[n2]), len(roles["endoscope"])
    nb = {n1: len(scs[n1]), n2: len(scs[n2])}
    N = {name: nb[name] * len(roles[name]) for name in (n1, n2)}
    cells = (n_a * n_b + (n_a + n_b) * n_e * 2) * T + (N[n1] * N[n2] * T if setup else 0)
    if cells > MAX_TRIAD_CELLS:
        raise ErrplanError(f"{where} spacing = {spacing:g}: {N[n1]} x {N[n2]} x {n_e} candidates over {T} targets "
                           f"would need {cells:.3g} per-target values (max {MAX_TRIAD_CELLS:,}): use a larger spacing "
                           "or resolution" + (" or fewer bases" if setup else ""))
    t1 = time.perf_counter()
    covs = {}
    for name, sc in ((n1, sc1), (n2, sc2)):
        items = [_candidate_item(sc, c) for c in roles[name]]
        per = max(1, math.ceil(len(items) * nb[name] / max(MIN_TASKS, 1)))
        batches = [(b, items[i:i + per]) for b in range(nb[name]) for i in range(0, len(items), per)]

        def tick(done, total, name=name):
            if progress:
                progress(0.5 * done / total, f"{name} candidates {done}/{total}")

        packed = []
        for part in map_tasks(cover_base_batch, jobs[name], batches, workers=workers, scheduler=scheduler,
                              progress=tick):
            packed.extend(part)
        covs[name] = np.array([np.unpackbits(p, count=T).astype(bool) for p in packed]).reshape(N[name], T)
    cover_s = time.perf_counter() - t1
    # endoscope: lens, axis, visibility; hull points conv(box_e ∪ {lens})
    P1, P2, PE = roles[n1], roles[n2], roles["endoscope"]
    port_of = {n1: np.tile(np.arange(n_a), nb[n1]), n2: np.tile(np.arange(n_b), nb[n2])}
    base_of = {n1: np.repeat(np.arange(nb[n1]), n_a), n2: np.repeat(np.arange(nb[n2]), n_b)}
    axes_e = geo.optical_axis(PE, np.asarray(endo.look_at, float)[None, :])
    lens = PE + endo.insertion * axes_e
    vis = np.array([geo.visible(X, lens[i], axes_e[i], endo.fov, endo.depth, model_e) for i in range(len(PE))])
    off_e = geo.endoscope_box(endo) - np.asarray(endo.port.estimate, float)
    hull_e = np.concatenate([PE[:, None, :] + off_e[None], lens[:, None, :]], axis=1)
    boxes = {name: roles[name][:, None, :] + jobs[name][0].offsets[None] for name in (n1, n2)}
    D1 = np.full((len(P1), len(PE), T), np.nan)
    D2 = np.full((len(P2), len(PE), T), np.nan)
    done = {n1: np.zeros(len(P1), bool), n2: np.zeros(len(P2), bool)}
    dist_t = [0.0, 0]

    def ensure(rows1, rows2):
        """Exact shaft distances of these instrument ports to every endoscope candidate, per target (tasks of
        a few ports each)."""
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
    ARM = arm_done = ARM_REST = None
    PAT = PREST = None
    kin, geos, Qc, Qrest = {}, {}, {}, {}
    need_geo = arm_c is not None or patient is not None
    if need_geo:
        from ..kinematics import arm_for
        from ..kinematics.urdf.collision import ArmCollision

        for name in (n1, n2):
            kin[name] = [arm_for(s_b.robot) for s_b in scs[name]]
            try:
                geos[name] = tuple(ArmCollision.from_arm(a) for a in kin[name])
            except ErrplanError as err:
                key = (f"[setup] arm_clearance = {arm_c:g}" if arm_c is not None
                       else f"[setup] patient_clearance = {patient[1]:g}")
                raise ErrplanError(f"{where}: {key}: arm {name!r}: {err}") from None
        Pc = {n1: P1, n2: P2}
        Qc = {name: np.full((N[name], T, kin[name][0].n), np.nan) for name in (n1, n2)}
        qdone = {name: np.zeros(N[name], bool) for name in (n1, n2)}
        if setup:  # each candidate's arm at rest: the wrist on the shaft from its rest tip through its port
            for name in (n1, n2):
                rest = np.asarray(st.rest(name), float)
                L = float(st.arm(name).instrument.length)
                Qrest[name] = np.full((N[name], kin[name][0].n), np.nan)
                for b in range(nb[name]):
                    rows = np.flatnonzero(base_of[name] == b)
                    u = geo.unit(rest[None] - Pc[name][port_of[name][rows]])
                    q, ok = kin[name][b].inverse(rest[None] - L * u)
                    Qrest[name][rows] = np.where(np.asarray(ok, bool)[:, None], q, np.nan)

        def configs(name, rows):
            """Each arm at the targets its candidates ``rows`` cover: the wrist at t - L (t - p)/|t - p|."""
            rows = [r for r in rows if not qdone[name][r]]
            if not rows:
                return
            L = float(st.arm(name).instrument.length)
            for b in range(nb[name]):
                rb = [r for r in rows if base_of[name][r] == b]
                if not rb:
                    continue
                cov = covs[name][rb]  # (r, T)
                u = geo.unit(X[None] - Pc[name][port_of[name][rb]][:, None])
                W = X[None] - L * u
                q, ok = kin[name][b].inverse(W[cov])
                Qr = np.full((len(rb), T, kin[name][b].n), np.nan)
                Qr[cov] = np.where(np.asarray(ok, bool)[:, None], q, np.nan)
                Qc[name][rb] = Qr
            qdone[name][rows] = True

    if arm_c is not None:
        ARM = np.ones((N[n1], N[n2], T), bool)
        arm_done = np.zeros((N[n1], N[n2]), bool)
        ARM_REST = np.ones((N[n1], N[n2]), bool) if setup else None
        d12 = np.linalg.norm(P1[:, None] - P2[None], axis=-1)

    def ensure_arms(pairs):
        """Arm clearances of the instrument pairs ``pairs`` at the targets both cover (module docstring); for a
        setup first at rest, the targets only of the pairs clear there and whose arms clear the patient at
        rest (every setup of the others is rejected already)."""
        t = time.perf_counter()
        todo = sorted({(i, j) for i, j in pairs if not arm_done[i, j]})
        check = [(i, j) for i, j in todo if d12[port_of[n1][i], port_of[n2][j]] >= float(o["port_spacing"])]
        total = 0
        if setup:
            if PREST is not None:
                check = [(i, j) for i, j in check if PREST[n1][i] and PREST[n2][j]]
            if check:
                per = max(1, math.ceil(len(check) / max(MIN_TASKS, 1)))
                chunks = [check[k:k + per] for k in range(0, len(check), per)]
                items = [[(int(base_of[n1][i]), int(base_of[n2][j]), Qrest[n1][i][None], Qrest[n2][j][None])
                          for i, j in ch] for ch in chunks]
                for ch, part in zip(chunks, map_tasks(arm_rows, (geos[n1], geos[n2], float(arm_c)), items,
                                                      workers=workers, scheduler=scheduler)):
                    for (i, j), ok in zip(ch, part):
                        ARM_REST[i, j] = ok
                total += len(check)
                check = [(i, j) for i, j in check if ARM_REST[i, j]]
        configs(n1, sorted({i for i, _ in check}))
        configs(n2, sorted({j for _, j in check}))
        where_t = [(i, j, np.flatnonzero(covs[n1][i] & covs[n2][j])) for i, j in check]
        where_t = [w for w in where_t if len(w[2])]
        n_t = sum(len(w[2]) for w in where_t)
        if n_t:
            per = max(1, math.ceil(n_t / max(MIN_TASKS, 1)))
            chunks, cur, size = [], [], 0
            for w in where_t:
                cur.append(w)
                size += len(w[2])
                if size >= per:
                    chunks.append(cur)
                    cur, size = [], 0
            if cur:
                chunks.append(cur)
            items = [[(int(base_of[n1][i]), int(base_of[n2][j]), Qc[n1][i, tt], Qc[n2][j, tt]) for i, j, tt in ch]
                     for ch in chunks]
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
        arm_t[2] += total + n_t

    def ensure_all(rows1, rows2, pairs):
        ensure(sorted({int(port_of[n1][r]) for r in rows1}), sorted({int(port_of[n2][r]) for r in rows2}))
        if arm_c is not None:
            ensure_arms(pairs)

    # the patient: every candidate's links from the body at the targets it covers and at rest (yes/no; the
    # exact distances for the reported setups only)
    pat_t = [0.0, 0]
    if patient is not None:
        t = time.perf_counter()
        body, pc = patient
        PAT, PREST = {}, {}
        for name in (n1, n2):
            configs(name, list(range(N[name])))
            items, where_q = [], []
            for b in range(nb[name]):
                rows = np.flatnonzero(base_of[name] == b)
                cov = covs[name][rows]
                items.append((b, np.concatenate([Qc[name][rows][cov], Qrest[name][rows]])))
                where_q.append((rows, cov))
            parts = map_tasks(patient_rows, (geos[name], body, float(pc)), items, workers=workers,
                              scheduler=scheduler)
            PAT[name] = np.ones((N[name], T), bool)
            PREST[name] = np.zeros(N[name], bool)
            for (rows, cov), ok in zip(where_q, parts):
                k = int(cov.sum())
                blk = np.ones((len(rows), T), bool)
                blk[cov] = ok[:k]
                PAT[name][rows] = blk
                PREST[name][rows] = ok[k:]
                pat_t[1] += len(ok)
        pat_t[0] = time.perf_counter() - t

    mstar, mtol = float(o["manipulation_angle"]), float(o["manipulation_tolerance"])
    U1, U2, UE = (geo.unit(X[None] - P[:, None]) for P in (P1, P2, lens))  # (N, T, 3) unit vectors p -> t
    M = geo.unit_angles(U1, U2)  # (N1, N2, T): m(t)
    A1 = geo.unit_angles(U1, UE)  # (N1, E, T): a_1(t)
    A2 = geo.unit_angles(U2, UE)
    pat = {} if PAT is None else {name: (PAT[name], PREST[name]) for name in (n1, n2)}
    data = TriadData(covs[n1], covs[n2], vis, ((M - mstar) / mtol) ** 2, A1, A2, D1, D2,
                     np.linalg.norm(P1[:, None] - P2[None], axis=-1), np.linalg.norm(P1[:, None] - PE[None], axis=-1),
                     np.linalg.norm(P2[:, None] - PE[None], axis=-1), float(o["coverage_weight"]),
                     float(o["azimuth_tolerance"]), float(o["port_spacing"]), float(st.shaft_clearance), int(keep),
                     ARM, None if arm_c is None else float(arm_c), arm_done,
                     port_of[n1] if setup else None, port_of[n2] if setup else None,
                     pat[n1][0] if pat else None, pat[n2][0] if pat else None,
                     pat[n1][1] if pat else None, pat[n2][1] if pat else None, ARM_REST)
    t3 = time.perf_counter()
    sub = (lambda f, m: progress(0.5 + 0.5 * f, m)) if progress else None
    found = search(data, prune=prune, workers=workers, scheduler=scheduler, progress=sub, ensure=ensure_all)
    exact, exact_rest = {}, {}

    def exact_arm(i1, i2) -> np.ndarray:
        """(T,) the exact arm clearances of a reported pair at the targets both instruments cover (the
        search keeps only whether they are at least arm_clearance)."""
        from ..kinematics.urdf.collision import clearances

        if (i1, i2) not in exact:
            tt = np.flatnonzero(covs[n1][i1] & covs[n2][i2])
            row = np.full(T, np.inf)
            g1, g2 = geos[n1][base_of[n1][i1]], geos[n2][base_of[n2][i2]]
            row[tt] = clearances(g1, Qc[n1][i1, tt], g2, Qc[n2][i2, tt])
            exact[(i1, i2)] = row
            if setup:
                exact_rest[(i1, i2)] = float(clearances(g1, Qrest[n1][i1][None], g2, Qrest[n2][i2][None])[0])
        return exact[(i1, i2)]

    exact_pat: dict = {}

    def exact_patient(name, i) -> tuple[np.ndarray, float]:
        """((T,) the exact link-to-body distances of a reported candidate at the targets it covers (inf
        elsewhere), its distance at rest)."""
        from ..kinematics.urdf.collision import patient_clearances

        if (name, i) not in exact_pat:
            tt = np.flatnonzero(covs[name][i])
            g = geos[name][base_of[name][i]]
            row = np.full(T, np.inf)
            row[tt] = patient_clearances(g, Qc[name][i, tt], patient[0])
            exact_pat[(name, i)] = (row, float(patient_clearances(g, Qrest[name][i][None], patient[0])[0]))
        return exact_pat[(name, i)]

    def tie_key(i1, i2, ie) -> float:
        """The smallest arm clearance over the covered targets and at rest (larger wins a tie)."""
        c = data.cov1[i1] & data.cov2[i2] & data.vis[ie]
        row = exact_arm(i1, i2)[c]
        return min(float(row.min()) if len(row) else math.inf, exact_rest[(i1, i2)])

    ties = 0
    if setup and arm_c is not None and found["best"]:
        # ties go to the larger smallest arm clearance: every triad tied with the best must be in the list
        k_all = int(keep)
        while len(found["best"]) == k_all and _tied(found["best"][-1][0], found["best"][0][0]):
            k_all *= 2
            found = search(replace(data, keep=k_all), prune=prune, workers=workers, scheduler=scheduler,
                           progress=sub, ensure=ensure_all)
        group = [b for b in found["best"] if _tied(b[0], found["best"][0][0])]
        ties = len(group)
        group.sort(key=lambda b: (-tie_key(*b[1:]), b[1:]))
        rest_list = [b for b in found["best"] if not _tied(b[0], found["best"][0][0])]
        found["best"] = (group + rest_list)[:keep]
    search_s = time.perf_counter() - t3 - dist_t[0] - arm_t[0]
    dist_s = dist_t[0]

    def figures(s, i1, i2, ie) -> dict:
        j1, j2 = data.ports(i1, i2)
        c = data.cov1[i1] & data.cov2[i2] & data.vis[ie]
        m = M[j1, j2]
        cl = np.minimum(D1[j1, ie], D2[j2, ie])[c]
        ac = exact_arm(i1, i2)[c] if ARM is not None else np.zeros(0)
        out = {"ports": {n1: P1[j1].tolist(), n2: P2[j2].tolist(), "endoscope": PE[ie].tolist()}, "score": s,
               "coverage": {n1: float(np.mean(data.cov1[i1])), n2: float(np.mean(data.cov2[i2])),
                            "both": float(np.mean(c))},
               "visible": float(np.mean(data.vis[ie])),
               "manipulation_angle": {"mean": float(np.mean(m)), "min": float(np.min(m)), "max": float(np.max(m))},
               "azimuth_difference_mean": float(np.mean(np.abs(A1[j1, ie] - A2[j2, ie]))),
               "port_spacing_min": float(min(data.d12[j1, j2], data.d1e[j1, ie], data.d2e[j2, ie])),
               "shaft_clearance_min": float(cl.min()) if len(cl) else None,
               "arm_clearance_min": float(ac.min()) if len(ac) else None, "indices": [int(i1), int(i2), int(ie)]}
        if setup:
            b1, b2 = int(base_of[n1][i1]), int(base_of[n2][i2])
            out["bases"] = {n1: {"position": list(bases[n1][b1][0]), "rpy": list(bases[n1][b1][1])},
                            n2: {"position": list(bases[n2][b2][0]), "rpy": list(bases[n2][b2][1])}}
            out["base_indices"] = [b1, b2]
            out["arm_clearance_rest"] = exact_rest.get((i1, i2)) if ARM is not None else None
            if PAT is not None:
                (r1, z1), (r2, z2) = exact_patient(n1, i1), exact_patient(n2, i2)
                pd = np.concatenate([r1[c], r2[c], [z1, z2]])
                out["patient_clearance_min"] = float(pd.min())
                out["patient_clearance_targets"] = {n1: np.where(c, r1, np.nan).tolist(),
                                                    n2: np.where(c, r2, np.nan).tolist()}
                out["patient_clearance_rest"] = {n1: z1, n2: z2}
            else:
                out["patient_clearance_min"] = None
        return out

    if not found["best"]:
        arms = "" if arm_c is None else f", arm clearance {arm_c:g} m"
        pat_s = "" if patient is None else f", patient clearance {patient[1]:g} m"
        what = "setup" if setup else "triad"
        raise ErrplanError(f"{where}: no {what} of the {found['triads']} meets the hard constraints (port spacing "
                           f"{o['port_spacing']:g} m, shaft clearance {st.shaft_clearance:g} m{arms}{pat_s} at "
                           "covered targets" + (" and at rest)" if setup else ")"))
    ranked = [figures(*b) for b in found["best"]]
    rejected = dict(found["rejected"], arm_clearance=found["rejected"]["arm_clearance"] if arm_c is not None
                    else None)
    if setup:
        rejected["patient_clearance"] = found["rejected"]["patient_clearance"] if patient is not None else None
    else:
        rejected.pop("patient_clearance")
    unit = "setups" if setup else "triads"
    out = {
        "best": ranked[0], "ranked": ranked[1:],
        "candidates": {n1: P1.tolist(), n2: P2.tolist(), "endoscope": PE.tolist()},
        "targets": T,
        "rejected": rejected,
        "search": {"triads": found["triads"], "pairs": found["pairs"], "evaluated": found["evaluated"],
                   "pruned": found["pruned"], "pruned_share": found["pruned"] / max(found["triads"], 1),
                   "waves": found["waves"], "method": "branch and bound" if prune else "brute force",
                   "rejected_over": f"the evaluated {unit}" if arm_c is None else
                   f"the evaluated {unit} (arm_clearance: those whose instrument ports meet port_spacing)"},
        "instruments": [n1, n2], "region": {a: list(region[a]) for a in "xyz"}, "resolution": res,
        "weights": {"coverage_weight": data.W, "manipulation_angle": mstar, "manipulation_tolerance": mtol,
                    "azimuth_tolerance": data.a_tol},
        "port_spacing": data.port_spacing, "shaft_clearance": data.shaft_clearance,
        "arm_checks": "off" if arm_c is None else (f"on (arm_clearance {arm_c:g} m, "
                                                   f"{found['rejected']['arm_clearance']:,} {unit} rejected)"),
        "arm_clearance": None if arm_c is None else float(arm_c),
        "workers": workers, "scheduler": scheduler,
        "timing": {"coverage_s": cover_s, "distances_s": dist_s, "search_s": search_s,
                   "distance_rows": dist_t[1], "distance_rows_of": len(P1) + len(P2),
                   "arm_s": arm_t[0], "arm_pairs": arm_t[1], "arm_queries": arm_t[2]},
        "_arrays": {"targets": X, "lens": lens, "data": data,
                    # the best triad's arms per target (T, n) (NaN where not computed; arm checks on)
                    "arm_q": None if not Qc else {n1: Qc[n1][found["best"][0][1]],
                                                  n2: Qc[n2][found["best"][0][2]]}},
        "seconds": time.perf_counter() - t0,
    }
    if setup:
        out["bases"] = {name: [{"position": list(p), "rpy": list(r)} for p, r in bases[name]] for name in (n1, n2)}
        out["patient_clearance"] = None if patient is None else float(patient[1])
        out["search"]["setups"] = out["search"]["triads"]
        out["search"]["ties"] = ties
        out["search"]["tie_break"] = ("the larger smallest arm clearance (covered targets and rest), then the "
                                      "candidate indices" if arm_c is not None else "the candidate indices")
        out["timing"].update(patient_s=pat_t[0], patient_queries=pat_t[1])
        out["_arrays"]["arm_rest_q"] = None if not Qrest else {n1: Qrest[n1][found["best"][0][1]],
                                                                n2: Qrest[n2][found["best"][0][2]]}
        out["_arrays"]["base_of"] = base_of
        out["_arrays"]["port_of"] = port_of
    return out


def _tied(s: float, best: float) -> bool:
    """Whether score ``s`` ties ``best`` (equal up to rounding: the bases enter S only through coverage, so
    equal coverage gives the same sums)."""
    return s <= best + 1e-9 * max(1.0, abs(best))
