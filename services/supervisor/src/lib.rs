//! supervisor: launches the process set, reaps and restarts children with backoff, watches
//! their heartbeats (event services with deadlines), cleans the iceoryx2 resources of dead
//! nodes before a restart, and shuts down safe-state first. Everything it does is appended to
//! `<run_dir>/supervisor_events.csv` so runs and tests can be audited afterwards.

pub mod ctl;
pub mod front_door;
pub mod launch;
mod monitor;
pub mod preflight;
pub mod realtime;
pub mod restart;
mod viewer;

use std::collections::BTreeMap;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use millinav_kit::iceoryx2::port::listener::Listener;
use millinav_kit::iceoryx2::prelude::*;
use millinav_kit::iox_domain::Domain;
use millinav_kit::ports::{heartbeat_listener, Inbox, Outbox};
use millinav_kit::runlog::{RunLogWriter, SupervisorEventRow};
use millinav_kit::scenario::Scenario;
use millinav_kit::summary::{RunFacts, RunSummary};
use millinav_kit::{clock, env_vars, recording, rerun, Runtime};
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use shm_schemas::{
    board_state_name, deadlines, services, BoardFault, CoilStatus, Heartbeat, OperatorReply,
    OperatorRequest, OperatorState, OperatorVerb, ServiceId,
};

use crate::launch::{LaunchFile, ProcessSpec};
use crate::preflight::{CheckFailure, CheckTarget};
use crate::restart::{
    classify_exit, silent_too_long, startup_progress, Backoff, ExitKind, Startup, StormWatch,
};
use monitor::{monitor, Heartbeats};
pub use viewer::{merge_recordings, which, VIEWER_PORT};
use viewer::{start_viewer, viewer_layout};

/// Time a child gets between SIGTERM and SIGKILL at shutdown (coilbus zeroes the coils in it).
const CHILD_STOP_GRACE: Duration = Duration::from_secs(5);
/// How often a stopping child is polled.
const CHILD_STOP_POLL: Duration = Duration::from_millis(10);
/// Period of the monitor loop: reaping, restarts, hung detection, wall-time limit.
const MONITOR_TICK: Duration = Duration::from_millis(50);
/// Lines of a child's log shown on the console when it stops the set.
const CONSOLE_LOG_LINES: usize = 20;

/// Why the set was not started or was stopped, as the console should tell it. Both are
/// configuration errors: `millinav run` exits with `restart::EXIT_CONFIG` for them.
#[derive(Debug, thiserror::Error)]
pub enum FailFast {
    #[error("configuration check failed, nothing was started:\n{}", list_failures(.0))]
    ChecksFailed(Vec<CheckFailure>),
    #[error(
        "{service} exited with a configuration error ({status}); the set was stopped. \
         The end of {}:\n{output}",
        .log.display()
    )]
    ChildConfigError {
        service: String,
        status: String,
        log: PathBuf,
        output: String,
    },
}

/// Why a set that had started was stopped safe before its end: restarting would not help.
/// `millinav run` exits 1 for them, after the coils are at zero.
#[derive(Debug, thiserror::Error)]
pub enum StoppedSafe {
    #[error(
        "{service} did not finish starting (no heartbeat) within its start-up budget of \
         {budget_s:.0} s; the set was stopped safe. A cold or heavily loaded machine can be this \
         slow: raise `startup_budget_ms` in the launch file if it was only slow. The end of {}:\n{output}",
        .log.display()
    )]
    StartupOverBudget {
        service: String,
        budget_s: f64,
        log: PathBuf,
        output: String,
    },
    #[error(
        "{service} failed {failures} times within {window_s:.0} s (a restart storm); the set was \
         stopped safe. The end of {}:\n{output}",
        .log.display()
    )]
    RestartStorm {
        service: String,
        failures: usize,
        window_s: f64,
        log: PathBuf,
        output: String,
    },
}

fn list_failures(failures: &[CheckFailure]) -> String {
    failures
        .iter()
        .map(|f| format!("  {f}"))
        .collect::<Vec<_>>()
        .join("\n")
}

/// Where the viewer goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ViewerMode {
    /// Spawn a Rerun viewer when one is installed and a display is available.
    Auto,
    /// Always spawn a viewer (fails if `rerun` is not installed).
    Spawn,
    /// Only write the .rrd recording.
    None,
}

