//! Velocity from a model-based observer instead of differences of poses.
//!
//! A velocity differentiated from poses is either noisy (raw differences: 20 µm of localization
//! noise over 10 ms is 3 mm/s) or late (low-passed); a derivative term fed either rings in the
//! sampled loop and throws the coil currents between their limits. The nominal model knows what
//! moves the robot between two poses, the force the coils made, so a Kalman filter on
//! (p, v, d) per axis predicts the velocity from the commands and corrects it with each pose;
//! d is the push the model does not know (unmapped flow, drag it underestimates), a random walk
//! whose pace is `unknown_flow_change_mps_per_sqrt_s`, plus, when the pump's stroke rate is
//! known, a pulsatile push at that rate (an oscillator whose amplitude and phase the filter
//! learns: the internal model of the pulsation).
//!
//! The velocity is the model's instantaneous one at the pose's time. At 100 Hz it lets PID and
//! the paper-gain SMC run smoothly; at the paper's 10 Hz the scheduled SMCs, whose gains assume
//! the frame-averaged velocity of differences, ring with it (README "Coil effort").

use nalgebra::{SMatrix, SVector, Vector2};
use serde::{Deserialize, Serialize};

use crate::controllers::NominalModel;

/// Where the controllers' velocity comes from (`[control] velocity_estimate`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum VelocityEstimate {
    /// Finite differences of the fed positions, low-passed with `velocity_filter_ms`.
    #[default]
    Differences,
    /// The Kalman filter of this module (`[control.observer]`).
    Observer,
}

/// `[control.observer]` of a scenario.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ObserverConfig {
    /// Localization noise of one pose, per axis (mm, 1σ): the measurement noise. Default: the
    /// UNet's centroid error on the twin's test split (vision-eval, ≈ 0.02 mm).
    pub position_noise_mm: f64,
    /// How fast the push the model does not know may change, expressed as the flow speed that
    /// would make it (random-walk intensity, m/s per √s; the force is c_t times it). With the
    /// pump's rate known (`[control.latency] pulsation_hz`) the pulsation itself is an
    /// oscillator of the observer and this is the drift of its amplitude and of the steady
    /// push. Default 0.01: a robot moving 0.5–1 mm/s through a canal whose flow changes by
    /// 7 cm/s across ≈ 5 mm meets ≈ 0.01 m/s more or less flow per second. Larger follows faster
    /// changes and passes more localization noise into the velocity (at 100 Hz: 0.03 doubles
    /// the coil steps of PID, 0.003 halves them and lags in flow; README "Coil effort").
    pub unknown_flow_change_mps_per_sqrt_s: f64,
    /// Harmonics of the pump's rate the pulsation oscillator carries (1 to
    /// [`MAX_PULSATION_HARMONICS`]; used only with `[control.latency] pulsation_hz`). A
    /// peristaltic pump's flow is no sine: each roller pass pinches the tube and the flow turns
    /// sharply, so its stroke carries harmonics (a rectified sine's second is a fifth of its
    /// first, its third a twelfth). 1 models the fundamental alone.
    pub pulsation_harmonics: usize,
}

impl Default for ObserverConfig {
    fn default() -> Self {
        Self {
            position_noise_mm: 0.02,
            unknown_flow_change_mps_per_sqrt_s: 0.01,
            pulsation_harmonics: 1,
        }
    }
}

impl ObserverConfig {
    /// The first field that is out of range, with why.
    pub fn invalid_field(&self) -> Option<(&'static str, String)> {
        [
            ("position_noise_mm", self.position_noise_mm),
            (
                "unknown_flow_change_mps_per_sqrt_s",
                self.unknown_flow_change_mps_per_sqrt_s,
            ),
        ]
        .into_iter()
        .find_map(|(name, value)| {
            (!(value.is_finite() && value > 0.0))
                .then(|| (name, format!("must be finite and > 0, got {value}")))
        })
        .or_else(|| {
            let harmonics = self.pulsation_harmonics;
            (!(1..=MAX_PULSATION_HARMONICS).contains(&harmonics)).then(|| {
                (
                    "pulsation_harmonics",
                    format!("must be 1 to {MAX_PULSATION_HARMONICS}, got {harmonics}"),
                )
            })
        })
    }
}

