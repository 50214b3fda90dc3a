"""Recordings of a setup with several instruments and the endoscope (rerun-sdk 0.41), all under ``world``
in metres, y up as the 3-D plan view:

:func:`record_setup_plan` (``errplan plan SETUP --record F.rrd``):

- ``world/arms/<arm>/links/<object>``: each arm from its URDF's visual geometry (``Mesh3D`` per object,
  :func:`.arms.log_arm_geometry`; links drawn as lines between joint frames, ``world/arms/<arm>/chain``,
  always); ``world/arms/<arm>/shaft``: its instrument (wrist -> true port -> tip); ``world/arms/<arm>/port``;
  on the ``motion`` timeline each query's arm follows its planned path (tip every ~2 mm, the arm by
  :func:`errplan.kinematics.urdf.collision.arm_at_tip`) while the other arms hold their rest;
- ``world/endoscope/shaft`` (port -> lens), ``world/endoscope/lens``, ``world/endoscope/cone`` (the view
  cone as a mesh, vertex 0 the apex at the lens, cut at the far depth) and ``world/endoscope/camera``: a
  ``Pinhole`` at the lens looking along the optical axis (field of view ``fov``); the blueprint's
  "view from the endoscope" is a 3-D view whose eye is the lens, looking at ``look_at``;
- ``world/queries/<query>/{planned,direct}``: the paths; ``world/anatomy/**``: the anatomy's meshes.

:func:`record_triad` (``errplan tolerance SETUP --record F.rrd``), per ``triad_placement`` query under
``world/triad/<query>``: ``candidates/<role>`` (every candidate port of the role), ``chosen/<role>`` (the
best triad's port), ``shafts/<instrument>`` (one line from the chosen port to every target),
``shafts/endoscope`` (port -> lens), ``cone`` (the chosen endoscope's view cone), ``targets`` (the
targets coloured by the manipulation angle m(t), Turbo from m* - 2 m_tol to m* + 2 m_tol, labelled in
degrees) and ``manipulation_angle`` (the angles, in degrees, as a scalar series on the ``target``
timeline, one row per target).
"""
from __future__ import annotations

import math

import numpy as np

from . import sdk
from .arms import log_arm_geometry
from .style import DIRECT_COLOR, PLANNED_COLOR, PORT_TRUE_COLOR, entity_name, turbo

ARM_COLORS = ((120, 170, 230), (230, 150, 90), (150, 210, 130), (200, 140, 210))
ENDO_COLOR = (90, 220, 220)
CONE_ALPHA = 60


# --------------------------------------------------------------------------- geometry (numpy)
def view_cone_mesh(lens, axis, fov: float, far: float, n: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """The view cone of full angle ``fov`` from ``lens`` along the unit ``axis``, cut where the depth
    along the axis is ``far``: vertices (n + 2, 3) (0: the apex at the lens, 1..n: the rim, n + 1: the
    rim's centre) and triangles (2 n, 3) (the side and the disc)."""
    lens, axis = np.asarray(lens, float), np.asarray(axis, float)
    e1, e2 = _frame(axis)
    r = far * math.tan(fov / 2.0)
    a = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    centre = lens + far * axis
    rim = centre + r * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2)
    V = np.vstack([lens, rim, centre])
    i = np.arange(n)
    side = np.stack([np.zeros(n, int), 1 + i, 1 + (i + 1) % n], axis=1)
    disc = np.stack([np.full(n, n + 1), 1 + (i + 1) % n, 1 + i], axis=1)
    return V, np.vstack([side, disc])


def _frame(axis) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing the unit ``axis`` to a right-handed frame."""
    axis = np.asarray(axis, float)
    h = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = np.cross(axis, h)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def camera_rotation(axis, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World-from-camera rotation (3, 3) of a camera with rerun's RDF convention (x right, y down, z
    forward) looking along the unit ``axis``, with ``up`` (world) toward the top of its image."""
    f = np.asarray(axis, float) / np.linalg.norm(axis)
    u = np.asarray(up, float)
    u = u - f * float(f @ u)
    if np.linalg.norm(u) < 1e-9:  # looking along "up": any perpendicular
        u = _frame(f)[0]
    down = -u / np.linalg.norm(u)
    right = np.cross(down, f)
    return np.stack([right, down, f], axis=1)


