//! `fieldgen fit-coils`: a coil calibration from gaussmeter measurements.
//!
//! Each measurement row gives a probe position, the current in every coil and the measured
//! field. The model is linear in its unknowns, B(p, I) = Σ_k M_k I_k B̃_k(p) + B₀, with B̃_k the
//! rig's base model (analytic or maps, per ampere), M_k a gain g_k·𝟙 or a free 3 × 3 matrix, and
//! B₀ a uniform background field. The unknowns come from linear least squares with faer:
//! a thin SVD of the column-scaled design matrix decides the rank (and names the coils that the
//! current patterns cannot separate) and gives the parameters' standard errors; a
//! column-pivoted QR solves. Rows whose residual is far outside the noise (robust scale from the
//! median) are reported by line and refitted without; rows held out (every k-th, or a second
//! file) verify the fit.
//!
//! Measurement file (CSV, `#` comments, header row, columns in any order, names
//! case-insensitive): `x_mm, y_mm, z_mm` (or `_m`), one `I_<coil>_A` per coil of the rig, and
//! `Bx_mT, By_mT, Bz_mT` (or `_T`, `_G`, `_uT`). Documented in `fieldmaps/coils/CALIBRATION.md`.

use std::path::{Path, PathBuf};

use anyhow::Context;
use faer::prelude::*;
use faer::Mat;
use fieldmaps::calibration::{CoilCalibration, CoilCorrection, CorrectionModel};
use fieldmaps::coils::CoilField;
use fieldmaps::rigfile::{Rig, RigCoilField};
use nalgebra::{Matrix3, Vector3};
use thiserror::Error;

/// Singular values below this fraction of the largest (column-scaled design) count as zero.
const RANK_TOLERANCE: f64 = 1e-9;
/// Median of |r| for a 3-vector of unit-variance Gaussian noise (chi with 3 degrees of freedom).
const CHI3_MEDIAN: f64 = 1.5382;
/// Outlier rejection rounds before the outlier set must have settled.
const MAX_OUTLIER_ROUNDS: usize = 8;

#[derive(Debug, Error, PartialEq)]
pub enum FitError {
    #[error("{file}: {message}")]
    Input { file: String, message: String },
    #[error("{file}: line {line}: {message}")]
    Row {
        file: String,
        line: u64,
        message: String,
    },
    #[error("rank-deficient measurements: {0}")]
    RankDeficient(String),
    #[error("{0}")]
    Other(String),
}

/// One measurement, SI.
#[derive(Debug, Clone, PartialEq)]
pub struct Measurement {
    /// Line in its file (1 = header).
    pub line: u64,
    pub position_m: Vector3<f64>,
    /// Current in every rig coil, A, in the rig's coil order.
    pub currents_a: Vec<f64>,
    pub field_t: Vector3<f64>,
}

fn length_scale(unit: &str) -> Option<f64> {
    match unit {
        "m" => Some(1.0),
        "mm" => Some(1e-3),
        _ => None,
    }
}

fn field_scale(unit: &str) -> Option<f64> {
    match unit {
        "t" => Some(1.0),
        "mt" => Some(1e-3),
        "ut" => Some(1e-6),
        "g" => Some(1e-4),
        _ => None,
    }
}

/// Reads a measurement file for the coils `coil_names` (the rig's order).
pub fn read_measurements(path: &Path, coil_names: &[&str]) -> Result<Vec<Measurement>, FitError> {
    let file = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| FitError::Input {
        file: file.clone(),
        message: format!("cannot read: {e}"),
    })?;
    parse_measurements(&text, &file, coil_names)
}