/// Prior spread of the velocity when the observer starts (m/s): a robot at rest or drifting.
const INITIAL_VELOCITY_STD_MPS: f64 = 0.01;
/// Prior spread of the unknown push at start, steady and pulsatile, as a flow speed (m/s).
const INITIAL_FLOW_STD_MPS: f64 = 0.1;

/// Most harmonics of the pump's rate the observer models (`pulsation_harmonics`).
pub const MAX_PULSATION_HARMONICS: usize = 3;
/// Per axis: position, velocity, steady push, and the pulsatile push as one oscillator per
/// harmonic of the pump's rate (two phases each). Oscillators not modelled stay at zero.
const STATES: usize = 3 + 2 * MAX_PULSATION_HARMONICS;
/// Index of the first oscillator state.
const FIRST_OSCILLATOR: usize = 3;
type StateVector = SVector<f64, STATES>;
type StateMatrix = SMatrix<f64, STATES, STATES>;

/// Kalman filter on (p, v, d, z₁, z₂, …) per axis, d the steady push the model does not know and
/// z₁ the pulsatile one at the pump's rate (z₂ its quadrature; further pairs its harmonics, each
/// pushing like z₁); both axes share the covariance (same model, same noise).
pub struct VelocityObserver {
    config: ObserverConfig,
    model: NominalModel,
    /// The pump's stroke rate (rad/s), when known (`[control.latency] pulsation_hz`).
    pulsation_rad_s: Option<f64>,
    /// Oscillators in use: the configured harmonics with a known rate, else none.
    harmonics: usize,
    state: Option<ObserverState>,
    /// Force held since the last pose (the achieved force of the last command) and the flow
    /// the nominal drag acts against.
    held_force_n: Vector2<f64>,
    held_flow_mps: Vector2<f64>,
    /// The transition over the last step length (most steps are one frame period).
    transition: Option<(f64, StateMatrix, StateVector)>,
}

#[derive(Debug, Clone, Copy)]
struct ObserverState {
    time_ns: u64,
    axes: [StateVector; 2],
    covariance: StateMatrix,
}

impl VelocityObserver {
    /// `model` is the moving body's (mass including the added mass); `pulsation_hz` the pump's
    /// stroke rate when the lab knows it.
    pub fn new(config: ObserverConfig, model: NominalModel, pulsation_hz: Option<f64>) -> Self {
        let harmonics = if pulsation_hz.is_some() {
            config.pulsation_harmonics.clamp(1, MAX_PULSATION_HARMONICS)
        } else {
            0
        };
        Self {
            config,
            model,
            pulsation_rad_s: pulsation_hz.map(|hz| std::f64::consts::TAU * hz),
            harmonics,
            state: None,
            held_force_n: Vector2::zeros(),
            held_flow_mps: Vector2::zeros(),
            transition: None,
        }
    }

    /// Starts over from the next pose (after a hold or a rejected pose).
    pub fn reset(&mut self) {
        self.state = None;
        self.held_force_n = Vector2::zeros();
    }

    /// The force the coils make from now until the next pose, against flow `flow_mps`.
    pub fn applied(&mut self, force_n: Vector2<f64>, flow_mps: Vector2<f64>) {
        self.held_force_n = force_n;
        self.held_flow_mps = flow_mps;
    }

    /// Exact discretisation over `h` seconds: the state transition and the response to a
    /// constant force input (N), from the exponential of the augmented continuous model.
    fn discretised(&mut self, h: f64) -> (StateMatrix, StateVector) {
        if let Some((cached_h, phi, gamma)) = self.transition {
            if cached_h == h {
                return (phi, gamma);
            }
        }
        let m = self.model.mass_kg;
        let omega = self.pulsation_rad_s.unwrap_or(0.0);
        let mut augmented = SMatrix::<f64, { STATES + 1 }, { STATES + 1 }>::zeros();
        augmented[(0, 1)] = 1.0;
        augmented[(1, 1)] = -self.model.linear_drag_n_s_per_m / m;
        augmented[(1, 2)] = 1.0 / m;
        for k in 0..self.harmonics {
            let (z1, z2) = (FIRST_OSCILLATOR + 2 * k, FIRST_OSCILLATOR + 2 * k + 1);
            let rate = omega * (k + 1) as f64;
            augmented[(1, z1)] = 1.0 / m;
            augmented[(z1, z2)] = -rate;
            augmented[(z2, z1)] = rate;
        }
        augmented[(1, STATES)] = 1.0 / m;
        let exp = (augmented * h).exp();
        let phi: StateMatrix = exp.fixed_view::<STATES, STATES>(0, 0).into_owned();
        let gamma: StateVector = exp.fixed_view::<STATES, 1>(0, STATES).into_owned();
        self.transition = Some((h, phi, gamma));
        (phi, gamma)
    }

