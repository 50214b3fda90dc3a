#!/usr/bin/env python
"""A blueprint (.rbl) for the abdomen plan recording (docs/abdomen_viewer_shot.sh): one 3-D view of the
anatomy, the robot and the paths. Usage: abdomen_viewer_blueprint.py RECORDING.rrd OUT.rbl EYE TARGET
(EYE, TARGET: "x,y,z" in m, the world frame of errplan's recordings, y up). ``entities`` and
``save_view`` also serve the other viewer shots (docs/setup_viewer_blueprint.py)."""
import sys
import rerun as rr
import rerun.blueprint as rrb
import rerun.chunk as rrc


def entities(rrd):
    """The entity paths of a recording."""
    return {ch.entity_path for ch in rrc.RrdReader(rrd).stream().to_chunks()}


def save_view(out, name, hide, eye, target, overrides=None):
    """Save one 3-D view of /world (without ``hide``, with the camera at ``eye`` looking at ``target``,
    y up, no grid, panels collapsed) as the blueprint ``out`` of application "errplan"."""
    bp = rrb.Blueprint(
        rrb.Spatial3DView(origin="/world", name=name, contents=["+ /world/**"] + ["- " + h for h in hide],
                          eye_controls=rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=eye,
                                                         look_target=target, eye_up=[0.0, 1.0, 0.0]),
                          line_grid=rrb.LineGrid3D(visible=False), overrides=overrides or {}),
        collapse_panels=True)
    bp.save("errplan", out)


def point(arg):
    """ "x,y,z" -> [x, y, z]."""
    return [float(v) for v in arg.split(",")]


if __name__ == "__main__":
    rrd, out = sys.argv[1], sys.argv[2]
    ents = entities(rrd)
    queries = sorted({e.split("/")[2] for e in ents if e.startswith("/world/") and e.endswith("/planned")
                      and e.count("/") == 3})
    hide = ["/world/fields/**", "/world/port/error_box/**"]
    for q in queries:
        hide += [f"/world/{q}/corners/**", f"/world/{q}/sim/**", f"/world/{q}/segments/**"]
    save_view(out, "abdomen: organs, vessel, body wall; planned (green) and direct (red) paths", hide,
              point(sys.argv[3]), point(sys.argv[4]),
              {"/world/anatomy/body_wall": rr.Mesh3D.from_fields(albedo_factor=(230, 200, 170, 12))})
    print(queries)
