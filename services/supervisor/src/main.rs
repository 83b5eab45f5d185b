//! `millinav`: the front door. `run` and `ctl` are the supervisor's own; the tool commands hand
//! their arguments to the workspace's tools next to this executable (`front_door`).
use std::ffi::OsString;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;
use clap::{Args, Parser, Subcommand};
use millinav_kit::scenario::ScenarioError;
use millinav_supervisor::front_door::Tool;
use millinav_supervisor::launch::{LaunchError, LaunchFile};
use millinav_supervisor::restart::EXIT_CONFIG;
use millinav_supervisor::{FailFast, SupervisorOptions, ViewerMode};

/// millinav: autonomous navigation of a magnetic millirobot through a heart phantom.
/// `millinav run` launches the process set (plant/camera, vision, flow, control, coilbus) on
/// the digital twin, supervises it and writes a Rerun recording of the run. The other commands
/// prepare a rig and study runs; `millinav <command> --help` shows each one's options.
#[derive(Parser)]
#[command(name = "millinav", version)]
struct Cli {
    #[command(subcommand)]
    command: Commands,
}

/// An iceoryx2 prefix as `kit::iox_domain` accepts it.
fn iox_prefix(text: &str) -> Result<String, String> {
    millinav_kit::iox_domain::validate_prefix(text).map(|()| text.to_owned())
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
        /// iceoryx2 file prefix of the set (give each concurrent run its own): letters, digits
        /// and '-', ending in one '_'. The set owns every iceoryx2 file that begins with it.
        #[arg(long, default_value = "millinav_", value_parser = iox_prefix)]
        iox_prefix: String,
        /// iceoryx2 root directory of the set. Keep it short: iceoryx2 creates Unix sockets
        /// under it, and their paths (root + prefix + a hash) must fit in 108 bytes.
        #[arg(long, default_value = "/tmp/millinav/iceoryx2")]
        iox_root: PathBuf,
        /// Stop after this many wall-clock seconds even if the run has not finished (default
        /// 600; none in a session).
        #[arg(long)]
        max_wall_s: Option<f64>,
        /// A session: control starts disarmed (`millinav ctl arm`), the twin runs past the
        /// scenario's duration, and the set runs until `millinav ctl stop` or Ctrl-C.
        #[arg(long)]
        session: bool,
        /// Record the camera's raw stream losslessly into the run (`frames/raw.mkv` + per-frame
        /// stamps in `frames/frames.csv`); replay it with `[camera] source = "replay:<run dir>"`.
        #[arg(long)]
        record_frames: bool,
        /// Directory of the service executables (default: next to this executable).
        #[arg(long)]
        bin_dir: Option<PathBuf>,
    },
    /// Send an operator command to a running set (give the --iox-prefix and --iox-root of its
    /// `millinav run`). Prints control's answer and the state it produced; exits 1 when control
    /// refused the command (nothing changed), 2 when no answer came.
    Ctl {
        /// iceoryx2 file prefix of the running set.
        #[arg(long, default_value = "millinav_", value_parser = iox_prefix)]
        iox_prefix: String,
        /// iceoryx2 root directory of the running set.
        #[arg(long, default_value = "/tmp/millinav/iceoryx2")]
        iox_root: PathBuf,
        /// Seconds to wait for control's answer.
        #[arg(long, default_value_t = 3.0)]
        timeout_s: f64,
        #[command(subcommand)]
        verb: CtlVerb,
    },
    /// Coil and flow field maps: build them from a rig file, import FEA and CFD exports, fit
    /// coils to gaussmeter readings.
    #[command(disable_help_flag = true)]
    Maps(ToolArgs),
    /// Check a rig file against its maps, mask and limits.
    Rig {
        #[command(subcommand)]
        what: RigCommand,
    },
    /// Camera calibration: intrinsics from checkerboard views, the floor homography, checks.
    #[command(disable_help_flag = true)]
    Calib(ToolArgs),
    /// Plan an A* path through the rig's canal mask.
    #[command(disable_help_flag = true)]
    Plan(ToolArgs),
    /// Vision: training crops, labelled frames, evaluation, the capsule's appearance.
    Vision {
        #[command(subcommand)]
        what: VisionCommand,
    },
    /// Experiment matrices (the paper's table, robustness, latency), locally or on Slurm.
    #[command(disable_help_flag = true)]
    Experiments(ToolArgs),
    /// Benchmarks: latency, loop rate, IPC, vision.
    #[command(disable_help_flag = true)]
    Bench(ToolArgs),
}

/// The arguments of a tool command, handed to the tool as they are (`--help` included).
#[derive(Args)]
struct ToolArgs {
    #[arg(trailing_var_arg = true, allow_hyphen_values = true, num_args = 0..)]
    args: Vec<OsString>,
}

#[derive(Subcommand)]
enum RigCommand {
    /// Check the rig file: maps, mask, coils, limits.
    #[command(disable_help_flag = true)]
    Check(ToolArgs),
}

#[derive(Subcommand)]
enum VisionCommand {
    /// Render training crops with masks and keypoints from the twin's camera.
    #[command(disable_help_flag = true)]
    Dataset(ToolArgs),
    /// Turn LabelMe-labelled frames of your camera into training crops.
    #[command(disable_help_flag = true)]
    ImportLabels(ToolArgs),
    /// Precision, recall, IoU, keypoint errors and latency of the localizers.
    #[command(disable_help_flag = true)]
    Eval(ToolArgs),
    /// Measure the capsule's colours for the classical localizer.
    #[command(disable_help_flag = true)]
    Appearance(ToolArgs),
}

