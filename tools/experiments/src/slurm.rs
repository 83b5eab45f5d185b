//! The Slurm backend: a campaign's cells as one job array (one array task per cell, or per
//! `cells_per_task` cells), each task running `experiments run-cell` on the shared campaign
//! directory. Progress comes from `squeue` and the result files; a task's end state from `sacct`
//! where the cluster keeps accounting, else from `scontrol` while the controller remembers it.

use std::cell::OnceCell;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context};
use serde::{Deserialize, Serialize};

use crate::campaign::{Campaign, CellFiles, Progress};
pub use crate::slurm_settings::{valid_time_limit, SlurmSettings};

/// Where a program is on `PATH`, if it is.
pub fn find_on_path(program: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|dir| dir.join(program))
            .find(|p| p.is_file())
    })
}

/// Runs a Slurm command and returns its standard output; an error with its standard error.
fn slurm_command(program: &str, args: &[&str]) -> anyhow::Result<String> {
    let output = Command::new(program)
        .args(args)
        .output()
        .with_context(|| format!("running {program}"))?;
    if !output.status.success() {
        bail!(
            "{program} {} failed ({}): {}",
            args.join(" "),
            output.status,
            String::from_utf8_lossy(&output.stderr).trim()
        );
    }
    Ok(String::from_utf8_lossy(&output.stdout).into_owned())
}

/// Refuses a submission that cannot work, before anything is submitted: the Slurm commands
/// missing, the controller unreachable, a partition that does not exist.
pub fn preflight(settings: &SlurmSettings) -> anyhow::Result<()> {
    settings.validate()?;
    for program in ["sbatch", "squeue", "sinfo"] {
        if find_on_path(program).is_none() {
            bail!(
                "{program} is not on PATH: the Slurm backend submits with sbatch and follows the \
                 tasks with squeue from this machine (a login node with the Slurm client \
                 commands; Debian: apt install slurm-client)"
            );
        }
    }
    let listing = slurm_command("sinfo", &["-h", "-o", "%P"])
        .context("asking the cluster for its partitions (is slurmctld reachable?)")?;
    let partitions: Vec<String> = listing
        .lines()
        .map(|l| l.trim().trim_end_matches('*').to_owned())
        .filter(|l| !l.is_empty())
        .collect();
    if let Some(partition) = &settings.partition {
        if !partitions.iter().any(|p| p == partition) {
            bail!(
                "partition {partition:?} does not exist on this cluster; its partitions: {}",
                partitions.join(", ")
            );
        }
    } else if !listing.lines().any(|l| l.trim().ends_with('*')) {
        bail!(
            "the cluster has no default partition: name one with --partition ({})",
            partitions.join(", ")
        );
    }
    Ok(())
}

/// The cluster's largest array index + 1 (`MaxArraySize`), when `scontrol` says.
fn max_array_size() -> Option<usize> {
    let config = slurm_command("scontrol", &["show", "config"]).ok()?;
    config.lines().find_map(|l| {
        let (key, value) = l.split_once('=')?;
        (key.trim() == "MaxArraySize")
            .then(|| value.trim().parse().ok())
            .flatten()
    })
}

/// The array tasks of a campaign: task `t` runs cells `t·k .. (t+1)·k`.
pub fn task_of(cell: usize, cells_per_task: usize) -> usize {
    cell / cells_per_task.max(1)
}

pub fn cells_of_task(
    task: usize,
    cells_per_task: usize,
    cell_count: usize,
) -> std::ops::Range<usize> {
    let k = cells_per_task.max(1);
    (task * k).min(cell_count)..((task + 1) * k).min(cell_count)
}

/// `--array` of these task indices: ranges where they run on (`0-9,12,15-17`).
pub fn array_spec(tasks: &[usize], max_parallel: Option<u32>) -> String {
    let mut sorted = tasks.to_vec();
    sorted.sort_unstable();
    sorted.dedup();
    let mut out = String::new();
    let mut i = 0;
    while i < sorted.len() {
        let start = sorted[i];
        let mut end = start;
        while i + 1 < sorted.len() && sorted[i + 1] == end + 1 {
            i += 1;
            end = sorted[i];
        }
        if !out.is_empty() {
            out.push(',');
        }
        if end == start {
            let _ = write!(out, "{start}");
        } else {
            let _ = write!(out, "{start}-{end}");
        }
        i += 1;
    }
    if let Some(n) = max_parallel {
        let _ = write!(out, "%{n}");
    }
    out
}

/// Quotes `text` for a POSIX shell.
fn shell_quote(text: &str) -> String {
    format!("'{}'", text.replace('\'', r"'\''"))
}

