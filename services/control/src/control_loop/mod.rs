//! The port-free loop: feed it poses (with their flow estimate), get commands. `step_at` is the
//! pipeline; each stage lives in a file of its own.

mod allocation;
mod feed;
mod field_turning;
mod gains;
mod gate;
#[cfg(test)]
mod tests;

use std::collections::VecDeque;
use std::sync::Arc;

use fieldmaps::allocation::CoilRatings;
use fieldmaps::physics;
use fieldmaps::rig::{RobotParams, SaturationCurve};
use fieldmaps::rigfile::Rig;
use millinav_kit::contract::ContractViolations;
use nalgebra::Vector2;
use shm_schemas::{services, zone, CoilCommand, ControlMode, FlowEstimate, Pose, MAX_COILS};

use self::allocation::Allocated;
use self::feed::Fed;
use crate::coil_gains::{CoilGainEstimator, GainUpdate};
use crate::config::ControlConfig;
use crate::controllers::{ControlInput, ControlTerms, Controller, NominalModel, SmcGains};
use crate::latency::Predictor;
use crate::latency::PredictorBank;
use crate::observer::{VelocityEstimate, VelocityObserver};
use crate::reference::{Reference, ReferenceSample};

/// Allowance on top of `max_speed_mps · Δt` before a pose counts as a jump, so that
/// localization noise on the two poses cannot reject a real move when Δt is short.
const POSE_JUMP_SLACK_M: f64 = 3e-3;

/// Candidate orientation fields are this far apart when the heading may turn.
const FIELD_HEADING_STEP_DEG: f64 = 15.0;
/// The asked force's direction a pulling field follows is averaged over this long (s): the
/// pump's stroke (1–3 Hz) turns it, frame-to-frame noise does not.
const PULL_FORCE_AVERAGE_S: f64 = 0.1;
/// A force counts as made when the allocation misses it by at most this fraction.
const FORCE_MADE_FRACTION: f64 = 0.02;
/// A turn toward more force must miss the asked force by this fraction less than staying.
const TURN_HYSTERESIS_FRACTION: f64 = 0.05;
/// A slew-bounded allocation this far short of the asked force (fraction of it) is allocated
/// again without the bound, for the force the coils could make at their ratings.
const SLEW_SHORTFALL_FRACTION: f64 = 1e-3;

/// One control decision, with what went into it (for logging and tests).
#[derive(Debug, Clone)]
pub struct Decision {
    pub command: CoilCommand,
    pub terms: ControlTerms,
    pub reference_m: Vector2<f64>,
    pub finished: bool,
    /// Why the pose was not used, if it was not.
    pub rejected: Option<&'static str>,
    /// Actuation time − capture time of the pose (s): the delay the loop saw.
    pub pose_age_s: f64,
    /// The position the controller was fed (predicted for the actuation time when
    /// compensating, else the measured one).
    pub fed_position_m: Vector2<f64>,
    /// The position predicted for the actuation time (whether fed or not).
    pub predicted_position_m: Vector2<f64>,
    /// The share of the measured motion the predictor's model missed, recently (0 to 1).
    pub unpredicted_motion_share: f64,
    /// The latency predictor's disturbance time constant in use, in delays (the chosen
    /// candidate of `[control.latency] disturbance_delays_candidates`).
    pub disturbance_delays: f64,
    /// What this pose's heading did to the coil-gain estimate, when estimating.
    pub gain_update: Option<GainUpdate>,
    /// The bound on the asked force from the predictor's expected miss (N): with
    /// `[control.latency] max_field_turn_at_miss_rad` above 0 (0.2 by default) and the latency
    /// compensated, once the predictor has seen two poses.
    pub force_cap_n: Option<f64>,
}

