//! Validation of the parsed rig file and construction of the runtime objects. Each check
//! reports the first problem as one error naming the file and the key path.

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{Unit, Vector2, Vector3};

use super::key_path::key_path_at;
use super::schema;
use super::{
    CameraCalibration, CameraPixelFormat, FieldModel, FlowCondition, Rig, RigCamera, RigCoil,
    RigCoilField, RigFileError, RigPhantom, Route, Zone, ZoneKind, MAX_COILS, MAX_FILAMENTS,
};
use super::{RIG_FORMAT, RIG_VERSION};
use crate::calibration::{CalibratedField, CoilCalibration};
use crate::coils::{Coil, CoilSystem, Winding};
use crate::fieldmap::CoilFieldMaps;
use crate::flowmap::FlowMap;
use crate::mask::{CanalMask, MaskError};
use crate::phantom::{ImageGeometry, Inlet, Outlet};
use crate::rig::{RigError, RobotParams};
use crate::walls::WallField;

/// Where errors point.
pub(super) struct Ctx<'a> {
    pub path: &'a Path,
    pub dir: &'a Path,
}

impl Ctx<'_> {
    pub(super) fn err(&self, field: impl Into<String>, message: impl Into<String>) -> RigFileError {
        RigFileError::Invalid {
            path: self.path.to_owned(),
            field: field.into(),
            message: message.into(),
        }
    }

    fn resolve(&self, relative: &Path) -> PathBuf {
        if relative.is_absolute() {
            relative.to_owned()
        } else {
            self.dir.join(relative)
        }
    }

    pub(super) fn toml_error(&self, text: &str, e: &toml::de::Error) -> RigFileError {
        let (field, line) = match e.span() {
            Some(span) => (
                key_path_at(text, span.start),
                Some(text[..span.start.min(text.len())].matches('\n').count() + 1),
            ),
            None => (String::new(), None),
        };
        let field = if field.is_empty() {
            "(top level)".to_string()
        } else {
            field
        };
        let message = match line {
            Some(line) => format!("{} (line {line})", e.message().trim()),
            None => e.message().trim().to_string(),
        };
        self.err(field, message)
    }
}

pub(super) fn finite(v: &[f64]) -> bool {
    v.iter().all(|x| x.is_finite())
}

pub(super) fn positive(v: f64) -> bool {
    v.is_finite() && v > 0.0
}

pub(super) fn fmt_vec(v: &[f64]) -> String {
    let parts: Vec<String> = v.iter().map(|x| format!("{x}")).collect();
    format!("[{}]", parts.join(", "))
}

fn check_name(
    ctx: &Ctx<'_>,
    field: &str,
    name: &str,
    seen: &mut HashSet<String>,
) -> Result<(), RigFileError> {
    if name.is_empty()
        || !name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-'))
    {
        return Err(ctx.err(
            field,
            format!("{name:?}: use ASCII letters, digits, '_' or '-' (not empty)"),
        ));
    }
    if !seen.insert(name.to_string()) {
        return Err(ctx.err(field, format!("duplicate name {name:?}")));
    }
    Ok(())
}

/// Default heat budget of a coil above its continuous rating: this many seconds at its limit.
const DEFAULT_THERMAL_BUDGET_S: f64 = 10.0;

fn require_positive(ctx: &Ctx<'_>, field: &str, v: f64) -> Result<(), RigFileError> {
    if positive(v) {
        Ok(())
    } else {
        Err(ctx.err(field, format!("must be finite and > 0, got {v}")))
    }
}

fn mm3(v: [f64; 3]) -> Vector3<f64> {
    Vector3::new(v[0], v[1], v[2]) / 1e3
}

fn mm2(v: [f64; 2]) -> Vector2<f64> {
    Vector2::new(v[0], v[1]) / 1e3
}