/// Writes `<campaign>/slurm/job.sh`: the `#SBATCH` header, the setup command, and the
/// `run-cell` of the task's cells.
pub fn write_job_script(campaign: &Campaign, settings: &SlurmSettings) -> anyhow::Result<PathBuf> {
    let slurm_dir = campaign.dir.join("slurm");
    let logs = slurm_dir.join("logs");
    std::fs::create_dir_all(&logs).with_context(|| format!("creating {}", logs.display()))?;
    let manifest = &campaign.manifest;
    let mut script = String::from("#!/bin/bash\n");
    let _ = writeln!(script, "#SBATCH --job-name={}", settings.job_name);
    let _ = writeln!(script, "#SBATCH --output={}/%A_%a.out", logs.display());
    if let Some(partition) = &settings.partition {
        let _ = writeln!(script, "#SBATCH --partition={partition}");
    }
    if let Some(time) = &settings.time {
        let _ = writeln!(script, "#SBATCH --time={time}");
    }
    let _ = writeln!(script, "#SBATCH --cpus-per-task={}", settings.cpus_per_task);
    for line in &settings.sbatch_lines {
        let _ = writeln!(script, "#SBATCH {line}");
    }
    let _ = writeln!(
        script,
        "# millinav campaign {} ({} cells, {} mode, {} per task); written by experiments.\n\
         set -euo pipefail",
        campaign.dir.display(),
        manifest.cells.len(),
        manifest.mode.name(),
        settings.cells_per_task
    );
    if let Some(setup) = &settings.setup {
        let _ = writeln!(script, "{setup}");
    }
    let _ = writeln!(
        script,
        "export MILLINAV_ROOT={}\nexec {} run-cell --campaign {} --array-task \"$SLURM_ARRAY_TASK_ID\"",
        shell_quote(&manifest.data_root.to_string_lossy()),
        shell_quote(&manifest.bin_dir.join("experiments").to_string_lossy()),
        shell_quote(&campaign.out.to_string_lossy()),
    );
    let path = slurm_dir.join("job.sh");
    std::fs::write(&path, script).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

/// One `sbatch` of the campaign.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Submission {
    pub job_id: String,
    pub tasks: Vec<usize>,
    pub submitted_unix_s: u64,
}

#[derive(Debug, Default, Serialize, Deserialize)]
struct Submissions {
    #[serde(default)]
    submission: Vec<Submission>,
}

fn submissions_path(campaign: &Campaign) -> PathBuf {
    campaign.dir.join("slurm").join("submissions.toml")
}

/// Every submission of the campaign, oldest first.
pub fn submissions(campaign: &Campaign) -> anyhow::Result<Vec<Submission>> {
    let path = submissions_path(campaign);
    match std::fs::read_to_string(&path) {
        Ok(text) => Ok(toml::from_str::<Submissions>(&text)
            .with_context(|| format!("{}: not a list of submissions", path.display()))?
            .submission),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Vec::new()),
        Err(e) => Err(e).with_context(|| format!("reading {}", path.display())),
    }
}

/// Submits the array tasks `tasks` of the campaign (after `sbatch --test-only` accepted the
/// same submission) and records the job.
pub fn submit(
    campaign: &Campaign,
    settings: &SlurmSettings,
    tasks: &[usize],
) -> anyhow::Result<Submission> {
    anyhow::ensure!(!tasks.is_empty(), "nothing to submit");
    if let (Some(limit), Some(&last)) = (max_array_size(), tasks.iter().max()) {
        if last >= limit {
            bail!(
                "the array would need task index {last}, above the cluster's MaxArraySize \
                 {limit}: put more cells in a task (--cells-per-task {})",
                campaign.manifest.cells.len().div_ceil(limit)
            );
        }
    }
    let script = write_job_script(campaign, settings)?;
    let array = array_spec(tasks, settings.max_parallel);
    let script_arg = script.to_string_lossy().into_owned();
    let array_arg = format!("--array={array}");
    slurm_command("sbatch", &["--test-only", &array_arg, &script_arg])
        .context("the cluster refuses the submission (sbatch --test-only)")?;
    let output = slurm_command("sbatch", &["--parsable", &array_arg, &script_arg])?;
    let job_id = output
        .trim()
        .split(';')
        .next()
        .filter(|id| !id.is_empty() && id.bytes().all(|b| b.is_ascii_digit()))
        .with_context(|| format!("sbatch answered {output:?}, not a job id"))?
        .to_owned();
    let submission = Submission {
        job_id,
        tasks: tasks.to_vec(),
        submitted_unix_s: std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs()),
    };
    let mut all = Submissions {
        submission: submissions(campaign)?,
    };
    all.submission.push(submission.clone());
    let path = submissions_path(campaign);
    std::fs::write(&path, toml::to_string(&all)?)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(submission)
}

/// An array task's state in the queue.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Queued {
    pub state: String,
    pub reason: String,
}

