//! flow: the controller's flow knowledge, as in the paper: a steady CFD map looked up at the
//! robot's estimated position. It never sees the true (pulsatile, perturbed) flow.

use std::path::PathBuf;

use fieldmaps::flowmap::FlowMap;
use fieldmaps::rigfile::{Zone, ZoneKind};
use millinav_kit::contract::ContractViolations;
use millinav_kit::ports::{Inbox, Outbox};
use millinav_kit::recording;
use millinav_kit::rerun;
use millinav_kit::scenario::Scenario;
use millinav_kit::{ConfigContext, ConfigError, Runtime, ServiceLoop};
use nalgebra::Vector2;
use serde::{Deserialize, Serialize};
use shm_schemas::{deadlines, services, zone, Flag, FlowEstimate, Pose};

/// `[flow]` section of a scenario. The zones come from the rig (`[[phantom.zones]]`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FlowConfig {
    /// Steady flow map (relative to the scenario file); none means static fluid.
    pub map: Option<PathBuf>,
    /// Spacing of the arrows logged once to the recording (mm).
    pub arrow_spacing_mm: f64,
}

impl Default for FlowConfig {
    fn default() -> Self {
        Self {
            map: None,
            arrow_spacing_mm: 4.0,
        }
    }
}

/// Looks up the steady map and classifies the zone at a position.
pub struct FlowEstimator {
    pub map: FlowMap,
    pub config: FlowConfig,
    /// The rig's named zones (high disturbance, recirculation).
    pub zones: Vec<Zone>,
}

impl FlowEstimator {
    pub fn new(map: FlowMap, config: FlowConfig, zones: Vec<Zone>) -> Self {
        Self { map, config, zones }
    }

    pub fn estimate(&self, pose: &Pose) -> FlowEstimate {
        let mut estimate = FlowEstimate {
            stamp: pose.stamp,
            ..Default::default()
        };
        // A pose flagged invalid, with a bad flag byte or non-finite numbers gets an invalid
        // estimate (still sent: control waits for the estimate of every pose).
        if !pose.is_usable() {
            return estimate;
        }
        let p = Vector2::new(pose.position_m[0], pose.position_m[1]);
        let v = self.map.sample(&p);
        let moving = self.map.peak_speed() > 0.0;
        let mut flags = 0;
        if !self.map.covers(&p) {
            flags |= zone::OUTSIDE_MAP;
        }
        if moving {
            for z in self.zones.iter().filter(|z| z.contains(&p)) {
                flags |= match z.kind {
                    ZoneKind::HighDisturbance => zone::HIGH_DISTURBANCE,
                    ZoneKind::Recirculation => zone::RECIRCULATION,
                };
            }
        }
        estimate.velocity_mps = [v.x, v.y];
        estimate.speed_mps = v.norm();
        estimate.zone_flags = flags;
        estimate.valid = Flag::TRUE;
        estimate
    }

    /// The field as arrows (mm, mm/s scaled for display), logged once per run.
    pub fn log_field(&self, rec: &rerun::RecordingStream) {
        let step = (self.config.arrow_spacing_mm * 1e-3).max(1e-4);
        let (mut origins, mut vectors) = (Vec::new(), Vec::new());
        let x0 = self.map.origin_m.x;
        let y0 = self.map.origin_m.y;
        let x1 = x0 + (self.map.nx - 1) as f64 * self.map.spacing_m;
        let y1 = y0 + (self.map.ny - 1) as f64 * self.map.spacing_m;
        let mut y = y0;
        while y <= y1 {
            let mut x = x0;
            while x <= x1 {
                let v = self.map.sample(&Vector2::new(x, y));
                if v.norm() > 1e-4 {
                    origins.push([(x * 1e3) as f32, (y * 1e3) as f32]);
                    // 1 cm/s drawn as 1 mm.
                    vectors.push([(v.x * 100.0) as f32, (v.y * 100.0) as f32]);
                }
                x += step;
            }
            y += step;
        }
        let _ = rec.log_static(
            "world/flow_field",
            &rerun::Arrows2D::from_vectors(vectors).with_origins(origins),
        );
    }
}

