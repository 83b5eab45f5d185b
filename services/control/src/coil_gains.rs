//! Online correction of the actuation model: each allocated coil's gain (true field over the
//! model's), estimated from the heading the camera sees.
//!
//! A permanent-magnet capsule turns into the field it sits in within a millisecond (overdamped:
//! rotational drag over |m|·|B|), so at every frame its heading is the direction of the *true*
//! in-plane field made by the currents in effect at the capture time. The model predicts
//! `B = Σ_k I_k b_k(p) + B_bg`; with true gains `g_k = 1 + δ_k` the capsule axis `u` satisfies
//! `u × (Σ_k (1 + δ_k) I_k b_k + B_bg + ΔB_bg) = 0`, one equation *linear* in the unknown δ and
//! background correction ΔB_bg:
//!
//! ```text
//! Σ_k δ_k · I_k (u × b_k)  +  u × ΔB_bg  =  −u × B_model
//! ```
//!
//! The equation is homogeneous in the gains: scaling every coil by one factor turns no field,
//! so headings tell the gains only *relative to each other* (and all gains at zero would fit
//! any heading). The estimate is held to a mean gain of 1 (a perfect pseudo-measurement
//! Σ δ_k = 0 after every update); a common scale error is a force gain error, which the
//! controllers' observers carry, and the field's magnitude follows it without turning.
//!
//! The flow pushes the capsule but does not turn it, so this signal carries none of the
//! disturbance that the controller fights (the force residual a DOB sees does, and closed-loop
//! regression of it on the commanded force is biased toward −1). The unknowns are constant or
//! drift slowly (coil heating), so a Kalman filter over them (recursive least squares with a
//! prior and a small random walk) converges as the currents vary along the path; every
//! measurement is gated on its innovation, so a frame where the capsule is held by a wall or the
//! heading is misread is counted and skipped, not learned.
//!
//! The allocation then uses `A · diag(ĝ)`: force and field columns scaled together, so the
//! commanded orientation field (and through it the direction of every force) holds when the
//! coils drive hard, which is where a gain error hurts most.

use nalgebra::{DMatrix, DVector, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use fieldmaps::coils::CoilField;

/// `[control.gain_estimation]` of a scenario.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct GainEstimationConfig {
    /// Estimate the coil gains online and allocate with them.
    pub enabled: bool,
    /// Prior standard deviation of each coil's gain error (fraction of the model's gain): how
    /// far the coil data may be off before any frame is seen.
    pub prior_std: f64,
    /// Prior standard deviation of each in-plane component of an unmodelled uniform background
    /// field (mT; the Earth's horizontal field is ≈ 0.02 mT, steel nearby can add more).
    pub background_prior_mt: f64,
    /// Standard deviation of the measured heading (deg): vision's heading noise plus what the
    /// model of the alignment leaves out.
    pub heading_noise_deg: f64,
    /// Random walk of every gain (fraction per √s): how fast the gains may drift, e.g. as the
    /// coils warm up. 0 holds them constant once learned.
    pub gain_drift_per_sqrt_s: f64,
    /// Measurements whose innovation exceeds this many standard deviations are skipped.
    pub gate_sigma: f64,
    /// Frames whose modelled field is weaker than this are skipped (mT): the heading says
    /// little about the field's direction there.
    pub min_field_mt: f64,
    /// The field must have held its direction (within `heading_noise_deg`) for this long
    /// before a frame's capture for the frame to measure it (ms): the coil currents' L/R rise.
    /// The loop also waits at least three of the capsule's rotation time constants (rotational
    /// drag / (|m|·|B|): 11 ms at 20 cP and 1 mT), since the capsule trails a turning field.
    pub settle_ms: f64,
    /// At most one frame per this interval is learned from (ms). Frames closer together carry
    /// the same model error (map interpolation, a wall, the capsule's lag), which the filter
    /// would take for independent evidence: at 100 Hz, learning from every frame drove the
    /// gains to their bounds within 40 s in still fluid.
    pub min_interval_ms: f64,
    /// Estimated gains are kept within [1 − max_gain_error, 1 + max_gain_error].
    pub max_gain_error: f64,
}

impl Default for GainEstimationConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            prior_std: 0.15,
            background_prior_mt: 0.05,
            heading_noise_deg: 1.0,
            gain_drift_per_sqrt_s: 1e-3,
            gate_sigma: 4.0,
            min_field_mt: 0.3,
            settle_ms: 5.0,
            min_interval_ms: 100.0,
            max_gain_error: 0.5,
        }
    }
}

