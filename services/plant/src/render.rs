//! The twin's top camera: an RGB view of the phantom at the rig's camera size and scale,
//! with the capsule drawn in it.
//! The capsule shows a resin body filled with blue dye, a lighter release cap at the tip and the
//! dark magnet at the tail, so tip and tail are distinguishable as on the rig.
//!
//! Camera effects (`[plant.camera]`, [`CameraConfig`]):
//! - blur: `blur_passes` separable binomial [1 2 1]/4 passes (defocus/motion softening). The
//!   background variants are blurred once at construction; per frame only the capsule's region
//!   is re-rendered from the sharp background and blurred, which is bit-identical to blurring
//!   the whole frame (the region carries a margin of 2 × `blur_passes` pixels) at a fraction
//!   of the cost;
//! - lighting drift: a slow global gain g(t) = 1 + A·(0.7·sin(ωt + φ₁) + 0.3·sin(ωt/0.37 + φ₂))
//!   with ω = 2π/T, quantised to 1/256 and applied to the whole frame with integer arithmetic
//!   (one vectorised pass);
//! - latency: `latency_frames` is applied by the plant loop, which keeps a ring of past states
//!   and renders frame k from the state of frame k − latency; the stamp's capture time is that
//!   state's time and its grab time the publish time, like a camera whose driver timestamps the
//!   exposure (V4L2 buffer timestamps), so control can measure the delay;
//! - exposure period: with `exposure_period_frames` N the camera exposes every N-th frame and
//!   the frames between repeat the latest exposure (same image, same capture stamp): a camera
//!   or vision slower than the coil loop, which control bridges with its latency predictor;
//! - ground truth for datasets: [`Camera::render_sample`] returns the frame, a per-pixel class
//!   mask ([`MASK_BODY`], [`MASK_CAP`], [`MASK_MAGNET`], 0 elsewhere; pixel centre inside the
//!   capsule, before blur) and the tip/centroid/tail keypoints.

use fieldmaps::mask::CanalMask;
use fieldmaps::phantom::ImageGeometry;
use nalgebra::Vector2;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

pub const BODY_RGB: [u8; 3] = [40, 110, 210];
pub const CAP_RGB: [u8; 3] = [130, 175, 235];
pub const MAGNET_RGB: [u8; 3] = [25, 25, 30];
const CANAL_RGB: [f64; 3] = [228.0, 226.0, 214.0];
const WALL_RGB: [f64; 3] = [196.0, 168.0, 160.0];

/// Colours and shading of the rendered scene. The default is the twin's look; dataset
/// generation varies it (domain randomization) so a model does not learn one palette.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Palette {
    pub canal_rgb: [f64; 3],
    pub wall_rgb: [f64; 3],
    pub body_rgb: [u8; 3],
    pub cap_rgb: [u8; 3],
    pub magnet_rgb: [u8; 3],
    /// Darkening toward the capsule's rim, a lit cylinder seen from above: the colour is
    /// scaled by 1 − rim_shading·(d/r)², d the distance from the axis (0 = flat).
    pub rim_shading: f64,
    /// Grey levels a specular stripe along the capsule adds at its peak (0 = none).
    pub specular: f64,
    /// Where the stripe runs, across the axis as a fraction of the radius (light direction).
    pub specular_offset: f64,
}

impl Palette {
    /// The shading of a capsule pixel at `rim` (distance from the axis / radius) and signed
    /// `across` (same units): maps a base colour value to the lit one. Flat without shading.
    fn lit(&self, rim: f64, across: f64) -> impl Fn(u8) -> f64 {
        let scale = 1.0 - self.rim_shading * rim.min(1.0).powi(2);
        let stripe = if self.specular == 0.0 {
            0.0
        } else {
            self.specular * (-((across - self.specular_offset) / 0.25).powi(2)).exp()
        };
        move |value| f64::from(value) * scale + stripe
    }
}

impl Default for Palette {
    fn default() -> Self {
        Self {
            canal_rgb: CANAL_RGB,
            wall_rgb: WALL_RGB,
            body_rgb: BODY_RGB,
            cap_rgb: CAP_RGB,
            magnet_rgb: MAGNET_RGB,
            rim_shading: 0.0,
            specular: 0.0,
            specular_offset: 0.0,
        }
    }
}

/// Number of pre-rendered background variants cycled through for temporal noise.
const BACKGROUND_VARIANTS: usize = 4;

/// Mask class of the resin body (dye) in [`RenderedSample::mask`].
pub const MASK_BODY: u8 = 1;
/// Mask class of the release cap (tip end).
pub const MASK_CAP: u8 = 2;
/// Mask class of the magnet (tail end).
pub const MASK_MAGNET: u8 = 3;

