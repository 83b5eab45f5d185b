//! Campaigns: a matrix planned once into a directory, each cell run by `run-cell` into a result
//! file of its own (on local threads, or as Slurm array tasks that share the directory), and
//! `collect` turning the result files into `results.csv`, `table.md` and the figures. Both
//! backends go through the same three steps, so the same seeds give the same tables.
//!
//! Layout under `<out>/campaign/`:
//! - `manifest.toml`: the matrix (every cell), mode, the base scenario, the content hash of the
//!   binaries and data, and the Slurm settings when it runs there;
//! - `cells/<cell>.toml`: each cell's whole scenario (`millinav run` takes it as it is);
//! - `results/<cell>.toml`: each finished cell's metrics, trace summary, scenario and hashes,
//!   written atomically (a killed task leaves none);
//! - `traces/<cell>.csv`: the first trial's trace of each paper-matrix cell, for the figures;
//! - `failed/<cell>.txt`: why a cell failed; `running/<cell>.toml`: who is running it now;
//! - `slurm/`: the job script, the submissions and the tasks' logs.

use std::collections::BTreeMap;
use std::io::Read as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use anyhow::{bail, Context};
use millinav_kit::runlog::{RunLogWriter, TruthRow};
use millinav_kit::scenario::Scenario;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::report::{self, Outcome};
use crate::robustness::{self, Case, CaseOutcome};
use crate::slurm_settings::SlurmSettings;
use crate::{
    cell_scenario, fast_run, metrics, process_run_isolated, read_truth, recorded_run, reference_of,
    scenario_document, write_rrd, Cell, Metrics, RunIsolation, TraceRow,
};

/// The campaign's folder inside an experiments output directory.
pub const CAMPAIGN_SUBDIR: &str = "campaign";
/// Version of the campaign layout; a directory of another version is refused.
pub const CAMPAIGN_FORMAT: u32 = 1;

/// How a cell runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// One process, the services' libraries, ground truth + localization noise for vision.
    Fast,
    /// The real process set in lockstep through `millinav run` (slow: full camera + vision).
    Process,
}

impl Mode {
    pub fn name(self) -> &'static str {
        match self {
            Mode::Fast => "fast",
            Mode::Process => "process",
        }
    }
}

/// Which matrix a campaign runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MatrixKind {
    /// The paper's matrix on the base scenario's rig (the rig's own flow conditions).
    Paper,
    /// One disturbance at a time around one flow condition of the rig (`--robustness`).
    Robustness,
}

/// One cell of either matrix.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "matrix", rename_all = "lowercase")]
pub enum CellSpec {
    Paper(Cell),
    Robustness(Case),
}

impl CellSpec {
    pub fn name(&self) -> String {
        match self {
            CellSpec::Paper(cell) => cell.name(),
            CellSpec::Robustness(case) => case.name(),
        }
    }

    /// The cell's whole scenario.
    pub fn scenario_text(&self, base: &Scenario) -> anyhow::Result<String> {
        match self {
            CellSpec::Paper(cell) => cell_scenario(base, cell),
            CellSpec::Robustness(case) => robustness::case_scenario(base, case),
        }
    }

    /// Whether the figures need this cell's trace (the first trial of a paper-matrix cell).
    fn keeps_trace(&self) -> bool {
        matches!(self, CellSpec::Paper(cell) if cell.seed == 1)
    }
}

/// A file that went into the build hash, with its own hash.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HashedFile {
    /// Relative to the data root when under it, else absolute.
    pub path: String,
    pub sha256: String,
    pub bytes: u64,
}

/// The content hash of the binaries and data a campaign's cells run on.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BuildId {
    pub sha256: String,
    pub files: Vec<HashedFile>,
}

impl BuildId {
    /// Hashes the experiments binary, in process mode every `millinav*` binary beside it (the
    /// supervisor and the services it launches) and the default UNet model, the rig file and
    /// every file it names, and every file a cell's scenario names.
    pub fn of(
        mode: Mode,
        bin_dir: &Path,
        rig: &fieldmaps::rigfile::Rig,
        scenarios: &[String],
    ) -> anyhow::Result<Self> {
        let root = fieldmaps::data_root();
        let mut paths: Vec<PathBuf> = vec![bin_dir.join("experiments")];
        if mode == Mode::Process {
            for entry in std::fs::read_dir(bin_dir)
                .with_context(|| format!("listing the binaries in {}", bin_dir.display()))?
            {
                let path = entry?.path();
                let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
                let is_binary = name.as_deref().is_some_and(|n| {
                    (n == "millinav" || n.starts_with("millinav-")) && !n.contains('.')
                }) && is_executable(&path);
                if is_binary {
                    paths.push(path);
                }
            }
        }
        if mode == Mode::Process {
            // Vision runs the committed model unless a scenario names another (hashed below).
            let model = root.join(millinav_vision::DEFAULT_MODEL);
            if model.is_file() {
                paths.push(model);
            }
        }
        paths.extend(rig_files(rig)?);
        for text in scenarios {
            let doc: toml::Table = toml::from_str(text).context("a cell's scenario")?;
            named_files(&toml::Value::Table(doc), &root, &mut paths);
        }
        paths.sort();
        paths.dedup();
        let mut files = Vec::with_capacity(paths.len());
        let mut all = Sha256::new();
        for path in paths {
            let (sha256, bytes) = sha256_of_file(&path)?;
            let shown = path
                .strip_prefix(&root)
                .unwrap_or(&path)
                .to_string_lossy()
                .into_owned();
            all.update(shown.as_bytes());
            all.update(sha256.as_bytes());
            files.push(HashedFile {
                path: shown,
                sha256,
                bytes,
            });
        }
        Ok(Self {
            sha256: hex(&all.finalize()),
            files,
        })
    }

