#!/usr/bin/env bash
# Installs what millinav needs on a Debian machine with Rust, idempotently:
#   - Debian packages for OpenCV bindings (libopencv-dev, clang, libclang-dev);
#   - a Python venv with pinned versions of the Rerun CLI/reader (rerun-sdk), the ONNX Runtime
#     shared library (onnxruntime; its 1.x must serve the C API version of ort's api-24 feature,
#     which the vision service checks at start-up), magpylib (the field-map cross-check test)
#     and iceoryx2 (the foreign-reader contract test).
# Safe to run again: it only installs what is missing or differs from a pin.
set -euo pipefail

VENV="${MILLINAV_VENV:-$HOME/.cache/millinav/venv}"
# Python packages, pinned; a venv whose installed version of any of them differs is reinstalled.
PYTHON_PINS=(rerun-sdk==0.36.3 onnxruntime==1.32.0 magpylib==6.3.0 iceoryx2==0.10.0)
APT_PACKAGES=(libopencv-dev clang libclang-dev libzstd-dev pkg-config)

"$(dirname "$0")/apt_install.sh" setup "${APT_PACKAGES[@]}"

if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating Python venv at $VENV"
  mkdir -p "$(dirname "$VENV")"
  python3 -m venv "$VENV"
fi
pins_installed() {
  "$VENV/bin/python" - "${PYTHON_PINS[@]}" <<'EOF'
import sys
from importlib.metadata import PackageNotFoundError, version
for pin in sys.argv[1:]:
    name, wanted = pin.split("==")
    try:
        if version(name) != wanted:
            sys.exit(1)
    except PackageNotFoundError:
        sys.exit(1)
EOF
}
if ! pins_installed >/dev/null 2>&1; then
  echo "setup: installing ${PYTHON_PINS[*]} into $VENV"
  "$VENV/bin/pip" install -q --disable-pip-version-check "${PYTHON_PINS[@]}"
fi
