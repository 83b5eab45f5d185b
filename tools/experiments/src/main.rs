//! `experiments`: the paper's matrix on the twin, with tables and figures.
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

use anyhow::Context;
use clap::{Parser, ValueEnum};
use fieldmaps::rigfile::Rig;
use indicatif::{ProgressBar, ProgressStyle};
use millinav_experiments::report::{self, Outcome};
use millinav_experiments::robustness;
use millinav_experiments::{
    cell_scenario, fast_run, metrics, process_run, recorded_run, reference_of, rig_matrix,
    set_in_table, write_rrd, Cell, Metrics, TraceRow,
};
use millinav_kit::scenario::Scenario;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Mode {
    /// One process, the services' libraries, ground truth + localization noise for vision.
    Fast,
    /// The real process set in lockstep through `millinav run` (slow: full camera + vision).
    Process,
}

/// Runs the paper's matrix (viscosity {20, 4.3} cP x flow {static, 7, 10 cm/s} x controller
/// {PID, MPC, SMC-DOB, SMC without DOB} x trials) on the digital twin and writes results.csv,
/// table.md and PNG figures into --out.
#[derive(Parser)]
#[command(name = "experiments", version)]
struct Args {
    /// Base scenario (run, trajectory, plant and vision settings); each cell overrides fluid,
    /// flow map, controller and seed.
    #[arg(long, default_value = "scenarios/paper.toml")]
    base: PathBuf,
    #[arg(long, value_enum, default_value = "fast")]
    mode: Mode,
    /// Seeded trials per cell.
    #[arg(long, default_value_t = 3)]
    trials: u64,
    /// Also run the auto-scheduled SMC-DOB with constrained allocation (beyond the paper).
    #[arg(long)]
    beyond: bool,
    /// Only these controllers (comma separated), e.g. smc-dob,pid.
    #[arg(long, value_delimiter = ',')]
    controllers: Vec<String>,
    /// Only cells whose name contains one of these (comma separated), e.g. 20cp_q180,4.3cp_static.
    #[arg(long, value_delimiter = ',')]
    only: Vec<String>,
    /// Camera frame period and so control period (ms) instead of the base scenario's; e.g. 100
    /// for the paper's 10 Hz loop.
    #[arg(long)]
    frame_period_ms: Option<f64>,
    /// Camera latency (ms) on top of the frame period, instead of the base scenario's
    /// `[plant.camera] latency_frames`: a whole number of frame periods, e.g. 100 at 10 Hz.
    #[arg(long)]
    camera_latency_ms: Option<f64>,
    /// Standard deviation of the twin's per-coil gain error that control does not know
    /// (`[plant.physics] coil_gain_error_std`, a fraction: 0.1 for 10 %) instead of the base
    /// scenario's.
    #[arg(long)]
    coil_gain_error: Option<f64>,
    /// Feed the controllers the delayed pose as measured (`[control.latency] compensate =
    /// false`) instead of the state predicted for the actuation time.
    #[arg(long)]
    no_latency_compensation: bool,
    /// Skip the per-run Rerun recordings of fast mode (`<out>/runs/<cell>.rrd`; process mode
    /// always keeps each run's `run.rrd` under `<out>/runs/<cell>/run/`).
    #[arg(long)]
    no_rrd: bool,
    /// Process mode: take each cell's ground truth from an earlier run of the same cell under
    /// `<out>/runs/` instead of running it again (to re-report after a change to the metrics or
    /// figures). A cell whose recorded scenario differs is an error; wall_s then is read time.
    #[arg(long)]
    reuse_runs: bool,
    /// Run the robustness matrix instead of the paper's: 20 cP at 7 cm/s with one disturbance
    /// varied at a time (pulsation rate and amplitude, flow noise, recirculation, per-coil gain
    /// error, camera latency, viscosity) at 10 and 100 Hz, for the scheduled SMC-DOB and the
    /// baselines (or --controllers); writes robustness.csv, robustness.md, robustness.png.
    #[arg(long)]
    robustness: bool,
    /// Worker threads (fast mode).
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Output directory.
    #[arg(long, default_value = "results")]
    out: PathBuf,
}

