//! The plant's emulated Teensy: the same serial protocol as the real board, on a pty pair whose
//! slave side coilbus opens like any serial device. It applies `SetCurrents`, acknowledges, sends
//! telemetry, and zeroes its outputs on its own watchdog when frames stop coming. Every frame it
//! receives is appended to `teensy_events.csv` in the run directory (wall clock), so tests can
//! observe exactly when currents reached zero.
//!
//! It can also be told to suffer a link fault (`LinkFault`): a pulled USB cable (the device node
//! vanishes; the board stays powered from its own supply and keeps driving its last currents
//! until its watchdog zeroes them) or a firmware stall (nothing read or sent; the board's
//! hardware watchdog resets it, zeroing its outputs). Every zeroing the board does on its own is
//! logged with its time (`watchdog_zero`, `hw_watchdog_reset`), so a test measures time to safe
//! state at the board's zero. The plant maps SIGUSR1/SIGUSR2 to these so fault-injection tests
//! can hit the link like any other service.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use millinav_firmware_core::{Board, HardwareLimits};
use millinav_kit::runlog::{RunLogWriter, TeensyEventRow};
use millinav_teensy_protocol::{
    amps_to_ma, encode, ma_to_amps, AckStatus, BoardState, CoilValues, Decoder, Message, Packet,
    FLAG_SAFE_ZERO,
};
use serialport::{SerialPort, TTYPort};
use shm_schemas::{MAX_COILS, NO_FRAME};

const TELEMETRY_PERIOD: Duration = Duration::from_millis(50);
/// How often the board retries creating its device node if the OS refuses (replug).
const REPLUG_RETRY: Duration = Duration::from_millis(100);

/// A fault of the serial link, injected on purpose.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkFault {
    /// USB cable pulled for this long: the device node disappears; the board keeps running on
    /// its own supply (the worst case: a board powered from USB alone would go dark at once),
    /// holds its last currents and zeroes them when its watchdog expires; then it is plugged
    /// back in under the same link path.
    Unplug(Duration),
    /// Firmware stalls for this long: nothing is read, applied or sent. After the watchdog
    /// period the hardware watchdog resets the board (outputs zero); it boots with an empty
    /// receive buffer when the stall ends.
    Hang(Duration),
    /// A brown-out or a reset: the board restarts at once, unconfigured and disarmed (outputs
    /// zero) with an empty receive buffer.
    Reboot,
}

/// Log the first rejected frame and then every this many (a wrong rig rejects every frame).
const REJECTION_LOG_EVERY: u64 = 100;

/// What the emulated board currently drives, shared with the plant loop. Coil arrays hold the
/// board's `coil_count` channels first; the rest stay zero.
#[derive(Debug, Clone)]
pub struct TeensyOutputs {
    /// Channels of the board: a `SetCurrents` for another count is rejected.
    pub coil_count: usize,
    pub currents_a: [f64; MAX_COILS],
    /// Currents of the newest controller command (not a safe-zero, not the watchdog).
    pub last_command_currents_a: [f64; MAX_COILS],
    /// Frame of the newest controller command applied (`NO_FRAME` for none).
    pub last_command_frame: u64,
    pub watchdog_tripped: bool,
    pub frames_received: u64,
    pub rx_errors: u64,
    /// `SetCurrents` frames refused because their coil count is not the board's.
    pub rejected_frames: u64,
}

impl TeensyOutputs {
    /// The currents the board's channels drive.
    pub fn currents(&self) -> &[f64] {
        &self.currents_a[..self.coil_count]
    }

    /// The currents of the newest controller command, one per channel.
    pub fn last_command_currents(&self) -> &[f64] {
        &self.last_command_currents_a[..self.coil_count]
    }
}

struct Shared {
    outputs: Mutex<TeensyOutputs>,
    /// The board's logic: the same crate the Teensy firmware links (`firmware/core`).
    board: Mutex<Board>,
    command_arrived: Condvar,
    stop: AtomicBool,
    /// The e-stop input pin (pressed = true); the board latches on it.
    estop_pressed: AtomicBool,
    /// Per channel, what the current sense reads as a fraction of the current driven (1: a
    /// healthy channel; a faulty driver or an open coil reads less).
    sense_gain: Mutex<[f64; MAX_COILS]>,
    fault: Mutex<Option<LinkFault>>,
}

pub struct EmulatedTeensy {
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
    pub link_path: PathBuf,
}

