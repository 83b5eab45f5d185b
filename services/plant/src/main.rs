//! plant process (thin: all logic lives in the library).
use clap::Parser;

/// The digital twin of the rig: physics, camera frames, PlantTruth and an emulated Teensy on a pty.
#[derive(Parser)]
#[command(
    name = "millinav-plant",
    version,
    after_help = "Signals: SIGUSR1 unplugs the emulated Teensy's USB link for \
                  [plant.link_faults] unplug_ms (default 500 ms); SIGUSR2 stalls its firmware for \
                  hang_ms (default 800 ms; its hardware watchdog zeroes the coils after 250 ms). \
                  SIGINT/SIGTERM stop the run."
)]
struct Args {
    /// Scenario TOML file (the run, fluid and trajectory, plus a [plant] table).
    #[arg(long)]
    scenario: std::path::PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    millinav_plant::main_with_scenario(&args.scenario)
}
