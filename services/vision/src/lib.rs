//! vision: camera frames in, `Pose` out. A tracker searches a region of interest around the
//! last detection and falls back to the whole frame when the robot is lost. A frame without a
//! confident, unambiguous detection yields an invalid pose, never a guess.

pub mod classical;
pub mod ort_version;
pub mod unet;

use fieldmaps::rigfile::Rig;
use millinav_kit::ports::{FrameInbox, Outbox};
use millinav_kit::recording;
use millinav_kit::rerun;
use millinav_kit::scenario::Scenario;
use millinav_kit::{ConfigContext, ConfigError, Runtime, ServiceLoop};
use serde::{Deserialize, Serialize};
use shm_schemas::{deadlines, services, Flag, FrameHeader, PixelFormat, Pose, PoseSource};

use std::path::PathBuf;

use crate::classical::{CapsuleSize, ClassicalLocalizer, Detection, LocalizeError, SearchRect};
use crate::unet::{find_onnxruntime, UnetError, UnetLocalizer};

/// Which localizer produces poses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum LocalizerKind {
    /// UNet on a region of interest; the classical localizer re-acquires a lost robot.
    #[default]
    Unet,
    /// OpenCV colour segmentation and moments only (baseline and fallback).
    Classical,
}

/// `[vision]` section of a scenario.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VisionConfig {
    pub localizer: LocalizerKind,
    /// UNet model (ONNX); relative paths are taken from the workspace root, then the scenario.
    pub model: PathBuf,
    /// libonnxruntime.so; default: ORT_DYLIB_PATH, then the project venv's onnxruntime wheel.
    pub onnxruntime: Option<PathBuf>,
    /// Side of the square search region around the last detection (mm), classical path.
    pub roi_mm: f64,
    /// The capsule's length in the model's training crops, in model-input pixels: the UNet
    /// crops this camera's frames so the capsule reaches it at that size. Default: the
    /// committed model's, [`COMMITTED_MODEL_CAPSULE_LENGTH_PX`]; a model trained on another
    /// rig (`unet-dataset --rig`) states its own (`unet-dataset` prints it).
    pub model_capsule_length_px: f64,
    /// Log the camera image (with the segmentation and keypoints) every this many frames; 0
    /// never.
    pub image_log_every: u64,
    /// Logged image size: 1 = full resolution, 2 = every second pixel, ...
    pub image_log_downsample: u32,
    /// JPEG quality of the logged image (1–100); 0 logs raw pixels (lossless, 3 bytes a pixel).
    pub image_log_jpeg_quality: u8,
}

impl Default for VisionConfig {
    fn default() -> Self {
        Self {
            localizer: LocalizerKind::default(),
            model: PathBuf::from(DEFAULT_MODEL),
            onnxruntime: None,
            roi_mm: 20.0,
            model_capsule_length_px: COMMITTED_MODEL_CAPSULE_LENGTH_PX,
            image_log_every: 25,
            image_log_downsample: 1,
            image_log_jpeg_quality: 90,
        }
    }
}

/// The capsule's length in the committed model's training crops (model-input pixels): a
/// property of the model, as `unet-dataset` prints it for the crops it was trained on
/// (`scripts/train_unet.sh` renders them without `--rig`, i.e. on the paper rig's file).
pub const COMMITTED_MODEL_CAPSULE_LENGTH_PX: f64 = 41.02;

/// The committed model the service runs, relative to the workspace root: `FLOAT_MODEL`
/// quantized to int8 with 7-bit weights (tools/unet/quantize.py; keypoint head kept in float):
/// the float model's test-set accuracy on CPUs with and without VNNI (measured here without);
/// faster than float only where the CPU has VNNI.
pub const DEFAULT_MODEL: &str = "tools/unet/model/unet_roi96_int8.onnx";

/// The trained float32 model `DEFAULT_MODEL` was quantized from.
pub const FLOAT_MODEL: &str = "tools/unet/model/unet_roi96.onnx";

/// Resolves the model path: absolute, else relative to the repository root
/// (`fieldmaps::data_root`), else relative to the scenario file.
pub fn resolve_model(config: &VisionConfig, scenario: &Scenario) -> PathBuf {
    if config.model.is_absolute() {
        return config.model.clone();
    }
    let from_root = fieldmaps::data_root().join(&config.model);
    if from_root.exists() {
        return from_root;
    }
    scenario.resolve(&config.model)
}

