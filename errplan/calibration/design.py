"""Experiment design: choose the bench runs that make the catalogue's parameters identifiable.

A bench is a set of runs (a start tip, a target tip; the controller drives from one to the other
and the bench records one row per step, docs/interfaces.md). What calibrate can tell apart
depends on where those rows are: on P1's three starts, ``joint_offset.dq1`` and
``gravity_sag.c1`` move the tip the same way to within a correlation of 0.999, and no fit can
separate them.

The design problem (the standard one of robot calibration, e.g. Sun & Hollerbach 2008, "Observability
index selection for robot calibration"): let ``J`` be the stacked pose-residual Jacobian of *all*
catalogue parameters at the declared model (every effect at 0), one block of rows per run. With
tracker noise sigma, the least-squares estimate of the parameters has covariance
``sigma^2 (J^T J)^-1``; ``M = J^T J = sum over runs of M_r`` is the information matrix. Choose N
runs from a candidate set to maximise a criterion of ``M``:

- **D-optimal**: ``log det M``. The volume of the confidence ellipsoid of all parameters
  shrinks; it is invariant to the parameters' units and to any linear reparametrisation (metres,
  radians and 1/m^2 mix here, and ``det(S M S) = det(S)^2 det M``), and ``log det`` is concave and
  submodular over runs, so greedy selection followed by Fedorov exchange is the classical, reliable
  algorithm. But D trades correlation for magnitude freely: on P1's scenario a D-optimal bench
  confuses port offset and shaft flexion *more* than the default one (0.995 against 0.983).
- **A-optimal**: ``-log trace(M^-1)`` in units of each parameter's typical size (the effect's
  ``default_scales``): the mean variance, which depends on those units.
- **E-optimal**: ``log lambda_min`` of ``M`` in the same units: the worst direction only; it
  ignores every other direction, and is not smooth.
- **G** (the default): ``-sum_i log (M^-1)_ii``, the product of the parameters' marginal
  variances. ``sum_i log V_ii = log det V - log det R`` with ``R`` the estimates' correlation
  matrix, so G is D-optimality plus a decorrelation term; unit invariant like D; its mean log sigma
  is what "the parameters' sigma on average" measures.

Every criterion can carry the separation constraint (:class:`Objective`): every pair of effects
below a cross correlation of ``SEPARATE`` when both are fitted. ``benchmarks/calibration.py``
compares them; G with separation is the default, because it is unit invariant, it rewards what
calibrate reports (marginal sigmas, inflated by correlation), and with the constraint it separates
every pair the default bench confuses. The price is stated, not hidden: the rows that tell port
offset from shaft flexion are near the port, where every effect moves the tip least, so
single-effect sigmas rise there (docs/calibration.md).

Candidates: start tips on a grid over the whole tip workspace, each with the bench's targets (P1's
8 directions in the plane, the 14 of interfaces.md in 3-D) at 20 and 40 mm; start and target must
be *robust*: reachable with margins (joint limits, tip and wrist away from the true and the
estimated port, as :func:`errplan.experiment.choose_starts`) and, when the scenario has an
``[uncertainty]`` error set and a rigid controller, valid under every instance of it
(:class:`errplan.fields.KernelEvaluator`). Each candidate run is predicted on the declared model,
noise-free (:func:`errplan.experiment.simulate_bench`), so a run's rows, its length and friction's
directions are those the bench will record; runs that do not arrive are dropped.

What is written here (no library fits; see docs/calibration.md): the information blocks from the
effect models' central-difference Jacobian (:class:`errplan.effects.EffectModel`), greedy
selection and a Fedorov exchange over whole runs (block updates: a run adds a rank-``rows x d``
matrix, so the rank-one formulas of single-row designs do not apply), a row budget, and the
identifiability summary (condition number, correlations, predicted sigmas) of any bench.
"""
from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..effects import CATALOGUE, EffectModel, catalogue
from ..errors import ErrplanError
from ..experiment import MeasuredData

CRITERIA = ("G", "D", "A", "E")
#: the separation target: every pair of effects below this cross correlation (a margin under CONFUSED)
SEPARATE = 0.94
#: a pair of effects whose largest cross correlation exceeds this is "confused" by a bench
CONFUSED = 0.95
#: targets of candidate runs: the bench's directions at these distances (m)
CANDIDATE_DISTANCES = (0.020, 0.040)
#: start-grid spacing (m) and the most candidate starts kept, by dimension
CANDIDATE_SPACING = {2: 0.010, 3: 0.020}
MAX_CANDIDATE_STARTS = {2: 600, 3: 500}
#: ridge added to the information matrix (scaled units) while a greedy design is still singular
RIDGE = 1e-9


