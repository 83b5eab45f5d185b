//! Training's two optional departures from the paper's recipe (`train.py --iou-weight W`,
//! `--ema DECAY`): the soft-IoU term is 0 for a confident exact mask and 1 for a confident
//! inverted one, leaves the paper's loss unchanged at weight 0, and adds W x (1 - soft IoU)
//! otherwise; a run with both trains, records them in its metrics and exports a model; a value
//! out of range is refused before any data is read, naming the option.
//!
//! Needs JAX, optax and onnx in the project's venv (`scripts/setup_training.sh`, which the test
//! command runs).
use std::path::{Path, PathBuf};
use std::process::Command;

mod common;
use common::{scratch_with_tiny_split, train_py_refusal, venv_python};

fn unet_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).to_owned()
}

fn python(script: &str, args: &[&str]) -> String {
    let out = Command::new(venv_python())
        .current_dir(unet_dir())
        .args(["-c", script])
        .args(args)
        .output()
        .expect("the venv's python runs (scripts/setup_training.sh)");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// The number printed after `key ` in the script's output.
fn value(stdout: &str, key: &str) -> f64 {
    stdout
        .lines()
        .find_map(|line| line.strip_prefix(&format!("{key} ")))
        .unwrap_or_else(|| panic!("no {key} in {stdout}"))
        .trim()
        .parse()
        .unwrap_or_else(|e| panic!("{key}: {e} in {stdout}"))
}

#[test]
fn the_soft_iou_term_measures_the_overlap_and_is_off_by_default() {
    let script = r#"
import numpy as np
import train
mask = np.zeros((2, 96, 96), dtype=np.uint8)
mask[:, 40:56, 30:66] = 1
sure = 30.0 * (2 * mask.astype(np.float32) - 1)            # logit of the capsule class
exact = np.stack([-sure, sure], axis=1)
inverted = np.stack([sure, -sure], axis=1)
print("exact", float(train.soft_jaccard(exact, mask)))
print("inverted", float(train.soft_jaccard(inverted, mask)))
rng = np.random.default_rng(0)
seg = rng.standard_normal((2, 2, 96, 96)).astype(np.float32)
kp = (rng.random((2, 3, 2)) * 95).astype(np.float32)
pres = rng.standard_normal((2, 1)).astype(np.float32)
kps = (rng.random((2, 3, 2)) * 95).astype(np.float32)
has = np.ones(2, np.float32)
paper = train.loss_fn(seg, kp, pres, mask, kps, has)
print("default_diff", float(train.loss_fn(seg, kp, pres, mask, kps, has, 0.0) - paper))
print("weighted_diff", float(train.loss_fn(seg, kp, pres, mask, kps, has, 0.5) - paper
                             - 0.5 * train.soft_jaccard(seg, mask)))
print("soft", float(train.soft_jaccard(seg, mask)))
"#;
    let out = python(script, &[]);
    assert!(value(&out, "exact") < 2e-3, "{out}");
    assert!(value(&out, "inverted") > 0.999, "{out}");
    assert_eq!(value(&out, "default_diff"), 0.0, "{out}");
    assert!(value(&out, "weighted_diff").abs() < 1e-6, "{out}");
    // Random logits overlap the 16x36 box only by chance: the term is far from 0.
    assert!(value(&out, "soft") > 0.5, "{out}");
}

#[test]
fn a_run_with_both_trains_and_records_them() {
    let (dir, data) = scratch_with_tiny_split("loss-options");
    let model = dir.join("m.onnx");
    let metrics = dir.join("m.json");
    let out = Command::new(venv_python())
        .current_dir(unet_dir())
        .arg("train.py")
        .arg("--data")
        .arg(&data)
        .arg("--out")
        .arg(&model)
        .arg("--metrics")
        .arg(&metrics)
        .args(["--epochs", "2", "--batch", "4", "--iou-weight", "0.5"])
        .args(["--ema", "0.99", "--augment", "flips"])
        .output()
        .expect("the venv's python runs (scripts/setup_training.sh)");
    assert!(
        out.status.success(),
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let recorded: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&metrics).expect("metrics written"))
            .expect("metrics are JSON");
    assert_eq!(recorded["iou_weight"], 0.5);
    assert_eq!(recorded["ema"], 0.99);
    assert_eq!(recorded["epochs"], 2);
    assert!(std::fs::metadata(&model).expect("model exported").len() > 10_000);
    assert!(dir.join("m.npz").exists(), "weights beside the model");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn values_out_of_range_are_refused_naming_the_option() {
    for (option, value) in [
        ("--iou-weight", "-1"),
        ("--iou-weight", "11"),
        ("--ema", "0.5"),
        ("--ema", "1.0"),
    ] {
        let (code, stderr) = train_py_refusal(&[option, value]);
        assert_eq!(code, Some(2), "{option} {value}: {stderr}");
        assert!(
            stderr.contains(&format!("{option} {value}")),
            "{option} {value}: {stderr}"
        );
    }
}