/// `[plant.camera]`: image degradations of the twin's camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraConfig {
    /// Passes of the separable [1 2 1]/4 blur (0 = sharp).
    pub blur_passes: u32,
    /// Relative amplitude A of the global lighting gain drift (0 = constant lighting).
    pub lighting_drift_amplitude: f64,
    /// Period T of the slow lighting drift, s.
    pub lighting_drift_period_s: f64,
    /// Frames between capture and delivery (applied by the plant loop).
    pub latency_frames: u32,
    /// The camera exposes a new image every this many loop frames (`[run] frame_period_ms`);
    /// the frames between deliver the latest exposure again, stamps included, as a camera or
    /// a vision stage slower than the coil loop leaves the loop its latest pose (applied by
    /// the plant loop; 1: an exposure per frame).
    pub exposure_period_frames: u32,
    /// The camera vanishes (unplugged, driver hang) at this run time, s: no raw frame is
    /// published for `dropout_s` while the physics goes on (applied by the plant loop).
    pub dropout_at_s: Option<f64>,
    /// How long the camera stays away, s.
    pub dropout_s: f64,
}

impl Default for CameraConfig {
    fn default() -> Self {
        Self {
            blur_passes: 1,
            lighting_drift_amplitude: 0.04,
            lighting_drift_period_s: 20.0,
            latency_frames: 0,
            exposure_period_frames: 1,
            dropout_at_s: None,
            dropout_s: 0.0,
        }
    }
}

impl CameraConfig {
    /// How many frames before frame `seq` the state it shows was: the latency, plus the frames
    /// since the latest exposure (`exposure_period_frames`; exposures at frames 0, N, 2N, …
    /// of the captured states), never before frame 0.
    pub fn shown_frames_ago(&self, seq: u64) -> u64 {
        (u64::from(self.latency_frames) + self.frames_since_exposure(seq)).min(seq)
    }

    /// How many frames before frame `seq` its exposure was first delivered: 0 for a fresh
    /// exposure, up to `exposure_period_frames` − 1 for its repeats.
    pub fn frames_since_exposure(&self, seq: u64) -> u64 {
        seq.saturating_sub(u64::from(self.latency_frames))
            % u64::from(self.exposure_period_frames.max(1))
    }

    /// Past states the plant loop keeps so that [`Self::shown_frames_ago`] can reach back.
    pub fn history_len(&self) -> usize {
        self.latency_frames as usize + self.exposure_period_frames.max(1) as usize
    }

    /// Whether the camera is away at run time `time_s` (`dropout_at_s`, `dropout_s`).
    pub fn in_dropout(&self, time_s: f64) -> bool {
        self.dropout_at_s
            .is_some_and(|at| time_s >= at && time_s < at + self.dropout_s)
    }

    /// No blur, no drift, no latency: the camera as [`Camera::new`] makes it.
    pub fn off() -> Self {
        Self {
            blur_passes: 0,
            lighting_drift_amplitude: 0.0,
            lighting_drift_period_s: 20.0,
            latency_frames: 0,
            exposure_period_frames: 1,
            dropout_at_s: None,
            dropout_s: 0.0,
        }
    }
}

/// Pose and size of the capsule to draw (SI).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CapsulePose {
    pub position_m: Vector2<f64>,
    pub heading_rad: f64,
    pub length_m: f64,
    pub diameter_m: f64,
}

/// One frame with its ground truth, for dataset generation.
#[derive(Debug, Clone)]
pub struct RenderedSample {
    /// RGB8, row-major, width × height × 3.
    pub rgb: Vec<u8>,
    /// One class per pixel (0 background, [`MASK_BODY`], [`MASK_CAP`], [`MASK_MAGNET`]).
    pub mask: Vec<u8>,
    pub keypoints: CapsuleKeypoints,
}

/// A rectangular part of the frame held in its own buffer.
struct Region {
    col0: usize,
    row0: usize,
    width: usize,
    height: usize,
}

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
    /// Blurred copies of `backgrounds` (empty when `config.blur_passes` is 0).
    blurred: Vec<Vec<u8>>,
    pub noise_std: f64,
    pub config: CameraConfig,
    /// Scene colours; the capsule's may be changed between draws (the background's are
    /// baked in at construction, see [`Camera::with_palette`]).
    pub palette: Palette,
    drift_phases: (f64, f64),
}

impl Camera {
    /// A camera with noise only (no blur, no drift), as before effects existed.
    pub fn new(
        canal: &CanalMask,
        geometry: ImageGeometry,
        rng: &mut ChaCha8Rng,
        noise_std: f64,
    ) -> Self {
        Self::with_palette(canal, geometry, rng, noise_std, Palette::default())
    }