/// The localization pipeline of the service: ROI tracking, the chosen localizer, re-acquisition.
pub struct Pipeline {
    pub tracker: RoiTracker,
    classical: ClassicalLocalizer,
    unet: Option<UnetLocalizer>,
    roi_mm: f64,
}

/// What one frame gave.
pub struct FrameResult {
    pub detection: Result<Detection, LocalizeError>,
    pub source: PoseSource,
    /// Segmentation of the classical path, with its search rectangle (for the recording).
    pub classical_mask: Option<(opencv::core::Mat, SearchRect)>,
}

impl Pipeline {
    /// The pipeline for `rig`'s capsule seen by `rig`'s camera.
    pub fn new(config: &VisionConfig, scenario: &Scenario, rig: &Rig) -> Result<Self, UnetError> {
        let size = CapsuleSize::of(&rig.robot);
        let unet = match config.localizer {
            LocalizerKind::Classical => None,
            LocalizerKind::Unet => {
                let runtime = find_onnxruntime(config.onnxruntime.as_deref())?;
                let model = resolve_model(config, scenario);
                let unet = UnetLocalizer::load(
                    &model,
                    &runtime,
                    size.length_m * 1e3,
                    rig.camera.geometry.mm_per_px,
                )?
                .with_model_scale(config.model_capsule_length_px);
                Some(unet)
            }
        };
        Ok(Self {
            tracker: RoiTracker::default(),
            classical: ClassicalLocalizer::new(size, rig.appearance),
            unet,
            roi_mm: config.roi_mm,
        })
    }

    /// Frame pixels per model-input pixel of the UNet's crops (None: classical only).
    pub fn unet_crop_scale(&self) -> Option<f64> {
        self.unet.as_ref().map(UnetLocalizer::scale)
    }

    /// Localizes the capsule in one RGB frame.
    pub fn process(
        &mut self,
        rgb: &[u8],
        width: usize,
        height: usize,
        mm_per_px: f64,
    ) -> FrameResult {
        let (w, h) = (width as i32, height as i32);
        let roi_px = (self.roi_mm / mm_per_px).round() as i32;
        let mut result = FrameResult {
            detection: Err(LocalizeError::NotFound),
            source: PoseSource::Classical,
            classical_mask: None,
        };
        // Classical: the whole answer, or (UNet) only re-acquisition when the robot is lost.
        let predicted = match (&self.unet, self.tracker.last_px) {
            (Some(_), Some(last)) => Some(last),
            _ => {
                let rect = self.tracker.search_rect(w, h, roi_px);
                match self.classical.localize(rgb, w, h, rect, mm_per_px) {
                    Ok((d, mask)) => {
                        result.classical_mask = Some((mask, rect));
                        result.detection = Ok(d);
                        Some(d.centroid_px)
                    }
                    Err(e) => {
                        result.detection = Err(e);
                        None
                    }
                }
            }
        };
        if let (Some(unet), Some(centre)) = (self.unet.as_mut(), predicted) {
            result.source = PoseSource::Unet;
            result.detection = unet.localize(rgb, width, height, centre);
        }
        self.tracker.update(result.detection.as_ref().ok());
        result
    }
}

/// Region-of-interest tracker: where to look in the next frame.
#[derive(Debug, Default)]
pub struct RoiTracker {
    pub last_px: Option<(f64, f64)>,
}

impl RoiTracker {
    pub fn search_rect(&self, width: i32, height: i32, roi_px: i32) -> SearchRect {
        match self.last_px {
            None => (0, 0, width, height),
            Some((cx, cy)) => {
                let side = roi_px.min(width).min(height).max(8);
                let x = ((cx as i32) - side / 2).clamp(0, width - side);
                let y = ((cy as i32) - side / 2).clamp(0, height - side);
                (x, y, side, side)
            }
        }
    }

    pub fn update(&mut self, detection: Option<&Detection>) {
        self.last_px = detection.map(|d| d.centroid_px);
    }
}

/// Converts a detection (pixels) into a pose (metres) with the frame's geometry.
pub fn pose_from_detection(header: &FrameHeader, d: &Detection, source: PoseSource) -> Pose {
    let to_world = |(c, r): (f64, f64)| header.pixel_to_world_m(c, r);
    let centroid = to_world(d.centroid_px);
    Pose {
        stamp: header.stamp,
        position_m: centroid,
        // Image y grows downwards: flip to the world's y-up convention.
        heading_rad: -d.heading_image_rad,
        tip_m: to_world(d.tip_px),
        centroid_m: centroid,
        tail_m: to_world(d.tail_px),
        confidence: d.confidence,
        source: source as u32,
        valid: Flag::TRUE,
        reserved: [0; 3],
    }
}

