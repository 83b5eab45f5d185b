//! supervisor: launches the process set, reaps and restarts children with backoff, watches
//! their heartbeats (event services with deadlines), cleans the iceoryx2 resources of dead
//! nodes before a restart, and shuts down safe-state first. Everything it does is appended to
//! `<run_dir>/supervisor_events.csv` so runs and tests can be audited afterwards.

pub mod launch;

use std::collections::BTreeMap;
use std::io::Write;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use millinav_kit::iceoryx2::port::listener::Listener;
use millinav_kit::iceoryx2::prelude::*;
use millinav_kit::iceoryx2::waitset::WaitSetRunResult;
use millinav_kit::ports::{heartbeat_listener, Inbox};
use millinav_kit::scenario::Scenario;
use millinav_kit::{clock, env_vars, recording, rerun, Runtime};
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use shm_schemas::{deadlines, services, Heartbeat, ServiceId};

use crate::launch::{LaunchFile, ProcessSpec};

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
}

/// Appends timestamped events to `supervisor_events.csv`.
pub struct EventLog {
    file: std::fs::File,
    rec: rerun::RecordingStream,
}

impl EventLog {
    fn new(path: &Path, rec: rerun::RecordingStream) -> anyhow::Result<Self> {
        let mut file = std::fs::File::create(path)?;
        writeln!(file, "monotonic_ns,service,event,detail")?;
        Ok(Self { file, rec })
    }

    pub fn record(&mut self, service: ServiceId, event: &str, detail: &str) {
        let _ = writeln!(
            self.file,
            "{},{},{event},{}",
            clock::monotonic_ns(),
            service.name(),
            detail.replace(',', ";")
        );
        let _ = self.file.flush();
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
    backoff: Duration,
    last_beat: Instant,
}

/// The running set.
pub struct Supervisor {
    options: SupervisorOptions,
    processes: Vec<ManagedProcess>,
    pub events: EventLog,
    base_env: Vec<(String, String)>,
}

impl Supervisor {
    fn binary_of(&self, spec: &ProcessSpec) -> PathBuf {
        match &spec.binary {
            Some(b) if b.is_absolute() => b.clone(),
            Some(b) => self.options.bin_dir.join(b),
            None => self.options.bin_dir.join(format!("millinav-{}", spec.name)),
        }
    }

