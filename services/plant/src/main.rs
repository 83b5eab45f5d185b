//! plant process (thin: all logic lives in the library).
millinav_kit::service_binary! {
    /// The digital twin of the rig: physics, camera frames, PlantTruth and an emulated Teensy on a
    /// pty. Scenario tables: [plant], and the map of [flow].
    name: "millinav-plant",
    service: Plant,
    library: millinav_plant,
    after_help: "Signals: SIGUSR1 unplugs the emulated Teensy's USB link for \
                 [plant.link_faults] unplug_ms (default 500 ms); SIGUSR2 stalls its firmware for \
                 hang_ms (default 800 ms; its hardware watchdog zeroes the coils after 250 ms). \
                 SIGINT/SIGTERM stop the run.",
}
