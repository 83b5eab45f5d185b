//! The paper's own loop (10 Hz) with the paper's pipeline delay, 60 ms from a frame's capture to
//! its command on the coils (the committed 10 Hz matrix, README "Latest matrix"), in fast mode:
//! the auto-scheduled SMC-DOB completes still fluid and the 7 cm/s flow the paper ran, at both
//! viscosities, without hand retuning, below the paper's SMC-DOB RMSE in still fluid and within
//! 1.5x of it in flow, and the paper-gain baselines it is compared with do worse. The 10 cm/s
//! cells: README; nothing here asserts them. One seed per cell (the matrix runs three).

use millinav_experiments::report::paper_smc_dob_rmse_mm;
use millinav_experiments::{fast_run, Cell, FlowSetting};
use millinav_tests::PaperCell;

/// The paper's pipeline: capture → coils, ms (README, "Latest matrix").
const PAPER_PIPELINE_DELAY_MS: f64 = 60.0;
/// How far above the paper's SMC-DOB RMSE the flow cells may be at that delay.
const FLOW_RMSE_FACTOR: f64 = 1.5;

fn run(viscosity_cp: f64, flow: FlowSetting, controller: &str) -> millinav_experiments::Metrics {
    let cell = Cell {
        viscosity_cp,
        flow,
        controller: controller.into(),
        seed: 1,
    };
    let paper = PaperCell::new(&cell, |base| {
        base.run.frame_period_ms = 100.0;
        millinav_tests::with_pipeline_delay(base, PAPER_PIPELINE_DELAY_MS);
    });
    let m = paper.metrics(&fast_run(&paper.scenario).expect("fast run"));
    println!(
        "{:<28} RMSE {:.2} P95 {:.2} Max {:.2} mm completed {}",
        cell.name(),
        m.rmse_mm,
        m.p95_mm,
        m.max_mm,
        m.completed
    );
    m
}

#[test]
fn scheduled_smc_dob_completes_still_fluid_and_7_cm_s_at_the_papers_pipeline() {
    for viscosity_cp in [20.0, 4.3] {
        for (flow, factor) in [
            (FlowSetting::Static, 1.0),
            (FlowSetting::Q180, FLOW_RMSE_FACTOR),
        ] {
            let m = run(viscosity_cp, flow, "smc-dob-auto");
            let bound = factor * paper_smc_dob_rmse_mm(viscosity_cp, flow).expect("paper RMSE");
            assert!(m.completed, "{viscosity_cp} cP {flow:?} did not complete");
            // Seed 1 of the committed matrix (results/results.csv, 2026-12-02): 1.29 mm at
            // 20 cP 7 cm/s against the paper's 1.00, 1.44 at 4.3 cP against 1.60; 0.05 / 0.05 mm
            // in still fluid.
            assert!(
                m.rmse_mm <= bound,
                "{viscosity_cp} cP {flow:?}: RMSE {:.2} mm above {bound:.2}",
                m.rmse_mm
            );
        }
    }
}

#[test]
fn baselines_fail_or_degrade_at_low_viscosity_at_10_hz() {
    let auto = run(4.3, FlowSetting::Static, "smc-dob-auto");
    let pid = run(4.3, FlowSetting::Static, "pid");
    let mpc = run(4.3, FlowSetting::Static, "mpc");
    let without_dob = run(4.3, FlowSetting::Static, "smc-auto");
    assert!(auto.completed);
    // The paper's PID failed here. Through our latency compensation with its force bound
    // (2026-12-02) it completes, at 80x the scheduled SMC-DOB's RMSE (seed 1: 4.05 against
    // 0.05 mm); fed the stale pose as the paper's loop was, it fails (README, "Calibration").
    assert!(
        !pid.completed || pid.rmse_mm > 10.0 * auto.rmse_mm,
        "PID close to SMC-DOB at 4.3 cP at 10 Hz: {:.2} mm",
        pid.rmse_mm
    );
    assert!(mpc.rmse_mm > 10.0 * auto.rmse_mm, "MPC close to SMC-DOB");
    assert!(
        without_dob.rmse_mm > 2.0 * auto.rmse_mm,
        "DOB ablation changed little"
    );
}

/// The drag of `scenario`'s twin (its capsule as the plant makes it), over paper Eq. 7: the mean
/// along and across the capsule's axis, what a lab measures as force over terminal speed when
/// it pushes the capsule both ways.
fn measured_drag_factor(scenario: &millinav_kit::scenario::Scenario) -> f64 {
    let config: millinav_plant::PlantConfig = scenario.section("plant").expect("[plant]");
    let model = millinav_plant::build_model(scenario, &config).expect("plant model");
    let robot = model.robot;
    let eq7 = fieldmaps::physics::translational_damping(
        scenario.viscosity_pa_s(),
        robot.length_m,
        robot.diameter_m / 2.0,
    );
    model.linear_drag() / eq7
}

#[test]
fn told_the_capsules_drag_the_scheduled_dob_holds_a_cylinder_on_the_floor_at_the_papers_pipeline() {
    // A cylinder on a 30 µm film drags 5–8x paper Eq. 7. Untold, the observer takes the extra
    // drag for a disturbance and cancels it a delay late: still 20 cP fluid was lost at the
    // paper's 10 Hz and 60 ms (13.5 mm, 0/3 seeds; README "Telling control the capsule's drag").
    // Since the force bound (2026-12-02) the untold loop is no longer thrown, but it rings
    // above the paper's RMSE (seed 1: 0.97 mm against 0.49; told 0.03 mm).
    let gap_m = 3e-5;
    let cell = Cell {
        viscosity_cp: 20.0,
        flow: FlowSetting::Static,
        controller: "smc-dob-auto".into(),
        seed: 1,
    };
    let cell_told = |drag_factor: Option<f64>| {
        PaperCell::new(&cell, |base| {
            base.run.frame_period_ms = 100.0;
            millinav_tests::with_pipeline_delay(base, PAPER_PIPELINE_DELAY_MS);
            let mut set = |path: &[&str], value: toml::Value| {
                millinav_experiments::set_in_table(&mut base.sections, path, value)
                    .expect("scenario tables")
            };
            set(
                &["plant", "physics", "drag_shape"],
                toml::Value::String("cylinder".into()),
            );
            set(
                &["plant", "physics", "floor_gap_m"],
                toml::Value::Float(gap_m),
            );
            set(
                &["plant", "physics", "floor_flow_factor"],
                toml::Value::Float(1.7),
            );
            if let Some(factor) = drag_factor {
                set(&["control", "drag_factor"], toml::Value::Float(factor));
            }
        })
    };
    let run_told = |drag_factor: Option<f64>| {
        let paper = cell_told(drag_factor);
        let m = paper.metrics(&fast_run(&paper.scenario).expect("fast run"));
        println!(
            "drag factor told {drag_factor:?}: RMSE {:.2} mm, max {:.2} mm, completed {}",
            m.rmse_mm, m.max_mm, m.completed
        );
        m
    };
    let measured = measured_drag_factor(&cell_told(None).scenario);
    assert!((5.0..8.0).contains(&measured), "drag factor {measured}");
    let untold = run_told(None);
    let told = run_told(Some(measured));
    let paper = paper_smc_dob_rmse_mm(20.0, FlowSetting::Static).expect("paper RMSE");
    assert!(
        !untold.completed || untold.rmse_mm > paper,
        "untold held at {:.2} mm",
        untold.rmse_mm
    );
    assert!(told.completed);
    assert!(told.rmse_mm < paper, "told: RMSE {:.2} mm", told.rmse_mm);
}
