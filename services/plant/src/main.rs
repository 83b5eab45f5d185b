//! plant process (thin: all logic lives in the library).
use clap::Parser;

/// The digital twin of the rig: physics, camera frames, PlantTruth and an emulated Teensy on a pty.
#[derive(Parser)]
#[command(name = "millinav-plant", version)]
struct Args {
    /// Scenario TOML file (the run, fluid and trajectory, plus a [plant] table).
    #[arg(long)]
    scenario: std::path::PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    millinav_plant::main_with_scenario(&args.scenario)
}
