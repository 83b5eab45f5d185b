//! Robust actuation (issue 18, point 4). Fast mode at the paper's 10 Hz loop, with a per-coil
//! gain error of σ 10 % in the twin that control is not told: the scheduled SMC-DOB (its
//! orientation field turning for force at the coil limits, the coil gains learned online from
//! the heading) completes every condition of the paper's matrix for seeds 1–3. The RMSE is
//! printed; it is held only to within twice the paper's SMC-DOB RMSE here (a regression
//! guard: at 20 cP and 7 cm/s it sits within a few per cent of the paper's 1.00 mm). 4.3 cP at
//! 10 cm/s, which the paper did not run, must complete two of the three seeds: since the force
//! bound became the default (2026-12-02) seed 3 leaves 5 mm for over 2 s once (2.53 mm RMSE;
//! 2.11 mm without the bound), and which seed of that cell is lost moves with the bound's
//! setting (README, "Holding the slow estimate at the coil limit").

use millinav_experiments::report::paper_smc_dob_rmse_mm;
use millinav_experiments::{fast_run, set_in_table, Cell, FlowSetting};
use millinav_tests::PaperCell;

const GAIN_ERROR_STD: f64 = 0.1;

#[test]
fn ten_percent_coil_gain_error_at_10_hz_completes_every_condition() {
    let mut cells = Vec::new();
    for viscosity_cp in [20.0, 4.3] {
        for flow in [FlowSetting::Static, FlowSetting::Q180, FlowSetting::Q250] {
            for seed in 1..=3 {
                cells.push(Cell {
                    viscosity_cp,
                    flow,
                    controller: "smc-dob-auto".into(),
                    seed,
                });
            }
        }
    }
    // Two workers: the CI machine has two cores.
    let (left, right) = cells.split_at(cells.len() / 2);
    let outcomes: Vec<_> = std::thread::scope(|scope| {
        let workers: Vec<_> = [left, right]
            .into_iter()
            .map(|part| scope.spawn(move || part.iter().map(run_cell).collect::<Vec<_>>()))
            .collect();
        workers
            .into_iter()
            .flat_map(|w| w.join().expect("worker"))
            .collect()
    });
    let mut failures = Vec::new();
    let mut lost_beyond_the_paper = Vec::new();
    for (cell, completed, rmse_mm) in &outcomes {
        let bound = paper_smc_dob_rmse_mm(cell.viscosity_cp, cell.flow);
        println!(
            "{:<30} completed {completed} RMSE {rmse_mm:.2} mm (paper {bound:?})",
            cell.name()
        );
        match bound {
            Some(b) if !completed || *rmse_mm > 2.0 * b => failures.push(cell.name()),
            None if !completed => lost_beyond_the_paper.push(cell.name()),
            _ => {}
        }
    }
    assert!(
        failures.is_empty(),
        "failed, or above twice the paper's RMSE: {failures:?}"
    );
    assert!(
        lost_beyond_the_paper.len() <= 1,
        "lost beyond the paper's matrix: {lost_beyond_the_paper:?}"
    );
}

fn run_cell(cell: &Cell) -> (Cell, bool, f64) {
    let paper = PaperCell::new(cell, |base| {
        base.run.frame_period_ms = 100.0;
        set_in_table(
            &mut base.sections,
            &["plant", "physics", "coil_gain_error_std"],
            GAIN_ERROR_STD.into(),
        )
        .expect("plant.physics");
    });
    let m = paper.metrics(&fast_run(&paper.scenario).expect("fast run"));
    (cell.clone(), m.completed, m.rmse_mm)
}