# ----------------------------------------------------------------------------- information
def catalogue_model(sc, effects=None) -> EffectModel:
    """Every catalogue effect of the scenario's dimension (or the named ``effects``: physical, geometric
    or ``backlash``), in one model (nothing fitted; gravity sag left out on a URDF without inertial
    data, its identically zero joints fixed)."""
    if effects is None:
        # the physical catalogue; tracker_latency is identified wherever the tip moves (every run)
        # and needs no designed run, so the default design leaves it out
        return EffectModel(catalogue(sc, [c.name for c in CATALOGUE if c.name != "tracker_latency"],
                                     skip_without_gravity=True))
    from ..effects import EFFECTS, geometry_names

    allowed = [n for n in EFFECTS if n not in ("link_length", "joint_geometry")] + geometry_names(sc.dim)
    bad = [e for e in effects if e not in allowed]
    if bad or not effects or len(set(effects)) != len(effects):
        raise ErrplanError(f"--effects {','.join(effects)}: expected distinct effects of docs/physics.md for this "
                           f"scenario: {', '.join(dict.fromkeys(allowed))}")
    return EffectModel(catalogue(sc, list(effects)))


def row_jacobian(sc, data: MeasuredData, model: EffectModel | None = None) -> np.ndarray:
    """``d tracked tip / d theta`` (rows, d, p) at every row of ``data``, theta the parameters of
    ``model`` (default: the whole catalogue) in scaled units (value / the effect's default scale),
    at the declared model (every parameter 0); friction's directions from the rows
    (:meth:`MeasuredData.commanded_directions`)."""
    from .residual import declared_plant, motion_model

    model = catalogue_model(sc) if model is None else model
    base = declared_plant(sc, data)
    u = data.commanded_directions(motion_model(sc))
    # the prediction's derivative at every row (f = 0 - predicted); a dropout's row informs nothing
    f = model._residual_fn(data.q, u, np.zeros_like(data.tip), base, data.run, data.time)
    z0 = np.zeros(model.n_free)
    J = -model._jac(f, z0)              # f = tracked - predicted
    # a history effect (backlash: play of half-width |b|) is even in its parameter, so its central
    # difference at 0 is 0; its sensitivity is the one-sided one, the tip's lag under a small play;
    # a parameter with a range starting at 0 (tracker_latency's tau >= 0) likewise
    hist = np.array([getattr(e, "history", False) or (getattr(e, "bounds", None) or (None,))[0] == 0.0
                     for e in model.effects for _ in e.params], bool)[model.free]
    if hist.any():
        f0 = f(z0)
        for j in np.flatnonzero(hist):
            dz = np.zeros_like(z0)
            dz[j] = model.fd_step
            J[:, j] = -(f(dz) - f0) / model.fd_step
    J = J.reshape(data.rows, -1, model.n_free)
    J[~data.tracked] = 0.0
    return J


def run_blocks(J: np.ndarray, data: MeasuredData) -> np.ndarray:
    """Information blocks ``M_r = J_r^T J_r`` (runs, p, p) from row Jacobians (rows, d, p)."""
    p = J.shape[-1]
    out = np.zeros((data.runs, p, p))
    order = np.argsort(data.run, kind="stable")
    run = data.run[order]
    bounds = np.searchsorted(run, np.arange(data.runs + 1))
    Jo = J[order]
    for r in range(data.runs):
        A = Jo[bounds[r]:bounds[r + 1]].reshape(-1, p)
        out[r] = A.T @ A
    return out


