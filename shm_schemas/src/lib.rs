//! The millinav contract: every payload exchanged over iceoryx2 shared memory, the service
//! names, and the per-service deadlines. All payloads are `#[repr(C)]`, fixed-size and
//! self-contained so they can be placed in shared memory without serialization.
//!
//! Units are SI (m, s, A, T, N); times are nanoseconds on the run clock (sim time in lockstep,
//! monotonic time since run start in real-time mode). Every message carries the `FrameStamp` (or
//! at least the sequence number) of the camera frame it descends from so staleness and
//! end-to-end latency are measurable. Booleans travel as one-byte `Flag`s and coil values as
//! `MAX_COILS` arrays with an `active_coils` count. `CONTRACT.md` describes every payload byte
//! by byte for readers in other languages.

use core::mem::offset_of;
use core::time::Duration;
use iceoryx2::prelude::ZeroCopySend;

/// Version of the contract: payload layouts, their meaning and the service names. Every
/// payload's iceoryx2 type name ends in `.v<CONTRACT_VERSION>` (e.g. `millinav::Pose.v3`), and
/// iceoryx2 refuses to connect ports whose type names differ, so a peer built against another
/// version fails to open the services instead of misreading them. Bump it with any change a
/// foreign reader would notice (see `CONTRACT.md`); `tests::type_names_carry_the_contract_version`
/// checks every name.
pub const CONTRACT_VERSION: u32 = 4;

pub use shm_schemas_core::{wire_enum, BoardState, PixelMapping, MAX_COILS};

/// Bytes per pixel of an RGB8 frame (a frame's size is its rig camera's: `FrameHeader`).
pub const FRAME_CHANNELS: u32 = 3;

/// Sequence value used where a message does not descend from any frame (e.g. a safe-state zero).
pub const NO_FRAME: u64 = u64::MAX;

/// A boolean in shared memory: one byte, 0 = false, 1 = true. A `bool` field would make any
/// other byte written by a faulty or foreign peer undefined behaviour when read; a `Flag` is
/// always a valid `u8`, and `get` reports any other value as an error for the receiver to
/// count and treat as "not set".
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
pub struct Flag(u8);

impl Flag {
    pub const FALSE: Flag = Flag(0);
    pub const TRUE: Flag = Flag(1);

    /// The flag as received, whatever byte it holds (tests and foreign writers).
    pub const fn from_raw(byte: u8) -> Self {
        Self(byte)
    }

    pub const fn raw(self) -> u8 {
        self.0
    }

    /// The flag's value, or `None` for a byte other than 0 or 1.
    pub const fn get(self) -> Option<bool> {
        match self.0 {
            0 => Some(false),
            1 => Some(true),
            _ => None,
        }
    }
}

impl From<bool> for Flag {
    fn from(value: bool) -> Self {
        Self(u8::from(value))
    }
}

/// Reads `flag` of `payload`, naming both in the error when it holds a byte other than 0/1.
fn read_flag(
    flag: Flag,
    payload: &'static str,
    field: &'static str,
) -> Result<bool, ContractError> {
    flag.get().ok_or(ContractError::BadFlag {
        payload,
        field,
        value: flag.raw(),
    })
}

/// Copies `values` into a coil array; the count goes into the payload's `active_coils`.
pub fn coil_array(values: &[f64]) -> Result<([f64; MAX_COILS], u32), ContractError> {
    if values.len() > MAX_COILS {
        return Err(ContractError::BadCoilCount {
            payload: "coil array",
            count: values.len() as u64,
        });
    }
    let mut out = [0.0; MAX_COILS];
    out[..values.len()].copy_from_slice(values);
    Ok((out, values.len() as u32))
}

/// The `active_coils` leading entries of a received coil array.
fn active_slice<'a>(
    values: &'a [f64; MAX_COILS],
    active_coils: u32,
    payload: &'static str,
) -> Result<&'a [f64], ContractError> {
    values
        .get(..active_coils as usize)
        .ok_or(ContractError::BadCoilCount {
            payload,
            count: u64::from(active_coils),
        })
}

/// Which camera frame a message descends from: the stamp the frame source put on the frame,
/// carried unchanged by every message computed from it (pose, flow estimate, coil command).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
pub struct FrameStamp {
    /// Frame counter of the source, from 0; restarts with a new `incarnation`.
    pub seq: u64,
    /// Incarnation (restart count) of the frame source.
    pub incarnation: u64,
    /// Capture (exposure) time on the run clock, ns: when the scene looked like this frame.
    pub capture_time_ns: u64,
    /// Grab time on the run clock, ns: when the frame entered the set (the camera service
    /// dequeued it; the twin's simulated now). `grab − capture` is the camera's own latency,
    /// which control measures and compensates; 0 when the source knows no grab time.
    pub grab_time_ns: u64,
}

