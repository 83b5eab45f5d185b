//! Binary canal mask on the camera's top view: from the parametric phantom or from a
//! user-supplied (hand-outlined) PNG, white = canal.
//!
//! PNG rules: 8-bit (or lower, expanded to 8-bit) grayscale, grayscale+alpha, RGB, RGBA or
//! palette; the image size must match the [`ImageGeometry`] it is loaded for (1020 × 1020 by
//! default). A pixel is canal when its luminance is ≥ 128 (and, with alpha, when it is not
//! transparent). 16-bit images are refused with a clear error rather than guessed at.

use std::fs::File;
use std::io::{BufReader, BufWriter};
use std::path::{Path, PathBuf};

use nalgebra::Vector2;
use thiserror::Error;

use crate::phantom::{rasterize, ImageGeometry, Phantom, MASK_CANAL, MASK_WALL};

#[derive(Debug, Error)]
pub enum MaskError {
    #[error("cannot open mask {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("mask {path} is not a readable PNG: {message}")]
    Decode { path: PathBuf, message: String },
    #[error("mask {path} is {width}x{height} px, expected {expected_width}x{expected_height} px")]
    WrongSize {
        path: PathBuf,
        width: u32,
        height: u32,
        expected_width: u32,
        expected_height: u32,
    },
    #[error("mask {path} has {bits}-bit samples; save it as an 8-bit PNG")]
    NotEightBit { path: PathBuf, bits: u8 },
    #[error("mask {path} contains no canal (white) pixels")]
    NoCanal { path: PathBuf },
    #[error("cannot write mask {path}: {message}")]
    Write { path: PathBuf, message: String },
    #[error("invalid mask: {0}")]
    Invalid(String),
}

/// A binary canal mask (row-major, row 0 at the top of the image) with its image geometry.
#[derive(Debug, Clone, PartialEq)]
pub struct CanalMask {
    geometry: ImageGeometry,
    canal: Vec<bool>,
}

impl CanalMask {
    /// From row-major pixels (`true` = canal); the length must match the geometry.
    pub fn from_pixels(geometry: ImageGeometry, canal: Vec<bool>) -> Result<Self, MaskError> {
        geometry
            .validate()
            .map_err(|e| MaskError::Invalid(e.to_string()))?;
        let n = geometry.width_px as usize * geometry.height_px as usize;
        if canal.len() != n {
            return Err(MaskError::Invalid(format!(
                "{} pixels for a {}x{} image",
                canal.len(),
                geometry.width_px,
                geometry.height_px
            )));
        }
        Ok(Self { geometry, canal })
    }

    /// The parametric phantom rasterized on `geometry`.
    pub fn from_phantom(phantom: &Phantom, geometry: &ImageGeometry) -> Result<Self, MaskError> {
        let raster = rasterize(phantom, geometry);
        Self::from_pixels(*geometry, raster.iter().map(|&v| v == MASK_CANAL).collect())
    }

    /// Loads a PNG (white = canal) that must have `geometry`'s size.
    pub fn load_png(path: &Path, geometry: &ImageGeometry) -> Result<Self, MaskError> {
        let file = File::open(path).map_err(|source| MaskError::Io {
            path: path.to_owned(),
            source,
        })?;
        let decode = |e: png::DecodingError| MaskError::Decode {
            path: path.to_owned(),
            message: e.to_string(),
        };
        let mut decoder = png::Decoder::new(BufReader::new(file));
        decoder.set_transformations(png::Transformations::EXPAND);
        let mut reader = decoder.read_info().map_err(decode)?;
        let (width, height) = {
            let info = reader.info();
            (info.width, info.height)
        };
        if (width, height) != (geometry.width_px, geometry.height_px) {
            return Err(MaskError::WrongSize {
                path: path.to_owned(),
                width,
                height,
                expected_width: geometry.width_px,
                expected_height: geometry.height_px,
            });
        }
        let (color, depth) = reader.output_color_type();
        if depth != png::BitDepth::Eight {
            return Err(MaskError::NotEightBit {
                path: path.to_owned(),
                bits: depth as u8,
            });
        }
        let size = reader
            .output_buffer_size()
            .ok_or_else(|| MaskError::Decode {
                path: path.to_owned(),
                message: "image too large".into(),
            })?;
        let mut buf = vec![0u8; size];
        let frame = reader.next_frame(&mut buf).map_err(decode)?;
        let channels = match color {
            png::ColorType::Grayscale => 1,
            png::ColorType::GrayscaleAlpha => 2,
            png::ColorType::Rgb => 3,
            png::ColorType::Rgba => 4,
            png::ColorType::Indexed => {
                return Err(MaskError::Decode {
                    path: path.to_owned(),
                    message: "palette image was not expanded".into(),
                })
            }
        };
        let stride = frame.line_size;
        let mut canal = Vec::with_capacity(width as usize * height as usize);
        for row in buf.chunks(stride).take(height as usize) {
            for px in row.chunks(channels).take(width as usize) {
                let luminance = match channels {
                    1 | 2 => f64::from(px[0]),
                    _ => {
                        0.299 * f64::from(px[0])
                            + 0.587 * f64::from(px[1])
                            + 0.114 * f64::from(px[2])
                    }
                };
                let opaque = match channels {
                    2 => px[1] >= 128,
                    4 => px[3] >= 128,
                    _ => true,
                };
                canal.push(opaque && luminance >= 128.0);
            }
        }
        if !canal.iter().any(|&c| c) {
            return Err(MaskError::NoCanal {
                path: path.to_owned(),
            });
        }
        Self::from_pixels(*geometry, canal)
    }

