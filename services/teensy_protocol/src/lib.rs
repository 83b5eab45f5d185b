//! The Teensy serial protocol, spoken by coilbus and by the plant's emulated Teensy.
//!
//! Every frame on the wire (protocol version 2):
//!
//! | bytes | field | notes |
//! |---|---|---|
//! | 2 | sync | `0xA5 0x5A` |
//! | 1 | version | `PROTOCOL_VERSION`; a frame of another version is dropped and counted |
//! | 1 | kind | `MessageKind` |
//! | 2 | length | payload length, little endian, ≤ `MAX_PAYLOAD` |
//! | 4 | seq | sender's frame counter, little endian, wraps |
//! | length | payload | see `Message` |
//! | 2 | crc | CRC-16/CCITT-FALSE over version, kind, length, seq and payload, little endian |
//!
//! Payloads (all little endian; `n` = coil count, 0 ≤ n ≤ `MAX_COILS`):
//! - `SetCurrents` (0x01): frame_seq u64 (camera frame the command answers, `u64::MAX` for none),
//!   flags u8 (bit 0: safe-state zero), n u8, n x i32 coil currents in mA.
//! - `Ack` (0x02): acked seq u32, status u8 (`AckStatus`).
//! - `Telemetry` (0x03): n u8, n x i32 applied currents in mA, watchdog tripped u8, rx errors
//!   u32, frames received u32.
//!
//! The decoder resynchronises on the sync word after any corruption and counts what it dropped;
//! it never panics on arbitrary input. The full description (tables, CRC parameters, coil-count
//! check, watchdog semantics) is in `services/teensy_protocol/PROTOCOL.md`.
//!
//! Without its default `std` feature the crate is `no_std` and allocation-free (fixed buffers:
//! [`Frame`], the decoder's own), so the board firmware links the same code as the host; `std`
//! only adds the `Vec`-returning conveniences ([`Decoder::push`], [`check_decoder_invariants`]).
#![cfg_attr(not(feature = "std"), no_std)]

use crc::{Crc, CRC_16_IBM_3740};

/// Version byte of every frame. 1 was the fixed 12-coil layout without a version byte; 2 adds
/// the version byte and carries the coil count in `SetCurrents` and `Telemetry`.
pub const PROTOCOL_VERSION: u8 = 2;

use shm_schemas_core::wire_enum;
/// Most coils one frame can address: the contract's limit.
pub use shm_schemas_core::{BoardState, MAX_COILS};

pub const SYNC: [u8; 2] = [0xA5, 0x5A];
pub const HEADER_LEN: usize = 2 + 1 + 1 + 2 + 4;
pub const CRC_LEN: usize = 2;
/// Longest payload: a `Config` for `MAX_COILS` coils.
pub const MAX_PAYLOAD: usize = CONFIG_FIXED + CONFIG_PER_COIL * MAX_COILS;
/// Longest frame on the wire.
pub const MAX_FRAME: usize = HEADER_LEN + MAX_PAYLOAD + CRC_LEN;
/// CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF), known in the crc crate as IBM-3740.
const CRC16: Crc<u16> = Crc::<u16>::new(&CRC_16_IBM_3740);

const SET_CURRENTS_FIXED: usize = 8 + 1 + 1;
const ACK_LEN: usize = 4 + 1;
const TELEMETRY_FIXED: usize = 1 + 1 + 4 + 4;
const CONFIG_FIXED: usize = 1 + 4 + 2;
const CONFIG_PER_COIL: usize = 4 * 4;
const STATUS_FIXED: usize = 1 + 1 + 1 + 4 + 4;
const STATUS_PER_COIL: usize = 4 + 4 + 4 + 2;

/// The payload of `Arm`: arming is a deliberate act, not a byte a glitch can forge.
pub const ARM_KEY: [u8; 4] = *b"ARM!";
/// `Status.measured_ma` of a channel without a current sense input.
pub const NOT_MEASURED: i32 = i32::MIN;

/// Flag bit in `SetCurrents`: this is a safe-state zero, not a controller command.
pub const FLAG_SAFE_ZERO: u8 = 1;

/// Per-coil values of one frame (mA): at most `MAX_COILS`, their count travels in the frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CoilValues {
    values: [i32; MAX_COILS],
    count: u8,
}

