//! Scenario files: one TOML file describes a whole run (mode, seed, fluid, flow, trajectory) and
//! carries one table per service (`[plant]`, `[vision]`, `[flow]`, `[control]`, `[coilbus]`)
//! that the service parses into its own config type.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use crate::config::{ConfigContext, ConfigError};
use fieldmaps::rigfile::Rig;

#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    #[error("cannot read scenario {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("scenario {path} is not valid: {message}")]
    Invalid { path: PathBuf, message: String },
}

impl From<ScenarioError> for ConfigError {
    fn from(error: ScenarioError) -> Self {
        Self::new(error.to_string())
    }
}

/// How the plant advances time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum ClockMode {
    /// The plant is the clock: frame k+1 only after the command for frame k (or a deadline miss).
    #[default]
    Lockstep,
    /// The plant steps on the wall clock; latest command wins.
    Realtime,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunSection {
    #[serde(default)]
    pub mode: ClockMode,
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// Run length in run-clock seconds; the plant ends the run after it.
    pub duration_s: f64,
    /// Camera frame period.
    #[serde(default = "default_frame_period_ms")]
    pub frame_period_ms: f64,
    /// Rig file the run uses (see [`Scenario::rig_path`]); required (empty only while
    /// [`Scenario::parse`] reports it missing).
    #[serde(default)]
    pub rig: PathBuf,
}

