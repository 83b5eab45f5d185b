//! `fieldgen import`: CFD exports from other tools → millinav flow maps (`.flow.csv`).
//!
//! Accepted inputs (one point per row; scattered points are fine):
//! - ANSYS Fluent "ASCII" or CSV solution export (`File > Export > Solution Data`, cell or node
//!   values): a header row naming the columns, e.g. `cellnumber, x-coordinate, y-coordinate,
//!   z-coordinate, x-velocity, y-velocity, z-velocity`, comma- or whitespace-separated; CFD-Post
//!   style names (`X [ m ]`, `Velocity u [ m s^-1 ]`) work too.
//! - OpenFOAM sampled-plane export: `raw` (`x y z U_x U_y U_z`, optional `#` header, or no
//!   header with exactly those six columns) or `csv` (`x,y,z,U_0,U_1,U_2`, also ParaView's
//!   `Points:0 … U:0 …`).
//!
//! Column names are matched case-insensitively after dropping units in brackets and spaces.
//! Points are converted to metres (`--length-unit`), optionally filtered to one plane
//! (`--plane-mm`), mapped to the camera's (x, y) (`--axes`, `--offset-*-mm`), then resampled on
//! a regular grid by inverse-distance weighting (or nearest neighbour) at the grid nodes that
//! lie in the canal mask; nodes outside the mask (wall) are zero.

use std::path::{Path, PathBuf};

use anyhow::Context;
use fieldmaps::flowmap::FlowMap;
use fieldmaps::mask::CanalMask;
use fieldmaps::phantom::ImageGeometry;
use nalgebra::Vector2;
use thiserror::Error;

#[derive(Debug, Error, PartialEq)]
pub enum ImportError {
    #[error("no header row naming the columns and the rows are not plain `x y z Ux Uy Uz`")]
    NoHeader,
    #[error("no column for {what} (looked for {candidates}); columns found: {found}")]
    MissingColumn {
        what: &'static str,
        candidates: String,
        found: String,
    },
    #[error("line {line}: {message}")]
    BadRow { line: usize, message: String },
    #[error("no data points{0}")]
    NoPoints(&'static str),
    #[error("bad parameter: {0}")]
    BadParameter(String),
}

/// Which exporter wrote the file (only changes what a header-less file is assumed to be).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ExportFormat {
    Auto,
    Fluent,
    Openfoam,
}

/// Length unit of the coordinates in the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LengthUnit {
    M,
    Mm,
}

impl LengthUnit {
    pub fn to_m(self) -> f64 {
        match self {
            LengthUnit::M => 1.0,
            LengthUnit::Mm => 1e-3,
        }
    }
}

/// Unit of the velocities in the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum VelocityUnit {
    #[value(name = "m/s")]
    MPerS,
    #[value(name = "mm/s")]
    MmPerS,
}

impl VelocityUnit {
    pub fn to_mps(self) -> f64 {
        match self {
            VelocityUnit::MPerS => 1.0,
            VelocityUnit::MmPerS => 1e-3,
        }
    }
}

/// Which two file axes are the camera's x and y (the third is the plane normal).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Axes {
    Xy,
    Xz,
    Yz,
}

impl Axes {
    fn indices(self) -> (usize, usize, usize) {
        match self {
            Axes::Xy => (0, 1, 2),
            Axes::Xz => (0, 2, 1),
            Axes::Yz => (1, 2, 0),
        }
    }
}

/// Resampling method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Method {
    /// Inverse-distance weighting (power 2) of the points within the search radius.
    Idw,
    /// The nearest point within the search radius.
    Nearest,
}

/// The parsed table, in file units: coordinates and velocity (missing z columns are 0).
#[derive(Debug, Clone, PartialEq)]
pub struct Table {
    pub position: Vec<[f64; 3]>,
    pub velocity: Vec<[f64; 3]>,
}

fn normalize(name: &str) -> String {
    let mut out = String::new();
    let mut depth = 0;
    for ch in name.trim().trim_matches('"').trim_matches('\'').chars() {
        match ch {
            '[' | '(' => depth += 1,
            ']' | ')' => depth = (depth - 1).max(0),
            c if depth == 0 && !c.is_whitespace() && c != '"' => out.extend(c.to_lowercase()),
            _ => {}
        }
    }
    out
}

