//! vision process (thin: all logic lives in the library).
use clap::Parser;

/// Localizes the capsule in camera frames and publishes its Pose.
#[derive(Parser)]
#[command(name = "millinav-vision", version)]
struct Args {
    /// Scenario TOML file (the run, fluid and trajectory, plus a [vision] table).
    #[arg(long)]
    scenario: std::path::PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    millinav_vision::main_with_scenario(&args.scenario)
}