/// Traces of the first trial (seed 1) of each cell, for the trace figures.
type FirstTrials = Vec<(Cell, Vec<TraceRow>)>;

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let base = load_base(&args)?;
    if args.robustness {
        return run_robustness(&args, &base);
    }
    let rig = base.rig()?;
    let cells = selected_cells(&args, &rig)?;
    std::fs::create_dir_all(&args.out)?;
    let threads = match args.mode {
        Mode::Fast => args.threads.max(1),
        Mode::Process => 1,
    };
    let start = Instant::now();
    let (mut outcomes, traces) = run_cells(&args, &base, cells, threads)?;
    outcomes.sort_by_key(|o| o.cell.name());
    let mode = format!("{:?}", args.mode).to_lowercase();
    write_tables(&args, &base, &outcomes, &mode)?;
    println!(
        "{} runs in {:.1} s ({mode} mode, {threads} threads)",
        outcomes.len(),
        start.elapsed().as_secs_f64()
    );
    if report::register_font() {
        write_figures(&args, &base, &outcomes, &traces)?;
    } else {
        eprintln!("no DejaVu font found (apt install fonts-dejavu-core): figures skipped");
    }
    Ok(())
}

/// The base scenario, with `--frame-period-ms`, `--camera-latency-ms`, `--coil-gain-error`
/// and `--no-latency-compensation` applied.
fn load_base(args: &Args) -> anyhow::Result<Scenario> {
    let mut base = Scenario::load(&args.base)
        .with_context(|| format!("base scenario {}", args.base.display()))?;
    if let Some(period) = args.frame_period_ms {
        anyhow::ensure!(
            period.is_finite() && (1.0..=1000.0).contains(&period),
            "--frame-period-ms must be within 1..=1000, got {period}"
        );
        base.run.frame_period_ms = period;
    }
    if let Some(latency_ms) = args.camera_latency_ms {
        let frames = latency_ms / base.run.frame_period_ms;
        anyhow::ensure!(
            latency_ms.is_finite()
                && latency_ms >= 0.0
                && (frames - frames.round()).abs() < 1e-6
                && frames <= 100.0,
            "--camera-latency-ms must be a whole number of frame periods ({} ms) up to 100 of \
             them, got {latency_ms}",
            base.run.frame_period_ms
        );
        set_in_table(
            &mut base.sections,
            &["plant", "camera", "latency_frames"],
            toml::Value::Integer(frames.round() as i64),
        )?;
    }
    if let Some(std) = args.coil_gain_error {
        anyhow::ensure!(
            std.is_finite() && (0.0..0.5).contains(&std),
            "--coil-gain-error must be within 0..0.5 (a fraction), got {std}"
        );
        set_in_table(
            &mut base.sections,
            &["plant", "physics", "coil_gain_error_std"],
            toml::Value::Float(std),
        )?;
    }
    if args.no_latency_compensation {
        set_in_table(
            &mut base.sections,
            &["control", "latency", "compensate"],
            toml::Value::Boolean(false),
        )?;
    }
    Ok(base)
}