impl FrameStamp {
    /// A stamp captured and grabbed at the same instant (a source that cannot tell them apart).
    pub const fn new(seq: u64, incarnation: u64, capture_time_ns: u64) -> Self {
        Self {
            seq,
            incarnation,
            capture_time_ns,
            grab_time_ns: capture_time_ns,
        }
    }

    /// The same stamp grabbed at `grab_time_ns`.
    pub const fn grabbed_at(self, grab_time_ns: u64) -> Self {
        Self {
            grab_time_ns,
            ..self
        }
    }

    /// The camera's latency this stamp shows (grab − capture), ns.
    pub fn camera_latency_ns(&self) -> u64 {
        self.grab_time_ns.saturating_sub(self.capture_time_ns)
    }

    /// Capture time on the run clock, s.
    pub fn capture_time_s(&self) -> f64 {
        self.capture_time_ns as f64 * 1e-9
    }

    /// True if both stamps name the same frame of the same source incarnation.
    pub fn same_frame(&self, other: &FrameStamp) -> bool {
        self.seq == other.seq && self.incarnation == other.incarnation
    }

    /// Key that orders frames: a later source incarnation, then a later frame, is newer.
    pub fn order_key(&self) -> (u64, u64) {
        (self.incarnation, self.seq)
    }

    /// True if this stamp names a strictly newer frame than `other`.
    pub fn is_newer_than(&self, other: &FrameStamp) -> bool {
        self.order_key() > other.order_key()
    }
}

wire_enum! {
    /// Pixel layouts a frame may carry.
    pub enum PixelFormat: u32 {
        Rgb8 = 1 => "rgb8",
        Gray8 = 2 => "gray8",
    }
}

impl PixelFormat {
    pub fn channels(self) -> u32 {
        match self {
            Self::Rgb8 => 3,
            Self::Gray8 => 1,
        }
    }
}

/// User header of the Frame service (`publish_subscribe::<[u8]>().user_header::<FrameHeader>()`).
/// Pixels map to the world by [`PixelMapping`]'s convention ([`FrameHeader::pixel_to_world_m`]).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::FrameHeader.v4")]
pub struct FrameHeader {
    pub stamp: FrameStamp,
    pub width: u32,
    pub height: u32,
    /// Bytes from one row's start to the next.
    pub stride: u32,
    /// A `PixelFormat` discriminant.
    pub pixel_format: u32,
    pub mm_per_px: f64,
    /// World x (mm) of the outer corner of pixel (0, 0).
    pub origin_x_mm: f64,
    /// World y (mm) of the outer corner of pixel (0, 0).
    pub origin_y_mm: f64,
}

impl FrameHeader {
    /// Checks that the header describes a buffer of `payload_len` bytes that can be read safely.
    pub fn validate(&self, payload_len: usize) -> Result<PixelFormat, ContractError> {
        let format = PixelFormat::from_repr(self.pixel_format)
            .ok_or(ContractError::UnknownPixelFormat(self.pixel_format))?;
        let row_bytes = self.width as usize * format.channels() as usize;
        if self.width == 0 || self.height == 0 || (self.stride as usize) < row_bytes {
            return Err(ContractError::BadGeometry {
                width: self.width,
                height: self.height,
                stride: self.stride,
            });
        }
        let needed = self.stride as usize * self.height as usize;
        if payload_len < needed {
            return Err(ContractError::ShortPayload {
                needed,
                got: payload_len,
            });
        }
        if !(self.mm_per_px.is_finite() && self.mm_per_px > 0.0) {
            return Err(ContractError::BadScale(self.mm_per_px));
        }
        if !(self.origin_x_mm.is_finite() && self.origin_y_mm.is_finite()) {
            return Err(ContractError::BadOrigin);
        }
        Ok(format)
    }

    /// The frame's image ↔ world mapping.
    pub fn pixel_mapping(&self) -> PixelMapping {
        PixelMapping {
            mm_per_px: self.mm_per_px,
            origin_x_mm: self.origin_x_mm,
            origin_y_mm: self.origin_y_mm,
        }
    }

    /// Sets the header's scale and origin from `mapping`.
    pub fn with_mapping(mut self, mapping: PixelMapping) -> Self {
        self.mm_per_px = mapping.mm_per_px;
        self.origin_x_mm = mapping.origin_x_mm;
        self.origin_y_mm = mapping.origin_y_mm;
        self
    }

    /// Pixel coordinates (col, row; integers are pixel centres) → world point (x, y), m.
    pub fn pixel_to_world_m(&self, col: f64, row: f64) -> [f64; 2] {
        self.pixel_mapping().pixel_to_world_m(col, row)
    }

    /// World point (x, y) in m → continuous pixel coordinates (col, row).
    pub fn world_to_pixel(&self, world_m: [f64; 2]) -> (f64, f64) {
        self.pixel_mapping().world_to_pixel(world_m)
    }
}

