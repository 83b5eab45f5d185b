//! The interface of the latency predictors: the single [`StatePredictor`] and the
//! [`PredictorBank`] that picks one of several by how well each predicted.
//!
//! [`StatePredictor`]: super::StatePredictor
//! [`PredictorBank`]: super::PredictorBank

use nalgebra::Vector2;

use super::LatencyConfig;

/// What the predictor hands the controller for one pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Predicted {
    /// The motion the model predicts from the capture time to the actuation time.
    pub motion_ahead_m: Vector2<f64>,
    /// The model's velocity at the actuation time.
    pub velocity_mps: Vector2<f64>,
    /// Steady disturbance force the predictor attributes to what the nominal model lacks, N.
    pub disturbance_n: Vector2<f64>,
    /// Actuation time − capture time, s.
    pub horizon_s: f64,
}

/// Predicts the robot's state at a command's actuation time from a delayed pose and the forces
/// the coils made since.
pub trait Predictor {
    /// The `[control.latency]` table it runs with.
    fn config(&self) -> &LatencyConfig;

    /// Forgets the model state (after a rejected pose or a hold); the force history stays,
    /// since it is what the coils did.
    fn reset(&mut self);

    /// Records that `force_n` acts from `start_ns` on (the achieved force of a command, zero for
    /// hold and safe), against flow `flow_mps`.
    fn commanded(&mut self, start_ns: u64, force_n: Vector2<f64>, flow_mps: Vector2<f64>);

    /// Takes the position measured at `capture_ns` and predicts the motion until
    /// `actuation_ns`. `flow_mps` is the flow estimate for this pose (used before any command
    /// was recorded).
    fn predict(
        &mut self,
        position_m: Vector2<f64>,
        capture_ns: u64,
        actuation_ns: u64,
        flow_mps: Vector2<f64>,
    ) -> Predicted;

    /// The command acting at `actuation_ns` asked `asked_n` and the coils made `achieved_n`
    /// (nothing to a predictor that does not care).
    fn achieved(&mut self, _actuation_ns: u64, _asked_n: Vector2<f64>, _achieved_n: Vector2<f64>) {}

    /// The disturbance the model expects, on average, over the `span_s` from `from_ns` on (a
    /// command's hold, about one pose interval); none when it cannot tell.
    fn lead_disturbance(&self, from_ns: u64, span_s: f64) -> Option<Vector2<f64>>;

    /// The share of the measured motion between poses the model did not predict (0 to 1).
    fn unpredicted_motion_share(&self) -> f64;

    /// How far the robot may be from where the model puts it `horizon_s` after a pose (m).
    fn expected_miss_m(&self, horizon_s: f64) -> f64;

    /// The disturbance time constant in use, in delays.
    fn active_disturbance_delays(&self) -> f64 {
        self.config().disturbance_delays
    }
}
