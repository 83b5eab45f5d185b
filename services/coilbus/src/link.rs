//! The serial link to the Teensy: opens lazily, reconnects after the port vanishes, never blocks
//! the loop for long.

use std::io::{Read, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};

use crate::protocol::{encode, BoardConfig, BoardState, Decoder, Message, Packet};

const RECONNECT_INTERVAL: Duration = Duration::from_millis(100);
const IO_TIMEOUT: Duration = Duration::from_millis(5);
/// The Teensy sends telemetry every 50 ms; this long without a byte means it hung or the link
/// is dead even though the device node is still there, so the port is closed and reopened.
pub const LINK_SILENCE: Duration = Duration::from_millis(200);

/// A change of the link, with the run clock's time, for the run directory's link log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LinkEvent {
    pub monotonic_ns: u64,
    /// `open` or `lost`.
    pub kind: &'static str,
    pub detail: String,
}

pub struct SerialLink {
    path: PathBuf,
    baud: u32,
    port: Option<TTYPort>,
    decoder: Decoder,
    tx_seq: u32,
    last_attempt: Option<Instant>,
    pub reconnects: u64,
    was_open: bool,
    last_rx: Option<Instant>,
    events: Vec<LinkEvent>,
    /// What the board is told at start-up (`Config`), and whether it should be armed.
    board_config: Option<BoardConfig>,
    arm_wanted: bool,
    /// The board's state from its last `Status`.
    board_state: Option<BoardState>,
    /// Valid packets decoded when the port last opened.
    packets_at_open: u64,
}

impl SerialLink {
    pub fn new(path: PathBuf, baud: u32) -> Self {
        Self {
            path,
            baud,
            port: None,
            decoder: Decoder::new(),
            tx_seq: 0,
            last_attempt: None,
            reconnects: 0,
            was_open: false,
            last_rx: None,
            events: Vec::new(),
            board_config: None,
            arm_wanted: false,
            board_state: None,
            packets_at_open: 0,
        }
    }

    /// The configuration the board gets whenever it reports itself unconfigured (at start-up
    /// and after a reset).
    pub fn set_board_config(&mut self, config: BoardConfig) {
        self.board_config = Some(config);
    }

    /// Whether the board should be armed: a configured, disarmed board is sent `Arm` while this
    /// holds. A latched e-stop or thermal trip is never re-armed from here.
    pub fn set_arm_wanted(&mut self, wanted: bool) {
        self.arm_wanted = wanted;
    }

    /// The board's state from its last `Status` frame (none yet: an old board or no link).
    pub fn board_state(&self) -> Option<BoardState> {
        self.board_state
    }