/// Everything the supervisor needs to run a set.
#[derive(Debug, Clone)]
pub struct SupervisorOptions {
    pub scenario: PathBuf,
    pub launch: LaunchFile,
    pub run_dir: PathBuf,
    /// Directory holding the service executables.
    pub bin_dir: PathBuf,
    pub viewer: ViewerMode,
    /// iceoryx2 prefix for the whole set (unique per run unless given).
    pub iox_prefix: String,
    pub iox_root: PathBuf,
    /// Stop the run after this much wall time even if the plant has not finished.
    pub max_wall_time: Duration,
    /// A session: control starts disarmed and the twin runs until `ctl stop` or a signal.
    pub session: bool,
    /// The camera service records its raw stream into the run.
    pub record_frames: bool,
}

/// Appends timestamped events to `supervisor_events.csv`.
pub struct EventLog {
    out: RunLogWriter<SupervisorEventRow>,
    rec: rerun::RecordingStream,
}

impl EventLog {
    fn new(run_dir: &Path, rec: rerun::RecordingStream) -> anyhow::Result<Self> {
        Ok(Self {
            out: RunLogWriter::in_run_dir(run_dir)?,
            rec,
        })
    }

    pub fn record(&mut self, service: ServiceId, event: &str, detail: &str) {
        let row = SupervisorEventRow {
            monotonic_ns: clock::monotonic_ns(),
            service: service.name().to_owned(),
            event: event.to_owned(),
            detail: detail.to_owned(),
        };
        if let Err(e) = self.out.append_now(&row) {
            tracing::warn!("cannot log a supervisor event: {e}");
        }
        let _ = self.rec.log(
            "supervisor/events",
            &rerun::TextLog::new(format!("{}: {event} {detail}", service.name())),
        );
    }
}

struct ManagedProcess {
    spec: ProcessSpec,
    id: ServiceId,
    child: Option<Child>,
    incarnation: u64,
    started_at: Instant,
    /// When the process died and is waiting for its backoff to pass.
    restart_at: Option<Instant>,
    backoff: Backoff,
    /// Its current incarnation has beaten once: it has started, and silence now means hung.
    ready: bool,
    /// When a slow start was last noted.
    slow_noted_at: Option<Instant>,
    /// Its recent failures, to stop a restart storm.
    storm: StormWatch,
    last_beat: Instant,
    /// Its stdout + stderr, appended across incarnations.
    log: PathBuf,
    /// Length of `log` when the current incarnation started: where its output begins.
    log_start: u64,
}

impl ManagedProcess {
    fn new(
        spec: &ProcessSpec,
        id: ServiceId,
        log_dir: &Path,
        policy: &launch::RestartPolicy,
    ) -> Self {
        let now = Instant::now();
        Self {
            spec: spec.clone(),
            id,
            child: None,
            incarnation: 0,
            started_at: now,
            restart_at: None,
            backoff: Backoff::new(policy),
            ready: false,
            slow_noted_at: None,
            storm: StormWatch::default(),
            last_beat: now,
            log: log_dir.join(format!("{}.log", spec.name)),
            log_start: 0,
        }
    }

    /// The last lines its current incarnation wrote.
    fn output_tail(&self) -> String {
        use std::io::{Read, Seek};
        let mut text = String::new();
        if let Ok(mut file) = std::fs::File::open(&self.log) {
            let _ = file.seek(std::io::SeekFrom::Start(self.log_start));
            let mut bytes = Vec::new();
            let _ = file.read_to_end(&mut bytes);
            text = String::from_utf8_lossy(&bytes).into_owned();
        }
        let lines: Vec<&str> = text.trim_end().lines().collect();
        lines[lines.len().saturating_sub(CONSOLE_LOG_LINES)..].join("\n")
    }
}