/// The campaign's array tasks still in the queue, by (job, task).
pub fn queued(jobs: &[String]) -> anyhow::Result<BTreeMap<(String, usize), Queued>> {
    let mut out = BTreeMap::new();
    if jobs.is_empty() {
        return Ok(out);
    }
    // Without -j: squeue refuses the whole call when one job id has left the controller.
    let format = ["-h", "-r", "-o", "%F|%K|%T|%r"];
    let listing = match slurm_command("squeue", &[&format[..], &["--me"]].concat()) {
        Ok(listing) => listing,
        // Slurm before 20.11 has no --me.
        Err(e) => match std::env::var("USER").or_else(|_| std::env::var("LOGNAME")) {
            Ok(user) => slurm_command("squeue", &[&format[..], &["-u", &user]].concat())?,
            Err(_) => return Err(e),
        },
    };
    for line in listing.lines() {
        let fields: Vec<&str> = line.trim().split('|').collect();
        let [job, task, state, reason] = fields[..] else {
            continue;
        };
        if !jobs.iter().any(|j| j == job) {
            continue;
        }
        if let Ok(task) = task.parse::<usize>() {
            out.insert(
                (job.to_owned(), task),
                Queued {
                    state: state.to_owned(),
                    reason: reason.to_owned(),
                },
            );
        }
    }
    Ok(out)
}

/// How the campaign's array tasks that left the queue ended (`COMPLETED`, `CANCELLED`,
/// `TIMEOUT`, `PREEMPTED`, `FAILED`, `NODE_FAIL`, `OUT_OF_MEMORY`…), from one `sacct` call; `None`
/// where the cluster keeps no accounting.
fn accounted_end_states(jobs: &[String]) -> Option<BTreeMap<(String, usize), String>> {
    if jobs.is_empty() {
        return Some(BTreeMap::new());
    }
    let ids = jobs.join(",");
    let text = slurm_command(
        "sacct",
        &["-n", "-P", "-X", "-j", &ids, "-o", "JobID,State"],
    )
    .ok()?;
    let mut states = BTreeMap::new();
    for line in text.lines() {
        let Some((id, state)) = line.trim().split_once('|') else {
            continue;
        };
        let Some((job, task)) = id.split_once('_') else {
            continue;
        };
        if let Ok(task) = task.parse::<usize>() {
            states.insert((job.to_owned(), task), state.to_owned());
        }
    }
    Some(states)
}

/// How one array task ended, from `scontrol` while the controller remembers it (clusters
/// without accounting).
fn remembered_end_state(job: &str, task: usize) -> Option<String> {
    let text = slurm_command("scontrol", &["-o", "show", "job", &format!("{job}_{task}")]).ok()?;
    text.split_whitespace()
        .find_map(|field| field.strip_prefix("JobState="))
        .map(str::to_owned)
}

/// The progress of a campaign: its files, the queue, and for a task that left the queue
/// without finishing its cells, how Slurm ended it and where its log is.
pub fn progress(campaign: &Campaign) -> anyhow::Result<Progress> {
    let settings = campaign.manifest.slurm.clone().unwrap_or_default();
    let submissions = submissions(campaign)?;
    let jobs: Vec<String> = submissions.iter().map(|s| s.job_id.clone()).collect();
    let queue = queued(&jobs)?;
    // The latest submission of each task.
    let mut latest: BTreeMap<usize, &Submission> = BTreeMap::new();
    for s in &submissions {
        for &t in &s.tasks {
            latest.insert(t, s);
        }
    }
    let logs = campaign.dir.join("slurm").join("logs");
    let accounted = OnceCell::new();
    let mut end_states: BTreeMap<(String, usize), Option<String>> = BTreeMap::new();
    let cells = &campaign.manifest.cells;
    let mut p = Progress {
        total: cells.len(),
        ..Default::default()
    };
    for (i, cell) in cells.iter().enumerate() {
        let files = campaign.cell_files(i);
        if files == CellFiles::Done {
            p.done += 1;
            continue;
        }
        let task = task_of(i, settings.cells_per_task);
        let submission = latest.get(&task);
        let in_queue = submission.and_then(|s| queue.get(&(s.job_id.clone(), task)));
        // A task still in the queue is in flight, whatever its cells say so far: it may go on
        // to its next cell, and a task that is COMPLETING has not got its final state yet.
        match in_queue {
            Some(q) if q.state == "PENDING" => {
                p.pending += 1;
                continue;
            }
            Some(_) => {
                p.running += 1;
                continue;
            }
            None => {}
        }
        let mut why = match &files {
            CellFiles::Failed(reason) => format!("failed: {}", first_line(reason)),
            CellFiles::Started(marker) => format!(
                "killed while running on {}{}",
                marker.host,
                marker
                    .slurm_task
                    .as_ref()
                    .map(|t| format!(" (task {t})"))
                    .unwrap_or_default()
            ),
            CellFiles::NotRun => match submission {
                None => "never submitted".into(),
                Some(s) => format!("array task {}_{task} ended without running it", s.job_id),
            },
            CellFiles::Done => continue,
        };
        if let Some(s) = submission {
            let state =
                end_states
                    .entry((s.job_id.clone(), task))
                    .or_insert_with(|| {
                        match accounted.get_or_init(|| accounted_end_states(&jobs)) {
                            Some(states) => states.get(&(s.job_id.clone(), task)).cloned(),
                            None => remembered_end_state(&s.job_id, task),
                        }
                    });
            let log = logs.join(format!("{}_{task}.out", s.job_id));
            match state {
                Some(state) => {
                    let _ = write!(why, "; Slurm: {state}");
                }
                // Slurm keeps no record of an array task cancelled before it was started.
                None if !log.exists() && files == CellFiles::NotRun => {
                    why = format!(
                        "array task {}_{task} left the queue without starting (cancelled while \
                         pending, or the controller no longer remembers it)",
                        s.job_id
                    );
                }
                None => {}
            }
            if log.is_file() {
                let _ = write!(why, "; log {}", log.display());
                // A cell that failed has said why; for one that never ran, the log's last line
                // (a failed setup command, a crash) says it.
                if !matches!(files, CellFiles::Failed(_)) {
                    if let Some(last) = last_line(&log) {
                        let _ = write!(why, ": {last:?}");
                    }
                }
            }
        }
        p.failed.push((cell.name(), why));
    }
    Ok(p)
}

