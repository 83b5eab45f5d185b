//! The whole process set runs closed-loop in lockstep on the digital twin, and the run's
//! recording parses back with the entities a lab engineer looks at.

use std::process::Command;
use std::sync::OnceLock;
use std::time::Duration;

use millinav_kit::summary::{RunSummary, SUMMARY_JSON};
use millinav_tests::{scenario_text, tracking, venv_dir, RunSet, Tracking};

/// RMSE bound for PID on this short static-fluid path (the paper's PID: 0.82 mm at 20 cP).
const RMSE_BOUND_M: f64 = 0.5e-3;

struct Outcome {
    run: RunSet,
    tracking: Tracking,
    complete: bool,
}

/// One run shared by the tests of this file (a closed-loop run costs a few seconds).
fn outcome() -> &'static Outcome {
    static OUTCOME: OnceLock<Outcome> = OnceLock::new();
    OUTCOME.get_or_init(|| {
        let text = scenario_text(
            7.0,
            &[[-18.0, 12.0], [-12.0, 8.0], [-10.0, 4.0]],
            2.0,
            "[control]\ncontroller = \"pid\"\n",
        );
        let mut run = RunSet::start("closedloop", &text).expect("start run");
        run.remove_at_exit();
        let status = run.wait(Duration::from_secs(120)).expect("run finishes");
        assert!(status.success(), "supervisor exit status {status}");
        let scenario = run.scenario().expect("scenario");
        let truth = run.truth().expect("truth");
        let tracking = tracking(&scenario, &truth, 0.0).expect("tracking");
        let complete = run
            .supervisor_events()
            .expect("events")
            .iter()
            .any(|e| e.service == "plant" && e.event == "run_complete");
        Outcome {
            run,
            tracking,
            complete,
        }
    })
}

#[test]
fn follows_a_short_path_to_its_end_in_lockstep() {
    let o = outcome();
    println!(
        "closed loop (PID, 20 cP, static): RMSE {:.3} mm, max {:.3} mm, final {:.3} mm, wall contacts {}",
        o.tracking.rmse_m * 1e3,
        o.tracking.max_m * 1e3,
        o.tracking.final_error_m * 1e3,
        o.tracking.wall_contacts
    );
    assert!(o.complete, "the plant did not report run_complete");
    assert!(
        o.tracking.rmse_m < RMSE_BOUND_M,
        "RMSE {:.3} mm exceeds {:.3} mm",
        o.tracking.rmse_m * 1e3,
        RMSE_BOUND_M * 1e3
    );
    assert!(o.tracking.final_error_m < 0.5e-3, "did not reach the end");
    assert_eq!(o.tracking.wall_contacts, 0);
    // A clean shutdown leaves no shared memory behind.
    assert!(
        o.run.shm_segments().is_empty(),
        "leaked segments: {:?}",
        o.run.shm_segments()
    );
}

#[test]
fn the_run_ends_with_a_summary_that_agrees_with_its_logs() {
    let o = outcome();
    let printed = o.run.supervisor_stdout().expect("supervisor stdout");
    println!("{printed}");
    for line in [
        "Run summary",
        "as control saw:",
        "truth (twin):",
        "rerun ",
        "summary.json",
    ] {
        assert!(printed.contains(line), "{line:?} missing from\n{printed}");
    }
    let text = std::fs::read_to_string(o.run.run_dir.join(SUMMARY_JSON)).expect("summary.json");
    let summary: RunSummary = serde_json::from_str(&text).expect("summary.json parses");
    assert_eq!(summary.ending, "run complete");
    // Truth against the reference: what the test harness measures from truth.csv (the summary
    // takes the reference at control's actuation time, a frame later: 2 mm/s × 10 ms).
    let truth = summary.truth.expect("truth figures in the twin");
    assert!(truth.completed, "{summary:?}");
    assert!(
        (truth.rmse_mm - o.tracking.rmse_m * 1e3).abs() < 0.02 + 0.05 * truth.rmse_mm,
        "summary RMSE {} mm, harness {} mm",
        truth.rmse_mm,
        o.tracking.rmse_m * 1e3
    );
    // What control saw is vision's pose: within a few hundredths of a mm of the truth's figures.
    let seen = summary.as_control_saw.expect("control figures");
    assert!(
        seen.completed && (seen.rmse_mm - truth.rmse_mm).abs() < 0.05,
        "{summary:?}"
    );
    assert!(
        summary.poses_used as f64 > 0.95 * summary.frames as f64,
        "{summary:?}"
    );
    assert!(summary.frames > 500, "7 s at 100 Hz: {summary:?}");
    assert_eq!(summary.wall_contacts, Some(0));
    assert!(summary.restarts.values().all(|&r| r == 0), "{summary:?}");
    assert!(summary.peak_current_a > 0.0 && summary.energy_j.is_some_and(|e| e > 0.0));
    assert!(summary.recording.as_ref().is_some_and(|p| p.is_file()));
}

