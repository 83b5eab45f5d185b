//! End to end through the real process set in real-time mode: `millinav run` (supervisor +
//! plant, vision, flow, control, coilbus) on the short scenario with `mode = "realtime"`.
//!
//! Timestamps, all CLOCK_MONOTONIC: frame capture = run epoch + `grab_time_ns` carried by
//! every Pose/CoilCommand (the frame entering the set; the twin's camera adds no latency here) (the epoch is read from a child's `MILLINAV_CLOCK_EPOCH_NS`); Pose and
//! CoilCommand arrival = this process subscribed next to control and coilbus (same topics,
//! same QoS); serial write = the emulated Teensy's receipt of the frame on its pty
//! (`teensy_events.csv`).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use millinav_kit::clock::monotonic_ns;
use millinav_kit::iceoryx2::prelude::*;
use millinav_kit::ports::Inbox;
use millinav_kit::runlog::{self, TeensyEventRow, TruthRow};
use millinav_kit::{iceoryx_config, iox};
use shm_schemas::{services, CoilCommand, Pose};

use crate::BenchError;

/// What one run gave.
#[derive(Debug, Default)]
pub struct E2eResult {
    /// capture → Pose received (ns), per frame in the window.
    pub pose_ns: Vec<f64>,
    /// capture → CoilCommand received next to coilbus (ns).
    pub command_ns: Vec<f64>,
    /// capture → frame received by the Teensy over serial (ns).
    pub serial_ns: Vec<f64>,
    /// Frames the plant published in the window.
    pub frames: usize,
    /// Frames whose command reached the Teensy.
    pub commanded: usize,
    /// Frames without a command at the Teensy within one frame period of capture.
    pub deadline_misses: usize,
    pub window_s: f64,
    pub frame_period_s: f64,
    pub run_dir: PathBuf,
}

impl E2eResult {
    pub fn closed_loop_hz(&self) -> f64 {
        if self.window_s > 0.0 {
            self.commanded as f64 / self.window_s
        } else {
            0.0
        }
    }
    pub fn frame_hz(&self) -> f64 {
        if self.window_s > 0.0 {
            self.frames as f64 / self.window_s
        } else {
            0.0
        }
    }
}

/// Writes the real-time variant of the scenario `src` (relative paths from the workspace root).
fn write_scenario(src: &Path, dir: &Path, duration_s: f64) -> Result<(PathBuf, f64), BenchError> {
    let src = crate::workspace_root().join(src);
    let text = std::fs::read_to_string(&src)?;
    let mut table: toml::Table = text
        .parse()
        .map_err(|e| BenchError::Setup(format!("{}: {e}", src.display())))?;
    let run = table
        .get_mut("run")
        .and_then(|r| r.as_table_mut())
        .ok_or_else(|| BenchError::Setup(format!("{}: no [run]", src.display())))?;
    run.insert("mode".into(), toml::Value::String("realtime".into()));
    run.insert("duration_s".into(), toml::Value::Float(duration_s));
    let period_ms = run
        .get("frame_period_ms")
        .and_then(|v| v.as_float())
        .unwrap_or(10.0);
    let path = dir.join("realtime.toml");
    std::fs::write(
        &path,
        toml::to_string(&table).map_err(|e| BenchError::Setup(e.to_string()))?,
    )?;
    Ok((path, period_ms * 1e-3))
}

/// The run epoch, from the environment of any process of this run (found by its prefix).
fn find_epoch(prefix: &str) -> Option<u64> {
    let want = format!("MILLINAV_IOX_PREFIX={prefix}");
    for entry in std::fs::read_dir("/proc").ok()?.flatten() {
        let Ok(env) = std::fs::read(entry.path().join("environ")) else {
            continue;
        };
        let vars: Vec<&[u8]> = env.split(|&b| b == 0).collect();
        if !vars.contains(&want.as_bytes()) {
            continue;
        }
        for v in vars {
            if let Some(rest) = v.strip_prefix(b"MILLINAV_CLOCK_EPOCH_NS=") {
                if let Some(epoch) = std::str::from_utf8(rest).ok().and_then(|s| s.parse().ok()) {
                    return Some(epoch);
                }
            }
        }
    }
    None
}