impl CoilValues {
    /// `values` as a frame's coil block, or `None` when there are more than `MAX_COILS`.
    pub fn new(values: &[i32]) -> Option<Self> {
        if values.len() > MAX_COILS {
            return None;
        }
        let mut out = [0i32; MAX_COILS];
        out[..values.len()].copy_from_slice(values);
        Some(Self {
            values: out,
            count: values.len() as u8,
        })
    }

    /// `count` zeros (`count` is capped at `MAX_COILS`).
    pub fn zeros(count: usize) -> Self {
        Self {
            values: [0; MAX_COILS],
            count: count.min(MAX_COILS) as u8,
        }
    }

    pub fn len(&self) -> usize {
        usize::from(self.count)
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    pub fn as_slice(&self) -> &[i32] {
        &self.values[..self.len()]
    }
}

wire_enum! {
    pub enum MessageKind: u8 {
        SetCurrents = 0x01 => "set_currents",
        Ack = 0x02 => "ack",
        Telemetry = 0x03 => "telemetry",
        Arm = 0x04 => "arm",
        Disarm = 0x05 => "disarm",
        EStop = 0x06 => "estop",
        Config = 0x07 => "config",
        Status = 0x08 => "status",
    }
}

/// One coil's electrical and thermal rating, as the host sends it in `Config`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CoilRating {
    pub resistance_mohm: u32,
    /// Current magnitude limit, mA.
    pub max_ma: u32,
    /// Current the coil carries indefinitely, mA (the I²t budget fills above it).
    pub continuous_ma: u32,
    /// Heat budget above the continuous current, ∫(I² − I_c²) dt, in mA²·s / 1000 (= A²·s × 1000).
    pub i2t_budget: u32,
}

/// `Config` payload: supply voltage, watchdog and every channel's rating.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BoardConfig {
    pub supply_mv: u32,
    pub watchdog_ms: u16,
    coils: [CoilRating; MAX_COILS],
    count: u8,
}

impl BoardConfig {
    /// `None` when there are more than `MAX_COILS` ratings.
    pub fn new(supply_mv: u32, watchdog_ms: u16, coils: &[CoilRating]) -> Option<Self> {
        (coils.len() <= MAX_COILS).then(|| Self::of_first(supply_mv, watchdog_ms, coils))
    }

    /// The first `MAX_COILS` of `coils` (all of them when they fit).
    pub fn of_first(supply_mv: u32, watchdog_ms: u16, coils: &[CoilRating]) -> Self {
        let coils = &coils[..coils.len().min(MAX_COILS)];
        let mut all = [CoilRating::default(); MAX_COILS];
        all[..coils.len()].copy_from_slice(coils);
        Self {
            supply_mv,
            watchdog_ms,
            coils: all,
            count: coils.len() as u8,
        }
    }

    pub fn coils(&self) -> &[CoilRating] {
        &self.coils[..usize::from(self.count)]
    }
}

/// One channel in `Status`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ChannelStatus {
    /// What the host last asked, mA.
    pub commanded_ma: i32,
    /// What the board drives after clamps, derating and state, mA.
    pub applied_ma: i32,
    /// The sense input's reading, mA, or [`NOT_MEASURED`].
    pub measured_ma: i32,
    /// Heat budget used, ‰ (1000 = tripped).
    pub thermal_permille: u16,
}

/// `Status` payload: the board's safety state and every channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BoardStatus {
    /// `BoardState` as a byte.
    pub state: u8,
    /// `STATUS_*` bits.
    pub flags: u8,
    channels: [ChannelStatus; MAX_COILS],
    count: u8,
    pub rx_errors: u32,
    pub frames_received: u32,
}

impl BoardStatus {
    pub fn new(
        state: u8,
        flags: u8,
        channels: &[ChannelStatus],
        rx_errors: u32,
        frames_received: u32,
    ) -> Option<Self> {
        if channels.len() > MAX_COILS {
            return None;
        }
        let mut all = [ChannelStatus::default(); MAX_COILS];
        all[..channels.len()].copy_from_slice(channels);
        Some(Self {
            state,
            flags,
            channels: all,
            count: channels.len() as u8,
            rx_errors,
            frames_received,
        })
    }

    pub fn channels(&self) -> &[ChannelStatus] {
        &self.channels[..usize::from(self.count)]
    }
}

/// `BoardStatus.flags`: the watchdog has zeroed the outputs.
pub const STATUS_WATCHDOG: u8 = 1;
/// At least one channel was clamped to its limit.
pub const STATUS_CLAMPED: u8 = 1 << 1;
/// At least one channel is derated by its heat budget.
pub const STATUS_DERATING: u8 = 1 << 2;
/// The emergency-stop input is active now.
pub const STATUS_ESTOP_INPUT: u8 = 1 << 3;
/// The last `Config` was refused (see the board's limits).
pub const STATUS_CONFIG_REFUSED: u8 = 1 << 4;

