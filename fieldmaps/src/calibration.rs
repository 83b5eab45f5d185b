//! Coil calibration: corrections fitted to gaussmeter measurements (`fieldgen fit-coils`) and
//! applied on top of a base field model (analytic or maps). A rig file selects it with
//! `field_model = { kind = "maps", dir = "<dir>", calibration = "<file>" }`.
//!
//! Model, per coil k with base field B̃_k(p) and gradient G̃_k(p) per ampere:
//! - `gain`:   B_k = g_k · B̃_k,  G_k = g_k · G̃_k (winding turns, core permeability, driver gain);
//! - `matrix`: B_k = M_k · B̃_k, G_k = M_k · G̃_k (a 3 × 3 correction also absorbing a tilted or
//!   displaced coil to first order; M_k G̃_k is no longer exactly symmetric, which is the price of
//!   a free linear correction);
//!
//! plus a uniform background field B₀ (earth, the table's steel, remanence) that adds to any
//! current pattern and has no gradient. File format: `fieldmaps/coils/CALIBRATION.md`.

use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::coils::CoilField;

/// The `format` tag of a calibration file.
pub const CALIBRATION_FORMAT: &str = "millinav-coil-calibration";
/// The version this loader reads.
pub const CALIBRATION_VERSION: u32 = 1;

#[derive(Debug, Error)]
pub enum CalibrationError {
    #[error("{}: cannot read calibration: {source}", path.display())]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: cannot write calibration: {source}", path.display())]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: {field}: {message}", path.display())]
    Invalid {
        path: PathBuf,
        field: String,
        message: String,
    },
}

/// The correction of one coil.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CoilCorrection {
    /// Scalar gain on the base field and gradient.
    Gain(f64),
    /// 3 × 3 matrix applied to the base field vector and (from the left) to its gradient.
    Matrix(Matrix3<f64>),
}

impl CoilCorrection {
    /// The corrected (field, gradient).
    pub fn apply(&self, b: Vector3<f64>, g: Matrix3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
        match self {
            CoilCorrection::Gain(k) => (b * *k, g * *k),
            CoilCorrection::Matrix(m) => (m * b, m * g),
        }
    }

    /// The gain this correction amounts to along the base field: the scalar gain, or for a
    /// matrix the mean of its diagonal (for reports).
    pub fn nominal_gain(&self) -> f64 {
        match self {
            CoilCorrection::Gain(k) => *k,
            CoilCorrection::Matrix(m) => m.trace() / 3.0,
        }
    }
}

/// Which correction a calibration carries per coil.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CorrectionModel {
    Gain,
    Matrix,
}

