#!/usr/bin/env python
"""A blueprint (.rbl) for the setup placement recording (docs/setup_viewer_shot.sh): one 3-D view of the
candidate bases, the chosen ones, both arms at a target (translucent), the chosen ports, the endoscope, the
targets and the body (the arms at rest, the candidate ports, the shaft fans and the view cone hidden).
Usage: setup_viewer_blueprint.py RECORDING.rrd OUT.rbl EYE TARGET (EYE, TARGET: "x,y,z" in m, the world
frame of errplan's recordings, y up)."""
import sys

import rerun as rr
import rerun.chunk as rrc
from abdomen_viewer_blueprint import entities, point, save_view

ALPHA = 110  # the arms' links translucent: the arm behind and the links' chain show through


def translucent_links(rrd):
    """{entity: Mesh3D override}: every arm link at a target with its recorded colour at alpha ALPHA."""
    out = {}
    for ch in rrc.RrdReader(rrd).stream().to_chunks():
        e = ch.entity_path
        if e.startswith("/world/arms/") and "_at_a_target/links/" in e:
            rb = ch.to_record_batch()
            if "Mesh3D:albedo_factor" in rb.schema.names:
                rgba = rb.column("Mesh3D:albedo_factor").to_pylist()[-1][0]  # packed 0xRRGGBBAA
                rgb = [(rgba >> s) & 255 for s in (24, 16, 8)]
                out[e] = rr.Mesh3D.from_fields(albedo_factor=(*rgb, ALPHA))
    return out


rrd, out = sys.argv[1], sys.argv[2]
ents = entities(rrd)
queries = sorted({e.split("/")[3] for e in ents if e.startswith("/world/triad/") and "/bases/chosen/" in e})
if not queries:
    sys.exit(f"{rrd}: no setup placement (world/triad/<query>/bases/chosen)")
hide = ["/world/arms/*_at_rest/**"]
bigger = {}  # the candidate bases drawn larger: the arms' bases hide the small dots
for q in queries:
    t = f"/world/triad/{q}"
    hide += [f"{t}/candidates/**", f"{t}/endoscope/camera/**", f"{t}/endoscope/cone/**", f"{t}/shafts/**",
             f"{t}/patient_clearance_targets/**"]
    bigger.update({e: rr.Points3D.from_fields(radii=rr.Radius.ui_points(9.0)) for e in ents
                   if e.startswith(f"{t}/bases/candidates/")})
save_view(out, "setup placement: candidate bases (dark), chosen bases, the UR5s at a target, the torso", hide,
          point(sys.argv[3]), point(sys.argv[4]),
          {"/world/anatomy/body_wall": rr.Mesh3D.from_fields(albedo_factor=(230, 200, 170, 90)),
           **translucent_links(rrd), **bigger})
print(queries)
