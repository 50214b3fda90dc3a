"""rerun recordings of errplan results (rerun-sdk 0.41). The only module that imports rerun.

Coordinates: everything lives in one 2-D space ``plane`` in metres. The viewer's 2-D axes point
right and down, so a tip ``[y, z]`` is drawn at ``(u, v) = (z, -y)``: z (toward the patient) to the
right, y up. A field image is placed in metres by a ``Transform3D`` on its own entity
(translation to the grid's corner, scale = the grid resolution), so pixel ``(col, row)`` covers
the grid cell of ``(z, y)`` it samples.

Plan recordings (:func:`record_plan`):

- ``plane/fields/{G_norm,phi_hat_max,rho_star}``: colormapped ``DepthImage`` (0 = outside the
  workspace, not drawn), static;
- ``plane/workspace``: the robust workspace boundary (``LineStrips2D``, cell edges), static;
- ``plane/port/true``, ``plane/port/estimate`` (``Points2D``), ``plane/port/error_box``, static;
- ``plane/<query>/planned``, ``plane/<query>/direct``: the paths (``LineStrips2D``), static;
  ``plane/<query>/segments``: segment ends labelled with their gain and certified ``||G||``;
- ``plane/<query>/sim/{planned,direct}/trajectory`` (static, whole run) and ``.../tip`` (one row
  per step on the ``step`` timeline); ``plane/<query>/corners/{planned,direct}``: the replays
  under every corner of the error box (static);
- ``series/<query>/{planned,direct}/error`` and ``.../phi``: error length (m) and the angle
  between desired and actual motion (rad) per step (``Scalars`` on ``step``);
- ``gains/<query>/{gain,certified_G_norm}``: per segment on the ``segment`` timeline;
- ``summary``: a markdown table (``TextDocument``).

A blueprint opens on the tip plane with the ``||G||`` field, the paths and the trajectories, the
error and angle series beside it, and tabs with the other fields and the summary.
"""
from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from .errors import ErrplanError

FIELD_RANGES = {"G_norm": (0.0, 1.2), "phi_hat_max": (0.0, math.pi / 2), "rho_star": (0.0, 1.0)}
FIELD_COLORMAPS = {"G_norm": "Turbo", "phi_hat_max": "Viridis", "rho_star": "Plasma"}
PLANNED_COLOR = (40, 220, 90)
DIRECT_COLOR = (240, 60, 60)
PORT_TRUE_COLOR = (255, 255, 255)
PORT_EST_COLOR = (255, 200, 0)


def uv(pts) -> np.ndarray:
    """Tip-plane points ``[y, z]`` (..., 2) -> viewer 2-D coordinates ``(z, -y)``."""
    p = np.asarray(pts, float)
    return np.stack([p[..., 1], -p[..., 0]], axis=-1)


def entity_name(name: str) -> str:
    """A query name as one entity-path part (letters, digits, ``-``, ``_``)."""
    s = re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_")
    return s or "query"


def entity_names(runs) -> list[str]:
    """One distinct entity-path part per query (``_2``, ``_3``... appended on collisions)."""
    out, seen = [], set()
    for r in runs:
        base = entity_name(r.name)
        q, i = base, 1
        while q in seen:
            i += 1
            q = f"{base}_{i}"
        seen.add(q)
        out.append(q)
    return out


def field_image(mf, name: str) -> tuple[np.ndarray, list[float], list[float]]:
    """Image (rows = y descending, cols = z ascending; 0 outside), translation and scale."""
    a = getattr(mf, name, None)
    if a is None:
        raise ErrplanError(f"field {name!r} was not computed")
    img = np.where(mf.valid & np.isfinite(a), a, 0.0)[::-1, :].astype(np.float32)
    res = mf.resolution
    # pixel (col j, row i) covers u in [u0 + j res, u0 + (j+1) res]: centred on z[j] and -y[ny-1-i]
    translation = [float(mf.z[0] - res / 2), float(-mf.y[-1] - res / 2), 0.0]
    return img, translation, [res, res, 1.0]


def workspace_edges(mf) -> np.ndarray:
    """Boundary of the valid grid cells as 2-point strips (n, 2, 2) in tip coordinates."""
    v = np.asarray(mf.valid, bool)
    res = mf.resolution
    y, z = mf.y, mf.z
    segs = []
    pad = np.zeros((v.shape[0] + 2, v.shape[1] + 2), bool)
    pad[1:-1, 1:-1] = v
    # edges between (i, j) and (i+1, j) along y: a horizontal (constant-y) edge of the pixel squares
    dy = pad[1:, 1:-1] != pad[:-1, 1:-1]          # (ny+1, nz)
    ii, jj = np.nonzero(dy)
    ye = y[0] + (ii - 0.5) * res
    segs.append(np.stack([np.stack([ye, z[jj] - res / 2], -1), np.stack([ye, z[jj] + res / 2], -1)], 1))
    dz = pad[1:-1, 1:] != pad[1:-1, :-1]          # (ny, nz+1)
    ii, jj = np.nonzero(dz)
    ze = z[0] + (jj - 0.5) * res
    segs.append(np.stack([np.stack([y[ii] - res / 2, ze], -1), np.stack([y[ii] + res / 2, ze], -1)], 1))
    return np.concatenate(segs) if segs else np.zeros((0, 2, 2))


