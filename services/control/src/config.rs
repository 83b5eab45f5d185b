//! The `[control]` table: what a scenario configures of the loop, with its defaults.

use fieldmaps::physics;
use fieldmaps::rig::CoilLimits;
use fieldmaps::rigfile::Rig;
use nalgebra::Vector2;
use serde::{Deserialize, Serialize};

use crate::coil_gains::GainEstimationConfig;
use crate::controllers::{ControllerKind, ForceSite, MpcGains, PidGains, SmcGains};
use crate::latency::LatencyConfig;
use crate::observer::{ObserverConfig, VelocityEstimate};

/// `[control]` section of a scenario.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ControlConfig {
    pub controller: ControllerKind,
    pub pid: PidGains,
    pub smc: SmcGains,
    /// MPC gains (`[control.mpc]`).
    pub mpc: MpcGains,
    /// Heading of the orientation field (deg from +x; the paper fixes 45° in static tests).
    pub field_heading_deg: f64,
    /// Magnitude of the orientation field (mT). Unset: whatever holds the rig's magnet with
    /// `aligning_torque_n_m`.
    pub field_magnitude_mt: Option<f64>,
    /// With `field_magnitude_mt` unset, the orientation field is this torque over the rig's
    /// magnet moment (|m|·B, N·m). The field's pull on the magnet scales with |m|·B as well, so
    /// a capsule with a stronger magnet gets a weaker field, the same turning and the same
    /// pull. Default: the paper's 1 mT on its 0.86e-3 A·m² magnet
    /// (`fieldmaps::physics::DEFAULT_ALIGNING_TORQUE_N_M`).
    pub aligning_torque_n_m: f64,
    /// The coils' current time constant (ms): L/R, or the driver's current loop, measured by
    /// the lab (a current step on the board's Status). The scheduled SMC-DOB counts it
    /// (`SmcGains::coil_time_constant_s`), and so does the orientation field: the capsule
    /// follows a commanded field through the coils' lag and its own rotation, so a turning
    /// field turns that much slower and the coil-gain estimate waits that much longer for the
    /// field to settle before it learns from a frame. 0 (default): coils that follow within a
    /// frame.
    pub coil_time_constant_ms: f64,
    /// The capsule's translational drag as the lab measured it, over paper Eq. 7's c_t (which
    /// every controller, the latency predictor and the velocity observer assume). A capsule
    /// lying on the phantom floor drags several times Eq. 7 (a cylinder on a 30 µm film ×5–8,
    /// README "What the twin lacks"), and a loop that assumes far too little drag feeds the
    /// physical damping back through its observer across the delay: at the paper's 10 Hz with
    /// 60 ms, 8× the nominal drag lost still 20 cP fluid. Measure it as force over terminal
    /// speed in still fluid (README, "Telling control the capsule's drag"). 1 (default): Eq. 7.
    pub drag_factor: f64,
    /// ω0 of paper Eq. 2 (N/T): weight of the field rows against the force rows.
    pub omega0_n_per_t: f64,
    /// After the last good pose, hold the field this long, then go safe.
    pub hold_timeout_ms: f64,
    /// Fastest believable robot speed; larger pose jumps are rejected.
    pub max_speed_mps: f64,
    /// Where the controllers' velocity comes from: low-passed differences of the fed
    /// positions, or the model-based observer (`[control.observer]`), which predicts it from
    /// the forces the coils made and corrects it with each pose.
    pub velocity_estimate: VelocityEstimate,
    /// Time constant of the differences' low-pass filter (`velocity_estimate = "differences"`).
    pub velocity_filter_ms: f64,
    /// The velocity observer (`velocity_estimate = "observer"`).
    pub observer: ObserverConfig,
    /// Current and power limits the allocation respects, one rating for every coil; default:
    /// each coil's own from the rig file (`Rig::coil_ratings`).
    pub limits: Option<CoilLimits>,
    /// Allocate with the constrained QP (per-coil and total limits, best effort when the
    /// command is infeasible) instead of the paper's pseudo-inverse followed by scaling.
    pub constrained_allocation: bool,
    /// Weight of the two field rows against the force rows in the constrained allocation's
    /// best-effort fit. When the command is out of reach, the orientation field (the robot's
    /// heading, hence the direction of every force) is kept and force is given up first;
    /// with equal weights the fit trades the 1 mT field for force and the robot tumbles.
    pub field_row_weight: f64,
    /// Allocate over all the rig's coils instead of its `allocation_coils` (the paper's rig:
    /// all 12 instead of 8; the idle mid coils add force authority where the flow pushes
    /// hardest).
    pub use_all_coils: bool,
    /// Latency compensation (`[control.latency]`).
    pub latency: LatencyConfig,
    /// Fastest change of any coil current while tracking (A/s; none: unlimited). The
    /// allocation is then the constrained one (whatever `constrained_allocation` says) with
    /// every coil kept within this rate of its previous current: the command is met as far as
    /// the coils can follow, the coils with room making up for the others. Hold and safe are
    /// never slowed.
    pub max_current_slew_a_per_s: Option<f64>,
    /// Where the slew bound would withhold a large share of the asked force, a faster one
    /// (`[control.slew_yield]`; none: the bound always holds).
    pub slew_yield: Option<SlewYieldConfig>,
    /// Online correction of the coil gains from the measured heading
    /// (`[control.gain_estimation]`, off by default).
    pub gain_estimation: GainEstimationConfig,
    /// Turn the orientation field (and with it the capsule) when the coils cannot make the
    /// asked force at the present heading, by at most this many degrees per command, toward
    /// the heading where they come closest (none: the field stays at `field_heading_deg`, as
    /// in the paper). The force the coils can make in one direction depends several-fold on
    /// the magnet's heading, since F = (m·∇)B. Once the force is within reach again the field
    /// turns back toward `field_heading_deg` as far as the force stays within reach. Whatever
    /// this allows, the field turns no faster than the capsule follows it within one 15°
    /// candidate step (sin 15° over its rotation time constant plus the coils' told
    /// `coil_time_constant_ms`: about 1350°/s at 20 cP and 1 mT with instant coils), so at a
    /// fast loop a turn is spread over several commands.
    pub field_heading_turn_deg: Option<f64>,
    /// Where the fluid moves (the flow service reports flow at the robot), the turning field
    /// (`field_heading_turn_deg`) heads for the direction of the asked force, averaged over
    /// 0.1 s, instead of `field_heading_deg`: the magnet is pulled along its axis. Pulled
    /// sideways, the field gradient that makes the force's sideways part also turns the field
    /// by that part × distance / (|m| |B|) for every metre the capsule is from where the
    /// allocation placed it, and with the latency's prediction error (millimetres in a
    /// 10 cm/s pulsatile jet) the capsule turns and the force with it. Not under a slew bound
    /// (`max_current_slew_a_per_s`): turning the field to pull costs current steps the bound
    /// withholds (20 cP 10 cm/s at 100 Hz, bounded at 60 A/s: 0.69 mm pulling, 0.38 mm not).
    pub field_follows_force: bool,
    /// Wall clearance of the paths `millinav ctl goto` plans (A* on the canal mask), mm. The
    /// paper's 5 mm suits its heart phantom; a narrower vessel needs less (vessel8: 3).
    pub replan_clearance_mm: f64,
}

