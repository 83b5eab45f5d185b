//! The Teensy serial protocol, spoken by coilbus and by the plant's emulated Teensy.
//!
//! Every frame on the wire:
//!
//! | bytes | field | notes |
//! |---|---|---|
//! | 2 | sync | `0xA5 0x5A` |
//! | 1 | kind | `MessageKind` |
//! | 2 | length | payload length, little endian, ≤ `MAX_PAYLOAD` |
//! | 4 | seq | sender's frame counter, little endian, wraps |
//! | length | payload | see `Message` |
//! | 2 | crc | CRC-16/CCITT-FALSE over kind, length, seq and payload, little endian |
//!
//! Payloads (all little endian):
//! - `SetCurrents` (0x01): frame_seq u64 (camera frame the command answers, `u64::MAX` for none),
//!   flags u8 (bit 0: safe-state zero), 12 x i32 coil currents in mA.
//! - `Ack` (0x02): acked seq u32, status u8 (`AckStatus`).
//! - `Telemetry` (0x03): 12 x i32 applied currents in mA, watchdog tripped u8, rx errors u32,
//!   frames received u32.
//!
//! The decoder resynchronises on the sync word after any corruption and counts what it dropped;
//! it never panics on arbitrary input. The full description (tables, CRC parameters, watchdog
//! semantics) is in `services/teensy_protocol/PROTOCOL.md`.

use crc::{Crc, CRC_16_IBM_3740};
/// Coils addressed by one frame; coilbus asserts at compile time that this equals
/// `shm_schemas::COIL_COUNT` (kept here so the crate needs nothing but `crc`).
pub const COIL_COUNT: usize = 12;

pub const SYNC: [u8; 2] = [0xA5, 0x5A];
pub const HEADER_LEN: usize = 2 + 1 + 2 + 4;
pub const CRC_LEN: usize = 2;
pub const MAX_PAYLOAD: usize = 64;
/// CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF), known in the crc crate as IBM-3740.
const CRC16: Crc<u16> = Crc::<u16>::new(&CRC_16_IBM_3740);

const SET_CURRENTS_LEN: usize = 8 + 1 + 4 * COIL_COUNT;
const ACK_LEN: usize = 4 + 1;
const TELEMETRY_LEN: usize = 4 * COIL_COUNT + 1 + 4 + 4;

/// Flag bit in `SetCurrents`: this is a safe-state zero, not a controller command.
pub const FLAG_SAFE_ZERO: u8 = 1;

#[repr(u8)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MessageKind {
    SetCurrents = 0x01,
    Ack = 0x02,
    Telemetry = 0x03,
}

impl MessageKind {
    fn from_u8(value: u8) -> Option<Self> {
        match value {
            0x01 => Some(Self::SetCurrents),
            0x02 => Some(Self::Ack),
            0x03 => Some(Self::Telemetry),
            _ => None,
        }
    }
}

#[repr(u8)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AckStatus {
    Applied = 0,
    /// The Teensy clamped at least one channel to its own hardware limit.
    Clamped = 1,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Message {
    SetCurrents {
        frame_seq: u64,
        flags: u8,
        currents_ma: [i32; COIL_COUNT],
    },
    Ack {
        acked_seq: u32,
        status: u8,
    },
    Telemetry {
        applied_ma: [i32; COIL_COUNT],
        watchdog_tripped: bool,
        rx_errors: u32,
        frames_received: u32,
    },
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
    (current_a * 1000.0)
        .round()
        .clamp(i32::MIN as f64, i32::MAX as f64) as i32
}

pub fn ma_to_amps(current_ma: i32) -> f64 {
    current_ma as f64 / 1000.0
}

