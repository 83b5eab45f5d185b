//! The experiments tool on the second committed rig, through its command line: the matrix comes
//! from the rig's own flow conditions, cells run on its maps, and the table names the rig.

use std::process::Command;

#[test]
fn experiments_run_a_cell_of_the_second_rigs_matrix() {
    let root = fieldmaps::data_root();
    let out = std::env::temp_dir().join(format!("millinav-exp8-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let status = Command::new(env!("CARGO_BIN_EXE_experiments"))
        .current_dir(&root)
        .args([
            "--base",
            "scenarios/vessel8.toml",
            "--controllers",
            "mpc",
            "--only",
            "4.3cp_q120",
            "--trials",
            "1",
            "--no-rrd",
            "--out",
        ])
        .arg(&out)
        .status()
        .expect("experiments runs");
    assert!(status.success(), "experiments exit {status}");
    let table = std::fs::read_to_string(out.join("table.md")).expect("table.md");
    assert!(table.contains("rig vessel8"), "{table}");
    assert!(
        table.contains("| 4.3 cP, 120 mL/min | mpc | 1 | 1/1 |"),
        "{table}"
    );
    let csv = std::fs::read_to_string(out.join("results.csv")).expect("results.csv");
    assert_eq!(csv.lines().count(), 2, "{csv}");
    // A condition the rig does not have selects nothing: a clear error, not an empty table.
    let refused = Command::new(env!("CARGO_BIN_EXE_experiments"))
        .current_dir(&root)
        .args([
            "--base",
            "scenarios/vessel8.toml",
            "--only",
            "20cp_q180",
            "--out",
        ])
        .arg(&out)
        .output()
        .expect("experiments runs");
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("no cell of the matrix"), "{stderr}");
    let _ = std::fs::remove_dir_all(&out);
}
