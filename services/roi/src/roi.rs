//! Region-of-interest preprocessing of RGB frames for the UNet.

/// Side of the square crop taken from the full-resolution frame (px).
pub const CROP_PX: usize = 192;
/// Downsampling factor from the crop to the model input.
pub const DOWNSAMPLE: usize = 2;
/// Side of the model input (px).
pub const INPUT_PX: usize = CROP_PX / DOWNSAMPLE;

/// Where a crop sits in the frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Crop {
    /// Column and row of the crop's top-left pixel in the frame.
    pub col0: usize,
    pub row0: usize,
}

impl Crop {
    /// A crop of `CROP_PX` centred as close to (col, row) as the frame allows.
    /// Returns None when the frame is smaller than a crop or the centre is not finite.
    pub fn around(col: f64, row: f64, width: usize, height: usize) -> Option<Self> {
        if width < CROP_PX || height < CROP_PX || !col.is_finite() || !row.is_finite() {
            return None;
        }
        let clamp = |c: f64, size: usize| -> usize {
            let start = (c - CROP_PX as f64 / 2.0).round();
            start.clamp(0.0, (size - CROP_PX) as f64) as usize
        };
        Some(Self {
            col0: clamp(col, width),
            row0: clamp(row, height),
        })
    }

    /// Model-input pixel coordinates (continuous, pixel centres at integers) → frame pixels.
    pub fn input_to_frame(&self, x: f64, y: f64) -> (f64, f64) {
        let f = DOWNSAMPLE as f64;
        (
            self.col0 as f64 + (x + 0.5) * f - 0.5,
            self.row0 as f64 + (y + 0.5) * f - 0.5,
        )
    }

    /// Frame pixels → model-input pixel coordinates.
    pub fn frame_to_input(&self, col: f64, row: f64) -> (f64, f64) {
        let f = DOWNSAMPLE as f64;
        (
            (col - self.col0 as f64 + 0.5) / f - 0.5,
            (row - self.row0 as f64 + 0.5) / f - 0.5,
        )
    }
}

/// Crops and box-downsamples an RGB frame (`width` px per row, tightly packed) into
/// `INPUT_PX x INPUT_PX x 3` u8, row-major.
pub fn extract_rgb(frame: &[u8], width: usize, crop: &Crop, out: &mut Vec<u8>) {
    out.clear();
    out.resize(INPUT_PX * INPUT_PX * 3, 0);
    let f = DOWNSAMPLE;
    let norm = (f * f) as u32;
    for y in 0..INPUT_PX {
        for x in 0..INPUT_PX {
            let mut acc = [0u32; 3];
            for dy in 0..f {
                let row = crop.row0 + y * f + dy;
                let base = (row * width + crop.col0 + x * f) * 3;
                for dx in 0..f {
                    let i = base + dx * 3;
                    for (c, a) in acc.iter_mut().enumerate() {
                        *a += frame.get(i + c).copied().unwrap_or(0) as u32;
                    }
                }
            }
            let o = (y * INPUT_PX + x) * 3;
            for c in 0..3 {
                out[o + c] = ((acc[c] + norm / 2) / norm) as u8;
            }
        }
    }
}

/// Maps model-input pixels back to frame pixels: a training-scale [`Crop`] or a [`ScaledCrop`].
pub trait CropGeometry {
    /// Model-input pixel coordinates (continuous, pixel centres at integers) → frame pixels.
    fn input_to_frame(&self, x: f64, y: f64) -> (f64, f64);
    /// Frame pixels per model-input pixel, along each axis.
    fn frame_px_per_input_px(&self) -> f64;
}

impl CropGeometry for Crop {
    fn input_to_frame(&self, x: f64, y: f64) -> (f64, f64) {
        Crop::input_to_frame(self, x, y)
    }
    fn frame_px_per_input_px(&self) -> f64 {
        DOWNSAMPLE as f64
    }
}

/// A square of `INPUT_PX × scale` frame pixels resampled to the model input: for a camera that
/// shows the capsule at another size than the training crops did, so the model sees it at the
/// size it learnt.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScaledCrop {
    /// Frame coordinates of the crop's top-left corner (the outer corner of its first pixel).
    pub col0: f64,
    pub row0: f64,
    /// Frame pixels per model-input pixel.
    pub scale: f64,
}

