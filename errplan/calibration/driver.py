"""The calibration driver: residual -> noise floor -> candidates -> selection -> report."""
from __future__ import annotations

import itertools
from typing import Callable

import numpy as np

from ..effects import CATALOGUE, predict_tracked
from ..errors import DataError
from ..experiment import MeasuredData
from .fit import Candidate, _folds, fit_candidate
from .noise import noise_floor, structure_test
from .report import CalibrationReport, Errors
from .residual import (approach_mask, arrival_tolerance, check_against_model, declared_plant, motion_model, pose_residual,
                       replay, rms, trajectory_errors)
from .selection import select

DEFAULT_FOLDS = 5


# ----------------------------------------------------------------------------- driver
def calibrate(sc, data: MeasuredData, *, validate: MeasuredData | None = None, seed: int = 0,
              folds: int = DEFAULT_FOLDS, progress: Callable[[float, str], None] | None = None) -> CalibrationReport:
    """Find which catalogue effects (if any) the data need on top of the scenario's declared model."""
    from ..experiment import bench_controller, require_planar

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