#[test]
fn recording_parses_back_with_image_pose_error_and_current_entities() {
    let o = outcome();
    let rrd = o.run.run_dir.join("run.rrd");
    assert!(
        rrd.is_file(),
        "no merged recording at {} (the `rerun` CLI comes with scripts/setup.sh)",
        rrd.display()
    );
    let rerun = venv_dir().join("bin/rerun");
    let verify = Command::new(&rerun)
        .args(["rrd", "verify"])
        .arg(&rrd)
        .output()
        .expect("run rerun rrd verify");
    assert!(
        verify.status.success(),
        "rerun rrd verify failed: {}",
        String::from_utf8_lossy(&verify.stderr)
    );
    let python = venv_dir().join("bin/python");
    let listing = Command::new(python)
        .arg("-c")
        .arg(
            "import sys\nfrom rerun.experimental import RrdReader\n\
             print('\\n'.join(sorted({c.entity_path for c in RrdReader(sys.argv[1]).stream()})))",
        )
        .arg(&rrd)
        .output()
        .expect("run the Python reader");
    assert!(
        listing.status.success(),
        "Python reader failed: {}",
        String::from_utf8_lossy(&listing.stderr)
    );
    let paths = String::from_utf8_lossy(&listing.stdout);
    println!("entities in run.rrd:\n{paths}");
    // The README's list: camera image, mask, keypoints, estimated pose, error, force, currents.
    for wanted in [
        "/camera/image",
        "/camera/mask",
        "/camera/keypoints",
        "/world/robot/estimated",
        "/control/error_mm/norm",
        "/control/force_des_n/x",
        "/coilbus/current_a/0",
        "/world/planned_path",
        // The 3D rig: coils coloured by current, canal outline, capsule, field and force.
        "/rig3d/coils",
        "/rig3d/canal",
        "/rig3d/robot",
        "/rig3d/field",
        "/rig3d/force",
    ] {
        assert!(
            paths.lines().any(|p| p.trim() == wanted),
            "entity {wanted} missing from the recording"
        );
    }
    // The viewer's layout travels with the recording: a blueprint store with its views.
    let python = venv_dir().join("bin/python");
    let layout = Command::new(python)
        .arg("-c")
        .arg(
            "import sys\nfrom rerun.experimental import RrdReader\nr = RrdReader(sys.argv[1])\n\
             bps = r.blueprints()\nprint(len(bps))\n\
             print('\\n'.join(sorted({c.entity_path for c in r.stream(store=bps[0])})) if bps else '')",
        )
        .arg(&rrd)
        .output()
        .expect("run the Python reader");
    let text = String::from_utf8_lossy(&layout.stdout);
    println!("blueprint stores and entities:\n{text}");
    assert!(
        layout.status.success(),
        "{}",
        String::from_utf8_lossy(&layout.stderr)
    );
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("1"), "one blueprint in run.rrd\n{text}");
    let views = lines.filter(|l| l.starts_with("/view/")).count();
    assert!(views >= 9, "{views} views in the blueprint\n{text}");
}
