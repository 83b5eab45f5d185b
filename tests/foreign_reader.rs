//! The contract is readable from outside Rust: a Python script using only `ctypes` and the PyPI
//! `iceoryx2==0.10.0` package (`tests/foreign_reader.py`, structures written from
//! `shm_schemas/CONTRACT.md`) subscribes to the Pose and CoilCommand services of a live lockstep
//! run in the run's own iceoryx2 namespace, and what it decodes agrees with what the run wrote
//! (the twin's truth.csv, the emulated Teensy's event log).

use std::collections::HashMap;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use fieldmaps::rigfile::Rig;
use millinav_tests::{scenario_text, venv_dir, RunSet};
use nalgebra::Vector2;
use serde_json::Value;

/// Vision's centroid error on the twin is a few hundredths of a mm; 1 mm only catches a
/// misdecoded field (wrong offset, wrong unit), not localisation noise.
const POSE_TOLERANCE_M: f64 = 1e-3;

fn python() -> std::path::PathBuf {
    venv_dir().join("bin").join("python")
}

fn reader_script() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("foreign_reader.py")
}

fn f64s(value: &Value) -> Vec<f64> {
    value
        .as_array()
        .expect("an array")
        .iter()
        .map(|v| v.as_f64().expect("a number"))
        .collect()
}

fn u64_at(value: &Value, path: &[&str]) -> u64 {
    let mut v = value;
    for key in path {
        v = &v[*key];
    }
    v.as_u64()
        .unwrap_or_else(|| panic!("{path:?} is not an integer in {value}"))
}

/// Frames in order: each seq newer than the one before, except frame 0, which the lockstep
/// plant re-publishes until the whole chain has answered it once.
fn in_frame_order(seqs: &[u64]) -> bool {
    seqs.windows(2)
        .all(|w| w[0] < w[1] || (w[0] == 0 && w[1] == 0))
}