/// (frame_seq, capture run-clock ns, arrival monotonic ns) of every message on `topic`.
type Arrivals = Vec<(u64, u64, u64)>;

fn subscribe<T>(
    prefix: String,
    root: PathBuf,
    topic: &'static str,
    stop: Arc<AtomicBool>,
    key: fn(&T) -> (u64, u64),
) -> std::thread::JoinHandle<Result<Arrivals, BenchError>>
where
    T: std::fmt::Debug + millinav_kit::iceoryx2::prelude::ZeroCopySend + Copy + 'static,
{
    std::thread::spawn(move || {
        let config = iceoryx_config(Some(&prefix), Some(&root))?;
        let name = format!("bench-e2e-{}", topic.replace('/', "-"));
        let node = NodeBuilder::new()
            .name(&NodeName::new(&name).map_err(iox("node name"))?)
            .config(&config)
            .create::<ipc::Service>()
            .map_err(iox("node"))?;
        let inbox = Inbox::<T>::new(&node, topic)?;
        let mut out = Vec::new();
        while !stop.load(Ordering::Relaxed) {
            inbox.wait(Duration::from_millis(50));
            let msgs = inbox.receive_all()?;
            let now = monotonic_ns();
            for m in msgs {
                let (seq, capture) = key(&m);
                out.push((seq, capture, now));
            }
        }
        Ok(out)
    })
}

