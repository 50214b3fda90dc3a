"""Close the loop with measured data: residual -> missing effect -> model -> error before and after.

Pipeline (:func:`calibrate`):

1. **Replay with the declared model.** The declared model is the scenario's truth as it stands
   (arm, shaft, ``port.position``, the tip load of its error set closest to 0 — P2's scenarios
   fix one — and any ``[effects]`` it already declares). *Pose residual*: tracked
   tip minus the model's tracked tip at the encoder angles, every row at once; port friction's
   direction ``u`` for row t+1 is the motion the command of step t produced under the declared
   model, ``x_model(q(t+1)) - x_model(q(t))`` from two consecutive encoder rows of the run
   (:func:`motion_model`, :meth:`MeasuredData.commanded_directions`; docs/physics.md). *Trajectory
   residual*: the controller (:class:`errplan.simulation.ControllerModel`, at each run's gain)
   re-simulated noise-free on the model from each run's first encoder reading, step for step
   against the measured tracked tips, all runs batched. ``trajectory_rms_*`` covers each run's
   approach (steps 1 .. first arrival within ``max(0.5 mm, 4 noise floors)`` of the target: the
   paths P1 Fig. 8 compares), leaving out runs that diverge or cycle (see :func:`approach_mask`);
   the RMS over every step >= 1 of every run is reported beside it. After arrival the measured tip
   only jitters with the noise the controller chases, which a noise-free replay cannot predict
   (and a friction model makes the replay chatter there).
2. **Noise floor** (:func:`noise_floor`): the pose residual is fitted by a flexible smooth model
   — on compact clusters of rows (k-means of the model tip positions, 60-240 rows each) a
   quadratic or cubic Legendre polynomial (cluster size and degree by AIC) in the local tip
   position times ``[1, u_y, u_z]`` (``u`` friction's direction, so anything linear in the motion
   direction, like port friction, is smooth too) —
   and the noise floor is the degrees-of-freedom corrected RMS of what is left,
   ``sqrt(RSS / (2n - 2m))``. Every effect of the catalogue and the usual unmodelled ones (link
   lengths, scale errors) are smooth in the configuration, so what the local polynomials cannot
   follow is the measurement noise (tracker, plus encoder noise seen through the Jacobian).
3. **Candidates** (:mod:`errplan.effects`): every effect alone, every pair, and the best pair
   plus each other effect; each fitted by nonlinear least squares on the pose residual, with
   ``s^2 (J^T J)^-1`` uncertainties and an identifiability check (unidentifiable combinations are
   not selectable and say why).
4. **Selection.** Among the selectable candidates (and "none") in order of BIC
   (``N ln(RSS/N) + p ln N``, ``N = 2n``), the first whose BIC and held-out pose error (folds of
   whole runs, seeded; each fold refitted from the full fit) are below those of every candidate
   with one effect fewer. Clean data select nothing; an effect that does not pay for its
   parameters on both counts is not added.
5. **Explained?** The selected model's residual is tested for structure with the same flexible
   model: an F test of the smooth part and its size ``s`` (its RMS after removing what the fit of
   pure noise would absorb). ``explained`` is false when the structure is significant
   (p < 1e-3) and ``s`` is at least the noise floor, i.e. the residual RMS is well above it.

All RMS values (pose, trajectory, noise floor) are **per coordinate**: the square root of the
mean over rows and over y, z of the squared residual. The noise floor therefore estimates the
tracker's sigma directly.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from .effects import CATALOGUE, EffectModel, predict_tracked
from .errors import DataError, ErrplanError
from .experiment import MeasuredData

STRUCTURE_P = 1e-3          # F-test level for "the residual has structure"
STRUCTURE_RATIO = 1.0       # structured RMS >= this x noise floor -> not explained
DEFAULT_FOLDS = 5
TEXT_CANDIDATES = 10        # candidates listed on stdout (all of them in the JSON)


def arrival_tolerance(noise_sigma: float) -> float:
    """Distance (m) within which a measured run counts as arrived: max(0.5 mm, 4 noise floors)."""
    return max(5e-4, 4.0 * noise_sigma)


# ----------------------------------------------------------------------------- residuals
def declared_plant(sc):
    """The declared model: the scenario's truth (``[port] position``, its tip load, the effects it
    already declares), no noise (:func:`errplan.experiment.truth_plant`)."""
    from .experiment import truth_plant

    return truth_plant(sc, effects=True, noise=False)


def check_against_model(data: MeasuredData, plant, what: str = "the declared model") -> None:
    """Every row's encoder angles must give a wrist from which the shaft reaches through the port."""
    w = plant.wrist(data.q)
    ok = plant.shaft_reaches(w) & plant.arm.within_limits(plant.link_angles_q(data.q), tol=0.05)
    if not np.all(ok):
        i = int(np.flatnonzero(~ok)[0])
        raise DataError(f"{data.source}: row {i + 1} (run {data.run_ids[data.run[i]]!r}, step {data.step[i]}): encoder "
                        f"angles {np.round(data.q[i], 5).tolist()} put the wrist at {np.round(w[i], 4).tolist()}, "
                        f"where {what} cannot hold the shaft through the port at "
                        f"{np.round(plant.true_port, 4).tolist()} or is outside the joint limits "
                        f"(is the data from this scenario?)")
    # every effect of the catalogue moves the tip by mm to cm; a tracked tip farther from the
    # model's tip than the whole shaft, or a target outside anything the tip can reach, is not
    # measured data of this scenario (and would only overflow the fits)
    L = float(plant.length)
    with np.errstate(all="ignore"):
        model_tip = plant.tip(data.q)
        off = np.linalg.norm(data.tip - model_tip, axis=-1)
    bad = np.flatnonzero(~(off < L))
    if len(bad):
        i = int(bad[0])
        raise DataError(f"{data.source}: row {i + 1} (run {data.run_ids[data.run[i]]!r}, step {data.step[i]}): tracked tip "
                        f"{_pt(data.tip[i])} is {_m(off[i])} from {what}'s tip {_pt(model_tip[i])} at its encoder "
                        f"angles, more than the shaft length {L:g} m (is the data from this scenario?)")
    reach = 2.0 * (L + float(plant.arm.l1) + float(plant.arm.l2))  # a bound on the tip workspace's diameter
    with np.errstate(all="ignore"):
        far = np.linalg.norm(data.target - model_tip, axis=-1)
    bad = np.flatnonzero(~(far < reach))
    if len(bad):
        i = int(bad[0])
        raise DataError(f"{data.source}: row {i + 1} (run {data.run_ids[data.run[i]]!r}): target {_pt(data.target[i])} is "
                        f"{_m(far[i])} from the tip, farther than the robot can reach ({reach:g} m; is the data from "
                        f"this scenario?)")


