//! The coil-driver board's own faults through the whole process set (issue 19, point 6): the
//! e-stop pressed mid-run, a thermal trip under a long high-current hold, a driver channel whose
//! current sense disagrees with the command, and a board that reboots disarmed. The emulated
//! board runs `firmware/core`, the logic the Teensy firmware links; the faults are scheduled in
//! `[plant.board_faults]` (and, for the thermal trip, by a rig whose coils have a small heat
//! budget).
//!
//! What each must show:
//! - e-stop, thermal trip, faulty channel: the board drives nothing after the fault (no non-zero
//!   frame at the board after its `estop` / `thermal_trip` event, or after coilbus latched the
//!   disagreement), coilbus latches the fault and says why in `coilbus_link.csv`, and the
//!   supervisor ends the run with a non-zero exit naming the fault;
//! - reboot: the board comes back unconfigured and disarmed, coilbus configures and re-arms it
//!   (the set is healthy) and the run completes.
//!
//! Table: `cargo test --release -p millinav-tests --test board_faults -- --nocapture`

use std::time::Duration;

use millinav_kit::runlog::{self, LinkEventRow};
use millinav_tests::{scenario_text, RunSet, TeensyEvent};

const RUN_TIMEOUT: Duration = Duration::from_secs(240);

/// A circle in the right atrium held for `duration_s` with `extra` tables appended.
fn circle(duration_s: f64, extra: &str) -> String {
    let points = millinav_tests::atrium_circle_mm();
    scenario_text(
        duration_s,
        &points,
        1.0,
        &format!("[control]\ncontroller = \"pid\"\n[vision]\nlocalizer = \"classical\"\n{extra}"),
    )
}

fn link_rows(run: &RunSet) -> Vec<LinkEventRow> {
    runlog::read_run_dir(&run.run_dir).expect("coilbus_link.csv")
}

/// Runs `scenario` to its end; returns the run and whether the supervisor exited cleanly.
fn run(name: &str, scenario: &str) -> (RunSet, bool) {
    let mut run = RunSet::start(name, scenario).expect("start the set");
    let status = run.wait(RUN_TIMEOUT).expect("the run ends");
    (run, status.success())
}

/// The board's events from the first `kind` on, and that first event.
fn after<'a>(events: &'a [TeensyEvent], kind: &str) -> (&'a TeensyEvent, &'a [TeensyEvent]) {
    let at = events
        .iter()
        .position(|e| e.kind == kind)
        .unwrap_or_else(|| panic!("no `{kind}` event at the board: {events:?}"));
    (&events[at], &events[at + 1..])
}

/// No frame after `from` drove any current.
fn assert_nothing_driven(rest: &[TeensyEvent], what: &str) {
    let driven: Vec<&TeensyEvent> = rest
        .iter()
        .filter(|e| e.kind == "command" && e.max_abs_current_a > 0.0)
        .collect();
    assert!(
        driven.is_empty(),
        "{what}: the board drove current afterwards: {:?}",
        &driven[..driven.len().min(5)]
    );
}

/// coilbus latched `fault` (its link log says why) and the supervisor ended the run on it.
fn assert_ended_on(run: &RunSet, clean_exit: bool, fault: &str) -> String {
    assert!(
        !clean_exit,
        "the run must end with an error on a board fault"
    );
    let console = run.supervisor_console().expect("supervisor console");
    assert!(
        console.contains(&format!("reported `{fault}`")),
        "the supervisor's exit does not name `{fault}`:\n{console}"
    );
    let events = run.supervisor_events().expect("supervisor events");
    assert!(
        events
            .iter()
            .any(|e| e.event == "board_fault" && e.detail == fault),
        "no board_fault {fault} in supervisor_events.csv: {events:?}"
    );
    let rows = link_rows(run);
    let row = rows
        .iter()
        .find(|r| r.event == "board_fault")
        .unwrap_or_else(|| panic!("no board_fault in coilbus_link.csv: {rows:?}"));
    assert!(row.detail.starts_with(fault), "{}", row.detail);
    row.detail.clone()
}

