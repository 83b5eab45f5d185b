//! A real camera's lens and registration (`[camera.calibration]`): the pinhole + OpenCV
//! `plumb_bob` distortion model and the homography from undistorted pixels to the world plane.
//! One implementation for the twin (which renders through the lens) and the camera service
//! (which rectifies through it), so the two agree to rounding; the calib tool checks it against
//! OpenCV's `projectPoints`.

use nalgebra::{Matrix3, Vector3};

use crate::phantom::ImageGeometry;
use crate::rigfile::CameraCalibration;

/// Fixed-point iterations that invert the distortion (OpenCV's `undistortPoints` uses 5; lenses
/// with a few percent of barrel need more to reach 1e-6 px).
const UNDISTORT_ITERATIONS: usize = 20;

impl CameraCalibration {
    fn k(&self) -> (f64, f64, f64, f64) {
        let k = &self.camera_matrix;
        (k[0], k[4], k[2], k[5])
    }

    /// Normalized pinhole coordinates → distorted normalized coordinates (plumb_bob).
    pub fn distort_normalized(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.distortion_coefficients;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Distorted normalized coordinates → normalized pinhole coordinates (iterative inverse).
    pub fn undistort_normalized(&self, xd: f64, yd: f64) -> (f64, f64) {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..UNDISTORT_ITERATIONS {
            let (dx, dy) = self.distort_normalized(x, y);
            x -= dx - xd;
            y -= dy - yd;
        }
        (x, y)
    }

    /// The homography (undistorted pixels → world mm), when the camera is registered.
    fn homography(&self) -> Option<Matrix3<f64>> {
        self.image_to_world_mm.map(|h| Matrix3::from_row_slice(&h))
    }

    /// World point (mm, on the control plane) → raw (distorted) pixel (col, row); none without
    /// a registration or for a point on the horizon.
    pub fn raw_pixel_of_world_mm(&self, x_mm: f64, y_mm: f64) -> Option<(f64, f64)> {
        let inverse = self.homography()?.try_inverse()?;
        let p = inverse * Vector3::new(x_mm, y_mm, 1.0);
        if p.z.abs() < f64::EPSILON {
            return None;
        }
        let (fx, fy, cx, cy) = self.k();
        let (xn, yn) = ((p.x / p.z - cx) / fx, (p.y / p.z - cy) / fy);
        let (xd, yd) = self.distort_normalized(xn, yn);
        Some((fx * xd + cx, fy * yd + cy))
    }

    /// Raw (distorted) pixel (col, row) → world point (mm); none without a registration.
    pub fn world_mm_of_raw_pixel(&self, col: f64, row: f64) -> Option<[f64; 2]> {
        let h = self.homography()?;
        let (fx, fy, cx, cy) = self.k();
        let (xn, yn) = self.undistort_normalized((col - cx) / fx, (row - cy) / fy);
        let p = h * Vector3::new(fx * xn + cx, fy * yn + cy, 1.0);
        (p.z.abs() >= f64::EPSILON).then(|| [p.x / p.z, p.y / p.z])
    }

    /// For every pixel of the canonical `view` (row-major), the raw pixel it shows: the maps of
    /// one `remap` that rectifies a raw frame onto the view. Errors when the camera is not
    /// registered or when part of the view falls outside the raw image (a phantom vision would
    /// see half-black).
    pub fn rectification_map(&self, view: &ImageGeometry) -> Result<PixelMap, String> {
        if self.image_to_world_mm.is_none() {
            return Err(
                "the camera has no registration (camera.calibration.image_to_world_mm): \
                 run `calib homography` first"
                    .into(),
            );
        }
        let (w, h) = (view.width_px as usize, view.height_px as usize);
        let mut map = PixelMap {
            width: w,
            height: h,
            cols: Vec::with_capacity(w * h),
            rows: Vec::with_capacity(w * h),
        };
        let (max_col, max_row) = (
            f64::from(self.image_width) - 0.5,
            f64::from(self.image_height) - 0.5,
        );
        let mut outside = 0usize;
        for row in 0..h {
            for col in 0..w {
                let x_mm = view.origin_x_mm + (col as f64 + 0.5) * view.mm_per_px;
                let y_mm = view.origin_y_mm - (row as f64 + 0.5) * view.mm_per_px;
                let (u, v) = self
                    .raw_pixel_of_world_mm(x_mm, y_mm)
                    .unwrap_or((f64::NAN, f64::NAN));
                if !(u >= -0.5 && v >= -0.5 && u <= max_col && v <= max_row) {
                    outside += 1;
                }
                map.cols.push(u as f32);
                map.rows.push(v as f32);
            }
        }
        if outside > 0 {
            return Err(format!(
                "{outside} of the canonical view's {} pixels map outside the raw {}x{} image: \
                 the registration (image_to_world_mm) or the lens does not see the whole view",
                w * h,
                self.image_width,
                self.image_height
            ));
        }
        Ok(map)
    }

    /// For every raw pixel (row-major), the canonical-view pixel it sees (col, row), NaN where
    /// the lens maps it nowhere: the twin renders the raw frame from its canonical render with
    /// this map.
    pub fn raw_view_map(&self, view: &ImageGeometry) -> Result<PixelMap, String> {
        if self.image_to_world_mm.is_none() {
            return Err(
                "the camera has no registration (camera.calibration.image_to_world_mm)".into(),
            );
        }
        let (w, h) = (self.image_width as usize, self.image_height as usize);
        let mapping = view.pixel_mapping();
        let mut map = PixelMap {
            width: w,
            height: h,
            cols: Vec::with_capacity(w * h),
            rows: Vec::with_capacity(w * h),
        };
        for row in 0..h {
            for col in 0..w {
                let (c, r) = match self.world_mm_of_raw_pixel(col as f64, row as f64) {
                    Some([x, y]) => mapping.world_to_pixel([x * 1e-3, y * 1e-3]),
                    None => (f64::NAN, f64::NAN),
                };
                map.cols.push(c as f32);
                map.rows.push(r as f32);
            }
        }
        Ok(map)
    }
}

/// A per-pixel source map (what OpenCV's `remap` takes as map_x, map_y): output pixel i reads
/// the source at (`cols[i]`, `rows[i]`), pixel centres at integers.
#[derive(Debug, Clone, PartialEq)]
pub struct PixelMap {
    pub width: usize,
    pub height: usize,
    pub cols: Vec<f32>,
    pub rows: Vec<f32>,
}

impl PixelMap {
    /// The bilinear taps of this map for a source of `source_width` × `source_height` pixels,
    /// `channels` interleaved bytes each, rows `source_stride` bytes apart: computed once, so
    /// every frame only gathers and blends (a 1280 × 1024 raw frame every 10 ms).
    pub fn sampler(
        &self,
        source_width: usize,
        source_height: usize,
        source_stride: usize,
        channels: usize,
    ) -> BilinearSampler {
        let taps = self
            .cols
            .iter()
            .zip(&self.rows)
            .map(|(&u, &v)| {
                let (c0, r0) = (u.floor(), v.floor());
                // NaN fails every comparison: a pixel the lens maps nowhere is outside.
                let inside = c0 >= 0.0
                    && r0 >= 0.0
                    && (c0 as usize) + 1 < source_width
                    && (r0 as usize) + 1 < source_height;
                if !inside {
                    return Tap::OUTSIDE;
                }
                let offset = r0 as usize * source_stride + c0 as usize * channels;
                let weight = |fraction: f32| (fraction * WEIGHT_ONE as f32).round() as u16;
                Tap {
                    offset: u32::try_from(offset).unwrap_or(u32::MAX),
                    col_weight: weight(u - c0),
                    row_weight: weight(v - r0),
                }
            })
            .collect();
        BilinearSampler {
            taps,
            source_stride,
            channels,
            source_len: source_height.saturating_sub(1) * source_stride + source_width * channels,
        }
    }
}

/// Fixed-point weight of a whole pixel: fractions are sampled in 1/256 (OpenCV's INTER_LINEAR
/// remap uses 1/32).
const WEIGHT_ONE: u32 = 256;

/// One output pixel's source: the byte offset of its top-left neighbour and its fractional
/// position towards the right and lower neighbours.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Tap {
    offset: u32,
    col_weight: u16,
    row_weight: u16,
}

