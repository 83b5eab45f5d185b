//! plant: the digital twin of the rig. It owns the physics (truth), renders the top camera,
//! publishes frames and `PlantTruth`, and exposes an emulated Teensy on a pty pair that coilbus
//! drives exactly like the real board. In lockstep mode it is the run's clock.

pub mod fault_signals;
pub mod model;
pub mod render;
pub mod rng_streams;
pub mod teensy;
pub mod trueflow;

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use anyhow::Context;
use fieldmaps::flowmap::FlowMap;
use fieldmaps::rig::FluidParams;
use fieldmaps::rigfile::{CameraPixelFormat, Rig};
use millinav_kit::ports::{FrameOutbox, Outbox};
use millinav_kit::recording;
use millinav_kit::runlog::{ContactRow, RunLogRow, RunLogWriter, TeensyEventRow, TruthRow};
use millinav_kit::scenario::{ClockMode, Scenario};
use millinav_kit::service_loop::keep_alive;
use millinav_kit::{ConfigContext, ConfigError, Runtime};
use nalgebra::Vector2;
use serde::{Deserialize, Serialize};
use shm_schemas::{
    deadlines, services, Flag, FrameHeader, FrameStamp, PixelFormat, PlantTruth, FRAME_CHANNELS,
    MAX_COILS,
};

use crate::model::{PlantModel, PlantPhysicsConfig, PlantState};
use crate::render::{Camera, CameraConfig, CapsulePose};
use crate::teensy::{EmulatedTeensy, LinkFault};
use millinav_teensy_protocol::BoardState;

/// `[plant]` section of a scenario.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlantConfig {
    /// Start position (mm); defaults to the first trajectory waypoint.
    pub initial_position_mm: Option<[f64; 2]>,
    pub initial_heading_deg: f64,
    /// Standard deviation of camera pixel noise (8-bit levels).
    pub camera_noise_std: f64,
    /// Log the true pose every frame and a summary image every this many frames.
    pub log_every_frames: u64,
    pub physics: PlantPhysicsConfig,
    /// Time from a frame's capture to the command answering it reaching the coils, ms: vision
    /// inference, control, the serial link and the amplifier (lockstep only; a real-time run
    /// has its real delays). The coils drive the previous command until then. Less than one
    /// frame period; whole frames more are `[plant.camera] latency_frames`. The controller
    /// learns of it only from `[control.latency] unstamped_delay_ms`, as on a rig.
    pub command_delay_ms: f64,
    /// Blur, lighting drift, latency (`[plant.camera]`).
    pub camera: CameraConfig,
    /// What SIGUSR1 / SIGUSR2 do to the emulated Teensy link (`[plant.link_faults]`).
    pub link_faults: LinkFaultConfig,
    /// Board faults at set run times (`[plant.board_faults]`).
    pub board_faults: BoardFaultSchedule,
}

/// Faults of the emulated coil-driver board at set run times (s on the run clock; none by
/// default): the e-stop button pressed, the board rebooting, a driver channel whose current
/// sense reads `sense_fault_gain` × what it drives.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BoardFaultSchedule {
    pub estop_at_s: Option<f64>,
    pub reboot_at_s: Option<f64>,
    pub sense_fault_at_s: Option<f64>,
    pub sense_fault_channel: usize,
    pub sense_fault_gain: f64,
}

impl Default for BoardFaultSchedule {
    fn default() -> Self {
        Self {
            estop_at_s: None,
            reboot_at_s: None,
            sense_fault_at_s: None,
            sense_fault_channel: 0,
            sense_fault_gain: 0.5,
        }
    }
}

/// Durations of the link faults the plant injects on a signal: SIGUSR1 pulls the USB cable for
/// `unplug_ms`, SIGUSR2 stalls the board's firmware for `hang_ms` (longer than the Teensy
/// watchdog, so the hardware watchdog resets the board).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LinkFaultConfig {
    pub unplug_ms: u64,
    pub hang_ms: u64,
}

impl Default for LinkFaultConfig {
    fn default() -> Self {
        Self {
            unplug_ms: 500,
            hang_ms: 800,
        }
    }
}

impl Default for PlantConfig {
    fn default() -> Self {
        Self {
            initial_position_mm: None,
            initial_heading_deg: 45.0,
            camera_noise_std: 3.0,
            log_every_frames: 1,
            physics: PlantPhysicsConfig::default(),
            command_delay_ms: 0.0,
            camera: CameraConfig::default(),
            link_faults: LinkFaultConfig::default(),
            board_faults: BoardFaultSchedule::default(),
        }
    }
}

/// `[flow]` section as far as the plant is concerned: which steady map drives the true flow.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct FlowMapChoice {
    /// Path of a steady flow map (relative to the scenario file); none means static fluid.
    pub map: Option<std::path::PathBuf>,
}

impl FlowMapChoice {
    pub fn load(&self, scenario: &Scenario) -> anyhow::Result<FlowMap> {
        match &self.map {
            None => Ok(FlowMap::zero()),
            Some(path) => Ok(FlowMap::load(&scenario.resolve(path))?),
        }
    }
}