def endoscope_geometry(e) -> dict:
    """The nominal endoscope ``e`` (:class:`errplan.scenario.Endoscope`): port, unit optical axis, lens."""
    from ..anatomy.setup import lens_of, optical_axis

    port = np.asarray(e.port.estimate, float)
    return {"port": port, "axis": optical_axis(port, e.look_at), "lens": lens_of(port, e.look_at, e.insertion)}


def resample_path(path, step: float = 0.002, most: int = 60) -> np.ndarray:
    """Points of a polyline (n, 3) about every ``step`` m (at most ``most`` of them, ends kept)."""
    from ..anatomy.setup import resample

    pts = resample(np.asarray(path, float).reshape(-1, 3), step)
    if len(pts) > most:
        pts = pts[np.unique(np.linspace(0, len(pts) - 1, most).round().astype(int))]
    return pts


def arm_along(arm, tips, port, length: float, near=None) -> np.ndarray:
    """Joint values (n, joints) putting the tip at each of ``tips`` through ``port`` (each solved near the
    previous one: one branch along the path)."""
    from ..kinematics.urdf.collision import arm_at_tip

    out = []
    for t in np.asarray(tips, float):
        near = arm_at_tip(arm, t, port, length, near=near)
        out.append(near)
    return np.array(out)


# --------------------------------------------------------------------------- logging pieces
def _arm_models(st) -> dict:
    """Per arm: its ``UrdfArm``, visual geometry (None when the URDF has none: links as lines), port and
    rest configuration."""
    from ..errors import ErrplanError
    from ..kinematics import arm_for
    from ..kinematics.urdf.collision import ArmCollision

    out = {}
    for name, sc in zip(st.arm_names, st.arms):
        arm = arm_for(sc.robot)
        try:
            geo = ArmCollision.from_arm(arm, kind="visual")
        except ErrplanError:
            geo = None
        port = np.asarray(sc.port.position, float)
        rest = st.rest(name)
        q_rest = arm_at_tip(arm, rest, port, sc.instrument.length) if rest is not None else None
        out[name] = {"arm": arm, "geo": geo, "port": port, "length": float(sc.instrument.length),
                     "rest_tip": None if rest is None else np.asarray(rest, float), "q_rest": q_rest}
    return out


def arm_at_tip(arm, tip, port, length, near=None):
    from ..kinematics.urdf.collision import arm_at_tip as _at

    return _at(arm, np.asarray(tip, float), port, length, near=near)


def _log_arm_state(rec, rr, name: str, m: dict, q, tip, color, static: bool = False) -> None:
    ui = rr.Radius.ui_points
    base = f"world/arms/{entity_name(name)}"
    if m["geo"] is not None:
        log_arm_geometry(rec, f"{base}/links", m["geo"], q, color=color, static=static)
    arm = m["arm"]
    rec.log(f"{base}/chain", rr.LineStrips3D([arm.chain_points(np.asarray(q, float))], colors=color, radii=ui(3.0)),
            static=static)
    wrist = arm.forward(np.asarray(q, float))
    rec.log(f"{base}/shaft", rr.LineStrips3D([[wrist, m["port"], tip]], colors=(235, 235, 235), radii=ui(2.0)),
            static=static)
    rec.log(f"{base}/tip", rr.Points3D([tip], colors=color, radii=ui(5.0)), static=static)


