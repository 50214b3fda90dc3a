"""The noise floor of a residual and the test for structure left in it (steps 2 and 5 of
:mod:`errplan.calibration`): local polynomials on k-means clusters of rows."""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from .residual import rms

STRUCTURE_P = 1e-3          # level of the held-out-runs test for "the residual has structure"
STRUCTURE_RATIO = 0.25      # structured RMS >= this x noise floor (and significant) -> not explained
STRUCTURE_FOLDS = 5         # folds of whole runs for the held-out structure test


# ----------------------------------------------------------------------------- noise floor
def _exponents(dim: int, degree: int) -> list[tuple[int, ...]]:
    return [e for e in itertools.product(range(degree + 1), repeat=dim) if sum(e) <= degree]


def _legendre_total(x: np.ndarray, degree: int) -> np.ndarray:
    """Total-degree Legendre features of d-dimensional points in [-1, 1]^d (n, C(degree + d, d))."""
    from numpy.polynomial import legendre

    V = [legendre.legvander(x[:, i], degree) for i in range(x.shape[1])]
    cols = [np.prod([V[i][:, k] for i, k in enumerate(e)], axis=0) for e in _exponents(x.shape[1], degree)]
    return np.stack(cols, axis=-1)


def _nearest(x: np.ndarray, c: np.ndarray, block: int = 2**20) -> np.ndarray:
    """Index of the nearest centre (k, d) for each point (n, d), in blocks of rows so that the
    distance table never exceeds ``block`` entries (the number of clusters grows with the rows)."""
    out = np.empty(len(x), int)
    step = max(1, block // max(len(c), 1))
    for i in range(0, len(x), step):
        xb = x[i:i + step]
        out[i:i + len(xb)] = np.argmin(np.sum((xb[:, None, :] - c[None]) ** 2, axis=2), axis=1)
    return out


def kmeans_labels(x: np.ndarray, clusters: int, iters: int = 30) -> np.ndarray:
    """Deterministic k-means of points (n, d): farthest-point initialisation from the point
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


def _lstsq(F: np.ndarray, b: np.ndarray, rcond: float = 1e-10) -> tuple[np.ndarray, int]:
    """Least squares through the SVD (singular values below ``rcond`` times the largest dropped):
    the solution and the rank. ``np.linalg.lstsq`` (LAPACK gelsd) gives the same answer but, with
    a threaded OpenBLAS on a busy 2-core machine, can take 100x longer on these small matrices."""
    U, sv, Vt = np.linalg.svd(F, full_matrices=False)
    keep = sv > rcond * (sv[0] if len(sv) else 0.0)
    coef = (Vt[keep].T / sv[keep]) @ (U[:, keep].T @ b)
    return coef, int(keep.sum())


@dataclass
class LocalBasis:
    """The flexible smooth model: on each cluster of rows (``labels``, k-means of the model tip
    positions) a Legendre polynomial of ``degree`` in the local tip coordinates times
    ``[1, u_1, .., u_d]`` (lower degree where a cluster has too few rows)."""

    labels: np.ndarray
    degree: int = 2

    def _cluster(self, k: int, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        idx = np.flatnonzero(self.labels == k)
        nc = len(idx)
        d = self.degree
        dim = x.shape[1]
        while d > 0 and (1 + u.shape[1]) * len(_exponents(dim, d)) > nc / 2.5:
            d -= 1
        xx = x[idx]
        lo, hi = xx.min(axis=0), xx.max(axis=0)
        hi = np.where(hi > lo, hi, lo + 1e-3)
        P = _legendre_total(2 * (xx - lo) / (hi - lo) - 1, d)
        return idx, np.concatenate([P] + [P * u[idx, i:i + 1] for i in range(u.shape[1])], axis=1)

    def predict_held_out(self, r: np.ndarray, x: np.ndarray, u: np.ndarray, train: np.ndarray) -> np.ndarray:
        """The smooth model fitted on the rows ``train`` (mask) and evaluated on every row (n, d):
        the same clusters and per-cluster bases as :meth:`fit` (a row of a cluster without enough
        training rows is predicted 0)."""
        pred = np.zeros_like(r)
        for k in range(int(self.labels.max()) + 1):
            idx, F = self._cluster(k, x, u)
            tr = train[idx]
            if len(idx) == 0 or tr.sum() < F.shape[1] + 2:
                continue
            coef, _ = _lstsq(F[tr], r[idx][tr])
            pred[idx] = F @ coef
        return pred

    def fit(self, r: np.ndarray, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, float, int]:
        """Fit residuals (n, d): fitted values (n, d), RSS (m^2), total rank per coordinate."""
        fit = np.zeros_like(r)
        rank = 0
        for k in range(int(self.labels.max()) + 1):
            idx, F = self._cluster(k, x, u)
            if len(idx) == 0:
                continue
            coef, rk = _lstsq(F, r[idx])
            fit[idx] = F @ coef
            rank += int(rk)
        res = r - fit
        return fit, float(np.sum(res * res)), rank


#: flexible-model settings tried for the noise floor: (rows per cluster, polynomial degree); in 3-D
#: a cubic times [1, u] has 80 terms per coordinate, so the clusters are larger
FLEX_CONFIGS = ((60, 2), (90, 2), (120, 2), (90, 3), (120, 3), (180, 3), (240, 3))
FLEX_CONFIGS_3D = ((120, 2), (180, 2), (240, 2), (240, 3), (360, 3), (480, 3))


#: the delays (in steps of the data's median step duration) of the noise floor's motion features: every
#: tracker_latency the catalogue allows (0 <= tau <= 5 steps) is a combination of them
LATENCY_LAGS = 5


def latency_features(x: np.ndarray, run: np.ndarray, time: np.ndarray | None = None,
                     lags: int = LATENCY_LAGS) -> np.ndarray:
    """The noise floor's motion features (n, d * lags): for k = 1 .. ``lags``, the model tip ``x`` (n, d)
    at the row's time - k median steps minus at the row's time, linear in time between the rows of a
    run (:func:`errplan.effects.delayed`, ``tracker_latency``'s own interpolation). A tracked tip that
    is late by tau reads ``x(t - tau) - x(t)`` off the model's: for tau on this grid one column per
    coordinate, between two grid points (nearly) a combination of the two. Each row's features are its
    run's past only, so they never follow the row's own noise (the closed loop reacts to a row's noise
    from the next row on). ``time`` None: the step index within the run."""
    from ..effects import delayed

    x = np.asarray(x, float)
    run = np.asarray(run)
    if len(x) == 0:
        return np.zeros((0, x.shape[1] * lags))
    dt = 1.0
    if time is not None:
        t = np.asarray(time, float)
        d = np.diff(t)[run[1:] == run[:-1]]
        d = d[d > 0]
        dt = float(np.median(d)) if len(d) else 1.0
    return np.concatenate([delayed(x, time, run, k * dt) - x for k in range(1, lags + 1)], axis=1)


def _project_out(F: np.ndarray, A: np.ndarray, rcond: float = 1e-10) -> tuple[np.ndarray, int]:
    """``A`` minus its least-squares projection on the columns of ``F``, and the rank of ``F``."""
    U, sv, _ = np.linalg.svd(F, full_matrices=False)
    keep = sv > rcond * (sv[0] if len(sv) else 0.0)
    Uk = U[:, keep]
    return A - Uk @ (Uk.T @ A), int(keep.sum())


def _fit_with_motion(basis: LocalBasis, r: np.ndarray, x: np.ndarray, u: np.ndarray,
                     m: np.ndarray) -> tuple[np.ndarray, float, int, np.ndarray]:
    """The local polynomials of ``basis`` plus global columns ``m`` (n, k) fitted jointly to ``r``
    (Frisch-Waugh-Lovell: each cluster's basis projected out of ``r`` and ``m``, the global
    coefficients from what is left, the local ones from ``r - m coef``). Returns the fitted values
    (n, d), the RSS, the rank per coordinate and the global coefficients (k, d)."""
    rr = np.zeros_like(r)
    mm = np.zeros_like(m)
    rank = 0
    for k in range(int(basis.labels.max()) + 1):
        idx, F = basis._cluster(k, x, u)
        if len(idx) == 0:
            continue
        both, rk = _project_out(F, np.concatenate([r[idx], m[idx]], axis=1))
        rr[idx], mm[idx] = both[:, :r.shape[1]], both[:, r.shape[1]:]
        rank += rk
    scale = np.sqrt(np.mean(mm * mm, axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    coef, rk_m = _lstsq(mm / scale, rr)
    coef = coef / scale[:, None]
    res = rr - mm @ coef
    return r - res, float(np.sum(res * res)), rank + rk_m, coef


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
    #: the global coefficients (k, d) of the motion features when given (:func:`latency_features`)
    motion_coef: np.ndarray | None = field(repr=False, default=None)

    def to_json(self) -> dict:
        return {"sigma": self.sigma, "clusters": self.clusters, "degree": self.degree,
                "parameters_per_coordinate": self.features, "smooth_rms": self.smooth_rms,
                "motion_features": 0 if self.motion_coef is None else int(self.motion_coef.shape[0]),
                "estimator": "dof-corrected RMS, sqrt(RSS / d(n - m)), left by local polynomials in the tip position "
                             "x [1, u] on k-means clusters of rows (cluster size and degree by AIC) and, fitted with "
                             "them, the motion: the model tip 1..5 steps earlier minus now"}


def noise_floor(r: np.ndarray, x: np.ndarray, u: np.ndarray, configs=None, motion: np.ndarray | None = None) -> NoiseFloor:
    """Estimate the measurement noise (per coordinate, m) from a pose residual ``r`` (n, d).

    ``x`` (n, d) are the model tip positions (where the rows are), ``u`` (n, d) friction's
    directions. Every catalogue effect and the usual unmodelled ones are smooth in the
    configuration (friction linear in ``u``), so a flexible local model — polynomials in ``x``
    times ``[1, u_1, .., u_d]`` on compact clusters of rows — follows them, and what is left is the
    noise: ``sigma = sqrt(RSS / (d (n - m)))``, m the parameters per coordinate. The cluster size
    and degree come from ``configs`` (default :data:`FLEX_CONFIGS`, :data:`FLEX_CONFIGS_3D`) by AIC
    (``N ln(RSS/N) + 2 (d m)``, ``N = d n``).

    ``motion`` (n, k): global columns fitted with the local polynomials (:func:`latency_features`):
    a late tracker's residual follows the motion, not the pose, and no local polynomial of the pose
    follows it; without them the latency would be taken for noise (docs/physics.md "The structure
    test sees the motion"). They count in m.
    """
    n, dim = r.shape
    if motion is not None and (motion.ndim != 2 or motion.shape[1] == 0 or not np.all(np.isfinite(motion))):
        motion = None
    N = dim * n
    configs = (FLEX_CONFIGS if dim == 2 else FLEX_CONFIGS_3D) if configs is None else configs
    best = None
    for per, deg in configs:
        labels = kmeans_labels(x, max(1, n // per))
        basis = LocalBasis(labels, deg)
        coef = None
        if motion is None:
            fit, rss, rank = basis.fit(r, x, u)
        else:
            fit, rss, rank, coef = _fit_with_motion(basis, r, x, u, motion)
        if n - rank < max(2, n // 4):
            continue
        aic = N * math.log(max(rss, 1e-300) / N) + 2 * dim * rank
        if best is None or aic < best[0]:
            best = (aic, basis, fit, rss, rank, deg, coef)
    if best is None:
        s = rms(r - r.mean(axis=0))
        return NoiseFloor(s, 1, 0, 1, 0.0, LocalBasis(np.zeros(n, int), 0), x)
    _, basis, fit, rss, rank, deg, coef = best
    return NoiseFloor(math.sqrt(rss / (dim * (n - rank))), int(basis.labels.max()) + 1, deg, rank, rms(fit), basis, x,
                      coef)


def motion_features(step: np.ndarray, run: np.ndarray, time: np.ndarray | None = None) -> np.ndarray:
    """The row's motion (docs/physics.md "The structure test sees the motion"): the model tip's step
    from the row before, ``x_model(q(t)) - x_model(q(t-1))`` (``step`` (n, d), zero at a run's first
    row), divided by the step's duration (``time`` differences within the run; without ``time``, one
    step). ``run`` (n,) the run of each row; rows run-major, steps ascending. Returns (n, d)."""
    step = np.asarray(step, float)
    run = np.asarray(run)
    first = np.r_[True, run[1:] != run[:-1]] if len(run) else np.zeros(0, bool)
    out = np.where(first[:, None], 0.0, step)
    if time is not None:
        t = np.asarray(time, float)
        dt = np.r_[1.0, np.diff(t)] if len(t) else np.zeros(0)
        dt = np.where(first | ~(dt > 0), 1.0, dt)
        out = out / dt[:, None]
    return out


def model_steps(x: np.ndarray, run: np.ndarray) -> np.ndarray:
    """``x(t) - x(t-1)`` within each run (zero at a run's first row) for points ``x`` (n, d)."""
    x = np.asarray(x, float)
    run = np.asarray(run)
    d = np.zeros_like(x)
    if len(x) > 1:
        d[1:] = x[1:] - x[:-1]
        d[np.r_[True, run[1:] != run[:-1]]] = 0.0
    return d


@dataclass
class GlobalBasis:
    """The structure test's second flexible model, fitted on all the rows at once: a total-degree
    ``degree`` Legendre polynomial of the model tip over the rows' bounding box, the row's motion
    (:func:`motion_features`, columns normalised) and friction's direction ``u``. Few parameters
    (planar 14, spatial 26 per coordinate), so fitted without some runs it still predicts the others:
    a warp of the tracker's space, a latency (the residual follows the velocity) or friction."""

    x: np.ndarray
    v: np.ndarray | None
    degree: int = 3

    def features(self, u: np.ndarray) -> np.ndarray:
        lo, hi = self.x.min(axis=0), self.x.max(axis=0)
        hi = np.where(hi > lo, hi, lo + 1e-3)
        cols = [_legendre_total(2 * (self.x - lo) / (hi - lo) - 1, self.degree)]
        if self.v is not None:
            cols.append(self.v)
        if u is not None:
            cols.append(u)
        F = np.concatenate(cols, axis=1)
        norm = np.sqrt(np.mean(F * F, axis=0))
        return F / np.where(norm > 0, norm, 1.0)

    def fit(self, r: np.ndarray, u: np.ndarray) -> tuple[float, int]:
        coef, rank = _lstsq(self.features(u), r)
        res = r - self.features(u) @ coef
        return float(np.sum(res * res)), rank

    def predict_held_out(self, r: np.ndarray, u: np.ndarray, train: np.ndarray) -> np.ndarray:
        F = self.features(u)
        if train.sum() < F.shape[1] + 2:
            return np.zeros_like(r)
        coef, _ = _lstsq(F[train], r[train])
        return F @ coef


@dataclass
class Structure:
    """Is a residual structured? Two flexible models fitted on some runs must predict the residual of
    the others (held-out whole runs); see :func:`structure_test`."""

    rms: float            # per-coordinate RMS of the residual
    structured_rms: float  # RMS of the part the flexible models find (the larger of the two's, in sample)
    f_stat: float          # the in-sample F statistic (information only: it fires on closed-loop noise)
    p_value: float         # the held-out-runs test's one-sided p-value (both models, Bonferroni)
    ratio: float           # rms / noise floor
    structured: bool
    f_p_value: float = float("nan")   # the in-sample F test's p-value (information only)
    runs: int = 0
    test: str = "held-out runs"
    #: each flexible model's p-value and structured RMS: {"local": {...}, "global": {...}}
    models: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"rms": self.rms, "structured_rms": self.structured_rms, "f_statistic": self.f_stat,
                "p_value": self.p_value, "rms_over_noise_floor": self.ratio, "structured": self.structured,
                "in_sample_f_p_value": self.f_p_value, "runs": self.runs, "test": self.test, "models": self.models}


def _run_scores(r: np.ndarray, pred: np.ndarray, run: np.ndarray, runs: int) -> float:
    """One-sided Wilcoxon signed-rank p-value that the runs' held-out scores ``sum r . pred`` lean positive."""
    from scipy.stats import wilcoxon

    g = np.bincount(run, weights=np.sum(r * pred, axis=1), minlength=runs)
    nz = g[g != 0]
    return float(wilcoxon(nz, alternative="greater").pvalue) if len(nz) >= 2 else 1.0


def structure_test(r: np.ndarray, u: np.ndarray, nf: NoiseFloor, run: np.ndarray | None = None,
                   seed: int = 0, motion: np.ndarray | None = None) -> Structure:
    """Is residual ``r`` (n, d) structured? Tested by whole runs (``run`` (n,) the run of each row).

    In closed loop each row's encoder angles depend on earlier rows' tracker noise, so rows are not
    exchangeable and an in-sample F test of a flexible model fires on pure noise. The test here
    holds whole runs out: a flexible model is fitted on the other folds' runs and predicts the
    held-out runs' residual (:data:`STRUCTURE_FOLDS` folds of runs, seeded). Each run's score
    ``g = sum over its rows of r . prediction``: a run's noise is independent of the other runs'
    (every run starts afresh from its start), so for noise the score has mean 0 whatever the closed
    loop did inside the runs; where the residual has a shape the runs share it is positive. One-sided
    Wilcoxon signed-rank test over runs that the scores lean positive.

    Two flexible models, each tested so, the smaller p-value doubled (Bonferroni):
    - ``local``: the noise floor's local polynomials on k-means clusters times ``[1, u]`` (follows a
      field that changes within the workspace; with many parameters per cluster, fitted without a
      fifth of the runs it predicts mostly noise where the held-out runs go, so it alone misses a
      smooth field of the whole workspace less than twice the noise floor);
    - ``global``: :class:`GlobalBasis`, a cubic of the tip over the workspace, the row's ``motion``
      (:func:`motion_features`) and ``u``: few parameters, so it predicts held-out runs (a tracker
      warp, a latency, friction).

    ``structured_rms``: the size of the smooth part, ``sqrt(max(0, RSS0 - RSS1 - d m sigma^2) / (d n))``
    in sample (what a model removes beyond what it would absorb from pure noise), the larger of the
    two. Structured (not explained) when ``p < STRUCTURE_P`` and that model's ``structured_rms`` is at
    least ``STRUCTURE_RATIO`` noise floors. Without ``run`` (or with fewer than 4 runs) every row is its
    own run. The local model's in-sample F statistic and its p-value are kept for information."""
    from scipy.stats import f as fdist

    n, dim = r.shape
    rss0 = float(np.sum(r * r))
    ratio = rms(r) / max(nf.sigma, 1e-300)
    _, rss1, rank = nf.basis.fit(r, nf.x, u)
    df1, df2 = dim * rank, dim * (n - rank)
    if df1 <= 0 or df2 <= 0:
        return Structure(rms(r), 0.0, 0.0, 1.0, ratio, False)
    fstat = ((rss0 - rss1) / df1) / max(rss1 / df2, 1e-300)
    p_f = float(fdist.sf(fstat, df1, df2))
    run = np.arange(n) if run is None or len(np.unique(run)) < 4 else np.unique(np.asarray(run), return_inverse=True)[1]
    runs = int(run.max()) + 1
    k = min(STRUCTURE_FOLDS, runs)
    rng = np.random.default_rng(seed)
    fold_of_run = np.empty(runs, int)
    fold_of_run[rng.permutation(runs)] = np.arange(runs) % k
    fold = fold_of_run[run]
    glob = GlobalBasis(nf.x, motion)
    pred_l, pred_g = np.zeros_like(r), np.zeros_like(r)
    for f_ in range(k):
        te = fold == f_
        pred_l[te] = nf.basis.predict_held_out(r, nf.x, u, ~te)[te]
        pred_g[te] = glob.predict_held_out(r, u, ~te)[te]
    rss_g, rank_g = glob.fit(r, u)
    sig2 = nf.sigma ** 2
    models = {}
    for name, pred, rss_m, rk in (("local", pred_l, rss1, rank), ("global", pred_g, rss_g, rank_g)):
        s = math.sqrt(max(0.0, (rss0 - rss_m) - dim * rk * sig2) / (dim * n))
        models[name] = {"p_value": _run_scores(r, pred, run, runs), "structured_rms": s, "parameters_per_coordinate": rk}
    p = min(1.0, 2 * min(m["p_value"] for m in models.values()))
    structured = any(min(1.0, 2 * m["p_value"]) < STRUCTURE_P and m["structured_rms"] >= STRUCTURE_RATIO * nf.sigma
                     for m in models.values())
    s = max(m["structured_rms"] for m in models.values())
    return Structure(rms(r), s, float(fstat), p, ratio, bool(structured), p_f, runs, models=models)