/// The last non-empty line of a task's log (what a failed setup command or a crash printed),
/// shortened to a line of a report.
fn last_line(log: &Path) -> Option<String> {
    const LONGEST: usize = 160;
    let text = std::fs::read_to_string(log).ok()?;
    let line = text.lines().rev().map(str::trim).find(|l| !l.is_empty())?;
    Some(match line.char_indices().nth(LONGEST) {
        Some((cut, _)) => format!("{}…", &line[..cut]),
        None => line.to_owned(),
    })
}

fn first_line(text: &str) -> &str {
    text.lines().next().unwrap_or(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn array_specs_are_ranges() {
        assert_eq!(array_spec(&[0, 1, 2, 3], None), "0-3");
        assert_eq!(
            array_spec(&[7, 0, 1, 2, 5, 9, 10], Some(4)),
            "0-2,5,7,9-10%4"
        );
        assert_eq!(array_spec(&[3], None), "3");
    }

    #[test]
    fn tasks_cover_every_cell_once() {
        for k in 1..5 {
            let n: usize = 11;
            let tasks = n.div_ceil(k);
            let covered: Vec<usize> = (0..tasks).flat_map(|t| cells_of_task(t, k, n)).collect();
            assert_eq!(covered, (0..n).collect::<Vec<_>>());
            assert!((0..n).all(|c| cells_of_task(task_of(c, k), k, n).contains(&c)));
        }
    }

    #[test]
    fn time_limits_in_slurms_forms() {
        for ok in [
            "30",
            "30:00",
            "01:30:00",
            "2-0",
            "2-12:00",
            "1-00:00:00",
            "UNLIMITED",
        ] {
            assert!(valid_time_limit(ok), "{ok}");
        }
        for bad in ["", "1h", "1:2:3:4", "-5", "2-", "a-1", "1:", "30 min"] {
            assert!(!valid_time_limit(bad), "{bad}");
        }
    }

    #[test]
    fn settings_refuse_what_sbatch_would() {
        let mut s = SlurmSettings {
            time: Some("1h".into()),
            ..Default::default()
        };
        assert!(s.validate().unwrap_err().to_string().contains("1h"));
        s.time = Some("00:10:00".into());
        s.sbatch_lines = vec!["--array=0-3".into()];
        assert!(s.validate().unwrap_err().to_string().contains("--array"));
        s.sbatch_lines = vec!["#SBATCH --mem=1G".into()];
        assert!(s.validate().is_err());
        s.sbatch_lines = vec!["--mem=1G".into()];
        s.validate().unwrap();
        let dir = std::env::temp_dir().join(format!("mx-slurm-settings-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("slurm.toml");
        std::fs::write(&file, "partition = \"gpu\"\ncpus_per_tsk = 2\n").unwrap();
        let err = format!("{:#}", SlurmSettings::load(&file).unwrap_err());
        assert!(
            err.contains("slurm.toml") && err.contains("cpus_per_tsk"),
            "{err}"
        );
        std::fs::write(
            &file,
            "partition = \"gpu\"\ntime = \"2:00:00\"\nsetup = \"module load x\"\n",
        )
        .unwrap();
        let s = SlurmSettings::load(&file).unwrap();
        assert_eq!(s.partition.as_deref(), Some("gpu"));
        assert_eq!(s.cells_per_task, 1);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
