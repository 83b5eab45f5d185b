//! The campaign path on this machine, through the command line: a matrix planned into --out,
//! its cells run into result files, `collect` writing the tables; a lost result found by
//! `status`, run again by `resume` and collected into the same table; `run-cell` in a process of
//! its own giving the same result as the in-process run; and the inputs refused before anything
//! runs or is submitted.

mod common;
use common::{short_static_cells, text, without_wall_time};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn experiments(args: &[&str], path_env: Option<&str>) -> Output {
    let mut command = Command::new(env!("CARGO_BIN_EXE_experiments"));
    command.current_dir(fieldmaps::data_root()).args(args);
    if let Some(path) = path_env {
        command.env("PATH", path);
    }
    command.output().expect("experiments runs")
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("mx-campaign-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// Two seeds of PID in the short scenario's still fluid, without recordings, on 2 threads.
fn matrix() -> Vec<&'static str> {
    [
        &short_static_cells("pid", "2")[..],
        &["--no-rrd", "--threads=2"],
    ]
    .concat()
}

fn run_matrix(out: &Path, extra: &[&str]) -> Output {
    let out = out.to_string_lossy().into_owned();
    experiments(&[&matrix()[..], &["--out", &out], extra].concat(), None)
}

#[test]
fn every_trace_keeps_each_runs_truth_beyond_position() {
    let out = scratch("traces");
    let run = run_matrix(&out, &["--every-trace"]);
    assert!(run.status.success(), "{}", text(&run));
    for seed in ["s1", "s2"] {
        let path = out.join(format!("campaign/traces/20cp_static_pid_{seed}.csv"));
        let trace = millinav_experiments::read_truth(&path).expect("trace");
        // The capsule moves along the route, its magnet along the 45° orientation field.
        assert!(
            trace.iter().any(|r| r.motion.velocity_mps.norm() > 1e-5),
            "{seed}"
        );
        let heading = trace.last().unwrap().motion.heading_rad;
        assert!(
            (heading - std::f64::consts::FRAC_PI_4).abs() < 0.1,
            "{seed}: heading {heading}"
        );
    }
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn a_local_campaign_resumes_a_lost_cell_into_the_same_table() {
    let out = scratch("resume");
    let dir = out.to_string_lossy().into_owned();
    let first = run_matrix(&out, &[]);
    assert!(first.status.success(), "{}", text(&first));
    let table = std::fs::read_to_string(out.join("table.md")).unwrap();
    let csv = std::fs::read_to_string(out.join("results.csv")).unwrap();
    assert!(
        table.contains("| 20 cP, static | pid | 2 | 2/2 |"),
        "{table}"
    );

    // A lost result: collect and status name the cell; resume runs that cell alone.
    std::fs::remove_file(out.join("campaign/results/20cp_static_pid_s2.toml")).unwrap();
    let collect = experiments(&["collect", &dir], None);
    assert!(!collect.status.success());
    assert!(
        String::from_utf8_lossy(&collect.stderr).contains("20cp_static_pid_s2"),
        "{}",
        text(&collect)
    );
    let status = experiments(&["status", &dir], None);
    assert_eq!(status.status.code(), Some(1), "{}", text(&status));
    assert!(String::from_utf8_lossy(&status.stderr).contains("20cp_static_pid_s2: not run"));
    let resume = experiments(&["resume", &dir], None);
    assert!(resume.status.success(), "{}", text(&resume));
    let resumed = String::from_utf8_lossy(&resume.stdout);
    assert!(resumed.contains("20cp_static_pid_s2") && !resumed.contains("20cp_static_pid_s1 ("));
    assert_eq!(
        std::fs::read_to_string(out.join("table.md")).unwrap(),
        table
    );

    // The same command again keeps the finished cells.
    let again = run_matrix(&out, &[]);
    assert!(again.status.success(), "{}", text(&again));
    assert!(
        String::from_utf8_lossy(&again.stdout).contains("2 of 2 cells already have results"),
        "{}",
        text(&again)
    );

    // run-cell in its own process writes the result the in-process run wrote.
    let result = out.join("campaign/results/20cp_static_pid_s1.toml");
    let metrics = |text: &str| text[text.find("[metrics]").unwrap()..].to_owned();
    let before = metrics(&std::fs::read_to_string(&result).unwrap());
    let cell = experiments(
        &[
            "run-cell",
            "--campaign",
            &dir,
            "--cell",
            "20cp_static_pid_s1",
        ],
        None,
    );
    assert!(cell.status.success(), "{}", text(&cell));
    let after = std::fs::read_to_string(&result).unwrap();
    // The metrics and the trace summary; wall_s and the times stand before them.
    assert_eq!(metrics(&after), before);
    let collect = experiments(&["collect", &dir], None);
    assert!(collect.status.success(), "{}", text(&collect));
    assert_eq!(
        std::fs::read_to_string(out.join("table.md")).unwrap(),
        table
    );
    assert_eq!(
        without_wall_time(&std::fs::read_to_string(out.join("results.csv")).unwrap()),
        without_wall_time(&csv)
    );
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn another_matrix_or_build_and_a_missing_sbatch_are_refused_before_anything_runs() {
    let out = scratch("refuse");
    let dir = out.to_string_lossy().into_owned();
    let first = run_matrix(&out, &[]);
    assert!(first.status.success(), "{}", text(&first));

    // Another matrix into the same directory.
    let other = experiments(
        &[
            &short_static_cells("mpc", "1")[..],
            &["--no-rrd", "--out", &dir],
        ]
        .concat(),
        None,
    );
    assert_eq!(other.status.code(), Some(2), "{}", text(&other));
    let stderr = String::from_utf8_lossy(&other.stderr);
    assert!(
        stderr.contains("another matrix") && stderr.contains("--fresh"),
        "{}",
        text(&other)
    );

    // Another build: the campaign says one of its data files had other contents.
    let manifest_path = out.join("campaign/manifest.toml");
    let manifest = std::fs::read_to_string(&manifest_path).unwrap();
    let mut doc: toml::Table = toml::from_str(&manifest).unwrap();
    let build = doc["build"].as_table_mut().unwrap();
    build.insert("sha256".into(), "0".repeat(64).into());
    let files = build["files"].as_array_mut().unwrap();
    let file = files
        .iter_mut()
        .find(|f| f["path"].as_str().unwrap().ends_with("paper.toml"))
        .expect("the rig file is hashed");
    file.as_table_mut()
        .unwrap()
        .insert("sha256".into(), "1".repeat(64).into());
    std::fs::write(&manifest_path, toml::to_string(&doc).unwrap()).unwrap();
    let rebuilt = run_matrix(&out, &[]);
    assert_eq!(rebuilt.status.code(), Some(2), "{}", text(&rebuilt));
    let stderr = String::from_utf8_lossy(&rebuilt.stderr);
    assert!(
        stderr.contains("another build") && stderr.contains("fieldmaps/rigs/paper.toml (changed)"),
        "{}",
        text(&rebuilt)
    );
    // resume and run-cell check the build too.
    let resume = experiments(&["resume", &dir], None);
    assert!(!resume.status.success());
    assert!(String::from_utf8_lossy(&resume.stderr).contains("changed since the campaign"));
    // --fresh starts over.
    let fresh = run_matrix(&out, &["--fresh"]);
    assert!(fresh.status.success(), "{}", text(&fresh));

    // The Slurm backend without sbatch on PATH: a clear error, and no campaign planned.
    let nowhere = scratch("nosbatch");
    let no_sbatch = experiments(
        &[
            &matrix()[..],
            &["--out", &nowhere.to_string_lossy(), "--backend", "slurm"],
        ]
        .concat(),
        Some("/nonexistent"),
    );
    assert_eq!(no_sbatch.status.code(), Some(2), "{}", text(&no_sbatch));
    assert!(
        String::from_utf8_lossy(&no_sbatch.stderr).contains("sbatch is not on PATH"),
        "{}",
        text(&no_sbatch)
    );
    assert!(!nowhere.exists());
    // Slurm settings that sbatch would refuse, and Slurm flags without the Slurm backend.
    let bad_time = run_matrix(&nowhere, &["--backend", "slurm", "--time", "1h"]);
    assert!(String::from_utf8_lossy(&bad_time.stderr).contains("\"1h\" is not a Slurm time limit"));
    let stray = run_matrix(&nowhere, &["--partition", "gpu"]);
    assert!(String::from_utf8_lossy(&stray.stderr).contains("go with --backend slurm"));
    assert!(!nowhere.exists());
    let _ = std::fs::remove_dir_all(&out);
}
