"""Measured data as a bench records it (docs/physics.md): a ``time`` column, tracker dropouts and a
late tracker (``tracker_latency``), and ``errplan experiment`` writing such benches.

The benches that matter here come from a plant errplan did not write: P1's planar arm in closed
form (physics.md "Robot", "Instrument and port") written in this file, driven by the inverse-Jacobian
controller whose Jacobian is a finite difference of the declared lever, with the latency applied by
``np.interp`` in time and the dropouts held (zero-order hold) by this file's own loop. On them: the
replay of the declared model plus the latency reproduces a noise-free bench to 1e-9 m (latency and
dropouts in the closed loop); calibration finds ``tracker_latency`` with tau within 0.1 step (no time
column) or max(10 %, 1 ms) (time with +-10 % jitter), alone and beside link lengths, a port offset or
gravity sag; a bench without latency never selects it; dropouts are counted and change no answer.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from errplan.api import load_scenario
from errplan.calibration import calibrate, replay
from errplan.calibration.residual import declared_plant, motion_model
from errplan.cli import main
from errplan.effects import delayed
from errplan.errors import DataError, ErrplanError
from errplan.experiment import bench_controller, burst_mask, parse_measured_csv, run_experiment

ROOT = Path(__file__).resolve().parents[1]
PORT = ROOT / "scenarios" / "beasley2004_port.toml"
GAIN = 0.4
SIGMA = 2e-4
#: the effects the in-process calibrations choose from (the whole physical catalogue costs twice as much)
EFFECTS = ["port_offset", "tracker_offset", "gravity_sag", "port_friction", "tracker_latency", "link_length"]

# ----------------------------------------------------------------------------- the test's own plant
L1 = L2 = 0.210
BASE = np.array([0.210, -0.210])
HOME = np.array([0.0, -math.pi / 2])
LENGTH = 0.320
PORT_TRUE = np.array([0.0, 0.160])
PORT_EST = np.array([0.020, 0.170])
#: start configurations (encoder angles) and P1's eight 20 mm targets around each start's tip
STARTS = [np.array([0.05, 0.10]), np.array([-0.10, 0.25]), np.array([0.12, -0.05])]
OFFS = 0.020 * np.array([[math.sin(a), math.cos(a)] for a in np.arange(8) * math.pi / 4])


def _dir(a):
    return np.array([math.sin(a), math.cos(a)])


def _tip(q, *, dl=(0.0, 0.0), port=PORT_TRUE, sag=(0.0, 0.0, 0.0)):
    """Closed-form lever tip of P1's planar arm (physics.md): link angles after gravity sag, link
    lengths declared + dl, the shaft through ``port``."""
    a1 = q[0] + HOME[0]
    a2 = a1 + q[1] + HOME[1]
    c1, c2, c3 = sag
    s1, s2 = c1 * math.cos(a1) + c2 * math.cos(a2), c3 * math.cos(a2)
    a1, a2 = a1 - s1, a2 - s1 - s2  # link angles = encoder angles - sag (a2 is absolute: both sags)
    w = BASE + (L1 + dl[0]) * _dir(a1) + (L2 + dl[1]) * _dir(a2)
    e = port - w
    return w + LENGTH * e / np.linalg.norm(e)


def _jhat(q, h=1e-7):
    """The controller's Jacobian: central differences of the declared lever through the port estimate."""
    cols = []
    for j in range(2):
        dq = np.zeros(2)
        dq[j] = h
        cols.append((_tip(q + dq, port=PORT_EST) - _tip(q - dq, port=PORT_EST)) / (2 * h))
    return np.stack(cols, axis=-1)


