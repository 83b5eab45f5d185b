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
}
