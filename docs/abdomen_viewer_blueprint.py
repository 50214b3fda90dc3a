#!/usr/bin/env python
"""A blueprint (.rbl) for the abdomen plan recording (docs/abdomen_viewer_shot.sh): one 3-D view of the
anatomy, the robot and the paths. Usage: abdomen_viewer_blueprint.py RECORDING.rrd OUT.rbl EYE TARGET
(EYE, TARGET: "x,y,z" in m, the world frame of errplan's recordings, y up)."""
import sys
import rerun as rr
import rerun.blueprint as rrb
import rerun.chunk as rrc

rrd, out = sys.argv[1], sys.argv[2]
eye = [float(v) for v in sys.argv[3].split(",")]
target = [float(v) for v in sys.argv[4].split(",")]
ents = {ch.entity_path for ch in rrc.RrdReader(rrd).stream().to_chunks()}
queries = sorted({e.split("/")[2] for e in ents if e.startswith("/world/") and e.endswith("/planned")
                  and e.count("/") == 3})
hide = ["/world/fields/**", "/world/port/error_box/**"]
for q in queries:
    hide += [f"/world/{q}/corners/**", f"/world/{q}/sim/**", f"/world/{q}/segments/**"]
bp = rrb.Blueprint(
    rrb.Spatial3DView(origin="/world", name="abdomen: organs, vessel, body wall; planned (green) and direct (red) paths",
                      contents=["+ /world/**"] + ["- " + h for h in hide],
                      eye_controls=rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=eye, look_target=target,
                                                     eye_up=[0.0, 1.0, 0.0]),
                      line_grid=rrb.LineGrid3D(visible=False),
                      overrides={"/world/anatomy/body_wall": rr.Mesh3D.from_fields(albedo_factor=(230, 200, 170, 12))}),
    collapse_panels=True)
bp.save("errplan", out)
print(queries)
