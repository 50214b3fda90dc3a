"""The empirical last resort (docs/physics.md "An empirical term, last"): a sparse correction of the
tracked tip when the best catalogue model still leaves a structured residual.

``Δ(x, q) = Σ_k θ_k φ_k(x, q)`` over a documented basis: monomials of the model tip's coordinates
about the data's centroid, scaled by the data's extent (half the range per coordinate), total degree
1..D (D ≤ 3; the constant is included); sin and cos of each encoder angle, orders 1 and 2. Fitted by
sequentially thresholded least squares (STLSQ, as in SINDy): least squares on the columns normalised
to unit RMS, coefficients below the threshold zeroed, refit on the survivors, ten rounds. The degree
D and the threshold are chosen by grouped K-fold cross-validation over whole runs (the lowest held-out
RMS; among those within 1 % of it, the fewest terms). Written over numpy (about 60 lines): PySINDy's
STLSQ is this loop, and the library would bring scikit-learn and its own feature-library machinery for
a basis errplan must define itself anyway.

Reported as ``empirical`` (never a physical effect: ``explained`` stays false) with the held-out RMS
before and after; ``history_dependent`` when the term does not lower the held-out runs' error by
a tenth: the residual then depends on the motion's history or on time, not on the pose.
"""
from __future__ import annotations

import itertools
import math

import numpy as np

DEGREES = (1, 2, 3)
THRESHOLDS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.5)   # in units of the residual's RMS per normalised column
STLSQ_ROUNDS = 10
HISTORY_GAIN = 0.9   # held-out RMS after / before above this: the pose basis does not predict the runs


def basis(x: np.ndarray, q: np.ndarray, centre: np.ndarray, extent: np.ndarray, degree: int):
    """Features (n, m) and their names for model tips ``x`` (n, d) and encoder angles ``q`` (n, N)."""
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
    return np.stack(cols, axis=1), names


def stlsq(F: np.ndarray, r: np.ndarray, threshold: float) -> np.ndarray:
    """Sequentially thresholded least squares: coefficients (m, d) of ``F @ coef ≈ r`` with every
    coefficient whose normalised size (coefficient x column RMS / residual RMS) is below
    ``threshold`` zeroed (a feature is kept while any coordinate needs it)."""
    norm = np.sqrt(np.mean(F * F, axis=0))
    norm = np.where(norm > 0, norm, 1.0)
    Fn = F / norm
    scale = max(float(np.sqrt(np.mean(r * r))), 1e-300)
    active = np.ones(F.shape[1], bool)
    coef = np.zeros((F.shape[1], r.shape[1]))
    for _ in range(STLSQ_ROUNDS):
        coef[:] = 0.0
        if active.any():
            coef[active] = np.linalg.lstsq(Fn[:, active], r, rcond=1e-10)[0]
        keep = np.max(np.abs(coef), axis=1) >= threshold * scale
        if np.array_equal(keep, active):
            break
        active = keep
    coef[~active] = 0.0
    return coef / norm[:, None]


def fit_empirical(x: np.ndarray, q: np.ndarray, r: np.ndarray, run: np.ndarray, *, folds: int = 5, seed: int = 0):
    """The empirical term for residual ``r`` (n, d) at model tips ``x`` and encoder angles ``q``,
    degree and threshold by grouped K-fold over whole runs. Returns the calibrate JSON's
    ``empirical`` object and a predictor ``f(x, q) -> (n, d)``."""
    x, q, r = (np.asarray(a, float) for a in (x, q, r))
    run = np.unique(np.asarray(run), return_inverse=True)[1]
    runs = int(run.max()) + 1
    k = max(2, min(folds, runs))
    rng = np.random.default_rng(seed)
    fold_of_run = np.empty(runs, int)
    fold_of_run[rng.permutation(runs)] = np.arange(runs) % k
    fold = fold_of_run[run]
    centre = x.mean(axis=0)
    extent = np.maximum((x.max(axis=0) - x.min(axis=0)) / 2, 1e-6)
    before = math.sqrt(float(np.mean(r * r)))
    best = None
    tried = []
    for deg in DEGREES:
        F, names = basis(x, q, centre, extent, deg)
        for th in THRESHOLDS:
            sse = 0.0
            for f in range(k):
                te = fold == f
                c = stlsq(F[~te], r[~te], th)
                e = r[te] - F[te] @ c
                sse += float(np.sum(e * e))
            ho = math.sqrt(sse / r.size)
            terms = int(np.count_nonzero(np.any(stlsq(F, r, th) != 0, axis=1)))
            cand = (ho, terms, deg, th)
            if best is None or ho < best[0]:
                best = cand
            tried.append(cand)
    ok = [c for c in tried if c[0] <= 1.01 * best[0]]
    ho, terms, deg, th = min(ok, key=lambda c: (c[1], c[0]))
    F, names = basis(x, q, centre, extent, deg)
    coef = stlsq(F, r, th)
    active = np.flatnonzero(np.any(coef != 0, axis=1))
    out = {"terms": [{"name": names[i], "coefficient": [float(v) for v in coef[i]]} for i in active],
           "degree": deg, "threshold": th, "folds": k, "held_out_rms_before": before, "held_out_rms_after": ho,
           "history_dependent": bool(ho > HISTORY_GAIN * before),
           "basis": "monomials of (model tip - centroid) / half-range up to the degree; sin, cos of each encoder "
                    "angle, orders 1 and 2", "centroid": [float(v) for v in centre],
           "extent": [float(v) for v in extent]}

    def predict(x2: np.ndarray, q2: np.ndarray) -> np.ndarray:
        return basis(np.asarray(x2, float), np.asarray(q2, float), centre, extent, deg)[0] @ coef

    return out, predict
