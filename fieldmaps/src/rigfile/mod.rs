//! The rig as data: one TOML file (`fieldmaps/rigs/paper.toml`, format in
//! `fieldmaps/rigs/FORMAT.md`) describes the electromagnet, the camera, the phantom and the
//! robot. [`Rig::load`] parses it, validates every value and every file it names, and builds
//! the runtime objects (coil field model, canal mask, zones, ports, limits).
//!
//! Errors name the file and the field: `fieldmaps/rigs/x.toml: coils[3].turns: must be > 0`.
//! Paths inside a rig file are relative to the rig file.

mod build;
mod key_path;
mod reference;
mod schema;
mod zone;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{Matrix3, Unit, Vector2, Vector3};
use thiserror::Error;

use crate::calibration::CalibratedField;
use crate::coils::{CoilField, CoilSystem, Winding};
use crate::fieldmap::CoilFieldMaps;
use crate::mask::CanalMask;
use crate::phantom::{ImageGeometry, Inlet, Outlet};
use crate::rig::{CoilLimits, RobotParams};
use crate::walls::WallField;

pub use zone::{Zone, ZoneKind};

/// Most coils a rig may have: the contract's limit (its coil arrays are this long).
pub use shm_schemas_core::MAX_COILS;

/// The `format` tag every rig file carries.
pub const RIG_FORMAT: &str = "millinav-rig";
/// The format version this loader reads.
pub const RIG_VERSION: u32 = 1;

/// The paper's rig, relative to the repository root ([`crate::data_root`]).
pub const PAPER_RIG: &str = "fieldmaps/rigs/paper.toml";

/// Most filaments per direction that sample a winding's cross-section.
pub const MAX_FILAMENTS: u32 = 64;

/// The committed paper rig file: [`PAPER_RIG`] under [`crate::data_root`].
pub fn paper_rig_path() -> PathBuf {
    crate::data_root().join(PAPER_RIG)
}

/// A rig file that cannot be used; the message names the file and the field.
#[derive(Debug, Error)]
pub enum RigFileError {
    #[error("{}: cannot read rig file: {source}", path.display())]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: {field}: {message}", path.display())]
    Invalid {
        path: PathBuf,
        /// Key path in the file, e.g. `coils[3].turns` (indices from 0).
        field: String,
        message: String,
    },
}

impl RigFileError {
    /// The offending key path, if the error is about one.
    pub fn field(&self) -> Option<&str> {
        match self {
            RigFileError::Read { .. } => None,
            RigFileError::Invalid { field, .. } => Some(field),
        }
    }
}

/// Which model gives the coils' fields.
#[derive(Debug, Clone, PartialEq)]
pub enum FieldModel {
    /// Closed-form Biot–Savart of each coil's winding ([`CoilSystem`]).
    Analytic,
    /// Grid maps in this directory ([`CoilFieldMaps`], `coils.toml` + `.npy`).
    Maps(PathBuf),
}

/// The built coil field model; implements [`CoilField`].
#[derive(Debug, Clone)]
pub enum RigCoilField {
    Analytic(CoilSystem),
    Maps(Arc<CoilFieldMaps>),
    /// A base model with the corrections of a calibration file (`<base> + calibration:<file>`).
    Calibrated(Arc<CalibratedField<RigCoilField>>),
}

impl CoilField for RigCoilField {
    fn coil_count(&self) -> usize {
        match self {
            RigCoilField::Analytic(system) => system.len(),
            RigCoilField::Maps(maps) => maps.coil_count(),
            RigCoilField::Calibrated(field) => field.coil_count(),
        }
    }

    fn field_and_gradient_per_amp(
        &self,
        coil: usize,
        p: &Vector3<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>) {
        match self {
            RigCoilField::Analytic(system) => system.field_and_gradient_per_amp(coil, p),
            RigCoilField::Maps(maps) => maps.field_and_gradient_per_amp(coil, p),
            RigCoilField::Calibrated(field) => field.field_and_gradient_per_amp(coil, p),
        }
    }

    fn background_field(&self, p: &Vector3<f64>) -> Vector3<f64> {
        match self {
            RigCoilField::Calibrated(field) => field.background_field(p),
            _ => Vector3::zeros(),
        }
    }
}

impl RigCoilField {
    /// The uncalibrated model underneath (itself when not calibrated).
    pub fn base(&self) -> &RigCoilField {
        match self {
            RigCoilField::Calibrated(field) => field.base.base(),
            other => other,
        }
    }
}

