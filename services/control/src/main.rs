//! control process (thin: all logic lives in the library).
use clap::Parser;

/// Tracks the reference trajectory: Pose + FlowEstimate in, CoilCommand out.
#[derive(Parser)]
#[command(name = "millinav-control", version)]
struct Args {
    /// Scenario TOML file (the run, fluid and trajectory, plus a [control] table).
    #[arg(long)]
    scenario: std::path::PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    millinav_control::main_with_scenario(&args.scenario)
}
