"""Candidate effect combinations fitted to the pose residual: fit on all rows, held-out error on
folds of whole runs, BIC (step 3 of :mod:`errplan.calibration`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..effects import EffectModel
from ..experiment import MeasuredData


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
    #: not identifiable only because its parameters correlate beyond the limit (a finite condition
    #: number, every column informed, the fit converged, finite sigmas): it may still be selected
    #: when it predicts the data better than every identifiable candidate (:func:`.selection.select`)
    weak: bool = False
    #: held-out squared error of each run (the folds' predictions), for the paired comparison of
    #: :func:`.selection.select`; None without folds
    heldout_runs: np.ndarray | None = None

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
            "weakly_identifiable": self.weak,
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


def fit_candidate(effects, data: MeasuredData, u: np.ndarray, base, fold_of_run: np.ndarray | None) -> Candidate:
    """Fit one combination (effect names, or :class:`errplan.effects.Effect` instances for the
    scenario's dimension) on all rows, its held-out error on folds of whole runs, and its BIC."""
    from ..effects import Effect, make_effect

    m = EffectModel([e if isinstance(e, Effect) else make_effect(e) for e in effects]).fit(
        data.q, u, data.tip, base, run=data.run, time=data.time)
    # dropouts (rows without a tracked tip) have no residual; they stay for the runs' history
    tracked = data.tracked
    n, d = int(tracked.sum()), data.dim
    p = m.n_free
    bic = _bic(m.rss_, d * n, p)
    ho = None
    if fold_of_run is not None:
        fold = fold_of_run[data.run]
        sse = 0.0
        run_sse = np.zeros(data.runs)
        for k in range(int(fold_of_run.max()) + 1):
            te = fold == k
            tr = ~te
            if d * int((tr & tracked).sum()) < p + 2:
                sse = float("nan")  # too few training rows for this candidate: no held-out error
                break
            if p:
                mk = EffectModel(m.effects, hold=m.hold, drop=m.drop).fit(data.q[tr], u[tr], data.tip[tr], base, x0=m.values_,
                                                            run=data.run[tr], time=data.time[tr])
                vals = mk.values_
            else:
                vals = np.zeros(m.n_params)
            with np.errstate(invalid="ignore", divide="ignore"):
                r = data.tip[te] - m.predict(base, data.q[te], u[te], vals, run=data.run[te], time=data.time[te])
            r = np.where(np.isfinite(r), r, 1.0)
            r[~tracked[te]] = 0.0  # a dropout has no residual
            sse += float(np.sum(r * r))
            run_sse += np.bincount(data.run[te], weights=np.sum(r * r, axis=1), minlength=data.runs)
        ho = math.sqrt(sse / (d * n)) if math.isfinite(sse) else None
    note = "" if m.identifiable_ else f"not identifiable: {m.why_}"
    free_sigma = np.asarray(m.sigma_, float)[m.free] if m.n_params else np.zeros(0)
    weak = (not m.identifiable_ and m.success_ and math.isfinite(m.condition_) and "no data depend" not in m.why_
            and bool(np.all(np.isfinite(free_sigma))))
    return Candidate(m, math.sqrt(m.rss_ / (d * n)), bic, ho, bool(m.identifiable_), note, weak=weak,
                     heldout_runs=run_sse if ho is not None else None)