def _log_endoscope(rec, rr, base: str, e, port=None) -> np.ndarray:
    """The endoscope (nominal, or through ``port``): shaft, lens, view cone and the Pinhole camera at the
    lens. Returns the lens."""
    from ..anatomy.setup import lens_of, optical_axis

    ui = rr.Radius.ui_points
    p = np.asarray(e.port.estimate if port is None else port, float)
    axis = optical_axis(p, e.look_at)
    lens = lens_of(p, e.look_at, e.insertion)
    rec.log(f"{base}/shaft", rr.LineStrips3D([[p, lens]], colors=ENDO_COLOR, radii=ui(3.0)), static=True)
    rec.log(f"{base}/lens", rr.Points3D([lens], colors=ENDO_COLOR, radii=ui(6.0), labels=["lens"]), static=True)
    V, T = view_cone_mesh(lens, axis, e.fov, e.depth[1])
    rec.log(f"{base}/cone", rr.Mesh3D(vertex_positions=V.astype(np.float32), triangle_indices=T.astype(np.uint32),
                                      albedo_factor=(*ENDO_COLOR, CONE_ALPHA)), static=True)
    rec.log(f"{base}/camera", rr.Transform3D(translation=lens, mat3x3=camera_rotation(axis)), static=True)
    rec.log(f"{base}/camera", rr.Pinhole(fov_y=float(e.fov), aspect_ratio=1.0, camera_xyz=rr.ViewCoordinates.RDF,
                                         image_plane_distance=float(e.depth[0])), static=True)
    return lens


def _log_anatomy(rec, rr, sc) -> None:
    from .space import log_anatomy_meshes

    log_anatomy_meshes(rec, rr, sc)


def _eye(rrb, position, target):
    return rrb.EyeControls3D(position=list(map(float, position)), look_target=list(map(float, target)),
                             eye_up=[0.0, 1.0, 0.0], kind=rrb.Eye3DKind.Orbital)


# --------------------------------------------------------------------------- plan of a setup
def record_setup_plan(path, st, plans, *, app_id: str = "errplan") -> None:
    """Write one ``.rrd`` of ``errplan plan`` on a setup: ``plans`` the ``(arm name, scenario, ScenarioPlan)``
    of every arm planned (module docstring). Nothing half-written on error."""
    models = _arm_models(st)
    e = st.endoscope

    def log(rec, rr):
        ui = rr.Radius.ui_points
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        _log_anatomy(rec, rr, st.arms[0])
        colors = {n: ARM_COLORS[i % len(ARM_COLORS)] for i, n in enumerate(st.arm_names)}
        for n, m in models.items():
            en = entity_name(n)
            rec.log(f"world/arms/{en}/port", rr.Points3D([m["port"]], colors=PORT_TRUE_COLOR, radii=ui(7.0),
                                                        labels=[f"{n} port"]), static=True)
        if e is not None:
            _log_endoscope(rec, rr, "world/endoscope", e)
        # the motion timeline: each planned query in turn, the other arms at rest (an arm without a query
        # of its own: at rest throughout, static)
        moving = {n for n, _, plan in plans if plan.queries}
        for n, m in models.items():
            if n not in moving and m["q_rest"] is not None:
                _log_arm_state(rec, rr, n, m, m["q_rest"], m["rest_tip"], colors[n], static=True)
        offset = 0
        for n, sc, plan in plans:
            m = models[n]
            for qp in plan.queries:
                qn = entity_name(f"{n} {qp.name}")
                rec.log(f"world/queries/{qn}/planned", rr.LineStrips3D([np.asarray(qp.planned.path)],
                                                                      colors=PLANNED_COLOR, radii=ui(3.5)), static=True)
                rec.log(f"world/queries/{qn}/direct", rr.LineStrips3D([np.asarray(qp.direct.path)],
                                                                     colors=DIRECT_COLOR, radii=ui(2.5)), static=True)
                tips = resample_path(qp.planned.path)
                qs = arm_along(m["arm"], tips, m["port"], m["length"], near=m["q_rest"])
                rec.set_time("motion", sequence=offset)
                rec.log("motion/query", rr.TextLog(f"arm {n}: {qp.name} (planned, {len(tips)} states)"))
                for o, mo in models.items():
                    if o != n and o in moving and mo["q_rest"] is not None:
                        _log_arm_state(rec, rr, o, mo, mo["q_rest"], mo["rest_tip"], colors[o])
                for i, (q, t) in enumerate(zip(qs, tips)):
                    rec.set_time("motion", sequence=offset + i)
                    _log_arm_state(rec, rr, n, m, q, t, colors[n])
                offset += len(tips)
        rec.reset_time()

    rrb = sdk.blueprint()
    region = st.arms[0].fields.region
    centre = np.array([0.5 * (region[a][0] + region[a][1]) for a in "xyz"])
    views = [rrb.Spatial3DView(origin="/world", name=f"{st.name}: arms, shafts, endoscope, paths",
                               eye_controls=_eye(rrb, centre + [0.35, 0.25, -0.45], centre))]
    if e is not None:
        g = endoscope_geometry(e)
        views.append(rrb.Spatial3DView(origin="/world", name="view from the endoscope (eye at the lens)",
                                       contents=["+ /world/**", "- /world/endoscope/**"],
                                       eye_controls=_eye(rrb, g["lens"], e.look_at)))
    bp = rrb.Blueprint(rrb.Horizontal(*views), rrb.TimePanel(timeline="motion", state="collapsed"),
                       collapse_panels=True)
    sdk.write(path, app_id, f"errplan-{st.name}", bp, log)


