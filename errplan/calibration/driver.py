"""The calibration driver: residual -> noise floor -> candidates -> selection -> report."""
from __future__ import annotations

import itertools
from typing import Callable, Sequence

import numpy as np

from ..effects import EFFECTS, catalogue, geometry_names, latency_in_data_units, predict_tracked
from ..errors import DataError, ErrplanError
from ..experiment import MeasuredData
from .blas import single_threaded_blas
from .fit import Candidate, _folds, fit_candidate
from .noise import latency_features, model_steps, motion_features, noise_floor, structure_test
from .outliers import find_outliers, listing
from .report import CalibrationReport, Errors
from .residual import (
    approach_mask,
    arrival_tolerance,
    check_against_model,
    declared_plant,
    motion_model,
    pose_residual,
    replay,
    rms,
)
from .selection import select

DEFAULT_FOLDS = 5


# ----------------------------------------------------------------------------- driver
def calibrate(sc, data: MeasuredData, *, validate: MeasuredData | None = None, seed: int = 0,
              folds: int = DEFAULT_FOLDS, progress: Callable[[float, str], None] | None = None,
              effects: Sequence[str] | None = None) -> CalibrationReport:
    """Find which catalogue effects (if any) the data need on top of the scenario's declared model.

    ``effects``: the candidate effects (default: the whole catalogue; on a URDF without inertial
    data, the catalogue without gravity sag, said in the report; asking for it there is one error).
    Runs with one BLAS thread (:mod:`.blas`).
    """
    with single_threaded_blas():
        return _calibrate(sc, data, validate=validate, seed=seed, folds=folds, progress=progress, effects=effects)