/// Runs the process set for `duration_s` of real time and measures it.
pub fn run(
    bin_dir: &Path,
    scenario: &Path,
    dir: &Path,
    duration_s: f64,
) -> Result<E2eResult, BenchError> {
    let supervisor = bin_dir.join("millinav");
    if !supervisor.is_file() {
        return Err(BenchError::Setup(format!(
            "{} not found: build the process set first (cargo build --release --bins -p millinav-supervisor -p millinav-plant -p millinav-vision -p millinav-flow -p millinav-control -p millinav-coilbus)",
            supervisor.display()
        )));
    }
    let (scenario, period_s) = write_scenario(scenario, dir, duration_s)?;
    let run_dir = dir.join("run");
    let prefix = format!("benche2e{}_", std::process::id());
    let root = dir.join("e2e-iox");
    let stop = Arc::new(AtomicBool::new(false));
    let poses = subscribe::<Pose>(
        prefix.clone(),
        root.clone(),
        services::POSE,
        stop.clone(),
        |p| (p.stamp.seq, p.stamp.grab_time_ns),
    );
    let commands = subscribe::<CoilCommand>(
        prefix.clone(),
        root.clone(),
        services::COMMAND,
        stop.clone(),
        |c| (c.stamp.seq, c.stamp.grab_time_ns),
    );
    let log = std::fs::File::create(dir.join("e2e-supervisor.log"))?;
    let mut child = Command::new(&supervisor)
        .arg("run")
        .arg(&scenario)
        .arg("--run-dir")
        .arg(&run_dir)
        .args(["--viewer", "none", "--iox-prefix", &prefix])
        .arg("--iox-root")
        .arg(&root)
        .stdin(Stdio::null())
        .stdout(log.try_clone()?)
        .stderr(log)
        .spawn()?;
    let started = Instant::now();
    let limit = Duration::from_secs_f64(duration_s + 60.0);
    let mut epoch = None;
    let status = loop {
        if epoch.is_none() && started.elapsed() > Duration::from_millis(500) {
            epoch = find_epoch(&prefix);
        }
        if let Some(status) = child.try_wait()? {
            break status;
        }
        if started.elapsed() > limit {
            let _ = child.kill();
            break child.wait()?;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    stop.store(true, Ordering::Relaxed);
    let join = |h: std::thread::JoinHandle<Result<Arrivals, BenchError>>| {
        h.join()
            .map_err(|_| BenchError::Setup("subscriber thread panicked".into()))?
    };
    let poses = join(poses)?;
    let commands = join(commands)?;
    let epoch = epoch.ok_or_else(|| {
        BenchError::Setup(format!(
            "could not read the run epoch of the process set (supervisor exited {status}; see {})",
            dir.join("e2e-supervisor.log").display()
        ))
    })?;
    analyse(&run_dir, epoch, period_s, &poses, &commands)
}

fn first_by_seq(arrivals: &Arrivals) -> HashMap<u64, (u64, u64)> {
    let mut m = HashMap::new();
    for &(seq, capture, at) in arrivals {
        m.entry(seq).or_insert((capture, at));
    }
    m
}

fn analyse(
    run_dir: &Path,
    epoch: u64,
    period_s: f64,
    poses: &Arrivals,
    commands: &Arrivals,
) -> Result<E2eResult, BenchError> {
    let setup = |e: runlog::RunLogError| BenchError::Setup(e.to_string());
    let teensy: Vec<TeensyEventRow> = runlog::read_run_dir(run_dir).map_err(setup)?;
    let mut serial: HashMap<u64, u64> = HashMap::new();
    for event in teensy.iter().filter(|e| e.event == "command") {
        if let Some(seq) = event.frame_seq {
            serial.entry(seq).or_insert(event.monotonic_ns);
        }
    }
    let truth: Vec<TruthRow> = runlog::read_run_dir(run_dir).map_err(setup)?;
    let last_frame = truth.iter().map(|row| row.frame_seq).max().unwrap_or(0);
    let poses = first_by_seq(poses);
    let commands = first_by_seq(commands);
    let captures: HashMap<u64, u64> = commands
        .iter()
        .map(|(&s, &(c, _))| (s, c))
        .chain(poses.iter().map(|(&s, &(c, _))| (s, c)))
        .collect();
    // Window: from 1 s after the first command (every process up) to 0.2 s before the end.
    let first = commands
        .keys()
        .filter(|&&s| s != shm_schemas::NO_FRAME)
        .min()
        .copied()
        .ok_or_else(|| BenchError::Setup("no CoilCommand was seen during the run".into()))?;
    let per_s = (1.0 / period_s).round() as u64;
    let (s0, s1) = (first + per_s, last_frame.saturating_sub(per_s / 5));
    if s1 <= s0 {
        return Err(BenchError::Setup(
            "run too short for a measurement window".into(),
        ));
    }
    let mut r = E2eResult {
        frame_period_s: period_s,
        run_dir: run_dir.to_owned(),
        ..Default::default()
    };
    let period_ns = (period_s * 1e9) as u64;
    for seq in s0..=s1 {
        r.frames += 1;
        let Some(&capture) = captures.get(&seq) else {
            r.deadline_misses += 1;
            continue;
        };
        let cap = epoch + capture;
        if let Some(&(_, at)) = poses.get(&seq) {
            r.pose_ns.push(at.saturating_sub(cap) as f64);
        }
        if let Some(&(_, at)) = commands.get(&seq) {
            r.command_ns.push(at.saturating_sub(cap) as f64);
        }
        match serial.get(&seq) {
            Some(&at) => {
                r.commanded += 1;
                let l = at.saturating_sub(cap);
                r.serial_ns.push(l as f64);
                if l > period_ns {
                    r.deadline_misses += 1;
                }
            }
            None => r.deadline_misses += 1,
        }
    }
    // Window length on the plant's clock: frames are published every period.
    r.window_s = (s1 - s0 + 1) as f64 * period_s;
    // Plant lag: if the plant could not keep its period, capture times tell.
    if let (Some(&c0), Some(&c1)) = (captures.get(&s0), captures.get(&s1)) {
        r.window_s = r
            .window_s
            .max((c1.saturating_sub(c0)) as f64 * 1e-9 + period_s);
    }
    Ok(r)
}
