"""The calibration views (:func:`record_calibration`, ``errplan calibrate --record``), planar and 3-D.


Calibration recordings (:func:`record_calibration`), all in the same ``plane`` space:

- ``plane/port/true``, ``plane/port/estimate`` (``Points2D``), static;
- ``plane/data/tracked``: every tracked tip of the fitting data (``Points2D``), static;
- ``plane/residual/before``, ``plane/residual/after``: the pose residual (tracked minus model
  tip) of every row as an arrow from the model tip, magnified by ``CAL_ARROW_GAIN`` (the same for
  both, so their lengths compare), coloured by length relative to the noise floor;
- ``plane/residual_map/before``, ``plane/residual_map/after``: the residual map — the mean residual
  over 10 mm cells (noise averages out, structure stays), magnified by ``CAL_MAP_GAIN``, coloured
  by the cell's mean residual over the noise floor (green <= 1, red >= 4): where a structured
  residual is left after the selected model;
- ``plane/replay/measured``, ``plane/replay/before``, ``plane/replay/after``: each run's measured
  tracked path and the controller replayed on the declared and on the corrected model;
- ``summary``: the readable report (``TextDocument``).

A spatial calibration (:func:`record_calibration` on a 3-D report) in one ``world`` space (y up):

- ``world/robot/**``: the robot from its URDF (meshes when they resolve, links as lines when they
  do not) at the median encoder reading of the data; ``world/port/true``, ``world/port/estimate``;
- ``world/data/tracked``: every tracked tip (``Points3D``);
- ``world/residual/before``, ``world/residual/after``: every row's pose residual as a 3-D arrow
  from the model tip, x``CAL_ARROW_GAIN``, coloured from green (noise floor) to red (4 floors);
- ``world/residual_map/before|after``: the mean residual over 10 mm cubes, x``CAL_MAP_GAIN``;
- ``world/replay/measured|before|after``: each run's measured path and the controller replayed on
  the declared and on the corrected model; ``summary``: the report.
"""
from __future__ import annotations

import math
import os

import numpy as np

from ..kinematics.urdf import rpy_matrix
from . import sdk
from .robot import _load_urdf_tree, _log_urdf
from .style import DIRECT_COLOR, PLANNED_COLOR, PORT_EST_COLOR, PORT_TRUE_COLOR, port_labels, uv

CAL_ARROW_GAIN = 10.0
CAL_MAP_GAIN = 20.0
CAL_CELL = 0.010


def _cal_colors(length: np.ndarray, noise: float) -> np.ndarray:
    """Green (<= 1 noise floor) to red (>= 4 noise floors), RGB uint8 (n, 3)."""
    t = np.clip((np.asarray(length, float) / max(noise, 1e-12) - 1.0) / 3.0, 0.0, 1.0)
    return np.stack([60 + 195 * t, 220 - 170 * t, 80 - 40 * t], axis=-1).astype(np.uint8)


