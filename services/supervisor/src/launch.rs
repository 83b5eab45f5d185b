//! Launch files: which processes make up the set, in start order.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use shm_schemas::ServiceId;

#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    #[error("cannot read launch file {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("launch file {path} is not valid: {message}")]
    Invalid { path: PathBuf, message: String },
}

/// One process of the set.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProcessSpec {
    /// Service name: plant, vision, flow, control or coilbus.
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
}

fn yes() -> bool {
    true
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RestartPolicy {
    /// First restart delay; doubles on each consecutive failure.
    pub initial_backoff_ms: u64,
    pub max_backoff_ms: u64,
    /// A process alive this long resets its backoff.
    pub stable_after_ms: u64,
    /// Heartbeat misses are ignored this long after a (re)start.
    pub startup_grace_ms: u64,
}

impl Default for RestartPolicy {
    fn default() -> Self {
        Self {
            initial_backoff_ms: 100,
            max_backoff_ms: 5000,
            stable_after_ms: 5000,
            startup_grace_ms: 3000,
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
        };
        Self {
            processes: ["plant", "coilbus", "flow", "vision", "control"]
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
        }
        if launch.restart.initial_backoff_ms == 0
            || launch.restart.max_backoff_ms < launch.restart.initial_backoff_ms
        {
            return Err(invalid(
                "restart: need 0 < initial_backoff_ms <= max_backoff_ms".into(),
            ));
        }
        Ok(launch)
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
        assert_eq!(launch.processes.len(), 5);
        assert_eq!(
            launch.shutdown_order(),
            vec![
                ServiceId::Control,
                ServiceId::Coilbus,
                ServiceId::Vision,
                ServiceId::Flow,
                ServiceId::Plant
            ]
        );
    }

    #[test]
    fn bad_launch_files_are_explained() {
        let p = Path::new("l.toml");
        let err = LaunchFile::parse("[[process]]\nname = \"camera9\"\n", p).unwrap_err();
        assert!(err.to_string().contains("unknown process name"), "{err}");
        let err = LaunchFile::parse(
            "[[process]]\nname = \"plant\"\n[[process]]\nname = \"plant\"\n",
            p,
        )
        .unwrap_err();
        assert!(err.to_string().contains("twice"), "{err}");
        let err = LaunchFile::parse("[[process]]\nnme = \"plant\"\n", p).unwrap_err();
        assert!(err.to_string().contains("nme"), "{err}");
        assert!(LaunchFile::parse("", p).is_err());
    }
}