impl GainEstimationConfig {
    /// The first field that is out of range, with why.
    pub fn invalid_field(&self) -> Option<(&'static str, String)> {
        let positive = [
            ("prior_std", self.prior_std),
            ("background_prior_mt", self.background_prior_mt),
            ("heading_noise_deg", self.heading_noise_deg),
            ("gate_sigma", self.gate_sigma),
        ];
        let non_negative = [
            ("gain_drift_per_sqrt_s", self.gain_drift_per_sqrt_s),
            ("min_field_mt", self.min_field_mt),
            ("settle_ms", self.settle_ms),
            ("min_interval_ms", self.min_interval_ms),
        ];
        if let Some((name, v)) = positive.iter().find(|(_, v)| !(v.is_finite() && *v > 0.0)) {
            return Some((name, format!("must be finite and > 0, got {v}")));
        }
        if let Some((name, v)) = non_negative
            .iter()
            .find(|(_, v)| !(v.is_finite() && *v >= 0.0))
        {
            return Some((name, format!("must be finite and >= 0, got {v}")));
        }
        if !(self.max_gain_error.is_finite()
            && self.max_gain_error > 0.0
            && self.max_gain_error < 1.0)
        {
            return Some((
                "max_gain_error",
                format!("must be within (0, 1), got {}", self.max_gain_error),
            ));
        }
        None
    }
}

/// What one frame did to the estimate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GainUpdate {
    /// Learned from.
    Used,
    /// The modelled field was too weak to tell a direction.
    WeakField,
    /// The innovation failed the gate (wall contact, misread heading, a transient).
    Gated,
    /// Within `min_interval_ms` of the last frame learned from.
    TooSoon,
}

/// Estimates of every allocated coil's gain and of a background field, from headings.
pub struct CoilGainEstimator {
    config: GainEstimationConfig,
    /// Coil ids of the rig, in allocation order.
    coil_ids: Vec<usize>,
    /// δ_1..δ_n, then ΔB_bg x and y (T).
    state: DVector<f64>,
    covariance: DMatrix<f64>,
    /// Capture time of the last frame learned from (ns), for the random walk and the interval.
    last_ns: Option<u64>,
    pub used: u64,
    pub gated: u64,
    pub weak: u64,
}

impl CoilGainEstimator {
    pub fn new(config: GainEstimationConfig, coil_ids: Vec<usize>) -> Self {
        let n = coil_ids.len();
        let mut covariance = DMatrix::zeros(n + 2, n + 2);
        for k in 0..n {
            covariance[(k, k)] = config.prior_std.powi(2);
        }
        let background_var = (config.background_prior_mt * 1e-3).powi(2);
        covariance[(n, n)] = background_var;
        covariance[(n + 1, n + 1)] = background_var;
        let mut estimator = Self {
            config,
            coil_ids,
            state: DVector::zeros(n + 2),
            covariance,
            last_ns: None,
            used: 0,
            gated: 0,
            weak: 0,
        };
        estimator.hold_mean_gain();
        estimator
    }

    /// Kalman update of the state with the scalar measurement `measured = regressor · state`
    /// of variance `noise_var`; the innovation, and its variance, are returned unapplied when
    /// they fail `gate_sigma` (None: no gate).
    fn update(
        &mut self,
        regressor: &DVector<f64>,
        measured: f64,
        noise_var: f64,
        gate_sigma: Option<f64>,
    ) -> bool {
        let innovation = measured - regressor.dot(&self.state);
        let p_phi = &self.covariance * regressor;
        let s = regressor.dot(&p_phi) + noise_var;
        if !(s.is_finite() && s > 0.0 && innovation.is_finite()) {
            return false;
        }
        if gate_sigma.is_some_and(|gate| innovation.abs() > gate * s.sqrt()) {
            return false;
        }
        let gain = &p_phi / s;
        self.state += &gain * innovation;
        self.covariance -= &gain * p_phi.transpose();
        // Keep it symmetric against rounding.
        self.covariance = (&self.covariance + self.covariance.transpose()) * 0.5;
        true
    }

    /// Σ δ_k = 0: what the headings cannot see is held at the model's overall scale.
    fn hold_mean_gain(&mut self) {
        let n = self.coil_ids.len();
        if n == 0 {
            return;
        }
        let mut mean = DVector::zeros(n + 2);
        mean.rows_mut(0, n).fill(1.0 / n as f64);
        let tiny = (self.config.prior_std * 1e-6).powi(2);
        self.update(&mean, 0.0, tiny, None);
    }

    pub fn config(&self) -> &GainEstimationConfig {
        &self.config
    }

