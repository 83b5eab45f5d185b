//! The rig as data: one TOML file (`fieldmaps/rigs/paper.toml`, format in
//! `fieldmaps/rigs/FORMAT.md`) describes the electromagnet, the camera, the phantom and the
//! robot. [`Rig::load`] parses it, validates every value and every file it names, and builds
//! the runtime objects (coil field model, canal mask, zones, ports, limits).
//!
//! Errors name the file and the field: `fieldmaps/rigs/x.toml: coils[3].turns: must be > 0`.
//! Paths inside a rig file are relative to the rig file.

mod schema;
mod zone;

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{Matrix3, Unit, Vector2, Vector3};
use thiserror::Error;

use crate::coils::{Coil, CoilField, CoilSystem, Winding};
use crate::fieldmap::CoilFieldMaps;
use crate::flowmap::FlowMap;
use crate::mask::{CanalMask, MaskError};
use crate::phantom::{ImageGeometry, Inlet, Outlet};
use crate::rig::{CoilLimits, RigError, RobotParams};

pub use zone::{Zone, ZoneKind};

/// Most coils a rig may have. Must equal `shm_schemas::MAX_COILS` (the contract's coil arrays);
/// fieldmaps does not depend on shm_schemas, so a workspace test ties the two.
pub const MAX_RIG_COILS: usize = 16;

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
}

