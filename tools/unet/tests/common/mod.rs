//! What the tests that run the Python training scripts share.
use std::path::PathBuf;

/// The project venv's python (`MILLINAV_VENV`, else `~/.cache/millinav/venv`), where
/// `scripts/setup_training.sh` installs JAX, optax and onnx.
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

/// A fresh scratch folder named for the test and process, with a tiny split in `data/` (train/
/// and val/, 8 random crops each with a box capsule, in unet-dataset's format), for runs of
/// train.py that only need to run: (folder, split).
#[allow(dead_code)] // not every test binary that includes this module trains
pub fn scratch_with_tiny_split(name: &str) -> (PathBuf, PathBuf) {
    let dir = std::env::temp_dir().join(format!("millinav-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let data = dir.join("data");
    let script = r#"
import sys
import numpy as np
import train
rng = np.random.default_rng(0)
for split in ("train", "val"):
    n = 8
    img = rng.random((n, 3, 96, 96), dtype=np.float32)
    mask = np.zeros((n, 96, 96), dtype=np.uint8)
    mask[:, 40:56, 30:66] = 1
    img[:, 2] = np.where(mask == 1, 0.9, img[:, 2])
    kps = np.tile(np.array([[[65.0, 48.0], [48.0, 48.0], [31.0, 48.0]]], np.float32), (n, 1, 1))
    train.save_split(f"{sys.argv[1]}/{split}", img, mask, np.ones(n), kps, 0.09)
"#;
    let out = std::process::Command::new(venv_python())
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(["-c", script])
        .arg(&data)
        .output()
        .expect("the venv's python runs (scripts/setup_training.sh)");
    assert!(
        out.status.success(),
        "tiny split: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    (dir, data)
}
