"""P1-style bench runs (P1 Sec. III-B, Fig. 8) and the measured-data CSV of docs/interfaces.md.

A bench run places the tip at a start, then drives it with the scenario's controller (the
declared model: rigid lever through the port *estimate*, or P2's flexion model) at the scenario
gain toward one of eight targets 20 mm away along y, z and the diagonals. The robot it drives is
the scenario's *truth*: the declared arm, shaft and true port plus the scenario's ``[effects]``
and its sensor noise (``[sensors] tracker_sigma``, ``encoder_sigma``).

Starts: P1's L, M, N = (0, 0.320), (0, 0.375), (0, 0.415) wherever they and their eight targets
are reachable, then further starts spread over the tip workspace (farthest-point sampling over
tips whose 30 mm neighbourhood is reachable with margin), so that the data see the effects in
many configurations. A run stops ``dwell`` steps after the tracked tip first came within
``tolerance`` of the target (the converged segment measures the noise), or after ``max_steps``
commands, or when a command leaves the joint limits / pulls the shaft out of the port.

:class:`MeasuredData` holds one CSV (rows run-major, steps ascending) and reads it robustly:
every malformed cell, missing column or short run raises one :class:`DataError` that names the
column, the row and the value.
"""
from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import DataError, ErrplanError
from .kinematics.shaft import flexed_wrist

COLUMNS = ("run", "step", "target_y", "target_z", "gain", "q1", "q2", "tip_y", "tip_z")  # planar (csv_columns)
P1_STARTS = ((0.0, 0.320), (0.0, 0.375), (0.0, 0.415))
TARGET_DISTANCE = 0.020
DEFAULT_STARTS = 8
DEFAULT_MAX_STEPS = 60
DEFAULT_DWELL = 10
#: memory (bytes) one measured-data row costs from parsing through calibration (the parsed row,
#: its arrays, the residuals and least-squares Jacobians of the candidate fits, the replay):
#: tracemalloc measured about 1 kB per row on a 2,300-row bench; four times that for a margin
ROW_BYTES = 4096
#: memory (bytes) one bench row costs while it is simulated and written (state lists, arrays, CSV text)
BENCH_ROW_BYTES = 1024
#: memory (bytes) per candidate start tip while the starts are chosen (the tip, its flags, distances)
START_TIP_BYTES = 64
#: candidate tips checked at once (each with 25 probe points through the inverse kinematics)
START_CHUNK = 8192


# ----------------------------------------------------------------------------- data
def csv_columns(dim: int = 2, n_joints: int = 2) -> tuple[str, ...]:
    """The measured-data CSV's columns (docs/interfaces.md): planar ``run, step, target_y,
    target_z, gain, q1, q2, tip_y, tip_z``; spatial ``run, step, target_x, target_y, target_z, gain,
    q1..qN, tip_x, tip_y, tip_z``."""
    ax = ("y", "z") if dim == 2 else ("x", "y", "z")
    return ("run", "step", *(f"target_{a}" for a in ax), "gain", *(f"q{i + 1}" for i in range(n_joints)),
            *(f"tip_{a}" for a in ax))


def data_shape(sc) -> tuple[int, int]:
    """``(dim, n_joints)`` of the measured data of scenario ``sc``."""
    if sc.dim == 3:
        return 3, len(sc.robot.joints)
    return 2, 2


