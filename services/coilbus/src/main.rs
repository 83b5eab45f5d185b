//! coilbus process: CoilCommand → clamped currents → Teensy serial link.
use clap::Parser;
use millinav_kit::{service_main, ServiceArgs};
use shm_schemas::ServiceId;

/// Drives the coil amplifiers: takes commands from control, enforces limits and deadlines, and
/// writes currents to the Teensy over a serial port (real, or the twin's emulated one).
/// Scenario table: [coilbus] (port, baud, optional lower current/power caps); coil count and
/// per-coil limits come from the scenario's rig file.
#[derive(Parser)]
#[command(name = "millinav-coilbus", version)]
struct Args {
    #[command(flatten)]
    service: ServiceArgs,
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    service_main(
        ServiceId::Coilbus,
        &args.service,
        millinav_coilbus::prepare,
        millinav_coilbus::run,
    )
}
