//! `experiments`: the paper's matrix (or the robustness matrix) on the twin, run as a campaign
//! on this machine or as a Slurm job array, with tables and figures.
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Context;
use clap::{Args, Parser, Subcommand, ValueEnum};
use fieldmaps::rigfile::Rig;
use millinav_experiments::campaign::{
    Campaign, CellSpec, MatrixKind, MatrixPlan, Mode, Planned, Progress,
};
use millinav_experiments::runner::{self, TaskCells, TaskEnd};
use millinav_experiments::slurm::{self, SlurmSettings};
use millinav_experiments::{
    add_capture_to_coils_delay, keys, noise_floor, report, rig_matrix, robustness,
    MAX_LATENCY_FRAMES,
};
use millinav_kit::scenario::Scenario;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Backend {
    /// Worker threads on this machine.
    Local,
    /// One Slurm job array: one task per cell (or per --cells-per-task cells), submitted with
    /// sbatch from this machine; the output directory must be on a file system the compute
    /// nodes share.
    Slurm,
}

/// Runs the paper's matrix (viscosity x flow x controller x trials, from the base scenario's
/// rig) or the robustness matrix on the digital twin as a campaign in --out: every cell runs
/// (`run-cell`) into a result file of its own, on local threads or as Slurm array tasks, and
/// `collect` turns the result files into results.csv, table.md and PNG figures.
#[derive(Parser)]
#[command(name = "experiments", version, args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    matrix: MatrixArgs,
}

#[derive(Subcommand)]
enum Command {
    /// Runs cells of a planned campaign and writes their result files (what each Slurm array
    /// task runs; also to re-run one cell by hand).
    RunCell(RunCellArgs),
    /// Where a campaign stands: cells done, running, pending, and failed or missing (by name,
    /// with why). Exits 1 when cells failed and nothing is left in flight.
    Status {
        /// The campaign's --out directory.
        dir: PathBuf,
        /// Wait (with a progress bar) until nothing of it is left in the Slurm queue.
        #[arg(long)]
        wait: bool,
    },
    /// Runs again every cell of a campaign that has no result (failed, killed, never run):
    /// resubmits their array tasks on Slurm, or runs them here for a local campaign; then
    /// waits and collects.
    Resume {
        /// The campaign's --out directory.
        dir: PathBuf,
        /// Submit and return without waiting.
        #[arg(long)]
        no_wait: bool,
        /// Worker threads (a local campaign).
        #[arg(long, default_value_t = 2)]
        threads: usize,
        #[command(flatten)]
        slurm: SlurmArgs,
    },
    /// Turns a campaign's result files into results.csv, table.md and the figures in its
    /// directory; names the cells that have no result.
    Collect {
        /// The campaign's --out directory.
        dir: PathBuf,
    },
}

#[derive(Args)]
struct RunCellArgs {
    /// The campaign's --out directory.
    #[arg(long)]
    campaign: PathBuf,
    /// Run the cells of this array task (Slurm's SLURM_ARRAY_TASK_ID).
    #[arg(long, conflicts_with = "cell", required_unless_present = "cell")]
    array_task: Option<usize>,
    /// Run this cell (its name, e.g. 20cp_q180_pid_s1).
    #[arg(long)]
    cell: Option<String>,
    /// Worker threads for fast-mode cells (default: SLURM_CPUS_PER_TASK, else 1).
    #[arg(long)]
    threads: Option<usize>,
}

