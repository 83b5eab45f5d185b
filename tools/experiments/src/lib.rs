//! The paper's experiment matrix on the digital twin.
//!
//! Two modes share the scenario, the metrics and the reports:
//! - `fast`: one process, the same libraries as the services (plant model, flow estimator,
//!   control loop, coilbus safety logic and its mA wire quantization), with the camera and
//!   vision replaced by ground truth plus Gaussian localization noise (σ from vision-eval);
//! - `process`: the real process set in lockstep through `millinav run`, metrics from truth.csv.

pub mod campaign;
pub mod keys;
pub mod noise_floor;
pub mod report;
pub mod robustness;
pub mod runner;
pub mod slurm;
pub mod slurm_settings;

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{bail, Context};
use fieldmaps::rigfile::Rig;
use millinav_coilbus::protocol::{amps_to_ma, ma_to_amps};
use millinav_coilbus::CoilBus;
use millinav_control::reference::Reference;
use millinav_kit::clock::secs_to_ns;
use millinav_kit::runlog::{self, RunLogRow, TruthRow};
use millinav_kit::scenario::Scenario;
use millinav_kit::summary::{tracking, ErrorSample};
use millinav_plant::PlantConfig;
use nalgebra::Vector2;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use shm_schemas::{deadlines, Flag, FrameStamp, Pose, PoseSource, MAX_COILS};

/// The flow of a cell: still fluid, or one of the rig's `[[phantom.flow]]` conditions by its
/// pump flow rate (at the cell's viscosity). Files carry its short form (`static`, `q180`).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(into = "String", try_from = "String")]
pub enum FlowSetting {
    Static,
    /// Pump flow rate, mL/min (whole numbers).
    Flow(u32),
}

impl FlowSetting {
    /// The paper's lower pump setting: 180 mL/min, peak ≈ 7 cm/s.
    pub const Q180: FlowSetting = FlowSetting::Flow(180);
    /// The paper's higher pump setting: 250 mL/min, peak ≈ 10 cm/s.
    pub const Q250: FlowSetting = FlowSetting::Flow(250);

    /// How tables and figure names call it. The paper names its two pump settings by their
    /// peak speed; other rigs' settings go by their flow rate.
    pub fn label(self) -> String {
        match self {
            Self::Static => "static".into(),
            Self::Q180 => "7 cm/s".into(),
            Self::Q250 => "10 cm/s".into(),
            Self::Flow(q) => format!("{q} mL/min"),
        }
    }

    /// Short form in cell names: `static`, `q180`.
    pub fn short(self) -> String {
        match self {
            Self::Static => "static".into(),
            Self::Flow(q) => format!("q{q}"),
        }
    }

    /// Parses [`Self::short`]'s form.
    pub fn from_short(text: &str) -> Option<Self> {
        match text {
            "static" => Some(Self::Static),
            _ => text.strip_prefix('q')?.parse().ok().map(Self::Flow),
        }
    }

    /// The rig's map for this setting at `viscosity_cp`, if the fluid moves; an error names
    /// the rig when it has no such condition.
    pub fn map(self, viscosity_cp: f64, rig: &Rig) -> anyhow::Result<Option<PathBuf>> {
        let Self::Flow(q) = self else {
            return Ok(None);
        };
        rig.phantom
            .flow_conditions
            .iter()
            .find(|c| {
                (c.flow_ml_min - f64::from(q)).abs() < 0.5
                    && (c.viscosity_pa_s * 1e3 - viscosity_cp).abs() < 0.05
            })
            .map(|c| Some(c.map_path.clone()))
            .with_context(|| {
                format!(
                    "{}: no [[phantom.flow]] condition at {q} mL/min and {viscosity_cp} cP",
                    rig.path.display()
                )
            })
    }
}

impl From<FlowSetting> for String {
    fn from(flow: FlowSetting) -> Self {
        flow.short()
    }
}

impl TryFrom<String> for FlowSetting {
    type Error = String;
    fn try_from(text: String) -> Result<Self, Self::Error> {
        Self::from_short(&text)
            .ok_or_else(|| format!("flow {text:?}: expected \"static\" or q<mL/min>, e.g. q180"))
    }
}

/// One cell of the matrix.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Cell {
    pub viscosity_cp: f64,
    pub flow: FlowSetting,
    /// Scenario name of the controller (pid, mpc, smc-dob, smc, smc-dob-auto).
    pub controller: String,
    pub seed: u64,
}

impl Cell {
    pub fn name(&self) -> String {
        format!(
            "{}cp_{}_{}_s{}",
            self.viscosity_cp,
            self.flow.short(),
            self.controller,
            self.seed
        )
    }
}

/// The matrix of a rig (the paper's on the paper rig, plus the auto-scheduled SMC-DOB when
/// `beyond` is set): for every viscosity among the rig's flow conditions (highest first), still
/// fluid and each condition at that viscosity (slowest first), every controller, `trials` seeds.
pub fn rig_matrix(rig: &Rig, trials: u64, beyond: bool) -> Vec<Cell> {
    let mut controllers = vec!["pid", "mpc", "smc-dob", "smc"];
    if beyond {
        controllers.push("smc-dob-auto");
        controllers.push("smc-auto");
    }
    let mut viscosities: Vec<f64> = Vec::new();
    for c in &rig.phantom.flow_conditions {
        let cp = (c.viscosity_pa_s * 1e4).round() / 10.0;
        if !viscosities.contains(&cp) {
            viscosities.push(cp);
        }
    }
    viscosities.sort_by(|a, b| b.total_cmp(a));
    let mut cells = Vec::new();
    for viscosity_cp in viscosities {
        let mut flows: Vec<FlowSetting> = rig
            .phantom
            .flow_conditions
            .iter()
            .filter(|c| ((c.viscosity_pa_s * 1e4).round() / 10.0 - viscosity_cp).abs() < 1e-9)
            .map(|c| FlowSetting::Flow(c.flow_ml_min.round() as u32))
            .collect();
        flows.sort();
        flows.dedup();
        for flow in std::iter::once(FlowSetting::Static).chain(flows) {
            for controller in &controllers {
                for seed in 1..=trials {
                    cells.push(Cell {
                        viscosity_cp,
                        flow,
                        controller: controller.to_string(),
                        seed,
                    });
                }
            }
        }
    }
    cells
}

