//! UNet localizer (paper Sec. II-B): mask + tip/centroid/tail keypoints from a 96x96 ROI,
//! run with ONNX Runtime (shared library from the PyPI `onnxruntime` wheel, loaded at start).
//! The ROI preprocessing is `millinav_roi::roi`, the same code that made the training data.

use std::path::{Path, PathBuf};

use millinav_roi::roi::{
    extract_rgb, extract_rgb_scaled, to_chw_f32, Crop, CropGeometry, ScaledCrop, DOWNSAMPLE,
    INPUT_PX,
};
use ort::session::Session;
use ort::value::TensorRef;

use crate::classical::{Detection, LocalizeError};

#[derive(Debug, thiserror::Error)]
pub enum UnetError {
    #[error("UNet model file {0} does not exist (train one with tools/unet/train.py or use localizer = \"classical\")")]
    MissingModel(PathBuf),
    #[error("ONNX Runtime library not found: {0}")]
    MissingRuntime(String),
    #[error("cannot load ONNX Runtime from {path}: {message}")]
    Runtime { path: PathBuf, message: String },
    #[error("model {path} cannot be used: {message}")]
    BadModel { path: PathBuf, message: String },
}

/// ONNX Runtime allows one environment per process, ever (ort refuses a second one even after
/// the first is dropped), so every model loaded in a process shares this one. The first runtime
/// library loaded serves them all.
fn environment(runtime: &Path) -> Result<ort::environment::Environment, String> {
    static ENVIRONMENT: std::sync::OnceLock<Result<ort::environment::Environment, String>> =
        std::sync::OnceLock::new();
    ENVIRONMENT
        .get_or_init(|| {
            // Checked before ort loads it, and held until ort has (see `open_checked`).
            let checked = crate::ort_version::open_checked(runtime).map_err(|e| e.to_string())?;
            let environment = ort::init_from(runtime)
                .map_err(|e| e.to_string())?
                .build()
                .map_err(|e| e.to_string());
            drop(checked);
            environment
        })
        .clone()
}

/// Finds `libonnxruntime.so*`: an explicit path, `ORT_DYLIB_PATH`, or the project venv's
/// `onnxruntime` wheel.
pub fn find_onnxruntime(explicit: Option<&Path>) -> Result<PathBuf, UnetError> {
    if let Some(path) = explicit {
        return if path.is_file() {
            Ok(path.to_owned())
        } else {
            Err(UnetError::MissingRuntime(format!(
                "{} is not a file",
                path.display()
            )))
        };
    }
    if let Some(path) = std::env::var_os("ORT_DYLIB_PATH") {
        let path = PathBuf::from(path);
        if path.is_file() {
            return Ok(path);
        }
    }
    let venv = std::env::var_os("MILLINAV_VENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(std::env::var_os("HOME").unwrap_or_default()).join(".cache/millinav/venv")
        });
    let lib = venv.join("lib");
    let candidates = std::fs::read_dir(&lib)
        .into_iter()
        .flatten()
        .flatten()
        .map(|python| python.path().join("site-packages/onnxruntime/capi"))
        .filter_map(|capi| std::fs::read_dir(capi).ok())
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("libonnxruntime.so"))
        });
    candidates.min().ok_or_else(|| {
        UnetError::MissingRuntime(format!(
            "set ORT_DYLIB_PATH or install the onnxruntime wheel into {} (scripts/setup.sh)",
            venv.display()
        ))
    })
}

pub struct UnetLocalizer {
    session: Session,
    rgb: Vec<u8>,
    input: Vec<f32>,
    /// Capsule length in model-input pixels, to reject implausible keypoints.
    expected_length_px: f64,
    /// Capsule length in frame pixels (this camera).
    frame_length_px: f64,
    /// Frame pixels per model-input pixel: `DOWNSAMPLE` (the training crops) unless
    /// [`Self::with_model_scale`] found this camera's capsule at another size.
    scale: f64,
}

/// Within this fraction of the training scale the crop is the training crop itself (the model
/// learnt ±12 % of capsule scale; this keeps the paper rig's crops bit for bit).
const SCALE_TOLERANCE: f64 = 0.05;