# --------------------------------------------------------------------------- triad placement
def triad_target_angles(result: dict) -> tuple[np.ndarray, np.ndarray]:
    """Targets (T, 3) of a ``triad_placement`` result and the manipulation angle m(t) (rad) at each
    for its best triad's instrument ports."""
    from ..anatomy.setup import manipulation_angle

    X = np.asarray(result["_arrays"]["targets"], float)
    n1, n2 = result["instruments"]
    P = result["best"]["ports"]
    return X, manipulation_angle(X, P[n1], P[n2])


def _log_setup(rec, rr, st, d: dict, base: str, X: np.ndarray, cols: dict) -> None:
    """A ``setup_placement`` result: the candidate bases per arm, the chosen ones, each arm drawn from its
    URDF at its chosen base (at rest, and at the first target both instruments cover), and the patient
    clearance per target (the smallest of the two arms' link-to-body distances, at the covered targets)."""
    from dataclasses import replace

    from ..errors import ErrplanError
    from ..kinematics import arm_for
    from ..kinematics.urdf.collision import ArmCollision

    ui = rr.Radius.ui_points
    b = d["best"]
    arrays = d["_arrays"]
    n1, n2 = d["instruments"]
    covered = None
    for name in (n1, n2):
        rn = entity_name(name)
        pos = np.array([c["position"] for c in d["bases"][name]], float)
        rec.log(f"{base}/bases/candidates/{rn}", rr.Points3D(pos, colors=tuple(int(0.55 * c) for c in cols[name]),
                                                            radii=ui(5.0)), static=True)
        rec.log(f"{base}/bases/chosen/{rn}", rr.Points3D([b["bases"][name]["position"]], colors=cols[name],
                                                        radii=ui(11.0), labels=[f"{name} base"]), static=True)
        Q = (arrays.get("arm_q") or {}).get(name)
        ok = np.zeros(len(X), bool) if Q is None else np.all(np.isfinite(Q), axis=1)
        covered = ok if covered is None else covered & ok
    for name in (n1, n2):
        sc = st.arm(name)
        robot = replace(sc.robot, base_position=tuple(b["bases"][name]["position"]),
                        base_rpy=tuple(b["bases"][name]["rpy"]))
        arm = arm_for(robot)
        try:
            geo = ArmCollision.from_arm(arm, kind="visual")
        except ErrplanError:
            geo = None
        m = {"arm": arm, "geo": geo, "port": np.asarray(b["ports"][name], float),
             "length": float(sc.instrument.length)}
        rest_q = (arrays.get("arm_rest_q") or {}).get(name)
        if rest_q is not None and np.all(np.isfinite(rest_q)):
            _log_arm_state(rec, rr, f"{name} at rest", m, rest_q, np.asarray(st.rest(name), float), cols[name],
                           static=True)
        if covered is not None and covered.any():
            k = int(np.flatnonzero(covered)[0])
            _log_arm_state(rec, rr, f"{name} at a target", m, arrays["arm_q"][name][k], X[k], cols[name], static=True)
    pt = b.get("patient_clearance_targets")
    if pt:
        v = np.fmin(np.array(pt[n1], float), np.array(pt[n2], float))  # NaN where not covered
        rec.log(f"{base}/patient_clearance", rr.SeriesPoints(names="patient clearance (mm)"), static=True)
        idx = np.flatnonzero(np.isfinite(v))
        if len(idx):
            rec.send_columns(f"{base}/patient_clearance", indexes=[rr.TimeColumn("target", sequence=idx)],
                             columns=rr.Scalars.columns(scalars=1000.0 * v[idx]))
            rec.log(f"{base}/patient_clearance_targets",
                    rr.Points3D(X[idx], colors=turbo(np.clip(v[idx] / max(float(np.nanmax(v)), 1e-9), 0.0, 1.0)),
                                radii=ui(4.0), labels=[f"patient {1000 * x:.1f} mm" for x in v[idx]],
                                show_labels=False), static=True)


