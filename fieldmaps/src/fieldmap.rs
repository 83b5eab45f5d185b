//! Current-normalized coil field maps on a regular 3D grid: file format, loading with checks,
//! and trilinear interpolation of B̃_i and ∇B̃_i (a drop-in [`CoilField`] for the direct model).
//!
//! On disk (see `fieldmaps/coils/FORMAT.md`): a TOML manifest `coils.toml` (format tag, units,
//! grid, coil list with CRC-32 of each data file) plus one NumPy `.npy` file per coil holding a
//! little-endian float32 C-order array of shape `(nz, ny, nx, 12)`; the 12 components are
//! [`COMPONENTS`]: B̃ (T/A) then ∇B̃ row-major (`∂B_i/∂x_j`, T/(A·m)).
//!
//! Interpolation ([`Interpolation`]): by default a trilinear blend of second-order Taylor steps
//! from the 8 surrounding nodes (uses the stored gradients, exact for quadratic fields); plain
//! trilinear on request. The stored gradient is interpolated, not differentiated, so the
//! interpolated ∇B̃ is a combination of symmetric traceless matrices, i.e. curl- and
//! divergence-free up to float32 rounding.

use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::coils::CoilField;

/// Format tag in the manifest.
pub const FORMAT_NAME: &str = "millinav-coil-fieldmap";
/// Format version this code reads and writes.
pub const FORMAT_VERSION: u32 = 1;
/// Manifest file name inside a map directory.
pub const MANIFEST_FILE: &str = "coils.toml";
/// NumPy dtype string of the data: little-endian float32.
pub const DTYPE: &str = "<f4";
/// Components per grid node, in storage order.
pub const COMPONENTS: [&str; 12] = [
    "Bx", "By", "Bz", "dBx/dx", "dBx/dy", "dBx/dz", "dBy/dx", "dBy/dy", "dBy/dz", "dBz/dx",
    "dBz/dy", "dBz/dz",
];
/// Number of components per node.
pub const COMPONENT_COUNT: usize = COMPONENTS.len();
/// Units of the field components, the gradient components and the grid.
pub const UNIT_FIELD: &str = "T/A";
pub const UNIT_GRADIENT: &str = "T/(A*m)";
pub const UNIT_LENGTH: &str = "m";

/// Errors from building, loading, writing and querying field maps. File errors name the file.
#[derive(Debug, Error)]
pub enum FieldMapError {
    #[error("{}: cannot read: {source}", path.display())]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: cannot write: {source}", path.display())]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: not a valid manifest: {message}", path.display())]
    Manifest { path: PathBuf, message: String },
    #[error("{}: mislabelled: {what}", path.display())]
    Mislabelled { path: PathBuf, what: String },
    #[error("{}: truncated: expected {expected} bytes, found {found}", path.display())]
    Truncated {
        path: PathBuf,
        expected: u64,
        found: u64,
    },
    #[error("{}: wrong grid: {what}", path.display())]
    WrongGrid { path: PathBuf, what: String },
    #[error(
        "{}: non-finite value {value} at node (ix={ix}, iy={iy}, iz={iz}), component {component}",
        path.display()
    )]
    NonFinite {
        path: PathBuf,
        value: f32,
        ix: usize,
        iy: usize,
        iz: usize,
        component: &'static str,
    },
    #[error(
        "{}: checksum mismatch: manifest says crc32 {expected:08x}, file has {found:08x} \
         (file corrupted or replaced)",
        path.display()
    )]
    Checksum {
        path: PathBuf,
        expected: u32,
        found: u32,
    },
    #[error("invalid grid: {0}")]
    InvalidGrid(String),
    #[error("invalid map data: {0}")]
    InvalidData(String),
    #[error("coil index {index} out of range (maps hold {count} coils)")]
    BadIndex { index: usize, count: usize },
    #[error("point ({:.4}, {:.4}, {:.4}) m is outside the map grid", p[0], p[1], p[2])]
    OutOfGrid { p: [f64; 3] },
}