pub(super) fn build(ctx: &Ctx<'_>, file: schema::RigFile) -> Result<Rig, RigFileError> {
    if file.format != RIG_FORMAT {
        return Err(ctx.err(
            "format",
            format!("must be {RIG_FORMAT:?}, got {:?}", file.format),
        ));
    }
    if file.version != RIG_VERSION {
        return Err(ctx.err(
            "version",
            format!(
                "this loader reads version {RIG_VERSION}, got {}",
                file.version
            ),
        ));
    }
    if file.name.trim().is_empty() {
        return Err(ctx.err("name", "must not be empty"));
    }
    let coils = build_coils(ctx, &file.coils)?;
    let em = &file.electromagnet;
    let field = "electromagnet.field_model";
    let (field_model, field_calibration) = parse_field_model(ctx, field, &em.field_model)?;
    let coil_field = build_field(ctx, field, &field_model, &coils)?;
    let coil_field = calibrate_field(ctx, field, coil_field, field_calibration.as_deref(), &coils)?;
    let (twin_field_model, twin_field_calibration, twin_coil_field) = match &em.twin_field_model {
        None => (
            field_model.clone(),
            field_calibration.clone(),
            coil_field.clone(),
        ),
        Some(value) => {
            let field = "electromagnet.twin_field_model";
            let (model, calibration) = parse_field_model(ctx, field, value)?;
            let built = build_field(ctx, field, &model, &coils)?;
            let built = calibrate_field(ctx, field, built, calibration.as_deref(), &coils)?;
            (model, calibration, built)
        }
    };
    require_positive(ctx, "electromagnet.max_total_power_w", em.max_total_power_w)?;
    let driver_supply_v = em.driver_supply_v.unwrap_or_else(|| {
        coils
            .iter()
            .map(|c| c.max_current_a * c.resistance_ohm)
            .fold(0.0, f64::max)
    });
    require_positive(ctx, "electromagnet.driver_supply_v", driver_supply_v)?;
    let allocation_coils = build_allocation(ctx, &em.allocation_coils, &coils)?;
    let reference_fields = super::reference::build(ctx, &em.reference_fields, &coils)?;
    let camera = build_camera(ctx, &file.camera)?;
    let phantom = build_phantom(ctx, &file.phantom, &camera)?;
    let robot = build_robot(ctx, &file.robot)?;
    let appearance = file.robot.appearance.unwrap_or_default();
    appearance
        .validate()
        .map_err(|(key, why)| ctx.err(format!("robot.appearance.{key}"), why))?;
    Ok(Rig {
        path: ctx.path.to_owned(),
        name: file.name,
        description: file.description,
        coils,
        field_model,
        field_calibration,
        coil_field,
        twin_field_model,
        twin_field_calibration,
        twin_coil_field,
        max_total_power_w: em.max_total_power_w,
        driver_supply_v,
        allocation_coils,
        reference_fields,
        camera,
        camera_source: file.camera.source.clone(),
        phantom,
        robot,
        appearance,
    })
}

fn build_coils(
    ctx: &Ctx<'_>,
    sections: &[schema::CoilSection],
) -> Result<Vec<RigCoil>, RigFileError> {
    if sections.is_empty() {
        return Err(ctx.err("coils", "a rig needs at least one coil"));
    }
    if sections.len() > MAX_COILS {
        return Err(ctx.err(
            "coils",
            format!(
                "{} coils, at most {MAX_COILS} are supported (the contract's MAX_COILS)",
                sections.len()
            ),
        ));
    }
    let mut seen = HashSet::new();
    let mut coils = Vec::with_capacity(sections.len());
    for (i, c) in sections.iter().enumerate() {
        let at = |key: &str| format!("coils[{i}].{key}");
        check_name(ctx, &at("name"), &c.name, &mut seen)?;
        if !finite(&c.center_mm) {
            return Err(ctx.err(
                at("center_mm"),
                format!("must be finite, got {}", fmt_vec(&c.center_mm)),
            ));
        }
        let axis = Vector3::from(c.axis);
        let axis = match (finite(&c.axis), axis.try_normalize(1e-12)) {
            (true, Some(unit)) => Unit::new_unchecked(unit),
            _ => {
                return Err(ctx.err(
                    at("axis"),
                    format!("must be a finite non-zero vector, got {}", fmt_vec(&c.axis)),
                ))
            }
        };
        if let Some(turns) = c.turns {
            if !positive(turns) {
                return Err(ctx.err(at("turns"), format!("must be > 0, got {turns}")));
            }
        }
        let winding = match &c.winding {
            None => None,
            Some(w) => {
                let f = |key: &str| format!("coils[{i}].winding.{key}");
                require_positive(ctx, &f("inner_radius_mm"), w.inner_radius_mm)?;
                if !(w.outer_radius_mm.is_finite() && w.outer_radius_mm > w.inner_radius_mm) {
                    return Err(ctx.err(
                        f("outer_radius_mm"),
                        format!(
                            "must exceed inner_radius_mm ({}), got {}",
                            w.inner_radius_mm, w.outer_radius_mm
                        ),
                    ));
                }
                require_positive(ctx, &f("length_mm"), w.length_mm)?;
                for (key, n) in [
                    ("radial_filaments", w.radial_filaments),
                    ("axial_filaments", w.axial_filaments),
                ] {
                    if !(1..=MAX_FILAMENTS).contains(&n) {
                        return Err(ctx.err(
                            f(key),
                            format!("must be within 1..={MAX_FILAMENTS}, got {n}"),
                        ));
                    }
                }
                Some(Winding {
                    inner_radius_m: w.inner_radius_mm / 1e3,
                    outer_radius_m: w.outer_radius_mm / 1e3,
                    length_m: w.length_mm / 1e3,
                    radial_filaments: w.radial_filaments as usize,
                    axial_filaments: w.axial_filaments as usize,
                })
            }
        };
        require_positive(ctx, &at("resistance_ohm"), c.resistance_ohm)?;
        require_positive(ctx, &at("max_current_a"), c.max_current_a)?;
        let continuous_current_a = c.continuous_current_a.unwrap_or(c.max_current_a);
        require_positive(ctx, &at("continuous_current_a"), continuous_current_a)?;
        if continuous_current_a > c.max_current_a {
            return Err(ctx.err(
                at("continuous_current_a"),
                format!(
                    "{continuous_current_a} A is above max_current_a = {} A",
                    c.max_current_a
                ),
            ));
        }
        let thermal_budget_a2s = c
            .thermal_budget_a2s
            .unwrap_or(c.max_current_a * c.max_current_a * DEFAULT_THERMAL_BUDGET_S);
        require_positive(ctx, &at("thermal_budget_a2s"), thermal_budget_a2s)?;
        let saturation = match &c.saturation {
            None => None,
            Some(points) => Some(
                crate::rig::SaturationCurve::new(points)
                    .map_err(|e| ctx.err(at("saturation"), e))?,
            ),
        };
        coils.push(RigCoil {
            name: c.name.clone(),
            center_m: mm3(c.center_mm),
            axis,
            turns: c.turns,
            winding,
            resistance_ohm: c.resistance_ohm,
            max_current_a: c.max_current_a,
            continuous_current_a,
            thermal_budget_a2s,
            saturation,
        });
    }
    Ok(coils)
}

