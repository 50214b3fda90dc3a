"""Each arm built once (errplan.models): the bundle a scenario or a setup turns into, the steps built
from it, and the checks that no step reads the scenario to build its own arm or error set again."""
from __future__ import annotations

import dataclasses
import math
import pickle
import re
from pathlib import Path

import numpy as np
import pytest

from errplan import api
from errplan.fields import ErrorSet, Evaluator
from errplan.fields.evaluator import SpatialEffectsEvaluator
from errplan.fields.search import worst_case
from errplan.kinematics import arm_for
from errplan.kinematics.arm import Arm
from errplan.kinematics.truth import Plant, effect_kwargs
from errplan.models import ArmModel, arm_model, build, build_arm
from errplan.planning.plan import PlannerSettings
from errplan.simulation import ControllerModel

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "errplan"
BOUNDED = ROOT / "scenarios" / "beasley2004_bounded.toml"
SPATIAL = ROOT / "scenarios" / "phantom15_spatial.toml"
TRIAD = ROOT / "scenarios" / "abdomen_triad.toml"


def _box(sc) -> ErrorSet:
    """The error set of docs/physics.md written out from the tables (not through the builder)."""
    u, d = sc.uncertainty, sc.dim
    names = ("port_x", "port_y", "port_z")[3 - d:]
    boxes = [getattr(u, n) for n in names]
    uncertain = any(b is not None for b in boxes)
    base = sc.port.estimate if uncertain else sc.port.position
    offs = [b or (0.0, 0.0) for b in boxes]
    tl = u.tip_force_over_ei or (0.0, 0.0)
    lo, hi = [o[0] for o in offs] + [tl[0]], [o[1] for o in offs] + [tl[1]]
    if d == 3:
        lo, hi = lo + [0.0], hi + [2 * math.pi if tl[1] > 0 else 0.0]
    noise = (u.sensor_noise.position, u.sensor_noise.angle) if u.sensor_noise else (0.0, 0.0)
    return ErrorSet(tuple(base), tuple(lo), tuple(hi), noise, u.samples)


# ----------------------------------------------------------------------------- one arm
def test_one_instrument_scenario_is_the_one_arm_case():
    sc = api.load_scenario(BOUNDED)
    (m,) = build(sc)
    assert isinstance(m, ArmModel) and m.arm_name == "arm" and m.scenario is sc
    assert m.name == sc.name and m.anatomy is sc.anatomy  # the tables answer as the scenario's
    assert m.dim == sc.dim == 2 and m.estimate == tuple(sc.port.estimate) and m.gain == sc.controller.gain
    assert m.errors == _box(sc)
    assert build(m) == (m,) and arm_model(m) is m  # what the top built passes through
    (m2,) = api.load_models(BOUNDED)
    assert m2.errors == m.errors and m2.queries == sc.queries  # a model answers its scenario's tables
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.arm_name = "other"


def test_planar_steps_from_the_model_equal_the_tables():
    """Evaluator, truth, controller and planner settings from the model equal the objects written out
    from the scenario's tables, and the worst case over the error set is identical on a small region."""
    sc = api.load_scenario(BOUNDED).with_(effects={"port_offset": {"dy": 0.001, "dz": -0.0005},
                                                   "joint_offset": {"dq1": 0.002, "dq2": 0.0}})
    m = build_arm(sc)
    arm = Arm.from_robot(sc.robot)
    es = _box(sc)
    folded = dataclasses.replace(es, base_port=(es.base_port[0] + 0.001, es.base_port[1] - 0.0005))
    ev_hand = Evaluator(arm, sc.instrument.length, tuple(sc.port.estimate), sc.controller.jacobian, folded,
                        {"joint_offset": (0.002, 0.0)})
    ev = Evaluator.from_model(m)
    assert ev.errors == folded and ev.effects == ev_hand.effects and ev.arm == arm
    x = np.array([[0.0, 0.30], [0.02, 0.33], [-0.03, 0.36]])
    a, b = (worst_case(e, x, sc.controller.gain, samples=2, refine=1) for e in (ev, ev_hand))
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    kw = effect_kwargs(sc.effects)
    assert Plant.from_model(m) == Plant(arm, sc.instrument.length, tuple(sc.port.position), **kw)
    assert Plant.from_model(m, effects=False, noise=True) == Plant(
        arm, sc.instrument.length, tuple(sc.port.position), tracker_sigma=sc.sensors.tracker_sigma,
        encoder_sigma=sc.sensors.encoder_sigma)
    assert m.truth.load == m.truth_load and m.truth.port_offset == (0.001, -0.0005)
    assert ControllerModel.from_model(m) == ControllerModel(arm, sc.instrument.length, tuple(sc.port.estimate),
                                                            sc.controller.jacobian, (0.0, 0.0))
    st = PlannerSettings.from_model(m, time=0.5)
    assert (st.planner, st.time, st.seed) == (sc.planner.planner, 0.5, sc.planner.seed)


