//! The digital twin's physics (the truth). It is deliberately richer than any controller's
//! nominal model: true coil gains differ from nominal, coil currents lag their commands, drag
//! has a quadratic form term, and the capsule turns toward the field with its own dynamics.
//! One implementation, used by the plant service and by in-process experiment runs.
//!
//! Truth the controller never sees:
//! - the true flow is the steady map × a pulsatile waveform + a slowly moving recirculation
//!   vortex + spatially smooth, temporally correlated (Ornstein–Uhlenbeck) noise, all seeded
//!   from the scenario seed (see [`crate::trueflow`]);
//! - optional Coulomb floor friction (`floor_friction_coefficient` μ, default 0 = off): the
//!   normal load is max((m − ρV)·g + the magnet's downward pull, 0) + `floor_extra_load_n`.
//!   With the default rig parameters the capsule is slightly buoyant in the glycerol mix
//!   (m = 50 mg < ρV ≈ 51 mg), so the load is only the magnet's pull toward the floor; friction
//!   is off by default because neither the paper nor RIG.md quantifies it. Turn it on (e.g.
//!   μ = 0.2 with a load of 1e-5 N) to study stiction; it is an impulse bounded by μ·N·h per
//!   substep, so a weak pull is held exactly (static) and a strong one slides at (|F| − μN)/c_t;
//! - wall contact is resolved with swept sub-moves no longer than a quarter of the capsule
//!   radius, so no force or speed can carry the capsule through a wall; contacts are counted.

use fieldmaps::coils::CoilField;
use fieldmaps::flowmap::FlowMap;
use fieldmaps::physics::{self, wrap_angle};
use fieldmaps::rig::{FluidParams, RobotParams, SaturationCurve};
use fieldmaps::rigfile::{RigPhantom, MAX_COILS};
use fieldmaps::walls::WallField;
use nalgebra::{Matrix2, Vector2, Vector3};
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use crate::rng_streams;
use crate::trueflow::{FlowDisturbance, FlowNoiseConfig, FlowNoiseState, RecirculationConfig};

/// Gravitational acceleration, m/s².
const GRAVITY_MPS2: f64 = 9.81;
/// Longest move between two wall checks, as a fraction of the capsule radius.
const SWEEP_FRACTION_OF_RADIUS: f64 = 0.25;
/// Upper bound on swept sub-moves per substep (a capsule this fast is already absurd).
const MAX_SWEEP_MOVES: usize = 4096;

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
    /// Coulomb friction coefficient μ against the phantom floor (0 disables friction).
    pub floor_friction_coefficient: f64,
    /// Extra normal load on the floor, N (e.g. a heavier capsule), added to the apparent weight.
    pub floor_extra_load_n: f64,
    /// Gap between the capsule and the phantom floor it lies on, m (none: free-stream drag, as
    /// in paper Eq. 7). The floor multiplies the translational drag by
    /// [`physics::wall_drag_factor_parallel`] (×2.6 at 5 % of the radius, ×3.4 at 1 %): a
    /// nearly neutrally buoyant capsule in a planar phantom rests on a wall, and the gap (the
    /// roughness of the two surfaces, a lubricating film) is what the paper does not give.
    pub floor_gap_m: Option<f64>,
    /// Factor of the flow's push on the capsule relative to its free-stream drag (none: the
    /// same factor as its own motion, [`Self::floor_gap_m`]'s). A body held against a wall
    /// is pushed by the flow less than it is braked moving through still fluid: a sphere
    /// touching a wall in shear flow feels 1.7005 × the Stokes drag of the undisturbed speed
    /// at its centre (Goldman, Cox & Brenner, *Chem. Eng. Sci.* 22, 653–660, 1967), against
    /// 3–4 × for its own motion at micron gaps. Taking the flow map's speed as the speed at
    /// the capsule's centre (a capsule filling much of a shallow canal's depth), 1.7.
    pub floor_flow_factor: Option<f64>,
    /// The capsule's shape for its translational drag. `paper`: paper Eq. 7, the same in every
    /// direction, and on a floor the sphere's wall factor. `cylinder`: a circular cylinder,
    /// whose friction along its axis differs from across it (Tirado & García de la Torre 1979,
    /// 1.49× and 1.74× Eq. 7 for the paper's capsule) and which, lying on a floor, slides along
    /// its axis against a gap^-½ film ([`physics::cylinder_axial_wall_friction`]: ×25 Eq. 7 at
    /// 3 µm) and across it against the sphere's logarithm.
    pub drag_shape: DragShape,
    /// Time-varying vortex in the recirculation zone (`[plant.physics.recirculation]`).
    pub recirculation: RecirculationConfig,
    /// Correlated flow noise (`[plant.physics.flow_noise]`).
    pub flow_noise: FlowNoiseConfig,
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
            floor_friction_coefficient: 0.0,
            floor_extra_load_n: 0.0,
            floor_gap_m: None,
            floor_flow_factor: None,
            drag_shape: DragShape::Paper,
            recirculation: RecirculationConfig::default(),
            flow_noise: FlowNoiseConfig::default(),
        }
    }
}