    /// What differs from `other`, file by file (for the error that refuses a campaign).
    pub fn differences(&self, other: &BuildId) -> Vec<String> {
        let mine: BTreeMap<&str, &str> = self
            .files
            .iter()
            .map(|f| (f.path.as_str(), f.sha256.as_str()))
            .collect();
        let theirs: BTreeMap<&str, &str> = other
            .files
            .iter()
            .map(|f| (f.path.as_str(), f.sha256.as_str()))
            .collect();
        let mut out = Vec::new();
        for (path, hash) in &mine {
            match theirs.get(path) {
                None => out.push(format!("{path} (only in this build)")),
                Some(h) if h != hash => out.push(format!("{path} (changed)")),
                Some(_) => {}
            }
        }
        for path in theirs.keys().filter(|p| !mine.contains_key(*p)) {
            out.push(format!("{path} (only in the campaign's build)"));
        }
        out
    }
}

fn is_executable(path: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(path).is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
}

/// The rig file and every file it names (mask, flow maps, coil maps, calibrations).
fn rig_files(rig: &fieldmaps::rigfile::Rig) -> anyhow::Result<Vec<PathBuf>> {
    use fieldmaps::rigfile::FieldModel;
    let mut files = vec![rig.path.clone(), rig.phantom.mask_path.clone()];
    files.extend(
        rig.phantom
            .flow_conditions
            .iter()
            .map(|c| c.map_path.clone()),
    );
    files.extend(rig.field_calibration.iter().cloned());
    files.extend(rig.twin_field_calibration.iter().cloned());
    for model in [&rig.field_model, &rig.twin_field_model] {
        if let FieldModel::Maps(dir) = model {
            for entry in std::fs::read_dir(dir)
                .with_context(|| format!("listing the coil maps in {}", dir.display()))?
            {
                let path = entry?.path();
                if path.is_file() {
                    files.push(path);
                }
            }
        }
    }
    Ok(files)
}

/// Every string in a scenario that names an existing file (absolute, or under the data root).
fn named_files(value: &toml::Value, root: &Path, out: &mut Vec<PathBuf>) {
    match value {
        toml::Value::String(text) => {
            let path = Path::new(text);
            let path = if path.is_absolute() {
                path.to_owned()
            } else {
                root.join(path)
            };
            if path.is_file() {
                out.push(path);
            }
        }
        toml::Value::Array(items) => items.iter().for_each(|v| named_files(v, root, out)),
        toml::Value::Table(table) => table.values().for_each(|v| named_files(v, root, out)),
        _ => {}
    }
}

fn sha256_of_file(path: &Path) -> anyhow::Result<(String, u64)> {
    let mut file =
        std::fs::File::open(path).with_context(|| format!("hashing {}", path.display()))?;
    let mut hasher = Sha256::new();
    let mut buffer = vec![0u8; 1 << 20];
    let mut bytes = 0u64;
    loop {
        let n = file
            .read(&mut buffer)
            .with_context(|| format!("hashing {}", path.display()))?;
        if n == 0 {
            break;
        }
        hasher.update(&buffer[..n]);
        bytes += n as u64;
    }
    Ok((hex(&hasher.finalize()), bytes))
}

fn sha256_of(text: &str) -> String {
    hex(&Sha256::digest(text.as_bytes()))
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// What a campaign runs; written once, when it is planned.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub format: u32,
    pub matrix: MatrixKind,
    pub mode: Mode,
    /// Hash of the mode, the options that change a result and every cell's name and scenario.
    pub matrix_sha256: String,
    /// Where the committed data was (`MILLINAV_ROOT` of every task).
    pub data_root: PathBuf,
    /// Where `experiments` and the services are.
    pub bin_dir: PathBuf,
    /// Fast mode writes each run's Rerun recording under `<out>/runs/`.
    pub write_rrd: bool,
    /// Process mode reads each cell's earlier run under `<out>/runs/` instead of running it.
    pub reuse_runs: bool,
    /// Fast mode keeps every run's trace in `campaign/traces/`, not only the first trial's
    /// that the figures need.
    #[serde(default)]
    pub every_trace: bool,
    /// The run settings line of `table.md` (frame period, latency, gain error, rig).
    pub table_header: String,
    /// The paper's numbers and targets go beside ours (the paper's rig only).
    pub on_paper_rig: bool,
    /// The base scenario with the command line's settings applied.
    pub base_scenario: String,
    pub slurm: Option<SlurmSettings>,
    pub build: BuildId,
    pub cells: Vec<CellSpec>,
}