/// Builds the twin's model for a scenario (shared with in-process experiment runs).
pub fn build_model(scenario: &Scenario, config: &PlantConfig) -> anyhow::Result<PlantModel> {
    let rig = scenario.rig()?;
    Ok(load_model(scenario, &rig, config)?)
}

/// The model from the rig (truth coil field, robot, walls) and the steady flow map.
fn load_model(
    scenario: &Scenario,
    rig: &Rig,
    config: &PlantConfig,
) -> Result<PlantModel, ConfigError> {
    let fluid = FluidParams {
        viscosity_pa_s: scenario.viscosity_pa_s(),
        density_kg_m3: scenario.fluid.density_kg_m3,
    };
    if config.physics.drag_shape == model::DragShape::Cylinder {
        // Tirado & García de la Torre's fits hold from length / diameter 2 on.
        let aspect = rig.robot.length_m / rig.robot.diameter_m;
        if !(aspect.is_finite() && aspect >= 2.0) {
            return Err(ConfigError::new(format!(
                "scenario {}: [plant] physics.drag_shape = \"cylinder\" needs a capsule at least \
                 twice as long as it is wide; the rig {} [robot] length_m / diameter_m is {aspect:.2} \
                 (use \"paper\")",
                scenario.path.display(),
                rig.path.display()
            )));
        }
    }
    let flow: FlowMapChoice = scenario.section("flow")?;
    let steady_flow = flow
        .load(scenario)
        .config_context(format!("scenario {}: [flow] map", scenario.path.display()))?;
    let mut model = PlantModel::new(
        rig.twin_coil_field.clone(),
        rig.robot,
        &fluid,
        &rig.phantom,
        steady_flow,
        config.physics.clone(),
        scenario.run.seed,
    );
    model.saturation = rig.coils.iter().map(|c| c.saturation.clone()).collect();
    Ok(model)
}

/// What the `[plant]` table configures, validated, with the model built from the files it
/// needs (coil field maps, the `[flow]` map).
pub struct PlantSetup {
    pub config: PlantConfig,
    pub model: PlantModel,
    /// The rig the scenario names (camera, phantom).
    pub rig: std::sync::Arc<Rig>,
}

/// The twin's real camera: for every raw pixel, the canonical-view pixel it sees.
struct RawView {
    /// Raw frame size (width, height) in pixels.
    size: (usize, usize),
    /// The raw view's map, compiled for the canonical render's layout.
    sampler: fieldmaps::lens::BilinearSampler,
    /// The canonical render the raw frame is sampled from.
    scratch: std::cell::RefCell<Vec<u8>>,
}

impl RawView {
    /// The rig camera's raw view, when `[camera.calibration]` registers a real camera.
    fn of(rig: &Rig) -> anyhow::Result<Option<Self>> {
        let Some(calibration) = rig
            .camera
            .calibration
            .filter(|c| c.image_to_world_mm.is_some())
        else {
            return Ok(None);
        };
        let view = rig.camera.geometry;
        let map = calibration
            .raw_view_map(&view)
            .map_err(|e| anyhow::anyhow!("{}: [camera.calibration]: {e}", rig.path.display()))?;
        let channels = FRAME_CHANNELS as usize;
        let (width, height) = (view.width_px as usize, view.height_px as usize);
        Ok(Some(Self {
            size: (map.width, map.height),
            sampler: map.sampler(width, height, width * channels, channels),
            scratch: std::cell::RefCell::new(vec![0; width * height * channels]),
        }))
    }
}

/// Most loop frames between two camera exposures (`[plant.camera] exposure_period_frames`): a
/// 1 Hz camera under a 100 Hz loop.
pub const MAX_EXPOSURE_PERIOD_FRAMES: u32 = 100;