/// [`read_measurements`] of text; `file` names it in errors.
pub fn parse_measurements(
    text: &str,
    file: &str,
    coil_names: &[&str],
) -> Result<Vec<Measurement>, FitError> {
    let input = |message: String| FitError::Input {
        file: file.to_string(),
        message,
    };
    let mut reader = csv::ReaderBuilder::new()
        .comment(Some(b'#'))
        .trim(csv::Trim::All)
        .from_reader(text.as_bytes());
    let headers = reader
        .headers()
        .map_err(|e| input(format!("cannot read the header row: {e}")))?
        .clone();
    let lower: Vec<String> = headers.iter().map(|h| h.to_ascii_lowercase()).collect();
    // Position and field columns: (column, scale to SI), one unit per group.
    let find_group = |stems: [&str; 3],
                      scale: fn(&str) -> Option<f64>,
                      what: &str,
                      example: &str|
     -> Result<[(usize, f64); 3], FitError> {
        let mut found = [(0usize, 0.0f64); 3];
        let mut units: Vec<(String, String)> = Vec::new();
        for (k, stem) in stems.iter().enumerate() {
            let hit = lower.iter().enumerate().find_map(|(col, h)| {
                let unit = h.strip_prefix(stem)?.strip_prefix('_')?;
                scale(unit).map(|s| (col, s, unit.to_string()))
            });
            let Some((col, s, unit)) = hit else {
                return Err(input(format!(
                    "no column for {what} {stem} (e.g. `{}`); columns found: {}",
                    example.replace('#', stem),
                    headers.iter().collect::<Vec<_>>().join(", ")
                )));
            };
            found[k] = (col, s);
            units.push((headers[col].to_string(), unit));
        }
        if units.iter().any(|(_, u)| *u != units[0].1) {
            return Err(input(format!(
                "{what} columns use different units ({}); use one unit for all three",
                units
                    .iter()
                    .map(|(h, _)| h.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            )));
        }
        Ok(found)
    };
    let position = find_group(["x", "y", "z"], length_scale, "position", "#_mm")?;
    let field = find_group(["bx", "by", "bz"], field_scale, "field", "#_mT")?;
    let mut current_cols = Vec::with_capacity(coil_names.len());
    for name in coil_names {
        let want = format!("i_{}_a", name.to_ascii_lowercase());
        match lower.iter().position(|h| *h == want) {
            Some(col) => current_cols.push(col),
            None => {
                return Err(input(format!(
                    "coil {name}: no current column `I_{name}_A` (give every coil of the rig a \
                     column, zeros where it was off)"
                )))
            }
        }
    }
    let known: Vec<String> = coil_names
        .iter()
        .map(|n| format!("i_{}_a", n.to_ascii_lowercase()))
        .collect();
    if let Some(extra) = lower
        .iter()
        .zip(headers.iter())
        .find(|(h, _)| h.starts_with("i_") && !known.contains(h))
    {
        return Err(input(format!(
            "current column `{}` names no coil of the rig ({})",
            extra.1,
            coil_names.join(", ")
        )));
    }
    let mut rows = Vec::new();
    for record in reader.records() {
        let record = record.map_err(|e| input(format!("bad CSV: {e}")))?;
        let line = record.position().map_or(0, |p| p.line());
        let value = |col: usize| -> Result<f64, FitError> {
            let raw = record.get(col).unwrap_or("");
            raw.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| FitError::Row {
                    file: file.to_string(),
                    line,
                    message: format!("column `{}`: {raw:?} is not a finite number", &headers[col]),
                })
        };
        let vec3 = |cols: &[(usize, f64); 3]| -> Result<Vector3<f64>, FitError> {
            Ok(Vector3::new(
                value(cols[0].0)? * cols[0].1,
                value(cols[1].0)? * cols[1].1,
                value(cols[2].0)? * cols[2].1,
            ))
        };
        rows.push(Measurement {
            line,
            position_m: vec3(&position)?,
            currents_a: current_cols
                .iter()
                .map(|&c| value(c))
                .collect::<Result<_, _>>()?,
            field_t: vec3(&field)?,
        });
    }
    if rows.is_empty() {
        return Err(input("no measurement rows".into()));
    }
    Ok(rows)
}

/// What to fit.
#[derive(Debug, Clone)]
pub struct FitOptions {
    pub model: CorrectionModel,
    pub background: bool,
    /// Coils kept at the base model (identity correction), e.g. coils never driven.
    pub unfitted: Vec<String>,
    /// A row is an outlier when its residual exceeds this many robust standard deviations…
    pub outlier_sigmas: f64,
    /// …and this floor, T (the probe's resolution: a perfect fit has no outliers).
    pub outlier_floor_t: f64,
    /// Report outliers but keep them in the fit.
    pub keep_outliers: bool,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            model: CorrectionModel::Gain,
            background: true,
            unfitted: Vec::new(),
            outlier_sigmas: 5.0,
            outlier_floor_t: 0.05e-3,
            keep_outliers: false,
        }
    }
}

/// Residual statistics of a set of rows, T.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorStats {
    pub rows: usize,
    /// RMS of |B_measured − B_model|.
    pub rms_t: f64,
    pub max_t: f64,
    /// `rms_t` relative to the RMS of |B_measured|.
    pub relative: f64,
}