/// `{ kind = "analytic" }` or `{ kind = "maps", dir = "<dir>" }`, either with an optional
/// `calibration = "<file>"`.
fn parse_field_model(
    ctx: &Ctx<'_>,
    field: &str,
    value: &toml::Value,
) -> Result<(FieldModel, Option<PathBuf>), RigFileError> {
    let example = "e.g. { kind = \"maps\", dir = \"../coils\" } or \
                   { kind = \"analytic\", calibration = \"coil_calibration.toml\" }";
    if let toml::Value::String(text) = value {
        return Err(ctx.err(
            field,
            format!("is a table now, not the string {text:?}: {example}"),
        ));
    }
    let section: schema::FieldModelSection = value
        .clone()
        .try_into()
        .map_err(|e| ctx.err(field, format!("{}; {example}", e.message())))?;
    let path = |p: &PathBuf, key: &str| {
        if p.as_os_str().is_empty() {
            Err(ctx.err(format!("{field}.{key}"), "must not be empty"))
        } else {
            Ok(ctx.resolve(p))
        }
    };
    let base = match (section.kind.as_str(), &section.dir) {
        ("analytic", None) => FieldModel::Analytic,
        ("analytic", Some(_)) => {
            return Err(ctx.err(
                format!("{field}.dir"),
                "belongs to kind = \"maps\" (the analytic model needs no maps)",
            ))
        }
        ("maps", Some(dir)) => FieldModel::Maps(path(dir, "dir")?),
        ("maps", None) => {
            return Err(ctx.err(
                format!("{field}.dir"),
                "required by kind = \"maps\": the directory of the maps' coils.toml",
            ))
        }
        (other, _) => {
            return Err(ctx.err(
                format!("{field}.kind"),
                format!("must be \"analytic\" or \"maps\", got {other:?}"),
            ))
        }
    };
    let calibration = section
        .calibration
        .as_ref()
        .map(|c| path(c, "calibration"))
        .transpose()?;
    Ok((base, calibration))
}

/// `base` with the calibration file's corrections, in the rig's coil order.
fn calibrate_field(
    ctx: &Ctx<'_>,
    field: &str,
    base: RigCoilField,
    calibration: Option<&Path>,
    coils: &[RigCoil],
) -> Result<RigCoilField, RigFileError> {
    let Some(path) = calibration else {
        return Ok(base);
    };
    let cal = CoilCalibration::load(path).map_err(|e| ctx.err(field, e.to_string()))?;
    let names: Vec<&str> = coils.iter().map(|c| c.name.as_str()).collect();
    let corrections = cal
        .ordered_for(&names)
        .map_err(|why| ctx.err(field, format!("{}: {why}", path.display())))?;
    Ok(RigCoilField::Calibrated(Arc::new(CalibratedField {
        base,
        corrections,
        background_t: cal.background_t,
    })))
}