const X_NAMES: &[&str] = &[
    "x-coordinate",
    "x",
    "points:0",
    "points_0",
    "coordinatex",
    "x_coordinate",
    "xcoordinate",
    "cellcenters:0",
    "ccx",
];
const Y_NAMES: &[&str] = &[
    "y-coordinate",
    "y",
    "points:1",
    "points_1",
    "coordinatey",
    "y_coordinate",
    "ycoordinate",
    "cellcenters:1",
    "ccy",
];
const Z_NAMES: &[&str] = &[
    "z-coordinate",
    "z",
    "points:2",
    "points_2",
    "coordinatez",
    "z_coordinate",
    "zcoordinate",
    "cellcenters:2",
    "ccz",
];
const U_NAMES: &[&str] = &[
    "x-velocity",
    "velocityu",
    "u",
    "ux",
    "u_x",
    "u:0",
    "u_0",
    "velocity:0",
    "velocity_0",
    "velocityx",
    "x_velocity",
    "xvelocity",
    "vx",
    "velocity[i]",
];
const V_NAMES: &[&str] = &[
    "y-velocity",
    "velocityv",
    "v",
    "uy",
    "u_y",
    "u:1",
    "u_1",
    "velocity:1",
    "velocity_1",
    "velocityy",
    "y_velocity",
    "yvelocity",
    "vy",
    "velocity[j]",
];
const W_NAMES: &[&str] = &[
    "z-velocity",
    "velocityw",
    "w",
    "uz",
    "u_z",
    "u:2",
    "u_2",
    "velocity:2",
    "velocity_2",
    "velocityz",
    "z_velocity",
    "zvelocity",
    "vz",
    "velocity[k]",
];

/// The cells of a text-table row: comma-, semicolon- or whitespace-separated (COMSOL, Fluent,
/// Maxwell and spreadsheet exports all occur).
pub(crate) fn split(line: &str) -> Vec<&str> {
    if line.contains(',') {
        line.split(',').map(str::trim).collect()
    } else if line.contains(';') {
        line.split(';').map(str::trim).collect()
    } else {
        line.split_whitespace().collect()
    }
}

fn is_numeric_row(fields: &[&str]) -> bool {
    !fields.is_empty()
        && fields
            .iter()
            .filter(|f| !f.is_empty())
            .all(|f| f.parse::<f64>().is_ok())
}

/// Parses a Fluent or OpenFOAM export (see the module docs).
pub fn parse_table(text: &str, format: ExportFormat) -> Result<Table, ImportError> {
    let mut header: Option<Vec<String>> = None;
    let mut last_comment: Option<Vec<String>> = None;
    let mut columns: Option<[Option<usize>; 6]> = None;
    let mut table = Table {
        position: Vec::new(),
        velocity: Vec::new(),
    };
    for (n, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if line.is_empty() || line.starts_with('[') {
            continue;
        }
        if let Some(comment) = line.strip_prefix('#') {
            let fields = split(comment);
            if !is_numeric_row(&fields) {
                last_comment = Some(fields.iter().map(|f| normalize(f)).collect());
            }
            continue;
        }
        let fields = split(line);
        if !is_numeric_row(&fields) {
            if columns.is_none() {
                header = Some(fields.iter().map(|f| normalize(f)).collect());
                continue;
            }
            return Err(ImportError::BadRow {
                line: n + 1,
                message: format!("not a row of numbers: {line:?}"),
            });
        }
        if columns.is_none() {
            let names = header.take().or(last_comment.take());
            columns = Some(match names {
                Some(names) => resolve_columns(&names)?,
                None if fields.len() == 6 && format != ExportFormat::Fluent => {
                    [Some(0), Some(1), Some(2), Some(3), Some(4), Some(5)]
                }
                None => return Err(ImportError::NoHeader),
            });
        }
        let cols = columns.as_ref().ok_or(ImportError::NoHeader)?;
        let get = |c: Option<usize>| -> Result<f64, ImportError> {
            let Some(c) = c else { return Ok(0.0) };
            let field = fields.get(c).ok_or_else(|| ImportError::BadRow {
                line: n + 1,
                message: format!("expected at least {} columns, got {}", c + 1, fields.len()),
            })?;
            let v: f64 = field.parse().map_err(|_| ImportError::BadRow {
                line: n + 1,
                message: format!("{field:?} is not a number"),
            })?;
            if v.is_finite() {
                Ok(v)
            } else {
                Err(ImportError::BadRow {
                    line: n + 1,
                    message: format!("non-finite value {field:?}"),
                })
            }
        };
        table
            .position
            .push([get(cols[0])?, get(cols[1])?, get(cols[2])?]);
        table
            .velocity
            .push([get(cols[3])?, get(cols[4])?, get(cols[5])?]);
    }
    if table.position.is_empty() {
        return Err(ImportError::NoPoints(" in the file"));
    }
    Ok(table)
}

