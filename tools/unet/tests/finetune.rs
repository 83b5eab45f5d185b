//! Your own frames, end to end (issue 17 point 3): labelled full frames of a capsule the
//! committed model has never seen (an orange dye in the held-out generator setting) go through
//! the one documented command, `scripts/finetune_unet.sh` — import into crops, evaluate the
//! committed model, fine-tune from its weights, export, quantize to int8 on the user's crops,
//! evaluate again — on this machine's CPU, with a few epochs. The committed model misses the
//! orange capsule; the fine-tuned int8 model finds it.
//!
//! Needs JAX (CPU), optax and onnx in the project's venv (`scripts/setup_training.sh`, which the
//! test command runs) and the workspace's binaries (unet-import, vision-eval) built beside this
//! one.
#![cfg(feature = "labelme")] // unet-import reads the frames with OpenCV
use std::path::Path;
use std::process::Command;

mod common;
use common::venv_python;

/// One localizer's row of a vision-eval table, by column name.
struct EvalRow {
    columns: Vec<String>,
    cells: Vec<String>,
}

impl EvalRow {
    fn read(path: &Path, localizer: &str) -> Self {
        let text =
            std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let split = |line: &str| -> Vec<String> {
            line.trim()
                .trim_matches('|')
                .split('|')
                .map(|c| c.trim().to_owned())
                .collect()
        };
        let mut lines = text.lines().filter(|l| l.starts_with('|'));
        let columns = split(lines.next().expect("a table header"));
        let cells = lines
            .map(split)
            .find(|cells| cells.first().map(String::as_str) == Some(localizer))
            .unwrap_or_else(|| panic!("{}: no {localizer} row", path.display()));
        Self { columns, cells }
    }

    /// A percentage column, as a number.
    fn percent(&self, column: &str) -> f64 {
        let i = self
            .columns
            .iter()
            .position(|c| c == column)
            .unwrap_or_else(|| panic!("no column {column} in {:?}", self.columns));
        self.cells[i]
            .trim_end_matches('%')
            .trim()
            .parse()
            .unwrap_or_else(|e| panic!("{column} = {:?}: {e}", self.cells[i]))
    }
}

#[test]
fn your_labelled_frames_fine_tune_the_committed_model_in_one_command() {
    let python = venv_python();
    let has_training = Command::new(&python)
        .args(["-c", "import jax, optax, onnx, onnxruntime"])
        .status()
        .is_ok_and(|s| s.success());
    assert!(
        has_training,
        "{} lacks jax, optax, onnx or onnxruntime: run scripts/setup_training.sh",
        python.display()
    );
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let bin = Path::new(env!("CARGO_BIN_EXE_unet-import"))
        .parent()
        .expect("the binaries' directory")
        .to_owned();
    let work = std::env::temp_dir().join(format!("millinav-finetune-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&work);
    let (labels, out) = (work.join("labels"), work.join("out"));

    let made = Command::new(env!("CARGO_BIN_EXE_unet-dataset"))
        .args(["--labelme-frames", "30", "--style", "heldout"])
        .arg("--rig")
        .arg(root.join("fieldmaps/rigs/paper.toml"))
        .args([
            "--dye-rgb",
            "215,110,30",
            "--cameras",
            "3",
            "--seed",
            "8200",
        ])
        .arg("--out")
        .arg(&labels)
        .output()
        .expect("unet-dataset runs");
    assert!(
        made.status.success(),
        "unet-dataset: {}",
        String::from_utf8_lossy(&made.stderr)
    );

    let finetune = Command::new("bash")
        .arg(root.join("scripts/finetune_unet.sh"))
        .arg(&labels)
        .arg(&out)
        .arg("--rig")
        .arg(root.join("fieldmaps/rigs/paper.toml"))
        .args(["--epochs", "3"])
        .env("PYTHON", &python)
        .env("BIN", &bin)
        .output()
        .expect("finetune_unet.sh runs");
    let log = format!(
        "{}{}",
        String::from_utf8_lossy(&finetune.stdout),
        String::from_utf8_lossy(&finetune.stderr)
    );
    assert!(finetune.status.success(), "finetune_unet.sh failed:\n{log}");
    for file in ["unet_roi96.onnx", "unet_roi96.npz", "unet_roi96_int8.onnx"] {
        assert!(out.join(file).is_file(), "no {file} in {}", out.display());
    }

    let before = EvalRow::read(&out.join("before.md"), "unet");
    let after = EvalRow::read(&out.join("after.md"), "unet");
    eprintln!("before: {:?}\nafter: {:?}", before.cells, after.cells);
    // The set is new to the committed model: it finds (almost) no orange capsule.
    assert!(
        before.percent("detected") <= 10.0,
        "the committed model already detects {} % of the orange capsules",
        before.percent("detected")
    );
    // Three epochs from the committed weights on 108 crops: measured 96.2 / 94.9 / 91.5 % and
    // 100 % detected here; the bounds leave room for another CPU's rounding.
    assert!(
        after.percent("detected") >= 90.0,
        "after: {:?}",
        after.cells
    );
    assert!(
        after.percent("precision") >= 90.0,
        "after: {:?}",
        after.cells
    );
    assert!(after.percent("recall") >= 90.0, "after: {:?}", after.cells);
    assert!(after.percent("IoU") >= 85.0, "after: {:?}", after.cells);
    let _ = std::fs::remove_dir_all(&work);
}
