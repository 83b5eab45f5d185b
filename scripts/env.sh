# Shared by run.sh and test.sh: installs prerequisites (idempotent) and sets the build
# environment. Source it from the repository root.
./scripts/setup.sh
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/millinav-target}"
export MILLINAV_VENV="${MILLINAV_VENV:-$HOME/.cache/millinav/venv}"
export PATH="$MILLINAV_VENV/bin:$PATH"
# The whole workspace's binaries. The tests reuse every dependency this builds: dev-dependencies
# switch on no extra feature of a shared crate (Feature alignment in Cargo.toml, checked by
# scripts/check_features.sh), so `cargo test` compiles only the dev-only crates and the tests.
cargo build --release --workspace --locked