fn resolve_columns(names: &[String]) -> Result<[Option<usize>; 6], ImportError> {
    let find = |cands: &[&str]| cands.iter().find_map(|c| names.iter().position(|n| n == c));
    let lists: [(&'static str, &[&str], bool); 6] = [
        ("x coordinate", X_NAMES, true),
        ("y coordinate", Y_NAMES, true),
        ("z coordinate", Z_NAMES, false),
        ("x velocity", U_NAMES, true),
        ("y velocity", V_NAMES, true),
        ("z velocity", W_NAMES, false),
    ];
    let mut out = [None; 6];
    for (k, (what, cands, required)) in lists.iter().enumerate() {
        out[k] = find(cands);
        if out[k].is_none() && *required {
            return Err(ImportError::MissingColumn {
                what,
                candidates: cands.join(" | "),
                found: names.join(", "),
            });
        }
    }
    Ok(out)
}

/// How the file's points become world samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Conversion {
    pub length: LengthUnit,
    pub velocity: VelocityUnit,
    pub axes: Axes,
    /// Keep only points whose out-of-plane coordinate is within `tol` of `value` (m).
    pub plane_m: Option<(f64, f64)>,
    /// Added to the in-plane coordinates after unit conversion, m.
    pub offset_m: Vector2<f64>,
}

impl Default for Conversion {
    fn default() -> Self {
        Self {
            length: LengthUnit::M,
            velocity: VelocityUnit::MPerS,
            axes: Axes::Xy,
            plane_m: None,
            offset_m: Vector2::zeros(),
        }
    }
}

/// World (x, y) points and in-plane velocities, SI.
#[derive(Debug, Clone, PartialEq)]
pub struct Samples {
    pub points: Vec<Vector2<f64>>,
    pub velocities: Vec<Vector2<f64>>,
}

pub fn to_samples(table: &Table, conv: &Conversion) -> Result<Samples, ImportError> {
    let (a, b, n) = conv.axes.indices();
    let (ls, vs) = (conv.length.to_m(), conv.velocity.to_mps());
    let mut s = Samples {
        points: Vec::new(),
        velocities: Vec::new(),
    };
    for (p, v) in table.position.iter().zip(&table.velocity) {
        if let Some((value, tol)) = conv.plane_m {
            if (p[n] * ls - value).abs() > tol {
                continue;
            }
        }
        s.points
            .push(Vector2::new(p[a] * ls, p[b] * ls) + conv.offset_m);
        s.velocities.push(Vector2::new(v[a] * vs, v[b] * vs));
    }
    if s.points.is_empty() {
        return Err(ImportError::NoPoints(
            " on the selected plane (check --plane-mm / --length-unit)",
        ));
    }
    Ok(s)
}

/// The output grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridSpec {
    pub origin_m: Vector2<f64>,
    pub spacing_m: f64,
    pub nx: usize,
    pub ny: usize,
}

impl GridSpec {
    /// The camera view at `spacing_m`, centred like `fieldgen cfd`'s maps.
    pub fn view(geometry: &ImageGeometry, spacing_m: f64) -> Self {
        let w = f64::from(geometry.width_px) * geometry.mm_per_px * 1e-3;
        let h = f64::from(geometry.height_px) * geometry.mm_per_px * 1e-3;
        let nx = (w / spacing_m).floor() as usize + 1;
        let ny = (h / spacing_m).floor() as usize + 1;
        let cx = geometry.origin_x_mm * 1e-3 + 0.5 * w;
        let cy = geometry.origin_y_mm * 1e-3 - 0.5 * h;
        Self {
            origin_m: Vector2::new(
                cx - 0.5 * (nx - 1) as f64 * spacing_m,
                cy - 0.5 * (ny - 1) as f64 * spacing_m,
            ),
            spacing_m,
            nx,
            ny,
        }
    }
}

/// How many grid nodes got a value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ResampleStats {
    /// Nodes inside the mask.
    pub inside: usize,
    /// Inside nodes with no sample within the search radius (left at zero).
    pub unfilled: usize,
}

