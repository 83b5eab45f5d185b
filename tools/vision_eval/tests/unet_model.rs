//! The committed UNet loads, meets accuracy floors on the committed test set, and a missing or
//! wrongly shaped model is refused at start-up with a clear error.

use std::path::{Path, PathBuf};

use millinav_roi::dataset::Split;
use millinav_vision::classical::CapsuleSize;
use millinav_vision::unet::{find_onnxruntime, UnetError, UnetLocalizer};
use millinav_vision_eval::eval::{evaluate_unet, table};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn load(model: &Path) -> Result<UnetLocalizer, UnetError> {
    let runtime = find_onnxruntime(None)?;
    UnetLocalizer::load(model, &runtime, 7.4, 92.0 / 1020.0)
}

#[test]
fn committed_model_meets_accuracy_floors() {
    meets_accuracy_floors(millinav_vision::DEFAULT_MODEL);
}

#[test]
fn float_model_it_was_quantized_from_meets_accuracy_floors() {
    meets_accuracy_floors(millinav_vision::FLOAT_MODEL);
}

fn meets_accuracy_floors(model: &str) {
    let split = Split::load(&root().join("tools/unet/testset")).expect("committed test set");
    let mut unet = load(&root().join(model)).expect("committed model loads");
    let size = CapsuleSize::of(&fieldmaps::rigfile::Rig::load_paper().unwrap().robot);
    let expected = size.length_m * 1e3 / split.labels[0].mm_per_px / 2.0;
    let report = evaluate_unet(&mut unet, &split, expected);
    println!("{}", table(std::slice::from_ref(&report)));
    // Floors: the paper's figures (98.7 % precision, 98.3 % recall, 97.1 % IoU) and 0.2 mm.
    assert!(report.precision >= 0.987, "precision {}", report.precision);
    assert!(report.recall >= 0.983, "recall {}", report.recall);
    assert!(report.iou >= 0.971, "IoU {}", report.iou);
    assert!(
        report.detection_rate >= 0.99,
        "detected {}",
        report.detection_rate
    );
    assert!(
        report.false_detection_rate <= 0.05,
        "false detections {}",
        report.false_detection_rate
    );
    assert!(
        report.centroid_err_mm_median < 0.2,
        "centroid {}",
        report.centroid_err_mm_median
    );
    // The heading comes from tail → tip: a quantized keypoint head once made this 0.2 mm.
    assert!(
        report.tip_err_mm_median < 0.05,
        "tip {}",
        report.tip_err_mm_median
    );
}

#[test]
fn missing_model_is_a_clear_start_up_error() {
    let err = load(Path::new("/nonexistent/model.onnx"))
        .err()
        .expect("must fail");
    assert!(matches!(err, UnetError::MissingModel(_)), "{err}");
    assert!(err.to_string().contains("does not exist"), "{err}");
}

#[test]
fn wrong_input_shape_is_a_clear_start_up_error() {
    let err = load(&root().join("tools/unet/model/wrong_shape.onnx"))
        .err()
        .expect("must fail");
    let text = err.to_string();
    assert!(matches!(err, UnetError::BadModel { .. }), "{text}");
    assert!(text.contains("shape") && text.contains("64"), "{text}");
}