/// `[control.slew_yield]`: the slew bound gives way where it would withhold much of the force.
/// A hard bound protects the amplifiers from chatter, but where the pump's stroke itself asks
/// for faster currents it holds the coils back until the robot leaves its path (issue 21 point
/// 7: at 20 cP 10 cm/s the stroke outruns a 60 A/s bound in 15–25 % of the frames where the jet
/// is strongest). Those frames are few, so yielding there keeps the p95 step within the bound.
/// Not for a loop that chatters (PID, the paper-gain SMCs): their chatter is a command the bound
/// withholds, and with the yield it comes back (README, "Coil effort").
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct SlewYieldConfig {
    /// The bound yields where the bounded allocation misses the asked force by more than this
    /// fraction of it (0–1).
    pub shortfall_fraction: f64,
    /// The rate every coil stays within where the bound yields (A/s; above
    /// `max_current_slew_a_per_s`).
    pub max_current_slew_a_per_s: f64,
}

impl Default for SlewYieldConfig {
    fn default() -> Self {
        Self {
            shortfall_fraction: 0.2,
            max_current_slew_a_per_s: 240.0,
        }
    }
}

impl Default for ControlConfig {
    fn default() -> Self {
        Self {
            controller: ControllerKind::Pid,
            pid: PidGains::default(),
            smc: SmcGains::default(),
            mpc: MpcGains::default(),
            field_heading_deg: 45.0,
            field_magnitude_mt: None,
            aligning_torque_n_m: physics::DEFAULT_ALIGNING_TORQUE_N_M,
            coil_time_constant_ms: 0.0,
            drag_factor: 1.0,
            omega0_n_per_t: 0.05,
            hold_timeout_ms: 300.0,
            max_speed_mps: 0.3,
            velocity_estimate: VelocityEstimate::Differences,
            velocity_filter_ms: 30.0,
            observer: ObserverConfig::default(),
            limits: None,
            constrained_allocation: false,
            field_row_weight: 1e4,
            use_all_coils: false,
            latency: LatencyConfig::default(),
            max_current_slew_a_per_s: None,
            slew_yield: None,
            gain_estimation: GainEstimationConfig::default(),
            field_heading_turn_deg: None,
            field_follows_force: false,
            replan_clearance_mm: fieldmaps::phantom::PLANNER_CLEARANCE_M * 1e3,
        }
    }
}

impl ControlConfig {
    /// The current limits on `rig`: this table's, else the rig's.
    pub fn limits_on(&self, rig: &Rig) -> CoilLimits {
        self.limits.unwrap_or_else(|| rig.coil_limits())
    }

    /// The coils the allocation drives on `rig`.
    pub fn coil_ids(&self, rig: &Rig) -> Vec<usize> {
        if self.use_all_coils {
            (0..rig.coils.len()).collect()
        } else {
            rig.allocation_coils.clone()
        }
    }

    /// The orientation field's magnitude (T) for a magnet of `magnet_moment_am2`.
    pub fn field_magnitude_t(&self, magnet_moment_am2: f64) -> f64 {
        match self.field_magnitude_mt {
            Some(mt) => mt * 1e-3,
            None => self.aligning_torque_n_m / magnet_moment_am2,
        }
    }

    /// The MPC gains of this table, with the force bound resolved on `rig` along `path_m`
    /// from the current limits and orientation field when the MPC is the selected controller.
    pub fn mpc_gains(&self, rig: &Rig, path_m: &[Vector2<f64>]) -> MpcGains {
        if self.controller != ControllerKind::Mpc {
            return self.mpc.clone();
        }
        let heading = self.field_heading_deg.to_radians();
        let field = Vector2::new(heading.cos(), heading.sin())
            * self.field_magnitude_t(rig.robot.magnet_moment_am2);
        let coil_ids = self.coil_ids(rig);
        let site = ForceSite {
            coils: &rig.coil_field,
            coil_ids: &coil_ids,
            magnet_moment_am2: rig.robot.magnet_moment_am2,
            points_m: path_m,
        };
        self.mpc
            .resolved(&site, &self.limits_on(rig), &field, self.omega0_n_per_t)
    }
}