    /// The estimated gain of each allocated coil (allocation order), within the configured
    /// bounds.
    pub fn gains(&self) -> Vec<f64> {
        let bound = self.config.max_gain_error;
        (0..self.coil_ids.len())
            .map(|k| 1.0 + self.state[k].clamp(-bound, bound))
            .collect()
    }

    /// The estimated unmodelled background field (T, in plane).
    pub fn background_t(&self) -> Vector2<f64> {
        let n = self.coil_ids.len();
        Vector2::new(self.state[n], self.state[n + 1])
    }

    /// Standard deviation of each gain estimate (allocation order).
    pub fn gain_std(&self) -> Vec<f64> {
        (0..self.coil_ids.len())
            .map(|k| self.covariance[(k, k)].max(0.0).sqrt())
            .collect()
    }

    /// The in-plane direction (rad) of the field that `currents_a` (allocation order) make at
    /// `position_m` as the estimate believes it, None where it is too weak to have one.
    pub fn believed_field_heading<F: CoilField + ?Sized>(
        &self,
        coils: &F,
        position_m: &Vector2<f64>,
        currents_a: &[f64],
    ) -> Option<f64> {
        let b = self.believed_field(coils, position_m, currents_a);
        (b.norm() >= self.config.min_field_mt * 1e-3 && b.norm().is_finite())
            .then(|| b.y.atan2(b.x))
    }

    fn believed_field<F: CoilField + ?Sized>(
        &self,
        coils: &F,
        position_m: &Vector2<f64>,
        currents_a: &[f64],
    ) -> Vector2<f64> {
        let p3 = Vector3::new(position_m.x, position_m.y, 0.0);
        let gains = self.gains();
        let mut believed = coils.background_field(&p3).xy() + self.background_t();
        for (k, &id) in self.coil_ids.iter().enumerate() {
            let current = currents_a.get(k).copied().unwrap_or(0.0);
            believed += coils.field_per_amp(id, &p3).xy() * (current * gains[k]);
        }
        believed
    }

    /// Learns from one frame: the capsule at `position_m` (m, on the control plane) pointed
    /// along `heading_rad` at `capture_ns`, with `currents_a[k]` in allocated coil k (the
    /// currents in effect then), on the model `coils`.
    pub fn observe<F: CoilField + ?Sized>(
        &mut self,
        coils: &F,
        position_m: &Vector2<f64>,
        heading_rad: f64,
        currents_a: &[f64],
        capture_ns: u64,
    ) -> GainUpdate {
        let n = self.coil_ids.len();
        if let Some(last) = self.last_ns {
            let dt = capture_ns.saturating_sub(last) as f64 * 1e-9;
            // Half a frame of slack, so a 10 Hz loop learns from every frame.
            if dt < self.config.min_interval_ms * 1e-3 * 0.95 {
                return GainUpdate::TooSoon;
            }
            let walk = self.config.gain_drift_per_sqrt_s.powi(2) * dt;
            for k in 0..n {
                self.covariance[(k, k)] += walk;
            }
        }
        self.last_ns = Some(capture_ns);
        let p3 = Vector3::new(position_m.x, position_m.y, 0.0);
        let u = Vector2::new(heading_rad.cos(), heading_rad.sin());
        let cross = |b: &Vector2<f64>| u.x * b.y - u.y * b.x;
        let mut regressor = DVector::zeros(n + 2);
        let mut modelled = coils.background_field(&p3).xy();
        for (k, &id) in self.coil_ids.iter().enumerate() {
            let current = currents_a.get(k).copied().unwrap_or(0.0);
            let b = coils.field_per_amp(id, &p3).xy();
            modelled += b * current;
            regressor[k] = current * cross(&b);
        }
        // u × ΔB_bg = u_x ΔB_y − u_y ΔB_x.
        regressor[n] = -u.y;
        regressor[n + 1] = u.x;
        // The field as the estimate believes it, for the weak-field test and the noise scale.
        let believed = self.believed_field(coils, position_m, currents_a);
        if believed.norm() < self.config.min_field_mt * 1e-3 || !believed.norm().is_finite() {
            self.weak += 1;
            return GainUpdate::WeakField;
        }
        let measured = -cross(&modelled);
        // A heading error σ_θ moves u × B by |B|·σ_θ.
        let noise = believed.norm() * self.config.heading_noise_deg.to_radians();
        if !self.update(
            &regressor,
            measured,
            noise * noise,
            Some(self.config.gate_sigma),
        ) {
            self.gated += 1;
            return GainUpdate::Gated;
        }
        self.hold_mean_gain();
        self.used += 1;
        GainUpdate::Used
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use nalgebra::Matrix3;

    /// A seeded source of numbers uniform in [−1, 1) (a 64-bit LCG: enough for test data).
    pub(crate) fn uniform_source(seed: u64) -> impl FnMut() -> f64 {
        let mut state = seed;
        move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        }
    }