/// A regular axis-aligned grid: node (ix, iy, iz) is at `origin_m + (ix, iy, iz) ⊙ spacing_m`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GridSpec {
    /// Position of node (0, 0, 0), m.
    pub origin_m: [f64; 3],
    /// Node spacing along x, y, z, m.
    pub spacing_m: [f64; 3],
    /// Node counts along x, y, z.
    pub shape: [usize; 3],
}

impl GridSpec {
    /// Grid centred at the origin covering `[-half_m, +half_m]` on each axis with nodes at most
    /// `max_spacing_m` apart (the spacing is shrunk so the nodes land on both faces).
    pub fn centered(half_m: [f64; 3], max_spacing_m: f64) -> Result<Self, FieldMapError> {
        if !(max_spacing_m.is_finite() && max_spacing_m > 0.0) {
            return Err(FieldMapError::InvalidGrid(format!(
                "spacing {max_spacing_m} m must be finite and > 0"
            )));
        }
        let mut g = Self {
            origin_m: [0.0; 3],
            spacing_m: [0.0; 3],
            shape: [0; 3],
        };
        for (k, &h) in half_m.iter().enumerate() {
            if !(h.is_finite() && h > 0.0) {
                return Err(FieldMapError::InvalidGrid(format!(
                    "half-extent {h} m must be finite and > 0"
                )));
            }
            let cells = ((2.0 * h / max_spacing_m) * (1.0 - 1e-9)).ceil().max(1.0);
            if cells > 100_000.0 {
                return Err(FieldMapError::InvalidGrid(format!(
                    "{cells} cells along one axis is too many"
                )));
            }
            g.origin_m[k] = -h;
            g.spacing_m[k] = 2.0 * h / cells;
            g.shape[k] = cells as usize + 1;
        }
        g.validate()?;
        Ok(g)
    }

    /// Finite origin, positive finite spacing, at least 2 nodes per axis, and a sane size.
    pub fn validate(&self) -> Result<(), FieldMapError> {
        for k in 0..3 {
            if !self.origin_m[k].is_finite() {
                return Err(FieldMapError::InvalidGrid(format!(
                    "origin[{k}] = {} is not finite",
                    self.origin_m[k]
                )));
            }
            if !(self.spacing_m[k].is_finite() && self.spacing_m[k] > 0.0) {
                return Err(FieldMapError::InvalidGrid(format!(
                    "spacing[{k}] = {} must be finite and > 0",
                    self.spacing_m[k]
                )));
            }
            if self.shape[k] < 2 {
                return Err(FieldMapError::InvalidGrid(format!(
                    "shape[{k}] = {} (need at least 2 nodes per axis)",
                    self.shape[k]
                )));
            }
        }
        // 1 Gi nodes ≫ anything sensible; keeps size arithmetic far from overflow.
        if self
            .shape
            .iter()
            .try_fold(1usize, |a, &n| a.checked_mul(n))
            .is_none_or(|n| n > 1 << 30)
        {
            return Err(FieldMapError::InvalidGrid(format!(
                "shape {:?} has too many nodes",
                self.shape
            )));
        }
        Ok(())
    }

    pub fn node_count(&self) -> usize {
        self.shape.iter().product()
    }

    /// Position of node (ix, iy, iz), m.
    pub fn node(&self, ix: usize, iy: usize, iz: usize) -> Vector3<f64> {
        Vector3::new(
            self.origin_m[0] + ix as f64 * self.spacing_m[0],
            self.origin_m[1] + iy as f64 * self.spacing_m[1],
            self.origin_m[2] + iz as f64 * self.spacing_m[2],
        )
    }

    /// Corner of the grid box with the largest coordinates, m.
    pub fn max_m(&self) -> [f64; 3] {
        std::array::from_fn(|k| self.origin_m[k] + (self.shape[k] - 1) as f64 * self.spacing_m[k])
    }

