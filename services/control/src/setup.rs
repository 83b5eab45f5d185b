//! What the `[control]` table and the trajectory configure, validated: the loop a scenario
//! describes.

use std::path::Path;
use std::sync::Arc;

use fieldmaps::rigfile::Rig;
use millinav_kit::scenario::Scenario;
use millinav_kit::{ConfigContext, ConfigError};

use crate::config::ControlConfig;
use crate::control_loop::ControlLoop;
use crate::reference::Reference;

/// What the `[control]` table and the trajectory configure, validated.
pub struct ControlSetup {
    pub config: ControlConfig,
    pub reference: Reference,
    /// The rig the scenario names.
    pub rig: Arc<Rig>,
}

impl ControlSetup {
    /// The loop for a fluid of `viscosity_pa_s`, answering as control incarnation `incarnation`.
    pub fn into_loop(self, viscosity_pa_s: f64, incarnation: u64) -> ControlLoop {
        ControlLoop::new(
            self.config,
            self.reference,
            viscosity_pa_s,
            incarnation,
            self.rig,
        )
    }
}

/// Parses and validates the `[control]` table and the reference trajectory. Every failure is a
/// configuration error naming the scenario and the field.
pub fn prepare(scenario: &Scenario) -> Result<ControlSetup, ConfigError> {
    let config: ControlConfig = scenario.section("control")?;
    let fields = Fields {
        scenario: &scenario.path,
    };
    check_numbers(&config, &fields)?;
    check_slew(&config, &fields)?;
    check_subtables(&config, &fields)?;
    let rig = scenario.rig()?;
    let reference = reference_on(scenario, &rig)?;
    Ok(ControlSetup {
        config,
        reference,
        rig,
    })
}

/// Names a field of the scenario's `[control]` tables in an error.
struct Fields<'a> {
    scenario: &'a Path,
}

impl Fields<'_> {
    fn name(&self, name: &str) -> String {
        format!("scenario {}: [control] {name}", self.scenario.display())
    }

    /// `value` is finite and above `min` (`strict`) or at least `min`.
    fn at_least(&self, name: &str, value: f64, min: f64, strict: bool) -> Result<(), ConfigError> {
        let fine = value.is_finite() && if strict { value > min } else { value >= min };
        if fine {
            return Ok(());
        }
        let relation = if strict { ">" } else { ">=" };
        Err(ConfigError::new(format!(
            "{} must be {relation} {min}, got {value}",
            self.name(name)
        )))
    }

    /// A sub-table's own check (`invalid_field`) as an error naming `[control.<table>]`.
    fn subtable(
        &self,
        table: &str,
        invalid: Option<(&'static str, String)>,
    ) -> Result<(), ConfigError> {
        match invalid {
            Some((name, why)) => Err(ConfigError::new(format!(
                "scenario {}: [control.{table}] {name} {why}",
                self.scenario.display()
            ))),
            None => Ok(()),
        }
    }
}

/// The `[control]` table's own numbers.
fn check_numbers(config: &ControlConfig, fields: &Fields<'_>) -> Result<(), ConfigError> {
    fields.at_least("hold_timeout_ms", config.hold_timeout_ms, 0.0, false)?;
    fields.at_least("max_speed_mps", config.max_speed_mps, 0.0, true)?;
    fields.at_least("velocity_filter_ms", config.velocity_filter_ms, 0.0, false)?;
    if let Some(mt) = config.field_magnitude_mt {
        fields.at_least("field_magnitude_mt", mt, 0.0, false)?;
    }
    fields.at_least("aligning_torque_n_m", config.aligning_torque_n_m, 0.0, true)?;
    fields.at_least(
        "coil_time_constant_ms",
        config.coil_time_constant_ms,
        0.0,
        false,
    )?;
    fields.at_least("drag_factor", config.drag_factor, 0.0, true)?;
    fields.at_least("omega0_n_per_t", config.omega0_n_per_t, 0.0, true)?;
    fields.at_least("field_row_weight", config.field_row_weight, 0.0, true)?;
    fields.at_least("replan_clearance_mm", config.replan_clearance_mm, 0.0, true)?;
    if !config.field_heading_deg.is_finite() {
        return Err(ConfigError::new(format!(
            "{} must be finite, got {}",
            fields.name("field_heading_deg"),
            config.field_heading_deg
        )));
    }
    if let Some(limits) = &config.limits {
        limits.validate().config_context(fields.name("limits"))?;
    }
    Ok(())
}

