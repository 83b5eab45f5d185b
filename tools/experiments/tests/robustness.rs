//! The robustness matrix through the command line, for one controller and one seed: every
//! axis and level at both loop rates becomes a row of robustness.md and robustness.csv, and the
//! heat map is a PNG.

use std::process::Command;

#[test]
fn the_robustness_matrix_reports_every_case() {
    let root = fieldmaps::data_root();
    let out = std::env::temp_dir().join(format!("millinav-robust-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let output = Command::new(env!("CARGO_BIN_EXE_experiments"))
        .current_dir(&root)
        .args([
            "--robustness",
            // The short path: every case must become a row, which needs no long run.
            "--base",
            "scenarios/short.toml",
            "--controllers",
            "smc-dob-auto",
            "--trials",
            "1",
            "--out",
        ])
        .arg(&out)
        .output()
        .expect("experiments runs");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let rig = fieldmaps::rigfile::Rig::load_paper().expect("paper rig");
    let around = millinav_experiments::robustness::Around::on_rig(&rig).expect("a flow condition");
    let expected = millinav_experiments::robustness::cases(&["smc-dob-auto".into()], 1, &around);
    let csv = std::fs::read_to_string(out.join("robustness.csv")).expect("robustness.csv");
    assert_eq!(csv.lines().count(), expected.len() + 1, "{csv}");
    let table = std::fs::read_to_string(out.join("robustness.md")).expect("robustness.md");
    let rows = table
        .lines()
        .filter(|l| l.starts_with("| ") && l.contains(" Hz |"));
    assert_eq!(rows.count(), expected.len(), "{table}");
    // The nominal twin at 100 Hz, as in the matrix: the scheduled SMC-DOB completes.
    assert!(
        table.contains("| pulsation Hz | 3 | 100 Hz | smc-dob-auto | 1/1 |"),
        "{table}"
    );
    // Each row's flow noise floor (the capsule's / a flow follower's): older poses and more
    // noise raise it, and it is the same for every setting the noise does not see.
    let floor = |axis: &str, level: &str, hz: &str| -> (f64, f64) {
        let prefix = format!("| {axis} | {level} | {hz} Hz | smc-dob-auto |");
        let row = table
            .lines()
            .find(|l| l.starts_with(&prefix))
            .unwrap_or_else(|| panic!("no row {prefix} in {table}"));
        let cell = row.trim_end_matches('|').rsplit('|').next().unwrap().trim();
        let (capsule, follower) = cell.split_once(" / ").expect("capsule / follower");
        (capsule.parse().unwrap(), follower.parse().unwrap())
    };
    assert!(floor("camera latency ms", "100", "100").0 > floor("camera latency ms", "50", "100").0);
    assert!(floor("camera latency ms", "50", "100").0 > floor("camera latency ms", "0", "100").0);
    for hz in ["10", "100"] {
        let nominal = floor("camera latency ms", "0", hz);
        assert!(nominal.0 > 0.0 && nominal.1 >= nominal.0, "{nominal:?}");
        assert!(floor("camera latency ms", "100", hz).0 > nominal.0);
        assert!(floor("flow noise", "0.2", hz).0 > nominal.0);
        assert_eq!(floor("pulsation Hz", "1", hz), nominal);
        assert_eq!(floor("coil gain error", "0.1", hz), nominal);
    }
    assert!(floor("camera latency ms", "0", "10").0 > floor("camera latency ms", "0", "100").0);
    if millinav_experiments::report::register_font() {
        let png = std::fs::read(out.join("robustness.png")).expect("robustness.png");
        assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    } else {
        // Without a font the figure is skipped, and said so.
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(stderr.contains("heat map skipped"), "{stderr}");
    }
    let _ = std::fs::remove_dir_all(&out);
}