impl ErrorStats {
    fn of(residuals: &[f64], measured: &[f64]) -> Self {
        let rms = |v: &[f64]| (v.iter().map(|r| r * r).sum::<f64>() / v.len().max(1) as f64).sqrt();
        let rms_t = rms(residuals);
        let rms_b = rms(measured);
        Self {
            rows: residuals.len(),
            rms_t,
            max_t: residuals.iter().copied().fold(0.0, f64::max),
            relative: if rms_b > 0.0 { rms_t / rms_b } else { 0.0 },
        }
    }

    pub fn describe(&self) -> String {
        format!(
            "{} rows, RMS {:.4} mT ({:.3} % of the RMS field), max {:.4} mT",
            self.rows,
            self.rms_t * 1e3,
            self.relative * 100.0,
            self.max_t * 1e3
        )
    }
}

/// A row the fit left out as an outlier.
#[derive(Debug, Clone, PartialEq)]
pub struct Outlier {
    pub line: u64,
    pub residual_t: f64,
    pub threshold_t: f64,
}

/// The fit and how well it holds.
#[derive(Debug, Clone)]
pub struct FitResult {
    pub calibration: CoilCalibration,
    /// Standard error of each coil's gain (gain model; the matrix diagonal's mean otherwise).
    pub gain_std_error: Vec<f64>,
    pub background_std_error_t: Vector3<f64>,
    pub fit: ErrorStats,
    /// The base model (no calibration) on the same rows.
    pub fit_uncalibrated: ErrorStats,
    pub outliers: Vec<Outlier>,
    pub outliers_kept: bool,
}

/// The base field of every coil at every row's position (per ampere), checked to be defined.
fn base_fields<F: CoilField + ?Sized>(
    base: &F,
    rows: &[Measurement],
    inside: impl Fn(&Vector3<f64>) -> bool,
    file: &str,
) -> Result<Vec<Vec<Vector3<f64>>>, FitError> {
    rows.iter()
        .map(|r| {
            if !inside(&r.position_m) {
                return Err(FitError::Row {
                    file: file.to_string(),
                    line: r.line,
                    message: format!(
                        "position ({:.1}, {:.1}, {:.1}) mm is outside the field model's grid",
                        r.position_m.x * 1e3,
                        r.position_m.y * 1e3,
                        r.position_m.z * 1e3
                    ),
                });
            }
            Ok((0..base.coil_count())
                .map(|k| base.field_per_amp(k, &r.position_m))
                .collect())
        })
        .collect()
}

/// Parameter layout of the linear model.
struct Layout {
    /// Per coil: first parameter index, or None when unfitted.
    coil_offset: Vec<Option<usize>>,
    per_coil: usize,
    background_offset: Option<usize>,
    count: usize,
}

impl Layout {
    fn new(coil_count: usize, fitted: &[bool], options: &FitOptions) -> Self {
        let per_coil = match options.model {
            CorrectionModel::Gain => 1,
            CorrectionModel::Matrix => 9,
        };
        let mut next = 0;
        let coil_offset = (0..coil_count)
            .map(|k| {
                fitted[k].then(|| {
                    next += per_coil;
                    next - per_coil
                })
            })
            .collect();
        let background_offset = options.background.then(|| {
            next += 3;
            next - 3
        });
        Self {
            coil_offset,
            per_coil,
            background_offset,
            count: next,
        }
    }

    /// The 3 design rows of one measurement, and the part of the field the fixed (unfitted)
    /// coils explain.
    fn rows(&self, currents: &[f64], base: &[Vector3<f64>]) -> (Vec<[f64; 3]>, Vector3<f64>) {
        let mut a = vec![[0.0; 3]; self.count];
        let mut fixed = Vector3::zeros();
        for (k, (&i, b)) in currents.iter().zip(base).enumerate() {
            let contribution = b * i;
            match self.coil_offset[k] {
                None => fixed += contribution,
                Some(o) if self.per_coil == 1 => {
                    for r in 0..3 {
                        a[o][r] = contribution[r];
                    }
                }
                Some(o) => {
                    // B_r += Σ_c M[r][c] · contribution[c]; parameter o + 3r + c.
                    for r in 0..3 {
                        for c in 0..3 {
                            a[o + 3 * r + c][r] = contribution[c];
                        }
                    }
                }
            }
        }
        if let Some(o) = self.background_offset {
            for r in 0..3 {
                a[o + r][r] = 1.0;
            }
        }
        (a, fixed)
    }

