//! coilbus: the only process that talks to the coil drivers. It takes `CoilCommand`s, rejects
//! stale ones, clamps per-coil and total limits on its own authority, writes them to the Teensy
//! over the serial protocol, zeroes the coils when commands miss their deadline, and reconnects
//! when the port goes away.

pub mod board;
pub mod link;
pub mod safety;
pub use millinav_teensy_protocol as protocol;

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use millinav_kit::ports::{Inbox, Outbox};
use millinav_kit::recording;
use millinav_kit::runlog::{LinkEventRow, RunLogRow, RunLogWriter};
use millinav_kit::scenario::Scenario;
use millinav_kit::{ConfigError, Runtime, ServiceLoop};
use serde::{Deserialize, Serialize};
use shm_schemas::{
    deadlines, services, BoardFault, CoilCommand, CoilStatus, ContractError, ControlMode, Flag,
    LinkState, BOARD_STATE_UNKNOWN, MAX_COILS, NO_FRAME,
};

use crate::board::{BoardMonitor, TelemetryTolerance};
use crate::link::SerialLink;
use crate::protocol::{AckStatus, CoilValues, Message, FLAG_SAFE_ZERO};
use crate::safety::{clamp_currents, CurrentLimits, StaleFilter};

/// Serial-link changes (`open`, `lost`) in a run directory: monotonic_ns,event,detail.
pub const LINK_EVENTS_CSV: &str = <LinkEventRow as RunLogRow>::FILE_NAME;

pub use millinav_teensy_protocol::EMULATED_PORT_LINK;

/// `[coilbus]` section of a scenario.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CoilbusConfig {
    /// Serial device of the Teensy, or `auto` for the plant's emulated Teensy in the run dir.
    pub port: String,
    pub baud: u32,
    /// Lowers every coil's current limit (A) below the rig's for this run; never raises it.
    pub max_current_a: Option<f64>,
    /// Lowers the rig's total power limit (W) for this run; never raises it.
    pub max_total_power_w: Option<f64>,
    /// Coils this bus drives (at most `MAX_COILS`; default: the rig's count); a command for
    /// another count is rejected.
    pub coil_count: Option<usize>,
    /// Zero the coils when no command was accepted for this long.
    pub command_deadline_ms: u64,
    /// Period of the housekeeping tick (reconnect, telemetry, safe-state keepalive).
    pub tick_ms: u64,
    /// `[coilbus.telemetry]`: how far the board's telemetry may stray from the command.
    pub telemetry: TelemetryTolerance,
    /// The watchdog the board is configured with, ms: no accepted command for this long and
    /// the board turns its outputs off (it accepts 20–2000 ms).
    pub board_watchdog_ms: u16,
}

impl Default for CoilbusConfig {
    fn default() -> Self {
        Self {
            port: "auto".into(),
            baud: 115_200,
            max_current_a: None,
            max_total_power_w: None,
            coil_count: None,
            command_deadline_ms: deadlines::COMMAND.as_millis() as u64,
            tick_ms: 20,
            telemetry: TelemetryTolerance::default(),
            board_watchdog_ms: 250,
        }
    }
}

/// What coilbus runs with: its table and the rig's limits and coil count, resolved.
#[derive(Debug, Clone)]
pub struct CoilbusSetup {
    pub config: CoilbusConfig,
    pub limits: CurrentLimits,
    pub coil_count: usize,
}

impl CoilbusConfig {
    pub fn port_path(&self, run_dir: &std::path::Path) -> PathBuf {
        if self.port == "auto" {
            run_dir.join(EMULATED_PORT_LINK)
        } else {
            PathBuf::from(&self.port)
        }
    }
}

/// Why a command was not driven.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CommandError {
    #[error(
        "CoilCommand for {got} coils rejected: coilbus drives {expected} coils, nothing driven \
         (control and coilbus are configured for different rigs)"
    )]
    CoilCount { got: u32, expected: usize },
    #[error("malformed CoilCommand rejected, nothing driven: {0}")]
    Malformed(#[from] ContractError),
    #[error("[coilbus] coil_count = {0}: must be 1 to {max}", max = MAX_COILS)]
    BadConfiguredCount(usize),
}

