"""``compute_fields``: a scenario's worst-case fields on its tip grid."""
from __future__ import annotations

import math

import numpy as np

from ..errors import ErrplanError
from ..metrics import phi_hat_max
from .evaluator import Evaluator
from .grid import MetricField, _aligned_axis, workspace_bounds
from .search import REFINE_LEVELS, Progress, _refined_at_gain, minimize_gain, worst_case


def compute_fields(sc, resolution: float | None = None, rho_star: bool = False, *,
                   samples: int | None = None, refine: int = REFINE_LEVELS,
                   progress: Progress | None = None) -> MetricField:
    """Worst-case fields of a scenario on its tip grid (docs/interfaces.md "fields npz")."""
    ev = Evaluator.from_scenario(sc)
    res = float(resolution or sc.fields.resolution)
    if res <= 0 or not math.isfinite(res):
        raise ErrplanError(f"resolution = {resolution!r}: expected a grid spacing > 0 m")
    y0, y1, z0, z1 = workspace_bounds(ev)
    y = _aligned_axis(y0 - 2 * res, y1 + 2 * res, res)
    z = _aligned_axis(z0 - 2 * res, z1 + 2 * res, res)
    if len(y) * len(z) > 4_000_000:
        raise ErrplanError(f"resolution = {res}: the grid would have {len(y) * len(z)} points (max 4,000,000)")
    Y, Z = np.meshgrid(y, z, indexing="ij")
    pts = np.stack([Y.ravel(), Z.ravel()], axis=-1)
    # Cheap prefilter: a robustly valid tip is within the shaft length of every port of the box,
    # in particular of its corners (the same strict test true_wrist applies to each instance).
    es = ev.errors
    near = np.ones(len(pts), bool)
    for th in es.corners():
        d = pts - es.port(th)
        near &= np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2) < ev.length
    cand = np.flatnonzero(near)
    k = float(sc.controller.gain)
    wc = worst_case(ev, pts[cand], k, samples=samples, refine=refine, keep_parts=rho_star, progress=progress)
    shape = Y.shape

    def scatter(v, fill=np.nan, dtype=float):
        a = np.full(len(pts), fill, dtype=dtype)
        a[cand] = v
        return a.reshape(shape)

    valid = scatter(wc["valid"], False, bool)
    gn = scatter(wc["G_norm"])
    pm = scatter(wc["phi_max"])
    ph = phi_hat_max(np.where(valid, gn, 1.0))
    ph[~valid] = np.nan
    meta = {"scenario": sc.name, "gain": k, "resolution": res, "jacobian": sc.controller.jacobian,
            "error_set": {"base_port": list(es.base_port), "lo": list(es.lo), "hi": list(es.hi),
                          "noise": list(es.noise), "samples": samples or es.samples, "refine_levels": refine},
            "length": ev.length, "effects": {name: dict(p) for name, p in sc.effects.items()}}
    mf = MetricField(y, z, valid, gn, ph, pm, meta=meta)
    if rho_star:
        if progress:
            progress(1.0, "minimising the worst case over the gain")
        v = wc["valid"]
        mu = wc["mu"][v].reshape(int(v.sum()), -1)
        nu = wc["nu"][v].reshape(int(v.sum()), -1)
        rs, ks = minimize_gain(mu, nu)
        # Certify at k*: the refined worst case over the continuous error set at that gain.
        xs = pts[cand][v]
        rs_ref = _refined_at_gain(ev, xs, ks, samples=samples, refine=refine)
        rs_ref = np.where(ks > 0, np.maximum(rs, rs_ref), 1.0)
        # The scenario gain is a candidate too: rho* never exceeds the refined ||G|| at k.
        g_k = wc["G_norm"][v]
        use_k = g_k < rs_ref
        rs_ref, ks = np.where(use_k, g_k, rs_ref), np.where(use_k, k, ks)
        none = rs_ref >= 1.0  # no certified contraction: rho* = 1 (k -> 0), k* = 0
        rs_ref, ks = np.where(none, 1.0, rs_ref), np.where(none, 0.0, ks)
        rfull = np.full(len(cand), np.nan)
        kfull = np.full(len(cand), np.nan)
        rfull[v] = rs_ref
        kfull[v] = ks
        mf.rho_star = scatter(rfull)
        mf.k_star = scatter(kfull)
    return mf