/// `[plant.physics] drag_shape`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DragShape {
    #[default]
    Paper,
    Cylinder,
}

/// Linear drag along the capsule's axis and across it (equal: the same in every direction),
/// N·s/m.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CapsuleDrag {
    pub axial_n_s_per_m: f64,
    pub transverse_n_s_per_m: f64,
}

impl CapsuleDrag {
    fn isotropic(c: f64) -> Self {
        Self {
            axial_n_s_per_m: c,
            transverse_n_s_per_m: c,
        }
    }

    fn is_isotropic(&self) -> bool {
        self.axial_n_s_per_m == self.transverse_n_s_per_m
    }

    /// The mean of the two: what one number stands for (`PlantModel::linear_drag`).
    fn mean(&self) -> f64 {
        0.5 * (self.axial_n_s_per_m + self.transverse_n_s_per_m)
    }

    /// The drag tensor for a capsule whose axis is `axis` (unit): c⊥·I + (c∥ − c⊥)·a·aᵀ.
    fn tensor(&self, axis: &Vector2<f64>) -> Matrix2<f64> {
        Matrix2::identity() * self.transverse_n_s_per_m
            + axis * axis.transpose() * (self.axial_n_s_per_m - self.transverse_n_s_per_m)
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
    /// Currents actually flowing in the coils (after the L/R lag); the rig's coils first, the
    /// rest of the array stays 0.
    pub coil_currents_a: [f64; MAX_COILS],
    /// True when the capsule touched a wall at any substep of the last `step`.
    pub wall_contact: bool,
    /// Number of contact onsets (free → touching transitions) since the start.
    pub contact_events: u64,
    /// Total time spent touching a wall, s.
    pub contact_time_s: f64,
    pub last_magnetic_force_n: Vector2<f64>,
    pub last_true_flow_mps: Vector2<f64>,
    /// Normal load on the floor at the last substep when friction is on (else 0), N.
    pub last_floor_load_n: f64,
    /// State of the correlated flow noise (seeded; part of the truth, never seen by control).
    pub flow_noise: FlowNoiseState,
    /// Contact state at the last substep (for onset counting).
    touching: bool,
}

/// Everything fixed about the twin for one run.
pub struct PlantModel {
    /// The true field model (the committed grid maps in the service; any `CoilField`).
    pub coils: Box<dyn CoilField + Send + Sync>,
    pub robot: RobotParams,
    /// The canal walls (signed distance from the rig's mask).
    pub walls: WallField,
    pub steady_flow: FlowMap,
    pub config: PlantPhysicsConfig,
    /// True gain of each coil relative to its nominal map.
    pub coil_gains: [f64; MAX_COILS],
    /// Each coil's saturation (the rig file's `saturation`), applied after the gain.
    pub saturation: Vec<Option<SaturationCurve>>,
    /// Recirculation vortex and noise modes of the true flow.
    pub disturbance: FlowDisturbance,
    seed: u64,
    linear_drag: CapsuleDrag,
    /// Linear drag coefficient of the flow's push (differs from the capsule's own on a floor).
    flow_coupling: CapsuleDrag,
    quadratic_drag_n_s2_per_m2: f64,
    rotational_drag_n_m_s: f64,
    /// Apparent weight on the floor (m − ρV)·g, N (may be negative: buoyant).
    apparent_weight_n: f64,
}

/// The capsule's drag on its own motion and the flow's push on it, for `config`'s shape and
/// floor.
fn capsule_drag(
    config: &PlantPhysicsConfig,
    viscosity_pa_s: f64,
    length_m: f64,
    radius_m: f64,
) -> (CapsuleDrag, CapsuleDrag) {
    let eq7 = physics::translational_damping(viscosity_pa_s, length_m, radius_m);
    let sphere_floor = config
        .floor_gap_m
        .map_or(1.0, |gap| physics::wall_drag_factor_parallel(gap, radius_m));
    let own = match config.drag_shape {
        DragShape::Paper => CapsuleDrag::isotropic(eq7 * sphere_floor),
        DragShape::Cylinder => {
            let (axial, transverse) =
                physics::cylinder_translational_friction(viscosity_pa_s, length_m, radius_m);
            let axial_on_floor = config.floor_gap_m.map_or(axial, |gap| {
                physics::cylinder_axial_wall_friction(viscosity_pa_s, length_m, radius_m, gap)
                    .max(axial)
            });
            CapsuleDrag {
                axial_n_s_per_m: axial_on_floor,
                transverse_n_s_per_m: transverse * sphere_floor,
            }
        }
    };
    // With `floor_flow_factor` the flow pushes with that factor of Eq. 7 in every direction;
    // without, as hard as the capsule's own motion is braked (a capsule that moves with the
    // fluid feels nothing).
    let flow = match config.floor_flow_factor {
        Some(factor) => CapsuleDrag::isotropic(eq7 * factor),
        None => own,
    };
    (own, flow)
}

/// [`PlantModel::flow_noise_response`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlowNoiseResponse {
    pub moving_mass_kg: f64,
    pub linear_drag_n_s_per_m: f64,
    pub flow_coupling_n_s_per_m: f64,
    /// RMS of the noise velocity's magnitude (both axes together), m/s.
    pub noise_rms_speed_mps: f64,
    pub correlation_time_s: f64,
}

