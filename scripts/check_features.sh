#!/usr/bin/env bash
# Fails when `cargo test` would build a dependency with other features than the run command's
# `cargo build` (scripts/env.sh), i.e. when one shared build would not serve both: every
# (package, features) that the normal build resolves must resolve the same with the
# dev-dependencies in. Fix a failure by declaring the listed features in [workspace.dependencies]
# and services/kit/Cargo.toml ("Feature alignment" there). Takes about a second; builds nothing.
set -euo pipefail
cd "$(dirname "$0")/.."
features() {
  cargo tree --workspace --locked --prefix none --format '{p} {f}' "$@" | sed 's/ (\*)$//' | sort -u
}
drift=$(comm -23 <(features -e no-dev) <(features))
if [ -n "$drift" ]; then
  echo "check_features: the test build would compile these dependencies again, with other features:" >&2
  echo "$drift" >&2
  exit 1
fi
