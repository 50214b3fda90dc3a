"""Replay measured data on a model: pose residual, friction's direction, batched controller replay,
approach rows and the trajectory error (step 1 of :mod:`errplan.calibration`)."""
from __future__ import annotations

import math

import numpy as np

from ..effects import latency_of, predict_tracked
from ..errors import DataError
from ..experiment import MeasuredData


def arrival_tolerance(noise_sigma: float) -> float:
    """Distance (m) within which a measured run counts as arrived: max(0.5 mm, 4 noise floors)."""
    return max(5e-4, 4.0 * noise_sigma)



# ----------------------------------------------------------------------------- residuals
def declared_plant(sc, data: MeasuredData | None = None):
    """The declared model: the scenario's truth (``[port] position``, its tip load, the effects it
    already declares), no noise (:func:`errplan.experiment.truth_plant`). With measured ``data``, a
    declared ``tracker_latency`` is taken in the data's time unit (seconds or steps)."""
    from ..effects import latency_in_data_units
    from ..experiment import truth_plant

    plant = truth_plant(sc, effects=True, noise=False)
    if data is not None and "tracker_latency" in sc.effects:
        tau = latency_in_data_units(sc.effects, sc, data)["tracker_latency"]["tau"]
        plant = plant.with_(tracker_latency=(tau,))
    return plant


#: a run in which the declared model's wrist comes this close to the port (m) is left out of the fits:
#: there the lever's tip direction turns by L / rho per metre of wrist motion (rho the wrist-port
#: distance), so the model's tip, and any effect's prediction of it, is undefined within the effects'
#: own millimetres
NEAR_PORT = 0.010
#: a tracked tip farther than the shaft length from the model's tip is degenerate geometry (not bad
#: data) only in a run whose model wrist comes this close to the port (m): a wrist error delta turns
#: the tip by about L delta / rho, which exceeds L only for rho < delta, and the catalogue's effects
#: move the wrist by millimetres to centimetres. Both tips lie within L of their ports, so such a tip
#: is also never more than 2.5 L from the model's.
DEGENERATE_RHO = 0.050
#: degenerate runs are left out up to this share of the runs; beyond it the data are taken for
#: another scenario's (one error)
MAX_LEFT_OUT = 0.2


def _degenerate_runs(data: MeasuredData, rho: np.ndarray, off: np.ndarray, L: float) -> tuple[np.ndarray, list[str]]:
    """Runs (indices) the lever model cannot describe, each with a sentence, from each row's model
    wrist-port distance ``rho`` and tracked-to-model tip distance ``off``: the wrist passes within
    :data:`NEAR_PORT` of the port, or a tip lies 1-2.5 shaft lengths off in a run whose wrist comes
    within :data:`DEGENERATE_RHO` (a large effect has driven the wrist through the port's
    neighbourhood, where the lever turns the tip by L / rho per metre of wrist error)."""
    closest = np.full(data.runs, np.inf)
    np.minimum.at(closest, data.run, np.where(np.isfinite(rho), rho, np.inf))
    worst = np.zeros(data.runs)
    np.maximum.at(worst, data.run, np.where(np.isfinite(off), off, np.inf))
    runs, notes = [], []
    for r in range(data.runs):
        if closest[r] < NEAR_PORT:
            why = f"the declared model's wrist passes {closest[r] * 1000:.1f} mm from the port"
        elif L <= worst[r] < 2.5 * L and closest[r] < DEGENERATE_RHO:
            why = (f"a tracked tip lies {worst[r]:.3g} m from the model's tip (more than the shaft), its wrist "
                   f"{closest[r] * 1000:.0f} mm from the port at the closest")
        else:
            continue
        runs.append(r)
        notes.append(f"run {data.run_ids[r]!r} left out: {why}")
    return np.array(runs, int), notes


