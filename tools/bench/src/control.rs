//! Control workloads: one controller update, one full `ControlLoop::step` (controller +
//! allocation), and the two allocations on their own.

use crate::workload::Workload;
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

fn model(rig: &Rig, viscosity_pa_s: f64) -> NominalModel {
    let robot = &rig.robot;
    NominalModel {
        mass_kg: robot.mass_kg,
        linear_drag_n_s_per_m: physics::translational_damping(
            viscosity_pa_s,
            robot.length_m,
            robot.diameter_m / 2.0,
        ),
    }
}

/// Robot position at step `k` of `period_s`: the reference plus a small deterministic tracking
/// error.
fn position(reference: &Reference, period_s: f64, k: usize) -> Vector2<f64> {
    let t = k as f64 * period_s;
    let e = 4e-4 * Vector2::new((0.7 * t).sin(), (1.1 * t).cos());
    reference.sample(t).position_m + e
}

/// A controller of `kind` with the default gains, and the inputs of a tracking run.
pub struct ControllerBench {
    pub controller: Box<dyn Controller>,
    reference: Reference,
    period_s: f64,
}

impl ControllerBench {
    pub fn new(kind: ControllerKind, work: &Workload) -> Result<Self, BenchError> {
        let config = ControlConfig {
            controller: kind,
            ..Default::default()
        };
        let reference = work.reference.clone();
        let mpc = config.mpc_gains(&work.rig, reference.waypoints());
        let nominal = model(&work.rig, work.viscosity_pa_s);
        Ok(Self {
            controller: kind.build(&config.pid, &config.smc, &mpc, nominal),
            reference,
            period_s: work.period_s,
        })
    }

    pub fn input(&self, k: usize) -> ControlInput {
        let dt = self.period_s;
        let t = k as f64 * dt;
        let p = position(&self.reference, dt, k);
        let p_prev = position(&self.reference, dt, k.saturating_sub(1));
        ControlInput {
            dt_s: dt,
            delay_s: 0.0,
            position_m: p,
            velocity_mps: (p - p_prev) / dt,
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
    period_s: f64,
}

impl LoopBench {
    pub fn new(kind: ControllerKind, work: &Workload) -> Result<Self, BenchError> {
        let config = ControlConfig {
            controller: kind,
            ..Default::default()
        };
        let reference = work.reference.clone();
        Ok(Self {
            control: ControlLoop::new(
                config,
                reference.clone(),
                work.viscosity_pa_s,
                0,
                work.rig.clone(),
            ),
            reference,
            period_s: work.period_s,
        })
    }

    pub fn pose(&self, k: usize) -> Pose {
        let p = position(&self.reference, self.period_s, k);
        let stamp_ns = (k as u64 + 1) * (self.period_s * 1e9) as u64;
        Pose {
            stamp: FrameStamp::new(k as u64, 0, stamp_ns),
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
    pub fn new(n: usize, work: &Workload) -> Result<Self, BenchError> {
        let (reference, rig) = (&work.reference, &work.rig);
        let config = ControlConfig::default();
        let omega0 = config.omega0_n_per_t;
        let h = config.field_heading_deg.to_radians();
        let b =
            Vector2::new(h.cos(), h.sin()) * config.field_magnitude_t(rig.robot.magnet_moment_am2);
        let cases = (0..n)
            .map(|k| {
                let p = position(reference, work.period_s, k * 50);
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
            limits: config.limits_on(rig),
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