/// Parses and validates the `[plant]` table and loads the model's files. Every failure is a
/// configuration error naming the scenario, the field or the file.
pub fn prepare(scenario: &Scenario) -> Result<PlantSetup, ConfigError> {
    let config: PlantConfig = scenario.section("plant")?;
    let field = |name: &str| format!("scenario {}: [plant] {name}", scenario.path.display());
    if !(config.camera_noise_std.is_finite() && config.camera_noise_std >= 0.0) {
        return Err(ConfigError::new(format!(
            "{} must be >= 0, got {}",
            field("camera_noise_std"),
            config.camera_noise_std
        )));
    }
    let substep_ms = config.physics.substep_ms;
    if !(substep_ms.is_finite() && substep_ms > 0.0) {
        return Err(ConfigError::new(format!(
            "{} must be > 0, got {substep_ms}",
            field("physics.substep_ms")
        )));
    }
    if let Some(gap) = config.physics.floor_gap_m {
        if !(gap.is_finite() && gap > 0.0) {
            return Err(ConfigError::new(format!(
                "{} must be > 0 m (leave it out for free-stream drag), got {gap}",
                field("physics.floor_gap_m")
            )));
        }
    }
    if let Some(factor) = config.physics.floor_flow_factor {
        if !(factor.is_finite() && factor > 0.0) {
            return Err(ConfigError::new(format!(
                "{} must be > 0, got {factor}",
                field("physics.floor_flow_factor")
            )));
        }
    }
    let frame_ms = scenario.frame_period_s() * 1e3;
    if !(config.command_delay_ms.is_finite()
        && config.command_delay_ms >= 0.0
        && config.command_delay_ms < frame_ms)
    {
        return Err(ConfigError::new(format!(
            "{} must be >= 0 ms and below the frame period ({frame_ms} ms; whole frames of \
             delay are [plant.camera] latency_frames), got {}",
            field("command_delay_ms"),
            config.command_delay_ms
        )));
    }
    let exposure_period = config.camera.exposure_period_frames;
    if !(1..=MAX_EXPOSURE_PERIOD_FRAMES).contains(&exposure_period) {
        return Err(ConfigError::new(format!(
            "{} must be within 1..={MAX_EXPOSURE_PERIOD_FRAMES} loop frames (1: an exposure \
             every frame), got {exposure_period}",
            field("camera.exposure_period_frames")
        )));
    }
    let dropout = (config.camera.dropout_at_s, config.camera.dropout_s);
    if dropout.0.is_some_and(|t| !(t.is_finite() && t >= 0.0))
        || !(dropout.1.is_finite() && dropout.1 >= 0.0)
    {
        return Err(ConfigError::new(format!(
            "{} = {:?} and camera.dropout_s = {} must be run times >= 0 s",
            field("camera.dropout_at_s"),
            dropout.0,
            dropout.1
        )));
    }
    if let Some(start) = config.initial_position_mm {
        if start.iter().any(|v| !v.is_finite()) {
            return Err(ConfigError::new(format!(
                "{} = {start:?} must hold finite numbers",
                field("initial_position_mm")
            )));
        }
    }
    let rig = scenario.rig()?;
    if rig.camera.pixel_format != CameraPixelFormat::Rgb8 {
        return Err(ConfigError::new(format!(
            "{}: camera.pixel_format: the twin renders rgb8 frames only, got {:?} \
             (gray8 is for a real camera)",
            rig.path.display(),
            rig.camera.pixel_format
        )));
    }
    let faults = &config.board_faults;
    for (name, at) in [
        ("board_faults.estop_at_s", faults.estop_at_s),
        ("board_faults.reboot_at_s", faults.reboot_at_s),
        ("board_faults.sense_fault_at_s", faults.sense_fault_at_s),
    ] {
        if at.is_some_and(|t| !(t.is_finite() && t >= 0.0)) {
            return Err(ConfigError::new(format!(
                "{} must be a run time ≥ 0 s, got {at:?}",
                field(name)
            )));
        }
    }
    if faults.sense_fault_channel >= rig.coils.len() {
        return Err(ConfigError::new(format!(
            "{} = {}: the rig has {} coils (channels 0 to {})",
            field("board_faults.sense_fault_channel"),
            faults.sense_fault_channel,
            rig.coils.len(),
            rig.coils.len().saturating_sub(1)
        )));
    }
    if !(faults.sense_fault_gain.is_finite() && faults.sense_fault_gain >= 0.0) {
        return Err(ConfigError::new(format!(
            "{} must be ≥ 0, got {}",
            field("board_faults.sense_fault_gain"),
            faults.sense_fault_gain
        )));
    }
    let model = load_model(scenario, &rig, &config)?;
    Ok(PlantSetup { config, model, rig })
}

/// Validates the `[plant]` table and loads the files the model needs (what `--check` runs).
pub fn check_config(scenario: &Scenario) -> Result<(), ConfigError> {
    prepare(scenario).map(drop)
}

pub fn initial_state(scenario: &Scenario, config: &PlantConfig, model: &PlantModel) -> PlantState {
    let start_mm = config
        .initial_position_mm
        .unwrap_or(scenario.trajectory.waypoints_mm[0]);
    model.initial_state(
        Vector2::new(start_mm[0] * 1e-3, start_mm[1] * 1e-3),
        config.initial_heading_deg.to_radians(),
    )
}

// The twin's coil arrays are the contract's.

/// The board's channel currents as the twin's coil currents (missing channels drive nothing).
fn twin_currents(board_a: &[f64]) -> [f64; MAX_COILS] {
    let mut out = [0.0; MAX_COILS];
    for (twin, board) in out.iter_mut().zip(board_a) {
        *twin = *board;
    }
    out
}

fn truth_of(state: &PlantState, coil_count: usize, frame_seq: u64, misses: u64) -> PlantTruth {
    PlantTruth {
        frame_seq,
        sim_time_ns: millinav_kit::clock::secs_to_ns(state.time_s),
        position_m: [state.position_m.x, state.position_m.y],
        velocity_mps: [state.velocity_mps.x, state.velocity_mps.y],
        heading_rad: state.heading_rad,
        true_flow_mps: [state.last_true_flow_mps.x, state.last_true_flow_mps.y],
        applied_currents_a: state.coil_currents_a,
        magnetic_force_n: [state.last_magnetic_force_n.x, state.last_magnetic_force_n.y],
        lockstep_misses: misses,
        active_coils: coil_count as u32,
        wall_contact: Flag::from(state.wall_contact),
        reserved: [0; 3],
    }
}