wire_enum! {
    pub enum AckStatus: u8 {
        Applied = 0 => "applied",
        /// The Teensy clamped at least one channel to its own hardware limit.
        Clamped = 1 => "clamped",
        /// The frame's coil count is not the board's: nothing was applied (outputs unchanged,
        /// and the frame does not feed the watchdog).
        RejectedCoilCount = 2 => "rejected_coil_count",
        /// The board is not armed (unconfigured, disarmed, e-stopped or thermally tripped):
        /// nothing applied, outputs stay off.
        NotArmed = 3 => "not_armed",
    }
}

#[derive(Debug, Clone, PartialEq)]
pub enum Message {
    SetCurrents {
        frame_seq: u64,
        flags: u8,
        currents_ma: CoilValues,
    },
    Ack {
        acked_seq: u32,
        status: u8,
    },
    Telemetry {
        applied_ma: CoilValues,
        watchdog_tripped: bool,
        rx_errors: u32,
        frames_received: u32,
    },
    /// Host → board: arm (payload [`ARM_KEY`]); also the deliberate re-arm after an e-stop.
    Arm,
    /// Host → board: outputs off, stay configured.
    Disarm,
    /// Host → board: latched emergency stop.
    EStop,
    /// Host → board: supply, watchdog and channel ratings (the board checks them).
    Config(BoardConfig),
    /// Board → host: state, flags and every channel.
    Status(BoardStatus),
}

/// A decoded frame with its link sequence number.
#[derive(Debug, Clone, PartialEq)]
pub struct Packet {
    pub seq: u32,
    pub message: Message,
}

/// Converts amperes to the wire's milliamperes, saturating and mapping NaN to zero.
pub fn amps_to_ma(current_a: f64) -> i32 {
    if current_a.is_nan() {
        return 0;
    }
    // Half away from zero by hand (`f64::round` needs std); `as` saturates at the i32 range.
    let ma = current_a * 1000.0;
    (if ma >= 0.0 { ma + 0.5 } else { ma - 0.5 }) as i32
}

pub fn ma_to_amps(current_ma: i32) -> f64 {
    current_ma as f64 / 1000.0
}

/// One encoded frame: at most [`MAX_FRAME`] bytes in a fixed buffer (no allocation).
#[derive(Clone, Copy)]
pub struct Frame {
    bytes: [u8; MAX_FRAME],
    len: usize,
}

impl Frame {
    fn new() -> Self {
        Self {
            bytes: [0; MAX_FRAME],
            len: 0,
        }
    }

    /// Appends `data`; the encoder never writes more than [`MAX_FRAME`] bytes.
    fn put(&mut self, data: &[u8]) {
        let end = (self.len + data.len()).min(MAX_FRAME);
        let n = end - self.len;
        self.bytes[self.len..end].copy_from_slice(&data[..n]);
        self.len = end;
    }

    pub fn as_slice(&self) -> &[u8] {
        &self.bytes[..self.len]
    }
}

impl core::ops::Deref for Frame {
    type Target = [u8];

    fn deref(&self) -> &[u8] {
        self.as_slice()
    }
}

impl AsRef<[u8]> for Frame {
    fn as_ref(&self) -> &[u8] {
        self.as_slice()
    }
}

impl core::fmt::Debug for Frame {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_list().entries(self.as_slice()).finish()
    }
}