    fn calibration(&self, x: &[f64], names: &[String], model: CorrectionModel) -> CoilCalibration {
        let corrections = self
            .coil_offset
            .iter()
            .map(|o| match (o, model) {
                (None, CorrectionModel::Gain) => CoilCorrection::Gain(1.0),
                (None, CorrectionModel::Matrix) => CoilCorrection::Matrix(Matrix3::identity()),
                (Some(o), CorrectionModel::Gain) => CoilCorrection::Gain(x[*o]),
                (Some(o), CorrectionModel::Matrix) => {
                    CoilCorrection::Matrix(Matrix3::from_fn(|r, c| x[o + 3 * r + c]))
                }
            })
            .collect();
        CoilCalibration {
            model,
            coil_names: names.to_vec(),
            corrections,
            background_t: self
                .background_offset
                .map_or(Vector3::zeros(), |o| Vector3::new(x[o], x[o + 1], x[o + 2])),
        }
    }

    /// What parameter `j` is, for messages.
    fn describe(&self, j: usize, names: &[String]) -> String {
        if let Some(o) = self.background_offset {
            if (o..o + 3).contains(&j) {
                return "the background field".into();
            }
        }
        self.coil_offset
            .iter()
            .position(|o| o.is_some_and(|o| (o..o + self.per_coil).contains(&j)))
            .map_or_else(
                || format!("parameter {j}"),
                |k| format!("coil {}", names[k]),
            )
    }
}

/// Least squares on `rows` (indices into the data): parameters and their standard errors.
fn solve(
    layout: &Layout,
    data: &[Measurement],
    base: &[Vec<Vector3<f64>>],
    rows: &[usize],
    names: &[String],
) -> Result<(Vec<f64>, Vec<f64>), FitError> {
    let n = layout.count;
    let m = 3 * rows.len();
    if m < n {
        return Err(FitError::RankDeficient(format!(
            "{} rows give {m} equations for {n} unknowns; measure at least {} rows",
            rows.len(),
            n.div_ceil(3)
        )));
    }
    let mut a = Mat::<f64>::zeros(m, n);
    let mut b = Mat::<f64>::zeros(m, 1);
    for (q, &i) in rows.iter().enumerate() {
        let (design, fixed) = layout.rows(&data[i].currents_a, &base[i]);
        for r in 0..3 {
            b[(3 * q + r, 0)] = data[i].field_t[r] - fixed[r];
            for (j, col) in design.iter().enumerate() {
                a[(3 * q + r, j)] = col[r];
            }
        }
    }
    // Unit-norm columns: field-per-amp columns (mT) and background columns (1) on one scale.
    let scale: Vec<f64> = (0..n)
        .map(|j| {
            let norm = (0..m).map(|i| a[(i, j)].powi(2)).sum::<f64>().sqrt();
            if norm > 0.0 {
                norm
            } else {
                1.0
            }
        })
        .collect();
    for (j, s) in scale.iter().enumerate() {
        for i in 0..m {
            a[(i, j)] /= s;
        }
    }
    let svd = a
        .thin_svd()
        .map_err(|e| FitError::Other(format!("SVD failed: {e:?}")))?;
    let s = svd.S().column_vector();
    let v = svd.V();
    let s_max = s[0];
    let weak: Vec<usize> = (0..n).filter(|&k| s[k] <= RANK_TOLERANCE * s_max).collect();
    if !weak.is_empty() {
        let mut involved: Vec<String> = Vec::new();
        for &k in &weak {
            for j in 0..n {
                let what = layout.describe(j, names);
                if v[(j, k)].abs() > 0.2 && !involved.contains(&what) {
                    involved.push(what);
                }
            }
        }
        return Err(FitError::RankDeficient(format!(
            "the current patterns cannot separate {} ({} of {n} parameters undetermined); \
             measure with each coil driven alone or in patterns that are not proportional, or \
             keep a never-driven coil at its model with --unfitted",
            involved.join(", "),
            weak.len()
        )));
    }
    let x_scaled = a.col_piv_qr().solve_lstsq(&b);
    let x: Vec<f64> = (0..n).map(|j| x_scaled[(j, 0)] / scale[j]).collect();
    // Residual variance per equation; Cov(x_scaled) = σ² V S⁻² Vᵀ.
    let mut sse = 0.0;
    for i in 0..m {
        let fit: f64 = (0..n).map(|j| a[(i, j)] * x_scaled[(j, 0)]).sum();
        sse += (b[(i, 0)] - fit).powi(2);
    }
    let sigma2 = if m > n { sse / (m - n) as f64 } else { 0.0 };
    let std_error = (0..n)
        .map(|j| {
            let var: f64 = (0..n).map(|k| (v[(j, k)] / s[k]).powi(2)).sum();
            (sigma2 * var).sqrt() / scale[j]
        })
        .collect();
    Ok((x, std_error))
}

