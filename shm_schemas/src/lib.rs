//! The millinav contract: every payload exchanged over iceoryx2 shared memory, the service
//! names, and the per-service deadlines. All payloads are `#[repr(C)]`, fixed-size and
//! self-contained so they can be placed in shared memory without serialization.
//!
//! Units are SI (m, s, A, T, N); times are nanoseconds on the run clock (sim time in lockstep,
//! monotonic time since run start in real-time mode). Every message carries the sequence number
//! of the camera frame it descends from so staleness and end-to-end latency are measurable.

use core::time::Duration;
use iceoryx2::prelude::ZeroCopySend;

/// Number of coils in the rig (4 units x 3 concentric coils).
pub const COIL_COUNT: usize = 12;

/// Camera frame geometry of the rig (top view, ≈92 x 92 mm).
pub const FRAME_WIDTH: u32 = 1020;
pub const FRAME_HEIGHT: u32 = 1020;
pub const FRAME_CHANNELS: u32 = 3;
pub const FRAME_BYTES: usize = (FRAME_WIDTH * FRAME_HEIGHT * FRAME_CHANNELS) as usize;
pub const FRAME_FIELD_OF_VIEW_MM: f64 = 92.0;

/// Sequence value used where a message does not descend from any frame (e.g. a safe-state zero).
pub const NO_FRAME: u64 = u64::MAX;

/// Pixel layouts a frame may carry.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelFormat {
    Rgb8 = 1,
    Gray8 = 2,
}

impl PixelFormat {
    pub fn from_u32(value: u32) -> Option<Self> {
        match value {
            1 => Some(Self::Rgb8),
            2 => Some(Self::Gray8),
            _ => None,
        }
    }

    pub fn channels(self) -> u32 {
        match self {
            Self::Rgb8 => 3,
            Self::Gray8 => 1,
        }
    }
}

/// User header of the Frame service (`publish_subscribe::<[u8]>().user_header::<FrameHeader>()`).
///
/// Pixel (col, row) maps to the world as
/// `x_mm = origin_x_mm + (col + 0.5) * mm_per_px`, `y_mm = origin_y_mm - (row + 0.5) * mm_per_px`
/// (x right, y up; mm here because it describes the image, a user-facing artefact).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::FrameHeader")]
pub struct FrameHeader {
    pub seq: u64,
    /// Incarnation of the frame source; a restarted source restarts `seq`.
    pub incarnation: u64,
    pub capture_time_ns: u64,
    pub width: u32,
    pub height: u32,
    pub stride: u32,
    /// A `PixelFormat` discriminant.
    pub pixel_format: u32,
    pub mm_per_px: f64,
    pub origin_x_mm: f64,
    pub origin_y_mm: f64,
}

impl FrameHeader {
    /// Checks that the header describes a buffer of `payload_len` bytes that can be read safely.
    pub fn validate(&self, payload_len: usize) -> Result<PixelFormat, ContractError> {
        let format = PixelFormat::from_u32(self.pixel_format)
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
        Ok(format)
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
}

/// Which localizer produced a pose.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoseSource {
    Classical = 1,
    Unet = 2,
}

/// Robot pose estimated by vision.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::Pose")]
pub struct Pose {
    pub frame_seq: u64,
    pub frame_incarnation: u64,
    pub capture_time_ns: u64,
    /// Centroid position (m).
    pub position_m: [f64; 2],
    /// Heading of the capsule axis, tail → tip, radians from +x.
    pub heading_rad: f64,
    pub tip_m: [f64; 2],
    pub centroid_m: [f64; 2],
    pub tail_m: [f64; 2],
    /// 0..1; meaningful only when `valid`.
    pub confidence: f64,
    /// False on no or ambiguous detection; the other fields are then not to be used.
    pub valid: bool,
    /// A `PoseSource` discriminant.
    pub source: u32,
}

impl Pose {
    /// A pose is usable only if flagged valid and all numbers are finite.
    pub fn is_usable(&self) -> bool {
        self.valid
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
#[type_name("millinav::FlowEstimate")]
pub struct FlowEstimate {
    /// Sequence of the frame of the pose this estimate was made for.
    pub frame_seq: u64,
    pub frame_incarnation: u64,
    pub capture_time_ns: u64,
    pub velocity_mps: [f64; 2],
    pub speed_mps: f64,
    /// Bit set of `zone::*`.
    pub zone_flags: u32,
    pub valid: bool,
}

/// What the controller asks of the coils.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ControlMode {
    /// Tracking the reference.
    Track = 1,
    /// Input stale or invalid for a short time: hold the last field, no force.
    Hold = 2,
    /// Input lost: zero currents.
    Safe = 3,
}

impl ControlMode {
    pub fn from_u32(value: u32) -> Option<Self> {
        match value {
            1 => Some(Self::Track),
            2 => Some(Self::Hold),
            3 => Some(Self::Safe),
            _ => None,
        }
    }
}

/// Coil currents requested by control for one frame.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::CoilCommand")]
pub struct CoilCommand {
    pub frame_seq: u64,
    pub frame_incarnation: u64,
    pub capture_time_ns: u64,
    /// Incarnation of the control process that produced the command.
    pub control_incarnation: u64,
    pub currents_a: [f64; COIL_COUNT],
    pub force_des_n: [f64; 2],
    pub field_des_t: [f64; 2],
    pub controller_id: u32,
    /// A `ControlMode` discriminant.
    pub mode: u32,
}

/// State of the serial link to the coil drivers.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkState {
    Disconnected = 0,
    Connected = 1,
}

