"""What a port-placement recording shows (``errplan tolerance --record``), for planar and spatial
``port_placement`` results.
rerun comes from :mod:`.sdk`.

Per query ``q`` (its name as one entity-path part):

planar, in one 2-D space ``placement/<q>/plane`` with errplan's tip-plane convention (a point
``[y, z]`` drawn at ``(z, -y)``: z to the right, y up; metres):

- ``coverage``: the coverage over the candidate grid, a heat map (``DepthImage``, Viridis, 0..1,
  placed in metres: pixel = one candidate cell);
- ``candidates``: every candidate port, labelled with its coverage;
- ``best`` (and ``refined``): the best port of the grid (and the refined one);
- ``region``: the task region's outline;
- ``certified``, ``not_certified``, ``unreachable``: the task-region grid points of the best port
  (robustly reachable with ``rho* <= 1 - certify_margin``; reachable but not; not reachable);
- ``rho_star``: the best port's ``rho*`` over the region grid (``DepthImage``, Plasma, 0..1).

spatial, in a 3-D space ``placement/<q>/space`` (``[x, y, z]``, y up) with the same entities (the
coverage as coloured cubes, one per candidate, the region as a box), and the coverage volume as
slices ``placement/<q>/slices/x_<mm>``: one heat map over ``(y, z)`` per candidate ``x``, with the
best port marked on its slice.

On the body wall (``candidates = "body_wall"``, 3-D), in ``placement/<q>/space``:

- ``anatomy/body_wall`` (ellipsoid or mesh) and ``anatomy/<obstacle>``: the anatomy as meshes;
- ``candidates``: every candidate port on the wall, coloured by its coverage (Viridis, 0..1) and
  labelled with it; ``best``: the best port; ``region``: the task region as a box.

``placement/<q>/summary``: a markdown table of the top candidates.
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ..errors import ErrplanError
from . import sdk
from .style import BEST_COLOR, CERTIFIED_COLOR, NOT_CERTIFIED_COLOR, REFINED_COLOR, REGION_COLOR, UNREACHABLE_COLOR, entity_names as _names, uv, viridis


def _results(results) -> list:
    if hasattr(results, "kind"):
        results = [results]
    out = [r for r in results if r.kind == "port_placement"]
    for r in out:
        if "_arrays" not in r.data and not _on_wall(r):
            raise ErrplanError(f"{r.name}: the placement result holds no arrays to record (keep_arrays=False)")
    return out


def _on_wall(r) -> bool:
    return bool(r.data.get("candidate_grid", {}).get("body_wall"))


def heat_image(values: np.ndarray, ya: np.ndarray, za: np.ndarray) -> tuple[np.ndarray, list, list]:
    """A (ny, nz) array over axes ``y``, ``z`` as a depth image (rows y descending, cols z ascending;
    values 0 raised to 1e-6 so that they are drawn, NaN not drawn), its translation and scale (one
    pixel per cell, centred on its grid point). Degenerate axes get the other axis' step (or 1 mm)."""
    img = np.where(np.isfinite(values), np.maximum(values, 1e-6), 0.0)[::-1, :].astype(np.float32)
    sy = float(ya[1] - ya[0]) if len(ya) > 1 else None
    sz = float(za[1] - za[0]) if len(za) > 1 else None
    sy = sy or sz or 0.001
    sz = sz or sy
    return img, [float(za[0] - sz / 2), float(-ya[-1] - sy / 2), 0.0], [sz, sy, 1.0]


def summary_markdown(r, top: int = 10) -> str:
    d = r.data
    m = d["region_points"]
    lines = [f"# port placement: {r.name}", "",
             f"{d['candidate_grid']['count']} candidate ports at {1000 * d['candidate_grid']['spacing']:g} mm; "
             f"task region of {m} points at {1000 * d['region_grid']['resolution']:g} mm; covered = "
             f"{d['criterion']}; ties: {d['tie_break']}.", "",
             "| rank | port (mm) | coverage | covered | max rho* |", "|---|---|---|---|---|"]
    for rank, i in enumerate(d["ranking"][:top], 1):
        c = d["candidates"][i]
        rho = c["max_rho_star"]
        lines.append(f"| {rank} | {', '.join(f'{1000 * v:.1f}' for v in c['port'])} | {100 * c['coverage']:.1f}% | "
                     f"{c['covered']}/{m} | {'-' if rho is None or not math.isfinite(rho) else f'{rho:.3f}'} |")
    if "refined" in d:
        f = d["refined"]
        lines.append(f"| refined | {', '.join(f'{1000 * v:.1f}' for v in f['port'])} | {100 * f['coverage']:.1f}% | "
                     f"{f['covered']}/{m} | {f['max_rho_star']:.3f} |" if f["max_rho_star"] is not None and
                     math.isfinite(f["max_rho_star"]) else
                     f"| refined | {', '.join(f'{1000 * v:.1f}' for v in f['port'])} | {100 * f['coverage']:.1f}% | "
                     f"{f['covered']}/{m} | - |")
    return "\n".join(lines) + "\n"