/// Log the first rejection of a kind and then every this many (a wrong rig rejects every frame).
const REJECTION_LOG_EVERY: u64 = 100;

/// The coilbus decision logic, independent of ports so it can be tested directly.
pub struct CoilBus {
    limits: CurrentLimits,
    coil_count: usize,
    deadline: Duration,
    stale: StaleFilter,
    last_accepted: Option<Instant>,
    /// Whether this process has written its start-up safe zero to the board.
    start_zero_written: bool,
    /// The board's telemetry against what this bus sent it.
    pub board: BoardMonitor,
    pub status: CoilStatus,
}

/// What to write to the Teensy after an input.
#[derive(Debug, Clone, PartialEq)]
pub struct Output {
    pub frame_seq: u64,
    pub flags: u8,
    /// The first `coil_count` entries are driven; the rest are zero.
    pub currents_a: [f64; MAX_COILS],
    pub coil_count: usize,
}

impl Output {
    /// The currents of the driven coils.
    pub fn currents(&self) -> &[f64] {
        &self.currents_a[..self.coil_count.min(MAX_COILS)]
    }
}

impl CoilBus {
    /// A bus driving `coil_count` coils (capped at `MAX_COILS`; `CoilbusConfig::validate`
    /// rejects larger counts before this is built).
    pub fn new(limits: CurrentLimits, deadline: Duration, coil_count: usize) -> Self {
        let coil_count = coil_count.min(MAX_COILS);
        let board = BoardMonitor::new(
            coil_count,
            &limits.max_current_a[..coil_count],
            TelemetryTolerance::default(),
        );
        Self {
            limits,
            coil_count,
            deadline,
            stale: StaleFilter::default(),
            last_accepted: None,
            start_zero_written: false,
            board,
            status: CoilStatus {
                board_state: BOARD_STATE_UNKNOWN,
                frame_seq: NO_FRAME,
                active_coils: coil_count as u32,
                watchdog_tripped: Flag::TRUE,
                ..Default::default()
            },
        }
    }