/// What a planned matrix needs besides its cells.
pub struct MatrixPlan {
    pub matrix: MatrixKind,
    pub mode: Mode,
    pub base: Scenario,
    pub cells: Vec<CellSpec>,
    pub write_rrd: bool,
    pub reuse_runs: bool,
    pub every_trace: bool,
    pub table_header: String,
    pub bin_dir: PathBuf,
    pub slurm: Option<SlurmSettings>,
}

/// One finished cell, as `run-cell` writes it.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CellResult {
    pub cell: String,
    pub matrix_sha256: String,
    pub build_sha256: String,
    pub scenario_sha256: String,
    pub host: String,
    /// `<array job>_<task>` when a Slurm task ran it.
    pub slurm_task: Option<String>,
    pub finished_unix_s: u64,
    pub wall_s: f64,
    /// The cell's whole scenario, as it ran.
    pub scenario: String,
    pub metrics: Metrics,
    pub trace: TraceSummary,
}

/// A few numbers of the run's trace (the whole trace is kept for the figures' cells only).
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TraceSummary {
    pub frames: usize,
    pub duration_s: f64,
    pub final_x_mm: f64,
    pub final_y_mm: f64,
}

impl TraceSummary {
    fn of(trace: &[TraceRow]) -> Self {
        let last = trace.last();
        Self {
            frames: trace.len(),
            duration_s: match (trace.first(), last) {
                (Some(a), Some(b)) => b.time_s - a.time_s,
                _ => 0.0,
            },
            final_x_mm: last.map_or(f64::NAN, |r| r.position_m.x * 1e3),
            final_y_mm: last.map_or(f64::NAN, |r| r.position_m.y * 1e3),
        }
    }
}

/// Who is running a cell now; left behind when the task was killed outright.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunningMarker {
    pub host: String,
    pub pid: u32,
    pub slurm_task: Option<String>,
    pub started_unix_s: u64,
}

/// Where a cell stands, from the files of the campaign alone.
#[derive(Debug, Clone, PartialEq)]
pub enum CellFiles {
    Done,
    /// `run-cell` failed and said why.
    Failed(String),
    /// A task started it and has not finished it (running now, or killed outright).
    Started(RunningMarkerSummary),
    NotRun,
}

/// The parts of a [`RunningMarker`] a report names.
#[derive(Debug, Clone, PartialEq)]
pub struct RunningMarkerSummary {
    pub host: String,
    pub slurm_task: Option<String>,
}

/// Where every cell of a campaign stands.
#[derive(Debug, Default)]
pub struct Progress {
    pub done: usize,
    pub running: usize,
    pub pending: usize,
    /// Cells that will not finish without `resume`, with why.
    pub failed: Vec<(String, String)>,
    pub total: usize,
}

impl Progress {
    pub fn in_flight(&self) -> bool {
        self.running + self.pending > 0
    }

    pub fn line(&self) -> String {
        format!(
            "{} done, {} running, {} pending, {} failed or missing of {}",
            self.done,
            self.running,
            self.pending,
            self.failed.len(),
            self.total
        )
    }
}

/// The environment of whoever runs cells: the hash it checked, and the stop flag.
pub struct RunContext<'a> {
    pub build_sha256: &'a str,
    pub terminated: &'a AtomicBool,
    pub slurm_task: Option<String>,
}

/// A campaign directory.
pub struct Campaign {
    /// The experiments output directory (tables and figures go here).
    pub out: PathBuf,
    /// `<out>/campaign`.
    pub dir: PathBuf,
    pub manifest: Manifest,
}

/// How [`Campaign::plan`] found the directory.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Planned {
    /// A new campaign was written.
    New,
    /// The same matrix of the same build was already there; finished cells are kept.
    Existing,
}

fn unix_now_s() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// This machine's name (tasks on a cluster run on many).
pub fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_owned())
        .unwrap_or_else(|_| "unknown".into())
}