/// How the monitor loop ended.
enum Ending {
    RunComplete,
    Signal,
    /// `millinav ctl stop`.
    OperatorStop,
    WallTimeLimit,
    /// A child exited with `EXIT_CONFIG`: stop the set and say why.
    ConfigError(FailFast),
    /// A child could not start in its budget or keeps failing: stop the set and say why.
    StoppedSafe(StoppedSafe),
    /// coilbus holds the coils at zero on the board's account (e-stop, thermal trip, telemetry
    /// that disagrees, another protocol version): the run cannot go on.
    BoardFault(&'static str),
}

/// The running set.
pub struct Supervisor {
    options: SupervisorOptions,
    processes: Vec<ManagedProcess>,
    pub events: EventLog,
    base_env: Vec<(String, String)>,
    /// Latest deadline-miss count of each (service, incarnation), for the run summary.
    deadline_misses: BTreeMap<(u32, u64), u64>,
    /// The set's iceoryx2 files, swept of half-made services before each restart.
    domain: Domain,
}

impl Supervisor {
    fn spawn(&mut self, index: usize) -> anyhow::Result<()> {
        let binary = self.processes[index].spec.executable(&self.options.bin_dir);
        let log_dir = self.options.run_dir.join("logs");
        std::fs::create_dir_all(&log_dir)?;
        let process = &self.processes[index];
        let name = process.spec.name.clone();
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&process.log)?;
        let log_start = log.metadata()?.len();
        let mut command = Command::new(&binary);
        command
            .arg("--scenario")
            .arg(&self.options.scenario)
            .args(&process.spec.args)
            .envs(self.base_env.iter().map(|(k, v)| (k.as_str(), v.as_str())))
            .env(env_vars::INCARNATION, process.incarnation.to_string())
            .env(
                env_vars::LOCK_MEMORY,
                if process.spec.realtime.lock_memory {
                    "1"
                } else {
                    "0"
                },
            )
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            // Own process group: a terminal's Ctrl-C reaches only the supervisor, which then
            // stops the children in a safe order.
            .process_group(0);
        // If the supervisor itself dies, every child gets SIGTERM: coilbus zeroes the coils on
        // its way out (and the Teensy watchdog covers a coilbus that cannot), so a dead
        // supervisor never leaves coils driven by an unsupervised set.
        // SAFETY: only async-signal-safe calls between fork and exec (prctl, getppid).
        unsafe {
            command.pre_exec(|| {
                nix::sys::prctl::set_pdeathsig(Signal::SIGTERM).map_err(std::io::Error::from)?;
                // The supervisor may have died between fork and prctl.
                if nix::unistd::getppid() == Pid::from_raw(1) {
                    return Err(std::io::Error::other("supervisor exited during spawn"));
                }
                Ok(())
            });
        }
        let child = command
            .spawn()
            .with_context(|| format!("starting {name} ({})", binary.display()))?;
        let pid = child.id();
        std::fs::create_dir_all(self.options.run_dir.join("pids"))?;
        std::fs::write(
            self.options
                .run_dir
                .join("pids")
                .join(format!("{name}.pid")),
            pid.to_string(),
        )?;
        let now = Instant::now();
        let incarnation = process.incarnation;
        let id = process.id;
        let process = &mut self.processes[index];
        process.child = Some(child);
        process.log_start = log_start;
        process.started_at = now;
        process.last_beat = now;
        process.restart_at = None;
        process.ready = false;
        process.slow_noted_at = None;
        self.events
            .record(id, "spawn", &format!("pid={pid} incarnation={incarnation}"));
        for outcome in self.processes[index].spec.realtime.apply(pid) {
            match outcome {
                realtime::Outcome::Applied(what) => self.events.record(id, "realtime", &what),
                realtime::Outcome::Denied(why) => {
                    tracing::warn!(service = %name, "real-time setting not applied: {why}");
                    self.events.record(id, "realtime_denied", &why);
                }
            }
        }
        Ok(())
    }

    /// Removes the resources (shared memory included) of every node of the set whose process
    /// died, and records how many under the service `id` that caused it.
    fn cleanup_dead_nodes(&mut self, node: &Node<ipc::Service>, id: ServiceId) {
        let cleanup = node.try_cleanup_dead_nodes();
        self.events.record(
            id,
            "cleanup_dead_nodes",
            &format!(
                "cleaned={} failed={}",
                cleanup.cleanups, cleanup.failed_cleanups
            ),
        );
    }