impl PlantModel {
    pub fn new(
        coils: impl CoilField + Send + Sync + 'static,
        robot: RobotParams,
        fluid: &FluidParams,
        phantom: &RigPhantom,
        steady_flow: FlowMap,
        config: PlantPhysicsConfig,
        seed: u64,
    ) -> Self {
        let mut rng = rng_streams::coil_gain_rng(seed);
        let gain_noise = Normal::new(0.0, config.coil_gain_error_std.abs())
            .unwrap_or_else(|_| Normal::new(0.0, 0.0).expect("zero std is valid"));
        let mut coil_gains = [1.0; MAX_COILS];
        for g in coil_gains.iter_mut() {
            *g = 1.0 + gain_noise.sample(&mut rng);
        }
        let radius = robot.diameter_m / 2.0;
        let (linear, flow_coupling) =
            capsule_drag(&config, fluid.viscosity_pa_s, robot.length_m, radius);
        // Projected area of the capsule seen broadside and end-on, averaged.
        let area = 0.5 * (robot.diameter_m * robot.length_m)
            + 0.5 * std::f64::consts::PI * radius * radius;
        let quadratic = 0.5 * fluid.density_kg_m3 * config.form_drag_coefficient * area;
        let rotational = physics::rotational_drag(fluid.viscosity_pa_s, robot.length_m, radius);
        // Same displaced volume as the rig parameters' added mass (cylinder approximation).
        let apparent_weight =
            (robot.mass_kg - fluid.density_kg_m3 * robot.volume_m3()) * GRAVITY_MPS2;
        let disturbance = FlowDisturbance::new(
            phantom,
            &config.recirculation,
            &config.flow_noise,
            steady_flow.condition_peak_speed(),
            seed,
        );
        Self {
            coils: Box::new(coils),
            robot,
            walls: phantom.walls.clone(),
            steady_flow,
            config,
            coil_gains,
            saturation: Vec::new(),
            disturbance,
            seed,
            linear_drag: linear,
            flow_coupling,
            quadratic_drag_n_s2_per_m2: quadratic,
            rotational_drag_n_m_s: rotational,
            apparent_weight_n: apparent_weight,
        }
    }

