//! `millinav ctl` against a running twin: status, a goal outside the canal refused with nothing
//! changed, pause holds position, goto replans (A*) and the robot gets there, estop zeroes the
//! coils and latches (resume refused) until arm, and every answer is in `operator_events.csv`.

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use millinav_kit::runlog::{self, ControlRow, RunLogRow};
use millinav_tests::{bin_dir, scenario_text, RunSet};

/// Runs `millinav ctl` against `run`'s set: (exit code, stdout + stderr).
fn ctl(run: &RunSet, args: &[&str]) -> (i32, String) {
    let out = Command::new(bin_dir().join("millinav"))
        .arg("ctl")
        .args(["--iox-prefix", &run.iox_prefix, "--iox-root"])
        .arg(&run.iox_root)
        .args(["--timeout-s", "5"])
        .args(args)
        .output()
        .expect("run millinav ctl");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    println!("$ millinav ctl {}\n{text}", args.join(" "));
    (out.status.code().unwrap_or(-1), text)
}

/// The rows of a log control is still writing (`read_rows` leaves out a line cut mid-write).
fn rows_so_far<R: RunLogRow>(run_dir: &Path) -> Vec<R> {
    runlog::read_rows(&run_dir.join(R::FILE_NAME)).unwrap_or_default()
}

/// Where control last saw the robot (m) and its mode and largest command, from `control.csv`.
fn last_seen(run: &RunSet) -> Option<ControlRow> {
    rows_so_far::<ControlRow>(&run.run_dir)
        .into_iter()
        .rev()
        .find(|r| r.measured_x_m.is_finite())
}

/// Where control saw the robot on average over the last `window_s` of its log (m), and the
/// time of the last row (s): a held robot rings about its place at the loop's own rate, so two
/// single rows can differ by the ringing's whole swing.
fn mean_seen(run: &RunSet, window_s: f64) -> Option<(f64, f64, f64)> {
    let rows: Vec<ControlRow> = rows_so_far::<ControlRow>(&run.run_dir)
        .into_iter()
        .filter(|r| r.measured_x_m.is_finite())
        .collect();
    let last_s = rows.last()?.time_s;
    let recent: Vec<&ControlRow> = rows
        .iter()
        .filter(|r| r.time_s >= last_s - window_s)
        .collect();
    let n = recent.len() as f64;
    let x = recent.iter().map(|r| r.measured_x_m).sum::<f64>() / n;
    let y = recent.iter().map(|r| r.measured_y_m).sum::<f64>() / n;
    Some((x, y, last_s))
}

/// Waits until control's log reaches scenario time `at_s` and returns its rows; `None` when
/// it does not within a minute of wall time (control stopped). Lockstep runs at whatever pace
/// the machine allows, so tests wait on scenario time, never on the wall clock.
fn rows_at(run: &RunSet, at_s: f64) -> Option<Vec<ControlRow>> {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let rows = rows_so_far::<ControlRow>(&run.run_dir);
        if rows.last().is_some_and(|r| r.time_s >= at_s) {
            return Some(rows);
        }
        if Instant::now() > deadline {
            return None;
        }
        wait(0.1);
    }
}

/// The time of control's last logged row (s); control flushes its log every half second of
/// scenario time, so its decision for a request just answered lies at most that far ahead.
fn log_time(run: &RunSet) -> f64 {
    rows_so_far::<ControlRow>(&run.run_dir)
        .last()
        .map_or(0.0, |r| r.time_s)
}

/// `mean_seen` once control's log reaches scenario time `at_s`.
fn mean_seen_after(run: &RunSet, window_s: f64, at_s: f64) -> Option<(f64, f64, f64)> {
    rows_at(run, at_s)?;
    mean_seen(run, window_s)
}

fn wait(s: f64) {
    std::thread::sleep(Duration::from_secs_f64(s));
}