/// The camera latency and whether control compensates it, for the table's header.
fn latency_note(base: &Scenario) -> String {
    let get = |path: &[&str]| {
        path.iter()
            .try_fold(None::<&toml::Value>, |at, key| {
                let table = match at {
                    None => Some(&base.sections),
                    Some(value) => value.as_table(),
                };
                table.and_then(|t| t.get(*key)).map(Some)
            })
            .flatten()
    };
    let frames = get(&["plant", "camera", "latency_frames"])
        .and_then(toml::Value::as_integer)
        .unwrap_or(0);
    let compensated = get(&["control", "latency", "compensate"])
        .and_then(toml::Value::as_bool)
        .unwrap_or(true);
    let gain_error = get(&["plant", "physics", "coil_gain_error_std"])
        .and_then(|v| v.as_float().or_else(|| v.as_integer().map(|i| i as f64)))
        .unwrap_or(millinav_plant::model::PlantPhysicsConfig::default().coil_gain_error_std);
    format!(
        "{} ms extra camera latency ({}), per-coil gain error σ {:.0} % unknown to control",
        frames as f64 * base.run.frame_period_ms,
        if compensated {
            "compensated"
        } else {
            "not compensated"
        },
        gain_error * 100.0
    )
}

/// The matrix's cells that `--beyond`, `--controllers` and `--only` select (at least one).
fn selected_cells(args: &Args, rig: &Rig) -> anyhow::Result<Vec<Cell>> {
    // Naming a beyond-the-paper controller asks for it, with or without --beyond.
    let beyond = args.beyond
        || args
            .controllers
            .iter()
            .any(|c| matches!(c.as_str(), "smc-dob-auto" | "smc-auto"));
    let all_controllers: Vec<String> =
        rig_matrix(rig, 1, true)
            .into_iter()
            .fold(Vec::new(), |mut names, c| {
                if !names.contains(&c.controller) {
                    names.push(c.controller);
                }
                names
            });
    if let Some(unknown) = args
        .controllers
        .iter()
        .find(|c| !all_controllers.contains(c))
    {
        anyhow::bail!(
            "unknown controller {unknown:?} in --controllers; known: {}",
            all_controllers.join(", ")
        );
    }
    let mut cells = rig_matrix(rig, args.trials.max(1), beyond);
    if !args.controllers.is_empty() {
        cells.retain(|c| args.controllers.contains(&c.controller));
    }
    if !args.only.is_empty() {
        cells.retain(|c| args.only.iter().any(|o| c.name().contains(o.as_str())));
    }
    anyhow::ensure!(
        !cells.is_empty(),
        "no cell of the matrix matches --only {:?} (cell names look like 4.3cp_q250_smc-dob-auto_s1)",
        args.only
    );
    Ok(cells)
}

/// Runs `work` on every item on `threads` workers with a progress bar (`label` names an item
/// and its result); returns the items with their results, in no particular order.
fn run_parallel<T: Send, R: Send>(
    items: Vec<T>,
    threads: usize,
    label: impl Fn(&T, &R) -> String + Sync,
    work: impl Fn(&T) -> anyhow::Result<R> + Sync,
) -> anyhow::Result<Vec<(T, R)>> {
    let bar = ProgressBar::new(items.len() as u64).with_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let done: Mutex<Vec<(T, R)>> = Mutex::new(Vec::new());
    let queue = Mutex::new(items);
    let poisoned = || anyhow::anyhow!("poisoned");
    let worker = || -> anyhow::Result<()> {
        loop {
            let Some(item) = queue.lock().map_err(|_| poisoned())?.pop() else {
                return Ok(());
            };
            let result = work(&item)?;
            bar.set_message(label(&item, &result));
            bar.inc(1);
            done.lock().map_err(|_| poisoned())?.push((item, result));
        }
    };
    std::thread::scope(|s| -> anyhow::Result<()> {
        let handles: Vec<_> = (0..threads).map(|_| s.spawn(worker)).collect();
        for h in handles {
            h.join().map_err(|_| anyhow::anyhow!("worker panicked"))??;
        }
        Ok(())
    })?;
    bar.finish();
    done.into_inner().map_err(|_| poisoned())
}