    /// Kills (SIGKILL) a process that stopped beating, so it is reaped and restarted.
    fn kill_hung(&mut self, index: usize, silent_for: Duration) {
        let process = &mut self.processes[index];
        if let Some(child) = &process.child {
            let pid = child.id();
            let _ = kill(Pid::from_raw(pid as i32), Signal::SIGCONT);
            let _ = kill(Pid::from_raw(pid as i32), Signal::SIGKILL);
            let id = process.id;
            self.events.record(
                id,
                "heartbeat_missed",
                &format!("pid={pid} silent_ms={}", silent_for.as_millis()),
            );
        }
    }

    /// Reaps exited children and schedules their restarts; says when the set must end (the
    /// plant finished the run, or a child rejected its configuration).
    fn reap(&mut self, node: &Node<ipc::Service>) -> anyhow::Result<Option<Ending>> {
        let mut ending = None;
        let policy = self.options.launch.restart.clone();
        for index in 0..self.processes.len() {
            let status = match self.processes[index].child.as_mut() {
                Some(child) => child.try_wait()?,
                None => None,
            };
            let Some(status) = status else { continue };
            let process = &mut self.processes[index];
            process.child = None;
            let id = process.id;
            let lived = process.started_at.elapsed();
            let detail = format!("status={status} lived_ms={}", lived.as_millis());
            match classify_exit(id, status) {
                ExitKind::RunComplete => {
                    self.events.record(id, "run_complete", &detail);
                    ending.get_or_insert(Ending::RunComplete);
                    continue;
                }
                ExitKind::ConfigError => {
                    let output = process.output_tail();
                    let error = FailFast::ChildConfigError {
                        service: process.spec.name.clone(),
                        status: status.to_string(),
                        log: process.log.clone(),
                        output,
                    };
                    self.events.record(id, "config_error", &detail);
                    // A configuration error outranks a run that happened to complete.
                    ending = Some(Ending::ConfigError(error));
                    continue;
                }
                ExitKind::Failed => self.events.record(id, "exit", &detail),
            }
            if !process.spec.restart {
                continue;
            }
            let now = Instant::now();
            if let Some(failures) = process.storm.failed(now, &policy) {
                let error = StoppedSafe::RestartStorm {
                    service: process.spec.name.clone(),
                    failures,
                    window_s: policy.storm_window_ms as f64 / 1000.0,
                    log: process.log.clone(),
                    output: process.output_tail(),
                };
                self.events
                    .record(id, "restart_storm", &format!("failures={failures}"));
                ending.get_or_insert(Ending::StoppedSafe(error));
                continue;
            }
            process.restart_at = Some(now + process.backoff.after_exit(lived, &policy));
            // The dead process's ports stay registered until someone cleans them up.
            self.cleanup_dead_nodes(node, id);
        }
        Ok(ending)
    }

    /// Watches the live children: one that has started and stopped beating is hung (killed,
    /// so that reaping restarts it); one still starting is left alone, its slowness noted,
    /// until its start-up budget has passed, which stops the set.
    fn watch_children(&mut self, now: Instant) -> Option<Ending> {
        let policy = self.options.launch.restart.clone();
        for index in 0..self.processes.len() {
            let p = &self.processes[index];
            if p.child.is_none() {
                continue;
            }
            if p.ready {
                if let Some(silent) = silent_too_long(now, p.last_beat, deadlines::HEARTBEAT) {
                    self.kill_hung(index, silent);
                    self.processes[index].last_beat = now;
                }
                continue;
            }
            let budget = p.spec.startup_budget(&policy);
            match startup_progress(now, p.started_at, budget, p.slow_noted_at) {
                Startup::Starting => {}
                Startup::Slow(waited) => {
                    let p = &mut self.processes[index];
                    p.slow_noted_at = Some(now);
                    let (id, name) = (p.id, p.spec.name.clone());
                    tracing::warn!(
                        service = %name,
                        "still starting after {:.0} s (start-up budget {:.0} s)",
                        waited.as_secs_f64(),
                        budget.as_secs_f64()
                    );
                    self.events.record(
                        id,
                        "slow_start",
                        &format!(
                            "waited_ms={} budget_ms={}",
                            waited.as_millis(),
                            budget.as_millis()
                        ),
                    );
                }
                Startup::OverBudget(waited) => {
                    let id = p.id;
                    self.events.record(
                        id,
                        "startup_over_budget",
                        &format!("waited_ms={}", waited.as_millis()),
                    );
                    return Some(Ending::StoppedSafe(StoppedSafe::StartupOverBudget {
                        service: p.spec.name.clone(),
                        budget_s: budget.as_secs_f64(),
                        log: p.log.clone(),
                        output: p.output_tail(),
                    }));
                }
            }
        }
        None
    }