    /// Whether `p` lies in the grid box (faces included, with 1 nm slack for rounding).
    pub fn contains(&self, p: &Vector3<f64>) -> bool {
        let max = self.max_m();
        (0..3).all(|k| p[k] >= self.origin_m[k] - 1e-9 && p[k] <= max[k] + 1e-9)
    }

    /// Whether the grid box contains `[lo, hi]` (component-wise).
    pub fn covers(&self, lo: &Vector3<f64>, hi: &Vector3<f64>) -> bool {
        self.contains(lo) && self.contains(hi)
    }

    /// Lower cell corner and fractional position in that cell, with `p` clamped into the box.
    fn locate(&self, p: &Vector3<f64>) -> ([usize; 3], [f64; 3]) {
        let mut idx = [0; 3];
        let mut t = [0.0; 3];
        for k in 0..3 {
            let n = self.shape[k];
            let u = (p[k] - self.origin_m[k]) / self.spacing_m[k];
            // NaN clamps to 0 (max/min ignore NaN), so a NaN point never indexes out of bounds.
            let u = u.max(0.0).min((n - 1) as f64);
            let i = (u.floor() as usize).min(n - 2);
            idx[k] = i;
            t[k] = u - i as f64;
        }
        (idx, t)
    }

    /// Flat node index in storage order (x fastest).
    fn flat(&self, ix: usize, iy: usize, iz: usize) -> usize {
        (iz * self.shape[1] + iy) * self.shape[0] + ix
    }
}

/// One coil's entry in the manifest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CoilEntry {
    pub index: usize,
    pub name: String,
    /// Data file, relative to the manifest's directory.
    pub file: String,
    /// CRC-32 (ISO-HDLC, as Python's `zlib.crc32`) of the whole data file.
    pub crc32: u32,
    /// Informational: winding centre (m), axis (unit vector), total turns.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub center_m: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub total_turns: Option<f64>,
}

/// Units block of the manifest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Units {
    pub field: String,
    pub gradient: String,
    pub length: String,
}

impl Default for Units {
    fn default() -> Self {
        Self {
            field: UNIT_FIELD.into(),
            gradient: UNIT_GRADIENT.into(),
            length: UNIT_LENGTH.into(),
        }
    }
}

/// The manifest `coils.toml`. `calibration` is free-form provenance (not read back).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub format: String,
    pub version: u32,
    #[serde(default)]
    pub description: String,
    #[serde(default)]
    pub generator: String,
    pub dtype: String,
    /// Array layout of each data file, documentation only (always "C (nz, ny, nx, 12)").
    #[serde(default)]
    pub layout: String,
    pub components: Vec<String>,
    pub units: Units,
    pub grid: GridSpec,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<toml::Table>,
    pub coil: Vec<CoilEntry>,
}

/// Informational per-coil data written into the manifest by [`CoilFieldMaps::write`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CoilInfo {
    pub name: String,
    pub center_m: Option<[f64; 3]>,
    pub axis: Option<[f64; 3]>,
    pub total_turns: Option<f64>,
}

/// Sample one coil of `field` on `grid`: `node_count × 12` float32 values in storage order.
/// `progress` is called after each (y, z) row with the number of nodes done in that row.
pub fn sample_coil<F: CoilField + ?Sized>(
    field: &F,
    coil: usize,
    grid: &GridSpec,
    mut progress: impl FnMut(usize),
) -> Vec<f32> {
    let [nx, ny, nz] = grid.shape;
    let mut out = Vec::with_capacity(grid.node_count() * COMPONENT_COUNT);
    for iz in 0..nz {
        for iy in 0..ny {
            for ix in 0..nx {
                let (b, g) = field.field_and_gradient_per_amp(coil, &grid.node(ix, iy, iz));
                out.extend(b.iter().map(|&v| v as f32));
                // nalgebra stores column-major; the file is row-major (∂B_i/∂x_j, j fastest).
                for i in 0..3 {
                    for j in 0..3 {
                        out.push(g[(i, j)] as f32);
                    }
                }
            }
            progress(nx);
        }
    }
    out
}