/// Port-free control loop: feed it poses (with their flow estimate), get commands.
pub struct ControlLoop {
    pub config: ControlConfig,
    pub reference: Reference,
    controller: Box<dyn Controller>,
    /// The rig: coil model (control's, never the twin's), canal mask, robot.
    rig: Arc<Rig>,
    coil_ids: Vec<usize>,
    /// Each allocated coil's limit and resistance: the rig's own, or `[control.limits]` for all.
    ratings: CoilRatings,
    /// The same in the field model's effective currents (differs for saturating coils).
    effective_ratings: CoilRatings,
    /// Each allocated coil's saturation curve (rig file), `None` when linear.
    saturation: Vec<Option<SaturationCurve>>,
    robot: RobotParams,
    incarnation: u64,
    last_good: Option<(u64, Vector2<f64>)>,
    /// Time and position of the last state fed to the controller (the velocity filter's input).
    last_fed: Option<(u64, Vector2<f64>)>,
    velocity: Vector2<f64>,
    last_mode: ControlMode,
    /// Predicts the state at actuation time from delayed poses and the issued forces.
    predictor: PredictorBank,
    /// The velocity from the forces and the fed positions (`velocity_estimate = "observer"`).
    observer: Option<VelocityObserver>,
    /// Actuation time and currents of the last tracking command (the slew limit's start).
    last_tracked: Option<(u64, [f64; MAX_COILS])>,
    /// Poses and flow estimates that broke the contract (bad flag bytes); treated as invalid.
    pub violations: ContractViolations,
    /// Online coil-gain estimate the allocation uses (`[control.gain_estimation]`).
    gain_estimator: Option<CoilGainEstimator>,
    /// Actuation time and currents of the recent commands, to know which currents were in
    /// effect when a frame was captured.
    issued: VecDeque<(u64, [f64; MAX_COILS])>,
    /// Heading of the orientation field commanded last (rad): `field_heading_deg` unless
    /// `field_heading_turn_deg` lets it turn.
    field_heading_rad: f64,
    /// The orientation field's magnitude (T): the table's, or the aligning torque over the
    /// rig's magnet.
    field_magnitude_t: f64,
    /// How long the field must have held its direction before a frame's heading measures it
    /// (ns): the gain estimate's `settle_ms`, and at least three rotation time constants.
    alignment_window_ns: u64,
    /// Three rotation time constants of the capsule in the orientation field (ns): after a
    /// turn held this long the magnet points where the field does.
    rotation_settle_ns: u64,
    /// The fastest the orientation field turns (rad/s): what the capsule follows within one
    /// candidate step (see `field_heading_turn_deg`).
    max_field_turn_rate_rad_per_s: f64,
    /// How far the field may still turn (rad): grows at the rate above, up to
    /// `field_heading_turn_deg`, and each turn spends it.
    field_turn_budget_rad: f64,
    /// The orientation field's heading from each command's actuation time (none: coils off),
    /// to know where it pointed when a frame was captured.
    field_history: VecDeque<(u64, Option<f64>)>,
    /// The magnet's heading minus the field's, last measured on a frame captured after the
    /// field had held still for `rotation_settle_ns` (rad).
    magnet_offset_rad: f64,
    /// The asked force averaged over `PULL_FORCE_AVERAGE_S` (N), and whether the fluid moves
    /// at the robot: the heading `field_follows_force` pulls along.
    pull_force_n: Vector2<f64>,
    fluid_moves: bool,
}

/// Commands remembered for matching frames to the currents in effect at their capture.
const ISSUED_HISTORY_LEN: usize = 64;
/// Commands whose orientation field is remembered: more than a pose may be old
/// (`max_pose_age_ms`) at a 1 kHz loop.
const FIELD_HISTORY_LEN: usize = 1024;

