"""The calibration report: errors before and after, the calibrate JSON of docs/interfaces.md and the
text a person reads (step 6 of :mod:`errplan.calibration`)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..effects import MAX_CONDITION, MAX_CORRELATION, EffectModel, implausible
from ..experiment import MeasuredData
from .fit import Candidate, _finite_or_none, _num
from .noise import STRUCTURE_P, STRUCTURE_RATIO, NoiseFloor, Structure

TEXT_CANDIDATES = 10        # candidates listed on stdout (all of them in the JSON)
TEXT_WIDTH = 110            # the report's sentences wrapped to this many columns (tables as wide as they are)


# ----------------------------------------------------------------------------- report
@dataclass
class Errors:
    """Before/after errors on one data set (m, per coordinate)."""

    pose_before: float
    pose_after: float
    trajectory_before: float      # over each run's approach (see approach_mask)
    trajectory_after: float
    trajectory_all_before: float  # over every step >= 1
    trajectory_all_after: float
    rows: int
    runs: int
    source: str
    arrival_tolerance: float
    trajectory_rows: int = 0
    unsettled_runs: int = 0

    def to_json(self) -> dict:
        return {"source": self.source, "rows": self.rows, "runs": self.runs,
                "pose_rms_before": self.pose_before, "pose_rms_after": self.pose_after,
                "trajectory_rms_before": _num(self.trajectory_before), "trajectory_rms_after": _num(self.trajectory_after),
                "trajectory_rms_all_steps_before": _num(self.trajectory_all_before),
                "trajectory_rms_all_steps_after": _num(self.trajectory_all_after),
                "arrival_tolerance": self.arrival_tolerance, "trajectory_rows": self.trajectory_rows,
                "trajectory_unsettled_runs_left_out": self.unsettled_runs}


@dataclass
class CalibrationReport:
    """Everything ``errplan calibrate`` found; ``to_json`` is the calibrate JSON of interfaces.md."""

    scenario: str
    data_source: str
    selected: list[str]
    explained: bool
    model: EffectModel
    noise: NoiseFloor
    structure: Structure
    structure_before: Structure
    candidates: list[Candidate]
    fit_errors: Errors
    validation_errors: Errors | None
    declared_effects: dict
    seed: int
    folds: int
    # arrays for the recording (fitting data)
    points: np.ndarray = field(repr=False, default=None)        # model tips (n, 2)
    residual_before: np.ndarray = field(repr=False, default=None)
    residual_after: np.ndarray = field(repr=False, default=None)
    tracked: np.ndarray = field(repr=False, default=None)
    replay_before: np.ndarray = field(repr=False, default=None)
    replay_after: np.ndarray = field(repr=False, default=None)
    data: MeasuredData | None = field(repr=False, default=None)
    #: parameters held at 0 because nothing can depend on them on this robot (label -> why)
    fixed: dict = field(default_factory=dict)
    #: catalogue effects not tried, with the reason
    skipped: list = field(default_factory=list)
    #: runs left out of the fits, with the reason (the declared model's wrist through the port's neighbourhood)
    left_out: list = field(default_factory=list)
    #: a sentence on what these rows cannot tell apart (effect pairs confused by the bench), and the numbers
    identifiability: str = ""
    bench: dict = field(default_factory=dict)
    #: the empirical term (calibrate JSON ``empirical``) when the residual stays structured, and its predictor
    empirical: dict | None = None
    empirical_predict: object = field(repr=False, default=None)
    #: the calibrate JSON's ``task`` (errplan.calibration.task; None: not computed) and ``exported`` (paths written)
    task: list | None = None
    exported: list = field(default_factory=list)
    #: the calibrate JSON's ``measured`` (docs/interfaces.md): the data as the bench recorded them
    #: (rows, runs, dropouts, runs without data, time unit, outliers [{"run", "step", "size"}];
    #: ``validation`` the same)
    measured: dict = field(default_factory=dict)
    #: the verdict (calibrate JSON ``verdict``: residual_ratio, structure_p, implausible, validation_ratio,
    #: failed); None only for reports built by hand
    verdict: dict | None = None

    @property
    def errors(self) -> Errors:
        """The errors the JSON reports: on the validation file when one was given."""
        return self.validation_errors or self.fit_errors

    @property
    def outliers(self) -> list[dict]:
        """The fit file's outliers, ``measured.outliers`` ([{"run", "step", "size"}])."""
        return list(self.measured.get("outliers", []))

    @property
    def fitted(self) -> dict[str, dict[str, float]]:
        """The fitted values of the selected effects: what the data add to the declared model."""
        return self.model.parameters()

    @property
    def parameters(self) -> dict[str, dict[str, float]]:
        """The selected effects as the bench has them: a declared value of the same effect plus
        the fitted correction (just the fitted value when the scenario declares none)."""
        out = {}
        held = set(self.model.held_labels)
        for e, ps in self.fitted.items():
            dec = self.declared_effects.get(e, {})
            out[e] = {p: (None if f"{e}.{p}" in self.fixed else dec.get(p, 0.0) + v) for p, v in ps.items()
                      if f"{e}.{p}" not in held}  # a geometric group reports only its identifiable parameters
        return out

    @property
    def uncertainty(self) -> dict[str, dict[str, float]]:
        held = set(self.model.held_labels)
        return {e: {p: v for p, v in ps.items() if f"{e}.{p}" not in held}
                for e, ps in _finite_or_none(self.model.uncertainties()).items()}

    @property
    def not_identifiable(self) -> dict[str, str]:
        """The selected effects' parameters reported as not identifiable (label -> why)."""
        return {k: v for k, v in self.fixed.items() if k.split(".")[0] in self.model.names}

    def not_identifiable_params(self) -> dict[str, list[str]]:
        """``{effect: [param, ...]}``: the selected effects' parameters held at zero and not reported."""
        out: dict[str, list[str]] = {}
        for lab in self.not_identifiable:
            e, p = lab.split(".", 1)
            out.setdefault(e, []).append(p)
        return out

    def effects_table(self) -> dict[str, dict[str, float]]:
        """Effects for the corrected scenario: every declared effect, with the selected ones
        replaced by their values on the bench (declared + fitted)."""
        out = {k: dict(v) for k, v in self.declared_effects.items()}
        for e, ps in self.parameters.items():
            out[e] = {p: v for p, v in ps.items() if v is not None}
        return out

    def to_json(self) -> dict:
        bic_none = next(c.bic for c in self.candidates if not c.effects)
        e = self.errors
        return {
            "scenario": self.scenario,
            "data": self.data_source,
            "measured": self.measured,
            "selected": list(self.selected),
            "explained": bool(self.explained),
            "verdict": {k: v for k, v in (self.verdict or {}).items() if k != "threshold"},
            "parameters": self.parameters,
            "fitted": self.fitted,
            "uncertainty": self.uncertainty,
            "noise_floor": self.noise.sigma,
            "pose_rms_before": e.pose_before,
            "pose_rms_after": e.pose_after,
            "trajectory_rms_before": _num(e.trajectory_before),
            "trajectory_rms_after": _num(e.trajectory_after),
            "errors_on": "validation" if self.validation_errors else "data",
            "fit": self.fit_errors.to_json(),
            "validation": self.validation_errors.to_json() if self.validation_errors else None,
            "noise": self.noise.to_json(),
            "residual_structure": {"before": self.structure_before.to_json(), "after": self.structure.to_json(),
                                   "rule": f"structured when the smooth part of the residual, predicted on held-out whole runs "
                                           f"by local polynomials or by a global cubic of the tip with the row's motion, is "
                                           f"significant (one-sided Wilcoxon signed-rank test over runs, the smaller p "
                                           f"doubled, p < {STRUCTURE_P:g}) and its RMS >= {STRUCTURE_RATIO:g} x noise floor"},
            "declared_effects": self.declared_effects,
            "effects": self.effects_table(),
            "exported": [str(p) for p in self.exported],
            **({"task": self.task} if self.task is not None else {}),
            "empirical": self.empirical,
            "implausible": implausible(self.model) if self.model.effects else [],
            "not_identifiable": self.not_identifiable_params(),
            "not_identifiable_why": self.not_identifiable,
            "identifiability": self.bench,
            "catalogue_fixed": self.fixed,
            "not_tried": list(self.skipped),
            "runs_left_out": list(self.left_out),
            "rms_convention": "per coordinate: sqrt(mean over rows and over the coordinates of residual^2), m",
            "selection": {"rule": "lowest BIC among identifiable candidates whose held-out pose error (folds of runs) "
                                  "beats every sub-model with one effect fewer",
                          "folds": self.folds, "seed": self.seed},
            "candidates": [c.to_json(bic_none) for c in self.candidates],
        }

    def text(self) -> str:
        mm = 1000.0
        lines = [f"calibration of {self.scenario} on {self.data_source} ({self.fit_errors.rows} rows, "
                 f"{self.fit_errors.runs} runs)"]
        lines += measured_lines(self.measured)
        if self.declared_effects:
            lines.append("declared effects: " + ", ".join(self.declared_effects))
        lines.append(f"noise floor {self.noise.sigma * mm:.4f} mm per coordinate (left by local degree-{self.noise.degree} "
                     f"polynomials on {self.noise.clusters} cluster(s) of rows)")
        lines.append(f"pose residual of the declared model: RMS {self.structure_before.rms * mm:.4f} mm "
                     f"({self.structure_before.ratio:.2f} x noise floor)")
        for why in self.skipped:
            lines.append(f"not tried: {why}")
        for why in self.left_out:
            lines.append(why)
        if self.identifiability:
            lines += _wrapped(self.identifiability)
        lines.append("")
        rows = []
        order = sorted(self.candidates, key=lambda c: c.bic)
        bic_none = next(c.bic for c in self.candidates if not c.effects)
        shown = order[:TEXT_CANDIDATES]
        shown += [c for c in order[TEXT_CANDIDATES:] if not c.effects or not c.selectable]
        notes: list[str] = []
        for c in shown:
            note = _readable_note(c.note)
            if note and note not in notes:
                notes.append(note)
            rows.append([("* " if c.selected else "  ") + c.label, c.model.n_free, c.rms * mm,
                         c.heldout_rms * mm if c.heldout_rms is not None else float("nan"), c.bic - bic_none,
                         c.model.condition_, "yes" if c.selectable else "no",
                         f"[{notes.index(note) + 1}]" if note else ""])
        more = len(order) - len(shown)
        lines.append(_table(["candidate", "p", "pose rms mm", "held-out mm", "dBIC", "cond", "ok", "note"], rows,
                            f"candidates (sorted by BIC; * selected; ok: identifiable, condition number <= "
                            f"{MAX_CONDITION:g} and correlations <= {MAX_CORRELATION:g}; {len(order)} tried"
                            + (f", {more} more in the JSON)" if more else ")")))
        for i, n in enumerate(notes):
            lines += _wrapped(f"  [{i + 1}] {n}", "      ")
        lines.append("")
        if self.selected:
            prow = []
            units_of = {ef.name: dict(zip(ef.params, ef.units)) for ef in self.model.effects}
            for e, ps in self.parameters.items():
                units = units_of[e]
                held = [lab.split(".", 1)[1] for lab in self.model.held_labels if lab.split(".", 1)[0] == e]
                if held:
                    prow.append([e, ", ".join(held), "not identifiable", "", "held at 0 (QR)"])
                dropped = {lab.split(".", 1)[1] for lab in self.model.dropped_labels if lab.split(".", 1)[0] == e}
                if dropped:
                    prow.append([e, ", ".join(p for p in ps if p in dropped), "0 (not needed)", "",
                                 "identifiable, but these rows do not need them (forward selection by BIC)"])
                for p, v in ps.items():
                    if p in dropped:
                        continue
                    f, unit = display_unit(units[p])
                    if v is None:
                        prow.append([e, p, "not identifiable", unit, self.fixed.get(f"{e}.{p}", "")])
                        continue
                    s = self.uncertainty[e][p]
                    sig = f"{s * f:.4f}" if s is not None else "?"
                    dec = self.declared_effects.get(e)
                    note = f"declared {dec.get(p, 0.0) * f:+.4f} + fitted {self.fitted[e][p] * f:+.4f}" if dec else ""
                    prow.append([e, p, f"{v * f:+.4f} ± {sig}", unit, note])
            lines.append(_table(["effect", "param", "value ± 1 sigma", "unit", ""], prow, "selected effects"))
            for flag in implausible(self.model):
                lines.append("implausible: " + flag["why"])
            chosen = next((c for c in self.candidates if c.selected), None)
            if chosen is not None and not chosen.selectable:
                lines.append(f"warning: {chosen.model.why_}: the selected effects fit and predict best, but these rows "
                             f"separate them poorly; `errplan experiment --design N` chooses runs that do")
        else:
            lines.append("selected effects: none (the declared model explains the data down to the noise)")
        e = self.errors
        on = "validation data" if self.validation_errors else "the data"
        lines.append("")
        lines.append(_table(["error (RMS per coordinate)", "before mm", "after mm"], [
            ["pose (tracked vs model tip)", e.pose_before * mm, e.pose_after * mm],
            ["trajectory, approach (controller replayed)", e.trajectory_before * mm, e.trajectory_after * mm],
            ["trajectory, every step", e.trajectory_all_before * mm, e.trajectory_all_after * mm],
        ], f"error before -> after on {on}"))
        if e.unsettled_runs:
            lines.append(f"({e.unsettled_runs} of {e.runs} runs diverged or cycled without arriving and are left out of "
                         f"the approach RMS)")
        val_out = (self.measured.get("validation") or {}).get("outliers", [])
        if self.outliers or val_out:
            lines.append("")
            lines += _outlier_lines(self.outliers, self.fit_errors.source, "left out of every fit and RMS")
            if self.validation_errors is not None:
                lines += _outlier_lines(val_out, self.validation_errors.source, "left out of its RMS, still predicted")
        lines.append("")
        lines += self.verdict_lines()
        if self.empirical is not None:
            em = self.empirical
            lines.append(f"empirical term (not a physical effect): {len(em['terms'])} term(s) of degree <= {em['degree']}, "
                         f"held-out RMS over runs {em['held_out_rms_before'] * mm:.4f} -> {em['held_out_rms_after'] * mm:.4f} mm"
                         + (f"; validation {em['validation_rms_declared'] * mm:.4f} (declared) -> "
                            f"{em['validation_rms_with_term'] * mm:.4f} mm" if "validation_rms_with_term" in em else ""))
            if em.get("export_note"):
                lines.append(f"  {em['export_note']}")
            if em.get("motion_terms"):
                lines.append(f"  terms on the row's motion ({', '.join(em['motion_terms'])}): history-dependent, the "
                             f"residual follows the motion (a latency, friction or hysteresis outside the catalogue?)")
            elif em["history_dependent"]:
                lines.append("  the term does not predict held-out runs: the residual depends on the motion's history or "
                             "on time, not on the pose")
        if not self.explained:
            lines.append("  the selected combination is only the catalogue's best approximation: an effect outside the "
                         "catalogue,\n  its parameters absorbing what it lacks (see the residual map in --record)")
        return "\n".join(lines)

    def verdict_lines(self) -> list[str]:
        """The verdict, each condition of docs/physics.md ("`explained` means explained") with its number."""
        mm = 1000.0
        s = self.structure
        v = self.verdict or {}
        failed = set(v.get("failed", []))
        thr = v.get("threshold", 1.25)
        mark = lambda c: "FAILED" if c in failed else "ok"  # noqa: E731
        out = [f"explained: {'yes' if self.explained else 'NO'}"
               + (f" — failed: {', '.join(sorted(failed))}" if failed else "")]
        out.append(f"  (a) {mark('a'):6} residual after {s.rms * mm:.4f} mm = {s.ratio:.2f} x noise floor "
                   f"(at most {thr:g})")
        models = s.models or {}
        names = {"local": "local polynomials", "global": "cubic of the tip with the motion"}
        detail = "; ".join(f"{names.get(k, k)}: p = {m['p_value']:.2g}, {m['structured_rms'] * mm:.4f} mm"
                           for k, m in models.items())
        out.append(f"  (b) {mark('b'):6} structure test over held-out runs: p = {s.p_value:.2g}, structured part "
                   f"{s.structured_rms * mm:.4f} mm")
        out += _wrapped(f"             (structured when p < {STRUCTURE_P:g} and >= {STRUCTURE_RATIO:g} x noise floor"
                        + (f"; {detail})" if detail else ")"), "              ")
        imp = v.get("implausible", [])
        out.append(f"  (c) {mark('c'):6} " + ("implausible: " + ", ".join(imp) if imp else "no selected parameter implausible"))
        if self.validation_errors is not None and v.get("validation_ratio") is not None:
            ve = self.validation_errors
            out.append(f"  (d) {mark('d'):6} validation pose error {ve.pose_before * mm:.4f} -> {ve.pose_after * mm:.4f} mm"
                       f" = {v['validation_ratio']:.2f} x noise floor (below before, at most {thr:g})")
        else:
            out.append("  (d) -      no validation file")
        return out


