//! control process (thin: all logic lives in the library).
millinav_kit::service_binary! {
    /// Tracks the reference trajectory: Pose + FlowEstimate in, CoilCommand out. Scenario table:
    /// [control].
    name: "millinav-control",
    service: Control,
    library: millinav_control,
}