/// |residual| of every row under `calibration` on top of the base fields.
pub fn residuals(
    calibration_field: impl Fn(usize, &[Vector3<f64>]) -> Vec<Vector3<f64>>,
    background: Vector3<f64>,
    data: &[Measurement],
    base: &[Vec<Vector3<f64>>],
) -> Vec<f64> {
    data.iter()
        .enumerate()
        .map(|(i, row)| {
            let fields = calibration_field(i, &base[i]);
            let model: Vector3<f64> = fields
                .iter()
                .zip(&row.currents_a)
                .map(|(b, &c)| b * c)
                .sum::<Vector3<f64>>()
                + background;
            (row.field_t - model).norm()
        })
        .collect()
}

fn calibrated_residuals(
    cal: &CoilCalibration,
    data: &[Measurement],
    base: &[Vec<Vector3<f64>>],
) -> Vec<f64> {
    residuals(
        |_, fields| {
            fields
                .iter()
                .zip(&cal.corrections)
                .map(|(b, c)| c.apply(*b, Matrix3::zeros()).0)
                .collect()
        },
        cal.background_t,
        data,
        base,
    )
}

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n == 0 {
        0.0
    } else if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    }
}

/// The base model the calibration corrects: the rig's control model without its calibration.
pub fn base_model(rig: &Rig) -> &RigCoilField {
    rig.coil_field.base()
}

/// Whether `p` is where the base model is defined (inside the grid for maps).
pub fn model_covers(field: &RigCoilField, p: &Vector3<f64>) -> bool {
    match field {
        RigCoilField::Maps(maps) => maps.try_field_and_gradient_per_amp(0, p).is_ok(),
        RigCoilField::Calibrated(c) => model_covers(&c.base, p),
        RigCoilField::Analytic(_) => true,
    }
}

/// Fits the calibration of `base` (coil names `names`) to `data` (`file` names it in errors).
pub fn fit<F: CoilField + ?Sized>(
    base: &F,
    covers: impl Fn(&Vector3<f64>) -> bool,
    names: &[String],
    data: &[Measurement],
    file: &str,
    options: &FitOptions,
) -> Result<FitResult, FitError> {
    for name in &options.unfitted {
        if !names.contains(name) {
            return Err(FitError::Other(format!(
                "--unfitted {name}: no such coil ({})",
                names.join(", ")
            )));
        }
    }
    let fields = base_fields(base, data, covers, file)?;
    let fitted: Vec<bool> = names
        .iter()
        .enumerate()
        .map(|(k, name)| {
            !options.unfitted.contains(name) && data.iter().any(|r| r.currents_a[k] != 0.0)
        })
        .collect();
    if let Some(k) = (0..names.len()).find(|&k| !fitted[k] && !options.unfitted.contains(&names[k]))
    {
        return Err(FitError::RankDeficient(format!(
            "coil {} carries no current in any row, so its correction cannot be fitted; drive it \
             in some rows, or keep it at its model with --unfitted {}",
            names[k], names[k]
        )));
    }
    let layout = Layout::new(names.len(), &fitted, options);
    let mut used: Vec<usize> = (0..data.len()).collect();
    let mut outliers: Vec<Outlier> = Vec::new();
    let mut rounds = 0;
    let (calibration, std_error) = loop {
        let (x, std_error) = solve(&layout, data, &fields, &used, names)?;
        let calibration = layout.calibration(&x, names, options.model);
        let all = calibrated_residuals(&calibration, data, &fields);
        let mut used_residuals: Vec<f64> = used.iter().map(|&i| all[i]).collect();
        let sigma = median(&mut used_residuals) / CHI3_MEDIAN;
        let threshold = (options.outlier_sigmas * sigma).max(options.outlier_floor_t);
        let now: Vec<Outlier> = all
            .iter()
            .enumerate()
            .filter(|(_, &r)| r > threshold)
            .map(|(i, &r)| Outlier {
                line: data[i].line,
                residual_t: r,
                threshold_t: threshold,
            })
            .collect();
        let settled = now
            .iter()
            .map(|o| o.line)
            .eq(outliers.iter().map(|o| o.line));
        outliers = now;
        rounds += 1;
        if options.keep_outliers || settled || rounds >= MAX_OUTLIER_ROUNDS {
            break (calibration, std_error);
        }
        let excluded: Vec<u64> = outliers.iter().map(|o| o.line).collect();
        used = (0..data.len())
            .filter(|&i| !excluded.contains(&data[i].line))
            .collect();
        if used.len() * 2 < data.len() {
            return Err(FitError::Other(format!(
                "more than half of the rows ({} of {}) disagree with the model beyond {:.3} mT: \
                 wrong units, coil order or sign convention, or the wrong rig?",
                excluded.len(),
                data.len(),
                threshold * 1e3
            )));
        }
    };
    let stats_on = |residual: &[f64], rows: &[usize]| {
        let r: Vec<f64> = rows.iter().map(|&i| residual[i]).collect();
        let b: Vec<f64> = rows.iter().map(|&i| data[i].field_t.norm()).collect();
        ErrorStats::of(&r, &b)
    };
    let calibrated = calibrated_residuals(&calibration, data, &fields);
    let uncalibrated = calibrated_residuals(&CoilCalibration::identity(names), data, &fields);
    let gain_std_error = layout
        .coil_offset
        .iter()
        .map(|o| match (o, options.model) {
            (None, _) => 0.0,
            (Some(o), CorrectionModel::Gain) => std_error[*o],
            (Some(o), CorrectionModel::Matrix) => {
                ((std_error[*o].powi(2) + std_error[o + 4].powi(2) + std_error[o + 8].powi(2))
                    / 9.0)
                    .sqrt()
            }
        })
        .collect();
    let background_std_error_t = layout.background_offset.map_or(Vector3::zeros(), |o| {
        Vector3::new(std_error[o], std_error[o + 1], std_error[o + 2])
    });
    Ok(FitResult {
        fit: stats_on(&calibrated, &used),
        fit_uncalibrated: stats_on(&uncalibrated, &used),
        calibration,
        gain_std_error,
        background_std_error_t,
        outliers,
        outliers_kept: options.keep_outliers,
    })
}