/// Resamples scattered samples onto `grid`; nodes outside `mask` (when given) are zero.
pub fn resample(
    samples: &Samples,
    grid: &GridSpec,
    mask: Option<&CanalMask>,
    method: Method,
    radius_m: f64,
) -> Result<(FlowMap, ResampleStats), ImportError> {
    if !(radius_m.is_finite() && radius_m > 0.0) {
        return Err(ImportError::BadParameter(
            "search radius must be > 0".into(),
        ));
    }
    if !(grid.spacing_m.is_finite() && grid.spacing_m > 0.0) || grid.nx < 2 || grid.ny < 2 {
        return Err(ImportError::BadParameter(
            "grid must be ≥ 2x2 with spacing > 0".into(),
        ));
    }
    if samples.points.is_empty() {
        return Err(ImportError::NoPoints(""));
    }
    // Bucket the samples (bucket = radius).
    let lo = samples
        .points
        .iter()
        .fold(Vector2::repeat(f64::INFINITY), |a, p| a.inf(p));
    let hi = samples
        .points
        .iter()
        .fold(Vector2::repeat(f64::NEG_INFINITY), |a, p| a.sup(p));
    let bx = (((hi.x - lo.x) / radius_m).floor() as usize + 1).min(4096);
    let by = (((hi.y - lo.y) / radius_m).floor() as usize + 1).min(4096);
    let cell = Vector2::new(
        ((hi.x - lo.x) / bx as f64).max(radius_m),
        ((hi.y - lo.y) / by as f64).max(radius_m),
    );
    let bucket_of = |p: &Vector2<f64>| {
        let i = (((p.x - lo.x) / cell.x).floor().max(0.0) as usize).min(bx - 1);
        let j = (((p.y - lo.y) / cell.y).floor().max(0.0) as usize).min(by - 1);
        (i, j)
    };
    let mut buckets: Vec<Vec<usize>> = vec![Vec::new(); bx * by];
    for (k, p) in samples.points.iter().enumerate() {
        let (i, j) = bucket_of(p);
        buckets[j * bx + i].push(k);
    }
    let mut velocity = Vec::with_capacity(grid.nx * grid.ny);
    let mut stats = ResampleStats {
        inside: 0,
        unfilled: 0,
    };
    for j in 0..grid.ny {
        for i in 0..grid.nx {
            let node = grid.origin_m + Vector2::new(i as f64, j as f64) * grid.spacing_m;
            if mask.is_some_and(|m| !m.contains(&node)) {
                velocity.push(Vector2::zeros());
                continue;
            }
            stats.inside += 1;
            let lo_b = bucket_of(&(node - Vector2::repeat(radius_m)));
            let hi_b = bucket_of(&(node + Vector2::repeat(radius_m)));
            let (mut wsum, mut vsum) = (0.0, Vector2::zeros());
            let mut nearest: Option<(f64, usize)> = None;
            let mut exact = None;
            for bj in lo_b.1..=hi_b.1 {
                for bi in lo_b.0..=hi_b.0 {
                    for &k in &buckets[bj * bx + bi] {
                        let d = (samples.points[k] - node).norm();
                        if d > radius_m {
                            continue;
                        }
                        if d < 1e-12 {
                            exact = Some(k);
                        }
                        if nearest.is_none_or(|(dn, _)| d < dn) {
                            nearest = Some((d, k));
                        }
                        let w = 1.0 / (d * d).max(1e-24);
                        wsum += w;
                        vsum += samples.velocities[k] * w;
                    }
                }
            }
            let v = match (method, exact, nearest) {
                (_, _, None) => {
                    stats.unfilled += 1;
                    Vector2::zeros()
                }
                (_, Some(k), _) => samples.velocities[k],
                (Method::Nearest, None, Some((_, k))) => samples.velocities[k],
                (Method::Idw, None, Some(_)) => vsum / wsum,
            };
            velocity.push(v);
        }
    }
    Ok((
        FlowMap {
            nx: grid.nx,
            ny: grid.ny,
            origin_m: grid.origin_m,
            spacing_m: grid.spacing_m,
            velocity_mps: velocity,
            chamber_peak_mps: None,
        },
        stats,
    ))
}