def test_spatial_steps_from_the_model_equal_the_tables():
    sc = api.load_scenario(SPATIAL).with_(effects={"joint_offset": {"dq1": 0.003, "dq2": 0.0, "dq3": -0.002}})
    m = build_arm(sc)
    assert m.dim == 3 and m.arm is arm_for(sc.robot) and m.errors == _box(sc)
    assert set(m.jacobian_effects) == {"joint_offset"}
    ev = SpatialEffectsEvaluator.from_model(m)
    hand = SpatialEffectsEvaluator(Plant(m.arm, sc.instrument.length, tuple(m.errors.base_port),
                                         joint_offset=(0.003, 0.0, -0.002)),
                                   tuple(sc.port.estimate), _box(sc), sc.controller.jacobian)
    assert ev.plant == hand.plant and ev.errors == hand.errors
    x = np.array([[0.0, 0.0, 0.30], [0.01, -0.01, 0.31]])
    th = np.zeros((2, 5))
    th[1, :3] = m.errors.hi[:3]
    (M1, _, ok1), (M2, _, ok2) = ev.parts(x, th), hand.parts(x, th)
    np.testing.assert_array_equal(ok1, ok2)
    np.testing.assert_array_equal(M1, M2)


def test_fields_of_a_model_equal_those_of_its_scenario():
    """The fields of a model built at the top and of the scenario it was built from (built inside the
    step) are the same arrays, planar (compiled) and spatial (P2's flexion controller: the evaluator built
    from the model)."""
    from errplan.fields import compute_fields

    planar = api.load_scenario(BOUNDED)
    spatial = api.load_scenario(ROOT / "scenarios" / "phantom15_flexion.toml")  # P2's controller: numpy path
    for sc, res, region in ((planar, 0.02, None),
                            (spatial, 0.02, {"x": (-0.02, 0.02), "y": (-0.02, 0.02), "z": (0.33, 0.35)})):
        if region:
            sc = sc.with_(fields=dataclasses.replace(sc.fields, region={**(sc.fields.region or {}), **region}))
        a = compute_fields(sc, res, samples=2, workers=1)
        b = compute_fields(build_arm(sc), res, samples=2, workers=1)
        assert a.valid.any()
        for key in ("valid", "G_norm", "phi_hat_max"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))