/// Sets `path` (tables, then a key) in a scenario's TOML, creating the tables on the way.
pub fn set_in_table(
    doc: &mut toml::Table,
    path: &[&str],
    value: toml::Value,
) -> anyhow::Result<()> {
    let (key, tables) = path.split_last().context("empty key path")?;
    table_at(doc, tables)?.insert(key.to_string(), value);
    Ok(())
}

/// The table at `tables` in a scenario's TOML, created (with those above it) where missing.
pub fn table_at<'a>(
    doc: &'a mut toml::Table,
    tables: &[&str],
) -> anyhow::Result<&'a mut toml::Table> {
    let mut table = doc;
    for name in tables {
        table = table
            .entry(name.to_string())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()))
            .as_table_mut()
            .with_context(|| format!("scenario: {name} is not a table"))?;
    }
    Ok(table)
}

/// Most whole frames of camera latency a matrix may ask for (the plant keeps that many past
/// states).
pub const MAX_LATENCY_FRAMES: i64 = 100;

/// Adds `delay_ms` from capture to the coils to a scenario's TOML as the lockstep twin takes a
/// real pipeline's delay: whole frame periods become camera latency (`[plant.camera]
/// latency_frames`: the frame shows an older state, which control measures from its stamps) and
/// the rest a delay inside the frame (`[plant] command_delay_ms`: the previous command drives
/// until then), which control is told as a lab would measure it (`[control.latency]
/// unstamped_delay_ms`). A delay inside the frame that reaches a frame period carries into one
/// more frame of latency. So any delay is possible at any loop rate: 50 ms at 10 Hz is half a
/// frame, 35 ms at 100 Hz three frames and 5 ms.
pub fn add_capture_to_coils_delay(
    doc: &mut toml::Table,
    delay_ms: f64,
    frame_period_ms: f64,
) -> anyhow::Result<()> {
    anyhow::ensure!(
        delay_ms.is_finite() && delay_ms >= 0.0,
        "a delay from capture to the coils must be >= 0 ms, got {delay_ms}"
    );
    anyhow::ensure!(
        frame_period_ms.is_finite() && frame_period_ms > 0.0,
        "the frame period must be > 0 ms, got {frame_period_ms}"
    );
    let frames_before = keys::CAMERA_LATENCY_FRAMES.number(doc).unwrap_or(0.0);
    let in_frame_before = keys::COMMAND_DELAY_MS.number(doc).unwrap_or(0.0);
    let told_before = keys::UNSTAMPED_DELAY_MS.number(doc).unwrap_or(0.0);
    // A hair of tolerance so that 100 ms at a 10 ms frame is ten frames, not nine and 10 ms.
    let tolerance_ms = 1e-9 * frame_period_ms.max(1.0);
    let in_frame_total = in_frame_before + delay_ms;
    let carried = ((in_frame_total + tolerance_ms) / frame_period_ms).floor();
    let frames = frames_before + carried;
    let in_frame = (in_frame_total - carried * frame_period_ms).max(0.0);
    let in_frame = if in_frame < tolerance_ms {
        0.0
    } else {
        in_frame
    };
    anyhow::ensure!(
        frames <= MAX_LATENCY_FRAMES as f64,
        "a delay from capture to the coils of {:.1} ms is more than {MAX_LATENCY_FRAMES} frame \
         periods ({frame_period_ms} ms)",
        frames_before * frame_period_ms + in_frame_before + delay_ms
    );
    keys::CAMERA_LATENCY_FRAMES.set(doc, frames as i64)?;
    if in_frame != in_frame_before {
        keys::COMMAND_DELAY_MS.set(doc, in_frame)?;
        // Control is told what the stamps cannot show: the change inside the frame.
        let told = (told_before + in_frame - in_frame_before).max(0.0);
        keys::UNSTAMPED_DELAY_MS.set(doc, told)?;
    }
    Ok(())
}

/// Sections of a scenario that `--set` may change: the services' tables. The run, fluid and
/// trajectory tables are the matrix's own (flags and cells set them).
pub const SETTABLE_SECTIONS: [&str; 7] = millinav_kit::scenario::KNOWN_SECTIONS;

/// Applies one `--set KEY=VALUE` to a scenario's service tables: KEY a dotted path such as
/// `plant.physics.floor_gap_m`, VALUE a TOML value (`3e-6`, `true`, `"classical"`, `[1, 2]`).
/// A key outside the services' tables or a value that is not TOML is an error naming it;
/// whether the key exists is for the services' own checks, which name the field.
pub fn apply_setting(sections: &mut toml::Table, setting: &str) -> anyhow::Result<()> {
    let (key, value) = setting
        .split_once('=')
        .with_context(|| format!("--set {setting:?}: expected KEY=VALUE"))?;
    let path: Vec<&str> = key.trim().split('.').collect();
    anyhow::ensure!(
        path.len() >= 2 && path.iter().all(|p| !p.is_empty()),
        "--set {setting:?}: KEY must be a dotted path into a table, e.g. plant.physics.floor_gap_m"
    );
    anyhow::ensure!(
        SETTABLE_SECTIONS.contains(&path[0]),
        "--set {setting:?}: {:?} is not a service table (one of {}); the run, fluid and \
         trajectory tables come from the flags and the matrix",
        path[0],
        SETTABLE_SECTIONS.join(", ")
    );
    let parsed: toml::Table = toml::from_str(&format!("value = {}", value.trim()))
        .with_context(|| format!("--set {setting:?}: the value is not a TOML value"))?;
    let value = parsed
        .get("value")
        .cloned()
        .with_context(|| format!("--set {setting:?}: no value"))?;
    set_in_table(sections, &path, value)
}

