#!/usr/bin/env bash
# Bounded cargo-fuzz run of the Teensy protocol decoder (fuzz/fuzz_targets/decoder.rs):
# arbitrary bytes in data-driven chunks must never panic, never grow the decoder's buffer without
# bound, and only yield packets that were in the input. Installs a nightly toolchain and
# cargo-fuzz when missing (idempotent). Usage: scripts/fuzz.sh [seconds, default 60].
# Exit status: 0 when the run finished without a finding; a crash leaves its input in
# fuzz/artifacts/decoder/ and fails.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds="${1:-60}"
if ! command -v rustup >/dev/null 2>&1; then
    # cargo-fuzz needs a nightly toolchain, which only rustup can provide here.
    echo "fuzz.sh: SKIPPED — rustup not found, so no nightly toolchain for cargo-fuzz;" \
        "the decoder's invariants still ran as property tests (services/coilbus/tests/protocol_props.rs)" >&2
    exit 0
fi
if ! rustup run nightly rustc --version >/dev/null 2>&1; then
    rustup toolchain install nightly --profile minimal
fi
if ! cargo fuzz --version >/dev/null 2>&1; then
    cargo install cargo-fuzz --version 0.13.2 --locked
fi
cd fuzz
mkdir -p corpus/decoder
cargo +nightly fuzz run decoder corpus/decoder -- -max_total_time="$seconds" -print_final_stats=1
