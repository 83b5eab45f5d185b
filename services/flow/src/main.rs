//! flow process (thin: all logic lives in the library).
use clap::Parser;
use millinav_kit::{service_main, ServiceArgs};
use shm_schemas::ServiceId;

/// Looks up the steady flow map at the robot and publishes a FlowEstimate. Scenario table:
/// [flow].
#[derive(Parser)]
#[command(name = "millinav-flow", version)]
struct Args {
    #[command(flatten)]
    service: ServiceArgs,
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    service_main(
        ServiceId::Flow,
        &args.service,
        millinav_flow::prepare,
        millinav_flow::run,
    )
}