/// Field maps of a set of coils on one grid; implements [`CoilField`] by interpolation
/// ([`Interpolation`]).
#[derive(Debug, Clone, PartialEq)]
pub struct CoilFieldMaps {
    grid: GridSpec,
    coils: Vec<CoilInfo>,
    /// Per coil: node_count × 12 values in storage order.
    data: Vec<Vec<f32>>,
    interpolation: Interpolation,
}

/// How [`CoilFieldMaps`] interpolates between grid nodes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Interpolation {
    /// Plain trilinear interpolation of each stored component (error O(h²)).
    Trilinear,
    /// Trilinear blend of per-node second-order Taylor steps: B from each node is
    /// B_n + ½ ∇B_n (p − x_n) (exact for fields quadratic in p, error O(h³)); ∇B likewise
    /// with ∂∇B/∂x_k from second-order differences of the stored gradients (central inside,
    /// one-sided on the grid faces). Every term of the interpolated ∇B is a symmetric traceless matrix, so
    /// it stays exactly curl- and divergence-free.
    #[default]
    Quadratic,
}

impl CoilFieldMaps {
    /// Assemble maps from sampled data (e.g. [`sample_coil`]); checks sizes and finiteness.
    pub fn from_parts(
        grid: GridSpec,
        coils: Vec<CoilInfo>,
        data: Vec<Vec<f32>>,
    ) -> Result<Self, FieldMapError> {
        grid.validate()?;
        if coils.len() != data.len() || coils.is_empty() {
            return Err(FieldMapError::InvalidData(format!(
                "{} coil descriptions for {} data arrays (need the same, >= 1)",
                coils.len(),
                data.len()
            )));
        }
        let want = grid.node_count() * COMPONENT_COUNT;
        for (c, d) in coils.iter().zip(&data) {
            if d.len() != want {
                return Err(FieldMapError::InvalidData(format!(
                    "coil {}: {} values, grid needs {want}",
                    c.name,
                    d.len()
                )));
            }
            if let Some(k) = d.iter().position(|v| !v.is_finite()) {
                return Err(FieldMapError::InvalidData(format!(
                    "coil {}: non-finite value at flat index {k}",
                    c.name
                )));
            }
        }
        check_names(coils.iter().map(|c| c.name.as_str())).map_err(FieldMapError::InvalidData)?;
        Ok(Self {
            grid,
            coils,
            data,
            interpolation: Interpolation::default(),
        })
    }

    /// Sample every coil of `field` on `grid` (single thread; see [`sample_coil`] to
    /// parallelise or report progress).
    pub fn sample<F: CoilField + ?Sized>(
        field: &F,
        coils: Vec<CoilInfo>,
        grid: GridSpec,
    ) -> Result<Self, FieldMapError> {
        grid.validate()?;
        let data = (0..coils.len())
            .map(|i| sample_coil(field, i, &grid, |_| {}))
            .collect();
        Self::from_parts(grid, coils, data)
    }

    /// Load `dir/coils.toml` and the data files it lists, checking labels (format, version,
    /// dtype, units, components, names), sizes, grid agreement, finiteness and checksums.
    pub fn load(dir: &Path) -> Result<Self, FieldMapError> {
        let mpath = dir.join(MANIFEST_FILE);
        let text = std::fs::read_to_string(&mpath).map_err(|source| FieldMapError::Read {
            path: mpath.clone(),
            source,
        })?;
        let manifest: Manifest = toml::from_str(&text).map_err(|e| FieldMapError::Manifest {
            path: mpath.clone(),
            message: e.to_string(),
        })?;
        check_manifest(&manifest).map_err(|what| FieldMapError::Mislabelled {
            path: mpath.clone(),
            what,
        })?;
        manifest
            .grid
            .validate()
            .map_err(|e| FieldMapError::WrongGrid {
                path: mpath.clone(),
                what: e.to_string(),
            })?;
        let grid = manifest.grid;
        let mut coils = Vec::with_capacity(manifest.coil.len());
        let mut data = Vec::with_capacity(manifest.coil.len());
        for entry in &manifest.coil {
            let path = dir.join(&entry.file);
            let bytes = std::fs::read(&path).map_err(|source| FieldMapError::Read {
                path: path.clone(),
                source,
            })?;
            data.push(decode_coil_file(&path, &bytes, &grid, entry.crc32)?);
            coils.push(CoilInfo {
                name: entry.name.clone(),
                center_m: entry.center_m,
                axis: entry.axis,
                total_turns: entry.total_turns,
            });
        }
        Ok(Self {
            grid,
            coils,
            data,
            interpolation: Interpolation::default(),
        })
    }