def _region_classes(A: dict, prefix: str = "best") -> dict[str, np.ndarray]:
    valid = np.asarray(A[f"{prefix}_valid"], bool)
    rho = np.asarray(A[f"{prefix}_rho_star"], float)
    with np.errstate(invalid="ignore"):
        cert = valid & np.isfinite(rho) & (rho <= A["bound"]) & (rho < 1.0)
    X = np.asarray(A["region_points"], float)
    return {"certified": X[cert], "not_certified": X[valid & ~cert], "unreachable": X[~valid]}


def placement_blueprint(rr, results, sc) -> Any:
    """The default layout: per query its plane (2-D) or its space and slices (3-D), and its summary."""
    rrb = rr.blueprint
    results = _results(results)
    tabs = []
    for r, q in zip(results, _names(results)):
        base = f"placement/{q}"
        if _on_wall(r):
            main = rrb.Spatial3DView(origin=f"{base}/space", name=f"{r.name}: coverage over ports on the body wall")
            tabs.append(rrb.Horizontal(main, rrb.TextDocumentView(origin=f"{base}/summary", name="top candidates"),
                                       column_shares=[3, 1], name=r.name))
        elif sc.dim == 2:
            main = rrb.Spatial2DView(origin=f"{base}/plane", name=f"{r.name}: coverage over candidate ports")
            tabs.append(rrb.Horizontal(main, rrb.TextDocumentView(origin=f"{base}/summary", name="top candidates"),
                                       column_shares=[3, 1], name=r.name))
        else:
            xs = r.data["_arrays"]["candidate_axes"][0]
            slices = [rrb.Spatial2DView(origin=f"{base}/slices/{_slice_name(x)}", name=f"x = {1000 * x:.1f} mm")
                      for x in xs]
            main = rrb.Spatial3DView(origin=f"{base}/space", name=f"{r.name}: coverage over candidate ports")
            tabs.append(rrb.Horizontal(main, rrb.Vertical(rrb.Tabs(*slices, name="coverage slices"),
                                                          rrb.TextDocumentView(origin=f"{base}/summary",
                                                                               name="top candidates")),
                                       column_shares=[3, 2], name=r.name))
    return rrb.Blueprint(rrb.Tabs(*tabs) if len(tabs) > 1 else tabs[0], collapse_panels=True)


def _slice_name(x: float) -> str:
    return f"x_{1000 * x:+.1f}mm".replace(".", "p").replace("+", "p").replace("-", "m")


def log_placement(rec, rr, results, sc) -> None:
    """Log one or more ``port_placement`` :class:`errplan.tolerance.ToleranceResult` (with their
    ``_arrays``) of scenario ``sc`` into recording ``rec`` with the rerun module ``rr``."""
    results = _results(results)
    for r, q in zip(results, _names(results)):
        if _on_wall(r):
            _log_wall(rec, rr, r, f"placement/{q}", sc)
        elif sc.dim == 2:
            _log_plane(rec, rr, r, f"placement/{q}")
        else:
            _log_space(rec, rr, r, f"placement/{q}")
        rec.log(f"placement/{q}/summary", rr.TextDocument(summary_markdown(r), media_type="text/markdown"),
                static=True)


def _labels(d: dict) -> list[str]:
    return [f"{100 * c['coverage']:.1f}%" for c in d["candidates"]]


