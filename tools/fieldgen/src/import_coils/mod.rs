//! `fieldgen import-coils`: per-coil field data from FEA exports or field measurements (COMSOL
//! spreadsheet or grid text, ANSYS Maxwell `.fld`, generic CSV; m/cm/mm, T/mT/G) → the map
//! format of `fieldmaps/coils/FORMAT.md`.
//!
//! Every map node gets its field and gradient from one local fit of a magnetic scalar
//! potential, φ = Σ θ_j ψ_j(p − node), over the data points within a radius (weighted, closer
//! points more): ψ_j are the harmonic polynomials of degree 1 to 4 (Δψ = 0), so the fitted field
//! B = ∇φ is exactly curl- and divergence-free and its gradient ∇∇φ exactly symmetric and
//! traceless. Gradient columns in the file enter the same fit as observations of ∇∇φ. Noise is
//! averaged over the neighbourhood instead of differenced.

mod parse;

use std::collections::HashMap;
use std::path::PathBuf;

use anyhow::Context;
use fieldmaps::fieldmap::{CoilFieldMaps, CoilInfo, GridSpec};
use fieldmaps::rigfile::Rig;
use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::{DMatrix, Matrix3, SymmetricEigen, Vector3};
use thiserror::Error;

pub use parse::{parse_export, CoilSamples, UnitHints};

#[derive(Debug, Error, PartialEq)]
pub enum ImportCoilError {
    #[error("{file}: {message}")]
    Format { file: String, message: String },
    #[error("{file}: units: {message}")]
    Units { file: String, message: String },
    #[error("{file}: line {line}: {message}")]
    Row {
        file: String,
        line: u64,
        message: String,
    },
    #[error("{file}: {message}")]
    Coverage { file: String, message: String },
    #[error("{0}")]
    Input(String),
}

/// Positions closer than this are the same point (duplicates, grid detection), m.
const SAME_POINT_M: f64 = 1e-7;

fn key(p: &Vector3<f64>) -> [i64; 3] {
    [0, 1, 2].map(|k| (p[k] / SAME_POINT_M).round() as i64)
}