/// One coil as the rig file describes it (SI units).
#[derive(Debug, Clone, PartialEq)]
pub struct RigCoil {
    pub name: String,
    pub center_m: Vector3<f64>,
    /// Positive current gives a field along `axis` at the coil centre.
    pub axis: Unit<Vector3<f64>>,
    /// Total turns; required by the analytic model, informational with maps.
    pub turns: Option<f64>,
    /// Winding cross-section; required by the analytic model, informational with maps.
    pub winding: Option<Winding>,
    pub resistance_ohm: f64,
    pub max_current_a: f64,
    /// Current the coil carries indefinitely, A (≤ `max_current_a`).
    pub continuous_current_a: f64,
    /// Heat above the continuous rating the coil tolerates, ∫(I² − I_c²) dt in A²·s: the
    /// board's I²t budget.
    pub thermal_budget_a2s: f64,
    /// Effective gain against current (`saturation`), if the coil saturates.
    pub saturation: Option<crate::rig::SaturationCurve>,
}

/// Pixel layout of the camera's frames (mirrors `shm_schemas::PixelFormat`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CameraPixelFormat {
    Rgb8,
    Gray8,
}

/// The top camera: resolution, pixel layout and image ↔ world mapping.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RigCamera {
    /// The canonical top view: the frames vision sees (a real camera's are rectified to it).
    pub geometry: ImageGeometry,
    pub pixel_format: CameraPixelFormat,
    /// The real camera's lens and its registration to the world (`[camera.calibration]`).
    pub calibration: Option<CameraCalibration>,
}

/// A real camera's intrinsics (pinhole + OpenCV's 5-coefficient `plumb_bob` distortion, ROS
/// `camera_info` names) and the homography from its undistorted pixels to the world plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraCalibration {
    /// The raw frames' size (what the camera delivers, before rectification).
    pub image_width: u32,
    pub image_height: u32,
    /// Row-major K = [fx 0 cx; 0 fy cy; 0 0 1], px.
    pub camera_matrix: [f64; 9],
    /// k1, k2, p1, p2, k3.
    pub distortion_coefficients: [f64; 5],
    pub reprojection_error_px: Option<f64>,
    /// Undistorted raw pixels → world mm (row-major 3x3); none until `calib homography` ran.
    pub image_to_world_mm: Option<[f64; 9]>,
    pub registration_residual_mm: Option<f64>,
}

/// A flow condition with its steady map.
#[derive(Debug, Clone, PartialEq)]
pub struct FlowCondition {
    pub name: String,
    /// Absolute (resolved against the rig file's directory).
    pub map_path: PathBuf,
    pub flow_ml_min: f64,
    pub viscosity_pa_s: f64,
}

/// The phantom: canal mask, ports, zones, flow maps.
#[derive(Debug, Clone, PartialEq)]
pub struct RigPhantom {
    pub mask_path: PathBuf,
    pub mask: CanalMask,
    /// Signed distance to the canal wall, from the mask (plant contact, clearance checks).
    pub walls: WallField,
    pub inlets: Vec<Inlet>,
    pub outlets: Vec<Outlet>,
    pub zones: Vec<Zone>,
    pub flow_conditions: Vec<FlowCondition>,
    /// Default start and goal (`[phantom.route]`), if the file gives them.
    pub route: Option<Route>,
}

/// A default start and goal on the canal, m.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Route {
    pub start_m: Vector2<f64>,
    pub end_m: Vector2<f64>,
}

impl RigPhantom {
    /// Whether `p` (m) is on a canal pixel of the mask.
    pub fn contains(&self, p: &Vector2<f64>) -> bool {
        self.mask.contains(p)
    }

    /// Zones containing `p` (m).
    pub fn zones_at(&self, p: Vector2<f64>) -> impl Iterator<Item = &Zone> + '_ {
        self.zones.iter().filter(move |z| z.contains(&p))
    }

    /// Where the twin centres the recirculation vortex of `zone`: its `center_mm` when the file
    /// gives one, else the centroid of the canal pixels inside it (the zone's own centroid when
    /// it covers none).
    pub fn zone_center(&self, zone: &Zone) -> Vector2<f64> {
        if let Some(c) = zone.center_m {
            return c;
        }
        let g = self.mask.geometry();
        let (mut sum, mut count) = (Vector2::zeros(), 0usize);
        for row in 0..g.height_px {
            for col in 0..g.width_px {
                if !self.mask.is_canal_px(i64::from(col), i64::from(row)) {
                    continue;
                }
                let p = g.px_to_world(f64::from(col), f64::from(row));
                if zone.contains(&p) {
                    sum += p;
                    count += 1;
                }
            }
        }
        if count > 0 {
            sum / count as f64
        } else {
            zone.polygon_m.iter().sum::<Vector2<f64>>() / zone.polygon_m.len().max(1) as f64
        }
    }

    /// Whether `p` (m) lies in any zone of `kind`.
    pub fn in_zone(&self, kind: ZoneKind, p: &Vector2<f64>) -> bool {
        self.zones.iter().any(|z| z.kind == kind && z.contains(p))
    }
}