fn log_truth(
    rec: &millinav_kit::rerun::RecordingStream,
    state: &PlantState,
    path: &mut Vec<[f32; 2]>,
) {
    let p = [
        (state.position_m.x * 1e3) as f32,
        (state.position_m.y * 1e3) as f32,
    ];
    path.push(p);
    let _ = rec.log(
        "world/robot/true_position",
        &millinav_kit::rerun::Points2D::new([p]).with_radii([1.4]),
    );
    recording::scalar(rec, "plant/true_x_mm", state.position_m.x * 1e3);
    recording::scalar(rec, "plant/true_y_mm", state.position_m.y * 1e3);
    recording::scalar(
        rec,
        "plant/wall_contact",
        f64::from(u8::from(state.wall_contact)),
    );
    recording::scalar(rec, "plant/contact_events", state.contact_events as f64);
    if path.len().is_multiple_of(25) {
        let _ = rec.log(
            "world/actual_path",
            &millinav_kit::rerun::LineStrips2D::new([path.clone()]),
        );
    }
}

/// How often a lockstep plant looks whether the board is armed before its first frame.
const BOARD_POLL: Duration = Duration::from_millis(5);

/// The plant process: publish frame k and its truth, wait for the command that answers it
/// (lockstep) or for the next frame time (realtime), step the physics, repeat until the run's
/// duration or SIGINT / SIGTERM.
pub fn run(rt: &mut Runtime, scenario: &Scenario, setup: PlantSetup) -> anyhow::Result<()> {
    let mut twin = Twin::start(rt, scenario, setup)?;
    let session = millinav_kit::in_session();
    tracing::info!(
        mode = ?scenario.run.mode,
        duration_s = scenario.run.duration_s,
        session,
        "plant running"
    );
    loop {
        if rt.shutdown_requested() {
            tracing::info!("plant: shutdown requested");
            break;
        }
        let run_time_ns = match scenario.run.mode {
            ClockMode::Lockstep => millinav_kit::clock::secs_to_ns(twin.state.time_s),
            ClockMode::Realtime => rt.env.run_clock_ns(),
        };
        if !twin.board_ready() {
            // Lockstep starts with the board armed: a command to a disarmed board is refused,
            // and the run would begin with a frame nobody can answer.
            keep_alive(&mut rt.heartbeat, &[&twin.frames, &twin.truth_out]);
            std::thread::sleep(BOARD_POLL);
            continue;
        }
        twin.show_frame(&rt.rec, run_time_ns)?;
        keep_alive(&mut rt.heartbeat, &[&twin.frames, &twin.truth_out]);
        // A session runs until the operator (or a signal) stops the set.
        if twin.state.time_s >= scenario.run.duration_s && !session {
            twin.log_completion();
            break;
        }
        twin.inject_requested_faults();
        twin.inject_scheduled_faults();
        // None until the chain answers once: frame 0 is shown again.
        if let Some(currents) = twin.await_command() {
            twin.advance(&currents);
        }
    }
    twin.stop()
}

/// The twin while it runs: the truth, the camera, the outputs and logs, and the emulated
/// Teensy the coils are driven through.
struct Twin<'s> {
    scenario: &'s Scenario,
    config: PlantConfig,
    model: PlantModel,
    state: PlantState,
    geometry: fieldmaps::phantom::ImageGeometry,
    camera: Camera,
    /// The rig's real camera (lens, pose, resolution) when it has one: the raw frame is the
    /// canonical render seen through it. None: the camera delivers the canonical view itself.
    lens: Option<RawView>,
    /// States of the last `latency_frames` + `exposure_period_frames` frames: frame k shows the
    /// state of the latest exposure at least L frames old ([`CameraConfig::shown_frames_ago`]).
    history: VecDeque<PlantState>,
    teensy: EmulatedTeensy,
    frames: FrameOutbox,
    truth_out: Outbox<PlantTruth>,
    truth_csv: TruthCsv,
    contacts: ContactLog,
    actual_path: Vec<[f32; 2]>,
    incarnation: u64,
    seq: u64,
    misses: u64,
    /// The chain has answered a frame once (lockstep).
    started: bool,
    /// Scheduled board faults already injected.
    fired: Vec<&'static str>,
    last_recorded: Option<u64>,
    wall_start: Instant,
    /// The coils' command before the current one: what they drive during the command delay.
    previous_command_a: [f64; MAX_COILS],
}