def _readable_note(note: str) -> str:
    """A candidate's note for the text table: the clauses that say something (a correlation or a
    condition number that is not a number says nothing beyond "no data depend on ...")."""
    parts = [p for p in note.split("; ") if "nan" not in p.split() and not p.endswith("+nan")
             and "condition number inf" not in p]
    return "; ".join(parts)


def _table(headers, rows, title) -> str:
    """:func:`errplan.report.format_table` without the padding at the ends of the lines."""
    from ..report import format_table

    return "\n".join(line.rstrip() for line in format_table(headers, rows, title).splitlines())


def _wrapped(text: str, indent: str = "  ", width: int = TEXT_WIDTH) -> list[str]:
    """``text`` wrapped at spaces to ``width`` columns, continuation lines indented by ``indent``."""
    import textwrap

    return textwrap.wrap(text, width, subsequent_indent=indent, break_long_words=False, break_on_hyphens=False)


def _outlier_lines(outliers: list, source: str, what: str) -> list[str]:
    if not outliers:
        return []
    listed = ", ".join(f"run {o['run']} step {o['step']} ({o['size'] * 1000:.2f} mm)" for o in outliers[:12])
    more = f", and {len(outliers) - 12} more in the JSON" if len(outliers) > 12 else ""
    return _wrapped(f"outliers in {source}: {len(outliers)} lone row(s) beyond 6 robust sigmas, {what}: {listed}{more}")


def measured_lines(measured: dict) -> list[str]:
    """What the report says about the data as recorded: dropouts, runs without data, the time unit
    (nothing for a clean table in steps)."""
    out = []
    for what, m in (("data", measured), ("validation", measured.get("validation"))):
        if not m or (not m.get("dropouts") and m.get("time") != "seconds" and not m.get("runs_without_data")):
            continue
        s = (f"{what}: {m['rows']} rows in {m['runs']} runs, {m['dropouts']} without a tracked tip (dropouts: kept for "
             f"the runs' history and the controller replay, no pose residual); time in {m['time']}")
        if m.get("runs_without_data"):
            s += f"; runs with fewer than 2 tracked rows (nothing to fit): {', '.join(map(str, m['runs_without_data']))}"
        out.append(s)
    return out


def display_unit(unit: str) -> tuple[float, str]:
    """Factor and unit a parameter is shown in: metres as mm, radians as mrad, rad/(N m) as
    mrad/(N m), anything else as it is."""
    return {"m": (1e3, "mm"), "rad": (1e3, "mrad"), "rad/(N m)": (1e3, "mrad/(N m)"), "s": (1e3, "ms")}.get(unit, (1.0, unit))