/// Writes `text` to `path` through a temporary file and a rename, so a reader never sees half
/// a file and a killed writer leaves none.
fn write_atomically(path: &Path, text: &str) -> anyhow::Result<()> {
    let dir = path.parent().context("a file without a folder")?;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let name = path.file_name().context("a path without a file name")?;
    let tmp = dir.join(format!(
        ".{}.{}.tmp",
        name.to_string_lossy(),
        std::process::id()
    ));
    std::fs::write(&tmp, text).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

impl Campaign {
    /// The campaign of `out` (an experiments output directory, or its `campaign` folder).
    pub fn open(out: &Path) -> anyhow::Result<Self> {
        let (out, dir) = if out.join(CAMPAIGN_SUBDIR).join("manifest.toml").is_file() {
            (out.to_owned(), out.join(CAMPAIGN_SUBDIR))
        } else if out.join("manifest.toml").is_file() && out.ends_with(CAMPAIGN_SUBDIR) {
            (out.parent().unwrap_or(out).to_owned(), out.to_owned())
        } else {
            bail!(
                "{} holds no campaign (no {CAMPAIGN_SUBDIR}/manifest.toml): give the --out \
                 directory of an experiments run",
                out.display()
            );
        };
        let path = dir.join("manifest.toml");
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}", path.display()))?;
        let manifest: Manifest = toml::from_str(&text)
            .with_context(|| format!("{}: not a campaign manifest", path.display()))?;
        if manifest.format != CAMPAIGN_FORMAT {
            bail!(
                "{}: campaign format {} (this build reads format {CAMPAIGN_FORMAT}); run it with \
                 the build that planned it, or plan it again with --fresh",
                path.display(),
                manifest.format
            );
        }
        Ok(Self { out, dir, manifest })
    }

    /// Plans `plan` into `out`: writes the manifest and every cell's scenario. A directory that
    /// already holds the same matrix of the same build keeps its finished cells; one that holds
    /// another build's or another matrix's is refused (unless `fresh`, which deletes it).
    pub fn plan(out: &Path, plan: MatrixPlan, fresh: bool) -> anyhow::Result<(Self, Planned)> {
        let rig = plan.base.rig()?;
        let mut scenarios = Vec::with_capacity(plan.cells.len());
        let mut names = std::collections::BTreeSet::new();
        for cell in &plan.cells {
            let name = cell.name();
            anyhow::ensure!(names.insert(name.clone()), "two cells are named {name}");
            scenarios.push(cell.scenario_text(&plan.base)?);
        }
        let mut matrix = Sha256::new();
        matrix.update(format!(
            "format {CAMPAIGN_FORMAT}\nmode {}\nrrd {}\nreuse {}\n",
            plan.mode.name(),
            plan.write_rrd,
            plan.reuse_runs
        ));
        for (cell, text) in plan.cells.iter().zip(&scenarios) {
            matrix.update(cell.name().as_bytes());
            matrix.update([0]);
            matrix.update(text.as_bytes());
            matrix.update([0]);
        }
        let build = BuildId::of(plan.mode, &plan.bin_dir, &rig, &scenarios)?;
        let manifest = Manifest {
            format: CAMPAIGN_FORMAT,
            matrix: plan.matrix,
            mode: plan.mode,
            matrix_sha256: hex(&matrix.finalize()),
            data_root: std::path::absolute(fieldmaps::data_root())?,
            bin_dir: std::path::absolute(&plan.bin_dir)?,
            write_rrd: plan.write_rrd,
            reuse_runs: plan.reuse_runs,
            every_trace: plan.every_trace,
            table_header: plan.table_header,
            on_paper_rig: rig.path == fieldmaps::rigfile::paper_rig_path(),
            base_scenario: toml::to_string(&scenario_document(&plan.base)?)?,
            slurm: plan.slurm,
            build,
            cells: plan.cells,
        };
        let out = std::path::absolute(out)?;
        let dir = out.join(CAMPAIGN_SUBDIR);
        let manifest_path = dir.join("manifest.toml");
        let mut planned = Planned::New;
        if manifest_path.exists() {
            if fresh {
                std::fs::remove_dir_all(&dir)
                    .with_context(|| format!("removing the old campaign {}", dir.display()))?;
            } else {
                let old = Self::open(&out)?;
                old.refuse_if_other(&manifest)?;
                planned = Planned::Existing;
            }
        }
        let campaign = Self { out, dir, manifest };
        if planned == Planned::New {
            for (cell, text) in campaign.manifest.cells.iter().zip(&scenarios) {
                write_atomically(&campaign.scenario_path(&cell.name()), text)?;
            }
            campaign.write_manifest()?;
        } else {
            // The same cells of the same build: keep what is done, take the new settings (a
            // resubmission may go to another partition; the cells still to run may keep every
            // trace).
            let mut kept = Self::open(&campaign.out)?;
            kept.manifest.slurm = campaign.manifest.slurm;
            kept.manifest.every_trace = campaign.manifest.every_trace;
            kept.write_manifest()?;
            return Ok((kept, planned));
        }
        Ok((campaign, planned))
    }

    /// Refuses to mix `new` into this campaign when it is another matrix or another build.
    fn refuse_if_other(&self, new: &Manifest) -> anyhow::Result<()> {
        let path = self.dir.join("manifest.toml");
        if self.manifest.matrix_sha256 != new.matrix_sha256 {
            let old: std::collections::BTreeSet<String> =
                self.manifest.cells.iter().map(CellSpec::name).collect();
            let now: std::collections::BTreeSet<String> =
                new.cells.iter().map(CellSpec::name).collect();
            let only_new: Vec<&String> = now.difference(&old).take(3).collect();
            let only_old: Vec<&String> = old.difference(&now).take(3).collect();
            bail!(
                "{} holds a campaign of another matrix ({} cells, {} mode; this one has {} cells, \
                 {} mode{}{}{}): give another --out, or --fresh to delete it and start over",
                path.display(),
                self.manifest.cells.len(),
                self.manifest.mode.name(),
                new.cells.len(),
                new.mode.name(),
                if only_new.is_empty() {
                    String::new()
                } else {
                    format!("; new cells {only_new:?}")
                },
                if only_old.is_empty() {
                    String::new()
                } else {
                    format!("; cells no longer in it {only_old:?}")
                },
                if only_new.is_empty() && only_old.is_empty() {
                    "; the same cell names with other scenarios or options"
                } else {
                    ""
                }
            );
        }
        if self.manifest.build.sha256 != new.build.sha256 {
            let changed = self.manifest.build.differences(&new.build);
            bail!(
                "{} was written by another build: {}. Its results cannot be mixed with this \
                 build's; give another --out, or --fresh to delete it and start over",
                path.display(),
                changed.join(", ")
            );
        }
        Ok(())
    }

    pub fn write_manifest(&self) -> anyhow::Result<()> {
        write_atomically(
            &self.dir.join("manifest.toml"),
            &toml::to_string(&self.manifest)?,
        )
    }

    pub fn scenario_path(&self, name: &str) -> PathBuf {
        self.dir.join("cells").join(format!("{name}.toml"))
    }

    pub fn result_path(&self, name: &str) -> PathBuf {
        self.dir.join("results").join(format!("{name}.toml"))
    }

    fn trace_path(&self, name: &str) -> PathBuf {
        self.dir.join("traces").join(format!("{name}.csv"))
    }

    fn failed_path(&self, name: &str) -> PathBuf {
        self.dir.join("failed").join(format!("{name}.txt"))
    }

    fn running_path(&self, name: &str) -> PathBuf {
        self.dir.join("running").join(format!("{name}.toml"))
    }

    /// The cell's result, if it has one of this campaign; an error when the file is damaged or
    /// from another campaign or build.
    pub fn result(&self, index: usize) -> anyhow::Result<Option<CellResult>> {
        let name = self.manifest.cells[index].name();
        let path = self.result_path(&name);
        let text = match std::fs::read_to_string(&path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
        };
        let result: CellResult = toml::from_str(&text)
            .with_context(|| format!("{}: not a cell result", path.display()))?;
        if result.cell != name
            || result.matrix_sha256 != self.manifest.matrix_sha256
            || result.build_sha256 != self.manifest.build.sha256
        {
            bail!(
                "{}: a result of another cell, matrix or build than this campaign's",
                path.display()
            );
        }
        Ok(Some(result))
    }

    /// Where cell `index` stands, from the campaign's files.
    pub fn cell_files(&self, index: usize) -> CellFiles {
        let name = self.manifest.cells[index].name();
        if self.result_path(&name).is_file() {
            return CellFiles::Done;
        }
        if let Ok(text) = std::fs::read_to_string(self.failed_path(&name)) {
            return CellFiles::Failed(text.trim().to_owned());
        }
        if let Ok(text) = std::fs::read_to_string(self.running_path(&name)) {
            if let Ok(marker) = toml::from_str::<RunningMarker>(&text) {
                return CellFiles::Started(RunningMarkerSummary {
                    host: marker.host,
                    slurm_task: marker.slurm_task,
                });
            }
        }
        CellFiles::NotRun
    }

    /// Cells without a result, in the matrix's order.
    pub fn unfinished(&self) -> Vec<usize> {
        (0..self.manifest.cells.len())
            .filter(|&i| self.cell_files(i) != CellFiles::Done)
            .collect()
    }

    /// Where a campaign run on this machine stands, from its files alone.
    pub fn local_progress(&self) -> Progress {
        let mut p = Progress {
            total: self.manifest.cells.len(),
            ..Default::default()
        };
        for (i, cell) in self.manifest.cells.iter().enumerate() {
            let why = match self.cell_files(i) {
                CellFiles::Done => {
                    p.done += 1;
                    continue;
                }
                CellFiles::Failed(reason) => {
                    format!("failed: {}", reason.lines().next().unwrap_or_default())
                }
                CellFiles::Started(marker) => {
                    format!("interrupted while running on {}", marker.host)
                }
                CellFiles::NotRun => "not run".into(),
            };
            p.failed.push((cell.name(), why));
        }
        p
    }

    /// Records why cell `index` could not run.
    pub fn mark_failed(&self, index: usize, why: &str) {
        let name = self.manifest.cells[index].name();
        let _ = write_atomically(&self.failed_path(&name), &format!("{why}\n"));
    }

    /// Forgets why unfinished cells failed (before they run again).
    pub fn clear_failures(&self, cells: &[usize]) {
        for &i in cells {
            let name = self.manifest.cells[i].name();
            let _ = std::fs::remove_file(self.failed_path(&name));
            let _ = std::fs::remove_file(self.running_path(&name));
        }
    }

    /// The iceoryx2 tag of this campaign's process-mode runs.
    pub fn iox_tag(&self) -> String {
        format!("mx{}", &self.manifest.matrix_sha256[..8])
    }

    /// Hashes the binaries and data as they are now and refuses them when they are not the
    /// ones the campaign was planned with (a rebuild between submission and run).
    pub fn check_build(&self) -> anyhow::Result<String> {
        let base = Scenario::parse(
            &self.manifest.base_scenario,
            &self.dir.join("manifest.toml"),
        )?;
        let rig = base.rig()?;
        let scenarios = self
            .manifest
            .cells
            .iter()
            .map(|c| {
                let path = self.scenario_path(&c.name());
                std::fs::read_to_string(&path)
                    .with_context(|| format!("reading {}", path.display()))
            })
            .collect::<anyhow::Result<Vec<String>>>()?;
        let now = BuildId::of(self.manifest.mode, &self.manifest.bin_dir, &rig, &scenarios)?;
        if now.sha256 != self.manifest.build.sha256 {
            bail!(
                "the binaries or data changed since the campaign in {} was planned: {}. Plan it \
                 again (--fresh) with this build",
                self.dir.display(),
                self.manifest.build.differences(&now).join(", ")
            );
        }
        Ok(now.sha256)
    }

    /// Runs cell `index` and writes its result (and its trace when the figures need it). A
    /// failure is written to `failed/<cell>.txt` and returned.
    pub fn run_cell(&self, index: usize, context: &RunContext<'_>) -> anyhow::Result<CellResult> {
        let spec = self.manifest.cells.get(index).with_context(|| {
            format!(
                "the campaign has {} cells, no cell {index}",
                self.manifest.cells.len()
            )
        })?;
        let name = spec.name();
        let marker = RunningMarker {
            host: host_name(),
            pid: std::process::id(),
            slurm_task: context.slurm_task.clone(),
            started_unix_s: unix_now_s(),
        };
        let _ = std::fs::remove_file(self.failed_path(&name));
        write_atomically(&self.running_path(&name), &toml::to_string(&marker)?)?;
        let outcome = self.run_cell_inner(spec, &name, context);
        if let Err(e) = &outcome {
            let _ = write_atomically(&self.failed_path(&name), &format!("{e:#}\n"));
        }
        let _ = std::fs::remove_file(self.running_path(&name));
        outcome
    }

    fn run_cell_inner(
        &self,
        spec: &CellSpec,
        name: &str,
        context: &RunContext<'_>,
    ) -> anyhow::Result<CellResult> {
        let scenario_path = self.scenario_path(name);
        let text = std::fs::read_to_string(&scenario_path)
            .with_context(|| format!("reading {}", scenario_path.display()))?;
        let scenario = Scenario::parse(&text, &scenario_path)?;
        let runs = self.out.join("runs");
        let start = Instant::now();
        let trace = match self.manifest.mode {
            Mode::Fast => fast_run(&scenario)?,
            Mode::Process if self.manifest.reuse_runs => recorded_run(&text, &runs.join(name))?,
            Mode::Process => {
                let tag = self.iox_tag();
                process_run_isolated(
                    &text,
                    &self.manifest.bin_dir,
                    &runs,
                    name,
                    RunIsolation {
                        iox_tag: &tag,
                        terminated: context.terminated,
                    },
                )?
            }
        };
        if context.terminated.load(Ordering::Relaxed) {
            return Err(crate::Terminated.into());
        }
        let wall_s = start.elapsed().as_secs_f64();
        let reference = reference_of(&scenario)?;
        if self.manifest.mode == Mode::Fast && self.manifest.write_rrd {
            std::fs::create_dir_all(&runs)?;
            write_rrd(&runs.join(format!("{name}.rrd")), name, &trace, &reference)?;
        }
        let m = metrics(
            &trace,
            &reference,
            scenario.rig()?.coil_limits().coil_resistance_ohm,
        );
        if spec.keeps_trace() || self.manifest.every_trace {
            self.write_trace(name, &trace)?;
        }
        let result = CellResult {
            cell: name.to_owned(),
            matrix_sha256: self.manifest.matrix_sha256.clone(),
            build_sha256: context.build_sha256.to_owned(),
            scenario_sha256: sha256_of(&text),
            host: host_name(),
            slurm_task: context.slurm_task.clone(),
            finished_unix_s: unix_now_s(),
            wall_s,
            scenario: text,
            metrics: m,
            trace: TraceSummary::of(&trace),
        };
        write_atomically(&self.result_path(name), &toml::to_string(&result)?)?;
        Ok(result)
    }

    fn write_trace(&self, name: &str, trace: &[TraceRow]) -> anyhow::Result<()> {
        let path = self.trace_path(name);
        std::fs::create_dir_all(path.parent().context("trace folder")?)?;
        let tmp = path.with_extension(format!("csv.{}.tmp", std::process::id()));
        let _ = std::fs::remove_file(&tmp);
        let mut writer = RunLogWriter::<TruthRow>::open_append(&tmp)?;
        for (seq, row) in trace.iter().enumerate() {
            writer.append(&TruthRow {
                frame_seq: seq as u64,
                frame_incarnation: 0,
                sim_time_s: row.time_s,
                x_m: row.position_m.x,
                y_m: row.position_m.y,
                vx_mps: row.motion.velocity_mps.x,
                vy_mps: row.motion.velocity_mps.y,
                heading_rad: row.motion.heading_rad,
                flow_x_mps: row.motion.flow_mps.x,
                flow_y_mps: row.motion.flow_mps.y,
                wall_contact: row.wall_contact,
                max_abs_current_a: row.max_abs_current_a,
                lockstep_misses: 0,
                sum_sq_current_a2: Some(row.sum_sq_current_a2),
                coil_currents_a: row.coil_currents_a.map(|c| TruthRow::format_currents(&c)),
            })?;
        }
        writer.flush()?;
        std::fs::rename(&tmp, &path).with_context(|| format!("writing {}", path.display()))?;
        Ok(())
    }

    /// Every cell's result; an error naming the cells that have none (or a damaged one).
    pub fn results(&self) -> anyhow::Result<Vec<(CellSpec, CellResult)>> {
        let mut out = Vec::with_capacity(self.manifest.cells.len());
        let mut missing = Vec::new();
        for (i, spec) in self.manifest.cells.iter().enumerate() {
            match self.result(i)? {
                Some(result) => {
                    let planned = self.scenario_path(&spec.name());
                    let text = std::fs::read_to_string(&planned)
                        .with_context(|| format!("reading {}", planned.display()))?;
                    if sha256_of(&text) != result.scenario_sha256 {
                        bail!(
                            "{}: ran another scenario than {}",
                            self.result_path(&spec.name()).display(),
                            planned.display()
                        );
                    }
                    out.push((spec.clone(), result));
                }
                None => missing.push(spec.name()),
            }
        }
        if !missing.is_empty() {
            bail!(
                "{} of {} cells have no result: {}{}; see `experiments status {}`, and run them \
                 with `experiments resume {}`",
                missing.len(),
                self.manifest.cells.len(),
                missing
                    .iter()
                    .take(20)
                    .cloned()
                    .collect::<Vec<_>>()
                    .join(", "),
                if missing.len() > 20 { ", …" } else { "" },
                self.out.display(),
                self.out.display()
            );
        }
        Ok(out)
    }

    /// Turns the result files into the matrix's tables (printed and returned) and figures.
    pub fn collect(&self) -> anyhow::Result<String> {
        let results = self.results()?;
        std::fs::create_dir_all(&self.out)?;
        match self.manifest.matrix {
            MatrixKind::Paper => self.collect_paper(results),
            MatrixKind::Robustness => self.collect_robustness(results),
        }
    }

    fn collect_paper(&self, results: Vec<(CellSpec, CellResult)>) -> anyhow::Result<String> {
        let mut outcomes = Vec::with_capacity(results.len());
        let mut traces = Vec::new();
        for (spec, result) in results {
            let keeps_trace = spec.keeps_trace();
            let CellSpec::Paper(cell) = spec else {
                bail!("a robustness cell in a paper-matrix campaign");
            };
            if keeps_trace {
                let path = self.trace_path(&cell.name());
                traces.push((cell.clone(), read_truth(&path)?));
            }
            outcomes.push(Outcome {
                cell,
                metrics: result.metrics,
                wall_s: result.wall_s,
            });
        }
        outcomes.sort_by_key(|o| o.cell.name());
        report::write_csv(&outcomes, &self.out.join("results.csv"))?;
        let mut table = report::markdown_table(
            &outcomes,
            &self.manifest.table_header,
            self.manifest.on_paper_rig,
        );
        if self.manifest.on_paper_rig {
            table += &report::target_checks(&outcomes);
        }
        std::fs::write(self.out.join("table.md"), &table)?;
        if report::register_font() {
            let base = Scenario::parse(
                &self.manifest.base_scenario,
                &self.dir.join("manifest.toml"),
            )?;
            report::write_figures(&base, &outcomes, &traces, &self.out)?;
        } else {
            eprintln!("no DejaVu font found (apt install fonts-dejavu-core): figures skipped");
        }
        Ok(table)
    }

    fn collect_robustness(&self, results: Vec<(CellSpec, CellResult)>) -> anyhow::Result<String> {
        let outcomes = results
            .into_iter()
            .map(|(spec, result)| match spec {
                CellSpec::Robustness(case) => Ok(CaseOutcome {
                    case,
                    metrics: result.metrics,
                }),
                CellSpec::Paper(_) => bail!("a paper-matrix cell in a robustness campaign"),
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        let on_paper_rig = self.manifest.on_paper_rig;
        // The flow noise's floor of each setting's twin, from its cell's scenario.
        let floor_m = |case: &robustness::Case| {
            let path = self.scenario_path(&case.name());
            let text = std::fs::read_to_string(&path).ok()?;
            let scenario = Scenario::parse(&text, &path).ok()?;
            let floor = crate::noise_floor::scenario_floor(&scenario).ok()?;
            Some((floor.floor_m, floor.fluid_particle_floor_m))
        };
        let table = robustness::write_tables(&outcomes, on_paper_rig, &floor_m, &self.out)?;
        if report::register_font() {
            robustness::heat_map(&outcomes, on_paper_rig, &self.out.join("robustness.png"))?;
        } else {
            eprintln!("no DejaVu font found (apt install fonts-dejavu-core): heat map skipped");
        }
        Ok(table)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::FlowSetting;

    #[test]
    fn cells_go_through_toml_and_back() {
        let cells = vec![
            CellSpec::Paper(Cell {
                viscosity_cp: 4.3,
                flow: FlowSetting::Q180,
                controller: "smc-dob-auto".into(),
                seed: 2,
            }),
            CellSpec::Paper(Cell {
                viscosity_cp: 20.0,
                flow: FlowSetting::Static,
                controller: "pid".into(),
                seed: 1,
            }),
            CellSpec::Robustness(Case {
                axis: robustness::Axis::CameraLatencyMs,
                level: 100.0,
                viscosity_cp: 20.0,
                flow: FlowSetting::Q180,
                frame_period_ms: 100.0,
                controller: "mpc".into(),
                seed: 3,
            }),
        ];
        #[derive(Serialize, Deserialize)]
        struct Wrapper {
            cells: Vec<CellSpec>,
        }
        let text = toml::to_string(&Wrapper {
            cells: cells.clone(),
        })
        .unwrap();
        let back: Wrapper = toml::from_str(&text).unwrap();
        assert_eq!(back.cells, cells, "{text}");
        assert!(text.contains("flow = \"q180\""), "{text}");
        assert!(text.contains("axis = \"camera-latency-ms\""), "{text}");
    }

    #[test]
    fn metrics_survive_a_result_file_exactly() {
        let metrics = Metrics {
            rmse_mm: 0.1 + 0.2,
            p95_mm: 1.0 / 3.0,
            max_mm: 2.5e-7,
            completed: true,
            wall_contact_frames: 4,
            peak_current_a: 5.999_999_999_9,
            energy_j: 1_234.567_890_123,
            current_step_p95_a: f64::NAN,
            current_tv_a_per_s: 17.0,
        };
        let text = toml::to_string(&metrics).unwrap();
        let back: Metrics = toml::from_str(&text).unwrap();
        assert_eq!(back.rmse_mm.to_bits(), metrics.rmse_mm.to_bits());
        assert_eq!(back.p95_mm.to_bits(), metrics.p95_mm.to_bits());
        assert_eq!(back.max_mm.to_bits(), metrics.max_mm.to_bits());
        assert_eq!(back.energy_j.to_bits(), metrics.energy_j.to_bits());
        assert!(back.current_step_p95_a.is_nan());
        assert_eq!(back.wall_contact_frames, 4);
    }

    #[test]
    fn the_stale_iox_sweep_removes_only_dead_owners_of_its_tag() {
        let tag = format!("mxtest{:x}", std::process::id() % 0xffff);
        let tmp = std::env::temp_dir();
        // A pid that cannot be running (above the kernel's pid_max of 2^22).
        let dead = tmp.join(format!("{tag}-4999999-0"));
        let alive = tmp.join(format!("{tag}-{}-0", std::process::id()));
        let other = tmp.join(format!("{tag}x-4999999-0"));
        for dir in [&dead, &alive, &other] {
            std::fs::create_dir_all(dir).unwrap();
        }
        let removed = crate::sweep_stale_iox(&tag);
        assert!(removed >= 1);
        assert!(!dead.exists());
        assert!(alive.exists() && other.exists());
        let _ = std::fs::remove_dir_all(&alive);
        let _ = std::fs::remove_dir_all(&other);
    }
}
