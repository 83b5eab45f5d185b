//! Sliding-mode control with a disturbance observer (paper Eq. 8–14), and its ablations.

use nalgebra::Vector2;
use serde::{Deserialize, Serialize};

use super::interface::{ControlInput, ControlTerms, Controller, NominalModel};

/// SMC-DOB gains (paper Eq. 8–14). K1..K3 are not given in the paper; ours set the nominal
/// error dynamics to ω_n = sqrt(K2/K3) ≈ 12.6 rad/s (2 Hz) with ζ = K1/(2 sqrt(K2 K3)) = 1.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SmcGains {
    pub gamma: f64,
    pub lambda: f64,
    pub k1: f64,
    pub k2: f64,
    pub k3: f64,
    /// Switching gain K4 (N).
    pub k4_n: f64,
    /// DOB filter time constant η (s).
    pub eta_s: f64,
    /// Boundary layer φ (m).
    pub phi_m: f64,
    pub wp: f64,
    pub wr: f64,
    /// Run with the disturbance observer (false = the paper's "SMC without DOB" ablation).
    pub use_dob: bool,
    /// Schedule K4, η and φ automatically from the flow map's local speed (static gains in
    /// still fluid, the paper's flow gains at `schedule_ref_speed_mps`) and widen η and φ in
    /// the high-disturbance zone as the paper did by hand (η x1.75, φ x1.5). The observer then
    /// also takes the force the coils could make at their ratings as the loop's input instead
    /// of the force asked for: at the coil limits the difference is not a disturbance, and
    /// counting it as one winds d̂ up until the robot, once free, is thrown across the canal.
    /// A slew bound's shortfall is counted: it passes within frames, and d̂ makes up the mean
    /// force the bound withholds (without it, under a 60 A/s bound at 20 cP 10 cm/s, the robot sat
    /// 1.25 mm off its path on average for 20 s).
    pub auto_schedule: bool,
    pub flow_k4_n: f64,
    pub flow_eta_s: f64,
    pub flow_phi_m: f64,
    pub schedule_ref_speed_mps: f64,
    /// With `auto_schedule`: the boundary layer is widened so that the switching term's slope
    /// γ·K4/φ (a derivative gain on the estimated velocity) stays at or below this fraction of
    /// m̂/Δt, the nominal mass over the measured sample time. Above ≈ m̂/Δt the sampled loop
    /// rings: with the paper's K4/φ at our 100 Hz the slope is ≈ 9 m̂/Δt and SMC chatters at the
    /// current limit.
    pub sampled_gain_fraction: f64,
    /// With `auto_schedule`: the nominal error dynamics' natural frequency ω_n = sqrt(K2/K3)
    /// is kept at or below this many radians per sample (ω_n·Δt), with ζ unchanged. The
    /// default ω_n (2 Hz) is 0.13 rad per sample at 100 Hz but 1.26 at the paper's 10 Hz.
    pub sampled_bandwidth_rad: f64,
    /// With `auto_schedule`: the DOB's time constant η is kept at or above this many times
    /// the measured capture → actuation delay plus half the sample time (the mean delay of a
    /// command held over its sample).
    pub delay_eta_factor: f64,
    /// With `auto_schedule`: how many standard deviations of the coil gains' uncertainty
    /// (`ControlInput::coil_gain_std`) the force model may be off, ε. The latency predictor
    /// removes the measured capture → actuation delay only as far as its nominal force model is
    /// right: a force the coils make ε off leaves about ε·delay of it in the loop (at most 2ε/ω
    /// at the loop's bandwidth ω; `unpredicted_lag_s`), which counts as loop lag in the
    /// switching slope's sampled-loop bound (a fraction of m̂/(Δt + τ + that lag)). 2 (95 %):
    /// with the online gain estimate's 15 % prior, ε = 0.3 until the gains are learned, which
    /// held +30 ms of camera latency with a 10 % coil gain error at 100 Hz where 0 loses still
    /// fluid (README, "Camera latency with a coil calibration error"). 0: off. No effect
    /// without a measured delay. ε is at least the share of the robot's motion the predictor
    /// measurably failed to predict (`ControlInput::unpredicted_motion_share`: flow noise,
    /// form drag, whatever the nominal model lacks), which reaches the loop a delay late just
    /// the same (README, "What the predictor misses counts as lag").
    pub delay_model_error_sigmas: f64,
    /// With `auto_schedule`: ε is at least the share of the motion the latency predictor
    /// measurably missed (`ControlInput::unpredicted_motion_share`; see
    /// `delay_model_error_sigmas`). false: the coil gains' uncertainty alone (the behaviour
    /// before 2026-11-28).
    pub unpredicted_motion_lag: bool,
    /// With `auto_schedule` and the DOB: what the latency predictor expects of the
    /// disturbance at the actuation time (`ControlInput::predicted_disturbance_n`) leads the
    /// DOB's estimate. The DOB sees a push only through its η filter, late and damped (a 3 Hz
    /// pulsation through η = 0.12 s: 40 % of it, 66° late); the predictor fits the pulsation
    /// across the delay. d̂ becomes the DOB's estimate plus the predicted disturbance less the
    /// same prediction passed through the DOB's filter, so a steady prediction adds nothing and
    /// the DOB still corrects whatever the prediction gets wrong.
    pub predicted_disturbance_lead: bool,
    /// The coils' current time constant (s): `[control] coil_time_constant_ms`, not a gain.
    /// With `auto_schedule` and the DOB it counts as loop lag in the switching slope's
    /// sampled-loop bound (within a fraction of m̂/(Δt + τ)), and the DOB takes the force the
    /// coils made through that lag over each sample instead of the force commanded. 0: coils
    /// that follow within the sample.
    #[serde(skip)]
    pub coil_time_constant_s: f64,
}