/// A scenario as a TOML document: its run, fluid and trajectory tables and every other section.
pub fn scenario_document(scenario: &Scenario) -> anyhow::Result<toml::Table> {
    let mut doc: toml::Table = toml::Table::new();
    doc.insert("run".into(), toml::Table::try_from(&scenario.run)?.into());
    doc.insert(
        "fluid".into(),
        toml::Table::try_from(&scenario.fluid)?.into(),
    );
    doc.insert(
        "trajectory".into(),
        toml::Table::try_from(&scenario.trajectory)?.into(),
    );
    for (key, value) in &scenario.sections {
        doc.insert(key.clone(), value.clone());
    }
    Ok(doc)
}

/// The scenario text of a cell: the base scenario's run, trajectory, plant and vision tables
/// with the cell's fluid, flow map, controller and seed.
pub fn cell_scenario(base: &Scenario, cell: &Cell) -> anyhow::Result<String> {
    let rig = base.rig()?;
    let mut doc = scenario_document(base)?;
    keys::SEED.set(&mut doc, cell.seed as i64)?;
    keys::VISCOSITY_CP.set(&mut doc, cell.viscosity_cp)?;
    keys::FLOW_MAP.remove(&mut doc)?;
    if let Some(map) = cell.flow.map(cell.viscosity_cp, &rig)? {
        keys::FLOW_MAP.set(&mut doc, map.to_string_lossy().into_owned())?;
    }
    keys::CONTROLLER.set(&mut doc, cell.controller.clone())?;
    match cell.controller.as_str() {
        "smc-dob-auto" | "smc-auto" => {
            keys::CONSTRAINED_ALLOCATION.set(&mut doc, true)?;
            keys::USE_ALL_COILS.set(&mut doc, true)?;
            // Beyond the paper too: the orientation field turns for force at the coil limits
            // and, where the fluid moves, to pull the magnet along its axis; the coil gains
            // are corrected online from the heading.
            keys::FIELD_HEADING_TURN_DEG.set_if_absent(&mut doc, 45.0)?;
            keys::FIELD_FOLLOWS_FORCE.set_if_absent(&mut doc, true)?;
            keys::GAIN_ESTIMATION_ENABLED.set_if_absent(&mut doc, true)?;
        }
        // The paper ran its SMC with a second, fixed gain set whenever the fluid moved.
        "smc-dob" | "smc" if cell.flow != FlowSetting::Static => {
            let paper = millinav_control::controllers::SmcGains::default();
            // The base scenario's flow gains where it gives them, else the paper's.
            for (gain, flow_gain, paper) in [
                (keys::SMC_K4_N, keys::SMC_FLOW_K4_N, paper.flow_k4_n),
                (keys::SMC_ETA_S, keys::SMC_FLOW_ETA_S, paper.flow_eta_s),
                (keys::SMC_PHI_M, keys::SMC_FLOW_PHI_M, paper.flow_phi_m),
            ] {
                let value = flow_gain.number(&doc).unwrap_or(paper);
                gain.set(&mut doc, value)?;
            }
        }
        _ => {}
    }
    Ok(toml::to_string(&doc)?)
}

/// One frame of a run's trace.
#[derive(Debug, Clone, Copy)]
pub struct TraceRow {
    pub time_s: f64,
    pub position_m: Vector2<f64>,
    pub wall_contact: bool,
    pub max_abs_current_a: f64,
    /// Σ I² over the coils (A²), for energy.
    pub sum_sq_current_a2: f64,
    /// Current in each coil (A; rest 0), when the trace has them.
    pub coil_currents_a: Option<[f64; MAX_COILS]>,
    /// The capsule's velocity, magnet heading (rad from +x) and the true flow at it: what the
    /// plant knew, for tracing a run (zero where the source trace lacks them).
    pub motion: TraceMotion,
}

/// The truth beyond position that a trace carries (see [`TraceRow::motion`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TraceMotion {
    pub velocity_mps: Vector2<f64>,
    pub heading_rad: f64,
    pub flow_mps: Vector2<f64>,
}

/// Localization noise of the fast mode (per axis), from vision-eval's centroid error.
pub const FAST_POSE_NOISE_M: f64 = 2.0e-5;

/// Heading noise of the fast mode (rad, ≈ 0.3°): vision's heading is the tip–tail axis, its
/// keypoints ≈ 0.02 mm off each (vision-eval, p50–p95 0.011–0.027 mm) about 6 mm apart, so
/// √2 · 0.02 / 6 ≈ 0.005 rad. Drawn on a stream of its own, so the position noise of a seed
/// is what it was before headings were noisy.
pub const FAST_HEADING_NOISE_RAD: f64 = 5.0e-3;

