"""Outliers of measured data (docs/physics.md "Measured data as a bench records it"): a tracker that
swaps markers or catches a reflection gives a few rows far off.

A row is an outlier when its pose residual, after the best fit so far, is beyond
:data:`OUTLIER_SIGMAS` robust sigmas of the data's noise (the median absolute deviation of the
residual per coordinate times 1.4826) in some coordinate, and it stands alone in its run: neither
neighbouring tracked row of the same run is beyond :data:`NEIGHBOUR_SIGMAS` robust sigmas. A residual
that persists over consecutive rows is structure (an unmodelled latency is largest over a run's fast
first rows), never outliers.

"The best fit so far" is the noise floor's flexible model (:func:`errplan.calibration.noise.noise_floor`:
local polynomials of the model tip times ``[1, u]`` on k-means clusters of rows), fitted to the
declared model's residual: it follows every catalogue effect and the usual unmodelled ones, so what it
leaves is the noise and the outliers. Least squares is pulled toward an outlier (and its neighbours
away from it), so the fit is redone without every row beyond 6 robust sigmas found so far (up to
:data:`ITERATIONS` times, until the set stops changing), each such row then judged, alone or not, by
the residual of a fit it did not take part in. The caller excludes the outliers from
every fit, the noise floor and every RMS, and names each one.
"""
from __future__ import annotations

import dataclasses

import numpy as np

OUTLIER_SIGMAS = 6.0    # a row beyond this many robust sigmas (some coordinate) ...
NEIGHBOUR_SIGMAS = 3.0  # ... whose neighbouring tracked rows in its run are both within this many
MAD_TO_SIGMA = 1.4826   # the normal distribution's sigma over its median absolute deviation
ITERATIONS = 4


def robust_sigma(res: np.ndarray) -> np.ndarray:
    """Per-coordinate robust sigma (d,) of residuals (n, d): 1.4826 x the median absolute deviation."""
    res = np.asarray(res, float)
    med = np.median(res, axis=0)
    s = MAD_TO_SIGMA * np.median(np.abs(res - med), axis=0)
    return np.where(s > 0, s, np.finfo(float).tiny)


def lone_rows(res: np.ndarray, run: np.ndarray, tracked: np.ndarray, sigma: np.ndarray | None = None) -> np.ndarray:
    """The rows (n,) bool beyond :data:`OUTLIER_SIGMAS` robust sigmas whose neighbouring tracked rows of
    the same run (the one before and the one after, skipping dropouts) are within
    :data:`NEIGHBOUR_SIGMAS`. ``res`` (n, d) residuals (anything on untracked rows), ``run`` (n,),
    ``tracked`` (n,) bool; rows run-major, steps ascending. ``sigma`` (d,) defaults to
    :func:`robust_sigma` of the tracked rows."""
    res = np.asarray(res, float)
    run = np.asarray(run)
    tracked = np.asarray(tracked, bool)
    n = len(res)
    out = np.zeros(n, bool)
    idx = np.flatnonzero(tracked)
    if len(idx) < 3:
        return out
    sigma = robust_sigma(res[idx]) if sigma is None else np.asarray(sigma, float)
    med = np.median(res[idx], axis=0)
    z = np.max(np.abs(res[idx] - med) / sigma, axis=1)
    rr = run[idx]
    same_prev = np.r_[False, rr[1:] == rr[:-1]]
    same_next = np.r_[rr[:-1] == rr[1:], False]
    mid = z > NEIGHBOUR_SIGMAS
    prev_mid = np.r_[False, mid[:-1]] & same_prev
    next_mid = np.r_[mid[1:], False] & same_next
    out[idx] = (z > OUTLIER_SIGMAS) & ~prev_mid & ~next_mid
    return out


def find_outliers(r: np.ndarray, x: np.ndarray, u: np.ndarray, run: np.ndarray, tracked: np.ndarray,
                  extra: np.ndarray | None = None, return_residual: bool = False, motion: np.ndarray | None = None):
    """The outliers (n,) bool of a pose residual ``r`` (n, d) (the declared model's; NaN allowed on
    untracked rows) at model tips ``x`` (n, d), friction's directions ``u`` (n, d), runs ``run`` (n,),
    ``tracked`` (n,) bool (False on dropouts). ``extra`` (n, k): further smooth regressors the fit so
    far may use, appended to ``u``. ``motion`` (n, k): the noise floor's global motion features
    (:func:`errplan.calibration.noise.latency_features`), fitted with the local polynomials once and
    their part removed first (a late tracker's residual follows the motion: left in, it would inflate
    the robust sigma and show at a run's fast rows). With ``return_residual`` also the residual (n, d)
    after the fit without the far rows (NaN on untracked rows): an outlier's size is its norm."""
    from .noise import noise_floor

    tracked = np.asarray(tracked, bool) & np.all(np.isfinite(r), axis=1)
    idx = np.flatnonzero(tracked)
    out = np.zeros(len(r), bool)
    if len(idx) < 10:
        return (out, np.where(np.isfinite(r), r, np.nan)) if return_residual else out
    rt, xt, ut = r[idx], x[idx], u[idx]
    if extra is not None:
        ut = np.concatenate([ut, extra[idx]], axis=1)
    mt = None if motion is None else np.asarray(motion, float)[idx]
    nf = noise_floor(rt, xt, ut, motion=mt)
    basis = nf.basis
    if nf.motion_coef is not None:
        rt = rt - mt @ nf.motion_coef
    # every row beyond OUTLIER_SIGMAS is left out of the next fit (lone or not): least squares pulls the
    # fit toward an outlier, and so its neighbours (a run dwelling at its target sits at one place) away
    # from it; the rows are judged alone or not on the residual of a fit without them
    far = np.zeros(len(idx), bool)
    for _ in range(ITERATIONS):
        res = rt - basis.predict_held_out(rt, xt, ut, ~far)
        sig = robust_sigma(res[~far])
        new = np.max(np.abs(res - np.median(res[~far], axis=0)) / sig, axis=1) > OUTLIER_SIGMAS
        if np.array_equal(new, far):
            break
        far = new
    out[idx] = lone_rows(res, run[idx], np.ones(len(idx), bool), sig)
    if return_residual:
        full = np.full_like(np.asarray(r, float), np.nan)
        full[idx] = res
        return out, full
    return out


def without_rows(data, drop: np.ndarray):
    """``data`` (a :class:`errplan.experiment.MeasuredData`) without the rows ``drop`` (n,) bool: every
    per-row array subset, the runs kept (a run may lose rows; its remaining rows keep their steps)."""
    drop = np.asarray(drop, bool)
    if not drop.any():
        return data
    keep = ~drop
    n = data.rows
    changes = {}
    for f in dataclasses.fields(data):
        if not f.init:
            continue
        v = getattr(data, f.name)
        if isinstance(v, np.ndarray) and v.ndim >= 1 and len(v) == n:
            changes[f.name] = v[keep]
    return dataclasses.replace(data, **changes)


def listing(data, rows: np.ndarray, residual: np.ndarray) -> list[dict]:
    """``[{"run", "step", "size"}]`` for the rows ``rows`` (n,) bool: run id, step and the size (m) of
    the row's pose residual ``residual`` (n, d)."""
    return [{"run": data.run_ids[data.run[i]], "step": int(data.step[i]), "size": float(np.linalg.norm(residual[i]))}
            for i in np.flatnonzero(rows)]
