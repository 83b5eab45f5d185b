//! The model-based latency predictor: the nominal model run from a delayed pose over the forces
//! the coils made since, with a learned steady disturbance and pump pulsation.

use std::collections::VecDeque;

use nalgebra::{Matrix3, Vector2, Vector3};

use super::{LatencyConfig, Predicted, Predictor};
use crate::controllers::NominalModel;

/// A force held from `start_ns` until the next segment starts.
#[derive(Debug, Clone, Copy)]
struct ForceSegment {
    start_ns: u64,
    /// Achieved magnetic force, N.
    force_n: Vector2<f64>,
    /// Flow velocity the nominal drag acts against, m/s.
    flow_mps: Vector2<f64>,
}

/// The model at one instant: per axis (x, y) the state (p, v, d̂). Positions are relative (only
/// the motion between two instants is used).
#[derive(Debug, Clone, Copy)]
struct ModelState {
    time_ns: u64,
    state: [Vector3<f64>; 2],
    /// Response (p, v) of the model to a unit force along each disturbance basis function
    /// (1, cos ωt, sin ωt), the same on both axes: the regressors of the pulsation fit.
    sensitivity: [Vector2<f64>; BASIS],
}

/// Disturbance basis functions of the pulsation fit: steady, cos ωt, sin ωt.
const BASIS: usize = 3;

/// Recursive least-squares fit of the disturbance force d(t) = θ·(1, cos ωt, sin ωt) per axis.
#[derive(Debug, Clone)]
struct PulsationFit {
    omega_rad_s: f64,
    coefficients: [Vector3<f64>; 2],
    covariance: Matrix3<f64>,
}

/// Initial uncertainty of each fitted force coefficient (1σ, N): far above any push the capsule
/// meets (≈ 1e-4 N), so that the first poses already fit it (a tight prior would leave the
/// gain tiny for seconds, until forgetting has inflated the covariance).
const PULSATION_PRIOR_STD_N: f64 = 1e-2;

impl PulsationFit {
    fn new(hz: f64) -> Self {
        Self {
            omega_rad_s: std::f64::consts::TAU * hz,
            coefficients: [Vector3::zeros(); 2],
            covariance: Matrix3::identity() * PULSATION_PRIOR_STD_N.powi(2),
        }
    }

    fn basis(&self, t_s: f64) -> Vector3<f64> {
        let phase = self.omega_rad_s * t_s;
        Vector3::new(1.0, phase.cos(), phase.sin())
    }

    /// The fitted force on each axis for basis values `b`.
    fn force_of(&self, b: &Vector3<f64>) -> Vector2<f64> {
        Vector2::new(self.coefficients[0].dot(b), self.coefficients[1].dot(b))
    }

    /// The fitted force on each axis at `t_s`.
    fn force(&self, t_s: f64) -> Vector2<f64> {
        self.force_of(&self.basis(t_s))
    }

    /// The fitted force's mean over `[from_s, from_s + span_s]`: the basis functions' means.
    fn mean_force(&self, from_s: f64, span_s: f64) -> Vector2<f64> {
        let w = self.omega_rad_s;
        if span_s * w < 1e-9 {
            return self.force(from_s);
        }
        let (start, end) = (w * from_s, w * (from_s + span_s));
        self.force_of(&Vector3::new(
            1.0,
            (end.sin() - start.sin()) / (w * span_s),
            (start.cos() - end.cos()) / (w * span_s),
        ))
    }
}

/// Weight of each new interval in the averaged pose interval (one odd gap does not switch the
/// lead off).
const POSE_INTERVAL_SMOOTHING: f64 = 0.05;

/// Longest sub-step of the propagation while a pulsation is fitted (the fitted force is held
/// over each), s.
const PULSATION_SUBSTEP_S: f64 = 2e-3;

