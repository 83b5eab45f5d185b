//! PID with flow feedforward (paper Eq. 15–16).

use nalgebra::Vector2;
use serde::{Deserialize, Serialize};

use super::interface::{ControlInput, ControlTerms, Controller, NominalModel};

/// PID with flow feedforward (paper Eq. 15–16): F = Kp e + Ki ∫e + Kd ė − c_t V.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PidGains {
    pub kp_n_per_m: f64,
    pub ki_n_per_m_s: f64,
    pub kd_n_s_per_m: f64,
    /// Anti-windup bound on |∫e| per axis (m·s).
    pub integral_limit_m_s: f64,
}

impl Default for PidGains {
    fn default() -> Self {
        Self {
            kp_n_per_m: 5e-2,
            ki_n_per_m_s: 5e-3,
            kd_n_s_per_m: 8e-3,
            integral_limit_m_s: 0.05,
        }
    }
}

pub struct Pid {
    gains: PidGains,
    model: NominalModel,
    integral: Vector2<f64>,
}

impl Pid {
    pub fn new(gains: PidGains, model: NominalModel) -> Self {
        Self {
            gains,
            model,
            integral: Vector2::zeros(),
        }
    }
}

impl Controller for Pid {
    fn name(&self) -> &'static str {
        "pid"
    }
    fn id(&self) -> u32 {
        1
    }
    fn update(&mut self, input: &ControlInput) -> (Vector2<f64>, ControlTerms) {
        let e = input.reference.position_m - input.position_m;
        let e_dot = input.reference.velocity_mps - input.velocity_mps;
        let limit = self.gains.integral_limit_m_s;
        self.integral = (self.integral + e * input.dt_s).map(|v| v.clamp(-limit, limit));
        let force = e * self.gains.kp_n_per_m
            + self.integral * self.gains.ki_n_per_m_s
            + e_dot * self.gains.kd_n_s_per_m
            - input.flow_mps * self.model.linear_drag_n_s_per_m;
        (
            force,
            ControlTerms {
                error_m: e,
                error_rate_mps: e_dot,
                ..Default::default()
            },
        )
    }
    fn reset(&mut self) {
        self.integral = Vector2::zeros();
    }
}
