//! Protocol version negotiation: a board that answers with well-formed frames of another
//! protocol version is recognised by its version byte, never configured or armed, and coilbus
//! latches the refusal (coils held at zero, the reason names both versions).

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use crc::{Crc, CRC_16_IBM_3740};
use millinav_coilbus::link::SerialLink;
use millinav_coilbus::protocol::{
    encode, BoardState, BoardStatus, ChannelStatus, Decoder, Message, Packet, PROTOCOL_VERSION,
};
use millinav_coilbus::safety::CurrentLimits;
use millinav_coilbus::CoilBus;
use serialport::{SerialPort, TTYPort};
use shm_schemas::BoardFault;

/// The wire's CRC (CRC-16/CCITT-FALSE, as PROTOCOL.md specifies).
const CRC16: Crc<u16> = Crc::<u16>::new(&CRC_16_IBM_3740);

/// A `Status` frame as a board speaking `version` would send it: this layout, another version
/// byte, a valid CRC.
fn status_frame_of_version(version: u8) -> Vec<u8> {
    let status = BoardStatus::new(
        BoardState::Disarmed as u8,
        0,
        &[ChannelStatus::default(); 3],
        0,
        0,
    )
    .unwrap();
    let mut frame = encode(&Packet {
        seq: 1,
        message: Message::Status(status),
    })
    .to_vec();
    frame[2] = version;
    let n = frame.len();
    let crc = CRC16.checksum(&frame[2..n - 2]);
    frame[n - 2..].copy_from_slice(&crc.to_le_bytes());
    frame
}

#[test]
fn a_board_of_another_protocol_version_is_refused_by_name() {
    let (mut board_side, host_side) = TTYPort::pair().expect("a pty pair");
    let path = host_side.name().expect("the pty has a name");
    let foreign = PROTOCOL_VERSION + 1;
    let limits = CurrentLimits::uniform(6.0, 10.0, 2160.0);

    let mut link = SerialLink::new(path.into(), 115_200);
    link.set_board_config(millinav_coilbus::board_config(&limits, 3, 250));
    link.set_arm_wanted(true);
    let deadline = Instant::now() + Duration::from_secs(5);
    let mut seen = None;
    while Instant::now() < deadline && seen.is_none() {
        board_side
            .write_all(&status_frame_of_version(foreign))
            .unwrap();
        link.ensure_open(Instant::now());
        link.poll();
        seen = link.foreign_version();
        std::thread::sleep(Duration::from_millis(20));
    }
    assert_eq!(
        seen,
        Some(foreign),
        "the host did not recognise the version"
    );

    // Nothing the host wrote configures or arms the board.
    board_side.set_timeout(Duration::from_millis(50)).unwrap();
    let mut written = Vec::new();
    let mut buf = [0u8; 4096];
    while let Ok(n) = board_side.read(&mut buf) {
        if n == 0 {
            break;
        }
        written.extend_from_slice(&buf[..n]);
    }
    let sent = Decoder::new().push(&written);
    assert!(
        !sent
            .iter()
            .any(|p| matches!(p.message, Message::Config(_) | Message::Arm)),
        "the host configured or armed a board of another version: {sent:?}"
    );

    // coilbus latches the refusal: zeros only, never armed.
    let mut bus = CoilBus::new(limits, Duration::from_millis(100), 3);
    let fault = bus.on_foreign_version(foreign).expect("a fault latched");
    assert_eq!(fault.kind, BoardFault::ProtocolVersion);
    assert!(
        fault.detail.contains(&format!("version {foreign}"))
            && fault.detail.contains(&format!("speaks {PROTOCOL_VERSION}")),
        "{}",
        fault.detail
    );
    assert_eq!(bus.status.board_fault, BoardFault::ProtocolVersion as u8);
    bus.start_zero_sent();
    assert!(!bus.may_arm());
    let out = bus.on_tick(Instant::now()).expect("a safe zero");
    assert!(out.currents().iter().all(|&a| a == 0.0));
}