/// A loaded, validated rig.
#[derive(Debug, Clone)]
pub struct Rig {
    /// The rig file it came from.
    pub path: PathBuf,
    pub name: String,
    pub description: String,
    pub coils: Vec<RigCoil>,
    /// The model control plans with (`electromagnet.field_model`), without its calibration.
    pub field_model: FieldModel,
    /// The calibration file `field_model` adds (its `calibration`), if any.
    pub field_calibration: Option<PathBuf>,
    /// The model control plans with, calibration applied.
    pub coil_field: RigCoilField,
    /// The model the twin's physics uses (`electromagnet.twin_field_model`, else `field_model`).
    pub twin_field_model: FieldModel,
    pub twin_field_calibration: Option<PathBuf>,
    pub twin_coil_field: RigCoilField,
    /// Total ohmic power over all coils, W.
    pub max_total_power_w: f64,
    /// The coil drivers' supply voltage, V: the board turns a current into PWM duty |I|·R / V.
    pub driver_supply_v: f64,
    /// Indices (into `coils`) the allocation may drive, in the file's order.
    pub allocation_coils: Vec<usize>,
    /// Fields the coils are known to make (`electromagnet.reference_fields`), which the coil
    /// model should reproduce.
    pub reference_fields: Vec<crate::coils::ReferenceField>,
    pub camera: RigCamera,
    /// The rig's frame source for the camera service (`camera.source`: a V4L2 device, a video
    /// file, ...); a scenario's `[camera] source` overrides it. None: the twin.
    pub camera_source: Option<String>,
    pub phantom: RigPhantom,
    pub robot: RobotParams,
    /// How the capsule looks to the classical localizer (`[robot.appearance]`).
    pub appearance: crate::rig::CapsuleAppearance,
}

