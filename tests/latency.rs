//! Latency compensation (issue 21, point 1). Fast mode: with one extra camera frame at the
//! paper's 10 Hz (+100 ms) and +50 ms at 100 Hz, the auto-scheduled SMC-DOB fed the state
//! predicted for the actuation time (`[control.latency] compensate = true`, the default)
//! completes the still-fluid cells (and at 100 Hz the 7 cm/s cell) below the paper's RMSE, and
//! the same controller fed the stale pose loses the robot or tracks 5x worse than the paper.
//! With a per-coil gain error as well (+30 ms at 100 Hz) it still holds still fluid. Process
//! set: the same at 10 Hz in still fluid, the delay measured from the frames' stamps.

use millinav_experiments::report::paper_smc_dob_rmse_mm;
use millinav_experiments::{fast_run, process_run, set_in_table, Cell, FlowSetting, Metrics};
use millinav_kit::scenario::Scenario;
use millinav_tests::PaperCell;

/// Sets `[plant.camera] latency_frames` and `[control.latency] compensate` of a base scenario.
fn with_latency(base: &mut Scenario, latency_frames: u32, compensate: bool) {
    let sections = &mut base.sections;
    set_in_table(
        sections,
        &["plant", "camera", "latency_frames"],
        i64::from(latency_frames).into(),
    )
    .expect("plant.camera");
    set_in_table(
        sections,
        &["control", "latency", "compensate"],
        compensate.into(),
    )
    .expect("control.latency");
}

fn run(
    viscosity_cp: f64,
    flow: FlowSetting,
    frame_period_ms: f64,
    latency_frames: u32,
    compensate: bool,
) -> Metrics {
    run_seed(
        viscosity_cp,
        flow,
        frame_period_ms,
        latency_frames,
        compensate,
        1,
        |_| {},
    )
}

/// `run` with another seed and further changes to the base scenario.
fn run_seed(
    viscosity_cp: f64,
    flow: FlowSetting,
    frame_period_ms: f64,
    latency_frames: u32,
    compensate: bool,
    seed: u64,
    change: impl Fn(&mut Scenario),
) -> Metrics {
    let cell = Cell {
        viscosity_cp,
        flow,
        controller: "smc-dob-auto".into(),
        seed,
    };
    let paper = PaperCell::new(&cell, |base| {
        base.run.frame_period_ms = frame_period_ms;
        with_latency(base, latency_frames, compensate);
        change(base);
    });
    let m = paper.metrics(&fast_run(&paper.scenario).expect("fast run"));
    println!(
        "{:<28} {frame_period_ms} ms + {latency_frames} frames, compensate {compensate}: \
         RMSE {:.2} P95 {:.2} Max {:.2} mm completed {}",
        cell.name(),
        m.rmse_mm,
        m.p95_mm,
        m.max_mm,
        m.completed
    );
    m
}

/// `held` completed below the paper's RMSE of its cell (`bound`, mm), and `without` (the same
/// run without what `what` names) lost the robot or tracked more than 5x `worse_than` mm.
fn assert_held_only_with(
    held: &Metrics,
    without: &Metrics,
    bound: f64,
    worse_than: f64,
    what: &str,
) {
    assert!(
        held.completed && held.rmse_mm <= bound,
        "with {what}: RMSE {:.2} mm (paper {bound:.2}), completed {}",
        held.rmse_mm,
        held.completed
    );
    assert!(
        !without.completed || without.rmse_mm > 5.0 * worse_than,
        "without {what} the loop did well too (RMSE {:.2} mm)",
        without.rmse_mm
    );
}

fn assert_recovered(viscosity_cp: f64, flow: FlowSetting, frame_period_ms: f64, frames: u32) {
    let compensated = run(viscosity_cp, flow, frame_period_ms, frames, true);
    // Fed the stale pose, the same controller loses the robot or oscillates far off the path.
    let stale = run(viscosity_cp, flow, frame_period_ms, frames, false);
    let bound = paper_smc_dob_rmse_mm(viscosity_cp, flow).expect("the paper reports this cell");
    let what = format!("latency compensation ({viscosity_cp} cP {flow:?})");
    assert_held_only_with(&compensated, &stale, bound, bound, &what);
}

