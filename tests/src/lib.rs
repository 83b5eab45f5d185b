//! Harness for cross-process tests: starts the real supervisor and process set in an isolated
//! iceoryx2 namespace (own prefix and root) and run directory, and reads back what the run left
//! behind (ground truth, emulated-Teensy events, supervisor events, recordings).

pub mod sources;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use millinav_control::reference::Reference;
use millinav_kit::runlog::{self, LinkEventRow, SupervisorEventRow, TeensyEventRow};
use millinav_kit::scenario::Scenario;
use nalgebra::Vector2;

/// Directory holding the built executables (the test binary lives in `<target>/release/deps`).
pub fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    let deps = exe.parent().expect("deps dir");
    deps.parent().expect("profile dir").to_owned()
}

/// `name` as part of an iceoryx2 prefix: letters, digits and '-' (kit::iox_domain).
pub fn prefix_safe(name: &str) -> String {
    name.chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
        .collect()
}

/// A run of the whole set under the supervisor.
pub struct RunSet {
    pub name: String,
    pub run_dir: PathBuf,
    pub scenario_path: PathBuf,
    pub iox_prefix: String,
    pub iox_root: PathBuf,
    supervisor: Option<Child>,
}

impl RunSet {
    /// Writes `scenario_toml` into a fresh run directory and starts the supervisor on it.
    pub fn start(name: &str, scenario_toml: &str) -> anyhow::Result<Self> {
        Self::start_with(name, scenario_toml, None, &[])
    }

    /// Like [`RunSet::start`] with more `millinav run` arguments (e.g. `--session`).
    pub fn start_with_args(name: &str, scenario_toml: &str, args: &[&str]) -> anyhow::Result<Self> {
        Self::start_with(name, scenario_toml, None, args)
    }