@dataclass
class BenchInfo:
    """What a bench can identify, from its information matrix ``M`` (scaled units) for the whole
    catalogue (:func:`row_jacobian`).

    ``labels`` the parameters (``effect.param``), ``effects`` the parameter indices of each effect,
    ``scales`` each parameter's scale (SI), ``sigma`` the tracker's noise (m) for the predicted
    uncertainties.
    """

    M: np.ndarray
    rows: int
    runs: int
    labels: list[str]
    effects: dict[str, list[int]]
    scales: np.ndarray
    sigma: float

    # derived
    @property
    def p(self) -> int:
        return len(self.labels)

    def _normalised(self, idx=None) -> tuple[np.ndarray, np.ndarray]:
        idx = np.arange(self.p) if idx is None else np.asarray(idx)
        A = self.M[np.ix_(idx, idx)]
        d = np.sqrt(np.maximum(np.diag(A), 1e-300))
        return A / np.outer(d, d), d

    def condition(self, idx=None) -> float:
        """Condition number of the column-normalised stacked Jacobian (as calibrate's check)."""
        An, _ = self._normalised(idx)
        ev = np.linalg.eigvalsh(An)
        return float(math.sqrt(ev[-1] / ev[0])) if ev[0] > 1e-14 * ev[-1] else float("inf")

    def correlation(self, idx=None) -> np.ndarray:
        """Correlations of the parameter estimates (p, p), NaN off the diagonal when singular."""
        An, _ = self._normalised(idx)
        try:
            C = np.linalg.inv(An)
        except np.linalg.LinAlgError:
            C = np.full_like(An, np.nan)
        d = np.sqrt(np.abs(np.diag(C)))
        with np.errstate(invalid="ignore", divide="ignore"):
            out = C / np.outer(d, d)
        np.fill_diagonal(out, 1.0)
        return out

    def largest_correlation(self, idx=None) -> tuple[float, str, str]:
        """The largest |correlation| between two parameters and their labels."""
        idx = np.arange(self.p) if idx is None else np.asarray(idx)
        C = self.correlation(idx)
        off = np.abs(C - np.eye(len(idx)))
        off = np.where(np.isfinite(off), off, 1.0)
        i, j = np.unravel_index(int(np.argmax(off)), off.shape)
        return float(off[i, j]), self.labels[idx[i]], self.labels[idx[j]]

    def pair_correlation(self, a: str, b: str) -> float:
        """How well effects ``a`` and ``b`` can be told apart when both are fitted: the largest
        |correlation| between a parameter of ``a`` and one of ``b`` in the two-effect model."""
        ia, ib = self.effects[a], self.effects[b]
        C = self.correlation(ia + ib)
        cross = np.abs(C[:len(ia), len(ia):])
        return float(np.max(np.where(np.isfinite(cross), cross, 1.0)))

    def pair_correlations(self) -> dict[tuple[str, str], float]:
        return {(a, b): self.pair_correlation(a, b) for a, b in itertools.combinations(self.effects, 2)}

    def sigmas(self, idx=None) -> np.ndarray:
        """Predicted 1-sigma uncertainty (SI) of each parameter when those of ``idx`` (default all)
        are fitted together on this bench, with the tracker's noise."""
        idx = np.arange(self.p) if idx is None else np.asarray(idx)
        try:
            cov = np.linalg.inv(self.M[np.ix_(idx, idx)])
        except np.linalg.LinAlgError:
            return np.full(len(idx), np.inf)
        return self.sigma * np.sqrt(np.abs(np.diag(cov))) * self.scales[idx]

    def criterion(self, name: str = "D") -> float:
        return float(_criterion(self.M[None], name)[0])

    def to_json(self) -> dict:
        c, a, b = self.largest_correlation()
        return {"rows": self.rows, "runs": self.runs, "condition_number": _finite(self.condition()),
                "largest_correlation": {"value": c, "between": [a, b]},
                "log_det_information": _finite(self.criterion("D")),
                "pair_correlations": {f"{a}+{b}": v for (a, b), v in self.pair_correlations().items()},
                "sigma": {lab: _finite(s) for lab, s in zip(self.labels, self.sigmas())}}


