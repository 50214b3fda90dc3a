"""The truth's geometry reaches the fields and the gain certificates (docs/physics.md "From measured data to
the plan"): ``link_length``, ``joint_geometry``, ``instrument_length`` and ``tracker_registration``.

Every field is checked against an independent reference written here: the planar arm in closed form
(its own forward kinematics, inverse kinematics and Jacobians), URDF arms through pinocchio on a URDF whose
joint origins were edited as the ``joint_geometry`` parametrization says (an IK solve with scipy on that
model puts the true tip at ``x``; the declared URDF gives the controller's ``Jhat`` at the same encoder
angles), and ``G = I - k R J Jhat^-1`` with ``R`` from scipy's rotation vectors. The error sets are single
instances (no uncertainty), so the field at a tip is the reference's ``||G||`` there. The certificate
checks: a segment the declared model certifies is not certified on a truth where it diverges (and the
simulation on that truth shows it), and every certified segment of a plan on a geometric truth replays
monotonic on it.
"""
from __future__ import annotations

import math
import sys
import xml.etree.ElementTree as ET
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from errplan.api import load_scenario
from errplan.errorset import uncovered_effects
from errplan.fields import compute_fields
from errplan.models import arm_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
from arms import arm_scenario  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PLANAR = ROOT / "scenarios" / "beasley2004_port.toml"
PHANTOM = ROOT / "scenarios" / "phantom15_spatial.toml"

# ----------------------------------------------------------------------------- planar reference
H1, H2 = 0.0, -math.pi / 2
BASE = np.array([0.210, -0.210])
LIM = np.array([[-1.9, 1.2], [-0.7, 1.0]])
SUM = (-0.3, 2.8)


def _dir(a):
    return np.array([math.sin(a), math.cos(a)])


def _arm_fk(q, l1, l2):
    a1 = q[0] + H1
    a2 = a1 + q[1] + H2
    return BASE + l1 * _dir(a1) + l2 * _dir(a2)


def _arm_jac(q, l1, l2):
    a1 = q[0] + H1
    a2 = a1 + q[1] + H2
    d1 = np.array([math.cos(a1), -math.sin(a1)])
    d2 = np.array([math.cos(a2), -math.sin(a2)])
    return np.stack([l1 * d1 + l2 * d2, l2 * d2], axis=1)


def _arm_ik(w, l1, l2):
    """Both elbow branches in closed form; the first inside P1's limits (None when neither is)."""
    d = w - BASE
    r2 = d @ d
    c = (r2 - l1 * l1 - l2 * l2) / (2 * l1 * l2)
    if abs(c) > 1:
        return None
    for s in (1.0, -1.0):
        beta = s * math.acos(c)                                   # angle of link 2 relative to link 1
        # direction of d in the (sin, cos) angle convention
        ad = math.atan2(d[0], d[1])
        a1 = ad - math.atan2(l2 * math.sin(beta), l1 + l2 * math.cos(beta))
        a2 = a1 + beta
        q = np.array([a1 - H1, a2 - a1 - H2])
        q = (q + math.pi) % (2 * math.pi) - math.pi
        if (np.all(q >= LIM[:, 0] - 1e-12) and np.all(q <= LIM[:, 1] + 1e-12)
                and SUM[0] - 1e-12 <= q.sum() <= SUM[1] + 1e-12 and np.allclose(_arm_fk(q, l1, l2), w, atol=1e-12)):
            return q
    return None


def _lever(w, p, L):
    """d tip / d w of the rigid lever through ``p`` (any dimension)."""
    u = (p - w) / np.linalg.norm(p - w)
    r = np.linalg.norm(p - w)
    n = len(w)
    return np.eye(n) - (L / r) * (np.eye(n) - np.outer(u, u))


def _rot2(rx):
    c, s = math.cos(rx), math.sin(rx)
    return np.array([[c, -s], [s, c]])


