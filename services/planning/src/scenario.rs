//! A plan written out: a `[trajectory]` block, or a scenario with its trajectory replaced.

use crate::{Plan, PlanError};

/// The `[trajectory]` block for a scenario file.
pub fn trajectory_toml(plan: &Plan, speed_mm_s: Option<f64>) -> String {
    let mut out = String::from("[trajectory]\nwaypoints_mm = [\n");
    for p in plan.waypoints_mm() {
        out.push_str(&format!("    [{:.3}, {:.3}],\n", p[0], p[1]));
    }
    out.push_str("]\n");
    if let Some(v) = speed_mm_s {
        out.push_str(&format!("speed_mm_s = {v}\n"));
    }
    out
}

/// `template` (a scenario's TOML text) with its `[trajectory] waypoints_mm` replaced by the
/// plan's waypoints (and `speed_mm_s` if given); other keys are kept.
pub fn scenario_with_plan(
    template: &str,
    plan: &Plan,
    speed_mm_s: Option<f64>,
    rig: Option<&std::path::Path>,
) -> Result<String, PlanError> {
    let mut doc: toml::Table = toml::from_str(template)
        .map_err(|e| PlanError::Config(format!("scenario template: {e}")))?;
    if let Some(rig) = rig {
        // The plan is on this rig's phantom: the scenario runs on it.
        let run = doc
            .entry("run")
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        let Some(run) = run.as_table_mut() else {
            return Err(PlanError::Config(
                "scenario template: `run` is not a table".into(),
            ));
        };
        run.insert("rig".into(), rig.to_string_lossy().into_owned().into());
    }
    let entry = doc
        .entry("trajectory")
        .or_insert_with(|| toml::Value::Table(toml::Table::new()));
    let Some(traj) = entry.as_table_mut() else {
        return Err(PlanError::Config(
            "scenario template: `trajectory` is not a table".into(),
        ));
    };
    let points = plan
        .waypoints_mm()
        .into_iter()
        .map(|p| toml::Value::Array(vec![p[0].into(), p[1].into()]))
        .collect();
    traj.insert("waypoints_mm".into(), toml::Value::Array(points));
    if let Some(v) = speed_mm_s {
        traj.insert("speed_mm_s".into(), v.into());
    }
    toml::to_string(&doc).map_err(|e| PlanError::Config(format!("cannot write scenario: {e}")))
}
