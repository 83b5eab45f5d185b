//! Nothing wedges: children SIGKILLed at random points of their start-up (scenario read, maps
//! and model loading, node and service creation), over a hundred times in one seeded run. A
//! child killed while it creates an iceoryx2 service leaves that service half-made; the
//! supervisor must remove it before the next start, or every later start hangs on it. After
//! the soak every child must start again, the loop must run, and the stopped set must leave
//! no iceoryx2 file or shared-memory segment behind.

use std::path::Path;
use std::time::{Duration, Instant};

use millinav_tests::{scenario_text, RunSet};
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Kills during a child's start-up.
const KILLS: usize = 110;
/// A kill lands this long after the child's spawn, drawn uniformly: the services' start-up
/// (scenario, maps, node, services) fits in it on this machine.
const LATEST_KILL: Duration = Duration::from_millis(400);

const SERVICES: [&str; 6] = ["plant", "camera", "coilbus", "flow", "vision", "control"];

/// The default set, restarted at once and never stopped for failing often: the soak fails on
/// purpose.
fn launch_file() -> String {
    let mut text = String::from(
        "[restart]\ninitial_backoff_ms = 10\nmax_backoff_ms = 50\nstable_after_ms = 1000\n\
         storm_restarts = 100000\n",
    );
    for name in SERVICES {
        text += &format!("[[process]]\nname = \"{name}\"\n");
    }
    text
}

/// Waits for the supervisor to start a new incarnation of `service` (its pid file changes from
/// `old`), and returns its pid.
fn respawned(run: &RunSet, service: &str, old: i32) -> i32 {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        if let Ok(pid) = run.pid_of(service) {
            if pid != old {
                return pid;
            }
        }
        assert!(
            Instant::now() < deadline,
            "{service} was not restarted within 20 s after a kill"
        );
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// iceoryx2 files of the prefix under its root.
fn files_with_prefix(root: &Path, prefix: &str) -> Vec<String> {
    let mut found = Vec::new();
    let mut dirs = vec![root.to_owned()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).into_iter().flatten().flatten() {
            let path = entry.path();
            if path.is_dir() {
                dirs.push(path);
            } else if entry.file_name().to_string_lossy().starts_with(prefix) {
                found.push(path.display().to_string());
            }
        }
    }
    found
}

#[test]
fn children_killed_mid_start_a_hundred_times_never_wedge_the_set() {
    let text = scenario_text(
        600.0,
        &[[-18.0, 12.0], [-12.0, 8.0]],
        0.5,
        "[control]\ncontroller = \"pid\"\n",
    );
    let base = std::env::temp_dir().join(format!("millinav-soak-{}", std::process::id()));
    std::fs::create_dir_all(&base).expect("dir");
    let launch = base.join("launch.toml");
    std::fs::write(&launch, launch_file()).expect("launch file");
    let mut run = RunSet::start_with_args(
        "killsoak",
        &text,
        &["--launch", launch.to_str().expect("utf-8 path")],
    )
    .expect("start run");
    run.wait_for_frames(50, Duration::from_secs(120))
        .expect("the loop runs before the soak");

    let mut rng = ChaCha8Rng::seed_from_u64(66);
    for kill_no in 0..KILLS {
        let service = SERVICES[rng.random_range(0..SERVICES.len())];
        // A running child first (the first time), then the new incarnation mid-start.
        let old = run.pid_of(service).expect("pid");
        let _ = kill(Pid::from_raw(old), Signal::SIGKILL);
        let pid = respawned(&run, service, old);
        let delay = LATEST_KILL.mul_f64(rng.random::<f64>());
        std::thread::sleep(delay);
        let _ = kill(Pid::from_raw(pid), Signal::SIGKILL);
        if kill_no % 20 == 0 {
            eprintln!("kill {kill_no}: {service} {delay:?} after its spawn");
        }
        respawned(&run, service, pid);
    }

    // Every child's latest incarnation starts (reports ready after its last spawn) and the
    // loop runs on: nothing wedged.
    let deadline = Instant::now() + Duration::from_secs(90);
    loop {
        let events = run.supervisor_events().expect("events");
        let not_ready: Vec<&str> = SERVICES
            .into_iter()
            .filter(|s| {
                let last_spawn = events
                    .iter()
                    .filter(|e| e.service == *s && e.event == "spawn")
                    .map(|e| e.monotonic_ns)
                    .max()
                    .unwrap_or(0);
                !events
                    .iter()
                    .any(|e| e.service == *s && e.event == "ready" && e.monotonic_ns > last_spawn)
            })
            .collect();
        if not_ready.is_empty() {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "not started again within 90 s after the soak: {not_ready:?}\n{}",
            run.supervisor_console().unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let commanded = run
        .teensy_events()
        .expect("teensy events")
        .iter()
        .filter(|e| e.kind == "command")
        .count();
    let more_commands = Instant::now() + Duration::from_secs(60);
    while run
        .teensy_events()
        .expect("teensy events")
        .iter()
        .filter(|e| e.kind == "command")
        .count()
        < commanded + 100
    {
        assert!(
            Instant::now() < more_commands,
            "the loop does not run after the soak"
        );
        std::thread::sleep(Duration::from_millis(50));
    }

    let events = run.supervisor_events().expect("events");
    let swept = events
        .iter()
        .filter(|e| e.event == "removed_half_made_service")
        .count();
    eprintln!("half-made services removed before a restart: {swept}");
    let status = run.stop(Duration::from_secs(60)).expect("stops");
    assert!(status.success(), "supervisor exit {status}");
    let left = files_with_prefix(&run.iox_root, &run.iox_prefix);
    assert!(left.is_empty(), "iceoryx2 files left behind: {left:#?}");
    let shm = run.shm_segments();
    assert!(shm.is_empty(), "shared memory left behind: {shm:?}");
    let _ = std::fs::remove_dir_all(&base);
}