    /// Four coils around the origin, each a dipole-like field with a gradient, enough to test
    /// the estimator without a rig file.
    struct Square;
    impl CoilField for Square {
        fn coil_count(&self) -> usize {
            4
        }
        fn field_and_gradient_per_amp(
            &self,
            coil: usize,
            p: &Vector3<f64>,
        ) -> (Vector3<f64>, Matrix3<f64>) {
            let angle = coil as f64 * std::f64::consts::FRAC_PI_2;
            let axis = Vector3::new(angle.cos(), angle.sin(), 0.0);
            let centre = axis * 0.08;
            let r = p - centre;
            let d = r.norm();
            // Dipole field of a unit moment along −axis (pointing at the workspace).
            let m = -axis * 2e-3;
            let b = (r * (3.0 * m.dot(&r) / d.powi(5))) - m / d.powi(3);
            (b * 1e-4, Matrix3::zeros())
        }
    }

    #[test]
    fn recovers_gains_and_background_from_headings() {
        // Mean 1: headings see gains only relative to each other (see the module docs).
        let truth = [1.08, 0.93, 1.04, 0.95];
        let background = Vector2::new(3e-5, -2e-5);
        let coils = Square;
        let mut estimator = CoilGainEstimator::new(
            GainEstimationConfig {
                enabled: true,
                heading_noise_deg: 0.5,
                ..Default::default()
            },
            vec![0, 1, 2, 3],
        );
        let mut uniform = uniform_source(12345);
        for frame in 0..600u64 {
            let p = Vector2::new(uniform() * 0.02, uniform() * 0.02);
            let currents: Vec<f64> = (0..4).map(|_| uniform() * 3.0).collect();
            let mut field = background;
            for (k, c) in currents.iter().enumerate() {
                field += coils.field_per_amp(k, &Vector3::new(p.x, p.y, 0.0)).xy() * (c * truth[k]);
            }
            let heading = field.y.atan2(field.x) + uniform() * 0.5f64.to_radians();
            estimator.observe(&coils, &p, heading, &currents, frame * 100_000_000);
        }
        for (k, (g, t)) in estimator.gains().iter().zip(truth).enumerate() {
            assert!((g - t).abs() < 0.01, "coil {k}: {g} vs {t}");
        }
        assert!((estimator.background_t() - background).norm() < 3e-6);
        assert!(estimator.used > 500, "used {}", estimator.used);
    }

    #[test]
    fn a_misread_heading_is_gated_not_learned() {
        let coils = Square;
        let mut estimator = CoilGainEstimator::new(
            GainEstimationConfig {
                enabled: true,
                ..Default::default()
            },
            vec![0, 1, 2, 3],
        );
        let p = Vector2::new(0.005, -0.004);
        let currents = [2.0, -1.0, 0.5, 1.5];
        let mut field = Vector2::zeros();
        for (k, c) in currents.iter().enumerate() {
            field += coils.field_per_amp(k, &Vector3::new(p.x, p.y, 0.0)).xy() * *c;
        }
        let right = field.y.atan2(field.x);
        for frame in 0..50 {
            estimator.observe(&coils, &p, right, &currents, frame * 100_000_000);
        }
        // A frame 10 ms after the last one learned from adds nothing new (a 100 Hz loop).
        let soon = estimator.observe(&coils, &p, right, &currents, 49 * 100_000_000 + 10_000_000);
        assert_eq!(soon, GainUpdate::TooSoon);
        let before = estimator.gains();
        // Wedged against a wall at 60° off the field.
        let update = estimator.observe(&coils, &p, right + 1.0, &currents, 50 * 100_000_000);
        assert_eq!(update, GainUpdate::Gated);
        assert_eq!(estimator.gains(), before);
    }

    #[test]
    fn config_errors_name_the_field() {
        let bad = GainEstimationConfig {
            heading_noise_deg: 0.0,
            ..Default::default()
        };
        assert_eq!(
            bad.invalid_field().map(|(n, _)| n),
            Some("heading_noise_deg")
        );
        let bad = GainEstimationConfig {
            max_gain_error: 1.5,
            ..Default::default()
        };
        assert_eq!(bad.invalid_field().map(|(n, _)| n), Some("max_gain_error"));
        assert_eq!(GainEstimationConfig::default().invalid_field(), None);
    }
}
