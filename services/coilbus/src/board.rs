//! What coilbus expects of the coil-driver board, checked against the board's `Status`
//! telemetry: its state, its clamp flag, and per channel the current it was asked for, the one
//! it applies and (where it senses them) the one it measures. A board that went safe (e-stop,
//! thermal trip), speaks another protocol version, or disagrees with what coilbus commanded
//! latches a [`BoardFault`]; coilbus then holds the coils at zero and never re-arms it.

use serde::{Deserialize, Serialize};
use shm_schemas::{BoardFault, MAX_COILS};

use crate::protocol::{
    AckStatus, BoardState, BoardStatus, NOT_MEASURED, PROTOCOL_VERSION, STATUS_CLAMPED,
    STATUS_CONFIG_REFUSED, STATUS_DERATING, STATUS_WATCHDOG,
};

/// How far telemetry may stray from the command before coilbus calls it a disagreement.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TelemetryTolerance {
    /// Measured vs applied current: the larger of this (A) …
    pub current_a: f64,
    /// … and this fraction of the applied current.
    pub fraction: f64,
    /// Consecutive disagreeing `Status` frames (20 ms apart) before coilbus goes safe: a coil's
    /// current lags its command by its L/R time constant, and a `Status` may cross a command.
    pub persistence: u32,
}

impl Default for TelemetryTolerance {
    fn default() -> Self {
        Self {
            current_a: 0.1,
            fraction: 0.1,
            persistence: 3,
        }
    }
}

/// Commands in flight a `Status` may lag behind (four at 100 Hz is 40 ms).
const RECENT_COMMANDS: usize = 4;

/// A latched fault and its explanation.
#[derive(Debug, Clone, PartialEq)]
pub struct Fault {
    pub kind: BoardFault,
    pub detail: String,
}

/// Tracks the board's telemetry against what coilbus sent it.
#[derive(Debug, Clone)]
pub struct BoardMonitor {
    tolerance: TelemetryTolerance,
    coil_count: usize,
    /// The newest `SetCurrents` values written (mA), newest first: a `Status` crossing commands
    /// in flight may report any of them.
    recent_commands: [Option<[i32; MAX_COILS]>; RECENT_COMMANDS],
    /// Per-coil limit coilbus clamps to (mA): a board clamping below it has another `Config`.
    limits_ma: [i32; MAX_COILS],
    strikes: u32,
    /// The board acknowledged (applied or clamped) a command of this process since it armed:
    /// `Status` frames after that ack reflect this process's commands, earlier ones (queued in
    /// the port while a predecessor ran, or before arming) may not.
    synced: bool,
    armed_seen: bool,
    pub state: Option<BoardState>,
    pub flags: u8,
    pub thermal_permille: u16,
    fault: Option<Fault>,
}

impl BoardMonitor {
    pub fn new(coil_count: usize, limits_a: &[f64], tolerance: TelemetryTolerance) -> Self {
        let mut limits_ma = [i32::MAX; MAX_COILS];
        for (limit, a) in limits_ma.iter_mut().zip(limits_a) {
            *limit = crate::protocol::amps_to_ma(*a);
        }
        Self {
            tolerance,
            coil_count: coil_count.min(MAX_COILS),
            recent_commands: [None; RECENT_COMMANDS],
            limits_ma,
            strikes: 0,
            synced: false,
            armed_seen: false,
            state: None,
            flags: 0,
            thermal_permille: 0,
            fault: None,
        }
    }

    /// The latched fault, if any.
    pub fn fault(&self) -> Option<&Fault> {
        self.fault.as_ref()
    }

    /// Records the currents of a `SetCurrents` written to the board.
    pub fn commanded(&mut self, currents_ma: &[i32]) {
        let mut values = [0; MAX_COILS];
        let n = currents_ma.len().min(MAX_COILS);
        values[..n].copy_from_slice(&currents_ma[..n]);
        self.recent_commands.rotate_right(1);
        self.recent_commands[0] = Some(values);
    }

    /// Notes the board's `Ack` of a `SetCurrents` (its `AckStatus` byte).
    pub fn acked(&mut self, status: u8) {
        if status == AckStatus::Applied as u8 || status == AckStatus::Clamped as u8 {
            self.synced = true;
        }
    }

