//! Latency compensation: a pose describes the robot at its frame's capture time, but the command
//! computed from it acts later (camera, inference, flow, serial link). Every controller is fed
//! the state predicted for the command's actuation time instead of the stale measurement.
//!
//! The predictor is a Smith predictor: the measured position plus the motion the nominal model
//! (`m v̇ = F + d̂ − c (v − u)`, m including the added mass) predicts from the capture time to
//! the actuation time under the force history the loop actually commanded (the allocation's
//! achieved force, piecewise constant from each command's actuation time). The model's velocity
//! runs open loop on the commands (a velocity differentiated from delayed, noisy poses would
//! make the prediction as noisy as the poses); `d̂` is what the nominal model lacks (flow the map
//! does not know, drag it underestimates), learned slowly from how far the measured motion
//! between two poses differs from the model's, so that a steady push is predicted too
//! (a filtered Smith predictor).
//!
//! The delay is measured per pose: actuation time − capture time, where the actuation time is
//! "now" (the frame's grab time in lockstep, the run clock in real time) plus the delay the
//! stamps cannot show (`unstamped_delay_ms`: serial link, amplifier, a camera without exposure
//! timestamps).
//!
//! Files: this one the `[control.latency]` table; `predictor` the interface the loop uses;
//! `state` the single model-based predictor; `bank` the bank that picks among several.

mod bank;
mod predictor;
mod state;

pub use bank::PredictorBank;
pub use predictor::{Predicted, Predictor};
#[cfg(test)]
pub(crate) use state::tests;
pub use state::StatePredictor;
pub(crate) use state::MOTION_SHARE_WINDOW_S;

use serde::{Deserialize, Serialize};

/// `[control.latency]` of a scenario.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct LatencyConfig {
    /// Feed controllers the state predicted for the actuation time (false: the measured pose
    /// and finite-difference velocity, as if there were no delay).
    pub compensate: bool,
    /// Delay after "now" that no timestamp shows: serial link, board, amplifier, or the whole
    /// camera latency for a camera that stamps frames on arrival (ms).
    pub unstamped_delay_ms: f64,
    /// Poses older than this at actuation time are not used (ms): the loop holds, then goes
    /// safe, as for a lost pose.
    pub max_pose_age_ms: f64,
    /// Time constant of the predictor's disturbance estimate in multiples of each pose's
    /// measured delay. An estimate learned from poses that old chases stale information when it
    /// is faster than a few delays (at 1x flow runs were lost), and lags the flow's own changes
    /// when it is much slower (README, "Camera latency and its compensation"). 0: the fixed
    /// `disturbance_time_constant_ms`.
    pub disturbance_delays: f64,
    /// The disturbance estimate's time constant when it is shorter than `disturbance_delays`
    /// delays (ms; with `disturbance_delays = 0`, its time constant). 0 with
    /// `disturbance_delays = 0` turns it off (plain Smith predictor).
    pub disturbance_time_constant_ms: f64,
    /// Candidate values of `disturbance_delays` to choose from while running: each predicts,
    /// and the one whose predictions the later poses confirmed best feeds the controller
    /// (`crate::predictor_bank`; README, "Choosing the disturbance bandwidth from the data").
    /// Default 1, 2 and 4 delays; empty: `disturbance_delays` alone.
    pub disturbance_delays_candidates: Vec<f64>,
    /// Pulsation rate of the flow (Hz; the pump's stroke rate, which the lab sets): the
    /// disturbance estimate then also carries a sinusoid at this rate (amplitude and phase
    /// learned by recursive least squares), so that a pulsatile push is predicted across the
    /// delay instead of being seen late. None: a steady estimate only.
    pub pulsation_hz: Option<f64>,
    /// Fewest poses per pulsation period for the fitted pulsation to lead a controller's
    /// disturbance estimate (`StatePredictor::lead_disturbance`): fewer, and the lead is off
    /// unless the delay is long (`lead_min_delay_periods`). At the paper's 10 Hz and 3 Hz there
    /// are 3.3 (README, "The predicted disturbance leads the DOB").
    pub lead_min_poses_per_period: f64,
    /// With fewer poses per period than `lead_min_poses_per_period`, the fitted pulsation still
    /// leads when the pose's capture → actuation delay is at least this share of a period.
    /// A DOB answers a pulsation through its filter (66° late at 3 Hz with η = 0.12 s) and the
    /// delay (ω·D more); from about a quarter period late on, its answer adds to the push
    /// instead of cancelling it (at 3 Hz and η = 0.12 s from D ≈ 22 ms, 0.067 period), and the
    /// fit, however coarse, is the better guess. Measured at 10 Hz (README, "The lead across a
    /// long delay"): the lead costs at 6 and 21 ms and gains at 36, 66 and 106 ms. 0: always.
    pub lead_min_delay_periods: f64,
    /// The largest turn of the orientation field at the capsule (rad) that the asked force's
    /// gradient may cause across the predictor's expected miss (`StatePredictor::
    /// expected_miss_m`): the asked force is bounded to this × |m||B| / miss. 0: no bound;
    /// default 0.2, and none with `compensate = false`. It binds where the prediction has
    /// failed (a stroke of the jet the model did not foresee), not while it holds (README,
    /// "Bounding the force by the predictor's miss").
    pub max_field_turn_at_miss_rad: f64,
}

impl Default for LatencyConfig {
    fn default() -> Self {
        Self {
            compensate: true,
            unstamped_delay_ms: 0.0,
            max_pose_age_ms: 500.0,
            disturbance_delays: 4.0,
            disturbance_time_constant_ms: 100.0,
            disturbance_delays_candidates: vec![1.0, 2.0, 4.0],
            pulsation_hz: None,
            lead_min_poses_per_period: 10.0,
            lead_min_delay_periods: 0.08,
            max_field_turn_at_miss_rad: 0.2,
        }
    }
}

impl LatencyConfig {
    /// The first field that is out of range, with why.
    pub fn invalid_field(&self) -> Option<(&'static str, String)> {
        let checks: [(&'static str, f64, bool); 7] = [
            ("unstamped_delay_ms", self.unstamped_delay_ms, false),
            ("max_pose_age_ms", self.max_pose_age_ms, true),
            ("disturbance_delays", self.disturbance_delays, false),
            (
                "disturbance_time_constant_ms",
                self.disturbance_time_constant_ms,
                false,
            ),
            (
                "lead_min_poses_per_period",
                self.lead_min_poses_per_period,
                false,
            ),
            ("lead_min_delay_periods", self.lead_min_delay_periods, false),
            (
                "max_field_turn_at_miss_rad",
                self.max_field_turn_at_miss_rad,
                false,
            ),
        ];
        if let Some(bad) = self
            .disturbance_delays_candidates
            .iter()
            .find(|d| !(d.is_finite() && **d >= 0.0))
        {
            return Some((
                "disturbance_delays_candidates",
                format!("every candidate must be finite and >= 0, got {bad}"),
            ));
        }
        if let Some(hz) = self.pulsation_hz {
            if !(hz.is_finite() && hz > 0.0) {
                return Some(("pulsation_hz", format!("must be finite and > 0, got {hz}")));
            }
        }
        checks.into_iter().find_map(|(name, value, strict)| {
            let fine = value.is_finite() && if strict { value > 0.0 } else { value >= 0.0 };
            (!fine).then(|| {
                let relation = if strict { "> 0" } else { ">= 0" };
                (name, format!("must be finite and {relation}, got {value}"))
            })
        })
    }
}