/// Loads what the `[flow]` table names: its config and the steady map (`FlowMap::zero` when
/// none). Every failure is a configuration error naming the scenario, the field and the file.
pub fn prepare(scenario: &Scenario) -> Result<FlowEstimator, ConfigError> {
    let config: FlowConfig = scenario.section("flow")?;
    let field = |name: &str| format!("scenario {}: [flow] {name}", scenario.path.display());
    if !(config.arrow_spacing_mm.is_finite() && config.arrow_spacing_mm > 0.0) {
        return Err(ConfigError::new(format!(
            "{} must be > 0, got {}",
            field("arrow_spacing_mm"),
            config.arrow_spacing_mm
        )));
    }
    let map = match &config.map {
        None => FlowMap::zero(),
        Some(path) => FlowMap::load(&scenario.resolve(path)).config_context(field("map"))?,
    };
    let rig = scenario.rig()?;
    Ok(FlowEstimator::new(map, config, rig.phantom.zones.clone()))
}

/// Validates the `[flow]` table and the flow map it names (what `--check` runs).
pub fn check_config(scenario: &Scenario) -> Result<(), ConfigError> {
    prepare(scenario).map(drop)
}

pub fn load_estimator(scenario: &Scenario) -> anyhow::Result<FlowEstimator> {
    Ok(prepare(scenario)?)
}

/// The flow process: every pose gets its estimate (control waits for the one matching its
/// pose).
pub fn run(rt: &mut Runtime, _scenario: &Scenario, estimator: FlowEstimator) -> anyhow::Result<()> {
    estimator.log_field(&rt.rec);
    let poses = Inbox::<Pose>::new(&rt.node, services::POSE)?;
    let estimates = Outbox::<FlowEstimate>::new(&rt.node, services::FLOW)?;
    let mut violations = ContractViolations::default();
    let mut service_loop = ServiceLoop::new();
    service_loop.input_with_deadline(&poses, deadlines::POSE);
    service_loop.output(&estimates);
    service_loop.run(&mut rt.heartbeat, |_| {
        for pose in poses.receive_all()? {
            let _ = violations.check(services::POSE, pose.validity());
            let estimate = estimator.estimate(&pose);
            estimates.send(estimate)?;
            if estimate.valid == Flag::TRUE {
                log_estimate(&rt.rec, &pose, &estimate);
            }
        }
        anyhow::Ok(())
    })?;
    Ok(())
}

fn log_estimate(rec: &rerun::RecordingStream, pose: &Pose, estimate: &FlowEstimate) {
    recording::set_time(rec, pose.stamp.capture_time_ns, pose.stamp.seq);
    let _ = rec.log(
        "world/flow_at_robot",
        &rerun::Arrows2D::from_vectors([[
            (estimate.velocity_mps[0] * 100.0) as f32,
            (estimate.velocity_mps[1] * 100.0) as f32,
        ]])
        .with_origins([[
            (pose.position_m[0] * 1e3) as f32,
            (pose.position_m[1] * 1e3) as f32,
        ]]),
    );
    recording::scalar(rec, "flow/speed_mps", estimate.speed_mps);
    recording::scalar(rec, "flow/zone_flags", f64::from(estimate.zone_flags));
}

#[cfg(test)]
mod tests {
    use super::*;
    use millinav_kit::scratch::ScratchDir;

    /// A scenario file in a directory of its own, with `flow_table` as its `[flow]` table.
    fn scenario_with(name: &str, flow_table: &str) -> (Scenario, ScratchDir) {
        let dir = ScratchDir::new(&format!("millinav-flow-{name}")).unwrap();
        let text = format!(
            "[run]\nduration_s = 1.0\nrig = \"fieldmaps/rigs/paper.toml\"\n[fluid]\nviscosity_cp = 20.0\n\
             [trajectory]\nwaypoints_mm = [[0.0, 0.0], [5.0, 0.0]]\n[flow]\n{flow_table}\n"
        );
        let path = dir.join("scenario.toml");
        (Scenario::parse(&text, &path).unwrap(), dir)
    }