pub fn invalid_pose(header: &FrameHeader) -> Pose {
    Pose {
        stamp: header.stamp,
        valid: Flag::FALSE,
        source: PoseSource::Classical as u32,
        ..Default::default()
    }
}

/// Every `step`-th pixel of every `step`-th row of a packed RGB frame.
fn downsample(rgb: &[u8], width: usize, height: usize, step: usize) -> Vec<u8> {
    if step <= 1 {
        return rgb[..width * height * 3].to_vec();
    }
    let (w, h) = (width / step, height / step);
    let mut out = Vec::with_capacity(w * h * 3);
    for row in 0..h {
        let src_row = &rgb[(step * row) * width * 3..(step * row + 1) * width * 3];
        for col in 0..w {
            out.extend_from_slice(&src_row[step * col * 3..step * col * 3 + 3]);
        }
    }
    out
}

fn log_frame(
    rec: &rerun::RecordingStream,
    header: &FrameHeader,
    rgb: &[u8],
    detection: Option<&Detection>,
    robot_mask: Option<(&opencv::core::Mat, SearchRect)>,
    log_image: bool,
    config: &VisionConfig,
) {
    use opencv::prelude::*;
    let (w, h) = (header.width as usize, header.height as usize);
    let step = config.image_log_downsample.max(1) as usize;
    if log_image {
        let small = downsample(rgb, w, h, step);
        let image = millinav_kit::recording::camera_image(
            small,
            w / step,
            h / step,
            config.image_log_jpeg_quality,
        );
        let _ = rec.log("camera/image", image.as_ref());
        if let Some((mask, rect)) = robot_mask {
            // The segmentation of the search region, placed in the logged frame.
            let (lw, lh) = (w / step, h / step);
            let mut full = vec![0u8; lw * lh];
            for r in (0..rect.3).step_by(step) {
                if let Ok(line) = mask.at_row::<u8>(r) {
                    for c in (0..rect.2 as usize).step_by(step) {
                        let (fr, fc) = ((rect.1 + r) as usize / step, (rect.0 as usize + c) / step);
                        if fr < lh && fc < lw && line[c] > 0 {
                            full[fr * lw + fc] = 1;
                        }
                    }
                }
            }
            let _ = rec.log(
                "camera/mask",
                &rerun::SegmentationImage::new(
                    full,
                    rerun::datatypes::ImageFormat::segmentation(
                        [(w / step) as u32, (h / step) as u32],
                        rerun::datatypes::ChannelDatatype::U8,
                    ),
                ),
            );
        }
    }
    if let Some(d) = detection {
        let scale = step as f64;
        let at = |(c, r): (f64, f64)| [(c / scale) as f32, (r / scale) as f32];
        let _ = rec.log(
            "camera/keypoints",
            &rerun::Points2D::new([at(d.tip_px), at(d.centroid_px), at(d.tail_px)])
                .with_labels(["tip", "centroid", "tail"])
                .with_radii([2.0]),
        );
    }
}

/// What the `[vision]` table configures, validated and loaded: the config and the pipeline
/// with its model.
pub struct VisionSetup {
    pub config: VisionConfig,
    pub pipeline: Pipeline,
}

