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

/// Runs `train.py` with `options` and paths that do not exist, for options it must refuse before
/// reading any data: its exit code and standard error.
#[allow(dead_code)] // not every test binary that includes this module refuses options
pub fn train_py_refusal(options: &[&str]) -> (Option<i32>, String) {
    let out = std::process::Command::new(venv_python())
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args([
            "train.py",
            "--data",
            "/nonexistent",
            "--out",
            "/nonexistent/x.onnx",
        ])
        .args(options)
        .output()
        .expect("the venv's python runs (scripts/setup_training.sh)");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}