    /// Opens the link and polls until the board reports itself armed (after `Config` and `Arm`
    /// when [`Self::set_board_config`] and [`Self::set_arm_wanted`] asked for them), or `timeout`
    /// passes; true when armed. For tools and tests that talk to a board directly.
    pub fn wait_armed(&mut self, timeout: Duration) -> bool {
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            self.ensure_open(Instant::now());
            self.poll();
            if self.board_state == Some(BoardState::Armed) {
                return true;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        false
    }

    /// Configures and arms the board as its `Status` asks for.
    fn handshake(&mut self, state: BoardState) {
        self.board_state = Some(state);
        match state {
            BoardState::Unconfigured => {
                if let Some(config) = self.board_config {
                    self.send(&Message::Config(config));
                }
            }
            BoardState::Disarmed if self.arm_wanted => {
                self.send(&Message::Arm);
            }
            _ => {}
        }
    }

    /// The protocol version the board speaks when it is not this host's: well-formed frames of
    /// another version arrived since the port opened and no valid one did.
    pub fn foreign_version(&self) -> Option<u8> {
        self.decoder
            .foreign_version
            .filter(|_| self.decoder.counters.packets == self.packets_at_open)
    }

    /// Logs a board fault with the link's changes (`coilbus_link.csv`).
    pub fn record_board_fault(&mut self, kind: &str, detail: &str) {
        self.record("board_fault", format!("{kind}: {detail}"));
    }

    pub fn is_open(&self) -> bool {
        self.port.is_some()
    }

    pub fn decoder_errors(&self) -> u64 {
        self.decoder.counters.errors()
    }

    /// Link changes since the last call.
    pub fn take_events(&mut self) -> Vec<LinkEvent> {
        std::mem::take(&mut self.events)
    }

    fn record(&mut self, kind: &'static str, detail: String) {
        self.events.push(LinkEvent {
            monotonic_ns: millinav_kit::clock::monotonic_ns(),
            kind,
            detail,
        });
    }

    /// Closes a port that has been silent for `LINK_SILENCE`, then tries to (re)open the port,
    /// at most once per reconnect interval.
    pub fn ensure_open(&mut self, now: Instant) {
        if self.port.is_some()
            && self
                .last_rx
                .is_some_and(|t| now.duration_since(t) > LINK_SILENCE)
        {
            let why = std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                format!("no byte from the Teensy for {LINK_SILENCE:?}"),
            );
            self.drop_port(&why);
        }
        if self.port.is_some() {
            return;
        }
        if self
            .last_attempt
            .is_some_and(|t| now.duration_since(t) < RECONNECT_INTERVAL)
        {
            return;
        }
        self.last_attempt = Some(now);
        let path = self.path.to_string_lossy().into_owned();
        match serialport::new(&path, self.baud)
            .timeout(IO_TIMEOUT)
            // A restarted coilbus must be able to reopen the same device.
            .exclusive(false)
            .open_native()
        {
            Ok(port) => {
                // What waits in the port was written before this process listened (frames
                // queued while a predecessor was stopped): it says nothing about now.
                let _ = port.clear(serialport::ClearBuffer::Input);
                if self.was_open {
                    self.reconnects += 1;
                }
                self.was_open = true;
                tracing::info!(port = %path, "serial link open");
                self.port = Some(port);
                self.last_rx = Some(now);
                self.packets_at_open = self.decoder.counters.packets;
                self.decoder.foreign_version = None;
                self.record("open", path);
            }
            Err(e) => tracing::debug!(port = %path, "serial open failed: {e}"),
        }
    }

    fn drop_port(&mut self, why: &std::io::Error) {
        tracing::warn!(port = %self.path.display(), "serial link lost: {why}");
        self.port = None;
        self.record("lost", why.to_string());
    }

    /// Encodes and writes one message; false (and the port closed for reconnect) on failure.
    pub fn send(&mut self, message: &Message) -> bool {
        let Some(port) = self.port.as_mut() else {
            return false;
        };
        self.tx_seq = self.tx_seq.wrapping_add(1);
        let bytes = encode(&Packet {
            seq: self.tx_seq,
            message: message.clone(),
        });
        match port.write_all(&bytes) {
            Ok(()) => true,
            Err(e) => {
                self.drop_port(&e);
                false
            }
        }
    }

    /// Reads whatever is waiting, without blocking, and returns decoded packets.
    pub fn poll(&mut self) -> Vec<Packet> {
        let Some(port) = self.port.as_mut() else {
            return Vec::new();
        };
        let waiting = match port.bytes_to_read() {
            Ok(n) => n as usize,
            Err(e) => {
                let e = std::io::Error::other(e.to_string());
                self.drop_port(&e);
                return Vec::new();
            }
        };
        if waiting == 0 {
            return Vec::new();
        }
        let mut buf = vec![0u8; waiting.min(64 * 1024)];
        match port.read(&mut buf) {
            Ok(n) => {
                if n > 0 {
                    self.last_rx = Some(Instant::now());
                }
                let packets = self.decoder.push(&buf[..n]);
                let newest = packets.iter().rev().find_map(|p| match &p.message {
                    Message::Status(st) => BoardState::from_repr(st.state),
                    _ => None,
                });
                if let Some(state) = newest {
                    self.handshake(state);
                }
                packets
            }
            // A signal (SIGCONT, ...) that interrupted the wait is not a lost link.
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::TimedOut | std::io::ErrorKind::Interrupted
                ) =>
            {
                Vec::new()
            }
            Err(e) => {
                self.drop_port(&e);
                Vec::new()
            }
        }
    }
}