impl EmulatedTeensy {
    /// Creates the pty pair, links its slave to `link_path`, and starts serving a board with
    /// `coil_count` channels (1 to `MAX_COILS`).
    pub fn start(
        link_path: &Path,
        events_path: &Path,
        watchdog: Duration,
        coil_count: usize,
    ) -> anyhow::Result<Self> {
        if coil_count == 0 || coil_count > MAX_COILS {
            anyhow::bail!("emulated Teensy: {coil_count} channels, must be 1 to {MAX_COILS}");
        }
        let mut pty = Pty::plug_in(link_path)?;
        // Append: a restarted plant continues the board's log.
        let mut events = TeensyEvents::open_append(events_path)?;

        let shared = Arc::new(Shared {
            outputs: Mutex::new(TeensyOutputs {
                coil_count,
                currents_a: [0.0; MAX_COILS],
                last_command_currents_a: [0.0; MAX_COILS],
                last_command_frame: NO_FRAME,
                watchdog_tripped: true,
                frames_received: 0,
                rx_errors: 0,
                rejected_frames: 0,
            }),
            board: Mutex::new(Board::new(HardwareLimits::standard(coil_count))),
            command_arrived: Condvar::new(),
            stop: AtomicBool::new(false),
            estop_pressed: AtomicBool::new(false),
            sense_gain: Mutex::new([1.0; MAX_COILS]),
            fault: Mutex::new(None),
        });
        let thread_shared = shared.clone();
        let thread_link = link_path.to_owned();
        let thread = std::thread::Builder::new()
            .name("teensy".into())
            .spawn(move || {
                // When the last frame arrived; the board's watchdog runs from it, plugged in or not.
                let mut last_rx: Option<Instant> = None;
                loop {
                    let unplugged_for = match serve(
                        &mut pty.master,
                        &thread_shared,
                        &mut events,
                        watchdog,
                        &mut last_rx,
                    ) {
                        Served::Stopped => return,
                        Served::Unplugged(duration) => duration,
                    };
                    drop(pty);
                    let _ = std::fs::remove_file(&thread_link);
                    let held = lock(&thread_shared).currents_a;
                    log_event(&mut events, NO_FRAME, 0, &held, "unplugged");
                    tracing::warn!("emulated Teensy unplugged for {unplugged_for:?}");
                    if !run_unplugged(
                        &thread_shared,
                        &mut events,
                        watchdog,
                        last_rx,
                        unplugged_for,
                    ) {
                        return;
                    }
                    pty = loop {
                        match Pty::plug_in(&thread_link) {
                            Ok(pty) => break pty,
                            Err(e) => {
                                tracing::error!("emulated Teensy cannot re-create its pty: {e:#}");
                                if !sleep_unless_stopped(&thread_shared, REPLUG_RETRY) {
                                    return;
                                }
                            }
                        }
                    };
                    let outputs = lock(&thread_shared).currents_a;
                    log_event(&mut events, NO_FRAME, 0, &outputs, "replugged");
                }
            })?;
        Ok(Self {
            shared,
            thread: Some(thread),
            link_path: link_path.to_owned(),
        })
    }

    /// Makes the board suffer `fault` (it acts on it within a few milliseconds).
    pub fn inject(&self, fault: LinkFault) {
        *self.shared.fault.lock().unwrap_or_else(|p| p.into_inner()) = Some(fault);
    }

    /// Presses the e-stop button (it stays pressed).
    pub fn press_estop(&self) {
        self.shared.estop_pressed.store(true, Ordering::Relaxed);
    }

    /// From now on channel `channel`'s current sense reads `gain` × the current driven (a
    /// faulty driver channel); other channels read what they drive.
    pub fn fail_channel(&self, channel: usize, gain: f64) {
        if let Some(g) = self
            .shared
            .sense_gain
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get_mut(channel)
        {
            *g = gain;
        }
    }

    pub fn outputs(&self) -> TeensyOutputs {
        lock(&self.shared).clone()
    }

    /// The board's state (unconfigured, disarmed, armed, e-stopped, tripped).
    pub fn board_state(&self) -> BoardState {
        lock_board(&self.shared).state()
    }

