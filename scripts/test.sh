#!/usr/bin/env bash
# The test command: installs prerequisites (idempotent), builds, and runs every test.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
cargo test --release --workspace --locked