def check_against_model(data: MeasuredData, plant, what: str = "the declared model", *,
                        leave_out: bool = False) -> tuple[MeasuredData, list[str]]:
    """Every row's encoder angles must give a wrist from which the shaft reaches through the port,
    every tracked tip must lie within the shaft length of the model's tip and every target within
    the robot's reach; the first row that does not is one error (numbered as in the file).

    With ``leave_out``, runs that drove the model's wrist through the port's neighbourhood
    (:func:`_degenerate_runs`) are real rows the lever model cannot describe: they are left out,
    up to :data:`MAX_LEFT_OUT` of the runs (beyond it the data are taken for another scenario's),
    and checked no further. Returns the data to fit and a sentence per run left out. Rows outside
    the joint limits or without a shaft through the port are bad data, never left out."""
    w = plant.wrist(data.q)
    ok = plant.shaft_reaches(w) & plant.arm.within_limits(plant.link_angles_q(data.q), tol=0.05)
    if not np.all(ok):
        i = int(np.flatnonzero(~ok)[0])
        raise DataError(f"{data.source}: row {i + 1} (run {data.run_ids[data.run[i]]!r}, step {data.step[i]}): encoder "
                        f"angles {np.round(data.q[i], 5).tolist()} put the wrist at {np.round(w[i], 4).tolist()}, "
                        f"where {what} cannot hold the shaft through the port at "
                        f"{np.round(plant.true_port, 4).tolist()} or is outside the joint limits "
                        f"(is the data from this scenario?)")
    # every effect of the catalogue moves the tip by mm to cm; a tracked tip farther from the
    # model's tip than the whole shaft, or a target outside anything the tip can reach, is not
    # measured data of this scenario (and would only overflow the fits)
    L = float(plant.length)
    with np.errstate(all="ignore"):
        model_tip = plant.tip(data.q)
        off = np.linalg.norm(data.tip - model_tip, axis=-1)
    off = np.where(data.tracked, off, 0.0)  # a dropout has no tracked tip to check
    kept = np.ones(data.rows, bool)
    notes: list[str] = []
    if leave_out:
        rho = np.linalg.norm(w - np.asarray(plant.true_port, float), axis=-1)
        bad_runs, notes = _degenerate_runs(data, rho, off, L)
        if len(bad_runs) > MAX_LEFT_OUT * data.runs:
            bad_runs, notes = bad_runs[:0], []
        kept = ~np.isin(data.run, bad_runs)
    for i in np.flatnonzero(kept & ~(off < L))[:1]:
        raise DataError(f"{_row(data, i)}, step {data.step[i]}): tracked tip {_pt(data.tip[i])} is {_m(off[i])} "
                        f"from {what}'s tip {_pt(model_tip[i])} at its encoder angles, more than the shaft length "
                        f"{L:g} m (is the data from this scenario?)")
    reach = 2.0 * (L + arm_reach(plant.arm))  # a bound on the tip workspace's diameter
    with np.errstate(all="ignore"):
        far = np.linalg.norm(data.target - model_tip, axis=-1)
    for i in np.flatnonzero(kept & ~(far < reach))[:1]:
        raise DataError(f"{_row(data, i)}): target {_pt(data.target[i])} is {_m(far[i])} from the tip, farther than "
                        f"the robot can reach ({reach:g} m; is the data from this scenario?)")
    if notes:
        data = data.subset(np.setdiff1d(np.arange(data.runs), bad_runs))
    return data, notes


def arm_reach(arm) -> float:
    """A bound on the distance from the arm's base to its wrist (m): l1 + l2 for P1's planar arm,
    the largest wrist distance from the wrists' centre over a joint grid for a URDF arm, times 2."""
    if hasattr(arm, "l1"):
        return float(arm.l1) + float(arm.l2)
    w = arm.sample_wrists(9)
    return 2.0 * float(np.max(np.linalg.norm(w - w.mean(axis=0), axis=-1))) if len(w) else 0.0


def _row(data, i) -> str:
    """``"<file>: row N (run 'id'"``: the start of an error about row ``i`` (0-based) of measured data."""
    i = int(i)
    return f"{data.source}: row {i + 1} (run {data.run_ids[data.run[i]]!r}"


def _pt(x) -> str:
    return "[" + ", ".join(f"{float(v):.6g}" for v in x) + "]"


def _m(d: float) -> str:
    return f"{d:.4g} m" if math.isfinite(d) else "more than 1e300 m"


def rms(r: np.ndarray) -> float:
    """Per-coordinate RMS of residual vectors (n, d)."""
    r = np.asarray(r, float)
    return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")


def motion_model(sc):
    """``x_model`` of docs/physics.md ``port_friction``: the scenario's arm, shaft (its tip load) and
    ``port.position``, no effects. Friction's direction is the motion a command produces under it,
    for the bench (:func:`errplan.experiment.run_experiment`), the replay and the fits alike."""
    from ..experiment import truth_plant

    return truth_plant(sc, effects=False, noise=False)