impl Default for SmcGains {
    fn default() -> Self {
        Self {
            gamma: 2.0,
            lambda: 1.0,
            k1: 25.1,
            k2: 158.0,
            k3: 1.0,
            k4_n: 2.0e-4,
            eta_s: 6.0e-2,
            phi_m: 9.0e-3,
            wp: 1.0,
            wr: 1.0,
            use_dob: true,
            auto_schedule: false,
            flow_k4_n: 3.0e-4,
            flow_eta_s: 12.0e-2,
            flow_phi_m: 18.0e-3,
            schedule_ref_speed_mps: 0.07,
            sampled_gain_fraction: 0.5,
            sampled_bandwidth_rad: 0.5,
            delay_eta_factor: 2.0,
            delay_model_error_sigmas: 2.0,
            unpredicted_motion_lag: true,
            predicted_disturbance_lead: true,
            coil_time_constant_s: 0.0,
        }
    }
}

/// A command held over its sample (zero-order hold) acts on average this many sample times
/// after the actuation time.
const ZERO_ORDER_HOLD_DELAY: f64 = 0.5;

/// Over how long the SMC-DOB averages a slew bound's shortfall before its observer counts it
/// (s). The shortfall swings within each pump stroke (the bound holds the coils back
/// on the stroke's rise and lets them catch up after); counted frame by frame, those swings feed
/// back through d̂ into the very command the bound holds back, and under a tight bound the loop
/// rings without limit (`tests/dob.rs`); the paper-gain SMC-DOB, which took them so, settled
/// into a slow limit cycle in still fluid under a 60 A/s bound (4.3 cP: 2.19 mm, with the mean
/// 0.49 mm). About one stroke at the paper's 3 Hz, several η.
const SLEW_SHORTFALL_MEAN_S: f64 = 0.3;

/// The loop lag a latency predictor whose force model is `model_error` off leaves of a
/// `delay_s` delay, at the loop's bandwidth `bandwidth_rad_s`. The prediction then misses
/// ε·(e^(−sD) − 1) of the loop's own response: about ε·D of delay while ωD is small, but never
/// more than 2ε in magnitude, which at the bandwidth is 2ε/ω of delay. So it is
/// ε·2·sin(ωD/2)/ω, with ωD at most π.
fn unpredicted_lag_s(model_error: f64, delay_s: f64, bandwidth_rad_s: f64) -> f64 {
    let half_phase = (bandwidth_rad_s * delay_s / 2.0).min(std::f64::consts::FRAC_PI_2);
    model_error * 2.0 * half_phase.sin() / bandwidth_rad_s.max(1e-9)
}