    /// Writes the mask as an 8-bit grayscale PNG (canal 255, wall 0).
    pub fn save_png(&self, path: &Path) -> Result<(), MaskError> {
        let write = |message: String| MaskError::Write {
            path: path.to_owned(),
            message,
        };
        let file = File::create(path).map_err(|e| write(e.to_string()))?;
        let mut encoder = png::Encoder::new(
            BufWriter::new(file),
            self.geometry.width_px,
            self.geometry.height_px,
        );
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(|e| write(e.to_string()))?;
        writer
            .write_image_data(&self.to_bytes())
            .map_err(|e| write(e.to_string()))?;
        writer.finish().map_err(|e| write(e.to_string()))
    }

    /// Row-major bytes, [`MASK_CANAL`] / [`MASK_WALL`].
    pub fn to_bytes(&self) -> Vec<u8> {
        self.canal
            .iter()
            .map(|&c| if c { MASK_CANAL } else { MASK_WALL })
            .collect()
    }

    pub fn geometry(&self) -> &ImageGeometry {
        &self.geometry
    }

    pub fn width(&self) -> u32 {
        self.geometry.width_px
    }

    pub fn height(&self) -> u32 {
        self.geometry.height_px
    }

    /// Whether pixel (col, row) is canal; out-of-image is wall.
    pub fn is_canal_px(&self, col: i64, row: i64) -> bool {
        if col < 0 || row < 0 || col >= i64::from(self.width()) || row >= i64::from(self.height()) {
            return false;
        }
        self.canal[row as usize * self.width() as usize + col as usize]
    }

    /// Whether world point `p` (m) falls on a canal pixel; outside the image or non-finite is
    /// wall.
    pub fn contains(&self, p: &Vector2<f64>) -> bool {
        self.geometry
            .pixel_of(p)
            .is_some_and(|(c, r)| self.is_canal_px(i64::from(c), i64::from(r)))
    }

    /// Number of canal pixels.
    pub fn canal_pixels(&self) -> usize {
        self.canal.iter().filter(|&&c| c).count()
    }

    /// Exact Euclidean distance (m) from every canal pixel centre to the nearest wall pixel
    /// centre (0 on wall pixels); row-major. Felzenszwalb–Huttenlocher separable transform,
    /// O(pixels). Pixels outside the image count as canal (an open port is not a wall).
    pub fn clearance_map(&self) -> Vec<f64> {
        let walls: Vec<bool> = self.canal.iter().map(|&c| !c).collect();
        let px_m = self.geometry.mm_per_px * 1e-3;
        squared_distance_px(self.width() as usize, self.height() as usize, &walls)
            .iter()
            .map(|&v| {
                if v >= UNREACHED {
                    f64::INFINITY
                } else {
                    v.sqrt() * px_m
                }
            })
            .collect()
    }

    /// The mask seen through another image geometry (e.g. the camera's): one byte per pixel of
    /// `geometry`, row-major, `MASK_CANAL` where the pixel centre falls on canal, else
    /// `MASK_WALL`. Identity when `geometry` is the mask's own.
    pub fn resampled(&self, geometry: &ImageGeometry) -> Vec<u8> {
        if geometry == &self.geometry {
            return self.to_bytes();
        }
        let (w, h) = (geometry.width_px as usize, geometry.height_px as usize);
        let mut out = vec![MASK_WALL; w * h];
        for (row, line) in out.chunks_exact_mut(w.max(1)).enumerate() {
            for (col, px) in line.iter_mut().enumerate() {
                if self.contains(&geometry.px_to_world(col as f64, row as f64)) {
                    *px = MASK_CANAL;
                }
            }
        }
        out
    }