fn build_field(
    ctx: &Ctx<'_>,
    field: &str,
    model: &FieldModel,
    coils: &[RigCoil],
) -> Result<RigCoilField, RigFileError> {
    match model {
        FieldModel::Analytic => {
            let mut built = Vec::with_capacity(coils.len());
            for (i, c) in coils.iter().enumerate() {
                let (Some(turns), Some(winding)) = (c.turns, c.winding.as_ref()) else {
                    let missing = if c.turns.is_none() {
                        "turns"
                    } else {
                        "winding"
                    };
                    return Err(ctx.err(
                        format!("coils[{i}].{missing}"),
                        format!("required by the analytic field model ({field})"),
                    ));
                };
                built.push(Coil::from_winding(
                    c.name.clone(),
                    c.center_m,
                    c.axis,
                    winding,
                    turns,
                ));
            }
            Ok(RigCoilField::Analytic(CoilSystem { coils: built }))
        }
        FieldModel::Maps(dir) => {
            let maps = CoilFieldMaps::load(dir).map_err(|e| ctx.err(field, e.to_string()))?;
            let names: Vec<&str> = maps.coils().iter().map(|c| c.name.as_str()).collect();
            if names.len() != coils.len() {
                return Err(ctx.err(
                    "coils",
                    format!(
                        "{} coils, but the field maps in {} hold {} ({})",
                        coils.len(),
                        dir.display(),
                        names.len(),
                        names.join(", ")
                    ),
                ));
            }
            for (i, (c, map_name)) in coils.iter().zip(&names).enumerate() {
                if c.name != *map_name {
                    return Err(ctx.err(
                        format!("coils[{i}].name"),
                        format!(
                            "{:?}, but the field maps in {} have {map_name:?} at index {i} \
                             (coils must be listed in the maps' order)",
                            c.name,
                            dir.display()
                        ),
                    ));
                }
            }
            Ok(RigCoilField::Maps(Arc::new(maps)))
        }
    }
}

fn build_allocation(
    ctx: &Ctx<'_>,
    names: &[String],
    coils: &[RigCoil],
) -> Result<Vec<usize>, RigFileError> {
    if names.is_empty() {
        return Err(ctx.err(
            "electromagnet.allocation_coils",
            "must name at least one coil",
        ));
    }
    let mut ids = Vec::with_capacity(names.len());
    for (k, name) in names.iter().enumerate() {
        let field = format!("electromagnet.allocation_coils[{k}]");
        let Some(id) = coils.iter().position(|c| &c.name == name) else {
            return Err(ctx.err(field, format!("no coil named {name:?} in [[coils]]")));
        };
        if ids.contains(&id) {
            return Err(ctx.err(field, format!("{name:?} is listed twice")));
        }
        ids.push(id);
    }
    Ok(ids)
}

fn build_camera(ctx: &Ctx<'_>, c: &schema::CameraSection) -> Result<RigCamera, RigFileError> {
    if c.width_px == 0 || c.height_px == 0 {
        let key = if c.width_px == 0 {
            "width_px"
        } else {
            "height_px"
        };
        return Err(ctx.err(format!("camera.{key}"), "must be > 0"));
    }
    if u64::from(c.width_px) * u64::from(c.height_px) > ImageGeometry::MAX_PIXELS {
        return Err(ctx.err(
            "camera.width_px",
            format!(
                "{}x{} px exceeds {} pixels",
                c.width_px,
                c.height_px,
                ImageGeometry::MAX_PIXELS
            ),
        ));
    }
    require_positive(ctx, "camera.mm_per_px", c.mm_per_px)?;
    if !finite(&c.origin_mm) {
        return Err(ctx.err(
            "camera.origin_mm",
            format!("must be finite, got {}", fmt_vec(&c.origin_mm)),
        ));
    }
    let geometry = ImageGeometry {
        width_px: c.width_px,
        height_px: c.height_px,
        mm_per_px: c.mm_per_px,
        origin_x_mm: c.origin_mm[0],
        origin_y_mm: c.origin_mm[1],
    };
    let calibration = match &c.calibration {
        Some(section) => Some(build_camera_calibration(ctx, section, &geometry)?),
        None => None,
    };
    Ok(RigCamera {
        geometry,
        pixel_format: match c.pixel_format {
            schema::PixelFormatName::Rgb8 => CameraPixelFormat::Rgb8,
            schema::PixelFormatName::Gray8 => CameraPixelFormat::Gray8,
        },
        calibration,
    })
}

