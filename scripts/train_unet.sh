#!/usr/bin/env bash
# Trains the UNet localizer on domain-randomized twin renders with the camera's shifts applied
# in training (tools/unet/augment.py), then quantizes it to int8 for the vision service.
# Needs python3 with JAX, optax, onnx and onnxruntime (scripts/setup_training.sh: CPU wheels; the
# CPU works, for hours; on an NVIDIA GPU, minutes, after `pip install "jax[cuda12]==0.10.2"` in
# the same venv) and a built unet-dataset (BIN, default $CARGO_TARGET_DIR/release).
#
#   scripts/train_unet.sh OUT_DIR [train.py options, e.g. --epochs 80]
#
# OUT_DIR gets data/ (the crops), unet_roi96.onnx / .npz (model, weights), unet_roi96_int8.onnx,
# training_metrics.json and train_log.txt. Evaluate with
#   millinav vision eval --rig RIG --model OUT_DIR/unet_roi96_int8.onnx [--robustness]
# and copy the models to tools/unet/model/ when they hold up. Sizes: TRAIN_PER crops per
# randomized generator (4 of them, default 4000), MINUTES of training at most (default 8).
# RIG: the rig whose camera, phantom and capsule the crops render (default: the paper's rig, whose
# model tools/unet/model/ holds).
set -euo pipefail
OUT=${1:?usage: scripts/train_unet.sh OUT_DIR [train.py options]}
shift
ROOT=$(cd "$(dirname "$0")/.." && pwd)
BIN=${BIN:-${CARGO_TARGET_DIR:-$ROOT/target}/release}
RIG=${RIG:-$ROOT/fieldmaps/rigs/paper.toml}
PYTHON=${PYTHON:-python3}
TRAIN_PER=${TRAIN_PER:-4000}
MINUTES=${MINUTES:-8}
DATA="$OUT/data"
mkdir -p "$DATA"
[ -x "$BIN/unet-dataset" ] || { echo "no $BIN/unet-dataset: cargo build --release -p millinav-unet" >&2; exit 1; }
"$PYTHON" -c "import jax, optax, onnx, onnxruntime" ||
  { echo "$PYTHON lacks jax, optax, onnx or onnxruntime (scripts/setup_training.sh)" >&2; exit 1; }

echo "== crops (seeds 5000-5302; the committed test set uses 9002, the held-out split 4000)"
pids=()
gen() { "$BIN/unet-dataset" "$@" --rig "$RIG" >"$DATA/$(basename "$2").log" 2>&1 & pids+=($!); }
gen --out "$DATA/main" --style randomized --train 2000 --val 500 --test 500 --cameras 16 --seed 5000
for k in 1 2 3 4; do
  gen --out "$DATA/r$k" --style randomized --train "$TRAIN_PER" --val 0 --test 0 --cameras 16 --seed $((5000 + 10 * k))
done
gen --out "$DATA/twin" --style twin --train 2000 --val 0 --test 0 --cameras 8 --seed 5200
gen --out "$DATA/calib" --style randomized --train 300 --val 0 --test 0 --cameras 8 --seed 5300
for p in "${pids[@]}"; do wait "$p" || { echo "unet-dataset failed, see $DATA/*.log" >&2; exit 1; }; done
tail -qn1 "$DATA"/*.log

echo "== training"
"$PYTHON" "$ROOT/tools/unet/train.py" --data "$DATA/main" \
  --data "$DATA/r1" --data "$DATA/r2" --data "$DATA/r3" --data "$DATA/r4" --data "$DATA/twin" \
  --out "$OUT/unet_roi96.onnx" --batch 64 --epochs 100 --patience 12 --max-minutes "$MINUTES" \
  --dump-augmented "$DATA/calib_shifted" 300 --metrics "$OUT/training_metrics.json" "$@" \
  2>&1 | tee "$OUT/train_log.txt"

echo "== int8 (calibrated on clean and shifted crops that no split above trains on)"
"$PYTHON" "$ROOT/tools/unet/quantize.py" --calib "$DATA/calib/train" --calib "$DATA/calib_shifted" \
  --samples 300 --model "$OUT/unet_roi96.onnx" --out "$OUT/unet_roi96_int8.onnx"
echo "done: $OUT/unet_roi96.onnx, $OUT/unet_roi96_int8.onnx"
