"""Spatial (3-D) gains, simulation and recording end to end, on the bundled PHANToM 1.5
(scenarios/phantom15_spatial.toml) and on a real arm nobody here described, example-robot-data's UR5
(tests/arms.py; issue 22's setup, where the direct move of ``rise`` crosses a singular controller Jacobian).

Every number is checked against something written here and independent of errplan's own code paths:

- certificates: random tips of every certified ball and random instances of the error set (any load
  direction normal to the port->tip line), the true Jacobian by central differences of the shaft model,
  the controller's lever Jacobian written out, numpy's SVD;
- corner replays: a quasi-static controller loop on a pinocchio model built here from the URDF (its own
  forward kinematics and frame Jacobian, the base placement and held joints applied by hand), under
  every corner of the 3-D port box: every run converges and the distance to the active target never
  grows, in as many steps as errplan.simulation takes;
- recordings: ``rerun rrd verify``, and read back with ``rerun.chunk.RrdReader``: the robot's URDF
  geometry, one joint transform per replayed state whose composition (static URDF transforms + joint
  rows + placement) puts the wrist where the simulation had it, the field slices and surfaces, the
  paths, trajectories and time series of every query;
- bad input: an endpoint outside the robust workspace, or where no gain can certify, is one error
  naming the query and the value.
"""
from __future__ import annotations

import re

import math
import os
import shutil
import subprocess
import sys
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest

from errplan.cli import main
from errplan.errors import InfeasibleError
from errplan.fields import compute_fields
from errplan.kinematics import arm_for
from errplan.kinematics.shaft import flexed_tip, flexed_wrist_plane
from errplan.pipeline import run_pipeline
from errplan.planning import plan_scenario
from errplan.recording import entity_names, level_surface, slice_mesh, turbo
from errplan.api import load_scenario

from arms import needs_omni, ur5_scenario
from test_fields_spatial import omni_scenario
from errplan.models import build_arm

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = ROOT / "scenarios" / "phantom15_spatial.toml"
METRICS = ("G_norm", "phi_hat_max", "rho_star")
S_KEYS = {"from", "to", "gain", "certified_G_norm"}
R_KEYS = {"steps", "final_error", "max_deviation", "max_phi", "monotonic"}
P_KEYS = {"path", "cost", "length", "max_G_norm", "max_phi_hat_max"}

UR5_QUERIES = """
[[query]]
name = "rise"                              # issue 22: the direct move crosses a singular controller Jacobian
start = [0.15, -0.05, 0.72]
goal = [0.05, 0.2, 0.75]

[[query]]
name = "across"
start = [0.0, 0.0, 0.70]
goal = [0.2, 0.1, 0.8]
"""
UR5_OUTSIDE = [-0.048, -0.096, 0.688]  # a grid tip of the task region outside the UR5's robust workspace
OMNI_QUERIES = """
[[query]]
name = "omni-across"                       # crosses the port axis
start = [-0.05, 0.05, 0.38]
goal = [0.05, 0.05, 0.38]
"""


def _run(sc, res, path):
    mf = compute_fields(sc, res, metrics=METRICS)
    plan = plan_scenario(sc, mf)
    out = run_pipeline(sc, plan.queries, mf, record=str(path))
    return sc, mf, out, path


@pytest.fixture(scope="module")
def phantom_run(tmp_path_factory):
    return _run(load_scenario(PHANTOM), 0.012, tmp_path_factory.mktemp("ph") / "phantom.rrd")


@pytest.fixture(scope="module")
def ur5_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("ur5")
    return _run(load_scenario(ur5_scenario(d, UR5_QUERIES)), 0.008, d / "ur5.rrd")


@pytest.fixture(params=["phantom", "ur5"])
def run(request):
    return request.getfixturevalue(f"{request.param}_run")


# ----------------------------------------------------------------------------- an independent arm
def _rpy(r, p, y):
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return (np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
            @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]]))