/// Errors in a payload received from another process.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ContractError {
    #[error("unknown pixel format {0}")]
    UnknownPixelFormat(u32),
    #[error("bad frame geometry {width}x{height} stride {stride}")]
    BadGeometry {
        width: u32,
        height: u32,
        stride: u32,
    },
    #[error("frame payload too short: need {needed} bytes, got {got}")]
    ShortPayload { needed: usize, got: usize },
    #[error("bad frame scale {0} mm/px")]
    BadScale(f64),
    #[error("non-finite frame origin")]
    BadOrigin,
    #[error("{payload}.{field} holds {value}, not a flag (0 or 1)")]
    BadFlag {
        payload: &'static str,
        field: &'static str,
        value: u8,
    },
    #[error("{payload} carries {count} coils, more than MAX_COILS = {max}", max = MAX_COILS)]
    BadCoilCount { payload: &'static str, count: u64 },
}

wire_enum! {
    /// Which localizer produced a pose.
    pub enum PoseSource: u32 {
        Classical = 1 => "classical",
        Unet = 2 => "unet",
    }
}

/// Robot pose estimated by vision.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::Pose.v4")]
pub struct Pose {
    /// The frame this pose was measured in.
    pub stamp: FrameStamp,
    /// Centroid position (m).
    pub position_m: [f64; 2],
    /// Heading of the capsule axis, tail → tip, radians from +x.
    pub heading_rad: f64,
    pub tip_m: [f64; 2],
    pub centroid_m: [f64; 2],
    pub tail_m: [f64; 2],
    /// 0..1; meaningful only when `valid`.
    pub confidence: f64,
    /// A `PoseSource` discriminant.
    pub source: u32,
    /// 1 = a pose was found; 0 = no or ambiguous detection, the other fields are not to be
    /// used. Read it with [`Pose::validity`].
    pub valid: Flag,
    /// Sent as 0, ignored.
    pub reserved: [u8; 3],
}

impl Pose {
    /// The `valid` flag, or an error when it holds a byte other than 0/1.
    pub fn validity(&self) -> Result<bool, ContractError> {
        read_flag(self.valid, "Pose", "valid")
    }

    /// A pose is usable only if flagged valid (a bad flag byte is not valid) and all numbers
    /// are finite.
    pub fn is_usable(&self) -> bool {
        self.validity() == Ok(true)
            && self.position_m.iter().all(|v| v.is_finite())
            && self.heading_rad.is_finite()
            && self.confidence.is_finite()
    }
}

/// Zone flags of a flow estimate.
pub mod zone {
    pub const HIGH_DISTURBANCE: u32 = 1 << 0;
    pub const RECIRCULATION: u32 = 1 << 1;
    pub const OUTSIDE_MAP: u32 = 1 << 2;
}

/// Steady-map flow estimate at the robot (flow service).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::FlowEstimate.v4")]
pub struct FlowEstimate {
    /// The frame of the pose this estimate was made for.
    pub stamp: FrameStamp,
    pub velocity_mps: [f64; 2],
    pub speed_mps: f64,
    /// Bit set of `zone::*`.
    pub zone_flags: u32,
    /// 1 = the estimate may be used; read it with [`FlowEstimate::validity`].
    pub valid: Flag,
    /// Sent as 0, ignored.
    pub reserved: [u8; 3],
}

impl FlowEstimate {
    /// The `valid` flag, or an error when it holds a byte other than 0/1.
    pub fn validity(&self) -> Result<bool, ContractError> {
        read_flag(self.valid, "FlowEstimate", "valid")
    }
}

wire_enum! {
    /// What the controller asks of the coils.
    pub enum ControlMode: u32 {
        /// Tracking the reference.
        Track = 1 => "track",
        /// Input stale or invalid for a short time: hold the last field, no force.
        Hold = 2 => "hold",
        /// Input lost: zero currents.
        Safe = 3 => "safe",
    }
}

/// Coil currents requested by control for one frame.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::CoilCommand.v4")]
pub struct CoilCommand {
    /// The frame of the pose the command answers.
    pub stamp: FrameStamp,
    /// Incarnation of the control process that produced the command.
    pub control_incarnation: u64,
    /// Coils of the rig control allocated for; coilbus rejects a command whose count is not
    /// its own.
    pub active_coils: u32,
    /// A `ControlMode` discriminant.
    pub mode: u32,
    pub controller_id: u32,
    /// Sent as 0, ignored.
    pub reserved: u32,
    /// A; entries from `active_coils` on are 0. Read them with [`CoilCommand::currents`].
    pub currents_a: [f64; MAX_COILS],
    pub force_des_n: [f64; 2],
    pub field_des_t: [f64; 2],
}

impl CoilCommand {
    /// The `active_coils` requested currents, or an error for a count above `MAX_COILS`.
    pub fn currents(&self) -> Result<&[f64], ContractError> {
        active_slice(&self.currents_a, self.active_coils, "CoilCommand")
    }

    /// Sets the currents and the active coil count from `currents_a`.
    pub fn set_currents(&mut self, currents_a: &[f64]) -> Result<(), ContractError> {
        (self.currents_a, self.active_coils) = coil_array(currents_a)?;
        Ok(())
    }
}

