#!/usr/bin/env bash
# Issue 21 point 3: calibrate the twin's free physics on a subset of the paper's cells, freeze it,
# predict the rest. Fit cells: static 20 cP with PID, MPC and SMC-DOB (the paper's gains, 10 Hz,
# 3 seeds). Parameters: the floor gap (none, or 100 / 30 / 10 / 3 / 1 µm; with a floor the flow
# pushes with Goldman–Cox–Brenner's 1.7, see [plant.physics] floor_flow_factor) and the coils'
# L/R time constant (5 / 15 / 30 ms). Cost: mean over the fit cells of |ln(RMSE / paper)|, plus 1
# for every trial lost. The best pair then runs the paper's whole matrix (the held-out cells are
# every other cell the paper reports) and <out>/calibration.md holds both tables.
#
# Not fitted but fixed from the paper's pipeline: every run has PIPELINE_DELAY_MS (default 60)
# from a frame's capture to its command reaching the coils, not compensated, as the paper's
# controllers did not ([plant] command_delay_ms). The paper's loop ran sequentially at 8–10 Hz
# "including image processing and control computation", its UNet alone at 18 fps (56 ms), so
# the delay lies between 56 ms and the 100–125 ms period; 60 ms is that lower bound plus the
# serial link. PIPELINE_DELAY_MS=0 gives the calibration without it.
#
# DRAG_SHAPE=cylinder calibrates the twin whose capsule's drag is a cylinder's ([plant.physics]
# drag_shape): on the floor it slides along its axis against a gap^-½ film, not a sphere's
# logarithm (README, "What the twin lacks").
#
# FIT_COST="pid smc-dob" scores the fit on those controllers only (every fit cell is still run
# and shown): the paper prints PID's and SMC-DOB's gains but not MPC's weights, so MPC's RMSE
# measures our choice of weights as much as the plant. REUSE_FIT=1 keeps the fit runs already
# in OUT/fit (to score them again) and runs only what is missing.
#
#   ./scripts/calibrate_twin.sh [OUT]    (default OUT: results/calibration; ≈ 6 min on 2 cores)
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-results/calibration}"
source scripts/env.sh >/dev/null
experiments="$CARGO_TARGET_DIR/release/experiments"
mkdir -p "$out/fit"

delay_ms="${PIPELINE_DELAY_MS:-60}"
shape="${DRAG_SHAPE:-paper}"
common=(--base scenarios/paper.toml --frame-period-ms 100 --trials 3 --no-rrd --fresh
  --set "plant.command_delay_ms=$delay_ms" --no-latency-compensation
  --set "plant.physics.drag_shape=\"$shape\"")
gaps=(none 1e-4 3e-5 1e-5 3e-6 1e-6)
taus=(5 15 30)
flags_for() { # gap tau -> experiments flags
  local flags="--set plant.physics.coil_time_constant_ms=$2"
  [ "$1" = none ] || flags+=" --set plant.physics.floor_gap_m=$1 --set plant.physics.floor_flow_factor=1.7"
  echo "$flags"
}