/// Parses and validates the `[vision]` table and loads the model and ONNX Runtime it names.
/// Every failure is a configuration error naming the scenario, the field and the file.
pub fn prepare(scenario: &Scenario) -> Result<VisionSetup, ConfigError> {
    let config: VisionConfig = scenario.section("vision")?;
    let field = |name: &str| format!("scenario {}: [vision] {name}", scenario.path.display());
    if !(config.roi_mm.is_finite() && config.roi_mm > 0.0) {
        return Err(ConfigError::new(format!(
            "{} must be > 0, got {}",
            field("roi_mm"),
            config.roi_mm
        )));
    }
    if !(config.model_capsule_length_px.is_finite() && config.model_capsule_length_px > 0.0) {
        return Err(ConfigError::new(format!(
            "{} must be > 0 (model-input pixels), got {}",
            field("model_capsule_length_px"),
            config.model_capsule_length_px
        )));
    }
    if config.image_log_downsample == 0 || config.image_log_jpeg_quality > 100 {
        return Err(ConfigError::new(format!(
            "{} must be >= 1 and {} between 0 (raw) and 100, got {} and {}",
            field("image_log_downsample"),
            field("image_log_jpeg_quality"),
            config.image_log_downsample,
            config.image_log_jpeg_quality
        )));
    }
    if config.localizer == LocalizerKind::Unet {
        let model = resolve_model(&config, scenario);
        if !model.is_file() {
            return Err(ConfigError::new(format!(
                "{} = {}: {} is not a file",
                field("model"),
                config.model.display(),
                model.display()
            )));
        }
    }
    let rig = scenario.rig()?;
    let pipeline = Pipeline::new(&config, scenario, &rig).config_context(field("localizer"))?;
    if let Some(scale) = pipeline.unet_crop_scale() {
        // A crop that does not fit in the frame gives no pose at all; say why at start-up.
        let side_px = millinav_roi::roi::INPUT_PX as f64 * scale;
        let geometry = rig.camera.geometry;
        if side_px > f64::from(geometry.width_px.min(geometry.height_px)) {
            return Err(ConfigError::new(format!(
                "{}: the UNet's crop would be {side_px:.0} frame px square (the capsule is {:.1} px \
                 long in the rig's {} x {} px camera, {} px in the model's training crops), \
                 larger than the frame; set it to what the model was trained on, train one \
                 for this camera (`unet-dataset --rig`), or use localizer = \"classical\"",
                field("model_capsule_length_px"),
                CapsuleSize::of(&rig.robot).length_m * 1e3 / geometry.mm_per_px,
                geometry.width_px,
                geometry.height_px,
                config.model_capsule_length_px,
            )));
        }
    }
    Ok(VisionSetup { config, pipeline })
}

/// Validates the `[vision]` table and loads its model (what `--check` runs).
pub fn check_config(scenario: &Scenario) -> Result<(), ConfigError> {
    prepare(scenario).map(drop)
}

/// A warning is logged for the first frame without a pose, then for every this many.
const WARN_EVERY_LOST_FRAMES: u64 = 100;

/// The vision process: the newest frame gets a pose (valid or not), older ones are skipped.
pub fn run(rt: &mut Runtime, _scenario: &Scenario, setup: VisionSetup) -> anyhow::Result<()> {
    let VisionSetup {
        config,
        mut pipeline,
    } = setup;
    let frames = FrameInbox::new(&rt.node)?;
    let poses = Outbox::<Pose>::new(&rt.node, services::POSE)?;
    match pipeline.unet_crop_scale() {
        Some(scale) if scale != millinav_roi::roi::DOWNSAMPLE as f64 => tracing::info!(
            localizer = ?config.localizer,
            frame_px_per_model_px = scale,
            "vision ready; this camera shows the capsule at another size than the model's \
             training crops, so the UNet's crops are resampled to the model's scale"
        ),
        _ => tracing::info!(localizer = ?config.localizer, "vision ready"),
    }
    let mut lost_frames: u64 = 0;

    let mut service_loop = ServiceLoop::new();
    service_loop.input_with_deadline(&frames, deadlines::FRAME);
    service_loop.output(&poses);
    service_loop.run(&mut rt.heartbeat, |_| {
        let Some(sample) = frames.latest()? else {
            tracing::debug!("woke without a frame");
            return Ok(());
        };
        tracing::debug!(seq = sample.user_header().stamp.seq, "frame");
        let header = *sample.user_header();
        let pose = pose_for_frame(
            &mut pipeline,
            &config,
            &rt.rec,
            &header,
            sample.payload(),
            &mut lost_frames,
        );
        drop(sample);
        log_pose(&rt.rec, &pose);
        poses.send(pose)?;
        anyhow::Ok(())
    })?;
    Ok(())
}

