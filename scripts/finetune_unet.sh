#!/usr/bin/env bash
# Fine-tunes the committed UNet localizer on your own labelled frames, then exports, quantizes
# and evaluates it against the committed model, in one command:
#
#   scripts/finetune_unet.sh LABELS OUT_DIR [--rig my_rig.toml] [train.py options]
#
# LABELS: a directory of LabelMe files (format: tools/unet/LABELS.md) or a split that
# unet-import already made (train/ and val/). OUT_DIR gets split/ (the imported crops),
# unet_roi96.onnx / .npz (fine-tuned model and its weights), unet_roi96_int8.onnx (quantized,
# calibrated on your crops), before.md / after.md (vision-eval on your val frames) and
# finetune_log.txt. Needs python3 with JAX, optax, onnx and onnxruntime (the project's venv after
# scripts/setup.sh and scripts/setup_training.sh: CPU only, no CUDA libraries; with a GPU,
# `pip install "jax[cuda12]==0.10.2"` there too) and the project built (BIN, default
# $CARGO_TARGET_DIR/release: unet-import, vision-eval). SKIP_EVAL=1 leaves out the two
# evaluations (a GPU machine without the project's OpenCV; run them where it is built).
# INIT: the weights to start from (default tools/unet/model/unet_roi96.npz; a PyTorch .pt
# state dict of the earlier trainer works too).
set -euo pipefail
usage="usage: scripts/finetune_unet.sh LABELS OUT_DIR --rig RIG [train.py options]"
LABELS=${1:?$usage}
OUT=${2:?$usage}
shift 2
[ "${1:-}" = "--rig" ] || { echo "$usage (RIG: the rig file whose camera took the frames)" >&2; exit 2; }
RIG_ARGS=(--rig "${2:?--rig needs a file}")
shift 2
ROOT=$(cd "$(dirname "$0")/.." && pwd)
BIN=${BIN:-${CARGO_TARGET_DIR:-$ROOT/target}/release}
PYTHON=${PYTHON:-python3}
INIT=${INIT:-$ROOT/tools/unet/model/unet_roi96.npz}
COMMITTED="$ROOT/tools/unet/model/unet_roi96_int8.onnx"
die() { echo "finetune_unet: $*" >&2; exit 1; }
[ -e "$LABELS" ] || die "$LABELS: no such file or directory"
[ -f "$INIT" ] || die "$INIT: no weights to start from"
"$PYTHON" -c "import jax, optax, onnx, onnxruntime" 2>/dev/null ||
  die "$PYTHON lacks jax, optax, onnx or onnxruntime (scripts/setup_training.sh)"
mkdir -p "$OUT"

if [ -f "$LABELS/train/labels.csv" ]; then
  SPLIT=$LABELS
  echo "== using the split in $SPLIT"
else
  [ -x "$BIN/unet-import" ] || die "no $BIN/unet-import: cargo build --release -p millinav-unet"
  SPLIT="$OUT/split"
  echo "== importing $LABELS"
  "$BIN/unet-import" --labels "$LABELS" --out "$SPLIT" "${RIG_ARGS[@]}"
fi
[ -f "$SPLIT/val/labels.csv" ] || die "$SPLIT/val: no val split (unet-import puts every 5th frame there; label at least 5 frames)"

evaluate() {
  [ "${SKIP_EVAL:-0}" = 1 ] && { echo "(evaluation skipped: SKIP_EVAL=1)"; return; }
  [ -x "$BIN/vision-eval" ] || die "no $BIN/vision-eval: cargo build --release -p millinav-vision-eval (or SKIP_EVAL=1)"
  "$BIN/vision-eval" --split "$SPLIT/val" --model "$1" "${RIG_ARGS[@]}" --out "$2" >/dev/null
  grep -E "^\| (unet|localizer)" "$2"
}

echo "== the committed model on your val frames"
evaluate "$COMMITTED" "$OUT/before.md"

echo "== fine-tuning from $INIT"
"$PYTHON" "$ROOT/tools/unet/train.py" --data "$SPLIT" --init "$INIT" --lr 3e-4 --epochs 60 \
  --patience 10 --out "$OUT/unet_roi96.onnx" --metrics "$OUT/finetune_metrics.json" "$@" \
  2>&1 | tee "$OUT/finetune_log.txt" | grep -v "^epoch"

echo "== int8, calibrated on your crops"
"$PYTHON" "$ROOT/tools/unet/quantize.py" --calib "$SPLIT/train" --samples 300 \
  --model "$OUT/unet_roi96.onnx" --out "$OUT/unet_roi96_int8.onnx"

echo "== the fine-tuned model on your val frames"
evaluate "$OUT/unet_roi96_int8.onnx" "$OUT/after.md"
echo "done: $OUT/unet_roi96_int8.onnx; run it with [vision] model = \"$OUT/unet_roi96_int8.onnx\" in your scenario"