    /// Like [`Camera::new`] with the scene in `palette`'s colours.
    pub fn with_palette(
        canal: &CanalMask,
        geometry: ImageGeometry,
        rng: &mut ChaCha8Rng,
        noise_std: f64,
        palette: Palette,
    ) -> Self {
        Self::build(
            canal,
            geometry,
            rng,
            noise_std,
            CameraConfig::off(),
            palette,
        )
    }

    /// A camera with the effects of `config` (blur, lighting drift); draws from `rng` after
    /// the same draws as [`Camera::new`].
    pub fn with_config(
        canal: &CanalMask,
        geometry: ImageGeometry,
        rng: &mut ChaCha8Rng,
        noise_std: f64,
        config: CameraConfig,
    ) -> Self {
        let mut camera = Self::build(canal, geometry, rng, noise_std, config, Palette::default());
        camera.drift_phases = (
            rng.random_range(0.0..std::f64::consts::TAU),
            rng.random_range(0.0..std::f64::consts::TAU),
        );
        let (w, h) = (camera.width(), camera.height());
        let passes = camera.config.blur_passes;
        if passes > 0 {
            camera.blurred = camera
                .backgrounds
                .iter()
                .map(|bg| {
                    let mut img = bg.clone();
                    blur_rgb(&mut img, w, h, passes);
                    img
                })
                .collect();
        }
        camera
    }

