#!/bin/sh
# docs/screenshot.png and docs/screenshot_3d.png: the demo's planar and spatial recordings in the real
# (native) rerun viewer with the blueprint errplan writes into them, on a machine without a screen, as
# docs/abdomen_viewer_shot.sh (same Debian packages:
#   apt-get install -y xvfb mesa-vulkan-drivers libgl1-mesa-dri libegl1 imagemagick; optional: pngquant).
# Run from the repository root: sh docs/demo_shot.sh [PYTHON]
# 1. errplan demo records the planar demo scenario and the spatial one, one at a time (--scenario);
# 2. the viewer opens each recording under Xvfb (its own blueprint: the view, the series, the tabs) and
#    `--screenshot-to` saves the frame and quits; the window renders at 2x (3200x2000 at the top left) and
#    the screen is large enough that the pointer, at its centre, is off the window: no hover tooltip;
#    imagemagick halves the frame to 1600x1000 and pngquant (Debian's pngquant), when present, packs it.
set -eu
PY=${1:-python}
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT
export CI=true  # rerun: no analytics
RERUN=$(dirname "$(command -v "$PY")")/rerun
[ -x "$RERUN" ] || RERUN=rerun
shot() {  # shot SCENARIO OUT
  "$PY" -m errplan demo --scenario "$1" --record "$TMP/demo.rrd" >"$TMP/demo.log"
  xvfb-run -a -s "-screen 0 5000x3400x24" sh -c \
    "exec '$RERUN' '$TMP/demo.rrd' --window-size 1600x1000 --screenshot-to '$TMP/raw.png'" \
    >"$TMP/viewer.log" 2>&1
  convert "$TMP/raw.png" -resize 50% -strip "$2"
  if command -v pngquant >/dev/null; then pngquant --quality 70-95 --speed 1 --strip -f -o "$2" "$2"; fi
  rm -f "$TMP/demo.rrd" "$TMP/raw.png"
  echo "wrote $2"
}
shot scenarios/beasley2004_bounded.toml docs/screenshot.png
shot scenarios/phantom15_spatial.toml docs/screenshot_3d.png
