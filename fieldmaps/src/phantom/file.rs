//! A parametric phantom as data: a TOML file of discs and tubes (`format =
//! "millinav-phantom"`), its ports and its default task, from which a canal mask is drawn
//! (`cargo run -p fieldmaps --example phantom_mask -- PHANTOM.toml WIDTH_PX FIELD_MM MASK.png`).
//! The paper's heart phantom is `fieldmaps/rigs/paper/heart_phantom.toml`.
//!
//! Lengths are millimetres in the file, metres in [`Phantom`]. Errors name the file and the key.

use std::path::{Path, PathBuf};

use nalgebra::{Unit, Vector2};
use serde::Deserialize;
use thiserror::Error;

use super::{Inlet, Outlet, Phantom, PhantomError, Primitive};

/// The `format` tag of a phantom file.
pub const PHANTOM_FORMAT: &str = "millinav-phantom";
/// The version this loader reads.
pub const PHANTOM_VERSION: u32 = 1;

/// A phantom file that cannot be used.
#[derive(Debug, Error)]
pub enum PhantomFileError {
    #[error("{path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("{path}: {field}: {message}")]
    Invalid {
        path: PathBuf,
        field: String,
        message: String,
    },
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PhantomFile {
    format: String,
    version: u32,
    #[serde(default)]
    #[allow(dead_code)] // free text for the reader of the file
    description: String,
    start_mm: [f64; 2],
    end_mm: [f64; 2],
    primitives: Vec<PrimitiveSection>,
    #[serde(default)]
    inlets: Vec<InletSection>,
    outlet: OutletSection,
}

#[derive(Debug, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
enum PrimitiveSection {
    Disc {
        #[serde(default)]
        #[allow(dead_code)] // names the piece for the reader of the file
        name: String,
        center_mm: [f64; 2],
        radius_mm: f64,
    },
    Tube {
        #[serde(default)]
        #[allow(dead_code)] // names the piece for the reader of the file
        name: String,
        points_mm: Vec<[f64; 2]>,
        radius_mm: f64,
    },
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct InletSection {
    name: String,
    mouth_mm: [f64; 2],
    direction: [f64; 2],
    diameter_mm: f64,
    length_mm: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct OutletSection {
    name: String,
    mouth_mm: [f64; 2],
    direction: [f64; 2],
    diameter_mm: f64,
}

/// A point in mm → m.
fn point(v: [f64; 2]) -> Vector2<f64> {
    Vector2::new(v[0], v[1]) * 1e-3
}

/// A length in mm → m (correctly rounded, so `6.5` mm is the `6.5e-3` m one would write).
fn length(mm: f64) -> f64 {
    mm / 1000.0
}

impl Phantom {
    /// Reads and checks a phantom file.
    pub fn load(path: &Path) -> Result<Self, PhantomFileError> {
        let text = std::fs::read_to_string(path).map_err(|source| PhantomFileError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// Parses `text` as the phantom file at `path`.
    pub fn parse(text: &str, path: &Path) -> Result<Self, PhantomFileError> {
        let invalid = |field: &str, message: String| PhantomFileError::Invalid {
            path: path.to_owned(),
            field: field.to_owned(),
            message,
        };
        let file: PhantomFile = toml::from_str(text).map_err(|e| PhantomFileError::Parse {
            path: path.to_owned(),
            message: e.to_string(),
        })?;
        if file.format != PHANTOM_FORMAT {
            return Err(invalid(
                "format",
                format!("must be {PHANTOM_FORMAT:?}, got {:?}", file.format),
            ));
        }
        if file.version != PHANTOM_VERSION {
            return Err(invalid(
                "version",
                format!(
                    "this loader reads version {PHANTOM_VERSION}, got {}",
                    file.version
                ),
            ));
        }
        let primitives = file.primitives.iter().map(primitive).collect();
        let inlets = file
            .inlets
            .iter()
            .enumerate()
            .map(|(i, s)| {
                Ok(Inlet {
                    name: s.name.clone(),
                    mouth_m: point(s.mouth_mm),
                    direction: direction(s.direction)
                        .ok_or_else(|| invalid(&format!("inlets[{i}].direction"), not_zero()))?,
                    diameter_m: length(s.diameter_mm),
                    length_m: length(s.length_mm),
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        let o = &file.outlet;
        let outlet = Outlet {
            name: o.name.clone(),
            mouth_m: point(o.mouth_mm),
            direction: direction(o.direction)
                .ok_or_else(|| invalid("outlet.direction", not_zero()))?,
            diameter_m: length(o.diameter_mm),
        };
        Phantom::new(
            primitives,
            inlets,
            outlet,
            point(file.start_mm),
            point(file.end_mm),
        )
        .map_err(|e| match e {
            PhantomError::BadPrimitive(i) => invalid(
                &format!("primitives[{i}]"),
                "needs finite coordinates, a radius > 0 and, for a tube, a point".into(),
            ),
            PhantomError::PointOutside(which) => {
                invalid(&format!("{which}_mm"), "is not inside the canal".into())
            }
            other => invalid("primitives", other.to_string()),
        })
    }
}

fn primitive(section: &PrimitiveSection) -> Primitive {
    match section {
        PrimitiveSection::Disc {
            center_mm,
            radius_mm,
            ..
        } => Primitive::Disc {
            center_m: point(*center_mm),
            radius_m: length(*radius_mm),
        },
        PrimitiveSection::Tube {
            points_mm,
            radius_mm,
            ..
        } => Primitive::Tube {
            points_m: points_mm.iter().copied().map(point).collect(),
            radius_m: length(*radius_mm),
        },
    }
}

fn direction(v: [f64; 2]) -> Option<Unit<Vector2<f64>>> {
    let v = Vector2::from(v);
    v.iter()
        .all(|c| c.is_finite())
        .then(|| Unit::try_new(v, 1e-12))
        .flatten()
}

fn not_zero() -> String {
    "must be a finite non-zero vector".into()
}
