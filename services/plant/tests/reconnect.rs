//! coilbus's serial link survives the port vanishing and coming back at the same path (the
//! emulated Teensy's pty is dropped and a new one created, as when the board is re-plugged).

mod common;

use common::armed_link;
use std::time::{Duration, Instant};

use millinav_coilbus::link::SerialLink;
use millinav_coilbus::protocol::{amps_to_ma, CoilValues, Message};
use millinav_kit::runlog::{self, TeensyEventRow};
use millinav_plant::teensy::{EmulatedTeensy, LinkFault};

/// Channels of the emulated board in these tests.
const CHANNELS: usize = 12;

fn command(frame_seq: u64, amps: f64) -> Message {
    Message::SetCurrents {
        frame_seq,
        flags: 0,
        currents_ma: CoilValues::new(&[amps_to_ma(amps); CHANNELS]).unwrap(),
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
                assert_eq!(out.last_command_currents(), [amps; CHANNELS]);
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
        EmulatedTeensy::start(&link_path, &dir.join("events1.csv"), watchdog, CHANNELS).unwrap();
    let mut link = armed_link(&link_path, CHANNELS, 250);
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
        EmulatedTeensy::start(&link_path, &dir.join("events2.csv"), watchdog, CHANNELS).unwrap();
    assert!(deliver(&mut link, &second, 300, -2.0), "no reconnect");
    assert!(link.is_open());
    assert_eq!(link.reconnects, 1);
    drop(second);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Rows of the board's event log: (monotonic_ns, max |current| A, event).
fn board_events(path: &std::path::Path) -> Vec<(u64, f64, String)> {
    let rows: Vec<TeensyEventRow> = runlog::read_rows(path).unwrap();
    rows.into_iter()
        .map(|row| (row.monotonic_ns, row.max_abs_current_a, row.event))
        .collect()
}

#[test]
fn an_unplugged_board_holds_its_currents_until_its_watchdog_zeroes_them() {
    let dir = std::env::temp_dir().join(format!("millinav-unplug-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let link_path = dir.join("teensy.pty");
    let events_path = dir.join("events.csv");
    // Long enough that the checks below never race the watchdog on a loaded machine.
    let watchdog = Duration::from_secs(2);
    let board = EmulatedTeensy::start(&link_path, &events_path, watchdog, CHANNELS).unwrap();
    let mut link = armed_link(&link_path, CHANNELS, watchdog.as_millis() as u16);
    assert!(deliver(&mut link, &board, 1, 1.5), "no first command");
    board.inject(LinkFault::Unplug(Duration::from_secs(3)));
    let until = Instant::now() + Duration::from_secs(1);
    while link_path.exists() && Instant::now() < until {
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(!link_path.exists(), "the device node did not vanish");
    // Cable out, board powered: it still drives the last command...
    assert_eq!(board.outputs().currents(), [1.5; CHANNELS]);
    // ... until its watchdog zeroes it.
    let until = Instant::now() + Duration::from_secs(5);
    while board.outputs().currents() != [0.0; CHANNELS] && Instant::now() < until {
        std::thread::sleep(Duration::from_millis(10));
    }
    assert_eq!(board.outputs().currents(), [0.0; CHANNELS]);
    let events = board_events(&events_path);
    let last_frame = events
        .iter()
        .rfind(|e| e.2 == "command")
        .expect("the command is logged");
    let unplugged = events.iter().find(|e| e.2 == "unplugged").expect("unplug");
    let zeroed = events
        .iter()
        .find(|e| e.2 == "watchdog_zero" && e.0 > unplugged.0)
        .expect("the watchdog's zeroing is logged with its time");
    assert_eq!(unplugged.1, 1.5, "the unplug event shows the held current");
    assert!(
        zeroed.0 - last_frame.0 >= watchdog.as_nanos() as u64,
        "zeroed {} ms after the last frame, before the {watchdog:?} watchdog",
        (zeroed.0 - last_frame.0) as f64 * 1e-6
    );
    drop(board);
    let _ = std::fs::remove_dir_all(&dir);
}
