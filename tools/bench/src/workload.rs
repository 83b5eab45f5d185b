//! What the workloads run on: a scenario's rig, trajectory, fluid and frame period (the bench's
//! `--scenario`; the criterion benches use `scenarios/short.toml`).

use std::path::Path;
use std::sync::Arc;

use fieldmaps::rigfile::Rig;
use millinav_control::reference::Reference;
use millinav_kit::scenario::Scenario;

use crate::BenchError;

/// A loaded scenario, ready for the workloads.
pub struct Workload {
    /// The scenario's rig.
    pub rig: Arc<Rig>,
    /// Its trajectory.
    pub reference: Reference,
    /// Its fluid's viscosity, Pa·s.
    pub viscosity_pa_s: f64,
    /// Its frame period, s.
    pub period_s: f64,
}

impl Workload {
    /// The scenario at `path` (relative paths from the workspace root).
    pub fn load(path: &Path) -> Result<Self, BenchError> {
        let path = crate::workspace_root().join(path);
        let setup =
            |e: &dyn std::fmt::Display| BenchError::Setup(format!("{}: {e}", path.display()));
        let scenario = Scenario::load(&path).map_err(|e| setup(&e))?;
        let rig = scenario.rig().map_err(|e| setup(&e))?;
        let t = &scenario.trajectory;
        let reference =
            Reference::new(&scenario.waypoints_m(), t.speed_mm_s * 1e-3, t.start_time_s)
                .map_err(|e| setup(&e))?;
        Ok(Self {
            rig,
            reference,
            viscosity_pa_s: scenario.viscosity_pa_s(),
            period_s: scenario.frame_period_s(),
        })
    }

    /// The workspace's short scenario (`scenarios/short.toml`).
    pub fn short() -> Result<Self, BenchError> {
        Self::load(Path::new("scenarios/short.toml"))
    }
}