fn build_camera_calibration(
    ctx: &Ctx<'_>,
    c: &schema::CameraCalibrationSection,
    view: &ImageGeometry,
) -> Result<CameraCalibration, RigFileError> {
    let key = |k: &str| format!("camera.calibration.{k}");
    if c.image_width == 0 || c.image_height == 0 {
        return Err(ctx.err(key("image_width"), "the raw image size must be > 0"));
    }
    if u64::from(c.image_width) * u64::from(c.image_height) > ImageGeometry::MAX_PIXELS {
        return Err(ctx.err(
            key("image_width"),
            format!("exceeds {} pixels", ImageGeometry::MAX_PIXELS),
        ));
    }
    let k = &c.camera_matrix;
    let pinhole = finite(k)
        && k[0] > 0.0
        && k[4] > 0.0
        && k[1] == 0.0
        && k[3] == 0.0
        && k[6..] == [0.0, 0.0, 1.0];
    if !pinhole {
        return Err(ctx.err(
            key("camera_matrix"),
            format!(
                "must be [fx, 0, cx, 0, fy, cy, 0, 0, 1] with fx, fy > 0, got {}",
                fmt_vec(k)
            ),
        ));
    }
    if c.distortion_model != "plumb_bob" {
        return Err(ctx.err(
            key("distortion_model"),
            format!(
                "{:?} is not supported; \"plumb_bob\" (k1, k2, p1, p2, k3) is",
                c.distortion_model
            ),
        ));
    }
    let distortion: [f64; 5] = c
        .distortion_coefficients
        .as_slice()
        .try_into()
        .ok()
        .filter(|d: &[f64; 5]| finite(d))
        .ok_or_else(|| {
            ctx.err(
                key("distortion_coefficients"),
                format!(
                    "plumb_bob needs 5 finite numbers (k1, k2, p1, p2, k3), got {}",
                    fmt_vec(&c.distortion_coefficients)
                ),
            )
        })?;
    for (name, value) in [
        ("reprojection_error_px", c.reprojection_error_px),
        ("registration_residual_mm", c.registration_residual_mm),
    ] {
        if value.is_some_and(|v| !(v.is_finite() && v >= 0.0)) {
            return Err(ctx.err(key(name), "must be finite and >= 0"));
        }
    }
    if let Some(h) = &c.image_to_world_mm {
        check_registration(c, h, view).map_err(|m| ctx.err(key("image_to_world_mm"), m))?;
    }
    Ok(CameraCalibration {
        image_width: c.image_width,
        image_height: c.image_height,
        camera_matrix: *k,
        distortion_coefficients: distortion,
        reprojection_error_px: c.reprojection_error_px,
        image_to_world_mm: c.image_to_world_mm,
        registration_residual_mm: c.registration_residual_mm,
    })
}

/// The homography must be invertible and bring the whole canonical view into the raw image
/// (undistorted pixels, with a pixel of slack): a view partly outside the camera's image would
/// show vision a phantom that is not there.
fn check_registration(
    c: &schema::CameraCalibrationSection,
    h: &[f64; 9],
    view: &ImageGeometry,
) -> Result<(), String> {
    let m = nalgebra::Matrix3::from_row_slice(h);
    let inverse = m
        .try_inverse()
        .filter(|i| h.iter().all(|v| v.is_finite()) && i.iter().all(|v| v.is_finite()))
        .ok_or_else(|| {
            format!(
                "must be a finite, invertible 3x3 matrix, got {}",
                fmt_vec(h)
            )
        })?;
    let x0 = view.origin_x_mm;
    let y0 = view.origin_y_mm;
    let x1 = x0 + f64::from(view.width_px) * view.mm_per_px;
    let y1 = y0 - f64::from(view.height_px) * view.mm_per_px;
    for (x, y) in [(x0, y0), (x1, y0), (x1, y1), (x0, y1)] {
        let p = inverse * nalgebra::Vector3::new(x, y, 1.0);
        let (u, v) = (p.x / p.z, p.y / p.z);
        let inside = p.z.abs() > 1e-12
            && (-1.0..=f64::from(c.image_width) + 1.0).contains(&u)
            && (-1.0..=f64::from(c.image_height) + 1.0).contains(&v);
        if !inside {
            return Err(format!(
                "the canonical view's corner ({x:.2}, {y:.2}) mm falls at pixel ({u:.1}, {v:.1}), \
                 outside the {}x{} px camera image: the registration maps the phantom outside \
                 the image",
                c.image_width, c.image_height
            ));
        }
    }
    Ok(())
}

