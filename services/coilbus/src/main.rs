//! coilbus process: CoilCommand → clamped currents → Teensy serial link.
use clap::Parser;

/// Drives the coil amplifiers: takes commands from control, enforces limits and deadlines, and
/// writes currents to the Teensy over a serial port (real, or the twin's emulated one).
#[derive(Parser)]
#[command(name = "millinav-coilbus", version)]
struct Args {
    /// Scenario TOML file; its [coilbus] table configures port, baud and limits.
    #[arg(long)]
    scenario: std::path::PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    millinav_coilbus::main_with_scenario(&args.scenario)
}
