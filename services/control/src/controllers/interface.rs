//! What every controller shares: its input, the terms it logs, the trait, and the nominal model.

use nalgebra::Vector2;

use crate::reference::ReferenceSample;

/// What a controller knows at one step.
#[derive(Debug, Clone, Copy)]
pub struct ControlInput {
    /// Time since the previous step (from capture timestamps, never the wall clock).
    pub dt_s: f64,
    /// Capture → actuation delay of this pose (s). With latency compensation the state is
    /// predicted across it, but a disturbance the model does not know still shows this late.
    pub delay_s: f64,
    pub position_m: Vector2<f64>,
    /// Estimated robot velocity (filtered finite differences of poses).
    pub velocity_mps: Vector2<f64>,
    pub reference: ReferenceSample,
    /// Steady-map flow at the robot (flow service).
    pub flow_mps: Vector2<f64>,
    /// In the high-disturbance zone of the flow map.
    pub high_disturbance: bool,
    /// The latency predictor's estimate of the force the nominal model lacks while this
    /// command acts: its steady part plus the fitted pulsation's mean over one pose interval
    /// from the actuation time, N. None without compensation, before the first pose, or when
    /// the poses are too sparse to resolve the pulsation.
    pub predicted_disturbance_n: Option<Vector2<f64>>,
    /// How far the coils' gains may be off, as control knows them (relative 1σ): the online
    /// estimate's uncertainty, RMS over the coils weighted by the currents they carry, when
    /// `[control.gain_estimation]` is on, else its `prior_std` (the coil data's stated
    /// accuracy). The force the loop asks for is made about this far off.
    pub coil_gain_std: f64,
    /// The share of the robot's measured motion between poses that the latency predictor's
    /// nominal model did not predict (RMS residual over RMS motion, recent poses; 0 before
    /// any or without compensation). That share of the motion reaches the loop only after the
    /// delay.
    pub unpredicted_motion_share: f64,
}

/// Internal signals worth logging.
#[derive(Debug, Clone, Copy, Default)]
pub struct ControlTerms {
    pub error_m: Vector2<f64>,
    pub error_rate_mps: Vector2<f64>,
    pub sliding_surface: Vector2<f64>,
    pub disturbance_estimate_n: Vector2<f64>,
}

pub trait Controller: Send {
    fn name(&self) -> &'static str;
    /// Numeric id carried in `CoilCommand::controller_id`.
    fn id(&self) -> u32;
    /// Desired planar force (N) for this step.
    fn update(&mut self, input: &ControlInput) -> (Vector2<f64>, ControlTerms);
    /// The force the allocation made for the last `update` (less than asked when the coils
    /// saturate or a slew bound holds them back) and the force the coils could make at their
    /// ratings, the slew bound aside (equal to it without a bound). Controllers that model their
    /// own input take it from here.
    fn applied(&mut self, _achieved_n: Vector2<f64>, _at_ratings_n: Vector2<f64>) {}
    /// Forget integrators and filters (after a hold or a restart of the loop).
    fn reset(&mut self);
}

/// The nominal model every controller may use: mass and the paper's linear drag.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NominalModel {
    pub mass_kg: f64,
    /// c_t of paper Eq. 7 for the scenario's viscosity.
    pub linear_drag_n_s_per_m: f64,
}
