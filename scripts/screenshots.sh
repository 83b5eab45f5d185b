#!/usr/bin/env bash
# Screenshots of the Rerun viewer on real runs of the twin, rendered headless, for the docs:
#   docs/images/viewer-default.png  the default layout (scenarios/default.toml, the layout the
#                                   supervisor sends with every recording)
#   docs/images/viewer-flow-cell.png     a flow cell's tracking (scenarios/flow.toml)
# The viewer renders with Mesa's software Vulkan driver under a virtual X server (Debian's xvfb
# and mesa-vulkan-drivers, installed here when missing); it exits non-zero after writing the
# screenshot, so success is the PNG being there. The virtual screen is larger than the window so
# that its pointer, which starts at the screen's centre, hovers over nothing.
#
# Usage: scripts/screenshots.sh [OUT_DIR]   (default docs/images)
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
OUT="${1:-docs/images}"
mkdir -p "$OUT"

scripts/apt_install.sh screenshots xvfb xauth mesa-vulkan-drivers

WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT
MILLINAV="$CARGO_TARGET_DIR/release/millinav"

# One run of a scenario, without a viewer: its merged recording.
record() {
  local scenario="$1" name="$2"
  echo "screenshots: running $scenario" >&2
  "$MILLINAV" run "$scenario" --viewer none --run-dir "$WORK/$name" \
    --iox-prefix "shots$$-$name"_ --iox-root "$WORK/iox-$name" >"$WORK/$name.log" 2>&1 || {
    tail -20 "$WORK/$name.log" >&2
    exit 1
  }
  echo "$WORK/$name/run.rrd"
}

# A screenshot of the viewer showing FILES (a recording, and optionally a blueprint).
shoot() {
  local png="$1"
  shift
  rm -f "$png"
  WGPU_BACKEND=vulkan timeout 300 xvfb-run -a -s "-screen 0 7000x5000x24" \
    "$MILLINAV_VENV/bin/rerun" "$@" --window-size 1600x1000 --screenshot-to "$png" \
    >"$WORK/viewer.log" 2>&1 || true
  if [ ! -s "$png" ]; then
    tail -20 "$WORK/viewer.log" >&2
    echo "screenshots: the viewer wrote no $png" >&2
    exit 1
  fi
  echo "screenshots: wrote $png"
}

default_rrd="$(record scenarios/default.toml default | tail -1)"
flow_rrd="$(record scenarios/flow.toml flow | tail -1)"
shoot "$OUT/viewer-default.png" "$default_rrd"
shoot "$OUT/viewer-flow-cell.png" "$flow_rrd"
