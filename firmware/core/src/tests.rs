use millinav_teensy_protocol::{
    decode_one, encode, BoardConfig, BoardState, CoilRating, CoilValues, Message, Packet,
    STATUS_CLAMPED, STATUS_WATCHDOG,
};

use super::*;

const CHANNELS: usize = 4;

fn rating() -> CoilRating {
    // 10 Ω, 6 A limit, 3 A continuous, 27 A²·s above it (6 A for 1 s).
    CoilRating {
        resistance_mohm: 10_000,
        max_ma: 6_000,
        continuous_ma: 3_000,
        i2t_budget: 27_000,
    }
}

fn config() -> Packet {
    Packet {
        seq: 1,
        message: Message::Config(BoardConfig::new(60_000, 250, &[rating(); CHANNELS]).unwrap()),
    }
}

fn frame(message: Message) -> Packet {
    Packet { seq: 9, message }
}

fn set(ma: [i32; CHANNELS]) -> Packet {
    frame(Message::SetCurrents {
        frame_seq: 0,
        flags: 0,
        currents_ma: CoilValues::new(&ma).unwrap(),
    })
}

fn ack_status(reply: Option<Packet>) -> u8 {
    match reply.map(|p| p.message) {
        Some(Message::Ack { status, .. }) => status,
        other => panic!("no ack: {other:?}"),
    }
}

/// A configured, armed board at t = 0.
fn armed() -> Board {
    let mut b = Board::new(HardwareLimits::standard(CHANNELS));
    b.handle(&config(), 0);
    b.handle(&frame(Message::Arm), 0);
    assert_eq!(b.state(), BoardState::Armed);
    b
}

#[test]
fn starts_unconfigured_then_disarmed_and_drives_nothing_until_armed() {
    let mut b = Board::new(HardwareLimits::standard(CHANNELS));
    assert_eq!(b.state(), BoardState::Unconfigured);
    assert_eq!(
        ack_status(b.handle(&set([1000; CHANNELS]), 0)),
        AckStatus::NotArmed as u8
    );
    b.handle(&frame(Message::Arm), 0);
    assert_eq!(
        b.state(),
        BoardState::Unconfigured,
        "arming without a config"
    );
    b.handle(&config(), 0);
    assert_eq!(b.state(), BoardState::Disarmed);
    assert_eq!(
        ack_status(b.handle(&set([1000; CHANNELS]), 1)),
        AckStatus::NotArmed as u8
    );
    assert!(b.outputs().iter().all(|o| o.duty == 0));
    b.handle(&frame(Message::Arm), 2);
    assert_eq!(
        ack_status(b.handle(&set([1000, -2000, 0, 6000]), 3)),
        AckStatus::Applied as u8
    );
    let out = b.outputs();
    // 1 A × 10 Ω of 60 V = 1/6 duty.
    assert!((f64::from(out[0].duty) / f64::from(PWM_MAX) - 1.0 / 6.0).abs() < 1e-3);
    assert!(out[0].forward && !out[1].forward);
    assert_eq!(out[3].duty, PWM_MAX);
    b.handle(&frame(Message::Disarm), 4);
    assert_eq!(b.state(), BoardState::Disarmed);
    assert!(b.outputs().iter().all(|o| o.duty == 0));
}

#[test]
fn bad_configs_are_refused_and_flagged() {
    let mut b = Board::new(HardwareLimits::standard(CHANNELS));
    let mut bad = [rating(); CHANNELS];
    bad[2].max_ma = 40_000; // above the 30 A drivers
    let cfg = BoardConfig::new(60_000, 250, &bad).unwrap();
    assert_eq!(b.check_config(&cfg), Err(ConfigRefusal::Coil(2)));
    b.handle(&frame(Message::Config(cfg)), 0);
    assert_eq!(b.state(), BoardState::Unconfigured);
    let Message::Status(st) = b.status().message else {
        panic!()
    };
    assert_ne!(st.flags & STATUS_CONFIG_REFUSED, 0);
    let few = BoardConfig::new(60_000, 250, &[rating(); 3]).unwrap();
    assert_eq!(b.check_config(&few), Err(ConfigRefusal::ChannelCount));
    let low = BoardConfig::new(5_000, 250, &[rating(); CHANNELS]).unwrap();
    assert_eq!(b.check_config(&low), Err(ConfigRefusal::Supply));
    // No reconfiguration while armed.
    let mut a = armed();
    a.handle(&config(), 1);
    let Message::Status(st) = a.status().message else {
        panic!()
    };
    assert_ne!(st.flags & STATUS_CONFIG_REFUSED, 0);
}