def _calibrate(sc, data: MeasuredData, *, validate, seed, folds, progress, effects) -> CalibrationReport:
    from ..experiment import bench_controller, data_shape

    prog = progress or (lambda f, m="": None)
    dim, n_joints = data_shape(sc)
    for d_ in (data,) + ((validate,) if validate is not None else ()):
        if (d_.dim, d_.n_joints) != (dim, n_joints):
            raise DataError(f"{d_.source}: data with {d_.dim}-D tips and {d_.n_joints} joints for a scenario with "
                            f"{dim}-D tips and {n_joints} joints")
    if effects is not None:
        bad = [e for e in effects if e not in EFFECTS]
        if bad or not effects:
            raise ErrplanError(f"--effects {','.join(effects)}: expected effects of docs/physics.md: {', '.join(EFFECTS)}")
    from ..effects import CATALOGUE

    wanted = effects if effects is not None else [c.name for c in CATALOGUE] + geometry_names(dim) + ["backlash"]
    cat = catalogue(sc, wanted, skip_without_gravity=effects is None, data=data)  # data: tracker_latency's time unit
    # geometric groups (QR picks their parameters) and backlash: candidates alone
    geo = [e for e in cat if e.qr_identify or getattr(e, "history", False)]
    cat = [e for e in cat if e not in geo]
    skipped = [] if effects is not None or any(e.name == "gravity_sag" for e in cat) else [
        "gravity_sag (the URDF has no inertial data, so no generalized gravity)"]
    base = declared_plant(sc, data)  # data: a declared tracker_latency in the data's time unit
    # --- a bench as it records (dropouts, time): the files as read, runs without tracked data named
    measured = data.measured_json()
    if validate is not None:
        measured["validation"] = validate.measured_json()
    data, thin = _without_thin_runs(data)
    # ---
    data, left_out = check_against_model(data, base, leave_out=True)
    left_out = thin + left_out
    if validate is not None:
        validate, left_v = check_against_model(validate, base, leave_out=True)
        left_out += [f"validation {s}" for s in left_v]
    ctrl = bench_controller(sc)
    xmodel = motion_model(sc)  # friction's u: the motion each command produces under the declared model
    u = data.commanded_directions(xmodel)
    r0 = pose_residual(data, base, u)
    tr = data.tracked  # rows with a tracked tip: the only ones with a pose residual
    if not np.all(np.isfinite(r0[tr])):
        i = int(np.flatnonzero(tr & ~np.all(np.isfinite(r0), axis=1))[0])
        raise DataError(f"{data.source}: row {i + 1}: the declared model has no tip at encoder angles {data.q[i].tolist()}")
    x0 = predict_tracked(base, data.q, u, data.run, data.time)
    v = _motion(data, xmodel)  # the rows' motion: the structure test's
    lag = _lagged(data, xmodel)  # the noise floor's: the model tip 1..5 steps earlier (a late tracker reads it)
    # outliers (lone rows far off: errplan.calibration.outliers) lose their tips as dropouts do: left out of
    # every fit, the noise floor and every RMS, kept for the runs' history; the controller replay runs on
    # the data as read (`full`: the controller read what the bench read, outliers included)
    full = data
    outlier, r_smooth = find_outliers(r0, x0, u, data.run, tr, return_residual=True, motion=lag)
    measured["outliers"] = listing(data, outlier, r_smooth)
    if outlier.any():
        data = data.without_tips(outlier)
        tr = data.tracked
        r0 = np.where(tr[:, None], r0, np.nan)
    nf = noise_floor(r0[tr], x0[tr], u[tr], motion=lag[tr])
    st0 = structure_test(r0[tr], u[tr], nf, data.run[tr], seed, motion=v[tr])
    prog(0.05, "noise floor")
    ident, ident_text = _identifiability(sc, data, cat)
    k = min(folds, data.runs)
    fold_of_run = _folds(data.runs, k, seed) if k >= 2 else None
    by_name = {e.name: e for e in cat + geo}
    names = [e.name for e in cat]
    # --- tracker_latency joins the pairs, triples and geometry combinations only when it alone beats
    # the declared model (a latency shows wherever the tip moves): a bench without one is spared them
    paired = [a for a in names if a != "tracker_latency"]
    # ---
    combos: list[tuple[str, ...]] = ([()] + [(a,) for a in names] + list(itertools.combinations(paired, 2))
                                     + [(g.name,) for g in geo])
    n_params = {e.name: sum(not f for f in e.fixed) for e in cat + geo}
    fits = lambda key: sum(n_params[e] for e in key) <= dim * data.rows - 2  # noqa: E731 (some residual dof left)
    combos = [c for c in combos if fits(c)]
    cands: dict[tuple[str, ...], Candidate] = {}
    fit = lambda key: fit_candidate([by_name[e] for e in key], data, u, base, fold_of_run)  # noqa: E731
    for i, combo in enumerate(combos):
        cands[combo] = fit(combo)
        prog(0.05 + 0.75 * (i + 1) / len(combos), "+".join(combo) or "none")
    # --- tracker_latency's pairs, when it alone beats the declared model (else it leaves the combinations)
    if len(paired) < len(names):
        if cands[("tracker_latency",)].bic < cands[()].bic:
            for a in paired:
                key = tuple(x for x in names if x in (a, "tracker_latency"))
                if fits(key):
                    cands[key] = fit(key)
        else:
            names = paired
    # --- triples: the best pair plus each other effect, when that pair beats its singles
    pairs = [c for key, c in cands.items() if len(key) == 2 and c.selectable]
    if pairs:
        bp = min(pairs, key=lambda c: c.bic)
        if all(bp.bic < cands[(e,)].bic for e in bp.effects) and bp.bic < cands[()].bic:
            for e in names:
                if e in bp.effects:
                    continue
                key = tuple(x for x in names if x in bp.effects or x == e)
                if fits(key):
                    cands[key] = fit(key)
    # geometry plus physics: the best geometric group (when it beats "none") with each physical effect;
    # a real robot's geometry is off and it sags, and neither alone predicts the runs
    singles = [(g.name,) for g in geo if g.qr_identify and (g.name,) in cands and cands[(g.name,)].selectable]
    if singles:
        bg = min(singles, key=lambda k: cands[k].bic)
        if cands[bg].bic < cands[()].bic:
            for e in names:
                key = bg + (e,)
                if fits(key):
                    c = cands[key] = fit(key)
                    if c.model.identifiable_mask.sum() <= cands[bg].model.identifiable_mask.sum():
                        # QR held as many of the group's parameters as the effect brought (a joint offset
                        # is a joint origin's turn about its axis): the same model, reparametrised
                        c.selectable = c.weak = False
                        c.note = f"the same model as {bg[0]}: QR holds as many of its parameters as {e} adds"
    prog(0.85, "selection")
    chosen = select(cands)
    chosen.selected = True
    for c in cands.values():
        if not c.selectable and not c.note:
            c.note = "not identifiable"
    model = chosen.model
    after = model.plant(base)
    x1 = predict_tracked(after, data.q, u, data.run, data.time)
    r1 = data.tip - x1
    # the noise the selected model leaves (the same flexible model on its residual): a run's arrival is judged
    # with it (the same rows calibrated on its bench, the `--export-bench` file, then judge them alike: "before"
    # there is "after" here). Either estimate is the noise plus what the flexible model cannot follow of its
    # residual, so the noise floor is the smaller: a history effect the catalogue fits (a latency on fast,
    # oscillating runs) may leave more than the motion features follow in the declared model's residual.
    nf1 = noise_floor(r1[tr], x1[tr], u[tr], motion=lag[tr])
    tol = arrival_tolerance(nf1.sigma)
    if nf1.sigma < nf.sigma:
        nf = nf1
        st0.ratio = st0.rms / nf.sigma
    st1 = structure_test(r1[tr], u[tr], nf, data.run[tr], seed, motion=v[tr])

    def errors(d: MeasuredData, rows: MeasuredData, r_before: np.ndarray, r_after: np.ndarray) -> Errors:
        """``d`` the data as read (the replay), ``rows`` the same rows with the outliers' tips removed."""
        tb, tb_all = _trajectory_errors(d, rows, base, ctrl, tol, xmodel)
        ta, ta_all = _trajectory_errors(d, rows, after, ctrl, tol, xmodel)
        mask, unsettled = approach_mask(rows, tol)
        return Errors(rms(r_before[rows.tracked]), rms(r_after[rows.tracked]), tb, ta, tb_all, ta_all, d.rows, d.runs,
                      d.source, tol, int(mask.sum()), int(unsettled.sum()))

    fit_err = errors(full, data, r0, r1)
    val_err = None
    if validate is not None:
        uv = validate.commanded_directions(xmodel)
        rv0 = pose_residual(validate, base, uv)
        xv_after = predict_tracked(after, validate.q, uv, validate.run, validate.time)
        rv1 = validate.tip - xv_after
        # outliers of the validation file: listed and left out of its RMS, still predicted
        out_v, rv_smooth = find_outliers(rv1, xv_after, uv, validate.run, validate.tracked, return_residual=True,
                                         motion=_lagged(validate, xmodel))
        measured["validation"]["outliers"] = listing(validate, out_v, rv_smooth)
        val_rows = validate.without_tips(out_v) if out_v.any() else validate
        val_err = errors(validate, val_rows, rv0, rv1)
    verdict = _verdict(r1[tr], nf.sigma, st1, model, val_err, bool(model.names))
    explained = not verdict["failed"]
    empirical = emp_predict = None
    if not explained:  # the last resort: a sparse correction over a documented basis (never "explained")
        from .empirical import fit_empirical

        empirical, emp_predict = fit_empirical(x1[tr], data.q[tr], r1[tr], data.run[tr], folds=max(2, folds), seed=seed,
                                               motion=v[tr])
        # the scenario format has no key for it (a correction of what the tracker reads, centred and
        # scaled on these rows, not a property of the robot): --predictions carries it, the export not
        empirical["in_exported_scenario"] = False
        empirical["export_note"] = ("not in the exported scenario: the scenario format has no key for an empirical "
                                    "correction of the tracked tip; --predictions includes it")
    if empirical is not None and validate is not None:
        tv = val_rows.tracked
        empirical["validation_rms_declared"] = rms(rv0[tv])
        empirical["validation_rms_selected"] = rms(rv1[tv])
        empirical["validation_rms_with_term"] = rms(rv1[tv] - emp_predict(xv_after[tv], validate.q[tv],
                                                                          _motion(validate, xmodel)[tv]))
    pred0, _ = replay(full, base, ctrl, xmodel)
    pred1, _ = replay(full, after, ctrl, xmodel)
    fixed = {f"{e.name}.{p_}": e.why_fixed or "identically zero sensitivity on this robot"
             for e in cat + geo for p_, fx in zip(e.params, e.fixed) if fx}
    for lab in model.held_labels:
        fixed[lab] = ("not identifiable from these rows: QR with column pivoting of the regressor puts it below "
                      "1e-6 of the first pivot (a combination of the other parameters shows the same)")
    prog(1.0, "done")
    cand_list = sorted(cands.values(), key=lambda c: (len(c.effects), c.bic))
    return CalibrationReport(
        scenario=sc.name, data_source=data.source, selected=model.names, explained=explained, model=model,
        noise=nf, structure=st1, structure_before=st0, candidates=cand_list, fit_errors=fit_err,
        validation_errors=val_err, declared_effects={k2: dict(v) for k2, v in latency_in_data_units(sc.effects, sc, data).items()}, seed=seed, folds=k,
        points=x0[tr], residual_before=r0[tr], residual_after=r1[tr], tracked=data.tip[tr],  # tracked rows
        replay_before=pred0, replay_after=pred1, data=full, fixed=fixed, skipped=skipped, left_out=left_out,
        identifiability=ident_text, bench=ident, empirical=empirical, empirical_predict=emp_predict,
        measured=measured, verdict=verdict)


