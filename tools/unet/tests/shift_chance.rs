//! Training's camera shifts with a family's chance given (`train.py --shift-chance FAMILY=P`):
//! the chances reach the geometric families (all at 0, mask and keypoints come back as they
//! went in; scale at 1, every crop is zoomed), and a wrong family or chance is refused before
//! any data is read, naming the option and the families.
//!
//! Needs JAX in the project's venv (`scripts/setup_training.sh`, which the test command runs).
use std::path::{Path, PathBuf};
use std::process::Command;

mod common;
use common::{train_py_refusal, venv_python};

fn unet_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).to_owned()
}

#[test]
fn the_chances_reach_the_shifts() {
    let script = r#"
import jax
import numpy as np
import augment
rng = np.random.default_rng(0)
img = rng.random((16, 3, 96, 96), dtype=np.float32)
mask = np.zeros((16, 96, 96), dtype=np.uint8)
mask[:, 40:56, 30:66] = 1
kps = np.tile(np.array([[[65.0, 48.0], [48.0, 48.0], [31.0, 48.0]]], np.float32), (16, 1, 1))
key = jax.random.PRNGKey(0)
none = {family: 0.0 for family in augment.FAMILIES}
_, m, k = augment.camera_shifts(key, img, mask, kps, none)
print("unchanged", str(np.array_equal(np.asarray(m), mask)).lower(), str(np.array_equal(np.asarray(k), kps)).lower())
_, m, k = augment.camera_shifts(key, img, mask, kps, dict(none, scale=1.0))
moved = int((np.abs(np.asarray(k) - kps).max(axis=(1, 2)) > 1e-3).sum())
print("zoomed", moved)
try:
    augment.camera_shifts(key, img, mask, kps, {"fog": 0.5})
    print("refused false")
except ValueError as e:
    print("refused", str("fog" in str(e) and "jpeg" in str(e)).lower())
"#;
    let out = Command::new(venv_python())
        .current_dir(unet_dir())
        .args(["-c", script])
        .output()
        .expect("the venv's python runs (scripts/setup_training.sh)");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("unchanged true true"), "{stdout}");
    // Scale at chance 1: every crop zoomed or shifted (a draw of exactly 1.0 and no shift has
    // probability zero).
    assert!(stdout.contains("zoomed 16"), "{stdout}");
    assert!(stdout.contains("refused true"), "{stdout}");
}

#[test]
fn a_wrong_shift_chance_is_refused_naming_the_option() {
    for (item, names) in [
        ("fog=0.5", "fog=0.5"),
        ("jpeg=1.5", "jpeg=1.5"),
        ("jpeg", "'jpeg'"),
    ] {
        let (code, stderr) = train_py_refusal(&["--shift-chance", item]);
        assert_eq!(code, Some(2), "{item}: {stderr}");
        assert!(
            stderr.contains("--shift-chance") && stderr.contains(names),
            "{item}: {stderr}"
        );
        assert!(
            stderr.contains("blur") && stderr.contains("scale"),
            "{stderr}"
        );
    }
}
