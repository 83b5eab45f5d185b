//! `planner --scenario-template T -o OUT`: the written scenario runs as long as its new path
//! needs, and the template's flow map is still found from where OUT is written.

use std::path::{Path, PathBuf};
use std::process::Command;

use millinav_kit::scenario::Scenario;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("planner-template-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn a_short_template_is_lengthened_and_its_flow_map_re_based() {
    let base = scratch("rebase");
    let (lab, runs) = (base.join("lab"), base.join("runs/today"));
    std::fs::create_dir_all(lab.join("maps")).unwrap();
    std::fs::create_dir_all(&runs).unwrap();
    std::fs::write(lab.join("maps/q180.npz"), b"stand-in").unwrap();
    let template = lab.join("template.toml");
    std::fs::write(
        &template,
        "[run]\nduration_s = 5.0\nrig = \"fieldmaps/rigs/paper.toml\"\n\
         [fluid]\nviscosity_cp = 20.0\n\
         [trajectory]\nwaypoints_mm = [[0.0, 0.0], [1.0, 0.0]]\nspeed_mm_s = 1.0\n\
         [flow]\nmap = \"maps/q180.npz\"\n",
    )
    .unwrap();
    let out = runs.join("planned.toml");
    let run = Command::new(env!("CARGO_BIN_EXE_planner"))
        .current_dir(root())
        .args(["--rig", "fieldmaps/rigs/paper.toml", "--scenario-template"])
        .arg(&template)
        .arg("-o")
        .arg(&out)
        .output()
        .expect("planner runs");
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");

    let scenario = Scenario::load(&out).expect("the written scenario parses");
    let points = &scenario.trajectory.waypoints_mm;
    let length_mm: f64 = points
        .windows(2)
        .map(|w| (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]))
        .sum();
    assert!(
        length_mm > 50.0,
        "the paper's route is long: {length_mm} mm"
    );
    let travel_s = length_mm / scenario.trajectory.speed_mm_s;
    assert!(
        scenario.run.duration_s >= travel_s + 5.0,
        "duration {} s for {travel_s:.1} s of travel",
        scenario.run.duration_s
    );
    assert!(stderr.contains("duration_s 5 s"), "{stderr}");

    let map = scenario.sections["flow"]["map"].as_str().unwrap();
    assert!(Path::new(map).is_relative(), "{map}");
    assert_eq!(
        std::fs::read(scenario.resolve(Path::new(map))).unwrap(),
        b"stand-in",
        "{map} from {}",
        runs.display()
    );
    assert!(stderr.contains("[flow] map maps/q180.npz"), "{stderr}");
    // The rig, named from the repository root, works from anywhere: it stays as given.
    assert_eq!(scenario.run.rig, Path::new("fieldmaps/rigs/paper.toml"));

    // Written beside the template, nothing needs re-basing.
    let beside = lab.join("beside.toml");
    let run = Command::new(env!("CARGO_BIN_EXE_planner"))
        .current_dir(root())
        .args(["--rig", "fieldmaps/rigs/paper.toml", "--scenario-template"])
        .arg(&template)
        .arg("-o")
        .arg(&beside)
        .output()
        .expect("planner runs");
    assert!(run.status.success());
    let scenario = Scenario::load(&beside).unwrap();
    assert_eq!(
        scenario.sections["flow"]["map"].as_str(),
        Some("maps/q180.npz")
    );
    let _ = std::fs::remove_dir_all(&base);
}
