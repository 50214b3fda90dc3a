"""Kinematic models: the planar arm (:mod:`.arm`), any URDF chain (:mod:`.urdf`), the shaft (:mod:`.shaft`)
and the true robot with physics.md's effects (:mod:`.truth`).

Layer: above :mod:`errplan.scenario` (plain data), below metrics, fields and everything else. The
scenario builds no robot; :func:`arm_for` does, and :func:`check_scenario` runs the checks of a scenario
that need its robot.
"""
from __future__ import annotations

from functools import lru_cache

from ..errors import ScenarioError


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


def check_scenario(sc) -> None:
    """The checks of a scenario that need its robot; one :class:`ScenarioError` naming the value.

    Builds the arm (for a URDF this loads the file once, cached: a missing file, a joint or link not in
    it, or an arm that cannot place the wrist in 3-D is reported here, before any work starts), then
    checks that the shaft can reach through the port, true and estimated, from some wrist pose.
    """
    arm = arm_for(sc.robot)
    L = sc.instrument.length
    for key, port in (("[port] position", sc.port.position), ("[port] estimate", sc.port.estimate)):
        if not arm.nearer_than(port, L):
            dmin = arm.min_distance_to(port)
            raise ScenarioError(f"{sc.source}: {key} = {list(port)!r}: expected a port the shaft can reach: the "
                                f"nearest reachable wrist is {dmin:.4f} m away, more than the shaft length "
                                f"{L:.4f} m (port out of reach)")
