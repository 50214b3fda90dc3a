"""Kinematic models: the planar arm (:mod:`.arm`), any URDF chain (:mod:`.urdf`), the shaft (:mod:`.shaft`)
and the true robot with physics.md's effects (:mod:`.truth`)."""
from __future__ import annotations

from functools import lru_cache


def arm_for(robot):
    """The arm model of a scenario's ``[robot]``: :class:`.arm.Arm` for P1's planar arm,
    :class:`.urdf.UrdfArm` (loaded once per distinct robot) for a URDF."""
    if hasattr(robot, "urdf"):
        return _urdf_arm(robot)
    from .arm import Arm

    return Arm.from_robot(robot)


@lru_cache(maxsize=8)
def _urdf_arm(robot):
    from .urdf import UrdfArm

    return UrdfArm.from_robot(robot)