    /// A heartbeat of `service`'s current incarnation: the first one says it has started.
    fn note_started(&mut self, service: ServiceId, incarnation: u64, now: Instant) {
        let Some(process) = self
            .processes
            .iter_mut()
            .find(|p| p.id == service && p.incarnation == incarnation && p.child.is_some())
        else {
            return;
        };
        if process.ready {
            return;
        }
        process.ready = true;
        process.last_beat = now;
        let startup_ms = now
            .saturating_duration_since(process.started_at)
            .as_millis();
        let detail = format!("incarnation={incarnation} startup_ms={startup_ms}");
        self.events.record(service, "ready", &detail);
    }

    fn spawn_all(&mut self) -> anyhow::Result<()> {
        (0..self.processes.len()).try_for_each(|index| self.spawn(index))
    }

    fn restart_due(&mut self) -> anyhow::Result<()> {
        let now = Instant::now();
        for index in 0..self.processes.len() {
            let process = &mut self.processes[index];
            if process.child.is_none() && process.restart_at.is_some_and(|t| now >= t) {
                let id = process.id;
                if let Some(later) = self.sweep_half_made(id) {
                    self.processes[index].restart_at = Some(later);
                    continue;
                }
                let process = &mut self.processes[index];
                process.incarnation += 1;
                let incarnation = process.incarnation;
                self.spawn(index)?;
                self.events
                    .record(id, "restart", &format!("incarnation={incarnation}"));
            }
        }
        Ok(())
    }

    /// Removes the services that a killed child left half-made, so that its next start (or any
    /// other child's) does not hang on them. Returns when to try again if one is still too
    /// young to tell from a live creator's.
    fn sweep_half_made(&mut self, id: ServiceId) -> Option<Instant> {
        match self.domain.sweep_half_made(std::time::SystemTime::now()) {
            Ok(sweep) => {
                for path in &sweep.removed {
                    self.events.record(
                        id,
                        "removed_half_made_service",
                        &path.display().to_string(),
                    );
                }
                let wait = sweep.retry_at?.duration_since(std::time::SystemTime::now());
                wait.ok().map(|wait| Instant::now() + wait)
            }
            Err(e) => {
                self.events.record(id, "sweep_failed", &e.to_string());
                None
            }
        }
    }

    /// Stops every child: control first, coilbus (which zeroes the coils), then the rest.
    fn shutdown(&mut self) {
        for id in self.options.launch.shutdown_order() {
            let Some(index) = self.processes.iter().position(|p| p.id == id) else {
                continue;
            };
            let Some(mut child) = self.processes[index].child.take() else {
                continue;
            };
            let pid = Pid::from_raw(child.id() as i32);
            let _ = kill(pid, Signal::SIGCONT);
            let _ = kill(pid, Signal::SIGTERM);
            let deadline = Instant::now() + CHILD_STOP_GRACE;
            let status = loop {
                match child.try_wait() {
                    Ok(Some(status)) => break Some(status),
                    Ok(None) if Instant::now() < deadline => std::thread::sleep(CHILD_STOP_POLL),
                    _ => {
                        let _ = child.kill();
                        break child.wait().ok();
                    }
                }
            };
            self.events.record(
                id,
                "stopped",
                &status.map(|s| s.to_string()).unwrap_or_default(),
            );
        }
    }
}

/// What `run` settles before anything starts.
struct Plan {
    scenario: Scenario,
    scenario_path: PathBuf,
    run_dir: PathBuf,
    /// Each process's executable, in launch order.
    executables: Vec<PathBuf>,
}

