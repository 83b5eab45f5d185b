//! vision process (thin: all logic lives in the library).
use clap::Parser;
use millinav_kit::{service_main, ServiceArgs};
use shm_schemas::ServiceId;

/// Localizes the capsule in camera frames and publishes its Pose. Scenario table: [vision].
#[derive(Parser)]
#[command(name = "millinav-vision", version)]
struct Args {
    #[command(flatten)]
    service: ServiceArgs,
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    service_main(
        ServiceId::Vision,
        &args.service,
        millinav_vision::prepare,
        millinav_vision::run,
    )
}
