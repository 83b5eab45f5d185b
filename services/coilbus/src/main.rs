//! coilbus process: CoilCommand → clamped currents → Teensy serial link.
millinav_kit::service_binary! {
    /// Drives the coil amplifiers: takes commands from control, enforces limits and deadlines, and
    /// writes currents to the Teensy over a serial port (real, or the twin's emulated one).
    /// Scenario table: [coilbus] (port, baud, optional lower current/power caps); coil count and
    /// per-coil limits come from the scenario's rig file.
    name: "millinav-coilbus",
    service: Coilbus,
    library: millinav_coilbus,
}