#[test]
fn the_operator_drives_a_running_twin() {
    let text = scenario_text(
        90.0,
        &[[-18.0, 12.0], [-12.0, 8.0], [-10.0, 4.0]],
        2.0,
        "[control]\ncontroller = \"pid\"\n",
    );
    let mut run = RunSet::start("operator", &text).expect("start run");
    run.wait_for_frames(100, Duration::from_secs(60))
        .expect("the loop runs");

    let (code, out) = ctl(&run, &["status"]);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("state: tracking"), "{out}");

    // A goal outside the canal: refused with the reason, nothing changes.
    let (code, out) = ctl(&run, &["goto", "40", "40"]);
    assert_eq!(code, 1, "{out}");
    assert!(
        out.contains("REFUSED") && out.contains("state: tracking"),
        "{out}"
    );

    // Pause: the robot holds where it is.
    let (code, out) = ctl(&run, &["pause"]);
    assert_eq!(code, 0, "{out}");
    assert!(
        out.contains("holding") && out.contains("state: paused"),
        "{out}"
    );
    let a = mean_seen_after(&run, 0.5, log_time(&run) + 1.5).expect("control kept running");
    let b = mean_seen_after(&run, 0.5, a.2 + 2.0).expect("control kept running");
    let drift_mm = (b.0 - a.0).hypot(b.1 - a.1) * 1e3;
    assert!(drift_mm < 0.3, "paused robot moved {drift_mm:.3} mm");

    // Goto: a new A* path from the current pose, and the robot gets there.
    let (code, out) = ctl(&run, &["goto", "-6", "-6"]);
    assert_eq!(code, 0, "{out}");
    assert!(
        out.contains("following") && out.contains("state: tracking"),
        "{out}"
    );
    // 30 s of scenario time to get there; a minute of wall time without a new row is a stall.
    let give_up_s = log_time(&run) + 30.0;
    let arrived = loop {
        let seen = last_seen(&run).expect("control rows");
        let off_mm = (seen.measured_x_m + 6e-3).hypot(seen.measured_y_m + 6e-3) * 1e3;
        if off_mm < 1.0 {
            break true;
        }
        if seen.time_s > give_up_s {
            println!("last seen {seen:?}, {off_mm:.2} mm from the goal");
            break false;
        }
        rows_at(&run, seen.time_s + 0.5).expect("control kept logging");
    };
    assert!(arrived, "the robot did not reach the goto goal");

    // Estop: coils at zero, latched; resume is refused until arm.
    let (code, out) = ctl(&run, &["estop"]);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("emergency-stopped"), "{out}");
    let after = rows_at(&run, log_time(&run) + 1.5).expect("control kept logging");
    let last = after.last().expect("control rows");
    assert_eq!(last.mode, shm_schemas::ControlMode::Safe as u32, "{last:?}");
    assert_eq!(last.max_abs_current_a, 0.0, "{last:?}");
    let (code, out) = ctl(&run, &["resume"]);
    assert_eq!(code, 1, "{out}");
    let (code, out) = ctl(&run, &["arm"]);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("state: paused"), "{out}");

    let status = run.stop(Duration::from_secs(30)).expect("stop");
    assert!(status.success(), "supervisor exit {status}");
    // Every answer is in the run's operator events, refusals included.
    let events = std::fs::read_to_string(run.run_dir.join("operator_events.csv"))
        .expect("operator_events.csv");
    println!("{events}");
    for (verb, accepted) in [
        ("status", true),
        ("goto", false),
        ("pause", true),
        ("goto", true),
        ("estop", true),
        ("resume", false),
        ("arm", true),
    ] {
        assert!(
            events
                .lines()
                .any(|l| l.contains(&format!(",{verb},{accepted},"))),
            "no {verb} accepted={accepted} row\n{events}"
        );
    }
}

#[test]
fn a_session_starts_disarmed_runs_past_its_duration_and_ends_on_ctl_stop() {
    // 2 s of scenario: a session runs past it until the operator stops the set.
    let text = scenario_text(
        2.0,
        &[[-18.0, 12.0], [-12.0, 8.0]],
        2.0,
        "[control]\ncontroller = \"pid\"\n",
    );
    let mut run = RunSet::start_with_args("session", &text, &["--session"]).expect("start run");
    run.wait_for_frames(300, Duration::from_secs(60))
        .expect("the twin runs past the scenario's 2 s");
    let (code, out) = ctl(&run, &["status"]);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("state: disarmed"), "{out}");
    let rows: Vec<ControlRow> = rows_so_far(&run.run_dir);
    let last = rows.last().expect("control rows");
    assert_eq!(
        last.mode,
        shm_schemas::ControlMode::Safe as u32,
        "disarmed: {last:?}"
    );
    assert_eq!(last.max_abs_current_a, 0.0);
    let (code, out) = ctl(&run, &["arm"]);
    assert_eq!(code, 0, "{out}");
    let last = rows_at(&run, log_time(&run) + 1.0)
        .and_then(|rows| rows.last().cloned())
        .expect("control kept logging");
    assert_ne!(
        last.mode,
        shm_schemas::ControlMode::Safe as u32,
        "armed: {last:?}"
    );
    let (code, out) = ctl(&run, &["stop"]);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("stopping"), "{out}");
    let status = run.wait(Duration::from_secs(30)).expect("the set ends");
    assert!(status.success(), "supervisor exit {status}");
    let summary = std::fs::read_to_string(run.run_dir.join("summary.json")).expect("summary");
    assert!(summary.contains("stopped by the operator"), "{summary}");
    let events = run.supervisor_events().expect("events");
    assert!(events.iter().any(|e| e.event == "operator_stop"));
}