wire_enum! {
    /// State of the serial link to the coil drivers.
    pub enum LinkState: u32 {
        Disconnected = 0 => "disconnected",
        Connected = 1 => "connected",
    }
}

/// `CoilStatus::board_state` before the board sent its first `Status`.
pub const BOARD_STATE_UNKNOWN: u8 = u8::MAX;

/// The name of a `CoilStatus::board_state` value, for logs and viewers.
pub fn board_state_name(state: u8) -> &'static str {
    match state {
        BOARD_STATE_UNKNOWN => "unknown",
        state => BoardState::from_repr(state).map_or("invalid", BoardState::name),
    }
}

wire_enum! {
    /// Why coilbus holds the coils safe on the board's account (`CoilStatus::board_fault`). Latched
    /// until coilbus restarts.
    pub enum BoardFault: u8 {
        None = 0 => "none",
        /// The board speaks another serial-protocol version.
        ProtocolVersion = 1 => "protocol_version",
        /// The board latched its emergency stop (input pin or `EStop` frame).
        EStop = 2 => "estop",
        /// A coil spent its I²t budget and the board tripped.
        ThermalTrip = 3 => "thermal_trip",
        /// The board's telemetry disagrees with what coilbus commanded (state, clamps, currents).
        TelemetryDisagrees = 4 => "telemetry_disagrees",
        /// The board refused the configuration coilbus sent (outside its hardware limits).
        ConfigRefused = 5 => "config_refused",
    }
}

/// What coilbus applied and how healthy its link is.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::CoilStatus.v4")]
pub struct CoilStatus {
    /// Frame of the last applied command (`NO_FRAME` for a safe-state zero).
    pub frame_seq: u64,
    /// A; entries from `active_coils` on are 0.
    pub applied_currents_a: [f64; MAX_COILS],
    /// A `LinkState` discriminant.
    pub link_state: u32,
    /// Coils coilbus drives (its configured count).
    pub active_coils: u32,
    /// 1 while currents are zeroed because commands missed their deadline; read it with
    /// [`CoilStatus::watchdog`].
    pub watchdog_tripped: Flag,
    /// The board's state from its newest `Status` (`BoardState` of the serial protocol:
    /// 0 unconfigured, 1 disarmed, 2 armed, 3 e-stop, 4 thermal trip), or
    /// [`BOARD_STATE_UNKNOWN`] before the first `Status`.
    pub board_state: u8,
    /// The board's `STATUS_*` flags from its newest `Status`.
    pub board_flags: u8,
    /// A `BoardFault` discriminant: why coilbus holds the coils safe (0 = none).
    pub board_fault: u8,
    /// Sent as 0, ignored.
    pub reserved: [u8; 2],
    /// The most used heat budget over the coils, ‰ (1000 = tripped).
    pub thermal_permille: u16,
    pub frames_sent: u64,
    pub acks_received: u64,
    pub rx_errors: u64,
    pub stale_commands_rejected: u64,
    pub clamp_events: u64,
    pub deadline_misses: u64,
    pub reconnects: u64,
    /// Commands refused because their `active_coils` differs from coilbus's coil count, or
    /// their coil data is malformed (nothing driven for them).
    pub coil_count_rejected: u64,
    /// Frames the board refused (its coil count differs from the frame's): `Ack` status
    /// `RejectedCoilCount` in the serial protocol.
    pub board_rejected: u64,
}

impl CoilStatus {
    /// The `watchdog_tripped` flag, or an error when it holds a byte other than 0/1.
    pub fn watchdog(&self) -> Result<bool, ContractError> {
        read_flag(self.watchdog_tripped, "CoilStatus", "watchdog_tripped")
    }

    /// The `active_coils` applied currents, or an error for a count above `MAX_COILS`.
    pub fn applied_currents(&self) -> Result<&[f64], ContractError> {
        active_slice(&self.applied_currents_a, self.active_coils, "CoilStatus")
    }
}

/// Ground truth of the digital twin. For metrics and tests only: no controller may read it.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::PlantTruth.v4")]
pub struct PlantTruth {
    pub frame_seq: u64,
    pub sim_time_ns: u64,
    pub position_m: [f64; 2],
    pub velocity_mps: [f64; 2],
    pub heading_rad: f64,
    pub true_flow_mps: [f64; 2],
    /// A; entries from `active_coils` on are 0.
    pub applied_currents_a: [f64; MAX_COILS],
    pub magnetic_force_n: [f64; 2],
    /// Frames the plant stepped without the matching command (lockstep deadline misses).
    pub lockstep_misses: u64,
    /// Coils of the twin's rig.
    pub active_coils: u32,
    /// 1 while the capsule touches a canal wall; read it with [`PlantTruth::wall_contact`].
    pub wall_contact: Flag,
    /// Sent as 0, ignored.
    pub reserved: [u8; 3],
}

