//! Ports and the service loop over real iceoryx2 shared memory: delivery, ordering, overflow,
//! frames, deadlines, heartbeats, and that a loop sleeps between wakes.

mod common;

use std::time::{Duration, Instant};

use common::Isolated;
use millinav_kit::ports::{
    FrameInbox, FrameOutbox, HeartbeatSender, Inbox, Outbox, FRAME_SUBSCRIBER_BUFFER,
    SUBSCRIBER_BUFFER,
};
use millinav_kit::service_loop::{LoopEnd, ServiceLoop};
use millinav_kit::KitError;
use shm_schemas::{
    deadlines, services, FrameHeader, FrameStamp, Heartbeat, PixelFormat, ServiceId,
};

const TOPIC: &str = "kit_test/values";

/// Runs a loop on `inbox` (with `deadline`) for `length` of wall time; returns the wall time
/// after the start of each wake that reported a missed deadline, and how many wakes saw a
/// sample announced.
fn watch(
    inbox: &Inbox<u64>,
    heartbeat: &mut HeartbeatSender,
    deadline: Duration,
    length: Duration,
) -> (Vec<Duration>, usize) {
    let mut service_loop = ServiceLoop::new();
    let input = service_loop.input_with_deadline(inbox, deadline);
    let start = Instant::now();
    let (mut misses, mut fired) = (Vec::new(), 0);
    let end = service_loop
        .run(heartbeat, |wake| {
            if wake.missed_deadline(input) {
                misses.push(start.elapsed());
            }
            if wake.fired(input) {
                fired += 1;
            }
            inbox.receive_all()?;
            if start.elapsed() >= length {
                wake.stop();
            }
            Ok::<(), KitError>(())
        })
        .expect("loop");
    assert_eq!(end, LoopEnd::Stopped);
    (misses, fired)
}

#[test]
fn outbox_delivers_every_message_in_order() {
    let world = Isolated::new();
    let node = world.node();
    let inbox = Inbox::<u64>::new(&node, TOPIC).unwrap();
    let outbox = Outbox::<u64>::new(&node, TOPIC).unwrap();
    for value in [3, 1, 4] {
        outbox.send(value).unwrap();
    }
    assert_eq!(inbox.receive_all().unwrap(), vec![3, 1, 4]);
    assert!(inbox.receive_all().unwrap().is_empty(), "delivered twice");
}

#[test]
fn a_slow_reader_keeps_the_newest_messages() {
    let world = Isolated::new();
    let node = world.node();
    let inbox = Inbox::<u64>::new(&node, TOPIC).unwrap();
    let outbox = Outbox::<u64>::new(&node, TOPIC).unwrap();
    for value in 1..=10 {
        outbox.send(value).unwrap();
    }
    let newest: Vec<u64> = (10 - SUBSCRIBER_BUFFER as u64 + 1..=10).collect();
    assert_eq!(inbox.receive_all().unwrap(), newest);
}

#[test]
fn latest_returns_the_newest_and_drops_the_older() {
    let world = Isolated::new();
    let node = world.node();
    let inbox = Inbox::<u64>::new(&node, TOPIC).unwrap();
    let outbox = Outbox::<u64>::new(&node, TOPIC).unwrap();
    assert_eq!(inbox.latest().unwrap(), None);
    for value in [7, 8, 9] {
        outbox.send(value).unwrap();
    }
    assert_eq!(inbox.latest().unwrap(), Some(9));
    assert!(inbox.receive_all().unwrap().is_empty(), "older ones kept");
    outbox.send(10).unwrap();
    assert_eq!(inbox.latest().unwrap(), Some(10));
}

fn header(seq: u64) -> FrameHeader {
    FrameHeader {
        stamp: FrameStamp::new(seq, 0, 0),
        width: 4,
        height: 2,
        stride: 12,
        pixel_format: PixelFormat::Rgb8 as u32,
        ..Default::default()
    }
}

#[test]
fn frames_arrive_with_their_header_and_pixels() {
    let world = Isolated::new();
    let node = world.node();
    let inbox = FrameInbox::new(&node).unwrap();
    let outbox = FrameOutbox::new(&node, 1020 * 1020 * 3).unwrap();
    let pixels: Vec<u8> = (0..24).collect();
    outbox.send(header(5), &pixels, |rgb| rgb[0] = 200).unwrap();
    let frame = inbox.latest().unwrap().expect("a frame");
    assert_eq!(*frame.user_header(), header(5));
    assert_eq!(frame.payload()[0], 200, "the draw step is lost");
    assert_eq!(&frame.payload()[1..], &pixels[1..]);
    drop(frame);

    // Written in place; the newest of several queued frames wins.
    for seq in 6..6 + FRAME_SUBSCRIBER_BUFFER as u64 + 1 {
        outbox
            .send_in_place(header(seq), 24, |rgb| rgb.fill(seq as u8))
            .unwrap();
    }
    let newest = 6 + FRAME_SUBSCRIBER_BUFFER as u64;
    let frame = inbox.latest().unwrap().expect("a frame");
    assert_eq!(frame.user_header().stamp.seq, newest);
    assert!(frame.payload().iter().all(|&b| b == newest as u8));
    drop(frame);
    assert!(inbox.latest().unwrap().is_none(), "older frames kept");
}

