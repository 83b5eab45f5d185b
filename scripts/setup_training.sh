#!/usr/bin/env bash
# Installs what UNet training and fine-tuning need (tools/unet/train.py, quantize.py,
# check_export.py, scripts/train_unet.sh, scripts/finetune_unet.sh) into the project's Python
# venv, idempotently: JAX's CPU wheels, optax and onnx, pinned; silent when they are there. Run
# after scripts/setup.sh (which makes the venv and pins onnxruntime). The test command runs it
# so that the fine-tune test trains on the CPU.
#
# Apart from setup.sh because the run command does not need it; it adds about 0.5 GB (jaxlib
# most of it) and no CUDA libraries. A lab training on an NVIDIA GPU adds, in the same venv:
#   pip install "jax[cuda12]==0.10.2"
# (several GB of CUDA wheels), and train.py then runs on the GPU.
set -euo pipefail

VENV="${MILLINAV_VENV:-$HOME/.cache/millinav/venv}"
TRAINING_PINS=(jax==0.10.2 jaxlib==0.10.2 optax==0.2.8 onnx==1.19.1)

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