/// Runs every cell on `threads` workers with a progress bar; returns the outcomes (in no
/// particular order) and the first trials' traces.
fn run_cells(
    args: &Args,
    base: &Scenario,
    cells: Vec<Cell>,
    threads: usize,
) -> anyhow::Result<(Vec<Outcome>, FirstTrials)> {
    let bin_dir = std::env::current_exe()?
        .parent()
        .context("exe dir")?
        .to_owned();
    let runs = run_parallel(
        cells,
        threads,
        |cell, (_, m, _): &(Vec<TraceRow>, Metrics, f64)| {
            format!("{} RMSE {:.2} mm", cell.name(), m.rmse_mm)
        },
        |cell| run_cell(args, base, &bin_dir, cell),
    )?;
    let mut outcomes = Vec::with_capacity(runs.len());
    let mut traces = Vec::new();
    for (cell, (trace, metrics, wall_s)) in runs {
        if cell.seed == 1 {
            traces.push((cell.clone(), trace));
        }
        outcomes.push(Outcome {
            cell,
            metrics,
            wall_s,
        });
    }
    Ok((outcomes, traces))
}

/// The robustness matrix (`--robustness`): runs every case in fast mode and writes
/// robustness.csv, robustness.md and robustness.png into `--out`.
fn run_robustness(args: &Args, base: &Scenario) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.mode == Mode::Fast,
        "--robustness runs in fast mode only (thousands of runs; see README)"
    );
    let known = ["pid", "mpc", "smc-dob", "smc", "smc-dob-auto", "smc-auto"];
    let controllers: Vec<String> = if args.controllers.is_empty() {
        ["smc-dob-auto", "pid", "mpc", "smc-dob"]
            .map(String::from)
            .to_vec()
    } else {
        args.controllers.clone()
    };
    if let Some(unknown) = controllers.iter().find(|c| !known.contains(&c.as_str())) {
        anyhow::bail!(
            "unknown controller {unknown:?} in --controllers; known: {}",
            known.join(", ")
        );
    }
    let cases = robustness::cases(&controllers, args.trials.max(1));
    std::fs::create_dir_all(&args.out)?;
    let start = Instant::now();
    let runs = run_parallel(
        cases,
        args.threads.max(1),
        |case, m: &Metrics| format!("{} RMSE {:.2} mm", case.name(), m.rmse_mm),
        |case| {
            let text = robustness::case_scenario(base, case)?;
            let scenario = Scenario::parse(&text, &args.out.join(format!("{}.toml", case.name())))?;
            let trace = fast_run(&scenario)?;
            let reference = reference_of(&scenario)?;
            Ok(metrics(
                &trace,
                &reference,
                scenario.rig()?.coil_limits().coil_resistance_ohm,
            ))
        },
    )?;
    let outcomes: Vec<robustness::CaseOutcome> = runs
        .into_iter()
        .map(|(case, metrics)| robustness::CaseOutcome { case, metrics })
        .collect();
    let table = robustness::write_tables(&outcomes, &args.out)?;
    println!("{table}");
    println!(
        "{} runs in {:.1} s (fast mode, {} threads)",
        outcomes.len(),
        start.elapsed().as_secs_f64(),
        args.threads.max(1)
    );
    if report::register_font() {
        robustness::heat_map(&outcomes, &args.out.join("robustness.png"))?;
    } else {
        eprintln!("no DejaVu font found (apt install fonts-dejavu-core): heat map skipped");
    }
    Ok(())
}

/// One cell's run in the selected mode (with its Rerun recording in fast mode), its metrics,
/// and the seconds it took.
fn run_cell(
    args: &Args,
    base: &Scenario,
    bin_dir: &Path,
    cell: &Cell,
) -> anyhow::Result<(Vec<TraceRow>, Metrics, f64)> {
    let text = cell_scenario(base, cell)?;
    let scenario = Scenario::parse(&text, &args.out.join(format!("{}.toml", cell.name())))?;
    let t0 = Instant::now();
    let trace = match args.mode {
        Mode::Fast => fast_run(&scenario)?,
        Mode::Process if args.reuse_runs => {
            recorded_run(&text, &args.out.join("runs").join(cell.name()))?
        }
        Mode::Process => process_run(&text, bin_dir, &args.out.join("runs"), &cell.name())?,
    };
    let reference = reference_of(&scenario)?;
    if args.mode == Mode::Fast && !args.no_rrd {
        let runs = args.out.join("runs");
        std::fs::create_dir_all(&runs)?;
        write_rrd(
            &runs.join(format!("{}.rrd", cell.name())),
            &cell.name(),
            &trace,
            &reference,
        )?;
    }
    let m = metrics(
        &trace,
        &reference,
        scenario.rig()?.coil_limits().coil_resistance_ohm,
    );
    Ok((trace, m, t0.elapsed().as_secs_f64()))
}

