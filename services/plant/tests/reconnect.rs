//! coilbus's serial link survives the port vanishing and coming back at the same path (the
//! emulated Teensy's pty is dropped and a new one created, as when the board is re-plugged).

use std::time::{Duration, Instant};

use fieldmaps::coils::COIL_COUNT;
use millinav_coilbus::link::SerialLink;
use millinav_coilbus::protocol::{amps_to_ma, CoilValues, Message};
use millinav_plant::teensy::EmulatedTeensy;

fn command(frame_seq: u64, amps: f64) -> Message {
    Message::SetCurrents {
        frame_seq,
        flags: 0,
        currents_ma: CoilValues::new(&[amps_to_ma(amps); COIL_COUNT]).unwrap(),
    }
}

/// Keeps (re)opening and sending `frame_seq` until the Teensy applied it.
fn deliver(link: &mut SerialLink, teensy: &EmulatedTeensy, frame_seq: u64, amps: f64) -> bool {
    let deadline = Instant::now() + Duration::from_secs(5);
    while Instant::now() < deadline {
        link.ensure_open(Instant::now());
        link.poll();
        if link.send(&command(frame_seq, amps)) {
            let (out, in_time) = teensy.wait_for_frame(frame_seq, Duration::from_millis(50));
            if in_time {
                assert_eq!(out.last_command_currents(), [amps; COIL_COUNT]);
                return true;
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    false
}

#[test]
fn serial_link_reconnects_when_the_port_comes_back() {
    let dir = std::env::temp_dir().join(format!("millinav-reconnect-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let link_path = dir.join("teensy.pty");
    let watchdog = Duration::from_millis(250);

    let first =
        EmulatedTeensy::start(&link_path, &dir.join("events1.csv"), watchdog, COIL_COUNT).unwrap();
    let mut link = SerialLink::new(link_path.clone(), 115_200);
    assert!(
        deliver(&mut link, &first, 1, 1.5),
        "first port never answered"
    );
    assert!(link.is_open());
    assert_eq!(link.reconnects, 0);

    // The port vanishes: writes fail and the link closes; nothing panics.
    drop(first);
    assert!(!link_path.exists());
    let mut noticed = false;
    for seq in 2..200 {
        link.poll();
        if !link.send(&command(seq, 0.5)) {
            noticed = true;
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(noticed, "the link never noticed the port was gone");
    assert!(!link.is_open());
    link.ensure_open(Instant::now());
    assert!(!link.is_open(), "opened a port that does not exist");

    // A new board at the same path: the link reopens on its own and commands flow again.
    let second =
        EmulatedTeensy::start(&link_path, &dir.join("events2.csv"), watchdog, COIL_COUNT).unwrap();
    assert!(deliver(&mut link, &second, 300, -2.0), "no reconnect");
    assert!(link.is_open());
    assert_eq!(link.reconnects, 1);
    drop(second);
    let _ = std::fs::remove_dir_all(&dir);
}
