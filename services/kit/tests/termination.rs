//! SIGTERM ends a service loop. Its own test binary: the signal goes to the whole process.

mod common;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::Isolated;
use millinav_kit::ports::HeartbeatSender;
use millinav_kit::service_loop::{LoopEnd, ServiceLoop};
use millinav_kit::KitError;
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use shm_schemas::ServiceId;

#[test]
fn sigterm_ends_the_loop() {
    let world = Isolated::new();
    let node = world.node();
    let mut heartbeat = HeartbeatSender::new(&node, ServiceId::Vision, 0).unwrap();
    let running = Arc::new(AtomicBool::new(false));
    let signaller = {
        let running = running.clone();
        std::thread::spawn(move || {
            // iceoryx2 installs its handler when the loop first waits; signal only after that.
            while !running.load(Ordering::Acquire) {
                std::thread::sleep(Duration::from_millis(5));
            }
            kill(Pid::this(), Signal::SIGTERM).expect("kill");
            Instant::now()
        })
    };
    let give_up = Instant::now() + Duration::from_secs(10);
    let end = ServiceLoop::new()
        .run(&mut heartbeat, |wake| {
            running.store(true, Ordering::Release);
            if Instant::now() > give_up {
                wake.stop();
            }
            Ok::<(), KitError>(())
        })
        .unwrap();
    let ended = Instant::now();
    let signalled = signaller.join().unwrap();
    assert_eq!(end, LoopEnd::Terminated);
    // Noticed at the latest on the next tick (100 ms), with room for a loaded host.
    assert!(ended.duration_since(signalled) < Duration::from_secs(2));
}
