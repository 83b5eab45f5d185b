//! `fieldgen rig-check` on the committed paper rig and on a broken copy of it.
use std::path::Path;
use std::process::Command;

fn fieldgen(rig: &Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_fieldgen"))
        .args(["rig-check", "--rig"])
        .arg(rig)
        .output()
        .unwrap()
}

/// `fieldgen rig-check <args> --rig <committed rig>` passes and prints every one of `needles`.
fn checks_out(rig_file: &str, args: &[&str], needles: &[&str]) {
    let rig = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fieldmaps/rigs")
        .join(rig_file);
    let out = Command::new(env!("CARGO_BIN_EXE_fieldgen"))
        .arg("rig-check")
        .args(args)
        .arg("--rig")
        .arg(&rig)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for needle in needles {
        assert!(stdout.contains(needle), "{needle} missing from\n{stdout}");
    }
}

#[test]
fn paper_rig_checks_out() {
    checks_out(
        "paper.toml",
        &[],
        &[
            "coils: 12",
            "allocation: 8 coils",
            "camera: 1020x1020 px",
            "inlet-1",
            "zone",
            "flow conditions: 4",
            "force budget at 1.000 mT, control's default for this magnet,",
            "force budget at 5 mT",
            "rig ok",
        ],
    );
}

#[test]
fn bad_rig_names_file_and_field() {
    let paper = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fieldmaps/rigs/paper.toml");
    let text =
        std::fs::read_to_string(&paper)
            .unwrap()
            .replacen("turns = 191.788", "turns = 0.0", 1);
    // Next to paper.toml would let its relative paths resolve, but the tests must not write
    // into the source tree; the coil error comes before any data file is opened.
    let dir = std::env::temp_dir().join(format!("millinav-rig-check-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let bad = dir.join("bad.toml");
    std::fs::write(&bad, text).unwrap();
    let out = fieldgen(&bad);
    std::fs::remove_dir_all(&dir).ok();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains(&format!("{}: coils[1].turns: must be > 0", bad.display())),
        "{stderr}"
    );
}

#[test]
fn vessel8_rig_checks_out_with_its_force_budget() {
    // The second rig: nothing in the code knows it. Its coils must push the capsule with at
    // least 0.2 mN in every direction at the route's ends while holding a 5 mT field.
    checks_out(
        "vessel8.toml",
        &["--field-mt", "5", "--min-force-mn", "0.2"],
        &[
            "coils: 8",
            "allocation: 8 coils",
            "camera: 800x640 px Rgb8",
            "branch-outlet",
            "flow conditions: 3",
            "force budget at 5 mT",
            // The paper's aligning torque over vessel8's 5.61e-3 A·m² magnet.
            "force budget at 0.153 mT, control's default for this magnet,",
            "rig ok",
        ],
    );
}

#[test]
fn an_empty_field_list_skips_the_force_budget_and_a_bad_one_is_named() {
    let rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fieldmaps/rigs/paper.toml");
    let run = |field: &str| {
        Command::new(env!("CARGO_BIN_EXE_fieldgen"))
            .args(["rig-check", field, "--rig"])
            .arg(&rig)
            .output()
            .unwrap()
    };
    let out = run("--field-mt=");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("rig ok"), "{stdout}");
    assert!(!stdout.contains("force budget"), "{stdout}");
    let out = run("--field-mt=1,x");
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("\"x\" is not a field magnitude"),
        "{stderr}"
    );
}

/// The paper rig written to `dir` with its data paths absolute, one flow map at `flow_map`.
fn paper_copy(dir: &Path, flow_map: &Path) -> std::path::PathBuf {
    let rigs = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fieldmaps/rigs")
        .canonicalize()
        .unwrap();
    let rigs = rigs.display();
    let text = std::fs::read_to_string(format!("{rigs}/paper.toml"))
        .unwrap()
        .replace("dir = \"../", &format!("dir = \"{rigs}/../"))
        .replace("\"paper/", &format!("\"{rigs}/paper/"))
        .replacen(
            "\"../flow/q180_mu20.flow.csv\"",
            &format!("{flow_map:?}"),
            1,
        )
        .replace("\"../flow/", &format!("\"{rigs}/../flow/"));
    std::fs::create_dir_all(dir).unwrap();
    let path = dir.join("rig.toml");
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn a_rig_whose_flow_maps_are_not_made_yet_checks_out_and_says_so() {
    let dir = std::env::temp_dir().join(format!("millinav-rig-check-flow-{}", std::process::id()));
    let missing = dir.join("not-made-yet.flow.csv");
    let out = fieldgen(&paper_copy(&dir, &missing));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("rig ok, except its flow maps"), "{stdout}");
    assert!(stdout.contains("millinav maps cfd --all --rig"), "{stdout}");
    // A map that is there but wrong is refused like any other error.
    std::fs::write(&missing, "not a flow map\n").unwrap();
    let out = fieldgen(&paper_copy(&dir, &missing));
    let stderr = String::from_utf8_lossy(&out.stderr);
    std::fs::remove_dir_all(&dir).ok();
    assert!(!out.status.success());
    assert!(stderr.contains("is not a valid flow map"), "{stderr}");
}