def _without_thin_runs(data: MeasuredData) -> tuple[MeasuredData, list[str]]:
    """The data without the runs that have fewer than 2 tracked rows (they add nothing to a fit;
    docs/physics.md "Dropouts"), and a sentence naming each; none left is one error."""
    thin = data.thin_runs
    if not len(thin):
        return data, []
    if len(thin) == data.runs:
        raise DataError(f"{data.source}: no run has 2 rows with a tracked tip ({data.dropouts} of {data.rows} rows are "
                        f"dropouts): nothing to calibrate")
    n_tr = np.bincount(data.run[data.tracked], minlength=data.runs)
    notes = [f"run {data.run_ids[r]!r} left out: {int(n_tr[r])} tracked row(s) of {int(data.lengths[r])} (a run needs "
             f"2 tracked rows to add anything to the fit)" for r in thin]
    return data.subset(np.setdiff1d(np.arange(data.runs), thin)), notes


#: the verdict's thresholds (docs/physics.md "`explained` means explained"): the residual after the
#: selected model, and the validation file's pose error after, at most this many noise floors
VERDICT_RATIO = 1.25
CONDITIONS = {
    "a": "the residual after the selected model is above {ratio:g} x the noise floor",
    "b": "the structure test finds structure left in the residual",
    "c": "a selected parameter is implausible",
    "d": "the validation file's pose error after is not below its error before, or above {ratio:g} x the noise floor",
}