impl ControlLoop {
    pub fn new(
        config: ControlConfig,
        reference: Reference,
        viscosity_pa_s: f64,
        incarnation: u64,
        rig: Arc<Rig>,
    ) -> Self {
        let robot = rig.robot;
        let model = NominalModel {
            mass_kg: robot.mass_kg,
            linear_drag_n_s_per_m: physics::translational_damping(
                viscosity_pa_s,
                robot.length_m,
                robot.diameter_m / 2.0,
            ) * config.drag_factor,
        };
        let coils = CoilSetup::of(&config, &rig);
        let controller = build_controller(&config, &rig, &reference, model);
        // The predictor moves the whole body: the fluid it drags along counts (added mass).
        let moving = NominalModel {
            mass_kg: robot.mass_kg + robot.added_mass_kg,
            ..model
        };
        let predictor = PredictorBank::new(config.latency.clone(), moving);
        let observer = (config.velocity_estimate == VelocityEstimate::Observer).then(|| {
            VelocityObserver::new(config.observer.clone(), moving, config.latency.pulsation_hz)
        });
        let field = FieldTiming::of(&config, &robot, viscosity_pa_s);
        let gain_estimator = config
            .gain_estimation
            .enabled
            .then(|| CoilGainEstimator::new(config.gain_estimation.clone(), coils.ids.clone()));
        Self {
            field_heading_rad: config.field_heading_deg.to_radians(),
            field_turn_budget_rad: config
                .field_heading_turn_deg
                .map_or(0.0, |deg| deg.max(0.0).to_radians()),
            config,
            reference,
            controller,
            coil_ids: coils.ids,
            ratings: coils.ratings,
            effective_ratings: coils.effective_ratings,
            saturation: coils.saturation,
            rig,
            robot,
            incarnation,
            last_good: None,
            last_fed: None,
            velocity: Vector2::zeros(),
            last_mode: ControlMode::Safe,
            predictor,
            observer,
            last_tracked: None,
            violations: ContractViolations::default(),
            gain_estimator,
            issued: VecDeque::with_capacity(ISSUED_HISTORY_LEN),
            field_magnitude_t: field.magnitude_t,
            alignment_window_ns: field.alignment_window_ns,
            rotation_settle_ns: field.rotation_settle_ns,
            max_field_turn_rate_rad_per_s: field.max_turn_rate_rad_per_s,
            field_history: VecDeque::with_capacity(FIELD_HISTORY_LEN),
            magnet_offset_rad: 0.0,
            pull_force_n: Vector2::zeros(),
            fluid_moves: false,
        }
    }

    /// When a command computed now takes effect: now plus the delay no stamp shows.
    fn actuation_ns(&self, now_ns: u64) -> u64 {
        now_ns.saturating_add(millinav_kit::clock::secs_to_ns(
            self.config.latency.unstamped_delay_ms * 1e-3,
        ))
    }

    /// Coils the loop allocates for: the `active_coils` of every command.
    pub fn coil_count(&self) -> usize {
        self.rig.coils.len()
    }

    /// A command answering `pose` with no currents yet (all coils of the rig at zero).
    fn command_for(&self, pose: &Pose) -> CoilCommand {
        CoilCommand {
            stamp: pose.stamp,
            control_incarnation: self.incarnation,
            controller_id: self.controller.id(),
            // The rig's count (a rig file holds at most MAX_COILS coils).
            active_coils: self.coil_count() as u32,
            ..Default::default()
        }
    }

