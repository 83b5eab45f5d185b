//! The rig file as written (serde, TOML). Every table denies unknown keys; nothing has a
//! default except where FORMAT.md says so. Lengths are millimetres (`_mm`) except in `[robot]`,
//! which is [`crate::rig::RobotParams`]'s SI form.

use std::path::PathBuf;

use serde::Deserialize;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RigFile {
    pub format: String,
    pub version: u32,
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub electromagnet: ElectromagnetSection,
    /// Defaults to none so that "no coils" gets the clear count error, not a parse error.
    #[serde(default)]
    pub coils: Vec<CoilSection>,
    pub camera: CameraSection,
    pub phantom: PhantomSection,
    pub robot: RobotSection,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ElectromagnetSection {
    /// A table ([`FieldModelSection`]); read as a value so the retired string form gets a
    /// message that says what to write instead.
    pub field_model: toml::Value,
    /// The plant's (truth) field model; defaults to `field_model`.
    #[serde(default)]
    pub twin_field_model: Option<toml::Value>,
    pub max_total_power_w: f64,
    /// The coil drivers' supply voltage, V (default: the largest I_max · R over the coils).
    #[serde(default)]
    pub driver_supply_v: Option<f64>,
    pub allocation_coils: Vec<String>,
    /// Fields the coils are known to make (gaussmeter readings, FEA results).
    #[serde(default)]
    pub reference_fields: Vec<ReferenceFieldSection>,
}

/// `{ kind = "analytic" | "maps", dir = "<maps dir>", calibration = "<file>" }`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct FieldModelSection {
    pub kind: String,
    #[serde(default)]
    pub dir: Option<PathBuf>,
    #[serde(default)]
    pub calibration: Option<PathBuf>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ReferenceFieldSection {
    pub source: String,
    pub coils: Vec<String>,
    /// Current in each named coil, A (one of this and `power_w`).
    #[serde(default)]
    pub current_a: Option<f64>,
    /// Ohmic power in each named coil, W: the current is sqrt(P / R) of that coil.
    #[serde(default)]
    pub power_w: Option<f64>,
    pub point_mm: [f64; 3],
    pub direction: [f64; 3],
    pub field_mt: f64,
    #[serde(default)]
    pub gradient_mt_per_cm: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct CoilSection {
    pub name: String,
    pub center_mm: [f64; 3],
    pub axis: [f64; 3],
    pub turns: Option<f64>,
    pub winding: Option<WindingSection>,
    pub resistance_ohm: f64,
    pub max_current_a: f64,
    /// Current the coil carries indefinitely (default: `max_current_a`).
    pub continuous_current_a: Option<f64>,
    /// Heat above the continuous rating the coil tolerates, A²·s (default: 10 s at the limit).
    pub thermal_budget_a2s: Option<f64>,
    /// [[current_a, gain], …]: effective gain against current; absent = linear coil.
    #[serde(default)]
    pub saturation: Option<Vec<[f64; 2]>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct WindingSection {
    pub inner_radius_mm: f64,
    pub outer_radius_mm: f64,
    pub length_mm: f64,
    pub radial_filaments: u32,
    pub axial_filaments: u32,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub(crate) enum PixelFormatName {
    Rgb8,
    Gray8,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct CameraSection {
    pub width_px: u32,
    pub height_px: u32,
    pub pixel_format: PixelFormatName,
    pub mm_per_px: f64,
    pub origin_mm: [f64; 2],
    /// Where the camera service reads frames on this rig (`/dev/video0`, ...).
    #[serde(default)]
    pub source: Option<String>,
    /// The real camera's lens and registration (`calib` writes it); none for a camera that
    /// delivers the canonical top view itself.
    #[serde(default)]
    pub calibration: Option<CameraCalibrationSection>,
}

/// ROS `camera_info` names for the intrinsics; the registration is ours.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct CameraCalibrationSection {
    pub image_width: u32,
    pub image_height: u32,
    pub camera_matrix: [f64; 9],
    pub distortion_model: String,
    pub distortion_coefficients: Vec<f64>,
    #[serde(default)]
    pub reprojection_error_px: Option<f64>,
    /// Undistorted raw-image pixels → world mm, row-major 3x3.
    #[serde(default)]
    pub image_to_world_mm: Option<[f64; 9]>,
    #[serde(default)]
    pub registration_residual_mm: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct PhantomSection {
    pub mask: PathBuf,
    pub mask_mm_per_px: f64,
    pub mask_origin_mm: [f64; 2],
    #[serde(default)]
    pub inlets: Vec<InletSection>,
    #[serde(default)]
    pub outlets: Vec<OutletSection>,
    #[serde(default)]
    pub zones: Vec<ZoneSection>,
    #[serde(default)]
    pub flow: Vec<FlowSection>,
    #[serde(default)]
    pub route: Option<RouteSection>,
}

/// The default start and goal of a run on this phantom (planner, scenarios without a path).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RouteSection {
    pub start_mm: [f64; 2],
    pub end_mm: [f64; 2],
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct InletSection {
    pub name: String,
    pub position_mm: [f64; 2],
    pub direction: [f64; 2],
    pub diameter_mm: f64,
    pub length_mm: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct OutletSection {
    pub name: String,
    pub position_mm: [f64; 2],
    pub direction: [f64; 2],
    pub diameter_mm: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub(crate) enum ZoneKindName {
    HighDisturbance,
    Recirculation,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ZoneSection {
    pub name: String,
    pub kind: ZoneKindName,
    pub polygon_mm: Vec<[f64; 2]>,
    #[serde(default)]
    pub center_mm: Option<[f64; 2]>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct FlowSection {
    pub name: String,
    pub map: PathBuf,
    pub flow_ml_min: f64,
    pub viscosity_cp: f64,
}

/// [`crate::rig::RobotParams`] with every field required: a rig file that forgot its magnet
/// should not silently get the paper's.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RobotSection {
    pub magnet_moment_am2: f64,
    pub mass_kg: f64,
    pub added_mass_kg: f64,
    pub length_m: f64,
    pub diameter_m: f64,
    /// `[robot.appearance]`: the classical localizer's colour ranges (default: the twin's).
    #[serde(default)]
    pub appearance: Option<crate::rig::CapsuleAppearance>,
}
