//! The supervisor binary with fake children (shell scripts named in a launch file): a failing
//! `--check` starts nothing, a child exiting with code 78 stops the set, any other exit is
//! restarted with backoff until the failures make a restart storm, and a child that does not
//! start within its budget stops the set (none of them ever beats).

use std::os::unix::fs::PermissionsExt;
use std::path::PathBuf;
use std::process::{Command, Output, Stdio};

const EXIT_CONFIG: i32 = 78;

const SCENARIO: &str =
    "[run]\nmode = \"lockstep\"\nseed = 1\nduration_s = 1.0\nframe_period_ms = 10.0\nrig = \"fieldmaps/rigs/paper.toml\"\n\n\
[fluid]\nviscosity_cp = 20.0\n\n\
[trajectory]\nwaypoints_mm = [[-18.0, 12.0], [-12.0, 8.0]]\nspeed_mm_s = 2.0\nstart_time_s = 0.5\n";

struct Bench {
    name: String,
    dir: PathBuf,
    children: Vec<(String, PathBuf)>,
    /// The launch file's `[restart]` table.
    restart: String,
    /// More keys of one process's `[[process]]` table.
    process_keys: Vec<(String, String)>,
}

impl Bench {
    fn new(name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("sv-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("dir");
        std::fs::write(dir.join("scenario.toml"), SCENARIO).expect("scenario");
        Self {
            name: name.into(),
            dir,
            children: Vec::new(),
            process_keys: Vec::new(),
            restart:
                "[restart]\ninitial_backoff_ms = 50\nmax_backoff_ms = 200\nstable_after_ms = 5000\n\
                      startup_budget_ms = 30000\nstorm_restarts = 1000\n"
                    .into(),
        }
    }

    /// More keys in `process`'s `[[process]]` table.
    fn keys(mut self, process: &str, keys: &str) -> Self {
        self.process_keys.push((process.into(), keys.into()));
        self
    }

    /// Another `[restart]` table for the launch file.
    fn restart(mut self, table: &str) -> Self {
        self.restart = format!("[restart]\n{table}");
        self
    }

    /// A fake service: `on_check` runs for `--check`, `on_run` otherwise. Every start leaves a
    /// line in `<dir>/<name>.starts`.
    fn child(mut self, name: &str, on_check: &str, on_run: &str) -> Self {
        let script = self.dir.join(format!("fake-{name}"));
        let starts = self.dir.join(format!("{name}.starts"));
        std::fs::write(
            &script,
            format!(
                "#!/bin/sh\nif [ \"$1\" = --check ]; then\n{on_check}\nfi\necho started >> {}\n{on_run}\n",
                starts.display()
            ),
        )
        .expect("script");
        std::fs::set_permissions(&script, std::fs::Permissions::from_mode(0o755)).expect("chmod");
        self.children.push((name.into(), script));
        self
    }

    fn starts(&self, name: &str) -> usize {
        std::fs::read_to_string(self.dir.join(format!("{name}.starts")))
            .map(|t| t.lines().count())
            .unwrap_or(0)
    }

    fn run_dir(&self) -> PathBuf {
        self.dir.join("run")
    }

    /// `millinav run` on the fake set; returns its output once it exits.
    fn run(&self, max_wall_s: f64) -> Output {
        let mut launch = self.restart.clone();
        for (name, script) in &self.children {
            launch += &format!(
                "[[process]]\nname = \"{name}\"\nbinary = \"{}\"\n",
                script.display()
            );
            for (_, keys) in self.process_keys.iter().filter(|(p, _)| p == name) {
                launch += keys;
            }
        }
        let launch_path = self.dir.join("launch.toml");
        std::fs::write(&launch_path, launch).expect("launch");
        Command::new(env!("CARGO_BIN_EXE_millinav"))
            .arg("run")
            .arg(self.dir.join("scenario.toml"))
            .arg("--launch")
            .arg(&launch_path)
            .arg("--run-dir")
            .arg(self.run_dir())
            .args(["--viewer", "none", "--max-wall-s", &max_wall_s.to_string()])
            .arg("--iox-prefix")
            .arg(format!(
                "sv{}-{}_",
                std::process::id(),
                self.name.replace(|c: char| !c.is_ascii_alphanumeric(), "-")
            ))
            .arg("--iox-root")
            .arg(self.dir.join("iox"))
            .env("MILLINAV_RERUN", "off")
            .stdin(Stdio::null())
            .output()
            .expect("run millinav")
    }

    fn events(&self) -> String {
        std::fs::read_to_string(self.run_dir().join("supervisor_events.csv")).unwrap_or_default()
    }
}

impl Drop for Bench {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

#[test]
fn a_failing_check_starts_nothing_and_names_every_failure() {
    let bench = Bench::new("check")
        .child("plant", "exit 0", "exec sleep 30")
        .child(
            "control",
            "echo 'scenario.toml: [control]: unknown field `controler`' >&2; exit 78",
            "exec sleep 30",
        )
        .child(
            "flow",
            "echo 'flow.csv: line 3: bad number' >&2; exit 78",
            "exec sleep 30",
        );
    let output = bench.run(30.0);
    let console = stderr(&output);
    assert_eq!(output.status.code(), Some(EXIT_CONFIG), "{console}");
    assert!(console.contains("nothing was started"), "{console}");
    assert!(console.contains("unknown field `controler`"), "{console}");
    assert!(
        console.contains("flow.csv: line 3: bad number"),
        "{console}"
    );
    assert!(
        !console.contains("plant ("),
        "plant passed its check:\n{console}"
    );
    for name in ["plant", "control", "flow"] {
        assert_eq!(bench.starts(name), 0, "{name} was started");
    }
    assert!(!bench.run_dir().join("pids").exists());
}

#[test]
fn a_child_exiting_with_a_configuration_error_stops_the_set() {
    let bench = Bench::new("runtime")
        .child("plant", "exit 0", "exec sleep 30")
        .child(
            "coilbus",
            "exit 0",
            "sleep 0.3; echo 'cannot open /dev/ttyACM7: [coilbus] port' >&2; exit 78",
        );
    let output = bench.run(30.0);
    let console = stderr(&output);
    assert_eq!(output.status.code(), Some(EXIT_CONFIG), "{console}");
    assert!(
        console.contains("coilbus exited with a configuration error"),
        "{console}"
    );
    assert!(
        console.contains("cannot open /dev/ttyACM7: [coilbus] port"),
        "{console}"
    );
    // Not restarted; the rest of the set was stopped in order.
    assert_eq!(bench.starts("coilbus"), 1);
    let events = bench.events();
    assert!(events.contains("coilbus,config_error"), "{events}");
    assert!(!events.contains("coilbus,restart"), "{events}");
    assert!(events.contains("plant,stopped"), "{events}");
    assert!(!events.contains("wall_time_limit"), "{events}");
}

#[test]
fn any_other_exit_is_restarted_with_backoff() {
    let bench = Bench::new("restart")
        .child("plant", "exit 0", "exec sleep 30")
        .child("vision", "exit 0", "exit 1");
    let output = bench.run(1.5);
    let console = stderr(&output);
    // The wall-time limit ends the run; that is not an error.
    assert!(output.status.success(), "{console}");
    let events = bench.events();
    assert!(events.contains("vision,restart,incarnation=2"), "{events}");
    assert!(bench.starts("vision") >= 3, "{events}");
    assert!(events.contains("wall_time_limit"), "{events}");
}

#[test]
fn a_child_that_keeps_failing_stops_the_set_as_a_restart_storm() {
    let bench = Bench::new("storm")
        .restart("initial_backoff_ms = 50\nmax_backoff_ms = 100\nstorm_restarts = 3\nstorm_window_ms = 60000\n")
        .child("plant", "exit 0", "exec sleep 30")
        .child("vision", "exit 0", "echo 'vision: cannot open the model' >&2; exit 1");
    let started = std::time::Instant::now();
    let output = bench.run(30.0);
    let console = stderr(&output);
    assert_eq!(output.status.code(), Some(1), "{console}");
    assert!(
        console.contains("vision failed 3 times within 60 s (a restart storm)"),
        "{console}"
    );
    assert!(console.contains("cannot open the model"), "{console}");
    assert!(started.elapsed().as_secs_f64() < 10.0, "{console}");
    assert_eq!(bench.starts("vision"), 3);
    let events = bench.events();
    assert!(
        events.contains("vision,restart_storm,failures=3"),
        "{events}"
    );
    assert!(events.contains("plant,stopped"), "{events}");
    let summary = std::fs::read_to_string(bench.run_dir().join("summary.json")).unwrap_or_default();
    assert!(summary.contains("restart storm"), "{summary}");
}

#[test]
fn a_start_over_its_budget_stops_the_set_and_says_why() {
    let bench = Bench::new("budget")
        .restart("startup_budget_ms = 60000\nstorm_restarts = 1000\n")
        .child("plant", "exit 0", "exec sleep 30")
        .child(
            "vision",
            "exit 0",
            "echo 'loading the model' >&2; exec sleep 30",
        )
        // Vision gets a budget of its own, shorter than the file's.
        .keys("vision", "startup_budget_ms = 1500\n");
    let output = bench.run(30.0);
    let console = stderr(&output);
    assert_eq!(output.status.code(), Some(1), "{console}");
    assert!(
        console.contains(
            "vision did not finish starting (no heartbeat) within its start-up budget of 2 s"
        ),
        "{console}"
    );
    assert!(console.contains("loading the model"), "{console}");
    let events = bench.events();
    assert!(events.contains("vision,startup_over_budget"), "{events}");
    assert!(!events.contains("heartbeat_missed"), "{events}");
    assert!(!events.contains(",restart,"), "{events}");
    // The plant, with the file's minute, was never taken for hung in the meantime.
    assert_eq!(bench.starts("plant"), 1);
}
