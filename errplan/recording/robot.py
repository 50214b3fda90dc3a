"""A URDF robot in a recording: rerun's URDF loader with the arm's package folders (the scenario's
``package_path``, ``ROS_PACKAGE_PATH`` and the installed description packages, :mod:`errplan.packages`)."""
from __future__ import annotations

import os

from .. import packages
from . import sdk


def _log_urdf(tree, rec, arm) -> None:
    """Log the arm's URDF (meshes resolved through its package path) with rerun's URDF loader;
    ROS_PACKAGE_PATH is set for the call and restored after."""
    env = _package_env(arm)
    saved = os.environ.get("ROS_PACKAGE_PATH")
    try:
        os.environ.update(env)
        tree.log_urdf_to_recording(rec)
    finally:
        if saved is None:
            os.environ.pop("ROS_PACKAGE_PATH", None)
        else:
            os.environ["ROS_PACKAGE_PATH"] = saved


def _mesh_uris(urdf_text: str) -> list[str]:
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(urdf_text)
    except ET.ParseError:
        return []
    return [m.get("filename", "") for m in root.iter("mesh")]


def _package_env(arm) -> dict:
    """``ROS_PACKAGE_PATH`` for rerun's URDF importer: every folder errplan resolves ``package://`` URIs in
    (the scenario's ``package_path`` against the URDF's folder, the environment's, the installed
    description packages), so the recording finds the same meshes errplan does."""
    return {"ROS_PACKAGE_PATH": packages.ros_package_path(arm.package_path, arm.urdf_path.parent)}


def _load_urdf_tree(arm):
    """``rerun.urdf.UrdfTree`` of the arm's URDF under ``world/<robot name>`` (mesh URIs resolved
    through :func:`_package_env`), or None when rerun cannot read it."""
    ru = sdk.urdf()

    env = _package_env(arm)
    saved = {k: os.environ.get(k) for k in env}
    try:
        os.environ.update(env)
        # (the prefix is one entity-path part: the robot lands under world/<robot name>/...)
        return ru.UrdfTree.from_file_path(str(arm.urdf_path), "world", frame_prefix="robot/")
    except Exception:  # rerun's importer refused the file: the links are drawn as lines
        return None
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
