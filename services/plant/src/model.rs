//! The digital twin's physics (the truth). It is deliberately richer than any controller's
//! nominal model: true coil gains differ from nominal, coil currents lag their commands, drag
//! has a quadratic form term, and the capsule turns toward the field with its own dynamics.
//! One implementation, used by the plant service and by in-process experiment runs.

use fieldmaps::coils::{CoilSystem, COIL_COUNT};
use fieldmaps::flowmap::FlowMap;
use fieldmaps::phantom::Phantom;
use fieldmaps::physics;
use fieldmaps::rig::{FluidParams, RobotParams};
use nalgebra::{Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

/// `[plant]` physics knobs of a scenario.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlantPhysicsConfig {
    /// Standard deviation of the per-coil gain error (fraction): the true field differs from
    /// the nominal maps the controller uses.
    pub coil_gain_error_std: f64,
    /// L/R time constant of the coil currents.
    pub coil_time_constant_ms: f64,
    /// Form-drag coefficient C_d of the quadratic term 0.5·ρ·C_d·A·|v|v (0 disables it).
    pub form_drag_coefficient: f64,
    /// Integration step of the physics.
    pub substep_ms: f64,
    /// Amplitude of the pulsatile modulation of the steady flow (fraction of the steady value).
    pub pulsation_amplitude: f64,
    pub pulsation_hz: f64,
}

impl Default for PlantPhysicsConfig {
    fn default() -> Self {
        Self {
            coil_gain_error_std: 0.03,
            coil_time_constant_ms: 5.0,
            form_drag_coefficient: 1.0,
            substep_ms: 0.5,
            pulsation_amplitude: 0.5,
            pulsation_hz: 3.0,
        }
    }
}

/// State of the capsule and the coils.
#[derive(Debug, Clone, PartialEq)]
pub struct PlantState {
    pub time_s: f64,
    pub position_m: Vector2<f64>,
    pub velocity_mps: Vector2<f64>,
    /// Direction of the magnetic moment (tail → tip), rad from +x.
    pub heading_rad: f64,
    /// Currents actually flowing in the coils (after the L/R lag).
    pub coil_currents_a: [f64; COIL_COUNT],
    pub wall_contact: bool,
    pub last_magnetic_force_n: Vector2<f64>,
    pub last_true_flow_mps: Vector2<f64>,
}

/// Everything fixed about the twin for one run.
pub struct PlantModel {
    pub coils: CoilSystem,
    pub robot: RobotParams,
    pub phantom: Phantom,
    pub steady_flow: FlowMap,
    pub config: PlantPhysicsConfig,
    /// True gain of each coil relative to its nominal map.
    pub coil_gains: [f64; COIL_COUNT],
    linear_drag_n_s_per_m: f64,
    quadratic_drag_n_s2_per_m2: f64,
    rotational_drag_n_m_s: f64,
}