    fn start_with(
        name: &str,
        scenario_toml: &str,
        namespace: Option<(&str, &Path)>,
        extra_args: &[&str],
    ) -> anyhow::Result<Self> {
        let base =
            std::env::temp_dir().join(format!("millinav-test-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&base);
        let run_dir = base.join("run");
        std::fs::create_dir_all(&run_dir)?;
        let scenario_path = base.join("scenario.toml");
        std::fs::write(&scenario_path, scenario_toml)?;
        let (iox_prefix, iox_root) = match namespace {
            Some((prefix, root)) => (prefix.to_owned(), root.to_owned()),
            None => (
                format!("mt{}-{}_", std::process::id(), prefix_safe(name)),
                base.join("iceoryx2"),
            ),
        };
        let mut command = Command::new(bin_dir().join("millinav"));
        command
            .arg("run")
            .arg(&scenario_path)
            .arg("--run-dir")
            .arg(&run_dir)
            .args(["--viewer", "none", "--max-wall-s", "300"])
            .args(extra_args)
            .arg("--iox-prefix")
            .arg(&iox_prefix)
            .arg("--iox-root")
            .arg(&iox_root)
            .env("PATH", path_with_rerun())
            .stdin(Stdio::null())
            .stdout(std::fs::File::create(base.join("supervisor.out"))?)
            .stderr(std::fs::File::create(base.join("supervisor.log"))?);
        let supervisor = command.spawn().context("starting millinav run")?;
        Ok(Self {
            name: name.to_owned(),
            run_dir,
            scenario_path,
            iox_prefix,
            iox_root,
            supervisor: Some(supervisor),
        })
    }

    /// Starts a new supervisor in a new run directory but in the iceoryx2 namespace (prefix and
    /// root) of `previous`, as an operator restarting after a supervisor crash would.
    pub fn restart_in(previous: &RunSet, name: &str, scenario_toml: &str) -> anyhow::Result<Self> {
        let mut run = Self::start_with(
            name,
            scenario_toml,
            Some((&previous.iox_prefix, &previous.iox_root)),
            &[],
        )?;
        run.name = name.to_owned();
        Ok(run)
    }

    /// SIGKILLs the supervisor (the children are left to fend for themselves).
    pub fn kill_supervisor(&mut self) -> anyhow::Result<()> {
        let mut child = self
            .supervisor
            .take()
            .context("supervisor already reaped")?;
        child.kill()?;
        child.wait()?;
        Ok(())
    }

    /// Waits for the supervisor to exit.
    pub fn wait(&mut self, timeout: Duration) -> anyhow::Result<ExitStatus> {
        let deadline = Instant::now() + timeout;
        let child = self
            .supervisor
            .as_mut()
            .context("supervisor already reaped")?;
        loop {
            if let Some(status) = child.try_wait()? {
                self.supervisor = None;
                return Ok(status);
            }
            if Instant::now() > deadline {
                let _ = child.kill();
                bail!(
                    "run {} did not finish within {timeout:?}; see {}",
                    self.name,
                    self.run_dir.display()
                );
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Waits for the supervisor and checks that it exited cleanly after the plant reported
    /// `run_complete` (the whole scenario ran).
    pub fn assert_completes(&mut self, timeout: Duration) {
        self.assert_completed_by("plant", timeout);
    }

    /// Waits for the supervisor and checks that it exited cleanly after `service` (the plant,
    /// or the camera at the end of a replayed recording) reported `run_complete`.
    pub fn assert_completed_by(&mut self, service: &str, timeout: Duration) {
        let status = self.wait(timeout).expect("run finishes");
        assert!(status.success(), "supervisor exit {status}");
        let events = self.supervisor_events().expect("supervisor events");
        assert!(
            events
                .iter()
                .any(|e| e.service == service && e.event == "run_complete"),
            "run {} did not complete: {events:?}",
            self.name
        );
    }

    /// Asks the supervisor to stop (SIGTERM) and waits for it.
    pub fn stop(&mut self, timeout: Duration) -> anyhow::Result<ExitStatus> {
        let child = self
            .supervisor
            .as_ref()
            .context("supervisor already reaped")?;
        nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(child.id() as i32),
            nix::sys::signal::Signal::SIGTERM,
        )?;
        self.wait(timeout)
    }

    /// PID of the supervisor (`millinav run`) while it runs.
    pub fn supervisor_pid(&self) -> anyhow::Result<i32> {
        Ok(self
            .supervisor
            .as_ref()
            .context("supervisor already reaped")?
            .id() as i32)
    }

    pub fn scenario(&self) -> anyhow::Result<Scenario> {
        Ok(Scenario::load(&self.scenario_path)?)
    }

    /// PID of a service's current incarnation, from the supervisor's pid files.
    pub fn pid_of(&self, service: &str) -> anyhow::Result<i32> {
        let text =
            std::fs::read_to_string(self.run_dir.join("pids").join(format!("{service}.pid")))?;
        Ok(text.trim().parse()?)
    }

    /// Waits until the plant has published at least `frames` frames.
    pub fn wait_for_frames(&self, frames: u64, timeout: Duration) -> anyhow::Result<()> {
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            let commanded = self
                .teensy_events()
                .unwrap_or_default()
                .iter()
                .filter_map(|e| e.frame_seq)
                .max()
                .unwrap_or(0);
            if commanded >= frames {
                return Ok(());
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        bail!("the loop did not reach frame {frames} within {timeout:?}")
    }

    pub fn truth(&self) -> anyhow::Result<Vec<TruthRow>> {
        read_truth(
            &self
                .run_dir
                .join(<runlog::TruthRow as runlog::RunLogRow>::FILE_NAME),
        )
    }

    pub fn teensy_events(&self) -> anyhow::Result<Vec<TeensyEvent>> {
        let rows: Vec<TeensyEventRow> = runlog::read_run_dir(&self.run_dir)?;
        Ok(rows
            .into_iter()
            .map(|row| TeensyEvent {
                monotonic_ns: row.monotonic_ns,
                frame_seq: row.frame_seq,
                max_abs_current_a: row.max_abs_current_a,
                kind: row.event,
            })
            .collect())
    }

    /// coilbus's serial-link log (`open` / `lost`), as (monotonic_ns, event).
    pub fn link_events(&self) -> anyhow::Result<Vec<(u64, String)>> {
        let rows: Vec<LinkEventRow> = runlog::read_run_dir(&self.run_dir)?;
        Ok(rows
            .into_iter()
            .map(|row| (row.monotonic_ns, row.event))
            .collect())
    }

    pub fn supervisor_events(&self) -> anyhow::Result<Vec<SupervisorEvent>> {
        Ok(runlog::read_run_dir(&self.run_dir)?)
    }

    /// What the supervisor printed on its console (stderr).
    pub fn supervisor_console(&self) -> anyhow::Result<String> {
        let base = self.run_dir.parent().context("run dir has no parent")?;
        Ok(std::fs::read_to_string(base.join("supervisor.log"))?)
    }

    /// What the supervisor printed on stdout (the run summary).
    pub fn supervisor_stdout(&self) -> anyhow::Result<String> {
        let base = self.run_dir.parent().context("run dir has no parent")?;
        Ok(std::fs::read_to_string(base.join("supervisor.out"))?)
    }

    /// Services the supervisor started (its `spawn` events); none when it never got that far.
    pub fn spawned(&self) -> Vec<String> {
        self.supervisor_events()
            .unwrap_or_default()
            .into_iter()
            .filter(|e| e.event == "spawn")
            .map(|e| e.service)
            .collect()
    }

    /// Shared-memory segments of this run still present in /dev/shm (excluding iceoryx2's
    /// global node counter, which it never removes by design).
    pub fn shm_segments(&self) -> Vec<String> {
        shm_segments_with_prefix(&self.iox_prefix)
    }
}

impl Drop for RunSet {
    fn drop(&mut self) {
        if let Some(child) = self.supervisor.as_mut() {
            let _ = nix::sys::signal::kill(
                nix::unistd::Pid::from_raw(child.id() as i32),
                nix::sys::signal::Signal::SIGTERM,
            );
            let _ = child.wait();
        }
        for name in shm_segments_with_prefix(&self.iox_prefix) {
            let _ = std::fs::remove_file(Path::new("/dev/shm").join(name));
        }
        if let Ok(entries) = std::fs::read_dir("/dev/shm") {
            for e in entries.flatten() {
                if e.file_name()
                    .to_string_lossy()
                    .starts_with(&self.iox_prefix)
                {
                    let _ = std::fs::remove_file(e.path());
                }
            }
        }
        // A passing test leaves nothing behind (its recordings run to hundreds of MB); a failing
        // one keeps its run directory for the post-mortem, as does every run when
        // MILLINAV_KEEP_TEST_RUNS=1 (to compare a passing run with a failed one).
        if let Some(base) = self.run_dir.parent() {
            let keep = std::env::var("MILLINAV_KEEP_TEST_RUNS").is_ok_and(|v| v == "1");
            if std::thread::panicking() || keep {
                eprintln!("run {} kept for inspection: {}", self.name, base.display());
            } else {
                let _ = std::fs::remove_dir_all(base);
            }
        }
    }
}

/// Runs kept in a `static` (shared by the tests of one file) are never dropped, so their
/// directories would pile up in /tmp at every test run: these are removed when the test process
/// exits, unless one of its tests failed (then they are kept for the post-mortem, as a failed
/// test's own run is) or `MILLINAV_KEEP_TEST_RUNS=1`.
static SHARED_RUN_DIRS: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());
static A_TEST_FAILED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

extern "C" fn remove_shared_runs() {
    let keep = std::env::var("MILLINAV_KEEP_TEST_RUNS").is_ok_and(|v| v == "1");
    let dirs = SHARED_RUN_DIRS
        .lock()
        .map(|d| d.clone())
        .unwrap_or_default();
    for dir in dirs {
        if keep || A_TEST_FAILED.load(std::sync::atomic::Ordering::SeqCst) {
            eprintln!("shared run kept for inspection: {}", dir.display());
        } else {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

impl RunSet {
    /// Marks this run as shared by a test file's `static`: see `SHARED_RUN_DIRS`.
    pub fn remove_at_exit(&self) {
        static INSTALL: std::sync::Once = std::sync::Once::new();
        INSTALL.call_once(|| {
            let previous = std::panic::take_hook();
            std::panic::set_hook(Box::new(move |info| {
                A_TEST_FAILED.store(true, std::sync::atomic::Ordering::SeqCst);
                previous(info);
            }));
            // SAFETY: `remove_shared_runs` is a plain function that touches only statics.
            unsafe {
                nix::libc::atexit(remove_shared_runs);
            }
        });
        if let (Some(base), Ok(mut dirs)) = (self.run_dir.parent(), SHARED_RUN_DIRS.lock()) {
            dirs.push(base.to_path_buf());
        }
    }
}

pub fn shm_segments_with_prefix(prefix: &str) -> Vec<String> {
    std::fs::read_dir("/dev/shm")
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(prefix) && !n.ends_with(".global_mgmt"))
        .collect()
}

#[derive(Debug, Clone)]
pub struct TruthRow {
    pub frame_seq: u64,
    pub sim_time_s: f64,
    pub position_m: Vector2<f64>,
    pub wall_contact: bool,
    pub max_abs_current_a: f64,
    pub lockstep_misses: u64,
}

pub fn read_truth(path: &Path) -> anyhow::Result<Vec<TruthRow>> {
    let rows: Vec<runlog::TruthRow> = runlog::read_rows(path)?;
    Ok(rows
        .into_iter()
        .map(|row| TruthRow {
            frame_seq: row.frame_seq,
            sim_time_s: row.sim_time_s,
            position_m: Vector2::new(row.x_m, row.y_m),
            wall_contact: row.wall_contact,
            max_abs_current_a: row.max_abs_current_a,
            lockstep_misses: row.lockstep_misses,
        })
        .collect())
}

#[derive(Debug, Clone)]
pub struct TeensyEvent {
    pub monotonic_ns: u64,
    pub frame_seq: Option<u64>,
    pub max_abs_current_a: f64,
    pub kind: String,
}

impl TeensyEvent {
    /// True when the board drove every coil to zero here: a frame of zeros (coilbus's safe
    /// zero, or a command of zeros) or the board zeroing on its own (its watchdog, or the
    /// hardware watchdog resetting a stalled board). Link events (unplug, replug, reboot) are
    /// not: they say nothing about what the outputs did.
    pub fn drives_zero(&self) -> bool {
        match self.kind.as_str() {
            "command" | "safe_zero" => self.max_abs_current_a == 0.0,
            "watchdog_zero" | "hw_watchdog_reset" => true,
            _ => false,
        }
    }

    /// True for a frame coilbus sent (a command or its safe zero).
    pub fn is_frame(&self) -> bool {
        matches!(self.kind.as_str(), "command" | "safe_zero")
    }
}

/// What the fault tests allow on top of a safety deadline ("coils at zero within one
/// deadline"). The mechanisms are not instantaneous: coilbus checks its command deadline on a
/// 20 ms tick and the board's watchdog polls every 5 ms; on top of that every process shares 2
/// loaded cores with the build and the other tests. The README's fault-matrix run shows at
/// most 9 ms over a bound.
pub const SCHEDULING_TOLERANCE_MS: f64 = 40.0;

/// A row of `supervisor_events.csv`.
pub type SupervisorEvent = SupervisorEventRow;

/// Tracking metrics from ground truth against the scenario's reference.
#[derive(Debug, Clone, Copy)]
pub struct Tracking {
    pub rmse_m: f64,
    pub max_m: f64,
    pub final_error_m: f64,
    pub wall_contacts: usize,
}

/// Errors of the truth trace against the reference, for frames at or after `from_time_s`.
pub fn tracking(
    scenario: &Scenario,
    truth: &[TruthRow],
    from_time_s: f64,
) -> anyhow::Result<Tracking> {
    let reference = Reference::new(
        &scenario.waypoints_m(),
        scenario.trajectory.speed_mm_s * 1e-3,
        scenario.trajectory.start_time_s,
    )?;
    // A plant restarted or frames republished at start give repeated rows: keep one per frame.
    let mut errors = Vec::new();
    let mut last_seq = None;
    for row in truth.iter().filter(|r| r.sim_time_s >= from_time_s) {
        if last_seq == Some(row.frame_seq) {
            continue;
        }
        last_seq = Some(row.frame_seq);
        let r = reference.sample(row.sim_time_s);
        errors.push((row.position_m - r.position_m).norm());
    }
    if errors.is_empty() {
        bail!("no ground truth after t = {from_time_s} s");
    }
    let rmse = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    Ok(Tracking {
        rmse_m: rmse,
        max_m: errors.iter().cloned().fold(0.0, f64::max),
        final_error_m: *errors.last().unwrap_or(&f64::NAN),
        wall_contacts: truth.iter().filter(|r| r.wall_contact).count(),
    })
}

/// The project's Python environment (made by scripts/setup.sh).
pub fn venv_dir() -> PathBuf {
    std::env::var_os("MILLINAV_VENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(std::env::var_os("HOME").unwrap_or_default()).join(".cache/millinav/venv")
        })
}

/// PATH with the venv's bin directory first, so the supervisor finds the `rerun` CLI.
pub fn path_with_rerun() -> std::ffi::OsString {
    let mut paths = vec![venv_dir().join("bin")];
    if let Some(existing) = std::env::var_os("PATH") {
        paths.extend(std::env::split_paths(&existing));
    }
    std::env::join_paths(paths).unwrap_or_default()
}

/// A scenario file's text for tests.
pub fn scenario_text(
    duration_s: f64,
    waypoints_mm: &[[f64; 2]],
    speed_mm_s: f64,
    extra: &str,
) -> String {
    let points: Vec<String> = waypoints_mm
        .iter()
        .map(|p| format!("[{:.3}, {:.3}]", p[0], p[1]))
        .collect();
    format!(
        "[run]\nmode = \"lockstep\"\nseed = 3\nduration_s = {duration_s}\nframe_period_ms = 10.0\nrig = \"fieldmaps/rigs/paper.toml\"\n\n\
         [fluid]\nviscosity_cp = 20.0\n\n\
         [trajectory]\nwaypoints_mm = [{}]\nspeed_mm_s = {speed_mm_s}\nstart_time_s = 0.5\n\n{extra}\n",
        points.join(", ")
    )
}

/// The committed second rig's scenario (`scenarios/vessel8.toml`: 8-coil ring, branched vessel)
/// with its relative paths made absolute (so it can be written anywhere), `duration_s` set, and
/// `extra` tables appended. `flow = false` runs it in still fluid.
pub fn vessel8_scenario_text(duration_s: f64, flow: bool, extra: &str) -> String {
    let root = fieldmaps::data_root();
    let text = std::fs::read_to_string(root.join("scenarios/vessel8.toml"))
        .expect("scenarios/vessel8.toml");
    let flow_dir = root.join("fieldmaps/rigs/vessel8/flow");
    let mut out = String::new();
    for line in text.lines() {
        if line.starts_with("duration_s") {
            out.push_str(&format!("duration_s = {duration_s}\n"));
        } else if line.starts_with("map = ") {
            if flow {
                let file = line.rsplit('/').next().unwrap_or("").trim_end_matches('"');
                out.push_str(&format!("map = {:?}\n", flow_dir.join(file)));
            }
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    out.push_str(extra);
    out
}

/// Sets the scenario's pipeline delay, capture → coils inside the frame (`[plant]
/// command_delay_ms`), and tells control the same (`[control.latency] unstamped_delay_ms`), as
/// `experiments --command-delay-ms` does.
pub fn with_pipeline_delay(base: &mut Scenario, delay_ms: f64) {
    for path in [
        &["plant", "command_delay_ms"][..],
        &["control", "latency", "unstamped_delay_ms"][..],
    ] {
        millinav_experiments::set_in_table(&mut base.sections, path, toml::Value::Float(delay_ms))
            .expect("scenario tables");
    }
}

/// Takes the scenario's pipeline delay out: for tests of a mechanism on a case that was found
/// and measured on the twin before the scenarios had that delay, which moves single seeds of a
/// chaotic case.
pub fn without_pipeline_delay(base: &mut Scenario) {
    with_pipeline_delay(base, 0.0);
}

/// One cell of the paper's matrix built from `scenarios/paper.toml` (after `adjust`, e.g. a
/// shorter run or another frame period), ready to run in either mode and to score.
pub struct PaperCell {
    /// The cell's scenario text (what `process_run` takes).
    pub text: String,
    pub scenario: Scenario,
    reference: Reference,
}

impl PaperCell {
    pub fn new(cell: &millinav_experiments::Cell, adjust: impl FnOnce(&mut Scenario)) -> Self {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let mut base = Scenario::load(&root.join("scenarios/paper.toml")).expect("paper scenario");
        adjust(&mut base);
        let text = millinav_experiments::cell_scenario(&base, cell).expect("cell scenario");
        let scenario =
            Scenario::parse(&text, &root.join("scenarios/cell.toml")).expect("parse cell");
        let reference = millinav_experiments::reference_of(&scenario).expect("reference");
        Self {
            text,
            scenario,
            reference,
        }
    }

    /// The matrix's metrics of a trace of this cell.
    pub fn metrics(
        &self,
        trace: &[millinav_experiments::TraceRow],
    ) -> millinav_experiments::Metrics {
        let resistance = self
            .scenario
            .rig()
            .expect("the cell's rig")
            .coil_limits()
            .coil_resistance_ohm;
        millinav_experiments::metrics(trace, &self.reference, resistance)
    }
}

/// Waypoints of a 5 mm circle in the paper rig's right atrium (centre (−16, 10) mm): a robot that
/// follows it stays in the canal however long the run is.
pub fn atrium_circle_mm() -> Vec<[f64; 2]> {
    (0..=24)
        .map(|i| {
            let a = i as f64 / 24.0 * std::f64::consts::TAU;
            [-16.0 + 5.0 * a.cos(), 10.0 + 5.0 * a.sin()]
        })
        .collect()
}

/// Localization error of a run, mm: for every frame whose pose control used (`control.csv`),
/// the distance from that pose to the twin's truth of the same frame (`truth.csv`).
pub fn pose_errors_vs_truth_mm(run_dir: &Path) -> anyhow::Result<Vec<f64>> {
    let truth: std::collections::BTreeMap<u64, Vector2<f64>> =
        read_truth(&run_dir.join("truth.csv"))?
            .into_iter()
            .map(|row| (row.frame_seq, row.position_m))
            .collect();
    let control: Vec<runlog::ControlRow> = runlog::read_run_dir(run_dir)?;
    Ok(control
        .iter()
        .filter(|row| row.pose_used)
        .filter_map(|row| {
            let t = truth.get(&row.frame_seq)?;
            Some((Vector2::new(row.measured_x_m, row.measured_y_m) - t).norm() * 1e3)
        })
        .collect())
}

/// Poses of a run by frame: (x, y) m from `control.csv`, frames whose pose control used.
pub fn used_poses(run_dir: &Path) -> anyhow::Result<std::collections::BTreeMap<u64, Vector2<f64>>> {
    let control: Vec<runlog::ControlRow> = runlog::read_run_dir(run_dir)?;
    Ok(control
        .into_iter()
        .filter(|row| row.pose_used)
        .map(|row| {
            (
                row.frame_seq,
                Vector2::new(row.measured_x_m, row.measured_y_m),
            )
        })
        .collect())
}

/// The median of `values` (NaN when empty).
pub fn median(values: &[f64]) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    match sorted.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => sorted[n / 2],
        n => 0.5 * (sorted[n / 2 - 1] + sorted[n / 2]),
    }
}
