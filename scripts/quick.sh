#!/usr/bin/env bash
# The contributor's quick loop: the gates and the tests of the crates you changed, after a build
# (run.sh or test.sh once). Not a replacement for ./scripts/test.sh, which CI runs.
#
#   ./scripts/quick.sh millinav-control            # one crate: fmt, clippy, its unit tests
#   ./scripts/quick.sh fieldmaps millinav-kit      # several
#   ./scripts/quick.sh --all-tests millinav-plant  # its integration tests too (tests/*.rs)
#
# Uses the release build's target directory (CARGO_TARGET_DIR, default
# ~/.cache/millinav-target), so nothing the build made is compiled again.
set -euo pipefail
cd "$(dirname "$0")/.."
usage() {
  sed -n '2,10p' "$0" | sed 's/^# \{0,1\}//'
  exit "${1:-0}"
}
scope=(--lib --bins)
crates=()
for arg in "$@"; do
  case "$arg" in
    -h|--help) usage 0 ;;
    --all-tests) scope=(--all-targets) ;;
    -*) echo "quick.sh: unknown option $arg" >&2; usage 2 ;;
    *) crates+=(-p "$arg") ;;
  esac
done
[ ${#crates[@]} -gt 0 ] || { echo "quick.sh: name at least one crate (its package name)" >&2; usage 2; }
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/millinav-target}"
export MILLINAV_VENV="${MILLINAV_VENV:-$HOME/.cache/millinav/venv}"
export PATH="$MILLINAV_VENV/bin:$PATH"
start=$(date +%s)
cargo fmt --all -- --check
cargo clippy --release --locked "${crates[@]}" --all-targets -- -D warnings
cargo test --release --locked "${crates[@]}" "${scope[@]}"
echo "quick.sh: ${crates[*]} passed in $(( $(date +%s) - start )) s (the full test command is ./scripts/test.sh)"