impl PlantTruth {
    /// The `wall_contact` flag, or an error when it holds a byte other than 0/1.
    pub fn in_wall_contact(&self) -> Result<bool, ContractError> {
        read_flag(self.wall_contact, "PlantTruth", "wall_contact")
    }

    /// The `active_coils` applied currents, or an error for a count above `MAX_COILS`.
    pub fn applied_currents(&self) -> Result<&[f64], ContractError> {
        active_slice(&self.applied_currents_a, self.active_coils, "PlantTruth")
    }
}

/// Health beacon every service publishes on `HEALTH_SERVICE`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::Heartbeat.v4")]
pub struct Heartbeat {
    /// A `ServiceId` discriminant.
    pub service: u32,
    pub pid: u32,
    pub incarnation: u64,
    pub cycles: u64,
    pub deadline_misses: u64,
    pub wall_time_ns: u64,
    /// Samples the service's source lost before it saw them (camera: frames the device or the
    /// recording skipped), since this incarnation started.
    pub dropped_samples: u64,
    /// Faults of the service's source (camera: stall, unplug, read error, end of stream), since
    /// this incarnation started.
    pub source_faults: u64,
}

/// Most waypoints one operator request carries.
pub const MAX_OPERATOR_WAYPOINTS: usize = 32;

wire_enum! {
    /// What the operator asks of the running set (`millinav ctl`).
    pub enum OperatorVerb: u32 {
        /// Report the state; changes nothing.
        Status = 1 => "status",
        /// Plan from the current pose to `waypoints_m[0]` on the canal mask and follow it.
        Goto = 2 => "goto",
        /// Follow the current pose → `waypoints_m[..waypoint_count]`.
        Waypoints = 3 => "waypoints",
        /// Hold the current position.
        Pause = 4 => "pause",
        /// Continue the path held by `Pause`.
        Resume = 5 => "resume",
        /// Allow coil currents again (holding position until `Resume` or a new path).
        Arm = 6 => "arm",
        /// Zero the coil currents until `Arm`.
        Disarm = 7 => "disarm",
        /// Zero the coil currents, latched until `Arm`.
        EStop = 8 => "estop",
        /// End the run (answered by the supervisor, which stops the set safe-state first).
        Stop = 9 => "stop",
    }
}

wire_enum! {
    /// The operator's state as control keeps it.
    pub enum OperatorState: u32 {
        /// Following the path.
        Tracking = 1 => "tracking",
        /// Holding position (coils on).
        Paused = 2 => "paused",
        /// Coils at zero until `Arm`.
        Disarmed = 3 => "disarmed",
        /// Coils at zero, latched, until `Arm`.
        EStopped = 4 => "emergency-stopped",
        /// The set is shutting down (after `Stop`).
        Stopping = 5 => "stopping",
    }
}

/// One operator request (`OPERATOR_REQUEST`); answered by an [`OperatorReply`] with the same
/// `request_id`. A request sent again with the same id is answered again, not applied again.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::OperatorRequest.v4")]
pub struct OperatorRequest {
    pub request_id: u64,
    /// An `OperatorVerb` discriminant.
    pub verb: u32,
    pub waypoint_count: u32,
    /// World positions, m: `Goto` uses the first, `Waypoints` the first `waypoint_count`.
    pub waypoints_m: [[f64; 2]; MAX_OPERATOR_WAYPOINTS],
}

/// Control's answer to an [`OperatorRequest`] (`OPERATOR_REPLY`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("millinav::OperatorReply.v4")]
pub struct OperatorReply {
    pub request_id: u64,
    /// 1 = done, 0 = refused (nothing changed).
    pub accepted: Flag,
    /// Sent as 0, ignored.
    pub reserved: [u8; 3],
    /// The `OperatorState` after the request.
    pub state: u32,
    /// Last measured position, m (NaN before the first pose).
    pub position_m: [f64; 2],
    /// Where the current path ends, m.
    pub target_m: [f64; 2],
    /// UTF-8, NUL-padded: what was done, or why it was refused. Read it with
    /// [`OperatorReply::text`].
    pub message: [u8; 160],
}

impl OperatorReply {
    /// A reply with `message` (cut at a character boundary to fit).
    pub fn new(request_id: u64, accepted: bool, state: OperatorState, message: &str) -> Self {
        let mut bytes = [0u8; 160];
        let mut end = message.len().min(bytes.len());
        while !message.is_char_boundary(end) {
            end -= 1;
        }
        bytes[..end].copy_from_slice(&message.as_bytes()[..end]);
        Self {
            request_id,
            accepted: if accepted { Flag::TRUE } else { Flag::FALSE },
            reserved: [0; 3],
            state: state as u32,
            position_m: [f64::NAN; 2],
            target_m: [f64::NAN; 2],
            message: bytes,
        }
    }