def pose_residual(data: MeasuredData, plant, u: np.ndarray | None = None) -> np.ndarray:
    """Tracked tip minus the model's tracked tip at the encoder angles (n, d), m. ``u`` (friction's
    direction per row) defaults to :meth:`MeasuredData.commanded_directions` under
    ``plant.declared()``. A dropout's row is NaN (no tracked tip): select ``data.tracked`` rows
    for any statistic."""
    u = data.commanded_directions(plant.declared()) if u is None else u
    return data.tip - predict_tracked(plant, data.q, u, data.run, data.time)


def _controller_jacobian(ctrl, plant, q: np.ndarray) -> np.ndarray:
    """The controller's ``Jhat`` at encoder angles ``q`` (r, N); the flexion controller reads the
    model's end poses there (noise-free)."""
    if ctrl.jacobian == "rigid":
        return ctrl.J_hat(q)
    with np.errstate(invalid="ignore", divide="ignore"):
        return ctrl.J_hat(q, plant)


def replay(data: MeasuredData, plant, ctrl, model=None) -> tuple[np.ndarray, np.ndarray]:
    """Re-simulate every run on ``plant`` with controller ``ctrl`` from its first encoder reading.

    Noise-free and quasi-static, exactly the loop of :func:`errplan.simulation.simulate`, batched
    over runs; friction's direction is the motion each command produces under ``model`` (default
    ``plant.declared()``; :func:`motion_model`). Returns the predicted tracked tip for every row
    (n, d) and, per run, whether the replay stayed in the workspace for the whole measured length
    (runs,). A replay that leaves the workspace holds its last state. The plant's backlash is
    carried: the links lag the replayed encoder angles by the play, mid-band at each run's start.

    A bench as it records (docs/physics.md): the plant's ``tracker_latency`` delays the tracked
    tip the controller reads (the model's tip at the row's time - tau, linear in time between the
    replayed rows, :func:`errplan.effects.delayed`); at a row the data mark as a dropout the
    controller reads the last tracked tip of its run (zero-order hold; before the run's first
    tracked row it commands nothing). The predicted tip of every row (dropouts too) is the
    model's tracked tip there.
    """
    from ..experiment import _inv_batch

    model = plant.declared() if model is None else model
    first = data.first
    R = data.runs
    lengths = data.lengths
    T = int(lengths.max()) if R else 0
    # rows of each step, in run order (O(rows) memory, whatever the run lengths)
    by_step = np.lexsort((data.run, data.step))
    bounds = np.searchsorted(data.step[by_step], np.arange(T + 1))
    first = first[np.argsort(data.run[first])]  # run r's step 0
    q = data.q[first].copy()
    target = data.target[first]
    gain = data.gain[first]
    d = data.dim
    u = np.zeros((R, d))
    alive = np.ones(R, bool)
    pred = np.zeros_like(data.tip)
    tracked = np.zeros((R, d))
    # backlash: the links lag the encoders by the play, mid-band at a run's start (as the bench and
    # the fit, effects.backlash_angles); the controller sees the encoders, the tracker the links
    play = np.abs(np.asarray(getattr(plant, "backlash", ()) or np.zeros(q.shape[1]), float))
    theta = q.copy()
    # a bench as it records: the rows' times and dropouts per (step, run), the tracker's latency
    tau = latency_of(plant, data.time, data.run)
    seen = np.zeros((T, R), bool)            # the data have this (run, step) row
    seen[data.step, data.run] = True
    lost = np.zeros((T, R), bool)             # ... and it is a dropout
    lost[data.step[~data.tracked], data.run[~data.tracked]] = True
    if tau:
        times = np.zeros((T, R))
        times[data.step, data.run] = data.time
        # past a run's last row its time keeps its last step (never used: the run has no more rows)
        times = np.where(seen, times, np.nan)
        times = np.fmax.accumulate(times, axis=0)
        tips, true_tip = [], np.zeros((R, d))
    held = np.full((R, d), np.nan)            # the last tracked tip the controller read, per run
    for t in range(T):
        theta = np.minimum(np.maximum(theta, q - play), q + play) if play.any() else q
        with np.errstate(invalid="ignore", divide="ignore"):
            if tau:
                true_tip = np.where(alive[:, None], plant.tip(theta, u), true_tip)
                tips.append(true_tip)
                tr = plant.tracked(_delayed_now(tips, times[:t + 1], tau, seen[t]))
            else:
                tr = plant.tracked(plant.tip(theta, u))  # the tracker's registration too, not only its offset
        tracked = np.where(alive[:, None], tr, tracked)
        rows_t = by_step[bounds[t]:bounds[t + 1]]
        pred[rows_t] = tracked[data.run[rows_t]]
        held = np.where(lost[t][:, None], held, tracked)
        if t == T - 1:
            break
        has = lengths > t
        err = np.nan_to_num(target - held)    # a run not tracked yet commands nothing
        with np.errstate(invalid="ignore", divide="ignore"):
            Jinv, singular = _inv_batch(_controller_jacobian(ctrl, plant, q))
            dq = gain[:, None] * np.einsum("rij,rj->ri", np.nan_to_num(Jinv), err)
        q_new = q + dq
        with np.errstate(invalid="ignore", divide="ignore"):
            ok = (~singular & plant.arm.within_limits(plant.link_angles_q(q_new))
                  & plant.shaft_reaches(plant.wrist(q_new)) & np.all(np.isfinite(q_new), axis=-1))
        step_ok = alive & ok & has
        with np.errstate(invalid="ignore", divide="ignore"):
            u = np.where(step_ok[:, None], model.motion_direction(q, q_new, u), u)
        q = np.where(step_ok[:, None], q_new, q)
        alive &= ok | ~has
    return pred, alive


