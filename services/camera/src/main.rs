//! camera process (thin: all logic lives in the library).
use clap::Parser;
use millinav_kit::{service_main, ServiceArgs};
use shm_schemas::ServiceId;

/// Publishes the rig's canonical top-view frames from a camera (a V4L2 device, a video file, a
/// folder of images, a recorded run or the twin's raw camera), rectified with the rig file's
/// `[camera.calibration]`. Scenario table: [camera].
#[derive(Parser)]
#[command(name = "millinav-camera", version)]
struct Args {
    #[command(flatten)]
    service: ServiceArgs,
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    service_main(
        ServiceId::Camera,
        &args.service,
        millinav_camera::prepare,
        millinav_camera::run,
    )
}
