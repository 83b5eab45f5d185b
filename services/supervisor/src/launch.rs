//! Launch files: which processes make up the set, in start order.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use shm_schemas::ServiceId;

use crate::realtime::Realtime;

#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    #[error("cannot read launch file {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("launch file {path} is not valid: {message}")]
    Invalid { path: PathBuf, message: String },
    #[error("executable for {name} not found at {path} (build with `cargo build --release`)")]
    MissingExecutable { name: String, path: PathBuf },
}

/// One process of the set.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProcessSpec {
    /// Service name: plant, camera, vision, flow, control or coilbus.
    pub name: String,
    /// Executable; defaults to `millinav-<name>` next to the supervisor's own executable.
    #[serde(default)]
    pub binary: Option<PathBuf>,
    /// Extra arguments after `--scenario <file>`.
    #[serde(default)]
    pub args: Vec<String>,
    /// Restart the process when it dies (default true).
    #[serde(default = "yes")]
    pub restart: bool,
    /// Scheduling priority, CPU affinity and memory locking (`[process.realtime]`).
    #[serde(default)]
    pub realtime: Realtime,
    /// Longest this process may take from its start to its first heartbeat (loading maps and
    /// models on a cold, loaded machine); default `[restart] startup_budget_ms`.
    #[serde(default)]
    pub startup_budget_ms: Option<u64>,
}

fn yes() -> bool {
    true
}

impl ProcessSpec {
    /// Its start-up budget: its own, else the launch file's.
    pub fn startup_budget(&self, policy: &RestartPolicy) -> std::time::Duration {
        std::time::Duration::from_millis(self.startup_budget_ms.unwrap_or(policy.startup_budget_ms))
    }

