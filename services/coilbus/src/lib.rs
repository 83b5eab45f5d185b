//! coilbus: the only process that talks to the coil drivers. It takes `CoilCommand`s, rejects
//! stale ones, clamps per-coil and total limits on its own authority, writes them to the Teensy
//! over the serial protocol, zeroes the coils when commands miss their deadline, and reconnects
//! when the port goes away.

pub mod link;
pub mod safety;
pub use millinav_teensy_protocol as protocol;

// The protocol crate carries its own coil count so it can stay dependency-free.
const _: () = assert!(protocol::COIL_COUNT == shm_schemas::COIL_COUNT);

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use millinav_kit::iceoryx2::prelude::*;
use millinav_kit::iceoryx2::waitset::WaitSetRunResult;
use millinav_kit::ports::{Inbox, Outbox};
use millinav_kit::recording;
use millinav_kit::scenario::Scenario;
use millinav_kit::Runtime;
use serde::{Deserialize, Serialize};
use shm_schemas::{
    deadlines, services, CoilCommand, CoilStatus, ControlMode, LinkState, COIL_COUNT, NO_FRAME,
};

use crate::link::SerialLink;
use crate::protocol::{Message, FLAG_SAFE_ZERO};
use crate::safety::{clamp_currents, CurrentLimits, StaleFilter};

/// Serial-link changes (`open`, `lost`) in a run directory: monotonic_ns,event,detail.
pub const LINK_EVENTS_CSV: &str = "coilbus_link.csv";

pub use millinav_teensy_protocol::EMULATED_PORT_LINK;

/// `[coilbus]` section of a scenario.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CoilbusConfig {
    /// Serial device of the Teensy, or `auto` for the plant's emulated Teensy in the run dir.
    pub port: String,
    pub baud: u32,
    pub limits: CurrentLimits,
    /// Zero the coils when no command was accepted for this long.
    pub command_deadline_ms: u64,
    /// Period of the housekeeping tick (reconnect, telemetry, safe-state keepalive).
    pub tick_ms: u64,
}

impl Default for CoilbusConfig {
    fn default() -> Self {
        Self {
            port: "auto".into(),
            baud: 115_200,
            limits: CurrentLimits::default(),
            command_deadline_ms: deadlines::COMMAND.as_millis() as u64,
            tick_ms: 20,
        }
    }
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

/// The coilbus decision logic, independent of ports so it can be tested directly.
pub struct CoilBus {
    limits: CurrentLimits,
    deadline: Duration,
    stale: StaleFilter,
    last_accepted: Option<Instant>,
    pub status: CoilStatus,
}

/// What to write to the Teensy after an input.
#[derive(Debug, Clone, PartialEq)]
pub struct Output {
    pub frame_seq: u64,
    pub flags: u8,
    pub currents_a: [f64; COIL_COUNT],
}

impl CoilBus {
    pub fn new(limits: CurrentLimits, deadline: Duration) -> Self {
        Self {
            limits,
            deadline,
            stale: StaleFilter::default(),
            last_accepted: None,
            status: CoilStatus {
                frame_seq: NO_FRAME,
                watchdog_tripped: true,
                ..Default::default()
            },
        }
    }

    /// Checks a command and computes what to send for it. Nothing is recorded until
    /// `applied` confirms the write reached the Teensy, so a command that could not be sent
    /// (link down) does not make its frame count as applied.
    pub fn on_command(&mut self, cmd: &CoilCommand) -> Option<Output> {
        if !self.stale.is_fresh(cmd) {
            self.status.stale_commands_rejected += 1;
            return None;
        }
        let requested = match ControlMode::from_u32(cmd.mode) {
            Some(ControlMode::Track) | Some(ControlMode::Hold) => cmd.currents_a,
            // Safe, or a mode this build does not know: zero.
            _ => [0.0; COIL_COUNT],
        };
        let (currents, clamped) = clamp_currents(&requested, &self.limits);
        if clamped {
            self.status.clamp_events += 1;
        }
        Some(Output {
            frame_seq: cmd.frame_seq,
            flags: 0,
            currents_a: currents,
        })
    }

    /// Records that `out`, computed from `cmd`, was written to the Teensy.
    pub fn applied(&mut self, cmd: &CoilCommand, out: &Output, now: Instant) {
        self.stale.commit(cmd);
        self.last_accepted = Some(now);
        self.status.watchdog_tripped = false;
        self.status.frame_seq = out.frame_seq;
        self.status.applied_currents_a = out.currents_a;
    }

    /// Checks the command deadline; returns a zeroing output when it just tripped or while
    /// tripped (a keep-alive so the Teensy keeps seeing the safe state).
    pub fn on_tick(&mut self, now: Instant) -> Option<Output> {
        let expired = self
            .last_accepted
            .is_none_or(|t| now.duration_since(t) > self.deadline);
        if !expired {
            return None;
        }
        if !self.status.watchdog_tripped {
            self.status.watchdog_tripped = true;
            self.status.deadline_misses += 1;
            tracing::warn!(
                "no command for {:?}: coils to zero (safe state)",
                self.deadline
            );
        }
        Some(self.safe_zero())
    }