/// Encodes one packet into a fresh buffer.
pub fn encode(packet: &Packet) -> Vec<u8> {
    let mut payload = Vec::with_capacity(MAX_PAYLOAD);
    let kind = match &packet.message {
        Message::SetCurrents {
            frame_seq,
            flags,
            currents_ma,
        } => {
            payload.extend_from_slice(&frame_seq.to_le_bytes());
            payload.push(*flags);
            for c in currents_ma {
                payload.extend_from_slice(&c.to_le_bytes());
            }
            MessageKind::SetCurrents
        }
        Message::Ack { acked_seq, status } => {
            payload.extend_from_slice(&acked_seq.to_le_bytes());
            payload.push(*status);
            MessageKind::Ack
        }
        Message::Telemetry {
            applied_ma,
            watchdog_tripped,
            rx_errors,
            frames_received,
        } => {
            for c in applied_ma {
                payload.extend_from_slice(&c.to_le_bytes());
            }
            payload.push(u8::from(*watchdog_tripped));
            payload.extend_from_slice(&rx_errors.to_le_bytes());
            payload.extend_from_slice(&frames_received.to_le_bytes());
            MessageKind::Telemetry
        }
    };
    let mut out = Vec::with_capacity(HEADER_LEN + payload.len() + CRC_LEN);
    out.extend_from_slice(&SYNC);
    out.push(kind as u8);
    out.extend_from_slice(&(payload.len() as u16).to_le_bytes());
    out.extend_from_slice(&packet.seq.to_le_bytes());
    out.extend_from_slice(&payload);
    let crc = CRC16.checksum(&out[2..]);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}

/// What the decoder threw away, for link health telemetry.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DecodeCounters {
    pub packets: u64,
    pub crc_errors: u64,
    pub bad_length: u64,
    pub unknown_kind: u64,
    pub bad_payload: u64,
    /// Bytes skipped while hunting for a sync word.
    pub skipped_bytes: u64,
}

impl DecodeCounters {
    pub fn errors(&self) -> u64 {
        self.crc_errors + self.bad_length + self.unknown_kind + self.bad_payload
    }
}

/// Streaming decoder: feed it whatever the port returned, take out whole packets.
#[derive(Debug, Default)]
pub struct Decoder {
    buffer: Vec<u8>,
    pub counters: DecodeCounters,
}

impl Decoder {
    pub fn new() -> Self {
        Self::default()
    }

    /// Appends bytes and returns every complete, valid packet now available.
    pub fn push(&mut self, bytes: &[u8]) -> Vec<Packet> {
        self.buffer.extend_from_slice(bytes);
        let mut packets = Vec::new();
        let mut start = 0usize;
        loop {
            // Hunt for the sync word.
            let Some(offset) = find_sync(&self.buffer[start..]) else {
                // Keep a trailing 0xA5: it may be the first half of a sync word.
                let keep_from = if self.buffer.len() > start && self.buffer.last() == Some(&SYNC[0])
                {
                    self.buffer.len() - 1
                } else {
                    self.buffer.len()
                };
                self.counters.skipped_bytes += (keep_from - start) as u64;
                start = keep_from;
                break;
            };
            self.counters.skipped_bytes += offset as u64;
            start += offset;
            let available = &self.buffer[start..];
            if available.len() < HEADER_LEN {
                break;
            }
            let length = u16::from_le_bytes([available[3], available[4]]) as usize;
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
            let seq = u32::from_le_bytes([frame[5], frame[6], frame[7], frame[8]]);
            let payload = &frame[HEADER_LEN..HEADER_LEN + length];
            match MessageKind::from_u8(frame[2]) {
                None => self.counters.unknown_kind += 1,
                Some(kind) => match parse_payload(kind, payload) {
                    Some(message) => {
                        self.counters.packets += 1;
                        packets.push(Packet { seq, message });
                    }
                    None => self.counters.bad_payload += 1,
                },
            }
            start += total;
        }
        self.buffer.drain(..start);
        // A peer that sends only garbage must not grow the buffer without bound.
        if self.buffer.len() > 4 * (HEADER_LEN + MAX_PAYLOAD + CRC_LEN) {
            self.counters.skipped_bytes += self.buffer.len() as u64;
            self.buffer.clear();
        }
        packets
    }
}