/// Encodes one packet.
pub fn encode(packet: &Packet) -> Frame {
    let mut out = Frame::new();
    out.put(&SYNC);
    out.put(&[PROTOCOL_VERSION, 0, 0, 0]); // version, kind and length filled in below
    out.put(&packet.seq.to_le_bytes());
    let kind = match &packet.message {
        Message::SetCurrents {
            frame_seq,
            flags,
            currents_ma,
        } => {
            out.put(&frame_seq.to_le_bytes());
            out.put(&[*flags, currents_ma.count]);
            for c in currents_ma.as_slice() {
                out.put(&c.to_le_bytes());
            }
            MessageKind::SetCurrents
        }
        Message::Ack { acked_seq, status } => {
            out.put(&acked_seq.to_le_bytes());
            out.put(&[*status]);
            MessageKind::Ack
        }
        Message::Telemetry {
            applied_ma,
            watchdog_tripped,
            rx_errors,
            frames_received,
        } => {
            out.put(&[applied_ma.count]);
            for c in applied_ma.as_slice() {
                out.put(&c.to_le_bytes());
            }
            out.put(&[u8::from(*watchdog_tripped)]);
            out.put(&rx_errors.to_le_bytes());
            out.put(&frames_received.to_le_bytes());
            MessageKind::Telemetry
        }
        Message::Arm => {
            out.put(&ARM_KEY);
            MessageKind::Arm
        }
        Message::Disarm => MessageKind::Disarm,
        Message::EStop => MessageKind::EStop,
        Message::Config(c) => {
            out.put(&[c.count]);
            out.put(&c.supply_mv.to_le_bytes());
            out.put(&c.watchdog_ms.to_le_bytes());
            for r in c.coils() {
                out.put(&r.resistance_mohm.to_le_bytes());
                out.put(&r.max_ma.to_le_bytes());
                out.put(&r.continuous_ma.to_le_bytes());
                out.put(&r.i2t_budget.to_le_bytes());
            }
            MessageKind::Config
        }
        Message::Status(st) => {
            out.put(&[st.state, st.flags, st.count]);
            for ch in st.channels() {
                out.put(&ch.commanded_ma.to_le_bytes());
                out.put(&ch.applied_ma.to_le_bytes());
                out.put(&ch.measured_ma.to_le_bytes());
                out.put(&ch.thermal_permille.to_le_bytes());
            }
            out.put(&st.rx_errors.to_le_bytes());
            out.put(&st.frames_received.to_le_bytes());
            MessageKind::Status
        }
    };
    let payload_len = (out.len - HEADER_LEN) as u16;
    out.bytes[3] = kind as u8;
    out.bytes[4..6].copy_from_slice(&payload_len.to_le_bytes());
    let crc = CRC16.checksum(&out.bytes[2..out.len]);
    out.put(&crc.to_le_bytes());
    out
}

/// What the decoder threw away, for link health telemetry.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DecodeCounters {
    pub packets: u64,
    /// Frames (with a valid-looking header position) of another protocol version.
    pub bad_version: u64,
    pub crc_errors: u64,
    pub bad_length: u64,
    pub unknown_kind: u64,
    pub bad_payload: u64,
    /// Bytes skipped while hunting for a sync word.
    pub skipped_bytes: u64,
}

impl DecodeCounters {
    pub fn errors(&self) -> u64 {
        self.bad_version + self.crc_errors + self.bad_length + self.unknown_kind + self.bad_payload
    }
}

/// Bytes the decoder holds: a partial frame (< [`MAX_FRAME`]) plus one more frame's worth of
/// new input per parsing pass.
const DECODER_CAPACITY: usize = 2 * MAX_FRAME;

/// Streaming decoder: feed it whatever the port returned, take out whole packets. Fixed memory:
/// it never holds more than a partial frame between calls.
#[derive(Debug)]
pub struct Decoder {
    buffer: [u8; DECODER_CAPACITY],
    len: usize,
    pub counters: DecodeCounters,
    /// The version byte of the newest well-formed frame (CRC valid) of another protocol version:
    /// the peer speaks that version.
    pub foreign_version: Option<u8>,
}

/// The length of the frame at the start of `bytes` when it is whole and its CRC holds.
fn whole_frame_len(bytes: &[u8]) -> Option<usize> {
    if bytes.len() < HEADER_LEN {
        return None;
    }
    let length = u16::from_le_bytes([bytes[4], bytes[5]]) as usize;
    let total = HEADER_LEN + length + CRC_LEN;
    if length > MAX_PAYLOAD || bytes.len() < total {
        return None;
    }
    let expected = CRC16.checksum(&bytes[2..HEADER_LEN + length]);
    let got = u16::from_le_bytes([bytes[total - 2], bytes[total - 1]]);
    (expected == got).then_some(total)
}

impl Default for Decoder {
    fn default() -> Self {
        Self {
            buffer: [0; DECODER_CAPACITY],
            len: 0,
            counters: DecodeCounters::default(),
            foreign_version: None,
        }
    }
}

impl Decoder {
    pub fn new() -> Self {
        Self::default()
    }

    /// Bytes held back as the start of a frame not yet complete (always < [`MAX_FRAME`]).
    pub fn pending(&self) -> usize {
        self.len
    }

