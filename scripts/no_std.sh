#!/usr/bin/env bash
# Proves the serial protocol, the board logic and the Teensy 4.x firmware build for the coil-driver board: the Teensy 4.x core (Cortex-M7,
# thumbv7em-none-eabihf) without the standard library. Installs the target with rustup on demand
# (as fuzz.sh installs nightly); without rustup, or when the target cannot be installed, it says
# SKIPPED loudly and why, and fails under CI=true (CI must prove it).
set -euo pipefail
cd "$(dirname "$0")/.."
target=thumbv7em-none-eabihf
skip() {
    echo "no_std.sh: SKIPPED — $1; the no_std builds of millinav-teensy-protocol, millinav-firmware-core and the Teensy 4.x firmware were NOT checked" >&2
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

# The Teensy 4.x firmware (its own workspace, pinned by its own Cargo.lock).
# From its own directory: its .cargo/config.toml sets the target and the linker script.
(cd firmware/teensy4 && cargo clippy --release --locked -- -D warnings && cargo build --release --locked)
elf="${CARGO_TARGET_DIR:-$PWD/firmware/teensy4/target}/$target/release/millinav-teensy4"
[ -f "$elf" ] || { echo "no_std.sh: the firmware build left no $elf" >&2; exit 1; }
# The .hex teensy_loader_cli flashes, from rustup's llvm-tools (installed like the target).
host=$(rustc -vV | sed -n 's/^host: //p')
objcopy="$(rustc --print sysroot)/lib/rustlib/$host/bin/llvm-objcopy"
if [ ! -x "$objcopy" ]; then
    rustup component add llvm-tools >/dev/null 2>&1 || true
fi
if [ -x "$objcopy" ]; then
    "$objcopy" -O ihex "$elf" "$elf.hex"
    head -c 15 "$elf.hex" | grep -q '^:020000046000' || { echo "no_std.sh: $elf.hex does not start at the Teensy's flash (0x60000000)" >&2; exit 1; }
    echo "no_std.sh: Teensy 4.x firmware built: $elf.hex (flash: see firmware/FIRMWARE.md)"
else
    echo "no_std.sh: firmware ELF built ($elf), but NO .hex: llvm-tools could not be installed (rustup component add llvm-tools)" >&2
    [ "${CI:-}" = "true" ] && exit 1
fi
