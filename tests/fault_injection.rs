//! Fault injection: SIGKILL control in the middle of a lockstep tracking run. The coils must
//! reach zero within one command deadline (seen at the emulated Teensy), the supervisor must
//! restart control, and tracking must resume and complete. And the signals a stop brings: a
//! SIGCONT alone stops nothing, and the stop itself (SIGTERM, then the supervisor's SIGCONT and
//! SIGTERM to each child) ends every process cleanly.

use std::time::Duration;

use millinav_kit::clock::monotonic_ns;
use millinav_tests::{scenario_text, tracking, RunSet, SCHEDULING_TOLERANCE_MS};
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use shm_schemas::deadlines;

#[test]
fn killing_control_zeroes_coils_then_restart_resumes_tracking() {
    let text = scenario_text(
        9.0,
        &[[-18.0, 12.0], [-12.0, 8.0], [-10.0, 2.0]],
        1.5,
        "[control]\ncontroller = \"pid\"\n",
    );
    let mut run = RunSet::start("faultcontrol", &text).expect("start run");
    run.wait_for_frames(300, Duration::from_secs(60))
        .expect("loop running");
    let pid = run.pid_of("control").expect("control pid");
    let killed_at = monotonic_ns();
    kill(Pid::from_raw(pid), Signal::SIGKILL).expect("SIGKILL control");
    let status = run.wait(Duration::from_secs(180)).expect("run finishes");
    assert!(status.success(), "supervisor exit status {status}");

    let events = run.teensy_events().expect("teensy events");
    let last_command_before = events
        .iter()
        .rfind(|e| e.kind == "command" && e.monotonic_ns <= killed_at)
        .expect("commands before the kill")
        .clone();
    let zero = events
        .iter()
        .find(|e| e.monotonic_ns > last_command_before.monotonic_ns && e.drives_zero())
        .expect("currents reached zero after the kill")
        .clone();
    let resumed = events
        .iter()
        .find(|e| {
            e.kind == "command"
                && e.monotonic_ns > zero.monotonic_ns
                && e.frame_seq > last_command_before.frame_seq
        })
        .expect("commands resumed after the restart")
        .clone();
    let supervisor = run.supervisor_events().expect("supervisor events");
    let detected = supervisor
        .iter()
        .find(|e| e.service == "control" && e.event == "exit" && e.monotonic_ns >= killed_at)
        .expect("supervisor saw control exit");
    let restarted = supervisor
        .iter()
        .find(|e| e.service == "control" && e.event == "restart" && e.monotonic_ns >= killed_at)
        .expect("supervisor restarted control");
    assert!(
        supervisor
            .iter()
            .any(|e| e.service == "plant" && e.event == "run_complete"),
        "run did not complete"
    );

    let ms = |a: u64, b: u64| (b as f64 - a as f64) * 1e-6;
    let deadline_ms = deadlines::COMMAND.as_secs_f64() * 1e3;
    let zero_after_last_command = ms(last_command_before.monotonic_ns, zero.monotonic_ns);
    let zero_after_kill = ms(killed_at, zero.monotonic_ns);
    let detection = ms(killed_at, detected.monotonic_ns);
    let restart = ms(killed_at, restarted.monotonic_ns);
    let resume = ms(killed_at, resumed.monotonic_ns);
    println!(
        "fault injection: SIGKILL control at frame ~{:?}",
        last_command_before.frame_seq
    );
    println!("  time to zero current: {zero_after_kill:.1} ms after the kill, {zero_after_last_command:.1} ms after the last command (deadline {deadline_ms:.0} ms, by {})", zero.kind);
    println!("  supervisor detection: {detection:.1} ms; restart issued: {restart:.1} ms");
    println!("  time to resume tracking (first new command at the Teensy): {resume:.1} ms");

    assert!(
        zero_after_last_command <= deadline_ms + SCHEDULING_TOLERANCE_MS,
        "coils reached zero {zero_after_last_command:.1} ms after the last command; deadline {deadline_ms} ms \
         + {SCHEDULING_TOLERANCE_MS} ms tolerance"
    );
    let scenario = run.scenario().expect("scenario");
    let truth = run.truth().expect("truth");
    let t = tracking(&scenario, &truth, 0.0).expect("tracking");
    println!(
        "  tracking over the whole run: RMSE {:.3} mm, max {:.3} mm, final {:.3} mm",
        t.rmse_m * 1e3,
        t.max_m * 1e3,
        t.final_error_m * 1e3
    );
    assert!(
        t.final_error_m < 0.5e-3,
        "did not reach the end after the restart"
    );
    assert!(
        t.max_m < 3e-3,
        "error grew to {:.2} mm during the outage",
        t.max_m * 1e3
    );
}

#[test]
fn a_sigcont_stops_nothing_and_a_sigterm_stops_every_process_cleanly() {
    let text = scenario_text(
        60.0,
        &[[-18.0, 12.0], [-12.0, 8.0], [-10.0, 2.0]],
        1.5,
        "[control]\ncontroller = \"pid\"\n",
    );
    let mut run = RunSet::start("sigcont", &text).expect("start run");
    run.wait_for_frames(100, Duration::from_secs(60))
        .expect("loop running");
    let services = ["plant", "camera", "vision", "flow", "control", "coilbus"];
    let pids: Vec<i32> = services
        .iter()
        .map(|s| run.pid_of(s).expect("pid"))
        .collect();
    // SIGCONT to the supervisor and every service, as a shell's `fg` or systemd sends it: it
    // interrupts their waits, which must simply go on.
    let supervisor_pid = run.supervisor_pid().expect("supervisor pid");
    for _ in 0..5 {
        for pid in pids.iter().chain([&supervisor_pid]) {
            kill(Pid::from_raw(*pid), Signal::SIGCONT).expect("SIGCONT");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let before = run
        .teensy_events()
        .expect("teensy events")
        .iter()
        .filter_map(|e| e.frame_seq)
        .max()
        .unwrap_or(0);
    run.wait_for_frames(before + 100, Duration::from_secs(60))
        .expect("the loop goes on after SIGCONT");
    let events = run.supervisor_events().expect("supervisor events");
    assert!(
        !events
            .iter()
            .any(|e| matches!(e.event.as_str(), "signal" | "exit" | "restart" | "stopped")),
        "a SIGCONT stopped something: {events:?}"
    );
    let link = run.link_events().expect("coilbus link events");
    assert!(
        link.iter().filter(|(_, kind)| kind != "open").count() == 0,
        "a SIGCONT cost the serial link: {link:?}"
    );

    let status = run.stop(Duration::from_secs(60)).expect("supervisor stops");
    assert!(status.success(), "supervisor exit {status}");
    let events = run.supervisor_events().expect("supervisor events");
    for service in services {
        assert!(
            events.iter().any(|e| e.service == service
                && e.event == "stopped"
                && e.detail == "exit status: 0"),
            "{service} did not stop on its SIGTERM: {events:?}"
        );
    }
}