def record_triad(path, st, results, *, app_id: str = "errplan") -> None:
    """Write one ``.rrd`` of the ``triad_placement`` results (:class:`errplan.tolerance.ToleranceResult`)
    of setup ``st`` (module docstring). Nothing half-written on error."""
    e = st.endoscope
    names = [entity_name(r.name) for r in results]

    def log(rec, rr):
        ui = rr.Radius.ui_points
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        _log_anatomy(rec, rr, st.arms[0])
        for r, qn in zip(results, names):
            d = r.data
            base = f"world/triad/{qn}"
            n1, n2 = d["instruments"]
            roles = (n1, n2, "endoscope")
            cols = {n1: ARM_COLORS[0], n2: ARM_COLORS[1], "endoscope": ENDO_COLOR}
            for role in roles:
                rn = entity_name(role)
                rec.log(f"{base}/candidates/{rn}", rr.Points3D(np.asarray(d["candidates"][role], float),
                                                               colors=tuple(int(0.55 * c) for c in cols[role]),
                                                               radii=ui(3.0)), static=True)
                rec.log(f"{base}/chosen/{rn}", rr.Points3D([d["best"]["ports"][role]], colors=cols[role],
                                                           radii=ui(9.0), labels=[f"{role} port"]), static=True)
            X, m = triad_target_angles(d)
            for role in (n1, n2):
                p = np.asarray(d["best"]["ports"][role], float)
                rec.log(f"{base}/shafts/{entity_name(role)}",
                        rr.LineStrips3D([[p, x] for x in X], colors=(*cols[role], 90), radii=ui(0.75)), static=True)
            _log_endoscope(rec, rr, f"{base}/endoscope", e, port=d["best"]["ports"]["endoscope"])
            w = d["weights"]
            lo = w["manipulation_angle"] - 2 * w["manipulation_tolerance"]
            hi = w["manipulation_angle"] + 2 * w["manipulation_tolerance"]
            rec.log(f"{base}/targets", rr.Points3D(X, colors=turbo(np.clip((m - lo) / (hi - lo), 0.0, 1.0)),
                                                   radii=ui(5.0), labels=[f"m = {math.degrees(v):.1f} deg" for v in m],
                                                   show_labels=False), static=True)
            rec.log(f"{base}/manipulation_angle", rr.SeriesPoints(names="m(t) (deg)"), static=True)
            rec.send_columns(f"{base}/manipulation_angle", indexes=[rr.TimeColumn("target", sequence=np.arange(len(m)))],
                             columns=rr.Scalars.columns(scalars=np.degrees(m)))
            if "bases" in d:
                _log_setup(rec, rr, st, d, base, X, cols)

    rrb = sdk.blueprint()
    d0 = results[0].data
    reg = d0["region"]
    centre = np.array([0.5 * (reg[a][0] + reg[a][1]) for a in "xyz"])
    main = rrb.Spatial3DView(origin="/world", name="triad: candidates, chosen ports, shafts, m(t) at the targets",
                             eye_controls=_eye(rrb, centre + [0.30, 0.22, -0.40], centre))
    plots = [rrb.TimeSeriesView(origin=f"/world/triad/{q}/manipulation_angle", name=f"{q}: m(t) per target")
             for q in names]
    plots += [rrb.TimeSeriesView(origin=f"/world/triad/{q}/patient_clearance", name=f"{q}: patient clearance per target")
              for q, r in zip(names, results) if r.data["best"].get("patient_clearance_targets")]
    bp = rrb.Blueprint(rrb.Horizontal(main, rrb.Vertical(*plots), column_shares=[3, 1]), collapse_panels=True)
    sdk.write(path, app_id, f"errplan-{st.name}-triad", bp, log)
