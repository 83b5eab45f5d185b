#!/usr/bin/env bash
# Installs what UNet training and fine-tuning need (tools/unet/train.py, quantize.py,
# scripts/train_unet.sh, scripts/finetune_unet.sh) into the project's Python venv, idempotently:
# PyTorch and onnx, pinned. Run after scripts/setup.sh (which makes the venv and pins
# onnxruntime). The test command runs it so that the fine-tune test runs on CPU.
#
# Heavy on purpose and apart from setup.sh: PyPI's Linux torch wheel brings its CUDA libraries
# (about 7 GB installed, about a minute here); the run command does not need it.
set -euo pipefail

VENV="${MILLINAV_VENV:-$HOME/.cache/millinav/venv}"
TRAINING_PINS=(torch==2.9.1 onnx==1.19.1)

[ -x "$VENV/bin/python" ] || { echo "setup_training: no venv at $VENV: run scripts/setup.sh first" >&2; exit 1; }
if ! "$VENV/bin/python" - "${TRAINING_PINS[@]}" <<'EOF' >/dev/null 2>&1
import sys
from importlib.metadata import version
for pin in sys.argv[1:]:
    name, wanted = pin.split("==")
    if version(name).split("+")[0] != wanted:
        sys.exit(1)
EOF
then
  echo "setup_training: installing ${TRAINING_PINS[*]} into $VENV"
  "$VENV/bin/pip" install -q --disable-pip-version-check "${TRAINING_PINS[@]}"
fi