def planar_reference(x, *, l=(0.21, 0.21), dl=(0.0, 0.0), L=0.32, dL=0.0, port, est, k, rx=0.0):
    """``(valid, ||G||)`` at tip ``x`` of P1's arm whose links are ``l + dl`` and instrument ``L + dL``."""
    lt1, lt2, Lt = l[0] + dl[0], l[1] + dl[1], L + dL
    r = np.linalg.norm(x - port)
    if not (1e-9 < r < Lt):
        return False, np.nan
    w = x - Lt * (x - port) / r
    q = _arm_ik(w, lt1, lt2)
    if q is None:
        return False, np.nan
    J = _lever(w, port, Lt) @ _arm_jac(q, lt1, lt2)
    wh = _arm_fk(q, *l)
    Jh = _lever(wh, est, L) @ _arm_jac(q, *l)
    G = np.eye(2) - k * _rot2(rx) @ J @ np.linalg.inv(Jh)
    return True, float(np.linalg.norm(G, 2))


def _planar(effects, tmp_path, region=None, name="planar"):
    text = PLANAR.read_text()
    text = text.split("[[query]]")[0]
    body = "".join(f"[effects.{n}]\n" + "".join(f"{k} = {v!r}\n" for k, v in p.items()) for n, p in effects.items())
    reg = region or {"y": (-0.05, 0.05), "z": (0.30, 0.40)}
    text = text.replace("[fields]\nresolution = 0.002                         # m",
                        "[fields]\nresolution = 0.01\nregion = { y = [%r, %r], z = [%r, %r] }" % (*reg["y"], *reg["z"]))
    assert "region" in text
    p = tmp_path / f"{name}.toml"
    p.write_text(text + "\n" + body)
    return load_scenario(p)


def _field_points(f):
    axes = f.axes
    P = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(axes))
    return P, f.valid.reshape(-1), f.G_norm.reshape(-1)


def _compare(P, valid, G, ref):
    rv = np.array([r[0] for r in ref])
    rg = np.array([r[1] for r in ref])
    agree = np.mean(rv == valid)
    assert agree >= 0.999, f"valid masks agree on {agree:.4f} of {len(P)} tips"
    both = rv & valid
    assert both.sum() >= 0.5 * len(P)
    err = np.max(np.abs(G[both] - rg[both]))
    assert err < 1e-6, f"max | ||G|| - reference | = {err:.3g}"
    return both


@pytest.mark.parametrize("effects", [
    {"link_length": {"dl1": 0.004, "dl2": -0.003}},
    {"instrument_length": {"dL": 0.006}},
    {"tracker_registration": {"rx": 0.04, "by": 0.001, "bz": -0.002}},
    {"link_length": {"dl1": -0.002, "dl2": 0.003}, "instrument_length": {"dL": -0.004},
     "tracker_registration": {"rx": -0.03}},
], ids=["link_length", "instrument_length", "tracker_registration", "all_three"])
def test_planar_fields_equal_the_closed_form(effects, tmp_path):
    sc = _planar(effects, tmp_path, region={"y": (-0.12, 0.12), "z": (0.22, 0.44)})
    f = compute_fields(sc, resolution=0.02, metrics=("G_norm",))
    P, valid, G = _field_points(f)
    ll = effects.get("link_length", {})
    ref = [planar_reference(x, dl=(ll.get("dl1", 0.0), ll.get("dl2", 0.0)),
                            dL=effects.get("instrument_length", {}).get("dL", 0.0),
                            port=np.array([0.0, 0.160]), est=np.array([0.020, 0.170]), k=1.0,
                            rx=effects.get("tracker_registration", {}).get("rx", 0.0)) for x in P]
    both = _compare(P, valid, G, ref)
    # and the truth is not the declared model: the field moved
    f0 = compute_fields(sc.with_(effects={}), resolution=0.02, metrics=("G_norm",))
    assert np.nanmax(np.abs(f0.G_norm.reshape(-1)[both] - G[both])) > 1e-3