    /// The rig the loop drives: its coil model (control's, never the twin's), canal and robot.
    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    pub fn controller_name(&self) -> &'static str {
        self.controller.name()
    }

    /// The largest force worth asking for a pose `pose_age_s` old at actuation, with
    /// `[control.latency] max_field_turn_at_miss_rad` above 0. F = (m·∇)B: the gradient that makes
    /// a force F is at least |F|/|m|, so at a capsule δ from where the allocation placed the
    /// field (the predictor's expected miss) it turns the orientation field by up to
    /// |F|·δ/(|m||B|). Past about a radian the magnet follows a field that pushes it the wrong
    /// way and the capsule is thrown (README, "Bounding the force by the predictor's miss").
    fn miss_force_cap_n(&self, pose_age_s: f64) -> Option<f64> {
        // Part of the compensation: a loop fed the stale pose (the paper's, as it ran) has none.
        if !self.config.latency.compensate {
            return None;
        }
        let turn_rad = self.config.latency.max_field_turn_at_miss_rad;
        let miss_m = self.predictor.expected_miss_m(pose_age_s);
        (turn_rad > 0.0 && miss_m > 0.0)
            .then(|| turn_rad * self.robot.magnet_moment_am2 * self.field_magnitude_t / miss_m)
    }

    /// The rig coils the allocation drives, in allocation order.
    pub fn coil_ids(&self) -> &[usize] {
        &self.coil_ids
    }

    /// A safe-state (zero current) command answering `pose`, e.g. when an input is lost.
    pub fn safe(&mut self, pose: &Pose, why: &'static str) -> Decision {
        self.safe_at(pose, why, pose.stamp.grab_time_ns)
    }

    /// [`Self::safe`] with "now" on the run clock given.
    pub fn safe_at(&mut self, pose: &Pose, why: &'static str, now_ns: u64) -> Decision {
        let actuation_ns = self.actuation_ns(now_ns);
        let reference = self.reference.sample(actuation_ns as f64 * 1e-9);
        self.controller.reset();
        self.predictor.reset();
        self.predictor
            .commanded(actuation_ns, Vector2::zeros(), Vector2::zeros());
        self.last_mode = ControlMode::Safe;
        // Tracking resumes from zero current.
        self.last_tracked = Some((actuation_ns, [0.0; MAX_COILS]));
        self.record_issued(actuation_ns, [0.0; MAX_COILS]);
        self.record_field(actuation_ns, None);
        Decision {
            command: CoilCommand {
                mode: ControlMode::Safe as u32,
                ..self.command_for(pose)
            },
            terms: ControlTerms::default(),
            reference_m: reference.position_m,
            finished: reference.finished,
            rejected: Some(why),
            pose_age_s: actuation_ns.saturating_sub(pose.stamp.capture_time_ns) as f64 * 1e-9,
            fed_position_m: Vector2::new(pose.position_m[0], pose.position_m[1]),
            predicted_position_m: Vector2::new(pose.position_m[0], pose.position_m[1]),
            gain_update: None,
            unpredicted_motion_share: self.predictor.unpredicted_motion_share(),
            disturbance_delays: self.predictor.active_disturbance_delays(),
            force_cap_n: None,
        }
    }

    /// One step in lockstep: the command for `pose` given the flow estimate made for it (if
    /// any), "now" being the frame's grab time (the twin holds its clock until the command).
    pub fn step(&mut self, pose: &Pose, flow: Option<&FlowEstimate>) -> Decision {
        self.step_at(pose, flow, pose.stamp.grab_time_ns)
    }

    /// One step with "now" on the run clock given (real time: the run clock at this step):
    /// the pose is checked (a rejected one holds or goes safe), the state is predicted for the
    /// actuation time, the controller asks for a force, and the coils are allocated for it.
    pub fn step_at(&mut self, pose: &Pose, flow: Option<&FlowEstimate>, now_ns: u64) -> Decision {
        let timing = self.timing(pose, now_ns);
        if let Some(why) = self.check_pose(pose, timing.capture_ns, timing.actuation_ns) {
            return self.reject(pose, why, &timing);
        }
        let measured = Vector2::new(pose.position_m[0], pose.position_m[1]);
        let tracking = self.resume_tracking();
        let gain_update = self.observe_pose(pose, measured, timing.capture_ns);
        let flow = self.flow_at(pose, flow);
        let fed = self.feed(measured, &timing, flow.velocity_mps, tracking);
        let input = self.control_input(&timing, &fed, &flow);
        let (asked, terms) = self.controller.update(&input);
        let force_cap_n = self.miss_force_cap_n(timing.pose_age_s);
        let force = capped(asked, force_cap_n);
        let allocated = self.allocate_force(pose, &fed, &force, &timing, flow.velocity_mps);
        self.commit_tracking(timing.actuation_ns, &force, &allocated, flow.velocity_mps);
        let field = self.desired_field();
        let command = CoilCommand {
            mode: ControlMode::Track as u32,
            force_des_n: [force.x, force.y],
            field_des_t: [field.x, field.y],
            currents_a: allocated.currents,
            ..self.command_for(pose)
        };
        Decision {
            command,
            terms,
            reference_m: timing.reference.position_m,
            finished: timing.reference.finished,
            rejected: None,
            pose_age_s: timing.pose_age_s,
            fed_position_m: fed.position_m,
            predicted_position_m: measured + fed.predicted.motion_ahead_m,
            gain_update,
            unpredicted_motion_share: self.predictor.unpredicted_motion_share(),
            disturbance_delays: self.predictor.active_disturbance_delays(),
            force_cap_n,
        }
    }

    /// When the pose was captured, when this step's command acts, and where the robot should
    /// be then.
    fn timing(&self, pose: &Pose, now_ns: u64) -> StepTiming {
        let capture_ns = pose.stamp.capture_time_ns;
        let actuation_ns = self.actuation_ns(now_ns.max(capture_ns));
        StepTiming {
            capture_ns,
            actuation_ns,
            pose_age_s: (actuation_ns - capture_ns) as f64 * 1e-9,
            // The robot should be where the reference is when the command acts.
            reference: self.reference.sample(actuation_ns as f64 * 1e-9),
        }
    }

    /// Whether the loop was tracking before this pose; if not, the predictor and the observer
    /// start afresh.
    fn resume_tracking(&mut self) -> bool {
        let tracking = self.last_mode == ControlMode::Track;
        if !tracking {
            self.predictor.reset();
            if let Some(observer) = &mut self.observer {
                observer.reset();
            }
        }
        tracking
    }

    /// Takes a usable pose as the last good one and, when it is a new exposure, teaches the
    /// coil gains from its heading.
    fn observe_pose(
        &mut self,
        pose: &Pose,
        measured: Vector2<f64>,
        capture_ns: u64,
    ) -> Option<GainUpdate> {
        // A camera slower than the loop delivers its latest exposure again: one observation.
        let fresh = self.last_good.is_none_or(|(t_prev, _)| capture_ns > t_prev);
        self.last_good = Some((capture_ns, measured));
        if fresh {
            self.learn_gains(pose, capture_ns)
        } else {
            None
        }
    }

    /// The flow estimate made for this pose's frame, when there is a valid one (else none: zero
    /// flow, no high disturbance).
    fn flow_at(&mut self, pose: &Pose, flow: Option<&FlowEstimate>) -> FlowAtPose {
        let flow_valid = flow.map(|f| self.violations.check(services::FLOW, f.validity()));
        match (flow, flow_valid) {
            (Some(f), Some(Ok(true))) if f.stamp.same_frame(&pose.stamp) => FlowAtPose {
                velocity_mps: Vector2::new(f.velocity_mps[0], f.velocity_mps[1]),
                high_disturbance: f.zone_flags & zone::HIGH_DISTURBANCE != 0,
            },
            _ => FlowAtPose {
                velocity_mps: Vector2::zeros(),
                high_disturbance: false,
            },
        }
    }

    /// What the controller is told for this step.
    fn control_input(&self, timing: &StepTiming, fed: &Fed, flow: &FlowAtPose) -> ControlInput {
        let compensate = self.config.latency.compensate;
        ControlInput {
            dt_s: fed.dt_s,
            delay_s: timing.pose_age_s,
            position_m: fed.position_m,
            velocity_mps: self.velocity,
            reference: timing.reference,
            flow_mps: flow.velocity_mps,
            high_disturbance: flow.high_disturbance,
            // Over the command's hold, which lasts about one pose interval.
            predicted_disturbance_n: self
                .predictor
                .lead_disturbance(timing.actuation_ns, fed.dt_s)
                .filter(|_| compensate),
            coil_gain_std: self.coil_gain_std(),
            unpredicted_motion_share: if compensate {
                self.predictor.unpredicted_motion_share()
            } else {
                0.0
            },
        }
    }

    /// Remembers what this tracking command does and tells the controller, the predictor and
    /// the observer the force the coils make.
    fn commit_tracking(
        &mut self,
        actuation_ns: u64,
        force: &Vector2<f64>,
        allocated: &Allocated,
        flow_mps: Vector2<f64>,
    ) {
        self.last_tracked = Some((actuation_ns, allocated.currents));
        self.record_issued(actuation_ns, allocated.currents);
        self.record_field(actuation_ns, Some(self.field_heading_rad));
        self.controller
            .applied(allocated.achieved, allocated.at_ratings);
        self.predictor
            .achieved(actuation_ns, *force, allocated.achieved);
        self.predictor
            .commanded(actuation_ns, allocated.achieved, flow_mps);
        if let Some(observer) = &mut self.observer {
            observer.applied(allocated.achieved, flow_mps);
        }
        self.last_mode = ControlMode::Track;
    }
}