    /// The requested currents of `cmd` if it addresses exactly this bus's coils.
    pub fn check_coil_count<'a>(&self, cmd: &'a CoilCommand) -> Result<&'a [f64], CommandError> {
        let currents = cmd.currents()?;
        if currents.len() != self.coil_count {
            return Err(CommandError::CoilCount {
                got: cmd.active_coils,
                expected: self.coil_count,
            });
        }
        Ok(currents)
    }

    /// Checks a command and computes what to send for it. Nothing is recorded until
    /// `applied` confirms the write reached the Teensy, so a command that could not be sent
    /// (link down) does not make its frame count as applied. A command for another coil count
    /// is rejected (counted in `coil_count_rejected`, logged) and nothing is driven for it.
    pub fn on_command(&mut self, cmd: &CoilCommand) -> Option<Output> {
        if self.board.fault().is_some() {
            // The board went safe or cannot be trusted: nothing but zeros until a restart.
            return None;
        }
        let requested = match self.check_coil_count(cmd) {
            Ok(currents) => currents,
            Err(e) => {
                self.status.coil_count_rejected += 1;
                let n = self.status.coil_count_rejected;
                if n == 1 || n.is_multiple_of(REJECTION_LOG_EVERY) {
                    tracing::error!(rejected = n, "{e}");
                }
                return None;
            }
        };
        if !self.stale.is_fresh(cmd) {
            self.status.stale_commands_rejected += 1;
            return None;
        }
        let zeros = [0.0; MAX_COILS];
        let requested = match ControlMode::from_repr(cmd.mode) {
            Some(ControlMode::Track) | Some(ControlMode::Hold) => requested,
            // Safe, or a mode this build does not know: zero.
            _ => &zeros[..self.coil_count],
        };
        let (currents, clamped) = clamp_currents(requested, &self.limits);
        if clamped {
            self.status.clamp_events += 1;
        }
        Some(Output {
            frame_seq: cmd.stamp.seq,
            flags: 0,
            currents_a: currents,
            coil_count: self.coil_count,
        })
    }

    /// Counts a board acknowledgement; a board that refused a frame for its coil count is
    /// counted in `board_rejected` and logged.
    pub fn on_ack(&mut self, status: u8) {
        self.status.acks_received += 1;
        if status == AckStatus::RejectedCoilCount as u8 {
            self.status.board_rejected += 1;
            let n = self.status.board_rejected;
            if n == 1 || n.is_multiple_of(REJECTION_LOG_EVERY) {
                tracing::error!(
                    rejected = n,
                    coil_count = self.coil_count,
                    "the coil-driver board rejected a frame for {} coils: its own coil count \
                     differs (nothing driven); check [coilbus] coil_count against the board",
                    self.coil_count
                );
            }
        }
    }

    /// Records that `out`, computed from `cmd`, was written to the Teensy.
    pub fn applied(&mut self, cmd: &CoilCommand, out: &Output, now: Instant) {
        self.stale.commit(cmd);
        self.last_accepted = Some(now);
        self.status.watchdog_tripped = Flag::FALSE;
        self.status.frame_seq = out.frame_seq;
        self.status.applied_currents_a = out.currents_a;
    }

    /// Checks the command deadline; returns a zeroing output when it just tripped or while
    /// tripped (a keep-alive so the Teensy keeps seeing the safe state).
    pub fn on_tick(&mut self, now: Instant) -> Option<Output> {
        if self.board.fault().is_some() {
            return Some(self.safe_zero());
        }
        let expired = self
            .last_accepted
            .is_none_or(|t| now.duration_since(t) > self.deadline);
        if !expired {
            return None;
        }
        if self.status.watchdog_tripped != Flag::TRUE {
            self.status.watchdog_tripped = Flag::TRUE;
            self.status.deadline_misses += 1;
            tracing::warn!(
                "no command for {:?}: coils to zero (safe state)",
                self.deadline
            );
        }
        Some(self.safe_zero())
    }

    /// A (re)started coilbus does not know what the board drives (its predecessor may have died
    /// mid-command), so its first frame is a safe zero and commands apply from the next cycle
    /// on. Returns that zero until `start_zero_sent` confirms it reached the board.
    pub fn start_zero(&mut self) -> Option<Output> {
        (!self.start_zero_written).then(|| self.safe_zero())
    }

    /// Records that the start-up zero was written to the board.
    pub fn start_zero_sent(&mut self) {
        self.start_zero_written = true;
    }

    /// Whether the board may be armed: this process has put it in a known state (its start-up
    /// zero went out).
    pub fn may_arm(&self) -> bool {
        self.start_zero_written && self.board.fault().is_none()
    }

    /// Uses `tolerance` for the board's telemetry from now on.
    pub fn set_telemetry_tolerance(&mut self, tolerance: TelemetryTolerance) {
        self.board = BoardMonitor::new(
            self.coil_count,
            &self.limits.max_current_a[..self.coil_count],
            tolerance,
        );
    }

    /// Checks a board `Status` against what this bus sent; a fault latched now is returned (the
    /// caller logs it, disarms the board where it still can, and the bus holds zeros).
    pub fn on_board_status(&mut self, status: &protocol::BoardStatus) -> Option<board::Fault> {
        let fault = self.board.on_status(status).cloned();
        self.sync_board_fields();
        fault
    }

    /// Refuses a board that speaks another protocol version.
    pub fn on_foreign_version(&mut self, version: u8) -> Option<board::Fault> {
        let fault = self.board.foreign_version(version).cloned();
        self.sync_board_fields();
        fault
    }

    fn sync_board_fields(&mut self) {
        self.status.board_state = self.board.state.map_or(BOARD_STATE_UNKNOWN, |s| s as u8);
        self.status.board_flags = self.board.flags;
        self.status.thermal_permille = self.board.thermal_permille;
        self.status.board_fault = self.board.fault().map_or(BoardFault::None, |f| f.kind) as u8;
    }

    pub fn safe_zero(&mut self) -> Output {
        self.status.frame_seq = NO_FRAME;
        self.status.applied_currents_a = [0.0; MAX_COILS];
        Output {
            frame_seq: NO_FRAME,
            flags: FLAG_SAFE_ZERO,
            currents_a: [0.0; MAX_COILS],
            coil_count: self.coil_count,
        }
    }
}

