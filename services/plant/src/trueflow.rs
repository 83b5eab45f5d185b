//! The parts of the true flow that no controller knows about: a slowly moving, slowly breathing
//! vortex in the recirculation zone and spatially smooth, temporally correlated noise.
//!
//! Both scale with the steady map's peak speed, so a static-fluid scenario (zero map) stays
//! exactly still. Everything is drawn from the scenario seed.
//!
//! - Recirculation: a Lamb–Oseen-like vortex, v_θ(r) = U(t)·(r/r_c)·exp((1 − (r/r_c)²)/2)
//!   (peak U at r = r_c), whose centre orbits `center_mm` with radius `orbit_radius_mm` and
//!   period `period_s`, and whose strength breathes U(t) = U₀·(0.75 + 0.25·sin(2πt/T + φ)).
//!   It is windowed to the paper's recirculation band y ∈ [−5, 10] mm with 1 mm smooth edges.
//! - Noise: `FLOW_NOISE_MODES` divergence-free plane-wave modes (stream function
//!   ψ = sin(k·p + φ)/|k|, wavelengths uniform in `wavelength_mm`), each with an
//!   Ornstein–Uhlenbeck amplitude of unit stationary variance and correlation time
//!   `correlation_time_s`. The RMS noise speed is `fraction` × the map's peak speed.

use fieldmaps::rigfile::{RigPhantom, Zone, ZoneKind};
use nalgebra::Vector2;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::rng_streams;

/// Number of smooth spatial modes of the flow noise.
pub const FLOW_NOISE_MODES: usize = 6;
/// Width of the smooth edges of the recirculation band, m.
const BAND_EDGE_M: f64 = 1.0e-3;

/// `[plant.physics.recirculation]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RecirculationConfig {
    /// Peak swirl speed as a fraction of the steady map's peak speed (0 disables the vortex).
    pub strength_fraction: f64,
    /// Mean centre of the vortex (edge unit: mm, world frame); default: the rig's
    /// recirculation zone centre (`RigPhantom::zone_center`).
    pub center_mm: Option<[f64; 2]>,
    /// Radius of the centre's orbit, mm.
    pub orbit_radius_mm: f64,
    /// Core radius (where the swirl speed peaks), mm.
    pub core_radius_mm: f64,
    /// Period of the orbit and of the strength modulation, s.
    pub period_s: f64,
}

impl Default for RecirculationConfig {
    fn default() -> Self {
        Self {
            strength_fraction: 0.25,
            center_mm: None,
            orbit_radius_mm: 1.5,
            core_radius_mm: 3.0,
            period_s: 6.0,
        }
    }
}

/// `[plant.physics.flow_noise]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FlowNoiseConfig {
    /// RMS noise speed as a fraction of the steady map's peak speed (0 disables the noise).
    pub fraction: f64,
    /// Correlation time of each mode's Ornstein–Uhlenbeck amplitude, s.
    pub correlation_time_s: f64,
    /// Range of the modes' wavelengths, mm.
    pub wavelength_mm: [f64; 2],
}

impl Default for FlowNoiseConfig {
    fn default() -> Self {
        Self {
            fraction: 0.1,
            correlation_time_s: 0.3,
            wavelength_mm: [8.0, 30.0],
        }
    }
}

/// Evolving state of the flow noise: the modes' OU amplitudes and the generator that drives
/// them. Part of the plant state (`model::PlantState`), so two runs with the same seed and the
/// same steps evolve identically.
#[derive(Debug, Clone, PartialEq)]
pub struct FlowNoiseState {
    pub amplitudes: [f64; FLOW_NOISE_MODES],
    rng: ChaCha8Rng,
}

#[derive(Debug, Clone, PartialEq)]
struct Mode {
    /// Wave vector, rad/m.
    k: Vector2<f64>,
    phase: f64,
}

/// Fixed (per run) description of the vortex and the noise modes.
#[derive(Debug, Clone, PartialEq)]
pub struct FlowDisturbance {
    vortex_speed_mps: f64,
    /// The rig's recirculation zones: the vortex fades out over `BAND_EDGE_M` outside them.
    vortex_zones: Vec<Zone>,
    center_m: Vector2<f64>,
    orbit_radius_m: f64,
    core_radius_m: f64,
    omega_rad_s: f64,
    orbit_phase: f64,
    strength_phase: f64,
    noise_speed_mps: f64,
    correlation_time_s: f64,
    modes: Vec<Mode>,
}

