#!/usr/bin/env bash
# Proves the serial protocol and the board logic build for the coil-driver board: the Teensy 4.x core (Cortex-M7,
# thumbv7em-none-eabihf) without the standard library. Installs the target with rustup on demand
# (as fuzz.sh installs nightly); without rustup, or when the target cannot be installed, it says
# SKIPPED loudly and why, and fails under CI=true (CI must prove it).
set -euo pipefail
cd "$(dirname "$0")/.."
target=thumbv7em-none-eabihf
skip() {
    echo "no_std.sh: SKIPPED — $1; the no_std builds of millinav-teensy-protocol and millinav-firmware-core were NOT checked" >&2
    if [ "${CI:-}" = "true" ]; then
        exit 1
    fi
    exit 0
}
command -v rustup >/dev/null 2>&1 || skip "rustup not found, so no $target target"
if ! rustup target list --installed | grep -qx "$target"; then
    rustup target add "$target" || skip "rustup target add $target failed"
fi
cargo build --release --locked -p millinav-teensy-protocol --no-default-features --target "$target"
cargo build --release --locked -p millinav-firmware-core --target "$target"
echo "no_std.sh: millinav-teensy-protocol and millinav-firmware-core build for $target without std"
