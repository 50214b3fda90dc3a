"""Real third-party arms for the tests, from example-robot-data (a declared test dependency): scenarios
that name their URDF as ``package://`` and so work on any machine where the package is installed.

- ``ur5``: Universal Robots' UR5 (joint-limited description); shoulder pan, shoulder lift and elbow
  place ``wrist_1_link``; the base turned so that the arm's z axis is errplan's y (up).
- ``panda``: Franka Emika's Panda; joints 1, 2 and 4 place ``panda_link5``, joint 3 held at 0.3 rad.

The PHANToM Omni description (a user's URDF as it is) is used only where ERRPLAN_TEST_OMNI_URDF names
it: :data:`OMNI` and :data:`needs_omni`.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: A user's own URDF as it is, for the checks that want one beside the packaged arms: the PHANToM Omni
#: description (omni_description/urdf/omni.urdf), where ERRPLAN_TEST_OMNI_URDF names it; the repository
#: holds no copy and reads nothing outside itself.
_OMNI_GIVEN = os.environ.get("ERRPLAN_TEST_OMNI_URDF", "")
OMNI = Path(_OMNI_GIVEN) if _OMNI_GIVEN else ROOT / "tests" / "no-omni-given" / "urdf" / "omni.urdf"
SHARED_ROBOTS = OMNI.parents[2]  # the folder holding omni_description/: its package path
needs_omni = pytest.mark.skipif(not OMNI.is_file(), reason="no PHANToM Omni description given "
                                                          "(ERRPLAN_TEST_OMNI_URDF); the same checks run on "
                                                          "example-robot-data arms")

ARMS = {
    "ur5": dict(urdf="package://ur_description/urdf/ur5_joint_limited_robot.urdf",
                joints=["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint"], wrist="wrist_1_link",
                base_rpy=[-math.pi / 2, 0.0, 0.0], fixed_joints={}),
    "panda": dict(urdf="package://panda_description/urdf/panda.urdf",
                  joints=["panda_joint1", "panda_joint2", "panda_joint4"], wrist="panda_link5",
                  base_rpy=[-math.pi / 2, 0.0, 0.0], fixed_joints={"panda_joint3": 0.3}),
}

# issue 22's UR5 setup: a 350 mm shaft, a +-5 mm port box, gain 0.9, a task region above the port
UR5_BODY = """
[controller]
gain = 0.9
[uncertainty]
port_x = [-0.005, 0.005]
port_y = [-0.005, 0.005]
port_z = [-0.005, 0.005]
[fields]
resolution = 0.008
region = { x = [-0.05, 0.25], y = [-0.1, 0.25], z = [0.66, 0.86] }
[planner]
planner = "BITstar"
metric = "G_norm"
weight = 2.0
"""
UR5_PORT, UR5_ESTIMATE = [0.103, 0.196, 0.603], [0.1, 0.2, 0.6]


def _toml(v) -> str:
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + " }"
    if isinstance(v, (list, tuple)) or hasattr(v, "tolist") and getattr(v, "ndim", 0):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, str):
        return f'"{v}"'
    return repr(float(v))


def arm_scenario(folder: Path, arm: str, port, estimate, body: str = "", length: float = 0.35,
                 name: str | None = None) -> Path:
    """A scenario on one of :data:`ARMS` written into ``folder``: the arm, a shaft of ``length`` m through
    ``port`` (the controller believes ``estimate``), then ``body`` (further TOML tables)."""
    a = ARMS[arm]
    robot = "\n".join(f"{k} = {_toml(v)}" for k, v in a.items() if v != {})
    path = Path(folder) / f"{name or arm}.toml"
    path.write_text(f"""name = "{name or arm}"
[robot]
{robot}
[instrument]
length = {length}
[port]
position = {_toml(port)}
estimate = {_toml(estimate)}
{body}""", encoding="utf-8")
    return path


def ur5_scenario(folder: Path, queries: str = "", name: str = "ur5") -> Path:
    """Issue 22's UR5 scenario with ``queries`` (``[[query]]`` tables) appended."""
    return arm_scenario(folder, "ur5", UR5_PORT, UR5_ESTIMATE, UR5_BODY + queries, name=name)