impl PlantModel {
    pub fn new(
        coils: CoilSystem,
        robot: RobotParams,
        fluid: &FluidParams,
        phantom: Phantom,
        steady_flow: FlowMap,
        config: PlantPhysicsConfig,
        seed: u64,
    ) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x636f_696c);
        let gain_noise = Normal::new(0.0, config.coil_gain_error_std.abs())
            .unwrap_or_else(|_| Normal::new(0.0, 0.0).expect("zero std is valid"));
        let mut coil_gains = [1.0; COIL_COUNT];
        for g in coil_gains.iter_mut() {
            *g = 1.0 + gain_noise.sample(&mut rng);
        }
        let radius = robot.diameter_m / 2.0;
        let linear =
            physics::translational_damping(fluid.viscosity_pa_s, robot.length_m, radius);
        // Projected area of the capsule seen broadside and end-on, averaged.
        let area = 0.5 * (robot.diameter_m * robot.length_m)
            + 0.5 * std::f64::consts::PI * radius * radius;
        let quadratic = 0.5 * fluid.density_kg_m3 * config.form_drag_coefficient * area;
        // Slender-body rotational drag about a transverse axis: π μ L³ / (3 (ln(L/r) − 0.8)),
        // floored to stay finite for stubby bodies.
        let log_term = ((robot.length_m / radius).ln() - 0.8).max(0.1);
        let rotational = std::f64::consts::PI * fluid.viscosity_pa_s * robot.length_m.powi(3)
            / (3.0 * log_term);
        Self {
            coils,
            robot,
            phantom,
            steady_flow,
            config,
            coil_gains,
            linear_drag_n_s_per_m: linear,
            quadratic_drag_n_s2_per_m2: quadratic,
            rotational_drag_n_m_s: rotational,
        }
    }

    pub fn linear_drag(&self) -> f64 {
        self.linear_drag_n_s_per_m
    }

    pub fn initial_state(&self, position_m: Vector2<f64>, heading_rad: f64) -> PlantState {
        PlantState {
            time_s: 0.0,
            position_m,
            velocity_mps: Vector2::zeros(),
            heading_rad,
            coil_currents_a: [0.0; COIL_COUNT],
            wall_contact: false,
            last_magnetic_force_n: Vector2::zeros(),
            last_true_flow_mps: Vector2::zeros(),
        }
    }

    /// The true flow at `p` and time `t`: steady map times a pulsatile waveform.
    pub fn true_flow(&self, p: &Vector2<f64>, t: f64) -> Vector2<f64> {
        let steady = self.steady_flow.sample(p);
        if steady == Vector2::zeros() {
            return steady;
        }
        // Peristaltic-like: a rectified sine whose mean is 1 and peak 1 + amplitude.
        let phase = (std::f64::consts::PI * self.config.pulsation_hz * t).sin().abs();
        let mean_of_abs_sine = 2.0 / std::f64::consts::PI;
        let a = self.config.pulsation_amplitude;
        steady * (1.0 + a * (phase - mean_of_abs_sine) / (1.0 - mean_of_abs_sine))
    }

    fn moment(&self, heading: f64) -> Vector3<f64> {
        Vector3::new(heading.cos(), heading.sin(), 0.0) * self.robot.magnet_moment_am2
    }

    /// Advances the state by `dt` with the given commanded coil currents.
    pub fn step(&self, state: &mut PlantState, commanded_a: &[f64; COIL_COUNT], dt: f64) {
        let substep = (self.config.substep_ms * 1e-3).max(1e-5);
        let n = ((dt / substep).ceil() as usize).max(1);
        let h = dt / n as f64;
        for _ in 0..n {
            self.substep(state, commanded_a, h);
        }
    }

    fn substep(&self, state: &mut PlantState, commanded_a: &[f64; COIL_COUNT], h: f64) {
        // Coil currents follow their commands with the L/R lag (exact for a first-order lag).
        let tau = (self.config.coil_time_constant_ms * 1e-3).max(1e-6);
        let alpha = 1.0 - (-h / tau).exp();
        for (i, c) in state.coil_currents_a.iter_mut().enumerate() {
            let target = if commanded_a[i].is_finite() {
                commanded_a[i]
            } else {
                0.0
            };
            *c += alpha * (target - *c);
        }
        let true_currents: Vec<f64> = state
            .coil_currents_a
            .iter()
            .zip(&self.coil_gains)
            .map(|(c, g)| c * g)
            .collect();
        let p3 = Vector3::new(state.position_m.x, state.position_m.y, 0.0);
        let (field, gradient) = self.coils.field_and_gradient(&true_currents, &p3);
        let moment = self.moment(state.heading_rad);
        let force3 = physics::magnetic_force(&moment, &gradient);
        let force = Vector2::new(force3.x, force3.y);
        let torque_z = physics::magnetic_torque(&moment, &field).z;

        // Alignment: overdamped rotation (inertia is negligible at these scales).
        let omega = torque_z / self.rotational_drag_n_m_s;
        state.heading_rad = wrap_angle(state.heading_rad + (omega * h).clamp(-0.5, 0.5));

        let flow = self.true_flow(&state.position_m, state.time_s);
        let relative = state.velocity_mps - flow;
        let quadratic = -relative * (self.quadratic_drag_n_s2_per_m2 * relative.norm());
        let mass = self.robot.mass_kg + self.robot.added_mass_kg;
        // Semi-implicit in the linear drag, which is the stiff term at low viscosity.
        let c = self.linear_drag_n_s_per_m;
        let explicit = force + quadratic + flow * c;
        state.velocity_mps = (state.velocity_mps + explicit * (h / mass)) / (1.0 + c * h / mass);
        state.position_m += state.velocity_mps * h;
        state.wall_contact = self.resolve_walls(state);
        state.time_s += h;
        state.last_magnetic_force_n = force;
        state.last_true_flow_mps = flow;
    }

    /// Keeps both ends and the middle of the capsule inside the canal; returns true on contact.
    /// Position is projected back and the velocity component into the wall removed, so the
    /// capsule can never tunnel through a wall whatever the force.
    fn resolve_walls(&self, state: &mut PlantState) -> bool {
        let radius = self.robot.diameter_m / 2.0;
        let half_axis = (self.robot.length_m / 2.0 - radius).max(0.0);
        let axis = Vector2::new(state.heading_rad.cos(), state.heading_rad.sin());
        let mut contact = false;
        for _ in 0..3 {
            let mut pushed = false;
            for offset in [-half_axis, 0.0, half_axis] {
                let point = state.position_m + axis * offset;
                let penetration = self.phantom.signed_distance(&point) + radius;
                if penetration > 0.0 {
                    let normal = self.phantom.wall_normal(&point);
                    if !(normal.x.is_finite() && normal.y.is_finite()) {
                        continue;
                    }
                    state.position_m -= normal * penetration;
                    let into_wall = state.velocity_mps.dot(&normal);
                    if into_wall > 0.0 {
                        state.velocity_mps -= normal * into_wall;
                    }
                    contact = true;
                    pushed = true;
                }
            }
            if !pushed {
                break;
            }
        }
        contact
    }
}

pub fn wrap_angle(a: f64) -> f64 {
    let two_pi = std::f64::consts::TAU;
    let mut x = (a + std::f64::consts::PI) % two_pi;
    if x < 0.0 {
        x += two_pi;
    }
    x - std::f64::consts::PI
}

/// Seeded per-run random source for everything stochastic in the twin.
pub fn run_rng(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    let _: u64 = rng.random();
    rng
}