    /// The linear drag on the capsule's own motion (with `drag_shape = "cylinder"` the mean of
    /// its axial and transverse drag), N·s/m.
    pub fn linear_drag(&self) -> f64 {
        self.linear_drag.mean()
    }

    /// The linear drag along the capsule's axis and across it.
    pub fn axial_drag(&self) -> CapsuleDrag {
        self.linear_drag
    }

    /// How the flow noise moves the capsule, linearised: the moving mass, the drag on its own
    /// motion and the coupling to the flow (N·s/m), the noise's RMS speed and its correlation
    /// time (what `experiments --noise-floor` bounds the tracking error with).
    pub fn flow_noise_response(&self) -> FlowNoiseResponse {
        FlowNoiseResponse {
            moving_mass_kg: self.robot.mass_kg + self.robot.added_mass_kg,
            linear_drag_n_s_per_m: self.linear_drag.mean(),
            flow_coupling_n_s_per_m: self.flow_coupling.mean(),
            noise_rms_speed_mps: self.disturbance.noise_rms_speed_mps(),
            correlation_time_s: self.disturbance.noise_correlation_time_s(),
        }
    }

    pub fn initial_state(&self, position_m: Vector2<f64>, heading_rad: f64) -> PlantState {
        PlantState {
            time_s: 0.0,
            position_m,
            velocity_mps: Vector2::zeros(),
            heading_rad,
            coil_currents_a: [0.0; MAX_COILS],
            wall_contact: false,
            contact_events: 0,
            contact_time_s: 0.0,
            last_magnetic_force_n: Vector2::zeros(),
            last_true_flow_mps: Vector2::zeros(),
            last_floor_load_n: 0.0,
            flow_noise: self.disturbance.initial_noise(self.seed),
            touching: false,
        }
    }

    /// Quadratic form-drag coefficient 0.5·ρ·C_d·A, N·s²/m².
    pub fn quadratic_drag(&self) -> f64 {
        self.quadratic_drag_n_s2_per_m2
    }

    /// The deterministic part of the true flow at `p` and time `t`: steady map × pulsatile
    /// waveform + the recirculation vortex. [`Self::true_flow_with_noise`] adds the noise.
    pub fn true_flow(&self, p: &Vector2<f64>, t: f64) -> Vector2<f64> {
        self.pulsatile_flow(p, t) + self.disturbance.recirculation(p, t)
    }

    /// The full true flow: [`Self::true_flow`] plus the correlated noise in `noise`.
    pub fn true_flow_with_noise(
        &self,
        p: &Vector2<f64>,
        t: f64,
        noise: &FlowNoiseState,
    ) -> Vector2<f64> {
        let flow = self.true_flow(p, t);
        if self.steady_flow.covers(p) {
            flow + self.disturbance.noise(p, noise)
        } else {
            flow
        }
    }

    /// Steady map times the pulsatile waveform.
    pub fn pulsatile_flow(&self, p: &Vector2<f64>, t: f64) -> Vector2<f64> {
        let steady = self.steady_flow.sample(p);
        if steady == Vector2::zeros() {
            return steady;
        }
        steady * self.pulsation_factor(t)
    }

    /// The pulsatile waveform the steady map is multiplied by at `t`. Peristaltic-like: a
    /// rectified sine whose mean is 1 and peak 1 + amplitude; its period is 1 / pulsation_hz.
    pub fn pulsation_factor(&self, t: f64) -> f64 {
        let phase = (std::f64::consts::PI * self.config.pulsation_hz * t)
            .sin()
            .abs();
        let mean_of_abs_sine = 2.0 / std::f64::consts::PI;
        let a = self.config.pulsation_amplitude;
        1.0 + a * (phase - mean_of_abs_sine) / (1.0 - mean_of_abs_sine)
    }

    fn moment(&self, heading: f64) -> Vector3<f64> {
        Vector3::new(heading.cos(), heading.sin(), 0.0) * self.robot.magnet_moment_am2
    }

