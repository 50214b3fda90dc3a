"""rerun recordings of errplan results (rerun-sdk 0.41), one module per view:

- :mod:`.plane`: the planar plan (fields, workspace, paths, simulations, series, gains);
- :mod:`.space`: the 3-D plan (the robot from its URDF replaying the runs, field slices and surfaces);
- :mod:`.calibration`: ``errplan calibrate --record`` (residuals before and after, replays), plane and 3-D;
- :mod:`.placement`: ``errplan tolerance --record`` (port-placement coverage);
- :mod:`.setup`: several arms and the endoscope (``errplan plan SETUP --record``) and triad placement
  (``errplan tolerance SETUP --record``), with :mod:`.arms` (an arm's URDF geometry at a configuration);

below them :mod:`.robot` (a URDF robot in a recording), :mod:`.shapes` (images, edges, slices and
surfaces, numpy), :mod:`.style` (colours and names) and :mod:`.sdk`, the only module of errplan that
imports rerun (views get its modules from there) and the atomic writer every recording goes through.
"""
from __future__ import annotations

import os

from . import sdk
from .calibration import record_calibration, residual_map
from .placement import record_placement, write_placement
from .plane import _log_plan, blueprint
from .shapes import field_image, level_surface, slice_mesh, workspace_edges
from .space import SpatialScene, _log_plan_spatial, blueprint_spatial, expected_rows
from .placement import heat_image
from .setup import record_setup_plan, record_triad
from .style import entity_name, entity_names, turbo, uv, viridis

__all__ = ["record_plan", "record_setup_plan", "record_triad", "record_calibration", "record_placement", "write_placement", "entity_name", "entity_names",
           "uv", "turbo", "viridis", "heat_image", "field_image", "workspace_edges", "slice_mesh", "level_surface", "residual_map",
           "expected_rows"]


def record_plan(path: str | os.PathLike, sc, mf, runs, *, app_id: str = "errplan") -> None:
    """Write one ``.rrd`` with the fields, workspace, ports, paths, gains and simulations (planar: the tip
    plane, :mod:`.plane`; spatial: the 3-D scene, :mod:`.space`). Nothing half-written on error."""
    fields_logged = [n for n in ("G_norm", "phi_hat_max", "rho_star") if getattr(mf, n, None) is not None]
    if sc.dim == 3:
        scene = SpatialScene(sc, mf, runs)
        bp, log = blueprint_spatial(runs, scene), lambda rec, rr: _log_plan_spatial(rec, rr, sc, mf, runs, scene)
    else:
        bp, log = blueprint(runs, fields_logged), lambda rec, rr: _log_plan(rec, rr, sc, mf, runs, fields_logged)
    sdk.write(path, app_id, f"errplan-{sc.name}", bp, log)