    /// Write `dir/coils.toml` and one `.npy` per coil (`<name>.npy`), creating `dir`.
    /// `calibration` is stored verbatim as provenance.
    pub fn write(
        &self,
        dir: &Path,
        description: &str,
        generator: &str,
        calibration: Option<toml::Table>,
    ) -> Result<(), FieldMapError> {
        std::fs::create_dir_all(dir).map_err(|source| FieldMapError::Write {
            path: dir.to_path_buf(),
            source,
        })?;
        let [nx, ny, nz] = self.grid.shape;
        let mut entries = Vec::with_capacity(self.coils.len());
        for (index, (info, values)) in self.coils.iter().zip(&self.data).enumerate() {
            let file = format!("{}.npy", info.name);
            let bytes = encode_npy_f32(&[nz, ny, nx, COMPONENT_COUNT], values);
            let path = dir.join(&file);
            std::fs::write(&path, &bytes).map_err(|source| FieldMapError::Write {
                path: path.clone(),
                source,
            })?;
            entries.push(CoilEntry {
                index,
                name: info.name.clone(),
                file,
                crc32: crc32(&bytes),
                center_m: info.center_m,
                axis: info.axis,
                total_turns: info.total_turns,
            });
        }
        let manifest = Manifest {
            format: FORMAT_NAME.into(),
            version: FORMAT_VERSION,
            description: description.into(),
            generator: generator.into(),
            dtype: DTYPE.into(),
            layout: format!("C order (nz, ny, nx, {COMPONENT_COUNT}); x fastest"),
            components: COMPONENTS.iter().map(|s| s.to_string()).collect(),
            units: Units::default(),
            grid: self.grid,
            calibration,
            coil: entries,
        };
        let mpath = dir.join(MANIFEST_FILE);
        let text = toml::to_string(&manifest).map_err(|e| FieldMapError::Manifest {
            path: mpath.clone(),
            message: e.to_string(),
        })?;
        std::fs::write(&mpath, text).map_err(|source| FieldMapError::Write {
            path: mpath,
            source,
        })
    }

    pub fn grid(&self) -> &GridSpec {
        &self.grid
    }

    pub fn coils(&self) -> &[CoilInfo] {
        &self.coils
    }

    /// Index of the coil called `name`.
    pub fn coil_index(&self, name: &str) -> Option<usize> {
        self.coils.iter().position(|c| c.name == name)
    }

    /// Interpolated field and gradient per ampere; errors outside the grid box or for an
    /// unknown coil (the [`CoilField`] methods clamp / return zeros instead).
    pub fn try_field_and_gradient_per_amp(
        &self,
        coil: usize,
        p: &Vector3<f64>,
    ) -> Result<(Vector3<f64>, Matrix3<f64>), FieldMapError> {
        if coil >= self.data.len() {
            return Err(FieldMapError::BadIndex {
                index: coil,
                count: self.data.len(),
            });
        }
        if !self.grid.contains(p) {
            return Err(FieldMapError::OutOfGrid { p: [p.x, p.y, p.z] });
        }
        Ok(self.interpolate(coil, p))
    }