/// Writes one output to the Teensy; true when the bytes went out.
fn write_output(link: &mut SerialLink, bus: &mut CoilBus, out: &Output) -> bool {
    let currents_ma = out.currents_a.map(protocol::amps_to_ma);
    // `Output` never holds more than MAX_COILS coils, so the block always fits a frame.
    let Some(currents_ma) = CoilValues::new(&currents_ma[..out.coil_count.min(MAX_COILS)]) else {
        return false;
    };
    let message = Message::SetCurrents {
        frame_seq: out.frame_seq,
        flags: out.flags,
        currents_ma,
    };
    let sent = link.send(&message);
    if sent {
        bus.status.frames_sent += 1;
        if let Message::SetCurrents { currents_ma, .. } = &message {
            bus.board.commanded(currents_ma.as_slice());
        }
    }
    sent
}

fn log_output(rec: &millinav_kit::rerun::RecordingStream, out: &Output, bus: &CoilBus) {
    for (i, current) in out.currents().iter().enumerate() {
        recording::scalar(rec, &format!("coilbus/current_a/{i}"), *current);
    }
    recording::scalar(
        rec,
        "coilbus/watchdog_tripped",
        f64::from(bus.status.watchdog_tripped.raw()),
    );
}

/// Parses and validates the `[coilbus]` table. The serial port is not checked here: the
/// emulated one appears when the plant starts, and a real one may be plugged in later (the
/// link reconnects). Every failure is a configuration error naming the scenario and the field.
pub fn prepare(scenario: &Scenario) -> Result<CoilbusSetup, ConfigError> {
    let config: CoilbusConfig = scenario.section("coilbus")?;
    let field = |name: &str| format!("scenario {}: [coilbus] {name}", scenario.path.display());
    let positive = |name: &str, value: u64| {
        if value > 0 {
            Ok(())
        } else {
            Err(ConfigError::new(format!("{} must be > 0", field(name))))
        }
    };
    positive("baud", u64::from(config.baud))?;
    positive("command_deadline_ms", config.command_deadline_ms)?;
    // A zero tick would make the loop spin.
    positive("tick_ms", config.tick_ms)?;
    // The board's own range (firmware/core HardwareLimits::standard).
    if !(20..=2000).contains(&config.board_watchdog_ms) {
        return Err(ConfigError::new(format!(
            "{} must be 20 to 2000 ms (what the board accepts), got {}",
            field("board_watchdog_ms"),
            config.board_watchdog_ms
        )));
    }
    let telemetry = &config.telemetry;
    if !(telemetry.current_a.is_finite() && telemetry.current_a > 0.0) {
        return Err(ConfigError::new(format!(
            "{} must be > 0 A, got {}",
            field("telemetry.current_a"),
            telemetry.current_a
        )));
    }
    if !(telemetry.fraction.is_finite() && (0.0..=1.0).contains(&telemetry.fraction)) {
        return Err(ConfigError::new(format!(
            "{} must be 0 to 1, got {}",
            field("telemetry.fraction"),
            telemetry.fraction
        )));
    }
    positive("telemetry.persistence", u64::from(telemetry.persistence))?;
    if config.port.trim().is_empty() {
        return Err(ConfigError::new(format!(
            "{} must be a serial device or \"auto\"",
            field("port")
        )));
    }
    for (name, value) in [
        ("max_current_a", config.max_current_a),
        ("max_total_power_w", config.max_total_power_w),
    ] {
        if let Some(value) = value {
            if !(value.is_finite() && value > 0.0) {
                return Err(ConfigError::new(format!(
                    "{} must be > 0, got {value}",
                    field(name)
                )));
            }
        }
    }
    let rig = scenario.rig()?;
    let coil_count = config.coil_count.unwrap_or(rig.coils.len());
    if coil_count == 0 || coil_count > MAX_COILS {
        return Err(ConfigError::new(format!(
            "{}: {}",
            field("coil_count"),
            CommandError::BadConfiguredCount(coil_count)
        )));
    }
    let limits =
        CurrentLimits::from_rig(&rig).capped(config.max_current_a, config.max_total_power_w);
    Ok(CoilbusSetup {
        config,
        limits,
        coil_count,
    })
}