/// Runs the set until the plant finishes, a signal arrives, a child rejects its
/// configuration, or the wall-time limit passes.
pub fn run(options: SupervisorOptions) -> anyhow::Result<()> {
    let plan = plan(&options)?;
    check_configuration(&options.launch, &plan)?;
    let viewer = start_viewer(options.viewer)?;
    let domain = clean_domain(&options)?;
    let base_env = run_environment(&options, &plan, viewer.as_ref().map(|(_, url)| url));
    // The supervisor joins the run like any service.
    for (k, v) in &base_env {
        std::env::set_var(k, v);
    }
    let rt = Runtime::start(ServiceId::Supervisor)?;
    let started = Instant::now();
    if let Err(e) = viewer_layout().send(&rt.rec, Default::default()) {
        tracing::warn!("could not send the viewer layout: {e}");
    }
    tracing::info!(
        run_dir = %plan.run_dir.display(),
        scenario = %plan.scenario_path.display(),
        mode = ?plan.scenario.run.mode,
        rig = %plan.scenario.rig_path().display(),
        "supervisor starting the set"
    );
    let mut supervisor = Supervisor::new(&options, &plan, base_env, &rt, domain)?;
    // Dead nodes of an earlier set (left when clients of another kind kept its files).
    supervisor.cleanup_dead_nodes(&rt.node, ServiceId::Supervisor);
    let heartbeats = Heartbeats::connect(&rt, &supervisor.processes)?;
    let ending = supervisor
        .spawn_all()
        .and_then(|()| monitor(&mut supervisor, &rt, &heartbeats));
    let coil_resistance_ohm = plan
        .scenario
        .rig()
        .ok()
        .map(|rig| rig.coil_limits().coil_resistance_ohm);
    let summary = SummaryContext {
        started,
        coil_resistance_ohm,
    };
    finish(
        supervisor,
        rt,
        heartbeats,
        viewer,
        &plan.run_dir,
        ending,
        summary,
    )
}

/// The set's iceoryx2 domain (prefix and root), cleaned of whatever an earlier set with the same
/// prefix left behind (a crash, a SIGKILL, a child killed while it created a service). Refuses
/// to start beside a live set of the same prefix. Beside a live client of another kind (a
/// reader in another language, say) it only removes the half-made services, and the dead
/// nodes' resources once the supervisor's node exists.
fn clean_domain(options: &SupervisorOptions) -> anyhow::Result<Domain> {
    let config = millinav_kit::iceoryx_config(Some(&options.iox_prefix), Some(&options.iox_root))?;
    let domain = Domain::of(&config);
    let (set, clients): (Vec<_>, Vec<_>) = domain
        .live_nodes()?
        .into_iter()
        .partition(|node| is_set_node(&node.name));
    if !set.is_empty() {
        let who: Vec<String> = set
            .iter()
            .map(|n| format!("{} (pid {})", n.name, n.pid))
            .collect();
        bail!(
            "another set is running with --iox-prefix {} under --iox-root {}: {}. Stop it \
             (`millinav ctl stop` with that prefix and root) or give this run its own prefix",
            options.iox_prefix,
            options.iox_root.display(),
            who.join(", ")
        );
    }
    if clients.is_empty() {
        let removed = domain.wipe()?;
        if removed.files + removed.shared_memory > 0 {
            tracing::info!(
                files = removed.files,
                shared_memory = removed.shared_memory,
                "removed what an earlier set with this prefix left behind"
            );
        }
    } else {
        tracing::info!(
            ?clients,
            "clients of another kind are connected to this prefix: keeping its files"
        );
        domain.sweep_half_made(std::time::SystemTime::now())?;
    }
    Ok(domain)
}

/// A node of a millinav set: the kit names them `<service>-<incarnation>`.
fn is_set_node(name: &str) -> bool {
    name.rsplit_once('-').is_some_and(|(service, incarnation)| {
        ServiceId::from_name(service).is_some() && incarnation.parse::<u64>().is_ok()
    })
}

/// What the run summary needs from `run` beyond the supervisor.
struct SummaryContext {
    started: Instant,
    coil_resistance_ohm: Option<f64>,
}