/// Raw model outputs for one crop (model-input pixels).
#[derive(Debug, Clone)]
pub struct UnetOutput {
    pub mask: Vec<u8>,
    pub keypoints: [(f64, f64); 3],
    pub presence_logit: f64,
}

impl UnetLocalizer {
    /// Loads the model and checks it has the input and outputs this pipeline expects.
    pub fn load(
        model: &Path,
        runtime: &Path,
        capsule_length_mm: f64,
        mm_per_px: f64,
    ) -> Result<Self, UnetError> {
        if !model.is_file() {
            return Err(UnetError::MissingModel(model.to_owned()));
        }
        let rt_err = |message: String| UnetError::Runtime {
            path: runtime.to_owned(),
            message,
        };
        let env = environment(runtime).map_err(rt_err)?;
        let bad = |message: String| UnetError::BadModel {
            path: model.to_owned(),
            message,
        };
        let session = Session::builder(&env)
            .map_err(|e| bad(e.to_string()))?
            // One thread: the set shares 2 cores, and a 96x96 UNet does not scale past one.
            .with_intra_threads(1)
            .map_err(|e| bad(e.to_string()))?
            .commit_from_file(model)
            .map_err(|e| bad(e.to_string()))?;
        let inputs = session.inputs();
        if inputs.len() != 1 {
            return Err(bad(format!("expected 1 input, found {}", inputs.len())));
        }
        let shape: Vec<i64> = inputs[0]
            .dtype()
            .tensor_shape()
            .map(|s| s.iter().copied().collect())
            .unwrap_or_default();
        let want = [1, 3, INPUT_PX as i64, INPUT_PX as i64];
        if shape != want {
            return Err(bad(format!(
                "input {:?} has shape {shape:?}, this pipeline feeds {want:?}",
                inputs[0].name()
            )));
        }
        let names: Vec<&str> = session.outputs().iter().map(|o| o.name()).collect();
        for needed in ["seg", "keypoints", "presence"] {
            if !names.contains(&needed) {
                return Err(bad(format!("missing output {needed:?} (has {names:?})")));
            }
        }
        Ok(Self {
            session,
            rgb: Vec::new(),
            input: Vec::new(),
            expected_length_px: capsule_length_mm / mm_per_px / DOWNSAMPLE as f64,
            frame_length_px: capsule_length_mm / mm_per_px,
            scale: DOWNSAMPLE as f64,
        })
    }

    /// Crops so the capsule reaches the model at `model_capsule_length_px` (its length in the
    /// training crops, model-input pixels): a camera that shows it larger or smaller than the
    /// training camera did gets a crop of another size, resampled to the model input.
    pub fn with_model_scale(mut self, model_capsule_length_px: f64) -> Self {
        let scale = self.frame_length_px / model_capsule_length_px;
        if scale.is_finite() && scale > 0.0 {
            let training = DOWNSAMPLE as f64;
            self.scale = if (scale / training - 1.0).abs() <= SCALE_TOLERANCE {
                training
            } else {
                scale
            };
            self.expected_length_px = self.frame_length_px / self.scale;
        }
        self
    }

    /// Frame pixels per model-input pixel this localizer crops at.
    pub fn scale(&self) -> f64 {
        self.scale
    }