impl Tap {
    const OUTSIDE: Tap = Tap {
        offset: u32::MAX,
        col_weight: 0,
        row_weight: 0,
    };
}

/// A [`PixelMap`] compiled for one source layout ([`PixelMap::sampler`]).
#[derive(Debug, Clone, PartialEq)]
pub struct BilinearSampler {
    taps: Vec<Tap>,
    source_stride: usize,
    channels: usize,
    source_len: usize,
}

impl BilinearSampler {
    /// Samples `source` bilinearly into `out` (the map's size, `channels` bytes per pixel,
    /// packed); outside the source: black. The same sampling as OpenCV's INTER_LINEAR remap.
    /// A source shorter than the layout the sampler was built for reads as black.
    pub fn remap(&self, source: &[u8], out: &mut [u8]) {
        if source.len() < self.source_len {
            out.fill(0);
            return;
        }
        // A literal channel count lets the compiler unroll the per-pixel work.
        match self.channels {
            1 => self.remap_with(source, out, 1),
            3 => self.remap_with(source, out, 3),
            4 => self.remap_with(source, out, 4),
            channels => self.remap_with(source, out, channels),
        }
    }

    #[inline(always)]
    fn remap_with(&self, source: &[u8], out: &mut [u8], channels: usize) {
        let stride = self.source_stride;
        for (tap, px) in self.taps.iter().zip(out.chunks_exact_mut(channels)) {
            let base = tap.offset as usize;
            let (Some(top), Some(bottom)) = (
                source.get(base..base + 2 * channels),
                source.get(base + stride..base + stride + 2 * channels),
            ) else {
                px.fill(0);
                continue;
            };
            let (wc, wr) = (u32::from(tap.col_weight), u32::from(tap.row_weight));
            for (k, p) in px.iter_mut().enumerate() {
                *p = blend(
                    [top[k], top[k + channels], bottom[k], bottom[k + channels]],
                    wc,
                    wr,
                );
            }
        }
    }
}