/// The slew bound and where it yields (a yield needs a bound, and a faster rate than it).
fn check_slew(config: &ControlConfig, fields: &Fields<'_>) -> Result<(), ConfigError> {
    if let Some(rate) = config.max_current_slew_a_per_s {
        fields.at_least("max_current_slew_a_per_s", rate, 0.0, true)?;
    }
    let Some(yielding) = &config.slew_yield else {
        return Ok(());
    };
    let Some(rate) = config.max_current_slew_a_per_s else {
        return Err(ConfigError::new(format!(
            "{} needs a bound to yield from: set {}",
            fields.name("slew_yield"),
            fields.name("max_current_slew_a_per_s")
        )));
    };
    let fraction = yielding.shortfall_fraction;
    if !(fraction.is_finite() && fraction > 0.0 && fraction < 1.0) {
        return Err(ConfigError::new(format!(
            "{} must be within (0, 1), got {fraction}",
            fields.name("slew_yield.shortfall_fraction")
        )));
    }
    fields.at_least(
        "slew_yield.max_current_slew_a_per_s",
        yielding.max_current_slew_a_per_s,
        rate,
        true,
    )
}

/// The sub-tables' checks: gain estimation, observer, SMC delay model, latency.
fn check_subtables(config: &ControlConfig, fields: &Fields<'_>) -> Result<(), ConfigError> {
    fields.subtable("gain_estimation", config.gain_estimation.invalid_field())?;
    fields.subtable("observer", config.observer.invalid_field())?;
    let sigmas = config.smc.delay_model_error_sigmas;
    if !(sigmas.is_finite() && (0.0..=10.0).contains(&sigmas)) {
        return Err(ConfigError::new(format!(
            "scenario {}: [control.smc] delay_model_error_sigmas must be within 0..=10 (standard \
             deviations of the coil gains' uncertainty), got {sigmas}",
            fields.scenario.display()
        )));
    }
    fields.subtable("latency", config.latency.invalid_field())
}

/// The scenario's reference trajectory, every waypoint inside the rig's canal.
fn reference_on(scenario: &Scenario, rig: &Rig) -> Result<Reference, ConfigError> {
    let reference = Reference::new(
        &scenario.waypoints_m(),
        scenario.trajectory.speed_mm_s * 1e-3,
        scenario.trajectory.start_time_s,
    )
    .config_context(format!(
        "scenario {}: [trajectory]",
        scenario.path.display()
    ))?;
    let outside: Vec<String> = reference
        .waypoints()
        .iter()
        .filter(|p| !rig.phantom.contains(p))
        .map(|p| format!("({:.2}, {:.2})", p.x * 1e3, p.y * 1e3))
        .collect();
    if !outside.is_empty() {
        return Err(ConfigError::new(format!(
            "scenario {}: [trajectory] waypoints_mm {} lie outside the canal of rig {} (mask {})",
            scenario.path.display(),
            outside.join(", "),
            rig.path.display(),
            rig.phantom.mask_path.display()
        )));
    }
    Ok(reference)
}

/// Validates the `[control]` table and the trajectory (what `--check` runs).
pub fn check_config(scenario: &Scenario) -> Result<(), ConfigError> {
    prepare(scenario).map(drop)
}

