//! camera process (thin: all logic lives in the library).
millinav_kit::service_binary! {
    /// Publishes the rig's canonical top-view frames from a camera (a V4L2 device, a video file, a
    /// folder of images, a recorded run or the twin's raw camera), rectified with the rig file's
    /// `[camera.calibration]`. Scenario table: [camera].
    name: "millinav-camera",
    service: Camera,
    library: millinav_camera,
}
