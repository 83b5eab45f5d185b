#!/usr/bin/env bash
# Deadline misses of the process set at 100 Hz in real time with a CPU hog beside it (one busy
# loop per core), with the default launch and with scenarios/launch/realtime.toml (SCHED_FIFO,
# locked memory). Each run lasts MINUTES (default 10); the figures come from each run's
# summary.json. Prints a Markdown table.
#
#   scripts/bench_realtime.sh [MINUTES]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
MINUTES=${1:-10}
SECONDS_RUN=$(awk "BEGIN { print int($MINUTES * 60) }")
B="$CARGO_TARGET_DIR/release"
OUT=runs/bench-realtime
mkdir -p "$OUT"
SCENARIO="$OUT/scenario.toml"
sed -e 's/^mode = .*/mode = "realtime"/' -e "s/^duration_s = .*/duration_s = $((SECONDS_RUN + 30))/" \
  scenarios/default.toml > "$SCENARIO"
hogs=()
stop_hogs() { for p in "${hogs[@]}"; do kill "$p" 2>/dev/null || true; done; hogs=(); }
trap stop_hogs EXIT
rows=()
for setting in default realtime; do
  launch=()
  [ "$setting" = realtime ] && launch=(--launch scenarios/launch/realtime.toml)
  # A fresh run directory: logs append, and an earlier run's rows would mix in.
  rm -rf "${OUT:?}/$setting"
  for _ in $(seq "$(nproc)"); do (while :; do :; done) & hogs+=($!); done
  echo "== $setting: $MINUTES min at 100 Hz with $(nproc) busy loops beside the set" >&2
  "$B/millinav" run "$SCENARIO" "${launch[@]}" --run-dir "$OUT/$setting" --viewer none \
    --max-wall-s "$SECONDS_RUN" > "$OUT/$setting.out" 2>"$OUT/$setting.log" || true
  stop_hogs
  summary="$OUT/$setting/summary.json"
  [ -f "$summary" ] || { echo "no $summary (see $OUT/$setting.log)" >&2; exit 1; }
  denied=$(grep -c realtime_denied "$OUT/$setting/supervisor_events.csv" || true)
  rows+=("$(python3 - "$summary" "$setting" "$denied" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
m = s["deadline_misses"]
per = ", ".join(f"{k} {m.get(k, 0)}" for k in ["plant", "vision", "flow", "control", "coilbus"])
seen = s.get("as_control_saw") or {}
print(f"| {sys.argv[2]} | {s['duration_s']:.0f} s | {s['frames']} ({s['frames'] / (100 * s['duration_s']):.0%}) | {sum(m.values())} | {per} | "
      f"{sys.argv[3]} | {seen.get('rmse_mm', float('nan')):.3f} mm |")
PY
)")
done
echo "| launch | duration | frames answered (of 100 Hz) | deadline misses | per service | settings denied | RMSE (control saw) |"
echo "|---|---|---|---|---|---|---|"
printf '%s\n' "${rows[@]}"