    pub fn safe_zero(&mut self) -> Output {
        self.status.frame_seq = NO_FRAME;
        self.status.applied_currents_a = [0.0; COIL_COUNT];
        Output {
            frame_seq: NO_FRAME,
            flags: FLAG_SAFE_ZERO,
            currents_a: [0.0; COIL_COUNT],
        }
    }
}

/// Writes one output to the Teensy; true when the bytes went out.
fn write_output(link: &mut SerialLink, bus: &mut CoilBus, out: &Output) -> bool {
    let message = Message::SetCurrents {
        frame_seq: out.frame_seq,
        flags: out.flags,
        currents_ma: out.currents_a.map(protocol::amps_to_ma),
    };
    let sent = link.send(&message);
    if sent {
        bus.status.frames_sent += 1;
    }
    sent
}

fn log_output(rec: &millinav_kit::rerun::RecordingStream, out: &Output, bus: &CoilBus) {
    for (i, current) in out.currents_a.iter().enumerate() {
        recording::scalar(rec, &format!("coilbus/current_a/{i}"), *current);
    }
    recording::scalar(
        rec,
        "coilbus/watchdog_tripped",
        f64::from(u8::from(bus.status.watchdog_tripped)),
    );
}

/// The coilbus process loop.
pub fn run(rt: &mut Runtime, scenario: &Scenario) -> anyhow::Result<()> {
    let config: CoilbusConfig = scenario.section("coilbus")?;
    let port_path = config.port_path(&rt.env.run_dir);
    let commands = Inbox::<CoilCommand>::new(&rt.node, services::COMMAND)?;
    let status_out = Outbox::<CoilStatus>::new(&rt.node, services::COIL_STATUS)?;
    let mut link = SerialLink::new(port_path.clone(), config.baud);
    let mut link_log = millinav_kit::open_csv_append(
        &rt.env.run_dir.join(LINK_EVENTS_CSV),
        "monotonic_ns,event,detail",
    )
    .context("opening the link log")?;
    let mut bus = CoilBus::new(
        config.limits.clone(),
        Duration::from_millis(config.command_deadline_ms),
    );
    let run_start = Instant::now();

    let waitset = WaitSetBuilder::new()
        .create::<ipc::Service>()
        .map_err(millinav_kit::iox("waitset"))?;
    let command_guard = waitset
        .attach_deadline(&commands.listener, bus.deadline)
        .map_err(millinav_kit::iox("attach command deadline"))?;
    let tick_guard = waitset
        .attach_interval(Duration::from_millis(config.tick_ms))
        .map_err(millinav_kit::iox("attach tick"))?;
    tracing::info!(port = %port_path.display(), "coilbus ready");

    loop {
        let mut command_event = false;
        let mut deadline_missed = false;
        let result = waitset
            .wait_and_process_once_with_timeout(
                |id| {
                    if id.has_event_from(&command_guard) {
                        command_event = true;
                    } else if id.has_missed_deadline(&command_guard) {
                        deadline_missed = true;
                    } else if id.has_event_from(&tick_guard) {
                        // housekeeping below runs on every wake-up anyway
                    }
                    CallbackProgression::Continue
                },
                Duration::from_millis(config.tick_ms),
            )
            .map_err(millinav_kit::iox("waitset"))?;
        if matches!(
            result,
            WaitSetRunResult::TerminationRequest | WaitSetRunResult::Interrupt
        ) {
            break;
        }
        let now = Instant::now();
        link.ensure_open(now);
        for packet in link.poll() {
            if let Message::Ack { .. } = packet.message {
                bus.status.acks_received += 1;
            }
        }
        log_link_events(&mut link_log, link.take_events());
        if deadline_missed {
            rt.heartbeat.deadline_misses += 1;
        }
        // Even without an event, drain: a listener left undrained makes the WaitSet spin.
        let received = commands.receive_all()?;
        let _ = command_event;
        // Only the newest fresh command matters: older ones in the queue are superseded.
        let mut sent = None;
        if let Some((cmd, out)) = received
            .iter()
            .rev()
            .find_map(|cmd| bus.on_command(cmd).map(|out| (cmd, out)))
        {
            if write_output(&mut link, &mut bus, &out) {
                bus.applied(cmd, &out, now);
                sent = Some(out);
            }
        }
        if sent.is_none() {
            if let Some(zero) = bus.on_tick(now) {
                write_output(&mut link, &mut bus, &zero);
                sent = Some(zero);
            }
        }
        if let Some(out) = &sent {
            recording::set_time(
                &rt.rec,
                now.duration_since(run_start).as_nanos() as u64,
                out.frame_seq.min(i64::MAX as u64),
            );
            log_output(&rt.rec, out, &bus);
        }
        bus.status.link_state = if link.is_open() {
            LinkState::Connected as u32
        } else {
            LinkState::Disconnected as u32
        };
        bus.status.rx_errors = link.decoder_errors();
        bus.status.reconnects = link.reconnects;
        let _ = status_out.send(bus.status);
        rt.heartbeat.beat();
        commands_update(&status_out, rt);
    }
    // Safe state first: zero the coils before leaving.
    let out = bus.safe_zero();
    write_output(&mut link, &mut bus, &out);
    tracing::info!("coilbus stopped; coils zeroed");
    let _ = rt.rec.flush_blocking();
    Ok(())
}

fn log_link_events(log: &mut impl std::io::Write, events: Vec<link::LinkEvent>) {
    for event in events {
        // Commas would split the CSV field; the detail is free text.
        let detail = event.detail.replace(',', ";");
        let _ = writeln!(log, "{},{},{detail}", event.monotonic_ns, event.kind);
    }
    let _ = log.flush();
}

fn commands_update(status_out: &Outbox<CoilStatus>, rt: &Runtime) {
    status_out.update_connections();
    rt.heartbeat.update_connections();
}

/// Entry point shared by the binary: parse args, start, run.
pub fn main_with_scenario(scenario_path: &std::path::Path) -> anyhow::Result<()> {
    let mut rt = Runtime::start(shm_schemas::ServiceId::Coilbus)?;
    let scenario = Scenario::load(scenario_path)
        .with_context(|| format!("loading scenario {}", scenario_path.display()))?;
    run(&mut rt, &scenario)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn command(seq: u64, incarnation: u64, current: f64) -> CoilCommand {
        CoilCommand {
            frame_seq: seq,
            control_incarnation: incarnation,
            currents_a: [current; COIL_COUNT],
            mode: ControlMode::Track as u32,
            ..Default::default()
        }
    }

    #[test]
    fn deadline_zeroes_and_new_command_recovers() {
        let mut bus = CoilBus::new(CurrentLimits::default(), Duration::from_millis(100));
        let t0 = Instant::now();
        apply(&mut bus, &command(1, 0, 1.0), t0).unwrap();
        assert!(bus.on_tick(t0 + Duration::from_millis(50)).is_none());
        let zero = bus.on_tick(t0 + Duration::from_millis(150)).unwrap();
        assert_eq!(zero.currents_a, [0.0; COIL_COUNT]);
        assert_eq!(zero.flags, FLAG_SAFE_ZERO);
        assert!(bus.status.watchdog_tripped);
        assert_eq!(bus.status.deadline_misses, 1);
        let out = apply(
            &mut bus,
            &command(2, 0, 1.0),
            t0 + Duration::from_millis(160),
        )
        .unwrap();
        assert_eq!(out.currents_a, [1.0; COIL_COUNT]);
        assert!(!bus.status.watchdog_tripped);
    }

    #[test]
    fn stale_and_old_incarnation_commands_are_rejected() {
        let mut bus = CoilBus::new(CurrentLimits::default(), Duration::from_millis(100));
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
        let mut bus = CoilBus::new(CurrentLimits::default(), Duration::from_millis(100));
        let cmd = command(0, 0, 1.0);
        // Link down: computed but never applied.
        assert!(bus.on_command(&cmd).is_some());
        assert!(apply(&mut bus, &cmd, Instant::now()).is_some());
        assert!(apply(&mut bus, &cmd, Instant::now()).is_none());
    }

    #[test]
    fn limits_clamp_even_wild_and_nan_commands() {
        let limits = CurrentLimits::default();
        let mut bus = CoilBus::new(limits.clone(), Duration::from_millis(100));
        let mut wild = command(1, 0, 1e6);
        wild.currents_a[3] = f64::NAN;
        let out = apply(&mut bus, &wild, Instant::now()).unwrap();
        assert!(out
            .currents_a
            .iter()
            .all(|c| c.abs() <= limits.max_current_a));
        assert_eq!(out.currents_a[3], 0.0);
        let power: f64 = out
            .currents_a
            .iter()
            .map(|c| c * c * limits.coil_resistance_ohm)
            .sum();
        assert!(power <= limits.max_total_power_w * (1.0 + 1e-9));
        assert_eq!(bus.status.clamp_events, 1);
    }

    #[test]
    fn safe_mode_command_zeroes() {
        let mut bus = CoilBus::new(CurrentLimits::default(), Duration::from_millis(100));
        let mut cmd = command(1, 0, 2.0);
        cmd.mode = ControlMode::Safe as u32;
        let out = apply(&mut bus, &cmd, Instant::now()).unwrap();
        assert_eq!(out.currents_a, [0.0; COIL_COUNT]);
    }

    /// on_command followed by a successful write.
    fn apply(bus: &mut CoilBus, cmd: &CoilCommand, now: Instant) -> Option<Output> {
        let out = bus.on_command(cmd)?;
        bus.applied(cmd, &out, now);
        Some(out)
    }
}