def _log_plane(rec, rr, r, base: str) -> None:
    ui = rr.Radius.ui_points
    d, A = r.data, r.data["_arrays"]
    ya, za = A["candidate_axes"]
    img, tr, scale = heat_image(A["coverage"], ya, za)
    p = f"{base}/plane"
    rec.log(f"{p}/coverage", rr.Transform3D(translation=tr, scale=scale), static=True)
    rec.log(f"{p}/coverage", rr.DepthImage(img, meter=1.0, colormap="Viridis", depth_range=(0.0, 1.0),
                                           draw_order=-10.0), static=True)
    ports = np.array([c["port"] for c in d["candidates"]], float)
    rec.log(f"{p}/candidates", rr.Points2D(uv(ports), radii=ui(2.0), colors=(230, 230, 230), labels=_labels(d),
                                           show_labels=False, draw_order=20.0), static=True)
    rec.log(f"{p}/best", rr.Points2D(uv([d["best"]]), radii=ui(7.0), colors=BEST_COLOR,
                                     labels=[f"best port {100 * d['coverage']:.1f}%"], draw_order=40.0), static=True)
    if "refined" in d:
        f = d["refined"]
        rec.log(f"{p}/refined", rr.Points2D(uv([f["port"]]), radii=ui(5.0), colors=REFINED_COLOR,
                                            labels=[f"refined {100 * f['coverage']:.1f}%"], draw_order=41.0),
                static=True)
    (y0, y1), (z0, z1) = d["region"]["y"], d["region"]["z"]
    box = np.array([[y0, z0], [y1, z0], [y1, z1], [y0, z1], [y0, z0]])
    rec.log(f"{p}/region", rr.LineStrips2D([uv(box)], colors=REGION_COLOR, radii=ui(1.5), labels=["task region"],
                                           draw_order=30.0), static=True)
    ra, rz = A["region_axes"]
    rho = np.asarray(A["best_rho_star"], float).reshape(len(ra), len(rz))
    rho = np.where(np.asarray(A["best_valid"], bool).reshape(rho.shape), rho, np.nan)
    img, tr, scale = heat_image(rho, ra, rz)
    rec.log(f"{p}/rho_star", rr.Transform3D(translation=tr, scale=scale), static=True)
    rec.log(f"{p}/rho_star", rr.DepthImage(img, meter=1.0, colormap="Plasma", depth_range=(0.0, 1.0),
                                           draw_order=-9.0), static=True)
    for name, pts in _region_classes(A).items():
        col = {"certified": CERTIFIED_COLOR, "not_certified": NOT_CERTIFIED_COLOR}.get(name, UNREACHABLE_COLOR)
        rec.log(f"{p}/{name}", rr.Points2D(uv(pts.reshape(-1, 2)), radii=ui(2.5), colors=col, draw_order=25.0),
                static=True)


