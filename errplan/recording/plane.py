"""The planar plan view (:func:`errplan.recording.record_plan` on a planar scenario).

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

import numpy as np

from . import sdk
from .shapes import _merge_edges, field_image, workspace_edges
from .style import DIRECT_COLOR, FIELD_COLORMAPS, FIELD_RANGES, PLANNED_COLOR, PORT_EST_COLOR, PORT_TRUE_COLOR, entity_names, port_labels, uv


def _markdown_summary(sc, runs) -> str:
    if sc.dim == 3:
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


def series_tabs(rrb, runs, names) -> list:
    """The time-series tabs of a plan recording: each query's error length and angle per step (two queries,
    four plots, per tab), then the per-segment gains."""
    series = []
    for r, q in zip(runs, names):
        series.append(rrb.TimeSeriesView(origin=f"series/{q}",
                                         contents=[f"+ series/{q}/planned/error", f"+ series/{q}/direct/error"],
                                         name=f"{r.name}: error length (m) per step"))
        series.append(rrb.TimeSeriesView(origin=f"series/{q}",
                                         contents=[f"+ series/{q}/planned/phi", f"+ series/{q}/direct/phi"],
                                         name=f"{r.name}: φ (rad) per step"))
    groups = [rrb.Vertical(*series[i:i + 4], name="series: " + ", ".join(r.name for r in runs[i // 2:i // 2 + 2]))
              for i in range(0, len(series), 4)]
    return groups + [rrb.TimeSeriesView(origin="gains", name="per-segment gain and certified ||G||")]


def blueprint(runs, fields_logged: list[str]):
    """Tip plane (||G|| field, paths, trajectories) | series; tabs for other fields and the summary."""
    rrb = sdk.blueprint()

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
    right = rrb.Tabs(*series_tabs(rrb, runs, names), rrb.TextDocumentView(origin="summary", name="summary"), *others)
    return rrb.Blueprint(rrb.Horizontal(main, right, column_shares=[3, 2]), collapse_panels=True)


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
    lt, le = port_labels(sc.port.position, sc.port.estimate, max(float(a[-1] - a[0]) for a in mf.axes))
    rec.log("plane/port/true", rr.Points2D(uv([sc.port.position]), colors=PORT_TRUE_COLOR, radii=ui(6.0),
                                           labels=lt, draw_order=30.0), static=True)
    rec.log("plane/port/estimate", rr.Points2D(uv([sc.port.estimate]), colors=PORT_EST_COLOR, radii=ui(6.0),
                                               labels=le, draw_order=30.0), static=True)
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