#[test]
fn a_silent_input_misses_its_deadline_on_time() {
    let world = Isolated::new();
    let node = world.node();
    let inbox = Inbox::<u64>::new(&node, TOPIC).unwrap();
    let mut heartbeat = HeartbeatSender::new(&node, ServiceId::Flow, 0).unwrap();
    let deadline = Duration::from_millis(150);
    let (misses, fired) = watch(&inbox, &mut heartbeat, deadline, Duration::from_millis(700));
    assert_eq!(fired, 0);
    let first = *misses.first().expect("no deadline miss reported");
    // Never early; late by at most a generous scheduling allowance (the host is shared).
    assert!(
        first + Duration::from_millis(2) >= deadline,
        "reported early: {first:?}"
    );
    assert!(
        first <= deadline + Duration::from_millis(150),
        "reported late: {first:?}"
    );
    // The deadline re-arms: about one miss per deadline while nothing comes.
    assert!((2..=5).contains(&misses.len()), "{misses:?}");
    assert_eq!(heartbeat.deadline_misses(), misses.len() as u64);
}

#[test]
fn an_input_that_arrives_in_time_misses_no_deadline() {
    let world = Isolated::new();
    let node = world.node();
    let inbox = Inbox::<u64>::new(&node, TOPIC).unwrap();
    let mut heartbeat = HeartbeatSender::new(&node, ServiceId::Flow, 0).unwrap();
    let length = Duration::from_millis(600);
    let sender = {
        let config = world.config();
        std::thread::spawn(move || {
            let node = millinav_kit::iceoryx2::prelude::NodeBuilder::new()
                .config(&config)
                .create::<millinav_kit::iceoryx2::prelude::ipc::Service>()
                .unwrap();
            let outbox = Outbox::<u64>::new(&node, TOPIC).unwrap();
            let start = Instant::now();
            let mut sent = 0;
            // Every 10 ms against a 300 ms deadline: 30x slack for a loaded host.
            while start.elapsed() < length + Duration::from_millis(200) {
                outbox.send(sent).unwrap();
                sent += 1;
                std::thread::sleep(Duration::from_millis(10));
            }
            sent
        })
    };
    let (misses, fired) = watch(&inbox, &mut heartbeat, Duration::from_millis(300), length);
    let sent = sender.join().unwrap();
    assert!(misses.is_empty(), "deadline missed at {misses:?}");
    assert_eq!(heartbeat.deadline_misses(), 0);
    assert!(sent > 10 && fired > 5, "sent {sent}, woke for {fired}");
}

#[test]
fn an_unread_input_does_not_make_the_loop_spin() {
    let world = Isolated::new();
    let node = world.node();
    let inbox = Inbox::<u64>::new(&node, TOPIC).unwrap();
    let outbox = Outbox::<u64>::new(&node, TOPIC).unwrap();
    let mut heartbeat = HeartbeatSender::new(&node, ServiceId::Flow, 0).unwrap();
    outbox.send(1).unwrap();
    let mut service_loop = ServiceLoop::new();
    let input = service_loop.input(&inbox);
    let start = Instant::now();
    let (mut wakes, mut fired) = (0, 0);
    service_loop
        .run(&mut heartbeat, |wake| {
            // Never takes the sample: the loop itself must consume the announcement.
            wakes += 1;
            fired += usize::from(wake.fired(input));
            if start.elapsed() >= Duration::from_millis(500) {
                wake.stop();
            }
            Ok::<(), KitError>(())
        })
        .unwrap();
    assert_eq!(fired, 1);
    // One wake for the sample, one per 100 ms tick; a spinning loop wakes thousands of times.
    assert!(wakes <= 12, "{wakes} wakes in 500 ms");
    assert_eq!(inbox.receive_all().unwrap(), vec![1], "the sample was lost");
}

#[test]
fn the_heartbeat_beats_at_its_period() {
    let world = Isolated::new();
    let node = world.node();
    let health = Inbox::<Heartbeat>::new(&node, services::HEALTH).unwrap();
    let mut heartbeat = HeartbeatSender::new(&node, ServiceId::Control, 3).unwrap();
    let service_loop = ServiceLoop::new();
    let start = Instant::now();
    let mut beats: Vec<Heartbeat> = Vec::new();
    service_loop
        .run(&mut heartbeat, |wake| {
            beats.extend(health.receive_all()?);
            if start.elapsed() >= Duration::from_millis(1500) {
                wake.stop();
            }
            Ok::<(), KitError>(())
        })
        .unwrap();
    beats.extend(health.receive_all().unwrap());
    assert!(beats.iter().all(|b| b.service == ServiceId::Control as u32
        && b.incarnation == 3
        && b.pid == std::process::id()));
    assert!(beats.windows(2).all(|w| w[1].cycles > w[0].cycles));
    let mut gaps_ms: Vec<f64> = beats
        .windows(2)
        .map(|w| (w[1].wall_time_ns - w[0].wall_time_ns) as f64 * 1e-6)
        .collect();
    gaps_ms.sort_by(f64::total_cmp);
    let period_ms = deadlines::HEARTBEAT_PERIOD.as_secs_f64() * 1e3;
    let median = gaps_ms[gaps_ms.len() / 2];
    assert!(
        (period_ms * 0.9..=period_ms * 1.3).contains(&median),
        "median gap {median:.1} ms, period {period_ms} ms: {gaps_ms:?}"
    );
    assert!(
        (10..=16).contains(&beats.len()),
        "{} beats in 1.5 s at {period_ms} ms",
        beats.len()
    );
}
