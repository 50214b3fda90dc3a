"""The empirical last resort (docs/physics.md "An empirical term, last"): a sparse correction of the
tracked tip when the best catalogue model still leaves a structured residual.

``Δ(x, q) = Σ_k θ_k φ_k(x, q)`` over a documented basis: monomials of the model tip's coordinates
about the data's centroid, scaled by the data's extent (half the range per coordinate), total degree
1..D (D ≤ 3; the constant is included); sin and cos of each encoder angle, orders 1 and 2; and, when
the caller gives the rows' motion (the declared model tip's step over its duration,
:func:`errplan.calibration.noise.motion_features`), its coordinates scaled by their RMS (``vx'``, ...).
A term on the motion is history-dependent by construction (a row's motion is its run's history), and
the report says so. The basis with the motion is fitted beside the one without and kept only when its
held-out RMS is 5 % lower (:data:`MOTION_GAIN`): in closed loop the motion correlates with the pose.

Fitted with scikit-learn (the only module that imports it): the columns normalised to unit RMS, the
support of the term from the multi-task lasso path (:func:`sklearn.linear_model.lasso_path` with all
coordinates at once, so a feature is kept or dropped for every coordinate together), then the
coefficients refitted by least squares on that support (:class:`sklearn.linear_model.LinearRegression`,
a "relaxed" lasso: the lasso chooses the terms, its shrinkage does not bias them). The degree D and the
penalty are chosen by :class:`sklearn.model_selection.GroupKFold` over whole runs (shuffled with the
seed): the lowest held-out RMS, and among those within 1 % of it the fewest terms. The penalties are
a fixed grid relative to the full data's ``alpha_max`` (the smallest penalty that keeps no term), so
every fold is scored on the same grid.

Reported as ``empirical`` (never a physical effect: ``explained`` stays false) with the held-out RMS
before and after; ``history_dependent`` when the term does not lower the held-out runs' error by
a tenth: the residual then depends on the motion's history or on time, not on the pose.
"""
from __future__ import annotations

import itertools
import math
import warnings

import numpy as np

DEGREES = (1, 2, 3)
#: the penalties, relative to alpha_max (the smallest that keeps no term): 1 .. 1e-2 in 13 steps, and 0
#: (every term: plain least squares; below 1e-2 the path keeps nearly every term anyway, and coordinate
#: descent is slowest there)
ALPHA_GRID = np.r_[np.logspace(0.0, -2.0, 13), 0.0]
HISTORY_GAIN = 0.9   # held-out RMS after / before above this: the pose basis does not predict the runs
PARSIMONY = 1.01     # candidates within 1 % of the best held-out RMS: the fewest terms
MOTION_GAIN = 0.95   # terms on the motion kept only when they cut the held-out RMS by 5 % beyond the pose's


def basis(x: np.ndarray, q: np.ndarray, centre: np.ndarray, extent: np.ndarray, degree: int,
          v: np.ndarray | None = None, vscale: np.ndarray | None = None):
    """Features (n, m) and their names for model tips ``x`` (n, d), encoder angles ``q`` (n, N) and,
    optionally, the rows' motion ``v`` (n, d) over its scale ``vscale`` (d,)."""
    z = (np.asarray(x, float) - centre) / extent
    d = z.shape[1]
    axes = ("x", "y", "z")[3 - d:]
    cols, names = [np.ones(len(z))], ["1"]
    for deg in range(1, degree + 1):
        for e in itertools.combinations_with_replacement(range(d), deg):
            cols.append(np.prod(z[:, list(e)], axis=1))
            names.append("*".join(f"{axes[i]}'" for i in e))
    for j in range(q.shape[1]):
        for k in (1, 2):
            cols += [np.sin(k * q[:, j]), np.cos(k * q[:, j])]
            names += [f"sin({k}q{j + 1})" if k > 1 else f"sin(q{j + 1})", f"cos({k}q{j + 1})" if k > 1 else f"cos(q{j + 1})"]
    if v is not None:
        w = np.asarray(v, float) / vscale
        for i in range(d):
            cols.append(w[:, i])
            names.append(f"v{axes[i]}'")
    return np.stack(cols, axis=1), names


def is_motion_term(name: str) -> bool:
    """A term of :func:`basis` on the row's motion (history-dependent by construction)."""
    return name.startswith("v") and name.endswith("'") and "*" not in name