pub struct SmcDob {
    gains: SmcGains,
    model: NominalModel,
    p: Vector2<f64>,
    r: Vector2<f64>,
    previous_force: Vector2<f64>,
    /// The predicted disturbance through the DOB's filter (`predicted_disturbance_lead`).
    q: Vector2<f64>,
    previous_prediction: Vector2<f64>,
    initialized: bool,
    /// The force the coils make at the end of the last sample, through their lag.
    coil_force: Vector2<f64>,
    last_dt_s: f64,
    /// The slew bound's shortfall (force at the ratings − force made), averaged over
    /// `SLEW_SHORTFALL_MEAN_S`.
    slew_shortfall: Vector2<f64>,
}

impl SmcDob {
    pub fn new(gains: SmcGains, model: NominalModel) -> Self {
        Self {
            gains,
            model,
            p: Vector2::zeros(),
            r: Vector2::zeros(),
            previous_force: Vector2::zeros(),
            q: Vector2::zeros(),
            previous_prediction: Vector2::zeros(),
            initialized: false,
            coil_force: Vector2::zeros(),
            last_dt_s: 0.01,
            slew_shortfall: Vector2::zeros(),
        }
    }

    /// The gains for this step: as configured, or scheduled from the flow (see `auto_schedule`).
    fn scheduled(&self, input: &ControlInput) -> SmcGains {
        let g = &self.gains;
        if !g.auto_schedule {
            return g.clone();
        }
        let b = self.flow_blend(input);
        let lerp = |a: f64, c: f64| a + (c - a) * b;
        let zone = if input.high_disturbance { 1.0 } else { 0.0 };
        let k4_n = lerp(g.k4_n, g.flow_k4_n);
        let phi_m = lerp(g.phi_m, g.flow_phi_m) * (1.0 + 0.5 * zone);
        // Sample time as measured, bounded so one odd gap cannot make φ absurd.
        let dt = input.dt_s.clamp(1e-3, 0.2);
        // The coils' lag delays every command's effect like the sample time does.
        let lag = if g.use_dob {
            g.coil_time_constant_s.max(0.0)
        } else {
            0.0
        };
        let fraction = g.sampled_gain_fraction.max(1e-3);
        let unpredicted = unpredicted_lag_s(
            (g.delay_model_error_sigmas.max(0.0) * input.coil_gain_std)
                .max(if g.unpredicted_motion_lag {
                    input.unpredicted_motion_share
                } else {
                    0.0
                })
                .min(1.0),
            input.delay_s.clamp(0.0, 1.0),
            fraction / (dt + lag),
        );
        let sampled_limit = fraction * self.model.mass_kg / (dt + lag + unpredicted);
        // Slow u_eq's error dynamics (same damping ratio) when the sample time cannot carry them.
        let omega_n = (g.k2 / g.k3).sqrt();
        // Drag damps the capsule within a sample as well (c·Δt/m̂), so it earns more bandwidth.
        let drag_per_sample = self.model.linear_drag_n_s_per_m * dt / self.model.mass_kg;
        let budget = g.sampled_bandwidth_rad.max(1e-3) * (1.0 + drag_per_sample);
        let omega_scale = (budget / (omega_n * dt)).min(1.0);
        // The observer sees a disturbance only `delay_s` after it acts, and the command that
        // answers it is held for the whole sample (on average half a sample late); its filter
        // must be slower than both (phase lag ω·D at its bandwidth 1/η), or it feeds the delay
        // back. Half a sample is what lets a capsule on the phantom floor (drag several times
        // the nominal) be held at 10 Hz (README, "The observer and the sample").
        let eta_s = (lerp(g.eta_s, g.flow_eta_s) * (1.0 + 0.75 * zone))
            .max(g.delay_eta_factor * (input.delay_s.clamp(0.0, 1.0) + ZERO_ORDER_HOLD_DELAY * dt));
        SmcGains {
            k1: g.k1 * omega_scale,
            k2: g.k2 * omega_scale * omega_scale,
            k4_n,
            eta_s,
            phi_m: phi_m.max(g.gamma * k4_n / sampled_limit),
            ..g.clone()
        }
    }

