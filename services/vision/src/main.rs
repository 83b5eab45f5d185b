//! vision process (thin: all logic lives in the library).
millinav_kit::service_binary! {
    /// Localizes the capsule in camera frames and publishes its Pose. Scenario table: [vision].
    name: "millinav-vision",
    service: Vision,
    library: millinav_vision,
}