#[test]
fn clamps_to_each_coils_limit_and_rejects_other_counts() {
    let mut b = armed();
    assert_eq!(
        ack_status(b.handle(&set([9000, -9000, 100, 0]), 1)),
        AckStatus::Clamped as u8
    );
    let Message::Status(st) = b.status().message else {
        panic!()
    };
    assert_eq!(st.channels()[0].commanded_ma, 9000);
    assert_eq!(st.channels()[0].applied_ma, 6000);
    assert_eq!(st.channels()[1].applied_ma, -6000);
    let three = frame(Message::SetCurrents {
        frame_seq: 0,
        flags: 0,
        currents_ma: CoilValues::new(&[1, 2, 3]).unwrap(),
    });
    assert_eq!(
        ack_status(b.handle(&three, 2)),
        AckStatus::RejectedCoilCount as u8
    );
}

#[test]
fn estop_latches_until_a_deliberate_rearm_with_the_input_released() {
    let mut b = armed();
    b.handle(&set([2000; CHANNELS]), 1);
    b.tick(2, true, None);
    assert_eq!(b.state(), BoardState::EStop);
    assert!(b.outputs().iter().all(|o| o.duty == 0));
    // Commands, a released pin, a disarm: still latched.
    assert_eq!(
        ack_status(b.handle(&set([2000; CHANNELS]), 3)),
        AckStatus::NotArmed as u8
    );
    b.tick(4, false, None);
    b.handle(&frame(Message::Disarm), 5);
    assert_eq!(b.state(), BoardState::EStop);
    // Re-arm while the pin is held: refused; released: armed, from zero current.
    b.tick(6, true, None);
    b.handle(&frame(Message::Arm), 6);
    assert_eq!(b.state(), BoardState::EStop);
    b.tick(7, false, None);
    b.handle(&frame(Message::Arm), 7);
    assert_eq!(b.state(), BoardState::Armed);
    assert!(b.outputs().iter().all(|o| o.duty == 0));
    // The host's EStop frame latches too.
    b.handle(&frame(Message::EStop), 8);
    assert_eq!(b.state(), BoardState::EStop);
}

#[test]
fn watchdog_zeroes_the_outputs_until_the_next_command() {
    let mut b = armed();
    b.handle(&set([2000; CHANNELS]), 0);
    b.tick(200, false, None);
    assert!(b.outputs()[0].duty > 0);
    b.tick(300, false, None);
    assert!(b.outputs().iter().all(|o| o.duty == 0));
    let Message::Status(st) = b.status().message else {
        panic!()
    };
    assert_ne!(st.flags & STATUS_WATCHDOG, 0);
    assert_eq!(st.channels()[0].applied_ma, 0);
    b.handle(&set([2000; CHANNELS]), 310);
    assert!(b.outputs()[0].duty > 0);
}

#[test]
fn heat_derates_a_sustained_overload_towards_the_continuous_rating() {
    let mut b = armed();
    // 6 A on a 3 A-continuous coil: 27 A²/s of heat, the 27 A²·s budget in 1 s, but from 80 %
    // of it the allowed current falls towards 3 A, where the heat stops growing.
    let mut t = 0;
    let mut applied = 6000;
    while t < 5000 {
        b.handle(&set([6000, 0, 0, 0]), t);
        t += 10;
        b.tick(t, false, None);
        let Message::Status(st) = b.status().message else {
            panic!()
        };
        applied = st.channels()[0].applied_ma;
        if t > 1000 {
            assert_ne!(st.flags & STATUS_DERATING, 0);
        }
    }
    assert_eq!(
        b.state(),
        BoardState::Armed,
        "derating should have prevented the trip"
    );
    assert!((3000..3600).contains(&applied), "{applied} mA after 5 s");
}