/// What coilbus applied and how healthy its link is.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::CoilStatus")]
pub struct CoilStatus {
    /// Frame of the last applied command (`NO_FRAME` for a safe-state zero).
    pub frame_seq: u64,
    pub applied_currents_a: [f64; COIL_COUNT],
    /// A `LinkState` discriminant.
    pub link_state: u32,
    /// True while currents are zeroed because commands missed their deadline.
    pub watchdog_tripped: bool,
    pub frames_sent: u64,
    pub acks_received: u64,
    pub rx_errors: u64,
    pub stale_commands_rejected: u64,
    pub clamp_events: u64,
    pub deadline_misses: u64,
    pub reconnects: u64,
}

/// Ground truth of the digital twin. For metrics and tests only: no controller may read it.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::PlantTruth")]
pub struct PlantTruth {
    pub frame_seq: u64,
    pub sim_time_ns: u64,
    pub position_m: [f64; 2],
    pub velocity_mps: [f64; 2],
    pub heading_rad: f64,
    pub true_flow_mps: [f64; 2],
    pub applied_currents_a: [f64; COIL_COUNT],
    pub magnetic_force_n: [f64; 2],
    pub wall_contact: bool,
    /// Frames the plant stepped without the matching command (lockstep deadline misses).
    pub lockstep_misses: u64,
}

/// Health beacon every service publishes on `HEALTH_SERVICE`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("millinav::Heartbeat")]
pub struct Heartbeat {
    /// A `ServiceId` discriminant.
    pub service: u32,
    pub pid: u32,
    pub incarnation: u64,
    pub cycles: u64,
    pub deadline_misses: u64,
    pub wall_time_ns: u64,
}

/// The processes of the set.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum ServiceId {
    Plant = 1,
    Vision = 2,
    Flow = 3,
    Control = 4,
    Coilbus = 5,
    Supervisor = 6,
}

impl ServiceId {
    pub const ALL: [ServiceId; 6] = [
        Self::Plant,
        Self::Vision,
        Self::Flow,
        Self::Control,
        Self::Coilbus,
        Self::Supervisor,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Self::Plant => "plant",
            Self::Vision => "vision",
            Self::Flow => "flow",
            Self::Control => "control",
            Self::Coilbus => "coilbus",
            Self::Supervisor => "supervisor",
        }
    }

    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|s| s.name() == name)
    }

    pub fn from_u32(value: u32) -> Option<Self> {
        Self::ALL.into_iter().find(|s| *s as u32 == value)
    }

    /// Event service on which this process signals liveness.
    pub fn heartbeat_service(self) -> String {
        format!("millinav/{}/heartbeat", self.name())
    }
}

/// Data service names. Each has a companion event service (`event_service_of`).
pub mod services {
    pub const FRAME: &str = "millinav/camera/frame";
    pub const POSE: &str = "millinav/vision/pose";
    pub const FLOW: &str = "millinav/flow/estimate";
    pub const COMMAND: &str = "millinav/control/command";
    pub const COIL_STATUS: &str = "millinav/coilbus/status";
    pub const PLANT_TRUTH: &str = "millinav/plant/truth";
    pub const HEALTH: &str = "millinav/health";

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

    #[test]
    fn frame_header_validation_catches_bad_input() {
        let good = FrameHeader {
            width: FRAME_WIDTH,
            height: FRAME_HEIGHT,
            stride: FRAME_WIDTH * 3,
            pixel_format: PixelFormat::Rgb8 as u32,
            mm_per_px: FRAME_FIELD_OF_VIEW_MM / FRAME_WIDTH as f64,
            ..Default::default()
        };
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
    }

    #[test]
    fn nan_pose_is_not_usable() {
        let mut pose = Pose {
            valid: true,
            ..Default::default()
        };
        assert!(pose.is_usable());
        pose.position_m[0] = f64::NAN;
        assert!(!pose.is_usable());
    }

    #[test]
    fn service_names_round_trip() {
        for id in ServiceId::ALL {
            assert_eq!(ServiceId::from_name(id.name()), Some(id));
            assert_eq!(ServiceId::from_u32(id as u32), Some(id));
        }
    }
}