/// Runs a scenario in one process with the services' own libraries.
pub fn fast_run(scenario: &Scenario) -> anyhow::Result<Vec<TraceRow>> {
    let plant_config: PlantConfig = scenario.section("plant")?;
    let model = millinav_plant::build_model(scenario, &plant_config)?;
    let mut state = millinav_plant::initial_state(scenario, &plant_config, &model);
    let mut control = millinav_control::build_loop(scenario, 0)?;
    let flow = millinav_flow::load_estimator(scenario)?;
    let coilbus = millinav_coilbus::prepare(scenario)?;
    let mut bus = CoilBus::new(coilbus.limits, deadlines::COMMAND, coilbus.coil_count);
    let mut rng = ChaCha8Rng::seed_from_u64(scenario.run.seed ^ 0x7669_7369_6f6e);
    let noise = Normal::new(0.0, FAST_POSE_NOISE_M)?;
    let mut heading_rng = ChaCha8Rng::seed_from_u64(scenario.run.seed ^ 0x6865_6164);
    let heading_noise = Normal::new(0.0, FAST_HEADING_NOISE_RAD)?;
    let dt = scenario.frame_period_s();
    let frames = (scenario.run.duration_s / dt).ceil() as u64;
    let mut applied = [0.0; MAX_COILS];
    // What the coils drive during the command delay: the command before the current one.
    let mut previous_applied = [0.0; MAX_COILS];
    let command_delay_s = plant_config.command_delay_ms * 1e-3;
    let mut trace = Vec::with_capacity(frames as usize + 1);
    let now = std::time::Instant::now();
    // The camera's latency and exposure period as the plant applies them: frame k shows the
    // state of the latest exposure at least L frames old, captured at that state's time and
    // grabbed at frame k's; a repeated exposure is the same measurement.
    let camera = &plant_config.camera;
    let mut seen: VecDeque<(Vector2<f64>, f64, f64)> =
        VecDeque::with_capacity(camera.history_len());
    let mut measured_exposure: Option<(Vector2<f64>, f64)> = None;
    for seq in 0..=frames {
        trace.push(TraceRow {
            time_s: state.time_s,
            position_m: state.position_m,
            wall_contact: state.wall_contact,
            max_abs_current_a: state
                .coil_currents_a
                .iter()
                .fold(0.0, |m, c| m.max(c.abs())),
            sum_sq_current_a2: state.coil_currents_a.iter().map(|c| c * c).sum(),
            coil_currents_a: Some(state.coil_currents_a),
            motion: TraceMotion {
                velocity_mps: state.velocity_mps,
                heading_rad: state.heading_rad,
                flow_mps: state.last_true_flow_mps,
            },
        });
        if seq == frames {
            break;
        }
        seen.push_back((state.position_m, state.heading_rad, state.time_s));
        while seen.len() > camera.history_len() {
            seen.pop_front();
        }
        let ago = camera.shown_frames_ago(seq) as usize;
        let (seen_position, seen_heading, seen_time_s) = seen[seen.len() - 1 - ago];
        let (measured, heading) = match measured_exposure {
            Some(exposure) if camera.frames_since_exposure(seq) > 0 => exposure,
            _ => {
                let measured =
                    seen_position + Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng));
                let heading = seen_heading + heading_noise.sample(&mut heading_rng);
                *measured_exposure.insert((measured, heading))
            }
        };
        let pose = Pose {
            stamp: FrameStamp::new(seq, 0, secs_to_ns(seen_time_s))
                .grabbed_at(secs_to_ns(state.time_s)),
            position_m: [measured.x, measured.y],
            heading_rad: heading,
            confidence: 1.0,
            valid: Flag::TRUE,
            source: PoseSource::Unet as u32,
            ..Default::default()
        };
        let estimate = flow.estimate(&pose);
        let decision = control.step(&pose, Some(&estimate));
        if let Some(out) = bus.on_command(&decision.command) {
            bus.applied(&decision.command, &out, now);
            // The wire carries milliamperes.
            for (coil, current) in applied.iter_mut().zip(out.currents()) {
                *coil = ma_to_amps(amps_to_ma(*current));
            }
        }
        model.step_with_command_delay(&mut state, &previous_applied, &applied, dt, command_delay_s);
        previous_applied = applied;
    }
    Ok(trace)
}

/// A process-mode run was stopped by SIGTERM (Slurm's time limit, preemption, `scancel`) before
/// it finished; it has no result.
#[derive(Debug, Clone, Copy)]
pub struct Terminated;

impl std::fmt::Display for Terminated {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "terminated by SIGTERM (Slurm time limit, preemption or scancel) before the run ended"
        )
    }
}

impl std::error::Error for Terminated {}

/// How a process-mode run keeps to itself: the tag that starts its iceoryx2 prefix (one per
/// campaign, so a later task can find what a killed one left), and the flag that asks it to
/// stop.
#[derive(Clone, Copy)]
pub struct RunIsolation<'a> {
    pub iox_tag: &'a str,
    pub terminated: &'a AtomicBool,
}

/// The iceoryx2 file prefix of run `index` of process `pid` under `tag`: `<tag>_<pid>_<index>_`.
fn iox_prefix(tag: &str, pid: u32, index: u64) -> String {
    format!("{tag}-{pid}-{index}_")
}

/// Removes the shared-memory files and iceoryx2 roots that runs tagged `tag` left behind when
/// their process is gone (a task killed with SIGKILL cannot clean up after itself); returns
/// how many it removed.
pub fn sweep_stale_iox(tag: &str) -> usize {
    let alive = |pid: &str| Path::new("/proc").join(pid).exists();
    let owner = |name: &str| -> Option<String> {
        let rest = name.strip_prefix(tag)?.strip_prefix(['_', '-'])?;
        let pid: String = rest.chars().take_while(char::is_ascii_digit).collect();
        (!pid.is_empty()).then_some(pid)
    };
    let mut removed = 0;
    for dir in [PathBuf::from("/dev/shm"), std::env::temp_dir()] {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for entry in entries.flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            if owner(&name).is_some_and(|pid| !alive(&pid)) {
                let path = entry.path();
                let gone = if path.is_dir() {
                    std::fs::remove_dir_all(&path)
                } else {
                    std::fs::remove_file(&path)
                };
                removed += usize::from(gone.is_ok());
            }
        }
    }
    removed
}

