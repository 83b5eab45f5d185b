//! flow process (thin: all logic lives in the library).
use clap::Parser;

/// Looks up the steady flow map at the robot and publishes a FlowEstimate.
#[derive(Parser)]
#[command(name = "millinav-flow", version)]
struct Args {
    /// Scenario TOML file (the run, fluid and trajectory, plus a [flow] table).
    #[arg(long)]
    scenario: std::path::PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    millinav_flow::main_with_scenario(&args.scenario)
}
