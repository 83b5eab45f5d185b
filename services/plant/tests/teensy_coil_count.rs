//! The emulated Teensy checks the coil count a `SetCurrents` frame carries against its own
//! channels: a frame for another count is refused with `Ack` status `RejectedCoilCount`,
//! logged and counted, and drives nothing (outputs unchanged, the watchdog is not fed).

mod common;

use common::armed_link;
use std::time::{Duration, Instant};

use millinav_coilbus::link::SerialLink;
use millinav_coilbus::protocol::{amps_to_ma, AckStatus, CoilValues, Message, MAX_COILS};
use millinav_plant::teensy::EmulatedTeensy;

const BOARD_CHANNELS: usize = 12;

fn set_currents(frame_seq: u64, amps: f64, coils: usize) -> Message {
    Message::SetCurrents {
        frame_seq,
        flags: 0,
        currents_ma: CoilValues::new(&vec![amps_to_ma(amps); coils]).unwrap(),
    }
}

/// Sends `message` until the board acknowledges it (the pty may need a moment to open);
/// returns the ack status.
fn send_until_acked(link: &mut SerialLink, message: &Message) -> Option<u8> {
    let deadline = Instant::now() + Duration::from_secs(5);
    while Instant::now() < deadline {
        link.ensure_open(Instant::now());
        link.poll();
        if link.send(message) {
            let answer_by = Instant::now() + Duration::from_millis(200);
            while Instant::now() < answer_by {
                for packet in link.poll() {
                    if let Message::Ack { status, .. } = packet.message {
                        return Some(status);
                    }
                }
                std::thread::sleep(Duration::from_millis(2));
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    None
}

#[test]
fn a_frame_for_another_coil_count_is_rejected_and_drives_nothing() {
    let dir = std::env::temp_dir().join(format!("millinav-coilcount-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let link_path = dir.join("teensy.pty");
    let events = dir.join("events.csv");
    let board = EmulatedTeensy::start(
        &link_path,
        &events,
        Duration::from_millis(250),
        BOARD_CHANNELS,
    )
    .unwrap();
    let mut link = armed_link(&link_path, BOARD_CHANNELS, 250);

    let status = send_until_acked(&mut link, &set_currents(1, 1.5, BOARD_CHANNELS));
    assert_eq!(status, Some(AckStatus::Applied as u8));
    let before = board.outputs();
    assert_eq!(before.currents(), [1.5; BOARD_CHANNELS]);

    for (seq, coils) in [(2, 8), (3, 13), (4, MAX_COILS), (5, 0)] {
        let status = send_until_acked(&mut link, &set_currents(seq, -3.0, coils));
        assert_eq!(
            status,
            Some(AckStatus::RejectedCoilCount as u8),
            "a frame for {coils} coils was not rejected"
        );
    }
    let after = board.outputs();
    assert_eq!(after.rejected_frames, 4);
    assert_eq!(
        after.currents(),
        before.currents(),
        "a rejected frame drove the coils"
    );
    assert_eq!(after.last_command_frame, 1);
    assert_eq!(after.frames_received, before.frames_received);
    let log = std::fs::read_to_string(&events).unwrap();
    assert_eq!(log.matches("rejected_coil_count").count(), 4);

    // Rejected frames do not feed the watchdog: with only those arriving the board zeroes.
    let trip_by = Instant::now() + Duration::from_secs(2);
    while Instant::now() < trip_by && !board.outputs().watchdog_tripped {
        let _ = link.send(&set_currents(9, 2.0, 8));
        std::thread::sleep(Duration::from_millis(20));
    }
    let tripped = board.outputs();
    assert!(
        tripped.watchdog_tripped,
        "wrong-count frames kept the watchdog fed"
    );
    assert_eq!(tripped.currents(), [0.0; BOARD_CHANNELS]);
    drop(board);
    let _ = std::fs::remove_dir_all(&dir);
}