impl FlowDisturbance {
    /// The vortex lives in the recirculation zones of `phantom` (none: no vortex).
    pub fn new(
        phantom: &RigPhantom,
        recirculation: &RecirculationConfig,
        noise: &FlowNoiseConfig,
        peak_speed_mps: f64,
        seed: u64,
    ) -> Self {
        let mut rng = rng_streams::run_rng(seed, rng_streams::FLOW_DISTURBANCE);
        let orbit_phase = rng.random_range(0.0..std::f64::consts::TAU);
        let strength_phase = rng.random_range(0.0..std::f64::consts::TAU);
        let (l0, l1) = ordered(noise.wavelength_mm[0] * 1e-3, noise.wavelength_mm[1] * 1e-3);
        let modes = (0..FLOW_NOISE_MODES)
            .map(|_| {
                let wavelength = if l1 > l0 {
                    rng.random_range(l0..l1)
                } else {
                    l0
                };
                let direction: f64 = rng.random_range(0.0..std::f64::consts::TAU);
                let k = std::f64::consts::TAU / wavelength.max(1e-4);
                Mode {
                    k: Vector2::new(direction.cos(), direction.sin()) * k,
                    phase: rng.random_range(0.0..std::f64::consts::TAU),
                }
            })
            .collect();
        let finite = |x: f64| if x.is_finite() { x } else { 0.0 };
        let peak = finite(peak_speed_mps).max(0.0);
        let period = recirculation.period_s;
        let vortex_zones: Vec<Zone> = phantom
            .zones
            .iter()
            .filter(|z| z.kind == ZoneKind::Recirculation)
            .cloned()
            .collect();
        let center_m = match (recirculation.center_mm, vortex_zones.first()) {
            (Some(c), _) => Vector2::new(c[0], c[1]) * 1e-3,
            (None, Some(zone)) => phantom.zone_center(zone),
            (None, None) => Vector2::zeros(),
        };
        let strength = if vortex_zones.is_empty() {
            0.0
        } else {
            finite(recirculation.strength_fraction).max(0.0)
        };
        Self {
            vortex_speed_mps: strength * peak,
            vortex_zones,
            center_m,
            orbit_radius_m: finite(recirculation.orbit_radius_mm).max(0.0) * 1e-3,
            core_radius_m: finite(recirculation.core_radius_mm).max(0.1) * 1e-3,
            omega_rad_s: if period.is_finite() && period > 0.0 {
                std::f64::consts::TAU / period
            } else {
                0.0
            },
            orbit_phase,
            strength_phase,
            noise_speed_mps: finite(noise.fraction).max(0.0) * peak,
            correlation_time_s: finite(noise.correlation_time_s).max(1e-3),
            modes,
        }
    }

    /// RMS of the noise velocity's magnitude, m/s (0: no noise).
    pub fn noise_rms_speed_mps(&self) -> f64 {
        self.noise_speed_mps
    }

    /// Correlation time of the noise modes, s.
    pub fn noise_correlation_time_s(&self) -> f64 {
        self.correlation_time_s
    }

    /// Noise state at t = 0, drawn from the stationary distribution.
    pub fn initial_noise(&self, seed: u64) -> FlowNoiseState {
        let mut rng = rng_streams::run_rng(seed, rng_streams::FLOW_NOISE);
        let mut amplitudes = [0.0; FLOW_NOISE_MODES];
        for a in amplitudes.iter_mut() {
            *a = StandardNormal.sample(&mut rng);
        }
        FlowNoiseState { amplitudes, rng }
    }

    /// Exact OU update of the mode amplitudes over `h` seconds.
    pub fn advance_noise(&self, state: &mut FlowNoiseState, h: f64) {
        if self.noise_speed_mps == 0.0 || h.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return;
        }
        let decay = (-h / self.correlation_time_s).exp();
        let kick = (1.0 - decay * decay).max(0.0).sqrt();
        for a in state.amplitudes.iter_mut() {
            let xi: f64 = StandardNormal.sample(&mut state.rng);
            *a = *a * decay + kick * xi;
        }
    }

    /// Noise velocity at `p` for the current amplitudes.
    pub fn noise(&self, p: &Vector2<f64>, state: &FlowNoiseState) -> Vector2<f64> {
        if self.noise_speed_mps == 0.0 {
            return Vector2::zeros();
        }
        // Each mode has unit RMS speed (√2·cos), modes are independent: divide by √M.
        let scale =
            self.noise_speed_mps * std::f64::consts::SQRT_2 / (self.modes.len() as f64).sqrt();
        let mut v = Vector2::zeros();
        for (mode, a) in self.modes.iter().zip(&state.amplitudes) {
            let k_norm = mode.k.norm();
            let c = (mode.k.dot(p) + mode.phase).cos();
            // curl of ψ = sin(k·p + φ)/|k|: (∂ψ/∂y, −∂ψ/∂x).
            v += Vector2::new(mode.k.y, -mode.k.x) * (a * c / k_norm);
        }
        v * scale
    }

    /// Recirculation vortex velocity at `p`, time `t`.
    pub fn recirculation(&self, p: &Vector2<f64>, t: f64) -> Vector2<f64> {
        if self.vortex_speed_mps == 0.0 || !(p.x.is_finite() && p.y.is_finite() && t.is_finite()) {
            return Vector2::zeros();
        }
        let outside = self
            .vortex_zones
            .iter()
            .map(|z| z.distance_outside(p))
            .fold(f64::INFINITY, f64::min);
        let window = smoothstep((BAND_EDGE_M - outside) / BAND_EDGE_M);
        if window == 0.0 {
            return Vector2::zeros();
        }
        let theta = self.omega_rad_s * t;
        let center = self.center_m
            + Vector2::new(
                (theta + self.orbit_phase).cos(),
                (theta + self.orbit_phase).sin(),
            ) * self.orbit_radius_m;
        let d = p - center;
        let rc = self.core_radius_m;
        let r2 = d.norm_squared() / (rc * rc);
        if r2 > 50.0 {
            return Vector2::zeros();
        }
        let strength = self.vortex_speed_mps * (0.75 + 0.25 * (theta + self.strength_phase).sin());
        Vector2::new(-d.y, d.x) * (strength / rc * (0.5 * (1.0 - r2)).exp() * window)
    }
}