/// Removes every shared-memory file whose name starts with `prefix` (iceoryx2 keeps its global
/// node counter there even after a clean shutdown).
fn remove_shm_with_prefix(prefix: &str) {
    if let Ok(entries) = std::fs::read_dir("/dev/shm") {
        for entry in entries.flatten() {
            if entry.file_name().to_string_lossy().starts_with(prefix) {
                let _ = std::fs::remove_file(entry.path());
            }
        }
    }
}

/// How long the supervisor gets after SIGTERM to shut the set down safe-state first.
const SUPERVISOR_SHUTDOWN: std::time::Duration = std::time::Duration::from_secs(20);

/// Runs a scenario through the real process set (`millinav run`, lockstep) and reads back
/// the plant's ground truth ([`process_run_isolated`] under the tag `mx`, never stopped).
pub fn process_run(
    scenario_text: &str,
    bin_dir: &Path,
    work_dir: &Path,
    name: &str,
) -> anyhow::Result<Vec<TraceRow>> {
    let never = AtomicBool::new(false);
    process_run_isolated(
        scenario_text,
        bin_dir,
        work_dir,
        name,
        RunIsolation {
            iox_tag: "mx",
            terminated: &never,
        },
    )
}

/// Runs a scenario through the real process set (`millinav run`, lockstep) and reads back
/// the plant's ground truth. The run's iceoryx2 prefix and root are its own, and both are
/// removed when it ends, however it ends; when `isolation.terminated` is raised the set is shut
/// down and the run fails with [`Terminated`].
pub fn process_run_isolated(
    scenario_text: &str,
    bin_dir: &Path,
    work_dir: &Path,
    name: &str,
    isolation: RunIsolation<'_>,
) -> anyhow::Result<Vec<TraceRow>> {
    let dir = work_dir.join(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir)?;
    let scenario_path = dir.join("scenario.toml");
    std::fs::write(&scenario_path, scenario_text)?;
    let run_dir = dir.join("run");
    // iceoryx2 keeps Unix-socket paths under its root, and those are limited to 108 bytes:
    // keep the root and prefix short and unique per run instead of nesting them in `dir`.
    static RUNS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let run_index = RUNS.fetch_add(1, Ordering::Relaxed);
    let pid = std::process::id();
    let prefix = iox_prefix(isolation.iox_tag, pid, run_index);
    let iox_root = std::env::temp_dir().join(format!("{}-{pid}-{run_index}", isolation.iox_tag));
    let mut child = Command::new(bin_dir.join("millinav"))
        .arg("run")
        .arg(&scenario_path)
        .arg("--run-dir")
        .arg(&run_dir)
        .args(["--viewer", "none", "--iox-prefix", &prefix])
        .arg("--iox-root")
        .arg(&iox_root)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.join("supervisor.log"))?)
        .spawn()
        .context("running millinav")?;
    let ended = wait_or_terminate(&mut child, isolation.terminated);
    let _ = std::fs::remove_dir_all(&iox_root);
    remove_shm_with_prefix(&prefix);
    let status = ended?;
    if isolation.terminated.load(Ordering::Relaxed) {
        return Err(Terminated.into());
    }
    if !status.success() {
        bail!(
            "millinav run failed ({status}); see {}",
            dir.join("supervisor.log").display()
        );
    }
    read_truth(&run_dir.join(TruthRow::FILE_NAME))
}

/// Waits for the supervisor; once `terminated` is raised, asks it to shut down (SIGTERM) and
/// kills it if it has not within [`SUPERVISOR_SHUTDOWN`].
fn wait_or_terminate(
    child: &mut std::process::Child,
    terminated: &AtomicBool,
) -> anyhow::Result<std::process::ExitStatus> {
    use nix::sys::signal::{kill, Signal};
    use nix::unistd::Pid;
    let poll = std::time::Duration::from_millis(50);
    let mut asked_at: Option<std::time::Instant> = None;
    loop {
        if let Some(status) = child.try_wait()? {
            return Ok(status);
        }
        if terminated.load(Ordering::Relaxed) {
            let pid = Pid::from_raw(child.id() as i32);
            match asked_at {
                None => {
                    let _ = kill(pid, Signal::SIGTERM);
                    asked_at = Some(std::time::Instant::now());
                }
                Some(at) if at.elapsed() > SUPERVISOR_SHUTDOWN => {
                    let _ = child.kill();
                    return Ok(child.wait()?);
                }
                Some(_) => {}
            }
        }
        std::thread::sleep(poll);
    }
}

/// The trace of an earlier `process_run` of the scenario `scenario_text` in `dir`; an error if
/// it is missing or was run from a different scenario.
pub fn recorded_run(scenario_text: &str, dir: &Path) -> anyhow::Result<Vec<TraceRow>> {
    let recorded = dir.join("scenario.toml");
    let text = std::fs::read_to_string(&recorded)
        .with_context(|| format!("no recorded run: reading {}", recorded.display()))?;
    if text != scenario_text {
        bail!(
            "{} was run from another scenario than this cell's; run it again without --reuse-runs",
            recorded.display()
        );
    }
    read_truth(&dir.join("run").join(TruthRow::FILE_NAME))
}

