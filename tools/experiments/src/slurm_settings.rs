//! How a campaign's job array is submitted to Slurm: the settings a `--slurm-config` file or
//! the command line gives, and their checks. Kept in the campaign's manifest, so the campaign
//! and the Slurm backend both read them.

use std::path::Path;

use anyhow::Context;
use serde::{Deserialize, Serialize};

/// How the array is submitted; from the command line or a TOML file (`--slurm-config`) with
/// these keys. Kept in the campaign's manifest so `resume` submits the same way.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SlurmSettings {
    /// `--partition`; the cluster's default partition when absent.
    #[serde(default)]
    pub partition: Option<String>,
    /// `--time` of one array task (Slurm's forms: `MM`, `MM:SS`, `HH:MM:SS`, `D-HH`,
    /// `D-HH:MM`, `D-HH:MM:SS`); the partition's default when absent.
    #[serde(default)]
    pub time: Option<String>,
    /// `--cpus-per-task`; fast-mode cells of one task run on this many threads.
    #[serde(default = "one")]
    pub cpus_per_task: u32,
    /// Cells one array task runs, one after the other (keeps arrays under the cluster's
    /// MaxArraySize and amortises the start of a task).
    #[serde(default = "one_cell")]
    pub cells_per_task: usize,
    /// At most this many array tasks at once (`--array=…%N`).
    #[serde(default)]
    pub max_parallel: Option<u32>,
    /// Further `#SBATCH` options, one per entry, e.g. `--mem=2G`, `--account=mylab`.
    #[serde(default)]
    pub sbatch_lines: Vec<String>,
    /// A shell command each task runs first, e.g. `module load opencv`.
    #[serde(default)]
    pub setup: Option<String>,
    /// `--job-name`.
    #[serde(default = "default_job_name")]
    pub job_name: String,
    /// Seconds between two looks at the queue while waiting.
    #[serde(default = "default_poll_s")]
    pub poll_s: f64,
}

fn one() -> u32 {
    1
}
fn one_cell() -> usize {
    1
}
fn default_job_name() -> String {
    "millinav".into()
}
fn default_poll_s() -> f64 {
    10.0
}

impl Default for SlurmSettings {
    fn default() -> Self {
        Self {
            partition: None,
            time: None,
            cpus_per_task: one(),
            cells_per_task: one_cell(),
            max_parallel: None,
            sbatch_lines: Vec::new(),
            setup: None,
            job_name: default_job_name(),
            poll_s: default_poll_s(),
        }
    }
}

impl SlurmSettings {
    /// Reads a `--slurm-config` file; errors name the file and the key.
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading the Slurm settings {}", path.display()))?;
        let settings: Self = toml::from_str(&text).map_err(|e| {
            anyhow::anyhow!(
                "Slurm settings {}: {}",
                path.display(),
                e.message().trim_end()
            )
        })?;
        settings
            .validate()
            .with_context(|| format!("Slurm settings {}", path.display()))?;
        Ok(settings)
    }

    /// Checks what can be checked before asking the cluster.
    pub fn validate(&self) -> anyhow::Result<()> {
        if let Some(partition) = &self.partition {
            anyhow::ensure!(
                !partition.is_empty()
                    && partition
                        .chars()
                        .all(|c| c.is_ascii_alphanumeric() || "_-.".contains(c)),
                "partition {partition:?}: use letters, digits, '_', '-' and '.'"
            );
        }
        if let Some(time) = &self.time {
            anyhow::ensure!(
                valid_time_limit(time),
                "time {time:?} is not a Slurm time limit (MM, MM:SS, HH:MM:SS, D-HH, D-HH:MM, \
                 D-HH:MM:SS or UNLIMITED)"
            );
        }
        anyhow::ensure!(self.cpus_per_task >= 1, "cpus_per_task must be at least 1");
        anyhow::ensure!(
            self.cells_per_task >= 1,
            "cells_per_task must be at least 1"
        );
        anyhow::ensure!(
            self.max_parallel.is_none_or(|n| n >= 1),
            "max_parallel must be at least 1"
        );
        anyhow::ensure!(
            self.poll_s.is_finite() && self.poll_s >= 0.1,
            "poll_s must be at least 0.1 s, got {}",
            self.poll_s
        );
        anyhow::ensure!(
            !self.job_name.is_empty() && !self.job_name.contains(char::is_whitespace),
            "job_name {:?}: one word",
            self.job_name
        );
        for line in &self.sbatch_lines {
            anyhow::ensure!(
                line.starts_with('-') && !line.contains(['\n', '\r']),
                "sbatch line {line:?}: give one sbatch option, e.g. --mem=2G (without #SBATCH)"
            );
            for own in [
                "--array",
                "--output",
                "--error",
                "--job-name",
                "--partition",
                "--time",
                "--cpus-per-task",
            ] {
                anyhow::ensure!(
                    !line.starts_with(own),
                    "sbatch line {line:?}: {own} is set by experiments (use its own flag or key)"
                );
            }
        }
        if let Some(setup) = &self.setup {
            anyhow::ensure!(!setup.contains('\0'), "setup holds a NUL byte");
        }
        Ok(())
    }
}

/// Whether `text` is one of the forms `sbatch --time` takes.
pub fn valid_time_limit(text: &str) -> bool {
    if matches!(text, "UNLIMITED" | "INFINITE") {
        return true;
    }
    let numbers = |part: &str, count: std::ops::RangeInclusive<usize>| {
        let fields: Vec<&str> = part.split(':').collect();
        count.contains(&fields.len())
            && fields
                .iter()
                .all(|f| !f.is_empty() && f.len() <= 5 && f.bytes().all(|b| b.is_ascii_digit()))
    };
    match text.split_once('-') {
        Some((days, rest)) => numbers(days, 1..=1) && numbers(rest, 1..=3),
        None => numbers(text, 1..=3),
    }
}