    fn build(
        canal: &CanalMask,
        geometry: ImageGeometry,
        rng: &mut ChaCha8Rng,
        noise_std: f64,
        config: CameraConfig,
        palette: Palette,
    ) -> Self {
        let canal_mask = canal.resampled(&geometry);
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
                    let base = if canal_mask[i] > 0 {
                        palette.canal_rgb
                    } else {
                        palette.wall_rgb
                    };
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
            blurred: Vec::new(),
            noise_std,
            config,
            palette,
            drift_phases: (0.0, 0.0),
        }
    }

    fn width(&self) -> usize {
        self.geometry.width_px as usize
    }

    fn height(&self) -> usize {
        self.geometry.height_px as usize
    }

    /// Background pixels for frame `seq` (variants cycle so the noise changes frame to frame).
    /// Sharp; see [`Camera::frame_background`] for the one [`Camera::finish_frame`] expects.
    pub fn background(&self, seq: u64) -> &[u8] {
        &self.backgrounds[(seq as usize) % self.backgrounds.len()]
    }

    /// Background of frame `seq` as the camera sees it (blurred when blur is on).
    pub fn frame_background(&self, seq: u64) -> &[u8] {
        if self.blurred.is_empty() {
            self.background(seq)
        } else {
            &self.blurred[(seq as usize) % self.blurred.len()]
        }
    }

    /// Global lighting gain at time `t` (1 without drift), quantised to 1/256.
    pub fn lighting_gain(&self, time_s: f64) -> f64 {
        f64::from(self.gain_q8(time_s)) / 256.0
    }

    fn gain_q8(&self, time_s: f64) -> u16 {
        let a = self.config.lighting_drift_amplitude;
        let period = self.config.lighting_drift_period_s;
        if a == 0.0
            || !a.is_finite()
            || period.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
            || !time_s.is_finite()
        {
            return 256;
        }
        let w = std::f64::consts::TAU / period;
        let (p1, p2) = self.drift_phases;
        let g = 1.0 + a * (0.7 * (w * time_s + p1).sin() + 0.3 * (w / 0.37 * time_s + p2).sin());
        (g * 256.0).round().clamp(0.0, 1023.0) as u16
    }

    /// Completes frame `seq` in `rgb`, which must already hold [`Camera::frame_background`]:
    /// draws the capsule (with blur), then applies the lighting gain of `time_s`. When `mask`
    /// is given (width × height) the capsule's classes are written into it.
    pub fn finish_frame(
        &self,
        rgb: &mut [u8],
        capsule: &CapsulePose,
        seq: u64,
        time_s: f64,
        rng: &mut ChaCha8Rng,
        mask: Option<&mut [u8]>,
    ) {
        let (w, h) = (self.width(), self.height());
        if rgb.len() < w * h * 3 {
            return;
        }
        let passes = self.config.blur_passes as usize;
        // Margin 2p: p for the capsule's blur spreading out, p for the region's own edge.
        if let Some(region) = self.capsule_region(capsule, 2 * passes) {
            // Re-render the region from the sharp background, draw, blur, paste the part that
            // a whole-frame blur would give (everything but the margin, except at frame edges).
            let sharp = self.background(seq);
            let mut buf = vec![0u8; region.width * region.height * 3];
            for r in 0..region.height {
                let src = ((region.row0 + r) * w + region.col0) * 3;
                buf[r * region.width * 3..(r + 1) * region.width * 3]
                    .copy_from_slice(&sharp[src..src + region.width * 3]);
            }
            self.draw_into(&mut buf, &region, capsule, rng, mask);
            if passes > 0 {
                blur_rgb(&mut buf, region.width, region.height, passes as u32);
            }
            let keep_c0 = if region.col0 == 0 { 0 } else { passes };
            let keep_r0 = if region.row0 == 0 { 0 } else { passes };
            let keep_c1 = if region.col0 + region.width == w {
                region.width
            } else {
                region.width - passes
            };
            let keep_r1 = if region.row0 + region.height == h {
                region.height
            } else {
                region.height - passes
            };
            for r in keep_r0..keep_r1 {
                let dst = ((region.row0 + r) * w + region.col0 + keep_c0) * 3;
                let src = (r * region.width + keep_c0) * 3;
                let n = (keep_c1 - keep_c0) * 3;
                rgb[dst..dst + n].copy_from_slice(&buf[src..src + n]);
            }
        }
        let gain = self.gain_q8(time_s);
        if gain != 256 {
            apply_gain(&mut rgb[..w * h * 3], gain);
        }
    }

    /// Renders frame `seq` of `capsule` at `time_s` with all effects, plus its ground truth.
    pub fn render_sample(
        &self,
        capsule: &CapsulePose,
        seq: u64,
        time_s: f64,
        rng: &mut ChaCha8Rng,
    ) -> RenderedSample {
        let mut rgb = self.frame_background(seq).to_vec();
        let mut mask = vec![0u8; self.width() * self.height()];
        self.finish_frame(&mut rgb, capsule, seq, time_s, rng, Some(&mut mask));
        RenderedSample {
            rgb,
            mask,
            keypoints: self.keypoints(&capsule.position_m, capsule.heading_rad, capsule.length_m),
        }
    }

    /// Pixel box around the capsule plus `margin`, clipped to the frame; None if off-frame.
    fn capsule_region(&self, capsule: &CapsulePose, margin: usize) -> Option<Region> {
        let (w, h) = (self.width() as i64, self.height() as i64);
        let px_per_m = 1e3 / self.geometry.mm_per_px;
        let (cx, cy) = self.geometry.world_to_px(&capsule.position_m);
        let reach = capsule.length_m.max(capsule.diameter_m) / 2.0 * px_per_m + 2.0;
        if !(cx.is_finite() && cy.is_finite() && reach.is_finite()) {
            return None;
        }
        let m = margin as f64;
        let col0 = ((cx - reach - m).floor().max(-1.0) as i64).clamp(0, w);
        let col1 = (((cx + reach + m).ceil() + 1.0).min(w as f64 + 1.0) as i64).clamp(0, w);
        let row0 = ((cy - reach - m).floor().max(-1.0) as i64).clamp(0, h);
        let row1 = (((cy + reach + m).ceil() + 1.0).min(h as f64 + 1.0) as i64).clamp(0, h);
        // Enough room for the margins, or nothing of the capsule is visible.
        if col1 - col0 <= 2 * margin as i64 || row1 - row0 <= 2 * margin as i64 {
            return None;
        }
        Some(Region {
            col0: col0 as usize,
            row0: row0 as usize,
            width: (col1 - col0) as usize,
            height: (row1 - row0) as usize,
        })
    }

    pub fn keypoints(
        &self,
        position: &Vector2<f64>,
        heading: f64,
        length_m: f64,
    ) -> CapsuleKeypoints {
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
        let (w, h) = (self.width(), self.height());
        if rgb.len() < w * h * 3 {
            return;
        }
        let whole = Region {
            col0: 0,
            row0: 0,
            width: w,
            height: h,
        };
        let capsule = CapsulePose {
            position_m: *position,
            heading_rad: heading,
            length_m,
            diameter_m,
        };
        self.draw_into(rgb, &whole, &capsule, rng, None);
    }

    /// Draws the capsule into `buf`, which holds `region` of the frame; `mask` (whole frame)
    /// gets the class of every pixel whose centre is inside the capsule.
    fn draw_into(
        &self,
        buf: &mut [u8],
        region: &Region,
        capsule: &CapsulePose,
        rng: &mut ChaCha8Rng,
        mut mask: Option<&mut [u8]>,
    ) {
        let g = &self.geometry;
        let mm_per_px = g.mm_per_px;
        let px_per_m = 1e3 / mm_per_px;
        let (cx, cy) = g.world_to_px(&capsule.position_m);
        let half_len_px = capsule.length_m / 2.0 * px_per_m;
        let radius_px = capsule.diameter_m / 2.0 * px_per_m;
        let core_half = (half_len_px - radius_px).max(0.0);
        // Image rows grow downwards, so the world heading flips sign in pixel space.
        let (ax, ay) = (capsule.heading_rad.cos(), -capsule.heading_rad.sin());
        let magnet_half = 0.5e-3 * px_per_m;
        let magnet_center = -half_len_px + 0.3e-3 * px_per_m + magnet_half;
        let cap_start = half_len_px - 1.0e-3 * px_per_m;
        let reach = half_len_px + 2.0;
        if !(cx.is_finite() && cy.is_finite() && reach.is_finite()) {
            return;
        }
        let frame_w = g.width_px as i64;
        let (rc0, rr0) = (region.col0 as i64, region.row0 as i64);
        let (rc1, rr1) = (rc0 + region.width as i64, rr0 + region.height as i64);
        let col0 = ((cx - reach).floor() as i64).clamp(rc0, rc1);
        let col1 = ((cx + reach).ceil() as i64 + 1).clamp(rc0, rc1);
        let row0 = ((cy - reach).floor() as i64).clamp(rr0, rr1);
        let row1 = ((cy + reach).ceil() as i64 + 1).clamp(rr0, rr1);
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
                let palette = &self.palette;
                let (color, class) = if (along - magnet_center).abs() <= magnet_half
                    && across.abs() <= magnet_half
                {
                    (palette.magnet_rgb, MASK_MAGNET)
                } else if along >= cap_start {
                    (palette.cap_rgb, MASK_CAP)
                } else {
                    (palette.body_rgb, MASK_BODY)
                };
                if let Some(mask) = mask.as_deref_mut() {
                    if dist <= radius_px {
                        if let Some(m) = mask.get_mut((row * frame_w + col) as usize) {
                            *m = class;
                        }
                    }
                }
                let noise = self.noise_std * gaussian(rng);
                let lit = palette.lit(dist / radius_px.max(1e-9), across / radius_px.max(1e-9));
                let i = (((row - rr0) * region.width as i64 + (col - rc0)) * 3) as usize;
                for c in 0..3 {
                    let bg = buf[i + c] as f64;
                    let value = bg + coverage * (lit(color[c]) + noise - bg);
                    buf[i + c] = value.round().clamp(0.0, 255.0) as u8;
                }
            }
        }
    }
}