/// Force history and the model at the last capture time.
pub struct StatePredictor {
    config: LatencyConfig,
    model: NominalModel,
    segments: VecDeque<ForceSegment>,
    /// The model at the last pose's capture time, and that pose's position.
    last: Option<(ModelState, Vector2<f64>)>,
    pulsation: Option<PulsationFit>,
    /// The interval between poses, averaged (s; none before two poses).
    pose_interval_s: Option<f64>,
    /// Mean squares of the measured motion between poses and of what the model missed of it
    /// (m², over `MOTION_SHARE_WINDOW_S`).
    motion_sq_m2: f64,
    residual_sq_m2: f64,
}

/// Averaging time of the unpredicted motion share: several pulsation periods.
pub(crate) const MOTION_SHARE_WINDOW_S: f64 = 2.0;

/// Longest span of force history kept (ns): far more than any usable pose age.
const HISTORY_NS: u64 = 5_000_000_000;

impl Predictor for StatePredictor {
    fn config(&self) -> &LatencyConfig {
        &self.config
    }

    /// Forgets the model state (after a rejected pose or a hold); the force history stays,
    /// since it is what the coils did.
    fn reset(&mut self) {
        self.last = None;
        if let Some(hz) = self.config.pulsation_hz {
            self.pulsation = Some(PulsationFit::new(hz));
        }
    }

    /// Records that `force_n` acts from `start_ns` on (the achieved force of a command, zero for
    /// hold and safe), against flow `flow_mps`.
    fn commanded(&mut self, start_ns: u64, force_n: Vector2<f64>, flow_mps: Vector2<f64>) {
        // A command can only replace what has not started yet.
        while self.segments.back().is_some_and(|s| s.start_ns >= start_ns) {
            self.segments.pop_back();
        }
        self.segments.push_back(ForceSegment {
            start_ns,
            force_n,
            flow_mps,
        });
        let oldest_needed = self
            .last
            .map_or(start_ns, |(m, _)| m.time_ns.min(start_ns))
            .saturating_sub(HISTORY_NS);
        while self.segments.len() > 1 && self.segments[1].start_ns <= oldest_needed {
            self.segments.pop_front();
        }
    }

    /// Takes the position measured at `capture_ns` and predicts the motion until
    /// `actuation_ns`. `flow_mps` is the flow estimate for this pose (used before any command
    /// was recorded).
    fn predict(
        &mut self,
        position_m: Vector2<f64>,
        capture_ns: u64,
        actuation_ns: u64,
        flow_mps: Vector2<f64>,
    ) -> Predicted {
        let horizon_s = actuation_ns.saturating_sub(capture_ns) as f64 * 1e-9;
        let tau_s = self.disturbance_time_constant_s(horizon_s);
        let mut now = match self.last {
            Some((previous, previous_position)) if capture_ns > previous.time_ns => {
                let interval_s = (capture_ns - previous.time_ns) as f64 * 1e-9;
                self.pose_interval_s = Some(self.pose_interval_s.map_or(interval_s, |mean| {
                    mean + POSE_INTERVAL_SMOOTHING * (interval_s - mean)
                }));
                let mut at_capture = self.propagate(previous, capture_ns, flow_mps);
                let measured_motion = position_m - previous_position;
                self.record_residual(&previous, &at_capture, measured_motion, interval_s);
                if self.pulsation.is_some() {
                    self.fit_pulsation(&previous, &mut at_capture, measured_motion, tau_s);
                } else {
                    self.learn_disturbance(&previous, &mut at_capture, measured_motion, tau_s);
                }
                at_capture
            }
            Some((previous, _)) if capture_ns == previous.time_ns => previous,
            _ => ModelState {
                time_ns: capture_ns,
                state: [Vector3::zeros(); 2],
                sensitivity: [Vector2::zeros(); BASIS],
            },
        };
        // Positions are relative: re-anchor at each pose so they stay small.
        for axis in 0..2 {
            now.state[axis][0] = 0.0;
        }
        for response in &mut now.sensitivity {
            response[0] = 0.0;
        }
        self.last = Some((now, position_m));
        let ahead = self.propagate(now, actuation_ns.max(capture_ns), flow_mps);
        Predicted {
            motion_ahead_m: Vector2::new(ahead.state[0][0], ahead.state[1][0]),
            velocity_mps: Vector2::new(ahead.state[0][1], ahead.state[1][1]),
            disturbance_n: Vector2::new(ahead.state[0][2], ahead.state[1][2])
                + self.pulsation.as_ref().map_or(Vector2::zeros(), |fit| {
                    fit.force(actuation_ns as f64 * 1e-9)
                }),
            horizon_s,
        }
    }

