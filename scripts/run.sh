#!/usr/bin/env bash
# The run command: installs prerequisites (idempotent), builds, and runs the full process set on
# the digital twin with the default scenario. Extra arguments go to `millinav run`, e.g.
#   ./scripts/run.sh scenarios/short.toml --viewer none
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
if [ $# -eq 0 ]; then
  set -- scenarios/default.toml
fi
exec "$CARGO_TARGET_DIR/release/millinav" run "$@"