    /// The board speaks protocol `version`, not this host's: refused for good.
    pub fn foreign_version(&mut self, version: u8) -> Option<&Fault> {
        self.latch(
            BoardFault::ProtocolVersion,
            format!(
                "the board speaks serial-protocol version {version}, this host speaks \
                 {PROTOCOL_VERSION}: flash the firmware built from this repository \
                 (firmware/FIRMWARE.md); nothing is driven"
            ),
        )
    }

    /// Checks one `Status`; returns the fault it latched, if it latched one now.
    pub fn on_status(&mut self, status: &BoardStatus) -> Option<&Fault> {
        let state = BoardState::from_repr(status.state);
        if state == Some(BoardState::Armed) && self.state != state {
            // Commands sent before the board armed were refused (`NotArmed`): compare only
            // with what comes after.
            self.recent_commands = [None; RECENT_COMMANDS];
            self.synced = false;
        }
        self.state = state;
        self.flags = status.flags;
        self.thermal_permille = status
            .channels()
            .iter()
            .map(|c| c.thermal_permille)
            .max()
            .unwrap_or(0);
        if self.fault.is_some() {
            return None;
        }
        if status.flags & STATUS_CONFIG_REFUSED != 0 {
            return self.latch(
                BoardFault::ConfigRefused,
                "the board refused the configuration coilbus sent (channel count, supply \
                 voltage, watchdog or a coil rating outside its hardware limits: \
                 firmware/FIRMWARE.md); nothing is driven"
                    .into(),
            );
        }
        match state {
            Some(BoardState::Armed) => self.armed_seen = true,
            Some(BoardState::EStop) => {
                let by = if status.flags & crate::protocol::STATUS_ESTOP_INPUT != 0 {
                    "its e-stop input"
                } else {
                    "an EStop frame"
                };
                return self.latch(
                    BoardFault::EStop,
                    format!("the board latched its emergency stop ({by}): coils off"),
                );
            }
            Some(BoardState::ThermalTrip) => {
                let hottest = status
                    .channels()
                    .iter()
                    .enumerate()
                    .max_by_key(|(_, c)| c.thermal_permille)
                    .map_or(0, |(k, _)| k);
                return self.latch(
                    BoardFault::ThermalTrip,
                    format!(
                        "coil {hottest} spent its I²t heat budget: the board tripped, coils off"
                    ),
                );
            }
            // Unconfigured after a reset, or disarmed: the link configures and re-arms it.
            Some(BoardState::Unconfigured) | Some(BoardState::Disarmed) => {
                self.strikes = 0;
                return None;
            }
            None => {
                return self.strike(format!(
                    "the board reports an unknown state {}",
                    status.state
                ))
            }
        }
        if let Some(problem) = self.disagreement(status) {
            return self.strike(problem);
        }
        self.strikes = 0;
        None
    }

    /// What in an armed board's `Status` contradicts the command, if anything.
    fn disagreement(&self, status: &BoardStatus) -> Option<String> {
        let channels = status.channels();
        if channels.len() != self.coil_count {
            return Some(format!(
                "the board reports {} channels, coilbus drives {}",
                channels.len(),
                self.coil_count
            ));
        }
        let sent: Vec<&[i32; MAX_COILS]> = self.recent_commands.iter().flatten().collect();
        if sent.is_empty() || !self.synced {
            return None;
        }
        let watchdog = status.flags & STATUS_WATCHDOG != 0;
        let derating = status.flags & STATUS_DERATING != 0;
        for (k, ch) in channels.iter().enumerate() {
            if !sent.iter().any(|c| (c[k] - ch.commanded_ma).abs() <= 1) {
                return Some(format!(
                    "channel {k}: the board was asked for {} mA, coilbus sent {} mA",
                    ch.commanded_ma, sent[0][k]
                ));
            }
            let within_limit = ch.commanded_ma.abs() <= self.limits_ma[k];
            if !watchdog && !derating && within_limit && (ch.applied_ma - ch.commanded_ma).abs() > 1
            {
                return Some(format!(
                    "channel {k}: the board drives {} mA for a command of {} mA within the \
                     limit (its configuration differs from coilbus's)",
                    ch.applied_ma, ch.commanded_ma
                ));
            }
            if ch.measured_ma != NOT_MEASURED {
                let applied = f64::from(ch.applied_ma) * 1e-3;
                let measured = f64::from(ch.measured_ma) * 1e-3;
                let allowed = self
                    .tolerance
                    .current_a
                    .max(self.tolerance.fraction * applied.abs());
                if (measured - applied).abs() > allowed {
                    return Some(format!(
                        "channel {k}: measured {measured:.3} A, the board drives {applied:.3} A \
                         (tolerance {allowed:.3} A): a faulty driver or coil"
                    ));
                }
            }
        }
        if status.flags & STATUS_CLAMPED != 0
            && channels
                .iter()
                .enumerate()
                .all(|(k, c)| c.commanded_ma.abs() <= self.limits_ma[k])
        {
            return Some(
                "the board clamps currents coilbus holds within the limits (its configuration \
                 differs from coilbus's)"
                    .into(),
            );
        }
        None
    }