    /// The disturbance the model expects, on average, over the `span_s` from `from_ns` on (a
    /// command's hold, about one pose interval): the steady estimate of the last pose plus the
    /// fitted pulsation's mean. None before the second pose, and when the poses come too
    /// seldom to resolve the pulsation (fewer than `lead_min_poses_per_period` per period:
    /// at the paper's 10 Hz and 3 Hz, 3.3, where with little delay a fit from so few poses
    /// leads a controller astray) unless the last pose is at least `lead_min_delay_periods`
    /// of a period old at `from_ns`.
    fn lead_disturbance(&self, from_ns: u64, span_s: f64) -> Option<Vector2<f64>> {
        let (model, _) = self.last.as_ref()?;
        let span_s = span_s.max(0.0);
        let pulsation = match &self.pulsation {
            Some(fit) => {
                let period_s = std::f64::consts::TAU / fit.omega_rad_s;
                let sparse =
                    self.pose_interval_s? * self.config.lead_min_poses_per_period > period_s;
                let delay_s = from_ns.saturating_sub(model.time_ns) as f64 * 1e-9;
                if sparse && delay_s < self.config.lead_min_delay_periods * period_s {
                    return None;
                }
                fit.mean_force(from_ns as f64 * 1e-9, span_s)
            }
            None => Vector2::zeros(),
        };
        Some(Vector2::new(model.state[0][2], model.state[1][2]) + pulsation)
    }

    /// The share of the measured motion between poses that the model did not predict: RMS
    /// residual over RMS motion, at most 1 (0 before two poses).
    fn unpredicted_motion_share(&self) -> f64 {
        if self.motion_sq_m2 > 0.0 {
            (self.residual_sq_m2 / self.motion_sq_m2).sqrt().min(1.0)
        } else {
            0.0
        }
    }

    /// How far the robot may be from where the model puts it `horizon_s` after a pose: the
    /// recent RMS miss of the motion between poses (over `MOTION_SHARE_WINDOW_S`), grown in
    /// proportion to the horizon, never below one pose interval's (a command acts that long).
    /// 0 before two poses.
    fn expected_miss_m(&self, horizon_s: f64) -> f64 {
        match self.pose_interval_s {
            Some(interval_s) if interval_s > 0.0 => {
                self.residual_sq_m2.sqrt() * (horizon_s / interval_s).max(1.0)
            }
            _ => 0.0,
        }
    }
}

impl StatePredictor {
    pub fn new(config: LatencyConfig, model: NominalModel) -> Self {
        Self {
            model,
            segments: VecDeque::new(),
            last: None,
            pulsation: config.pulsation_hz.map(PulsationFit::new),
            pose_interval_s: None,
            motion_sq_m2: 0.0,
            residual_sq_m2: 0.0,
            config,
        }
    }

    /// Adds one pose interval's measured motion and the model's miss of it to the averages.
    /// The poses' own noise counts as a miss too; at 100 Hz in slow flow it is a fair part of
    /// the share (README, "What the predictor misses counts as lag").
    fn record_residual(
        &mut self,
        previous: &ModelState,
        at_capture: &ModelState,
        measured_motion: Vector2<f64>,
        interval_s: f64,
    ) {
        let model_motion =
            Vector2::from_fn(|axis, _| at_capture.state[axis][0] - previous.state[axis][0]);
        let residual = measured_motion - model_motion;
        if !(residual.norm_squared().is_finite() && measured_motion.norm_squared().is_finite()) {
            return;
        }
        let alpha = 1.0 - (-interval_s / MOTION_SHARE_WINDOW_S).exp();
        self.motion_sq_m2 += alpha * (measured_motion.norm_squared() - self.motion_sq_m2);
        self.residual_sq_m2 += alpha * (residual.norm_squared() - self.residual_sq_m2);
    }