/// Bilinear blend of a pixel's four neighbours (top-left, top-right, bottom-left, bottom-right)
/// with fixed-point weights towards the right (`wc`) and down (`wr`), rounded.
#[inline]
fn blend([top_left, top_right, bottom_left, bottom_right]: [u8; 4], wc: u32, wr: u32) -> u8 {
    let top = u32::from(top_left) * (WEIGHT_ONE - wc) + u32::from(top_right) * wc;
    let bottom = u32::from(bottom_left) * (WEIGHT_ONE - wc) + u32::from(bottom_right) * wc;
    let value = (top * (WEIGHT_ONE - wr) + bottom * wr + WEIGHT_ONE * WEIGHT_ONE / 2)
        / (WEIGHT_ONE * WEIGHT_ONE);
    value.min(255) as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lens() -> CameraCalibration {
        // A 1280 x 1024 camera 300 mm above a 92 mm view, tilted a little, with barrel.
        CameraCalibration {
            image_width: 1280,
            image_height: 1024,
            camera_matrix: [2400.0, 0.0, 645.0, 0.0, 2410.0, 508.0, 0.0, 0.0, 1.0],
            distortion_coefficients: [-0.12, 0.05, 0.0008, -0.0005, 0.0],
            reprojection_error_px: None,
            image_to_world_mm: Some([0.1, 0.004, -64.0, -0.003, -0.1, 51.0, 0.0, 0.00002, 1.0]),
            registration_residual_mm: None,
        }
    }

    #[test]
    fn undistortion_inverts_distortion() {
        let lens = lens();
        for (x, y) in [(0.0, 0.0), (0.2, -0.1), (-0.25, 0.2), (0.27, 0.21)] {
            let (xd, yd) = lens.distort_normalized(x, y);
            let (xu, yu) = lens.undistort_normalized(xd, yd);
            assert!((xu - x).abs() < 1e-9 && (yu - y).abs() < 1e-9, "{x} {y}");
        }
    }

    #[test]
    fn raw_pixels_and_world_points_round_trip() {
        let lens = lens();
        for (x, y) in [(0.0, 0.0), (-40.0, 40.0), (40.0, -40.0), (12.5, -3.0)] {
            let (u, v) = lens.raw_pixel_of_world_mm(x, y).unwrap();
            let [xb, yb] = lens.world_mm_of_raw_pixel(u, v).unwrap();
            assert!(
                (xb - x).abs() < 1e-6 && (yb - y).abs() < 1e-6,
                "{x} {y} -> {xb} {yb}"
            );
        }
    }

    #[test]
    fn a_view_outside_the_image_is_refused() {
        let lens = lens();
        let inside = ImageGeometry {
            width_px: 200,
            height_px: 200,
            mm_per_px: 0.4,
            origin_x_mm: -40.0,
            origin_y_mm: 40.0,
        };
        assert!(lens.rectification_map(&inside).is_ok());
        let too_wide = ImageGeometry {
            mm_per_px: 1.0,
            origin_x_mm: -100.0,
            origin_y_mm: 100.0,
            ..inside
        };
        let error = lens.rectification_map(&too_wide).unwrap_err();
        assert!(error.contains("outside the raw 1280x1024 image"), "{error}");
        let mut unregistered = lens;
        unregistered.image_to_world_mm = None;
        assert!(unregistered.rectification_map(&inside).is_err());
    }

    #[test]
    fn remap_samples_bilinearly() {
        // A 2x2 gray source; the map reads its centre and a point outside.
        let source = [0u8, 100, 200, 255];
        let map = PixelMap {
            width: 2,
            height: 1,
            cols: vec![0.5, 5.0],
            rows: vec![0.5, 0.0],
        };
        let mut out = [9u8; 2];
        map.sampler(2, 2, 2, 1).remap(&source, &mut out);
        assert_eq!(out, [139, 0]);
    }

    #[test]
    fn fixed_point_remap_matches_float_bilinear_sampling() {
        // A 3 × 3 RGB source in a padded stride, sampled at fractions that are not powers of two.
        let (w, h, channels, stride) = (3usize, 3usize, 3usize, 10usize);
        let source: Vec<u8> = (0..h * stride)
            .map(|i| ((i * 37 + 11) % 256) as u8)
            .collect();
        let points = [
            (0.1f32, 0.7f32),
            (1.33, 0.2),
            (0.9, 1.9),
            (1.999, 1.001),
            (0.0, 0.0),
        ];
        let map = PixelMap {
            width: points.len(),
            height: 1,
            cols: points.iter().map(|p| p.0).collect(),
            rows: points.iter().map(|p| p.1).collect(),
        };
        let mut out = vec![0u8; points.len() * channels];
        map.sampler(w, h, stride, channels).remap(&source, &mut out);
        for (i, &(u, v)) in points.iter().enumerate() {
            let (c0, r0) = (u.floor() as usize, v.floor() as usize);
            let (fc, fr) = (u - u.floor(), v - v.floor());
            for k in 0..channels {
                let at = |c: usize, r: usize| f32::from(source[r * stride + c * channels + k]);
                let top = at(c0, r0) * (1.0 - fc) + at(c0 + 1, r0) * fc;
                let bottom = at(c0, r0 + 1) * (1.0 - fc) + at(c0 + 1, r0 + 1) * fc;
                let expected = top * (1.0 - fr) + bottom * fr;
                let got = f32::from(out[i * channels + k]);
                assert!(
                    (got - expected).abs() <= 1.0,
                    "point {i} channel {k}: {got} vs {expected}"
                );
            }
        }
        // A source shorter than the layout reads as black rather than out of bounds.
        map.sampler(w, h, stride, channels)
            .remap(&source[..5], &mut out);
        assert!(out.iter().all(|&b| b == 0));
    }
}