/// The mask must cover exactly the camera's field of view: its size in pixels is the camera's
/// field of view divided by `mask_mm_per_px` (a whole number within 1e-6 px), and its origin is
/// the camera's within half a camera pixel.
fn mask_geometry(
    ctx: &Ctx<'_>,
    p: &schema::PhantomSection,
    camera: &ImageGeometry,
) -> Result<ImageGeometry, RigFileError> {
    require_positive(ctx, "phantom.mask_mm_per_px", p.mask_mm_per_px)?;
    if !finite(&p.mask_origin_mm) {
        return Err(ctx.err(
            "phantom.mask_origin_mm",
            format!("must be finite, got {}", fmt_vec(&p.mask_origin_mm)),
        ));
    }
    let fov = [
        f64::from(camera.width_px) * camera.mm_per_px,
        f64::from(camera.height_px) * camera.mm_per_px,
    ];
    let mut size = [0u32; 2];
    for (k, extent) in fov.iter().enumerate() {
        let px = extent / p.mask_mm_per_px;
        let whole = px.round();
        if (px - whole).abs() > 1e-6 * px.max(1.0) || whole < 1.0 || whole > f64::from(u32::MAX) {
            return Err(ctx.err(
                "phantom.mask_mm_per_px",
                format!(
                    "the camera's field of view ({:.4} x {:.4} mm) is not a whole number of \
                     {} mm mask pixels ({px:.4} px along {})",
                    fov[0],
                    fov[1],
                    p.mask_mm_per_px,
                    if k == 0 { "x" } else { "y" }
                ),
            ));
        }
        size[k] = whole as u32;
    }
    let tol = 0.5 * camera.mm_per_px;
    if (p.mask_origin_mm[0] - camera.origin_x_mm).abs() > tol
        || (p.mask_origin_mm[1] - camera.origin_y_mm).abs() > tol
    {
        return Err(ctx.err(
            "phantom.mask_origin_mm",
            format!(
                "{} must equal camera.origin_mm [{}, {}] within half a camera pixel",
                fmt_vec(&p.mask_origin_mm),
                camera.origin_x_mm,
                camera.origin_y_mm
            ),
        ));
    }
    let geometry = ImageGeometry {
        width_px: size[0],
        height_px: size[1],
        mm_per_px: p.mask_mm_per_px,
        origin_x_mm: p.mask_origin_mm[0],
        origin_y_mm: p.mask_origin_mm[1],
    };
    geometry
        .validate()
        .map_err(|e| ctx.err("phantom.mask_mm_per_px", e.to_string()))?;
    Ok(geometry)
}