    /// The disturbance estimate's time constant for a pose `horizon_s` old at actuation, s.
    fn disturbance_time_constant_s(&self, horizon_s: f64) -> f64 {
        (self.config.disturbance_delays * horizon_s)
            .max(self.config.disturbance_time_constant_ms * 1e-3)
    }

    /// Moves d̂ towards the force that would have made the model's motion since `previous`
    /// match the measured one (`measured_motion`), with time constant `tau_s`.
    fn learn_disturbance(
        &self,
        previous: &ModelState,
        at_capture: &mut ModelState,
        measured_motion: Vector2<f64>,
        tau_s: f64,
    ) {
        if tau_s <= 0.0 {
            return;
        }
        let dt = (at_capture.time_ns - previous.time_ns) as f64 * 1e-9;
        let alpha = 1.0 - (-dt / tau_s).exp();
        for axis in 0..2 {
            let model_motion = at_capture.state[axis][0] - previous.state[axis][0];
            // A steady force d moves the body at d / c: the missing force behind a velocity
            // mismatch.
            let missing =
                (measured_motion[axis] - model_motion) / dt * self.model.linear_drag_n_s_per_m;
            at_capture.state[axis][2] += alpha * missing;
        }
    }

    /// Recursive least squares on the motion mismatch since `previous`: the model is linear, so
    /// the mismatch is the sensitivities' motion times the coefficients' error. The model's
    /// velocity takes the correction's response along.
    fn fit_pulsation(
        &mut self,
        previous: &ModelState,
        at_capture: &mut ModelState,
        measured_motion: Vector2<f64>,
        tau_s: f64,
    ) {
        let Some(fit) = self.pulsation.as_mut() else {
            return;
        };
        let dt = (at_capture.time_ns - previous.time_ns) as f64 * 1e-9;
        let forgetting = (-dt / tau_s.max(1e-3)).exp();
        let regressor =
            Vector3::from_fn(|j, _| at_capture.sensitivity[j][0] - previous.sensitivity[j][0]);
        let p_phi = fit.covariance * regressor;
        let gain = p_phi / (forgetting + regressor.dot(&p_phi));
        for axis in 0..2 {
            let model_motion = at_capture.state[axis][0] - previous.state[axis][0];
            let correction = gain * (measured_motion[axis] - model_motion);
            fit.coefficients[axis] += correction;
            let velocity_response: f64 = (0..BASIS)
                .map(|j| correction[j] * at_capture.sensitivity[j][1])
                .sum();
            at_capture.state[axis][1] += velocity_response;
        }
        fit.covariance = (fit.covariance - gain * p_phi.transpose()) / forgetting;
        fit.covariance = (fit.covariance + fit.covariance.transpose()) * 0.5;
    }

