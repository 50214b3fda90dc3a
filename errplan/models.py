"""Each arm built once: a scenario (or one arm of a :class:`~errplan.scenario.Setup`) turned into the
bundle of models every step takes.

:func:`build` reads a scenario or a setup once and returns one :class:`ArmModel` per instrument arm (a
one-instrument scenario is the one-arm case, its arm named ``"arm"``). An :class:`ArmModel` holds

- the plain data it was built from (``scenario``: the arm's scenario as it moves among the others, the
  held shafts of the other instruments and the endoscope's joined to its ``[anatomy]`` obstacles),
- the kinematics (``arm``: P1's planar :class:`~errplan.kinematics.arm.Arm` or a
  :class:`~errplan.kinematics.urdf.UrdfArm`, the URDF loaded once per distinct robot),
- the error sets (``errors``: the declared box around the port estimate; ``true_errors``: the same box
  with a ``port_offset`` effect folded into its base port) and ``jacobian_effects`` (the truth's effects
  that change the true Jacobian),
- the truth (``truth``: the :class:`~errplan.kinematics.truth.Plant` at the load of the error set
  closest to 0, with its ``[effects]``, without sensor noise),
- the anatomy as this arm sees it (``anatomy_model``: an :class:`errplan.anatomy.ShaftClearance` of its
  obstacles, the held shafts of the others included, for the port box of ``true_errors``; None without
  obstacles), built on first use and then shared,
- the controller's parameters (``jacobian``, ``gain``, ``noise``, ``estimate``, ``length``) and the
  sensors.

Steps above this module build their own objects FROM the bundle (``Evaluator.from_model(m)``,
``SpatialModel.from_model(m)``, ``Plant.from_model(m)``, ``ControllerModel.from_model(m)``,
``PlannerSettings.from_model(m)``); none of them reads the scenario file or rebuilds an arm. For the
steps that still take the scenario's tables (queries, ``[planner]``, ``[fields]``, ...), an
:class:`ArmModel` answers every attribute of its scenario (``m.queries``, ``m.planner``, ``m.source``,
``m.with_(...)``), so a model goes wherever a scenario went; :func:`arm_model` turns either into a model
(a model passes through unchanged, so what the top built is what the steps use).

Layer: imports the scenario, the kinematics, the anatomy and the error set (:mod:`errplan.errorset`, plain
data); nothing above them. The fields sit above: they build their evaluators from a model.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Mapping

import numpy as np

from .scenario import Scenario, Setup

__all__ = ["ArmModel", "build", "build_arm", "arm_model"]


@dataclass(frozen=True, eq=False)
class ArmModel:
    """One instrument arm built once (see the module docstring). Immutable: the per-call scratch of a
    computation stays out of it (as pinocchio's Model and Data)."""

    arm_name: str
    scenario: Scenario

    # -- plain data, named -------------------------------------------------------------------------
    @property
    def dim(self) -> int:
        """2 (planar, [y, z]) or 3 (URDF arm, [x, y, z])."""
        return self.scenario.dim

    @property
    def length(self) -> float:
        return self.scenario.instrument.length

    @property
    def estimate(self) -> tuple[float, ...]:
        """The controller's port estimate."""
        return tuple(self.scenario.port.estimate)

    @property
    def jacobian(self) -> str:
        """The controller's Jacobian model: "rigid" or "flexion"."""
        return self.scenario.controller.jacobian

    @property
    def gain(self) -> float:
        return float(self.scenario.controller.gain)

    @property
    def noise(self) -> tuple[float, float]:
        """The flexion controller's bounds on measured (position, angle) noise."""
        n = self.scenario.uncertainty.sensor_noise
        return (n.position, n.angle) if n else (0.0, 0.0)

    @property
    def truth_load(self) -> float:
        """The tip load of the error set closest to 0 (the truth's load; a magnitude along -y in 3-D)."""
        tl = self.scenario.uncertainty.tip_force_over_ei
        return float(np.clip(0.0, tl[0], tl[1])) if tl is not None else 0.0

    # -- built parts -------------------------------------------------------------------------------
    @cached_property
    def arm(self):
        """The kinematics: P1's planar arm or the URDF arm (loaded once per distinct robot)."""
        from .kinematics import arm_for

        return arm_for(self.scenario.robot)

    @cached_property
    def errors(self):
        """The declared error set (:class:`errplan.fields.ErrorSet`): the box around the port estimate."""
        from .errorset import ErrorSet

        sc = self.scenario
        return ErrorSet.from_tables(sc.port, sc.uncertainty, sc.dim)

    @cached_property
    def _folded(self):
        from .errorset import error_set

        return error_set(self.scenario, self.errors)

    @property
    def true_errors(self):
        """:attr:`errors` with an ``[effects] port_offset`` folded into the base port."""
        return self._folded[0]

    @property
    def jacobian_effects(self) -> Mapping:
        """The truth's effects that change the true Jacobian (Plant keyword arguments in 2-D, effect
        tables in 3-D); empty for a truth the compiled kernels cover."""
        return self._folded[1]

    @cached_property
    def truth(self):
        """The true robot: ``[port] position``, the ``[effects]``, the load :attr:`truth_load`."""
        from .kinematics.truth import Plant

        return Plant.from_model(self, load=self.truth_load)

    @cached_property
    def anatomy_model(self):
        """The :class:`errplan.anatomy.ShaftClearance` of this arm's obstacles (the others' held shafts
        included) for the port box of :attr:`true_errors`, or None. Built on first use, then shared."""
        an = self.scenario.anatomy
        if an is None or (not an.obstacles and an.body_wall is None):
            return None
        from .anatomy import build as build_anatomy

        return build_anatomy(an, self.true_errors.port_corners())

    # -- a model goes where a scenario went --------------------------------------------------------
    def __getattr__(self, name: str):
        if name.startswith("_") or name == "scenario" or hasattr(type(self), name):
            raise AttributeError(name)  # (a built part that failed is not answered by the scenario's table)
        return getattr(self.scenario, name)

    def __reduce__(self):  # to a worker process: the plain data; a worker builds what it uses, once
        return (ArmModel, (self.arm_name, self.scenario))

    def __repr__(self) -> str:
        return f"ArmModel({self.arm_name!r}, dim={self.dim}, source={self.scenario.source!r})"


def build_arm(sc: Scenario, arm_name: str = "arm") -> ArmModel:
    """The :class:`ArmModel` of one arm's scenario (as it moves among the others: :meth:`Setup.moving`)."""
    if isinstance(sc, ArmModel):
        return sc
    m = ArmModel(arm_name, sc)
    m.arm, m.true_errors  # the kinematics and the error sets now: a bad robot fails at the top
    return m


def build(source: Setup | Scenario | ArmModel) -> tuple[ArmModel, ...]:
    """One :class:`ArmModel` per instrument arm of a setup (in ``arm_names`` order), each seeing the
    others' held shafts; a scenario or a model gives the one-arm tuple."""
    if isinstance(source, ArmModel):
        return (source,)
    if isinstance(source, Setup):
        return tuple(build_arm(source.moving(n), n) for n in source.arm_names)
    return (build_arm(source),)


def arm_model(x: Scenario | ArmModel, arm_name: str = "arm") -> ArmModel:
    """``x`` itself when it is a model (what the top built), else the model of scenario ``x``."""
    return x if isinstance(x, ArmModel) else build_arm(x, arm_name)
