#!/bin/sh
# docs/abdomen_viewer.png: the bundled abdomen in the real (native) rerun viewer, on a machine without a
# screen. Needs Debian's xvfb, mesa (llvmpipe: software Vulkan) and imagemagick:
#   apt-get install -y xvfb mesa-vulkan-drivers libgl1-mesa-dri libegl1 imagemagick
# Run from the repository root: sh docs/abdomen_viewer_shot.sh [PYTHON]
# 1. errplan plans the abdomen's three queries and records them (errplan plan --record);
# 2. docs/abdomen_viewer_blueprint.py writes a blueprint (.rbl, same application id "errplan"): one 3-D
#    view of world/ without the field slices, corner replays, simulated runs and segment marks, the wall
#    more transparent, the camera set;
# 3. the viewer opens both under Xvfb and `--screenshot-to` saves the frame and quits; the window renders
#    at 2x (2400x1600 at the top left) and the screen is large enough that the pointer, left at its centre
#    (xdotool could not move it), is off the window: no hover tooltip; imagemagick halves the frame.
set -eu
PY=${1:-python}
OUT=docs/abdomen_viewer.png
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT
export CI=true  # rerun: no analytics
RERUN=$(dirname "$(command -v "$PY")")/rerun
[ -x "$RERUN" ] || RERUN=rerun
"$PY" -m errplan plan scenarios/abdomen.toml --record "$TMP/abdomen.rrd" --json "$TMP/abdomen.json" >"$TMP/plan.log"
"$PY" docs/abdomen_viewer_blueprint.py "$TMP/abdomen.rrd" "$TMP/view.rbl" 0.30,0.20,0.08 0.0,0.02,0.32 >/dev/null
xvfb-run -a -s "-screen 0 5000x3400x24" sh -c \
  "exec '$RERUN' '$TMP/abdomen.rrd' '$TMP/view.rbl' --window-size 1200x800 --screenshot-to '$TMP/raw.png'" \
  >"$TMP/viewer.log" 2>&1
convert "$TMP/raw.png" -resize 50% -strip "$OUT"
echo "wrote $OUT"