total=$(( ${#gaps[@]} * ${#taus[@]} )); n=0
for gap in "${gaps[@]}"; do
  for tau in "${taus[@]}"; do
    n=$((n + 1)); name="gap_${gap}_tau_${tau}"
    if [ "${REUSE_FIT:-0}" = 1 ] && [ -f "$out/fit/$name/results.csv" ]; then
      echo "[$n/$total] fit: floor gap $gap m, coils $tau ms (kept from an earlier run)"
      continue
    fi
    echo "[$n/$total] fit: floor gap $gap m, coils $tau ms"
    # shellcheck disable=SC2046 # the flags are words
    "$experiments" "${common[@]}" --controllers pid,mpc,smc-dob --only 20cp_static \
      --out "$out/fit/$name" $(flags_for "$gap" "$tau") >"$out/fit/$name.log" 2>&1 ||
      { echo "experiments failed: see $out/fit/$name.log" >&2; exit 1; }
  done
done

fit_cost="${FIT_COST:-pid mpc smc-dob}"
best=$(python3 - "$out" "$fit_cost" "${gaps[@]}" -- "${taus[@]}" <<'EOF'
import csv, math, statistics, sys
out, scored = sys.argv[1], sys.argv[2].split()
split = sys.argv.index("--")
gaps, taus = sys.argv[3:split], sys.argv[split + 1:]
paper = {"pid": 0.82, "mpc": 1.57, "smc-dob": 0.49}
unknown = [c for c in scored if c not in paper]
if unknown or not scored:
    sys.exit(f"FIT_COST: {' '.join(unknown) or '(empty)'}: the fit cells are {' '.join(paper)}")
scores = []
for gap in gaps:
    for tau in taus:
        rows = {}
        for r in csv.DictReader(open(f"{out}/fit/gap_{gap}_tau_{tau}/results.csv")):
            rows.setdefault(r["controller"], []).append(r)
        cost, cells = 0.0, []
        for controller, target in paper.items():
            rs = rows[controller]
            rmse = statistics.mean(float(r["rmse_mm"]) for r in rs)
            lost = sum(r["completed"] != "true" for r in rs)
            if controller in scored:
                cost += abs(math.log(rmse / target)) / len(scored) + lost
            cells.append(f"{rmse:.2f}" + (f" ({len(rs) - lost}/{len(rs)})" if lost else ""))
        scores.append((cost, gap, tau, cells))
scores.sort(key=lambda s: s[0])
with open(f"{out}/fit.md", "w") as f:
    f.write("| floor gap | coils τ ms | PID (paper 0.82) | MPC (paper 1.57) | SMC-DOB (paper 0.49) | cost |\n")
    f.write("|---|---|---|---|---|---|\n")
    for cost, gap, tau, cells in scores:
        shown = "none (free stream)" if gap == "none" else f"{float(gap) * 1e6:g} µm"
        f.write(f"| {shown} | {tau} | " + " | ".join(cells) + f" | {cost:.2f} |\n")
print(scores[0][1], scores[0][2])
EOF
)
read -r gap tau <<<"$best"
echo "best fit: floor gap $gap, coils $tau ms; the paper's whole matrix with it (held-out cells)"
# shellcheck disable=SC2046
"$experiments" "${common[@]}" --controllers pid,mpc,smc-dob,smc --out "$out/held_out" \
  $(flags_for "$gap" "$tau") >"$out/held_out.log" 2>&1 ||
  { echo "experiments failed: see $out/held_out.log" >&2; exit 1; }

python3 - "$out" "$gap" "$tau" "$delay_ms" "$shape" "$fit_cost" <<'EOF'
import csv, statistics, sys
out, gap, tau, delay_ms, shape, fit_cost = sys.argv[1:7]
paper = [
    ("20", "static", "pid", 0.82, "fit"), ("20", "static", "mpc", 1.57, "fit"),
    ("20", "static", "smc-dob", 0.49, "fit"),
    ("4.3", "static", "pid", "failed", "held out"), ("4.3", "static", "mpc", "failed", "held out"),
    ("4.3", "static", "smc-dob", 1.05, "held out"),
    ("20", "7 cm/s", "pid", 1.59, "held out"), ("20", "7 cm/s", "smc-dob", 1.00, "held out"),
    ("20", "7 cm/s", "smc", "≈10x SMC-DOB", "held out"),
    ("4.3", "7 cm/s", "pid", "failed", "held out"), ("4.3", "7 cm/s", "mpc", "failed", "held out"),
    ("4.3", "7 cm/s", "smc-dob", 1.60, "held out"), ("20", "10 cm/s", "smc-dob", 2.0, "held out"),
]
rows = {}
for r in csv.DictReader(open(f"{out}/held_out/results.csv")):
    rows.setdefault((r["viscosity_cp"], r["flow"], r["controller"]), []).append(r)
mean = lambda k: statistics.mean(float(r["rmse_mm"]) for r in rows[k])
smc_dob_20_7 = mean(("20", "7 cm/s", "smc-dob"))
lines = ["| cell | set | paper RMSE mm | twin RMSE mm (completed) | ratio | within ±30 % / reproduced |",
         "|---|---|---|---|---|---|"]
within = {"fit": [0, 0], "held out": [0, 0]}
for v, f, c, target, role in paper:
    rs = rows[(v, f, c)]
    rmse = mean((v, f, c))
    done = sum(r["completed"] == "true" for r in rs)
    if isinstance(target, float):
        ratio = rmse / target
        ok = abs(ratio - 1) <= 0.3 and done == len(rs)
        ratio_text = f"{ratio:.2f}"
    elif target == "failed":
        ok, ratio_text = done < len(rs), "–"
    else:
        ok, ratio_text = rmse > 5 * smc_dob_20_7, f"{rmse / smc_dob_20_7:.1f}x SMC-DOB"
    within[role][0] += ok
    within[role][1] += 1
    lines.append(f"| {v} cP {f}, {c.upper()} | {role} | {target} | {rmse:.2f} ({done}/{len(rs)}) "
                 f"| {ratio_text} | {'yes' if ok else 'no'} |")
shown = "none (free-stream drag)" if gap == "none" else f"{float(gap) * 1e6:g} µm (flow factor 1.7)"
drag = ("a cylinder's (Tirado & García de la Torre; on the floor a gap^-½ film along its axis)"
        if shape == "cylinder" else "paper Eq. 7 (on the floor the sphere's wall factor)")
text = (f"Fixed, not fitted: {delay_ms} ms from a frame's capture to its command reaching the coils "
        f"(the paper's sequential 10 Hz pipeline), not compensated; the capsule's drag {drag}.\n\n"
        f"Calibrated on the fit cells (cost over {', '.join(c.upper() for c in fit_cost.split())}), "
        f"then frozen: floor gap {shown}, coil time constant {tau} ms. "
        f"Fit cells matched: {within['fit'][0]}/{within['fit'][1]}; held-out cells: "
        f"{within['held out'][0]}/{within['held out'][1]} (numeric within ±30 % with 3/3, or the "
        "paper's failure / ≈10x ablation reproduced).\n\nFit grid (`fit.md`, best first):\n\n"
        + open(f"{out}/fit.md").read() + "\nEvery cell the paper reports, with the frozen fit:\n\n"
        + "\n".join(lines) + "\n")
open(f"{out}/calibration.md", "w").write(text)
print(text)
EOF