def closed_form_bench(*, tau=0.0, dt=None, jitter=0.0, drop=0.0, burst=8, sigma=SIGMA, steps=30, seed=0,
                      starts=STARTS, **truth) -> str:
    """A bench of the test's own plant as a CSV text: per start, eight runs of ``steps`` commands at
    gain GAIN. The tracker reads the true tip at the row's time - ``tau`` (``np.interp`` in time over
    the run's true tips so far: before the first row the first row's), plus noise; a dropout row (bursts
    of 1..burst at a share ``drop``) has empty tip cells and the controller holds the last tracked tip
    (commanding nothing before the first). ``dt``: a ``time`` column, steps of dt (1 +- jitter)."""
    rng = np.random.default_rng(seed)
    lines = ["run,step," + ("time," if dt else "") + "target_y,target_z,gain,q1,q2,tip_y,tip_z"]
    clock = 100.0 if dt else 0.0
    for si, q0 in enumerate(starts):
        x0 = _tip(q0, **truth)
        for ti, off in enumerate(OFFS):
            target = x0 + off
            q = q0.copy()
            lost = burst_mask(steps + 1, drop, burst, rng) if drop else np.zeros(steps + 1, bool)
            times, tips, held = [], [], None
            t = clock
            for k in range(steps + 1):
                if k:
                    t += dt * (1 + rng.uniform(-jitter, jitter)) if dt else 1.0
                times.append(t)
                tips.append(_tip(q, **truth))
                x = np.array([np.interp(t - tau, times, [p[c] for p in tips]) for c in range(2)])
                x = x + rng.normal(0.0, sigma, 2) if sigma else x
                cells = "," if lost[k] else f"{x[0]:.17g},{x[1]:.17g}"
                tcell = f"{t:.17g}," if dt else ""
                lines.append(f"{si}-{ti},{k},{tcell}{target[0]:.17g},{target[1]:.17g},{GAIN},{q[0]:.17g},{q[1]:.17g},{cells}")
                if not lost[k]:
                    held = x
                if held is not None:
                    q = q + GAIN * np.linalg.solve(_jhat(q), target - held)
            clock = t + 1.0
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def sc():
    return load_scenario(PORT)


def _data(text, name="bench.csv"):
    return parse_measured_csv(text, name)


def _calibrate(sc, data, effects=EFFECTS, validate=None):
    return calibrate(sc, data, validate=validate, seed=0, folds=3, effects=effects)


# ----------------------------------------------------------------------------- parsing
HEADER = "run,step,target_y,target_z,gain,q1,q2,tip_y,tip_z"


def test_parser_time_dropouts_and_errors():
    text = ("run,step,time,target_y,target_z,gain,q1,q2,tip_y,tip_z\n"
            "a,0,10.0,0,0.34,0.5,0,0,0.0,0.32\n"
            "a,1,10.019,0,0.34,0.5,0.01,0.02,,\n"
            "a,2,10.041,0,0.34,0.5,0.02,0.03,0.001,0.33\n"
            "b,1,20.5,0,0.36,0.5,0.01,0.02,,\n"
            "b,0,20.48,0,0.36,0.5,0,0,,\n")
    d = _data(text)
    assert d.time_unit == "seconds"
    np.testing.assert_allclose(d.time, [10.0, 10.019, 10.041, 20.48, 20.5])
    np.testing.assert_array_equal(d.tracked, [True, False, True, False, False])
    assert np.isnan(d.tip[1]).all() and np.isfinite(d.q[1]).all()
    assert d.dropouts == 3
    m = d.measured_json()
    assert m == {"rows": 5, "runs": 2, "dropouts": 3, "runs_without_data": ["b"], "time": "seconds", "outliers": []}
    # rows left out of the residuals keep their place (the runs' history)
    d4 = d.without_tips(np.array([True, False, False, False, False]))
    assert d4.rows == 5 and d4.dropouts == 4 and np.array_equal(d4.time, d.time) and np.isfinite(d.tip[0]).all()
    # without a time column: the step index, in steps
    d2 = _data(HEADER + "\na,0,0,0.34,0.5,0,0,0.0,0.32\na,1,0,0.34,0.5,0.01,0,,\n")
    assert d2.time_unit == "steps" and d2.time.tolist() == [0.0, 1.0] and d2.dropouts == 1
    # round trip through the writer: the time column and the empty cells come back
    d3 = _data(d.to_csv_text())
    np.testing.assert_allclose(d3.time, d.time)
    np.testing.assert_array_equal(d3.tracked, d.tracked)
    with pytest.raises(DataError, match=r"row 2 column 'tip_z': empty while tip_y has a value"):
        _data(HEADER + "\na,0,0,0.34,0.5,0,0,0.0,0.32\na,1,0,0.34,0.5,0.01,0,0.001,\n")
    with pytest.raises(DataError, match=r"row 2 column 'time': value 10.0 \(run 'a', step 2\) is not after the previous step's time 10.5 \(row 3\)"):
        _data("run,step,time,target_y,target_z,gain,q1,q2,tip_y,tip_z\n"
              "a,0,10.0,0,0.34,0.5,0,0,0.0,0.32\na,2,10.0,0,0.34,0.5,0,0,0.0,0.32\na,1,10.5,0,0.34,0.5,0,0,0.0,0.32\n")
    with pytest.raises(DataError, match=r"row 1 column 'time': value '' is not a number"):
        _data("run,step,time,target_y,target_z,gain,q1,q2,tip_y,tip_z\na,0,,0,0.34,0.5,0,0,0.0,0.32\n")