    /// Blocks until a command for `frame_seq` (or newer) has been applied, or `timeout` passes.
    /// Returns the outputs and whether the command arrived in time.
    pub fn wait_for_frame(&self, frame_seq: u64, timeout: Duration) -> (TeensyOutputs, bool) {
        let deadline = Instant::now() + timeout;
        let mut guard = lock(&self.shared);
        loop {
            if guard.last_command_frame != NO_FRAME && guard.last_command_frame >= frame_seq {
                return (guard.clone(), true);
            }
            let now = Instant::now();
            if now >= deadline || self.shared.stop.load(Ordering::Relaxed) {
                return (guard.clone(), false);
            }
            guard = match self
                .shared
                .command_arrived
                .wait_timeout(guard, deadline - now)
            {
                Ok((g, _)) => g,
                Err(poisoned) => poisoned.into_inner().0,
            };
        }
    }

    pub fn stop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
        let _ = std::fs::remove_file(&self.link_path);
    }
}

impl Drop for EmulatedTeensy {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The board's end of a pty pair, its slave linked where coilbus looks for the port.
struct Pty {
    master: TTYPort,
    /// Kept open so the pty lives while coilbus restarts and reopens the slave.
    _slave: TTYPort,
}

impl Pty {
    fn plug_in(link_path: &Path) -> anyhow::Result<Self> {
        let (master, slave) = TTYPort::pair()?;
        let slave_name = slave
            .name()
            .ok_or_else(|| anyhow::anyhow!("pty slave has no device path"))?;
        // Keep our fds out of children and let coilbus reopen the slave after a restart.
        let mut master = master.try_clone_native()?;
        master.set_timeout(Duration::from_millis(5))?;
        let mut slave = slave.try_clone_native()?;
        slave.set_exclusive(false)?;
        // Replace the link atomically: coilbus never sees a half-made one.
        let staging = link_path.with_extension("plugging");
        let _ = std::fs::remove_file(&staging);
        std::os::unix::fs::symlink(&slave_name, &staging)?;
        std::fs::rename(&staging, link_path)?;
        tracing::info!(pty = %slave_name, link = %link_path.display(), "emulated Teensy ready");
        Ok(Self {
            master,
            _slave: slave,
        })
    }
}

/// A reset board: the firmware starts over, unconfigured and disarmed, outputs zero; logs why.
fn power_off(shared: &Shared, events: &mut TeensyEvents, event: &str) {
    {
        let mut board = lock_board(shared);
        let channels = lock(shared).coil_count;
        *board = Board::new(HardwareLimits::standard(channels));
        sync_outputs(shared, &board);
    }
    log_event(events, NO_FRAME, 0, &[0.0], event);
}

fn lock_board(shared: &Shared) -> std::sync::MutexGuard<'_, Board> {
    shared.board.lock().unwrap_or_else(|p| p.into_inner())
}

/// What the board drives, into the outputs the plant reads.
fn sync_outputs(shared: &Shared, board: &Board) {
    let driven = board.driven_ma();
    let mut out = lock(shared);
    for (a, ma) in out.currents_a.iter_mut().zip(driven) {
        *a = ma_to_amps(ma);
    }
    out.watchdog_tripped = !board.driving();
}

/// Milliseconds on the run's monotonic clock: the board's time base.
fn board_ms() -> u64 {
    millinav_kit::clock::monotonic_ns() / 1_000_000
}

/// Advances the board's clock (watchdog, heat budget); logs `watchdog_zero` or `thermal_trip`
/// when it stops driving on its own.
fn board_tick(shared: &Shared, events: &mut TeensyEvents) {
    let gains = *shared.sense_gain.lock().unwrap_or_else(|p| p.into_inner());
    let pressed = shared.estop_pressed.load(Ordering::Relaxed);
    let mut board = lock_board(shared);
    let was_driving = board.driving();
    // The emulated current sense: what the channel drives, times its gain.
    let mut measured = board.driven_ma();
    for (ma, gain) in measured.iter_mut().zip(gains) {
        *ma = (f64::from(*ma) * gain).round() as i32;
    }
    board.tick(board_ms(), pressed, Some(&measured));
    sync_outputs(shared, &board);
    if was_driving && !board.driving() {
        let why = match board.state() {
            BoardState::ThermalTrip => "thermal_trip",
            BoardState::EStop => "estop",
            _ => "watchdog_zero",
        };
        log_event(events, NO_FRAME, 0, &[0.0], why);
        tracing::warn!("emulated Teensy stopped driving on its own: {why}");
    }
}