    /// Number of coils of the rig (the first entries of the current arrays).
    pub fn coil_count(&self) -> usize {
        self.coils.coil_count().min(MAX_COILS)
    }

    /// Advances the state by `dt` with the given commanded coil currents (one per coil of the
    /// rig; missing entries count as 0, extra ones are ignored). `wall_contact` then tells
    /// whether the capsule touched a wall at any time during the step.
    pub fn step(&self, state: &mut PlantState, commanded_a: &[f64], dt: f64) {
        let substep = (self.config.substep_ms * 1e-3).max(1e-5);
        let n = if dt.is_finite() && dt > 0.0 {
            ((dt / substep).ceil() as usize).max(1)
        } else {
            return;
        };
        let h = dt / n as f64;
        let mut any_contact = false;
        for _ in 0..n {
            self.substep(state, commanded_a, h);
            any_contact |= state.touching;
        }
        state.wall_contact = any_contact;
    }

    /// [`Self::step`] for a command that reaches the coils `delay_s` into the step: the coils
    /// are driven with `previous_a` until then and with `commanded_a` after (a frame's command
    /// acts only once vision, control and the serial link have handled that frame). `delay_s`
    /// is clamped into [0, `dt`]; 0 is exactly [`Self::step`].
    pub fn step_with_command_delay(
        &self,
        state: &mut PlantState,
        previous_a: &[f64],
        commanded_a: &[f64],
        dt: f64,
        delay_s: f64,
    ) {
        let delay = if delay_s.is_finite() {
            delay_s.clamp(0.0, dt.max(0.0))
        } else {
            0.0
        };
        if delay <= 0.0 {
            self.step(state, commanded_a, dt);
            return;
        }
        self.step(state, previous_a, delay);
        let touched_before = state.wall_contact;
        if dt - delay > 0.0 {
            self.step(state, commanded_a, dt - delay);
        }
        state.wall_contact |= touched_before;
    }

