//! Running a campaign's cells: on worker threads here, as one Slurm array task (`run-cell`), and
//! following a submitted array until it leaves the queue.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;
use std::time::Duration;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};

use crate::campaign::{Campaign, CellFiles, CellResult, Mode, Progress, RunContext};
use crate::slurm;

pub fn progress_bar(len: usize) -> ProgressBar {
    ProgressBar::new(len as u64).with_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    )
}

/// Runs `work` on every item on `threads` workers with a progress bar (`label` names an item
/// and its result); returns the items with their results, in no particular order.
pub fn run_parallel<T: Send, R: Send>(
    items: Vec<T>,
    threads: usize,
    label: impl Fn(&T, &R) -> String + Sync,
    work: impl Fn(&T) -> anyhow::Result<R> + Sync,
) -> anyhow::Result<Vec<(T, R)>> {
    let bar = progress_bar(items.len());
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

/// Threads for cells here: fast mode as asked, process mode one cell at a time.
pub fn threads_for(mode: Mode, threads: usize) -> usize {
    match mode {
        Mode::Fast => threads.max(1),
        Mode::Process => 1,
    }
}

/// Runs `cells` of the campaign on `threads` workers here, each into its result file; a failing
/// cell writes why beside the results and does not stop the others.
pub fn run_here(
    campaign: &Campaign,
    build_sha256: &str,
    cells: Vec<usize>,
    threads: usize,
) -> anyhow::Result<()> {
    let never = AtomicBool::new(false);
    let context = RunContext {
        build_sha256,
        terminated: &never,
        slurm_task: None,
    };
    run_parallel(
        cells,
        threads,
        |&i, result: &Result<CellResult, String>| {
            let name = campaign.manifest.cells[i].name();
            match result {
                Ok(r) => format!("{name} RMSE {:.2} mm", r.metrics.rmse_mm),
                Err(e) => format!("{name} failed: {e}"),
            }
        },
        |&i| Ok(campaign.run_cell(i, &context).map_err(|e| format!("{e:#}"))),
    )?;
    Ok(())
}

/// The longest a result written on a compute node may take to show on this one (NFS
/// attribute caching).
const RESULT_VISIBILITY_GRACE_S: f64 = 5.0;

/// Looks at the queue every `poll_s` with a progress bar until nothing of the campaign is
/// left in it. A few failed looks in a row (a busy controller) are tolerated.
pub fn wait_for_slurm(campaign: &Campaign, poll_s: f64) -> anyhow::Result<Progress> {
    let bar = progress_bar(campaign.manifest.cells.len());
    let mut failed_looks = 0;
    let mut confirmed = false;
    loop {
        match slurm::progress(campaign) {
            Ok(p) => {
                failed_looks = 0;
                bar.set_position(p.done as u64);
                bar.set_message(format!(
                    "{} running, {} pending, {} failed",
                    p.running,
                    p.pending,
                    p.failed.len()
                ));
                if !p.in_flight() {
                    if p.failed.is_empty() || confirmed {
                        bar.finish();
                        return Ok(p);
                    }
                    // On a shared file system a result can show here a moment after its task
                    // left the queue: look once more before calling a cell failed.
                    confirmed = true;
                    std::thread::sleep(Duration::from_secs_f64(
                        poll_s.min(RESULT_VISIBILITY_GRACE_S),
                    ));
                    continue;
                }
            }
            Err(e) if failed_looks < 10 => {
                failed_looks += 1;
                bar.println(format!("looking at the queue failed (will retry): {e:#}"));
            }
            Err(e) => return Err(e),
        }
        std::thread::sleep(Duration::from_secs_f64(poll_s));
    }
}

/// Raised by SIGTERM (Slurm's time limit, preemption, scancel): a task stops, writes no
/// result, and leaves no shared memory behind.
static TERMINATED: AtomicBool = AtomicBool::new(false);

extern "C" fn on_sigterm(_: nix::libc::c_int) {
    TERMINATED.store(true, Ordering::SeqCst);
}

fn install_sigterm_handler() -> anyhow::Result<()> {
    use nix::sys::signal::{sigaction, SaFlags, SigAction, SigHandler, SigSet, Signal};
    let action = SigAction::new(
        SigHandler::Handler(on_sigterm),
        SaFlags::SA_RESTART,
        SigSet::empty(),
    );
    // SAFETY: the handler only stores to an atomic, which is async-signal-safe.
    unsafe { sigaction(Signal::SIGTERM, &action) }.context("installing the SIGTERM handler")?;
    Ok(())
}

/// Which cells one `run-cell` runs.
pub enum TaskCells<'a> {
    /// The cells of this Slurm array task.
    ArrayTask(usize),
    /// One cell, by name.
    Named(&'a str),
}

/// How a task ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TaskEnd {
    Finished,
    /// Some cells failed (each says why in its failure file and on stderr).
    CellsFailed,
    /// SIGTERM stopped it.
    Terminated,
}