    /// Canal flags, row-major (true = canal).
    pub fn canal_flags(&self) -> &[bool] {
        &self.canal
    }

    /// The canal's edge (m): centres of canal pixels with a wall pixel beside them, sampled
    /// every `step` pixels in both directions (for drawing the outline).
    pub fn outline_m(&self, step: usize) -> Vec<Vector2<f64>> {
        let step = step.max(1);
        let (w, h) = (i64::from(self.width()), i64::from(self.height()));
        let mut points = Vec::new();
        for row in (0..h).step_by(step) {
            for col in (0..w).step_by(step) {
                let edge = self.is_canal_px(col, row)
                    && [(1, 0), (-1, 0), (0, 1), (0, -1)]
                        .iter()
                        .any(|(dc, dr)| !self.is_canal_px(col + dc, row + dr));
                if edge {
                    points.push(self.geometry.px_to_world(col as f64, row as f64));
                }
            }
        }
        points
    }
}

/// What [`squared_distance_px`] returns where no source pixel exists.
pub(crate) const UNREACHED: f64 = 1e20;

/// Exact squared Euclidean distance (px²) from every pixel centre of a `w` × `h` grid to the
/// nearest pixel whose `sources` flag is set (0 on those); [`UNREACHED`] when there is none.
/// Felzenszwalb–Huttenlocher separable transform, O(pixels).
pub(crate) fn squared_distance_px(w: usize, h: usize, sources: &[bool]) -> Vec<f64> {
    let mut d2: Vec<f64> = sources
        .iter()
        .map(|&s| if s { 0.0 } else { UNREACHED })
        .collect();
    let mut line = Vec::new();
    let mut out = Vec::new();
    for c in 0..w {
        line.clear();
        line.extend((0..h).map(|r| d2[r * w + c]));
        edt_1d(&line, &mut out);
        for r in 0..h {
            d2[r * w + c] = out[r].min(UNREACHED);
        }
    }
    for r in 0..h {
        line.clear();
        line.extend_from_slice(&d2[r * w..(r + 1) * w]);
        edt_1d(&line, &mut out);
        for (dst, &v) in d2[r * w..(r + 1) * w].iter_mut().zip(&out) {
            *dst = v.min(UNREACHED);
        }
    }
    d2
}