def _pt(x) -> str:
    return "[" + ", ".join(f"{float(v):.6g}" for v in x) + "]"


def _m(d: float) -> str:
    return f"{d:.4g} m" if math.isfinite(d) else "more than 1e300 m"


def rms(r: np.ndarray) -> float:
    """Per-coordinate RMS of residual vectors (n, 2)."""
    r = np.asarray(r, float)
    return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")


def motion_model(sc):
    """``x_model`` of docs/physics.md ``port_friction``: the scenario's arm, shaft (its tip load) and
    ``port.position``, no effects. Friction's direction is the motion a command produces under it,
    for the bench (:func:`errplan.experiment.run_experiment`), the replay and the fits alike."""
    from .experiment import truth_plant

    return truth_plant(sc, effects=False, noise=False)


def pose_residual(data: MeasuredData, plant, u: np.ndarray | None = None) -> np.ndarray:
    """Tracked tip minus the model's tracked tip at the encoder angles (n, 2), m. ``u`` (friction's
    direction per row) defaults to :meth:`MeasuredData.commanded_directions` under
    ``plant.declared()``."""
    u = data.commanded_directions(plant.declared()) if u is None else u
    return data.tip - predict_tracked(plant, data.q, u)


def _controller_jacobian(ctrl, plant, q: np.ndarray) -> np.ndarray:
    """The controller's ``Jhat`` at encoder angles ``q`` (r, 2); the flexion controller reads the
    model's end poses there (noise-free)."""
    if ctrl.jacobian == "rigid":
        return ctrl.J_hat(q)
    with np.errstate(invalid="ignore", divide="ignore"):
        return ctrl.J_hat(q, plant)


def replay(data: MeasuredData, plant, ctrl, model=None) -> tuple[np.ndarray, np.ndarray]:
    """Re-simulate every run on ``plant`` with controller ``ctrl`` from its first encoder reading.

    Noise-free and quasi-static, exactly the loop of :func:`errplan.simulation.simulate`, batched
    over runs; friction's direction is the motion each command produces under ``model`` (default
    ``plant.declared()``; :func:`motion_model`). Returns the predicted tracked tip for every row
    (n, 2) and, per run, whether the replay stayed in the workspace for the whole measured length
    (runs,). A replay that leaves the workspace holds its last state.
    """
    from .metrics import inv2

    model = plant.declared() if model is None else model
    first = data.first
    R = data.runs
    lengths = data.lengths
    T = int(lengths.max()) if R else 0
    # rows of each step, in run order (O(rows) memory, whatever the run lengths)
    by_step = np.lexsort((data.run, data.step))
    bounds = np.searchsorted(data.step[by_step], np.arange(T + 1))
    first = first[np.argsort(data.run[first])]  # run r's step 0
    q = data.q[first].copy()
    target = data.target[first]
    gain = data.gain[first]
    u = np.zeros((R, 2))
    alive = np.ones(R, bool)
    pred = np.zeros_like(data.tip)
    off = np.asarray(plant.tracker_offset, float)
    tracked = np.zeros((R, 2))
    for t in range(T):
        with np.errstate(invalid="ignore", divide="ignore"):
            tr = plant.tip(q, u) + off
        tracked = np.where(alive[:, None], tr, tracked)
        rows_t = by_step[bounds[t]:bounds[t + 1]]
        pred[rows_t] = tracked[data.run[rows_t]]
        if t == T - 1:
            break
        has = lengths > t
        err = target - tracked
        with np.errstate(invalid="ignore", divide="ignore"):
            Jinv, singular = inv2(_controller_jacobian(ctrl, plant, q))
            dq = gain[:, None] * np.einsum("rij,rj->ri", np.nan_to_num(Jinv), err)
        q_new = q + dq
        with np.errstate(invalid="ignore", divide="ignore"):
            ok = (~singular & plant.arm.within_limits(plant.link_angles_q(q_new))
                  & plant.shaft_reaches(plant.wrist(q_new)) & np.all(np.isfinite(q_new), axis=-1))
        step_ok = alive & ok & has
        with np.errstate(invalid="ignore", divide="ignore"):
            u = np.where(step_ok[:, None], model.motion_direction(q, q_new, u), u)
        q = np.where(step_ok[:, None], q_new, q)
        alive &= ok | ~has
    return pred, alive