    /// Runs the model on an already preprocessed 96x96 RGB crop.
    pub fn infer(&mut self, rgb: &[u8]) -> Result<UnetOutput, LocalizeError> {
        to_chw_f32(rgb, &mut self.input);
        let err = |e: ort::Error| LocalizeError::OpenCv(format!("onnxruntime: {e}"));
        let view = ndarray::ArrayView4::from_shape((1, 3, INPUT_PX, INPUT_PX), &self.input)
            .map_err(|e| LocalizeError::OpenCv(e.to_string()))?;
        let outputs = self
            .session
            .run(ort::inputs![TensorRef::from_array_view(view).map_err(err)?])
            .map_err(err)?;
        let (_, seg) = outputs["seg"].try_extract_tensor::<f32>().map_err(err)?;
        let (_, kp) = outputs["keypoints"]
            .try_extract_tensor::<f32>()
            .map_err(err)?;
        let (_, presence) = outputs["presence"]
            .try_extract_tensor::<f32>()
            .map_err(err)?;
        let n = INPUT_PX * INPUT_PX;
        if seg.len() != 2 * n || kp.len() != 6 || presence.is_empty() {
            return Err(LocalizeError::OpenCv(
                "model outputs have unexpected sizes".into(),
            ));
        }
        let mask = (0..n).map(|i| u8::from(seg[n + i] > seg[i])).collect();
        let k = |i: usize| (kp[2 * i] as f64, kp[2 * i + 1] as f64);
        Ok(UnetOutput {
            mask,
            keypoints: [k(0), k(1), k(2)],
            presence_logit: presence[0] as f64,
        })
    }

    /// Localizes the capsule in the ROI around `predicted_px` of a full RGB frame.
    pub fn localize(
        &mut self,
        frame: &[u8],
        width: usize,
        height: usize,
        predicted_px: (f64, f64),
    ) -> Result<Detection, LocalizeError> {
        let mut rgb = std::mem::take(&mut self.rgb);
        let (col, row) = predicted_px;
        if self.scale == DOWNSAMPLE as f64 {
            let Some(crop) = Crop::around(col, row, width, height) else {
                self.rgb = rgb;
                return Err(LocalizeError::NotFound);
            };
            extract_rgb(frame, width, &crop, &mut rgb);
            let out = self.infer(&rgb);
            self.rgb = rgb;
            detection_from_output(&out?, &crop, self.expected_length_px)
        } else {
            let Some(crop) = ScaledCrop::around(col, row, width, height, self.scale) else {
                self.rgb = rgb;
                return Err(LocalizeError::NotFound);
            };
            extract_rgb_scaled(frame, width, height, &crop, &mut rgb);
            let out = self.infer(&rgb);
            self.rgb = rgb;
            detection_from_output(&out?, &crop, self.expected_length_px)
        }
    }
}

/// Turns model outputs into a detection in frame pixels, or says why there is none.
pub fn detection_from_output(
    out: &UnetOutput,
    crop: &impl CropGeometry,
    expected_length_px: f64,
) -> Result<Detection, LocalizeError> {
    if out.presence_logit < 0.0 {
        return Err(LocalizeError::NotFound);
    }
    // Centroid from the mask's first moments: sub-pixel, robust to one bad keypoint.
    let (mut m00, mut m10, mut m01) = (0.0, 0.0, 0.0);
    for (i, &v) in out.mask.iter().enumerate() {
        if v > 0 {
            let (x, y) = ((i % INPUT_PX) as f64, (i / INPUT_PX) as f64);
            m00 += 1.0;
            m10 += x;
            m01 += y;
        }
    }
    let expected_area = expected_length_px * expected_length_px * 0.35;
    if m00 < 0.3 * expected_area {
        return Err(LocalizeError::ImplausibleArea {
            area_px: m00,
            expected_px: expected_area,
        });
    }
    let centroid = (m10 / m00, m01 / m00);
    let [tip, _, tail] = out.keypoints;
    let axis = (tip.0 - tail.0, tip.1 - tail.1);
    let length = (axis.0 * axis.0 + axis.1 * axis.1).sqrt();
    if !(0.6 * expected_length_px..=1.4 * expected_length_px).contains(&length) {
        return Err(LocalizeError::Ambiguous);
    }
    let to_frame = |p: (f64, f64)| crop.input_to_frame(p.0, p.1);
    let f = crop.frame_px_per_input_px();
    let confidence = 1.0 / (1.0 + (-out.presence_logit).exp());
    Ok(Detection {
        centroid_px: to_frame(centroid),
        tip_px: to_frame(tip),
        tail_px: to_frame(tail),
        heading_image_rad: axis.1.atan2(axis.0),
        area_px: m00 * f * f,
        confidence,
    })
}