class PinArm:
    """The scenario's arm straight from pinocchio: wrist frame position and Jacobian in the world (base
    placement applied here), held joints at their values, the scenario's limits."""

    def __init__(self, sc):
        import pinocchio as pin

        r = sc.robot
        self.pin = pin
        self.model = pin.buildModelFromUrdf(r.urdf)
        self.data = self.model.createData()
        self.fid = self.model.getFrameId(r.wrist)
        self.R = _rpy(*r.base_rpy)
        self.p = np.asarray(r.base_position, float)
        self.q = pin.neutral(self.model)
        for name, val in dict(r.fixed_joints or ()).items():
            self.q[self.model.joints[self.model.getJointId(name)].idx_q] = val
        self.idx, self.vidx = [], []
        lims = []
        for name in r.joints:
            j = self.model.joints[self.model.getJointId(name)]
            assert j.nq == 1
            self.idx.append(j.idx_q)
            self.vidx.append(j.idx_v)
            lims.append((self.model.lowerPositionLimit[j.idx_q], self.model.upperPositionLimit[j.idx_q]))
        self.limits = np.array(r.joint_limits if r.joint_limits else lims, float)
        self.coupled = [(np.array([list(r.joints).index(n) for n in c.joints]), np.array(c.coeffs), c.lo, c.hi)
                        for c in (r.coupled_limits or ())]

    def _full(self, q3):
        q = self.q.copy()
        q[self.idx] = q3
        return q

    def fk(self, q3):
        self.pin.framesForwardKinematics(self.model, self.data, self._full(q3))
        return self.p + self.R @ self.data.oMf[self.fid].translation

    def jac(self, q3):
        q = self._full(q3)
        self.pin.computeJointJacobians(self.model, self.data, q)
        self.pin.framesForwardKinematics(self.model, self.data, q)
        J = self.pin.getFrameJacobian(self.model, self.data, self.fid, self.pin.LOCAL_WORLD_ALIGNED)[:3]
        return self.R @ J[:, self.vidx]

    def within(self, q3, tol=1e-12):
        ok = np.all((q3 >= self.limits[:, 0] - tol) & (q3 <= self.limits[:, 1] + tol))
        for idx, c, lo, hi in self.coupled:
            v = float(c @ q3[idx])
            ok = ok and lo - tol <= v <= hi + tol
        return bool(ok)


def _replay(sc, parm, port, start, waypoints, gains, tol_switch, tol_final, max_steps=20000):
    """Quasi-static controller loop (P1 eq. 1-5) on the pinocchio arm: straight shaft through the true
    ``port``, the controller's lever through the estimate. Returns (ok, steps, reason)."""
    L = sc.instrument.length
    est = np.asarray(sc.port.estimate, float)
    arm = arm_for(sc.robot)
    x = np.asarray(start, float)
    w = x - L * (x - port) / np.linalg.norm(x - port)
    q, ok = arm.inverse(w)
    assert ok and np.allclose(parm.fk(q), w, atol=1e-9)
    steps = 0
    for i, (b, k) in enumerate(zip(waypoints, gains)):
        tol = tol_final if i == len(waypoints) - 1 else tol_switch
        e_prev = np.linalg.norm(b - x)
        while np.linalg.norm(b - x) >= tol:
            w = parm.fk(q)
            d = est - w
            r = np.linalg.norm(d)
            Jh = (np.eye(3) - (L / r) * (np.eye(3) - np.outer(d, d) / r ** 2)) @ parm.jac(q)
            q = q + k * np.linalg.solve(Jh, b - x)
            if not parm.within(q):
                return False, steps, "left the joint limits"
            w = parm.fk(q)
            x = w + L * (port - w) / np.linalg.norm(port - w)
            e = np.linalg.norm(b - x)
            steps += 1
            if e > e_prev * (1 + 1e-9) + 1e-12:
                return False, steps, f"error grew {e_prev} -> {e}"
            e_prev = e
            if steps > max_steps:
                return False, steps, "max steps"
    return True, steps, ""