impl CoilField for RigCoilField {
    fn coil_count(&self) -> usize {
        match self {
            RigCoilField::Analytic(system) => system.len(),
            RigCoilField::Maps(maps) => maps.coil_count(),
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
    pub geometry: ImageGeometry,
    pub pixel_format: CameraPixelFormat,
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
    pub inlets: Vec<Inlet>,
    pub outlets: Vec<Outlet>,
    pub zones: Vec<Zone>,
    pub flow_conditions: Vec<FlowCondition>,
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
    pub field_model: FieldModel,
    pub coil_field: RigCoilField,
    /// Total ohmic power over all coils, W.
    pub max_total_power_w: f64,
    /// Indices (into `coils`) the allocation may drive, in the file's order.
    pub allocation_coils: Vec<usize>,
    pub camera: RigCamera,
    pub phantom: RigPhantom,
    pub robot: RobotParams,
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

    /// [`Self::load`] of the committed paper rig ([`paper_rig_path`]).
    pub fn load_paper() -> Result<Self, RigFileError> {
        Self::load(&paper_rig_path())
    }

    /// Parses `text` as the rig file at `path` (relative paths resolve against its directory).
    pub fn parse(text: &str, path: &Path) -> Result<Self, RigFileError> {
        let ctx = Ctx {
            path,
            dir: path.parent().unwrap_or(Path::new("")),
        };
        let file: schema::RigFile = toml::from_str(text).map_err(|e| ctx.toml_error(text, &e))?;
        build(&ctx, file)
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
        let model = match &self.field_model {
            FieldModel::Analytic => "analytic (Biot–Savart)".to_string(),
            FieldModel::Maps(dir) => format!("maps ({})", dir.display()),
        };
        let names = |ids: &[usize]| {
            ids.iter()
                .map(|&i| self.coils[i].name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        };
        let _ = writeln!(s, "rig {} ({})", self.name, self.path.display());
        let _ = writeln!(
            s,
            "coils: {} (max {MAX_RIG_COILS}), field model {model}, total power ≤ {} W",
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

/// Where errors point.
struct Ctx<'a> {
    path: &'a Path,
    dir: &'a Path,
}

impl Ctx<'_> {
    fn err(&self, field: impl Into<String>, message: impl Into<String>) -> RigFileError {
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

    fn toml_error(&self, text: &str, e: &toml::de::Error) -> RigFileError {
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

/// `[name]` / `[[name]]` header of a line, with whether it is an array of tables. Lines of a
/// multi-line array value (`[1.0, 2.0],`) are not headers.
fn header_of(line: &str) -> Option<(String, bool)> {
    let line = line.split('#').next().unwrap_or("").trim();
    let (inner, array) = if let Some(rest) = line.strip_prefix("[[") {
        (rest.strip_suffix("]]")?, true)
    } else {
        (line.strip_prefix('[')?.strip_suffix(']')?, false)
    };
    let inner = inner.trim();
    let first = inner.chars().next()?;
    let key_like = (first.is_ascii_alphabetic() || first == '_')
        && inner
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.' | ' '));
    key_like.then(|| (inner.replace(' ', ""), array))
}

/// Best-effort key path (`coils[3].winding.length_mm`) of the TOML text at byte `offset`, from
/// the table headers above it; for pointing errors from the parser at a field.
fn key_path_at(text: &str, offset: usize) -> String {
    let mut counts = std::collections::HashMap::<String, usize>::new();
    let mut table = String::new();
    let mut last_key: Option<String> = None;
    let mut line_start = 0;
    let indexed = |name: &str, counts: &std::collections::HashMap<String, usize>| {
        let mut out = String::new();
        let mut prefix = String::new();
        for (k, part) in name.split('.').enumerate() {
            if k > 0 {
                prefix.push('.');
                out.push('.');
            }
            prefix.push_str(part);
            out.push_str(part);
            if let Some(n) = counts.get(&prefix) {
                out.push_str(&format!("[{}]", n.saturating_sub(1)));
            }
        }
        out
    };
    for line in text.split_inclusive('\n') {
        let end = line_start + line.len();
        let here = offset >= line_start && offset < end;
        if let Some((name, array)) = header_of(line) {
            if array {
                *counts.entry(name.clone()).or_default() += 1;
            }
            table = indexed(&name, &counts);
            last_key = None;
            if here {
                return table;
            }
        } else {
            let code = line.split('#').next().unwrap_or("");
            if let Some((key, _)) = code.split_once('=') {
                let key = key.trim();
                if !key.is_empty() && !key.starts_with('[') && !key.starts_with('{') {
                    last_key = Some(key.trim_matches('"').to_string());
                }
            }
            if here {
                break;
            }
        }
        line_start = end;
    }
    match (table.is_empty(), last_key) {
        (_, None) => table,
        (true, Some(key)) => key,
        (false, Some(key)) => format!("{table}.{key}"),
    }
}

fn finite(v: &[f64]) -> bool {
    v.iter().all(|x| x.is_finite())
}

fn positive(v: f64) -> bool {
    v.is_finite() && v > 0.0
}

fn fmt_vec(v: &[f64]) -> String {
    let parts: Vec<String> = v.iter().map(|x| format!("{x}")).collect();
    format!("[{}]", parts.join(", "))
}

fn check_name(
    ctx: &Ctx,
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

fn require_positive(ctx: &Ctx, field: &str, v: f64) -> Result<(), RigFileError> {
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

fn build(ctx: &Ctx, file: schema::RigFile) -> Result<Rig, RigFileError> {
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
    let field_model = parse_field_model(ctx, &em.field_model)?;
    let coil_field = build_field(ctx, &field_model, &coils)?;
    require_positive(ctx, "electromagnet.max_total_power_w", em.max_total_power_w)?;
    let allocation_coils = build_allocation(ctx, &em.allocation_coils, &coils)?;
    let camera = build_camera(ctx, &file.camera)?;
    let phantom = build_phantom(ctx, &file.phantom, &camera)?;
    let robot = build_robot(ctx, &file.robot)?;
    Ok(Rig {
        path: ctx.path.to_owned(),
        name: file.name,
        description: file.description,
        coils,
        field_model,
        coil_field,
        max_total_power_w: em.max_total_power_w,
        allocation_coils,
        camera,
        phantom,
        robot,
    })
}

fn build_coils(ctx: &Ctx, sections: &[schema::CoilSection]) -> Result<Vec<RigCoil>, RigFileError> {
    if sections.is_empty() {
        return Err(ctx.err("coils", "a rig needs at least one coil"));
    }
    if sections.len() > MAX_RIG_COILS {
        return Err(ctx.err(
            "coils",
            format!(
                "{} coils, at most {MAX_RIG_COILS} are supported (MAX_RIG_COILS)",
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
        coils.push(RigCoil {
            name: c.name.clone(),
            center_m: mm3(c.center_mm),
            axis,
            turns: c.turns,
            winding,
            resistance_ohm: c.resistance_ohm,
            max_current_a: c.max_current_a,
        });
    }
    Ok(coils)
}

fn parse_field_model(ctx: &Ctx, text: &str) -> Result<FieldModel, RigFileError> {
    let field = "electromagnet.field_model";
    match text.trim() {
        "analytic" => Ok(FieldModel::Analytic),
        other => match other.strip_prefix("maps:") {
            Some(dir) if !dir.trim().is_empty() => {
                Ok(FieldModel::Maps(ctx.resolve(Path::new(dir.trim()))))
            }
            _ => Err(ctx.err(
                field,
                format!("must be \"analytic\" or \"maps:<dir>\", got {text:?}"),
            )),
        },
    }
}

fn build_field(
    ctx: &Ctx,
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
                        "required by the analytic field model",
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
            let field = "electromagnet.field_model";
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
    ctx: &Ctx,
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

fn build_camera(ctx: &Ctx, c: &schema::CameraSection) -> Result<RigCamera, RigFileError> {
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
    Ok(RigCamera {
        geometry: ImageGeometry {
            width_px: c.width_px,
            height_px: c.height_px,
            mm_per_px: c.mm_per_px,
            origin_x_mm: c.origin_mm[0],
            origin_y_mm: c.origin_mm[1],
        },
        pixel_format: match c.pixel_format {
            schema::PixelFormatName::Rgb8 => CameraPixelFormat::Rgb8,
            schema::PixelFormatName::Gray8 => CameraPixelFormat::Gray8,
        },
    })
}

/// The mask must cover exactly the camera's field of view: its size in pixels is the camera's
/// field of view divided by `mask_mm_per_px` (a whole number within 1e-6 px), and its origin is
/// the camera's within half a camera pixel.
fn mask_geometry(
    ctx: &Ctx,
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
    ctx: &Ctx,
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
    Ok(RigPhantom {
        mask_path,
        mask,
        inlets,
        outlets,
        zones,
        flow_conditions,
    })
}

/// Zones must lie on the phantom: every vertex within the mask's field of view (one camera
/// pixel of slack, so a band may run to the image edge) and at least one canal pixel centre
/// inside the polygon.
fn build_zones(
    ctx: &Ctx,
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
    ctx: &Ctx,
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

fn build_robot(ctx: &Ctx, r: &schema::RobotSection) -> Result<RobotParams, RigFileError> {
    let robot = RobotParams {
        magnet_moment_am2: r.magnet_moment_am2,
        mass_kg: r.mass_kg,
        added_mass_kg: r.added_mass_kg,
        length_m: r.length_m,
        diameter_m: r.diameter_m,
    };
    robot.validate().map_err(|e| match e {
        RigError::Invalid { field, reason } => ctx.err(field, reason),
        other => ctx.err("robot", other.to_string()),
    })?;
    Ok(robot)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn key_paths_follow_headers() {
        let text = "format = 1\n[electromagnet]\nfield_model = 2\n[[coils]]\nname = 1\n\
                    [[coils]]\nname = 2\nturns = 3\n[coils.winding]\nlength_mm = 4\n\
                    [phantom]\n[[phantom.zones]]\npolygon_mm = [\n  [1.0, 2.0],\n  [3.0, 4.0],\n]\n";
        let at = |needle: &str| key_path_at(text, text.find(needle).unwrap());
        assert_eq!(at("format"), "format");
        assert_eq!(at("field_model"), "electromagnet.field_model");
        assert_eq!(at("name = 1"), "coils[0].name");
        assert_eq!(at("turns"), "coils[1].turns");
        assert_eq!(at("length_mm"), "coils[1].winding.length_mm");
        assert_eq!(at("[3.0"), "phantom.zones[0].polygon_mm");
        assert_eq!(at("[[phantom.zones]]"), "phantom.zones[0]");
    }
}