impl<'s> Twin<'s> {
    /// Builds the camera, starts the emulated Teensy, opens the outputs and the logs.
    fn start(rt: &mut Runtime, scenario: &'s Scenario, setup: PlantSetup) -> anyhow::Result<Self> {
        let PlantSetup { config, model, rig } = setup;
        let state = initial_state(scenario, &config, &model);
        let geometry = rig.camera.geometry;
        let mut render_rng = rng_streams::run_rng(scenario.run.seed, rng_streams::CAMERA_SETUP);
        let camera = Camera::with_config(
            &rig.phantom.mask,
            geometry,
            &mut render_rng,
            config.camera_noise_std,
            config.camera.clone(),
        );
        let kept_states = config.camera.history_len();
        let contacts = ContactLog::create(&rt.env.run_dir.join(CONTACTS_CSV))?;
        std::fs::create_dir_all(&rt.env.run_dir)?;
        let teensy = EmulatedTeensy::start(
            &rt.env
                .run_dir
                .join(millinav_teensy_protocol::EMULATED_PORT_LINK),
            &rt.env.run_dir.join(TeensyEventRow::FILE_NAME),
            deadlines::TEENSY_WATCHDOG,
            model.coil_count(),
        )
        .context("starting the emulated Teensy")?;
        // iceoryx2 takes over every catchable signal the first time it checks for termination;
        // let it do so first, then claim SIGUSR1/SIGUSR2 for link faults.
        let _ = rt.shutdown_requested();
        fault_signals::install().context("installing the link-fault signal handlers")?;
        let lens = RawView::of(&rig)?;
        let frame_bytes = match &lens {
            Some(view) => view.size.0 * view.size.1 * FRAME_CHANNELS as usize,
            None => {
                geometry.width_px as usize * geometry.height_px as usize * FRAME_CHANNELS as usize
            }
        };
        // Raw frames, as a camera delivers them; the camera service rectifies them.
        let frames = FrameOutbox::on(&rt.node, services::RAW_FRAME, frame_bytes)?;
        let truth_out = Outbox::<PlantTruth>::new(&rt.node, services::PLANT_TRUTH)?;
        let truth_csv = TruthCsv::create(&rt.env.run_dir.join(TRUTH_CSV), rt.env.incarnation)?;
        let _ = rt.rec.log_static(
            "world/canal",
            &millinav_kit::rerun::Points2D::new(
                rig.phantom
                    .mask
                    .outline_m(2)
                    .iter()
                    .map(|p| [(p.x * 1e3) as f32, (p.y * 1e3) as f32]),
            )
            .with_radii([0.15]),
        );
        Ok(Self {
            scenario,
            config,
            model,
            state,
            geometry,
            camera,
            lens,
            history: VecDeque::with_capacity(kept_states),
            teensy,
            frames,
            truth_out,
            truth_csv,
            contacts,
            actual_path: Vec::new(),
            incarnation: rt.env.incarnation,
            seq: 0,
            misses: 0,
            started: false,
            fired: Vec::new(),
            last_recorded: None,
            wall_start: Instant::now(),
            previous_command_a: [0.0; MAX_COILS],
        })
    }

    /// Publishes the current frame and its truth. Frame 0 is re-published until the chain
    /// answers: each frame is recorded once only, so the trace does not depend on how long the
    /// other processes took to start.
    fn show_frame(
        &mut self,
        rec: &millinav_kit::rerun::RecordingStream,
        run_time_ns: u64,
    ) -> anyhow::Result<()> {
        let fresh_frame = self.last_recorded != Some(self.seq);
        if fresh_frame {
            self.history.push_back(self.state.clone());
            while self.history.len() > self.config.camera.history_len() {
                self.history.pop_front();
            }
        }
        self.publish(run_time_ns)?;
        if fresh_frame {
            self.record_frame(rec)?;
        }
        Ok(())
    }

    /// Sends the camera frame (showing the latest exposure at least `latency_frames` ago) and
    /// the current truth.
    fn publish(&self, run_time_ns: u64) -> anyhow::Result<()> {
        let (seq, state) = (self.seq, &self.state);
        let ago = self.config.camera.shown_frames_ago(seq) as usize;
        let shown = self
            .history
            .len()
            .checked_sub(ago + 1)
            .and_then(|i| self.history.get(i))
            .unwrap_or(state);
        // A repeated exposure is the same image: its noise and lighting are the exposure's.
        let repeats = self.config.camera.frames_since_exposure(seq);
        let image_seq = seq - repeats;
        let image_time_s = state.time_s - repeats as f64 * self.scenario.frame_period_s();
        let geometry = &self.geometry;
        // Stamped like a camera whose driver timestamps the exposure: captured when the scene
        // looked like the shown state, grabbed now.
        let shown_age_ns = millinav_kit::clock::secs_to_ns(state.time_s - shown.time_s);
        let stamp = FrameStamp::new(
            seq,
            self.incarnation,
            run_time_ns.saturating_sub(shown_age_ns),
        )
        .grabbed_at(run_time_ns);
        let header = FrameHeader {
            stamp,
            width: geometry.width_px,
            height: geometry.height_px,
            stride: geometry.width_px * FRAME_CHANNELS,
            pixel_format: PixelFormat::Rgb8 as u32,
            ..Default::default()
        }
        .with_mapping(geometry.pixel_mapping());
        let mut rng = rng_streams::frame_noise_rng(self.scenario.run.seed, image_seq);
        let capsule = CapsulePose {
            position_m: shown.position_m,
            heading_rad: shown.heading_rad,
            length_m: self.model.robot.length_m,
            diameter_m: self.model.robot.diameter_m,
        };
        let camera = &self.camera;
        if self.config.camera.in_dropout(state.time_s) {
            // The camera is away: the truth goes on, no frame reaches the set.
            self.truth_out
                .send(truth_of(state, self.model.coil_count(), seq, self.misses))?;
            return Ok(());
        }
        match &self.lens {
            None => self
                .frames
                .send(header, camera.frame_background(image_seq), |rgb| {
                    camera.finish_frame(rgb, &capsule, image_seq, image_time_s, &mut rng, None)
                })?,
            Some(view) => {
                let mut canonical = view.scratch.borrow_mut();
                canonical.copy_from_slice(camera.frame_background(image_seq));
                camera.finish_frame(
                    &mut canonical,
                    &capsule,
                    image_seq,
                    image_time_s,
                    &mut rng,
                    None,
                );
                let channels = FRAME_CHANNELS as usize;
                let (w, h) = view.size;
                let raw_header = FrameHeader {
                    width: w as u32,
                    height: h as u32,
                    stride: (w * channels) as u32,
                    ..header
                };
                self.frames
                    .send_in_place(raw_header, w * h * channels, |out| {
                        view.sampler.remap(&canonical, out)
                    })?;
            }
        }
        self.truth_out
            .send(truth_of(state, self.model.coil_count(), seq, self.misses))?;
        Ok(())
    }