# ----------------------------------------------------------------------------- certificates
def test_every_planned_segment_is_certified(run):
    sc, mf, out, _ = run
    assert len(out["queries"]) >= 2
    for q, r in zip(out["queries"], out["runs"]):
        assert {"name", "start", "goal", "planned", "direct", "gains", "simulation"} <= set(q)
        assert P_KEYS <= set(q["planned"]) and P_KEYS <= set(q["direct"])
        assert R_KEYS <= set(q["simulation"]["planned"]) and R_KEYS <= set(q["simulation"]["direct"])
        assert q["gains"] and all(S_KEYS <= set(s) for s in q["gains"])
        for s in q["gains"]:
            assert s["certified"] and s["certified_G_norm"] < 1 and s["step_ratio"] < 1, (q["name"], s)
            assert len(s["from"]) == 3 and len(s["to"]) == 3
        assert q["gains"][0]["from"] == pytest.approx(q["planned"]["path"][0])
        assert q["gains"][-1]["to"] == pytest.approx(q["planned"]["path"][-1])
        for a, b in zip(q["gains"][:-1], q["gains"][1:]):
            assert a["to"] == pytest.approx(b["from"])
        # the verification is denser than the optimiser, and refinement only raises the grid's worst case
        for s in r.schedule.segments:
            o, v = s.samples["optimiser"], s.samples["verification"]
            assert v["tips"] > 2 * o["tips"] and v["instances"] > 3 * o["instances"]
            assert v["grid_G_norm"] <= s.certified_G_norm + 1e-12
        sim = q["simulation"]
        assert sim["planned"]["monotonic"] and sim["planned"]["converged"] and sim["planned"]["final_error"] < 1e-5


def _random_ball(rng, c, R, n):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    return c + v * (R * np.cbrt(rng.uniform(0, 1, n)))[:, None]