    fn strike(&mut self, problem: String) -> Option<&Fault> {
        self.strikes += 1;
        if self.strikes >= self.tolerance.persistence.max(1) {
            let detail = format!("{problem} ({} consecutive Status frames)", self.strikes);
            return self.latch(BoardFault::TelemetryDisagrees, detail);
        }
        None
    }

    fn latch(&mut self, kind: BoardFault, detail: String) -> Option<&Fault> {
        if self.fault.is_some() {
            return None;
        }
        self.fault = Some(Fault { kind, detail });
        self.fault.as_ref()
    }

    /// Whether the board was seen armed since coilbus started.
    pub fn armed_seen(&self) -> bool {
        self.armed_seen
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::ChannelStatus;

    fn status(state: BoardState, flags: u8, channels: &[(i32, i32, i32)]) -> BoardStatus {
        let channels: Vec<ChannelStatus> = channels
            .iter()
            .map(|&(commanded_ma, applied_ma, measured_ma)| ChannelStatus {
                commanded_ma,
                applied_ma,
                measured_ma,
                thermal_permille: 0,
            })
            .collect();
        BoardStatus::new(state as u8, flags, &channels, 0, 0).unwrap()
    }

    /// A monitor of a 2-coil board that has reported itself armed.
    fn monitor() -> BoardMonitor {
        let mut m = BoardMonitor::new(2, &[6.0, 6.0], TelemetryTolerance::default());
        let armed = status(
            BoardState::Armed,
            0,
            &[(0, 0, NOT_MEASURED), (0, 0, NOT_MEASURED)],
        );
        assert!(m.on_status(&armed).is_none());
        m.acked(AckStatus::Applied as u8);
        m
    }

    #[test]
    fn an_agreeing_board_stays_healthy() {
        let mut m = monitor();
        m.commanded(&[1000, -2000]);
        for _ in 0..10 {
            let st = status(
                BoardState::Armed,
                0,
                &[(1000, 1000, 1020), (-2000, -2000, -1950)],
            );
            assert!(m.on_status(&st).is_none());
        }
        assert!(m.fault().is_none());
        assert!(m.armed_seen());
    }

    #[test]
    fn a_status_from_the_previous_command_is_not_a_disagreement() {
        let mut m = monitor();
        m.commanded(&[1000, 0]);
        m.commanded(&[1500, 0]);
        let st = status(
            BoardState::Armed,
            0,
            &[(1000, 1000, NOT_MEASURED), (0, 0, NOT_MEASURED)],
        );
        assert!(m.on_status(&st).is_none());
    }

    #[test]
    fn a_faulty_channel_latches_after_the_persistence() {
        let mut m = monitor();
        m.commanded(&[3000, 0]);
        let st = status(BoardState::Armed, 0, &[(3000, 3000, 1500), (0, 0, 0)]);
        assert!(m.on_status(&st).is_none());
        assert!(m.on_status(&st).is_none());
        let fault = m
            .on_status(&st)
            .cloned()
            .expect("third disagreeing Status latches");
        assert_eq!(fault.kind, BoardFault::TelemetryDisagrees);
        assert!(fault.detail.contains("channel 0"), "{}", fault.detail);
        // Latched: an agreeing Status does not clear it.
        let ok = status(BoardState::Armed, 0, &[(3000, 3000, 3000), (0, 0, 0)]);
        assert!(m.on_status(&ok).is_none());
        assert!(m.fault().is_some());
    }

    #[test]
    fn one_late_status_is_forgiven() {
        let mut m = monitor();
        m.commanded(&[3000, 0]);
        let lagging = status(BoardState::Armed, 0, &[(3000, 3000, 1500), (0, 0, 0)]);
        let settled = status(BoardState::Armed, 0, &[(3000, 3000, 2950), (0, 0, 0)]);
        for _ in 0..5 {
            assert!(m.on_status(&lagging).is_none());
            assert!(m.on_status(&settled).is_none());
        }
        assert!(m.fault().is_none());
    }

    #[test]
    fn commands_refused_before_arming_are_not_compared() {
        let mut m = BoardMonitor::new(2, &[6.0, 6.0], TelemetryTolerance::default());
        m.commanded(&[2000, 0]);
        let disarmed = status(BoardState::Disarmed, 0, &[(0, 0, 0), (0, 0, 0)]);
        assert!(m.on_status(&disarmed).is_none());
        m.commanded(&[2000, 0]);
        let armed = status(BoardState::Armed, 0, &[(0, 0, 0), (0, 0, 0)]);
        for _ in 0..5 {
            assert!(m.on_status(&armed).is_none());
        }
        assert!(m.fault().is_none());
    }

    #[test]
    fn status_queued_before_the_first_ack_is_not_compared() {
        // A restarted coilbus reads Status frames its stopped predecessor left in the port.
        let mut m = BoardMonitor::new(2, &[6.0, 6.0], TelemetryTolerance::default());
        m.commanded(&[0, 0]);
        let stale = status(
            BoardState::Armed,
            0,
            &[(-26, -26, NOT_MEASURED), (0, 0, NOT_MEASURED)],
        );
        for _ in 0..5 {
            assert!(m.on_status(&stale).is_none());
        }
        m.acked(AckStatus::Applied as u8);
        m.commanded(&[0, 0]);
        let fresh = status(
            BoardState::Armed,
            0,
            &[(0, 0, NOT_MEASURED), (0, 0, NOT_MEASURED)],
        );
        assert!(m.on_status(&fresh).is_none());
        assert!(m.fault().is_none());
    }

    #[test]
    fn estop_and_thermal_trip_latch_at_once() {
        let mut m = monitor();
        let st = status(
            BoardState::EStop,
            crate::protocol::STATUS_ESTOP_INPUT,
            &[(0, 0, NOT_MEASURED), (0, 0, NOT_MEASURED)],
        );
        let fault = m.on_status(&st).cloned().unwrap();
        assert_eq!(fault.kind, BoardFault::EStop);
        assert!(fault.detail.contains("input"));
        let mut m = monitor();
        let st = status(BoardState::ThermalTrip, 0, &[(0, 0, 0), (0, 0, 0)]);
        assert_eq!(m.on_status(&st).unwrap().kind, BoardFault::ThermalTrip);
    }

    #[test]
    fn a_board_clamping_within_the_limits_disagrees() {
        let mut m = monitor();
        m.commanded(&[5000, 0]);
        let st = status(
            BoardState::Armed,
            STATUS_CLAMPED,
            &[(5000, 4000, NOT_MEASURED), (0, 0, NOT_MEASURED)],
        );
        for _ in 0..2 {
            assert!(m.on_status(&st).is_none());
        }
        let fault = m.on_status(&st).unwrap();
        assert!(
            fault.detail.contains("configuration differs"),
            "{}",
            fault.detail
        );
    }

    #[test]
    fn a_rebooted_board_is_not_a_fault() {
        let mut m = monitor();
        m.commanded(&[1000, 0]);
        let st = status(
            BoardState::Unconfigured,
            0,
            &[(0, 0, NOT_MEASURED), (0, 0, NOT_MEASURED)],
        );
        for _ in 0..5 {
            assert!(m.on_status(&st).is_none());
        }
        assert!(m.fault().is_none());
    }

    #[test]
    fn a_refused_configuration_latches() {
        let mut m = BoardMonitor::new(2, &[6.0, 6.0], TelemetryTolerance::default());
        let st = status(
            BoardState::Unconfigured,
            STATUS_CONFIG_REFUSED,
            &[(0, 0, NOT_MEASURED), (0, 0, NOT_MEASURED)],
        );
        assert_eq!(m.on_status(&st).unwrap().kind, BoardFault::ConfigRefused);
    }

    #[test]
    fn another_protocol_version_is_refused_by_name() {
        let mut m = monitor();
        let fault = m.foreign_version(1).cloned().unwrap();
        assert_eq!(fault.kind, BoardFault::ProtocolVersion);
        assert!(fault.detail.contains("version 1"));
    }
}
