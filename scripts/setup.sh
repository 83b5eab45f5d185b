#!/usr/bin/env bash
# Installs what millinav needs on a Debian machine with Rust, idempotently:
#   - Debian packages for OpenCV bindings (libopencv-dev, clang, libclang-dev);
#   - a Python venv with the Rerun CLI/reader (rerun-sdk) and the ONNX Runtime shared library.
# Safe to run again: it only installs what is missing.
set -euo pipefail

VENV="${MILLINAV_VENV:-$HOME/.cache/millinav/venv}"
RERUN_SDK_VERSION="0.36.3"
APT_PACKAGES=(libopencv-dev clang libclang-dev)

missing=()
for pkg in "${APT_PACKAGES[@]}"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if ((${#missing[@]})); then
  echo "setup: installing ${missing[*]}"
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating Python venv at $VENV"
  mkdir -p "$(dirname "$VENV")"
  python3 -m venv "$VENV"
fi
if ! "$VENV/bin/python" -c "import rerun, onnxruntime, magpylib, sys; sys.exit(0 if rerun.__version__ == '$RERUN_SDK_VERSION' else 1)" >/dev/null 2>&1; then
  echo "setup: installing rerun-sdk==$RERUN_SDK_VERSION and onnxruntime into $VENV"
  "$VENV/bin/pip" install -q --disable-pip-version-check "rerun-sdk==$RERUN_SDK_VERSION" onnxruntime magpylib
fi
