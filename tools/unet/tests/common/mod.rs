//! What the tests that run the Python training scripts share.
use std::path::PathBuf;

/// The project venv's python (`MILLINAV_VENV`, else `~/.cache/millinav/venv`), where
/// `scripts/setup_training.sh` installs PyTorch.
pub fn venv_python() -> PathBuf {
    std::env::var_os("MILLINAV_VENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(std::env::var_os("HOME").unwrap_or_default()).join(".cache/millinav/venv")
        })
        .join("bin/python")
}