    /// Interpolation scheme used by the queries (default [`Interpolation::Quadratic`]).
    pub fn interpolation(&self) -> Interpolation {
        self.interpolation
    }

    pub fn set_interpolation(&mut self, scheme: Interpolation) {
        self.interpolation = scheme;
    }

    /// Interpolate all 12 components at `p` clamped into the grid box.
    fn interpolate(&self, coil: usize, p: &Vector3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
        let Some(d) = self.data.get(coil) else {
            return (Vector3::zeros(), Matrix3::zeros());
        };
        let grid = &self.grid;
        let ([ix, iy, iz], [tx, ty, tz]) = grid.locate(p);
        let node_values = |jx: usize, jy: usize, jz: usize| -> &[f32] {
            let base = grid.flat(jx, jy, jz) * COMPONENT_COUNT;
            &d[base..base + COMPONENT_COUNT]
        };
        let mut b = Vector3::zeros();
        let mut g = Matrix3::zeros();
        let corner = [ix, iy, iz];
        for (dz, wz) in [(0, 1.0 - tz), (1, tz)] {
            for (dy, wy) in [(0, 1.0 - ty), (1, ty)] {
                for (dx, wx) in [(0, 1.0 - tx), (1, tx)] {
                    let w = wx * wy * wz;
                    if w == 0.0 {
                        continue;
                    }
                    let n = [ix + dx, iy + dy, iz + dz];
                    let v = node_values(n[0], n[1], n[2]);
                    let bn = Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64);
                    let gn = Matrix3::from_fn(|i, j| v[3 + 3 * i + j] as f64);
                    match self.interpolation {
                        Interpolation::Trilinear => {
                            b += bn * w;
                            g += gn * w;
                        }
                        Interpolation::Quadratic => {
                            // Offset of p from this node, m.
                            let off = Vector3::from_fn(|k, _| {
                                let t = [tx, ty, tz][k];
                                let local = if n[k] == corner[k] { t } else { t - 1.0 };
                                local * grid.spacing_m[k]
                            });
                            b += (bn + gn * off * 0.5) * w;
                            // ∂G/∂x_k at the node by second-order differences of the stored
                            // gradients (central inside, one-sided on the faces).
                            let mut gt = gn;
                            for k in 0..3 {
                                if off[k] == 0.0 {
                                    continue;
                                }
                                let at = |m: usize| {
                                    let mut q = n;
                                    q[k] = m;
                                    let v = node_values(q[0], q[1], q[2]);
                                    Matrix3::from_fn(|i, j| v[3 + 3 * i + j] as f64)
                                };
                                let (last, h) = (grid.shape[k] - 1, grid.spacing_m[k]);
                                let dg = if n[k] > 0 && n[k] < last {
                                    (at(n[k] + 1) - at(n[k] - 1)) / (2.0 * h)
                                } else if last < 2 {
                                    (at(1) - at(0)) / h
                                } else if n[k] == 0 {
                                    (at(1) * 4.0 - at(0) * 3.0 - at(2)) / (2.0 * h)
                                } else {
                                    (at(last) * 3.0 - at(last - 1) * 4.0 + at(last - 2)) / (2.0 * h)
                                };
                                gt += dg * (0.5 * off[k]);
                            }
                            g += gt * w;
                        }
                    }
                }
            }
        }
        (b, g)
    }
}

impl CoilField for CoilFieldMaps {
    fn coil_count(&self) -> usize {
        self.data.len()
    }

    /// Interpolated value; points outside the grid box take the value at the nearest
    /// point of the box (check [`GridSpec::contains`] or use
    /// [`CoilFieldMaps::try_field_and_gradient_per_amp`] to reject them).
    fn field_and_gradient_per_amp(
        &self,
        coil: usize,
        p: &Vector3<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>) {
        self.interpolate(coil, p)
    }
}