/// Per-coil corrections and a background field, by coil name.
#[derive(Debug, Clone, PartialEq)]
pub struct CoilCalibration {
    pub model: CorrectionModel,
    /// Coil names in the order of `corrections`.
    pub coil_names: Vec<String>,
    pub corrections: Vec<CoilCorrection>,
    /// Uniform background field, T.
    pub background_t: Vector3<f64>,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CalibrationFile {
    format: String,
    version: u32,
    model: CorrectionModel,
    #[serde(rename = "background_mT")]
    background_mt: [f64; 3],
    /// Provenance (fit report); written, never read back.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    fit: Option<toml::Table>,
    coil: Vec<CoilEntry>,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CoilEntry {
    name: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    gain: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    matrix: Option<[[f64; 3]; 3]>,
}

impl CoilCalibration {
    /// Identity corrections (gain 1, no background) for `names`.
    pub fn identity(names: &[String]) -> Self {
        Self {
            model: CorrectionModel::Gain,
            coil_names: names.to_vec(),
            corrections: vec![CoilCorrection::Gain(1.0); names.len()],
            background_t: Vector3::zeros(),
        }
    }

    pub fn load(path: &Path) -> Result<Self, CalibrationError> {
        let text = std::fs::read_to_string(path).map_err(|source| CalibrationError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// Parses the text of the calibration file at `path` (named in errors).
    pub fn parse(text: &str, path: &Path) -> Result<Self, CalibrationError> {
        let err = |field: &str, message: String| CalibrationError::Invalid {
            path: path.to_owned(),
            field: field.to_string(),
            message,
        };
        let file: CalibrationFile =
            toml::from_str(text).map_err(|e| err("(file)", e.message().to_string()))?;
        if file.format != CALIBRATION_FORMAT {
            return Err(err(
                "format",
                format!("is {:?}, expected {CALIBRATION_FORMAT:?}", file.format),
            ));
        }
        if file.version != CALIBRATION_VERSION {
            return Err(err(
                "version",
                format!(
                    "this loader reads version {CALIBRATION_VERSION}, got {}",
                    file.version
                ),
            ));
        }
        if file.background_mt.iter().any(|v| !v.is_finite()) {
            return Err(err("background_mT", "must be finite".into()));
        }
        if file.coil.is_empty() {
            return Err(err("coil", "no [[coil]] entries".into()));
        }
        let mut names = Vec::with_capacity(file.coil.len());
        let mut corrections = Vec::with_capacity(file.coil.len());
        for (i, c) in file.coil.iter().enumerate() {
            if names.contains(&c.name) {
                return Err(err(
                    &format!("coil[{i}].name"),
                    format!("{:?} appears twice", c.name),
                ));
            }
            let correction = match (file.model, c.gain, c.matrix) {
                (CorrectionModel::Gain, Some(g), None) if g.is_finite() && g > 0.0 => {
                    CoilCorrection::Gain(g)
                }
                (CorrectionModel::Gain, Some(g), None) => {
                    return Err(err(
                        &format!("coil[{i}].gain"),
                        format!("{g} must be finite and > 0"),
                    ))
                }
                (CorrectionModel::Matrix, None, Some(m)) => {
                    let m = Matrix3::from_fn(|r, c| m[r][c]);
                    if m.iter().any(|v| !v.is_finite()) || m.determinant().abs() < 1e-6 {
                        return Err(err(
                            &format!("coil[{i}].matrix"),
                            "must be finite and invertible".into(),
                        ));
                    }
                    CoilCorrection::Matrix(m)
                }
                (model, _, _) => {
                    let want = match model {
                        CorrectionModel::Gain => "gain",
                        CorrectionModel::Matrix => "matrix",
                    };
                    return Err(err(
                        &format!("coil[{i}]"),
                        format!("model {want:?} needs exactly the key `{want}` for every coil"),
                    ));
                }
            };
            names.push(c.name.clone());
            corrections.push(correction);
        }
        Ok(Self {
            model: file.model,
            coil_names: names,
            corrections,
            background_t: Vector3::from(file.background_mt) * 1e-3,
        })
    }

    /// Writes the calibration with `fit` (free provenance: the fit report) to `path`.
    pub fn write(&self, path: &Path, fit: Option<toml::Table>) -> Result<(), CalibrationError> {
        let file = CalibrationFile {
            format: CALIBRATION_FORMAT.into(),
            version: CALIBRATION_VERSION,
            model: self.model,
            background_mt: (self.background_t * 1e3).into(),
            fit,
            coil: self
                .coil_names
                .iter()
                .zip(&self.corrections)
                .map(|(name, c)| match c {
                    CoilCorrection::Gain(g) => CoilEntry {
                        name: name.clone(),
                        gain: Some(*g),
                        matrix: None,
                    },
                    CoilCorrection::Matrix(m) => CoilEntry {
                        name: name.clone(),
                        gain: None,
                        matrix: Some(std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))),
                    },
                })
                .collect(),
        };
        let text = toml::to_string(&file).map_err(|e| CalibrationError::Invalid {
            path: path.to_owned(),
            field: "(file)".into(),
            message: e.to_string(),
        })?;
        let header =
            "# Coil calibration (fieldgen fit-coils); format: fieldmaps/coils/CALIBRATION.md\n";
        std::fs::write(path, format!("{header}{text}")).map_err(|source| CalibrationError::Write {
            path: path.to_owned(),
            source,
        })
    }

    /// The corrections in the order of `coil_names` (a rig's coils): every coil must be in the
    /// calibration; its extra coils are an error too (a calibration of another rig).
    pub fn ordered_for(&self, coil_names: &[&str]) -> Result<Vec<CoilCorrection>, String> {
        let mut out = Vec::with_capacity(coil_names.len());
        for name in coil_names {
            match self.coil_names.iter().position(|n| n == name) {
                Some(k) => out.push(self.corrections[k]),
                None => return Err(format!("coil {name:?} is missing from the calibration")),
            }
        }
        if let Some(extra) = self
            .coil_names
            .iter()
            .find(|n| !coil_names.contains(&n.as_str()))
        {
            return Err(format!(
                "the calibration has coil {extra:?}, which the rig does not have"
            ));
        }
        Ok(out)
    }
}

/// A base field model with per-coil corrections (in the base model's coil order) and a
/// background field.
#[derive(Debug, Clone)]
pub struct CalibratedField<F> {
    pub base: F,
    pub corrections: Vec<CoilCorrection>,
    pub background_t: Vector3<f64>,
}

impl<F: CoilField> CoilField for CalibratedField<F> {
    fn coil_count(&self) -> usize {
        self.base.coil_count()
    }

    fn field_and_gradient_per_amp(
        &self,
        coil: usize,
        p: &Vector3<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>) {
        let (b, g) = self.base.field_and_gradient_per_amp(coil, p);
        match self.corrections.get(coil) {
            Some(c) => c.apply(b, g),
            None => (b, g),
        }
    }

    fn background_field(&self, _p: &Vector3<f64>) -> Vector3<f64> {
        self.background_t
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn write_and_load_round_trip() {
        let dir = std::env::temp_dir().join(format!("millinav-cal-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("cal.toml");
        let names = vec!["a".to_string(), "b".to_string()];
        let mut cal = CoilCalibration::identity(&names);
        cal.corrections[1] = CoilCorrection::Gain(1.05);
        cal.background_t = Vector3::new(2e-5, -1e-5, 4e-5);
        cal.write(&path, None).unwrap();
        let back = CoilCalibration::load(&path).unwrap();
        assert_eq!(back.coil_names, names);
        assert_eq!(back.corrections[1], CoilCorrection::Gain(1.05));
        assert!((back.background_t - cal.background_t).norm() < 1e-15);
        assert_eq!(
            back.ordered_for(&["b", "a"]).unwrap()[0],
            CoilCorrection::Gain(1.05)
        );
        let missing = back.ordered_for(&["a", "c"]).unwrap_err();
        assert!(missing.contains("\"c\""), "{missing}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn bad_files_name_the_field() {
        let path = Path::new("x/cal.toml");
        let text = "format = \"millinav-coil-calibration\"\nversion = 1\nmodel = \"gain\"\n\
                    background_mT = [0, 0, 0]\n[[coil]]\nname = \"a\"\ngain = -1.0\n";
        let e = CoilCalibration::parse(text, path).unwrap_err().to_string();
        assert!(e.contains("x/cal.toml: coil[0].gain"), "{e}");
        let text = text.replace("gain = -1.0", "matrix = [[1,0,0],[0,1,0],[0,0,1]]");
        let e = CoilCalibration::parse(&text, path).unwrap_err().to_string();
        assert!(e.contains("coil[0]") && e.contains("`gain`"), "{e}");
    }
}