impl Rig {
    /// Reads, parses and validates a rig file and everything it names.
    pub fn load(path: &Path) -> Result<Self, RigFileError> {
        let text = std::fs::read_to_string(path).map_err(|source| RigFileError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// [`Self::load`] of the committed paper rig ([`paper_rig_path`]): the tests' fixture.
    pub fn load_paper() -> Result<Self, RigFileError> {
        Self::load(&paper_rig_path())
    }

    /// Parses `text` as the rig file at `path` (relative paths resolve against its directory).
    pub fn parse(text: &str, path: &Path) -> Result<Self, RigFileError> {
        let ctx = build::Ctx {
            path,
            dir: path.parent().unwrap_or(Path::new("")),
        };
        let file: schema::RigFile = toml::from_str(text).map_err(|e| ctx.toml_error(text, &e))?;
        build::build(&ctx, file)
    }

    /// Limits for the allocation in [`CoilLimits`]' one-value-for-all form: exact when every
    /// coil has the same rating, otherwise conservative (the lowest current limit, the highest
    /// resistance, so the power estimate never falls short).
    pub fn coil_limits(&self) -> CoilLimits {
        let min_current = self
            .coils
            .iter()
            .map(|c| c.max_current_a)
            .fold(f64::INFINITY, f64::min);
        let max_resistance = self
            .coils
            .iter()
            .map(|c| c.resistance_ohm)
            .fold(0.0, f64::max);
        CoilLimits {
            max_current_a: min_current,
            max_total_power_w: self.max_total_power_w,
            coil_resistance_ohm: max_resistance,
        }
    }

    /// Each of the coils `ids`' own current limit and resistance (in that order), with the
    /// total power budget: what the allocation respects.
    pub fn coil_ratings(&self, ids: &[usize]) -> crate::allocation::CoilRatings {
        let coil = |&id: &usize| self.coils.get(id);
        crate::allocation::CoilRatings {
            max_current_a: nalgebra::DVector::from_iterator(
                ids.len(),
                ids.iter()
                    .map(|id| coil(id).map_or(0.0, |c| c.max_current_a)),
            ),
            resistance_ohm: nalgebra::DVector::from_iterator(
                ids.len(),
                ids.iter()
                    .map(|id| coil(id).map_or(f64::INFINITY, |c| c.resistance_ohm)),
            ),
            max_total_power_w: self.max_total_power_w,
        }
    }

    /// The closed-form Biot–Savart model of the coils' windings and turns as the file gives
    /// them, uncalibrated, whichever model control and the twin use; None when a coil lacks
    /// `turns` or `[coils.winding]`.
    pub fn winding_model(&self) -> Option<CoilSystem> {
        let coils = self
            .coils
            .iter()
            .map(|c| {
                Some(crate::coils::Coil::from_winding(
                    c.name.clone(),
                    c.center_m,
                    c.axis,
                    c.winding.as_ref()?,
                    c.turns?,
                ))
            })
            .collect::<Option<Vec<_>>>()?;
        Some(CoilSystem { coils })
    }

    /// Index of the coil called `name`.
    pub fn coil_index(&self, name: &str) -> Option<usize> {
        self.coils.iter().position(|c| c.name == name)
    }

    /// A human-readable summary (what `fieldgen rig-check` prints).
    pub fn summary(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let g = &self.camera.geometry;
        let m = self.phantom.mask.geometry();
        let mut model = match &self.field_model {
            FieldModel::Analytic => "analytic (Biot–Savart)".to_string(),
            FieldModel::Maps(dir) => format!("maps ({})", dir.display()),
        };
        if let Some(cal) = &self.field_calibration {
            model.push_str(&format!(" + calibration ({})", cal.display()));
        }
        let names = |ids: &[usize]| {
            ids.iter()
                .map(|&i| self.coils[i].name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        };
        let _ = writeln!(s, "rig {} ({})", self.name, self.path.display());
        let _ = writeln!(
            s,
            "coils: {} (max {MAX_COILS}), field model {model}, total power ≤ {} W",
            self.coils.len(),
            self.max_total_power_w
        );
        for c in &self.coils {
            let _ = writeln!(
                s,
                "  {:<10} centre ({:.1}, {:.1}, {:.1}) mm, axis ({:.2}, {:.2}, {:.2}), {} Ω, ≤ {} A",
                c.name,
                c.center_m.x * 1e3,
                c.center_m.y * 1e3,
                c.center_m.z * 1e3,
                c.axis.x,
                c.axis.y,
                c.axis.z,
                c.resistance_ohm,
                c.max_current_a
            );
        }
        let _ = writeln!(
            s,
            "allocation: {} coils: {}",
            self.allocation_coils.len(),
            names(&self.allocation_coils)
        );
        let _ = writeln!(
            s,
            "camera: {}x{} px {:?}, {:.5} mm/px, origin ({}, {}) mm, field of view {:.2} x {:.2} mm",
            g.width_px,
            g.height_px,
            self.camera.pixel_format,
            g.mm_per_px,
            g.origin_x_mm,
            g.origin_y_mm,
            f64::from(g.width_px) * g.mm_per_px,
            f64::from(g.height_px) * g.mm_per_px
        );
        let _ = writeln!(
            s,
            "phantom: mask {} ({}x{} px, {:.5} mm/px, {} canal px)",
            self.phantom.mask_path.display(),
            m.width_px,
            m.height_px,
            m.mm_per_px,
            self.phantom.mask.canal_pixels()
        );
        for i in &self.phantom.inlets {
            let _ = writeln!(
                s,
                "  inlet  {:<16} at ({:.2}, {:.2}) mm, D {:.2} mm",
                i.name,
                i.mouth_m.x * 1e3,
                i.mouth_m.y * 1e3,
                i.diameter_m * 1e3
            );
        }
        for o in &self.phantom.outlets {
            let _ = writeln!(
                s,
                "  outlet {:<16} at ({:.2}, {:.2}) mm, D {:.2} mm",
                o.name,
                o.mouth_m.x * 1e3,
                o.mouth_m.y * 1e3,
                o.diameter_m * 1e3
            );
        }
        for z in &self.phantom.zones {
            let _ = writeln!(
                s,
                "  zone   {:<18} {} ({} vertices)",
                z.name,
                z.kind.as_str(),
                z.polygon_m.len()
            );
        }
        let _ = writeln!(s, "flow conditions: {}", self.phantom.flow_conditions.len());
        for f in &self.phantom.flow_conditions {
            let _ = writeln!(
                s,
                "  {:<12} {} mL/min, {} cP: {}",
                f.name,
                f.flow_ml_min,
                f.viscosity_pa_s * 1e3,
                f.map_path.display()
            );
        }
        let r = &self.robot;
        let _ = writeln!(
            s,
            "robot: {:.2} x {:.2} mm capsule, |m| {:.3e} A·m², mass {} mg",
            r.length_m * 1e3,
            r.diameter_m * 1e3,
            r.magnet_moment_am2,
            r.mass_kg * 1e6
        );
        s
    }
}