def _delayed_now(tips: list, times: np.ndarray, tau: float, now: np.ndarray) -> np.ndarray:
    """The replay's delayed true tip (R, d) at the current step ``t = len(tips) - 1``: each run's true
    tip at its time ``times[t] - tau`` (tau > 0), linear in time between the steps ``tips`` (t + 1 of
    (R, d)) at ``times`` (t + 1, R), the first step's before it (:func:`errplan.effects.delayed`).
    ``now`` (R,): the runs that have a row at step t (the others are not needed)."""
    t = len(tips) - 1
    s = times[t] - tau
    out = tips[0].copy()
    for k in range(t, 0, -1):  # the segment [k - 1, k] holding s, searched back from now
        t0, t1 = times[k - 1], times[k]
        inside = (s >= t0) & (s < t1)
        w = np.where(inside, (s - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0)[:, None]
        out = np.where(inside[:, None], tips[k - 1] + w * (tips[k] - tips[k - 1]), out)
        if np.all((s >= t0) | ~now):
            break
    return out


def approach_mask(data: MeasuredData, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows (n,) compared by the trajectory residual, and the runs (runs,) left out.

    A run's approach is steps 1 .. the first step whose tracked tip is within ``tolerance`` of the
    target: after arrival the measured tip only jitters with the noise the controller chases,
    which no noise-free replay predicts. A run that never arrives counts whole if its distance to
    the target never grew beyond its start distance after the first command (a slow gain), and is
    left out if it did (it diverged or cycles: the controller is not contracting there,
    ||G|| >= 1, and the path amplifies the measurement noise, so no replay can follow it step for
    step). The first command is not held against a run: it starts the tip moving from rest, and
    port friction then holds the tip back by up to its size, once, in a run that converges.
    """
    e = np.linalg.norm(data.tip - data.target, axis=-1)
    e = np.where(data.tracked, e, -np.inf)  # a dropout: no distance known (neither arrived nor growing)
    big = np.iinfo(np.int64).max
    arrive = np.full(data.runs, big)
    idx = np.flatnonzero((e < tolerance) & (data.step >= 1) & data.tracked)
    np.minimum.at(arrive, data.run[idx], data.step[idx])
    # a run's start distance: its first tracked row's
    e0 = np.full(data.runs, np.inf)
    tr = np.flatnonzero(data.tracked)
    first_tr = tr[np.unique(data.run[tr], return_index=True)[1]] if len(tr) else tr
    e0[data.run[first_tr]] = e[first_tr]
    late = data.step >= 2
    elate = np.zeros(data.runs)
    np.maximum.at(elate, data.run[late], e[late])
    unsettled = (arrive == big) & (elate > e0 + tolerance)
    mask = (data.step >= 1) & (data.step <= arrive[data.run]) & ~unsettled[data.run] & data.tracked
    return mask, unsettled


def trajectory_errors(data: MeasuredData, plant, ctrl, tolerance: float, model=None) -> tuple[float, float]:
    """Per-coordinate RMS of measured minus replayed tracked tips over the approach rows (see
    :func:`approach_mask`; NaN if there are none) and over every step >= 1 of every run."""
    pred, _ = replay(data, plant, ctrl, model)
    r = data.tip - pred
    mask, _ = approach_mask(data, tolerance)
    return (rms(r[mask]) if np.any(mask) else float("nan")), rms(r[(data.step >= 1) & data.tracked])