def _merge_edges(edges: np.ndarray) -> list[np.ndarray]:
    """Chain unit cell edges into polylines (fewer, longer strips)."""
    from collections import defaultdict

    key = lambda p: (round(float(p[0]), 9), round(float(p[1]), 9))  # noqa: E731
    adj: dict = defaultdict(list)
    for i, (a, b) in enumerate(edges):
        adj[key(a)].append((i, key(b)))
        adj[key(b)].append((i, key(a)))
    used = np.zeros(len(edges), bool)
    strips = []
    for i in range(len(edges)):
        if used[i]:
            continue
        used[i] = True
        a, b = key(edges[i][0]), key(edges[i][1])
        line = [a, b]
        for direction in (0, 1):
            cur = line[-1] if direction == 0 else line[0]
            while True:
                nxt = next(((j, p) for j, p in adj[cur] if not used[j]), None)
                if nxt is None:
                    break
                used[nxt[0]] = True
                cur = nxt[1]
                if direction == 0:
                    line.append(cur)
                else:
                    line.insert(0, cur)
        strips.append(np.array(line))
    return strips


def _markdown_summary(sc, runs) -> str:
    if getattr(sc, "dim", 2) == 3:
        head = ("World frame [x, y, z] (m), y up, z toward the patient. Field slices: worst-case ||G|| at the "
                f"scenario gain {sc.controller.gain:g} (colormap Turbo, 0 to 1.2: red where it reaches 1 or more).")
    else:
        head = ("Tip plane: z (m) to the right, y (m) up. Field image: worst-case ||G|| at the scenario gain "
                f"{sc.controller.gain:g} (colormap Turbo, 0 to 1.2: red where it reaches 1 or more).")
    lines = [f"# errplan plan: {sc.name}", "", sc.description or "", "", head, ""]
    for r in runs:
        lines += [f"## {r.name}", "",
                  "| path | segments | gain | certified ‖G‖ | certified | steps | monotonic | corners monotonic |",
                  "|---|---|---|---|---|---|---|---|"]
        for kind in ("planned", "direct"):
            sched = r.schedule if kind == "planned" else r.direct_schedule
            sim = r.sim_planned if kind == "planned" else r.sim_direct
            reps = r.corner_planned if kind == "planned" else r.corner_direct
            g = sched.gains if kind == "planned" else np.array([r.direct_gain])
            cg = sched.max_certified_G_norm
            lines.append(f"| {kind} | {len(sched.segments)} | {g.min():.3g}–{g.max():.3g} | "
                         f"{cg:.3f} | {'yes' if sched.certified else 'no'} | {sim.sim.steps} | "
                         f"{'yes' if sim.sim.monotonic else 'no'} | {sum(x.sim.monotonic for x in reps)}/{len(reps)} |")
        lines += ["", "Segments (planned):", "", "| # | from | to | gain | certified ‖G‖ | step ratio |", "|---|---|---|---|---|---|"]
        for i, s in enumerate(r.schedule.segments):
            a = ", ".join(f"{v:.4f}" for v in s.start)
            b = ", ".join(f"{v:.4f}" for v in s.end)
            lines.append(f"| {i} | ({a}) | ({b}) | {s.gain:.4f} | {s.certified_G_norm:.4f} | {s.step_ratio:.4f} |")
        lines.append("")
    return "\n".join(lines)