def approach_mask(data: MeasuredData, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows (n,) compared by the trajectory residual, and the runs (runs,) left out.

    A run's approach is steps 1 .. the first step whose tracked tip is within ``tolerance`` of the
    target: after arrival the measured tip only jitters with the noise the controller chases,
    which no noise-free replay predicts. A run that never arrives counts whole if its distance to
    the target never grew beyond its start distance after the first command (a slow gain), and is
    left out if it did (it diverged or cycles: the controller is not contracting there,
    ||G|| >= 1, and the path amplifies the measurement noise, so no replay can follow it step for
    step). The first command is not held against a run: it starts the tip moving from rest, and
    port friction then holds the tip back by up to its size, once, in a run that converges.
    """
    e = np.linalg.norm(data.tip - data.target, axis=-1)
    big = np.iinfo(np.int64).max
    arrive = np.full(data.runs, big)
    idx = np.flatnonzero((e < tolerance) & (data.step >= 1))
    np.minimum.at(arrive, data.run[idx], data.step[idx])
    e0 = e[data.first][np.argsort(data.run[data.first])]
    late = data.step >= 2
    elate = np.zeros(data.runs)
    np.maximum.at(elate, data.run[late], e[late])
    unsettled = (arrive == big) & (elate > e0 + tolerance)
    mask = (data.step >= 1) & (data.step <= arrive[data.run]) & ~unsettled[data.run]
    return mask, unsettled


def trajectory_errors(data: MeasuredData, plant, ctrl, tolerance: float, model=None) -> tuple[float, float]:
    """Per-coordinate RMS of measured minus replayed tracked tips over the approach rows (see
    :func:`approach_mask`; NaN if there are none) and over every step >= 1 of every run."""
    pred, _ = replay(data, plant, ctrl, model)
    r = data.tip - pred
    mask, _ = approach_mask(data, tolerance)
    return (rms(r[mask]) if np.any(mask) else float("nan")), rms(r[data.step >= 1])


# ----------------------------------------------------------------------------- noise floor
def _legendre_total(x: np.ndarray, degree: int) -> np.ndarray:
    """Total-degree Legendre features of 2-D points in [-1, 1]^2 (n, (d+1)(d+2)/2)."""
    from numpy.polynomial import legendre

    V0 = legendre.legvander(x[:, 0], degree)
    V1 = legendre.legvander(x[:, 1], degree)
    cols = [V0[:, i] * V1[:, j] for i in range(degree + 1) for j in range(degree + 1 - i)]
    return np.stack(cols, axis=-1)


def _nearest(x: np.ndarray, c: np.ndarray, block: int = 2**20) -> np.ndarray:
    """Index of the nearest centre (k, 2) for each point (n, 2), in blocks of rows so that the
    distance table never exceeds ``block`` entries (the number of clusters grows with the rows)."""
    out = np.empty(len(x), int)
    step = max(1, block // max(len(c), 1))
    for i in range(0, len(x), step):
        xb = x[i:i + step]
        out[i:i + len(xb)] = np.argmin(np.sum((xb[:, None, :] - c[None]) ** 2, axis=2), axis=1)
    return out


def kmeans_labels(x: np.ndarray, clusters: int, iters: int = 30) -> np.ndarray:
    """Deterministic k-means of points (n, 2): farthest-point initialisation from the point
    nearest the centroid, then Lloyd iterations. Returns labels (n,) in 0..clusters-1."""
    n = len(x)
    clusters = max(1, min(clusters, n))
    idx = [int(np.argmin(np.linalg.norm(x - x.mean(axis=0), axis=1)))]
    d = np.linalg.norm(x - x[idx[0]], axis=1)
    for _ in range(clusters - 1):
        i = int(np.argmax(d))
        idx.append(i)
        d = np.minimum(d, np.linalg.norm(x - x[i], axis=1))
    c = x[idx].copy()
    lab = np.zeros(n, int)
    for _ in range(iters):
        new = _nearest(x, c)
        if np.array_equal(new, lab) and _ > 0:
            break
        lab = new
        for k in range(len(c)):
            m = lab == k
            if np.any(m):
                c[k] = x[m].mean(axis=0)
    _, lab = np.unique(lab, return_inverse=True)
    return lab


@dataclass
class LocalBasis:
    """The flexible smooth model: on each cluster of rows (``labels``, k-means of the model tip
    positions) a Legendre polynomial of ``degree`` in the local tip coordinates times
    ``[1, u_y, u_z]`` (lower degree where a cluster has too few rows)."""

    labels: np.ndarray
    degree: int = 2

    def _cluster(self, k: int, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        idx = np.flatnonzero(self.labels == k)
        nc = len(idx)
        d = self.degree
        while d > 0 and 3 * (d + 1) * (d + 2) // 2 > nc / 2.5:
            d -= 1
        xx = x[idx]
        lo, hi = xx.min(axis=0), xx.max(axis=0)
        hi = np.where(hi > lo, hi, lo + 1e-3)
        P = _legendre_total(2 * (xx - lo) / (hi - lo) - 1, d)
        return idx, np.concatenate([P, P * u[idx, :1], P * u[idx, 1:2]], axis=1)

    def fit(self, r: np.ndarray, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, float, int]:
        """Fit residuals (n, 2): fitted values (n, 2), RSS (m^2), total rank per coordinate."""
        fit = np.zeros_like(r)
        rank = 0
        for k in range(int(self.labels.max()) + 1):
            idx, F = self._cluster(k, x, u)
            if len(idx) == 0:
                continue
            coef, _, rk, _ = np.linalg.lstsq(F, r[idx], rcond=1e-10)
            fit[idx] = F @ coef
            rank += int(rk)
        res = r - fit
        return fit, float(np.sum(res * res)), rank


#: flexible-model settings tried for the noise floor: (rows per cluster, polynomial degree)
FLEX_CONFIGS = ((60, 2), (90, 2), (120, 2), (90, 3), (120, 3), (180, 3), (240, 3))


@dataclass
class NoiseFloor:
    """Noise floor of a pose residual: ``sigma`` (m, per coordinate), the flexible model used
    (clusters, degree, parameters per coordinate) and the RMS of the smooth part it removed (m)."""

    sigma: float
    clusters: int
    degree: int
    features: int
    smooth_rms: float
    basis: LocalBasis
    x: np.ndarray = field(repr=False, default=None)

    def to_json(self) -> dict:
        return {"sigma": self.sigma, "clusters": self.clusters, "degree": self.degree,
                "parameters_per_coordinate": self.features, "smooth_rms": self.smooth_rms,
                "estimator": "dof-corrected RMS, sqrt(RSS / 2(n - m)), left by local polynomials in the tip position "
                             "x [1, u_y, u_z] on k-means clusters of rows (cluster size and degree by AIC)"}


def noise_floor(r: np.ndarray, x: np.ndarray, u: np.ndarray, configs=FLEX_CONFIGS) -> NoiseFloor:
    """Estimate the measurement noise (per coordinate, m) from a pose residual ``r`` (n, 2).

    ``x`` (n, 2) are the model tip positions (where the rows are), ``u`` (n, 2) friction's
    directions. Every catalogue effect and the usual unmodelled ones are smooth in the
    configuration (friction linear in ``u``), so a flexible local model — polynomials in ``x``
    times ``[1, u_y, u_z]`` on compact clusters of rows — follows them, and what is left is the
    noise: ``sigma = sqrt(RSS / (2 (n - m)))``, m the parameters per coordinate. The cluster size
    and degree come from ``configs`` by AIC (``N ln(RSS/N) + 2 (2m)``, ``N = 2n``).
    """
    n = len(r)
    N = 2 * n
    best = None
    for per, deg in configs:
        labels = kmeans_labels(x, max(1, n // per))
        basis = LocalBasis(labels, deg)
        fit, rss, rank = basis.fit(r, x, u)
        if n - rank < max(2, n // 4):
            continue
        aic = N * math.log(max(rss, 1e-300) / N) + 4 * rank
        if best is None or aic < best[0]:
            best = (aic, basis, fit, rss, rank, deg)
    if best is None:
        s = rms(r - r.mean(axis=0))
        return NoiseFloor(s, 1, 0, 1, 0.0, LocalBasis(np.zeros(n, int), 0), x)
    _, basis, fit, rss, rank, deg = best
    return NoiseFloor(math.sqrt(rss / (2 * (n - rank))), int(basis.labels.max()) + 1, deg, rank, rms(fit), basis, x)


@dataclass
class Structure:
    """Is a residual structured? F test of the flexible smooth model against "noise only"."""

    rms: float            # per-coordinate RMS of the residual
    structured_rms: float  # RMS of its smooth part beyond what a fit to pure noise absorbs
    f_stat: float
    p_value: float
    ratio: float           # rms / noise floor
    structured: bool

    def to_json(self) -> dict:
        return {"rms": self.rms, "structured_rms": self.structured_rms, "f_statistic": self.f_stat,
                "p_value": self.p_value, "rms_over_noise_floor": self.ratio, "structured": self.structured}


def structure_test(r: np.ndarray, u: np.ndarray, nf: NoiseFloor) -> Structure:
    """F test of the noise floor's flexible model on residual ``r`` (same rows) and the RMS of the
    smooth part beyond what fitting pure noise would absorb."""
    from scipy.stats import f as fdist

    n = len(r)
    rss0 = float(np.sum(r * r))
    ratio = rms(r) / max(nf.sigma, 1e-300)
    _, rss1, rank = nf.basis.fit(r, nf.x, u)
    df1, df2 = 2 * rank, 2 * (n - rank)
    if df1 <= 0 or df2 <= 0:
        return Structure(rms(r), 0.0, 0.0, 1.0, ratio, False)
    fstat = ((rss0 - rss1) / df1) / max(rss1 / df2, 1e-300)
    p = float(fdist.sf(fstat, df1, df2))
    s = math.sqrt(max(0.0, (rss0 - rss1) - df1 * nf.sigma ** 2) / (2 * n))
    return Structure(rms(r), s, float(fstat), p, ratio, bool(p < STRUCTURE_P and s >= STRUCTURE_RATIO * nf.sigma))


# ----------------------------------------------------------------------------- candidates
@dataclass
class Candidate:
    """One effect combination tried: its fit on all the data, its held-out error and BIC."""

    model: EffectModel
    rms: float
    bic: float
    heldout_rms: float | None
    selectable: bool
    note: str = ""
    selected: bool = False

    @property
    def effects(self) -> list[str]:
        return self.model.names

    @property
    def label(self) -> str:
        return self.model.label

    def to_json(self, bic_none: float) -> dict:
        m = self.model
        return {
            "effects": self.effects, "name": self.label, "n_params": m.n_params,
            "parameters": m.parameters(), "uncertainty": _finite_or_none(m.uncertainties()),
            "pose_rms": self.rms, "heldout_rms": self.heldout_rms, "bic": self.bic,
            "delta_bic": self.bic - bic_none, "score": self.bic - bic_none,
            "identifiable": bool(m.identifiable_), "condition_number": m.condition_ if math.isfinite(m.condition_) else None,
            "max_correlation": m.max_correlation_, "selectable": self.selectable, "selected": self.selected,
            "note": self.note,
        }


def _num(v: float) -> float | None:
    """A finite number, or None (JSON has no NaN): e.g. a trajectory RMS with no approach rows."""
    return float(v) if v is not None and math.isfinite(v) else None


def _finite_or_none(d: dict) -> dict:
    return {k: {p: (v if math.isfinite(v) else None) for p, v in ps.items()} for k, ps in d.items()}


def _bic(rss: float, n_obs: int, p: int) -> float:
    return n_obs * math.log(max(rss, 1e-300) / n_obs) + p * math.log(n_obs)


def _folds(runs: int, k: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    perm = rng.permutation(runs)
    fold = np.empty(runs, int)
    fold[perm] = np.arange(runs) % k
    return fold


def fit_candidate(effects: Sequence[str], data: MeasuredData, u: np.ndarray, base, fold_of_run: np.ndarray | None) -> Candidate:
    from .effects import make_effect

    m = EffectModel([make_effect(e) for e in effects]).fit(data.q, u, data.tip, base)
    n = data.rows
    bic = _bic(m.rss_, 2 * n, m.n_params)
    ho = None
    if fold_of_run is not None:
        fold = fold_of_run[data.run]
        sse = 0.0
        for k in range(int(fold_of_run.max()) + 1):
            te = fold == k
            tr = ~te
            if 2 * int(tr.sum()) < m.n_params + 2:
                sse = float("nan")  # too few training rows for this candidate: no held-out error
                break
            if m.n_params:
                mk = EffectModel(m.effects).fit(data.q[tr], u[tr], data.tip[tr], base, x0=m.values_)
                vals = mk.values_
            else:
                vals = np.zeros(0)
            with np.errstate(invalid="ignore", divide="ignore"):
                r = data.tip[te] - m.predict(base, data.q[te], u[te], vals)
            r = np.where(np.isfinite(r), r, 1.0)
            sse += float(np.sum(r * r))
        ho = math.sqrt(sse / (2 * n)) if math.isfinite(sse) else None
    note = "" if m.identifiable_ else f"not identifiable: {m.why_}"
    return Candidate(m, math.sqrt(m.rss_ / (2 * n)), bic, ho, bool(m.identifiable_), note)


def select(cands: dict[tuple[str, ...], Candidate]) -> Candidate:
    """The first selectable candidate by BIC whose held-out error beats every sub-model with one
    effect fewer (and whose BIC beats them too). "none" always qualifies."""
    order = sorted(cands.values(), key=lambda c: c.bic)
    for c in order:
        if not c.selectable:
            continue
        key = tuple(c.effects)
        ok = True
        for e in key:
            sub = cands.get(tuple(x for x in key if x != e))
            if sub is None:
                continue
            if c.bic >= sub.bic:
                ok = False
                if not c.note:
                    c.note = f"BIC not below {sub.label}"
                break
            if c.heldout_rms is not None and sub.heldout_rms is not None and c.heldout_rms >= sub.heldout_rms:
                ok = False
                if not c.note:
                    c.note = f"held-out error not below {sub.label}"
                break
        if ok:
            return c
    return cands[()]  # pragma: no cover - "none" is always selectable


# ----------------------------------------------------------------------------- report
@dataclass
class Errors:
    """Before/after errors on one data set (m, per coordinate)."""

    pose_before: float
    pose_after: float
    trajectory_before: float      # over each run's approach (see approach_mask)
    trajectory_after: float
    trajectory_all_before: float  # over every step >= 1
    trajectory_all_after: float
    rows: int
    runs: int
    source: str
    arrival_tolerance: float
    trajectory_rows: int = 0
    unsettled_runs: int = 0

    def to_json(self) -> dict:
        return {"source": self.source, "rows": self.rows, "runs": self.runs,
                "pose_rms_before": self.pose_before, "pose_rms_after": self.pose_after,
                "trajectory_rms_before": _num(self.trajectory_before), "trajectory_rms_after": _num(self.trajectory_after),
                "trajectory_rms_all_steps_before": _num(self.trajectory_all_before),
                "trajectory_rms_all_steps_after": _num(self.trajectory_all_after),
                "arrival_tolerance": self.arrival_tolerance, "trajectory_rows": self.trajectory_rows,
                "trajectory_unsettled_runs_left_out": self.unsettled_runs}


@dataclass
class CalibrationReport:
    """Everything ``errplan calibrate`` found; ``to_json`` is the calibrate JSON of interfaces.md."""

    scenario: str
    data_source: str
    selected: list[str]
    explained: bool
    model: EffectModel
    noise: NoiseFloor
    structure: Structure
    structure_before: Structure
    candidates: list[Candidate]
    fit_errors: Errors
    validation_errors: Errors | None
    declared_effects: dict
    seed: int
    folds: int
    # arrays for the recording (fitting data)
    points: np.ndarray = field(repr=False, default=None)        # model tips (n, 2)
    residual_before: np.ndarray = field(repr=False, default=None)
    residual_after: np.ndarray = field(repr=False, default=None)
    tracked: np.ndarray = field(repr=False, default=None)
    replay_before: np.ndarray = field(repr=False, default=None)
    replay_after: np.ndarray = field(repr=False, default=None)
    data: MeasuredData | None = field(repr=False, default=None)

    @property
    def errors(self) -> Errors:
        """The errors the JSON reports: on the validation file when one was given."""
        return self.validation_errors or self.fit_errors

    @property
    def fitted(self) -> dict[str, dict[str, float]]:
        """The fitted values of the selected effects: what the data add to the declared model."""
        return self.model.parameters()

    @property
    def parameters(self) -> dict[str, dict[str, float]]:
        """The selected effects as the bench has them: a declared value of the same effect plus
        the fitted correction (just the fitted value when the scenario declares none)."""
        out = {}
        for e, ps in self.fitted.items():
            dec = self.declared_effects.get(e, {})
            out[e] = {p: dec.get(p, 0.0) + v for p, v in ps.items()}
        return out

    @property
    def uncertainty(self) -> dict[str, dict[str, float]]:
        return _finite_or_none(self.model.uncertainties())

    def effects_table(self) -> dict[str, dict[str, float]]:
        """Effects for the corrected scenario: every declared effect, with the selected ones
        replaced by their values on the bench (declared + fitted)."""
        out = {k: dict(v) for k, v in self.declared_effects.items()}
        for e, ps in self.parameters.items():
            out[e] = dict(ps)
        return out

    def to_json(self) -> dict:
        bic_none = next(c.bic for c in self.candidates if not c.effects)
        e = self.errors
        return {
            "scenario": self.scenario,
            "data": self.data_source,
            "selected": list(self.selected),
            "explained": bool(self.explained),
            "parameters": self.parameters,
            "fitted": self.fitted,
            "uncertainty": self.uncertainty,
            "noise_floor": self.noise.sigma,
            "pose_rms_before": e.pose_before,
            "pose_rms_after": e.pose_after,
            "trajectory_rms_before": _num(e.trajectory_before),
            "trajectory_rms_after": _num(e.trajectory_after),
            "errors_on": "validation" if self.validation_errors else "data",
            "fit": self.fit_errors.to_json(),
            "validation": self.validation_errors.to_json() if self.validation_errors else None,
            "noise": self.noise.to_json(),
            "residual_structure": {"before": self.structure_before.to_json(), "after": self.structure.to_json(),
                                   "rule": f"not explained when the smooth part of the residual is significant "
                                           f"(F test p < {STRUCTURE_P:g}) and its RMS >= {STRUCTURE_RATIO:g} x noise floor"},
            "declared_effects": self.declared_effects,
            "effects": self.effects_table(),
            "rms_convention": "per coordinate: sqrt(mean over rows and over y, z of residual^2), m",
            "selection": {"rule": "lowest BIC among identifiable candidates whose held-out pose error (folds of runs) "
                                  "beats every sub-model with one effect fewer",
                          "folds": self.folds, "seed": self.seed},
            "candidates": [c.to_json(bic_none) for c in self.candidates],
        }

    def text(self) -> str:
        from .report import format_table

        mm = 1000.0
        lines = [f"calibration of {self.scenario} on {self.data_source} ({self.fit_errors.rows} rows, "
                 f"{self.fit_errors.runs} runs)"]
        if self.declared_effects:
            lines.append("declared effects: " + ", ".join(self.declared_effects))
        lines.append(f"noise floor {self.noise.sigma * mm:.4f} mm per coordinate (left by local degree-{self.noise.degree} "
                     f"polynomials on {self.noise.clusters} cluster(s) of rows)")
        lines.append(f"pose residual of the declared model: RMS {self.structure_before.rms * mm:.4f} mm "
                     f"({self.structure_before.ratio:.2f} x noise floor)")
        lines.append("")
        rows = []
        order = sorted(self.candidates, key=lambda c: c.bic)
        bic_none = next(c.bic for c in self.candidates if not c.effects)
        shown = order[:TEXT_CANDIDATES]
        shown += [c for c in order[TEXT_CANDIDATES:] if not c.effects or not c.selectable]
        for c in shown:
            rows.append([("* " if c.selected else "  ") + c.label, c.model.n_params, c.rms * mm,
                         c.heldout_rms * mm if c.heldout_rms is not None else float("nan"), c.bic - bic_none,
                         c.model.condition_, "yes" if c.selectable else "no", c.note])
        more = len(order) - len(shown)
        lines.append(format_table(["candidate", "p", "pose rms mm", "held-out mm", "dBIC", "cond", "ok", "note"], rows,
                                  f"candidates (sorted by BIC; * selected; {len(order)} tried"
                                  + (f", {more} more in the JSON)" if more else ")")))
        lines.append("")
        if self.selected:
            prow = []
            for e, ps in self.parameters.items():
                from .effects import EFFECTS

                units = dict(zip(EFFECTS[e].params, EFFECTS[e].units))
                for p, v in ps.items():
                    s = self.uncertainty[e][p]
                    f, unit = (mm, "mm") if units[p] == "m" else ((mm, "mrad") if units[p] == "rad" else (1.0, units[p]))
                    sig = f"{s * f:.4f}" if s is not None else "?"
                    dec = self.declared_effects.get(e)
                    note = f"declared {dec.get(p, 0.0) * f:+.4f} + fitted {self.fitted[e][p] * f:+.4f}" if dec else ""
                    prow.append([e, p, f"{v * f:+.4f} ± {sig}", unit, note])
            lines.append(format_table(["effect", "param", "value ± 1 sigma", "unit", ""], prow, "selected effects"))
        else:
            lines.append("selected effects: none (the declared model explains the data down to the noise)")
        e = self.errors
        on = "validation data" if self.validation_errors else "the data"
        lines.append("")
        lines.append(format_table(["error (RMS per coordinate)", "before mm", "after mm"], [
            ["pose (tracked vs model tip)", e.pose_before * mm, e.pose_after * mm],
            ["trajectory, approach (controller replayed)", e.trajectory_before * mm, e.trajectory_after * mm],
            ["trajectory, every step", e.trajectory_all_before * mm, e.trajectory_all_after * mm],
        ], f"error before -> after on {on}"))
        if e.unsettled_runs:
            lines.append(f"({e.unsettled_runs} of {e.runs} runs diverged or cycled without arriving and are left out of "
                         f"the approach RMS)")
        s = self.structure
        verdict = "yes" if self.explained else "NO"
        lines.append(f"explained: {verdict} — residual after {s.rms * mm:.4f} mm = {s.ratio:.2f} x noise floor; "
                     f"structured part {s.structured_rms * mm:.4f} mm (F test p = {s.p_value:.2g})")
        if not self.explained:
            lines.append("  a structured residual remains well above the noise floor: an effect outside the catalogue "
                         "(see the residual map in --record);\n  the selected combination is only the catalogue's best "
                         "approximation, its parameters absorb the unmodelled effect")
        return "\n".join(lines)


# ----------------------------------------------------------------------------- driver
def calibrate(sc, data: MeasuredData, *, validate: MeasuredData | None = None, seed: int = 0,
              folds: int = DEFAULT_FOLDS, progress: Callable[[float, str], None] | None = None) -> CalibrationReport:
    """Find which catalogue effects (if any) the data need on top of the scenario's declared model."""
    from .experiment import bench_controller, require_planar

    require_planar(sc, "calibration")
    prog = progress or (lambda f, m="": None)
    base = declared_plant(sc)
    check_against_model(data, base)
    if validate is not None:
        check_against_model(validate, base)
    ctrl = bench_controller(sc)
    xmodel = motion_model(sc)  # friction's u: the motion each command produces under the declared model
    u = data.commanded_directions(xmodel)
    r0 = pose_residual(data, base, u)
    if not np.all(np.isfinite(r0)):
        i = int(np.flatnonzero(~np.all(np.isfinite(r0), axis=1))[0])
        raise DataError(f"{data.source}: row {i + 1}: the declared model has no tip at encoder angles {data.q[i].tolist()}")
    x0 = predict_tracked(base, data.q, u)
    nf = noise_floor(r0, x0, u)
    st0 = structure_test(r0, u, nf)
    prog(0.05, "noise floor")
    k = min(folds, data.runs)
    fold_of_run = _folds(data.runs, k, seed) if k >= 2 else None
    names = [c.name for c in CATALOGUE]
    combos: list[tuple[str, ...]] = [()] + [(a,) for a in names] + list(itertools.combinations(names, 2))
    n_params = {c.name: len(c.params) for c in CATALOGUE}
    fits = lambda key: sum(n_params[e] for e in key) <= 2 * data.rows - 2  # noqa: E731 (some residual dof left)
    combos = [c for c in combos if fits(c)]
    cands: dict[tuple[str, ...], Candidate] = {}
    for i, combo in enumerate(combos):
        cands[combo] = fit_candidate(combo, data, u, base, fold_of_run)
        prog(0.05 + 0.75 * (i + 1) / len(combos), "+".join(combo) or "none")
    # triples: the best pair plus each other effect, when that pair beats its singles
    pairs = [c for key, c in cands.items() if len(key) == 2 and c.selectable]
    if pairs:
        bp = min(pairs, key=lambda c: c.bic)
        if all(bp.bic < cands[(e,)].bic for e in bp.effects) and bp.bic < cands[()].bic:
            for e in names:
                if e in bp.effects:
                    continue
                key = tuple(x for x in names if x in bp.effects or x == e)
                if fits(key):
                    cands[key] = fit_candidate(key, data, u, base, fold_of_run)
    prog(0.85, "selection")
    chosen = select(cands)
    chosen.selected = True
    for c in cands.values():
        if not c.selectable and not c.note:
            c.note = "not identifiable"
    model = chosen.model
    after = model.plant(base)
    r1 = data.tip - predict_tracked(after, data.q, u)
    st1 = structure_test(r1, u, nf)
    explained = not st1.structured

    # before / after errors
    tol = arrival_tolerance(nf.sigma)

    def errors(d: MeasuredData, r_before: np.ndarray, r_after: np.ndarray) -> Errors:
        tb, tb_all = trajectory_errors(d, base, ctrl, tol, xmodel)
        ta, ta_all = trajectory_errors(d, after, ctrl, tol, xmodel)
        mask, unsettled = approach_mask(d, tol)
        return Errors(rms(r_before), rms(r_after), tb, ta, tb_all, ta_all, d.rows, d.runs, d.source, tol,
                      int(mask.sum()), int(unsettled.sum()))

    fit_err = errors(data, r0, r1)
    val_err = None
    if validate is not None:
        uv = validate.commanded_directions(xmodel)
        val_err = errors(validate, pose_residual(validate, base, uv), pose_residual(validate, after, uv))
    pred0, _ = replay(data, base, ctrl, xmodel)
    pred1, _ = replay(data, after, ctrl, xmodel)
    prog(1.0, "done")
    cand_list = sorted(cands.values(), key=lambda c: (len(c.effects), c.bic))
    return CalibrationReport(
        scenario=sc.name, data_source=data.source, selected=model.names, explained=explained, model=model,
        noise=nf, structure=st1, structure_before=st0, candidates=cand_list, fit_errors=fit_err,
        validation_errors=val_err, declared_effects={k2: dict(v) for k2, v in sc.effects.items()}, seed=seed, folds=k,
        points=x0, residual_before=r0, residual_after=r1, tracked=data.tip,
        replay_before=pred0, replay_after=pred1, data=data)


# ----------------------------------------------------------------------------- scenario export
def _toml_key(k: str) -> str:
    import re

    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _toml_str(k)


def _toml_str(s: str) -> str:
    out = ['"']
    for ch in s:
        if ch == '"':
            out.append('\\"')
        elif ch == "\\":
            out.append("\\\\")
        elif ch == "\n":
            out.append("\\n")
        elif ch == "\t":
            out.append("\\t")
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    out.append('"')
    return "".join(out)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ErrplanError(f"cannot write the non-finite number {v} to TOML")
        return repr(v)
    if isinstance(v, str):
        return _toml_str(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    if hasattr(v, "item"):
        return _toml_value(v.item())
    raise ErrplanError(f"cannot write {type(v).__name__} {v!r} to TOML")


def to_toml(doc: dict, header: str = "") -> str:
    """A TOML document for a parsed-TOML-like dict: tables as ``[a.b]`` sections, lists of
    tables as ``[[a]]`` (their sub-tables inline), everything else inline."""
    lines: list[str] = [f"# {h}" if h else "#" for h in header.splitlines()] if header else []

    def is_aot(v) -> bool:
        return isinstance(v, list) and len(v) > 0 and all(isinstance(x, dict) for x in v)

    def emit(table: dict, path: list[str], inline_tables: bool) -> None:
        for k, v in table.items():
            if (isinstance(v, dict) and not inline_tables) or is_aot(v):
                continue
            lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
        if not inline_tables:
            for k, v in table.items():
                if isinstance(v, dict):
                    sub = path + [_toml_key(k)]
                    if any(not isinstance(x, dict) for x in v.values()) or not v:
                        lines.append("")
                        lines.append(f"[{'.'.join(sub)}]")
                    emit(v, sub, False)
        for k, v in table.items():
            if is_aot(v):
                sub = path + [_toml_key(k)]
                for item in v:
                    lines.append("")
                    lines.append(f"[[{'.'.join(sub)}]]")
                    emit(item, sub, True)

    emit(doc, [], False)
    return "\n".join(lines).lstrip("\n") + "\n"


def corrected_scenario_toml(sc, report: CalibrationReport) -> str:
    """The scenario's own TOML with the found effects under ``[effects]`` (declared + fitted)."""
    import tomllib
    from pathlib import Path

    from .scenario import parse_scenario

    try:
        doc = tomllib.loads(Path(sc.source).read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ErrplanError(f"{sc.source}: cannot re-read the scenario to export it: {e}") from None
    effects = report.effects_table()
    if effects:
        doc["effects"] = {e: {p: float(v) for p, v in ps.items()} for e, ps in effects.items()}
    else:
        doc.pop("effects", None)
    doc["name"] = f"{sc.name}-calibrated" if report.selected else sc.name
    found = ", ".join(report.selected) or "none"
    doc["description"] = (sc.description + " | " if sc.description else "") + f"calibrated: {found}"
    header = (f"{sc.name} corrected by `errplan calibrate` on {report.data_source}\n"
              f"found effects: {found}; explained: {str(report.explained).lower()}\n"
              f"noise floor {report.noise.sigma:.3e} m; pose RMS {report.fit_errors.pose_before:.3e} -> "
              f"{report.fit_errors.pose_after:.3e} m")
    text = to_toml(doc, header)
    parse_scenario(tomllib.loads(text), "<exported scenario>")  # reads back, or raises before writing
    return text