# ----------------------------------------------------------------------------- built once
def test_the_urdf_and_the_anatomy_are_built_once(monkeypatch):
    import errplan.anatomy as anatomy
    from errplan.gains import SpatialModel
    from errplan.kinematics import _urdf_arm
    from errplan.kinematics.urdf import UrdfArm

    loads, builds = [], []
    real_load, real_build = UrdfArm.from_robot.__func__, anatomy.build
    monkeypatch.setattr(UrdfArm, "from_robot", classmethod(lambda cls, r: loads.append(r) or real_load(cls, r)))
    monkeypatch.setattr(anatomy, "build", lambda *a, **k: builds.append(a) or real_build(*a, **k))
    _urdf_arm.cache_clear()
    try:
        ms = api.load_models(SPATIAL) + api.load_models(SPATIAL)
        (m,) = ms[:1]
        n_load = len(loads)
        assert n_load == 1  # one robot, one load, however many models and steps
        sm = SpatialModel.from_model(m)
        plant, ctl = Plant.from_model(m), ControllerModel.from_model(m)
        assert sm.arm is m.arm and plant.arm is m.arm and ctl.arm is m.arm and ms[1].arm is m.arm
        assert len(loads) == n_load
        if m.scenario.anatomy is not None:
            assert sm.anatomy_model is m.anatomy_model and m.anatomy_model is m.anatomy_model
            assert len(builds) == 1
    finally:
        _urdf_arm.cache_clear()


def test_a_model_pickles_to_its_plain_data():
    (m,) = api.load_models(SPATIAL)
    m2 = pickle.loads(pickle.dumps(m))
    assert set(m2.__dict__) == {"arm_name", "scenario"}  # the built parts are not carried: a worker builds its own
    assert isinstance(m2, ArmModel) and m2.arm_name == m.arm_name and m2.errors == m.errors
    assert m2.arm is m.arm  # (in this process: the same cached URDF arm)


# ----------------------------------------------------------------------------- several arms
def test_two_arms_each_see_the_others_held_shaft():
    st = api.load_setup(TRIAD)
    ms = build(st)
    assert [m.arm_name for m in ms] == list(st.arm_names) and len(ms) == 2
    for m, other in ((ms[0], ms[1]), (ms[1], ms[0])):
        names = [o.name for o in m.scenario.anatomy.obstacles]
        assert f"{other.arm_name} shaft (held)" in names and f"{m.arm_name} shaft (held)" not in names
        rest = np.asarray(st.rest(other.arm_name), float)
        alone = build_arm(st.arm(m.arm_name)).anatomy_model
        # the other's tip at rest lies on its held shaft: this arm's tip there is not clear, alone it is
        assert float(m.anatomy_model.tip(rest[None])[0]) < m.anatomy_model.required
        assert float(alone.tip(rest[None])[0]) > float(m.anatomy_model.tip(rest[None])[0])
    assert all(a.arm is b.arm for a, b in zip(ms, build(st)))  # each robot loaded once


# ----------------------------------------------------------------------------- steps don't read the scenario
def _sources():
    for p in sorted(PKG.rglob("*.py")):
        yield p.relative_to(ROOT), p.read_text(encoding="utf-8")


def test_no_step_builds_from_the_scenario():
    """The eight ``from_scenario`` constructors are gone (steps take the bundle: ``from_model``), and no
    module asks a scenario for its dimension with a default."""
    offenders = [f"{p}: {line.strip()}" for p, text in _sources() for line in text.splitlines()
                 if re.search(r"\bfrom_scenario\b", line)]
    assert not offenders, "\n".join(offenders)
    dims = [f"{p}: {line.strip()}" for p, text in _sources() for line in text.splitlines()
            if re.search(r"getattr\([^)]*[\"']dim[\"']", line)]
    assert not dims, "\n".join(dims)


def test_a_model_shadows_no_table_of_its_scenario():
    """A model goes where a scenario went: none of its own names may hide one of the scenario's (its
    ``name`` is the scenario's, its ``anatomy`` the ``[anatomy]`` table), except ``dim`` (the same)."""
    from errplan.scenario import Scenario

    own = {n for n in dir(ArmModel) if not n.startswith("_")} | {f.name for f in dataclasses.fields(ArmModel)}
    theirs = {n for n in dir(Scenario) if not n.startswith("_")} | {f.name for f in dataclasses.fields(Scenario)}
    assert own & theirs == {"dim"}


def test_every_scenario_object_has_a_dim():
    st = api.load_setup(TRIAD)
    assert st.dim == 3 == st.arms[0].dim == build(st)[0].dim
    assert api.load_setup(BOUNDED).dim == 2
