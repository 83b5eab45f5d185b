//! A SIGCONT that follows a SIGTERM (the supervisor's stop, systemd's stop) does not erase the
//! termination request, and a SIGCONT alone does not end the loop. Its own test binary: the
//! signals go to the whole process and the request, once made, stays.

mod common;

use std::time::{Duration, Instant};

use common::Isolated;
use millinav_kit::ports::HeartbeatSender;
use millinav_kit::service_loop::{LoopEnd, ServiceLoop};
use millinav_kit::{termination, KitError};
use nix::sys::signal::{raise, Signal};
use shm_schemas::ServiceId;

#[test]
fn sigterm_then_sigcont_still_ends_the_loop_and_sigcont_alone_does_not() {
    let world = Isolated::new();
    let node = world.node();
    let mut heartbeat = HeartbeatSender::new(&node, ServiceId::Camera, 0).unwrap();
    let mut wakes = 0u32;
    let mut wakes_after_sigcont = 0u32;
    let mut signalled_at = None;
    let give_up = Instant::now() + Duration::from_secs(10);
    let mut service_loop = ServiceLoop::new();
    service_loop.tick_every(Duration::from_millis(20));
    let end = service_loop
        .run(&mut heartbeat, |wake| {
            wakes += 1;
            match wakes {
                // Raised here, outside any wait: the handlers run at once, in this order, as a
                // busy process that was not in a wait would take two pending signals.
                1 => raise(Signal::SIGCONT).expect("raise SIGCONT"),
                2..=5 => wakes_after_sigcont += 1,
                6 => {
                    raise(Signal::SIGTERM).expect("raise SIGTERM");
                    raise(Signal::SIGCONT).expect("raise SIGCONT");
                    signalled_at = Some(Instant::now());
                }
                _ => {}
            }
            if Instant::now() > give_up {
                wake.stop();
            }
            Ok::<(), KitError>(())
        })
        .unwrap();
    assert_eq!(wakes_after_sigcont, 4, "a SIGCONT alone ended the loop");
    assert_eq!(
        end,
        LoopEnd::Terminated,
        "the SIGTERM was lost after {wakes} wakes"
    );
    assert_eq!(wakes, 6, "the loop woke again after the SIGTERM");
    assert!(signalled_at.is_some_and(|t| t.elapsed() < Duration::from_secs(5)));
    assert!(termination::requested());
}