/// 1D squared distance transform of a sampled function (Felzenszwalb & Huttenlocher 2012).
fn edt_1d(f: &[f64], out: &mut Vec<f64>) {
    let n = f.len();
    out.clear();
    out.resize(n, 0.0);
    if n == 0 {
        return;
    }
    let mut v = vec![0usize; n];
    let mut z = vec![0.0f64; n + 1];
    let mut k = 0usize;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    let inter = |q: usize, p: usize| {
        ((f[q] + (q * q) as f64) - (f[p] + (p * p) as f64)) / (2.0 * (q as f64 - p as f64))
    };
    for q in 1..n {
        let mut s = inter(q, v[k]);
        // z[0] = −∞, so this stops at k = 0 at the latest.
        while k > 0 && s <= z[k] {
            k -= 1;
            s = inter(q, v[k]);
        }
        k += 1;
        v[k] = q;
        z[k] = s;
        z[k + 1] = f64::INFINITY;
    }
    k = 0;
    for (q, o) in out.iter_mut().enumerate() {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let p = v[k];
        let d = q as f64 - p as f64;
        *o = d * d + f[p];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!("millinav-mask-{}-{name}", std::process::id()))
    }

    fn write_png(
        path: &Path,
        w: u32,
        h: u32,
        color: png::ColorType,
        depth: png::BitDepth,
        data: &[u8],
    ) {
        let file = File::create(path).unwrap();
        let mut enc = png::Encoder::new(BufWriter::new(file), w, h);
        enc.set_color(color);
        enc.set_depth(depth);
        let mut wr = enc.write_header().unwrap();
        wr.write_image_data(data).unwrap();
        wr.finish().unwrap();
    }

    #[test]
    fn phantom_mask_round_trips_through_png() {
        let g = crate::phantom::tests::geom();
        let mask = CanalMask::from_phantom(&crate::phantom::tests::heart(), &g).unwrap();
        let path = tmp("roundtrip.png");
        mask.save_png(&path).unwrap();
        let back = CanalMask::load_png(&path, &g).unwrap();
        assert_eq!(back, mask);
        let ph = crate::phantom::tests::heart();
        assert!(back.contains(&ph.default_start()));
        assert!(!back.contains(&Vector2::new(0.045, -0.045)));
        assert!(!back.contains(&Vector2::new(f64::NAN, 0.0)));
        std::fs::remove_file(&path).ok();
    }

    #[test]
    fn rgb_and_small_geometry() {
        let g = ImageGeometry {
            width_px: 4,
            height_px: 2,
            mm_per_px: 1.0,
            origin_x_mm: 0.0,
            origin_y_mm: 2.0,
        };
        let mut data = vec![0u8; 4 * 2 * 3];
        data[3..6].copy_from_slice(&[255, 255, 255]); // (col 1, row 0)
        data[12 + 9..12 + 12].copy_from_slice(&[200, 190, 180]); // (col 3, row 1)
        let path = tmp("rgb.png");
        write_png(
            &path,
            4,
            2,
            png::ColorType::Rgb,
            png::BitDepth::Eight,
            &data,
        );
        let m = CanalMask::load_png(&path, &g).unwrap();
        assert_eq!(m.canal_pixels(), 2);
        assert!(m.is_canal_px(1, 0) && m.is_canal_px(3, 1) && !m.is_canal_px(0, 0));
        std::fs::remove_file(&path).ok();
    }

    #[test]
    fn clear_errors() {
        let g = crate::phantom::tests::geom();
        let missing = CanalMask::load_png(Path::new("/nonexistent/mask.png"), &g).unwrap_err();
        assert!(matches!(missing, MaskError::Io { .. }), "{missing}");

        let path = tmp("small.png");
        write_png(
            &path,
            8,
            8,
            png::ColorType::Grayscale,
            png::BitDepth::Eight,
            &[255; 64],
        );
        let err = CanalMask::load_png(&path, &g).unwrap_err();
        assert!(err.to_string().contains("expected 1020x1020"), "{err}");

        let g8 = ImageGeometry {
            width_px: 8,
            height_px: 8,
            ..g
        };
        write_png(
            &path,
            8,
            8,
            png::ColorType::Grayscale,
            png::BitDepth::Sixteen,
            &[255; 128],
        );
        let err = CanalMask::load_png(&path, &g8).unwrap_err();
        assert!(
            matches!(err, MaskError::NotEightBit { bits: 16, .. }),
            "{err}"
        );

        write_png(
            &path,
            8,
            8,
            png::ColorType::Grayscale,
            png::BitDepth::Eight,
            &[0; 64],
        );
        let err = CanalMask::load_png(&path, &g8).unwrap_err();
        assert!(matches!(err, MaskError::NoCanal { .. }), "{err}");

        std::fs::write(&path, b"not a png at all").unwrap();
        let err = CanalMask::load_png(&path, &g8).unwrap_err();
        assert!(matches!(err, MaskError::Decode { .. }), "{err}");
        std::fs::remove_file(&path).ok();
    }

    #[test]
    fn clearance_matches_the_phantom_sdf() {
        let g = crate::phantom::tests::geom();
        let ph = crate::phantom::tests::heart();
        let mask = CanalMask::from_phantom(&ph, &g).unwrap();
        let clear = mask.clearance_map();
        let px = g.mm_per_px * 1e-3;
        // The right atrium's centre: the disc radius (15 mm) bounds the clearance.
        for p in [Vector2::new(-0.016, 0.010), Vector2::new(0.004, -0.024)] {
            let (c, r) = g.pixel_of(&p).unwrap();
            let d = clear[r as usize * g.width_px as usize + c as usize];
            let sdf = ph.clearance(&p);
            // The union SDF underestimates clearance inside overlaps; never by more than that.
            assert!(d >= sdf - 2.0 * px, "{p:?}: edt {d} vs sdf {sdf}");
            assert!(d < 0.02, "{d}");
        }
        let (c, r) = g.pixel_of(&Vector2::new(-0.030, 0.010)).unwrap();
        let d = clear[r as usize * g.width_px as usize + c as usize];
        assert!((d - 0.001).abs() < 2.0 * px, "{d}");
    }
}
