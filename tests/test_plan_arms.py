"""Planning with the arms outside the body ([setup] arm_clearance; errplan.planning.arm_checks).

Two UR5s (example-robot-data) hold instruments through ports 14 cm apart; the right one waits at rest.
The left instrument's query goes straight up past the place where its wrist links would swing within
``arm_clearance`` of the right arm's: the straight line breaks the clearance, the plan keeps it. The plan
is checked by an independent sampler: tips every 0.25 mm along the planned path, the configuration at
each found from scratch by scipy's least squares on a fresh pinocchio model of the URDF (continued from
the previous tip), and the distance between the arms measured by dense points on the URDF's collision
meshes (trimesh, a k-d tree; tests/test_arm_collision.py's method: never below the true distance, at
most 2 H / sqrt(3) above it)."""
from __future__ import annotations

import json
import math

import numpy as np
import pinocchio as pin
import pytest
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from conftest import SCENARIOS, to_toml
from errplan import api, packages
from errplan.anatomy import setup as geo
from errplan.cli import main

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore

UR5 = "package://ur_description/urdf/ur5_joint_limited_robot.urdf"
JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint"]
CLEARANCE = 0.035  # m, [setup] arm_clearance
START, GOAL = [-0.08, 0.0, 0.29], [-0.08, 0.0, 0.41]


def setup_doc() -> dict:
    """The bundled triad's tables with two UR5s, no anatomy but the held shafts, an endoscope that sees
    the task region, and one left query (see the module docstring)."""
    doc = tomllib.loads((SCENARIOS / "abdomen_triad.toml").read_text())
    doc["anatomy"] = {"clearance": 0.004}
    doc.pop("tolerance")
    for a, sx, rest in zip(doc["arm"], (-1, 1), ([-0.04, 0.02, 0.31], [0.07, 0.06, 0.31])):
        a["robot"] = {"urdf": UR5, "joints": JOINTS, "wrist": "wrist_1_link", "base_position": [sx * 0.5, 0.0, -0.05]}
        a["instrument"] = {"length": 0.30}
        a["rest"] = rest
        a["port"] = {"estimate": [sx * 0.07, 0.0, 0.17], "position": [sx * 0.07 + 0.002, 0.001, 0.171]}
    doc["endoscope"].update(port={"estimate": [-0.06, -0.08, 0.18], "position": [-0.06, -0.08, 0.18]},
                            look_at=[-0.06, 0.0, 0.35], depth=[0.02, 0.25])
    doc["setup"]["arm_clearance"] = CLEARANCE
    doc["fields"] = {"resolution": 0.008, "region": {"x": [-0.11, 0.0], "y": [-0.04, 0.04], "z": [0.27, 0.43]}}
    doc["query"] = [{"name": "up past the right arm", "arm": "left", "start": START, "goal": GOAL}]
    return doc