    /// Appends bytes and returns every complete, valid packet now available.
    #[cfg(feature = "std")]
    pub fn push(&mut self, bytes: &[u8]) -> Vec<Packet> {
        let mut packets = Vec::new();
        self.push_with(bytes, |p| packets.push(p));
        packets
    }

    /// Appends bytes and hands every complete, valid packet now available to `on_packet`, in
    /// order (the allocation-free form of [`Self::push`]).
    pub fn push_with(&mut self, mut bytes: &[u8], mut on_packet: impl FnMut(Packet)) {
        while !bytes.is_empty() {
            let n = bytes.len().min(DECODER_CAPACITY - self.len);
            self.buffer[self.len..self.len + n].copy_from_slice(&bytes[..n]);
            self.len += n;
            bytes = &bytes[n..];
            self.parse(&mut on_packet);
        }
    }

    /// Takes every whole frame out of the buffer; what stays is a partial frame (< MAX_FRAME).
    fn parse(&mut self, on_packet: &mut impl FnMut(Packet)) {
        let mut start = 0usize;
        loop {
            let held = &self.buffer[..self.len];
            // Hunt for the sync word.
            let Some(offset) = find_sync(&held[start..]) else {
                // Keep a trailing 0xA5: it may be the first half of a sync word.
                let keep_from = if held.len() > start && held.last() == Some(&SYNC[0]) {
                    held.len() - 1
                } else {
                    held.len()
                };
                self.counters.skipped_bytes += (keep_from - start) as u64;
                start = keep_from;
                break;
            };
            self.counters.skipped_bytes += offset as u64;
            start += offset;
            let available = &held[start..];
            if available.len() < HEADER_LEN {
                break;
            }
            if available[2] != PROTOCOL_VERSION {
                self.counters.bad_version += 1;
                // A whole frame whose CRC holds under this layout is a peer speaking another
                // version (negotiation: the host refuses it by name); anything else is a false
                // sync. Either way nothing of it is decoded.
                if let Some(total) = whole_frame_len(available) {
                    self.foreign_version = Some(available[2]);
                    start += total;
                } else {
                    start += 1;
                }
                continue;
            }
            let length = u16::from_le_bytes([available[4], available[5]]) as usize;
            if length > MAX_PAYLOAD {
                self.counters.bad_length += 1;
                start += 1; // skip this sync byte and look for the next
                continue;
            }
            let total = HEADER_LEN + length + CRC_LEN;
            if available.len() < total {
                break;
            }
            let frame = &available[..total];
            let expected = CRC16.checksum(&frame[2..HEADER_LEN + length]);
            let got = u16::from_le_bytes([frame[total - 2], frame[total - 1]]);
            if expected != got {
                self.counters.crc_errors += 1;
                start += 1;
                continue;
            }
            let seq = u32::from_le_bytes([frame[6], frame[7], frame[8], frame[9]]);
            let payload = &frame[HEADER_LEN..HEADER_LEN + length];
            match MessageKind::from_repr(frame[3]) {
                None => self.counters.unknown_kind += 1,
                Some(kind) => match parse_payload(kind, payload) {
                    Some(message) => {
                        self.counters.packets += 1;
                        on_packet(Packet { seq, message });
                    }
                    None => self.counters.bad_payload += 1,
                },
            }
            start += total;
        }
        self.buffer.copy_within(start..self.len, 0);
        self.len -= start;
    }
}

/// Feeds `data` to a fresh decoder in chunks whose sizes come from the data itself, then checks
/// the decoder's invariants: every returned packet re-encodes to a frame present in the input,
/// the packet counter matches, and the held-back bytes stay below one frame. Used by the
/// cargo-fuzz target (`fuzz/fuzz_targets/decoder.rs`) and by the property tests; panics on a
/// violation.
#[cfg(feature = "std")]
pub fn check_decoder_invariants(data: &[u8]) {
    let mut decoder = Decoder::new();
    let mut packets = Vec::new();
    let mut rest = data;
    let mut chunk = 1usize;
    while !rest.is_empty() {
        let n = chunk.min(rest.len());
        packets.extend(decoder.push(&rest[..n]));
        assert!(
            decoder.pending() < MAX_FRAME,
            "decoder holds {} bytes",
            decoder.pending()
        );
        chunk = 1 + (rest[0] as usize % 97);
        rest = &rest[n..];
    }
    assert_eq!(decoder.counters.packets, packets.len() as u64);
    for packet in &packets {
        let bytes = encode(packet);
        assert!(
            data.windows(bytes.len()).any(|w| w == bytes.as_slice()),
            "decoded a packet that is not in the input: {packet:?}"
        );
    }
}