def _finite(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


def bench_info(sc, data: MeasuredData, model: EffectModel | None = None) -> BenchInfo:
    """The identifiability summary of a bench (measured or predicted rows)."""
    model = catalogue_model(sc) if model is None else model
    J = row_jacobian(sc, data, model)
    A = J.reshape(-1, model.n_free)
    return _info(sc, model, A.T @ A, data.rows, data.runs)


def _info(sc, model: EffectModel, M: np.ndarray, rows: int, runs: int) -> BenchInfo:
    """The :class:`BenchInfo` of information ``M`` over the model's fitted (free) parameters."""
    sigma = float(sc.sensors.tracker_sigma) or 1e-4
    effects = {k: v for k, v in model.free_index().items() if v}
    return BenchInfo(M, rows, runs, model.free_labels, effects, model.scales[model.free], sigma)


# ----------------------------------------------------------------------------- criteria, selection
def _criterion(Ms: np.ndarray, name: str) -> np.ndarray:
    """Criterion (larger is better) of information matrices (k, p, p) in scaled units."""
    if name == "D":
        sign, ld = np.linalg.slogdet(Ms)
        return np.where(sign > 0, ld, -np.inf)
    if name == "E":  # log of the smallest eigenvalue (a log, so the separation penalty weighs as for D, G)
        lam = np.linalg.eigvalsh(Ms)[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(lam > 0, np.log(np.maximum(lam, 1e-300)), -np.inf)
    if name in ("A", "G"):
        # singular when the column-normalised matrix has a tiny determinant (slogdet is cheap)
        dg = np.sqrt(np.maximum(np.abs(np.diagonal(Ms, axis1=1, axis2=2)), 1e-300))
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            sign, ld = np.linalg.slogdet(Ms / (dg[:, :, None] * dg[:, None, :]))
        ok = (sign > 0) & (ld > math.log(1e-28))
        V = np.linalg.inv(np.where(ok[:, None, None], Ms, np.eye(Ms.shape[-1])))
        dv = np.diagonal(V, axis1=1, axis2=2)
        ok &= np.all(dv > 0, axis=1)
        if name == "A":  # minus the log of the summed variances (same optimum as -trace, penalty on a log scale)
            return np.where(ok, -np.log(np.maximum(np.sum(np.where(ok[:, None], dv, 1.0), axis=1), 1e-300)), -np.inf)
        return np.where(ok, -np.sum(np.log(np.where(ok[:, None], dv, 1.0)), axis=1), -np.inf)
    raise ErrplanError(f"design criterion {name!r}: expected one of {', '.join(CRITERIA)}")


def pair_correlations(Ms: np.ndarray, pairs: list[tuple[list[int], list[int]]]) -> np.ndarray:
    """For information matrices (k, p, p) and effect pairs (parameter indices of a, of b): the
    largest |correlation| between an estimate of a's and one of b's when a and b are fitted
    together (k, pairs); 1 where the pair model is singular."""
    out = np.ones((len(Ms), len(pairs)))
    for j, (ia, ib) in enumerate(pairs):
        idx = list(ia) + list(ib)
        S = Ms[:, idx][:, :, idx]
        dg = np.sqrt(np.maximum(np.abs(np.diagonal(S, axis1=1, axis2=2)), 1e-300))
        Sn = S / (dg[:, :, None] * dg[:, None, :])
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            sign, ld = np.linalg.slogdet(Sn)
        ok = (sign > 0) & (ld > math.log(1e-24))
        C = np.linalg.inv(np.where(ok[:, None, None], Sn, np.eye(len(idx))))
        dc = np.sqrt(np.abs(np.diagonal(C, axis1=1, axis2=2)))
        C = C / (dc[:, :, None] * dc[:, None, :])
        cross = np.abs(C[:, :len(ia), len(ia):]).reshape(len(Ms), -1).max(axis=1)
        out[:, j] = np.where(ok, np.minimum(cross, 1.0), 1.0)
    return out


@dataclass(frozen=True)
class Objective:
    """What a design maximises: ``criterion`` of the information of all catalogue parameters
    (scaled units), minus a penalty ``weight * sum over effect pairs of max(0, log(1 - target^2) -
    log(1 - rho^2))``, rho the pair's largest cross correlation (:func:`pair_correlations`), when
    ``separate`` is set: a constraint that every pair of effects stays separable, as a penalty."""

    criterion: str = "G"
    pairs: tuple = ()
    separate: float | None = None
    weight: float = 50.0

    def watching(self, M: np.ndarray, margin: float = 0.15) -> "Objective":
        """The same objective with the penalty only on the pairs within ``margin`` of the target at
        design ``M`` (one swap moves a correlation little; the others cost time, not answers)."""
        if self.separate is None or not self.pairs:
            return self
        rho = pair_correlations(M[None], list(self.pairs))[0]
        keep = tuple(pr for pr, r in zip(self.pairs, rho) if r > self.separate - margin)
        return Objective(self.criterion, keep, self.separate, self.weight)

    def __call__(self, Ms: np.ndarray) -> np.ndarray:
        score = _criterion(Ms, self.criterion)
        if self.separate is not None and self.pairs:
            rho = np.clip(pair_correlations(Ms, list(self.pairs)), 0.0, 1.0 - 1e-12)
            gap = np.log1p(-rho ** 2) - math.log1p(-self.separate ** 2)
            score = score + self.weight * np.minimum(gap, 0.0).sum(axis=1)
        return score


def select_runs(blocks: np.ndarray, rows: np.ndarray, n: int, *, max_rows: int | None = None,
                objective: Objective | str = "G", passes: int = 8, shortlist: int = 400,
                seed: int = 0) -> np.ndarray:
    """Indices of ``n`` runs maximising ``objective`` of the summed blocks (runs, p, p), with at
    most ``max_rows`` rows in all: greedy D-optimal (a ridge keeps the first, still singular steps
    defined: sequential D-optimality), then Fedorov exchange on the objective (swap a chosen run
    for the candidate that most improves it, while any swap does, at most ``passes`` sweeps). The
    separation penalty's weight is large, so that it acts as a constraint: while a pair is above the
    target, swaps that separate it win; once none is, a swap that pushes one above it is refused
    unless its gain in the criterion is out of all proportion.

    Each exchange step scores ``shortlist`` candidates, not all: the third with the largest
    first-order D gain ``tr(M^-1 M_r)`` and the rest drawn at random (seeded), a randomised
    exchange that costs a fraction of the full one and finds designs as good on the benchmarks.
    """
    objective = Objective(objective) if isinstance(objective, str) else objective
    R, p, _ = blocks.shape
    rows = np.asarray(rows, int)
    fill = n is None
    if fill:  # as many runs as the row budget holds
        if max_rows is None:
            raise ErrplanError("a design needs a number of runs or a row budget")
        n = int(np.searchsorted(np.cumsum(np.sort(rows)), max_rows, side="right"))
        if n == 0:
            raise ErrplanError(f"at most {max_rows} rows: not even the shortest candidate run fits")
    if n > R:
        raise ErrplanError(f"--design {n}: only {R} candidate runs in the robust workspace")
    budget = np.inf if max_rows is None else float(max_rows)
    smallest = np.sort(rows)
    if smallest[:n].sum() > budget:
        raise ErrplanError(f"--design {n} with at most {max_rows} rows: the {n} shortest candidate runs already "
                           f"have {int(smallest[:n].sum())} rows")
    ridge = RIDGE * np.eye(p) * max(1.0, float(np.max(np.trace(blocks, axis1=1, axis2=2))) / p)
    chosen: list[int] = []
    M = ridge.copy()
    used = 0
    free = np.ones(R, bool)
    for k in range(n):
        left = n - k - 1
        room = budget - used - (np.sort(rows[free])[:left + 1][:-1].sum() if left else 0)
        cand = np.flatnonzero(free & (rows <= (budget - used if fill else room)))
        if len(cand) == 0:
            if fill and k > 0:
                n = k
                break
            raise ErrplanError(f"--design {n} with at most {max_rows} rows: no design found within the rows "
                               f"(greedy, {k} runs in)")
        score = _criterion(M[None] + blocks[cand], "D")
        j = int(cand[int(np.argmax(score))])
        chosen.append(j)
        free[j] = False
        M = M + blocks[j]
        used += rows[j]
    M = M - ridge
    rng = np.random.default_rng(seed)
    flat = blocks.reshape(R, -1)
    for _ in range(passes):
        watched = objective.watching(M)
        best = float(watched(M[None])[0])
        improved = False
        for pos in range(n):
            i = chosen[pos]
            Mi = M - blocks[i]
            room = budget - (used - rows[i])
            cand = np.flatnonzero(free & (rows <= room))
            if len(cand) == 0:
                continue
            if len(cand) > shortlist:
                try:
                    g = flat[cand] @ np.linalg.inv(Mi + ridge).ravel()
                except np.linalg.LinAlgError:
                    g = np.zeros(len(cand))
                top = np.argsort(-g)[:shortlist // 3]
                rest = np.setdiff1d(np.arange(len(cand)), top)
                cand = cand[np.r_[top, rng.choice(rest, shortlist - len(top), replace=False)]]
            score = watched(Mi[None] + blocks[cand])
            k = int(np.argmax(score))
            if np.isfinite(score[k]) and score[k] - best > 1e-9 * max(1.0, abs(best)):
                j = int(cand[k])
                free[i], free[j] = True, False
                chosen[pos] = j
                used += rows[j] - rows[i]
                M = Mi + blocks[j]
                best = float(score[k])
                improved = True
        while fill:  # swaps may have freed rows: add the best run that still fits, while any does
            cand = np.flatnonzero(free & (rows <= budget - used))
            if len(cand) == 0:
                break
            if len(cand) > shortlist:
                cand = rng.choice(cand, shortlist, replace=False)
            score = watched(M[None] + blocks[cand])
            k = int(np.argmax(score))
            j = int(cand[k])
            chosen.append(j)
            free[j] = False
            M = M + blocks[j]
            used += rows[j]
            best = float(score[k])
            n += 1
            improved = True
        if not improved:
            break
    return np.array(chosen, int)


# ----------------------------------------------------------------------------- candidates
def robust_tips(sc, tips: np.ndarray) -> np.ndarray:
    """Mask (...) of tips where a bench can run: reachable with the bench's margins
    (:func:`errplan.experiment.tip_valid`) and, for a rigid controller with an ``[uncertainty]``
    error set, valid under every instance of it (:class:`errplan.fields.KernelEvaluator`)."""
    from ..experiment import START_MARGINS, tip_valid

    tips = np.asarray(tips, float)
    ok = tip_valid(sc, tips, **START_MARGINS)
    if sc.uncertainty.declared and sc.controller.jacobian == "rigid" and np.any(ok):
        try:
            from ..fields import KernelEvaluator

            ev = KernelEvaluator(sc)
        except ErrplanError:
            return ok
        idx = np.flatnonzero(ok.ravel())
        valid = np.asarray(ev.worst_case(tips.reshape(-1, sc.dim)[idx], sc.controller.gain, phi=False)["valid"], bool)
        flat = ok.ravel().copy()
        flat[idx] = valid
        ok = flat.reshape(ok.shape)
    return ok


def candidate_runs(sc, *, spacing: float | None = None, distances=CANDIDATE_DISTANCES,
                   max_starts: int | None = None, seed: int = 0) -> np.ndarray:
    """Candidate (start, target) pairs (R, 2, d): robust start tips on a grid over the tip
    workspace (at most ``max_starts``, spread by farthest-point sampling), each with the bench's
    target directions at ``distances`` whose target is robust too."""
    from ..experiment import target_offsets, tip_workspace_grid

    d = sc.dim
    spacing = CANDIDATE_SPACING[d] if spacing is None else spacing
    max_starts = MAX_CANDIDATE_STARTS[d] if max_starts is None else max_starts
    grid = tip_workspace_grid(sc, spacing, "the design's candidate starts", region=False)
    starts = grid[robust_tips(sc, grid)]
    if len(starts) == 0:
        raise ErrplanError(f"{sc.source}: no robust start tip for a designed bench")
    if len(starts) > max_starts:
        starts = starts[_spread(starts, max_starts)]
    offs = np.vstack([target_offsets(dist, d) for dist in distances])
    targets = starts[:, None, :] + offs[None]
    ok = robust_tips(sc, targets)
    pairs = np.stack([np.broadcast_to(starts[:, None, :], targets.shape), targets], axis=2)
    return pairs[ok]


def _spread(x: np.ndarray, k: int) -> np.ndarray:
    """Indices of ``k`` points spread over ``x`` (farthest-point sampling from the centroid)."""
    i = int(np.argmin(np.linalg.norm(x - x.mean(axis=0), axis=1)))
    idx = [i]
    dmin = np.linalg.norm(x - x[i], axis=1)
    for _ in range(k - 1):
        i = int(np.argmax(dmin))
        idx.append(i)
        dmin = np.minimum(dmin, np.linalg.norm(x - x[i], axis=1))
    return np.array(idx)


def predict_runs(sc, runs: np.ndarray, *, seed: int = 0, max_steps: int | None = None,
                 dwell: int | None = None) -> tuple[MeasuredData, np.ndarray]:
    """The rows a bench of ``runs`` (R, 2, d) would record on the declared model, and for each run
    its index in ``runs`` (runs whose first command already leaves the workspace record nothing and
    are dropped). Noise-free: with the tracker's noise in the prediction, the selection would favour
    runs whose noise happened to delay their arrival (more rows, more information) and the real
    bench would be shorter than designed. ``seed`` is kept for the interface (unused)."""
    from ..experiment import (
        DEFAULT_DWELL,
        DEFAULT_MAX_STEPS,
        bench_controller,
        simulate_bench,
        truth_plant,
    )

    max_steps = DEFAULT_MAX_STEPS if max_steps is None else max_steps
    dwell = DEFAULT_DWELL if dwell is None else dwell
    plant = truth_plant(sc, effects=True, noise=False)
    model = truth_plant(sc, effects=False, noise=False)
    runs = np.asarray(runs, float)
    q0, ok = _q0(plant, runs[:, 0])
    tol = max(5e-4, 3 * float(sc.sensors.tracker_sigma))
    idx = np.flatnonzero(ok)
    data = simulate_bench(plant, bench_controller(sc), q0[idx], runs[idx, 1], sc.controller.gain, max_steps=max_steps,
                          dwell=dwell, tolerance=tol, model=model)
    kept = idx[np.array([int(r) for r in data.run_ids], int)]
    data.run_ids = [str(k) for k in kept]
    return data, kept


def arrived(data: MeasuredData, tolerance: float) -> np.ndarray:
    """Per run (runs,): whether its tracked tip came within ``tolerance`` of the target."""
    hit = (np.linalg.norm(data.tip - data.target, axis=-1) < tolerance) & (data.step >= 1)
    return np.bincount(data.run, weights=hit, minlength=data.runs) > 0


def _q0(plant, tips: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q, ok = [], []
    for x in tips:
        try:
            q.append(plant.configuration_for_tip(x))
            ok.append(True)
        except ErrplanError:
            q.append(np.full(np.shape(plant.joint_offset), np.nan))
            ok.append(False)
    return np.array(q, float), np.array(ok, bool)


# ----------------------------------------------------------------------------- the design
@dataclass
class Design:
    """A designed bench against the default one: ``runs`` (N, 2, d) the chosen (start, target)
    pairs, ``default`` / ``designed`` their :class:`BenchInfo` (predicted rows)."""

    scenario: str
    criterion: str
    runs: np.ndarray
    default: BenchInfo
    designed: BenchInfo
    candidates: int
    seconds: float
    default_label: str = "default bench"
    meta: dict = field(default_factory=dict)

    def pairs(self) -> list[tuple[str, str, float, float]]:
        d0, d1 = self.default.pair_correlations(), self.designed.pair_correlations()
        return [(a, b, d0[(a, b)], d1[(a, b)]) for (a, b) in d0]

    def confused(self) -> list[tuple[str, str, float, float]]:
        """Pairs of effects the default bench confuses (cross correlation > CONFUSED)."""
        return [t for t in self.pairs() if t[2] > CONFUSED]

    def sigma_ratio(self) -> float:
        """Mean over parameters of designed / default predicted sigma, all catalogue parameters
        fitted together."""
        return float(np.mean(self.designed.sigmas() / self.default.sigmas()))

    def pair_sigma_ratio(self, a: str, b: str) -> float:
        """Mean over the parameters of effects ``a`` and ``b`` of designed / default predicted sigma
        when the two are fitted together (what a bench with both effects recovers)."""
        idx = self.default.effects[a] + self.default.effects[b]
        return float(np.mean(self.designed.sigmas(idx) / self.default.sigmas(idx)))

    def to_json(self) -> dict:
        return {"scenario": self.scenario, "criterion": self.criterion, "candidates": self.candidates,
                "runs": [{"start": r[0].tolist(), "target": r[1].tolist()} for r in self.runs],
                "default": self.default.to_json(), "designed": self.designed.to_json(),
                "confused_pairs": [{"effects": [a, b], "default": c0, "designed": c1,
                                    "sigma_ratio": self.pair_sigma_ratio(a, b)} for a, b, c0, c1 in self.confused()],
                "mean_sigma_ratio": self.sigma_ratio(), "seconds": self.seconds, **self.meta}

    def text(self) -> str:
        from ..report import format_table

        rows = []
        sep = self.meta.get("separate")
        label = f"designed ({self.criterion}-optimal" + (f", pairs < {sep:g})" if sep else ")")
        for name, b in ((self.default_label, self.default), (label, self.designed)):
            c, la, lb = b.largest_correlation()
            rows.append([name, b.runs, b.rows, f"{c:.4f}", f"{la} / {lb}", b.condition(), b.criterion("D")])
        what = (f"{self.default.p} parameters of {', '.join(self.meta['effects'])}" if self.meta.get("effects")
                else f"all {self.default.p} catalogue parameters")
        out = [format_table(["bench", "runs", "rows", "largest corr", "between", "cond", "log det M"], rows,
                            f"experiment design for {self.scenario}: {what}, {self.candidates} candidate runs")]
        if self.meta.get("rank"):
            rk = self.meta["rank"]
            held = self.meta.get("not_identifiable_by_any_run") or []
            out.append(f"identifiable parameters (QR rank of the rows' regressor): default bench {rk['default']} of "
                       f"{self.meta['parameters']}, designed {rk['designed']} of {self.meta['parameters']}"
                       + (f"; no candidate run can identify {', '.join(held)} (held at zero, as calibrate does)"
                          if held else ""))
        prow = []
        for a, b, c0, c1 in sorted(self.pairs(), key=lambda t: -t[2]):
            flag = "confused" if c0 > CONFUSED else ""
            note = (f"{flag} -> {'separated' if c1 < CONFUSED else 'STILL confused'}; sigma x "
                    f"{self.pair_sigma_ratio(a, b):.2f}") if flag else ""
            prow.append([f"{a} + {b}", f"{c0:.4f}", f"{c1:.4f}", note])
        out.append("")
        out.append(format_table(["effects fitted together", "default", "designed", ""], prow,
                                f"largest correlation between the two effects' parameters (confused: > {CONFUSED:g}; "
                                f"sigma x: designed / default, both fitted)"))
        s0, s1 = self.default.sigmas(), self.designed.sigmas()
        srow = [[lab, _si(s0[i], lab), _si(s1[i], lab), f"{s1[i] / s0[i]:.2f}"] for i, lab in enumerate(self.default.labels)]
        out.append("")
        out.append(format_table(["parameter", "sigma default", "sigma designed", "ratio"], srow,
                                f"predicted 1-sigma, all parameters fitted together (tracker sigma "
                                f"{self.default.sigma * 1e3:g} mm): mean ratio {self.sigma_ratio():.2f}"))
        return "\n".join(out)


def _si(v: float, label: str) -> str:
    if not math.isfinite(v):
        return "inf"
    eff, par = label.split(".", 1)
    angle = (par.startswith(("dq", "c")) or eff == "backlash"
             or (eff in ("joint_geometry", "tracker_registration") and par.startswith("r")))
    unit = "1/m^2" if eff == "shaft_flexion" else ("mrad" if angle else "mm")
    return f"{v:.4g} {unit}" if unit == "1/m^2" else f"{v * 1e3:.4g} {unit}"


def design_experiment(sc, n_runs: int | None = None, **kw) -> Design:
    """Choose bench runs that make the catalogue identifiable (:func:`_design_experiment`), with one
    BLAS thread (:mod:`.blas`)."""
    from .blas import single_threaded_blas

    with single_threaded_blas():
        return _design_experiment(sc, n_runs, **kw)


def _design_experiment(sc, n_runs: int | None = None, *, max_rows: int | None = None, criterion: str = "G",
                      separate: float | None = SEPARATE, seed: int = 0, n_starts: int | None = None,
                      max_steps: int | None = None, dwell: int | None = None, spacing: float | None = None,
                      effects=None, progress=None) -> Design:
    """Choose ``n_runs`` bench runs (default: as many as the row budget holds) that maximise the
    :class:`Objective` (``criterion`` of the catalogue's information, every pair of effects kept
    below the cross correlation ``separate``; None: no separation constraint) with at most
    ``max_rows`` rows (default: the default bench's rows, predicted; 0: no limit), and compare with
    the default bench (``n_starts`` starts times the bench's targets,
    :func:`errplan.experiment.choose_starts`)."""
    from ..experiment import DEFAULT_STARTS, choose_starts, target_offsets

    if criterion not in CRITERIA:
        raise ErrplanError(f"--criterion {criterion!r}: expected one of {', '.join(CRITERIA)}")
    if n_runs is not None and (isinstance(n_runs, bool) or not isinstance(n_runs, (int, np.integer)) or n_runs < 1):
        raise ErrplanError(f"--design {n_runs!r}: expected a number of runs >= 1")
    if separate is not None and not 0.0 < separate < 1.0:
        raise ErrplanError(f"separation target {separate!r}: expected a correlation between 0 and 1")
    prog = progress or (lambda f, m="": None)
    t0 = time.perf_counter()
    model = catalogue_model(sc, effects)
    # the default bench
    S = choose_starts(sc, DEFAULT_STARTS if n_starts is None else n_starts)
    offs = target_offsets(dim=sc.dim)
    default_runs = np.stack([np.repeat(S, len(offs), axis=0), (S[:, None] + offs[None]).reshape(-1, sc.dim)], axis=1)
    d0, _ = predict_runs(sc, default_runs, seed=seed, max_steps=max_steps, dwell=dwell)
    n_runs = None if n_runs is None else int(n_runs)
    prog(0.1, "default bench")
    cand = candidate_runs(sc, spacing=spacing, seed=seed)
    prog(0.2, f"{len(cand)} candidate runs")
    data, kept = predict_runs(sc, cand, seed=seed + 1, max_steps=max_steps, dwell=dwell)
    # a designed run must arrive: one that leaves the workspace or cycles measures little and
    # depends on the noise
    good = arrived(data, max(5e-4, 3 * sc.sensors.tracker_sigma))
    data = data.subset(np.flatnonzero(good))
    cand = cand[kept[good]]
    structural: list[str] = []
    if model.qr_identify:
        # a geometric group: the parameters no run of the whole candidate set can see (a translation
        # along a revolute axis, two that show the same) are held, as calibrate's QR holds them;
        # the design makes the rest, the base parameters, identifiable
        from .residual import declared_plant, motion_model

        model.identify(data.q, data.commanded_directions(motion_model(sc)), data.tip, declared_plant(sc, data),
                       run=data.run)
        structural = model.held_labels
    info0 = bench_info(sc, d0, model)
    max_rows = info0.rows if max_rows is None else (None if max_rows == 0 else int(max_rows))
    prog(0.4, "candidate rows")
    blocks = run_blocks(row_jacobian(sc, data, model), data)
    rows = data.lengths
    if n_runs is not None and n_runs * int(rows.max()) * sc.dim < model.n_free:
        raise ErrplanError(f"--design {n_runs}: too few runs for the catalogue's {model.n_free} parameters")
    pairs = tuple((tuple(info0.effects[a]), tuple(info0.effects[b])) for a, b in itertools.combinations(info0.effects, 2))
    objective = Objective(criterion, pairs, separate)
    chosen = select_runs(blocks, rows, n_runs, max_rows=max_rows, objective=objective)
    prog(0.95, "selection")
    M = blocks[chosen].sum(axis=0)
    info1 = _info(sc, model, M, int(rows[chosen].sum()), len(chosen))
    meta = {"max_rows": max_rows, "seed": seed, "separate": separate}
    if effects is not None:
        meta.update(effects=list(effects), not_identifiable_by_any_run=structural,
                    rank={"default": rank(sc, d0, model), "designed": None})
        d1, _ = predict_runs(sc, cand[chosen], seed=seed, max_steps=max_steps, dwell=dwell)
        meta["rank"]["designed"] = rank(sc, d1, model)
        meta["parameters"] = model.n_free
    return Design(sc.name, criterion, cand[chosen], info0, info1, len(cand), time.perf_counter() - t0,
                  meta=meta)


def rank(sc, data: MeasuredData, model: EffectModel) -> int:
    """The numerical rank of the model's regressor on ``data``'s rows: QR with column pivoting, the
    columns with |R_ii| >= QR_RTOL |R_11| (the test calibrate's :meth:`EffectModel.identify` applies)."""
    from scipy.linalg import qr

    from ..effects import QR_RTOL

    A = row_jacobian(sc, data, model).reshape(-1, model.n_free)
    if A.size == 0:
        return 0
    diag = np.abs(np.diag(qr(A, mode="r", pivoting=True)[0]))
    return int(np.count_nonzero(diag >= QR_RTOL * diag[0])) if diag[0] > 0 else 0