/// Builds the loop a scenario describes.
pub fn build_loop(scenario: &Scenario, incarnation: u64) -> anyhow::Result<ControlLoop> {
    Ok(prepare(scenario)?.into_loop(scenario.viscosity_pa_s(), incarnation))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A scenario as if read from a file of its own (parsed from text: nothing is written), with
    /// `control_table` as its `[control]`.
    fn scenario_with(name: &str, control_table: &str) -> Scenario {
        let dir =
            std::env::temp_dir().join(format!("millinav-control-{}-{name}", std::process::id()));
        let text = format!(
            "[run]\nduration_s = 1.0\nrig = \"fieldmaps/rigs/paper.toml\"\n[fluid]\nviscosity_cp = 20.0\n\
             [trajectory]\nwaypoints_mm = [[-18.0, 12.0], [-12.0, 8.0]]\n\
             [control]\n{control_table}\n"
        );
        Scenario::parse(&text, &dir.join("scenario.toml")).unwrap()
    }

    #[test]
    fn the_default_field_holds_any_magnet_with_the_papers_torque() {
        let config = ControlConfig::default();
        // The paper's 1 mT on its magnet, exactly (its matrices stay bit for bit).
        assert_eq!(config.field_magnitude_t(8.6e-4), 1e-3);
        let strong = config.field_magnitude_t(5.61e-3);
        assert!((strong * 5.61e-3 - 8.6e-7).abs() < 1e-15, "{strong} T");
        let fixed = ControlConfig {
            field_magnitude_mt: Some(0.3),
            ..ControlConfig::default()
        };
        assert_eq!(fixed.field_magnitude_t(5.61e-3), 0.3e-3);
    }

    #[test]
    fn check_config_accepts_good_tables() {
        check_config(&scenario_with("good", "controller = \"pid\"")).unwrap();
        check_config(&scenario_with(
            "smc",
            "controller = \"smc-dob\"\n[control.smc]",
        ))
        .unwrap();
    }

    #[test]
    fn check_config_rejects_typos_and_bad_values() {
        // The message a table is refused with.
        let refused = |name: &str, table: &str| {
            check_config(&scenario_with(name, table))
                .unwrap_err()
                .to_string()
        };
        let error = refused("typo", "controler = \"pid\"");
        assert!(
            error.contains("[control]") && error.contains("controler"),
            "{error}"
        );

        let error = refused("kind", "controller = \"magic\"");
        assert!(error.contains("magic"), "{error}");

        let error = refused("nested", "[control.pid]\nkpp = 1.0");
        assert!(error.contains("kpp"), "{error}");

        let error = refused("speed", "max_speed_mps = -1.0");
        assert!(error.contains("[control] max_speed_mps"), "{error}");

        let error = refused("replan", "replan_clearance_mm = 0.0");
        assert!(error.contains("[control] replan_clearance_mm"), "{error}");

        let error = refused(
            "model error",
            "[control.smc]\ndelay_model_error_sigmas = -1.5",
        );
        assert!(
            error.contains("[control.smc] delay_model_error_sigmas") && error.contains("-1.5"),
            "{error}"
        );

        let error = refused("slew", "max_current_slew_a_per_s = 0.0");
        assert!(
            error.contains("[control] max_current_slew_a_per_s"),
            "{error}"
        );

        let error = refused(
            "yield alone",
            "[control.slew_yield]\nshortfall_fraction = 0.2",
        );
        assert!(
            error.contains("[control] slew_yield") && error.contains("max_current_slew_a_per_s"),
            "{error}"
        );
        let error = refused(
            "yield fraction",
            "max_current_slew_a_per_s = 60.0\n[control.slew_yield]\nshortfall_fraction = 1.5",
        );
        assert!(
            error.contains("[control] slew_yield.shortfall_fraction"),
            "{error}"
        );
        let error = refused(
            "yield rate",
            "max_current_slew_a_per_s = 60.0\n[control.slew_yield]\nmax_current_slew_a_per_s = 30.0",
        );
        assert!(
            error.contains("[control] slew_yield.max_current_slew_a_per_s must be > 60"),
            "{error}"
        );

        let error = refused("latency", "[control.latency]\nmax_pose_age_ms = -5.0");
        assert!(
            error.contains("[control.latency] max_pose_age_ms"),
            "{error}"
        );

        let error = refused(
            "gains",
            "[control.gain_estimation]\nenabled = true\nprior_std = -0.1",
        );
        assert!(
            error.contains("[control.gain_estimation] prior_std"),
            "{error}"
        );

        let error = refused("torque", "aligning_torque_n_m = 0.0");
        assert!(error.contains("[control] aligning_torque_n_m"), "{error}");

        let error = refused("coils", "coil_time_constant_ms = -5.0");
        assert!(error.contains("[control] coil_time_constant_ms"), "{error}");

        let error = refused("drag", "drag_factor = 0.0");
        assert!(error.contains("[control] drag_factor"), "{error}");

        let error = refused(
            "limits",
            "[control.limits]\nmax_current_a = 0.0\nmax_total_power_w = 100.0\n\
             coil_resistance_ohm = 10.0",
        );
        assert!(
            error.contains("[control] limits") && error.contains("max_current_a"),
            "{error}"
        );
    }
}
