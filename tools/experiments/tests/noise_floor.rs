//! `experiments --noise-floor` prints one row per condition, from the twin each cell would run.

use std::process::Command;

// Only `text` is used here.
#[allow(dead_code)]
mod common;
use common::text;

/// The rows of `experiments --noise-floor --base BASE ARGS`, split into their columns.
fn table(base: &str, args: &[&str]) -> Vec<Vec<String>> {
    let output = Command::new(env!("CARGO_BIN_EXE_experiments"))
        .current_dir(fieldmaps::data_root())
        .args(["--noise-floor", "--base", base])
        .args(args)
        .output()
        .expect("experiments runs");
    assert!(output.status.success(), "{}", text(&output));
    String::from_utf8(output.stdout)
        .unwrap()
        .lines()
        .skip(2)
        .map(|line| line.split('|').map(|c| c.trim().to_string()).collect())
        .collect()
}

/// The floor column on the paper's rig, by condition.
fn floors(args: &[&str]) -> Vec<(String, f64)> {
    table("scenarios/paper.toml", args)
        .into_iter()
        .map(|cells| (cells[1].clone(), cells[5].parse().expect("a floor in mm")))
        .collect()
}

#[test]
fn another_rig_gets_its_own_conditions_and_no_paper_numbers() {
    let rows = table("scenarios/vessel8.toml", &[]);
    assert!(
        rows.iter().any(|r| r[1].contains("mL/min")),
        "vessel8's flow conditions: {rows:?}"
    );
    for row in &rows {
        assert_eq!(row[8], "–", "{row:?}");
        let floor: f64 = row[5].parse().unwrap();
        let following: f64 = row[6].parse().unwrap();
        assert!(following >= floor, "{row:?}");
    }
}

#[test]
fn the_flow_noise_floor_is_zero_in_still_fluid_and_grows_with_the_poses_age() {
    let now = floors(&["--frame-period-ms", "100"]);
    let late = floors(&["--frame-period-ms", "100", "--camera-latency-ms", "100"]);
    assert_eq!(now.len(), 6, "{now:?}");
    for ((condition, floor), (_, later)) in now.iter().zip(&late) {
        if condition.ends_with("static") {
            assert_eq!(*floor, 0.0, "{condition}");
            assert_eq!(*later, 0.0, "{condition}");
        } else {
            assert!(
                *floor > 0.0 && *later > 2.0 * floor,
                "{condition}: {floor} → {later}"
            );
        }
    }
    // Noise twice as strong (and nothing else changed) raises every flow cell's floor.
    let louder = floors(&[
        "--frame-period-ms",
        "100",
        "--set",
        "plant.physics.flow_noise.fraction=0.2",
    ]);
    for ((condition, floor), (_, loud)) in now.iter().zip(&louder) {
        if !condition.ends_with("static") {
            assert!(*loud > 1.2 * floor, "{condition}: {floor} → {loud}");
        }
    }
}

/// The pump's stroke, known exactly, under a force held over each frame: nothing in still
/// fluid, something at the paper's 10 Hz, next to nothing at 100 Hz, and the same whatever
/// the camera's latency (the hold is the loop's, not the poses').
#[test]
fn the_pulsation_held_per_frame_has_a_floor_of_the_loop_rate_alone() {
    let column = |args: &[&str]| -> Vec<(String, f64)> {
        table("scenarios/paper.toml", args)
            .into_iter()
            .map(|cells| (cells[1].clone(), cells[7].parse().expect("a floor in mm")))
            .collect()
    };
    let ten = column(&["--frame-period-ms", "100"]);
    let ten_late = column(&["--frame-period-ms", "100", "--camera-latency-ms", "100"]);
    let hundred = column(&[]);
    let still_pump = column(&[
        "--frame-period-ms",
        "100",
        "--set",
        "plant.physics.pulsation_amplitude=0.0",
    ]);
    assert_eq!(ten.len(), 6, "{ten:?}");
    for (i, (condition, at_10_hz)) in ten.iter().enumerate() {
        assert_eq!(*at_10_hz, ten_late[i].1, "{condition}");
        assert_eq!(still_pump[i].1, 0.0, "{condition}");
        if condition.ends_with("static") {
            assert_eq!(*at_10_hz, 0.0, "{condition}");
        } else {
            assert!(
                *at_10_hz > 0.0 && hundred[i].1 < at_10_hz / 10.0,
                "{condition}: {at_10_hz} at 10 Hz, {} at 100 Hz",
                hundred[i].1
            );
        }
    }
}

/// A camera ten times slower than the 100 Hz loop gives the poses of the 10 Hz loop, one every
/// 100 ms, aged the same at the coils: the same floor. A camera period that is not a whole
/// number of frames is refused, naming the flag.
#[test]
fn a_camera_slower_than_the_loop_has_the_floor_of_its_own_rate() {
    let camera = floors(&["--camera-period-ms", "100"]);
    let loop_10hz = floors(&["--frame-period-ms", "100"]);
    let loop_100hz = floors(&[]);
    assert_eq!(camera.len(), 6, "{camera:?}");
    for (((condition, slow), (_, ten)), (_, hundred)) in
        camera.iter().zip(&loop_10hz).zip(&loop_100hz)
    {
        assert!((slow - ten).abs() <= 1e-3, "{condition}: {slow} vs {ten}");
        if !condition.ends_with("static") {
            assert!(slow > &(2.0 * hundred), "{condition}: {slow} vs {hundred}");
        }
    }
    let output = Command::new(env!("CARGO_BIN_EXE_experiments"))
        .current_dir(fieldmaps::data_root())
        .args(["--noise-floor", "--camera-period-ms", "15"])
        .output()
        .expect("experiments runs");
    assert!(!output.status.success());
    let said = text(&output);
    assert!(
        said.contains("--camera-period-ms") && said.contains("whole multiple"),
        "{said}"
    );
}