def test_certificates_bound_an_independent_random_sample(run):
    """Random tips in each certified ball, random instances (port in the box, load magnitude in its range
    in a random direction normal to the port->tip line): the SVD norm of I - k J Jhat^-1 never exceeds the
    certified value by more than 1e-3 (a sample, not a bound)."""
    sc, _, out, _ = run
    es = build_arm(sc).errors
    arm = arm_for(sc.robot)
    L = sc.instrument.length
    est = np.asarray(sc.port.estimate, float)
    rng = np.random.default_rng(2024)
    segs = [s for r in out["runs"] for s in r.schedule.segments]
    worst_excess, checked = -1.0, 0
    for s in segs[:: max(1, len(segs) // 12)]:
        n = 600
        x = _random_ball(rng, s.end, s.radius, n)
        off = rng.uniform(es.lo_arr[:3], es.hi_arr[:3], (n, 3))
        p = np.asarray(es.base_port) + off
        tau = rng.uniform(es.lo[3], es.hi[3], n)
        e1 = (x - p) / np.linalg.norm(x - p, axis=-1, keepdims=True)
        e2 = rng.normal(size=(n, 3))
        e2 -= np.sum(e2 * e1, axis=-1, keepdims=True) * e1
        e2 /= np.linalg.norm(e2, axis=-1, keepdims=True)
        w, t = flexed_wrist_plane(x, p, L, tau, e2)
        r = np.linalg.norm(x - p, axis=-1)
        reach = (r < L) & (np.linalg.norm(p - w, axis=-1) < L) & arm.reachable(w)
        h = 1e-6
        J = np.stack([(flexed_tip(w + h * ev, p, L, t) - flexed_tip(w - h * ev, p, L, t)) / (2 * h)
                      for ev in np.eye(3)], axis=-1)
        d = est - w
        rho = np.linalg.norm(d, axis=-1)
        P = np.eye(3) - d[:, :, None] * d[:, None, :] / rho[:, None, None] ** 2
        Jh = np.eye(3) - (L / rho)[:, None, None] * P
        G = np.eye(3) - s.gain * J @ np.linalg.inv(Jh)
        g = np.linalg.norm(G, ord=2, axis=(-2, -1))[reach]
        assert reach.mean() > 0.5
        worst_excess = max(worst_excess, float(g.max() - s.certified_G_norm))
        checked += 1
    assert checked >= 5
    assert worst_excess < 1e-3, worst_excess


def test_corner_replays_converge_monotonically_on_an_independent_arm(run):
    """Every planned path with its gains under every corner of the 3-D port box, replayed on pinocchio
    (FK, frame Jacobian) with the loop above: converges, never moves away from the active target, in
    the number of steps errplan.simulation took (its corner replays)."""
    sc, _, out, _ = run
    parm = PinArm(sc)
    es = build_arm(sc).errors
    corners = es.port_corners()
    assert len(corners) == 8
    opts = out["runs"][0].schedule.options
    for r in out["runs"]:
        sched = r.schedule
        assert len(r.corner_planned) == 8
        for port, rep in zip(corners, r.corner_planned):
            ok, steps, why = _replay(sc, parm, port, r.planned_path[0], sched.waypoints, sched.gains,
                                     opts.switch_tolerance, opts.tolerance)
            assert ok, (sc.name, r.name, port.tolist(), steps, why)
            assert rep.sim.monotonic and rep.sim.converged
            assert abs(rep.sim.steps - steps) <= 1, (r.name, rep.sim.steps, steps)
        sim = r.simulation_json()["corners"]
        assert sim["planned_all_monotonic"] and sim["planned_all_converged"]
        assert len(sim["instances"][0]["port_offset"]) == 3


def test_the_truth_replay_matches_the_independent_loop(run):
    sc, _, out, _ = run
    parm = PinArm(sc)
    opts = out["runs"][0].schedule.options
    for r in out["runs"]:
        ok, steps, why = _replay(sc, parm, np.asarray(sc.port.position, float), r.planned_path[0],
                                 r.schedule.waypoints, r.schedule.gains, opts.switch_tolerance, opts.tolerance)
        assert ok, why
        assert abs(r.sim_planned.sim.steps - steps) <= 1


def test_long_direct_moves_are_not_certified(phantom_run):
    """The bundled queries' direct moves (150-185 mm, one segment) have no certifying gain; at the
    scenario gain they grow the error under some corner of the port box."""
    _, _, out, _ = phantom_run
    for q in out["queries"]:
        s = q["direct_gains"][0]
        assert not s["certified"]
        assert q["simulation"]["direct_gain_source"] == "scenario"
    assert any(not q["simulation"]["corners"]["direct_all_monotonic"] for q in out["queries"])


# ----------------------------------------------------------------------------- bad input
def test_endpoint_outside_the_robust_workspace_is_one_clear_error(ur5_run):
    sc, mf, _, _ = ur5_run
    bad, goal = UR5_OUTSIDE, [0.05, 0.2, 0.75]
    i = tuple(int(np.argmin(np.abs(a - v))) for a, v in zip(mf.axes, bad))
    assert not mf.valid[i] and np.allclose([a[j] for a, j in zip(mf.axes, i)], bad)
    q = {"name": "outside", "start": bad, "goal": goal, "planned": {"path": [bad, goal]}, "direct": {"path": [bad, goal]}}
    with pytest.raises(InfeasibleError, match=r"query 'outside': start \[-0\.048, -0\.096, 0\.688\] is outside "
                                              r"the robust workspace"):
        run_pipeline(sc, [q], mf)


def test_endpoint_where_no_gain_certifies_is_one_clear_error(phantom_run):
    sc, mf, _, _ = phantom_run
    i = np.argwhere(mf.valid & (mf.rho_star >= 0.999))
    assert len(i)
    goal = [float(mf.x[i[0][0]]), float(mf.y[i[0][1]]), float(mf.z[i[0][2]])]
    start = [0.0, 0.0, 0.36]
    q = {"name": "deep", "start": start, "goal": goal, "planned": {"path": [start, goal]}}
    with pytest.raises(InfeasibleError, match=r"query 'deep': goal \[.*\]: no gain can certify convergence there "
                                              r"\(rho\* = 1\.0000 > 1 - certify_margin = 0\.98\)"):
        run_pipeline(sc, [q], mf)


def test_cli_plan_refuses_a_bad_spatial_query(tmp_path, capsys):
    p = ur5_scenario(tmp_path, UR5_QUERIES.replace("start = [0.0, 0.0, 0.70]", f"start = {UR5_OUTSIDE}"))
    rec, js = tmp_path / "x.rrd", tmp_path / "x.json"
    assert main(["plan", str(p), "--record", str(rec), "--json", str(js)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "across" in err and "-0.096" in err
    assert not rec.exists() and not js.exists()


def test_a_direct_move_through_a_singularity_is_data_not_a_failure(tmp_path, capsys):
    """Issue 22 as a user ran it: the UR5 scenario's JSON is written (exit 0); the planned path certifies
    and replays as in the table; the direct move is reported not certified with its reason, in the
    table and in the JSON, where its unbounded ||G|| is null and named under ``non_finite``."""
    import json

    p = ur5_scenario(tmp_path, UR5_QUERIES.split("[[query]]\nname = \"across\"")[0])
    js = tmp_path / "plan.json"
    assert main(["plan", str(p), "--json", str(js)]) == 0
    out = capsys.readouterr().out
    assert "rise direct: 1 of 1 segment(s) not certified: the controller's Jacobian is singular" in out
    q = json.loads(js.read_text())["queries"][0]
    assert q["name"] == "rise"
    assert q["gains"] and all(g["certified"] and g["certified_G_norm"] < 1 for g in q["gains"])
    assert q["simulation"]["planned"]["monotonic"] is True
    assert q["simulation"]["corners"]["planned_all_monotonic"] is True
    d = q["direct_gains"][0]
    assert d["certified"] is False and d["certified_G_norm"] is None and "singular" in d["reason"]
    text = js.read_text()
    assert "Infinity" not in text and "NaN" not in text
    notes = []

    def walk(o):
        if isinstance(o, dict):
            if "non_finite" in o:
                notes.append(o["non_finite"])
                assert all(o[k] is None for k in o["non_finite"] if "[" not in k)
            for v in o.values():
                walk(v)
        elif isinstance(o, list):
            for v in o:
                walk(v)

    walk(q["direct_gains"])
    assert any(v == "inf" for n in notes for v in n.values())


# ----------------------------------------------------------------------------- recordings
def _rerun_cmd():
    exe = shutil.which("rerun")
    return [exe] if exe else [sys.executable, "-m", "rerun_cli"]


def _read(path):
    import rerun.chunk as rrc

    rows, batches = Counter(), defaultdict(list)
    for c in rrc.RrdReader(path).stream().to_chunks():
        rows[c.entity_path] += c.num_rows
        batches[c.entity_path].append(c.to_record_batch())
    return rows, batches


def test_recording_verifies_and_reads_back(run):
    sc, mf, out, path = run
    p = subprocess.run(_rerun_cmd() + ["rrd", "verify", str(path)], env=dict(os.environ, CI="1"),
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    rows, batches = _read(path)
    runs = out["runs"]
    states = sum(len(r.sim_planned.sim.q) + len(r.sim_direct.sim.q) for r in runs)
    # the robot: URDF geometry, joints per replayed state, the links as lines, the instrument
    arm = arm_for(sc.robot)
    geom = [e for e in rows if "/visual_geometries/" in e and e.startswith("/world/")]
    assert len(geom) >= 4
    for j in arm.joint_names:
        assert rows[f"/world/robot/joints/{j}"] == states
    for e in ("/world/robot/links", "/world/robot/shaft", "/world/robot/tip"):
        assert rows[e] == states
    assert rows["/world/robot/placement"] == 1 and rows["/tf_static"] >= 3
    # the fields: three slices of ||G|| and rho*, the ||G|| = 1 surface where the field crosses 1
    for n in ("G_norm", "rho_star"):
        for a in "xyz":
            assert rows[f"/world/fields/{n}/{a}"] == 1, (n, a)
    if np.nanmax(mf.G_norm) > 1 > np.nanmin(mf.G_norm):
        assert rows["/world/fields/surface/G_norm_1"] == 1
    for e in ("/world/port/true", "/world/port/estimate", "/world/port/error_box", "/summary"):
        assert rows[e] == 1, e
    # paths, trajectories and series per query
    for r, q in zip(runs, entity_names(runs)):
        for e in ("planned", "direct", "segments", "corners/planned", "corners/direct"):
            assert rows[f"/world/{q}/{e}"] == 1, (q, e)
        for kind, rep in (("planned", r.sim_planned), ("direct", r.sim_direct)):
            n = rep.sim.steps + 1
            assert rows[f"/world/{q}/sim/{kind}/tip"] == n
            assert rows[f"/world/{q}/sim/{kind}/trajectory"] == 1
            assert rows[f"/series/{q}/{kind}/error"] == n + 1
            assert rows[f"/series/{q}/{kind}/phi"] == n + 1
        assert rows[f"/gains/{q}/gain"] == len(r.schedule.segments) + 1
    import rerun.chunk as rrc

    assert rrc.RrdReader(path).blueprints()


def _quat(xyzw):
    x, y, z, w = xyzw
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_recorded_robot_puts_the_wrist_where_the_simulation_had_it(run):
    """Compose the recording's transforms (static URDF joints from /tf_static, the animated joints at a
    replay state, the placement of the URDF root in the world) from the wrist link's frame to the world:
    the wrist is where the simulated run had it (arm.forward of the true link angles), to float32."""
    sc, _, out, path = run
    _, batches = _read(path)
    edges = {}
    for rb in batches["/tf_static"]:
        for ch, pa, qu, tr in zip(*(rb.column(f"Transform3D:{n}").to_pylist()
                                    for n in ("child_frame", "parent_frame", "quaternion", "translation"))):
            edges[ch[0]] = (pa[0], _quat(qu[0]), np.array(tr[0]))
    (rb,) = batches["/world/robot/placement"]
    m = np.array(rb.column("Transform3D:mat3x3").to_pylist()[0][0]).reshape(3, 3).T  # column-major
    root_edge = (rb.column("Transform3D:parent_frame").to_pylist()[0][0], m,
                 np.array(rb.column("Transform3D:translation").to_pylist()[0][0]))
    edges[rb.column("Transform3D:child_frame").to_pylist()[0][0]] = root_edge
    arm = arm_for(sc.robot)
    animated = {}
    for j in arm.joint_names:
        rows = {}
        for rb in batches[f"/world/robot/joints/{j}"]:
            for t, ch, pa, qu, tr in zip(rb.column("replay").to_pylist(),
                                         *(rb.column(f"Transform3D:{n}").to_pylist()
                                           for n in ("child_frame", "parent_frame", "quaternion", "translation"))):
                rows[t] = (ch[0], (pa[0], _quat(qu[0]), np.array(tr[0])))
        animated[j] = rows
    from errplan.kinematics.truth import Plant

    truth = Plant.from_model(build_arm(sc))
    offset = 0
    checked = 0
    for r in out["runs"]:
        for rep in (r.sim_direct, r.sim_planned):
            qa = truth.link_angles_q(rep.sim.q)
            for i in sorted({0, len(qa) // 2, len(qa) - 1}):
                e = dict(edges)
                for j in arm.joint_names:
                    ch, edge = animated[j][offset + i]
                    e[ch] = edge
                frame, R, p = f"robot/{sc.robot.wrist}", np.eye(3), np.zeros(3)
                while frame in e:
                    parent, Rp, tp = e[frame]
                    R, p = Rp @ R, Rp @ p + tp
                    frame = parent
                assert frame == "tf#/world"
                assert np.allclose(p, arm.forward(qa[i]), atol=2e-6), (r.name, i)
                checked += 1
            offset += len(qa)
    assert checked >= 6


@pytest.fixture(scope="module")
def omni_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("omni")
    return _run(load_scenario(omni_scenario(d, extra=OMNI_QUERIES)), 0.01, d / "omni.rrd")


@needs_omni
def test_omni_meshes_resolve_and_missing_meshes_fall_back_to_lines(omni_run, tmp_path):
    """The Omni's seven STL meshes resolve through package_path and are in the recording; with a URDF
    whose meshes cannot be found the links are drawn as lines and the summary says so."""
    sc, mf, out, path = omni_run
    _, batches = _read(path)
    blobs = sum(1 for e, bs in batches.items() for rb in bs if "Asset3D:blob" in rb.schema.names)
    assert blobs == 7
    text = batches["/summary"][0].column("TextDocument:text").to_pylist()[0][0]
    assert "7/7 mesh files resolved" in text
    # the same robot with its meshes out of reach
    urdf = Path(sc.robot.urdf).read_text().replace("package://omni_description/meshes/", "package://nowhere/")
    (tmp_path / "omni_nomesh.urdf").write_text(urdf)
    # the scenario with its urdf line pointing at the copy (paths compared as written: a symlinked
    # folder of the description must not matter)
    p = re.sub(r'^urdf = ".*"$', f'urdf = "{tmp_path / "omni_nomesh.urdf"}"', omni_scenario(tmp_path).read_text(),
               count=1, flags=re.M)
    assert "omni_nomesh.urdf" in p
    (tmp_path / "nomesh.toml").write_text(p)
    sc2 = load_scenario(tmp_path / "nomesh.toml")
    a, b = [-0.05, 0.05, 0.38], [-0.03, 0.05, 0.38]
    res = run_pipeline(sc2, [{"name": "hop", "start": a, "goal": b, "planned": {"path": [a, b]}}], mf,
                       record=str(tmp_path / "nomesh.rrd"), corners=False)
    assert res["queries"][0]["gains"][0]["certified"]
    rows, batches = _read(tmp_path / "nomesh.rrd")
    assert not any("Asset3D:blob" in rb.schema.names for bs in batches.values() for rb in bs)
    assert rows["/world/robot/links"] == len(res["runs"][0].sim_planned.sim.q) + len(res["runs"][0].sim_direct.sim.q)
    text = batches["/summary"][0].column("TextDocument:text").to_pylist()[0][0]
    assert "0/7 mesh files resolved" in text and "links drawn as lines" in text


def test_slices_and_surfaces_are_placed_in_metres(phantom_run):
    """slice_mesh puts every vertex on the grid plane and colours it with the field's value; the marching-
    cubes surface of ||G|| = 1 lies where trilinear interpolation of the field gives 1 (scipy)."""
    from scipy.interpolate import RegularGridInterpolator

    _, mf, _, _ = phantom_run
    P, T, C = slice_mesh(mf, "G_norm", 2, 5)
    assert np.allclose(P[:, 2], mf.z[5]) and len(T)
    xi = np.abs(P[:, 0, None] - mf.x[None]).argmin(axis=1)
    yi = np.abs(P[:, 1, None] - mf.y[None]).argmin(axis=1)
    assert np.allclose(P[:, 0], mf.x[xi]) and np.allclose(P[:, 1], mf.y[yi])
    used = np.unique(T)
    vals = mf.G_norm[xi[used], yi[used], 5]
    assert np.all(mf.valid[xi[used], yi[used], 5])
    assert np.abs(C[used].astype(int) - turbo(vals / 1.2).astype(int)).max() <= 1  # (rounding to uint8)
    V, F, N = level_surface(mf, "G_norm", 1.0)
    f = RegularGridInterpolator((mf.x, mf.y, mf.z), np.where(mf.valid, mf.G_norm, np.nan))
    lo, hi = [a[0] for a in mf.axes], [a[-1] for a in mf.axes]
    assert np.all(V >= np.array(lo) - 1e-9) and np.all(V <= np.array(hi) + 1e-9)
    g = f(np.clip(V, lo, hi))
    # (NaN where the interpolation cell touches a tip outside the workspace: the vertex itself lies on a
    # grid edge between two workspace tips)
    assert np.nanmax(np.abs(g - 1.0)) < 1e-6 and np.isfinite(g).mean() > 0.5
    assert level_surface(mf, "G_norm", 100.0) is None
