#!/bin/sh
# docs/setup_viewer.png: the bundled setup placement (scenarios/ur5_setup.toml) in the real (native)
# rerun viewer, on a machine without a screen, as docs/abdomen_viewer_shot.sh (same Debian packages:
#   apt-get install -y xvfb mesa-vulkan-drivers libgl1-mesa-dri libegl1 imagemagick).
# Run from the repository root: sh docs/setup_viewer_shot.sh [PYTHON]
# 1. errplan chooses the bases with the port triad and records it (errplan tolerance --record);
# 2. docs/setup_viewer_blueprint.py writes a blueprint: one 3-D view of world/ with the candidate and
#    chosen bases, both UR5s at a target (translucent) and the torso, without the arms at rest, the
#    candidate ports, the shaft fans and the view cone; the camera above the head end of the table,
#    looking toward the bases;
# 3. the viewer opens both under Xvfb, `--screenshot-to` saves the frame and quits; imagemagick halves it.
set -eu
PY=${1:-python}
OUT=docs/setup_viewer.png
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT
export CI=true  # rerun: no analytics
RERUN=$(dirname "$(command -v "$PY")")/rerun
[ -x "$RERUN" ] || RERUN=rerun
"$PY" -m errplan tolerance scenarios/ur5_setup.toml --record "$TMP/setup.rrd" --json "$TMP/setup.json" \
  >"$TMP/tolerance.log"
"$PY" docs/setup_viewer_blueprint.py "$TMP/setup.rrd" "$TMP/view.rbl" 0.0,1.15,1.05 0.0,0.12,0.44 >/dev/null
xvfb-run -a -s "-screen 0 5000x3400x24" sh -c \
  "exec '$RERUN' '$TMP/setup.rrd' '$TMP/view.rbl' --window-size 1200x800 --screenshot-to '$TMP/raw.png'" \
  >"$TMP/viewer.log" 2>&1
convert "$TMP/raw.png" -resize 50% -strip "$OUT"
echo "wrote $OUT"