impl Supervisor {
    /// The supervisor's part of the run summary.
    fn facts(&self, ending: &anyhow::Result<Ending>, context: &SummaryContext) -> RunFacts {
        let mut deadline_misses = BTreeMap::new();
        for ((service, _), misses) in &self.deadline_misses {
            if let Some(id) = ServiceId::from_repr(*service) {
                *deadline_misses.entry(id.name().to_string()).or_insert(0) += misses;
            }
        }
        let restarts = self
            .processes
            .iter()
            .map(|p| (p.spec.name.clone(), p.incarnation))
            .collect();
        RunFacts {
            ending: match ending {
                Ok(Ending::RunComplete) => "run complete".into(),
                Ok(Ending::Signal) => "stopped by a signal (Ctrl-C or SIGTERM)".into(),
                Ok(Ending::OperatorStop) => "stopped by the operator (millinav ctl stop)".into(),
                Ok(Ending::WallTimeLimit) => {
                    format!("wall-time limit ({:?}) reached", self.options.max_wall_time)
                }
                Ok(Ending::ConfigError(_)) => "a service rejected its configuration".into(),
                Ok(Ending::StoppedSafe(StoppedSafe::StartupOverBudget { service, .. })) => {
                    format!("stopped safe: {service} did not start within its budget")
                }
                Ok(Ending::StoppedSafe(StoppedSafe::RestartStorm { service, .. })) => {
                    format!("stopped safe: {service} kept failing (restart storm)")
                }
                Ok(Ending::BoardFault(name)) => {
                    format!("coil-driver board fault `{name}`: coils held at zero")
                }
                Err(e) => format!("supervisor failed: {e:#}"),
            },
            duration_s: context.started.elapsed().as_secs_f64(),
            deadline_misses,
            restarts,
            coil_resistance_ohm: context.coil_resistance_ohm,
            recording: None,
        }
    }
}

/// Loads the scenario (its own errors name the file and field), makes the run directory and
/// finds every executable.
fn plan(options: &SupervisorOptions) -> anyhow::Result<Plan> {
    let scenario = Scenario::load(&options.scenario)?;
    // One clear error for a bad rig file, before five services each report it.
    scenario.rig()?;
    std::fs::create_dir_all(&options.run_dir)
        .with_context(|| format!("creating the run directory {}", options.run_dir.display()))?;
    Ok(Plan {
        scenario,
        scenario_path: std::fs::canonicalize(&options.scenario)?,
        run_dir: std::fs::canonicalize(&options.run_dir)?,
        executables: options.launch.executables(&options.bin_dir)?,
    })
}

/// Every child checks its configuration (`--check`) before any of them starts.
fn check_configuration(launch: &LaunchFile, plan: &Plan) -> anyhow::Result<()> {
    let targets: Vec<CheckTarget> = launch
        .processes
        .iter()
        .zip(&plan.executables)
        .map(|(spec, executable)| CheckTarget {
            name: spec.name.clone(),
            executable: executable.clone(),
            args: spec.args.clone(),
        })
        .collect();
    let failures = preflight::check_all(
        &targets,
        &plan.scenario_path,
        &plan.run_dir.join("logs"),
        preflight::CHECK_TIMEOUT,
    )
    .context("running the configuration checks")?;
    if failures.is_empty() {
        Ok(())
    } else {
        Err(FailFast::ChecksFailed(failures).into())
    }
}

/// The environment every process of the run gets (namespace, run dir, clock, recording).
fn run_environment(
    options: &SupervisorOptions,
    plan: &Plan,
    viewer_url: Option<&String>,
) -> Vec<(String, String)> {
    let recording_id = format!(
        "millinav-{}-{}",
        plan.run_dir
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("run"),
        clock::wall_ns()
    );
    let mut env = vec![
        (env_vars::IOX_PREFIX.to_string(), options.iox_prefix.clone()),
        (
            env_vars::IOX_ROOT.to_string(),
            options.iox_root.to_string_lossy().into_owned(),
        ),
        (
            env_vars::RUN_DIR.to_string(),
            plan.run_dir.to_string_lossy().into_owned(),
        ),
        (env_vars::RECORDING_ID.to_string(), recording_id),
        (
            env_vars::CLOCK_EPOCH_NS.to_string(),
            clock::monotonic_ns().to_string(),
        ),
    ];
    if let Some(url) = viewer_url {
        env.push((env_vars::RERUN_CONNECT.to_string(), url.clone()));
    }
    if options.session {
        env.push((env_vars::SESSION.to_string(), "1".to_string()));
    }
    if options.record_frames {
        env.push((env_vars::RECORD_FRAMES.to_string(), "1".to_string()));
    }
    env
}