def _normalised(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    norm = np.sqrt(np.mean(F * F, axis=0))
    norm = np.where(norm > 0, norm, 1.0)
    return F / norm, norm


def alpha_max(Fn: np.ndarray, r: np.ndarray) -> float:
    """The multi-task lasso's smallest penalty that keeps no term: ``max_j ‖Fn_jᵀ r‖₂ / n``."""
    return float(np.max(np.linalg.norm(Fn.T @ r, axis=1)) / len(r))


def supports(Fn: np.ndarray, r: np.ndarray, alphas: np.ndarray) -> np.ndarray:
    """The multi-task lasso path's supports (n_alphas, m) of ``Fn @ W ≈ r`` at ``alphas`` (scikit-learn,
    positive penalties in decreasing order); a zero penalty is every term."""
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.linear_model import lasso_path

    alphas = np.asarray(alphas, float)
    out = np.ones((len(alphas), Fn.shape[1]), bool)
    pos = alphas > 0
    if pos.any():
        with warnings.catch_warnings():
            # at the smallest penalties coordinate descent may stop at max_iter; only the support is used
            warnings.simplefilter("ignore", ConvergenceWarning)
            _, coefs, _ = lasso_path(np.asfortranarray(Fn), np.asfortranarray(r), alphas=alphas[pos], tol=1e-4,
                                     max_iter=1000)
        coefs = coefs.reshape(r.shape[1], Fn.shape[1], int(pos.sum()))  # (targets, features, alphas)
        out[pos] = np.any(coefs != 0.0, axis=0).T
    return out


def refit(Fn: np.ndarray, r: np.ndarray, support: np.ndarray) -> np.ndarray:
    """Least squares on the support (scikit-learn's LinearRegression, no intercept: the basis has the
    constant): coefficients (m, d) on the normalised columns, zero off the support."""
    from sklearn.linear_model import LinearRegression

    coef = np.zeros((Fn.shape[1], r.shape[1]))
    if support.any():
        coef[support] = LinearRegression(fit_intercept=False).fit(Fn[:, support], r).coef_.T
    return coef


def fit_empirical(x: np.ndarray, q: np.ndarray, r: np.ndarray, run: np.ndarray, *, folds: int = 5, seed: int = 0,
                  motion: np.ndarray | None = None):
    """The empirical term for residual ``r`` (n, d) at model tips ``x`` and encoder angles ``q`` (and
    the rows' ``motion`` (n, d) when given), degree and penalty by grouped K-fold over whole runs.
    Returns the calibrate JSON's ``empirical`` object and a predictor ``f(x, q, motion=None) -> (n, d)``."""
    from threadpoolctl import threadpool_limits

    # one thread for every BLAS and OpenMP pool (scipy's and scikit-learn's too, not only numpy's):
    # these are hundreds of small problems (errplan.calibration.blas)
    with threadpool_limits(limits=1):
        pose = _fit_empirical(x, q, r, run, folds, seed)
        if motion is None:
            return pose
        # the motion's terms only when they predict the held-out runs clearly better than the pose's alone:
        # in closed loop the motion correlates with where the tip is, and a warp of the tracker's space
        # would otherwise borrow a term on the motion and read as history-dependent
        moving = _fit_empirical(x, q, r, run, folds, seed, motion)
        if moving[0]["motion_terms"] and moving[0]["held_out_rms_after"] < MOTION_GAIN * pose[0]["held_out_rms_after"]:
            return moving
        return pose


def _fit_empirical(x, q, r, run, folds, seed, motion=None):
    from sklearn.model_selection import GroupKFold

    x, q, r = (np.asarray(a, float) for a in (x, q, r))
    v = None if motion is None else np.asarray(motion, float)
    vscale = None if v is None else np.where((s_ := np.sqrt(np.mean(v * v, axis=0))) > 0, s_, 1.0)
    run = np.unique(np.asarray(run), return_inverse=True)[1]
    runs = int(run.max()) + 1
    k = max(2, min(folds, runs))
    splits = list(GroupKFold(n_splits=k, shuffle=True, random_state=seed).split(x, r, groups=run))
    centre = x.mean(axis=0)
    extent = np.maximum((x.max(axis=0) - x.min(axis=0)) / 2, 1e-6)
    before = math.sqrt(float(np.mean(r * r)))
    tried = []   # (held-out RMS, terms, degree, alpha index)
    for deg in DEGREES:
        Fn, _ = _normalised(basis(x, q, centre, extent, deg, v, vscale)[0])
        alphas = max(alpha_max(Fn, r), 1e-300) * ALPHA_GRID
        sse = np.zeros(len(alphas))
        for tr, te in splits:
            for a, sup in enumerate(supports(Fn[tr], r[tr], alphas)):
                e = r[te] - Fn[te] @ refit(Fn[tr], r[tr], sup)
                sse[a] += float(np.sum(e * e))
        full = supports(Fn, r, alphas)
        tried += [(math.sqrt(sse[a] / r.size), int(full[a].sum()), deg, a) for a in range(len(alphas))]
    best = min(c[0] for c in tried)
    ho, terms, deg, a = min((c for c in tried if c[0] <= PARSIMONY * best), key=lambda c: (c[1], c[0]))
    F, names = basis(x, q, centre, extent, deg, v, vscale)
    Fn, norm = _normalised(F)
    alpha = max(alpha_max(Fn, r), 1e-300) * ALPHA_GRID[a]
    coef = refit(Fn, r, supports(Fn, r, np.array([alpha]))[0]) / norm[:, None]
    active = np.flatnonzero(np.any(coef != 0, axis=1))
    out = {"terms": [{"name": names[i], "coefficient": [float(v) for v in coef[i]]} for i in active],
           "degree": deg, "alpha": float(alpha), "alpha_relative": float(ALPHA_GRID[a]), "folds": k,
           "held_out_rms_before": before, "held_out_rms_after": ho,
           "history_dependent": bool(ho > HISTORY_GAIN * before or any(is_motion_term(names[i]) for i in active)),
           "motion_terms": [names[i] for i in active if is_motion_term(names[i])],
           "method": "scikit-learn: support by the multi-task lasso path on unit-RMS columns, least squares on "
                     "the support; degree and penalty by GroupKFold over whole runs",
           "basis": "monomials of (model tip - centroid) / half-range up to the degree; sin, cos of each encoder "
                    "angle, orders 1 and 2", "centroid": [float(v) for v in centre],
           "extent": [float(v) for v in extent]}

    def predict(x2: np.ndarray, q2: np.ndarray, motion2: np.ndarray | None = None) -> np.ndarray:
        x2 = np.asarray(x2, float)
        if v is not None and motion2 is None:
            if out["motion_terms"]:
                raise ValueError("this empirical term has terms on the motion: give the rows' motion")
            motion2 = np.zeros_like(x2)   # no active term on the motion: its columns do not matter
        v2 = None if v is None else np.asarray(motion2, float)
        return basis(x2, np.asarray(q2, float), centre, extent, deg, v2, vscale)[0] @ coef

    return out, predict