/// Duplicate points and holes in grid-like data, named.
pub fn check_samples(samples: &CoilSamples, file: &str) -> Result<(), ImportCoilError> {
    let mm =
        |p: &Vector3<f64>| format!("({:.3}, {:.3}, {:.3}) mm", p.x * 1e3, p.y * 1e3, p.z * 1e3);
    let mut seen: HashMap<[i64; 3], u64> = HashMap::with_capacity(samples.positions_m.len());
    for (p, &line) in samples.positions_m.iter().zip(&samples.lines) {
        if let Some(first) = seen.insert(key(p), line) {
            return Err(ImportCoilError::Row {
                file: file.into(),
                line,
                message: format!("duplicate point {} (also on line {first})", mm(p)),
            });
        }
    }
    // Grid-like data (values per axis multiply to about the point count): every node present.
    let mut axes: [Vec<i64>; 3] = Default::default();
    for (k, axis) in axes.iter_mut().enumerate() {
        *axis = seen.keys().map(|q| q[k]).collect();
        axis.sort_unstable();
        axis.dedup();
    }
    let product: usize = axes.iter().map(Vec::len).product();
    let n = samples.positions_m.len();
    if product != n && product <= n + n / 2 {
        let mut missing = Vec::new();
        for &z in &axes[2] {
            for &y in &axes[1] {
                for &x in &axes[0] {
                    if !seen.contains_key(&[x, y, z]) {
                        missing.push(Vector3::new(x as f64, y as f64, z as f64) * SAME_POINT_M);
                    }
                }
            }
        }
        return Err(ImportCoilError::Coverage {
            file: file.into(),
            message: format!(
                "grid with holes: {} of the {} grid points ({} x {} x {}) are missing, e.g. {}",
                missing.len(),
                product,
                axes[0].len(),
                axes[1].len(),
                axes[2].len(),
                missing
                    .iter()
                    .take(4)
                    .map(mm)
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        });
    }
    Ok(())
}

/// A polynomial in (x, y, z): (coefficient, exponents).
#[derive(Debug, Clone)]
struct Poly(Vec<(f64, [i32; 3])>);

impl Poly {
    fn gradient(&self, u: &Vector3<f64>) -> Vector3<f64> {
        let mut g = Vector3::zeros();
        for &(c, e) in &self.0 {
            for k in 0..3 {
                if e[k] > 0 {
                    let mut d = e;
                    d[k] -= 1;
                    g[k] += c * f64::from(e[k]) * monomial(u, d);
                }
            }
        }
        g
    }

    fn hessian(&self, u: &Vector3<f64>) -> Matrix3<f64> {
        let mut h = Matrix3::zeros();
        for &(c, e) in &self.0 {
            for i in 0..3 {
                for j in 0..3 {
                    let mut d = e;
                    let fi = f64::from(d[i]);
                    d[i] -= 1;
                    let fj = f64::from(d[j]);
                    d[j] -= 1;
                    if fi > 0.0 && fj > 0.0 {
                        h[(i, j)] += c * fi * fj * monomial(u, d);
                    }
                }
            }
        }
        h
    }
}

fn monomial(u: &Vector3<f64>, e: [i32; 3]) -> f64 {
    u.x.powi(e[0]) * u.y.powi(e[1]) * u.z.powi(e[2])
}

fn exponents(degree: i32) -> Vec<[i32; 3]> {
    let mut out = Vec::new();
    for a in (0..=degree).rev() {
        for b in (0..=degree - a).rev() {
            out.push([a, b, degree - a - b]);
        }
    }
    out
}

/// The harmonic polynomials of degree 1..=max_degree (3, 5, 7, 9 of them): the null space of
/// the Laplacian on each degree's monomials.
fn harmonic_basis(max_degree: i32) -> Vec<Poly> {
    let mut basis = Vec::new();
    for d in 1..=max_degree {
        let mono = exponents(d);
        if d < 2 {
            basis.extend(mono.iter().map(|&e| Poly(vec![(1.0, e)])));
            continue;
        }
        let lower = exponents(d - 2);
        let mut lap = DMatrix::<f64>::zeros(lower.len(), mono.len());
        for (col, e) in mono.iter().enumerate() {
            for k in 0..3 {
                if e[k] >= 2 {
                    let mut t = *e;
                    t[k] -= 2;
                    let row = lower.iter().position(|l| *l == t).unwrap_or(0);
                    lap[(row, col)] += f64::from(e[k] * (e[k] - 1));
                }
            }
        }
        let eig = SymmetricEigen::new(lap.transpose() * &lap);
        for (k, &value) in eig.eigenvalues.iter().enumerate() {
            if value.abs() < 1e-9 {
                let v = eig.eigenvectors.column(k);
                basis.push(Poly(
                    mono.iter()
                        .zip(v.iter())
                        .filter(|(_, c)| c.abs() > 1e-12)
                        .map(|(e, &c)| (c, *e))
                        .collect(),
                ));
            }
        }
    }
    basis
}

/// Uniform buckets for radius queries.
struct Buckets {
    cell: f64,
    map: HashMap<[i64; 3], Vec<usize>>,
}

impl Buckets {
    fn new(points: &[Vector3<f64>], cell: f64) -> Self {
        let mut map: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
        for (i, p) in points.iter().enumerate() {
            map.entry([0, 1, 2].map(|k| (p[k] / cell).floor() as i64))
                .or_default()
                .push(i);
        }
        Self { cell, map }
    }

    fn within(&self, points: &[Vector3<f64>], c: &Vector3<f64>, r: f64) -> Vec<usize> {
        let reach = (r / self.cell).ceil() as i64;
        let home = [0, 1, 2].map(|k| (c[k] / self.cell).floor() as i64);
        let mut out = Vec::new();
        for dx in -reach..=reach {
            for dy in -reach..=reach {
                for dz in -reach..=reach {
                    if let Some(ids) = self.map.get(&[home[0] + dx, home[1] + dy, home[2] + dz]) {
                        out.extend(ids.iter().filter(|&&i| (points[i] - c).norm() <= r));
                    }
                }
            }
        }
        out
    }
}

/// Median distance to the nearest other point (on up to 400 points).
fn typical_spacing(points: &[Vector3<f64>]) -> f64 {
    let step = (points.len() / 400).max(1);
    let mut lo = f64::INFINITY;
    let mut hi = 0.0f64;
    for p in points {
        for k in 0..3 {
            lo = lo.min(p[k]);
            hi = hi.max(p[k]);
        }
    }
    let guess = ((hi - lo).max(1e-6) / (points.len() as f64).cbrt()).max(1e-6);
    let buckets = Buckets::new(points, guess);
    let mut nn: Vec<f64> = points
        .iter()
        .step_by(step)
        .filter_map(|p| {
            let mut r = guess;
            for _ in 0..8 {
                let d = buckets
                    .within(points, p, r)
                    .iter()
                    .map(|&i| (points[i] - p).norm())
                    .filter(|&d| d > SAME_POINT_M)
                    .fold(f64::INFINITY, f64::min);
                if d.is_finite() {
                    return Some(d);
                }
                r *= 2.0;
            }
            None
        })
        .collect();
    nn.sort_by(f64::total_cmp);
    nn.get(nn.len() / 2).copied().unwrap_or(guess)
}

/// How the local fits are made.
#[derive(Debug, Clone, Copy)]
pub struct FitSettings {
    /// Highest harmonic degree of the potential (1..=4; 4 gives a field exact to 3rd order).
    pub degree: i32,
    /// Neighbourhood radius in units of the data's typical spacing (grown when too few points).
    pub radius_spacings: f64,
}

impl Default for FitSettings {
    fn default() -> Self {
        Self {
            degree: 4,
            radius_spacings: 2.0,
        }
    }
}

/// One coil resampled: 12 values per node in map storage order, and the fit's RMS residual
/// relative to the RMS field of the data used.
pub struct Resampled {
    pub values: Vec<f32>,
    pub fit_rms_relative: f64,
    pub radius_m: f64,
}

/// Field and gradient of one coil's samples at every node of `grid` by local harmonic fits.
pub fn resample(
    samples: &CoilSamples,
    grid: &GridSpec,
    settings: FitSettings,
    file: &str,
    progress: &ProgressBar,
) -> Result<Resampled, ImportCoilError> {
    if !(1..=4).contains(&settings.degree)
        || settings.radius_spacings.is_nan()
        || settings.radius_spacings <= 0.0
    {
        return Err(ImportCoilError::Input(format!(
            "fit degree must be 1..=4 and radius > 0 (got {}, {})",
            settings.degree, settings.radius_spacings
        )));
    }
    let points = &samples.positions_m;
    let mm =
        |p: &Vector3<f64>| format!("({:.2}, {:.2}, {:.2}) mm", p.x * 1e3, p.y * 1e3, p.z * 1e3);
    let (mut lo, mut hi) = (
        Vector3::repeat(f64::INFINITY),
        Vector3::repeat(f64::NEG_INFINITY),
    );
    for p in points {
        lo = lo.inf(p);
        hi = hi.sup(p);
    }
    let basis = harmonic_basis(settings.degree);
    let nb = basis.len();
    let h = typical_spacing(points);
    let radius = settings.radius_spacings * h;
    let buckets = Buckets::new(points, radius);
    let [nx, ny, nz] = grid.shape;
    let mut values = Vec::with_capacity(grid.node_count() * 12);
    let gradients = samples.gradient_t_per_m.as_ref();
    let eqs_per_point = if gradients.is_some() { 12 } else { 3 };
    let (mut residual_ss, mut field_ss) = (0.0, 0.0);
    for iz in 0..nz {
        for iy in 0..ny {
            for ix in 0..nx {
                let c = grid.node(ix, iy, iz);
                if (0..3).any(|k| c[k] < lo[k] - SAME_POINT_M || c[k] > hi[k] + SAME_POINT_M) {
                    return Err(ImportCoilError::Coverage {
                        file: file.into(),
                        message: format!(
                            "map node {} lies outside the data (x {:.1}..{:.1}, y {:.1}..{:.1}, \
                             z {:.1}..{:.1} mm): export a larger region or choose a smaller grid",
                            mm(&c),
                            lo.x * 1e3,
                            hi.x * 1e3,
                            lo.y * 1e3,
                            hi.y * 1e3,
                            lo.z * 1e3,
                            hi.z * 1e3
                        ),
                    });
                }
                // Grow the neighbourhood until the fit is determined (anisotropic or sparse data).
                let mut r = radius;
                let mut solved = None;
                for _ in 0..4 {
                    let near = buckets.within(points, &c, r);
                    if near.len() * eqs_per_point >= 2 * nb {
                        let rows = near.len() * eqs_per_point;
                        let mut a = DMatrix::<f64>::zeros(rows, nb);
                        let mut b = DMatrix::<f64>::zeros(rows, 1);
                        for (q, &i) in near.iter().enumerate() {
                            let u = (points[i] - c) / h;
                            let d = (points[i] - c).norm() / r;
                            let w = ((1.0 - d * d).max(0.0).powi(2) + 1e-3).sqrt();
                            for (j, psi) in basis.iter().enumerate() {
                                let g = psi.gradient(&u);
                                for k in 0..3 {
                                    a[(q * eqs_per_point + k, j)] = w * g[k];
                                }
                                if gradients.is_some() {
                                    let hs = psi.hessian(&u);
                                    for k in 0..9 {
                                        a[(q * eqs_per_point + 3 + k, j)] = w * hs[(k / 3, k % 3)];
                                    }
                                }
                            }
                            for k in 0..3 {
                                b[(q * eqs_per_point + k, 0)] = w * h * samples.field_t[i][k];
                            }
                            if let Some(g) = gradients {
                                for k in 0..9 {
                                    b[(q * eqs_per_point + 3 + k, 0)] =
                                        w * h * h * g[i][(k / 3, k % 3)];
                                }
                            }
                        }
                        let svd = a.clone().svd(true, true);
                        let s_max = svd.singular_values.max();
                        let s_min = svd.singular_values.min();
                        if s_min > 1e-9 * s_max {
                            if let Ok(theta) = svd.solve(&b, 1e-12 * s_max) {
                                let fit = &a * &theta;
                                for k in 0..rows {
                                    residual_ss += (fit[(k, 0)] - b[(k, 0)]).powi(2);
                                    if k % eqs_per_point < 3 {
                                        field_ss += b[(k, 0)].powi(2);
                                    }
                                }
                                solved = Some(theta);
                                break;
                            }
                        }
                    }
                    r *= 1.5;
                }
                let Some(theta) = solved else {
                    return Err(ImportCoilError::Coverage {
                        file: file.into(),
                        message: format!(
                            "too few data points (or points all in one plane) within {:.2} mm of \
                             map node {}: the data has a hole there, or is a 2-D slice (the maps \
                             need 3-D data)",
                            r / 1.5 * 1e3,
                            mm(&c)
                        ),
                    });
                };
                let zero = Vector3::zeros();
                let mut field = Vector3::zeros();
                let mut grad = Matrix3::zeros();
                for (j, psi) in basis.iter().enumerate() {
                    field += psi.gradient(&zero) * theta[(j, 0)] / h;
                    grad += psi.hessian(&zero) * theta[(j, 0)] / (h * h);
                }
                values.extend(field.iter().map(|&v| v as f32));
                for i in 0..3 {
                    for j in 0..3 {
                        values.push(grad[(i, j)] as f32);
                    }
                }
            }
            progress.inc(nx as u64);
        }
    }
    Ok(Resampled {
        values,
        fit_rms_relative: if field_ss > 0.0 {
            (residual_ss / field_ss).sqrt()
        } else {
            0.0
        },
        radius_m: radius,
    })
}

/// Command-line arguments of `fieldgen import-coils`.
#[derive(Debug, clap::Args)]
pub struct ImportCoilsArgs {
    /// Rig file whose coils the data describes (names, centres, axes). Default: the paper's.
    #[arg(long)]
    pub rig: Option<PathBuf>,
    /// One coil's export: NAME=FILE or NAME=FILE@CURRENT_A (the current the export was solved
    /// or measured at). Repeat for every coil of the rig.
    #[arg(long = "coil", value_name = "NAME=FILE[@A]", required = true)]
    pub coils: Vec<String>,
    /// Current of exports that give none after '@', A.
    #[arg(long, default_value_t = 1.0)]
    pub current_a: f64,
    /// Output map directory (coils.toml + one .npy per coil).
    #[arg(long)]
    pub out: PathBuf,
    /// Take the map grid from the maps in this directory (e.g. fieldmaps/coils).
    #[arg(long)]
    pub like: Option<PathBuf>,
    /// The map grid (without --like).
    #[command(flatten)]
    pub grid: crate::coils::MapGridArgs,
    /// Length unit of files that do not state one (m, cm, mm).
    #[arg(long)]
    pub length_unit: Option<String>,
    /// Field unit of files that do not state one (T, mT, uT, G).
    #[arg(long)]
    pub field_unit: Option<String>,
    /// Highest degree of the harmonic potential fitted around each node (1 to 4).
    #[arg(long, default_value_t = 4)]
    pub fit_degree: i32,
    /// Fit neighbourhood radius in data spacings.
    #[arg(long, default_value_t = 2.0)]
    pub fit_radius_spacings: f64,
}

/// `NAME=FILE[@A]`.
fn parse_coil_arg(arg: &str, default_a: f64) -> Result<(String, PathBuf, f64), ImportCoilError> {
    let bad = |why: &str| ImportCoilError::Input(format!("--coil {arg:?}: {why}"));
    let (name, rest) = arg
        .split_once('=')
        .ok_or_else(|| bad("expected NAME=FILE[@A]"))?;
    let (file, current) = match rest.rsplit_once('@') {
        Some((f, a)) => (
            f,
            a.trim()
                .parse::<f64>()
                .map_err(|_| bad("the current after '@' is not a number"))?,
        ),
        None => (rest, default_a),
    };
    if !(current.is_finite() && current != 0.0) {
        return Err(bad("the current must be finite and not 0"));
    }
    Ok((name.trim().to_string(), PathBuf::from(file.trim()), current))
}

pub fn run(args: &ImportCoilsArgs) -> anyhow::Result<()> {
    let rig_path = args
        .rig
        .clone()
        .unwrap_or_else(fieldmaps::rigfile::paper_rig_path);
    let rig = Rig::load(&rig_path)?;
    let mut given: HashMap<String, (PathBuf, f64)> = HashMap::new();
    for arg in &args.coils {
        let (name, file, current) = parse_coil_arg(arg, args.current_a)?;
        if rig.coil_index(&name).is_none() {
            anyhow::bail!(
                "--coil {arg:?}: the rig {} has no coil {name:?} (its coils: {})",
                rig.path.display(),
                rig.coils
                    .iter()
                    .map(|c| c.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        if given.insert(name.clone(), (file, current)).is_some() {
            anyhow::bail!("--coil: coil {name} given twice");
        }
    }
    let missing: Vec<&str> = rig
        .coils
        .iter()
        .map(|c| c.name.as_str())
        .filter(|n| !given.contains_key(*n))
        .collect();
    if !missing.is_empty() {
        anyhow::bail!(
            "no data for coil(s) {} of rig {}: give --coil NAME=FILE for every coil",
            missing.join(", "),
            rig.path.display()
        );
    }
    let grid = match &args.like {
        Some(dir) => *CoilFieldMaps::load(dir)?.grid(),
        None => args.grid.spec()?,
    };
    let hints = UnitHints {
        length: args.length_unit.clone(),
        field: args.field_unit.clone(),
    };
    let settings = FitSettings {
        degree: args.fit_degree,
        radius_spacings: args.fit_radius_spacings,
    };
    let bar = ProgressBar::new((grid.node_count() * rig.coils.len()) as u64);
    bar.set_style(
        ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} nodes ({eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut data = Vec::with_capacity(rig.coils.len());
    let mut infos = Vec::with_capacity(rig.coils.len());
    let mut provenance = toml::Table::new();
    provenance.insert("source".into(), "fieldgen import-coils".into());
    provenance.insert(
        "fit".into(),
        format!(
            "local harmonic scalar-potential fit, degree {}, radius {} data spacings",
            settings.degree, settings.radius_spacings
        )
        .into(),
    );
    let mut summary = Vec::new();
    for coil in &rig.coils {
        let (file, current) = &given[&coil.name];
        let label = file.display().to_string();
        let text = std::fs::read_to_string(file).with_context(|| format!("reading {label}"))?;
        let mut samples = parse_export(&text, &label, &hints)?;
        check_samples(&samples, &label)?;
        for b in &mut samples.field_t {
            *b /= *current;
        }
        if let Some(g) = samples.gradient_t_per_m.as_mut() {
            for m in g {
                *m /= *current;
            }
        }
        bar.set_message(coil.name.clone());
        let resampled = resample(&samples, &grid, settings, &label, &bar)?;
        summary.push(format!(
            "  {:<10} {} ({}, {} / {}{}), {} points at {} A, fit residual {:.3} % (radius {:.2} mm)",
            coil.name,
            label,
            samples.format,
            samples.length_unit,
            samples.field_unit,
            if samples.gradient_t_per_m.is_some() { ", with gradients" } else { "" },
            samples.positions_m.len(),
            current,
            resampled.fit_rms_relative * 100.0,
            resampled.radius_m * 1e3
        ));
        let mut entry = toml::Table::new();
        entry.insert("file".into(), label.clone().into());
        entry.insert("format".into(), samples.format.into());
        entry.insert("length_unit".into(), samples.length_unit.clone().into());
        entry.insert("field_unit".into(), samples.field_unit.clone().into());
        entry.insert("current_a".into(), (*current).into());
        entry.insert("points".into(), (samples.positions_m.len() as i64).into());
        entry.insert(
            "gradients_from_data".into(),
            samples.gradient_t_per_m.is_some().into(),
        );
        entry.insert(
            "fit_residual_percent".into(),
            (resampled.fit_rms_relative * 100.0).into(),
        );
        provenance.insert(coil.name.clone(), entry.into());
        data.push(resampled.values);
        infos.push(CoilInfo {
            name: coil.name.clone(),
            center_m: Some(coil.center_m.into()),
            axis: Some(coil.axis.into_inner().into()),
            total_turns: coil.turns,
        });
    }
    bar.finish_and_clear();
    let maps = CoilFieldMaps::from_parts(grid, infos, data)?;
    let command = format!("fieldgen import-coils {}", args.coils.join(" "));
    maps.write(
        &args.out,
        &format!(
            "Current-normalized field and gradient of the {} coils of rig {}, imported from \
             field data; see FORMAT.md",
            rig.coils.len(),
            rig.name
        ),
        &command,
        Some(provenance),
    )?;
    println!("imported {} coils:", rig.coils.len());
    for line in summary {
        println!("{line}");
    }
    let [gx, gy, gz] = grid.shape;
    println!(
        "wrote {} ({gx} x {gy} x {gz} nodes); use it with field_model = {{ kind = \"maps\", dir = \"{}\" }} in the rig file",
        args.out.display(),
        args.out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn harmonic_basis_has_the_right_size_and_is_harmonic() {
        let basis = harmonic_basis(4);
        assert_eq!(basis.len(), 3 + 5 + 7 + 9);
        let u = Vector3::new(0.3, -0.7, 0.45);
        for psi in &basis {
            let h = psi.hessian(&u);
            assert!(h.trace().abs() < 1e-9, "Laplacian {}", h.trace());
            assert!((h - h.transpose()).norm() < 1e-12);
        }
    }

    #[test]
    fn coil_arguments_parse() {
        assert_eq!(
            parse_coil_arg("N_small=a/b.txt@2.5", 1.0).unwrap(),
            ("N_small".into(), PathBuf::from("a/b.txt"), 2.5)
        );
        assert_eq!(parse_coil_arg("E=x.csv", 3.0).unwrap().2, 3.0);
        assert!(parse_coil_arg("E", 1.0).is_err());
        assert!(parse_coil_arg("E=x@0", 1.0).is_err());
    }

    #[test]
    fn export_of_a_known_field_resamples_exactly() {
        // A quadratic-potential field (uniform gradient), exact for any degree >= 2.
        let g = Matrix3::new(0.1, 0.02, 0.0, 0.02, -0.04, 0.01, 0.0, 0.01, -0.06);
        let b0 = Vector3::new(1e-3, -2e-3, 0.5e-3);
        let mut text = String::from("% Length unit: mm\n% x y z Bx (T) By (T) Bz (T)\n");
        for i in -4..=4 {
            for j in -4..=4 {
                for k in -2..=2 {
                    let p = Vector3::new(i as f64, j as f64, k as f64) * 1.5e-3;
                    let b = b0 + g * p;
                    text.push_str(&format!(
                        "{} {} {} {} {} {}\n",
                        p.x * 1e3,
                        p.y * 1e3,
                        p.z * 1e3,
                        b.x,
                        b.y,
                        b.z
                    ));
                }
            }
        }
        let samples = parse_export(&text, "t", &UnitHints::default()).unwrap();
        assert_eq!(samples.format, "COMSOL spreadsheet");
        check_samples(&samples, "t").unwrap();
        let grid = GridSpec::centered([4e-3, 4e-3, 2e-3], 2e-3).unwrap();
        let out = resample(
            &samples,
            &grid,
            FitSettings::default(),
            "t",
            &ProgressBar::hidden(),
        )
        .unwrap();
        for (n, node) in out.values.chunks(12).enumerate() {
            let [nx, ny, _] = grid.shape;
            let p = grid.node(n % nx, (n / nx) % ny, n / (nx * ny));
            let want = b0 + g * p;
            for k in 0..3 {
                assert!((f64::from(node[k]) - want[k]).abs() < 1e-8, "{n}: {node:?}");
            }
            for k in 0..9 {
                assert!((f64::from(node[3 + k]) - g[(k / 3, k % 3)]).abs() < 1e-6);
            }
        }
    }
}