/// Localizes the capsule in one received frame; a frame that cannot be read gives an invalid
/// pose. Counts consecutive frames without a pose in `lost_frames`.
fn pose_for_frame(
    pipeline: &mut Pipeline,
    config: &VisionConfig,
    rec: &rerun::RecordingStream,
    header: &FrameHeader,
    rgb: &[u8],
    lost_frames: &mut u64,
) -> Pose {
    match header.validate(rgb.len()) {
        Ok(PixelFormat::Rgb8) => {
            let (w, h) = (header.width as i32, header.height as i32);
            if header.stride != header.width * 3 {
                tracing::warn!(
                    "padded frames are not supported; frame {} dropped",
                    header.stamp.seq
                );
                invalid_pose(header)
            } else {
                let result = pipeline.process(rgb, w as usize, h as usize, header.mm_per_px);
                let log_image = config.image_log_every > 0
                    && header.stamp.seq.is_multiple_of(config.image_log_every);
                recording::set_time(rec, header.stamp.capture_time_ns, header.stamp.seq);
                let mask = result.classical_mask.as_ref().map(|(m, r)| (m, *r));
                match &result.detection {
                    Ok(detection) => {
                        *lost_frames = 0;
                        log_frame(rec, header, rgb, Some(detection), mask, log_image, config);
                        pose_from_detection(header, detection, result.source)
                    }
                    Err(why) => {
                        *lost_frames += 1;
                        if *lost_frames == 1 || lost_frames.is_multiple_of(WARN_EVERY_LOST_FRAMES) {
                            tracing::warn!(seq = header.stamp.seq, "no pose: {why}");
                        }
                        log_frame(rec, header, rgb, None, None, log_image, config);
                        invalid_pose(header)
                    }
                }
            }
        }
        Ok(other) => {
            tracing::warn!(
                "unsupported pixel format {other:?}; frame {} dropped",
                header.stamp.seq
            );
            invalid_pose(header)
        }
        Err(why) => {
            tracing::warn!("malformed frame {}: {why}", header.stamp.seq);
            invalid_pose(header)
        }
    }
}

fn log_pose(rec: &rerun::RecordingStream, pose: &Pose) {
    if pose.valid == Flag::TRUE {
        let _ = rec.log(
            "world/robot/estimated",
            &rerun::Points2D::new([[
                (pose.position_m[0] * 1e3) as f32,
                (pose.position_m[1] * 1e3) as f32,
            ]])
            .with_radii([1.0]),
        );
        recording::scalar(rec, "vision/x_mm", pose.position_m[0] * 1e3);
        recording::scalar(rec, "vision/y_mm", pose.position_m[1] * 1e3);
        recording::scalar(rec, "vision/heading_deg", pose.heading_rad.to_degrees());
    }
    recording::scalar(rec, "vision/valid", f64::from(pose.valid.raw()));
}

#[cfg(test)]
mod tests {
    use super::*;
    use millinav_kit::scratch::ScratchDir;

    /// A scenario file in a directory of its own, with `vision_table` as its `[vision]`.
    fn scenario_with(name: &str, vision_table: &str) -> (Scenario, ScratchDir) {
        let dir = ScratchDir::new(&format!("millinav-vision-{name}")).unwrap();
        let text = format!(
            "[run]\nduration_s = 1.0\nrig = \"fieldmaps/rigs/paper.toml\"\n[fluid]\nviscosity_cp = 20.0\n\
             [trajectory]\nwaypoints_mm = [[0.0, 0.0], [5.0, 0.0]]\n[vision]\n{vision_table}\n"
        );
        let path = dir.join("scenario.toml");
        (Scenario::parse(&text, &path).unwrap(), dir)
    }

    #[test]
    fn check_config_accepts_the_classical_localizer() {
        let (scenario, _) = scenario_with("classical", "localizer = \"classical\"");
        check_config(&scenario).unwrap();
    }

    #[test]
    fn check_config_rejects_typos_and_missing_or_corrupt_models() {
        let (scenario, dir) = scenario_with("typo", "localiser = \"classical\"");
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(
            error.contains("[vision]") && error.contains("localiser"),
            "{error}"
        );

        let absent = dir.join("absent.onnx");
        let (scenario, _) = scenario_with("absent", &format!("model = {:?}", absent));
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(
            error.contains("[vision] model") && error.contains("absent.onnx"),
            "{error}"
        );

        // Loading a corrupt model needs ONNX Runtime, which the project's setup installs.
        let corrupt = dir.join("corrupt.onnx");
        std::fs::write(&corrupt, b"not an ONNX model").unwrap();
        let (scenario, _) = scenario_with("corrupt", &format!("model = {:?}", corrupt));
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(
            error.contains("[vision]") && error.contains("corrupt.onnx"),
            "{error}"
        );

        let (scenario, _) = scenario_with("roi", "localizer = \"classical\"\nroi_mm = -1.0");
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(error.contains("[vision] roi_mm"), "{error}");

        let (scenario, _) = scenario_with("scale", "model_capsule_length_px = 0.0");
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(
            error.contains("[vision] model_capsule_length_px"),
            "{error}"
        );

        // A model trained on a capsule 2 px long would need crops 41x the paper rig's 82 px
        // capsule: larger than the frame, refused at start-up rather than never finding it.
        let (scenario, _) = scenario_with("huge", "model_capsule_length_px = 2.0");
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(
            error.contains("[vision] model_capsule_length_px")
                && error.contains("larger than the frame"),
            "{error}"
        );
    }
}