def _verdict(r1: np.ndarray, sigma: float, st, model, val_err, selected: bool) -> dict:
    """The verdict of docs/physics.md ("`explained` means explained"): the JSON ``verdict`` object,
    ``failed`` the conditions (a)-(d) that failed (empty: explained)."""
    from ..effects import implausible

    ratio = rms(r1) / max(sigma, 1e-300)
    flags = implausible(model) if model.effects else []
    names = sorted({f"{f['effect']}.{f['param']}" for f in flags})
    vratio = None
    failed = []
    if ratio > VERDICT_RATIO:
        failed.append("a")
    if st.structured:
        failed.append("b")
    if names:
        failed.append("c")
    if val_err is not None:
        vratio = val_err.pose_after / max(sigma, 1e-300)
        # nothing selected: the declared model is the model after, its error the same as before
        worse = val_err.pose_after >= val_err.pose_before if selected else val_err.pose_after > val_err.pose_before
        if worse or vratio > VERDICT_RATIO:
            failed.append("d")
    return {"residual_ratio": float(ratio), "structure_p": float(st.p_value), "implausible": names,
            "validation_ratio": None if vratio is None else float(vratio), "failed": failed,
            "threshold": VERDICT_RATIO}


def _motion(data: MeasuredData, xmodel) -> np.ndarray:
    """The rows' motion (n, d): the declared model tip's step from the row before over the step's
    duration (:func:`.noise.motion_features`; ``data.time`` when the data have one, else steps)."""
    with np.errstate(invalid="ignore"):
        steps = model_steps(xmodel.model_tip(data.q), data.run)
    steps = np.where(np.isfinite(steps), steps, 0.0)
    return motion_features(steps, data.run, getattr(data, "time", None))