impl Supervisor {
    fn new(
        options: &SupervisorOptions,
        plan: &Plan,
        base_env: Vec<(String, String)>,
        rt: &Runtime,
        domain: Domain,
    ) -> anyhow::Result<Self> {
        let log_dir = plan.run_dir.join("logs");
        let processes = options
            .launch
            .processes
            .iter()
            .filter_map(|spec| {
                ServiceId::from_name(&spec.name)
                    .map(|id| ManagedProcess::new(spec, id, &log_dir, &options.launch.restart))
            })
            .collect();
        Ok(Self {
            options: SupervisorOptions {
                scenario: plan.scenario_path.clone(),
                run_dir: plan.run_dir.clone(),
                ..options.clone()
            },
            processes,
            events: EventLog::new(&plan.run_dir, rt.rec.clone())?,
            base_env,
            deadline_misses: BTreeMap::new(),
            domain,
        })
    }
}

/// Stops the set safe-state first, leaves the viewer to the user, merges the recordings, and
/// turns the ending into the run's result.
fn finish(
    mut supervisor: Supervisor,
    rt: Runtime,
    heartbeats: Heartbeats,
    viewer: Option<(Child, String)>,
    run_dir: &Path,
    ending: anyhow::Result<Ending>,
    context: SummaryContext,
) -> anyhow::Result<()> {
    if let Err(e) = &ending {
        tracing::error!("supervisor loop failed: {e:#}");
    }
    supervisor.shutdown();
    // A child killed because it did not stop in its grace, or one whose resources could not be
    // removed when it died mid-run, leaves shared-memory segments behind in /dev/shm; the
    // supervisor is the last node of the set, so it removes them before it leaves.
    supervisor.cleanup_dead_nodes(&rt.node, ServiceId::Supervisor);
    supervisor
        .events
        .record(ServiceId::Supervisor, "shutdown_complete", "");
    if let Some((mut child, _)) = viewer {
        // The viewer belongs to the user now; just stop tracking it.
        let _ = child.try_wait();
    }
    drop(heartbeats);
    let _ = rt.rec.flush_blocking();
    let mut facts = supervisor.facts(&ending, &context);
    let domain = supervisor.domain.clone();
    drop(supervisor);
    drop(rt);
    leave_nothing_behind(&domain);
    facts.recording = match merge_recordings(run_dir) {
        Ok(Some(path)) => {
            tracing::info!(recording = %path.display(), "recording written");
            Some(path)
        }
        Ok(None) => None,
        Err(e) => {
            tracing::warn!("could not merge recordings: {e:#}");
            None
        }
    };
    match RunSummary::compute(run_dir, &facts) {
        Ok(summary) => {
            print!("{}", summary.text());
            match summary.write_json() {
                Ok(path) => println!("  summary:          {}", path.display()),
                Err(e) => tracing::warn!("could not write the run summary: {e}"),
            }
        }
        Err(e) => tracing::warn!("no run summary: {e}"),
    }
    match ending? {
        Ending::ConfigError(error) => Err(error.into()),
        Ending::StoppedSafe(error) => Err(error.into()),
        Ending::BoardFault(name) => bail!(
            "the run stopped safe: the coil-driver board reported `{name}` and coilbus held the \
             coils at zero (the reason is in {}/coilbus_link.csv and logs/coilbus.log)",
            run_dir.display()
        ),
        Ending::RunComplete | Ending::Signal | Ending::OperatorStop | Ending::WallTimeLimit => {
            Ok(())
        }
    }
}

/// Removes the set's iceoryx2 files once its last node (the supervisor's) is gone, so that no
/// half-made or stale service outlives the run. Clients of another kind still connected keep
/// them.
fn leave_nothing_behind(domain: &Domain) {
    match domain.live_nodes() {
        Ok(live) if live.is_empty() => match domain.wipe() {
            Ok(removed) => tracing::debug!(?removed, "iceoryx2 files of the set removed"),
            Err(e) => tracing::warn!("could not remove the set's iceoryx2 files: {e}"),
        },
        Ok(live) => tracing::info!(
            ?live,
            "nodes are still connected to the set's prefix: its iceoryx2 files stay"
        ),
        Err(e) => tracing::warn!("could not list the set's iceoryx2 nodes: {e}"),
    }
}