/// Reads a plant truth.csv into a trace (one row per frame; republished frames dropped).
pub fn read_truth(path: &Path) -> anyhow::Result<Vec<TraceRow>> {
    let rows: Vec<TruthRow> = runlog::read_rows(path)?;
    let mut trace = Vec::with_capacity(rows.len());
    let mut last_seq = None;
    for (line, row) in rows.into_iter().enumerate() {
        if last_seq == Some(row.frame_seq) {
            continue;
        }
        last_seq = Some(row.frame_seq);
        let coil_currents_a = match row.currents() {
            None => None,
            Some(Ok(values)) if values.len() <= MAX_COILS => {
                let mut currents = [0.0; MAX_COILS];
                currents[..values.len()].copy_from_slice(&values);
                Some(currents)
            }
            Some(Ok(values)) => bail!(
                "{}: row {}: coil_currents_a has {} values, at most {MAX_COILS} allowed",
                path.display(),
                line + 1,
                values.len()
            ),
            Some(Err(e)) => bail!("{}: row {}: coil_currents_a: {e}", path.display(), line + 1),
        };
        trace.push(TraceRow {
            time_s: row.sim_time_s,
            position_m: Vector2::new(row.x_m, row.y_m),
            wall_contact: row.wall_contact,
            max_abs_current_a: row.max_abs_current_a,
            // Older traces lack the Σ I² column: bound the sum by the largest current on every
            // coil a command can carry.
            sum_sq_current_a2: row
                .sum_sq_current_a2
                .unwrap_or(row.max_abs_current_a * row.max_abs_current_a * MAX_COILS as f64),
            coil_currents_a,
            motion: TraceMotion {
                velocity_mps: Vector2::new(row.vx_mps, row.vy_mps),
                heading_rad: row.heading_rad,
                flow_mps: Vector2::new(row.flow_x_mps, row.flow_y_mps),
            },
        });
    }
    Ok(trace)
}

/// Metrics of one run against its reference.
#[derive(Debug, Clone, Copy, Default, serde::Serialize, serde::Deserialize)]
pub struct Metrics {
    pub rmse_mm: f64,
    pub p95_mm: f64,
    pub max_mm: f64,
    pub completed: bool,
    pub wall_contact_frames: usize,
    pub peak_current_a: f64,
    /// Joule heat in the coils, Σ I² R dt (J).
    pub energy_j: f64,
    /// 95th percentile over frames of the largest per-coil current change in one frame (A);
    /// NaN when the trace lacks per-coil currents.
    pub current_step_p95_a: f64,
    /// Total variation of the coil currents, Σ over frames and coils of |ΔI|, per second (A/s).
    pub current_tv_a_per_s: f64,
}

/// The completion rule (error above `FAIL_ERROR_M` for `FAIL_TIME_S`, or no arrival) is the run
/// summary's: one rule for the tables and the end of every run.
pub use millinav_kit::summary::{FAIL_ERROR_M, FAIL_TIME_S};

pub fn metrics(trace: &[TraceRow], reference: &Reference, coil_resistance_ohm: f64) -> Metrics {
    let mut samples = Vec::with_capacity(trace.len());
    let mut energy = 0.0;
    for (i, row) in trace.iter().enumerate() {
        let sample = reference.sample(row.time_s);
        samples.push(ErrorSample {
            time_s: row.time_s,
            error_m: (row.position_m - sample.position_m).norm(),
            reference_finished: sample.finished,
        });
        if i > 0 {
            energy +=
                row.sum_sq_current_a2 * coil_resistance_ohm * (row.time_s - trace[i - 1].time_s);
        }
    }
    let current_steps = CurrentSteps::of(trace);
    let tracking = tracking(&samples);
    Metrics {
        rmse_mm: tracking.rmse_mm,
        p95_mm: tracking.p95_mm,
        max_mm: tracking.max_mm,
        completed: tracking.completed,
        wall_contact_frames: trace.iter().filter(|r| r.wall_contact).count(),
        peak_current_a: trace.iter().fold(0.0, |m, r| m.max(r.max_abs_current_a)),
        energy_j: energy,
        current_step_p95_a: current_steps.p95_a,
        current_tv_a_per_s: current_steps.tv_a_per_s,
    }
}

/// How much the coil currents move from frame to frame.
struct CurrentSteps {
    p95_a: f64,
    tv_a_per_s: f64,
}

impl CurrentSteps {
    fn of(trace: &[TraceRow]) -> Self {
        let mut largest_steps = Vec::with_capacity(trace.len());
        let mut total = 0.0;
        for pair in trace.windows(2) {
            let (Some(before), Some(after)) = (pair[0].coil_currents_a, pair[1].coil_currents_a)
            else {
                return Self {
                    p95_a: f64::NAN,
                    tv_a_per_s: f64::NAN,
                };
            };
            let steps = before.iter().zip(&after).map(|(a, b)| (b - a).abs());
            total += steps.clone().sum::<f64>();
            largest_steps.push(steps.fold(0.0, f64::max));
        }
        largest_steps.sort_by(|a, b| a.total_cmp(b));
        let duration = match (trace.first(), trace.last()) {
            (Some(first), Some(last)) if last.time_s > first.time_s => last.time_s - first.time_s,
            _ => f64::NAN,
        };
        Self {
            p95_a: largest_steps
                .get(((largest_steps.len() as f64 - 1.0) * 0.95).round() as usize)
                .copied()
                .unwrap_or(f64::NAN),
            tv_a_per_s: total / duration,
        }
    }
}

pub fn reference_of(scenario: &Scenario) -> anyhow::Result<Reference> {
    Ok(Reference::new(
        &scenario.waypoints_m(),
        scenario.trajectory.speed_mm_s * 1e-3,
        scenario.trajectory.start_time_s,
    )?)
}