#[test]
fn estop_pressed_mid_run_zeroes_the_coils_and_ends_the_run() {
    let (run, clean) = run(
        "estop",
        &circle(8.0, "[plant.board_faults]\nestop_at_s = 3.0\n"),
    );
    let events = run.teensy_events().unwrap();
    let (estop, rest) = after(&events, "estop");
    // The board zeroed on the tick that saw the input: the `estop` event is that zero.
    assert_eq!(estop.max_abs_current_a, 0.0);
    assert_nothing_driven(rest, "after the e-stop");
    let why = assert_ended_on(&run, clean, "estop");
    assert!(why.contains("e-stop input"), "{why}");
    println!("estop: {why}");
}

#[test]
fn thermal_trip_under_a_long_hold_zeroes_the_coils_and_ends_the_run() {
    // The paper rig with coils rated for 0.5 A continuously and a 0.05 A²·s heat budget: at
    // the currents a hold takes, the budget fills faster than derating between two commands
    // can stop it, so the board trips (its hard limit).
    let rigs = fieldmaps::data_root().join("fieldmaps/rigs");
    let rigs = rigs.display();
    let text = std::fs::read_to_string(fieldmaps::rigfile::paper_rig_path())
        .unwrap()
        .replace("dir = \"../", &format!("dir = \"{rigs}/../"))
        .replace("\"paper/", &format!("\"{rigs}/paper/"))
        .replace("\"../flow/", &format!("\"{rigs}/../flow/"))
        .replace(
            "\nmax_current_a = 6.0",
            "\ncontinuous_current_a = 0.5\nthermal_budget_a2s = 0.05\nmax_current_a = 6.0",
        );
    let dir = std::env::temp_dir().join(format!("millinav-thermal-rig-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let rig = dir.join("hot.toml");
    std::fs::write(&rig, text).unwrap();
    let scenario = circle(8.0, "").replacen(
        "rig = \"fieldmaps/rigs/paper.toml\"",
        &format!("rig = \"{}\"", rig.display()),
        1,
    );
    let (run, clean) = run("thermal", &scenario);
    let events = run.teensy_events().unwrap();
    let (_, rest) = after(&events, "thermal_trip");
    assert_nothing_driven(rest, "after the thermal trip");
    let why = assert_ended_on(&run, clean, "thermal_trip");
    println!("thermal trip: {why}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_faulty_driver_channel_is_caught_by_telemetry_and_disarmed() {
    // Channel 0's sense reads nothing of what it drives (an open coil or a dead driver).
    let (run, clean) = run(
        "sense",
        &circle(
            8.0,
            "[plant.board_faults]\nsense_fault_at_s = 3.0\nsense_fault_channel = 0\nsense_fault_gain = 0.0\n",
        ),
    );
    let why = assert_ended_on(&run, clean, "telemetry_disagrees");
    assert!(why.contains("channel 0"), "{why}");
    // coilbus disarmed the board: nothing driven after the disarm.
    let events = run.teensy_events().unwrap();
    let (_, rest) = after(&events, "disarm");
    assert_nothing_driven(rest, "after the disarm");
    println!("faulty channel: {why}");
}

#[test]
fn a_board_that_reboots_disarmed_is_configured_and_rearmed() {
    let (run, clean) = run(
        "reboot",
        &circle(8.0, "[plant.board_faults]\nreboot_at_s = 3.0\n"),
    );
    let events = run.teensy_events().unwrap();
    let (_, rest) = after(&events, "rebooted");
    let kinds: Vec<&str> = rest.iter().map(|e| e.kind.as_str()).collect();
    let config = kinds.iter().position(|k| *k == "config");
    let arm = kinds.iter().position(|k| *k == "arm");
    assert!(
        matches!((config, arm), (Some(c), Some(a)) if c < a),
        "coilbus did not configure then arm the rebooted board: {kinds:?}"
    );
    assert!(
        rest.iter()
            .any(|e| e.kind == "command" && e.max_abs_current_a > 0.0),
        "nothing was driven after the re-arm"
    );
    assert!(clean, "the run should complete after a reboot");
    let sup = run.supervisor_events().unwrap();
    assert!(sup.iter().any(|e| e.event == "run_complete"), "{sup:?}");
    assert!(!sup.iter().any(|e| e.event == "board_fault"), "{sup:?}");
}