    /// The message up to its first NUL (invalid UTF-8 shown replaced).
    pub fn text(&self) -> String {
        let end = self
            .message
            .iter()
            .position(|&b| b == 0)
            .unwrap_or(self.message.len());
        String::from_utf8_lossy(&self.message[..end]).into_owned()
    }
}

/// Pins a payload's size, alignment and every field's byte offset at compile time: a change
/// that moves a byte fails the build here, and `CONTRACT.md` (which lists the same numbers for
/// foreign readers) must change with it, together with `CONTRACT_VERSION`.
macro_rules! assert_layout {
    ($type:ty, size $size:expr, align $align:expr, { $($field:ident @ $offset:expr),* $(,)? }) => {
        const _: () = {
            assert!(size_of::<$type>() == $size);
            assert!(align_of::<$type>() == $align);
            $(assert!(offset_of!($type, $field) == $offset);)*
        };
    };
}

assert_layout!(Flag, size 1, align 1, {});
assert_layout!(FrameStamp, size 32, align 8, {
    seq @ 0, incarnation @ 8, capture_time_ns @ 16, grab_time_ns @ 24,
});
assert_layout!(FrameHeader, size 72, align 8, {
    stamp @ 0, width @ 32, height @ 36, stride @ 40, pixel_format @ 44,
    mm_per_px @ 48, origin_x_mm @ 56, origin_y_mm @ 64,
});
assert_layout!(Pose, size 120, align 8, {
    stamp @ 0, position_m @ 32, heading_rad @ 48, tip_m @ 56, centroid_m @ 72, tail_m @ 88,
    confidence @ 104, source @ 112, valid @ 116, reserved @ 117,
});
assert_layout!(FlowEstimate, size 64, align 8, {
    stamp @ 0, velocity_mps @ 32, speed_mps @ 48, zone_flags @ 56, valid @ 60, reserved @ 61,
});
assert_layout!(CoilCommand, size 216, align 8, {
    stamp @ 0, control_incarnation @ 32, active_coils @ 40, mode @ 44, controller_id @ 48,
    reserved @ 52, currents_a @ 56, force_des_n @ 184, field_des_t @ 200,
});
assert_layout!(CoilStatus, size 224, align 8, {
    frame_seq @ 0, applied_currents_a @ 8, link_state @ 136, active_coils @ 140,
    watchdog_tripped @ 144, board_state @ 145, board_flags @ 146, board_fault @ 147,
    reserved @ 148, thermal_permille @ 150, frames_sent @ 152, acks_received @ 160,
    rx_errors @ 168, stale_commands_rejected @ 176, clamp_events @ 184, deadline_misses @ 192,
    reconnects @ 200, coil_count_rejected @ 208, board_rejected @ 216,
});
assert_layout!(PlantTruth, size 232, align 8, {
    frame_seq @ 0, sim_time_ns @ 8, position_m @ 16, velocity_mps @ 32, heading_rad @ 48,
    true_flow_mps @ 56, applied_currents_a @ 72, magnetic_force_n @ 200, lockstep_misses @ 216,
    active_coils @ 224, wall_contact @ 228, reserved @ 229,
});
assert_layout!(Heartbeat, size 56, align 8, {
    service @ 0, pid @ 4, incarnation @ 8, cycles @ 16, deadline_misses @ 24, wall_time_ns @ 32,
    dropped_samples @ 40, source_faults @ 48,
});
assert_layout!(OperatorRequest, size 528, align 8, {
    request_id @ 0, verb @ 8, waypoint_count @ 12, waypoints_m @ 16,
});
assert_layout!(OperatorReply, size 208, align 8, {
    request_id @ 0, accepted @ 8, reserved @ 9, state @ 12, position_m @ 16, target_m @ 32,
    message @ 48,
});

wire_enum! {
    /// The processes of the set.
    #[derive(Hash, PartialOrd, Ord)]
    pub enum ServiceId: u32 {
        Plant = 1 => "plant",
        Vision = 2 => "vision",
        Flow = 3 => "flow",
        Control = 4 => "control",
        Coilbus = 5 => "coilbus",
        Supervisor = 6 => "supervisor",
        Camera = 7 => "camera",
    }
}

impl ServiceId {
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|s| s.name() == name)
    }

    /// Event service on which this process signals liveness.
    pub fn heartbeat_service(self) -> String {
        format!("millinav/{}/heartbeat", self.name())
    }
}

/// Data service names. Each has a companion event service (`event_service_of`).
pub mod services {
    /// Canonical top-view frames (rectified by the camera service): what vision reads.
    pub const FRAME: &str = "millinav/camera/frame";
    /// The twin's raw camera frames (its lens, its pose, its resolution), before rectification.
    pub const RAW_FRAME: &str = "millinav/camera/raw";
    pub const POSE: &str = "millinav/vision/pose";
    pub const FLOW: &str = "millinav/flow/estimate";
    pub const COMMAND: &str = "millinav/control/command";
    pub const COIL_STATUS: &str = "millinav/coilbus/status";
    pub const PLANT_TRUTH: &str = "millinav/plant/truth";
    pub const HEALTH: &str = "millinav/health";
    pub const OPERATOR_REQUEST: &str = "millinav/operator/request";
    pub const OPERATOR_REPLY: &str = "millinav/operator/reply";