/// results.csv and table.md (also printed).
fn write_tables(
    args: &Args,
    base: &Scenario,
    outcomes: &[Outcome],
    mode: &str,
) -> anyhow::Result<()> {
    report::write_csv(outcomes, &args.out.join("results.csv"))?;
    let rig = base.rig()?;
    // The paper's numbers and targets apply to the paper's rig only.
    let on_paper_rig = rig.path == fieldmaps::rigfile::paper_rig_path();
    let table = report::markdown_table(
        outcomes,
        &format!(
            "{mode}, {} ms frame period, {}, rig {} ({})",
            base.run.frame_period_ms,
            latency_note(base),
            rig.name,
            rig.path
                .strip_prefix(fieldmaps::data_root())
                .unwrap_or(&rig.path)
                .display()
        ),
        on_paper_rig,
    );
    let table = if on_paper_rig {
        table + &report::target_checks(outcomes)
    } else {
        table
    };
    std::fs::write(args.out.join("table.md"), &table)?;
    println!("{table}");
    Ok(())
}

/// The metric bar charts and, per condition, the first trials' trajectories.
fn write_figures(
    args: &Args,
    base: &Scenario,
    outcomes: &[Outcome],
    traces: &FirstTrials,
) -> anyhow::Result<()> {
    use report::BarMetric;
    let bars: [(BarMetric, &[&str], &str, &str); 4] = [
        (
            BarMetric::Rmse,
            &[],
            "RMSE by condition and controller (mean of trials)",
            "rmse_bars.png",
        ),
        (
            BarMetric::P95,
            &[],
            "P95 error by condition and controller (mean of trials)",
            "p95_bars.png",
        ),
        (
            BarMetric::Max,
            &[],
            "Max error by condition and controller (mean of trials)",
            "max_bars.png",
        ),
        (
            BarMetric::Rmse,
            &["smc-dob", "smc", "smc-dob-auto", "smc-auto"],
            "DOB ablation: RMSE with and without the observer",
            "dob_ablation.png",
        ),
    ];
    for (metric, only, title, file) in bars {
        report::metric_bars(outcomes, metric, only, title, &args.out.join(file))
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    let reference = reference_of(base)?;
    let mut conditions: Vec<(i64, String)> = traces
        .iter()
        .map(|(c, _)| ((c.viscosity_cp * 10.0) as i64, c.flow.label().to_string()))
        .collect();
    conditions.sort();
    conditions.dedup();
    for (v, flow) in conditions {
        let mut runs: Vec<(String, Vec<TraceRow>)> = traces
            .iter()
            .filter(|(c, _)| (c.viscosity_cp * 10.0) as i64 == v && c.flow.label() == flow)
            .map(|(c, t)| (c.controller.clone(), t.clone()))
            .collect();
        runs.sort_by(|a, b| a.0.cmp(&b.0));
        let title = format!("{} cP, {flow}", v as f64 / 10.0);
        let file = format!(
            "traces_{}cp_{}.png",
            v as f64 / 10.0,
            flow.replace([' ', '/'], "")
        );
        report::traces_figure(
            &runs,
            &reference,
            &base.rig()?.phantom.mask,
            &title,
            &args.out.join(file),
        )
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    Ok(())
}