    /// The model carried from its time to `to_ns` under the recorded forces.
    fn propagate(
        &self,
        mut model: ModelState,
        to_ns: u64,
        fallback_flow_mps: Vector2<f64>,
    ) -> ModelState {
        let mut t = model.time_ns;
        while t < to_ns {
            // The segment acting at t (none yet: no force, the current flow).
            let index = self.segments.partition_point(|s| s.start_ns <= t);
            let (force, flow) = match index.checked_sub(1) {
                Some(i) => (self.segments[i].force_n, self.segments[i].flow_mps),
                None => (Vector2::zeros(), fallback_flow_mps),
            };
            let next = self
                .segments
                .get(index)
                .map_or(to_ns, |s| s.start_ns.min(to_ns));
            let span = (next - t) as f64 * 1e-9;
            // With a fitted pulsation its force is held over short sub-steps.
            let pieces = match &self.pulsation {
                Some(_) => (span / PULSATION_SUBSTEP_S).ceil().max(1.0),
                None => 1.0,
            };
            let h = span / pieces;
            let (phi, gamma) = nominal_transition(&self.model, h);
            for piece in 0..pieces as usize {
                let mid_s = t as f64 * 1e-9 + (piece as f64 + 0.5) * h;
                let (fitted, basis) = match &self.pulsation {
                    Some(fit) => (fit.force(mid_s), fit.basis(mid_s)),
                    None => (Vector2::zeros(), Vector3::zeros()),
                };
                for axis in 0..2 {
                    let drive = (force[axis]
                        + fitted[axis]
                        + self.model.linear_drag_n_s_per_m * flow[axis])
                        / self.model.mass_kg;
                    model.state[axis] = phi * model.state[axis] + gamma * drive;
                }
                if self.pulsation.is_some() {
                    for (j, response) in model.sensitivity.iter_mut().enumerate() {
                        let full = phi * Vector3::new(response[0], response[1], 0.0)
                            + gamma * (basis[j] / self.model.mass_kg);
                        *response = Vector2::new(full[0], full[1]);
                    }
                }
            }
            t = next;
        }
        model.time_ns = to_ns.max(model.time_ns);
        model
    }
}