impl ScaledCrop {
    /// A crop centred as close to (col, row) as the frame allows, starting on a whole pixel.
    /// None when the frame is smaller than the crop, the centre is not finite or the scale is
    /// not positive.
    pub fn around(col: f64, row: f64, width: usize, height: usize, scale: f64) -> Option<Self> {
        let side = INPUT_PX as f64 * scale;
        if !(scale.is_finite() && scale > 0.0)
            || side > width as f64
            || side > height as f64
            || !col.is_finite()
            || !row.is_finite()
        {
            return None;
        }
        let start = |c: f64, size: usize| {
            (c - side / 2.0)
                .round()
                .clamp(0.0, (size as f64 - side).floor())
        };
        Some(Self {
            col0: start(col, width),
            row0: start(row, height),
            scale,
        })
    }
}

impl CropGeometry for ScaledCrop {
    fn input_to_frame(&self, x: f64, y: f64) -> (f64, f64) {
        (
            self.col0 + (x + 0.5) * self.scale - 0.5,
            self.row0 + (y + 0.5) * self.scale - 0.5,
        )
    }
    fn frame_px_per_input_px(&self) -> f64 {
        self.scale
    }
}

/// For each model-input pixel along one axis, the frame pixels it covers and by how much (the
/// covered length, in frame pixels).
fn area_taps(start: f64, scale: f64, size: usize) -> Vec<Vec<(usize, f32)>> {
    (0..INPUT_PX)
        .map(|i| {
            let (a, b) = (start + i as f64 * scale, start + (i + 1) as f64 * scale);
            let first = a.floor().max(0.0) as usize;
            let last = (b.ceil() as usize).min(size);
            (first..last)
                .filter_map(|p| {
                    let cover = b.min(p as f64 + 1.0) - a.max(p as f64);
                    (cover > 0.0).then_some((p, cover as f32))
                })
                .collect()
        })
        .collect()
}

/// Area-resamples a [`ScaledCrop`] of an RGB frame (`width` × `height`, tightly packed) into
/// `INPUT_PX x INPUT_PX x 3` u8: each model pixel is the mean of the frame pixels it covers,
/// weighted by the area covered (at scale 2 on whole pixels, [`extract_rgb`]'s box average).
pub fn extract_rgb_scaled(
    frame: &[u8],
    width: usize,
    height: usize,
    crop: &ScaledCrop,
    out: &mut Vec<u8>,
) {
    out.clear();
    out.resize(INPUT_PX * INPUT_PX * 3, 0);
    let cols = area_taps(crop.col0, crop.scale, width);
    let rows = area_taps(crop.row0, crop.scale, height);
    for (y, row_taps) in rows.iter().enumerate() {
        for (x, col_taps) in cols.iter().enumerate() {
            let mut acc = [0f32; 3];
            let mut weight = 0f32;
            for &(r, wr) in row_taps {
                for &(c, wc) in col_taps {
                    let i = (r * width + c) * 3;
                    let w = wr * wc;
                    for (k, a) in acc.iter_mut().enumerate() {
                        *a += w * f32::from(frame.get(i + k).copied().unwrap_or(0));
                    }
                    weight += w;
                }
            }
            let o = (y * INPUT_PX + x) * 3;
            for k in 0..3 {
                out[o + k] = if weight > 0.0 {
                    (acc[k] / weight).round().clamp(0.0, 255.0) as u8
                } else {
                    0
                };
            }
        }
    }
}

/// Majority-downsamples a binary mask crop (frame resolution) to the model input.
pub fn extract_mask(mask: &[u8], width: usize, crop: &Crop, out: &mut Vec<u8>) {
    out.clear();
    out.resize(INPUT_PX * INPUT_PX, 0);
    let f = DOWNSAMPLE;
    for y in 0..INPUT_PX {
        for x in 0..INPUT_PX {
            let mut on = 0;
            for dy in 0..f {
                for dx in 0..f {
                    let i = (crop.row0 + y * f + dy) * width + crop.col0 + x * f + dx;
                    on += usize::from(mask.get(i).copied().unwrap_or(0) > 0);
                }
            }
            out[y * INPUT_PX + x] = u8::from(2 * on >= f * f);
        }
    }
}