def test_cli_refuses_partial_tip_and_backward_time(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text(HEADER + "\na,0,0,0.34,0.5,0,0,0.0,0.32\na,1,0,0.34,0.5,0.01,0,,0.33\n")
    out = tmp_path / "c.json"
    assert main(["calibrate", str(PORT), str(bad), "--json", str(out)]) == 2
    assert "row 2 column 'tip_y': empty while tip_z has a value" in capsys.readouterr().err
    assert not out.exists()
    bad.write_text("run,step,time,target_y,target_z,gain,q1,q2,tip_y,tip_z\n"
                   "a,0,1.0,0,0.34,0.5,0,0,0.0,0.32\na,1,0.9,0,0.34,0.5,0,0,0.0,0.32\n")
    assert main(["calibrate", str(PORT), str(bad), "--json", str(out)]) == 2
    assert "column 'time'" in capsys.readouterr().err and not out.exists()


def test_delayed_is_linear_interpolation_in_time():
    """errplan.effects.delayed against np.interp per run and coordinate (runs of different lengths,
    uneven steps, tau beyond a run's first rows)."""
    rng = np.random.default_rng(3)
    run = np.repeat([0, 1, 2], [7, 3, 12])
    time = np.concatenate([np.cumsum(rng.uniform(0.5, 1.5, k)) + 50 * r for r, k in enumerate((7, 3, 12))])
    x = rng.normal(size=(len(run), 3))
    for tau in (0.3, 1.0, 2.7):
        got = delayed(x, time, run, tau)
        for r in range(3):
            m = run == r
            want = np.stack([np.interp(time[m] - tau, time[m], x[m, c]) for c in range(3)], axis=-1)
            np.testing.assert_allclose(got[m], want, rtol=0, atol=1e-12)
    # without times: the step index within the run
    got = delayed(x, None, run, 1.5)
    m = run == 2
    np.testing.assert_allclose(got[m], np.stack([np.interp(np.arange(12) - 1.5, np.arange(12), x[m, c])
                                                 for c in range(3)], axis=-1), atol=1e-12)
    with pytest.raises(ErrplanError, match="runs are needed"):
        delayed(x, time, None, 0.5)


def test_burst_mask_share_and_bursts():
    rng = np.random.default_rng(0)
    m = burst_mask(200_000, 0.03, 8, rng)
    assert abs(m.mean() - 0.03) < 0.003
    edges = np.flatnonzero(np.diff(np.r_[0, m.astype(int), 0]))
    lengths = edges[1::2] - edges[::2]
    assert lengths.max() > 8 and lengths.mean() > 3  # bursts (adjacent ones merge), never isolated rows only


# ----------------------------------------------------------------------------- the replay
@pytest.mark.parametrize("dt", [None, 0.02])
def test_replay_reproduces_a_late_tracker_with_dropouts(sc, dt):
    """A noise-free bench of the test's own plant (latency 1.6 steps, 10 % dropouts in bursts of up to
    5): errplan's replay of the declared model plus the latency, holding the last tracked tip at the
    data's dropouts, reproduces every tracked tip to 1e-9 m; without the latency it does not."""
    tau = 1.6 * (dt or 1.0)
    text = closed_form_bench(tau=tau, dt=dt, jitter=0.1, drop=0.1, burst=5, sigma=0.0, steps=20, seed=4,
                             starts=STARTS[:2])
    d = _data(text)
    assert d.dropouts > 10
    base = declared_plant(sc)
    ctrl = bench_controller(sc)
    pred, alive = replay(d, base.with_(tracker_latency=(tau,)), ctrl, motion_model(sc))
    assert alive.all()
    err = np.abs(pred - d.tip)[d.tracked]
    assert err.max() < 1e-9, err.max()
    pred0, _ = replay(d, base, ctrl, motion_model(sc))
    assert np.abs(pred0 - d.tip)[d.tracked].max() > 1e-3


def test_noise_free_latency_fit_is_exact_and_bounded(sc):
    """tracker_latency alone on noise-free rows of the test's plant (time column, jitter, dropouts):
    tau recovered to 1e-6 s; on rows without latency the fit stays at its bound 0."""
    from errplan.effects import EffectModel, catalogue

    base = declared_plant(sc)
    for tau in (0.027, 0.0):
        d = _data(closed_form_bench(tau=tau, dt=0.02, jitter=0.1, drop=0.05, sigma=0.0, steps=15, seed=6,
                                    starts=STARTS[:1]))
        e = catalogue(sc, ["tracker_latency"], data=d)[0]
        assert e.units == ("s",) and e.scales[0] == pytest.approx(0.02, rel=0.1)
        m = EffectModel([e]).fit(d.q, d.commanded_directions(motion_model(sc)), d.tip, base, run=d.run, time=d.time)
        assert m.values_[0] == pytest.approx(tau, abs=1e-6)
        assert 0.0 <= m.values_[0] <= 5 * d.time_step


# ----------------------------------------------------------------------------- calibration
def test_dropout_bench_keeps_its_answer(sc):
    """3 % burst dropouts on a port-offset bench: port_offset found as on the clean bench, the
    dropouts counted, tracker_latency not selected; the JSON's measured block."""
    truth = {"port": PORT_TRUE + [0.003, -0.002]}
    rep = _calibrate(sc, _data(closed_form_bench(drop=0.03, seed=1, **truth)))
    assert rep.selected == ["port_offset"]
    np.testing.assert_allclose(list(rep.parameters["port_offset"].values()), [0.003, -0.002], atol=2.5e-4)
    js = rep.to_json()
    m = js["measured"]
    assert m["dropouts"] > 0 and m["time"] == "steps" and m["outliers"] == [] and m["runs"] == 24
    assert m["dropouts"] == int(np.sum(~rep.data.tracked))
    assert math.isfinite(js["noise_floor"]) and math.isfinite(js["pose_rms_after"])
    assert js["noise_floor"] == pytest.approx(SIGMA, rel=0.15)
    # --predictions: a row for every row of the file, dropouts included, all finite
    from errplan.calibration.export import predictions_csv

    lines = predictions_csv(sc, rep, rep.data).splitlines()
    assert len(lines) == rep.data.rows + 1
    assert all(math.isfinite(float(v)) for line in lines[1:] for v in line.split(",")[2:])


def test_latency_in_steps_alone(sc):
    """Latency of 1.5 steps without a time column: tracker_latency alone, tau within 0.1 step."""
    rep = _calibrate(sc, _data(closed_form_bench(tau=1.5, drop=0.03, seed=2)))
    assert rep.selected == ["tracker_latency"]
    assert rep.parameters["tracker_latency"]["tau"] == pytest.approx(1.5, abs=0.1)
    assert rep.model.effects[0].units == ("steps",)


def test_latency_in_seconds_with_link_lengths(sc):
    """Latency of 30 ms at 20 ms steps jittered +-10 %, a time column, with link lengths 2 mm off:
    exactly link_length + tracker_latency, tau within max(10 %, 1 ms), the link lengths recovered."""
    truth = {"dl": (0.002, -0.0015)}
    rep = _calibrate(sc, _data(closed_form_bench(tau=0.030, dt=0.02, jitter=0.1, drop=0.03, seed=3, **truth)))
    assert sorted(rep.selected) == ["link_length", "tracker_latency"]
    assert rep.parameters["tracker_latency"]["tau"] == pytest.approx(0.030, abs=max(0.003, 0.001))
    np.testing.assert_allclose([rep.parameters["link_length"][k] for k in ("dl1", "dl2")], truth["dl"], atol=3e-4)
    assert rep.to_json()["measured"]["time"] == "seconds"


@pytest.mark.slow
@pytest.mark.parametrize("case", ["port_offset", "gravity_sag"])
def test_latency_combined_with_physics(sc, case):
    """Latency of 1 step (20 ms, time column, +-10 % jitter) beside a port offset or gravity sag."""
    truth = ({"port": PORT_TRUE + [0.003, -0.002]} if case == "port_offset"
             else {"sag": (0.004, 0.002, 0.003)})
    rep = _calibrate(sc, _data(closed_form_bench(tau=0.020, dt=0.02, jitter=0.1, drop=0.03, seed=5, **truth)))
    assert sorted(rep.selected) == sorted([case, "tracker_latency"])
    assert rep.parameters["tracker_latency"]["tau"] == pytest.approx(0.020, abs=max(0.002, 0.001))


# ----------------------------------------------------------------------------- errplan experiment
def _bench_scenario(tmp_path, sensors: str, effects: str = "", name="rec", sigma=0.0002) -> Path:
    text = PORT.read_text().replace('name = "beasley2004-port"', f'name = "{name}"', 1).split("[[query]]")[0]
    text = text.replace("tracker_sigma = 0.0002", f"tracker_sigma = {sigma!r}\n" + sensors, 1)
    p = tmp_path / f"{name}.toml"
    p.write_text(text + effects)
    return p


def test_experiment_writes_a_bench_as_recorded(tmp_path, sc):
    """[sensors] step_time/step_jitter/dropout_rate/dropout_burst/outlier_rate/outlier_size: a time
    column whose steps are 20 ms +- 10 %, dropouts, outliers 3-10 mm off the tracked tip (a noise-free
    tracker: every other row on the model); deterministic; bad keys refused."""
    p = _bench_scenario(tmp_path, "step_time = 0.02\nstep_jitter = 0.1\ndropout_rate = 0.05\ndropout_burst = 6\n"
                                  "outlier_rate = 0.03\noutlier_size = [0.003, 0.010]\n", sigma=0.0)
    truth = load_scenario(p)
    a = run_experiment(truth, seed=7, n_starts=2, max_steps=25).data
    b = run_experiment(truth, seed=7, n_starts=2, max_steps=25).data
    assert a.to_csv_text() == b.to_csv_text()
    assert a.time_unit == "seconds" and a.dropouts > 0
    dt = np.diff(a.time)[a.run[1:] == a.run[:-1]]
    assert dt.min() >= 0.018 - 1e-9 and dt.max() <= 0.022 + 1e-9 and dt.std() > 1e-4
    back = _data(a.to_csv_text())
    np.testing.assert_allclose(back.time, a.time, atol=1e-8)
    np.testing.assert_array_equal(back.tracked, a.tracked)
    from errplan.effects import predict_tracked

    x = predict_tracked(declared_plant(sc), a.q, a.commanded_directions(motion_model(sc)))
    off = np.linalg.norm(a.tip - x, axis=1)[a.tracked]
    out = off > 1e-9
    assert 0 < out.sum() < 0.08 * len(off)
    assert off[out].min() >= 0.003 - 1e-9 and off[out].max() <= 0.010 + 1e-9
    with pytest.raises(ErrplanError, match=r"\[sensors\] dropout_burst"):
        load_scenario(_bench_scenario(tmp_path, "dropout_rate = 0.03\ndropout_burst = 0\n", name="bad"))
    with pytest.raises(ErrplanError, match=r"\[effects.tracker_latency\] tau"):
        load_scenario(_bench_scenario(tmp_path, "step_time = 0.02\n", "\n[effects.tracker_latency]\ntau = 0.2\n",
                                      name="bad2"))


def test_experiment_latency_truth_matches_the_model(tmp_path, sc):
    """[effects.tracker_latency] in the truth of errplan experiment (seconds with step_time): the
    noise-free bench's tracked tips are the declared model's tips delayed by tau (fit-side
    prediction), and its replay reproduces them."""
    p = _bench_scenario(tmp_path, "step_time = 0.02\nstep_jitter = 0.1\ndropout_rate = 0.05\ndropout_burst = 4\n",
                        "\n[effects.tracker_latency]\ntau = 0.03\n", name="lat", sigma=0.0)
    truth = load_scenario(p)
    d = run_experiment(truth, seed=1, n_starts=2, max_steps=25).data
    from errplan.effects import predict_tracked

    plant = declared_plant(sc).with_(tracker_latency=(0.03,))
    u = d.commanded_directions(motion_model(sc))
    x = predict_tracked(plant, d.q, u, d.run, d.time)
    assert np.abs(x - d.tip)[d.tracked].max() < 1e-9
    pred, _ = replay(d, plant, bench_controller(sc), motion_model(sc))
    assert np.abs(pred - d.tip)[d.tracked].max() < 1e-9


# ----------------------------------------------------------------------------- 3-D: a pinocchio plant
UR5 = ROOT / "scenarios" / "ur5_port.toml"
#: encoder angles of three UR5 starts (shoulder pan, shoulder lift, elbow) inside the port's reach
UR5_STARTS = [np.array([-1.40441421306, -0.804477296758, 1.22235537425]),
              np.array([-1.52785812581, -0.980718245, 1.735563453])]


def pinocchio_bench(sc, *, tau, dt, port_offset, steps=22, seed=0, drop=0.03) -> str:
    """A 3-D bench of the UR5 computed with pinocchio (not errplan): the wrist is the origin of the
    scenario's wrist link (the other joints at 0), placed by base_rpy (R = Rz Ry Rx); the shaft is the
    lever through the true port (``port.position`` + ``port_offset``); the controller's Jacobian is a
    central difference of the lever through the port estimate; the tracker is ``tau`` late
    (``np.interp`` in time) and drops out in bursts."""
    import pinocchio as pin

    model = pin.buildModelFromUrdf(str(sc.robot.urdf))
    pdata = model.createData()
    fid = model.getFrameId(sc.robot.wrist)
    iq = [model.joints[model.getJointId(j)].idx_q for j in sc.robot.joints]
    r, p_, y = sc.robot.base_rpy
    rot = (pin.rpy.rpyToMatrix(r, p_, y))
    base = np.asarray(sc.robot.base_position, float)
    port = np.asarray(sc.port.position, float) + port_offset
    est = np.asarray(sc.port.estimate, float)
    L = sc.instrument.length

    def wrist(q):
        qf = pin.neutral(model)
        qf[iq] = q
        pin.framesForwardKinematics(model, pdata, qf)
        return base + rot @ pdata.oMf[fid].translation

    def tip(q, p=port):
        w = wrist(q)
        e = p - w
        return w + L * e / np.linalg.norm(e)

    def jhat(q, h=1e-7):
        return np.stack([(tip(q + h * np.eye(3)[j], est) - tip(q - h * np.eye(3)[j], est)) / (2 * h)
                         for j in range(3)], axis=-1)

    rng = np.random.default_rng(seed)
    offs = 0.020 * np.vstack([np.eye(3), -np.eye(3)])
    lines = ["run,step,time,target_x,target_y,target_z,gain,q1,q2,q3,tip_x,tip_y,tip_z"]
    clock, gain = 3.0, 0.5
    for si, q0 in enumerate(UR5_STARTS):
        x0 = tip(q0)
        for ti, off in enumerate(offs):
            target, q, held, times, tips, t = x0 + off, q0.copy(), None, [], [], clock
            lost = burst_mask(steps + 1, drop, 6, rng)
            for k in range(steps + 1):
                if k:
                    t += dt * (1 + rng.uniform(-0.1, 0.1))
                times.append(t)
                tips.append(tip(q))
                x = np.array([np.interp(t - tau, times, [v[c] for v in tips]) for c in range(3)])
                x = x + rng.normal(0.0, SIGMA, 3)
                cells = ",," if lost[k] else ",".join(f"{v:.17g}" for v in x)
                lines.append(f"{si}-{ti},{k},{t:.17g}," + ",".join(f"{v:.17g}" for v in target)
                             + f",{gain}," + ",".join(f"{v:.17g}" for v in q) + "," + cells)
                if not lost[k]:
                    held = x
                if held is not None:
                    q = q + gain * np.linalg.solve(jhat(q), target - held)
            clock = t + 1.0
    return "\n".join(lines) + "\n"


@pytest.mark.slow
def test_spatial_latency_with_a_port_offset_on_a_pinocchio_plant():
    """UR5 (pinocchio plant): a 35 ms late tracker at 20 ms steps (+-10 %) and a port 3 mm off:
    exactly port_offset + tracker_latency, tau within max(10 %, 1 ms), the offset within 0.3 mm."""
    pytest.importorskip("pinocchio")
    sc = load_scenario(UR5)
    off = np.array([0.003, -0.002, 0.0015])
    d = parse_measured_csv(pinocchio_bench(sc, tau=0.035, dt=0.02, port_offset=off), "ur5.csv", dim=3, n_joints=3)
    assert d.dropouts > 0
    rep = calibrate(sc, d, seed=0, folds=3, effects=["port_offset", "tracker_offset", "tracker_latency", "port_friction"])
    assert sorted(rep.selected) == ["port_offset", "tracker_latency"]
    assert rep.parameters["tracker_latency"]["tau"] == pytest.approx(0.035, abs=0.0035)
    np.testing.assert_allclose([rep.parameters["port_offset"][k] for k in ("dx", "dy", "dz")], off, atol=3e-4)


def test_runs_without_tracked_data_are_named_and_left_out():
    """A run with fewer than 2 tracked rows adds nothing to a fit: left out with a sentence naming it;
    a file with no usable run is one error."""
    from errplan.calibration.driver import _without_thin_runs

    text = (HEADER + "\na,0,0,0.34,0.5,0,0,0.0,0.32\na,1,0,0.34,0.5,0.01,0,0.001,0.33\n"
            "b,0,0,0.36,0.5,0,0,,\nb,1,0,0.36,0.5,0.01,0,0.002,0.331\nb,2,0,0.36,0.5,0.02,0,,\n")
    d = _data(text)
    kept, notes = _without_thin_runs(d)
    assert kept.run_ids == ["a"] and len(notes) == 1 and "run 'b' left out: 1 tracked row(s) of 3" in notes[0]
    with pytest.raises(DataError, match="no run has 2 rows with a tracked tip"):
        _without_thin_runs(d.subset([1]))


def test_experiment_latency_truth_in_3d(tmp_path):
    """The same in 3-D (UR5, latency in steps, dropouts): the bench's tracked tips are the declared
    model's delayed by tau, and the replay reproduces them."""
    text = UR5.read_text().split("[[query]]")[0].replace("tracker_sigma = 0.0002",
                                                        "tracker_sigma = 0.0\ndropout_rate = 0.05\ndropout_burst = 3")
    p = tmp_path / "ur5_lat.toml"
    p.write_text(text + "\n[effects.tracker_latency]\ntau = 1.3\n")
    truth = load_scenario(p)
    sc = load_scenario(UR5)
    d = run_experiment(truth, seed=2, starts=[[0.0, 0.0, 0.415]], max_steps=15).data
    assert d.time_unit == "steps" and d.dim == 3
    from errplan.effects import predict_tracked

    plant = declared_plant(sc).with_(tracker_latency=(1.3,))
    x = predict_tracked(plant, d.q, d.commanded_directions(motion_model(sc)), d.run, d.time)
    assert np.abs(x - d.tip)[d.tracked].max() < 1e-9
    pred, _ = replay(d, plant, bench_controller(sc), motion_model(sc))
    assert np.abs(pred - d.tip)[d.tracked].max() < 1e-9