/// The times of one step.
struct StepTiming {
    capture_ns: u64,
    actuation_ns: u64,
    /// Actuation time − capture time (s): the delay the loop sees.
    pose_age_s: f64,
    /// The reference at the actuation time.
    reference: ReferenceSample,
}

/// The flow service's estimate for the pose, as the controller uses it.
struct FlowAtPose {
    velocity_mps: Vector2<f64>,
    high_disturbance: bool,
}

/// `asked` shortened to `cap` (N) when it is longer.
fn capped(asked: Vector2<f64>, cap: Option<f64>) -> Vector2<f64> {
    match cap {
        Some(cap) if asked.norm() > cap => asked * (cap / asked.norm()),
        _ => asked,
    }
}

/// The configured controller, its MPC gains for the reference's path and its SMC told the
/// coils' lag.
fn build_controller(
    config: &ControlConfig,
    rig: &Rig,
    reference: &Reference,
    model: NominalModel,
) -> Box<dyn Controller> {
    let mpc = config.mpc_gains(rig, reference.waypoints());
    let smc = SmcGains {
        coil_time_constant_s: config.coil_time_constant_ms * 1e-3,
        ..config.smc.clone()
    };
    config.controller.build(&config.pid, &smc, &mpc, model)
}

/// The coils the loop allocates for and what it knows of each.
struct CoilSetup {
    ids: Vec<usize>,
    /// Each coil's limit and resistance: the rig's own, or `[control.limits]` for all.
    ratings: CoilRatings,
    /// The same in the field model's effective currents (differs for saturating coils).
    effective_ratings: CoilRatings,
    saturation: Vec<Option<SaturationCurve>>,
}

