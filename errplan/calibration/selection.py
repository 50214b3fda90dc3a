"""Selection among fitted candidates: BIC and held-out error against every sub-model (step 4 of
:mod:`errplan.calibration`)."""
from __future__ import annotations

import numpy as np

from .fit import Candidate

#: a combination must predict the held-out runs better than each sub-model with one effect fewer,
#: run by run: one-sided Wilcoxon signed-rank test of the runs' held-out squared errors at this level
#: (otherwise the two predict equally well and the smaller one is kept)
PAIRED_ALPHA = 0.01


def better_by_runs(c: Candidate, sub: Candidate) -> float:
    """p-value of "``c`` predicts the held-out runs better than ``sub``" (one-sided Wilcoxon signed-rank
    over the runs' held-out squared errors; 0 when either has no per-run errors: no test)."""
    from scipy.stats import wilcoxon

    a, b = c.heldout_runs, sub.heldout_runs
    if a is None or b is None or len(a) != len(b) or len(a) < 6:
        return 0.0
    d = np.asarray(b, float) - np.asarray(a, float)
    if not np.any(d):
        return 1.0
    return float(wilcoxon(d, alternative="greater").pvalue)


def select(cands: dict[tuple[str, ...], Candidate]) -> Candidate:
    """Candidates whose held-out error (folds of whole runs) is not below the declared model's are
    never selected. Then the first selectable candidate by BIC whose held-out error beats every sub-model with one
    effect fewer (and whose BIC beats them too), run by run (:func:`better_by_runs` below
    :data:`PAIRED_ALPHA`: two models that predict equally well keep the smaller). "none" always qualifies.

    A candidate that is not identifiable only because its parameters correlate beyond the limit
    (:attr:`Candidate.weak`) qualifies too when both its BIC and its held-out error are below those
    of every identifiable candidate: the data then say these effects, and reporting a worse-fitting
    identifiable combination instead would be confidently wrong. Its stated sigmas carry the
    correlation, and the report says that the bench separates them poorly."""
    order = sorted(cands.values(), key=lambda c: c.bic)
    none = cands[()]
    for c in order:
        # never a model that predicts the held-out runs worse than the declared one
        if c.effects and c.heldout_rms is not None and none.heldout_rms is not None and c.heldout_rms >= none.heldout_rms:
            c.selectable = False
            c.weak = False
            c.note = c.note or "held-out error not below the declared model's"
    ok_cands = [c for c in cands.values() if c.selectable]
    best_bic = min(c.bic for c in ok_cands)
    best_ho = min((c.heldout_rms for c in ok_cands if c.heldout_rms is not None), default=None)
    for c in order:
        if not c.selectable:
            if not (c.weak and c.bic < best_bic and (best_ho is None or (c.heldout_rms is not None
                                                                         and c.heldout_rms < best_ho))):
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
            p = better_by_runs(c, sub)
            if p > PAIRED_ALPHA:
                ok = False
                if not c.note:
                    c.note = (f"predicts the held-out runs no better than {sub.label} (paired test over runs "
                              f"p = {p:.2g} > {PAIRED_ALPHA:g}): the smaller model is kept")
                break
        if ok:
            if not c.selectable:
                c.note = "selected though poorly identifiable: fits and predicts best (see the warning below)"
            return c
    return cands[()]  # pragma: no cover - "none" is always selectable
