"""Selection among fitted candidates: BIC and held-out error against every sub-model (step 4 of
:mod:`errplan.calibration`)."""
from __future__ import annotations

from .fit import Candidate


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