/// Validates the `[coilbus]` table (what `--check` runs).
pub fn check_config(scenario: &Scenario) -> Result<(), ConfigError> {
    prepare(scenario).map(drop)
}

/// The coilbus process: on every wake (a command, its deadline, or the tick) it services the
/// serial link, applies the newest fresh command or keeps the coils at zero, and publishes its
/// status. On the way out it zeroes the coils.
pub fn run(rt: &mut Runtime, _scenario: &Scenario, setup: CoilbusSetup) -> anyhow::Result<()> {
    let CoilbusSetup {
        config,
        limits,
        coil_count,
    } = setup;
    let port_path = config.port_path(&rt.env.run_dir);
    let commands = Inbox::<CoilCommand>::new(&rt.node, services::COMMAND)?;
    let status_out = Outbox::<CoilStatus>::new(&rt.node, services::COIL_STATUS)?;
    let mut link = SerialLink::new(port_path.clone(), config.baud);
    link.set_board_config(board_config(&limits, coil_count, config.board_watchdog_ms));
    let mut link_log = RunLogWriter::<LinkEventRow>::in_run_dir(&rt.env.run_dir)
        .context("opening the link log")?;
    let mut bus = CoilBus::new(
        limits,
        Duration::from_millis(config.command_deadline_ms),
        coil_count,
    );
    bus.set_telemetry_tolerance(config.telemetry);
    let run_start = Instant::now();

    let mut service_loop = ServiceLoop::new();
    service_loop.input_with_deadline(&commands, bus.deadline);
    service_loop.output(&status_out);
    service_loop.tick_every(Duration::from_millis(config.tick_ms));
    tracing::info!(port = %port_path.display(), "coilbus ready");
    service_loop.run(&mut rt.heartbeat, |_| {
        let now = Instant::now();
        link.set_arm_wanted(bus.may_arm());
        service_link(&mut link, &mut bus, &mut link_log, now);
        let received = commands.receive_all()?;
        if let Some(out) = apply_commands(&mut link, &mut bus, &received, now) {
            recording::set_time(
                &rt.rec,
                now.duration_since(run_start).as_nanos() as u64,
                out.frame_seq.min(i64::MAX as u64),
            );
            log_output(&rt.rec, &out, &bus);
        }
        bus.status.link_state = if link.is_open() {
            LinkState::Connected as u32
        } else {
            LinkState::Disconnected as u32
        };
        bus.status.rx_errors = link.decoder_errors();
        bus.status.reconnects = link.reconnects;
        let _ = status_out.send(bus.status);
        anyhow::Ok(())
    })?;
    // Safe state first: zero the coils before leaving.
    let out = bus.safe_zero();
    write_output(&mut link, &mut bus, &out);
    link.send(&Message::Disarm);
    tracing::info!("coilbus stopped; coils zeroed, board disarmed");
    Ok(())
}

/// The board's `Config` from the rig's ratings: each coil's resistance, current limit (as
/// lowered for this run), continuous current and I²t heat budget, the drivers' supply voltage
/// (`electromagnet.driver_supply_v`), and the board's watchdog. The board refuses (and says so
/// in `Status`) what does not fit its hardware.
pub fn board_config(
    limits: &CurrentLimits,
    coil_count: usize,
    watchdog_ms: u16,
) -> protocol::BoardConfig {
    let n = coil_count.min(MAX_COILS);
    let to_milli = |v: f64| (v * 1000.0).round().clamp(1.0, u32::MAX as f64) as u32;
    let ratings: Vec<protocol::CoilRating> = (0..n)
        .map(|k| {
            let max_a = limits.max_current_a[k];
            protocol::CoilRating {
                resistance_mohm: to_milli(limits.coil_resistance_ohm[k]),
                max_ma: to_milli(max_a),
                continuous_ma: to_milli(limits.continuous_current_a[k].min(max_a)),
                i2t_budget: to_milli(limits.thermal_budget_a2s[k]),
            }
        })
        .collect();
    // `ratings` holds at most MAX_COILS coils, so the block always fits.
    protocol::BoardConfig::of_first(to_milli(limits.supply_v), watchdog_ms, &ratings)
}