/// Errors of `calibration` (and of the uncalibrated base) on rows it was not fitted to.
pub fn verify<F: CoilField + ?Sized>(
    base: &F,
    covers: impl Fn(&Vector3<f64>) -> bool,
    calibration: &CoilCalibration,
    data: &[Measurement],
    file: &str,
) -> Result<(ErrorStats, ErrorStats), FitError> {
    let fields = base_fields(base, data, covers, file)?;
    let measured: Vec<f64> = data.iter().map(|r| r.field_t.norm()).collect();
    let after = calibrated_residuals(calibration, data, &fields);
    let before = calibrated_residuals(
        &CoilCalibration::identity(&calibration.coil_names),
        data,
        &fields,
    );
    Ok((
        ErrorStats::of(&after, &measured),
        ErrorStats::of(&before, &measured),
    ))
}

/// Command-line arguments of `fieldgen fit-coils`.
#[derive(Debug, clap::Args)]
pub struct FitCoilsArgs {
    /// Rig file whose coils were measured; its control field model (without any calibration it
    /// already has) is the base the calibration corrects. Default: the paper's rig.
    #[arg(long)]
    pub rig: Option<PathBuf>,
    /// Measurement CSV: x_mm, y_mm, z_mm, I_<coil>_A for every coil, Bx_mT, By_mT, Bz_mT.
    #[arg(long)]
    pub measurements: PathBuf,
    /// Calibration file to write (TOML); the rig file references it.
    #[arg(long)]
    pub out: PathBuf,
    /// Correction per coil: a gain, or a 3 × 3 matrix.
    #[arg(long, value_enum, default_value_t = Model::Gain)]
    pub model: Model,
    /// Do not fit a background field (assume none).
    #[arg(long)]
    pub no_background: bool,
    /// Hold out every k-th row to verify the fit (0: none).
    #[arg(long, default_value_t = 5)]
    pub holdout_every: usize,
    /// A separate verification file (same columns), in addition to the held-out rows.
    #[arg(long)]
    pub verify: Option<PathBuf>,
    /// Coils kept at the base model (e.g. never driven during the measurement).
    #[arg(long, value_delimiter = ',')]
    pub unfitted: Vec<String>,
    /// Outlier threshold in robust standard deviations of the residual.
    #[arg(long, default_value_t = 5.0)]
    pub outlier_sigmas: f64,
    /// Outlier threshold floor, mT (about the probe's resolution).
    #[arg(long, default_value_t = 0.05)]
    pub outlier_floor_mt: f64,
    /// Report outliers but keep them in the fit.
    #[arg(long)]
    pub keep_outliers: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Model {
    Gain,
    Matrix,
}

pub fn run(args: &FitCoilsArgs) -> anyhow::Result<()> {
    let rig_path = args
        .rig
        .clone()
        .unwrap_or_else(fieldmaps::rigfile::paper_rig_path);
    let rig = crate::cfd::load_rig(&rig_path)?;
    let names: Vec<String> = rig.coils.iter().map(|c| c.name.clone()).collect();
    let name_refs: Vec<&str> = names.iter().map(String::as_str).collect();
    let base = base_model(&rig);
    let covers = |p: &Vector3<f64>| model_covers(base, p);
    let data = read_measurements(&args.measurements, &name_refs)?;
    let file = args.measurements.display().to_string();
    let (train, held): (Vec<_>, Vec<_>) = data
        .iter()
        .enumerate()
        .partition(|(i, _)| args.holdout_every == 0 || (i + 1) % args.holdout_every != 0);
    let train: Vec<Measurement> = train.into_iter().map(|(_, r)| r.clone()).collect();
    let held: Vec<Measurement> = held.into_iter().map(|(_, r)| r.clone()).collect();
    if !(args.outlier_sigmas > 0.0 && args.outlier_floor_mt >= 0.0) {
        anyhow::bail!("--outlier-sigmas must be > 0 and --outlier-floor-mt >= 0");
    }
    let options = FitOptions {
        model: match args.model {
            Model::Gain => CorrectionModel::Gain,
            Model::Matrix => CorrectionModel::Matrix,
        },
        background: !args.no_background,
        unfitted: args.unfitted.clone(),
        outlier_sigmas: args.outlier_sigmas,
        outlier_floor_t: args.outlier_floor_mt * 1e-3,
        keep_outliers: args.keep_outliers,
    };
    let result = fit(base, covers, &names, &train, &file, &options)?;
    let cal = &result.calibration;
    println!(
        "fitted {} model of {} coils on {} of {} rows ({})",
        match options.model {
            CorrectionModel::Gain => "gain",
            CorrectionModel::Matrix => "3x3 matrix",
        },
        names.len(),
        train.len()
            - if result.outliers_kept {
                0
            } else {
                result.outliers.len()
            },
        data.len(),
        args.measurements.display()
    );
    for (k, name) in names.iter().enumerate() {
        let c = &cal.corrections[k];
        let note = if args.unfitted.contains(name) {
            "  (unfitted: base model)".to_string()
        } else {
            format!("  ± {:.4}", result.gain_std_error[k])
        };
        match c {
            CoilCorrection::Gain(g) => println!("  {name:<12} gain {g:.4}{note}"),
            CoilCorrection::Matrix(m) => println!(
                "  {name:<12} matrix diag ({:.4}, {:.4}, {:.4}), largest off-diagonal {:.4}{note}",
                m[(0, 0)],
                m[(1, 1)],
                m[(2, 2)],
                (0..3)
                    .flat_map(|r| (0..3).filter(move |&c| c != r).map(move |c| (r, c)))
                    .map(|rc| m[rc].abs())
                    .fold(0.0, f64::max)
            ),
        }
    }
    let bg = cal.background_t * 1e3;
    let bg_se = result.background_std_error_t * 1e3;
    println!(
        "  background ({:.4}, {:.4}, {:.4}) mT ± ({:.4}, {:.4}, {:.4})",
        bg.x, bg.y, bg.z, bg_se.x, bg_se.y, bg_se.z
    );
    println!("fit:       {}", result.fit.describe());
    println!(
        "  uncalibrated model on the same rows: {}",
        result.fit_uncalibrated.describe()
    );
    if !result.outliers.is_empty() {
        println!(
            "outliers ({}, {}):",
            result.outliers.len(),
            if result.outliers_kept {
                "kept in the fit (--keep-outliers)"
            } else {
                "left out of the fit"
            }
        );
        for o in &result.outliers {
            println!(
                "  {}: line {}: residual {:.4} mT > {:.4} mT",
                args.measurements.display(),
                o.line,
                o.residual_t * 1e3,
                o.threshold_t * 1e3
            );
        }
    }
    let mut report = toml::Table::new();
    report.insert(
        "measurements".into(),
        args.measurements.display().to_string().into(),
    );
    report.insert("rig".into(), rig.path.display().to_string().into());
    report.insert("rows".into(), (data.len() as i64).into());
    report.insert("fit_rows".into(), (result.fit.rows as i64).into());
    report.insert("fit_rms_mT".into(), (result.fit.rms_t * 1e3).into());
    report.insert(
        "fit_relative_percent".into(),
        (result.fit.relative * 100.0).into(),
    );
    report.insert(
        "outlier_lines".into(),
        toml::Value::Array(
            result
                .outliers
                .iter()
                .map(|o| toml::Value::Integer(o.line as i64))
                .collect(),
        ),
    );
    let mut verify_sets: Vec<(String, Vec<Measurement>)> = Vec::new();
    if !held.is_empty() {
        verify_sets.push((
            format!("held out (every {}th row)", args.holdout_every),
            held,
        ));
    }
    if let Some(path) = &args.verify {
        verify_sets.push((
            path.display().to_string(),
            read_measurements(path, &name_refs)?,
        ));
    }
    for (k, (label, rows)) in verify_sets.iter().enumerate() {
        let (after, before) = verify(base, covers, cal, rows, label)?;
        println!("verify {label}: {}", after.describe());
        println!(
            "  uncalibrated model on the same rows: {}",
            before.describe()
        );
        let key = if k == 0 && args.holdout_every > 0 && !verify_sets[0].1.is_empty() {
            "holdout"
        } else {
            "verify"
        };
        report.insert(format!("{key}_rows"), (after.rows as i64).into());
        report.insert(format!("{key}_rms_mT"), (after.rms_t * 1e3).into());
        report.insert(
            format!("{key}_relative_percent"),
            (after.relative * 100.0).into(),
        );
    }
    if let Some(parent) = args.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("creating {}", parent.display()))?;
    }
    cal.write(&args.out, Some(report))?;
    println!("wrote {}", args.out.display());
    let base_text = match &rig.field_model {
        fieldmaps::rigfile::FieldModel::Analytic => "kind = \"analytic\"".to_string(),
        fieldmaps::rigfile::FieldModel::Maps(dir) => {
            format!("kind = \"maps\", dir = \"{}\"", dir.display())
        }
    };
    println!(
        "use it: in {}, [electromagnet] field_model = {{ {base_text}, calibration = \"{}\" }} \
         (paths relative to the rig file)",
        rig.path.display(),
        args.out.display()
    );
    Ok(())
}