fn build_phantom(
    ctx: &Ctx<'_>,
    p: &schema::PhantomSection,
    camera: &RigCamera,
) -> Result<RigPhantom, RigFileError> {
    let geometry = mask_geometry(ctx, p, &camera.geometry)?;
    let mask_path = ctx.resolve(&p.mask);
    let mask = CanalMask::load_png(&mask_path, &geometry).map_err(|e| {
        let message = match e {
            MaskError::WrongSize { .. } => format!(
                "{e} (the camera's {:.4} x {:.4} mm field of view at phantom.mask_mm_per_px = {})",
                f64::from(geometry.width_px) * geometry.mm_per_px,
                f64::from(geometry.height_px) * geometry.mm_per_px,
                geometry.mm_per_px
            ),
            other => other.to_string(),
        };
        ctx.err("phantom.mask", message)
    })?;

    let mut port_names = HashSet::new();
    let mut port = |kind: &str,
                    i: usize,
                    name: &str,
                    position_mm: [f64; 2],
                    direction: [f64; 2],
                    diameter_mm: f64|
     -> Result<(Vector2<f64>, Unit<Vector2<f64>>), RigFileError> {
        let at = |key: &str| format!("phantom.{kind}[{i}].{key}");
        check_name(ctx, &at("name"), name, &mut port_names)?;
        if !finite(&position_mm) {
            return Err(ctx.err(
                at("position_mm"),
                format!("must be finite, got {}", fmt_vec(&position_mm)),
            ));
        }
        let position = mm2(position_mm);
        if !mask.contains(&position) {
            return Err(ctx.err(
                at("position_mm"),
                format!(
                    "port {name:?} at {} mm is not on a canal pixel of the mask {}",
                    fmt_vec(&position_mm),
                    mask_path.display()
                ),
            ));
        }
        let dir = Vector2::from(direction);
        let dir = match (finite(&direction), dir.try_normalize(1e-12)) {
            (true, Some(unit)) => Unit::new_unchecked(unit),
            _ => {
                return Err(ctx.err(
                    at("direction"),
                    format!(
                        "must be a finite non-zero vector, got {}",
                        fmt_vec(&direction)
                    ),
                ))
            }
        };
        require_positive(ctx, &at("diameter_mm"), diameter_mm)?;
        Ok((position, dir))
    };
    let mut inlets = Vec::with_capacity(p.inlets.len());
    for (i, s) in p.inlets.iter().enumerate() {
        let (mouth_m, direction) = port(
            "inlets",
            i,
            &s.name,
            s.position_mm,
            s.direction,
            s.diameter_mm,
        )?;
        require_positive(ctx, &format!("phantom.inlets[{i}].length_mm"), s.length_mm)?;
        inlets.push(Inlet {
            name: s.name.clone(),
            mouth_m,
            direction,
            diameter_m: s.diameter_mm / 1e3,
            length_m: s.length_mm / 1e3,
        });
    }
    let mut outlets = Vec::with_capacity(p.outlets.len());
    for (i, s) in p.outlets.iter().enumerate() {
        let (mouth_m, direction) = port(
            "outlets",
            i,
            &s.name,
            s.position_mm,
            s.direction,
            s.diameter_mm,
        )?;
        outlets.push(Outlet {
            name: s.name.clone(),
            mouth_m,
            direction,
            diameter_m: s.diameter_mm / 1e3,
        });
    }

    let zones = build_zones(ctx, &p.zones, &mask)?;
    let flow_conditions = build_flow(ctx, &p.flow)?;
    let route = match &p.route {
        None => None,
        Some(r) => {
            let on_canal = |key: &str, v: [f64; 2]| {
                let at = format!("phantom.route.{key}");
                if !finite(&v) {
                    return Err(ctx.err(at, format!("must be finite, got {}", fmt_vec(&v))));
                }
                let p = mm2(v);
                if !mask.contains(&p) {
                    return Err(ctx.err(
                        at,
                        format!(
                            "{} mm is not on a canal pixel of the mask {}",
                            fmt_vec(&v),
                            mask_path.display()
                        ),
                    ));
                }
                Ok(p)
            };
            Some(Route {
                start_m: on_canal("start_mm", r.start_mm)?,
                end_m: on_canal("end_mm", r.end_mm)?,
            })
        }
    };
    let walls = WallField::from_mask(&mask);
    Ok(RigPhantom {
        mask_path,
        mask,
        walls,
        inlets,
        outlets,
        zones,
        flow_conditions,
        route,
    })
}

/// Zones must lie on the phantom: every vertex within the mask's field of view (one camera
/// pixel of slack, so a band may run to the image edge) and at least one canal pixel centre
/// inside the polygon.
fn build_zones(
    ctx: &Ctx<'_>,
    sections: &[schema::ZoneSection],
    mask: &CanalMask,
) -> Result<Vec<Zone>, RigFileError> {
    let g = mask.geometry();
    let lo = Vector2::new(
        g.origin_x_mm,
        g.origin_y_mm - f64::from(g.height_px) * g.mm_per_px,
    );
    let hi = Vector2::new(
        g.origin_x_mm + f64::from(g.width_px) * g.mm_per_px,
        g.origin_y_mm,
    );
    let slack = g.mm_per_px;
    let mut names = HashSet::new();
    let mut zones = Vec::with_capacity(sections.len());
    for (i, z) in sections.iter().enumerate() {
        let at = |key: &str| format!("phantom.zones[{i}].{key}");
        check_name(ctx, &at("name"), &z.name, &mut names)?;
        if z.polygon_mm.len() < 3 {
            return Err(ctx.err(
                at("polygon_mm"),
                format!("needs at least 3 vertices, got {}", z.polygon_mm.len()),
            ));
        }
        for (k, v) in z.polygon_mm.iter().enumerate() {
            if !finite(v) {
                return Err(ctx.err(
                    at("polygon_mm"),
                    format!("vertex {k} is not finite: {}", fmt_vec(v)),
                ));
            }
            let outside = v[0] < lo.x - slack
                || v[0] > hi.x + slack
                || v[1] < lo.y - slack
                || v[1] > hi.y + slack;
            if outside {
                return Err(ctx.err(
                    at("polygon_mm"),
                    format!(
                        "vertex {k} {} mm lies outside the mask's field of view \
                         (x {:.2}..{:.2} mm, y {:.2}..{:.2} mm)",
                        fmt_vec(v),
                        lo.x,
                        hi.x,
                        lo.y,
                        hi.y
                    ),
                ));
            }
        }
        let zone = Zone {
            name: z.name.clone(),
            kind: match z.kind {
                schema::ZoneKindName::HighDisturbance => ZoneKind::HighDisturbance,
                schema::ZoneKindName::Recirculation => ZoneKind::Recirculation,
            },
            polygon_m: z.polygon_mm.iter().map(|v| mm2(*v)).collect(),
            center_m: z.center_mm.map(mm2),
        };
        if !covers_canal(&zone, mask) {
            return Err(ctx.err(
                at("polygon_mm"),
                format!(
                    "zone {:?} covers no canal pixel of the mask (it lies outside the canal)",
                    z.name
                ),
            ));
        }
        if let (Some(raw), Some(center)) = (z.center_mm, zone.center_m) {
            if !finite(&raw) || !zone.contains(&center) || !mask.contains(&center) {
                return Err(ctx.err(
                    at("center_mm"),
                    format!(
                        "{} mm must be a finite point inside zone {:?} and on a canal pixel",
                        fmt_vec(&raw),
                        z.name
                    ),
                ));
            }
        }
        zones.push(zone);
    }
    Ok(zones)
}