/// Reopens a lost link, counts the board's acknowledgements and logs link changes.
fn service_link(
    link: &mut SerialLink,
    bus: &mut CoilBus,
    link_log: &mut RunLogWriter<LinkEventRow>,
    now: Instant,
) {
    link.ensure_open(now);
    let mut latched = Vec::new();
    for packet in link.poll() {
        match packet.message {
            Message::Ack { status, .. } => {
                bus.on_ack(status);
                bus.board.acked(status);
            }
            Message::Status(status) => latched.extend(bus.on_board_status(&status)),
            _ => {}
        }
    }
    if let Some(version) = link.foreign_version() {
        latched.extend(bus.on_foreign_version(version));
    }
    for fault in latched {
        tracing::error!(
            fault = fault.kind.name(),
            "coils held at zero: {}",
            fault.detail
        );
        // A board that disagrees (or speaks another version) is disarmed; an e-stopped or
        // tripped one stays latched as it is.
        if matches!(
            fault.kind,
            BoardFault::TelemetryDisagrees
                | BoardFault::ProtocolVersion
                | BoardFault::ConfigRefused
        ) {
            link.send(&Message::Disarm);
        }
        link.record_board_fault(fault.kind.name(), &fault.detail);
    }
    log_link_events(link_log, link.take_events());
}

/// Writes the start-up safe zero until it went out once, then the newest fresh command of
/// `received` (older ones in the queue are superseded), or the safe zero when the command
/// deadline has passed; returns what went out.
fn apply_commands(
    link: &mut SerialLink,
    bus: &mut CoilBus,
    received: &[CoilCommand],
    now: Instant,
) -> Option<Output> {
    if let Some(zero) = bus.start_zero() {
        if write_output(link, bus, &zero) {
            bus.start_zero_sent();
            return Some(zero);
        }
    } else if let Some((cmd, out)) = received
        .iter()
        .rev()
        .find_map(|cmd| bus.on_command(cmd).map(|out| (cmd, out)))
    {
        if write_output(link, bus, &out) {
            bus.applied(cmd, &out, now);
            return Some(out);
        }
    }
    let zero = bus.on_tick(now)?;
    write_output(link, bus, &zero);
    Some(zero)
}

