//! flow process (thin: all logic lives in the library).
millinav_kit::service_binary! {
    /// Looks up the steady flow map at the robot and publishes a FlowEstimate. Scenario table:
    /// [flow].
    name: "millinav-flow",
    service: Flow,
    library: millinav_flow,
}