    /// How far the schedule is from still fluid toward the flow gains: the flow map's local
    /// speed over `schedule_ref_speed_mps`, at most 1.
    fn flow_blend(&self, input: &ControlInput) -> f64 {
        let g = &self.gains;
        (input.flow_mps.norm() / g.schedule_ref_speed_mps.max(1e-6)).clamp(0.0, 1.0)
    }

    /// C(ẋ, V) = c_t (ẋ + V) exactly as the paper writes it (Eq. 12–13). With the DOB on, the
    /// C terms of d̂ and u_eq cancel; without it, −C adds damping and cancels the flow push.
    fn modeled_drag(&self, velocity: &Vector2<f64>, flow: &Vector2<f64>) -> Vector2<f64> {
        (velocity + flow) * self.model.linear_drag_n_s_per_m
    }
}

impl Controller for SmcDob {
    fn name(&self) -> &'static str {
        match (self.gains.use_dob, self.gains.auto_schedule) {
            (true, false) => "smc-dob",
            (true, true) => "smc-dob-auto",
            (false, false) => "smc",
            (false, true) => "smc-auto",
        }
    }
    fn id(&self) -> u32 {
        match (self.gains.use_dob, self.gains.auto_schedule) {
            (true, false) => 2,
            (true, true) => 5,
            (false, false) => 3,
            (false, true) => 6,
        }
    }
    fn update(&mut self, input: &ControlInput) -> (Vector2<f64>, ControlTerms) {
        let g = &self.scheduled(input);
        let m = self.model.mass_kg;
        let e = input.reference.position_m - input.position_m;
        let e_dot = input.reference.velocity_mps - input.velocity_mps;
        let s = e_dot * g.gamma + e * g.lambda;
        let c = self.modeled_drag(&input.velocity_mps, &input.flow_mps);

        // Scheduled with the flow like K4, η and φ: nothing in still fluid, where the
        // prediction has only noise to fit.
        let prediction = match input.predicted_disturbance_n {
            Some(predicted) if g.use_dob && g.auto_schedule && g.predicted_disturbance_lead => {
                predicted * self.flow_blend(input)
            }
            _ => Vector2::zeros(),
        };
        if !self.initialized {
            self.p = e_dot;
            self.r = Vector2::zeros();
            self.q = prediction;
            self.previous_prediction = prediction;
            self.initialized = true;
        }
        // Exact discretisation of the first-order filters ṗ = −(W/η)(p − ė), ṙ = −(W/η)(r − F_prev).
        let alpha_p = 1.0 - (-g.wp * input.dt_s / g.eta_s).exp();
        let alpha_r = 1.0 - (-g.wr * input.dt_s / g.eta_s).exp();
        let d_hat = if g.use_dob {
            let filtered_derivative = (self.p - e_dot) * (g.wp / g.eta_s);
            // The prediction filtered as r filters the force (one step behind, as the DOB).
            self.q += (self.previous_prediction - self.q) * alpha_r;
            let estimate = filtered_derivative * m - c - self.r + (prediction - self.q);
            self.p += (e_dot - self.p) * alpha_p;
            self.r += (self.previous_force - self.r) * alpha_r;
            estimate
        } else {
            Vector2::zeros()
        };
        let u_eq =
            (e_dot * g.k1 + e * g.k2) * (m / g.k3) + input.reference.acceleration_mps2 * m - c;
        let u_sw = s.map(|v| g.k4_n * (v / g.phi_m).tanh());
        let force = -d_hat + u_eq + u_sw;
        self.previous_force = force;
        self.last_dt_s = input.dt_s.clamp(1e-4, 0.5);
        self.previous_prediction = prediction;
        (
            force,
            ControlTerms {
                error_m: e,
                error_rate_mps: e_dot,
                sliding_surface: s,
                disturbance_estimate_n: d_hat,
            },
        )
    }
    fn applied(&mut self, achieved_n: Vector2<f64>, at_ratings_n: Vector2<f64>) {
        // A slew bound's shortfall reaches d̂ as its mean only.
        let dt = self.last_dt_s;
        let k = 1.0 - (-dt / SLEW_SHORTFALL_MEAN_S).exp();
        let shortfall = at_ratings_n - achieved_n;
        self.slew_shortfall += (shortfall - self.slew_shortfall) * k;
        if !self.gains.auto_schedule {
            // The paper's DOB takes the force asked for (its coil limits counted as a
            // disturbance, as the paper has it); of a slew bound's shortfall only the mean.
            self.previous_force -= shortfall - self.slew_shortfall;
        }
        // The coil limits stay out of the scheduled DOB's d̂ (anti-windup).
        let achieved_n = achieved_n + self.slew_shortfall;
        if self.gains.auto_schedule {
            let tau = self.gains.coil_time_constant_s;
            if self.gains.use_dob && tau > 0.0 {
                // A first-order lag from where the coils were toward the new command: its
                // mean over the sample (the DOB's input) and where it ends.
                let a = (-dt / tau).exp();
                let start = self.coil_force - achieved_n;
                self.previous_force = achieved_n + start * (tau / dt * (1.0 - a));
                self.coil_force = achieved_n + start * a;
            } else {
                self.previous_force = achieved_n;
            }
        }
    }
    fn reset(&mut self) {
        self.initialized = false;
        self.p = Vector2::zeros();
        self.r = Vector2::zeros();
        self.previous_force = Vector2::zeros();
        self.q = Vector2::zeros();
        self.previous_prediction = Vector2::zeros();
        self.coil_force = Vector2::zeros();
        self.slew_shortfall = Vector2::zeros();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference::ReferenceSample;

    fn input(dt_s: f64) -> ControlInput {
        ControlInput {
            dt_s,
            delay_s: 0.0,
            position_m: Vector2::zeros(),
            velocity_mps: Vector2::zeros(),
            reference: ReferenceSample {
                position_m: Vector2::zeros(),
                velocity_mps: Vector2::zeros(),
                acceleration_mps2: Vector2::zeros(),
                finished: false,
            },
            flow_mps: Vector2::zeros(),
            high_disturbance: false,
            predicted_disturbance_n: None,
            coil_gain_std: 0.0,
            unpredicted_motion_share: 0.0,
        }
    }

    fn scheduled(dt_s: f64, drag: f64) -> SmcGains {
        let model = NominalModel {
            mass_kg: 5e-5,
            linear_drag_n_s_per_m: drag,
        };
        let gains = SmcGains {
            auto_schedule: true,
            ..SmcGains::default()
        };
        SmcDob::new(gains, model).scheduled(&input(dt_s))
    }

    #[test]
    fn schedule_keeps_error_dynamics_at_100_hz_and_slows_them_at_10_hz() {
        let paper = SmcGains::default();
        let fast = scheduled(0.01, 1.2e-4);
        assert_eq!((fast.k1, fast.k2), (paper.k1, paper.k2));

        let slow = scheduled(0.1, 1.2e-4);
        let omega_dt = (slow.k2 / slow.k3).sqrt() * 0.1;
        let budget = paper.sampled_bandwidth_rad * (1.0 + 1.2e-4 * 0.1 / 5e-5);
        assert!((omega_dt - budget).abs() < 1e-9, "ω_n·Δt {omega_dt}");
        // Same damping ratio ζ = K1 / (2 sqrt(K2 K3)).
        let zeta = |g: &SmcGains| g.k1 / (2.0 * (g.k2 * g.k3).sqrt());
        assert!((zeta(&slow) - zeta(&paper)).abs() < 1e-9);
        // More drag damps more per sample, so it keeps more bandwidth.
        assert!(scheduled(0.1, 5.6e-4).k2 > slow.k2);
        // And the switching slope stays within the sampled-loop bound.
        let slope = slow.gamma * slow.k4_n / slow.phi_m;
        assert!(slope <= paper.sampled_gain_fraction * 5e-5 / 0.1 * (1.0 + 1e-9));
    }

    /// The scheduled switching slope γ·K4/φ of a 50 mg capsule in 4.3 cP at 100 Hz, with the
    /// coil gains' uncertainty (`sigmas` of `coil_gain_std`), the predictor's measured miss
    /// and the delay given.
    fn delayed_slope(sigmas: f64, coil_gain_std: f64, share: f64, delay_s: f64) -> f64 {
        let model = NominalModel {
            mass_kg: 5e-5,
            linear_drag_n_s_per_m: 1.2e-4,
        };
        let gains = SmcGains {
            auto_schedule: true,
            delay_model_error_sigmas: sigmas,
            ..SmcGains::default()
        };
        let g = SmcDob::new(gains, model).scheduled(&ControlInput {
            delay_s,
            coil_gain_std,
            unpredicted_motion_share: share,
            ..input(0.01)
        });
        g.gamma * g.k4_n / g.phi_m
    }

    #[test]
    fn the_delay_the_predictor_may_get_wrong_slows_the_switching_slope() {
        let slope_at =
            |sigmas, coil_gain_std, delay_s| delayed_slope(sigmas, coil_gain_std, 0.0, delay_s);
        // Off, with gains known exactly, or without a delay, the bound is m̂/Δt's fraction.
        let bound = SmcGains::default().sampled_gain_fraction * 5e-5 / 0.01;
        assert!((slope_at(0.0, 0.15, 0.05) - bound).abs() < 1e-9 * bound);
        assert!((slope_at(2.0, 0.0, 0.05) - bound).abs() < 1e-9 * bound);
        assert!((slope_at(2.0, 0.15, 0.0) - bound).abs() < 1e-9 * bound);
        // 2σ of 15 % is ε = 30 %. The loop's bandwidth is the slope over m̂: 0.5/Δt = 50 rad/s.
        // A 5 ms delay is short against it (ωD = 0.25): it counts as ε·D = 1.5 ms of lag.
        let short = slope_at(2.0, 0.15, 0.005);
        let expected = bound * 0.01 / (0.01 + 0.3 * 2.0 * (0.125f64).sin() / 50.0);
        assert!(
            (short - expected).abs() < 1e-9 * bound,
            "{short} {expected}"
        );
        assert!((0.01 / (0.01 + 0.3 * 0.005) - short / bound).abs() < 2e-3);
        // A 50 ms delay (ωD = 2.5) counts as 2ε·sin(1.25)/ω ≈ 11.4 ms, less than ε·D = 15 ms;
        // from ωD = π on (63 ms) every delay counts as the most, 2ε/ω = 12 ms.
        let slowed = slope_at(2.0, 0.15, 0.05);
        let expected = bound * 0.01 / (0.01 + 0.3 * 2.0 * (1.25f64).sin() / 50.0);
        assert!(
            (slowed - expected).abs() < 1e-9 * bound,
            "{slowed} {expected}"
        );
        let longest = slope_at(2.0, 0.15, 0.1);
        assert!((longest - bound * 0.01 / (0.01 + 0.012)).abs() < 1e-9 * bound);
        assert!((slope_at(2.0, 0.15, 0.5) - longest).abs() < 1e-9 * bound);
        // As the gains are learned the slope comes back; a wild uncertainty counts as ε = 1.
        assert!(slope_at(2.0, 0.02, 0.05) > slowed);
        let whole = slope_at(2.0, 5.0, 0.1);
        assert!((whole - bound * 0.01 / (0.01 + 0.04)).abs() < 1e-9 * bound);
    }

    #[test]
    fn motion_the_predictor_misses_slows_the_switching_slope_as_a_gain_error_does() {
        let slope_at =
            |coil_gain_std, share, delay_s| delayed_slope(2.0, coil_gain_std, share, delay_s);
        let bound = SmcGains::default().sampled_gain_fraction * 5e-5 / 0.01;
        // Without a delay nothing reaches the loop late.
        assert!((slope_at(0.0, 0.8, 0.0) - bound).abs() < 1e-9 * bound);
        // ε is the larger of 2σ of the gains and the measured share: 0.5 over 2·0.15.
        let slowed = slope_at(0.15, 0.5, 0.05);
        let expected = bound * 0.01 / (0.01 + 0.5 * 2.0 * (1.25f64).sin() / 50.0);
        assert!(
            (slowed - expected).abs() < 1e-9 * bound,
            "{slowed} {expected}"
        );
        assert!((slope_at(0.15, 0.1, 0.05) - slope_at(0.15, 0.0, 0.05)).abs() < 1e-12);
        assert!(slope_at(0.0, 0.9, 0.05) < slowed);
    }
}