#[derive(Args)]
struct MatrixArgs {
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
    /// Camera exposure period (ms), a whole multiple of the frame period: a camera (or vision)
    /// slower than the coil loop, which keeps the frame period and is fed the latest exposure
    /// again between exposures (`[plant.camera] exposure_period_frames`); e.g. 100 on the base
    /// scenario's 10 ms frames: a 10 Hz camera under a 100 Hz coil loop.
    #[arg(long)]
    camera_period_ms: Option<f64>,
    /// Extra latency from capture to the coils (ms) on top of the frame period, instead of the
    /// base scenario's `[plant.camera] latency_frames`, e.g. 100 at 10 Hz: whole frame periods
    /// are camera latency (control measures it from the frames' stamps), the rest a delay inside
    /// the frame added to `--command-delay-ms` (or the base scenario's) and told to control, so
    /// 50 ms at 10 Hz or 35 ms at 100 Hz run as well. At most 100 frame periods.
    #[arg(long)]
    camera_latency_ms: Option<f64>,
    /// Delay from a frame's capture to its command reaching the coils inside each frame (ms,
    /// below the frame period: inference, control, serial link), instead of none: sets the
    /// twin's `[plant] command_delay_ms` and tells control, as a lab would measure it
    /// (`[control.latency] unstamped_delay_ms`), e.g. 60 at 10 Hz for the paper's pipeline.
    #[arg(long)]
    command_delay_ms: Option<f64>,
    /// Standard deviation of the twin's per-coil gain error that control does not know
    /// (`[plant.physics] coil_gain_error_std`, a fraction: 0.1 for 10 %) instead of the base
    /// scenario's.
    #[arg(long)]
    coil_gain_error: Option<f64>,
    /// Feed the controllers the delayed pose as measured (`[control.latency] compensate =
    /// false`) instead of the state predicted for the actuation time.
    #[arg(long)]
    no_latency_compensation: bool,
    /// Set one key of the base scenario's service tables for every cell, e.g.
    /// `--set plant.physics.floor_gap_m=3e-6` or `--set control.velocity_filter_ms=60`
    /// (repeatable; VALUE is TOML; applied after the flags above, checked by the services).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    settings: Vec<String>,
    /// Skip the per-run Rerun recordings of fast mode (`<out>/runs/<cell>.rrd`; process mode
    /// always keeps each run's `run.rrd` under `<out>/runs/<cell>/run/`).
    #[arg(long)]
    no_rrd: bool,
    /// Fast mode: keep every run's trace (`<out>/campaign/traces/<cell>.csv`: position,
    /// velocity, magnet heading, true flow and coil currents per frame), not only each cell's
    /// first trial, which the figures use.
    #[arg(long)]
    every_trace: bool,
    /// Process mode: take each cell's ground truth from an earlier run of the same cell under
    /// `<out>/runs/` instead of running it again (to re-report after a change to the metrics or
    /// figures). A cell whose recorded scenario differs is an error; wall_s then is read time.
    #[arg(long)]
    reuse_runs: bool,
    /// Run the robustness matrix instead of the paper's: the rig's most viscous fluid at its
    /// lowest flow (20 cP at 7 cm/s on the paper's rig) with one disturbance varied at a time
    /// (pulsation rate and amplitude, flow noise, recirculation, per-coil gain error, camera
    /// latency, the rig's viscosities at that flow) at 10 and 100 Hz, for the scheduled SMC-DOB
    /// and the baselines (or --controllers); writes robustness.csv, robustness.md,
    /// robustness.png.
    #[arg(long)]
    robustness: bool,
    /// Run nothing: print, for every condition of the selected cells, the tracking error (RMS,
    /// mm) that no controller can beat in the twin's flow noise with these poses (frame period,
    /// camera latency, command delay, fast mode's pose noise): the Kalman predictor's error
    /// when the coils act, for the capsule with its linear drag and for a body that follows the
    /// flow at once (README, "The flow noise's floor"); and the error the pump's stroke, known
    /// exactly, leaves under a force held over each loop frame (README, "The pump's stroke
    /// under the loop's hold").
    #[arg(long, conflicts_with = "robustness")]
    noise_floor: bool,
    /// Worker threads (local backend, fast mode; process mode runs one cell at a time).
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Output directory: tables and figures, and the campaign (`<out>/campaign/`: the plan,
    /// every cell's scenario and result file). An --out that holds the same matrix of the same
    /// build keeps its finished cells; one of another build or matrix is refused.
    #[arg(long, default_value = "results")]
    out: PathBuf,
    /// Where the cells run.
    #[arg(long, value_enum, default_value = "local")]
    backend: Backend,
    /// Delete a campaign already in --out (another build's or matrix's) and start over.
    #[arg(long)]
    fresh: bool,
    /// Slurm: submit and return; follow with `experiments status DIR --wait`, then
    /// `experiments collect DIR`.
    #[arg(long)]
    no_wait: bool,
    #[command(flatten)]
    slurm: SlurmArgs,
}

/// How the Slurm array is submitted (the flags override --slurm-config's keys).
#[derive(Args, Clone, Default)]
struct SlurmArgs {
    /// TOML with the keys partition, time, cpus_per_task, cells_per_task, max_parallel,
    /// sbatch_lines (a list of options), setup, job_name, poll_s.
    #[arg(long, help_heading = "Slurm")]
    slurm_config: Option<PathBuf>,
    /// Partition of every array task (default: the cluster's default partition).
    #[arg(long, help_heading = "Slurm")]
    partition: Option<String>,
    /// Time limit of one array task, in sbatch's forms (e.g. 00:30:00 or 1-00:00:00).
    #[arg(long, help_heading = "Slurm")]
    time: Option<String>,
    /// CPUs of one array task; its fast-mode cells run on as many threads.
    #[arg(long, help_heading = "Slurm")]
    cpus_per_task: Option<u32>,
    /// Cells one array task runs (default 1; fixed once a campaign is submitted).
    #[arg(long, help_heading = "Slurm")]
    cells_per_task: Option<usize>,
    /// At most this many array tasks at once.
    #[arg(long, help_heading = "Slurm")]
    max_parallel: Option<u32>,
    /// A further #SBATCH option (repeatable), e.g. --sbatch-line=--mem=2G.
    #[arg(
        long = "sbatch-line",
        help_heading = "Slurm",
        allow_hyphen_values = true
    )]
    sbatch_lines: Vec<String>,
    /// A shell command each task runs first, e.g. "module load opencv".
    #[arg(long, help_heading = "Slurm")]
    setup: Option<String>,
    /// Seconds between two looks at the queue while waiting.
    #[arg(long, help_heading = "Slurm")]
    poll_s: Option<f64>,
}