    /// Appends the frame to the truth and contact logs and the recording.
    fn record_frame(&mut self, rec: &millinav_kit::rerun::RecordingStream) -> anyhow::Result<()> {
        let (seq, state) = (self.seq, &self.state);
        self.last_recorded = Some(seq);
        self.truth_csv
            .append(&truth_of(state, self.model.coil_count(), seq, self.misses))?;
        self.contacts.record(seq, state)?;
        recording::set_time(rec, millinav_kit::clock::secs_to_ns(state.time_s), seq);
        if seq.is_multiple_of(self.config.log_every_frames.max(1)) {
            log_truth(rec, state, &mut self.actual_path);
        }
        Ok(())
    }

    fn log_completion(&self) {
        tracing::info!(
            frames = self.seq,
            misses = self.misses,
            contact_events = self.state.contact_events,
            contact_time_s = self.state.contact_time_s,
            wall_s = self.wall_start.elapsed().as_secs_f64(),
            "run complete"
        );
    }

    /// Applies the board faults due at this run time (each once).
    fn inject_scheduled_faults(&mut self) {
        let now_s = self.state.time_s;
        let schedule = self.config.board_faults.clone();
        let mut due = |at: Option<f64>, name: &'static str| {
            let fire = at.is_some_and(|t| now_s >= t) && !self.fired.contains(&name);
            if fire {
                self.fired.push(name);
                tracing::warn!(at_s = now_s, "board fault injected: {name}");
            }
            fire
        };
        let estop = due(schedule.estop_at_s, "estop");
        let reboot = due(schedule.reboot_at_s, "reboot");
        let sense = due(schedule.sense_fault_at_s, "sense_fault");
        if estop {
            self.teensy.press_estop();
        }
        if reboot {
            self.teensy.inject(LinkFault::Reboot);
        }
        if sense {
            self.teensy
                .fail_channel(schedule.sense_fault_channel, schedule.sense_fault_gain);
        }
    }

    /// Applies the link fault a signal asked for, if any.
    fn inject_requested_faults(&self) {
        let faults = &self.config.link_faults;
        match fault_signals::take() {
            Some(fault_signals::Requested::Unplug) => self
                .teensy
                .inject(LinkFault::Unplug(Duration::from_millis(faults.unplug_ms))),
            Some(fault_signals::Requested::Hang) => self
                .teensy
                .inject(LinkFault::Hang(Duration::from_millis(faults.hang_ms))),
            None => {}
        }
    }

    /// Whether the run may show its next frame: in lockstep the first frame waits until coilbus
    /// has configured and armed the board (the chain answers it only then); realtime runs on.
    fn board_ready(&self) -> bool {
        self.started
            || self.scenario.run.mode == ClockMode::Realtime
            || self.teensy.board_state() == BoardState::Armed
    }

    /// The coil currents to step with. Lockstep: the command answering this frame, or what the
    /// board drives when it missed its deadline; `None` until the chain has answered once (the
    /// run starts when every process is up, not when the plant happens to be). Realtime: what
    /// the board drives at the next frame time.
    fn await_command(&mut self) -> Option<[f64; MAX_COILS]> {
        match self.scenario.run.mode {
            ClockMode::Lockstep => {
                let (outputs, in_time) = self
                    .teensy
                    .wait_for_frame(self.seq, deadlines::LOCKSTEP_COMMAND);
                if !self.started {
                    if !in_time {
                        return None;
                    }
                    self.started = true;
                    tracing::info!(
                        after_s = self.wall_start.elapsed().as_secs_f64(),
                        "closed loop established"
                    );
                } else if !in_time {
                    self.misses += 1;
                    tracing::debug!(seq = self.seq, "lockstep: command missed its deadline");
                }
                Some(if in_time {
                    // The command that answered this frame, even if a safe-zero keep-alive
                    // raced in after it: the step must not depend on wall-clock timing.
                    twin_currents(outputs.last_command_currents())
                } else {
                    twin_currents(outputs.currents())
                })
            }
            ClockMode::Realtime => {
                let frame_period = self.scenario.frame_period_s();
                let next =
                    self.wall_start + Duration::from_secs_f64((self.seq + 1) as f64 * frame_period);
                if let Some(wait) = next.checked_duration_since(Instant::now()) {
                    std::thread::sleep(wait);
                }
                Some(twin_currents(self.teensy.outputs().currents()))
            }
        }
    }

    /// Steps the physics one frame period with `currents` commanded: in lockstep from
    /// `command_delay_ms` into the frame on (the previous command until then), in real time
    /// from the frame's start (the set's own delays are real).
    fn advance(&mut self, currents: &[f64; MAX_COILS]) {
        let delay_s = match self.scenario.run.mode {
            ClockMode::Lockstep => self.config.command_delay_ms * 1e-3,
            ClockMode::Realtime => 0.0,
        };
        self.model.step_with_command_delay(
            &mut self.state,
            &self.previous_command_a,
            currents,
            self.scenario.frame_period_s(),
            delay_s,
        );
        self.previous_command_a = *currents;
        self.seq += 1;
    }

    /// Stops the emulated Teensy and flushes the logs.
    fn stop(mut self) -> anyhow::Result<()> {
        self.teensy.stop();
        self.truth_csv.flush()?;
        self.contacts.flush()?;
        Ok(())
    }
}