/// Cable out for `duration`: nothing arrives, the firmware keeps running and its watchdog
/// zeroes the held currents. False when the board was stopped meanwhile.
fn run_unplugged(
    shared: &Shared,
    events: &mut RunLogWriter<TeensyEventRow>,
    watchdog: Duration,
    last_rx: Option<Instant>,
    duration: Duration,
) -> bool {
    let _ = (watchdog, last_rx);
    let until = Instant::now() + duration;
    loop {
        let now = Instant::now();
        board_tick(shared, events);
        if now >= until {
            return true;
        }
        if !sleep_unless_stopped(shared, Duration::from_millis(5).min(until - now)) {
            return false;
        }
    }
}

/// Sleeps `duration` in short steps; false when the board was stopped meanwhile.
fn sleep_unless_stopped(shared: &Shared, duration: Duration) -> bool {
    let until = Instant::now() + duration;
    while Instant::now() < until {
        if shared.stop.load(Ordering::Relaxed) {
            return false;
        }
        std::thread::sleep(Duration::from_millis(5).min(until - Instant::now()));
    }
    !shared.stop.load(Ordering::Relaxed)
}

/// Firmware stall: nothing served for `duration`. A stall longer than `watchdog` trips the
/// hardware watchdog, which resets the board (outputs zero, empty receive buffer). False when
/// the board was stopped meanwhile.
fn stall(
    port: &mut TTYPort,
    shared: &Shared,
    events: &mut TeensyEvents,
    watchdog: Duration,
    duration: Duration,
) -> bool {
    let started = Instant::now();
    let driving = lock(shared).currents_a;
    log_event(events, NO_FRAME, 0, &driving, "hang");
    tracing::warn!("emulated Teensy firmware stalled for {duration:?}");
    if duration <= watchdog {
        return sleep_unless_stopped(shared, duration);
    }
    if !sleep_unless_stopped(shared, watchdog) {
        return false;
    }
    power_off(shared, events, "hw_watchdog_reset");
    if !sleep_unless_stopped(shared, duration.saturating_sub(started.elapsed())) {
        return false;
    }
    let _ = port.clear(serialport::ClearBuffer::Input);
    log_event(events, NO_FRAME, 0, &[0.0], "rebooted");
    true
}

/// Hands one frame to the board and mirrors what it did into the outputs and the event log;
/// returns the board's reply (an `Ack` for `SetCurrents`).
fn apply_packet(
    shared: &Shared,
    events: &mut RunLogWriter<TeensyEventRow>,
    packet: &Packet,
) -> Option<Packet> {
    let mut board = lock_board(shared);
    let reply = board.handle(packet, board_ms());
    sync_outputs(shared, &board);
    let driven: Vec<f64> = board.driven_ma().iter().map(|&ma| ma_to_amps(ma)).collect();
    drop(board);
    let Message::SetCurrents {
        frame_seq, flags, ..
    } = &packet.message
    else {
        let event = match packet.message {
            Message::Config(_) => "config",
            Message::Arm => "arm",
            Message::Disarm => "disarm",
            Message::EStop => "estop",
            _ => return reply,
        };
        log_event(events, NO_FRAME, 0, &driven, event);
        return reply;
    };
    let (frame_seq, flags) = (*frame_seq, *flags);
    let status = match reply.as_ref().map(|p| &p.message) {
        Some(Message::Ack { status, .. }) => *status,
        _ => AckStatus::Applied as u8,
    };
    if status == AckStatus::RejectedCoilCount as u8 {
        let (rejected, coil_count) = {
            let mut out = lock(shared);
            out.rejected_frames += 1;
            (out.rejected_frames, out.coil_count)
        };
        log_event(events, frame_seq, flags, &[0.0], "rejected_coil_count");
        if rejected == 1 || rejected.is_multiple_of(REJECTION_LOG_EVERY) {
            tracing::error!(
                rejected,
                "emulated Teensy rejected a frame for another coil count: the board has \
                 {coil_count} channels; nothing applied"
            );
        }
        return reply;
    }
    if status == AckStatus::NotArmed as u8 {
        log_event(events, frame_seq, flags, &[0.0], "not_armed");
        return reply;
    }
    let event = if flags & FLAG_SAFE_ZERO != 0 {
        "safe_zero"
    } else {
        "command"
    };
    log_event(events, frame_seq, flags, &driven, event);
    {
        let mut out = lock(shared);
        out.frames_received += 1;
        if flags & FLAG_SAFE_ZERO == 0 {
            out.last_command_frame = frame_seq;
            out.last_command_currents_a[..driven.len()].copy_from_slice(&driven);
        }
    }
    shared.command_arrived.notify_all();
    reply
}

