#!/usr/bin/env bash
# The test command: installs prerequisites (idempotent), builds, and runs every test.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
cargo test --release --workspace --locked
# The serial decoder under libFuzzer for a bounded time (nightly + cargo-fuzz, installed on demand).
./scripts/fuzz.sh "${MILLINAV_FUZZ_SECONDS:-60}"
