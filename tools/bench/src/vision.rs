//! Vision workloads on a frame rendered by the twin's camera of the rig (capsule in the canal).

use std::path::PathBuf;

use millinav_plant::render::{Camera, CameraConfig, CapsulePose};
use millinav_vision::classical::{CapsuleSize, ClassicalLocalizer, SearchRect};
use millinav_vision::unet::{find_onnxruntime, UnetLocalizer};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::BenchError;

/// A rendered frame with where the capsule is.
pub struct Scene {
    pub rgb: Vec<u8>,
    pub width: usize,
    pub height: usize,
    pub mm_per_px: f64,
    pub centroid_px: (f64, f64),
    /// The rig's capsule.
    pub capsule: CapsuleSize,
    /// The rig's colour ranges for the classical localizer.
    pub appearance: fieldmaps::rig::CapsuleAppearance,
}

impl Scene {
    /// Frame `seq` of the workload rig's camera with the capsule at its trajectory's start.
    pub fn render(seq: u64, work: &crate::workload::Workload) -> Result<Self, BenchError> {
        let rig = &work.rig;
        let geometry = rig.camera.geometry;
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let camera = Camera::with_config(
            &rig.phantom.mask,
            geometry,
            &mut rng,
            3.0,
            CameraConfig::default(),
        );
        let robot = &rig.robot;
        let position = work.reference.sample(0.0).position_m;
        let capsule = CapsulePose {
            position_m: position,
            heading_rad: 0.6,
            length_m: robot.length_m,
            diameter_m: robot.diameter_m,
        };
        let mut rgb = camera.frame_background(seq).to_vec();
        camera.finish_frame(&mut rgb, &capsule, seq, 0.0, &mut rng, None);
        Ok(Self {
            rgb,
            width: geometry.width_px as usize,
            height: geometry.height_px as usize,
            mm_per_px: geometry.mm_per_px,
            centroid_px: geometry.world_to_px(&position),
            capsule: CapsuleSize::of(&rig.robot),
            appearance: rig.appearance,
        })
    }

    /// Square search rectangle of `side_mm` around the capsule (the tracker's ROI).
    pub fn roi(&self, side_mm: f64) -> SearchRect {
        let side = (side_mm / self.mm_per_px).round() as i32;
        let (w, h) = (self.width as i32, self.height as i32);
        let x = ((self.centroid_px.0 as i32) - side / 2).clamp(0, w - side);
        let y = ((self.centroid_px.1 as i32) - side / 2).clamp(0, h - side);
        (x, y, side, side)
    }

    pub fn full(&self) -> SearchRect {
        (0, 0, self.width as i32, self.height as i32)
    }
}

pub fn classical(scene: &Scene) -> ClassicalLocalizer {
    ClassicalLocalizer::new(scene.capsule, scene.appearance)
}

/// The committed ROI UNet with the venv's ONNX Runtime (single intra-op thread, as in vision).
pub fn unet(scene: &Scene) -> Result<UnetLocalizer, BenchError> {
    let model = model_path();
    let runtime = find_onnxruntime(None).map_err(|e| BenchError::Setup(e.to_string()))?;
    UnetLocalizer::load(
        &model,
        &runtime,
        scene.capsule.length_m * 1e3,
        scene.mm_per_px,
    )
    .map_err(|e| BenchError::Setup(e.to_string()))
}

pub fn model_path() -> PathBuf {
    crate::workspace_root().join(millinav_vision::DEFAULT_MODEL)
}