# ----------------------------------------------------------------------------- URDF arms: pinocchio
def _edited_urdf(text: str, edits: dict) -> str:
    """The URDF with joint ``name``'s origin ``[R0, p0]`` replaced by ``[R(r) R0, p0 + d]`` for each
    ``{name: (d (3,), r (3,))}`` (rotation vector ``r``, both in the parent frame)."""
    root = ET.fromstring(text)
    for j in root.findall("joint"):  # the kinematic joints (not a transmission's references)
        if j.get("name") in edits:
            d, r = (np.asarray(v, float) for v in edits[j.get("name")])
            o = j.find("origin")
            p0 = np.array([float(v) for v in o.get("xyz", "0 0 0").split()])
            R0 = Rotation.from_euler("xyz", [float(v) for v in o.get("rpy", "0 0 0").split()]).as_matrix()
            R1 = Rotation.from_rotvec(r).as_matrix() @ R0
            o.set("xyz", " ".join(repr(float(v)) for v in p0 + d))
            o.set("rpy", " ".join(repr(float(v)) for v in Rotation.from_matrix(R1).as_euler("xyz")))
    return ET.tostring(root, encoding="unicode")


class PinArm:
    """An arm from URDF text through pinocchio: wrist position and its Jacobian (world frame, the
    scenario's base pose) for the actuated joints, the others held at 0."""

    def __init__(self, text, joints, wrist, base_position, base_rpy):
        import pinocchio as pin

        self.pin = pin
        self.model = pin.buildModelFromXML(text)
        self.data = self.model.createData()
        self.frame = self.model.getFrameId(wrist)
        self.idx = [self.model.joints[self.model.getJointId(n)].idx_v for n in joints]
        self.qi = [self.model.joints[self.model.getJointId(n)].idx_q for n in joints]
        self.Rb = Rotation.from_euler("xyz", base_rpy).as_matrix()
        self.pb = np.asarray(base_position, float)

    def _q(self, q):
        full = self.pin.neutral(self.model)
        full[self.qi] = q
        return full

    def fk(self, q):
        pin = self.pin
        pin.framesForwardKinematics(self.model, self.data, self._q(q))
        return self.Rb @ self.data.oMf[self.frame].translation + self.pb

    def jac(self, q):
        pin = self.pin
        J = pin.computeFrameJacobian(self.model, self.data, self._q(q), self.frame, pin.LOCAL_WORLD_ALIGNED)
        return self.Rb @ J[:3, self.idx]