/// Exact transition of the nominal model's (p, v, d) over `h` seconds, d a force held over
/// the step, and the response to a constant acceleration input (F + c u)/m. Shared by the
/// latency predictor and the velocity observer.
fn nominal_transition(model: &NominalModel, h: f64) -> (Matrix3<f64>, Vector3<f64>) {
    let m = model.mass_kg;
    let a = model.linear_drag_n_s_per_m / m;
    // (1 − e^{−ah})/a and (h − (1 − e^{−ah})/a)/a, with their a → 0 limits h and h²/2.
    let (decay, first, second) = if a * h < 1e-6 {
        (1.0 - a * h, h, h * h / 2.0)
    } else {
        let decay = (-a * h).exp();
        let first = (1.0 - decay) / a;
        (decay, first, (h - first) / a)
    };
    let phi = Matrix3::new(1.0, first, second / m, 0.0, decay, first / m, 0.0, 0.0, 1.0);
    (phi, Vector3::new(second, first, 0.0))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) const MODEL: NominalModel = NominalModel {
        mass_kg: 5e-5,
        linear_drag_n_s_per_m: 5.6e-4,
    };

    pub(crate) fn ns(t_s: f64) -> u64 {
        (t_s * 1e9).round() as u64
    }

    /// The nominal model simulated finely, with a constant extra force `d`.
    fn simulate(
        forces: &[(f64, Vector2<f64>)],
        d: Vector2<f64>,
        until_s: f64,
    ) -> Vec<(f64, Vector2<f64>)> {
        simulate_with(forces, |_| d, until_s)
    }

    /// [`simulate`] with an extra force that varies in time (positions every 10 µs).
    pub(crate) fn simulate_with(
        forces: &[(f64, Vector2<f64>)],
        d: impl Fn(f64) -> Vector2<f64>,
        until_s: f64,
    ) -> Vec<(f64, Vector2<f64>)> {
        let (mut p, mut v) = (Vector2::zeros(), Vector2::zeros());
        let dt = 1e-5;
        let mut out = Vec::new();
        let steps = (until_s / dt).round() as usize;
        for k in 0..=steps {
            let t = k as f64 * dt;
            out.push((t, p));
            let f = forces
                .iter()
                .rev()
                .find(|(start, _)| *start <= t + 1e-12)
                .map_or(Vector2::zeros(), |(_, f)| *f);
            let a = (f + d(t) - v * MODEL.linear_drag_n_s_per_m) / MODEL.mass_kg;
            v += a * dt;
            p += v * dt;
        }
        out
    }

    /// Feeds `predictor` the frames of `forces` (one command per frame, poses `delay` old,
    /// predictions one `period` ahead) against `truth`, and returns the worst prediction error
    /// and the worst error of the stale pose from frame `from_frame` on, m.
    fn replay(
        mut predictor: StatePredictor,
        forces: &[(f64, Vector2<f64>)],
        truth: &[(f64, Vector2<f64>)],
        (period, delay): (f64, f64),
        from_frame: usize,
    ) -> (f64, f64) {
        let at = |t: f64| truth[(t / 1e-5).round() as usize].1;
        let (mut worst, mut stale): (f64, f64) = (0.0, 0.0);
        for (k, (start, force)) in forces.iter().enumerate() {
            predictor.commanded(ns(*start), *force, Vector2::zeros());
            let now = *start;
            if now < delay {
                continue;
            }
            let captured = now - delay;
            let predicted = predictor.predict(
                at(captured),
                ns(captured),
                ns(now + period),
                Vector2::zeros(),
            );
            if k > from_frame {
                let target = at(now + period);
                worst = worst.max((at(captured) + predicted.motion_ahead_m - target).norm());
                stale = stale.max((at(captured) - target).norm());
            }
        }
        (worst, stale)
    }

    /// With the delay known and the model right, the prediction lands on the truth: the
    /// predictor learns the unknown steady force from delayed positions and the commands explain
    /// the rest. Without the disturbance estimate the steady push is missed.
    #[test]
    fn predicts_the_true_position_across_the_delay() {
        let period = 0.1;
        let delay = 0.2;
        let d = Vector2::new(1e-5, -2e-5);
        // A force that changes every frame, as a controller's would.
        let forces: Vec<(f64, Vector2<f64>)> = (0..80)
            .map(|k| {
                let t = k as f64 * period;
                (
                    t,
                    Vector2::new(2e-5 * (t * 3.0).sin(), 1e-5 * (t * 1.7).cos()),
                )
            })
            .collect();
        let truth = simulate(&forces, d, 8.0);
        let worst_error = |disturbance_time_constant_ms: f64| {
            let config = LatencyConfig {
                disturbance_delays: 0.0,
                disturbance_time_constant_ms,
                ..LatencyConfig::default()
            };
            replay(
                StatePredictor::new(config, MODEL),
                &forces,
                &truth,
                (period, delay),
                60,
            )
        };
        let (learned, stale) = worst_error(300.0);
        // The robot moves millimetres over the horizon; the stale pose is that far off.
        assert!(stale > 1e-3, "stale pose error {stale} m");
        assert!(learned < 2e-5, "worst prediction error {learned} m");
        let (plain, _) = worst_error(0.0);
        assert!(
            plain > 10.0 * learned,
            "plain Smith {plain} m vs {learned} m"
        );
    }

    /// A pulsatile push at a known rate (the pump's) is learned in amplitude and phase and
    /// predicted across the delay; the steady estimate alone misses most of it.
    #[test]
    fn predicts_a_pulsatile_push_at_the_pump_rate() {
        let (period, delay, hz) = (0.1, 0.1, 3.0);
        let omega = std::f64::consts::TAU * hz;
        let push = |t: f64| {
            Vector2::new(
                2e-5 + 3e-5 * (omega * t + 0.7).sin(),
                -1e-5 * (omega * t).cos(),
            )
        };
        let forces: Vec<(f64, Vector2<f64>)> = (0..150)
            .map(|k| (k as f64 * period, Vector2::new(-2e-5, 0.0)))
            .collect();
        let truth = simulate_with(&forces, push, 15.0);
        let worst_error = |pulsation_hz: Option<f64>| {
            let config = LatencyConfig {
                pulsation_hz,
                ..LatencyConfig::default()
            };
            let predictor = StatePredictor::new(config, MODEL);
            replay(predictor, &forces, &truth, (period, delay), 100).0
        };
        let fitted = worst_error(Some(hz));
        let steady = worst_error(None);
        assert!(fitted < 2e-5, "pulsation fit: worst error {fitted} m");
        assert!(
            steady > 10.0 * fitted,
            "steady only: {steady} m vs {fitted} m"
        );
    }

    /// The disturbance estimate keeps a few delays slower than the poses it learns from, and
    /// never faster than its floor; with no delay factor its time constant is fixed.
    #[test]
    fn the_disturbance_time_constant_follows_the_delay() {
        let scaled = StatePredictor::new(LatencyConfig::default(), MODEL);
        assert!((scaled.disturbance_time_constant_s(0.06) - 0.24).abs() < 1e-12);
        assert!((scaled.disturbance_time_constant_s(0.2) - 0.8).abs() < 1e-12);
        assert!((scaled.disturbance_time_constant_s(0.0) - 0.1).abs() < 1e-12);
        let fixed = StatePredictor::new(
            LatencyConfig {
                disturbance_delays: 0.0,
                disturbance_time_constant_ms: 1000.0,
                ..LatencyConfig::default()
            },
            MODEL,
        );
        assert_eq!(fixed.disturbance_time_constant_s(0.2), 1.0);
    }

    /// The pulsation leads a controller only from poses that resolve it, and then as its mean
    /// over the command's hold.
    #[test]
    fn the_lead_needs_poses_that_resolve_the_pulsation() {
        let config = LatencyConfig {
            pulsation_hz: Some(3.0),
            ..LatencyConfig::default()
        };
        let poses = |period_s: f64| {
            let mut predictor = StatePredictor::new(config.clone(), MODEL);
            assert_eq!(predictor.lead_disturbance(0, period_s), None);
            for k in 0..20 {
                let t = ns(k as f64 * period_s);
                predictor.predict(Vector2::zeros(), t, t, Vector2::zeros());
            }
            predictor
        };
        // 10 Hz poses: 3.3 per period of a 3 Hz pulsation, too few while the delay is short
        // (the last pose was captured at 1.9 s)...
        let sparse = poses(0.1);
        assert_eq!(sparse.lead_disturbance(ns(1.9), 0.1), None);
        assert_eq!(sparse.lead_disturbance(ns(1.92), 0.1), None);
        // ...but a DOB that sees the push a sixth of a period late is beaten by the fit.
        assert!(sparse.lead_disturbance(ns(1.9 + 1.0 / 18.0), 0.1).is_some());
        // 100 Hz: 33 per period.
        let mut fast = poses(0.01);
        let fit = fast.pulsation.as_mut().unwrap();
        fit.coefficients = [
            Vector3::new(1e-5, 2e-5, -3e-5),
            Vector3::new(0.0, -1e-5, 0.0),
        ];
        let steady = Vector2::new(
            fast.last.unwrap().0.state[0][2],
            fast.last.unwrap().0.state[1][2],
        );
        let (from_s, span_s) = (0.2371, 0.01);
        let lead = fast.lead_disturbance(ns(from_s), span_s).unwrap();
        let fit = fast.pulsation.as_ref().unwrap();
        let steps = 10_000;
        let numeric = (0..steps)
            .map(|k| fit.force(from_s + (k as f64 + 0.5) / steps as f64 * span_s))
            .sum::<Vector2<f64>>()
            / steps as f64;
        assert!(
            (lead - steady - numeric).norm() < 1e-12,
            "{lead:?} vs {numeric:?}"
        );
    }

    /// Without any delay the prediction is the measurement.
    #[test]
    fn the_share_of_motion_the_model_misses_is_measured() {
        let model = NominalModel {
            mass_kg: 7.5e-5,
            linear_drag_n_s_per_m: 5.6e-4,
        };
        // The capsule driven by a known 3 Hz force, and once more with a push the model lacks
        // (1.3 Hz, a rate the model does not carry).
        let share = |unknown_push_n: f64| {
            let mut predictor = StatePredictor::new(LatencyConfig::default(), model);
            let dt = 0.01;
            let (mut p, mut v) = (Vector2::zeros(), Vector2::zeros());
            for k in 0..2000u64 {
                let t = k as f64 * dt;
                let omega = std::f64::consts::TAU * 3.0;
                let force = Vector2::new((omega * t).sin(), (omega * t).cos()) * 5e-5;
                predictor.predict(p, ns(t), ns(t), Vector2::zeros());
                predictor.commanded(ns(t), force, Vector2::zeros());
                for step in 0..10 {
                    let h = dt / 10.0;
                    let mid = t + (step as f64 + 0.5) * h;
                    let push = unknown_push_n * (std::f64::consts::TAU * 1.3 * mid + 1.0).sin();
                    let a = (force + Vector2::new(push, 0.0) - v * model.linear_drag_n_s_per_m)
                        / model.mass_kg;
                    v += a * h;
                    p += v * h;
                }
            }
            predictor.unpredicted_motion_share()
        };
        let known = share(0.0);
        let pushed = share(3e-5);
        assert!(
            known < 0.05,
            "the model's own motion counted as missed: {known}"
        );
        assert!(
            pushed > 0.2 && pushed <= 1.0,
            "a push the model lacks: {pushed}"
        );
    }

    #[test]
    fn zero_horizon_predicts_no_motion() {
        let mut predictor = StatePredictor::new(LatencyConfig::default(), MODEL);
        let predicted = predictor.predict(
            Vector2::new(0.01, -0.02),
            ns(1.0),
            ns(1.0),
            Vector2::zeros(),
        );
        assert_eq!(predicted.motion_ahead_m, Vector2::zeros());
        assert_eq!(predicted.horizon_s, 0.0);
    }

    #[test]
    fn a_newer_command_replaces_a_pending_one() {
        let mut predictor = StatePredictor::new(LatencyConfig::default(), MODEL);
        predictor.commanded(ns(1.0), Vector2::new(1.0, 0.0), Vector2::zeros());
        predictor.commanded(ns(1.0), Vector2::new(2.0, 0.0), Vector2::zeros());
        assert_eq!(predictor.segments.len(), 1);
        assert_eq!(predictor.segments[0].force_n.x, 2.0);
    }

    #[test]
    fn bad_fields_are_named() {
        let config = LatencyConfig {
            max_pose_age_ms: 0.0,
            ..LatencyConfig::default()
        };
        assert_eq!(config.invalid_field().unwrap().0, "max_pose_age_ms");
        let config = LatencyConfig {
            lead_min_poses_per_period: f64::NAN,
            ..LatencyConfig::default()
        };
        assert_eq!(
            config.invalid_field().unwrap().0,
            "lead_min_poses_per_period"
        );
        let config = LatencyConfig {
            lead_min_delay_periods: -0.1,
            ..LatencyConfig::default()
        };
        assert_eq!(config.invalid_field().unwrap().0, "lead_min_delay_periods");
        let config = LatencyConfig {
            max_field_turn_at_miss_rad: -0.2,
            ..LatencyConfig::default()
        };
        assert_eq!(
            config.invalid_field().unwrap().0,
            "max_field_turn_at_miss_rad"
        );
        assert!(LatencyConfig::default().invalid_field().is_none());
    }

    #[test]
    fn the_expected_miss_is_the_rms_miss_per_pose_grown_with_the_horizon() {
        let mut predictor = StatePredictor::new(LatencyConfig::default(), MODEL);
        assert_eq!(predictor.expected_miss_m(0.1), 0.0);
        // No force: the model expects no motion, and each pose 0.1 s later is 1 mm further on.
        for k in 0..200u64 {
            let position = Vector2::new(1e-3 * k as f64, 0.0);
            predictor.predict(
                position,
                ns(0.1 * k as f64),
                ns(0.1 * k as f64),
                Vector2::zeros(),
            );
            predictor.commanded(ns(0.1 * k as f64), Vector2::zeros(), Vector2::zeros());
        }
        // The disturbance estimate learns the drift, so the miss falls below the 1 mm a pose.
        let miss = predictor.expected_miss_m(0.1);
        assert!(miss > 0.0 && miss < 1e-3, "{miss}");
        assert!((predictor.expected_miss_m(0.3) - 3.0 * miss).abs() < 1e-12);
        // Never less than one pose interval's miss: the command acts that long.
        assert_eq!(predictor.expected_miss_m(0.01), miss);
    }
}