def residual_map(points: np.ndarray, residual: np.ndarray, cell: float = CAL_CELL) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean residual per ``cell``-sized square (cube in 3-D) of the tips: centres (m, d), mean
    residual (m, d), rows per cell (m,)."""
    p = np.asarray(points, float)
    d = p.shape[1]
    key = np.floor(p / cell).astype(np.int64)
    uniq, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    mean = np.zeros((len(uniq), d))
    np.add.at(mean, inv, residual)
    mean /= counts[:, None]
    centre = np.zeros((len(uniq), d))
    np.add.at(centre, inv, p)
    centre /= counts[:, None]
    return centre, mean, counts


def calibration_blueprint():
    rrb = sdk.blueprint()

    common = ["+ plane/port/**", "+ plane/data/**"]
    before = rrb.Spatial2DView(origin="plane", name="residual before (declared model), x10 arrows",
                               contents=common + ["+ plane/residual/before", "+ plane/residual_map/before"])
    after = rrb.Spatial2DView(origin="plane", name="residual after (corrected model), x10 arrows",
                              contents=common + ["+ plane/residual/after", "+ plane/residual_map/after"])
    maps = rrb.Spatial2DView(origin="plane", name="residual map after (10 mm cells, x20)",
                             contents=common + ["+ plane/residual_map/after"])
    replay = rrb.Spatial2DView(origin="plane", name="paths: measured (white), replayed before (red) / after (green)",
                               contents=["+ plane/port/**", "+ plane/replay/**"])
    return rrb.Blueprint(rrb.Horizontal(rrb.Tabs(before, after, maps, replay),
                                        rrb.TextDocumentView(origin="summary", name="report"),
                                        column_shares=[3, 2]), collapse_panels=True)


def record_calibration(report, path: str | os.PathLike, sc=None, *, app_id: str = "errplan") -> None:
    """Write the ``.rrd`` of an :class:`errplan.calibration.CalibrationReport` (the module docstring says
    what it shows). Nothing half-written on error."""
    spatial = np.asarray(report.points).shape[-1] == 3
    bp = calibration_blueprint_spatial() if spatial else calibration_blueprint()
    log = _log_calibration_spatial if spatial else _log_calibration
    sdk.write(path, app_id, f"errplan-calibrate-{report.scenario}", bp, lambda rec, rr: log(rec, rr, report, sc))


def _extent(points, sc) -> float:
    """The size (m) of what the view shows: the measured tips and the ports."""
    p = np.vstack([np.asarray(points, float).reshape(-1, len(sc.port.position)), [sc.port.position],
                   [sc.port.estimate]])
    return float(np.max(p.max(axis=0) - p.min(axis=0)))


def _log_calibration(rec, rr, report, sc) -> None:
    ui = rr.Radius.ui_points
    noise = float(report.noise.sigma)
    pts = np.asarray(report.points, float)
    if sc is not None:
        lt, le = port_labels(sc.port.position, sc.port.estimate, _extent(pts, sc), "true port (declared)")
        rec.log("plane/port/true", rr.Points2D(uv([sc.port.position]), colors=PORT_TRUE_COLOR, radii=ui(6.0),
                                               labels=lt, draw_order=30.0), static=True)
        rec.log("plane/port/estimate", rr.Points2D(uv([sc.port.estimate]), colors=PORT_EST_COLOR, radii=ui(6.0),
                                                   labels=le, draw_order=30.0), static=True)
    rec.log("plane/data/tracked", rr.Points2D(uv(report.tracked), colors=(150, 150, 150), radii=ui(1.0),
                                              draw_order=5.0), static=True)
    for kind, r in (("before", report.residual_before), ("after", report.residual_after)):
        r = np.asarray(r, float)
        length = np.linalg.norm(r, axis=-1) / math.sqrt(2.0)  # per-coordinate scale, like the noise floor
        rec.log(f"plane/residual/{kind}",
                rr.Arrows2D(origins=uv(pts), vectors=uv(CAL_ARROW_GAIN * r), colors=_cal_colors(length, noise),
                            radii=ui(0.75), draw_order=10.0), static=True)
        centre, mean, counts = residual_map(pts, r)
        mlen = np.linalg.norm(mean, axis=-1) / math.sqrt(2.0)
        labels = [f"{1000 * m:.3f} mm ({n} rows)" for m, n in zip(np.linalg.norm(mean, axis=-1), counts)]
        rec.log(f"plane/residual_map/{kind}",
                rr.Arrows2D(origins=uv(centre), vectors=uv(CAL_MAP_GAIN * mean), colors=_cal_colors(mlen, noise),
                            radii=ui(2.0), labels=labels, show_labels=False, draw_order=12.0), static=True)
    d = report.data
    if d is not None:
        for kind, tips, col in (("measured", d.tip, (255, 255, 255)), ("before", report.replay_before, DIRECT_COLOR),
                                ("after", report.replay_after, PLANNED_COLOR)):
            strips = [uv(np.asarray(tips)[d.run == r]) for r in range(d.runs)]
            rec.log(f"plane/replay/{kind}", rr.LineStrips2D(strips, colors=col, radii=ui(1.0 if kind == "measured" else 0.75),
                                                            draw_order=20.0), static=True)
    text = ("# errplan calibrate\n\nArrows: residual (tracked minus model tip) x"
            f"{CAL_ARROW_GAIN:g}; residual map: mean over {CAL_CELL * 1000:g} mm cells x{CAL_MAP_GAIN:g}; colour: "
            "green at or below the noise floor, red at 4 noise floors or more.\n\n```\n" + report.text() + "\n```\n")
    rec.log("summary", rr.TextDocument(text, media_type="text/markdown"), static=True)


def calibration_blueprint_spatial():
    rrb = sdk.blueprint()

    common = ["+ world/robot/**", "+ world/port/**", "+ world/data/**"]
    views = [rrb.Spatial3DView(origin="world", name=name, contents=common + extra) for name, extra in (
        ("residual before (declared model), x10 arrows", ["+ world/residual/before", "+ world/residual_map/before"]),
        ("residual after (corrected model), x10 arrows", ["+ world/residual/after", "+ world/residual_map/after"]),
        ("residual map after (10 mm cubes, x20)", ["+ world/residual_map/after"]),
        ("paths: measured (white), replayed before (red) / after (green)", ["+ world/replay/**"]))]
    return rrb.Blueprint(rrb.Horizontal(rrb.Tabs(*views), rrb.TextDocumentView(origin="summary", name="report"),
                                        column_shares=[3, 2]), collapse_panels=True)


def _log_calibration_robot(rec, rr, sc, q) -> dict:
    """The scenario's URDF robot at encoder reading ``q`` (static): the URDF tree when rerun reads
    it, else (and always, as a thin overlay) the chain as lines."""
    from ..kinematics import arm_for

    arm = arm_for(sc.robot)
    ui = rr.Radius.ui_points
    tree = _load_urdf_tree(arm)
    if tree is not None:
        _log_urdf(tree, rec, arm)
        rec.log("world/robot/placement",
                rr.Transform3D(translation=list(arm.base_position), mat3x3=rpy_matrix(arm.base_rpy),
                               parent_frame="tf#/world", child_frame=f"robot/{tree.root_link().name}"), static=True)
        values = dict(arm.fixed_joints)
        values.update({name: float(v) for name, v in zip(arm.joint_names, q)})
        for name, val in values.items():
            j = tree.get_joint_by_name(name)
            if j is not None and j.joint_type != "fixed":
                rec.log(f"world/robot/joints/{name}", j.compute_transform(float(val), clamp=False), static=True)
    chain = arm.chain_points(np.asarray(q, float)[None])[0]
    rec.log("world/robot/links", rr.LineStrips3D([chain], colors=(200, 200, 215), radii=ui(2.0)), static=True)
    return {"urdf_loaded": tree is not None}


def _log_calibration_spatial(rec, rr, report, sc) -> None:
    ui = rr.Radius.ui_points
    noise = float(report.noise.sigma)
    pts = np.asarray(report.points, float)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
    d = report.data
    if sc is not None:
        if d is not None and d.rows:
            _log_calibration_robot(rec, rr, sc, np.median(d.q, axis=0))
        lt, le = port_labels(sc.port.position, sc.port.estimate, _extent(report.points, sc),
                             "true port (declared)")
        rec.log("world/port/true", rr.Points3D([sc.port.position], colors=PORT_TRUE_COLOR, radii=ui(6.0),
                                               labels=lt), static=True)
        rec.log("world/port/estimate", rr.Points3D([sc.port.estimate], colors=PORT_EST_COLOR, radii=ui(6.0),
                                                   labels=le), static=True)
    rec.log("world/data/tracked", rr.Points3D(report.tracked, colors=(150, 150, 150), radii=ui(1.0)), static=True)
    for kind, r in (("before", report.residual_before), ("after", report.residual_after)):
        r = np.asarray(r, float)
        length = np.linalg.norm(r, axis=-1) / math.sqrt(3.0)  # per-coordinate scale, like the noise floor
        rec.log(f"world/residual/{kind}",
                rr.Arrows3D(origins=pts, vectors=CAL_ARROW_GAIN * r, colors=_cal_colors(length, noise),
                            radii=ui(0.75)), static=True)
        centre, mean, counts = residual_map(pts, r)
        mlen = np.linalg.norm(mean, axis=-1) / math.sqrt(3.0)
        labels = [f"{1000 * m:.3f} mm ({n} rows)" for m, n in zip(np.linalg.norm(mean, axis=-1), counts)]
        rec.log(f"world/residual_map/{kind}",
                rr.Arrows3D(origins=centre, vectors=CAL_MAP_GAIN * mean, colors=_cal_colors(mlen, noise),
                            radii=ui(2.0), labels=labels, show_labels=False), static=True)
    if d is not None:
        for kind, tips, col in (("measured", d.tip, (255, 255, 255)), ("before", report.replay_before, DIRECT_COLOR),
                                ("after", report.replay_after, PLANNED_COLOR)):
            strips = [np.asarray(tips)[d.run == r] for r in range(d.runs)]
            rec.log(f"world/replay/{kind}", rr.LineStrips3D(strips, colors=col,
                                                            radii=ui(1.0 if kind == "measured" else 0.75)), static=True)
    text = ("# errplan calibrate (3-D)\n\nArrows: residual (tracked minus model tip) x"
            f"{CAL_ARROW_GAIN:g}; residual map: mean over {CAL_CELL * 1000:g} mm cubes x{CAL_MAP_GAIN:g}; colour: "
            "green at or below the noise floor, red at 4 noise floors or more. The robot is drawn at the median "
            "encoder reading of the data.\n\n```\n" + report.text() + "\n```\n")
    rec.log("summary", rr.TextDocument(text, media_type="text/markdown"), static=True)