    /// The executable: `binary` (relative to `bin_dir` unless absolute), else
    /// `<bin_dir>/millinav-<name>`.
    pub fn executable(&self, bin_dir: &Path) -> PathBuf {
        match &self.binary {
            Some(b) if b.is_absolute() => b.clone(),
            Some(b) => bin_dir.join(b),
            None => bin_dir.join(format!("millinav-{}", self.name)),
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RestartPolicy {
    /// First restart delay; doubles on each consecutive failure.
    pub initial_backoff_ms: u64,
    pub max_backoff_ms: u64,
    /// A process alive this long resets its backoff.
    pub stable_after_ms: u64,
    /// Longest a process may take from its start to its first heartbeat. Until that heartbeat
    /// the process is starting, not hung: it is never killed for silence, and a start that
    /// outlasts the budget stops the set safe with the reason.
    pub startup_budget_ms: u64,
    /// A restart storm: this many failures of one process within `storm_window_ms` stop the
    /// set safe (restarting it again will not help) and say why.
    pub storm_restarts: u32,
    pub storm_window_ms: u64,
}

impl Default for RestartPolicy {
    fn default() -> Self {
        Self {
            initial_backoff_ms: 100,
            max_backoff_ms: 5000,
            stable_after_ms: 5000,
            startup_budget_ms: 120_000,
            storm_restarts: 5,
            storm_window_ms: 60_000,
        }
    }
}

/// A parsed launch file.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaunchFile {
    /// Processes in start order; shutdown runs in reverse, control and coilbus first.
    #[serde(rename = "process")]
    pub processes: Vec<ProcessSpec>,
    #[serde(default)]
    pub restart: RestartPolicy,
}

impl Default for LaunchFile {
    fn default() -> Self {
        let process = |name: &str| ProcessSpec {
            name: name.into(),
            binary: None,
            args: Vec::new(),
            restart: true,
            realtime: Realtime::default(),
            startup_budget_ms: None,
        };
        Self {
            processes: ["plant", "camera", "coilbus", "flow", "vision", "control"]
                .into_iter()
                .map(process)
                .collect(),
            restart: RestartPolicy::default(),
        }
    }
}

impl LaunchFile {
    pub fn load(path: &Path) -> Result<Self, LaunchError> {
        let text = std::fs::read_to_string(path).map_err(|source| LaunchError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(&text, path)
    }

    pub fn parse(text: &str, path: &Path) -> Result<Self, LaunchError> {
        let invalid = |message: String| LaunchError::Invalid {
            path: path.to_owned(),
            message,
        };
        let launch: LaunchFile = toml::from_str(text).map_err(|e| invalid(e.to_string()))?;
        if launch.processes.is_empty() {
            return Err(invalid("no [[process]] entries".into()));
        }
        let mut seen = Vec::new();
        for p in &launch.processes {
            match ServiceId::from_name(&p.name) {
                Some(ServiceId::Supervisor) | None => {
                    return Err(invalid(format!(
                        "unknown process name {:?} (use plant, vision, flow, control, coilbus)",
                        p.name
                    )))
                }
                Some(id) if seen.contains(&id) => {
                    return Err(invalid(format!("process {:?} listed twice", p.name)))
                }
                Some(id) => seen.push(id),
            }
            p.realtime
                .validate()
                .map_err(|e| invalid(format!("process {:?}: realtime: {e}", p.name)))?;
        }
        if launch.restart.initial_backoff_ms == 0
            || launch.restart.max_backoff_ms < launch.restart.initial_backoff_ms
        {
            return Err(invalid(
                "restart: need 0 < initial_backoff_ms <= max_backoff_ms".into(),
            ));
        }
        if launch.restart.storm_restarts == 0 || launch.restart.storm_window_ms == 0 {
            return Err(invalid(
                "restart: storm_restarts and storm_window_ms must be above 0".into(),
            ));
        }
        let budgets = std::iter::once(("[restart]", Some(launch.restart.startup_budget_ms))).chain(
            launch
                .processes
                .iter()
                .map(|p| (p.name.as_str(), p.startup_budget_ms)),
        );
        for (owner, budget) in budgets {
            if budget == Some(0) {
                return Err(invalid(format!(
                    "{owner}: startup_budget_ms must be above 0"
                )));
            }
        }
        Ok(launch)
    }

    /// Every process's executable, in start order; an error names the first one missing.
    pub fn executables(&self, bin_dir: &Path) -> Result<Vec<PathBuf>, LaunchError> {
        self.processes
            .iter()
            .map(|spec| {
                let path = spec.executable(bin_dir);
                if path.is_file() {
                    Ok(path)
                } else {
                    Err(LaunchError::MissingExecutable {
                        name: spec.name.clone(),
                        path,
                    })
                }
            })
            .collect()
    }

    /// Order in which to stop: control first (no new commands), then coilbus (zeroes the
    /// coils as it exits), then the rest in reverse start order.
    pub fn shutdown_order(&self) -> Vec<ServiceId> {
        let mut order: Vec<ServiceId> = self
            .processes
            .iter()
            .rev()
            .filter_map(|p| ServiceId::from_name(&p.name))
            .collect();
        for first in [ServiceId::Coilbus, ServiceId::Control] {
            if let Some(i) = order.iter().position(|s| *s == first) {
                let id = order.remove(i);
                order.insert(0, id);
            }
        }
        order
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_set_and_shutdown_order() {
        let launch = LaunchFile::default();
        assert_eq!(launch.processes.len(), 6);
        assert_eq!(
            launch.shutdown_order(),
            vec![
                ServiceId::Control,
                ServiceId::Coilbus,
                ServiceId::Vision,
                ServiceId::Flow,
                ServiceId::Camera,
                ServiceId::Plant
            ]
        );
    }

    fn parse_err(text: &str) -> String {
        LaunchFile::parse(text, Path::new("sets/bad.toml"))
            .expect_err("the launch file must be rejected")
            .to_string()
    }

    #[test]
    fn errors_name_the_launch_file() {
        let err = parse_err("[[process]]\nname = \"camera9\"\n");
        assert!(err.contains("sets/bad.toml"), "{err}");
    }

    #[test]
    fn unknown_service_names_are_rejected() {
        let err = parse_err("[[process]]\nname = \"camera9\"\n");
        assert!(err.contains("unknown process name \"camera9\""), "{err}");
        // The supervisor is not a child of itself.
        let err = parse_err("[[process]]\nname = \"supervisor\"\n");
        assert!(err.contains("unknown process name \"supervisor\""), "{err}");
    }

    #[test]
    fn the_realtime_launch_file_parses_and_bad_settings_name_the_process() {
        let path =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenarios/launch/realtime.toml");
        let launch = LaunchFile::load(&path).expect("scenarios/launch/realtime.toml");
        let control = launch
            .processes
            .iter()
            .find(|p| p.name == "control")
            .unwrap();
        assert_eq!(control.realtime.fifo_priority, Some(70));
        assert!(control.realtime.lock_memory);
        let plant = launch.processes.iter().find(|p| p.name == "plant").unwrap();
        assert!(!plant.realtime.is_set());
        let err = parse_err("[[process]]\nname = \"vision\"\nrealtime = { fifo_priority = 120 }\n");
        assert!(err.contains("\"vision\"") && err.contains("1-99"), "{err}");
        let err = parse_err("[[process]]\nname = \"control\"\nrealtime = { priority = 5 }\n");
        assert!(
            err.contains("unknown field") && err.contains("priority"),
            "{err}"
        );
    }

    #[test]
    fn duplicate_process_names_are_rejected() {
        let err = parse_err("[[process]]\nname = \"plant\"\n[[process]]\nname = \"plant\"\n");
        assert!(err.contains("\"plant\" listed twice"), "{err}");
    }

    #[test]
    fn unknown_keys_are_rejected_wherever_they_are() {
        let err = parse_err("[[process]]\nnme = \"plant\"\n");
        assert!(err.contains("nme"), "{err}");
        let err = parse_err("[[process]]\nname = \"plant\"\n[restrat]\ninitial_backoff_ms = 1\n");
        assert!(err.contains("restrat"), "{err}");
        let err = parse_err(
            "[[process]]\nname = \"plant\"\n[restart]\ninitial_backof_ms = 100\n\
             max_backoff_ms = 200\nstable_after_ms = 1\nstartup_budget_ms = 1\n",
        );
        assert!(err.contains("initial_backof_ms"), "{err}");
    }

    #[test]
    fn a_set_needs_at_least_one_process() {
        assert!(parse_err("").contains("process"));
        let err = parse_err("process = []\n");
        assert!(err.contains("no [[process]] entries"), "{err}");
    }

    #[test]
    fn restart_settings_are_checked() {
        let policy = |initial: u64, max: u64| {
            format!(
                "[[process]]\nname = \"plant\"\n[restart]\ninitial_backoff_ms = {initial}\n\
                 max_backoff_ms = {max}\nstable_after_ms = 5000\nstartup_budget_ms = 3000\n"
            )
        };
        assert!(parse_err(&policy(0, 100)).contains("0 < initial_backoff_ms"));
        assert!(parse_err(&policy(200, 100)).contains("initial_backoff_ms <= max_backoff_ms"));
        let ok = LaunchFile::parse(&policy(100, 100), Path::new("ok.toml")).expect("valid");
        assert_eq!(ok.restart.max_backoff_ms, 100);
        // A key left out of [restart] keeps its default.
        let partial = "[[process]]\nname = \"plant\"\n[restart]\ninitial_backoff_ms = 100\n";
        let partial = LaunchFile::parse(partial, Path::new("ok.toml")).expect("valid");
        assert_eq!(partial.restart.initial_backoff_ms, 100);
        assert_eq!(
            partial.restart.startup_budget_ms,
            RestartPolicy::default().startup_budget_ms
        );
        // A budget or a storm of zero would stop every set at once: refused, named.
        let err = parse_err("[[process]]\nname = \"plant\"\n[restart]\nstartup_budget_ms = 0\n");
        assert!(err.contains("[restart]: startup_budget_ms"), "{err}");
        let err = parse_err("[[process]]\nname = \"plant\"\nstartup_budget_ms = 0\n");
        assert!(err.contains("plant: startup_budget_ms"), "{err}");
        let err = parse_err("[[process]]\nname = \"plant\"\n[restart]\nstorm_restarts = 0\n");
        assert!(err.contains("storm_restarts"), "{err}");
        let own = "[[process]]\nname = \"vision\"\nstartup_budget_ms = 900000\n";
        let own = LaunchFile::parse(own, Path::new("ok.toml")).expect("valid");
        assert_eq!(
            own.processes[0].startup_budget(&own.restart),
            std::time::Duration::from_secs(900)
        );
        // The per-process restart switch is a boolean, not a policy name.
        let err = parse_err("[[process]]\nname = \"plant\"\nrestart = \"always\"\n");
        assert!(err.contains("restart"), "{err}");
    }

    #[test]
    fn an_unreadable_launch_file_is_named() {
        let err = LaunchFile::load(Path::new("/nonexistent/set.toml"))
            .expect_err("no such file")
            .to_string();
        assert!(err.contains("/nonexistent/set.toml"), "{err}");
    }

    #[test]
    fn the_default_set_survives_a_round_trip_through_toml() {
        let text = toml::to_string(&LaunchFile::default()).expect("serialize");
        let back = LaunchFile::parse(&text, Path::new("default.toml")).expect("parse");
        let names: Vec<&str> = back.processes.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(
            names,
            ["plant", "camera", "coilbus", "flow", "vision", "control"]
        );
        assert!(back
            .processes
            .iter()
            .all(|p| p.restart && p.args.is_empty()));
    }

    #[test]
    fn control_and_coilbus_stop_first_in_any_start_order() {
        let launch = LaunchFile::parse(
            "[[process]]\nname = \"coilbus\"\n[[process]]\nname = \"plant\"\n\
             [[process]]\nname = \"control\"\n[[process]]\nname = \"vision\"\n",
            Path::new("l.toml"),
        )
        .expect("valid");
        assert_eq!(
            launch.shutdown_order(),
            vec![
                ServiceId::Control,
                ServiceId::Coilbus,
                ServiceId::Vision,
                ServiceId::Plant
            ]
        );
    }

    #[test]
    fn executables_resolve_against_the_bin_dir_and_missing_ones_are_named() {
        let dir = std::env::temp_dir().join(format!("launch-bins-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("sub")).expect("dir");
        std::fs::write(dir.join("millinav-plant"), "").expect("plant");
        std::fs::write(dir.join("sub/my-vision"), "").expect("vision");
        let launch = LaunchFile::parse(
            "[[process]]\nname = \"plant\"\n[[process]]\nname = \"vision\"\nbinary = \"sub/my-vision\"\n",
            Path::new("l.toml"),
        )
        .expect("valid");
        assert_eq!(
            launch.executables(&dir).expect("both exist"),
            vec![dir.join("millinav-plant"), dir.join("sub/my-vision")]
        );
        let absolute = ProcessSpec {
            name: "flow".into(),
            binary: Some("/usr/bin/env".into()),
            args: Vec::new(),
            restart: true,
            realtime: Realtime::default(),
            startup_budget_ms: None,
        };
        assert_eq!(absolute.executable(&dir), PathBuf::from("/usr/bin/env"));
        std::fs::remove_file(dir.join("sub/my-vision")).expect("remove");
        let err = launch
            .executables(&dir)
            .expect_err("vision is gone")
            .to_string();
        assert!(
            err.contains("vision") && err.contains("sub/my-vision"),
            "{err}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