/// Measurement rows from a known field (tests and demos): `patterns` current vectors at
/// `positions`, Gaussian noise of `noise_t` per component from `normal` (a standard normal
/// sampler).
pub fn synthesize<F: CoilField + ?Sized>(
    truth: &F,
    positions: &[Vector3<f64>],
    patterns: &[Vec<f64>],
    noise_t: f64,
    mut normal: impl FnMut() -> f64,
) -> Vec<Measurement> {
    positions
        .iter()
        .zip(patterns)
        .enumerate()
        .map(|(i, (p, currents))| {
            let (b, _) = truth.field_and_gradient(currents, p);
            let noise = Vector3::new(normal(), normal(), normal()) * noise_t;
            Measurement {
                line: i as u64 + 2,
                position_m: *p,
                currents_a: currents.clone(),
                field_t: b + noise,
            }
        })
        .collect()
}

/// Writes rows in the measurement CSV format (positions mm, currents A, field mT).
pub fn write_measurements(
    path: &Path,
    names: &[String],
    rows: &[Measurement],
) -> anyhow::Result<()> {
    let mut w =
        csv::Writer::from_path(path).with_context(|| format!("writing {}", path.display()))?;
    let mut header = vec!["x_mm".to_string(), "y_mm".into(), "z_mm".into()];
    header.extend(names.iter().map(|n| format!("I_{n}_A")));
    header.extend(["Bx_mT".into(), "By_mT".into(), "Bz_mT".into()]);
    w.write_record(&header)?;
    for r in rows {
        let mut rec: Vec<String> = (0..3)
            .map(|k| format!("{}", r.position_m[k] * 1e3))
            .collect();
        rec.extend(r.currents_a.iter().map(|c| format!("{c}")));
        rec.extend((0..3).map(|k| format!("{}", r.field_t[k] * 1e3)));
        w.write_record(&rec)?;
    }
    w.flush()?;
    Ok(())
}