/// Writes one fast-mode run as a Rerun recording at `path`: the reference path, then at 10 Hz of
/// simulated time the robot, its reference point, the tracking error and the peak coil current
/// (same entity names as the process set's recordings where they mean the same thing).
pub fn write_rrd(
    path: &Path,
    run_name: &str,
    trace: &[TraceRow],
    reference: &Reference,
) -> anyhow::Result<()> {
    use millinav_kit::rerun;
    let rec = rerun::RecordingStreamBuilder::new("millinav-experiments")
        .recording_id(run_name.to_owned())
        .save(path)
        .with_context(|| format!("opening {}", path.display()))?;
    let mm = |p: &Vector2<f64>| [(p.x * 1e3) as f32, (p.y * 1e3) as f32];
    let waypoints: Vec<[f32; 2]> = reference.waypoints().iter().map(mm).collect();
    rec.log_static("world/planned_path", &rerun::LineStrips2D::new([waypoints]))?;
    let mut next_log_s = f64::NEG_INFINITY;
    let mut path_so_far: Vec<[f32; 2]> = Vec::new();
    for (seq, row) in trace.iter().enumerate() {
        if row.time_s < next_log_s {
            continue;
        }
        next_log_s = row.time_s + 0.1;
        millinav_kit::recording::set_time(&rec, secs_to_ns(row.time_s), seq as u64);
        let target = reference.sample(row.time_s).position_m;
        path_so_far.push(mm(&row.position_m));
        rec.log(
            "world/robot/true",
            &rerun::Points2D::new([mm(&row.position_m)]).with_radii([1.4]),
        )?;
        rec.log(
            "world/reference",
            &rerun::Points2D::new([mm(&target)]).with_radii([0.5]),
        )?;
        rec.log(
            "world/actual_path",
            &rerun::LineStrips2D::new([path_so_far.clone()]),
        )?;
        millinav_kit::recording::scalar(
            &rec,
            "experiment/error_mm",
            (row.position_m - target).norm() * 1e3,
        );
        millinav_kit::recording::scalar(&rec, "experiment/max_current_a", row.max_abs_current_a);
        millinav_kit::recording::scalar(
            &rec,
            "experiment/wall_contact",
            f64::from(u8::from(row.wall_contact)),
        );
    }
    rec.flush_blocking()
        .map_err(|e| anyhow::anyhow!("flushing {}: {e}", path.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_setting_lands_in_its_table_and_bad_ones_are_named() {
        let mut sections = toml::Table::new();
        apply_setting(&mut sections, "plant.physics.floor_gap_m=3e-6").unwrap();
        apply_setting(&mut sections, "control.controller = \"pid\"").unwrap();
        assert_eq!(
            sections["plant"]["physics"]["floor_gap_m"].as_float(),
            Some(3e-6)
        );
        assert_eq!(sections["control"]["controller"].as_str(), Some("pid"));
        for (bad, says) in [
            ("plant.physics.floor_gap_m", "KEY=VALUE"),
            ("floor_gap_m=1", "dotted path"),
            ("fluid.viscosity_cp=4.3", "not a service table"),
            ("plant.physics.floor_gap_m=three", "not a TOML value"),
        ] {
            let message = format!("{:#}", apply_setting(&mut sections, bad).unwrap_err());
            assert!(
                message.contains(says) && message.contains(bad),
                "{bad}: {message}"
            );
        }
    }

    use super::*;

    #[test]
    fn a_delay_splits_into_whole_frames_and_the_rest_inside_the_frame() {
        let delays = |doc: &toml::Table| {
            let plant = doc["plant"].as_table().unwrap();
            let in_frame = plant.get("command_delay_ms").map(|v| v.as_float().unwrap());
            let told = doc
                .get("control")
                .map(|c| c["latency"]["unstamped_delay_ms"].as_float().unwrap());
            (
                plant["camera"]["latency_frames"].as_integer().unwrap(),
                in_frame,
                told,
            )
        };
        // Whole frames: camera latency alone, nothing inside the frame.
        let mut doc = toml::Table::new();
        add_capture_to_coils_delay(&mut doc, 100.0, 10.0).unwrap();
        assert_eq!(delays(&doc), (10, None, None));
        // Half a 10 Hz frame: inside the frame, told to control.
        let mut doc = toml::Table::new();
        add_capture_to_coils_delay(&mut doc, 50.0, 100.0).unwrap();
        assert_eq!(delays(&doc), (0, Some(50.0), Some(50.0)));
        // 35 ms at 100 Hz: three frames and 5 ms.
        let mut doc = toml::Table::new();
        add_capture_to_coils_delay(&mut doc, 35.0, 10.0).unwrap();
        let (frames, in_frame, told) = delays(&doc);
        assert_eq!(frames, 3);
        assert!((in_frame.unwrap() - 5.0).abs() < 1e-9 && (told.unwrap() - 5.0).abs() < 1e-9);
        // On top of a pipeline the scenario already has (6 ms inside a 10 ms frame, told),
        // 7 ms more carries into one frame and leaves 3 ms; control is told the change.
        let mut doc: toml::Table = toml::from_str(
            "[plant]\ncommand_delay_ms = 6.0\n[control.latency]\nunstamped_delay_ms = 6.0\n",
        )
        .unwrap();
        add_capture_to_coils_delay(&mut doc, 7.0, 10.0).unwrap();
        let (frames, in_frame, told) = delays(&doc);
        assert_eq!(frames, 1);
        assert!((in_frame.unwrap() - 3.0).abs() < 1e-9 && (told.unwrap() - 3.0).abs() < 1e-9);
        // Refused: negative, not finite, beyond the plant's history.
        for bad in [-1.0, f64::NAN, 1001.0 * 10.0] {
            let mut doc = toml::Table::new();
            assert!(
                add_capture_to_coils_delay(&mut doc, bad, 10.0).is_err(),
                "{bad}"
            );
        }
    }

    #[test]
    fn the_matrix_is_made_from_the_rigs_conditions() {
        // The paper rig: {20, 4.3} cP x {static, 180, 250 mL/min}, as the paper.
        let paper = Rig::load_paper().unwrap();
        let cells = rig_matrix(&paper, 1, false);
        let conditions: Vec<(f64, FlowSetting)> = cells
            .iter()
            .filter(|c| c.controller == "pid")
            .map(|c| (c.viscosity_cp, c.flow))
            .collect();
        use FlowSetting::Static;
        assert_eq!(
            conditions,
            [
                (20.0, Static),
                (20.0, FlowSetting::Q180),
                (20.0, FlowSetting::Q250),
                (4.3, Static),
                (4.3, FlowSetting::Q180),
                (4.3, FlowSetting::Q250)
            ]
        );
        assert_eq!(cells.len(), 6 * 4);
        // The second rig: its own conditions, and cells run on its own maps.
        let root = fieldmaps::data_root();
        let vessel = Rig::load(&root.join("fieldmaps/rigs/vessel8.toml")).unwrap();
        let cells = rig_matrix(&vessel, 1, false);
        let mut expected: Vec<(f64, FlowSetting)> = vec![];
        let mut viscosities: Vec<f64> = vessel
            .phantom
            .flow_conditions
            .iter()
            .map(|c| (c.viscosity_pa_s * 1e4).round() / 10.0)
            .collect();
        viscosities.sort_by(|a, b| b.total_cmp(a));
        viscosities.dedup();
        for v in viscosities {
            expected.push((v, Static));
            let mut flows: Vec<u32> = vessel
                .phantom
                .flow_conditions
                .iter()
                .filter(|c| ((c.viscosity_pa_s * 1e4).round() / 10.0 - v).abs() < 1e-9)
                .map(|c| c.flow_ml_min.round() as u32)
                .collect();
            flows.sort();
            expected.extend(flows.into_iter().map(|q| (v, FlowSetting::Flow(q))));
        }
        let got: Vec<(f64, FlowSetting)> = cells
            .iter()
            .filter(|c| c.controller == "pid")
            .map(|c| (c.viscosity_cp, c.flow))
            .collect();
        assert_eq!(got, expected);
        let base = Scenario::load(&root.join("scenarios/vessel8.toml")).unwrap();
        let moving = cells.iter().find(|c| c.flow != Static).unwrap();
        let text = cell_scenario(&base, moving).unwrap();
        let map = moving
            .flow
            .map(moving.viscosity_cp, &vessel)
            .unwrap()
            .unwrap();
        assert!(
            map.starts_with(root.join("fieldmaps/rigs/vessel8")),
            "{map:?}"
        );
        assert!(text.contains(&*map.to_string_lossy()), "{text}");
        assert!(text.contains("vessel8.toml"), "{text}");
        // A condition the rig lacks is an error naming the rig.
        let err = FlowSetting::Flow(999).map(4.3, &vessel).unwrap_err();
        assert!(err.to_string().contains("vessel8.toml"), "{err}");
    }

    #[test]
    fn metrics_on_a_perfect_and_a_lost_trace() {
        let reference = Reference::new(&[[0.0, 0.0], [0.01, 0.0]], 1e-3, 0.0).unwrap();
        let perfect: Vec<TraceRow> = (0..=100)
            .map(|i| {
                let t = i as f64 * 0.1;
                TraceRow {
                    time_s: t,
                    position_m: reference.sample(t).position_m,
                    wall_contact: false,
                    max_abs_current_a: 1.0,
                    sum_sq_current_a2: 1.0,
                    // One coil alternating between +1 and −1 A: a 2 A step every 0.1 s.
                    coil_currents_a: Some({
                        let mut currents = [0.0; MAX_COILS];
                        currents[0] = if i % 2 == 0 { 1.0 } else { -1.0 };
                        currents
                    }),
                    motion: TraceMotion::default(),
                }
            })
            .collect();
        let m = metrics(&perfect, &reference, 10.0);
        assert!(m.rmse_mm < 1e-9 && m.completed);
        assert!((m.energy_j - 100.0).abs() < 1e-6, "{}", m.energy_j);
        assert!((m.current_step_p95_a - 2.0).abs() < 1e-12);
        assert!(
            (m.current_tv_a_per_s - 20.0).abs() < 1e-9,
            "{}",
            m.current_tv_a_per_s
        );
        let lost: Vec<TraceRow> = perfect
            .iter()
            .map(|r| TraceRow {
                position_m: Vector2::new(-0.01, 0.0),
                ..*r
            })
            .collect();
        let m = metrics(&lost, &reference, 10.0);
        assert!(!m.completed);
        assert!((m.max_mm - 20.0).abs() < 1e-9);
    }

    #[test]
    fn completion_means_arriving_at_the_end() {
        // 10 mm at 1 mm/s: the reference reaches the end at 10 s; the run lasts 11.5 s.
        let reference = Reference::new(&[[0.0, 0.0], [0.01, 0.0]], 1e-3, 0.0).unwrap();
        let trace = |offset_after: f64, offset_m: f64| -> Vec<TraceRow> {
            (0..=115)
                .map(|i| {
                    let t = i as f64 * 0.1;
                    let offset = if t >= offset_after { offset_m } else { 0.0 };
                    TraceRow {
                        time_s: t,
                        position_m: reference.sample(t).position_m + Vector2::new(0.0, offset),
                        wall_contact: false,
                        max_abs_current_a: 0.0,
                        sum_sq_current_a2: 0.0,
                        coil_currents_a: None,
                        motion: TraceMotion::default(),
                    }
                })
                .collect()
        };
        // Arrived, then pushed 8 mm off for the last second: completed.
        assert!(metrics(&trace(10.55, 8e-3), &reference, 10.0).completed);
        // 6 mm off from just before the end on (1.6 s, under the lost-for-2 s rule): it never
        // arrived, so it did not complete.
        assert!(!metrics(&trace(9.95, 6e-3), &reference, 10.0).completed);
        // Cut short before the reference ends: judged by the last sample, as before.
        let short: Vec<TraceRow> = trace(5.0, 6e-3).into_iter().take(60).collect();
        assert!(!metrics(&short, &reference, 10.0).completed);
        let short: Vec<TraceRow> = trace(99.0, 0.0).into_iter().take(60).collect();
        assert!(metrics(&short, &reference, 10.0).completed);
    }
}