impl CoilSetup {
    fn of(config: &ControlConfig, rig: &Rig) -> Self {
        let ids = config.coil_ids(rig);
        let ratings = match &config.limits {
            Some(limits) => CoilRatings::uniform(limits, ids.len()),
            None => rig.coil_ratings(&ids),
        };
        let saturation: Vec<Option<SaturationCurve>> = ids
            .iter()
            .map(|&id| rig.coils.get(id).and_then(|c| c.saturation.clone()))
            .collect();
        let effective_ratings = ratings.effective(&saturation);
        Self {
            ids,
            ratings,
            effective_ratings,
            saturation,
        }
    }
}

/// The orientation field's magnitude and how fast the capsule follows it.
struct FieldTiming {
    magnitude_t: f64,
    alignment_window_ns: u64,
    rotation_settle_ns: u64,
    max_turn_rate_rad_per_s: f64,
}

impl FieldTiming {
    fn of(config: &ControlConfig, robot: &RobotParams, viscosity_pa_s: f64) -> Self {
        let magnitude_t = config.field_magnitude_t(robot.magnet_moment_am2);
        let rotation_time_constant_s =
            physics::rotational_drag(viscosity_pa_s, robot.length_m, robot.diameter_m / 2.0)
                / (robot.magnet_moment_am2 * magnitude_t).max(1e-12);
        // The capsule follows the commanded field through two lags in series: the coils'
        // currents (L/R, when control is told it) and its own rotation; the sum of their time
        // constants is the mean delay of the pair.
        let follow_time_constant_s =
            rotation_time_constant_s + config.coil_time_constant_ms.max(0.0) * 1e-3;
        let alignment_window_s =
            (config.gain_estimation.settle_ms * 1e-3).max(3.0 * follow_time_constant_s);
        Self {
            magnitude_t,
            alignment_window_ns: (alignment_window_s.min(10.0) * 1e9) as u64,
            rotation_settle_ns: ((3.0 * follow_time_constant_s).min(10.0) * 1e9) as u64,
            // Steadily turning at ω the overdamped capsule lags the field by asin(ω τ).
            max_turn_rate_rad_per_s: FIELD_HEADING_STEP_DEG.to_radians().sin()
                / follow_time_constant_s.max(1e-6),
        }
    }
}
