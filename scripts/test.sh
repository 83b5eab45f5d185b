#!/usr/bin/env bash
# The test command: installs prerequisites (idempotent), builds, checks the gates, and runs every
# test. Any failing gate fails the command.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
# Gates: formatting, one feature set for the run and test builds, and clippy with warnings as
# errors on every target (a check build: it type-checks the dependencies once more, without code
# generation). That no dependency goes unused is a test (tests/unused_dependencies.rs).
cargo fmt --all -- --check
./scripts/check_features.sh
cargo clippy --release --workspace --all-targets --locked -- -D warnings
# A private single-node Slurm cluster for the campaign test (slurm-wlm, munge; nothing started).
./scripts/setup_slurm.sh
# JAX (CPU wheels), optax and onnx for the UNet training tests (tools/unet/tests), on the CPU.
./scripts/setup_training.sh
cargo test --release --workspace --locked
# The serial protocol without std, for the board (rustup target installed on demand).
./scripts/no_std.sh
# The serial decoder under libFuzzer for a bounded time (nightly + cargo-fuzz, installed on demand).
./scripts/fuzz.sh "${MILLINAV_FUZZ_SECONDS:-60}"