#[test]
fn a_python_ctypes_reader_decodes_poses_and_commands_of_a_live_run() {
    let probe = Command::new(python())
        .args(["-c", "import iceoryx2"])
        .output()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", python().display()));
    assert!(
        probe.status.success(),
        "the project venv lacks the iceoryx2 Python package (pip install iceoryx2==0.10.0, \
         scripts/setup.sh): {}",
        String::from_utf8_lossy(&probe.stderr)
    );

    let text = scenario_text(
        4.0,
        &[[-18.0, 12.0], [-12.0, 8.0]],
        2.0,
        "[control]\ncontroller = \"pid\"\n",
    );
    let mut run = RunSet::start("foreignreader", &text).expect("start run");
    let out = run.run_dir.join("foreign_reader.json");
    let log = std::fs::File::create(run.run_dir.join("foreign_reader.log")).expect("log");
    let mut reader = Command::new(python())
        .arg(reader_script())
        .arg("--prefix")
        .arg(&run.iox_prefix)
        .arg("--root")
        .arg(&run.iox_root)
        .arg("--out")
        .arg(&out)
        .args(["--seconds", "150", "--idle-seconds", "3"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .expect("start the Python reader");
    let status = run.wait(Duration::from_secs(150)).expect("run finishes");
    assert!(status.success(), "supervisor exit status {status}");
    let deadline = Instant::now() + Duration::from_secs(30);
    let reader_status = loop {
        if let Some(status) = reader.try_wait().expect("reader status") {
            break status;
        }
        if Instant::now() > deadline {
            let _ = reader.kill();
            panic!("the Python reader did not stop after the run ended");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let reader_log =
        std::fs::read_to_string(run.run_dir.join("foreign_reader.log")).unwrap_or_default();
    assert!(
        reader_status.success(),
        "Python reader failed: {reader_log}"
    );
    let decoded: Value =
        serde_json::from_str(&std::fs::read_to_string(&out).expect("reader output"))
            .expect("reader JSON");
    let poses = decoded["poses"].as_array().expect("poses");
    let commands = decoded["commands"].as_array().expect("commands");
    let truth = run.truth().expect("truth.csv");
    eprintln!(
        "foreign reader decoded {} poses and {} commands of {} frames",
        poses.len(),
        commands.len(),
        truth.len()
    );
    // The reader polls; a slow moment may cost a few overwritten samples, not most of them.
    assert!(poses.len() * 2 >= truth.len(), "{} poses", poses.len());
    assert!(
        commands.len() * 2 >= truth.len(),
        "{} commands",
        commands.len()
    );

    // Poses: frames in order, flags 0/1, valid positions in the canal and where the twin was.
    let truth_at: HashMap<u64, Vector2<f64>> =
        truth.iter().map(|r| (r.frame_seq, r.position_m)).collect();
    let rig = Rig::load_paper().unwrap();
    let canal = &rig.phantom.mask;
    let pose_seqs: Vec<u64> = poses.iter().map(|p| u64_at(p, &["stamp", "seq"])).collect();
    assert!(in_frame_order(&pose_seqs), "pose seqs {pose_seqs:?}");
    let pose_times: Vec<u64> = poses
        .iter()
        .map(|p| u64_at(p, &["stamp", "capture_time_ns"]))
        .collect();
    assert!(
        pose_seqs
            .windows(2)
            .zip(pose_times.windows(2))
            .all(|(s, t)| t[0] < t[1] || (s[0] == s[1] && t[0] == t[1])),
        "capture times do not follow the frames"
    );
    let mut valid = 0;
    let mut compared = 0;
    let mut worst_m: f64 = 0.0;
    for pose in poses {
        let flag = u64_at(pose, &["valid"]);
        assert!(flag <= 1, "valid flag byte {flag}");
        assert!([1, 2].contains(&u64_at(pose, &["source"])), "source {pose}");
        if flag == 0 {
            continue;
        }
        valid += 1;
        let p = f64s(&pose["position_m"]);
        let p = Vector2::new(p[0], p[1]);
        assert!(p.x.is_finite() && p.y.is_finite());
        assert!(canal.contains(&p), "valid pose {p:?} outside the canal");
        let heading = pose["heading_rad"].as_f64().expect("heading");
        assert!(heading.is_finite());
        if let Some(t) = truth_at.get(&u64_at(pose, &["stamp", "seq"])) {
            compared += 1;
            worst_m = worst_m.max((p - t).norm());
        }
    }
    assert!(
        valid * 10 >= poses.len() * 9,
        "{valid} of {} poses valid",
        poses.len()
    );
    assert!(
        compared * 2 >= valid,
        "only {compared} poses matched a truth row"
    );
    eprintln!("worst decoded pose vs truth: {:.4} mm", worst_m * 1e3);
    assert!(worst_m <= POSE_TOLERANCE_M, "pose {worst_m} m from truth");

    // Commands: one per pose, every coil of the rig, finite currents within each coil's limit.
    let command_seqs: Vec<u64> = commands
        .iter()
        .map(|c| u64_at(c, &["stamp", "seq"]))
        .collect();
    assert!(
        in_frame_order(&command_seqs),
        "command seqs {command_seqs:?}"
    );
    let pose_time_of: HashMap<u64, u64> = pose_seqs.iter().copied().zip(pose_times).collect();
    let mut tracking = 0;
    let mut command_max: HashMap<u64, f64> = HashMap::new();
    for command in commands {
        assert_eq!(u64_at(command, &["active_coils"]) as usize, rig.coils.len());
        let currents = f64s(&command["currents_a"]);
        assert_eq!(currents.len(), rig.coils.len());
        assert!(
            currents
                .iter()
                .zip(&rig.coils)
                .all(|(c, coil)| c.is_finite() && c.abs() <= coil.max_current_a + 1e-9),
            "currents {currents:?}"
        );
        assert!(f64s(&command["inactive_currents_a"])
            .iter()
            .all(|c| *c == 0.0));
        let mode = u64_at(command, &["mode"]);
        assert!((1..=3).contains(&mode), "mode {mode}");
        if mode == 1 {
            tracking += 1;
        }
        assert_eq!(u64_at(command, &["controller_id"]), 1, "PID");
        let seq = u64_at(command, &["stamp", "seq"]);
        if let Some(t) = pose_time_of.get(&seq) {
            assert_eq!(
                u64_at(command, &["stamp", "capture_time_ns"]),
                *t,
                "the command of frame {seq} carries another stamp than its pose"
            );
        }
        command_max.insert(seq, currents.iter().fold(0.0, |m, c| m.max(c.abs())));
    }
    assert!(
        tracking * 10 >= commands.len() * 8,
        "{tracking} tracking commands"
    );

    // What the emulated Teensy applied for a frame is what the decoded command asked for (up to
    // the wire's 1 mA resolution; coilbus may only ever lower it by clamping).
    let events = run.teensy_events().expect("teensy events");
    let mut matched = 0;
    let mut agree = 0;
    for event in events.iter().filter(|e| e.kind == "command") {
        let Some(seq) = event.frame_seq else { continue };
        let Some(asked) = command_max.get(&seq) else {
            continue;
        };
        matched += 1;
        assert!(event.max_abs_current_a <= asked + 1e-3, "frame {seq}");
        if (event.max_abs_current_a - asked).abs() <= 1e-3 {
            agree += 1;
        }
    }
    assert!(matched * 2 >= commands.len(), "{matched} commands matched");
    assert!(agree * 10 >= matched * 9, "{agree} of {matched} agree");
}