fn ordered(a: f64, b: f64) -> (f64, f64) {
    let a = if a.is_finite() { a.max(1e-4) } else { 1e-2 };
    let b = if b.is_finite() { b.max(1e-4) } else { a };
    if a <= b {
        (a, b)
    } else {
        (b, a)
    }
}

/// 0 below 0, 1 above 1, smooth in between.
fn smoothstep(x: f64) -> f64 {
    let x = x.clamp(0.0, 1.0);
    x * x * (3.0 - 2.0 * x)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paper() -> RigPhantom {
        fieldmaps::rigfile::Rig::load_paper().unwrap().phantom
    }

    #[test]
    fn zero_peak_speed_means_no_disturbance() {
        let d = FlowDisturbance::new(
            &paper(),
            &RecirculationConfig::default(),
            &FlowNoiseConfig::default(),
            0.0,
            1,
        );
        let mut s = d.initial_noise(1);
        d.advance_noise(&mut s, 0.01);
        let p = Vector2::new(-0.014, 0.003);
        assert_eq!(d.recirculation(&p, 1.0), Vector2::zeros());
        assert_eq!(d.noise(&p, &s), Vector2::zeros());
    }

    #[test]
    fn vortex_lives_in_the_recirculation_band_and_swirls() {
        let d = FlowDisturbance::new(
            &paper(),
            &RecirculationConfig::default(),
            &FlowNoiseConfig::default(),
            0.01,
            1,
        );
        assert_eq!(
            d.recirculation(&Vector2::new(-0.014, 0.02), 0.0),
            Vector2::zeros()
        );
        let v = d.recirculation(&Vector2::new(-0.011, 0.0025), 0.0);
        assert!(v.norm() > 0.0 && v.norm() <= 0.0025 * 1.0001, "{v}");
        // A phantom without recirculation zones has no vortex.
        let mut bare = paper();
        bare.zones.clear();
        let d = FlowDisturbance::new(
            &bare,
            &RecirculationConfig::default(),
            &FlowNoiseConfig::default(),
            0.01,
            1,
        );
        assert_eq!(
            d.recirculation(&Vector2::new(-0.011, 0.0025), 0.0),
            Vector2::zeros()
        );
    }

    #[test]
    fn noise_rms_matches_fraction_and_is_correlated() {
        let cfg = FlowNoiseConfig::default();
        let d = FlowDisturbance::new(&paper(), &RecirculationConfig::default(), &cfg, 0.01, 5);
        let mut s = d.initial_noise(5);
        let h = 0.01;
        let points: Vec<Vector2<f64>> = (0..64)
            .map(|i| Vector2::new((i % 8) as f64 * 5e-3 - 0.02, (i / 8) as f64 * 5e-3 - 0.02))
            .collect();
        let (mut sum2, mut n, mut lag_sum, mut lag_norm) = (0.0, 0.0, 0.0, 0.0);
        let mut prev = d.noise(&Vector2::zeros(), &s);
        for _ in 0..40_000 {
            d.advance_noise(&mut s, h);
            for p in &points {
                sum2 += d.noise(p, &s).norm_squared();
                n += 1.0;
            }
            let v = d.noise(&Vector2::zeros(), &s);
            lag_sum += v.dot(&prev);
            lag_norm += v.norm_squared();
            prev = v;
        }
        let rms = (sum2 / n).sqrt();
        let expected = cfg.fraction * 0.01;
        assert!(
            (rms - expected).abs() < 0.2 * expected,
            "rms {rms} vs {expected}"
        );
        // One-step autocorrelation ≈ exp(−h/τ).
        let rho = lag_sum / lag_norm;
        assert!(
            (rho - (-h / cfg.correlation_time_s).exp()).abs() < 0.02,
            "rho {rho}"
        );
    }
}