/// `passes` separable [1 2 1]/4 passes over an RGB8 image, edges clamped, rounded.
pub fn blur_rgb(img: &mut [u8], width: usize, height: usize, passes: u32) {
    if width == 0 || height == 0 || img.len() < width * height * 3 {
        return;
    }
    let mut tmp = vec![0u8; width * height * 3];
    let stride = width * 3;
    for _ in 0..passes {
        // Horizontal: img → tmp.
        for r in 0..height {
            let line = &img[r * stride..(r + 1) * stride];
            let out = &mut tmp[r * stride..(r + 1) * stride];
            for c in 0..width {
                let l = c.saturating_sub(1);
                let rr = (c + 1).min(width - 1);
                for ch in 0..3 {
                    let v = u16::from(line[l * 3 + ch])
                        + 2 * u16::from(line[c * 3 + ch])
                        + u16::from(line[rr * 3 + ch]);
                    out[c * 3 + ch] = ((v + 2) >> 2) as u8;
                }
            }
        }
        // Vertical: tmp → img, whole rows at a time (vectorises).
        for r in 0..height {
            let up = &tmp[r.saturating_sub(1) * stride..][..stride];
            let mid = &tmp[r * stride..][..stride];
            let down = &tmp[(r + 1).min(height - 1) * stride..][..stride];
            let out = &mut img[r * stride..(r + 1) * stride];
            for (((o, a), b), d) in out.iter_mut().zip(up).zip(mid).zip(down) {
                let v = u16::from(*a) + 2 * u16::from(*b) + u16::from(*d);
                *o = ((v + 2) >> 2) as u8;
            }
        }
    }
}

/// Multiplies every byte by `gain_q8`/256, rounded and saturated.
fn apply_gain(img: &mut [u8], gain_q8: u16) {
    let gain = u32::from(gain_q8);
    for b in img.iter_mut() {
        *b = ((u32::from(*b) * gain + 128) >> 8).min(255) as u8;
    }
}

/// Standard normal sample (Box–Muller), enough for image noise.
fn gaussian(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.random_range(1e-12..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}