/// The first valid packet in `bytes` (a whole frame, e.g. from [`encode`]), if any.
pub fn decode_one(bytes: &[u8]) -> Option<Packet> {
    let mut decoder = Decoder::new();
    let mut first = None;
    decoder.push_with(bytes, |p| {
        if first.is_none() {
            first = Some(p);
        }
    });
    first
}

fn find_sync(bytes: &[u8]) -> Option<usize> {
    bytes.windows(2).position(|w| w == SYNC)
}

/// Reads a coil block: a count byte, then that many i32; `None` unless exactly `bytes` long
/// after `tail` trailing bytes are set aside.
fn read_coil_block(bytes: &[u8], tail: usize) -> Option<(CoilValues, &[u8])> {
    let (&count, rest) = bytes.split_first()?;
    let count = usize::from(count);
    if count > MAX_COILS || rest.len() != 4 * count + tail {
        return None;
    }
    let mut values = [0i32; MAX_COILS];
    for (value, chunk) in values.iter_mut().zip(rest[..4 * count].chunks_exact(4)) {
        *value = i32::from_le_bytes([chunk[0], chunk[1], chunk[2], chunk[3]]);
    }
    Some((
        CoilValues {
            values,
            count: count as u8,
        },
        &rest[4 * count..],
    ))
}

fn read_u32(bytes: &[u8]) -> u32 {
    u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]])
}

fn parse_payload(kind: MessageKind, payload: &[u8]) -> Option<Message> {
    match kind {
        MessageKind::SetCurrents if payload.len() >= SET_CURRENTS_FIXED => {
            let mut seq_bytes = [0u8; 8];
            seq_bytes.copy_from_slice(&payload[..8]);
            let (currents_ma, _) = read_coil_block(&payload[9..], 0)?;
            Some(Message::SetCurrents {
                frame_seq: u64::from_le_bytes(seq_bytes),
                flags: payload[8],
                currents_ma,
            })
        }
        MessageKind::Ack if payload.len() == ACK_LEN => Some(Message::Ack {
            acked_seq: read_u32(payload),
            status: payload[4],
        }),
        MessageKind::Telemetry if payload.len() >= TELEMETRY_FIXED => {
            let (applied_ma, tail) = read_coil_block(payload, 9)?;
            Some(Message::Telemetry {
                applied_ma,
                watchdog_tripped: tail[0] != 0,
                rx_errors: read_u32(&tail[1..]),
                frames_received: read_u32(&tail[5..]),
            })
        }
        MessageKind::Arm if payload == ARM_KEY => Some(Message::Arm),
        MessageKind::Disarm if payload.is_empty() => Some(Message::Disarm),
        MessageKind::EStop if payload.is_empty() => Some(Message::EStop),
        MessageKind::Config if payload.len() >= CONFIG_FIXED => {
            let n = usize::from(payload[0]);
            if n > MAX_COILS || payload.len() != CONFIG_FIXED + CONFIG_PER_COIL * n {
                return None;
            }
            let mut coils = [CoilRating::default(); MAX_COILS];
            for (k, c) in coils.iter_mut().take(n).enumerate() {
                let b = &payload[CONFIG_FIXED + CONFIG_PER_COIL * k..];
                *c = CoilRating {
                    resistance_mohm: read_u32(b),
                    max_ma: read_u32(&b[4..]),
                    continuous_ma: read_u32(&b[8..]),
                    i2t_budget: read_u32(&b[12..]),
                };
            }
            Some(Message::Config(BoardConfig {
                supply_mv: read_u32(&payload[1..]),
                watchdog_ms: u16::from_le_bytes([payload[5], payload[6]]),
                coils,
                count: n as u8,
            }))
        }
        MessageKind::Status if payload.len() >= STATUS_FIXED => {
            let n = usize::from(payload[2]);
            if n > MAX_COILS || payload.len() != STATUS_FIXED + STATUS_PER_COIL * n {
                return None;
            }
            let mut channels = [ChannelStatus::default(); MAX_COILS];
            for (k, ch) in channels.iter_mut().take(n).enumerate() {
                let b = &payload[3 + STATUS_PER_COIL * k..];
                *ch = ChannelStatus {
                    commanded_ma: read_u32(b) as i32,
                    applied_ma: read_u32(&b[4..]) as i32,
                    measured_ma: read_u32(&b[8..]) as i32,
                    thermal_permille: u16::from_le_bytes([b[12], b[13]]),
                };
            }
            let tail = &payload[3 + STATUS_PER_COIL * n..];
            Some(Message::Status(BoardStatus {
                state: payload[0],
                flags: payload[1],
                channels,
                count: n as u8,
                rx_errors: read_u32(tail),
                frames_received: read_u32(&tail[4..]),
            }))
        }
        _ => None,
    }
}