def blueprint(runs, fields_logged: list[str]):
    """Tip plane (||G|| field, paths, trajectories) | series; tabs for other fields and the summary."""
    import rerun.blueprint as rrb

    # (entity-path filters only support a trailing "/**": list the corner entities one by one)
    names = entity_names(runs)
    corners = [f"- plane/{q}/corners/**" for q in names]
    hidden = [f"- plane/fields/{n}" for n in fields_logged if n != "G_norm"]
    main = rrb.Spatial2DView(origin="plane", contents=["+ plane/**"] + hidden + corners,
                             name="tip plane: z → (m), y ↑ (m); worst-case ||G|| field")
    others = [rrb.Spatial2DView(origin="plane", name=f"field {n}",
                                contents=["+ plane/**"] + [f"- plane/fields/{m}" for m in fields_logged if m != n]
                                + corners)
              for n in fields_logged if n != "G_norm"]
    others.append(rrb.Spatial2DView(origin="plane", name="replays under the error-box corners",
                                    contents=["+ plane/**"] + hidden + [f"- plane/{q}/sim/**" for q in names]))
    series = []
    for r, q in zip(runs, names):
        series.append(rrb.TimeSeriesView(origin=f"series/{q}",
                                         contents=[f"+ series/{q}/planned/error", f"+ series/{q}/direct/error"],
                                         name=f"{r.name}: error length (m) per step"))
        series.append(rrb.TimeSeriesView(origin=f"series/{q}",
                                         contents=[f"+ series/{q}/planned/phi", f"+ series/{q}/direct/phi"],
                                         name=f"{r.name}: φ (rad) per step"))
    gains = [rrb.TimeSeriesView(origin="gains", name="per-segment gain and certified ||G||")]
    # two queries (four plots) per tab
    groups = [rrb.Vertical(*series[i:i + 4], name="series: " + ", ".join(r.name for r in runs[i // 2:i // 2 + 2]))
              for i in range(0, len(series), 4)]
    right = rrb.Tabs(*groups, *gains, rrb.TextDocumentView(origin="summary", name="summary"), *others)
    return rrb.Blueprint(rrb.Horizontal(main, right, column_shares=[3, 2]), collapse_panels=True)


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


def record_placement(path: str | os.PathLike, sc, results, *, app_id: str = "errplan") -> None:
    """Write the .rrd of port-placement results (``errplan tolerance --record``): the coverage over
    the candidate grid as a heat map (slices in 3-D) with the best port, the task region and its
    certified part (drawn by :mod:`errplan.placement_view`, which is handed the rerun module)."""
    import rerun as rr

    from .placement_view import write_placement

    write_placement(rr, path, sc, results, app_id=app_id)


def record_plan(path: str | os.PathLike, sc, mf, runs, *, app_id: str = "errplan") -> None:
    """Write one ``.rrd`` with the fields, workspace, ports, paths, gains and simulations (planar:
    the tip plane; spatial: the 3-D scene of :func:`_log_plan_spatial`).

    Written to a temporary file and renamed: nothing half-written on error.
    """
    import rerun as rr

    path = Path(path)
    if not path.parent.exists():
        raise ErrplanError(f"--record {path}: directory {path.parent} does not exist")
    tmp = path.with_name(path.name + ".part")
    rec = rr.RecordingStream(app_id, recording_id=f"errplan-{sc.name}", send_properties=False)
    fields_logged = [n for n in ("G_norm", "phi_hat_max", "rho_star") if getattr(mf, n, None) is not None]
    spatial = getattr(sc, "dim", 2) == 3
    if spatial:
        scene = SpatialScene(sc, mf, runs)
        bp = blueprint_spatial(runs, scene)
    else:
        bp = blueprint(runs, fields_logged)
    rec.save(tmp, default_blueprint=bp)
    try:
        if spatial:
            _log_plan_spatial(rec, rr, sc, mf, runs, scene)
        else:
            _log_plan(rec, rr, sc, mf, runs, fields_logged)
        rec.flush()
    finally:
        rec.disconnect()
    os.replace(tmp, path)


def _log_plan(rec, rr, sc, mf, runs, fields_logged) -> None:
    ui = rr.Radius.ui_points
    for n in fields_logged:
        img, tr, sc_ = field_image(mf, n)
        rec.log(f"plane/fields/{n}", rr.Transform3D(translation=tr, scale=sc_), static=True)
        rec.log(f"plane/fields/{n}", rr.DepthImage(img, meter=1.0, colormap=FIELD_COLORMAPS[n],
                                                   depth_range=FIELD_RANGES[n], draw_order=-10.0), static=True)
    strips = [uv(s) for s in _merge_edges(workspace_edges(mf))]
    rec.log("plane/workspace", rr.LineStrips2D(strips, colors=(200, 200, 200), radii=ui(1.0), draw_order=5.0),
            static=True)
    rec.log("plane/port/true", rr.Points2D(uv([sc.port.position]), colors=PORT_TRUE_COLOR, radii=ui(6.0),
                                           labels=["true port"], draw_order=30.0), static=True)
    rec.log("plane/port/estimate", rr.Points2D(uv([sc.port.estimate]), colors=PORT_EST_COLOR, radii=ui(6.0),
                                               labels=["estimated port"], draw_order=30.0), static=True)
    u = sc.uncertainty
    if u.port_y is not None or u.port_z is not None:
        (y0, y1), (z0, z1) = u.port_y or (0.0, 0.0), u.port_z or (0.0, 0.0)
        e = np.asarray(sc.port.estimate)
        box = e + np.array([[y0, z0], [y1, z0], [y1, z1], [y0, z1], [y0, z0]])
        rec.log("plane/port/error_box", rr.LineStrips2D([uv(box)], colors=PORT_EST_COLOR, radii=ui(1.0),
                                                         draw_order=30.0), static=True)
    for r, q in zip(runs, entity_names(runs)):
        base = f"plane/{q}"
        rec.log(f"{base}/planned", rr.LineStrips2D([uv(r.planned_path)], colors=PLANNED_COLOR, radii=ui(2.5),
                                                   draw_order=20.0), static=True)
        rec.log(f"{base}/direct", rr.LineStrips2D([uv(r.direct_path)], colors=DIRECT_COLOR, radii=ui(2.0),
                                                  draw_order=19.0), static=True)
        segs = r.schedule.segments
        rec.log(f"{base}/segments", rr.Points2D(
            uv(np.array([s.end for s in segs])), radii=ui(3.0),
            colors=[PLANNED_COLOR if s.certified else DIRECT_COLOR for s in segs],
            labels=[f"k={s.gain:.3f} ‖G‖≤{s.certified_G_norm:.3f}" for s in segs], show_labels=False,
            draw_order=21.0), static=True)
        for kind, rep, col in (("planned", r.sim_planned, PLANNED_COLOR), ("direct", r.sim_direct, DIRECT_COLOR)):
            rec.log(f"{base}/sim/{kind}/trajectory",
                    rr.LineStrips2D([uv(rep.sim.tip)], colors=tuple(int(0.6 * c) for c in col), radii=ui(1.0),
                                    draw_order=22.0), static=True)
        for kind, reps, col in (("planned", r.corner_planned, PLANNED_COLOR), ("direct", r.corner_direct, DIRECT_COLOR)):
            if reps:
                rec.log(f"{base}/corners/{kind}",
                        rr.LineStrips2D([uv(x.sim.tip) for x in reps], colors=tuple(int(0.4 * c) for c in col),
                                        radii=ui(0.75), draw_order=15.0), static=True)
        tip_of = lambda pts, col: rr.Points2D(uv(pts), colors=col, radii=ui(5.0), draw_order=40.0)  # noqa: E731
        _log_query_series(rec, rr, r, q, base, tip_of)
    rec.log("summary", rr.TextDocument(_markdown_summary(sc, runs), media_type="text/markdown"), static=True)


def _log_query_series(rec, rr, r, q: str, base: str, tip_of, replay: dict | None = None) -> None:
    """Per-segment gains (``segment`` timeline) and, per step (``step`` timeline), the simulated tip
    (``tip_of(points, colour)`` draws it: 2-D or 3-D), the error length and phi of both paths.
    ``replay`` ({kind: first state}): the steps also go on the ``replay`` timeline (3-D)."""
    segs = r.schedule.segments
    rec.log(f"gains/{q}/gain", rr.SeriesLines(colors=(90, 160, 255), names=f"{r.name}: gain k"), static=True)
    rec.log(f"gains/{q}/certified_G_norm", rr.SeriesLines(colors=(255, 140, 0), names=f"{r.name}: certified ||G||"),
            static=True)
    for i, s in enumerate(segs):
        rec.set_time("segment", sequence=i)
        rec.log(f"gains/{q}/gain", rr.Scalars(s.gain))
        if math.isfinite(s.certified_G_norm):  # an unbounded worst case is left out of the plot
            rec.log(f"gains/{q}/certified_G_norm", rr.Scalars(s.certified_G_norm))
    rec.reset_time()
    for kind, rep, col in (("planned", r.sim_planned, PLANNED_COLOR), ("direct", r.sim_direct, DIRECT_COLOR)):
        rec.log(f"series/{q}/{kind}/error", rr.SeriesLines(colors=col, names=f"{kind}: |x - target| (m)"), static=True)
        rec.log(f"series/{q}/{kind}/phi", rr.SeriesLines(colors=col, names=f"{kind}: φ (rad)"), static=True)
        sim = rep.sim
        err = sim.errors
        phi = np.concatenate([sim.phi, [0.0]]) if len(sim.phi) < len(sim.tip) else sim.phi
        for i in range(len(sim.tip)):
            rec.set_time("step", sequence=i)
            if replay is not None:
                rec.set_time("replay", sequence=replay[kind] + i)
            rec.log(f"{base}/sim/{kind}/tip", tip_of(sim.tip[i:i + 1], col))
            rec.log(f"series/{q}/{kind}/error", rr.Scalars(float(err[i])))
            rec.log(f"series/{q}/{kind}/phi", rr.Scalars(float(phi[i])))
    rec.reset_time()


# ============================================================================= spatial plans
# 3-D recordings (docs/interfaces.md "3-D plan JSON, recordings"), all under ``world`` in metres,
# world frame [x, y, z] with y up (``ViewCoordinates.RIGHT_HAND_Y_UP``):
#
# - ``world/<robot name>/**``: the robot from its URDF, loaded by rerun (``rerun.urdf.UrdfTree``:
#   meshes, primitives, the URDF's static joint transforms in named frames); mesh URIs resolve
#   through the scenario's ``package_path`` and ``$ROS_PACKAGE_PATH``. ``world/robot/placement``: the
#   URDF root in the world (``base_position``, ``base_rpy``); ``world/robot/joints/<joint>``: every
#   actuated joint's transform per state of the replay (``replay`` timeline, computed by
#   ``UrdfJoint.compute_transform`` from the true link angles), held joints static at their value;
#   ``world/robot/links``: the chain as lines (``UrdfArm.chain_points``), the robot itself when its
#   meshes do not resolve; ``world/robot/shaft`` and ``world/robot/tip``: the instrument per state;
# - the ``replay`` timeline plays the simulated runs under the truth one after the other (for each
#   query: direct, then planned; the errors and angles of ``series/**`` and the tips follow it
#   too); ``replay/run``: which run is playing (``TextLog``);
# - ``world/fields/G_norm/{x,y,z}``: the worst-case ``||G||`` field at the scenario gain as three
#   orthogonal slices (``Mesh3D`` with vertex colours, Turbo 0 to 1.2; no triangle outside the
#   workspace) through the port estimate's x and y and the queries' median depth;
#   ``world/fields/rho_star/{x,y,z}`` the same for rho*; ``world/fields/surface/G_norm_1`` and
#   ``world/fields/surface/rho_star_margin``: the surfaces ``||G|| = 1`` and
#   ``rho* = 1 - certify_margin`` (``skimage.measure.marching_cubes`` on the robust workspace);
# - ``world/port/{true,estimate}`` (``Points3D``), ``world/port/error_box`` (``Boxes3D``);
# - ``world/<query>/{planned,direct,segments}``, ``world/<query>/sim/{planned,direct}/{trajectory,tip}``,
#   ``world/<query>/corners/{planned,direct}``: as in the plane, in 3-D;
# - ``series/**``, ``gains/**``, ``summary``: the planar recording's time series and summary.
TURBO_R = (0.13572138, 4.61539260, -42.66032258, 132.13108234, -152.94239396, 59.28637943)
TURBO_G = (0.09140261, 2.19418839, 4.84296658, -14.18503333, 4.27729857, 2.82956604)
TURBO_B = (0.10667330, 12.64194608, -60.58204836, 110.36276771, -89.90310912, 27.34824973)
SURFACE_COLORS = {"G_norm_1": (255, 60, 40, 90), "rho_star_margin": (80, 140, 255, 90)}
SLICE_ALPHA = 110


def turbo(t) -> np.ndarray:
    """Turbo colormap for ``t`` in [0, 1] (a degree-5 polynomial fit per channel, within ~30/255 of
    the published table): RGB uint8 (..., 3)."""
    t = np.clip(np.asarray(t, float), 0.0, 1.0)
    out = [sum(c * t ** i for i, c in enumerate(coef)) for coef in (TURBO_R, TURBO_G, TURBO_B)]
    return (np.clip(np.stack(out, axis=-1), 0.0, 1.0) * 255).astype(np.uint8)


def slice_mesh(mf, name: str, axis: int, index: int, vrange=(0.0, 1.2)):
    """The field ``name`` on the grid plane ``axis = axes[axis][index]`` as a coloured triangle mesh:
    ``(vertices (n, 3), triangles (t, 3), colours (n, 3))``; a grid cell gets its two triangles only
    where its four corners are in the workspace (valid and finite)."""
    a = np.asarray(mf.array(name), float)
    v = np.asarray(mf.valid, bool) & np.isfinite(a)
    axes = [np.asarray(ax, float) for ax in mf.axes]
    sl = [slice(None)] * 3
    sl[axis] = index
    F, V = a[tuple(sl)], v[tuple(sl)]
    (ia, ib) = [i for i in range(3) if i != axis]
    A, B = np.meshgrid(axes[ia], axes[ib], indexing="ij")
    P = np.zeros(A.shape + (3,))
    P[..., ia], P[..., ib], P[..., axis] = A, B, axes[axis][index]
    na, nb = F.shape
    idx = np.arange(na * nb).reshape(na, nb)
    cell = V[:-1, :-1] & V[1:, :-1] & V[:-1, 1:] & V[1:, 1:]
    i00, i10, i01, i11 = idx[:-1, :-1][cell], idx[1:, :-1][cell], idx[:-1, 1:][cell], idx[1:, 1:][cell]
    tri = np.concatenate([np.stack([i00, i10, i11], -1), np.stack([i00, i11, i01], -1)]).astype(np.uint32)
    col = turbo((np.where(V, F, vrange[0]) - vrange[0]) / (vrange[1] - vrange[0]))
    return P.reshape(-1, 3), tri, col.reshape(-1, 3)


def level_surface(mf, name: str, level: float):
    """The surface ``field = level`` inside the robust workspace (marching cubes, scikit-image):
    ``(vertices (n, 3) in metres, triangles (t, 3), normals (n, 3))``, or None where the field does
    not cross the level there."""
    from skimage.measure import marching_cubes

    a = getattr(mf, name, None)
    if a is None:
        return None
    a = np.asarray(a, float)
    valid = np.asarray(mf.valid, bool) & np.isfinite(a)
    if min(a.shape) < 2 or not valid.any():
        return None
    vals = a[valid]
    if not (vals.min() < level < vals.max()):
        return None
    vol = np.where(valid, a, level)
    h = mf.resolution
    try:
        verts, faces, normals, _ = marching_cubes(vol, level, spacing=(h, h, h), mask=valid)
    except (ValueError, RuntimeError):
        return None
    if not len(faces):
        return None
    origin = np.array([ax[0] for ax in mf.axes], float)
    return verts + origin, faces.astype(np.uint32), normals


def _mesh_uris(urdf_text: str) -> list[str]:
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(urdf_text)
    except ET.ParseError:
        return []
    return [m.get("filename", "") for m in root.iter("mesh")]


def _rpy_matrix(rpy) -> np.ndarray:
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


class SpatialScene:
    """What a 3-D recording needs beyond the runs: the arm, the replayed runs (true link angles per
    state), the slice positions and the mesh URIs with whether they resolve."""

    def __init__(self, sc, mf, runs):
        from .kinematics import arm_for
        from .kinematics.truth import Plant

        self.arm = arm_for(sc.robot)
        truth = Plant.from_scenario(sc)
        self.names = entity_names(runs)
        self.replays = []  # (label, query entity, kind, link angles (n, joints), tips (n, 3), wrists (n, 3))
        self.offsets: dict = {}  # {query entity: {kind: first state on the replay timeline}}
        start = 0
        for r, q in zip(runs, self.names):
            for kind, rep in (("direct", r.sim_direct), ("planned", r.sim_planned)):
                qa = truth.link_angles_q(rep.sim.q)
                self.replays.append((f"{r.name} {kind}", q, kind, qa, rep.sim.tip, self.arm.forward(qa)))
                self.offsets.setdefault(q, {})[kind] = start
                start += len(qa)
        self.uris = _mesh_uris(self.arm.urdf_text)
        self.resolved = [u for u in self.uris if self.arm.resolve_uri(u) is not None]
        self.meshes_ok = len(self.resolved) == len(self.uris)
        axes = mf.axes
        est = np.asarray(sc.port.estimate, float)
        goals = [p for r in runs for p in (r.start, r.goal)]
        depth = float(np.median([g[2] for g in goals])) if goals else float(np.mean(axes[2]))
        target = (est[0], est[1], depth)
        self.slice_index = [int(np.argmin(np.abs(np.asarray(ax) - t))) for ax, t in zip(axes, target)]
        lo = np.array([ax[0] for ax in axes], float)
        hi = np.array([ax[-1] for ax in axes], float)
        self.centre = 0.5 * (lo + hi)
        # what the 3-D view frames: the task region (the field's grid) and the robot's base
        base = np.asarray(self.arm.base_position, float)
        lo, hi = np.minimum(lo, base), np.maximum(hi, base)
        self.look_target = self.centre + 0.15 * (base - self.centre)
        self.extent = float(np.max(hi - lo))
        self.fields = [n for n in ("G_norm", "rho_star") if getattr(mf, n, None) is not None]
        self.surfaces = {}
        if getattr(mf, "G_norm", None) is not None:
            self.surfaces["G_norm_1"] = level_surface(mf, "G_norm", 1.0)
        if getattr(mf, "rho_star", None) is not None:
            self.surfaces["rho_star_margin"] = level_surface(mf, "rho_star", 1.0 - sc.planner.certify_margin)


def _package_env(arm) -> dict:
    """``ROS_PACKAGE_PATH`` for rerun's URDF importer: the scenario's ``package_path`` (relative
    entries against the URDF's folder, as :meth:`UrdfArm.resolve_uri`) then the environment's."""
    dirs = []
    for d in arm.package_path:
        p = Path(d)
        dirs.append(str(p if p.is_absolute() else arm.urdf_path.parent / p))
    old = os.environ.get("ROS_PACKAGE_PATH", "")
    return {"ROS_PACKAGE_PATH": os.pathsep.join(dirs + ([old] if old else []))}


def _load_urdf_tree(arm):
    """``rerun.urdf.UrdfTree`` of the arm's URDF under ``world/<robot name>`` (mesh URIs resolved
    through :func:`_package_env`), or None when rerun cannot read it."""
    import rerun.urdf as ru

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


def _log_robot(rec, rr, sc, scene) -> dict:
    """The URDF robot, its placement, held joints, and the replay of every run (``replay`` timeline)."""
    arm = scene.arm
    ui = rr.Radius.ui_points
    tree = _load_urdf_tree(arm)
    info = {"urdf_loaded": tree is not None, "meshes": len(scene.uris), "meshes_resolved": len(scene.resolved)}
    joints = {}
    if tree is not None:
        _log_urdf(tree, rec, arm)
        root = tree.root_link().name
        rec.log("world/robot/placement",
                rr.Transform3D(translation=list(arm.base_position), mat3x3=_rpy_matrix(arm.base_rpy),
                               parent_frame="tf#/world", child_frame=f"robot/{root}"), static=True)
        for name, val in arm.fixed_joints.items():
            j = tree.get_joint_by_name(name)
            if j is not None and j.joint_type != "fixed":
                rec.log(f"world/robot/joints/{name}", j.compute_transform(float(val), clamp=False), static=True)
        joints = {name: tree.get_joint_by_name(name) for name in arm.joint_names}
    # the replay: one state per row of the concatenated runs
    offset = 0
    link_col = (170, 170, 185) if (tree is not None and scene.meshes_ok) else (230, 230, 240)
    link_r = ui(1.5) if (tree is not None and scene.meshes_ok) else ui(4.0)
    for label, q, kind, qa, tips, wrists in scene.replays:
        n = len(qa)
        seq = np.arange(offset, offset + n)
        tl = rr.TimeColumn("replay", sequence=seq)
        for i, name in enumerate(arm.joint_names):
            j = joints.get(name)
            if j is not None:
                rec.send_columns(f"world/robot/joints/{name}", indexes=[tl],
                                 columns=j.compute_transform_columns(qa[:, i].tolist(), clamp=False))
        rec.set_time("replay", sequence=offset)
        rec.log("replay/run", rr.TextLog(f"{label}: {n - 1} steps"))
        col = PLANNED_COLOR if kind == "planned" else DIRECT_COLOR
        chain = arm.chain_points(qa)
        port = np.asarray(sc.port.position, float)
        for i in range(n):
            rec.set_time("replay", sequence=offset + i)
            rec.log("world/robot/links", rr.LineStrips3D([chain[i]], colors=link_col, radii=link_r))
            rec.log("world/robot/shaft", rr.LineStrips3D([[wrists[i], port, tips[i]]], colors=(235, 235, 235),
                                                         radii=ui(2.0)))
            rec.log("world/robot/tip", rr.Points3D(tips[i:i + 1], colors=col, radii=ui(6.0), labels=[label],
                                                   show_labels=i == 0))
        offset += n
    rec.reset_time()
    info["replay_states"] = offset
    return info


def _log_plan_spatial(rec, rr, sc, mf, runs, scene) -> None:
    ui = rr.Radius.ui_points
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
    info = _log_robot(rec, rr, sc, scene)
    axes_names = ("x", "y", "z")
    for n in scene.fields:
        vr = FIELD_RANGES[n]
        for axis, idx in enumerate(scene.slice_index):
            P, T, C = slice_mesh(mf, n, axis, idx, vr)
            if len(T):
                rec.log(f"world/fields/{n}/{axes_names[axis]}",
                        rr.Mesh3D(vertex_positions=P, triangle_indices=T, vertex_colors=C,
                                  albedo_factor=(255, 255, 255, SLICE_ALPHA)), static=True)
    for key, surf in scene.surfaces.items():
        if surf is not None:
            V, T, N = surf
            rec.log(f"world/fields/surface/{key}",
                    rr.Mesh3D(vertex_positions=V, triangle_indices=T, vertex_normals=N,
                              albedo_factor=SURFACE_COLORS[key]), static=True)
    rec.log("world/port/true", rr.Points3D([sc.port.position], colors=PORT_TRUE_COLOR, radii=ui(7.0),
                                           labels=["true port"]), static=True)
    rec.log("world/port/estimate", rr.Points3D([sc.port.estimate], colors=PORT_EST_COLOR, radii=ui(7.0),
                                               labels=["estimated port"]), static=True)
    u = sc.uncertainty
    box = [u.port_x or (0.0, 0.0), u.port_y or (0.0, 0.0), u.port_z or (0.0, 0.0)]
    if any(b != (0.0, 0.0) for b in box):
        e = np.asarray(sc.port.estimate, float)
        lo, hi = e + [b[0] for b in box], e + [b[1] for b in box]
        rec.log("world/port/error_box", rr.Boxes3D(centers=[0.5 * (lo + hi)], half_sizes=[0.5 * (hi - lo)],
                                                   colors=PORT_EST_COLOR, radii=ui(1.0)), static=True)
    for r, q in zip(runs, scene.names):
        base = f"world/{q}"
        rec.log(f"{base}/planned", rr.LineStrips3D([r.planned_path], colors=PLANNED_COLOR, radii=ui(3.5)), static=True)
        rec.log(f"{base}/direct", rr.LineStrips3D([r.direct_path], colors=DIRECT_COLOR, radii=ui(2.5)), static=True)
        segs = r.schedule.segments
        rec.log(f"{base}/segments", rr.Points3D(
            np.array([s.end for s in segs]), radii=ui(3.0),
            colors=[PLANNED_COLOR if s.certified else DIRECT_COLOR for s in segs],
            labels=[f"k={s.gain:.3f} ‖G‖≤{s.certified_G_norm:.3f}" for s in segs], show_labels=False), static=True)
        for kind, rep, col in (("planned", r.sim_planned, PLANNED_COLOR), ("direct", r.sim_direct, DIRECT_COLOR)):
            rec.log(f"{base}/sim/{kind}/trajectory",
                    rr.LineStrips3D([rep.sim.tip], colors=tuple(int(0.6 * c) for c in col), radii=ui(1.5)), static=True)
        for kind, reps, col in (("planned", r.corner_planned, PLANNED_COLOR), ("direct", r.corner_direct, DIRECT_COLOR)):
            if reps:
                rec.log(f"{base}/corners/{kind}",
                        rr.LineStrips3D([x.sim.tip for x in reps], colors=tuple(int(0.4 * c) for c in col),
                                        radii=ui(0.75)), static=True)
        tip_of = lambda pts, col: rr.Points3D(pts, colors=col, radii=ui(5.0))  # noqa: E731
        _log_query_series(rec, rr, r, q, base, tip_of, scene.offsets[q])
    text = _markdown_summary(sc, runs) + "\n" + _spatial_notes(sc, mf, scene, info)
    rec.log("summary", rr.TextDocument(text, media_type="text/markdown"), static=True)


def _spatial_notes(sc, mf, scene, info) -> str:
    axes = mf.axes
    at = ", ".join(f"{a} = {axes[i][j]:.3f} m" for i, (a, j) in enumerate(zip(("x", "y", "z"), scene.slice_index)))
    robot = (f"robot: {scene.arm.urdf_path.name}, {info['meshes_resolved']}/{info['meshes']} mesh files resolved"
             + ("" if info["urdf_loaded"] else " (rerun could not read the URDF: links drawn as lines)")
             + ("" if scene.meshes_ok else "; links drawn as lines where meshes are missing"))
    surf = "; ".join(f"{k}: {'none in the region' if v is None else f'{len(v[1])} triangles'}"
                     for k, v in scene.surfaces.items())
    return "\n".join([
        "## 3-D scene", "",
        f"- {robot}; the `replay` timeline plays every simulated run under the truth ({info['replay_states']} states).",
        f"- field slices ({', '.join(scene.fields)}) at {at}; Turbo 0 to 1.2 for ||G||, 0 to 1 for rho*.",
        f"- surfaces: ||G|| = 1 at gain {sc.controller.gain:g} (red), rho* = {1 - sc.planner.certify_margin:g} (blue); {surf}.",
        "- white: true port; yellow: estimated port and the port error box.", ""])


def blueprint_spatial(runs, scene):
    """A 3-D view of the task region (robot, ||G|| slices and surfaces, ports, paths, trajectories)
    looking at it obliquely from the patient's side; series, gains, summary and the other fields
    in tabs; the time panel on the ``replay`` timeline."""
    import rerun.blueprint as rrb

    names = scene.names
    corners = [f"- /world/{q}/corners/**" for q in names]
    hidden_fields = [f"- /world/fields/{n}/**" for n in scene.fields if n != "G_norm"]
    hidden_fields.append("- /world/fields/surface/rho_star_margin")
    # from the side (+x), a little above and toward the patient: the robot, the port and the task region
    t = scene.look_target
    e = scene.extent
    eye = rrb.EyeControls3D(position=[t[0] + 0.36 * e, t[1] + 0.31 * e, t[2] + 0.62 * e], look_target=list(t),
                            eye_up=[0.0, 1.0, 0.0], kind=rrb.Eye3DKind.Orbital)
    main = rrb.Spatial3DView(origin="/world", contents=["+ /world/**"] + hidden_fields + corners,
                             name="3-D: robot, worst-case ||G|| slices, ||G|| = 1 surface, paths", eye_controls=eye)
    others = [rrb.Spatial3DView(origin="/world", name=f"field {n} and the surface rho* = 1 - margin",
                                contents=["+ /world/**", "- /world/fields/G_norm/**", "- /world/fields/surface/G_norm_1"]
                                + [f"- /world/fields/{m}/**" for m in scene.fields if m not in (n, "G_norm")] + corners,
                                eye_controls=eye)
              for n in scene.fields if n != "G_norm"]
    others.append(rrb.Spatial3DView(origin="/world", name="replays under the port-box corners", eye_controls=eye,
                                    contents=["+ /world/**", "- /world/fields/**"] + [f"- /world/{q}/sim/**" for q in names]))
    series = []
    for r, q in zip(runs, names):
        series.append(rrb.TimeSeriesView(origin=f"series/{q}",
                                         contents=[f"+ series/{q}/planned/error", f"+ series/{q}/direct/error"],
                                         name=f"{r.name}: error length (m) per step"))
        series.append(rrb.TimeSeriesView(origin=f"series/{q}",
                                         contents=[f"+ series/{q}/planned/phi", f"+ series/{q}/direct/phi"],
                                         name=f"{r.name}: φ (rad) per step"))
    gains = [rrb.TimeSeriesView(origin="gains", name="per-segment gain and certified ||G||")]
    groups = [rrb.Vertical(*series[i:i + 4], name="series: " + ", ".join(r.name for r in runs[i // 2:i // 2 + 2]))
              for i in range(0, len(series), 4)]
    right = rrb.Tabs(*groups, *gains, rrb.TextDocumentView(origin="summary", name="summary"),
                     rrb.TextLogView(origin="replay", name="replay: which run plays"), *others)
    return rrb.Blueprint(rrb.Horizontal(main, right, column_shares=[2, 1]),
                         rrb.TimePanel(timeline="replay", state="collapsed"), collapse_panels=True)


def expected_rows(runs) -> dict[str, int]:
    """Entity path -> number of rows :func:`record_plan` writes (for the read-back test)."""
    out = {}
    for r, q in zip(runs, entity_names(runs)):
        for kind, rep in (("planned", r.sim_planned), ("direct", r.sim_direct)):
            n = len(rep.sim.tip)
            out[f"/plane/{q}/sim/{kind}/tip"] = n
            out[f"/series/{q}/{kind}/error"] = n + 1  # + the static SeriesLines style row
            out[f"/series/{q}/{kind}/phi"] = n + 1
            out[f"/plane/{q}/sim/{kind}/trajectory"] = 1
        out[f"/gains/{q}/gain"] = len(r.schedule.segments) + 1
        out[f"/gains/{q}/certified_G_norm"] = sum(math.isfinite(s.certified_G_norm) for s in r.schedule.segments) + 1
        out[f"/plane/{q}/planned"] = 1
        out[f"/plane/{q}/direct"] = 1
        out[f"/plane/{q}/segments"] = 1
    out["/plane/workspace"] = 1
    out["/plane/port/true"] = 1
    out["/plane/port/estimate"] = 1
    out["/summary"] = 1
    return out


# ============================================================================= calibration
# Calibration recordings (errplan calibrate --record) are appended below this line by the
# calibration work; keep the plan section above self-contained.
#
# Calibration recordings (:func:`record_calibration`), all in the same ``plane`` space:
#
# - ``plane/port/true``, ``plane/port/estimate`` (``Points2D``), static;
# - ``plane/data/tracked``: every tracked tip of the fitting data (``Points2D``), static;
# - ``plane/residual/before``, ``plane/residual/after``: the pose residual (tracked minus model
#   tip) of every row as an arrow from the model tip, magnified by ``CAL_ARROW_GAIN`` (the same for
#   both, so their lengths compare), coloured by length relative to the noise floor;
# - ``plane/residual_map/before``, ``plane/residual_map/after``: the residual map — the mean residual
#   over 10 mm cells (noise averages out, structure stays), magnified by ``CAL_MAP_GAIN``, coloured
#   by the cell's mean residual over the noise floor (green <= 1, red >= 4): where a structured
#   residual is left after the selected model;
# - ``plane/replay/measured``, ``plane/replay/before``, ``plane/replay/after``: each run's measured
#   tracked path and the controller replayed on the declared and on the corrected model;
# - ``summary``: the readable report (``TextDocument``).
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
    import rerun.blueprint as rrb

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
    """Write the ``.rrd`` of an :class:`errplan.calibration.CalibrationReport` (see the section
    comment above). Written to a temporary file and renamed: nothing half-written on error."""
    import rerun as rr

    path = Path(path)
    if not path.parent.exists():
        raise ErrplanError(f"--record {path}: directory {path.parent} does not exist")
    tmp = path.with_name(path.name + ".part")
    spatial = np.asarray(report.points).shape[-1] == 3
    rec = rr.RecordingStream(app_id, recording_id=f"errplan-calibrate-{report.scenario}", send_properties=False)
    rec.save(tmp, default_blueprint=calibration_blueprint_spatial() if spatial else calibration_blueprint())
    try:
        (_log_calibration_spatial if spatial else _log_calibration)(rec, rr, report, sc)
        rec.flush()
    finally:
        rec.disconnect()
    os.replace(tmp, path)


def _log_calibration(rec, rr, report, sc) -> None:
    ui = rr.Radius.ui_points
    noise = float(report.noise.sigma)
    pts = np.asarray(report.points, float)
    if sc is not None:
        rec.log("plane/port/true", rr.Points2D(uv([sc.port.position]), colors=PORT_TRUE_COLOR, radii=ui(6.0),
                                               labels=["true port (declared)"], draw_order=30.0), static=True)
        rec.log("plane/port/estimate", rr.Points2D(uv([sc.port.estimate]), colors=PORT_EST_COLOR, radii=ui(6.0),
                                                   labels=["estimated port"], draw_order=30.0), static=True)
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


# ----------------------------------------------------------------------------- calibration in 3-D
# A spatial calibration (:func:`record_calibration` on a 3-D report) in one ``world`` space (y up):
#
# - ``world/robot/**``: the robot from its URDF (meshes when they resolve, links as lines when they
#   do not) at the median encoder reading of the data; ``world/port/true``, ``world/port/estimate``;
# - ``world/data/tracked``: every tracked tip (``Points3D``);
# - ``world/residual/before``, ``world/residual/after``: every row's pose residual as a 3-D arrow
#   from the model tip, x``CAL_ARROW_GAIN``, coloured from green (noise floor) to red (4 floors);
# - ``world/residual_map/before|after``: the mean residual over 10 mm cubes, x``CAL_MAP_GAIN``;
# - ``world/replay/measured|before|after``: each run's measured path and the controller replayed on
#   the declared and on the corrected model; ``summary``: the report.
def calibration_blueprint_spatial():
    import rerun.blueprint as rrb

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
    from .kinematics import arm_for

    arm = arm_for(sc.robot)
    ui = rr.Radius.ui_points
    tree = _load_urdf_tree(arm)
    if tree is not None:
        _log_urdf(tree, rec, arm)
        rec.log("world/robot/placement",
                rr.Transform3D(translation=list(arm.base_position), mat3x3=_rpy_matrix(arm.base_rpy),
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
        rec.log("world/port/true", rr.Points3D([sc.port.position], colors=PORT_TRUE_COLOR, radii=ui(6.0),
                                               labels=["true port (declared)"]), static=True)
        rec.log("world/port/estimate", rr.Points3D([sc.port.estimate], colors=PORT_EST_COLOR, radii=ui(6.0),
                                                   labels=["estimated port"]), static=True)
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