/// File name of the ground-truth trace in a run directory.
pub const TRUTH_CSV: &str = <TruthRow as RunLogRow>::FILE_NAME;

/// Ground truth of every frame, for metrics after the run (never read by a controller).
pub struct TruthCsv {
    out: RunLogWriter<TruthRow>,
    /// The plant's incarnation: its frames' seqs start from 0 again after a restart.
    incarnation: u64,
}

impl TruthCsv {
    pub fn create(path: &std::path::Path, incarnation: u64) -> anyhow::Result<Self> {
        // Append: a restarted plant continues the same trace.
        let out = RunLogWriter::open_append(path)?;
        Ok(Self { out, incarnation })
    }

    pub fn append(&mut self, t: &PlantTruth) -> anyhow::Result<()> {
        let max_current = t
            .applied_currents_a
            .iter()
            .fold(0.0f64, |m, c| m.max(c.abs()));
        let sum_sq_current: f64 = t.applied_currents_a.iter().map(|c| c * c).sum();
        self.out.append(&TruthRow {
            frame_seq: t.frame_seq,
            frame_incarnation: self.incarnation,
            sim_time_s: t.sim_time_ns as f64 * 1e-9,
            x_m: t.position_m[0],
            y_m: t.position_m[1],
            vx_mps: t.velocity_mps[0],
            vy_mps: t.velocity_mps[1],
            heading_rad: t.heading_rad,
            flow_x_mps: t.true_flow_mps[0],
            flow_y_mps: t.true_flow_mps[1],
            wall_contact: t.wall_contact == Flag::TRUE,
            max_abs_current_a: max_current,
            lockstep_misses: t.lockstep_misses,
            sum_sq_current_a2: Some(sum_sq_current),
            coil_currents_a: Some(TruthRow::format_currents(
                &t.applied_currents_a[..(t.active_coils as usize).min(MAX_COILS)],
            )),
        })?;
        Ok(())
    }

    pub fn flush(&mut self) -> anyhow::Result<()> {
        self.out.flush()?;
        Ok(())
    }
}

/// File name of the wall-contact log in a run directory.
pub const CONTACTS_CSV: &str = <ContactRow as RunLogRow>::FILE_NAME;

/// Wall contacts as they start and end (one row per change), with the running onset count.
pub struct ContactLog {
    out: RunLogWriter<ContactRow>,
    touching: bool,
    reported_events: u64,
}

impl ContactLog {
    pub fn create(path: &std::path::Path) -> anyhow::Result<Self> {
        let out = RunLogWriter::open_append(path)?;
        Ok(Self {
            out,
            touching: false,
            reported_events: 0,
        })
    }

    /// Logs a `start` when a new contact began during the last step (also a brief one that
    /// ended within it) and an `end` when the capsule is free again.
    pub fn record(&mut self, frame_seq: u64, state: &PlantState) -> anyhow::Result<()> {
        let row = |event: &str| ContactRow {
            frame_seq,
            sim_time_s: state.time_s,
            event: event.to_owned(),
            x_m: state.position_m.x,
            y_m: state.position_m.y,
            contact_events: state.contact_events,
            contact_time_s: state.contact_time_s,
        };
        if state.contact_events > self.reported_events || (state.wall_contact && !self.touching) {
            self.out.append(&row("start"))?;
            if state.contact_events > self.reported_events + 1 {
                tracing::debug!(frame_seq, "several wall contacts within one frame");
            }
        } else if !state.wall_contact && self.touching {
            self.out.append(&row("end"))?;
        }
        self.reported_events = state.contact_events;
        self.touching = state.wall_contact;
        Ok(())
    }