enum Served {
    Stopped,
    Unplugged(Duration),
}

fn lock(shared: &Shared) -> std::sync::MutexGuard<'_, TeensyOutputs> {
    shared.outputs.lock().unwrap_or_else(|p| p.into_inner())
}

type TeensyEvents = RunLogWriter<TeensyEventRow>;

/// Logs what the board received or did, flushed at once: tests watch this file during the run.
fn log_event(events: &mut TeensyEvents, frame_seq: u64, flags: u8, currents: &[f64], event: &str) {
    let row = TeensyEventRow {
        monotonic_ns: millinav_kit::clock::monotonic_ns(),
        frame_seq: (frame_seq != NO_FRAME).then_some(frame_seq),
        flags,
        max_abs_current_a: currents.iter().fold(0.0f64, |m, c| m.max(c.abs())),
        event: event.to_owned(),
    };
    if let Err(e) = events.append_now(&row) {
        tracing::warn!("emulated Teensy cannot log its event: {e}");
    }
}

fn serve(
    port: &mut TTYPort,
    shared: &Shared,
    events: &mut TeensyEvents,
    watchdog: Duration,
    last_rx: &mut Option<Instant>,
) -> Served {
    let mut decoder = Decoder::new();
    let mut buf = [0u8; 1024];
    let mut last_telemetry = Instant::now();
    let mut tx_seq = 0u32;
    while !shared.stop.load(Ordering::Relaxed) {
        let fault = shared
            .fault
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take();
        match fault {
            Some(LinkFault::Unplug(duration)) => return Served::Unplugged(duration),
            Some(LinkFault::Hang(duration)) => {
                if !stall(port, shared, events, watchdog, duration) {
                    return Served::Stopped;
                }
                // A reset board starts from scratch.
                decoder = Decoder::new();
                *last_rx = None;
                continue;
            }
            Some(LinkFault::Reboot) => {
                power_off(shared, events, "reboot");
                let _ = port.clear(serialport::ClearBuffer::Input);
                log_event(events, NO_FRAME, 0, &[0.0], "rebooted");
                tracing::warn!("emulated Teensy rebooted: unconfigured and disarmed");
                decoder = Decoder::new();
                continue;
            }
            None => {}
        }
        let packets = match port.read(&mut buf) {
            Ok(n) => decoder.push(&buf[..n]),
            // TimedOut: nothing waiting. BrokenPipe: no peer has the slave open right now.
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => Vec::new(),
            Err(_) => {
                std::thread::sleep(Duration::from_millis(5));
                Vec::new()
            }
        };
        let now = Instant::now();
        for packet in packets {
            if let Message::SetCurrents { .. } = packet.message {
                *last_rx = Some(now);
            }
            if let Some(reply) = apply_packet(shared, events, &packet) {
                let _ = port.write_all(&encode(&reply));
            }
        }
        lock(shared).rx_errors = decoder.counters.errors();
        board_tick(shared, events);
        if now.duration_since(last_telemetry) >= TELEMETRY_PERIOD {
            last_telemetry = now;
            let out = lock(shared).clone();
            let applied_ma: Vec<i32> = out.currents().iter().map(|a| amps_to_ma(*a)).collect();
            // `coil_count` ≤ MAX_COILS is checked in `start`.
            let applied_ma = CoilValues::new(&applied_ma).unwrap_or_else(|| CoilValues::zeros(0));
            tx_seq = tx_seq.wrapping_add(1);
            let telemetry = encode(&Packet {
                seq: tx_seq,
                message: Message::Telemetry {
                    applied_ma,
                    watchdog_tripped: out.watchdog_tripped,
                    rx_errors: out.rx_errors.min(u32::MAX as u64) as u32,
                    frames_received: (out.frames_received & u32::MAX as u64) as u32,
                },
            });
            let _ = port.write_all(&telemetry);
            let status = {
                let mut board = lock_board(shared);
                board.rx_errors = out.rx_errors.min(u32::MAX as u64) as u32;
                board.status()
            };
            let _ = port.write_all(&encode(&status));
        }
    }
    Served::Stopped
}
