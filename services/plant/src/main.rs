//! plant process (thin: all logic lives in the library).
use clap::Parser;
use millinav_kit::{service_main, ServiceArgs};
use shm_schemas::ServiceId;

/// The digital twin of the rig: physics, camera frames, PlantTruth and an emulated Teensy on a
/// pty. Scenario tables: [plant], and the map of [flow].
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
    #[command(flatten)]
    service: ServiceArgs,
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    service_main(
        ServiceId::Plant,
        &args.service,
        millinav_plant::prepare,
        millinav_plant::run,
    )
}