/// Feeds `data` to a fresh decoder in chunks whose sizes come from the data itself, then checks
/// the decoder's invariants: every returned packet re-encodes to a frame present in the input,
/// the packet counter matches, and the internal buffer stays bounded. Used by the cargo-fuzz
/// target (`fuzz/fuzz_targets/decoder.rs`) and by the property tests; panics on a violation.
pub fn check_decoder_invariants(data: &[u8]) {
    let mut decoder = Decoder::new();
    let mut packets = Vec::new();
    let mut rest = data;
    let mut chunk = 1usize;
    while !rest.is_empty() {
        let n = chunk.min(rest.len());
        packets.extend(decoder.push(&rest[..n]));
        assert!(
            decoder.buffer.len() <= HEADER_LEN + MAX_PAYLOAD + CRC_LEN,
            "decoder buffer grew to {}",
            decoder.buffer.len()
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

fn find_sync(bytes: &[u8]) -> Option<usize> {
    bytes.windows(2).position(|w| w == SYNC)
}

fn read_i32s(bytes: &[u8]) -> [i32; COIL_COUNT] {
    let mut out = [0i32; COIL_COUNT];
    for (value, chunk) in out.iter_mut().zip(bytes.chunks_exact(4)) {
        *value = i32::from_le_bytes([chunk[0], chunk[1], chunk[2], chunk[3]]);
    }
    out
}

fn read_u32(bytes: &[u8]) -> u32 {
    u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]])
}

fn parse_payload(kind: MessageKind, payload: &[u8]) -> Option<Message> {
    match kind {
        MessageKind::SetCurrents if payload.len() == SET_CURRENTS_LEN => {
            let mut seq_bytes = [0u8; 8];
            seq_bytes.copy_from_slice(&payload[..8]);
            Some(Message::SetCurrents {
                frame_seq: u64::from_le_bytes(seq_bytes),
                flags: payload[8],
                currents_ma: read_i32s(&payload[9..]),
            })
        }
        MessageKind::Ack if payload.len() == ACK_LEN => Some(Message::Ack {
            acked_seq: read_u32(payload),
            status: payload[4],
        }),
        MessageKind::Telemetry if payload.len() == TELEMETRY_LEN => {
            let n = 4 * COIL_COUNT;
            Some(Message::Telemetry {
                applied_ma: read_i32s(&payload[..n]),
                watchdog_tripped: payload[n] != 0,
                rx_errors: read_u32(&payload[n + 1..]),
                frames_received: read_u32(&payload[n + 5..]),
            })
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
        let mut currents = [0i32; COIL_COUNT];
        for (i, c) in currents.iter_mut().enumerate() {
            *c = (i as i32 - 6) * 1234;
        }
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
                    applied_ma: currents,
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
            stream.extend(encode(p));
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
        let mut bad = encode(&packets[0]);
        bad[12] ^= 0x40;
        let mut stream = bad;
        stream.extend(encode(&packets[1]));
        let mut decoder = Decoder::new();
        assert_eq!(decoder.push(&stream), vec![packets[1].clone()]);
        assert_eq!(decoder.counters.crc_errors, 1);
    }

    #[test]
    fn truncated_frame_waits_then_completes() {
        let bytes = encode(&sample_packets()[0]);
        let mut decoder = Decoder::new();
        assert!(decoder.push(&bytes[..10]).is_empty());
        assert_eq!(decoder.push(&bytes[10..]).len(), 1);
    }

    #[test]
    fn oversize_length_and_wrong_payload_size_are_counted() {
        let mut frame = vec![0xA5, 0x5A, 0x01, 0xFF, 0xFF, 0, 0, 0, 0];
        let mut decoder = Decoder::new();
        assert!(decoder.push(&frame).is_empty());
        assert_eq!(decoder.counters.bad_length, 1);

        // A valid CRC around a payload of the wrong size for its kind.
        frame = vec![0xA5, 0x5A, 0x02, 3, 0, 1, 0, 0, 0, 9, 9, 9];
        let crc = CRC16.checksum(&frame[2..]);
        frame.extend(crc.to_le_bytes());
        assert!(decoder.push(&frame).is_empty());
        assert_eq!(decoder.counters.bad_payload, 1);
    }

    #[test]
    fn garbage_never_grows_buffer_unbounded() {
        let mut decoder = Decoder::new();
        for i in 0..10_000u32 {
            decoder.push(&[(i % 251) as u8, 0xA5]);
        }
        assert!(decoder.buffer.len() <= 4 * (HEADER_LEN + MAX_PAYLOAD + CRC_LEN));
    }

    #[test]
    fn amps_conversion_saturates_and_rejects_nan() {
        assert_eq!(amps_to_ma(1.2345), 1235);
        assert_eq!(amps_to_ma(f64::NAN), 0);
        assert_eq!(amps_to_ma(1e12), i32::MAX);
        assert_eq!(ma_to_amps(-2500), -2.5);
    }
}