/// u8 HWC → f32 CHW in [0, 1], the model's input layout.
pub fn to_chw_f32(rgb: &[u8], out: &mut Vec<f32>) {
    let n = INPUT_PX * INPUT_PX;
    out.clear();
    out.resize(3 * n, 0.0);
    for (i, px) in rgb.chunks_exact(3).enumerate().take(n) {
        for c in 0..3 {
            out[c * n + i] = px[c] as f32 / 255.0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crop_is_clamped_and_coordinates_round_trip() {
        let crop = Crop::around(10.0, 1000.0, 1020, 1020).unwrap();
        assert_eq!(
            crop,
            Crop {
                col0: 0,
                row0: 1020 - CROP_PX
            }
        );
        let (x, y) = crop.frame_to_input(57.3, 900.2);
        let (c, r) = crop.input_to_frame(x, y);
        assert!((c - 57.3).abs() < 1e-9 && (r - 900.2).abs() < 1e-9);
        assert!(Crop::around(f64::NAN, 0.0, 1020, 1020).is_none());
        assert!(Crop::around(0.0, 0.0, 100, 100).is_none());
    }

    #[test]
    fn box_downsample_averages() {
        let width = 200;
        let mut frame = vec![0u8; width * 200 * 3];
        // A 2x2 block with values 0, 10, 20, 30 in the red channel at the crop origin.
        let crop = Crop { col0: 4, row0: 2 };
        for (k, (dx, dy)) in [(0, 0), (1, 0), (0, 1), (1, 1)].iter().enumerate() {
            frame[((2 + dy) * width + 4 + dx) * 3] = (k * 10) as u8;
        }
        let mut out = Vec::new();
        extract_rgb(&frame, width, &crop, &mut out);
        assert_eq!(out.len(), INPUT_PX * INPUT_PX * 3);
        assert_eq!(out[0], 15);
        let mut chw = Vec::new();
        to_chw_f32(&out, &mut chw);
        assert!((chw[0] - 15.0 / 255.0).abs() < 1e-6);
    }

    #[test]
    fn scaled_crop_at_the_training_scale_is_the_box_average() {
        let (width, height) = (300, 260);
        let frame: Vec<u8> = (0..width * height * 3)
            .map(|i| ((i * 7919) % 251) as u8)
            .collect();
        let crop = Crop::around(150.0, 120.0, width, height).unwrap();
        let scaled = ScaledCrop::around(150.0, 120.0, width, height, 2.0).unwrap();
        assert_eq!(
            (scaled.col0, scaled.row0),
            (crop.col0 as f64, crop.row0 as f64)
        );
        let (mut boxed, mut resampled) = (Vec::new(), Vec::new());
        extract_rgb(&frame, width, &crop, &mut boxed);
        extract_rgb_scaled(&frame, width, height, &scaled, &mut resampled);
        assert_eq!(boxed, resampled);
        let (c, r) = CropGeometry::input_to_frame(&scaled, 10.25, 40.5);
        assert_eq!((c, r), crop.input_to_frame(10.25, 40.5));
    }

    #[test]
    fn scaled_crop_keeps_an_edge_where_it_is() {
        // A vertical edge at frame column 100 (left dark, right bright), sampled at 1.25 frame
        // px per model px: the model pixels left of it are dark, right of it bright, the one
        // across it in between, and input_to_frame puts the transition at column 100.
        let (width, height) = (240, 240);
        let mut frame = vec![0u8; width * height * 3];
        for row in 0..height {
            for col in 100..width {
                frame[(row * width + col) * 3] = 200;
            }
        }
        let crop = ScaledCrop::around(100.0, 120.0, width, height, 1.25).unwrap();
        let mut out = Vec::new();
        extract_rgb_scaled(&frame, width, height, &crop, &mut out);
        let red = |x: usize| out[(48 * INPUT_PX + x) * 3];
        let edge = (0..INPUT_PX).find(|&x| red(x) > 0).unwrap();
        let (col, _) = CropGeometry::input_to_frame(&crop, edge as f64, 48.0);
        assert!(
            (col - 100.0).abs() <= 1.25,
            "edge at model px {edge} → frame {col}"
        );
        assert_eq!(red(edge - 1), 0);
        assert_eq!(red(edge + 1), 200);
        assert!(ScaledCrop::around(100.0, 100.0, 100, 100, 1.25).is_none());
        assert!(ScaledCrop::around(100.0, 100.0, 240, 240, 0.0).is_none());
    }
}