fn default_seed() -> u64 {
    1
}
fn default_frame_period_ms() -> f64 {
    10.0
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FluidSection {
    pub viscosity_cp: f64,
    #[serde(default = "default_density")]
    pub density_kg_m3: f64,
}

fn default_density() -> f64 {
    fieldmaps::rig::FluidParams::GLYCERIN_WATER_DENSITY
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrajectorySection {
    /// Waypoints in mm (user-facing); the reference moves along them at constant speed.
    pub waypoints_mm: Vec<[f64; 2]>,
    #[serde(default = "default_speed")]
    pub speed_mm_s: f64,
    /// Run-clock time at which the reference leaves the first waypoint.
    #[serde(default)]
    pub start_time_s: f64,
}

fn default_speed() -> f64 {
    0.5
}

/// A parsed scenario file.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Scenario {
    pub run: RunSection,
    pub fluid: FluidSection,
    pub trajectory: TrajectorySection,
    /// Service-specific tables, parsed by each service.
    #[serde(flatten)]
    pub sections: toml::Table,
    #[serde(skip)]
    pub path: PathBuf,
}

/// The services' own tables of a scenario (besides run, fluid and trajectory).
pub const KNOWN_SECTIONS: [&str; 7] = [
    "plant",
    "camera",
    "vision",
    "flow",
    "control",
    "coilbus",
    "supervisor",
];

impl Scenario {
    pub fn load(path: &Path) -> Result<Self, ScenarioError> {
        let text = std::fs::read_to_string(path).map_err(|source| ScenarioError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(&text, path)
    }

    pub fn parse(text: &str, path: &Path) -> Result<Self, ScenarioError> {
        let invalid = |message: String| ScenarioError::Invalid {
            path: path.to_owned(),
            message,
        };
        let mut scenario: Scenario = toml::from_str(text).map_err(|e| invalid(e.to_string()))?;
        scenario.path = path.to_owned();
        for key in scenario.sections.keys() {
            if !KNOWN_SECTIONS.contains(&key.as_str()) {
                return Err(invalid(format!(
                    "unknown section [{key}] (known: run, fluid, trajectory, {})",
                    KNOWN_SECTIONS.join(", ")
                )));
            }
        }
        let run = &scenario.run;
        if run.rig.as_os_str().is_empty() {
            return Err(invalid(
                "run.rig is missing: a scenario names the rig file it runs on, e.g. \
                 rig = \"fieldmaps/rigs/paper.toml\" (relative to the repository root or to \
                 the scenario)"
                    .into(),
            ));
        }
        if !(run.duration_s.is_finite() && run.duration_s > 0.0) {
            return Err(invalid(format!(
                "run.duration_s must be > 0, got {}",
                run.duration_s
            )));
        }
        if !(run.frame_period_ms.is_finite() && (1.0..=1000.0).contains(&run.frame_period_ms)) {
            return Err(invalid(format!(
                "run.frame_period_ms must be within 1..1000, got {}",
                run.frame_period_ms
            )));
        }
        let fluid = &scenario.fluid;
        if !(fluid.viscosity_cp.is_finite() && fluid.viscosity_cp > 0.0) {
            return Err(invalid(format!(
                "fluid.viscosity_cp must be > 0, got {}",
                fluid.viscosity_cp
            )));
        }
        let traj = &scenario.trajectory;
        if traj.waypoints_mm.len() < 2 {
            return Err(invalid(
                "trajectory.waypoints_mm needs at least 2 points".into(),
            ));
        }
        if traj.waypoints_mm.iter().flatten().any(|v| !v.is_finite()) {
            return Err(invalid(
                "trajectory.waypoints_mm holds a non-finite value".into(),
            ));
        }
        if !(traj.speed_mm_s.is_finite() && traj.speed_mm_s > 0.0) {
            return Err(invalid(format!(
                "trajectory.speed_mm_s must be > 0, got {}",
                traj.speed_mm_s
            )));
        }
        Ok(scenario)
    }

    /// Parses the service's own table (or its defaults when the table is absent).
    pub fn section<T: DeserializeOwned + Default>(&self, name: &str) -> Result<T, ScenarioError> {
        match self.sections.get(name) {
            None => Ok(T::default()),
            Some(value) => {
                value
                    .clone()
                    .try_into()
                    .map_err(|e: toml::de::Error| ScenarioError::Invalid {
                        path: self.path.clone(),
                        message: format!("[{name}]: {e}"),
                    })
            }
        }
    }

    pub fn viscosity_pa_s(&self) -> f64 {
        self.fluid.viscosity_cp * 1e-3
    }

    pub fn frame_period_s(&self) -> f64 {
        self.run.frame_period_ms * 1e-3
    }

    /// Waypoints in metres.
    pub fn waypoints_m(&self) -> Vec<[f64; 2]> {
        self.trajectory
            .waypoints_mm
            .iter()
            .map(|p| [p[0] * 1e-3, p[1] * 1e-3])
            .collect()
    }

    /// The rig file this scenario runs on, `[run] rig`: absolute as is, else relative to the
    /// repository root (`fieldmaps::data_root`, like other committed data) when it exists
    /// there, else relative to the scenario file.
    pub fn rig_path(&self) -> PathBuf {
        let rig = &self.run.rig;
        if rig.is_absolute() {
            return rig.clone();
        }
        let from_root = fieldmaps::data_root().join(rig);
        if from_root.exists() {
            return from_root;
        }
        self.resolve(rig)
    }

    /// The scenario's rig ([`Self::rig_path`]), loaded and validated. Cached per path for the
    /// life of the process, so in-process runs (experiments, tests) load each rig once.
    pub fn rig(&self) -> Result<Arc<Rig>, ConfigError> {
        type Cache = Mutex<HashMap<PathBuf, Arc<Rig>>>;
        static CACHE: OnceLock<Cache> = OnceLock::new();
        let path = self.rig_path();
        let cache = CACHE.get_or_init(Default::default);
        if let Some(rig) = cache.lock().ok().and_then(|c| c.get(&path).cloned()) {
            return Ok(rig);
        }
        let rig = Rig::load(&path)
            .map(Arc::new)
            .config_context(format!("scenario {}: [run] rig", self.path.display()))?;
        if let Ok(mut c) = cache.lock() {
            c.insert(path, rig.clone());
        }
        Ok(rig)
    }

    /// Resolves a path written in the scenario relative to the scenario file's directory.
    pub fn resolve(&self, relative: &Path) -> PathBuf {
        if relative.is_absolute() {
            return relative.to_owned();
        }
        self.path
            .parent()
            .map(|dir| dir.join(relative))
            .unwrap_or_else(|| relative.to_owned())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = r#"
[run]
duration_s = 5.0
rig = "fieldmaps/rigs/paper.toml"
[fluid]
viscosity_cp = 20.0
[trajectory]
waypoints_mm = [[0.0, 0.0], [5.0, 0.0]]
[control]
controller = "pid"
"#;

    #[test]
    fn parses_and_exposes_sections() {
        let s = Scenario::parse(GOOD, Path::new("x.toml")).unwrap();
        assert_eq!(s.run.mode, ClockMode::Lockstep);
        assert_eq!(s.run.frame_period_ms, 10.0);
        assert!((s.viscosity_pa_s() - 0.02).abs() < 1e-12);
        #[derive(Deserialize, Default)]
        struct C {
            controller: String,
        }
        let c: C = s.section("control").unwrap();
        assert_eq!(c.controller, "pid");
    }

    #[test]
    fn a_scenario_names_its_rig_which_resolves_like_committed_data() {
        let s = Scenario::parse(GOOD, Path::new("/somewhere/x.toml")).unwrap();
        let paper = s.rig_path();
        assert!(
            paper.ends_with("fieldmaps/rigs/paper.toml"),
            "{}",
            paper.display()
        );
        assert!(paper.is_file(), "{}", paper.display());

        // Not in the repository: next to the scenario.
        let own = GOOD.replace(
            "rig = \"fieldmaps/rigs/paper.toml\"",
            "rig = \"rigs/mine.toml\"",
        );
        let s = Scenario::parse(&own, Path::new("/somewhere/x.toml")).unwrap();
        assert_eq!(s.rig_path(), Path::new("/somewhere/rigs/mine.toml"));

        let absolute = GOOD.replace(
            "rig = \"fieldmaps/rigs/paper.toml\"",
            "rig = \"/labs/r.toml\"",
        );
        let s = Scenario::parse(&absolute, Path::new("x.toml")).unwrap();
        assert_eq!(s.rig_path(), Path::new("/labs/r.toml"));

        // None: refused, naming the key, not the paper's rig in silence.
        let none = GOOD.replace("rig = \"fieldmaps/rigs/paper.toml\"\n", "");
        let err = Scenario::parse(&none, Path::new("x.toml")).unwrap_err();
        assert!(err.to_string().contains("run.rig is missing"), "{err}");
    }

    #[test]
    fn rejects_bad_scenarios_with_clear_messages() {
        let typo = GOOD.replace("[control]", "[contrl]");
        let err = Scenario::parse(&typo, Path::new("x.toml")).unwrap_err();
        assert!(
            err.to_string().contains("unknown section [contrl]"),
            "{err}"
        );

        let nan = GOOD.replace("duration_s = 5.0", "duration_s = nan");
        let err = Scenario::parse(&nan, Path::new("x.toml")).unwrap_err();
        assert!(err.to_string().contains("duration_s"), "{err}");

        let one_point = GOOD.replace("[[0.0, 0.0], [5.0, 0.0]]", "[[0.0, 0.0]]");
        assert!(Scenario::parse(&one_point, Path::new("x.toml")).is_err());

        let missing = GOOD.replace("[fluid]\nviscosity_cp = 20.0", "");
        let err = Scenario::parse(&missing, Path::new("x.toml")).unwrap_err();
        assert!(err.to_string().contains("fluid"), "{err}");
    }
}