def spatial_reference(x, true_arm: PinArm, decl_arm: PinArm, seed_q, *, L, dL, port, est, k, R, limits, coupled=None):
    """``(valid, ||G||)`` at tip ``x``: the true wrist through the true port, the encoder angles by a
    least-squares IK on the true (edited) model from ``seed_q``, ``J`` and ``Jhat`` at those angles."""
    Lt = L + dL
    r = np.linalg.norm(x - port)
    if not (1e-9 < r < Lt) or seed_q is None or not np.all(np.isfinite(seed_q)):
        return False, np.nan
    w = x - Lt * (x - port) / r
    sol = least_squares(lambda q: true_arm.fk(q) - w, seed_q, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    q = sol.x
    if np.linalg.norm(true_arm.fk(q) - w) > 1e-10:
        return False, np.nan
    lim = np.asarray(limits, float)
    if np.any(q < lim[:, 0] - 1e-9) or np.any(q > lim[:, 1] + 1e-9):
        return False, np.nan
    if coupled is not None and not (coupled[1][0] - 1e-9 <= q[coupled[0]].sum() <= coupled[1][1] + 1e-9):
        return False, np.nan
    J = _lever(w, port, Lt) @ true_arm.jac(q)
    Jh = _lever(decl_arm.fk(q), est, L) @ decl_arm.jac(q)
    G = np.eye(3) - k * R @ J @ np.linalg.inv(Jh)
    return True, float(np.linalg.norm(G, 2))


def _spatial_effect_tables(geom: dict, dL: float, rot, b) -> dict:
    eff = {}
    if geom:
        eff["joint_geometry"] = dict(geom)
    if dL:
        eff["instrument_length"] = {"dL": dL}
    if rot is not None:
        eff["tracker_registration"] = {"rx": rot[0], "ry": rot[1], "rz": rot[2], "bx": b[0], "by": b[1], "bz": b[2]}
    return eff


def _edits(geom: dict, joints) -> dict:
    out = {}
    for i, name in enumerate(joints):
        d = [geom.get(f"{a}_{i + 1}", 0.0) for a in ("dx", "dy", "dz")]
        r = [geom.get(f"{a}_{i + 1}", 0.0) for a in ("rx", "ry", "rz")]
        if any(d) or any(r):
            out[name] = (d, r)
    return out


def _check_spatial(sc, geom, dL, rot, b, *, limits, coupled=None):
    sc = sc.with_(effects=_spatial_effect_tables(geom, dL, rot, b))
    m = arm_model(sc)
    rb = sc.robot
    text = m.arm.urdf_text
    decl = PinArm(text, rb.joints, rb.wrist, rb.base_position, rb.base_rpy)
    true = PinArm(_edited_urdf(text, _edits(geom, rb.joints)), rb.joints, rb.wrist, rb.base_position, rb.base_rpy)
    f = compute_fields(sc, metrics=("G_norm",))
    P, valid, G = _field_points(f)
    L = sc.instrument.length
    port, est = np.asarray(sc.port.position, float), np.asarray(sc.port.estimate, float)
    R = np.eye(3) if rot is None else Rotation.from_rotvec(rot).as_matrix()
    ref = []
    for x in P:
        r = np.linalg.norm(x - port)
        w = x - (L + dL) * (x - port) / max(r, 1e-12)
        seed, ok = m.arm.inverse(w)  # the declared arm's branch: where the IK on the true model starts
        ref.append(spatial_reference(x, true, decl, seed if ok else None, L=L, dL=dL, port=port, est=est,
                                     k=float(sc.controller.gain), R=R, limits=limits, coupled=coupled))
    both = _compare(P, valid, G, ref)
    f0 = compute_fields(sc.with_(effects={}), metrics=("G_norm",))
    assert np.nanmax(np.abs(f0.G_norm.reshape(-1)[both] - G[both])) > 1e-4


def _single_instance(sc, region, res):
    from errplan.scenario import Fields

    return sc.with_(uncertainty=replace(sc.uncertainty, port_x=None, port_y=None, port_z=None, tip_force_over_ei=None),
                    fields=Fields(res, region))


@pytest.fixture(scope="module")
def ur5(tmp_path_factory):
    d = tmp_path_factory.mktemp("ur5")
    p = arm_scenario(d, "ur5", [0.103, 0.196, 0.603], [0.1, 0.2, 0.6],
                     "[controller]\ngain = 0.9\n[fields]\nresolution = 0.03\n")
    return _single_instance(load_scenario(p), {"x": (-0.03, 0.09), "y": (-0.03, 0.09), "z": (0.66, 0.78)}, 0.04)


UR5_GEOM = {"dz_2": 0.003, "rx_2": 0.004, "dx_3": -0.002, "dz_3": -0.002, "ry_3": 0.006, "rz_3": -0.003}


@pytest.mark.parametrize("case", ["joint_geometry", "instrument_length", "tracker_registration"])
def test_ur5_fields_equal_pinocchio_on_the_edited_urdf(ur5, case):
    pi = math.pi
    lim = [[-pi, pi]] * 3
    if case == "joint_geometry":
        _check_spatial(ur5, UR5_GEOM, 0.0, None, None, limits=lim)
    elif case == "instrument_length":
        _check_spatial(ur5, {}, 0.005, None, None, limits=lim)
    else:
        _check_spatial(ur5, UR5_GEOM, -0.003, (0.01, -0.02, 0.015), (0.001, -0.002, 0.0005), limits=lim)


def test_phantom_like_arm_fields_equal_pinocchio_on_the_edited_urdf():
    sc = _single_instance(load_scenario(PHANTOM), {"x": (-0.06, 0.06), "y": (-0.06, 0.06), "z": (0.30, 0.42)}, 0.04)
    geom = {"dy_2": 0.002, "rz_2": 0.008, "dx_3": 0.002, "dz_3": 0.003, "rx_3": 0.010}
    _check_spatial(sc, geom, 0.004, (0.0, 0.0, 0.02), (0.0, 0.001, 0.0),
                   limits=[[-1.0, 1.0], [-1.9, 1.2], [-0.7, 1.0]], coupled=([1, 2], (-0.3, 2.8)))


def _fields_both_paths(sc, monkeypatch):
    """The field of ``sc`` through the compiled effects path and through the numpy one."""
    from errplan.fields.evaluator import SpatialEffectsEvaluator

    f = compute_fields(sc, metrics=("G_norm", "phi_max"), workers=1)
    with monkeypatch.context() as mp:
        mp.setattr(SpatialEffectsEvaluator, "compiled", property(lambda self: False))
        g = compute_fields(sc, metrics=("G_norm", "phi_max"), workers=1)
    return f, g


@pytest.mark.parametrize("arm", ["ur5", "phantom"])
def test_the_compiled_effects_path_equals_the_numpy_path(arm, ur5, monkeypatch):
    """Over the full error set (port box and tip loads), a truth with joint geometry, a longer instrument,
    joint offsets and a tracker registration: the compiled effects path's field is the numpy path's (the
    one checked against pinocchio above): the same valid tips, ||G|| and |phi_max| to 1e-9."""
    from errplan.fields.evaluator import SpatialEffectsEvaluator
    from errplan.scenario import Fields

    if arm == "ur5":
        base = load_scenario(ur5.source)
        geom = UR5_GEOM
        box = replace(base.uncertainty, port_x=(-0.004, 0.004), port_y=(-0.004, 0.004), port_z=(-0.004, 0.004),
                      tip_force_over_ei=(0.0, 1.0), samples=3)
        sc = base.with_(uncertainty=box, fields=Fields(0.1, {"x": (-0.25, 0.35), "y": (-0.25, 0.35), "z": (0.45, 0.9)}))
    else:
        geom = {"dy_2": 0.002, "rz_2": 0.008, "dx_3": 0.002, "dz_3": 0.003, "rx_3": 0.010}
        sc = load_scenario(PHANTOM).with_(fields=Fields(0.03, {"x": (-0.12, 0.12), "y": (-0.12, 0.12), "z": (0.28, 0.46)}))
    tables = _spatial_effect_tables(geom, 0.004, (0.01, -0.02, 0.015), (0.001, -0.002, 0.0005))
    tables["joint_offset"] = {"dq1": 0.004, "dq2": -0.003, "dq3": 0.002}
    sc = sc.with_(effects=tables)
    assert SpatialEffectsEvaluator.from_model(arm_model(sc)).compiled
    f, g = _fields_both_paths(sc, monkeypatch)
    assert np.array_equal(f.valid, g.valid) and f.valid.sum() >= 20
    v = f.valid
    assert np.max(np.abs(f.G_norm[v] - g.G_norm[v])) <= 1e-9
    assert np.max(np.abs(f.phi_max[v] - g.phi_max[v])) <= 1e-9


# ----------------------------------------------------------------------------- the certificates
def test_uncovered_effects_names_what_the_metrics_cannot_express(tmp_path):
    sc = _planar({"link_length": {"dl1": 0.001}, "backlash": {"b1": 0.001, "b2": 0.0},
                  "port_friction": {"fa": 0.0, "fn": 0.0005}, "tracker_offset": {"by": 0.001}}, tmp_path)
    assert uncovered_effects(sc) == ["backlash", "port_friction"]
    assert uncovered_effects(arm_model(sc)) == ["backlash", "port_friction"]
    assert uncovered_effects(sc.with_(effects={"port_friction": {"fa": 0.0, "fn": 0.0}})) == []
    # any effect outside the expressible list, whatever its name (a later one such as a tracker latency)
    assert uncovered_effects(sc.with_(effects={"tracker_latency": {"tau": 1.0}, "joint_offset": {"dq1": 0.01}})) \
        == ["tracker_latency"]


def test_a_segment_certified_on_the_declared_model_is_not_on_a_truth_it_diverges_on(tmp_path):
    """A 20 mm longer instrument turns the motion normal to the shaft up by s / (s - dL) (s the tip's
    distance past the port, 120 mm here): at gain 1.7 a short segment across the shaft contracts on the
    declared model (||G|| = 0.7 with a perfect port estimate) and diverges on the truth (||G|| above 1)."""
    from errplan.fields import Evaluator
    from errplan.gains import options_from_scenario
    from errplan.gains.verify import verify_segment
    from errplan.pipeline import truth_plant
    from errplan.simulation import ControllerModel, simulate

    eff = {"instrument_length": {"dL": 0.020}}
    sc = _planar(eff, tmp_path)
    sc = sc.with_(port=replace(sc.port, estimate=sc.port.position))  # a perfect model but for the length
    opts = options_from_scenario(sc)
    a, b, k = np.array([-0.006, 0.280]), np.array([0.0, 0.280]), 1.7
    decl = verify_segment(Evaluator.from_model(arm_model(sc.with_(effects={}))), a, b, k, 0.006, opts)
    true = verify_segment(Evaluator.from_model(arm_model(sc)), a, b, k, 0.006, opts)
    assert decl["G_norm"] < 1.0 and decl["step_ratio"] < 1.0
    assert not true["G_norm"] < 1.0
    plant = truth_plant(sc)
    sim = simulate(plant, ControllerModel.from_model(arm_model(sc)), plant.configuration_for_tip(a), [b], [k],
                   tolerance=1e-6, max_steps=40)
    assert not sim.monotonic


@pytest.mark.parametrize("arm", ["planar", "ur5"])
def test_every_certified_segment_of_a_plan_replays_monotonic_on_its_truth(arm, tmp_path):
    """Planar: longer/shorter links and a longer instrument; the UR5: joint_geometry and a longer
    instrument, with a port box (the truth is the box's centre, the certificate covers the box)."""
    from errplan.gains import options_from_scenario, schedule_gains
    from errplan.pipeline import replay, truth_plant
    from errplan.simulation import ControllerModel

    if arm == "planar":
        sc = _planar({"link_length": {"dl1": 0.004, "dl2": -0.003}, "instrument_length": {"dL": 0.006}}, tmp_path)
        path = np.array([[0.0, 0.415], [0.03, 0.38], [0.0, 0.33], [-0.04, 0.30]])
    else:
        p = arm_scenario(tmp_path, "ur5", [0.103, 0.196, 0.603], [0.1, 0.2, 0.6],
                         "[controller]\ngain = 0.9\n[uncertainty]\nport_x = [-0.002, 0.002]\n")
        sc = load_scenario(p).with_(effects={"joint_geometry": UR5_GEOM, "instrument_length": {"dL": 0.004}})
        path = np.array([[0.02, 0.03, 0.72], [0.05, 0.05, 0.70]])
    opts = options_from_scenario(sc)
    sched = schedule_gains(sc, path, opts)
    plant = truth_plant(sc)
    ctrl = ControllerModel.from_model(arm_model(sc))
    certified = [s for s in sched.segments if s.certified]
    assert certified
    for s in certified:
        rep = replay(plant, ctrl, s.start, [s.end], [float(s.gain)], opts)
        assert rep.sim.monotonic, f"segment {s.start} -> {s.end} certified at k = {s.gain:.3f}, not monotonic on the truth"


def test_the_exact_path_equals_newton_on_the_full_forward_map_under_loads():
    """Under the error set's tip loads (3-D: a load vector per instance) the exact path (the loaded shaft's
    wrist, the true arm's inverse, the analytic J) gives the maps Newton's method on the true forward map
    with finite-difference Jacobians gives (the general path, kept for gravity sag)."""
    from errplan.fields.evaluator import Evaluator, SpatialEffectsEvaluator

    class Newton(SpatialEffectsEvaluator):
        closed_form = False

    sc = load_scenario(PHANTOM).with_(effects={"joint_geometry": {"dy_2": 0.002, "rz_2": 0.008, "dz_3": 0.003},
                                                "instrument_length": {"dL": 0.004},
                                                "tracker_registration": {"rz": 0.02, "by": 0.001}})
    m = arm_model(sc)
    ev = SpatialEffectsEvaluator.from_model(m)
    nw = Newton(ev.plant, ev.estimate, ev.errors, ev.jacobian)
    rng = np.random.default_rng(3)
    x = np.array([0.0, 0.0, 0.36]) + rng.uniform(-0.04, 0.04, (12, 3))
    th = np.column_stack([rng.uniform(-0.005, 0.005, (12, 3)), rng.uniform(0.0, 1.0, 12), rng.uniform(0, 6.28, 12)])
    M1, _, ok1 = ev.parts(x, th)
    M2, _, ok2 = nw.parts(x, th)
    assert ok1.sum() >= 10 and np.array_equal(ok1, ok2)
    np.testing.assert_allclose(M1[ok1], M2[ok2], atol=1e-7)

    class Newton2(Evaluator):
        closed_form = False

    sp = _planar_scenario_with_load()
    e1 = Evaluator.from_model(arm_model(sp))
    e2 = Newton2(e1.arm, e1.length, e1.estimate, e1.jacobian, e1.errors, e1.effects)
    xp = np.array([0.0, 0.36]) + rng.uniform(-0.05, 0.05, (12, 2))
    tp = np.column_stack([rng.uniform(-0.005, 0.005, (12, 2)), rng.uniform(-1.0, 1.0, 12)])
    a = e1.parts_reach(xp, tp)
    b = e2.parts_reach(xp, tp)
    assert a[2].sum() >= 10 and np.array_equal(a[2], b[2])
    np.testing.assert_allclose(a[0][a[2]], b[0][b[2]], atol=1e-7)
    np.testing.assert_allclose(a[1][a[2]], b[1][b[2]], atol=1e-7)


def _planar_scenario_with_load():
    sc = load_scenario(PLANAR)
    return sc.with_(uncertainty=replace(sc.uncertainty, port_y=(-0.005, 0.005), port_z=(-0.005, 0.005),
                                        tip_force_over_ei=(-1.0, 1.0)),
                    effects={"link_length": {"dl1": 0.003, "dl2": -0.002}, "instrument_length": {"dL": 0.005},
                             "joint_offset": {"dq1": 0.01, "dq2": -0.005}, "tracker_registration": {"rx": 0.03}})


@pytest.mark.parametrize("dim", [2, 3])
def test_a_tracker_registration_certificate_is_the_rotated_loops(dim, tmp_path):
    """With a perfect model but for a tracker registered with a rotation R (angle a), J Jhat^-1 = I and the
    loop's matrix is I - k R: every pair of the ball has ||G|| = max(|1 - k e^{ia}|, |1 - k| in 3-D), and the
    one-step replay in the tracker's frame contracts by that much in a small ball (the lever's curvature
    adds to it in a large one, with or without a registration)."""
    from errplan.fields import Evaluator
    from errplan.gains import SpatialModel, options_from_scenario
    from errplan.gains.verify import verify_segment

    a, k = 0.35, 1.2
    if dim == 2:
        sc = _planar({"tracker_registration": {"rx": a, "by": 0.002, "bz": -0.001}}, tmp_path)
        sc = sc.with_(port=replace(sc.port, estimate=sc.port.position))
        ev = Evaluator.from_model(arm_model(sc))
        s, b = np.array([0.0, 0.37]), np.array([0.0004, 0.37])
    else:
        p = arm_scenario(tmp_path, "ur5", [0.103, 0.196, 0.603], [0.103, 0.196, 0.603], "[controller]\ngain = 0.9\n")
        axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
        r = a * axis
        sc = load_scenario(p).with_(effects={"tracker_registration": {"rx": r[0], "ry": r[1], "rz": r[2],
                                                                     "bx": 0.001, "by": 0.0, "bz": -0.002}})
        ev = SpatialModel.from_model(arm_model(sc))
        s, b = np.array([0.02, 0.03, 0.72]), np.array([0.0204, 0.03, 0.72])
    expect = max(abs(1 - k * np.exp(1j * a)), abs(1 - k) if dim == 3 else 0.0)
    res = verify_segment(ev, s, b, k, 0.0005, options_from_scenario(sc))
    assert res["reachable_tip_share"] == 1.0
    assert abs(res["G_norm"] - expect) < 1e-9
    assert abs(res["step_ratio"] - expect) < 0.02
    no = verify_segment(Evaluator.from_model(arm_model(sc.with_(effects={}))) if dim == 2 else
                        SpatialModel.from_model(arm_model(sc.with_(effects={}))), s, b, k, 0.0005, options_from_scenario(sc))
    assert abs(no["G_norm"] - abs(1 - k)) < 1e-9


def test_a_plan_on_a_registered_tracker_replays_monotonic_in_the_trackers_frame(tmp_path):
    """With a tracker registration the loop closes on the tracked tip R x + b: the certificate bounds that
    error, and the certified plan's replay on the truth shrinks it at every step (the true tip's distance to
    the target is not what the loop drives to zero)."""
    from errplan.gains import options_from_scenario, schedule_gains
    from errplan.pipeline import replay, truth_plant
    from errplan.simulation import ControllerModel

    sc = _planar({"tracker_registration": {"rx": 0.03, "by": 0.001, "bz": -0.0005},
                  "link_length": {"dl1": 0.002, "dl2": 0.0}}, tmp_path)
    opts = options_from_scenario(sc)
    path = np.array([[0.0, 0.415], [0.02, 0.37], [0.0, 0.32]])
    sched = schedule_gains(sc, path, opts)
    assert sched.certified
    plant = truth_plant(sc)
    sim = replay(plant, ControllerModel.from_model(arm_model(sc)), path[0], sched.waypoints, sched.gains, opts).sim
    e = np.linalg.norm(sim.target - sim.tracked, axis=-1)
    same = sim.segment[1:] == sim.segment[:-1]
    assert sim.converged and np.all(e[1:][same] <= e[:-1][same] * (1 + 1e-9) + 1e-12)
    np.testing.assert_allclose(sim.tracked, plant.tracked(sim.tip), atol=1e-15)  # noise-free: R x + b
    # the run's own flag (the plan JSON's "monotonic") is measured where the loop closes, so it says so
    np.testing.assert_allclose(sim.loop, sim.tracked, atol=1e-15)
    assert sim.monotonic
    # ... while the true tip's distance to the target, which the loop does not drive to zero, does grow
    et = sim.errors
    assert not np.all(et[1:][same] <= et[:-1][same] * (1 + 1e-9) + 1e-12)