    fn substep(&self, state: &mut PlantState, commanded_a: &[f64], h: f64) {
        // Coil currents follow their commands with the L/R lag (exact for a first-order lag).
        let tau = (self.config.coil_time_constant_ms * 1e-3).max(1e-6);
        let alpha = 1.0 - (-h / tau).exp();
        let n = self.coil_count();
        for (i, c) in state.coil_currents_a[..n].iter_mut().enumerate() {
            let target = commanded_a
                .get(i)
                .copied()
                .filter(|a| a.is_finite())
                .unwrap_or(0.0);
            *c += alpha * (target - *c);
        }
        let true_currents: Vec<f64> = state.coil_currents_a[..n]
            .iter()
            .zip(&self.coil_gains)
            .enumerate()
            .map(|(k, (c, g))| match self.saturation.get(k) {
                Some(Some(curve)) => curve.effective(c * g),
                _ => c * g,
            })
            .collect();
        let p3 = Vector3::new(state.position_m.x, state.position_m.y, 0.0);
        let (field, gradient) = self.coils.field_and_gradient(&true_currents, &p3);
        let moment = self.moment(state.heading_rad);
        let force3 = physics::magnetic_force(&moment, &gradient);
        let force = Vector2::new(force3.x, force3.y);
        let torque_z = physics::magnetic_torque(&moment, &field).z;
        let pull_down_n = (-force3.z).max(0.0);

        // Alignment: overdamped rotation (inertia is negligible at these scales).
        let omega = torque_z / self.rotational_drag_n_m_s;
        let heading_before = state.heading_rad;
        state.heading_rad = wrap_angle(state.heading_rad + (omega * h).clamp(-0.5, 0.5));

        self.disturbance.advance_noise(&mut state.flow_noise, h);
        let flow = self.true_flow_with_noise(&state.position_m, state.time_s, &state.flow_noise);
        let relative = state.velocity_mps - flow;
        let quadratic = -relative * (self.quadratic_drag_n_s2_per_m2 * relative.norm());
        let mass = self.robot.mass_kg + self.robot.added_mass_kg;
        // Semi-implicit in the linear drag, which is the stiff term at low viscosity.
        if self.linear_drag.is_isotropic() && self.flow_coupling.is_isotropic() {
            let c = self.linear_drag.axial_n_s_per_m;
            let explicit = force + quadratic + flow * self.flow_coupling.axial_n_s_per_m;
            state.velocity_mps =
                (state.velocity_mps + explicit * (h / mass)) / (1.0 + c * h / mass);
        } else {
            let axis = Vector2::new(state.heading_rad.cos(), state.heading_rad.sin());
            let explicit = force + quadratic + self.flow_coupling.tensor(&axis) * flow;
            let implicit = Matrix2::identity() + self.linear_drag.tensor(&axis) * (h / mass);
            // Symmetric positive definite (both drags > 0), so always invertible.
            state.velocity_mps = implicit.try_inverse().map_or(Vector2::zeros(), |inverse| {
                inverse * (state.velocity_mps + explicit * (h / mass))
            });
        }
        let mu = self.config.floor_friction_coefficient;
        let normal_load = (self.apparent_weight_n + pull_down_n).max(0.0)
            + self.config.floor_extra_load_n.max(0.0);
        if mu > 0.0 {
            // Coulomb friction as an impulse bounded by μ·N·h: it stops a slow capsule (static
            // friction holds it) and never reverses a moving one.
            let max_dv = mu * normal_load * h / mass;
            let speed = state.velocity_mps.norm();
            if speed <= max_dv {
                state.velocity_mps = Vector2::zeros();
            } else {
                state.velocity_mps *= 1.0 - max_dv / speed;
            }
        }
        if !(state.velocity_mps.x.is_finite() && state.velocity_mps.y.is_finite()) {
            state.velocity_mps = Vector2::zeros();
        }
        let mut touching = self.sweep(state, h);
        if touching && state.heading_rad != heading_before && self.penetration(state) > 1e-6 {
            // Wedged: the walls block the turn (a capsule longer than the canal is wide).
            state.heading_rad = heading_before;
            touching |= self.resolve_walls(state);
        }
        state.last_floor_load_n = if mu > 0.0 { normal_load } else { 0.0 };
        if touching {
            if !state.touching {
                state.contact_events += 1;
            }
            state.contact_time_s += h;
        }
        state.touching = touching;
        state.wall_contact = touching;
        state.time_s += h;
        state.last_magnetic_force_n = force;
        state.last_true_flow_mps = flow;
    }

    /// Moves the capsule by `velocity·h` in sub-moves no longer than a quarter radius, resolving
    /// the walls after each, so it cannot tunnel through a wall whatever its speed. True on
    /// contact.
    fn sweep(&self, state: &mut PlantState, h: f64) -> bool {
        let radius = self.robot.diameter_m / 2.0;
        let max_move = (SWEEP_FRACTION_OF_RADIUS * radius).max(1e-6);
        let distance = state.velocity_mps.norm() * h;
        let moves = ((distance / max_move).ceil() as usize).clamp(1, MAX_SWEEP_MOVES);
        let mut contact = false;
        let mut remaining = h;
        for k in 0..moves {
            let dt = remaining / (moves - k) as f64;
            remaining -= dt;
            // Never more than `max_move` per wall check, even past MAX_SWEEP_MOVES.
            let mut delta = state.velocity_mps * dt;
            let len = delta.norm();
            if len > max_move {
                delta *= max_move / len;
            }
            state.position_m += delta;
            contact |= self.resolve_walls(state);
        }
        contact
    }

    /// Deepest penetration of the capsule's ends and middle into the wall, m (≤ 0: free).
    pub fn penetration(&self, state: &PlantState) -> f64 {
        let radius = self.robot.diameter_m / 2.0;
        let half_axis = (self.robot.length_m / 2.0 - radius).max(0.0);
        let axis = Vector2::new(state.heading_rad.cos(), state.heading_rad.sin());
        [-half_axis, 0.0, half_axis]
            .iter()
            .map(|o| self.walls.signed_distance(&(state.position_m + axis * *o)) + radius)
            .fold(f64::NEG_INFINITY, f64::max)
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
                let penetration = self.walls.signed_distance(&point) + radius;
                if penetration > 0.0 {
                    let normal = self.walls.wall_normal(&point);
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