@dataclass
class MeasuredData:
    """Measured bench data, one row per controller step (docs/interfaces.md "Measured data").

    Arrays (n rows, run-major, steps ascending): ``run`` (n,) run index into ``run_ids``,
    ``step`` (n,), ``target`` (n, d) m, ``gain`` (n,), ``q`` (n, N) encoder angles rad,
    ``tip`` (n, d) tracked tip m; d = 2 planar ([y, z]), 3 spatial ([x, y, z]), N the actuated joints.

    A bench as it records (docs/physics.md "Measured data as a bench records it"): ``time`` (n,)
    the row's time, seconds when the file has a ``time`` column (``time_unit`` "seconds"), else the
    step index as a float (``time_unit`` "steps"); ``tracked`` (n,) False on a tracker dropout (a
    row without a tracked tip: its ``tip`` entries are NaN; the row keeps its encoders and its
    place in the run).
    """

    run_ids: list[str]
    run: np.ndarray
    step: np.ndarray
    target: np.ndarray
    gain: np.ndarray
    q: np.ndarray
    tip: np.ndarray
    source: str = "<memory>"
    time: np.ndarray | None = None
    time_unit: str = "steps"
    first: np.ndarray = field(init=False, repr=False)
    tracked: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.run = np.asarray(self.run, int)
        self.step = np.asarray(self.step, int)
        n = len(self.step)
        self.target = np.asarray(self.target, float).reshape(n, -1) if n else np.zeros((0, 2))
        self.gain = np.asarray(self.gain, float)
        self.q = np.asarray(self.q, float).reshape(n, -1) if n else np.zeros((0, 2))
        self.tip = np.asarray(self.tip, float).reshape(n, -1) if n else np.zeros((0, 2))
        self.first = np.flatnonzero(self.step == 0)
        finite = np.isfinite(self.tip)
        self.tracked = np.all(finite, axis=1)
        part = np.flatnonzero(np.any(finite, axis=1) & ~self.tracked)
        if len(part):
            i = int(part[0])
            raise DataError(f"{self.source}: row {i + 1}: tracked tip {self.tip[i].tolist()} has some coordinates and "
                            f"not others (a dropout has none)")
        if self.time_unit not in ("seconds", "steps"):
            raise ErrplanError(f"time_unit {self.time_unit!r}: expected 'seconds' or 'steps'")
        if self.time is None:
            self.time, self.time_unit = self.step.astype(float), "steps"
        else:
            self.time = np.asarray(self.time, float).reshape(n)

    @property
    def dropouts(self) -> int:
        """Rows without a tracked tip."""
        return int(np.sum(~self.tracked))

    @property
    def thin_runs(self) -> np.ndarray:
        """Run indices with fewer than 2 tracked rows: they add nothing to a fit."""
        return np.flatnonzero(np.bincount(self.run[self.tracked], minlength=self.runs) < 2)

    @property
    def time_step(self) -> float:
        """The data's typical step: the median duration between consecutive rows of a run (1.0 in steps)."""
        same = self.run[1:] == self.run[:-1]
        dt = np.diff(self.time)[same]
        dt = dt[dt > 0]
        return float(np.median(dt)) if len(dt) else 1.0

    def without_tips(self, rows: np.ndarray) -> "MeasuredData":
        """The same rows with the tracked tip of ``rows`` (n,) bool removed (NaN, ``tracked`` False):
        rows left out of every pose residual (an outlier, say) stay for the runs' history
        (``backlash``, ``tracker_latency``) and the controller replay, as a dropout does."""
        rows = np.asarray(rows, bool)
        tip = self.tip.copy()
        tip[rows] = np.nan
        return MeasuredData(self.run_ids, self.run, self.step, self.target, self.gain, self.q, tip, self.source,
                            self.time, self.time_unit)

    def measured_json(self) -> dict:
        """The calibrate JSON's ``measured`` object (docs/interfaces.md): rows, runs, dropouts, the
        runs with fewer than 2 tracked rows, the time unit, and ``outliers`` (filled by outlier
        detection; a list)."""
        return {"rows": self.rows, "runs": self.runs, "dropouts": self.dropouts,
                "runs_without_data": [self.run_ids[r] for r in self.thin_runs], "time": self.time_unit,
                "outliers": []}

    @property
    def dim(self) -> int:
        return self.tip.shape[1]

    @property
    def n_joints(self) -> int:
        return self.q.shape[1]

    @property
    def columns(self) -> tuple[str, ...]:
        return csv_columns(self.dim, self.n_joints)

    @property
    def rows(self) -> int:
        return len(self.step)

    @property
    def runs(self) -> int:
        return len(self.run_ids)

    @property
    def lengths(self) -> np.ndarray:
        return np.bincount(self.run, minlength=self.runs)

    def commanded_directions(self, model) -> np.ndarray:
        """Friction's direction ``u`` (n, 2) for every row (docs/physics.md ``port_friction``).

        The friction state of row t+1 comes from the command issued at step t, which the encoders
        read at t+1 (interfaces.md). That command moves the tip, under the declared ``model`` (a
        :class:`errplan.simulation.Plant`; its :meth:`~errplan.simulation.Plant.model_tip` is
        ``x_model``: arm, shaft and declared port, no effects), along
        ``x_model(q(t+1)) - x_model(q(t))``: row t+1's ``u`` is that direction, from two
        consecutive encoder rows of the run. Step 0 has ``u = 0``; a step that commands no motion
        keeps the previous ``u``. This is not the desired direction ``target - tip(t)``: the two
        differ by up to phi_max wherever the controller's Jacobian is wrong.
        """
        n = self.rows
        u = np.zeros((n, self.dim))
        if n == 0:
            return u
        order = np.lexsort((self.step, self.run))  # run-major, steps ascending (the usual layout already)
        run, step = self.run[order], self.step[order]
        xm = model.model_tip(self.q[order])
        d = np.zeros_like(xm)
        follows = np.zeros(n, bool)
        follows[1:] = (run[1:] == run[:-1]) & (step[1:] == step[:-1] + 1)
        d[1:] = xm[1:] - xm[:-1]
        norm = np.sqrt(np.sum(d * d, axis=-1))
        moved = follows & np.isfinite(norm) & (norm > 0)
        # the last moving step at or before each row, within the same run (forward fill)
        idx = np.where(moved, np.arange(n), -1)
        last = np.maximum.accumulate(idx)
        run_start = np.zeros(n, int)
        starts = np.flatnonzero(np.r_[True, run[1:] != run[:-1]])
        run_start[starts] = starts
        run_start = np.maximum.accumulate(run_start)
        has = last >= run_start
        src = np.where(has, last, 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            unit = d[src] / np.where(norm[src] > 0, norm[src], 1.0)[:, None]
        u[order] = np.where(has[:, None], unit, 0.0)
        return u

    def subset(self, runs: np.ndarray) -> "MeasuredData":
        """The rows of the given run indices (a new object with runs renumbered)."""
        runs = np.asarray(sorted(set(int(r) for r in runs)), int)
        mask = np.isin(self.run, runs)
        remap = -np.ones(self.runs, int)
        remap[runs] = np.arange(len(runs))
        return MeasuredData([self.run_ids[r] for r in runs], remap[self.run[mask]], self.step[mask],
                            self.target[mask], self.gain[mask], self.q[mask], self.tip[mask], self.source,
                            self.time[mask], self.time_unit)

    def to_csv_text(self) -> str:
        """The CSV of docs/interfaces.md; a ``time`` column (after ``step``) when the time is in
        seconds; a dropout's tip cells empty."""
        out = io.StringIO()
        cols = list(self.columns)
        seconds = self.time_unit == "seconds"
        if seconds:
            cols.insert(2, "time")
        out.write(",".join(cols) + "\n")
        vals = np.concatenate([self.target, self.gain[:, None], self.q, self.tip], axis=1)
        for i in range(self.rows):
            t = f"{self.time[i]:.9f}," if seconds else ""
            out.write(f"{self.run_ids[self.run[i]]},{self.step[i]},{t}"
                      + ",".join("" if not math.isfinite(v) else f"{v:.12g}" for v in vals[i]) + "\n")
        return out.getvalue()

    def write_csv(self, path: str | Path) -> None:
        from .report import write_atomic

        write_atomic(path, self.to_csv_text())


def _cell_float(text: str, column: str, row: int, where: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise DataError(f"{where}: row {row} column {column!r}: value {text!r} is not a number") from None
    if not math.isfinite(v):
        raise DataError(f"{where}: row {row} column {column!r}: value {text!r} is not finite")
    return v


def _check_header(header: list[str], cols: tuple[str, ...], source: str, dim: int, n_joints: int) -> None:
    """One clear error for a header that does not fit the scenario: planar columns in a spatial
    scenario or the reverse, joint columns for a different arm, missing or repeated columns."""
    where = "a spatial scenario ([x, y, z])" if dim == 3 else "a planar scenario ([y, z])"
    if dim == 3 and not any(c in header for c in ("target_x", "tip_x")) and any(
            c in header for c in ("target_y", "target_z", "tip_y", "tip_z")):
        raise DataError(f"{source}: planar columns (target_y, target_z, tip_y, tip_z without target_x, tip_x) for "
                        f"{where}: expected the columns {','.join(cols)}")
    if dim == 2 and any(c in header for c in ("target_x", "tip_x")):
        raise DataError(f"{source}: spatial columns ({', '.join(c for c in ('target_x', 'tip_x') if c in header)}) for "
                        f"{where}: expected the columns {','.join(cols)}")
    joints = [h for h in header if re.fullmatch(r"q[0-9]+", h)]
    extra = [h for h in joints if h not in cols]
    if extra:
        raise DataError(f"{source}: joint column(s) {', '.join(extra)}: the scenario's arm has {n_joints} actuated "
                        f"joints (columns q1..q{n_joints}); is the data from this scenario?")
    missing = [c for c in cols if c not in header]
    if missing:
        hint = ""
        if any(re.fullmatch(r"q[0-9]+", c) for c in missing):
            hint = f" (the scenario's arm has {n_joints} actuated joints: q1..q{n_joints})"
        raise DataError(f"{source}: missing column(s) {', '.join(missing)}{hint} (header has "
                        f"{', '.join(header) or 'nothing'}; expected {','.join(cols)})")
    dup = [c for c in cols if header.count(c) > 1]
    if dup:
        raise DataError(f"{source}: column(s) {', '.join(dup)} appear more than once in the header")


def parse_measured_csv(text: str, source: str = "<memory>", *, dim: int = 2, n_joints: int = 2) -> MeasuredData:
    """Parse measured-data CSV text (docs/interfaces.md); raise :class:`DataError` on any defect.

    ``dim`` and ``n_joints`` say which columns the scenario's data have (:func:`csv_columns`,
    :func:`data_shape`). Rows are numbered from 1 (the first data row; the header is line 1 of the
    file, so data row ``r`` is line ``r + 1``). Extra columns are ignored, except joint columns the
    arm does not have and the other dimension's coordinates. Runs may appear in any order; their
    steps must be 0, 1, ... without gaps or repeats, target and gain constant, at least 2 steps.

    A bench as it records (docs/physics.md): an optional ``time`` column (s, strictly increasing
    within a run, any step length); a row whose ``tip_*`` cells are all empty is a dropout (kept,
    its tip NaN, ``MeasuredData.tracked`` False); a row with only some of them empty is an error.
    """
    from .inputs import check_allocation

    cols = csv_columns(dim, n_joints)
    if not text.strip():
        raise DataError(f"{source}: the file is empty (expected a header {','.join(cols)} and data rows)")
    lines = text.count("\n") + 1
    check_allocation(source, f"{lines:,} lines", lines, ROW_BYTES, "reading and calibrating its rows")
    reader = csv.reader(io.StringIO(text))
    try:
        header = next(reader)
    except (StopIteration, csv.Error) as e:  # pragma: no cover - guarded by the empty check
        raise DataError(f"{source}: cannot read the CSV header: {e}") from None
    header = [h.strip() for h in header]
    _check_header(header, cols, source, dim, n_joints)
    idx = {c: header.index(c) for c in cols}
    if header.count("time") > 1:
        raise DataError(f"{source}: column(s) time appear more than once in the header")
    has_time = "time" in header
    tcol = header.index("time") if has_time else -1
    tipcols = [c for c in cols if c.startswith("tip_")]
    tcols = [c for c in cols if c.startswith("target_")] + ["gain"]
    runs: dict[str, list] = {}
    nrow = 0
    try:
        for row in reader:
            if not row or all(not c.strip() for c in row):
                continue
            nrow += 1
            if len(row) < len(header):
                raise DataError(f"{source}: row {nrow} has {len(row)} values, the header has {len(header)} columns")
            if any(c.strip() for c in row[len(header):]):
                raise DataError(f"{source}: row {nrow} has {len(row)} values, the header has {len(header)} columns "
                                f"(a value without a column)")
            rid = row[idx["run"]].strip()
            if not rid:
                raise DataError(f"{source}: row {nrow} column 'run': empty run id")
            st = row[idx["step"]].strip()
            sv = _cell_float(st, "step", nrow, source)
            if sv != int(sv) or sv < 0:
                raise DataError(f"{source}: row {nrow} column 'step': value {st!r} is not an integer >= 0")
            empty = [c for c in tipcols if not row[idx[c]].strip()]
            if empty and len(empty) < len(tipcols):
                full = [c for c in tipcols if c not in empty]
                raise DataError(f"{source}: row {nrow} column {empty[0]!r}: empty while {', '.join(full)} has a value "
                                f"(a tracker dropout leaves every tip cell empty)")
            vals = [math.nan if c in empty else _cell_float(row[idx[c]].strip(), c, nrow, source) for c in cols[2:]]
            tv = _cell_float(row[tcol].strip(), "time", nrow, source) if has_time else float(sv)
            runs.setdefault(rid, []).append((int(sv), nrow, vals, tv))
    except csv.Error as e:
        raise DataError(f"{source}: malformed CSV near row {nrow + 1}: {e}") from None
    if nrow == 0:
        raise DataError(f"{source}: no data rows after the header")
    run_ids, R, S, TG, K, Q, X, TM = [], [], [], [], [], [], [], []
    for ri, (rid, rows) in enumerate(runs.items()):
        rows.sort(key=lambda r: r[0])
        steps = [r[0] for r in rows]
        if len(rows) < 2:
            raise DataError(f"{source}: run {rid!r} has {len(rows)} step (row {rows[0][1]}); a run needs at least 2 steps "
                            f"(the state before the first command and after it)")
        if steps != list(range(len(steps))):
            seen = set()
            for s, r, *_ in rows:
                if s in seen:
                    raise DataError(f"{source}: run {rid!r}: step {s} appears twice (row {r})")
                seen.add(s)
            expect = next(i for i, s in enumerate(steps) if s != i)
            raise DataError(f"{source}: run {rid!r}: steps must be 0, 1, 2, ... without gaps; step {expect} is missing "
                            f"(found {steps[expect]} at row {rows[expect][1]})")
        v = np.array([r[2] for r in rows])
        for j, c in enumerate(tcols):
            bad = np.flatnonzero(v[:, j] != v[0, j])
            if len(bad):
                r = rows[bad[0]][1]
                raise DataError(f"{source}: run {rid!r}: column {c!r} changes within the run (row {r}: "
                                f"{float(v[bad[0], j])!r}, first row: {float(v[0, j])!r}); a run has one target and one gain")
        if not v[0, dim] > 0:
            raise DataError(f"{source}: run {rid!r} column 'gain': value {float(v[0, dim])!r} (row {rows[0][1]}) is not > 0")
        tm = np.array([r[3] for r in rows])
        back = np.flatnonzero(np.diff(tm) <= 0)
        if len(back):
            j = int(back[0]) + 1
            raise DataError(f"{source}: row {rows[j][1]} column 'time': value {float(tm[j])!r} (run {rid!r}, step {steps[j]}) "
                            f"is not after the previous step's time {float(tm[j - 1])!r} (row {rows[j - 1][1]}); time must increase "
                            f"strictly within a run")
        TM.append(tm)
        run_ids.append(rid)
        R.append(np.full(len(rows), ri))
        S.append(np.array(steps))
        TG.append(v[:, 0:dim]); K.append(v[:, dim]); Q.append(v[:, dim + 1:dim + 1 + n_joints])
        X.append(v[:, dim + 1 + n_joints:])
    return MeasuredData(run_ids, np.concatenate(R), np.concatenate(S), np.concatenate(TG), np.concatenate(K),
                        np.concatenate(Q), np.concatenate(X), source, np.concatenate(TM),
                        "seconds" if has_time else "steps")


def read_measured_csv(path: str | Path, sc=None) -> MeasuredData:
    """Read a measured-data CSV file (see :func:`parse_measured_csv`) with the columns of scenario
    ``sc`` (default: planar): a missing file, a directory, a binary or non-UTF-8 file, or a file too
    large for this machine is one :class:`DataError`."""
    from .inputs import read_text

    p = Path(path)
    dim, n = data_shape(sc) if sc is not None else (2, 2)
    return parse_measured_csv(read_text(p, "data file"), str(p), dim=dim, n_joints=n)


def require_planar(sc, what: str) -> None:
    """Bench runs and calibration are planar for now: a spatial scenario gets one clear error."""
    if sc.dim != 2:
        raise ErrplanError(f"{sc.source}: {what} of a spatial scenario (robot from a URDF) is not available yet; "
                           f"it runs on planar scenarios")


# ----------------------------------------------------------------------------- starts
#: margins of a bench tip: joint limits (rad or m), tip from the port, wrist from the port (m)
START_MARGINS = dict(limit_margin=0.05, port_margin=0.030, wrist_margin=0.040)
#: start-grid spacing (m) of :func:`choose_starts` by dimension
START_SPACING = {2: 0.005, 3: 0.010}


def _straight_wrist(x: np.ndarray, port: np.ndarray, length: float) -> np.ndarray:
    """The wrist (..., d) of a straight shaft of ``length`` whose tip is at ``x`` through ``port``."""
    if x.shape[-1] == 2:
        return flexed_wrist(x, port, length, np.zeros(x.shape[:-1]))
    e = x - port
    return x - length * e / np.linalg.norm(e, axis=-1, keepdims=True)


def tip_valid(sc, x: np.ndarray, *, limit_margin: float, port_margin: float, wrist_margin: float) -> np.ndarray:
    """Tips (..., d) a straight shaft through the true port reaches with margins: joint limits,
    tip and wrist away from the port, also from the controller's estimate (planar and spatial)."""
    from .kinematics import arm_for

    arm = arm_for(sc.robot)
    L = float(sc.instrument.length)
    port = np.asarray(sc.port.position, float)
    estimate = np.asarray(sc.port.estimate, float)
    x = np.asarray(x, float)
    dim = x.shape[-1]
    d = np.linalg.norm(x - port, axis=-1)
    ok = (d > port_margin) & (d < L - wrist_margin)
    away = np.zeros(dim)
    away[-1] = 0.5 * L
    xs = np.where(ok[..., None], x, port + away)
    w = _straight_wrist(xs, port, L)
    q, reach = arm.inverse(w)
    ok &= reach
    qs = np.where(reach[..., None], q, 0.0)
    ok &= arm.limit_margin(qs) >= limit_margin
    rho_e = np.linalg.norm(estimate - w, axis=-1)
    ok &= (rho_e > wrist_margin) & (rho_e < L - port_margin)
    return ok


def tip_workspace_grid(sc, spacing: float, what: str, region: bool = True) -> np.ndarray:
    """Grid points (m, d) at ``spacing`` over the bounding box of the tip workspace (a straight
    shaft through the true port), clipped to ``[fields] region`` when the scenario has one (and
    ``region``); the number of points is checked against the memory budget first."""
    from .inputs import check_allocation
    from .kinematics import arm_for

    arm = arm_for(sc.robot)
    L = float(sc.instrument.length)
    port = np.asarray(sc.port.position, float)
    dim = sc.dim
    w = arm.sample_wrists(61 if dim == 2 else 21)
    rho = np.linalg.norm(port - w, axis=-1)
    w = w[(rho > 1e-6) & (rho < L)]
    if len(w) == 0:
        raise ErrplanError(f"{sc.source}: the shaft cannot reach through the port from any wrist pose")
    tips = w + L * (port - w) / np.linalg.norm(port - w, axis=-1)[:, None]
    lo, hi = tips.min(axis=0), tips.max(axis=0)
    region = sc.fields.region if region else None
    if region:
        for i, ax in enumerate(sc.axes):
            if ax in region:
                lo[i], hi[i] = max(lo[i], region[ax][0]), min(hi[i], region[ax][1])
    counts = [float(np.floor(max(hi[i] - lo[i], 0.0) / spacing + 0.5)) + 1 for i in range(dim)]
    # the tip workspace spans about 2 (shaft length + reach): name whichever of the two dominates
    if dim == 2:
        big = max(("[instrument] length", L), ("[robot] link_lengths", [arm.l1, arm.l2]),
                  key=lambda kv: kv[1] if np.isscalar(kv[1]) else sum(kv[1]))
    else:
        big = ("[instrument] length", L)
    check_allocation(big[0], big[1], float(np.prod(counts)), START_TIP_BYTES,
                     f"{what} ({' x '.join(f'{c:.3g}' for c in counts)} candidate tips at {spacing * 1000:g} mm "
                     f"over the tip workspace)")
    axes = [lo[i] + spacing * np.arange(int(counts[i])) for i in range(dim)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, dim)


def _probe(radius: float, dim: int) -> np.ndarray:
    """Probe offsets of a start's neighbourhood: the centre, and two shells of the bench's
    target directions at ``radius`` and half of it (planar: 12 directions each)."""
    if dim == 2:
        ang = np.arange(12) * (np.pi / 6)
        ring = np.stack([np.sin(ang), np.cos(ang)], axis=-1)
    else:
        ring = target_offsets(1.0, 3)
    return np.vstack([np.zeros((1, dim)), radius * ring, 0.5 * radius * ring])


def target_offsets(distance: float = TARGET_DISTANCE, dim: int = 2) -> np.ndarray:
    """Target offsets ``distance`` from a start. Planar (8, 2): +z, then counter-clockwise in 45
    degree steps (P1 Sec. III-B). Spatial (14, 3): +-x, +-y, +-z, then the 8 cube diagonals
    (docs/interfaces.md), all of length ``distance``."""
    if dim == 2:
        a = np.arange(8) * (np.pi / 4)
        return distance * np.stack([np.sin(a), np.cos(a)], axis=-1)
    axes = np.vstack([np.eye(3), -np.eye(3)])[[0, 3, 1, 4, 2, 5]]
    diag = np.array([[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)], float) / np.sqrt(3.0)
    return distance * np.vstack([axes, diag]) + 0.0


def choose_starts(sc, n_starts: int = DEFAULT_STARTS, *, spacing: float | None = None,
                  radius: float = 0.030) -> np.ndarray:
    """Start tips (m, d): P1's L, M, N (at x = 0 in 3-D) where they and their targets are
    reachable, then starts spread over the tip workspace (farthest-point sampling over robust tips).

    A robust tip has every point of its ``radius`` neighbourhood (centre, two shells) reachable
    through the true port with 0.05 rad joint-limit margin, the tip 30 mm and the wrist 40 mm away
    from the port (and from the controller's port estimate). The start grid is 5 mm in the plane,
    10 mm in 3-D, over the tip workspace (within ``[fields] region`` when there is one).
    """
    if n_starts < 1:
        raise ErrplanError(f"starts {n_starts}: expected at least 1")
    dim = sc.dim
    spacing = START_SPACING[dim] if spacing is None else spacing
    kw = START_MARGINS
    chosen: list[np.ndarray] = []
    offs = target_offsets(dim=dim)
    for s in P1_STARTS:
        s = np.asarray(s if dim == 2 else (0.0,) + tuple(s), float)
        pts = np.vstack([s[None], s + offs])
        if np.all(tip_valid(sc, pts, limit_margin=0.02, port_margin=0.03, wrist_margin=0.04)):
            chosen.append(s)
        if len(chosen) >= n_starts:
            return np.array(chosen)
    cand = tip_workspace_grid(sc, spacing, "the bench's start search")
    probe = _probe(radius, dim)
    ok = np.zeros(len(cand), bool)
    chunk = max(1, START_CHUNK * 25 // len(probe))
    for c0 in range(0, len(cand), chunk):  # the probes of every tip: in chunks, memory stays flat
        c = cand[c0:c0 + chunk]
        ok[c0:c0 + len(c)] = np.all(tip_valid(sc, c[:, None, :] + probe[None], **kw), axis=1)
    cand = cand[ok]
    if len(cand) == 0 and not chosen:
        raise ErrplanError(f"{sc.source}: no start tip has its {radius * 1000:g} mm neighbourhood inside the tip "
                           f"workspace; the scenario's workspace is too small for a bench run")
    if len(cand):
        dmin = (np.min(np.linalg.norm(cand[:, None] - np.array(chosen)[None], axis=-1), axis=1) if chosen
                else np.linalg.norm(cand - cand.mean(axis=0), axis=-1) * -1.0)
        if not chosen:  # the robust tip nearest the centroid first
            i = int(np.argmax(dmin))
            chosen.append(cand[i])
            dmin = np.linalg.norm(cand - cand[i], axis=-1)
        while len(chosen) < n_starts and np.max(dmin) > 2 * TARGET_DISTANCE:
            i = int(np.argmax(dmin))
            chosen.append(cand[i])
            dmin = np.minimum(dmin, np.linalg.norm(cand - cand[i], axis=-1))
    return np.array(chosen)


# ----------------------------------------------------------------------------- the bench run
def scenario_load(sc) -> float:
    """The true lateral tip load over EI (1/m^2): the value of the error set's
    ``tip_force_over_ei`` closest to 0 (0 when the set allows it; P2's scenarios declare a fixed
    load there) — the same rule as :func:`errplan.pipeline.truth_plant`."""
    tl = sc.uncertainty.tip_force_over_ei
    return float(np.clip(0.0, tl[0], tl[1])) if tl is not None else 0.0


def truth_plant(sc, *, effects: bool = True, noise: bool = True):
    """The scenario's truth as a bench has it: ``[port] position``, the tip load of
    :func:`scenario_load`, its ``[effects]`` and (by default) its sensor noise."""
    from .simulation import Plant

    from .models import arm_model

    return Plant.from_model(arm_model(sc), load=scenario_load(sc), effects=effects, noise=noise)


def bench_controller(sc):
    """The scenario's controller (:class:`errplan.simulation.ControllerModel`) as the bench runs it
    (P2's flexion controller falls back to the rigid lever through the port estimate where the
    shaft does not bend, as ``ControllerModel.J_hat`` documents)."""
    from .simulation import ControllerModel

    from .models import arm_model

    return ControllerModel.from_model(arm_model(sc))


@dataclass
class ExperimentResult:
    """A bench run: the data and, per run, its start, target and how it ended."""

    data: MeasuredData
    starts: np.ndarray            # (m, d) start tips
    status: list[str]             # per run: "converged" | "max_steps" | "left_workspace"
    tolerance: float
    dwell: int
    max_steps: int
    targets: list | None = None   # per start, the targets of its runs (m lists of d-vectors)

    def summary_rows(self) -> list[list]:
        d = self.data
        rows = []
        for r in range(d.runs):
            m = (d.run == r) & d.tracked  # the run's tracked rows (a dropout has no tip)
            if not m.any():
                m = d.run == r
            tip = d.tip[m]
            tg = d.target[m][0]
            rows.append([d.run_ids[r], f"({tip[0, 0] * 1000:.1f}, {tip[0, 1] * 1000:.1f})",
                         f"({tg[0] * 1000:.1f}, {tg[1] * 1000:.1f})", int(np.sum(d.run == r)) - 1,
                         float(np.linalg.norm(tip[-1] - tg) * 1000), self.status[r]])
        return rows


def burst_mask(n: int, rate: float, burst: int, rng: np.random.Generator) -> np.ndarray:
    """Rows (n,) without a tracked tip: at each row outside a burst a burst of 1..``burst`` rows
    (uniform) starts with the probability that makes ``rate`` the expected share of rows,
    ``p = rate / (rate + m (1 - rate))``, m the mean burst length."""
    lost = np.zeros(n, bool)
    if rate <= 0 or n == 0:
        return lost
    m = (burst + 1) / 2.0
    p = rate / (rate + m * (1.0 - rate))
    start = rng.random(n) < p
    length = rng.integers(1, burst + 1, n)
    i = 0
    while i < n:
        if start[i]:
            lost[i:i + length[i]] = True
            i += int(length[i])
        else:
            i += 1
    return lost


def bench_recording(sensors, rows: int, dim: int, rng: np.random.Generator | None, clock: float = 0.0):
    """How a bench records one run of up to ``rows`` rows ([sensors], docs/interfaces.md): the rows'
    times (s from ``clock``, durations ``step_time`` times 1 + uniform(-step_jitter, step_jitter);
    None without ``step_time``: the tracker latency is then in steps), the dropout rows (bursts,
    :func:`burst_mask`) and the outliers' offsets (rows, dim) (size uniform in ``outlier_size``,
    random direction). All None when the sensors record a clean table."""
    if rng is None:
        return None, None, None
    times = lost = glitch = None
    if sensors.step_time is not None:
        dt = sensors.step_time * (1.0 + rng.uniform(-sensors.step_jitter, sensors.step_jitter, rows))
        times = clock + np.concatenate([[0.0], np.cumsum(dt[1:])])
    if sensors.dropout_rate > 0:
        lost = burst_mask(rows, sensors.dropout_rate, sensors.dropout_burst, rng)
    if sensors.outlier_rate > 0:
        hit = rng.random(rows) < sensors.outlier_rate
        size = rng.uniform(sensors.outlier_size[0], sensors.outlier_size[1], rows)
        v = rng.normal(size=(rows, dim))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        glitch = np.where(hit[:, None], size[:, None] * v, 0.0)
    return times, lost, glitch


def _inv_batch(A: np.ndarray, rcond: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Inverses of square matrices (..., d, d) and a mask of the singular ones (inverse 0 there)."""
    A = np.asarray(A, float)
    d = A.shape[-1]
    with np.errstate(invalid="ignore", over="ignore"):
        det = np.linalg.det(np.where(np.isfinite(A), A, 0.0))
        scale = np.prod(np.linalg.norm(A, axis=-1), axis=-1)
    singular = ~np.all(np.isfinite(A), axis=(-2, -1)) | ~(np.abs(det) > rcond * scale)
    safe = np.where(singular[..., None, None], np.eye(d), A)
    return np.where(singular[..., None, None], 0.0, np.linalg.inv(safe)), singular


def simulate_bench(plant, ctrl, q0: np.ndarray, targets: np.ndarray, gain: float, *, max_steps: int,
                   dwell: int, tolerance: float, rng: np.random.Generator | None = None, model=None) -> "MeasuredData":
    """Every bench run at once (numpy over runs): the loop of :func:`errplan.simulation.simulate`
    from encoder angles ``q0`` (R, n) toward ``targets`` (R, d) at ``gain``, stopped as
    :func:`run_experiment` stops a run (``dwell`` steps after the tracked tip first comes within
    ``tolerance``, after ``max_steps`` commands, or when a command leaves the workspace).

    The same physics as ``simulate`` (noise drawn per step for all runs, so a seeded run differs
    from ``run_experiment``'s in the noise draws only); used where many candidate runs must be
    predicted quickly (:mod:`errplan.calibration.design`). Runs with fewer than 2 rows are dropped.
    """
    model = plant.declared() if model is None else model
    q = np.array(q0, float)
    targets = np.asarray(targets, float)
    R, d = targets.shape
    u = np.zeros((R, d))
    q_true = q.copy()
    b = np.asarray(getattr(plant, "backlash", ()), float)
    play = b.size > 0 and bool(np.any(b))
    theta = q_true.copy()  # the links behind the play (backlash), mid-band at each run's start
    with np.errstate(invalid="ignore", divide="ignore"):
        tip = plant.tip(q_true, u)
    alive = np.ones(R, bool)
    stop_at = np.full(R, max_steps)          # last step index recorded
    rows_q, rows_x, rows_r, rows_s = [], [], [], []
    tau = float(np.asarray(getattr(plant, "tracker_latency", (0.0,)) or (0.0,), float)[0])
    hist_x: list = []
    for t in range(max_steps + 1):
        if tau:
            from .simulation import delayed_tip

            hist_x.append(tip.copy())
            tracked = plant.tracked(delayed_tip([k * plant.step_duration for k in range(t + 1)], hist_x, tau))
        else:
            tracked = plant.tracked(tip)
        if rng is not None and plant.tracker_sigma > 0:
            tracked = tracked + rng.normal(0.0, plant.tracker_sigma, tracked.shape)
        idx = np.flatnonzero(alive)
        rows_q.append(q[idx].copy()); rows_x.append(tracked[idx].copy())
        rows_r.append(idx); rows_s.append(np.full(len(idx), t))
        arrived = alive & (np.linalg.norm(tracked - targets, axis=-1) < tolerance) & (stop_at == max_steps)
        stop_at = np.where(arrived, np.minimum(t + dwell, max_steps), stop_at)
        alive &= t < stop_at
        if not np.any(alive) or t == max_steps:
            break
        err = targets - tracked
        if ctrl.jacobian == "rigid":
            Jh = ctrl.J_hat(q)
        else:
            from .simulation import plant_at

            with np.errstate(invalid="ignore", divide="ignore"):
                Jh = ctrl.J_hat(q, plant_at(plant, q_true))
        Jinv, singular = _inv_batch(Jh)
        dq = gain * np.einsum("rij,rj->ri", Jinv, err)
        q_new = q + dq
        q_read = q_new + rng.normal(0.0, plant.encoder_sigma, q_new.shape) if (
            rng is not None and plant.encoder_sigma > 0) else q_new
        with np.errstate(invalid="ignore", divide="ignore"):
            u_new = model.motion_direction(q, q_new, u)
            ok = (~singular & plant.arm.within_limits(plant.link_angles_q(q_new))
                  & plant.shaft_reaches(plant.wrist(q_new)) & np.all(np.isfinite(q_new), axis=-1))
        alive &= ok
        u = np.where(alive[:, None], u_new, u)
        q = np.where(alive[:, None], q_read, q)
        q_true = np.where(alive[:, None], q_new, q_true)
        if play:
            theta = np.where(alive[:, None], np.clip(theta, q_true - b, q_true + b), theta)
        with np.errstate(invalid="ignore", divide="ignore"):
            tip = np.where(alive[:, None], plant.tip(theta if play else q_true, u), tip)
    run = np.concatenate(rows_r)
    step = np.concatenate(rows_s)
    order = np.lexsort((step, run))
    run, step = run[order], step[order]
    Q, X = np.concatenate(rows_q)[order], np.concatenate(rows_x)[order]
    counts = np.bincount(run, minlength=R)
    keep = counts[run] >= 2
    kept = np.flatnonzero(counts >= 2)
    remap = -np.ones(R, int)
    remap[kept] = np.arange(len(kept))
    return MeasuredData([str(r) for r in kept], remap[run[keep]], step[keep], targets[run[keep]],
                        np.full(int(keep.sum()), float(gain)), Q[keep], X[keep], "<design>")


def run_experiment(sc, seed: int = 0, *, plant=None, starts=None, n_starts: int = DEFAULT_STARTS,
                   max_steps: int = DEFAULT_MAX_STEPS, dwell: int = DEFAULT_DWELL,
                   tolerance: float | None = None, runs=None) -> ExperimentResult:
    """A P1-style bench run on the scenario's truth (see the module docstring).

    ``plant`` overrides the truth (default: :func:`truth_plant`, the scenario's port, load,
    effects and sensor noise) — tests use it for effects outside the catalogue. ``tolerance``
    (m) defaults to ``max(0.5 mm, 3 tracker_sigma)``. Deterministic from ``seed``. ``runs``
    (m, 2, d): explicit (start, target) pairs instead of every start times P1's targets (a designed
    bench, :func:`errplan.calibration.design.design_experiment`); run ids are then
    ``"<start index>-<run of that start>"`` with the starts numbered in order of appearance.
    """
    from .inputs import check_allocation
    from .simulation import simulate

    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ErrplanError(f"max_steps {max_steps!r}: expected an integer >= 1")
    if isinstance(dwell, bool) or not isinstance(dwell, (int, np.integer)) or dwell < 0:
        raise ErrplanError(f"dwell {dwell!r}: expected an integer >= 0")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**63:
        raise ErrplanError(f"seed {seed!r}: expected an integer from 0 to 2^63 - 1")
    truth = plant if plant is not None else truth_plant(sc)
    # friction's direction u is the motion a command produces under the *declared* model (the
    # scenario's arm, shaft and port.position, no effects), whatever the truth is
    model = truth_plant(sc, effects=False, noise=False)
    ctrl = bench_controller(sc)
    tol = tolerance if tolerance is not None else max(5e-4, 3 * truth.tracker_sigma)
    if runs is not None:
        runs = np.asarray(runs, float)
        S, inv = np.unique(runs[:, 0], axis=0, return_inverse=True)
        first = [int(np.flatnonzero(inv.ravel() == k)[0]) for k in range(len(S))]
        order = np.argsort(first)                      # starts in order of appearance
        S = S[order]
        rank = np.empty(len(order), int)
        rank[order] = np.arange(len(order))
        groups = [[] for _ in S]
        for r, k in enumerate(inv.ravel()):
            groups[rank[k]].append(runs[r, 1])
        n_runs = len(runs)
    else:
        S = np.atleast_2d(np.asarray(starts, float)) if starts is not None else choose_starts(sc, n_starts)
        offs = target_offsets(dim=sc.dim)
        groups = [[s + o for o in offs] for s in S]
        n_runs = len(S) * len(offs)
    check_allocation("--max-steps", max_steps, n_runs * (max_steps + 1.0), BENCH_ROW_BYTES,
                     f"the bench data ({len(S)} start(s), {n_runs} runs x up to {max_steps + 1} rows)")
    rng = np.random.default_rng(seed)
    gain = sc.controller.gain
    # a bench as it records ([sensors]: time, dropouts, outliers) from its own stream: the noise
    # draws stay those of the clean bench
    sensors = sc.sensors
    srng = np.random.default_rng([seed, 1]) if sensors.records else None
    clock = 0.0
    ids, R, ST, TG, K, Q, X, status = [], [], [], [], [], [], [], []
    TM = []
    for si, s in enumerate(S):
        try:
            q0 = truth.configuration_for_tip(s)
        except ErrplanError as e:
            raise ErrplanError(f"start {si} {np.round(s, 4).tolist()}: {e}") from None
        for ti, tg in enumerate(groups[si]):
            tg = np.asarray(tg, float)
            times, lost, glitch = bench_recording(sensors, max_steps + 1, sc.dim, srng, clock)
            res = simulate(truth, ctrl, q0, tg[None], gain, tolerance=1e-300, max_steps=max_steps, rng=rng,
                           model=model, times=times, lost=lost, glitch=glitch)
            with np.errstate(invalid="ignore"):
                e = np.linalg.norm(res.tracked - tg, axis=-1)
            hit = np.flatnonzero(e < tol)
            n = len(res.q)
            st = res.status
            if len(hit) and hit[0] + dwell + 1 < n:
                n = hit[0] + dwell + 1
                st = "converged"
            elif len(hit):
                st = "converged"
            if n < 2:
                continue  # the very first command left the workspace: nothing measured
            rid = len(ids)
            ids.append(f"{si}-{ti}")
            R.append(np.full(n, rid)); ST.append(np.arange(n)); TG.append(np.repeat(tg[None], n, 0))
            K.append(np.full(n, gain)); Q.append(res.q[:n]); X.append(res.tracked[:n]); status.append(st)
            if sensors.step_time is not None:
                TM.append(times[:n])
                clock = float(times[n - 1]) + 10 * sensors.step_time  # the next run starts a little later
    if not ids:
        raise ErrplanError(f"{sc.source}: every bench run left the workspace on its first command")
    data = MeasuredData(ids, np.concatenate(R), np.concatenate(ST), np.concatenate(TG), np.concatenate(K),
                        np.concatenate(Q), np.concatenate(X), "<experiment>",
                        np.concatenate(TM) if TM else None, "seconds" if TM else "steps")
    return ExperimentResult(data, S, status, tol, dwell, max_steps, [list(g) for g in groups])