    pub fn flush(&mut self) -> anyhow::Result<()> {
        self.out.flush()?;
        Ok(())
    }
}

/// Canal boundary pixels as world points (mm), for the recording's map layer.
#[cfg(test)]
mod tests {
    use super::*;
    use millinav_kit::scratch::ScratchDir;

    /// A scenario file in a directory of its own with the given `[plant]` and `[flow]` tables.
    fn scenario_with(name: &str, plant_table: &str, flow_table: &str) -> (Scenario, ScratchDir) {
        let dir = ScratchDir::new(&format!("millinav-plant-{name}")).unwrap();
        let text = format!(
            "[run]\nduration_s = 1.0\nrig = \"fieldmaps/rigs/paper.toml\"\n[fluid]\nviscosity_cp = 20.0\n\
             [trajectory]\nwaypoints_mm = [[0.0, 0.0], [5.0, 0.0]]\n\
             [plant]\n{plant_table}\n[flow]\n{flow_table}\n"
        );
        let path = dir.join("scenario.toml");
        (Scenario::parse(&text, &path).unwrap(), dir)
    }

    #[test]
    fn check_config_accepts_a_good_table_and_map() {
        let (scenario, dir) = scenario_with("good", "camera_noise_std = 2.0", "map = \"m.txt\"");
        FlowMap::zero().save(&dir.join("m.txt")).unwrap();
        check_config(&scenario).unwrap();
    }

    #[test]
    fn check_config_rejects_typos_and_missing_or_corrupt_maps() {
        let (scenario, _) = scenario_with("typo", "camera_noise = 2.0", "");
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(
            error.contains("[plant]") && error.contains("camera_noise"),
            "{error}"
        );

        let (scenario, _) = scenario_with("nested", "[plant.physics]\nsubstep = 1.0", "");
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(error.contains("substep"), "{error}");

        let (scenario, _) = scenario_with("missing", "", "map = \"absent.txt\"");
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(
            error.contains("[flow] map") && error.contains("absent.txt"),
            "{error}"
        );

        // In the scenario's own directory, where the map's relative path points.
        let (scenario, corrupt_dir) = scenario_with("corrupt", "", "map = \"corrupt.txt\"");
        let missing = check_config(&scenario).unwrap_err().to_string();
        std::fs::write(corrupt_dir.join("corrupt.txt"), "garbage\n").unwrap();
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(
            error.contains("[flow] map") && error.contains("corrupt.txt"),
            "{error}"
        );
        assert_ne!(error, missing, "a corrupt map reads as a missing one");

        let (scenario, _) = scenario_with("substep", "[plant.physics]\nsubstep_ms = 0.0", "");
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(error.contains("[plant] physics.substep_ms"), "{error}");

        // The command delay lives inside one frame (the scenario's frames are 10 ms).
        for bad in ["10.0", "-1.0", "nan"] {
            let (scenario, _) = scenario_with("delay", &format!("command_delay_ms = {bad}"), "");
            let error = check_config(&scenario).unwrap_err().to_string();
            assert!(
                error.contains("[plant] command_delay_ms") && error.contains("latency_frames"),
                "{bad}: {error}"
            );
        }
        let (scenario, _) = scenario_with("delay_ok", "command_delay_ms = 6.0", "");
        check_config(&scenario).unwrap();

        for bad in ["0", "101"] {
            let (scenario, _) = scenario_with(
                "exposure",
                &format!("[plant.camera]\nexposure_period_frames = {bad}"),
                "",
            );
            let error = check_config(&scenario).unwrap_err().to_string();
            assert!(
                error.contains("[plant] camera.exposure_period_frames") && error.contains(bad),
                "{bad}: {error}"
            );
        }
        let (scenario, _) = scenario_with(
            "exposure_ok",
            "[plant.camera]\nexposure_period_frames = 10",
            "",
        );
        check_config(&scenario).unwrap();
    }

    /// A 10 Hz camera under a 100 Hz loop with 3 frames of latency: each frame shows the
    /// latest exposure (frames 0, 10, 20, … of the captured states) at least 3 frames old.
    #[test]
    fn frames_show_the_latest_exposure_old_enough() {
        let camera = CameraConfig {
            latency_frames: 3,
            exposure_period_frames: 10,
            ..CameraConfig::default()
        };
        let shown = |seq: u64| seq - camera.shown_frames_ago(seq);
        assert_eq!((0..=3).map(shown).collect::<Vec<_>>(), [0, 0, 0, 0]);
        assert_eq!(shown(12), 0);
        assert_eq!(shown(13), 10);
        assert_eq!(shown(22), 10);
        assert_eq!(shown(23), 20);
        assert!((0..500).all(|seq| camera.shown_frames_ago(seq) < camera.history_len() as u64));
        // One exposure a frame: the latency alone, as before the exposure period existed.
        let every_frame = CameraConfig {
            latency_frames: 3,
            ..CameraConfig::default()
        };
        assert_eq!(every_frame.history_len(), 4);
        assert!((3..50).all(|seq| every_frame.shown_frames_ago(seq) == 3));
        assert_eq!(every_frame.shown_frames_ago(1), 1);
    }
}
