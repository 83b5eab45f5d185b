//! train.py's UNet at another depth and width (`--levels`, `--width`): it trains into folders
//! that do not exist yet, records its shape, exports the service's inputs and outputs, and
//! quantizes with its keypoint head kept float (quantize.py finds the head in the graph, so the
//! check holds whatever the depth); `--init` takes the shape from the weights and refuses a
//! contradicting `--levels`; missing weights and shapes out of range are refused before any data
//! is read. The committed weights export to a graph that computes what the committed model
//! computes, with the layer names quantize.py looks for.
//!
//! Needs JAX, optax and onnx in the project's venv (`scripts/setup_training.sh`, which the test
//! command runs).
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod common;
use common::{scratch_with_tiny_split, train_py_refusal, venv_python};

fn unet_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).to_owned()
}

fn run(args: &[&str]) -> Output {
    Command::new(venv_python())
        .current_dir(unet_dir())
        .args(args)
        .output()
        .expect("the venv's python runs (scripts/setup_training.sh)")
}

fn ok(out: Output) -> String {
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{text}");
    text
}

/// Prints the model's inputs and outputs, and whether the heatmap convolution and the first
/// encoder convolution take their weights through a DequantizeLinear (quantized) or not.
const INSPECT: &str = r#"
import sys, onnx, onnxruntime as ort
session = ort.InferenceSession(sys.argv[1])
for port in session.get_inputs() + session.get_outputs():
    print("port", port.name, port.shape)
graph = onnx.load(sys.argv[1]).graph
producer = {o: n.op_type for n in graph.node for o in n.output}
for node in graph.node:
    if node.op_type == "Conv" and node.name in ("/heat/Conv", "/enc1/enc1.0/Conv"):
        print("weight", node.name, producer.get(node.input[1], "float"))
"#;

#[test]
fn a_deeper_unet_trains_quantizes_and_keeps_its_shape_on_init() {
    let (dir, data) = scratch_with_tiny_split("unet-shape");
    let out_dir = dir.join("not/yet");
    let model = out_dir.join("m.onnx");
    let metrics = out_dir.join("m.json");
    let (model_s, metrics_s, data_s) = (
        model.to_str().unwrap(),
        metrics.to_str().unwrap(),
        data.to_str().unwrap(),
    );
    ok(run(&[
        "train.py",
        "--data",
        data_s,
        "--out",
        model_s,
        "--metrics",
        metrics_s,
        "--levels",
        "4",
        "--width",
        "8",
        "--epochs",
        "1",
        "--batch",
        "4",
        "--augment",
        "flips",
    ]));
    let recorded: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&metrics).expect("metrics written"))
            .expect("metrics are JSON");
    assert_eq!(recorded["levels"], 4);
    assert_eq!(recorded["width"], 8);

    let int8 = out_dir.join("m8.onnx");
    let train_split = data.join("train");
    ok(run(&[
        "quantize.py",
        "--calib",
        train_split.to_str().unwrap(),
        "--samples",
        "8",
        "--model",
        model_s,
        "--out",
        int8.to_str().unwrap(),
    ]));
    let seen = ok(run(&["-c", INSPECT, int8.to_str().unwrap()]));
    for port in [
        "port image [1, 3, 96, 96]",
        "port seg [1, 2, 96, 96]",
        "port keypoints [1, 3, 2]",
        "port presence [1, 1]",
    ] {
        assert!(seen.contains(port), "{port} in {seen}");
    }
    assert!(seen.contains("weight /heat/Conv float"), "{seen}");
    assert!(
        seen.contains("weight /enc1/enc1.0/Conv DequantizeLinear"),
        "{seen}"
    );

    let weights = out_dir.join("m.npz");
    let again = out_dir.join("again.onnx");
    let base = [
        "train.py",
        "--data",
        data_s,
        "--init",
        weights.to_str().unwrap(),
        "--out",
        again.to_str().unwrap(),
        "--epochs",
        "0",
    ];
    let text = ok(run(&base));
    assert!(text.contains("(4 levels, width 8)"), "{text}");
    let refused = run(&[&base[..], &["--levels", "3"]].concat());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success(), "{stderr}");
    assert!(
        stderr.contains("--init") && stderr.contains("4 levels"),
        "{stderr}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn missing_weights_or_a_shape_out_of_range_are_refused_before_any_data_is_read() {
    for (options, names) in [
        (
            &["--init", "/nonexistent/w.npz"][..],
            "--init /nonexistent/w.npz: no such file",
        ),
        (&["--levels", "6"][..], "--levels 6"),
        (&["--width", "2"][..], "--width 2"),
    ] {
        let (code, stderr) = train_py_refusal(options);
        assert_eq!(code, Some(2), "{options:?}: {stderr}");
        assert!(stderr.contains(names), "{options:?}: {stderr}");
    }
}

/// check_export.py: export.py's graph of the committed weights, and train.py's own forward
/// pass, give the committed ONNX model's outputs on the committed test crops.
#[test]
fn the_committed_weights_export_to_what_the_committed_model_computes() {
    let text = ok(run(&["check_export.py"]));
    assert!(text.contains("ok: every difference within"), "{text}");
}

/// Every convolution of the committed graph is in the export under its name (quantize.py keeps
/// `/heat/Conv` in float by name), and the export has the committed model's ports.
#[test]
fn the_default_shape_exports_the_committed_layers_by_name() {
    let script = r#"
import sys, onnx, export, weights
export.export(weights.load("model/unet_roi96.npz"), sys.argv[1])
def layers(path):
    graph = onnx.load(path).graph
    convs = sorted(n.name for n in graph.node if n.op_type in ("Conv", "ConvTranspose"))
    ports = [p.name for p in list(graph.input) + list(graph.output)]
    return convs, ports
exported, committed = layers(sys.argv[1]), layers("model/unet_roi96.onnx")
print("convolutions", len(committed[0]), "same", exported == committed)
"#;
    let path =
        std::env::temp_dir().join(format!("millinav-unet-default-{}.onnx", std::process::id()));
    let text = ok(run(&["-c", script, path.to_str().unwrap()]));
    assert!(text.contains("same True"), "{text}");
    let _ = std::fs::remove_file(&path);
}
