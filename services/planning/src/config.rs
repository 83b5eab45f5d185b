//! The planner's parameters.

use fieldmaps::phantom::PLANNER_CLEARANCE_M;
use serde::{Deserialize, Serialize};

use crate::PlanError;

/// Planner parameters (paper defaults).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlannerConfig {
    /// Minimum wall clearance of the feasible core (paper: 5 mm).
    pub clearance_m: f64,
    /// Weight of the centerline bias in the cell cost (paper: 0.5).
    pub w_clear: f64,
    /// Moving-average window, samples (paper: 7).
    pub smoothing_window: usize,
    /// Evenly spaced output waypoints (paper: 10).
    pub waypoint_count: usize,
}

impl Default for PlannerConfig {
    fn default() -> Self {
        Self {
            clearance_m: PLANNER_CLEARANCE_M,
            w_clear: 0.5,
            smoothing_window: 7,
            waypoint_count: 10,
        }
    }
}

impl PlannerConfig {
    pub fn validate(&self) -> Result<(), PlanError> {
        if !(self.clearance_m.is_finite() && self.clearance_m >= 0.0) {
            return Err(PlanError::Config(
                "clearance must be finite and >= 0".into(),
            ));
        }
        if !(self.w_clear.is_finite() && self.w_clear >= 0.0) {
            return Err(PlanError::Config("w_clear must be finite and >= 0".into()));
        }
        if self.smoothing_window == 0 {
            return Err(PlanError::Config("smoothing window must be >= 1".into()));
        }
        if self.waypoint_count < 2 {
            return Err(PlanError::Config("need at least 2 waypoints".into()));
        }
        Ok(())
    }
}