    fn spawn(&mut self, index: usize) -> anyhow::Result<()> {
        let binary = self.binary_of(&self.processes[index].spec);
        let log_dir = self.options.run_dir.join("logs");
        std::fs::create_dir_all(&log_dir)?;
        let process = &self.processes[index];
        let name = process.spec.name.clone();
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(log_dir.join(format!("{name}.log")))?;
        let mut command = Command::new(&binary);
        command
            .arg("--scenario")
            .arg(&self.options.scenario)
            .args(&process.spec.args)
            .envs(self.base_env.iter().map(|(k, v)| (k.as_str(), v.as_str())))
            .env(env_vars::INCARNATION, process.incarnation.to_string())
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
        process.started_at = now;
        process.last_beat = now;
        process.restart_at = None;
        self.events
            .record(id, "spawn", &format!("pid={pid} incarnation={incarnation}"));
        Ok(())
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

    /// Reaps exited children; returns the service of a clean plant exit (run complete).
    fn reap(&mut self, node: &Node<ipc::Service>) -> anyhow::Result<bool> {
        let mut run_complete = false;
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
            if id == ServiceId::Plant && status.success() {
                self.events.record(id, "run_complete", &detail);
                run_complete = true;
                continue;
            }
            self.events.record(id, "exit", &detail);
            if !process.spec.restart {
                continue;
            }
            if lived >= Duration::from_millis(policy.stable_after_ms) {
                process.backoff = Duration::from_millis(policy.initial_backoff_ms);
            }
            process.restart_at = Some(Instant::now() + process.backoff);
            process.backoff =
                (process.backoff * 2).min(Duration::from_millis(policy.max_backoff_ms));
            // The dead process's ports stay registered until someone cleans them up.
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
        Ok(run_complete)
    }

    fn restart_due(&mut self) -> anyhow::Result<()> {
        let now = Instant::now();
        for index in 0..self.processes.len() {
            let process = &mut self.processes[index];
            if process.child.is_none() && process.restart_at.is_some_and(|t| now >= t) {
                process.incarnation += 1;
                let id = process.id;
                let incarnation = process.incarnation;
                self.spawn(index)?;
                self.events
                    .record(id, "restart", &format!("incarnation={incarnation}"));
            }
        }
        Ok(())
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
            let deadline = Instant::now() + Duration::from_secs(5);
            let status = loop {
                match child.try_wait() {
                    Ok(Some(status)) => break Some(status),
                    Ok(None) if Instant::now() < deadline => {
                        std::thread::sleep(Duration::from_millis(10))
                    }
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

/// Starts a Rerun viewer when asked (or when `auto` and one is usable); returns its gRPC URL.
fn start_viewer(mode: ViewerMode) -> anyhow::Result<Option<(Child, String)>> {
    let has_display =
        std::env::var_os("DISPLAY").is_some() || std::env::var_os("WAYLAND_DISPLAY").is_some();
    let wanted = match mode {
        ViewerMode::None => false,
        ViewerMode::Spawn => true,
        ViewerMode::Auto => has_display && which("rerun").is_some(),
    };
    if !wanted {
        return Ok(None);
    }
    let Some(rerun_bin) = which("rerun") else {
        bail!("--viewer spawn: no `rerun` executable on PATH (pip install rerun-sdk==0.36.3)");
    };
    let port = 9876;
    let child = Command::new(rerun_bin)
        .arg("--port")
        .arg(port.to_string())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .process_group(0)
        .spawn()
        .context("spawning the Rerun viewer")?;
    // Give the viewer a moment to open its port before the services connect.
    std::thread::sleep(Duration::from_millis(1500));
    Ok(Some((
        child,
        format!("rerun+http://127.0.0.1:{port}/proxy"),
    )))
}

/// Finds an executable on PATH.
pub fn which(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|dir| dir.join(name))
            .find(|candidate| candidate.is_file())
    })
}

/// Joins the per-process recordings into `<run_dir>/run.rrd` with the Rerun CLI when it is
/// installed (`rerun rrd merge`), otherwise leaves them in `<run_dir>/rrd/` and says so.
pub fn merge_recordings(run_dir: &Path) -> anyhow::Result<Option<PathBuf>> {
    let dir = recording::rrd_dir(run_dir);
    let mut parts: Vec<PathBuf> = match std::fs::read_dir(&dir) {
        Ok(entries) => entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "rrd"))
            .collect(),
        Err(_) => return Ok(None),
    };
    parts.sort();
    if parts.is_empty() {
        return Ok(None);
    }
    let Some(rerun_bin) = which("rerun") else {
        tracing::warn!(
            "`rerun` CLI not found: recordings left as parts in {} (open them together in the viewer)",
            dir.display()
        );
        return Ok(None);
    };
    let out = run_dir.join("run.rrd");
    let status = Command::new(rerun_bin)
        .args(["rrd", "merge"])
        .args(&parts)
        .arg("-o")
        .arg(&out)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .output()
        .context("running `rerun rrd merge`")?;
    if !status.status.success() {
        bail!(
            "`rerun rrd merge` failed: {}",
            String::from_utf8_lossy(&status.stderr).trim()
        );
    }
    Ok(Some(out))
}

/// Runs the set until the plant finishes, a signal arrives, or the wall-time limit passes.
pub fn run(options: SupervisorOptions) -> anyhow::Result<()> {
    // Fail early, with the scenario's own message, before any process starts.
    let scenario = Scenario::load(&options.scenario)?;
    std::fs::create_dir_all(&options.run_dir)?;
    let run_dir = std::fs::canonicalize(&options.run_dir)?;
    let scenario_path = std::fs::canonicalize(&options.scenario)?;
    for spec in &options.launch.processes {
        let probe = match &spec.binary {
            Some(b) if b.is_absolute() => b.clone(),
            Some(b) => options.bin_dir.join(b),
            None => options.bin_dir.join(format!("millinav-{}", spec.name)),
        };
        if !probe.is_file() {
            bail!(
                "executable for {} not found at {} (build with `cargo build --release`)",
                spec.name,
                probe.display()
            );
        }
    }
    let recording_id = format!(
        "millinav-{}-{}",
        run_dir
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("run"),
        clock::wall_ns()
    );
    let viewer = start_viewer(options.viewer)?;
    let mut base_env = vec![
        (env_vars::IOX_PREFIX.to_string(), options.iox_prefix.clone()),
        (
            env_vars::IOX_ROOT.to_string(),
            options.iox_root.to_string_lossy().into_owned(),
        ),
        (
            env_vars::RUN_DIR.to_string(),
            run_dir.to_string_lossy().into_owned(),
        ),
        (env_vars::RECORDING_ID.to_string(), recording_id.clone()),
        (
            env_vars::CLOCK_EPOCH_NS.to_string(),
            clock::monotonic_ns().to_string(),
        ),
    ];
    if let Some((_, url)) = &viewer {
        base_env.push((env_vars::RERUN_CONNECT.to_string(), url.clone()));
    }
    // The supervisor joins the run like any service.
    for (k, v) in &base_env {
        std::env::set_var(k, v);
    }
    let rt = Runtime::start(ServiceId::Supervisor)?;
    tracing::info!(
        run_dir = %run_dir.display(),
        scenario = %scenario_path.display(),
        mode = ?scenario.run.mode,
        "supervisor starting the set"
    );
    let events = EventLog::new(&run_dir.join("supervisor_events.csv"), rt.rec.clone())?;
    let initial_backoff = Duration::from_millis(options.launch.restart.initial_backoff_ms);
    let processes = options
        .launch
        .processes
        .iter()
        .filter_map(|spec| {
            ServiceId::from_name(&spec.name).map(|id| ManagedProcess {
                spec: spec.clone(),
                id,
                child: None,
                incarnation: 0,
                started_at: Instant::now(),
                restart_at: None,
                backoff: initial_backoff,
                last_beat: Instant::now(),
            })
        })
        .collect();
    let mut supervisor = Supervisor {
        options: SupervisorOptions {
            scenario: scenario_path,
            run_dir: run_dir.clone(),
            ..options.clone()
        },
        processes,
        events,
        base_env,
    };

    // A stale set from an earlier crashed run with the same prefix must not confuse this one.
    let cleanup = rt.node.try_cleanup_dead_nodes();
    if cleanup.cleanups > 0 {
        tracing::info!(
            cleaned = cleanup.cleanups,
            "removed resources of dead nodes"
        );
    }
    let listeners: Vec<(ServiceId, Listener<ipc::Service>)> = supervisor
        .processes
        .iter()
        .map(|p| Ok((p.id, heartbeat_listener(&rt.node, p.id)?)))
        .collect::<anyhow::Result<_>>()?;
    let health = Inbox::<Heartbeat>::new(&rt.node, services::HEALTH)?;
    for index in 0..supervisor.processes.len() {
        supervisor.spawn(index)?;
    }

    let outcome = monitor(&mut supervisor, &rt, &listeners, &health);
    if let Err(e) = &outcome {
        tracing::error!("supervisor loop failed: {e:#}");
    }
    supervisor.shutdown();
    supervisor
        .events
        .record(ServiceId::Supervisor, "shutdown_complete", "");
    if let Some((mut child, _)) = viewer {
        // The viewer belongs to the user now; just stop tracking it.
        let _ = child.try_wait();
    }
    drop(listeners);
    drop(health);
    let _ = rt.rec.flush_blocking();
    drop(supervisor);
    drop(rt);
    match merge_recordings(&run_dir) {
        Ok(Some(path)) => tracing::info!(recording = %path.display(), "recording written"),
        Ok(None) => {}
        Err(e) => tracing::warn!("could not merge recordings: {e:#}"),
    }
    outcome
}

fn monitor(
    supervisor: &mut Supervisor,
    rt: &Runtime,
    listeners: &[(ServiceId, Listener<ipc::Service>)],
    health: &Inbox<Heartbeat>,
) -> anyhow::Result<()> {
    let waitset = WaitSetBuilder::new()
        .create::<ipc::Service>()
        .map_err(millinav_kit::iox("waitset"))?;
    let guards = listeners
        .iter()
        .map(|(id, listener)| {
            waitset
                .attach_deadline(listener, deadlines::HEARTBEAT)
                .map(|g| (*id, g))
                .map_err(millinav_kit::iox("attach heartbeat"))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let _tick = waitset
        .attach_interval(Duration::from_millis(50))
        .map_err(millinav_kit::iox("attach tick"))?;
    let start = Instant::now();
    let grace = Duration::from_millis(supervisor.options.launch.restart.startup_grace_ms);
    let mut latest_health: BTreeMap<u32, Heartbeat> = BTreeMap::new();
    loop {
        let mut beating = Vec::new();
        let result = waitset
            .wait_and_process_once_with_timeout(
                |attachment| {
                    for (id, guard) in &guards {
                        if attachment.has_event_from(guard) {
                            beating.push(*id);
                        }
                    }
                    CallbackProgression::Continue
                },
                Duration::from_millis(50),
            )
            .map_err(millinav_kit::iox("waitset"))?;
        if matches!(
            result,
            WaitSetRunResult::TerminationRequest | WaitSetRunResult::Interrupt
        ) {
            supervisor
                .events
                .record(ServiceId::Supervisor, "signal", "shutting down");
            return Ok(());
        }
        for (id, listener) in listeners {
            let mut got = false;
            let _ = listener.try_wait(|_| got = true);
            if got && !beating.contains(id) {
                beating.push(*id);
            }
        }
        let now = Instant::now();
        for process in supervisor.processes.iter_mut() {
            if beating.contains(&process.id) {
                process.last_beat = now;
            }
        }
        for beat in health.receive_all()? {
            latest_health.insert(beat.service, beat);
        }
        if supervisor.reap(&rt.node)? {
            return Ok(());
        }
        // A live process that stopped beating is hung (or stopped): kill it; reap restarts it.
        for index in 0..supervisor.processes.len() {
            let p = &supervisor.processes[index];
            let silent = now.duration_since(p.last_beat);
            if p.child.is_some()
                && now.duration_since(p.started_at) > grace
                && silent > deadlines::HEARTBEAT
            {
                supervisor.kill_hung(index, silent);
                supervisor.processes[index].last_beat = now;
            }
        }
        supervisor.restart_due()?;
        rt.rec
            .set_duration_secs(recording::RUN_TIMELINE, rt.env.run_clock_ns() as f64 * 1e-9);
        for (service, beat) in &latest_health {
            if let Some(id) = ServiceId::from_u32(*service) {
                recording::scalar(
                    &rt.rec,
                    &format!("health/{}/deadline_misses", id.name()),
                    beat.deadline_misses as f64,
                );
            }
        }
        if start.elapsed() > supervisor.options.max_wall_time {
            supervisor.events.record(
                ServiceId::Supervisor,
                "wall_time_limit",
                &format!("{:?}", supervisor.options.max_wall_time),
            );
            return Ok(());
        }
    }
}
