//! Start-up is not a hang: the set starts with four busy loops per core beside it and the page
//! cache dropped (where this machine lets the test drop it), as a cold lab PC that is busy
//! with something else would start it. No child may be taken for hung while it starts (no
//! `heartbeat_missed`, no restart), every child reports ready, and the run completes, slowly.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use millinav_tests::{scenario_text, RunSet};

/// Busy loops that stop when dropped.
struct Hogs(Vec<Child>);

impl Hogs {
    fn start(count: usize) -> Self {
        Self(
            (0..count)
                .map(|_| {
                    Command::new("sh")
                        .args(["-c", "while :; do :; done"])
                        .stdin(Stdio::null())
                        .spawn()
                        .expect("a busy loop")
                })
                .collect(),
        )
    }
}

impl Drop for Hogs {
    fn drop(&mut self) {
        for hog in &mut self.0 {
            let _ = hog.kill();
            let _ = hog.wait();
        }
    }
}

/// Drops the page cache (needs root): the set's binaries, maps and model come from disk again.
fn drop_page_cache() -> bool {
    let _ = Command::new("sync").status();
    std::fs::write("/proc/sys/vm/drop_caches", "3\n").is_ok()
}

#[test]
fn the_set_starts_beside_four_busy_loops_per_core_without_a_restart() {
    let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
    let hogs = Hogs::start(4 * cores);
    let dropped = drop_page_cache();
    eprintln!(
        "{} busy loops; page cache {}",
        4 * cores,
        if dropped {
            "dropped"
        } else {
            "not dropped (no permission)"
        }
    );
    let text = scenario_text(
        2.0,
        &[[-18.0, 12.0], [-12.0, 8.0]],
        1.5,
        "[control]\ncontroller = \"pid\"\n",
    );
    let started = Instant::now();
    let mut run = RunSet::start("startload", &text).expect("start run");
    let status = run.wait(Duration::from_secs(280));
    drop(hogs);
    let events = run.supervisor_events().expect("supervisor events");
    let console = run.supervisor_console().unwrap_or_default();
    let status = status.unwrap_or_else(|e| panic!("{e}\n{console}\n{events:#?}"));
    eprintln!("the run took {:.1} s", started.elapsed().as_secs_f64());
    for e in events.iter().filter(|e| e.event == "ready") {
        eprintln!("{} ready: {}", e.service, e.detail);
    }
    let hung: Vec<_> = events
        .iter()
        .filter(|e| matches!(e.event.as_str(), "heartbeat_missed" | "restart" | "exit"))
        .collect();
    assert!(
        hung.is_empty(),
        "a starting child was taken for hung: {hung:#?}"
    );
    for service in ["plant", "camera", "coilbus", "flow", "vision", "control"] {
        assert!(
            events
                .iter()
                .any(|e| e.service == service && e.event == "ready"),
            "{service} never reported ready: {events:#?}"
        );
    }
    assert!(status.success(), "supervisor exit {status}\n{console}");
    assert!(
        events
            .iter()
            .any(|e| e.service == "plant" && e.event == "run_complete"),
        "the run did not complete: {events:#?}"
    );
}
