//! Control workloads: one controller update, one full `ControlLoop::step` (controller +
//! allocation), and the two allocations on their own.

use std::sync::Arc;

use fieldmaps::allocation::{
    actuation_matrix_from, allocate_constrained, allocate_pinv, ConstrainedSettings,
};
use fieldmaps::physics;
use fieldmaps::rig::CoilLimits;
use fieldmaps::rigfile::Rig;
use millinav_control::controllers::{ControlInput, Controller, ControllerKind, NominalModel};
use millinav_control::reference::Reference;
use millinav_control::{ControlConfig, ControlLoop};
use nalgebra::{DMatrix, DVector, Vector2, Vector3};
use shm_schemas::{Flag, FrameStamp, Pose};

use crate::BenchError;

/// The short scenario's trajectory (m), speed and start.
const WAYPOINTS: [[f64; 2]; 3] = [[-0.018, 0.012], [-0.012, 0.008], [-0.010, 0.004]];
const SPEED_MPS: f64 = 2e-3;
const START_S: f64 = 0.5;
const VISCOSITY_PA_S: f64 = 0.02;
const PERIOD_S: f64 = 0.01;

fn reference() -> Result<Reference, BenchError> {
    Reference::new(&WAYPOINTS, SPEED_MPS, START_S).map_err(|e| BenchError::Setup(e.to_string()))
}

/// The committed paper rig the workloads run on.
pub fn paper_rig() -> Result<Arc<Rig>, BenchError> {
    Rig::load_paper()
        .map(Arc::new)
        .map_err(|e| BenchError::Setup(e.to_string()))
}

fn model(rig: &Rig) -> NominalModel {
    let robot = &rig.robot;
    NominalModel {
        mass_kg: robot.mass_kg,
        linear_drag_n_s_per_m: physics::translational_damping(
            VISCOSITY_PA_S,
            robot.length_m,
            robot.diameter_m / 2.0,
        ),
    }
}

/// Robot position at step `k`: the reference plus a small deterministic tracking error.
fn position(reference: &Reference, k: usize) -> Vector2<f64> {
    let t = k as f64 * PERIOD_S;
    let e = 4e-4 * Vector2::new((0.7 * t).sin(), (1.1 * t).cos());
    reference.sample(t).position_m + e
}

/// A controller of `kind` with the default gains, and the inputs of a tracking run.
pub struct ControllerBench {
    pub controller: Box<dyn Controller>,
    reference: Reference,
}

impl ControllerBench {
    pub fn new(kind: ControllerKind) -> Result<Self, BenchError> {
        let config = ControlConfig {
            controller: kind,
            ..Default::default()
        };
        let rig = paper_rig()?;
        let reference = reference()?;
        let mpc = config.mpc_gains(&rig, reference.waypoints());
        Ok(Self {
            controller: kind.build(&config.pid, &config.smc, &mpc, model(&rig)),
            reference,
        })
    }

    pub fn input(&self, k: usize) -> ControlInput {
        let t = k as f64 * PERIOD_S;
        let p = position(&self.reference, k);
        let p_prev = position(&self.reference, k.saturating_sub(1));
        ControlInput {
            dt_s: PERIOD_S,
            delay_s: 0.0,
            position_m: p,
            velocity_mps: (p - p_prev) / PERIOD_S,
            reference: self.reference.sample(t),
            flow_mps: Vector2::new(1e-3, -2e-3),
            high_disturbance: false,
            predicted_disturbance_n: None,
            coil_gain_std: 0.0,
            unpredicted_motion_share: 0.0,
        }
    }

    /// One controller update for step `k`.
    pub fn step(&mut self, k: usize) {
        let input = self.input(k);
        std::hint::black_box(self.controller.update(&input));
    }
}

/// The port-free control loop of the service (controller + checks + pinv allocation).
pub struct LoopBench {
    pub control: ControlLoop,
    reference: Reference,
}

impl LoopBench {
    pub fn new(kind: ControllerKind) -> Result<Self, BenchError> {
        let config = ControlConfig {
            controller: kind,
            ..Default::default()
        };
        Ok(Self {
            control: ControlLoop::new(config, reference()?, VISCOSITY_PA_S, 0, paper_rig()?),
            reference: reference()?,
        })
    }

    pub fn pose(&self, k: usize) -> Pose {
        let p = position(&self.reference, k);
        Pose {
            stamp: FrameStamp::new(k as u64, 0, (k as u64 + 1) * (PERIOD_S * 1e9) as u64),
            position_m: [p.x, p.y],
            centroid_m: [p.x, p.y],
            heading_rad: 0.6,
            confidence: 1.0,
            valid: Flag::TRUE,
            ..Default::default()
        }
    }

    pub fn step(&mut self, k: usize) {
        let pose = self.pose(k);
        std::hint::black_box(self.control.step(&pose, None));
    }
}

/// Actuation matrices and commands at points along the trajectory.
pub struct AllocationBench {
    pub cases: Vec<(DMatrix<f64>, DVector<f64>)>,
    pub limits: CoilLimits,
    pub settings: ConstrainedSettings,
}

impl AllocationBench {
    /// `n` cases; every fourth asks for a force beyond what the limits allow (best effort).
    pub fn new(n: usize) -> Result<Self, BenchError> {
        let reference = reference()?;
        let rig = paper_rig()?;
        let config = ControlConfig::default();
        let omega0 = config.omega0_n_per_t;
        let h = config.field_heading_deg.to_radians();
        let b =
            Vector2::new(h.cos(), h.sin()) * config.field_magnitude_t(rig.robot.magnet_moment_am2);
        let cases = (0..n)
            .map(|k| {
                let p = position(&reference, k * 50);
                let heading = 0.6 + 0.01 * k as f64;
                let moment = physics::in_plane_moment(rig.robot.magnet_moment_am2, heading);
                let a = actuation_matrix_from(
                    &rig.coil_field,
                    &Vector3::new(p.x, p.y, 0.0),
                    &moment,
                    &rig.allocation_coils,
                    omega0,
                );
                let scale = if k % 4 == 3 { 50.0 } else { 1.0 };
                let angle = 0.37 * k as f64;
                let f = Vector2::new(angle.cos(), angle.sin()) * 2e-4 * scale;
                let c = DVector::from_vec(vec![f.x, f.y, omega0 * b.x, omega0 * b.y]);
                (a, c)
            })
            .collect();
        Ok(Self {
            cases,
            limits: config.limits_on(&rig),
            settings: ConstrainedSettings::default(),
        })
    }

    pub fn pinv(&self, k: usize) {
        let (a, c) = &self.cases[k % self.cases.len()];
        let _ = std::hint::black_box(allocate_pinv(a, c));
    }

    pub fn constrained(&self, k: usize) {
        let (a, c) = &self.cases[k % self.cases.len()];
        let _ = std::hint::black_box(allocate_constrained(a, c, &self.limits, &self.settings));
    }
}