def _lagged(data: MeasuredData, xmodel) -> np.ndarray:
    """The noise floor's motion features (n, 5 d) of the rows (:func:`.noise.latency_features` of the
    declared model tip; a row without a model tip contributes zeros)."""
    with np.errstate(invalid="ignore"):
        xm = xmodel.model_tip(data.q)
    xm = np.where(np.isfinite(xm), xm, 0.0)
    f = latency_features(xm, data.run, data.time)
    return np.where(np.isfinite(f), f, 0.0)


def _trajectory_errors(d: MeasuredData, rows: MeasuredData, plant, ctrl, tol: float, xmodel) -> tuple[float, float]:
    """:func:`.residual.trajectory_errors` with the controller replayed on the data as read (``d``) and
    compared on ``rows`` (the same rows, the outliers' tips removed: left out as dropouts are)."""
    pred, _ = replay(d, plant, ctrl, xmodel)
    r = rows.tip - pred
    mask, _ = approach_mask(rows, tol)
    every = (rows.step >= 1) & rows.tracked
    return (rms(r[mask]) if np.any(mask) else float("nan")), (rms(r[every]) if np.any(every) else float("nan"))


def _identifiability(sc, data: MeasuredData, cat) -> tuple[dict, str]:
    """What the rows can tell apart: the catalogue's information on them (:mod:`.design`), the
    effect pairs whose parameters correlate beyond :data:`.design.CONFUSED`, and a sentence."""
    from ..effects import EffectModel
    from .design import CONFUSED, bench_info

    try:
        info = bench_info(sc, data, EffectModel(cat))
    except (ErrplanError, np.linalg.LinAlgError):  # pragma: no cover - a report line, never a failure
        return {}, ""
    pairs = info.pair_correlations()
    conf = {f"{a}+{b}": v for (a, b), v in sorted(pairs.items(), key=lambda kv: -kv[1]) if v > CONFUSED}
    c, la, lb = info.largest_correlation()
    js = {"condition_number": info.condition() if np.isfinite(info.condition()) else None,
          "largest_correlation": {"value": c, "between": [la, lb]}, "pair_correlations":
          {f"{a}+{b}": v for (a, b), v in pairs.items()}, "confused_pairs": conf, "threshold": CONFUSED}
    if not pairs:  # a single effect (a geometric group with one physical effect, say): no pair to tell apart
        return js, f"identifiability of the catalogue on these rows: condition number {info.condition():.3g}"
    if not conf:
        return js, (f"identifiability of the catalogue on these rows: every pair of effects separable (largest cross "
                    f"correlation {max(pairs.values()):.3f} < {CONFUSED:g}), condition number {info.condition():.3g}")
    listed = ", ".join(f"{k} {v:.3f}" for k, v in conf.items())
    return js, (f"identifiability of the catalogue on these rows: {listed} correlate beyond {CONFUSED:g} "
                f"(condition number {info.condition():.3g}); `errplan experiment --design N` chooses runs that "
                f"separate them")
