//! The experiments' fast mode (plant, flow, control and coilbus libraries in one process, with
//! the localizer replaced by Gaussian pose noise) against the real process set in lockstep
//! (rendered frames, UNet vision, iceoryx2, the serial link): the same cell and seed must give
//! the same metrics within the tolerances below. The cells are the paper's scenario cut to its
//! first 20 s, in still fluid and in 7 cm/s pulsatile flow.
//!
//! Tolerances (stated in the README): |ΔRMSE| ≤ 0.05 mm, |ΔP95| ≤ 0.10 mm, |ΔMax| ≤ 0.25 mm,
//! the same completion verdict and no wall contact in either mode. The remaining difference is
//! the localization noise model (fast mode: 20 µm Gaussian; process: the UNet on rendered,
//! noisy, blurred frames).

use millinav_experiments::{fast_run, process_run, Cell, FlowSetting, Metrics};

const RMSE_TOL_MM: f64 = 0.05;
const P95_TOL_MM: f64 = 0.10;
const MAX_TOL_MM: f64 = 0.25;

fn compare(cell: Cell) {
    let paper = millinav_tests::PaperCell::new(&cell, |base| base.run.duration_s = 20.0);
    // One directory per cell: the tests run in parallel and each removes its own at the end.
    let work = std::env::temp_dir().join(format!(
        "millinav-fvp-{}-{}",
        std::process::id(),
        cell.name()
    ));
    let fast = paper.metrics(&fast_run(&paper.scenario).expect("fast run"));
    let process = paper.metrics(
        &process_run(&paper.text, &millinav_tests::bin_dir(), &work, &cell.name())
            .expect("process run"),
    );
    let row = |mode: &str, m: &Metrics| {
        println!(
            "{:<28} {mode:<8} RMSE {:.3} P95 {:.3} Max {:.3} mm completed {} contacts {}",
            cell.name(),
            m.rmse_mm,
            m.p95_mm,
            m.max_mm,
            m.completed,
            m.wall_contact_frames
        )
    };
    row("fast", &fast);
    row("process", &process);
    assert!(
        (fast.rmse_mm - process.rmse_mm).abs() <= RMSE_TOL_MM,
        "RMSE fast {:.3} vs process {:.3} mm",
        fast.rmse_mm,
        process.rmse_mm
    );
    assert!(
        (fast.p95_mm - process.p95_mm).abs() <= P95_TOL_MM,
        "P95 fast {:.3} vs process {:.3} mm",
        fast.p95_mm,
        process.p95_mm
    );
    assert!(
        (fast.max_mm - process.max_mm).abs() <= MAX_TOL_MM,
        "Max fast {:.3} vs process {:.3} mm",
        fast.max_mm,
        process.max_mm
    );
    assert_eq!(fast.completed, process.completed, "completion differs");
    assert!(fast.completed, "the cell did not complete");
    assert_eq!(
        (fast.wall_contact_frames, process.wall_contact_frames),
        (0, 0),
        "wall contacts"
    );
    let _ = std::fs::remove_dir_all(&work);
}

#[test]
fn pid_in_still_fluid_agrees() {
    compare(Cell {
        viscosity_cp: 20.0,
        flow: FlowSetting::Static,
        controller: "pid".into(),
        seed: 1,
    });
}

#[test]
fn auto_scheduled_smc_dob_in_pulsatile_flow_agrees() {
    compare(Cell {
        viscosity_cp: 20.0,
        flow: FlowSetting::Q180,
        controller: "smc-dob-auto".into(),
        seed: 1,
    });
}
