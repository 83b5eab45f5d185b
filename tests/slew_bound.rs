//! The scheduled SMC-DOB under a coil slew bound of 10 % of the coils' limit per 10 ms frame
//! (issue 21 point 7) in the paper's hardest flow cell, 20 cP at 10 cm/s, fast mode at 100 Hz:
//! the bound holds the coils back on the pump stroke's rise, and the loop counts that
//! shortfall in its disturbance estimate so that the robot is not left off its path. Without
//! that the bound cost 2.5x the RMSE here (0.64 against 0.26 mm); the test allows 1.6x.
//! Where the stroke outruns the bound, a bound that yields to 4x its rate when it would withhold
//! more than 20 % of the asked force (`[control.slew_yield]`) keeps the RMSE of the unbounded
//! loop (1.01x measured; the test allows 1.1x) with the p95 step still within the bound.
//! Measured on the twin without the scenarios' 6 ms pipeline delay and run without it: with
//! it the hard bound costs 1.73x (0.619 against 0.358 mm, 2026-11-28), the yielding bound is
//! what `results/smooth_100hz_yield` runs.

use millinav_experiments::{fast_run, set_in_table, Cell, FlowSetting, Metrics};
use millinav_tests::PaperCell;

fn run(max_step_fraction: Option<f64>, yield_fraction: Option<f64>) -> (Metrics, f64) {
    let cell = Cell {
        viscosity_cp: 20.0,
        flow: FlowSetting::Q250,
        controller: "smc-dob-auto".into(),
        seed: 1,
    };
    let mut limit_a = 0.0;
    let paper = PaperCell::new(&cell, |base| {
        millinav_tests::without_pipeline_delay(base);
        limit_a = base.rig().expect("rig").coil_limits().max_current_a;
        if let Some(fraction) = max_step_fraction {
            let rate_a_per_s = fraction * limit_a / (base.run.frame_period_ms * 1e-3);
            set_in_table(
                &mut base.sections,
                &["control", "max_current_slew_a_per_s"],
                rate_a_per_s.into(),
            )
            .expect("[control]");
            if let Some(shortfall) = yield_fraction {
                set_in_table(
                    &mut base.sections,
                    &["control", "slew_yield", "shortfall_fraction"],
                    shortfall.into(),
                )
                .expect("[control]");
                set_in_table(
                    &mut base.sections,
                    &["control", "slew_yield", "max_current_slew_a_per_s"],
                    (4.0 * rate_a_per_s).into(),
                )
                .expect("[control]");
            }
        }
    });
    let m = paper.metrics(&fast_run(&paper.scenario).expect("fast run"));
    println!(
        "bound {max_step_fraction:?} of {limit_a} A per frame, yield {yield_fraction:?}: RMSE {:.3} mm, completed {}, \
         p95 coil step {:.3} A",
        m.rmse_mm, m.completed, m.current_step_p95_a
    );
    (m, limit_a)
}

/// Completed, within 10 % of the limit per frame at p95, RMSE at most `ratio` x unbounded.
fn assert_held(bounded: &Metrics, free: &Metrics, limit_a: f64, ratio: f64, what: &str) {
    assert!(bounded.completed, "{what}: not completed");
    assert!(
        bounded.current_step_p95_a <= 0.1 * limit_a + 1e-3,
        "{what}: p95 coil step {:.3} A above 10 % of the {limit_a} A limit",
        bounded.current_step_p95_a
    );
    assert!(
        bounded.rmse_mm <= ratio * free.rmse_mm,
        "{what}: RMSE {:.3} mm against {:.3} mm unbounded",
        bounded.rmse_mm,
        free.rmse_mm
    );
}

#[test]
fn under_a_slew_bound_the_scheduled_dob_keeps_to_its_path_in_pulsatile_flow() {
    let (free, _) = run(None, None);
    assert!(free.completed);
    let (bounded, limit_a) = run(Some(0.1), None);
    assert!(
        free.current_step_p95_a > 0.1 * limit_a,
        "the cell should need the bound: unbounded p95 step {:.3} A",
        free.current_step_p95_a
    );
    assert_held(&bounded, &free, limit_a, 1.6, "hard bound");
    // Where the stroke outruns it, the bound that yields keeps the unbounded loop's RMSE.
    let (yielding, _) = run(Some(0.1), Some(0.2));
    assert_held(&yielding, &free, limit_a, 1.1, "yielding bound");
}