def _log_wall(rec, rr, r, base: str, sc) -> None:
    """A body-wall placement: the wall and the obstacles as meshes, the candidate ports on the wall
    coloured by coverage, the best port and the task region (module docstring)."""
    from ..fields.compute import anatomy_model
    from .space import OBSTACLE_COLOR, WALL_COLOR

    ui = rr.Radius.ui_points
    d = r.data
    s = f"{base}/space"
    rec.log(s, rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
    an = anatomy_model(sc)
    for srf in an.surfaces:
        rec.log(f"{s}/anatomy/{srf.name}", rr.Mesh3D(vertex_positions=srf.vertices, triangle_indices=srf.faces,
                                                     albedo_factor=OBSTACLE_COLOR), static=True)
    wm = an.wall_mesh()
    rec.log(f"{s}/anatomy/body_wall", rr.Mesh3D(vertex_positions=wm[0], triangle_indices=wm[1],
                                                albedo_factor=WALL_COLOR), static=True)
    ports = np.array([c["port"] for c in d["candidates"]], float).reshape(-1, 3)
    cov = np.array([c["coverage"] for c in d["candidates"]], float)
    rec.log(f"{s}/candidates", rr.Points3D(ports, radii=ui(4.0), colors=viridis(cov), labels=_labels(d),
                                           show_labels=False), static=True)
    rec.log(f"{s}/best", rr.Points3D([d["best"]], radii=ui(9.0), colors=BEST_COLOR,
                                     labels=[f"best port {100 * d['coverage']:.1f}%"]), static=True)
    lo = np.array([d["region"][a][0] for a in ("x", "y", "z")])
    hi = np.array([d["region"][a][1] for a in ("x", "y", "z")])
    rec.log(f"{s}/region", rr.Boxes3D(centers=[(lo + hi) / 2], half_sizes=[(hi - lo) / 2], colors=REGION_COLOR,
                                      labels=["task region"]), static=True)


def _log_space(rec, rr, r, base: str) -> None:
    ui = rr.Radius.ui_points
    d, A = r.data, r.data["_arrays"]
    s = f"{base}/space"
    rec.log(s, rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
    ports = np.array([c["port"] for c in d["candidates"]], float)
    cov = np.array([c["coverage"] for c in d["candidates"]], float)
    h = 0.3 * float(d["candidate_grid"]["spacing"])
    rec.log(f"{s}/coverage", rr.Boxes3D(centers=ports, half_sizes=np.full_like(ports, h), colors=viridis(cov),
                                        fill_mode="solid", labels=_labels(d), show_labels=False), static=True)
    rec.log(f"{s}/best", rr.Points3D([d["best"]], radii=ui(8.0), colors=BEST_COLOR,
                                     labels=[f"best port {100 * d['coverage']:.1f}%"]), static=True)
    if "refined" in d:
        f = d["refined"]
        rec.log(f"{s}/refined", rr.Points3D([f["port"]], radii=ui(6.0), colors=REFINED_COLOR,
                                            labels=[f"refined {100 * f['coverage']:.1f}%"]), static=True)
    lo = np.array([d["region"][a][0] for a in ("x", "y", "z")])
    hi = np.array([d["region"][a][1] for a in ("x", "y", "z")])
    rec.log(f"{s}/region", rr.Boxes3D(centers=[(lo + hi) / 2], half_sizes=[(hi - lo) / 2], colors=REGION_COLOR,
                                      labels=["task region"]), static=True)
    for name, pts in _region_classes(A).items():
        col = {"certified": CERTIFIED_COLOR, "not_certified": NOT_CERTIFIED_COLOR}.get(name, UNREACHABLE_COLOR)
        rec.log(f"{s}/{name}", rr.Points3D(pts.reshape(-1, 3), radii=ui(2.5), colors=col), static=True)
    xa, ya, za = A["candidate_axes"]
    best = np.asarray(d["best"], float)
    for i, x in enumerate(xa):
        sl = f"{base}/slices/{_slice_name(x)}"
        img, tr, scale = heat_image(A["coverage"][i], ya, za)
        rec.log(f"{sl}/coverage", rr.Transform3D(translation=tr, scale=scale), static=True)
        rec.log(f"{sl}/coverage", rr.DepthImage(img, meter=1.0, colormap="Viridis", depth_range=(0.0, 1.0),
                                                draw_order=-10.0), static=True)
        yz = np.stack(np.meshgrid(ya, za, indexing="ij"), -1).reshape(-1, 2)
        labels = [f"{100 * v:.1f}%" for v in np.asarray(A["coverage"][i]).ravel()]
        rec.log(f"{sl}/candidates", rr.Points2D(uv(yz), radii=ui(2.0), colors=(230, 230, 230), labels=labels,
                                                show_labels=False, draw_order=20.0), static=True)
        if abs(x - best[0]) < 1e-12:
            rec.log(f"{sl}/best", rr.Points2D(uv([best[1:]]), radii=ui(7.0), colors=BEST_COLOR,
                                              labels=[f"best port {100 * d['coverage']:.1f}%"], draw_order=40.0),
                    static=True)


def write_placement(rr, path, sc, results: Iterable, *, app_id: str = "errplan") -> None:
    """Write one ``.rrd`` of ``port_placement`` results: a temporary file renamed at the end, so
    nothing half-written on error. ``rr`` is the rerun module (errplan.recording passes it)."""
    path = Path(path)
    if not path.parent.exists():
        raise ErrplanError(f"--record {path}: directory {path.parent} does not exist")
    results = _results(results)
    tmp = path.with_name(path.name + ".part")
    rec = rr.RecordingStream(app_id, recording_id=f"errplan-placement-{sc.name}", send_properties=False)
    rec.save(tmp, default_blueprint=placement_blueprint(rr, results, sc))
    try:
        log_placement(rec, rr, results, sc)
        rec.flush()
    finally:
        rec.disconnect()
    os.replace(tmp, path)


def record_placement(path: str | os.PathLike, sc, results, *, app_id: str = "errplan") -> None:
    """Write the .rrd of port-placement results (``errplan tolerance --record``): the coverage over
    the candidate grid as a heat map (slices in 3-D) with the best port, the task region and its
    certified part (drawn by :mod:`errplan.placement_view`, which is handed the rerun module)."""
    rr = sdk.rerun()

    write_placement(rr, path, sc, results, app_id=app_id)