fn log_link_events(log: &mut RunLogWriter<LinkEventRow>, events: Vec<link::LinkEvent>) {
    for event in events {
        let row = LinkEventRow {
            monotonic_ns: event.monotonic_ns,
            event: event.kind.to_string(),
            detail: event.detail,
        };
        if let Err(e) = log.append_now(&row) {
            tracing::warn!("cannot log a link change: {e}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const COILS: usize = 12;

    fn command(seq: u64, incarnation: u64, current: f64) -> CoilCommand {
        command_for(COILS, seq, incarnation, current)
    }

    fn command_for(coils: usize, seq: u64, incarnation: u64, current: f64) -> CoilCommand {
        let mut cmd = CoilCommand {
            stamp: shm_schemas::FrameStamp::new(seq, 0, 0),
            control_incarnation: incarnation,
            mode: ControlMode::Track as u32,
            ..Default::default()
        };
        cmd.set_currents(&vec![current; coils]).unwrap();
        cmd
    }

    /// The committed paper rig's limits.
    fn paper_limits() -> CurrentLimits {
        CurrentLimits::from_rig(&fieldmaps::rigfile::Rig::load_paper().unwrap())
    }

    fn bus() -> CoilBus {
        CoilBus::new(paper_limits(), Duration::from_millis(100), COILS)
    }

    #[test]
    fn deadline_zeroes_and_new_command_recovers() {
        let mut bus = bus();
        let t0 = Instant::now();
        apply(&mut bus, &command(1, 0, 1.0), t0).unwrap();
        assert!(bus.on_tick(t0 + Duration::from_millis(50)).is_none());
        let zero = bus.on_tick(t0 + Duration::from_millis(150)).unwrap();
        assert_eq!(zero.currents(), [0.0; COILS]);
        assert_eq!(zero.flags, FLAG_SAFE_ZERO);
        assert_eq!(bus.status.watchdog(), Ok(true));
        assert_eq!(bus.status.deadline_misses, 1);
        let out = apply(
            &mut bus,
            &command(2, 0, 1.0),
            t0 + Duration::from_millis(160),
        )
        .unwrap();
        assert_eq!(out.currents(), [1.0; COILS]);
        assert_eq!(bus.status.watchdog(), Ok(false));
    }

    #[test]
    fn a_started_coilbus_zeroes_the_board_before_any_command() {
        let mut bus = CoilBus::new(paper_limits(), Duration::from_millis(100), COILS);
        let zero = bus
            .start_zero()
            .expect("a fresh coilbus starts with a zero");
        assert_eq!(zero.currents(), [0.0; COILS]);
        assert_eq!(zero.flags, FLAG_SAFE_ZERO);
        // Not written yet (link closed): still owed.
        assert!(bus.start_zero().is_some());
        bus.start_zero_sent();
        assert!(bus.start_zero().is_none());
        assert!(apply(&mut bus, &command(1, 0, 1.0), Instant::now()).is_some());
    }

    #[test]
    fn stale_and_old_incarnation_commands_are_rejected() {
        let mut bus = bus();
        let t = Instant::now();
        assert!(apply(&mut bus, &command(10, 1, 1.0), t).is_some());
        assert!(apply(&mut bus, &command(9, 1, 1.0), t).is_none());
        assert!(apply(&mut bus, &command(10, 1, 1.0), t).is_none());
        // An older control incarnation is never applied again, even with a newer frame.
        assert!(apply(&mut bus, &command(11, 0, 1.0), t).is_none());
        assert!(apply(&mut bus, &command(11, 2, 1.0), t).is_some());
        assert_eq!(bus.status.stale_commands_rejected, 3);
    }

    #[test]
    fn a_command_that_was_not_written_can_be_sent_again() {
        let mut bus = bus();
        let cmd = command(0, 0, 1.0);
        // Link down: computed but never applied.
        assert!(bus.on_command(&cmd).is_some());
        assert!(apply(&mut bus, &cmd, Instant::now()).is_some());
        assert!(apply(&mut bus, &cmd, Instant::now()).is_none());
    }

    #[test]
    fn limits_clamp_even_wild_and_nan_commands() {
        let limits = paper_limits();
        let mut bus = CoilBus::new(limits.clone(), Duration::from_millis(100), COILS);
        let mut wild = command(1, 0, 1e6);
        wild.currents_a[3] = f64::NAN;
        let out = apply(&mut bus, &wild, Instant::now()).unwrap();
        assert!(out
            .currents_a
            .iter()
            .zip(&limits.max_current_a)
            .all(|(c, max)| c.abs() <= *max));
        assert_eq!(out.currents_a[3], 0.0);
        let power: f64 = out
            .currents_a
            .iter()
            .zip(&limits.coil_resistance_ohm)
            .map(|(c, r)| c * c * r)
            .sum();
        assert!(power <= limits.max_total_power_w * (1.0 + 1e-9));
        assert_eq!(bus.status.clamp_events, 1);
    }

    /// A scenario with `coilbus_table` as its `[coilbus]`.
    fn scenario_with(coilbus_table: &str) -> Scenario {
        let text = format!(
            "[run]\nduration_s = 1.0\nrig = \"fieldmaps/rigs/paper.toml\"\n[fluid]\nviscosity_cp = 20.0\n\
             [trajectory]\nwaypoints_mm = [[0.0, 0.0], [5.0, 0.0]]\n[coilbus]\n{coilbus_table}\n"
        );
        Scenario::parse(&text, std::path::Path::new("coilbus-test.toml")).unwrap()
    }

    #[test]
    fn check_config_accepts_defaults_and_a_device() {
        check_config(&scenario_with("")).unwrap();
        check_config(&scenario_with("port = \"/dev/ttyACM0\"\nbaud = 9600")).unwrap();
    }

    #[test]
    fn check_config_rejects_typos_and_bad_values() {
        let error = check_config(&scenario_with("prot = \"auto\""))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("[coilbus]") && error.contains("prot"),
            "{error}"
        );
        let error = check_config(&scenario_with("max_curent_a = 1.0"))
            .unwrap_err()
            .to_string();
        assert!(error.contains("max_curent_a"), "{error}");
        let error = check_config(&scenario_with("tick_ms = 0"))
            .unwrap_err()
            .to_string();
        assert!(error.contains("[coilbus] tick_ms"), "{error}");
        let error = check_config(&scenario_with("max_current_a = nan"))
            .unwrap_err()
            .to_string();
        assert!(error.contains("[coilbus] max_current_a"), "{error}");
    }

    #[test]
    fn safe_mode_command_zeroes() {
        let mut bus = bus();
        let mut cmd = command(1, 0, 2.0);
        cmd.mode = ControlMode::Safe as u32;
        let out = apply(&mut bus, &cmd, Instant::now()).unwrap();
        assert_eq!(out.currents(), [0.0; COILS]);
    }

    #[test]
    fn a_command_for_another_coil_count_is_rejected_and_nothing_is_driven() {
        let mut bus = bus();
        let t0 = Instant::now();
        apply(&mut bus, &command(1, 0, 1.0), t0).unwrap();
        let applied = bus.status.applied_currents_a;
        for coils in [8, 11, 13, 16] {
            let cmd = command_for(coils, 2, 0, 2.0);
            assert!(bus.on_command(&cmd).is_none(), "{coils} coils accepted");
            let err = bus.check_coil_count(&cmd).unwrap_err();
            assert_eq!(
                err,
                CommandError::CoilCount {
                    got: coils as u32,
                    expected: COILS
                }
            );
            assert!(err
                .to_string()
                .contains(&format!("for {coils} coils rejected")));
        }
        assert_eq!(bus.status.coil_count_rejected, 4);
        // What was driven before stays; the right count for the same frame still goes through.
        assert_eq!(bus.status.applied_currents_a, applied);
        assert_eq!(bus.status.active_coils, COILS as u32);
        assert!(apply(&mut bus, &command(2, 0, 2.0), t0).is_some());
        // The deadline still zeroes the coils when only wrong-count commands arrive.
        assert!(bus.on_command(&command_for(8, 3, 0, 2.0)).is_none());
        let zero = bus.on_tick(t0 + Duration::from_millis(150)).unwrap();
        assert_eq!(zero.currents(), [0.0; COILS]);
    }

    #[test]
    fn a_command_with_an_impossible_coil_count_is_rejected() {
        let mut bus = bus();
        let mut cmd = command(1, 0, 1.0);
        cmd.active_coils = MAX_COILS as u32 + 1;
        assert!(matches!(
            bus.check_coil_count(&cmd),
            Err(CommandError::Malformed(ContractError::BadCoilCount { .. }))
        ));
        assert!(bus.on_command(&cmd).is_none());
        assert_eq!(bus.status.coil_count_rejected, 1);
    }

    #[test]
    fn board_rejections_are_counted() {
        let mut bus = bus();
        bus.on_ack(AckStatus::Applied as u8);
        bus.on_ack(AckStatus::RejectedCoilCount as u8);
        assert_eq!(bus.status.acks_received, 2);
        assert_eq!(bus.status.board_rejected, 1);
    }

    #[test]
    fn configured_coil_count_is_validated() {
        for bad in [0, MAX_COILS + 1] {
            let error = check_config(&scenario_with(&format!("coil_count = {bad}")))
                .unwrap_err()
                .to_string();
            assert!(error.contains("[coilbus] coil_count"), "{error}");
        }
    }

    #[test]
    fn limits_come_from_the_rig_and_the_scenario_only_lowers_them() {
        let setup = prepare(&scenario_with("")).unwrap();
        let rig = fieldmaps::rigfile::Rig::load_paper().unwrap();
        assert_eq!(setup.coil_count, rig.coils.len());
        assert_eq!(setup.limits, CurrentLimits::from_rig(&rig));
        let capped = prepare(&scenario_with(
            "max_current_a = 2.0\nmax_total_power_w = 1e6",
        ))
        .unwrap();
        assert!(capped.limits.max_current_a[..rig.coils.len()]
            .iter()
            .all(|&m| m == 2.0));
        assert_eq!(capped.limits.max_total_power_w, rig.max_total_power_w);
    }

    /// on_command followed by a successful write.
    fn apply(bus: &mut CoilBus, cmd: &CoilCommand, now: Instant) -> Option<Output> {
        let out = bus.on_command(cmd)?;
        bus.applied(cmd, &out, now);
        Some(out)
    }
}