/// One `run-cell`: checks the build, then runs the selected cells that have no result yet
/// (fast mode on `threads`, default SLURM_CPUS_PER_TASK or 1), stopping on SIGTERM.
pub fn run_task(
    campaign: &Campaign,
    selection: TaskCells<'_>,
    threads: Option<usize>,
) -> anyhow::Result<TaskEnd> {
    install_sigterm_handler()?;
    let manifest = &campaign.manifest;
    let cells: Vec<usize> = match selection {
        TaskCells::Named(name) => vec![manifest
            .cells
            .iter()
            .position(|c| c.name() == name)
            .with_context(|| {
                format!(
                    "no cell {name:?} in the campaign {} (cells look like {})",
                    campaign.dir.display(),
                    manifest.cells[0].name()
                )
            })?],
        TaskCells::ArrayTask(task) => {
            let per_task = manifest.slurm.as_ref().map_or(1, |s| s.cells_per_task);
            let range = slurm::cells_of_task(task, per_task, manifest.cells.len());
            anyhow::ensure!(
                !range.is_empty(),
                "array task {task} has no cells: the campaign has {} cells, {per_task} per task",
                manifest.cells.len()
            );
            range.collect()
        }
    };
    let slurm_task = match (
        std::env::var("SLURM_ARRAY_JOB_ID"),
        std::env::var("SLURM_ARRAY_TASK_ID"),
    ) {
        (Ok(job), Ok(task)) => Some(format!("{job}_{task}")),
        _ => None,
    };
    if manifest.mode == Mode::Process {
        // What tasks killed outright on this node left behind.
        let removed = crate::sweep_stale_iox(&campaign.iox_tag());
        if removed > 0 {
            eprintln!("removed {removed} iceoryx2 files of killed runs of this campaign");
        }
    } else {
        // A fast-mode cell cannot stop half way: leave at once, writing nothing.
        std::thread::spawn(|| loop {
            if TERMINATED.load(Ordering::SeqCst) {
                eprintln!("terminated by SIGTERM: no result written");
                std::process::exit(143);
            }
            std::thread::sleep(Duration::from_millis(100));
        });
    }
    let build = match campaign.check_build() {
        Ok(hash) => hash,
        Err(e) => {
            // Every cell of the task says why it did not run.
            for &i in &cells {
                campaign.mark_failed(i, &format!("{e:#}"));
            }
            return Err(e);
        }
    };
    let todo: Vec<usize> = cells
        .into_iter()
        .filter(|&i| campaign.cell_files(i) != CellFiles::Done)
        .collect();
    let threads = match manifest.mode {
        Mode::Process => 1,
        Mode::Fast => threads
            .or_else(|| std::env::var("SLURM_CPUS_PER_TASK").ok()?.parse().ok())
            .unwrap_or(1)
            .max(1),
    };
    let context = RunContext {
        build_sha256: &build,
        terminated: &TERMINATED,
        slurm_task,
    };
    let results = run_parallel(
        todo,
        threads,
        |&i, result: &Result<f64, String>| {
            let name = manifest.cells[i].name();
            match result {
                Ok(rmse) => format!("{name} RMSE {rmse:.2} mm"),
                Err(e) => format!("{name} failed: {e}"),
            }
        },
        |&i| {
            if TERMINATED.load(Ordering::SeqCst) {
                return Ok(Err(crate::Terminated.to_string()));
            }
            Ok(campaign
                .run_cell(i, &context)
                .map(|r| r.metrics.rmse_mm)
                .map_err(|e| format!("{e:#}")))
        },
    )?;
    let mut failed = false;
    for (i, result) in &results {
        if let Err(e) = result {
            failed = true;
            eprintln!("{}: {e}", manifest.cells[*i].name());
        }
    }
    Ok(if TERMINATED.load(Ordering::SeqCst) {
        TaskEnd::Terminated
    } else if failed {
        TaskEnd::CellsFailed
    } else {
        TaskEnd::Finished
    })
}