/// Name of the emulated Teensy's pty link inside a run directory: the plant's emulated board
/// creates it, coilbus opens it when its port is `auto`.
pub const EMULATED_PORT_LINK: &str = "teensy.pty";

#[cfg(test)]
mod tests {
    use super::*;

    fn sample_packets() -> Vec<Packet> {
        let values: Vec<i32> = (0..12).map(|i| (i - 6) * 1234).collect();
        let currents = CoilValues::new(&values).unwrap();
        vec![
            Packet {
                seq: 7,
                message: Message::SetCurrents {
                    frame_seq: 123_456_789,
                    flags: 0,
                    currents_ma: currents,
                },
            },
            Packet {
                seq: 8,
                message: Message::Ack {
                    acked_seq: 7,
                    status: AckStatus::Clamped as u8,
                },
            },
            Packet {
                seq: u32::MAX,
                message: Message::Telemetry {
                    applied_ma: CoilValues::new(&[7, -7, 1 << 30]).unwrap(),
                    watchdog_tripped: true,
                    rx_errors: 3,
                    frames_received: 99,
                },
            },
        ]
    }

    #[test]
    fn round_trip_each_message() {
        for packet in sample_packets() {
            let mut decoder = Decoder::new();
            assert_eq!(decoder.push(&encode(&packet)), vec![packet]);
            assert_eq!(decoder.counters.errors(), 0);
        }
    }

    #[test]
    fn byte_by_byte_stream_with_garbage_between() {
        let packets = sample_packets();
        let mut stream = vec![0x00, 0xA5, 0x13, 0xFF];
        for p in &packets {
            stream.extend_from_slice(&encode(p));
            stream.extend([0xA5, 0xA5, 0x01]);
        }
        let mut decoder = Decoder::new();
        let mut got = Vec::new();
        for b in stream {
            got.extend(decoder.push(&[b]));
        }
        assert_eq!(got, packets);
        assert!(decoder.counters.skipped_bytes > 0);
    }

    #[test]
    fn corrupted_frame_is_rejected_and_next_one_survives() {
        let packets = sample_packets();
        let mut bad = encode(&packets[0]).to_vec();
        bad[12] ^= 0x40;
        let mut stream = bad;
        stream.extend_from_slice(&encode(&packets[1]));
        let mut decoder = Decoder::new();
        assert_eq!(decoder.push(&stream), vec![packets[1].clone()]);
        assert_eq!(decoder.counters.crc_errors, 1);
    }

    #[test]
    fn truncated_frame_waits_then_completes() {
        let bytes = encode(&sample_packets()[0]);
        let mut decoder = Decoder::new();
        assert!(decoder.push(&bytes[..11]).is_empty());
        assert_eq!(decoder.push(&bytes[11..]).len(), 1);
    }

    /// A frame with a correct CRC around arbitrary header fields and payload.
    fn raw_frame(version: u8, kind: u8, payload: &[u8]) -> Vec<u8> {
        let mut frame = vec![0xA5, 0x5A, version, kind];
        frame.extend((payload.len() as u16).to_le_bytes());
        frame.extend(1u32.to_le_bytes());
        frame.extend(payload);
        let crc = CRC16.checksum(&frame[2..]);
        frame.extend(crc.to_le_bytes());
        frame
    }

    #[test]
    fn oversize_length_and_wrong_payload_size_are_counted() {
        let frame = vec![0xA5, 0x5A, PROTOCOL_VERSION, 0x01, 0xFF, 0xFF, 0, 0, 0, 0];
        let mut decoder = Decoder::new();
        assert!(decoder.push(&frame).is_empty());
        assert_eq!(decoder.counters.bad_length, 1);

        // A valid CRC around a payload of the wrong size for its kind.
        assert!(decoder
            .push(&raw_frame(PROTOCOL_VERSION, 0x02, &[9, 9, 9]))
            .is_empty());
        assert_eq!(decoder.counters.bad_payload, 1);
    }

