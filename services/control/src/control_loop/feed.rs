//! The state the controller is fed: the pose carried across the delay by the latency predictor
//! (a Smith predictor), and the velocity from filtered differences or the observer.

use nalgebra::Vector2;

use super::{ControlLoop, StepTiming};
use crate::latency::Predicted;
use crate::latency::Predictor;

/// What the controller is fed for one pose.
pub(super) struct Fed {
    /// The predictor's view of the motion until the actuation time.
    pub predicted: Predicted,
    /// The position fed (predicted for the actuation time when compensating, else measured).
    pub position_m: Vector2<f64>,
    /// Time since the previous fed state (s; 0 when the loop starts afresh or the pose repeats).
    pub dt_s: f64,
}

impl ControlLoop {
    /// Predicts the state at the actuation time from the measured position and updates the
    /// velocity the controllers see.
    pub(super) fn feed(
        &mut self,
        measured: Vector2<f64>,
        timing: &StepTiming,
        flow_mps: Vector2<f64>,
        tracking: bool,
    ) -> Fed {
        let predicted =
            self.predictor
                .predict(measured, timing.capture_ns, timing.actuation_ns, flow_mps);
        // Smith predictor: the measurement plus the motion the model predicts over the delay
        // (exactly the measurement when there is none). The controllers see the predicted
        // positions at actuation times as they would see undelayed poses, velocity included
        // (the same filtered finite differences, so their tuning carries over).
        let (fed_ns, position_m) = if self.config.latency.compensate {
            (timing.actuation_ns, measured + predicted.motion_ahead_m)
        } else {
            (timing.capture_ns, measured)
        };
        let dt_s = self.filter_velocity(fed_ns, position_m, tracking);
        self.last_fed = Some((fed_ns, position_m));
        if let Some(observer) = &mut self.observer {
            self.velocity = observer.update(fed_ns, position_m, flow_mps);
        }
        Fed {
            predicted,
            position_m,
            dt_s,
        }
    }

    /// Low-passed differences of the fed positions (`velocity_filter_ms`); the time since the
    /// previous fed state (s), 0 when it repeats or the loop starts afresh (velocity zeroed).
    fn filter_velocity(&mut self, fed_ns: u64, position_m: Vector2<f64>, tracking: bool) -> f64 {
        match self.last_fed {
            Some((t_prev, p_prev)) if fed_ns > t_prev && tracking => {
                let dt = (fed_ns - t_prev) as f64 * 1e-9;
                let raw = (position_m - p_prev) / dt;
                let tau = (self.config.velocity_filter_ms * 1e-3).max(1e-6);
                self.velocity += (raw - self.velocity) * (1.0 - (-dt / tau).exp());
                dt
            }
            Some((t_prev, _)) if fed_ns == t_prev => 0.0,
            _ => {
                self.velocity = Vector2::zeros();
                0.0
            }
        }
    }
}