    /// Name of the event service that announces new samples on `data_service`.
    pub fn event_service_of(data_service: &str) -> String {
        format!("{data_service}/event")
    }
}

/// Deadlines: a receiver that sees no sample within its deadline records a miss and acts.
pub mod deadlines {
    use super::Duration;

    /// Vision expects a frame at least this often (real-time camera at ≥ 10 Hz).
    pub const FRAME: Duration = Duration::from_millis(200);
    /// Control expects a pose at least this often before it holds, then goes safe.
    pub const POSE: Duration = Duration::from_millis(200);
    /// Control waits at most this long for the flow estimate of the current pose.
    pub const FLOW_FOR_POSE: Duration = Duration::from_millis(30);
    /// coilbus zeroes all currents when no command arrived for this long.
    pub const COMMAND: Duration = Duration::from_millis(100);
    /// The Teensy (and its emulator) zero PWM on their own when no frame came for this long.
    pub const TEENSY_WATCHDOG: Duration = Duration::from_millis(250);
    /// In lockstep the plant waits this long for the command of frame k, then steps anyway.
    pub const LOCKSTEP_COMMAND: Duration = Duration::from_millis(250);
    /// Every service beats at least this often; the supervisor restarts one that misses it.
    pub const HEARTBEAT: Duration = Duration::from_millis(1000);
    /// Period at which services emit heartbeats.
    pub const HEARTBEAT_PERIOD: Duration = Duration::from_millis(100);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn type_name<T: ZeroCopySend>() -> &'static str {
        // SAFETY: only reads the name; the layouts are pinned by `assert_layout!` above.
        unsafe { <T as ZeroCopySend>::type_name() }
    }

    #[test]
    fn type_names_carry_the_contract_version() {
        let names = [
            type_name::<FrameHeader>(),
            type_name::<Pose>(),
            type_name::<FlowEstimate>(),
            type_name::<CoilCommand>(),
            type_name::<CoilStatus>(),
            type_name::<PlantTruth>(),
            type_name::<Heartbeat>(),
            type_name::<OperatorRequest>(),
            type_name::<OperatorReply>(),
        ];
        let suffix = format!(".v{CONTRACT_VERSION}");
        for name in names {
            assert!(
                name.starts_with("millinav::") && name.ends_with(&suffix),
                "{name} does not end in {suffix}"
            );
        }
        assert_eq!(type_name::<Pose>(), "millinav::Pose.v4");
    }

    /// A camera of this size for the header tests (any size works the same).
    const WIDTH: u32 = 640;
    const HEIGHT: u32 = 640;
    const FRAME_BYTES: usize = (WIDTH * HEIGHT * FRAME_CHANNELS) as usize;

    fn good_header() -> FrameHeader {
        FrameHeader {
            width: WIDTH,
            height: HEIGHT,
            stride: WIDTH * 3,
            pixel_format: PixelFormat::Rgb8 as u32,
            mm_per_px: 92.0 / WIDTH as f64,
            origin_x_mm: -46.0,
            origin_y_mm: 46.0,
            ..Default::default()
        }
    }

    #[test]
    fn frame_header_validation_catches_bad_input() {
        let good = good_header();
        assert_eq!(good.validate(FRAME_BYTES), Ok(PixelFormat::Rgb8));
        assert!(matches!(
            good.validate(FRAME_BYTES - 1),
            Err(ContractError::ShortPayload { .. })
        ));
        let bad_format = FrameHeader {
            pixel_format: 99,
            ..good
        };
        assert!(bad_format.validate(FRAME_BYTES).is_err());
        let bad_scale = FrameHeader {
            mm_per_px: f64::NAN,
            ..good
        };
        assert!(bad_scale.validate(FRAME_BYTES).is_err());
        let bad_origin = FrameHeader {
            origin_y_mm: f64::INFINITY,
            ..good
        };
        assert_eq!(
            bad_origin.validate(FRAME_BYTES),
            Err(ContractError::BadOrigin)
        );
    }

    #[test]
    fn pixel_mapping_follows_the_documented_convention_and_round_trips() {
        let header = good_header();
        let s = header.mm_per_px;
        // The centre of pixel (0, 0) lies half a pixel inside the origin corner.
        let corner = header.pixel_to_world_m(0.0, 0.0);
        assert!((corner[0] - (-46.0 + 0.5 * s) * 1e-3).abs() < 1e-12);
        assert!((corner[1] - (46.0 - 0.5 * s) * 1e-3).abs() < 1e-12);
        // Rows grow downward, y grows upward.
        assert!(header.pixel_to_world_m(0.0, 10.0)[1] < corner[1]);
        // The image centre is the world origin for a centred camera.
        let mid = (WIDTH as f64 - 1.0) / 2.0;
        let centre = header.pixel_to_world_m(mid, mid);
        assert!(centre[0].abs() < 1e-12 && centre[1].abs() < 1e-12);
        for (col, row) in [(12.25, 700.5), (0.0, 1019.0), (511.7, 3.3)] {
            let (c, r) = header.world_to_pixel(header.pixel_to_world_m(col, row));
            assert!((c - col).abs() < 1e-9 && (r - row).abs() < 1e-9);
        }
    }

    #[test]
    fn nan_pose_is_not_usable() {
        let mut pose = Pose {
            valid: Flag::TRUE,
            ..Default::default()
        };
        assert!(pose.is_usable());
        pose.position_m[0] = f64::NAN;
        assert!(!pose.is_usable());
    }

    #[test]
    fn a_flag_byte_other_than_0_or_1_is_an_error_never_true() {
        let mut pose = Pose {
            valid: Flag::from_raw(2),
            ..Default::default()
        };
        assert_eq!(
            pose.validity(),
            Err(ContractError::BadFlag {
                payload: "Pose",
                field: "valid",
                value: 2
            })
        );
        assert!(!pose.is_usable());
        pose.valid = Flag::from(true);
        assert_eq!(pose.validity(), Ok(true));
        let flow = FlowEstimate {
            valid: Flag::from_raw(0xFF),
            ..Default::default()
        };
        assert!(flow.validity().is_err());
        let status = CoilStatus {
            watchdog_tripped: Flag::from_raw(7),
            ..Default::default()
        };
        assert!(status.watchdog().is_err());
        let truth = PlantTruth {
            wall_contact: Flag::from_raw(1),
            ..Default::default()
        };
        assert_eq!(truth.in_wall_contact(), Ok(true));
        assert_eq!(Flag::default().get(), Some(false));
    }

    #[test]
    fn coil_arrays_carry_their_count_and_reject_too_many() {
        let mut cmd = CoilCommand::default();
        cmd.set_currents(&[1.0, -2.0, 3.0]).unwrap();
        assert_eq!(cmd.active_coils, 3);
        assert_eq!(cmd.currents().unwrap(), &[1.0, -2.0, 3.0]);
        assert!(cmd.currents_a[3..].iter().all(|c| *c == 0.0));
        assert!(cmd.set_currents(&[0.0; MAX_COILS + 1]).is_err());
        cmd.active_coils = MAX_COILS as u32 + 1;
        assert_eq!(
            cmd.currents(),
            Err(ContractError::BadCoilCount {
                payload: "CoilCommand",
                count: MAX_COILS as u64 + 1
            })
        );
        let status = CoilStatus {
            active_coils: u32::MAX,
            ..Default::default()
        };
        assert!(status.applied_currents().is_err());
    }

    #[test]
    fn frame_stamps_compare_by_incarnation_then_seq() {
        let a = FrameStamp::new(10, 1, 5);
        assert!(FrameStamp::new(11, 1, 0).is_newer_than(&a));
        assert!(FrameStamp::new(0, 2, 0).is_newer_than(&a));
        assert!(!FrameStamp::new(10, 1, 99).is_newer_than(&a));
        assert!(a.same_frame(&FrameStamp::new(10, 1, 99)));
        assert!(!a.same_frame(&FrameStamp::new(10, 0, 5)));
        assert!((FrameStamp::new(0, 0, 1_500_000_000).capture_time_s() - 1.5).abs() < 1e-12);
    }

    #[test]
    fn service_names_round_trip() {
        for id in ServiceId::ALL {
            assert_eq!(ServiceId::from_name(id.name()), Some(id));
            assert_eq!(ServiceId::from_repr(id as u32), Some(id));
        }
    }

    #[test]
    fn every_wire_enum_round_trips_and_names_each_variant_once() {
        macro_rules! check {
            ($($name:ident: $repr:ty),+) => {$(
                let mut names = std::collections::BTreeSet::new();
                for v in $name::ALL {
                    assert_eq!($name::from_repr(v as $repr), Some(v), "{}", stringify!($name));
                    assert!(names.insert(v.name()), "{}: {} twice", stringify!($name), v.name());
                }
                let unused = (0..=<$repr>::from(u8::MAX))
                    .find(|n| !$name::ALL.iter().any(|v| *v as $repr == *n))
                    .unwrap();
                assert_eq!($name::from_repr(unused), None, "{}", stringify!($name));
            )+};
        }
        check!(
            PixelFormat: u32,
            PoseSource: u32,
            ControlMode: u32,
            LinkState: u32,
            BoardFault: u8,
            BoardState: u8,
            OperatorVerb: u32,
            OperatorState: u32,
            ServiceId: u32
        );
        assert_eq!(board_state_name(BoardState::EStop as u8), "estop");
        assert_eq!(board_state_name(BOARD_STATE_UNKNOWN), "unknown");
        assert_eq!(board_state_name(200), "invalid");
    }
}