    #[test]
    fn coil_count_must_match_the_block_and_stay_within_max() {
        let mut decoder = Decoder::new();
        // Says 3 coils, carries 2.
        let mut short = vec![0u8; 8];
        short.extend([0, 3]);
        short.extend([0u8; 8]);
        assert!(decoder
            .push(&raw_frame(PROTOCOL_VERSION, 0x01, &short))
            .is_empty());
        // Says 17 coils (above MAX_COILS) and carries them: still refused.
        let mut over = vec![0u8; 8];
        over.extend([0, (MAX_COILS + 1) as u8]);
        over.extend(vec![0u8; 4 * (MAX_COILS + 1)]);
        let frame = raw_frame(PROTOCOL_VERSION, 0x01, &over);
        assert!(decoder.push(&frame).is_empty());
        assert_eq!(
            decoder.counters.bad_payload + decoder.counters.bad_length,
            2
        );
        // Any count up to MAX_COILS round-trips, including none.
        for n in [0usize, 1, 8, 12, MAX_COILS] {
            let values: Vec<i32> = (0..n as i32).map(|i| i * 1000 - 3).collect();
            let packet = Packet {
                seq: n as u32,
                message: Message::SetCurrents {
                    frame_seq: 1,
                    flags: 0,
                    currents_ma: CoilValues::new(&values).unwrap(),
                },
            };
            assert_eq!(decoder.push(&encode(&packet)), vec![packet]);
        }
        assert!(CoilValues::new(&[0; MAX_COILS + 1]).is_none());
    }

    #[test]
    fn the_documented_example_frame_is_what_encode_writes() {
        let mut currents = [0i32; 12];
        currents[0] = 1000;
        let bytes = encode(&Packet {
            seq: 1,
            message: Message::SetCurrents {
                frame_seq: 5,
                flags: 0,
                currents_ma: CoilValues::new(&currents).unwrap(),
            },
        });
        // PROTOCOL.md, "Example".
        let head = [
            0xA5, 0x5A, 0x02, 0x01, 0x3A, 0x00, 0x01, 0x00, 0x00, 0x00, 0x05, 0, 0, 0, 0, 0, 0, 0,
            0x00, 0x0C, 0xE8, 0x03, 0x00, 0x00,
        ];
        assert_eq!(&bytes[..head.len()], &head);
        assert_eq!(bytes.len(), HEADER_LEN + 58 + CRC_LEN);
        assert!(bytes[head.len()..bytes.len() - 2].iter().all(|b| *b == 0));
    }

    #[test]
    fn a_frame_of_another_protocol_version_is_dropped_and_counted() {
        let good = encode(&sample_packets()[1]).to_vec();
        let mut old = good.clone();
        old[2] = 1;
        let crc = CRC16.checksum(&old[2..old.len() - 2]);
        let n = old.len();
        old[n - 2..].copy_from_slice(&crc.to_le_bytes());
        let mut stream = old;
        stream.extend(&good);
        let mut decoder = Decoder::new();
        assert_eq!(decoder.push(&stream), vec![sample_packets()[1].clone()]);
        assert_eq!(decoder.counters.bad_version, 1);
        assert!(decoder.counters.errors() >= 1);
        // Its CRC holds: a peer speaking version 1, named for the host's refusal.
        assert_eq!(decoder.foreign_version, Some(1));
    }

    #[test]
    fn a_false_sync_with_another_version_byte_names_no_version() {
        let good = encode(&sample_packets()[1]).to_vec();
        let mut stream = vec![
            SYNC[0], SYNC[1], 7, 1, 3, 0, 0, 0, 0, 0, 1, 2, 3, 0xFF, 0xFF,
        ];
        stream.extend(&good);
        let mut decoder = Decoder::new();
        assert_eq!(decoder.push(&stream), vec![sample_packets()[1].clone()]);
        assert_eq!(decoder.counters.bad_version, 1);
        assert_eq!(decoder.foreign_version, None);
    }

    #[test]
    fn garbage_never_grows_buffer_unbounded() {
        let mut decoder = Decoder::new();
        for i in 0..10_000u32 {
            decoder.push(&[(i % 251) as u8, 0xA5]);
        }
        assert!(decoder.buffer.len() <= 4 * MAX_FRAME);
    }

    #[test]
    fn amps_conversion_saturates_and_rejects_nan() {
        assert_eq!(amps_to_ma(1.2345), 1235);
        assert_eq!(amps_to_ma(f64::NAN), 0);
        assert_eq!(amps_to_ma(1e12), i32::MAX);
        assert_eq!(ma_to_amps(-2500), -2.5);
    }
}
