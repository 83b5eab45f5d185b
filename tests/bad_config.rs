//! Fail fast on bad configuration, through the real `millinav run`: a typo in any service's
//! scenario table, or a flow map it cannot read, stops the supervisor before any process
//! starts, with exit code 78 and the file and field named on its console.

use std::path::Path;
use std::time::Duration;

use millinav_tests::{scenario_text, RunSet};

/// `EX_CONFIG`, the exit code of every configuration error.
const EXIT_CONFIG: i32 = 78;
/// Upper bound on waiting for the supervisor: a set that started anyway would instead run until
/// its wall cap (300 s in the harness), restarting the failing child.
const GIVE_UP_AFTER: Duration = Duration::from_secs(60);

/// Runs `extra` (scenario tables) and checks the run was refused with `expected` on the console.
fn refused(name: &str, extra: &str, expected: &[&str]) {
    let text = scenario_text(2.0, &[[-18.0, 12.0], [-12.0, 8.0]], 2.0, extra);
    refused_text(name, &text, expected);
}

/// Runs the scenario `text` and checks the run was refused with `expected` on the console.
fn refused_text(name: &str, text: &str, expected: &[&str]) {
    let mut run = RunSet::start(name, text).expect("start millinav run");
    let status = run.wait(GIVE_UP_AFTER).expect("the supervisor exits");
    let console = run.supervisor_console().expect("console");
    assert_eq!(
        status.code(),
        Some(EXIT_CONFIG),
        "exit status {status}; console:\n{console}"
    );
    for needle in expected {
        assert!(
            console.contains(needle),
            "console does not mention {needle:?}:\n{console}"
        );
    }
    assert_eq!(
        run.spawned(),
        Vec::<String>::new(),
        "no process may start on a bad configuration"
    );
    assert!(
        !run.run_dir.join("pids").exists(),
        "a child was started (pid files exist)"
    );
}

#[test]
fn a_typo_in_control_is_refused() {
    refused(
        "badcontrol",
        "[control]\ncontroler = \"pid\"\n",
        &["scenario.toml", "controler"],
    );
}

#[test]
fn a_typo_in_flow_is_refused() {
    refused(
        "badflow",
        "[flow]\nmapp = \"flow.csv\"\n",
        &["scenario.toml", "mapp"],
    );
}

#[test]
fn a_typo_in_vision_is_refused() {
    refused(
        "badvision",
        "[vision]\nlocaliser = \"classical\"\n",
        &["scenario.toml", "localiser"],
    );
}

#[test]
fn a_typo_in_coilbus_is_refused() {
    refused(
        "badcoilbus",
        "[coilbus]\nbauds = 9600\n",
        &["scenario.toml", "bauds"],
    );
}

#[test]
fn a_typo_in_plant_is_refused() {
    refused(
        "badplant",
        "[plant]\ncamera_noise = 2.0\n",
        &["scenario.toml", "camera_noise"],
    );
}

/// A map file outside the run's directory (RunSet recreates that directory when it starts).
fn map_file(name: &str, contents: Option<&str>) -> std::path::PathBuf {
    let path = std::env::temp_dir().join(format!("millinav-badmap-{}-{name}", std::process::id()));
    let _ = std::fs::remove_file(&path);
    if let Some(contents) = contents {
        std::fs::write(&path, contents).expect("write map");
    }
    path
}

fn flow_map_table(path: &Path) -> String {
    format!("[flow]\nmap = \"{}\"\n", path.display())
}

#[test]
fn a_corrupt_flow_map_is_refused() {
    let map = map_file("corrupt.csv", Some("this is not a flow map\n1,2\n"));
    let file_name = map.file_name().and_then(|n| n.to_str()).expect("name");
    refused("corruptmap", &flow_map_table(&map), &[file_name]);
    let _ = std::fs::remove_file(&map);
}

#[test]
fn a_missing_flow_map_is_refused() {
    let map = map_file("missing.csv", None);
    let file_name = map.file_name().and_then(|n| n.to_str()).expect("name");
    refused("missingmap", &flow_map_table(&map), &[file_name]);
}

/// The second committed rig with its data paths made absolute, one value replaced, written
/// where a scenario can name it.
fn broken_rig(name: &str, from: &str, to: &str) -> std::path::PathBuf {
    let rigs = fieldmaps::data_root().join("fieldmaps/rigs");
    let text = std::fs::read_to_string(rigs.join("vessel8.toml"))
        .expect("vessel8.toml")
        .replace(
            "\"vessel8/",
            &format!("\"{}/", rigs.join("vessel8").display()),
        );
    assert!(text.contains(from), "vessel8.toml has no {from:?}");
    let path = std::env::temp_dir().join(format!(
        "millinav-badrig-{}-{name}.toml",
        std::process::id()
    ));
    std::fs::write(&path, text.replacen(from, to, 1)).expect("write rig");
    path
}

#[test]
fn a_bad_rig_file_is_refused_before_anything_starts() {
    let rig = broken_rig("zeroturns", "turns = ", "turns = 0.0 # ");
    let text = millinav_tests::vessel8_scenario_text(2.0, false, "").replace(
        "rig = \"fieldmaps/rigs/vessel8.toml\"",
        &format!("rig = {:?}", rig),
    );
    let file = rig
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or_default()
        .to_owned();
    refused_text("badrig", &text, &[&file, "coils[0].turns"]);
    let _ = std::fs::remove_file(&rig);
}