/// The directory of this executable: where the services and tools are.
fn own_dir() -> anyhow::Result<PathBuf> {
    Ok(std::env::current_exe()?
        .parent()
        .context("executable has no directory")?
        .to_owned())
}

/// Runs the tool command `words` with `args` in place of this process.
fn run_tool(words: &str, args: ToolArgs) -> anyhow::Result<ExitCode> {
    let tool = Tool::named(words).with_context(|| format!("no tool for `millinav {words}`"))?;
    Err(tool.exec(&own_dir()?, &args.args).into())
}

#[derive(Subcommand)]
enum CtlVerb {
    /// Plan from the robot's pose to (X, Y) in mm with the A* planner on the rig's canal mask
    /// (clearance: the scenario's `[control] replan_clearance_mm`, default 5) and follow it.
    Goto {
        #[arg(allow_negative_numbers = true)]
        x_mm: f64,
        #[arg(allow_negative_numbers = true)]
        y_mm: f64,
    },
    /// Follow the path in FILE (TOML: `waypoints_mm = [[x, y], ...]`, mm, at most 32) from the
    /// robot's pose.
    Waypoints { file: PathBuf },
    /// Hold the current position.
    Pause,
    /// Continue the paused path where it stopped.
    Resume,
    /// Allow coil currents again; the robot holds position until resume or a new path.
    Arm,
    /// Zero the coil currents until arm.
    Disarm,
    /// Zero the coil currents, latched until arm.
    Estop,
    /// Report the state, the robot's position and where the path ends.
    Status,
    /// End the run: the supervisor stops the set safe-state first and writes the summary.
    Stop,
}

/// Configuration errors (scenario, launch file, a child's check or exit) end with `EX_CONFIG`,
/// like the services themselves; anything else with 1.
fn main() -> ExitCode {
    match run_cli(Cli::parse()) {
        Ok(code) => code,
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

fn run_cli(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Commands::Maps(args) => run_tool("maps", args),
        Commands::Rig {
            what: RigCommand::Check(args),
        } => run_tool("rig check", args),
        Commands::Calib(args) => run_tool("calib", args),
        Commands::Plan(args) => run_tool("plan", args),
        Commands::Vision { what } => match what {
            VisionCommand::Dataset(args) => run_tool("vision dataset", args),
            VisionCommand::ImportLabels(args) => run_tool("vision import-labels", args),
            VisionCommand::Eval(args) => run_tool("vision eval", args),
            VisionCommand::Appearance(args) => run_tool("vision appearance", args),
        },
        Commands::Experiments(args) => run_tool("experiments", args),
        Commands::Bench(args) => run_tool("bench", args),
        Commands::Ctl {
            iox_prefix,
            iox_root,
            timeout_s,
            verb,
        } => {
            use millinav_supervisor::ctl;
            use shm_schemas::{Flag, OperatorVerb};
            if !(timeout_s.is_finite() && timeout_s > 0.0) {
                anyhow::bail!("--timeout-s must be a positive number of seconds");
            }
            let (verb, goal, file) = match verb {
                CtlVerb::Goto { x_mm, y_mm } => (OperatorVerb::Goto, Some([x_mm, y_mm]), None),
                CtlVerb::Waypoints { file } => (OperatorVerb::Waypoints, None, Some(file)),
                CtlVerb::Pause => (OperatorVerb::Pause, None, None),
                CtlVerb::Resume => (OperatorVerb::Resume, None, None),
                CtlVerb::Arm => (OperatorVerb::Arm, None, None),
                CtlVerb::Disarm => (OperatorVerb::Disarm, None, None),
                CtlVerb::Estop => (OperatorVerb::EStop, None, None),
                CtlVerb::Status => (OperatorVerb::Status, None, None),
                CtlVerb::Stop => (OperatorVerb::Stop, None, None),
            };
            let request = ctl::request(verb, goal, file.as_deref())?;
            match ctl::send(
                &request,
                &iox_prefix,
                &iox_root,
                Duration::from_secs_f64(timeout_s),
            ) {
                Ok(reply) => {
                    println!("{}", ctl::describe(verb, &reply));
                    Ok(if reply.accepted == Flag::TRUE {
                        ExitCode::SUCCESS
                    } else {
                        ExitCode::from(1)
                    })
                }
                Err(e @ ctl::CtlError::NoAnswer(_)) => {
                    eprintln!("Error: {e}");
                    Ok(ExitCode::from(2))
                }
                Err(e) => Err(e.into()),
            }
        }
        Commands::Run {
            scenario,
            launch,
            run_dir,
            viewer,
            iox_prefix,
            iox_root,
            max_wall_s,
            session,
            record_frames,
            bin_dir,
        } => {
            let launch = match launch {
                Some(path) => LaunchFile::load(&path)?,
                None => LaunchFile::default(),
            };
            let bin_dir = match bin_dir {
                Some(dir) => dir,
                None => own_dir()?,
            };
            let run_dir = run_dir.unwrap_or_else(|| {
                let secs = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map(|d| d.as_secs())
                    .unwrap_or(0);
                PathBuf::from("runs").join(format!("run-{secs}"))
            });
            let max_wall_time = match (max_wall_s, session) {
                (Some(s), _) if !(s.is_finite() && s > 0.0) => {
                    anyhow::bail!("--max-wall-s must be a positive number of seconds")
                }
                (Some(s), _) => Duration::from_secs_f64(s),
                (None, true) => Duration::MAX,
                (None, false) => Duration::from_secs(600),
            };
            millinav_supervisor::run(SupervisorOptions {
                scenario,
                launch,
                run_dir,
                bin_dir,
                viewer,
                iox_prefix,
                iox_root,
                max_wall_time,
                session,
                record_frames,
            })?;
            Ok(ExitCode::SUCCESS)
        }
    }
}