#[test]
fn one_extra_frame_at_10_hz_is_compensated_in_still_fluid() {
    for viscosity_cp in [20.0, 4.3] {
        assert_recovered(viscosity_cp, FlowSetting::Static, 100.0, 1);
    }
}

#[test]
fn fifty_ms_at_100_hz_is_compensated_in_still_fluid_and_7_cm_s_flow() {
    assert_recovered(20.0, FlowSetting::Static, 10.0, 5);
    assert_recovered(20.0, FlowSetting::Q180, 10.0, 5);
}

/// A per-coil gain error the controller does not know, with camera latency, at 100 Hz: the
/// predictor removes the delay only as far as its force model is right, so the scheduled SMC-DOB
/// counts a share of the delay as loop lag in its switching slope, as large as the coil gains
/// are uncertain (`[control.smc] delay_model_error_sigmas`, 2 by default), or as the share of the
/// motion it measurably missed (`unpredicted_motion_lag`, on by default), whichever is larger.
/// Without either share the same run (still 4.3 cP fluid, +30 ms, 10 % gain error, seed 2)
/// rang from the start and was thrown across the canal; since the orientation field turns no
/// faster than the capsule follows it (2026-11-28) it rings without being thrown, at 0.58 mm
/// against 0.06 mm with the share, so the test asks for a 5x gain instead of a loss. The case
/// was found on the twin without the scenarios' 6 ms pipeline delay and runs without it: with
/// it, +36 ms in all, seed 2 holds even without the share (0.24 mm), so the case would no
/// longer tell the two apart.
#[test]
fn latency_with_a_coil_gain_error_is_held_in_still_fluid() {
    let with_gain_error = |delay_model_error_sigmas: Option<f64>| {
        move |base: &mut Scenario| {
            millinav_tests::without_pipeline_delay(base);
            let sections = &mut base.sections;
            set_in_table(
                sections,
                &["plant", "physics", "coil_gain_error_std"],
                0.1.into(),
            )
            .expect("plant.physics");
            if let Some(sigmas) = delay_model_error_sigmas {
                set_in_table(
                    sections,
                    &["control", "smc", "delay_model_error_sigmas"],
                    sigmas.into(),
                )
                .expect("control.smc");
                set_in_table(
                    sections,
                    &["control", "smc", "unpredicted_motion_lag"],
                    false.into(),
                )
                .expect("control.smc");
            }
        }
    };
    let still = FlowSetting::Static;
    let held = run_seed(4.3, still, 10.0, 3, true, 2, with_gain_error(None));
    let unshared = run_seed(4.3, still, 10.0, 3, true, 2, with_gain_error(Some(0.0)));
    let bound = paper_smc_dob_rmse_mm(4.3, still).expect("the paper reports this cell");
    let what = "the delay share (the defaults)";
    assert_held_only_with(&held, &unshared, bound, held.rmse_mm, what);
}

/// Through the real process set (rendered frames stamped with capture and grab time, UNet
/// vision, flow, control, the serial link) at the paper's 10 Hz with one extra camera frame:
/// control measures the delay from the stamps and the scheduled SMC-DOB completes below the
/// paper's RMSE.
#[test]
fn the_process_set_compensates_one_extra_frame_at_10_hz() {
    let cell = Cell {
        viscosity_cp: 20.0,
        flow: FlowSetting::Static,
        controller: "smc-dob-auto".into(),
        seed: 1,
    };
    let paper = PaperCell::new(&cell, |base| {
        base.run.frame_period_ms = 100.0;
        base.run.duration_s = 120.0;
        with_latency(base, 1, true);
    });
    let work = std::env::temp_dir().join(format!("millinav-latency-{}", std::process::id()));
    let trace = process_run(
        &paper.text,
        &millinav_tests::bin_dir(),
        &work,
        "latency-10hz",
    )
    .expect("process run");
    let m = paper.metrics(&trace);
    println!(
        "process 10 Hz + 1 frame: RMSE {:.3} P95 {:.3} Max {:.3} mm completed {}",
        m.rmse_mm, m.p95_mm, m.max_mm, m.completed
    );
    let bound = paper_smc_dob_rmse_mm(20.0, FlowSetting::Static).expect("paper value");
    assert!(m.completed && m.rmse_mm <= bound, "{m:?}");
    let _ = std::fs::remove_dir_all(&work);
}
