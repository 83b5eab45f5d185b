//! `millinav`: the supervisor's command line.
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;
use clap::{Parser, Subcommand};
use millinav_kit::scenario::ScenarioError;
use millinav_supervisor::launch::{LaunchError, LaunchFile};
use millinav_supervisor::restart::EXIT_CONFIG;
use millinav_supervisor::{FailFast, SupervisorOptions, ViewerMode};

/// millinav: autonomous navigation of a magnetic millirobot through a heart phantom.
/// `millinav run` launches the process set (plant/camera, vision, flow, control, coilbus) on
/// the digital twin, supervises it and writes a Rerun recording of the run.
#[derive(Parser)]
#[command(name = "millinav", version)]
struct Cli {
    #[command(subcommand)]
    command: Commands,
}

#[derive(Subcommand)]
enum Commands {
    /// Launch and supervise the process set for one scenario.
    Run {
        /// Scenario TOML (run mode, seed, fluid, flow, trajectory, per-service tables).
        #[arg(default_value = "scenarios/default.toml")]
        scenario: PathBuf,
        /// Launch file listing the processes; default: the full set on the digital twin.
        #[arg(long)]
        launch: Option<PathBuf>,
        /// Directory for this run's recordings, logs and event files (default runs/<time>).
        #[arg(long)]
        run_dir: Option<PathBuf>,
        /// Rerun viewer: auto spawns one when installed and a display exists.
        #[arg(long, value_enum, default_value = "auto")]
        viewer: ViewerMode,
        /// iceoryx2 file prefix of the set (give each concurrent run its own).
        #[arg(long, default_value = "millinav_")]
        iox_prefix: String,
        /// iceoryx2 root directory of the set. Keep it short: iceoryx2 creates Unix sockets
        /// under it, and their paths (root + prefix + a hash) must fit in 108 bytes.
        #[arg(long, default_value = "/tmp/millinav/iceoryx2")]
        iox_root: PathBuf,
        /// Stop after this many wall-clock seconds even if the run has not finished.
        #[arg(long, default_value_t = 600.0)]
        max_wall_s: f64,
        /// Directory of the service executables (default: next to this executable).
        #[arg(long)]
        bin_dir: Option<PathBuf>,
    },
}

/// Configuration errors (scenario, launch file, a child's check or exit) end with `EX_CONFIG`,
/// like the services themselves; anything else with 1.
fn main() -> ExitCode {
    match run_cli(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            // The message and its causes, without a backtrace: this is what a user reads.
            eprintln!("Error: {error:#}");
            let config_error = error.downcast_ref::<FailFast>().is_some()
                || error.downcast_ref::<ScenarioError>().is_some()
                || error.downcast_ref::<LaunchError>().is_some()
                || millinav_kit::config::is_config_error(&error);
            if config_error {
                ExitCode::from(EXIT_CONFIG)
            } else {
                ExitCode::FAILURE
            }
        }
    }
}

fn run_cli(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Commands::Run {
            scenario,
            launch,
            run_dir,
            viewer,
            iox_prefix,
            iox_root,
            max_wall_s,
            bin_dir,
        } => {
            let launch = match launch {
                Some(path) => LaunchFile::load(&path)?,
                None => LaunchFile::default(),
            };
            let bin_dir = match bin_dir {
                Some(dir) => dir,
                None => std::env::current_exe()?
                    .parent()
                    .context("executable has no directory")?
                    .to_owned(),
            };
            let run_dir = run_dir.unwrap_or_else(|| {
                let secs = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map(|d| d.as_secs())
                    .unwrap_or(0);
                PathBuf::from("runs").join(format!("run-{secs}"))
            });
            if !(max_wall_s.is_finite() && max_wall_s > 0.0) {
                anyhow::bail!("--max-wall-s must be a positive number of seconds");
            }
            millinav_supervisor::run(SupervisorOptions {
                scenario,
                launch,
                run_dir,
                bin_dir,
                viewer,
                iox_prefix,
                iox_root,
                max_wall_time: Duration::from_secs_f64(max_wall_s),
            })
        }
    }
}