    #[test]
    fn check_config_accepts_a_good_table_and_a_good_map() {
        let (scenario, dir) = scenario_with("good", "map = \"steady.txt\"");
        FlowMap::zero().save(&dir.join("steady.txt")).unwrap();
        check_config(&scenario).unwrap();
        let (scenario, _) = scenario_with("none", "arrow_spacing_mm = 2.0");
        check_config(&scenario).unwrap();
    }

    #[test]
    fn check_config_rejects_a_typo_a_missing_and_a_corrupt_map() {
        let (scenario, _) = scenario_with("typo", "mapp = \"steady.txt\"");
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(
            error.contains("[flow]") && error.contains("mapp"),
            "{error}"
        );

        let (scenario, _) = scenario_with("absent", "map = \"absent.txt\"");
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(
            error.contains("[flow] map") && error.contains("absent.txt"),
            "{error}"
        );

        // In the scenario's own directory, where the map's relative path points.
        let (scenario, dir) = scenario_with("corrupt", "map = \"corrupt.txt\"");
        let missing = check_config(&scenario).unwrap_err().to_string();
        std::fs::write(dir.join("corrupt.txt"), "this is not a flow map\n1 2 x\n").unwrap();
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(
            error.contains("[flow] map") && error.contains("corrupt.txt"),
            "{error}"
        );
        assert_ne!(error, missing, "a corrupt map reads as a missing one");

        let (scenario, _) = scenario_with("spacing", "arrow_spacing_mm = 0.0");
        let error = check_config(&scenario).unwrap_err().to_string();
        assert!(error.contains("arrow_spacing_mm"), "{error}");
    }

    #[test]
    fn invalid_pose_gets_invalid_estimate() {
        let est = FlowEstimator::new(FlowMap::zero(), FlowConfig::default(), Vec::new());
        let pose = Pose {
            valid: Flag::TRUE,
            position_m: [f64::NAN, 0.0],
            ..Default::default()
        };
        assert_eq!(est.estimate(&pose).validity(), Ok(false));
        let bad_flag = Pose {
            valid: Flag::from_raw(0x2A),
            ..Default::default()
        };
        assert_eq!(est.estimate(&bad_flag).validity(), Ok(false));
        let ok = Pose {
            valid: Flag::TRUE,
            stamp: shm_schemas::FrameStamp::new(7, 2, 70),
            ..Default::default()
        };
        let e = est.estimate(&ok);
        assert_eq!(e.validity(), Ok(true));
        assert_eq!(e.stamp, ok.stamp);
        assert_eq!(e.zone_flags, 0);
    }

    #[test]
    fn zones_stop_short_of_the_outflow_channel() {
        // A uniform non-zero map so zone flags are active.
        let mut map = FlowMap::zero();
        map.velocity_mps
            .iter_mut()
            .for_each(|v| *v = Vector2::new(0.01, 0.0));
        let rig = fieldmaps::rigfile::Rig::load_paper().unwrap();
        let est = FlowEstimator::new(map, FlowConfig::default(), rig.phantom.zones.clone());
        let flags = |x_mm: f64, y_mm: f64| {
            est.estimate(&Pose {
                valid: Flag::TRUE,
                position_m: [x_mm * 1e-3, y_mm * 1e-3],
                ..Default::default()
            })
            .zone_flags
        };
        // Lower right atrium / valve: both zones.
        let both = zone::HIGH_DISTURBANCE | zone::RECIRCULATION;
        assert_eq!(flags(-15.0, -3.0) & both, both);
        // Tricuspid neck below the recirculation band: high disturbance only.
        assert_eq!(flags(-5.0, -8.0) & both, zone::HIGH_DISTURBANCE);
        // Outflow channel at the same heights: neither.
        assert_eq!(flags(29.0, -3.0) & both, 0);
        assert_eq!(flags(28.0, 5.0) & both, 0);
    }
}