/// Arguments of `fieldgen import`.
#[derive(Debug, clap::Args)]
pub struct ImportArgs {
    /// The export file (Fluent ASCII/CSV or OpenFOAM raw/CSV).
    pub input: PathBuf,
    /// Rig file: the camera view the map covers and the canal mask.
    #[arg(long)]
    pub rig: PathBuf,
    /// Output flow map (.flow.csv).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, value_enum, default_value = "auto")]
    pub format: ExportFormat,
    /// Unit of the coordinates in the file.
    #[arg(long, value_enum, default_value = "m")]
    pub length_unit: LengthUnit,
    /// Unit of the velocities in the file.
    #[arg(long, value_enum, default_value = "m/s")]
    pub velocity_unit: VelocityUnit,
    /// File axes that are the camera's x and y.
    #[arg(long, value_enum, default_value = "xy")]
    pub axes: Axes,
    /// Keep only points on this plane (out-of-plane coordinate, mm), e.g. 8 for the paper's
    /// control plane when the export holds several planes or a volume.
    #[arg(long)]
    pub plane_mm: Option<f64>,
    /// Tolerance of --plane-mm, mm.
    #[arg(long, default_value_t = 0.25)]
    pub plane_tol_mm: f64,
    /// Added to the file's in-plane coordinates (after unit conversion), mm.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub offset_x_mm: f64,
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub offset_y_mm: f64,
    #[arg(long, value_enum, default_value = "idw")]
    pub method: Method,
    /// Search radius around each grid node, mm.
    #[arg(long, default_value_t = 1.0)]
    pub radius_mm: f64,
    /// Output grid spacing over the rig's camera view, mm.
    #[arg(long, default_value_t = 0.5)]
    pub spacing_mm: f64,
    /// Canal mask PNG (white = canal, the size and scale of the rig's mask) instead of the rig's.
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// Fill every grid node (no canal mask).
    #[arg(long, conflicts_with = "mask")]
    pub no_mask: bool,
}

/// Reads, converts and resamples an export; returns the map and its statistics.
pub fn import_file(
    path: &Path,
    format: ExportFormat,
    conv: &Conversion,
    grid: &GridSpec,
    mask: Option<&CanalMask>,
    method: Method,
    radius_m: f64,
) -> anyhow::Result<(FlowMap, ResampleStats, usize)> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let table =
        parse_table(&text, format).with_context(|| format!("parsing {}", path.display()))?;
    let samples = to_samples(&table, conv)?;
    let (map, stats) = resample(&samples, grid, mask, method, radius_m)?;
    Ok((map, stats, samples.points.len()))
}

pub fn run(args: &ImportArgs) -> anyhow::Result<()> {
    // The rig's own flow maps need not exist yet: this may be what makes one.
    let rig = crate::cfd::load_rig(&args.rig)?;
    let geometry = rig.camera.geometry;
    let mask = match (&args.mask, args.no_mask) {
        (_, true) => None,
        (Some(p), false) => Some(CanalMask::load_png(p, rig.phantom.mask.geometry())?),
        (None, false) => Some(rig.phantom.mask.clone()),
    };
    if !(args.spacing_mm > 0.0 && args.plane_tol_mm >= 0.0) {
        anyhow::bail!("--spacing-mm must be > 0 and --plane-tol-mm ≥ 0");
    }
    let conv = Conversion {
        length: args.length_unit,
        velocity: args.velocity_unit,
        axes: args.axes,
        plane_m: args.plane_mm.map(|z| (z * 1e-3, args.plane_tol_mm * 1e-3)),
        offset_m: Vector2::new(args.offset_x_mm, args.offset_y_mm) * 1e-3,
    };
    let grid = GridSpec::view(&geometry, args.spacing_mm * 1e-3);
    let (map, stats, points) = import_file(
        &args.input,
        args.format,
        &conv,
        &grid,
        mask.as_ref(),
        args.method,
        args.radius_mm * 1e-3,
    )?;
    let header = format!(
        "# generated by: fieldgen import {}\n# points = {points}\n",
        args.input.display()
    );
    std::fs::write(&args.out, header + &map.to_text())
        .with_context(|| format!("writing {}", args.out.display()))?;
    println!(
        "{} points → {}x{} map ({} nodes in the canal, {} without a point within {} mm), peak {:.1} mm/s → {}",
        points,
        map.nx,
        map.ny,
        stats.inside,
        stats.unfilled,
        args.radius_mm,
        map.peak_speed() * 1e3,
        args.out.display()
    );
    if stats.unfilled * 10 > stats.inside {
        eprintln!("warning: over 10 % of canal nodes have no point within --radius-mm; increase it or check --offset/--axes/--length-unit");
    }
    Ok(())
}