#[test]
fn current_the_board_did_not_ask_for_trips_it_and_rearm_waits_for_cooling() {
    let mut b = armed();
    // The host asks nothing but the sense input reads 6 A (a stuck driver): the heat counts
    // what flows, and the full budget trips the board.
    let mut t = 0;
    while t < 3000 && b.state() == BoardState::Armed {
        b.handle(&set([0; CHANNELS]), t);
        t += 10;
        b.tick(t, false, Some(&[6000, 0, 0, 0]));
    }
    assert_eq!(b.state(), BoardState::ThermalTrip);
    assert!(
        (900..=1100).contains(&t),
        "tripped after {t} ms, expected about 1 s"
    );
    assert!(b.outputs().iter().all(|o| o.duty == 0));
    let Message::Status(st) = b.status().message else {
        panic!()
    };
    assert_eq!(st.channels()[0].measured_ma, 6000);
    assert_eq!(st.channels()[0].thermal_permille, 1000);
    b.handle(&frame(Message::Arm), t);
    assert_eq!(b.state(), BoardState::ThermalTrip, "re-armed while hot");
    // Idle (the sense reads 0 now), the heat falls at I_c² = 9 A²/s: below half the budget
    // after about 1.5 s.
    for _ in 0..200 {
        t += 10;
        b.tick(t, false, Some(&[0; CHANNELS]));
    }
    b.handle(&frame(Message::Arm), t);
    assert_eq!(b.state(), BoardState::Armed);
}

#[test]
fn status_frames_round_trip_through_the_wire() {
    let mut b = armed();
    b.handle(&set([1500, -200, 0, 6000]), 1);
    let status = b.status();
    let bytes = encode(&status);
    assert_eq!(decode_one(&bytes), Some(status));
    let cfg = config();
    assert_eq!(decode_one(&encode(&cfg)), Some(cfg));
}

#[test]
fn bad_frames_are_dropped_counted_and_reported() {
    let mut b = armed();
    let mut decoder = millinav_teensy_protocol::Decoder::new();
    let good = encode(&set([1000; CHANNELS])).to_vec();
    let mut bad_crc = good.clone();
    let last = bad_crc.len() - 1;
    bad_crc[last] ^= 0xFF;
    let mut bad_version = good.clone();
    bad_version[2] = 9;
    let mut bad_length = good.clone();
    bad_length[4] = 0xFF;
    bad_length[5] = 0xFF;
    let wrong_count = encode(&frame(Message::SetCurrents {
        frame_seq: 1,
        flags: 0,
        currents_ma: CoilValues::new(&[1000; CHANNELS + 1]).unwrap(),
    }))
    .to_vec();
    let out_of_range = encode(&set([i32::MAX, i32::MIN, 0, 0])).to_vec();
    let mut acks = Vec::new();
    for bytes in [&bad_crc, &bad_version, &bad_length] {
        b.receive(&mut decoder, bytes, 1, |p| acks.push(p));
    }
    assert!(acks.is_empty(), "a damaged frame was handled: {acks:?}");
    assert!(b.rx_errors >= 3, "rx_errors {}", b.rx_errors);
    // A frame for another coil count is refused and drives nothing.
    b.receive(&mut decoder, &wrong_count, 2, |p| acks.push(p));
    assert_eq!(ack_status(acks.pop()), AckStatus::RejectedCoilCount as u8);
    assert!(b.outputs().iter().all(|o| o.duty == 0));
    // Out-of-range currents are clamped to the coil's limit.
    b.receive(&mut decoder, &out_of_range, 3, |p| acks.push(p));
    assert_eq!(ack_status(acks.pop()), AckStatus::Clamped as u8);
    assert_eq!(&b.driven_ma()[..2], &[6_000, -6_000]);
    // The counts travel in Status.
    let status = match b.status().message {
        Message::Status(st) => st,
        other => panic!("{other:?}"),
    };
    assert!(status.rx_errors >= 3);
    assert_eq!(status.flags & STATUS_CLAMPED, STATUS_CLAMPED);
    // Arm while e-stopped (pin held): refused, still latched.
    b.tick(4, true, None);
    b.receive(&mut decoder, &encode(&frame(Message::Arm)), 5, |p| {
        acks.push(p)
    });
    assert_eq!(b.state(), BoardState::EStop);
}
