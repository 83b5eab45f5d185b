//! The "beyond the paper" claim at the paper's own loop rate (10 Hz), in fast mode: the
//! auto-scheduled SMC-DOB with constrained allocation completes the elevated-flow and
//! low-viscosity cells without hand retuning, at or below the paper's SMC-DOB RMSE where the
//! paper reports one, and the paper-gain baselines it is compared with do worse. One seed per
//! cell (the matrix in the README runs three).

use millinav_experiments::report::paper_smc_dob_rmse_mm;
use millinav_experiments::{fast_run, Cell, FlowSetting};
use millinav_tests::PaperCell;

/// RMSE bound where the paper reports none (4.3 cP at 10 cm/s): the 20 cP bound of that flow.
const UNREPORTED_BOUND_MM: f64 = 2.0;

fn run(viscosity_cp: f64, flow: FlowSetting, controller: &str) -> millinav_experiments::Metrics {
    let cell = Cell {
        viscosity_cp,
        flow,
        controller: controller.into(),
        seed: 1,
    };
    let paper = PaperCell::new(&cell, |base| base.run.frame_period_ms = 100.0);
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
fn scheduled_smc_dob_completes_every_flow_cell_at_10_hz() {
    for viscosity_cp in [20.0, 4.3] {
        for flow in [FlowSetting::Q180, FlowSetting::Q250] {
            let m = run(viscosity_cp, flow, "smc-dob-auto");
            let bound = paper_smc_dob_rmse_mm(viscosity_cp, flow).unwrap_or(UNREPORTED_BOUND_MM);
            assert!(m.completed, "{viscosity_cp} cP {flow:?} did not complete");
            // At or below the paper's mean, as the doc above says (seed 1 here: 0.97 vs 1.00 mm
            // at 20 cP 7 cm/s is the thinnest margin).
            assert!(
                m.rmse_mm <= bound,
                "{viscosity_cp} cP {flow:?}: RMSE {:.2} mm above the paper's {bound:.2}",
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
    assert!(!pid.completed, "PID completed 4.3 cP at 10 Hz");
    assert!(mpc.rmse_mm > 10.0 * auto.rmse_mm, "MPC close to SMC-DOB");
    assert!(
        without_dob.rmse_mm > 2.0 * auto.rmse_mm,
        "DOB ablation changed little"
    );
}
