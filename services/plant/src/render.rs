//! The twin's top camera: a 1020x1020 RGB view of the phantom with the capsule drawn in it.
//! The capsule shows a resin body filled with blue dye, a lighter release cap at the tip and the
//! dark magnet at the tail, so tip and tail are distinguishable as on the rig.

use fieldmaps::phantom::{rasterize, ImageGeometry, Phantom};
use nalgebra::Vector2;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

pub const BODY_RGB: [u8; 3] = [40, 110, 210];
pub const CAP_RGB: [u8; 3] = [130, 175, 235];
pub const MAGNET_RGB: [u8; 3] = [25, 25, 30];
const CANAL_RGB: [f64; 3] = [228.0, 226.0, 214.0];
const WALL_RGB: [f64; 3] = [196.0, 168.0, 160.0];

/// Number of pre-rendered background variants cycled through for temporal noise.
const BACKGROUND_VARIANTS: usize = 4;

/// Ground-truth projection of the capsule in the image (pixels).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CapsuleKeypoints {
    pub tip_px: (f64, f64),
    pub centroid_px: (f64, f64),
    pub tail_px: (f64, f64),
}

pub struct Camera {
    pub geometry: ImageGeometry,
    pub canal_mask: Vec<u8>,
    backgrounds: Vec<Vec<u8>>,
    pub noise_std: f64,
}

impl Camera {
    pub fn new(phantom: &Phantom, geometry: ImageGeometry, rng: &mut ChaCha8Rng, noise_std: f64) -> Self {
        let canal_mask = rasterize(phantom, &geometry);
        let (w, h) = (geometry.width_px as usize, geometry.height_px as usize);
        // Smooth texture from a few random plane waves: agarose is not uniform.
        let waves: Vec<(f64, f64, f64, f64)> = (0..6)
            .map(|_| {
                (
                    rng.random_range(0.005..0.04),
                    rng.random_range(0.0..std::f64::consts::TAU),
                    rng.random_range(0.0..std::f64::consts::TAU),
                    rng.random_range(2.0..6.0),
                )
            })
            .collect();
        let mut texture = vec![0.0f64; w * h];
        for (row, line) in texture.chunks_mut(w).enumerate() {
            for (col, t) in line.iter_mut().enumerate() {
                *t = waves
                    .iter()
                    .map(|(k, dir, phase, amp)| {
                        amp * (k * (col as f64 * dir.cos() + row as f64 * dir.sin()) + phase).sin()
                    })
                    .sum();
            }
        }
        let backgrounds = (0..BACKGROUND_VARIANTS)
            .map(|_| {
                let mut img = vec![0u8; w * h * 3];
                for (i, px) in img.chunks_mut(3).enumerate() {
                    let base = if canal_mask[i] > 0 { CANAL_RGB } else { WALL_RGB };
                    let n = texture[i] + noise_std * gaussian(rng);
                    for (c, b) in px.iter_mut().zip(base) {
                        *c = (b + n).round().clamp(0.0, 255.0) as u8;
                    }
                }
                img
            })
            .collect();
        Self {
            geometry,
            canal_mask,
            backgrounds,
            noise_std,
        }
    }

    /// Background pixels for frame `seq` (variants cycle so the noise changes frame to frame).
    pub fn background(&self, seq: u64) -> &[u8] {
        &self.backgrounds[(seq as usize) % self.backgrounds.len()]
    }

    pub fn keypoints(&self, position: &Vector2<f64>, heading: f64, length_m: f64) -> CapsuleKeypoints {
        let axis = Vector2::new(heading.cos(), heading.sin());
        let px = |p: Vector2<f64>| self.geometry.world_to_px(&p);
        CapsuleKeypoints {
            tip_px: px(position + axis * (length_m / 2.0)),
            centroid_px: px(*position),
            tail_px: px(position - axis * (length_m / 2.0)),
        }
    }

    /// Paints the capsule into `rgb` (a frame already holding the background).
    #[allow(clippy::too_many_arguments)]
    pub fn draw_capsule(
        &self,
        rgb: &mut [u8],
        position: &Vector2<f64>,
        heading: f64,
        length_m: f64,
        diameter_m: f64,
        rng: &mut ChaCha8Rng,
    ) {
        let g = &self.geometry;
        let mm_per_px = g.mm_per_px;
        let px_per_m = 1e3 / mm_per_px;
        let (cx, cy) = g.world_to_px(position);
        let half_len_px = length_m / 2.0 * px_per_m;
        let radius_px = diameter_m / 2.0 * px_per_m;
        let core_half = (half_len_px - radius_px).max(0.0);
        // Image rows grow downwards, so the world heading flips sign in pixel space.
        let (ax, ay) = (heading.cos(), -heading.sin());
        let magnet_half = 0.5e-3 * px_per_m;
        let magnet_center = -half_len_px + 0.3e-3 * px_per_m + magnet_half;
        let cap_start = half_len_px - 1.0e-3 * px_per_m;
        let reach = half_len_px + 2.0;
        let (w, h) = (g.width_px as i64, g.height_px as i64);
        let col0 = ((cx - reach).floor() as i64).clamp(0, w);
        let col1 = ((cx + reach).ceil() as i64 + 1).clamp(0, w);
        let row0 = ((cy - reach).floor() as i64).clamp(0, h);
        let row1 = ((cy + reach).ceil() as i64 + 1).clamp(0, h);
        for row in row0..row1 {
            for col in col0..col1 {
                let dx = col as f64 - cx;
                let dy = row as f64 - cy;
                let along = dx * ax + dy * ay;
                let across = -dx * ay + dy * ax;
                let clamped = along.clamp(-core_half, core_half);
                let dist = ((along - clamped).powi(2) + across.powi(2)).sqrt();
                let coverage = (radius_px + 0.5 - dist).clamp(0.0, 1.0);
                if coverage <= 0.0 {
                    continue;
                }
                let color = if (along - magnet_center).abs() <= magnet_half && across.abs() <= magnet_half {
                    MAGNET_RGB
                } else if along >= cap_start {
                    CAP_RGB
                } else {
                    BODY_RGB
                };
                let noise = self.noise_std * gaussian(rng);
                let i = ((row * w + col) * 3) as usize;
                for c in 0..3 {
                    let bg = rgb[i + c] as f64;
                    let value = bg + coverage * (color[c] as f64 + noise - bg);
                    rgb[i + c] = value.round().clamp(0.0, 255.0) as u8;
                }
            }
        }
    }
}

/// Standard normal sample (Box–Muller), enough for image noise.
fn gaussian(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.random_range(1e-12..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}
