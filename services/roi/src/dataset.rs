//! On-disk layout of one dataset split (e.g. `train/`, `val/`, `test/`):
//! - `images.u8`: N x INPUT_PX x INPUT_PX x 3 raw RGB (model input after ROI preprocessing);
//! - `masks.u8`: N x INPUT_PX x INPUT_PX, 1 = capsule, 0 = background;
//! - `labels.csv`: one row per sample, keypoints in model-input pixel coordinates;
//!
//! Full frames are not stored, only what the model sees. Raw arrays load with `numpy.fromfile(..., dtype=uint8).reshape(...)`.

use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};

use crate::roi::INPUT_PX;

pub const LABELS_HEADER: &str =
    "index,has_robot,tip_x,tip_y,centroid_x,centroid_y,tail_x,tail_y,crop_col0,crop_row0,mm_per_px";

#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
}

/// Labels of one sample (model-input pixels).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Label {
    pub has_robot: bool,
    pub tip: (f64, f64),
    pub centroid: (f64, f64),
    pub tail: (f64, f64),
    pub crop_col0: usize,
    pub crop_row0: usize,
    pub mm_per_px: f64,
}

/// A loaded split.
#[derive(Debug, Clone, Default)]
pub struct Split {
    pub images: Vec<u8>,
    pub masks: Vec<u8>,
    pub labels: Vec<Label>,
}

impl Split {
    pub fn len(&self) -> usize {
        self.labels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.labels.is_empty()
    }

    pub fn image(&self, i: usize) -> &[u8] {
        let n = INPUT_PX * INPUT_PX * 3;
        &self.images[i * n..(i + 1) * n]
    }

    pub fn mask(&self, i: usize) -> &[u8] {
        let n = INPUT_PX * INPUT_PX;
        &self.masks[i * n..(i + 1) * n]
    }

    pub fn push(&mut self, image: &[u8], mask: &[u8], label: Label) {
        self.images.extend_from_slice(image);
        self.masks.extend_from_slice(mask);
        self.labels.push(label);
    }

    pub fn save(&self, dir: &Path) -> Result<(), DatasetError> {
        let io = |path: &Path| {
            let path = path.to_owned();
            move |source| DatasetError::Io { path, source }
        };
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let p = dir.join("images.u8");
        std::fs::write(&p, &self.images).map_err(io(&p))?;
        let p = dir.join("masks.u8");
        std::fs::write(&p, &self.masks).map_err(io(&p))?;
        let p = dir.join("labels.csv");
        let mut out = std::io::BufWriter::new(std::fs::File::create(&p).map_err(io(&p))?);
        writeln!(out, "{LABELS_HEADER}").map_err(io(&p))?;
        for (i, l) in self.labels.iter().enumerate() {
            writeln!(
                out,
                "{i},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{},{},{:.6}",
                u8::from(l.has_robot),
                l.tip.0,
                l.tip.1,
                l.centroid.0,
                l.centroid.1,
                l.tail.0,
                l.tail.1,
                l.crop_col0,
                l.crop_row0,
                l.mm_per_px
            )
            .map_err(io(&p))?;
        }
        out.flush().map_err(io(&p))
    }

    pub fn load(dir: &Path) -> Result<Self, DatasetError> {
        let read = |name: &str| {
            let p = dir.join(name);
            std::fs::read(&p).map_err(|source| DatasetError::Io { path: p, source })
        };
        let images = read("images.u8")?;
        let masks = read("masks.u8")?;
        let p = dir.join("labels.csv");
        let file = std::fs::File::open(&p).map_err(|source| DatasetError::Io {
            path: p.clone(),
            source,
        })?;
        let bad = |message: String| DatasetError::Format {
            path: p.clone(),
            message,
        };
        let mut labels = Vec::new();
        for (n, line) in std::io::BufReader::new(file).lines().enumerate() {
            let line = line.map_err(|e| bad(e.to_string()))?;
            if n == 0 {
                if line.trim() != LABELS_HEADER {
                    return Err(bad("unexpected header".into()));
                }
                continue;
            }
            let f: Vec<&str> = line.split(',').collect();
            if f.len() != 11 {
                return Err(bad(format!("line {}: expected 11 fields", n + 1)));
            }
            let num = |i: usize| -> Result<f64, DatasetError> {
                f[i].parse::<f64>()
                    .map_err(|_| bad(format!("line {}: field {} is not a number", n + 1, i + 1)))
            };
            labels.push(Label {
                has_robot: f[1] == "1",
                tip: (num(2)?, num(3)?),
                centroid: (num(4)?, num(5)?),
                tail: (num(6)?, num(7)?),
                crop_col0: num(8)? as usize,
                crop_row0: num(9)? as usize,
                mm_per_px: num(10)?,
            });
        }
        let n = labels.len();
        if images.len() != n * INPUT_PX * INPUT_PX * 3 || masks.len() != n * INPUT_PX * INPUT_PX {
            return Err(bad(format!(
                "array sizes do not match {n} labels of {INPUT_PX}x{INPUT_PX} samples"
            )));
        }
        Ok(Self {
            images,
            masks,
            labels,
        })
    }
}
