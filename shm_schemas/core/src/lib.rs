//! The contract's limits and conventions that need no transport: the most coils anything
//! carries, and the image ↔ world pixel convention. `no_std` and without dependencies, so the
//! domain library (`fieldmaps`), the serial protocol and the board's firmware share the one
//! definition with the shared-memory contract (`shm_schemas`, which re-exports them).

#![no_std]

mod wire_enum;

/// Largest number of coils a rig has, a payload and a serial frame carry. Arrays of coil values are
/// this long; `active_coils` says how many leading entries are meaningful (the rest are zero).
/// 16 covers the rigs in view (12 paper coils, an 8-coil ring, 6-coil Helmholtz/Maxwell sets).
pub const MAX_COILS: usize = 16;

wire_enum! {
    /// The coil board's safety state: `BoardStatus.state` on the serial link, `CoilStatus::board_state`
    /// in the contract.
    pub enum BoardState: u8 {
        /// No valid `Config` yet: outputs off, `SetCurrents` refused.
        Unconfigured = 0 => "unconfigured",
        /// Configured, outputs off; `Arm` (with the serial protocol's `ARM_KEY`) arms.
        Disarmed = 1 => "disarmed",
        /// Outputs follow `SetCurrents`.
        Armed = 2 => "armed",
        /// Latched: outputs off until a deliberate re-arm (or a reset), whatever else arrives.
        EStop = 3 => "estop",
        /// A coil spent its I²t budget: outputs off until it cooled and the host re-arms.
        ThermalTrip = 4 => "thermal_trip",
    }
}

/// The contract's image ↔ world convention, the one place it is computed (`shm_schemas::FrameHeader` and
/// `fieldmaps::phantom::ImageGeometry` both delegate here).
///
/// Pixel coordinates (col, row) are continuous with pixel centres at integers; pixel (0, 0)'s
/// outer corner is the origin:
/// `x_mm = origin_x_mm + (col + 0.5) * mm_per_px`, `y_mm = origin_y_mm - (row + 0.5) * mm_per_px`
/// (x right, y up, rows down; mm because it describes the image, a user-facing artefact).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelMapping {
    pub mm_per_px: f64,
    pub origin_x_mm: f64,
    pub origin_y_mm: f64,
}

impl PixelMapping {
    /// Pixel coordinates → world point (x, y), m.
    pub fn pixel_to_world_m(&self, col: f64, row: f64) -> [f64; 2] {
        [
            (self.origin_x_mm + (col + 0.5) * self.mm_per_px) * 1e-3,
            (self.origin_y_mm - (row + 0.5) * self.mm_per_px) * 1e-3,
        ]
    }

    /// World point (x, y) in m → continuous pixel coordinates (col, row).
    pub fn world_to_pixel(&self, world_m: [f64; 2]) -> (f64, f64) {
        (
            (world_m[0] * 1e3 - self.origin_x_mm) / self.mm_per_px - 0.5,
            (self.origin_y_mm - world_m[1] * 1e3) / self.mm_per_px - 0.5,
        )
    }
}
