//! control process (thin: all logic lives in the library).
use clap::Parser;
use millinav_kit::{service_main, ServiceArgs};
use shm_schemas::ServiceId;

/// Tracks the reference trajectory: Pose + FlowEstimate in, CoilCommand out. Scenario table:
/// [control].
#[derive(Parser)]
#[command(name = "millinav-control", version)]
struct Args {
    #[command(flatten)]
    service: ServiceArgs,
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    service_main(
        ServiceId::Control,
        &args.service,
        millinav_control::prepare,
        millinav_control::run,
    )
}
