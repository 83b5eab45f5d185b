# Shared by run.sh and test.sh: installs prerequisites (idempotent) and sets the build
# environment. Source it from the repository root.
./scripts/setup.sh
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/millinav-target}"
export MILLINAV_VENV="${MILLINAV_VENV:-$HOME/.cache/millinav/venv}"
export PATH="$MILLINAV_VENV/bin:$PATH"
# One feature-unified build of the whole workspace serves the binaries and every test.
cargo build --release --workspace --locked