impl SlurmArgs {
    /// `base` (a campaign's earlier settings, or the defaults), then --slurm-config, then the
    /// flags.
    fn settings(&self, base: SlurmSettings) -> anyhow::Result<SlurmSettings> {
        let mut s = match &self.slurm_config {
            Some(path) => SlurmSettings::load(path)?,
            None => base,
        };
        if let Some(v) = &self.partition {
            s.partition = Some(v.clone());
        }
        if let Some(v) = &self.time {
            s.time = Some(v.clone());
        }
        if let Some(v) = self.cpus_per_task {
            s.cpus_per_task = v;
        }
        if let Some(v) = self.cells_per_task {
            s.cells_per_task = v;
        }
        if let Some(v) = self.max_parallel {
            s.max_parallel = Some(v);
        }
        if !self.sbatch_lines.is_empty() {
            s.sbatch_lines = self.sbatch_lines.clone();
        }
        if let Some(v) = &self.setup {
            s.setup = Some(v.clone());
        }
        if let Some(v) = self.poll_s {
            s.poll_s = v;
        }
        s.validate()?;
        Ok(s)
    }

    fn given(&self) -> bool {
        self.slurm_config.is_some()
            || self.partition.is_some()
            || self.time.is_some()
            || self.cpus_per_task.is_some()
            || self.cells_per_task.is_some()
            || self.max_parallel.is_some()
            || !self.sbatch_lines.is_empty()
            || self.setup.is_some()
            || self.poll_s.is_some()
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let outcome = match cli.command {
        None => run_matrix(&cli.matrix),
        Some(Command::RunCell(args)) => run_cell(&args),
        Some(Command::Status { dir, wait }) => status(&dir, wait),
        Some(Command::Resume {
            dir,
            no_wait,
            threads,
            slurm,
        }) => resume(&dir, no_wait, threads, &slurm),
        Some(Command::Collect { dir }) => collect(&dir).map(|()| ExitCode::SUCCESS),
    };
    match outcome {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}

/// `--noise-floor`'s table (the paper's numbers only on the paper's rig).
fn print_noise_floors(rows: &[noise_floor::FloorRow], on_paper_rig: bool) {
    println!(
        "| condition | loop | pose age when the coils act (ms) | noise RMS (mm/s) | floor RMSE (mm) \
         | floor, following the flow (mm) | pulsation known, held per frame (mm) | paper SMC-DOB (mm) |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for row in rows {
        let s = &row.sampling;
        let youngest_ms = (s.latency_frames as f64 * s.frame_period_s + s.command_delay_s) * 1e3;
        let paper = report::paper_smc_dob_rmse_mm(row.viscosity_cp, row.flow)
            .filter(|_| on_paper_rig)
            .map_or("–".to_string(), |v| format!("{v:.2}"));
        // Not computed for a pump slower than the cycle the floor is solved over.
        let held_stroke = if row.pulsation_hold_floor_m.is_finite() {
            format!("{:.3}", row.pulsation_hold_floor_m * 1e3)
        } else {
            "–".to_string()
        };
        println!(
            "| {} cP, {} | {:.0} Hz | {:.0}–{:.0} | {:.1} | {:.3} | {:.3} | {} | {} |",
            row.viscosity_cp,
            row.flow.label(),
            1.0 / s.frame_period_s,
            youngest_ms,
            youngest_ms + s.frame_period_s * 1e3,
            row.noise_rms_speed_mps * 1e3,
            row.floor_m * 1e3,
            row.fluid_particle_floor_m * 1e3,
            held_stroke,
            paper
        );
    }
}

/// Plans the matrix into --out, runs it on the chosen backend, and collects it.
fn run_matrix(args: &MatrixArgs) -> anyhow::Result<ExitCode> {
    let base = load_base(args)?;
    if args.noise_floor {
        let rig = base.rig()?;
        let cells = selected_cells(args, &rig)?;
        let on_paper_rig = rig.path == fieldmaps::rigfile::paper_rig_path();
        print_noise_floors(&noise_floor::condition_floors(&base, &cells)?, on_paper_rig);
        return Ok(ExitCode::SUCCESS);
    }
    anyhow::ensure!(
        !args.reuse_runs || args.mode == Mode::Process,
        "--reuse-runs reads earlier process-mode runs: use it with --mode process"
    );
    anyhow::ensure!(
        args.backend == Backend::Slurm || !args.slurm.given() && !args.no_wait,
        "Slurm options (--partition, --time, --no-wait, …) go with --backend slurm"
    );
    let (matrix, cells) = if args.robustness {
        (
            MatrixKind::Robustness,
            robustness_cases(args, &*base.rig()?)?,
        )
    } else {
        let rig = base.rig()?;
        (
            MatrixKind::Paper,
            selected_cells(args, &rig)?
                .into_iter()
                .map(CellSpec::Paper)
                .collect(),
        )
    };
    let settings = match args.backend {
        Backend::Local => None,
        Backend::Slurm => {
            let settings = args.slurm.settings(SlurmSettings::default())?;
            slurm::preflight(&settings)?;
            Some(settings)
        }
    };
    if !args.fresh {
        if let Ok(old) = Campaign::open(&args.out) {
            let jobs = slurm::submissions(&old)?;
            if !jobs.is_empty() {
                anyhow::bail!(
                    "{} holds a campaign submitted to Slurm (job {}): follow it with `experiments \
                     status {dir}`, run what is missing with `experiments resume {dir}`, or \
                     start over with --fresh",
                    old.dir.display(),
                    jobs.iter()
                        .map(|j| j.job_id.as_str())
                        .collect::<Vec<_>>()
                        .join(", "),
                    dir = args.out.display()
                );
            }
        }
    }
    let start = Instant::now();
    let mode = args.mode;
    let (campaign, planned) = Campaign::plan(
        &args.out,
        MatrixPlan {
            matrix,
            mode,
            table_header: report::table_header(mode.name(), &base)?,
            base,
            cells,
            write_rrd: !args.no_rrd,
            every_trace: args.every_trace,
            reuse_runs: args.reuse_runs,
            bin_dir: bin_dir()?,
            slurm: settings.clone(),
        },
        args.fresh,
    )?;
    let unfinished = campaign.unfinished();
    if planned == Planned::Existing {
        println!(
            "{}: {} of {} cells already have results (same build and matrix); running the {} \
             others",
            campaign.dir.display(),
            campaign.manifest.cells.len() - unfinished.len(),
            campaign.manifest.cells.len(),
            unfinished.len()
        );
    }
    match settings {
        None => {
            let threads = runner::threads_for(mode, args.threads);
            let build = campaign.manifest.build.sha256.clone();
            runner::run_here(&campaign, &build, unfinished, threads)?;
            finish(&campaign, &campaign.local_progress(), start, threads)
        }
        Some(settings) => submit_and_follow(&campaign, &settings, &unfinished, args.no_wait, start),
    }
}

/// Submits the tasks of `cells`, then (unless `no_wait`) follows them and collects.
fn submit_and_follow(
    campaign: &Campaign,
    settings: &SlurmSettings,
    cells: &[usize],
    no_wait: bool,
    start: Instant,
) -> anyhow::Result<ExitCode> {
    if cells.is_empty() {
        println!("every cell has a result already");
        return finish(campaign, &slurm::progress(campaign)?, start, 0);
    }
    let mut tasks: Vec<usize> = cells
        .iter()
        .map(|&c| slurm::task_of(c, settings.cells_per_task))
        .collect();
    tasks.dedup();
    let submission = slurm::submit(campaign, settings, &tasks)?;
    println!(
        "submitted {} cells as {} array tasks of job {} ({})",
        cells.len(),
        tasks.len(),
        submission.job_id,
        campaign.dir.join("slurm").join("job.sh").display()
    );
    let dir = campaign.out.display();
    if no_wait {
        println!(
            "follow it with `experiments status {dir} --wait`, then `experiments collect {dir}` \
             (or `experiments resume {dir}` for what failed)"
        );
        return Ok(ExitCode::SUCCESS);
    }
    let progress = runner::wait_for_slurm(campaign, settings.poll_s)?;
    finish(campaign, &progress, start, 0)
}

/// Collects a campaign whose cells all finished, or names the ones that did not.
fn finish(
    campaign: &Campaign,
    progress: &Progress,
    start: Instant,
    threads: usize,
) -> anyhow::Result<ExitCode> {
    if !progress.failed.is_empty() {
        report_failures(campaign, progress);
        return Ok(ExitCode::from(1));
    }
    let table = campaign.collect()?;
    println!("{table}");
    let backend = if campaign.manifest.slurm.is_some() {
        "Slurm".to_string()
    } else {
        format!("{threads} threads")
    };
    println!(
        "{} runs in {:.1} s ({} mode, {backend}); tables and figures in {}",
        progress.total,
        start.elapsed().as_secs_f64(),
        campaign.manifest.mode.name(),
        campaign.out.display()
    );
    Ok(ExitCode::SUCCESS)
}

fn report_failures(campaign: &Campaign, progress: &Progress) {
    eprintln!("{}", progress.line());
    for (name, why) in &progress.failed {
        eprintln!("  {name}: {why}");
    }
    eprintln!(
        "run them again with `experiments resume {}`",
        campaign.out.display()
    );
}

/// `run-cell`: the cells of one array task (or one named cell), one result file each.
fn run_cell(args: &RunCellArgs) -> anyhow::Result<ExitCode> {
    let campaign = Campaign::open(&args.campaign)?;
    let selection = match (&args.cell, args.array_task) {
        (Some(name), _) => TaskCells::Named(name),
        (None, Some(task)) => TaskCells::ArrayTask(task),
        (None, None) => anyhow::bail!("give --array-task or --cell"),
    };
    Ok(
        match runner::run_task(&campaign, selection, args.threads)? {
            TaskEnd::Finished => ExitCode::SUCCESS,
            TaskEnd::CellsFailed => ExitCode::from(1),
            TaskEnd::Terminated => ExitCode::from(143),
        },
    )
}

/// `status`: the campaign's progress, and the failed or missing cells with why.
fn status(dir: &Path, wait: bool) -> anyhow::Result<ExitCode> {
    let campaign = Campaign::open(dir)?;
    let progress = match &campaign.manifest.slurm {
        None => campaign.local_progress(),
        Some(settings) if wait => runner::wait_for_slurm(&campaign, settings.poll_s)?,
        Some(_) => slurm::progress(&campaign)?,
    };
    println!("{}: {}", campaign.dir.display(), progress.line());
    if progress.in_flight() {
        return Ok(ExitCode::SUCCESS);
    }
    if progress.failed.is_empty() {
        println!(
            "every cell has a result: `experiments collect {}` writes the tables",
            campaign.out.display()
        );
        return Ok(ExitCode::SUCCESS);
    }
    report_failures(&campaign, &progress);
    Ok(ExitCode::from(1))
}

/// `resume`: runs again every cell without a result.
fn resume(dir: &Path, no_wait: bool, threads: usize, args: &SlurmArgs) -> anyhow::Result<ExitCode> {
    let start = Instant::now();
    let mut campaign = Campaign::open(dir)?;
    let build = campaign.check_build()?;
    let unfinished = campaign.unfinished();
    let Some(old) = campaign.manifest.slurm.clone() else {
        anyhow::ensure!(
            !args.given() && !no_wait,
            "{} ran on this machine: Slurm options do not apply to its resume",
            campaign.dir.display()
        );
        report_resumed(&campaign, &campaign.local_progress());
        let threads = runner::threads_for(campaign.manifest.mode, threads);
        campaign.clear_failures(&unfinished);
        runner::run_here(&campaign, &build, unfinished, threads)?;
        return finish(&campaign, &campaign.local_progress(), start, threads);
    };
    let settings = args.settings(old.clone())?;
    anyhow::ensure!(
        settings.cells_per_task == old.cells_per_task,
        "the campaign was submitted with {} cells per task; its array tasks keep that",
        old.cells_per_task
    );
    slurm::preflight(&settings)?;
    let progress = slurm::progress(&campaign)?;
    if progress.in_flight() {
        anyhow::bail!(
            "{} of the campaign's cells are still in the Slurm queue ({}); wait for them \
             (`experiments status {} --wait`) or scancel them first",
            progress.running + progress.pending,
            progress.line(),
            campaign.out.display()
        );
    }
    report_resumed(&campaign, &progress);
    campaign.clear_failures(&unfinished);
    campaign.manifest.slurm = Some(settings.clone());
    campaign.write_manifest()?;
    submit_and_follow(&campaign, &settings, &unfinished, no_wait, start)
}

fn report_resumed(campaign: &Campaign, progress: &Progress) {
    println!(
        "{}: {}; running again:",
        campaign.dir.display(),
        progress.line()
    );
    for (name, why) in &progress.failed {
        println!("  {name} ({why})");
    }
}

/// `collect`: the tables and figures from the result files.
fn collect(dir: &Path) -> anyhow::Result<()> {
    let campaign = Campaign::open(dir)?;
    let table = campaign.collect()?;
    println!("{table}");
    println!(
        "{} cells collected into {}",
        campaign.manifest.cells.len(),
        campaign.out.display()
    );
    Ok(())
}

fn bin_dir() -> anyhow::Result<PathBuf> {
    Ok(std::env::current_exe()?
        .parent()
        .context("the experiments binary has no folder")?
        .to_owned())
}

/// The base scenario, with `--frame-period-ms`, `--camera-latency-ms`, `--coil-gain-error`,
/// `--no-latency-compensation` and every `--set` applied.
fn load_base(args: &MatrixArgs) -> anyhow::Result<Scenario> {
    let mut base = Scenario::load(&args.base)
        .with_context(|| format!("base scenario {}", args.base.display()))?;
    if let Some(period) = args.frame_period_ms {
        anyhow::ensure!(
            period.is_finite() && (1.0..=1000.0).contains(&period),
            "--frame-period-ms must be within 1..=1000, got {period}"
        );
        base.run.frame_period_ms = period;
    }
    if let Some(camera_ms) = args.camera_period_ms {
        let frames = camera_ms / base.run.frame_period_ms;
        anyhow::ensure!(
            frames.is_finite()
                && (frames - frames.round()).abs() < 1e-9
                && (1.0..=f64::from(millinav_plant::MAX_EXPOSURE_PERIOD_FRAMES))
                    .contains(&frames.round()),
            "--camera-period-ms must be a whole multiple (1 to {}) of the frame period ({} ms), \
             got {camera_ms}",
            millinav_plant::MAX_EXPOSURE_PERIOD_FRAMES,
            base.run.frame_period_ms
        );
        keys::CAMERA_EXPOSURE_PERIOD_FRAMES.set(&mut base.sections, frames.round() as i64)?;
    }
    if let Some(delay_ms) = args.command_delay_ms {
        anyhow::ensure!(
            delay_ms.is_finite() && delay_ms >= 0.0 && delay_ms < base.run.frame_period_ms,
            "--command-delay-ms must be >= 0 and below the frame period ({} ms; whole frames of \
             delay are --camera-latency-ms), got {delay_ms}",
            base.run.frame_period_ms
        );
        for key in [keys::COMMAND_DELAY_MS, keys::UNSTAMPED_DELAY_MS] {
            key.set(&mut base.sections, delay_ms)?;
        }
    }
    if let Some(latency_ms) = args.camera_latency_ms {
        anyhow::ensure!(
            latency_ms.is_finite()
                && latency_ms >= 0.0
                && latency_ms <= MAX_LATENCY_FRAMES as f64 * base.run.frame_period_ms,
            "--camera-latency-ms must be within 0..={} ({MAX_LATENCY_FRAMES} frame periods of {} \
             ms), got {latency_ms}",
            MAX_LATENCY_FRAMES as f64 * base.run.frame_period_ms,
            base.run.frame_period_ms
        );
        keys::CAMERA_LATENCY_FRAMES.set(&mut base.sections, 0)?;
        add_capture_to_coils_delay(&mut base.sections, latency_ms, base.run.frame_period_ms)?;
    }
    if let Some(std) = args.coil_gain_error {
        anyhow::ensure!(
            std.is_finite() && (0.0..0.5).contains(&std),
            "--coil-gain-error must be within 0..0.5 (a fraction), got {std}"
        );
        keys::COIL_GAIN_ERROR_STD.set(&mut base.sections, std)?;
    }
    if args.no_latency_compensation {
        keys::LATENCY_COMPENSATE.set(&mut base.sections, false)?;
    }
    for setting in &args.settings {
        millinav_experiments::apply_setting(&mut base.sections, setting)?;
    }
    if !args.settings.is_empty() {
        // A misspelt key or a bad value fails here, naming the field, not in every cell.
        let what = || format!("--set {}", args.settings.join(" --set "));
        millinav_plant::check_config(&base).with_context(what)?;
        millinav_control::check_config(&base).with_context(what)?;
        millinav_flow::check_config(&base).with_context(what)?;
        millinav_coilbus::check_config(&base).with_context(what)?;
        if args
            .settings
            .iter()
            .any(|s| s.trim_start().starts_with("vision."))
        {
            millinav_vision::check_config(&base).with_context(what)?;
        }
    }
    Ok(base)
}

/// The matrix's cells that `--beyond`, `--controllers` and `--only` select (at least one).
fn selected_cells(args: &MatrixArgs, rig: &Rig) -> anyhow::Result<Vec<millinav_experiments::Cell>> {
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

/// The robustness matrix's cases on `rig` for `--controllers` (default: the scheduled SMC-DOB
/// and the baselines), `--only` applied to their names.
fn robustness_cases(args: &MatrixArgs, rig: &Rig) -> anyhow::Result<Vec<CellSpec>> {
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
    let around = robustness::Around::on_rig(rig)?;
    let mut cases = robustness::cases(&controllers, args.trials.max(1), &around);
    if !args.only.is_empty() {
        cases.retain(|c| args.only.iter().any(|o| c.name().contains(o.as_str())));
    }
    anyhow::ensure!(
        !cases.is_empty(),
        "no case of the robustness matrix matches --only {:?} (names look like \
         pulsation-hz_1_100ms_pid_s1)",
        args.only
    );
    Ok(cases.into_iter().map(CellSpec::Robustness).collect())
}