/// Whether some canal pixel centre lies in `zone` (scans the polygon's bounding box only).
fn covers_canal(zone: &Zone, mask: &CanalMask) -> bool {
    let g = mask.geometry();
    let (lo, hi) = zone.bounds();
    let (c0, r1) = g.world_to_px(&lo);
    let (c1, r0) = g.world_to_px(&hi);
    let clamp_col = |v: f64| v.clamp(0.0, f64::from(g.width_px) - 1.0) as i64;
    let clamp_row = |v: f64| v.clamp(0.0, f64::from(g.height_px) - 1.0) as i64;
    for row in clamp_row(r0.floor())..=clamp_row(r1.ceil()) {
        for col in clamp_col(c0.floor())..=clamp_col(c1.ceil()) {
            if mask.is_canal_px(col, row) && zone.contains(&g.px_to_world(col as f64, row as f64)) {
                return true;
            }
        }
    }
    false
}

/// A `# key = value` header entry of a flow map, as a number.
fn flow_header_value(text: &str, key: &str) -> Option<f64> {
    text.lines()
        .map_while(|l| l.trim().strip_prefix('#'))
        .filter_map(|kv| kv.split_once('='))
        .find(|(k, _)| k.trim() == key)
        .and_then(|(_, v)| v.trim().parse().ok())
}

fn build_flow(
    ctx: &Ctx<'_>,
    sections: &[schema::FlowSection],
) -> Result<Vec<FlowCondition>, RigFileError> {
    let mut names = HashSet::new();
    let mut out = Vec::with_capacity(sections.len());
    for (i, f) in sections.iter().enumerate() {
        let at = |key: &str| format!("phantom.flow[{i}].{key}");
        check_name(ctx, &at("name"), &f.name, &mut names)?;
        require_positive(ctx, &at("flow_ml_min"), f.flow_ml_min)?;
        require_positive(ctx, &at("viscosity_cp"), f.viscosity_cp)?;
        let map_path = ctx.resolve(&f.map);
        let text = std::fs::read_to_string(&map_path).map_err(|e| {
            ctx.err(
                at("map"),
                format!("cannot read flow map {}: {e}", map_path.display()),
            )
        })?;
        FlowMap::parse(&text).map_err(|e| {
            ctx.err(
                at("map"),
                format!("{} is not a valid flow map: {e}", map_path.display()),
            )
        })?;
        // A map that says which condition it was made for must agree with the rig file.
        for (key, header_key, value) in [
            ("flow_ml_min", "flow_ml_min", f.flow_ml_min),
            ("viscosity_cp", "viscosity_cp", f.viscosity_cp),
        ] {
            if let Some(in_map) = flow_header_value(&text, header_key) {
                if (in_map - value).abs() > 1e-3 * value.abs().max(in_map.abs()) {
                    return Err(ctx.err(
                        at(key),
                        format!(
                            "{value}, but the map {} was made for {header_key} = {in_map}",
                            map_path.display()
                        ),
                    ));
                }
            }
        }
        out.push(FlowCondition {
            name: f.name.clone(),
            map_path,
            flow_ml_min: f.flow_ml_min,
            viscosity_pa_s: f.viscosity_cp * 1e-3,
        });
    }
    Ok(out)
}

fn build_robot(ctx: &Ctx<'_>, r: &schema::RobotSection) -> Result<RobotParams, RigFileError> {
    let robot = RobotParams {
        magnet_moment_am2: r.magnet_moment_am2,
        mass_kg: r.mass_kg,
        added_mass_kg: r.added_mass_kg,
        length_m: r.length_m,
        diameter_m: r.diameter_m,
    };
    robot.validate().map_err(|e| match e {
        RigError::Invalid { field, reason } => ctx.err(field, reason),
    })?;
    Ok(robot)
}