fn check_names<'a>(names: impl Iterator<Item = &'a str>) -> Result<(), String> {
    let mut seen = std::collections::HashSet::new();
    for n in names {
        if n.is_empty()
            || !n
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        {
            return Err(format!(
                "coil name {n:?} must be non-empty ASCII letters, digits, '_' or '-'"
            ));
        }
        if !seen.insert(n) {
            return Err(format!("coil name {n:?} appears twice"));
        }
    }
    Ok(())
}

fn check_manifest(m: &Manifest) -> Result<(), String> {
    if m.format != FORMAT_NAME {
        return Err(format!(
            "format is {:?}, expected {FORMAT_NAME:?}",
            m.format
        ));
    }
    if m.version != FORMAT_VERSION {
        return Err(format!(
            "format version {} is not supported (this build reads {FORMAT_VERSION})",
            m.version
        ));
    }
    if m.dtype != DTYPE {
        return Err(format!("dtype is {:?}, expected {DTYPE:?}", m.dtype));
    }
    if m.components != COMPONENTS {
        return Err(format!(
            "components are {:?}, expected {COMPONENTS:?}",
            m.components
        ));
    }
    if m.units != Units::default() {
        return Err(format!(
            "units are {:?}, expected field {UNIT_FIELD:?}, gradient {UNIT_GRADIENT:?}, \
             length {UNIT_LENGTH:?}",
            m.units
        ));
    }
    if m.coil.is_empty() {
        return Err("no [[coil]] entries".into());
    }
    for (k, c) in m.coil.iter().enumerate() {
        if c.index != k {
            return Err(format!(
                "coil {:?} has index {} but is entry {k} (entries must be in index order)",
                c.name, c.index
            ));
        }
        let file = Path::new(&c.file);
        if c.file.is_empty() || file.is_absolute() || c.file.contains("..") {
            return Err(format!(
                "coil {:?}: data file {:?} must be a plain relative name",
                c.name, c.file
            ));
        }
    }
    check_names(m.coil.iter().map(|c| c.name.as_str()))
}

/// Decode and check one coil's `.npy` file against the manifest's grid and checksum.
fn decode_coil_file(
    path: &Path,
    bytes: &[u8],
    grid: &GridSpec,
    expected_crc: u32,
) -> Result<Vec<f32>, FieldMapError> {
    let header = parse_npy_header(path, bytes)?;
    if header.descr != DTYPE {
        return Err(FieldMapError::Mislabelled {
            path: path.into(),
            what: format!("dtype {:?}, expected {DTYPE:?}", header.descr),
        });
    }
    if header.fortran_order {
        return Err(FieldMapError::Mislabelled {
            path: path.into(),
            what: "fortran_order is True, expected C order".into(),
        });
    }
    let [nx, ny, nz] = grid.shape;
    let want_shape = [nz, ny, nx, COMPONENT_COUNT];
    if header.shape != want_shape {
        return Err(FieldMapError::WrongGrid {
            path: path.into(),
            what: format!(
                "array shape {:?}, but the manifest grid needs (nz, ny, nx, {COMPONENT_COUNT}) = \
                 {want_shape:?}",
                header.shape
            ),
        });
    }
    let n_values = grid.node_count() * COMPONENT_COUNT;
    let expected = (header.data_offset + 4 * n_values) as u64;
    let found = bytes.len() as u64;
    if found < expected {
        return Err(FieldMapError::Truncated {
            path: path.into(),
            expected,
            found,
        });
    }
    if found > expected {
        return Err(FieldMapError::Mislabelled {
            path: path.into(),
            what: format!(
                "{} bytes after the {expected} bytes its header describes",
                found - expected
            ),
        });
    }
    let values: Vec<f32> = bytes[header.data_offset..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    if let Some(k) = values.iter().position(|v| !v.is_finite()) {
        let node = k / COMPONENT_COUNT;
        return Err(FieldMapError::NonFinite {
            path: path.into(),
            value: values[k],
            ix: node % nx,
            iy: (node / nx) % ny,
            iz: node / (nx * ny),
            component: COMPONENTS[k % COMPONENT_COUNT],
        });
    }
    let found_crc = crc32(bytes);
    if found_crc != expected_crc {
        return Err(FieldMapError::Checksum {
            path: path.into(),
            expected: expected_crc,
            found: found_crc,
        });
    }
    Ok(values)
}

/// CRC-32/ISO-HDLC (zlib's crc32).
pub fn crc32(bytes: &[u8]) -> u32 {
    crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC).checksum(bytes)
}

