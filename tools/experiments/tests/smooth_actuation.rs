//! The default run (PID, still 20 cP, 100 Hz) with the committed default scenario's smooth
//! actuation (velocity from the model-based observer, coil slew bound) against the same run
//! with low-passed differences and no bound: the coil steps fall within 10 % of the coils'
//! limit and the tracking is no worse (issue 21 point 7).

use std::path::Path;

use millinav_experiments::{fast_run, metrics, reference_of, scenario_document, set_in_table};
use millinav_kit::scenario::Scenario;

/// Simulated seconds: the path's first stretch, enough for several thousand frames.
const DURATION_S: f64 = 20.0;

fn shortened(scenario: &Scenario, path: &Path, smooth: bool) -> Scenario {
    let mut doc = scenario_document(scenario).expect("scenario as TOML");
    set_in_table(&mut doc, &["run", "duration_s"], DURATION_S.into()).expect("duration");
    if !smooth {
        let control = doc
            .get_mut("control")
            .and_then(toml::Value::as_table_mut)
            .expect("[control]");
        control.remove("max_current_slew_a_per_s");
        control.insert("velocity_estimate".into(), "differences".into());
    }
    let text = toml::to_string(&doc).expect("TOML text");
    Scenario::parse(&text, path).expect("scenario parses")
}

#[test]
fn the_default_run_moves_its_coils_smoothly_and_tracks_no_worse() {
    let path = fieldmaps::data_root().join("scenarios/default.toml");
    let scenario = Scenario::load(&path).expect("default scenario");
    let rig = scenario.rig().expect("rig");
    let limits = rig.coil_limits();
    let (limit_a, resistance) = (limits.max_current_a, limits.coil_resistance_ohm);
    let run = |smooth: bool| {
        let scenario = shortened(&scenario, &path, smooth);
        let trace = fast_run(&scenario).expect("fast run");
        metrics(
            &trace,
            &reference_of(&scenario).expect("reference"),
            resistance,
        )
    };
    let (smooth, differences) = (run(true), run(false));
    eprintln!("smooth {smooth:?}\ndifferences {differences:?}");
    assert!(
        smooth.current_step_p95_a <= 0.1 * limit_a + 1e-3,
        "p95 coil step {:.3} A above 10 % of the {limit_a} A limit",
        smooth.current_step_p95_a
    );
    assert!(
        differences.current_step_p95_a > 2.0 * smooth.current_step_p95_a,
        "without the observer and the bound the coils should chatter: p95 step {:.3} A vs {:.3} A",
        differences.current_step_p95_a,
        smooth.current_step_p95_a
    );
    assert!(smooth.completed && differences.completed);
    assert!(
        smooth.rmse_mm <= differences.rmse_mm,
        "smooth RMSE {:.3} mm worse than {:.3} mm with differences",
        smooth.rmse_mm,
        differences.rmse_mm
    );
}