    /// Takes the position at `time_ns` and returns the velocity estimate there.
    pub fn update(
        &mut self,
        time_ns: u64,
        position_m: Vector2<f64>,
        flow_mps: Vector2<f64>,
    ) -> Vector2<f64> {
        let c = self.model.linear_drag_n_s_per_m;
        let measurement_var = (self.config.position_noise_mm * 1e-3).powi(2);
        let push_var = |speed_mps: f64| (c * speed_mps).powi(2);
        let oscillators = FIRST_OSCILLATOR..FIRST_OSCILLATOR + 2 * self.harmonics;
        let Some(mut state) = self.state.filter(|s| time_ns >= s.time_ns) else {
            self.held_flow_mps = flow_mps;
            let mut prior = StateVector::zeros();
            prior[0] = measurement_var;
            prior[1] = INITIAL_VELOCITY_STD_MPS.powi(2);
            prior[2] = push_var(INITIAL_FLOW_STD_MPS);
            for i in oscillators {
                prior[i] = push_var(INITIAL_FLOW_STD_MPS);
            }
            self.state = Some(ObserverState {
                time_ns,
                axes: [0, 1].map(|axis| {
                    let mut x = StateVector::zeros();
                    x[0] = position_m[axis];
                    x
                }),
                covariance: StateMatrix::from_diagonal(&prior),
            });
            return Vector2::zeros();
        };
        let h = (time_ns - state.time_ns) as f64 * 1e-9;
        if h > 0.0 {
            let (phi, gamma) = self.discretised(h);
            for axis in 0..2 {
                let input = self.held_force_n[axis] + c * self.held_flow_mps[axis];
                state.axes[axis] = phi * state.axes[axis] + gamma * input;
            }
            let change = push_var(self.config.unknown_flow_change_mps_per_sqrt_s) * h;
            state.covariance = phi * state.covariance * phi.transpose();
            state.covariance[(2, 2)] += change;
            for i in oscillators {
                state.covariance[(i, i)] += change;
            }
        }
        let mut row = SMatrix::<f64, 1, STATES>::zeros();
        row[0] = 1.0;
        let innovation_var = state.covariance[(0, 0)] + measurement_var;
        let gain: StateVector = state.covariance.column(0) / innovation_var;
        for axis in 0..2 {
            let innovation = position_m[axis] - state.axes[axis][0];
            state.axes[axis] += gain * innovation;
        }
        // Joseph form keeps the covariance symmetric and positive under rounding.
        let keep = StateMatrix::identity() - gain * row;
        state.covariance =
            keep * state.covariance * keep.transpose() + gain * gain.transpose() * measurement_var;
        state.time_ns = time_ns;
        self.state = Some(state);
        self.held_flow_mps = flow_mps;
        Vector2::new(state.axes[0][1], state.axes[1][1])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    const MODEL: NominalModel = NominalModel {
        mass_kg: 7.5e-5,
        linear_drag_n_s_per_m: 5.6e-4,
    };

    /// The nominal model simulated finely under `force(t)` plus an unknown push `push(t)`;
    /// poses every `period_s` with Gaussian noise. Returns the RMS velocity error of the
    /// observer and of 30 ms low-passed differences after `settle_s`.
    fn track(
        force: impl Fn(f64) -> f64,
        push: impl Fn(f64) -> f64,
        period_s: f64,
        noise_m: f64,
        pulsation_hz: Option<f64>,
        pulsation_harmonics: usize,
    ) -> (f64, f64) {
        let config = ObserverConfig {
            pulsation_harmonics,
            ..Default::default()
        };
        let mut observer = VelocityObserver::new(config, MODEL, pulsation_hz);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let noise = Normal::new(0.0, noise_m).unwrap();
        let (mut p, mut v) = (0.0, 0.0);
        let dt = 1e-5;
        let substeps = (period_s / dt).round() as usize;
        let (mut filtered, mut last_measured) = (0.0, None::<f64>);
        let alpha = 1.0 - (-period_s / 0.03f64).exp();
        let (mut observer_sq, mut filter_sq, mut n) = (0.0, 0.0, 0);
        for k in 0..(4.0 / period_s) as usize {
            let t = k as f64 * period_s;
            let measured = p + noise.sample(&mut rng);
            let estimate = observer.update(
                (t * 1e9) as u64,
                Vector2::new(measured, 0.0),
                Vector2::zeros(),
            );
            if let Some(previous) = last_measured {
                filtered += ((measured - previous) / period_s - filtered) * alpha;
            }
            last_measured = Some(measured);
            if t > 1.0 {
                observer_sq += (estimate.x - v).powi(2);
                filter_sq += (filtered - v).powi(2);
                n += 1;
            }
            let f = force(t);
            observer.applied(Vector2::new(f, 0.0), Vector2::zeros());
            for j in 0..substeps {
                let ts = t + j as f64 * dt;
                let a = (f + push(ts) - MODEL.linear_drag_n_s_per_m * v) / MODEL.mass_kg;
                v += a * dt;
                p += v * dt;
            }
        }
        (
            (observer_sq / n as f64).sqrt(),
            (filter_sq / n as f64).sqrt(),
        )
    }

    #[test]
    fn known_forces_give_a_velocity_several_times_closer_than_filtered_differences() {
        // A force switching every 0.2 s, as a loop correcting its error would command.
        let force = |t: f64| {
            if ((t / 0.2) as u64).is_multiple_of(2) {
                2e-5
            } else {
                -2e-5
            }
        };
        let (observer, filtered) = track(force, |_| 0.0, 0.01, 2e-5, None, 1);
        assert!(
            observer * 3.0 < filtered,
            "observer {observer:.2e} m/s vs filtered differences {filtered:.2e} m/s"
        );
    }

    #[test]
    fn an_unknown_pulsating_push_is_followed() {
        // ±3.5 cm/s of unmapped flow at 3 Hz at 20 cP: the velocity it makes is ≈ 2 cm/s.
        let push = |t: f64| 5.6e-4 * 0.035 * (std::f64::consts::TAU * 3.0 * t).sin();
        let (observer, filtered) = track(|_| 0.0, push, 0.01, 2e-5, Some(3.0), 1);
        assert!(
            observer < 0.1 * 0.02 && observer < filtered,
            "observer {observer:.2e} m/s vs filtered differences {filtered:.2e} m/s"
        );
    }

    #[test]
    fn a_peristaltic_push_is_followed_closer_with_its_harmonics() {
        // A rectified sine at 3 Hz strokes (a peristaltic pump's pinch), ±3.5 cm/s at 20 cP.
        let push = |t: f64| {
            let stroke = (std::f64::consts::PI * 3.0 * t).sin().abs();
            5.6e-4 * 0.035 * (stroke - 2.0 / std::f64::consts::PI)
                / (1.0 - 2.0 / std::f64::consts::PI)
        };
        let (fundamental, _) = track(|_| 0.0, push, 0.01, 2e-5, Some(3.0), 1);
        let (harmonics, _) = track(|_| 0.0, push, 0.01, 2e-5, Some(3.0), 3);
        assert!(
            harmonics < 0.8 * fundamental,
            "three harmonics {harmonics:.2e} m/s vs the fundamental alone {fundamental:.2e} m/s"
        );
    }

    #[test]
    fn out_of_range_fields_are_named() {
        let config = ObserverConfig {
            position_noise_mm: 0.0,
            ..Default::default()
        };
        assert_eq!(config.invalid_field().unwrap().0, "position_noise_mm");
        let config = ObserverConfig {
            pulsation_harmonics: MAX_PULSATION_HARMONICS + 1,
            ..Default::default()
        };
        assert_eq!(config.invalid_field().unwrap().0, "pulsation_harmonics");
        assert!(ObserverConfig::default().invalid_field().is_none());
    }
}
