"""The 3-D plan view (:func:`errplan.recording.record_plan` on a spatial scenario).

3-D recordings (docs/interfaces.md "3-D plan JSON, recordings"), all under ``world`` in metres,
world frame [x, y, z] with y up (``ViewCoordinates.RIGHT_HAND_Y_UP``):

- ``world/<robot name>/**``: the robot from its URDF, loaded by rerun (``rerun.urdf.UrdfTree``:
  meshes, primitives, the URDF's static joint transforms in named frames); mesh URIs resolve
  through the scenario's ``package_path`` and ``$ROS_PACKAGE_PATH``. ``world/robot/placement``: the
  URDF root in the world (``base_position``, ``base_rpy``); ``world/robot/joints/<joint>``: every
  actuated joint's transform per state of the replay (``replay`` timeline, computed by
  ``UrdfJoint.compute_transform`` from the true link angles), held joints static at their value;
  ``world/robot/links``: the chain as lines (``UrdfArm.chain_points``), the robot itself when its
  meshes do not resolve; ``world/robot/shaft`` and ``world/robot/tip``: the instrument per state;
- the ``replay`` timeline plays the simulated runs under the truth one after the other (for each
  query: direct, then planned; the errors and angles of ``series/**`` and the tips follow it
  too); ``replay/run``: which run is playing (``TextLog``);
- ``world/fields/G_norm/{x,y,z}``: the worst-case ``||G||`` field at the scenario gain as three
  orthogonal slices (``Mesh3D`` with vertex colours, Turbo 0 to 1.2; no triangle outside the
  workspace) through the port estimate's x and y and the queries' median depth;
  ``world/fields/rho_star/{x,y,z}`` the same for rho*; ``world/fields/surface/G_norm_1`` and
  ``world/fields/surface/rho_star_margin``: the surfaces ``||G|| = 1`` and
  ``rho* = 1 - certify_margin`` (``skimage.measure.marching_cubes`` on the robust workspace);
- ``world/port/{true,estimate}`` (``Points3D``), ``world/port/error_box`` (``Boxes3D``);
- ``world/<query>/{planned,direct,segments}``, ``world/<query>/sim/{planned,direct}/{trajectory,tip}``,
  ``world/<query>/corners/{planned,direct}``: as in the plane, in 3-D;
- ``series/**``, ``gains/**``, ``summary``: the planar recording's time series and summary.
"""
from __future__ import annotations

import math

import numpy as np

from ..kinematics.urdf import rpy_matrix
from . import sdk
from .plane import _log_query_series, _markdown_summary, series_tabs
from .robot import _load_urdf_tree, _log_urdf, _mesh_uris
from .shapes import level_surface, slice_mesh
from .style import DIRECT_COLOR, FIELD_RANGES, PLANNED_COLOR, PORT_EST_COLOR, PORT_TRUE_COLOR, SLICE_ALPHA, SURFACE_COLORS, entity_names, port_labels


class SpatialScene:
    """What a 3-D recording needs beyond the runs: the arm, the replayed runs (true link angles per
    state), the slice positions and the mesh URIs with whether they resolve."""

    def __init__(self, sc, mf, runs):
        from ..models import arm_model

        m = arm_model(sc)
        self.arm = m.arm
        truth = m.truth if m.truth_load == 0.0 else m.truth.with_(load=0.0)
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
                rr.Transform3D(translation=list(arm.base_position), mat3x3=rpy_matrix(arm.base_rpy),
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
    lt, le = port_labels(sc.port.position, sc.port.estimate, scene.extent)
    rec.log("world/port/true", rr.Points3D([sc.port.position], colors=PORT_TRUE_COLOR, radii=ui(7.0),
                                           labels=lt), static=True)
    rec.log("world/port/estimate", rr.Points3D([sc.port.estimate], colors=PORT_EST_COLOR, radii=ui(7.0),
                                               labels=le), static=True)
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
    _log_anatomy(rec, rr, sc, mf, runs, scene)
    text = _markdown_summary(sc, runs) + "\n" + _spatial_notes(sc, mf, scene, info)
    rec.log("summary", rr.TextDocument(text, media_type="text/markdown"), static=True)


OBSTACLE_COLOR = (200, 90, 110, 200)
WALL_COLOR = (230, 200, 170, 50)
BLOCKED_COLOR = (150, 150, 150)


def log_anatomy_meshes(rec, rr, sc):
    """The anatomy of ``sc`` as meshes: ``world/anatomy/<obstacle>`` and ``world/anatomy/body_wall``
    (static). Returns the anatomy model (None without ``[anatomy]``)."""
    from ..fields.compute import anatomy_model

    an = anatomy_model(sc)
    if an is None:
        return None
    for srf in an.surfaces:
        rec.log(f"world/anatomy/{srf.name}", rr.Mesh3D(vertex_positions=srf.vertices, triangle_indices=srf.faces,
                                                       albedo_factor=OBSTACLE_COLOR), static=True)
    wm = an.wall_mesh()
    if wm is not None:
        rec.log("world/anatomy/body_wall", rr.Mesh3D(vertex_positions=wm[0], triangle_indices=wm[1],
                                                     albedo_factor=WALL_COLOR), static=True)
    return an


def _log_anatomy(rec, rr, sc, mf, runs, scene) -> None:
    """``[anatomy]``: ``world/anatomy/<obstacle>`` and ``world/anatomy/body_wall`` as meshes,
    ``world/fields/blocked`` the grid tips that are reachable but not robustly clear (the blocked part
    of the workspace), and ``series/<query>/<kind>/clearance``: the shaft's clearance (m) at every
    state of the runs under the truth (true port to tip), on the ``step`` and ``replay`` timelines."""
    from ..models import arm_model

    an = log_anatomy_meshes(rec, rr, sc)
    if an is None:
        return
    ui = rr.Radius.ui_points
    cl = getattr(mf, "clearance", None)
    if cl is not None:
        blocked = np.isfinite(cl) & (cl < an.required)
        if blocked.any():
            rec.log("world/fields/blocked", rr.Points3D(mf.points()[blocked], colors=BLOCKED_COLOR, radii=ui(1.5)),
                    static=True)
    port = arm_model(sc).truth.true_port
    mt = an.with_box(port)
    for r, q in zip(runs, scene.names):
        for kind, rep, col in (("planned", r.sim_planned, PLANNED_COLOR), ("direct", r.sim_direct, DIRECT_COLOR)):
            rec.log(f"series/{q}/{kind}/clearance", rr.SeriesLines(colors=col, names=f"{kind}: clearance (m)"),
                    static=True)
            c = mt.tip(rep.sim.tip)
            for i, v in enumerate(c):
                rec.set_time("step", sequence=i)
                rec.set_time("replay", sequence=scene.offsets[q][kind] + i)
                rec.log(f"series/{q}/{kind}/clearance", rr.Scalars(float(v)))
    rec.reset_time()


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
    rrb = sdk.blueprint()

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
    right = rrb.Tabs(*series_tabs(rrb, runs, names), rrb.TextDocumentView(origin="summary", name="summary"),
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