const NPY_MAGIC: &[u8] = b"\x93NUMPY";

struct NpyHeader {
    descr: String,
    fortran_order: bool,
    shape: Vec<usize>,
    data_offset: usize,
}

/// Encode a float32 array as NumPy format 1.0 (header padded to a multiple of 64 bytes).
pub fn encode_npy_f32(shape: &[usize], values: &[f32]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|n| n.to_string()).collect();
    let shape_str = if dims.len() == 1 {
        format!("({},)", dims[0])
    } else {
        format!("({})", dims.join(", "))
    };
    let mut dict =
        format!("{{'descr': '{DTYPE}', 'fortran_order': False, 'shape': {shape_str}, }}");
    // magic(6) + version(2) + len(2) + dict + '\n' ≡ 0 mod 64.
    let total = 10 + dict.len() + 1;
    dict.push_str(&" ".repeat((64 - total % 64) % 64));
    dict.push('\n');
    let mut out = Vec::with_capacity(10 + dict.len() + 4 * values.len());
    out.extend_from_slice(NPY_MAGIC);
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

fn parse_npy_header(path: &Path, bytes: &[u8]) -> Result<NpyHeader, FieldMapError> {
    let truncated = |expected: usize| FieldMapError::Truncated {
        path: path.into(),
        expected: expected as u64,
        found: bytes.len() as u64,
    };
    let mislabelled = |what: String| FieldMapError::Mislabelled {
        path: path.into(),
        what,
    };
    if bytes.len() < 10 {
        return Err(truncated(10));
    }
    if &bytes[..6] != NPY_MAGIC {
        return Err(mislabelled(
            "not a NumPy .npy file (bad magic bytes)".into(),
        ));
    }
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(truncated(12));
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        v => return Err(mislabelled(format!("unsupported .npy version {v}"))),
    };
    let end = start + header_len;
    if bytes.len() < end {
        return Err(truncated(end));
    }
    let text = std::str::from_utf8(&bytes[start..end])
        .map_err(|_| mislabelled(".npy header is not text".into()))?;
    let value_of = |key: &str| -> Result<&str, FieldMapError> {
        let pat = format!("'{key}':");
        let at = text
            .find(&pat)
            .ok_or_else(|| mislabelled(format!(".npy header has no {key:?}")))?;
        Ok(text[at + pat.len()..].trim_start())
    };
    let descr = {
        let v = value_of("descr")?;
        let v = v
            .strip_prefix('\'')
            .and_then(|r| r.split('\'').next())
            .ok_or_else(|| mislabelled("unreadable 'descr' in .npy header".into()))?;
        v.to_string()
    };
    let fortran_order = {
        let v = value_of("fortran_order")?;
        if v.starts_with("False") {
            false
        } else if v.starts_with("True") {
            true
        } else {
            return Err(mislabelled(
                "unreadable 'fortran_order' in .npy header".into(),
            ));
        }
    };
    let shape = {
        let v = value_of("shape")?;
        let inner = v
            .strip_prefix('(')
            .and_then(|r| r.split(')').next())
            .ok_or_else(|| mislabelled("unreadable 'shape' in .npy header".into()))?;
        inner
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(|s| {
                s.parse::<usize>()
                    .map_err(|_| mislabelled(format!("bad dimension {s:?} in .npy shape")))
            })
            .collect::<Result<Vec<_>, _>>()?
    };
    Ok(NpyHeader {
        descr,
        fortran_order,
        shape,
        data_offset: end,
    })
}
