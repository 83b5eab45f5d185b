//! coilbus's own safety rules: current limits and staleness. They hold whatever the controller
//! asks for, so they are deliberately independent of the control code.

use serde::{Deserialize, Serialize};
use shm_schemas::{CoilCommand, FrameStamp, MAX_COILS};

/// Hard limits of the drivers and supplies.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CurrentLimits {
    /// Per coil, either sign.
    pub max_current_a: f64,
    /// Sum of I²R over all coils.
    pub max_total_power_w: f64,
    pub coil_resistance_ohm: f64,
}

impl Default for CurrentLimits {
    fn default() -> Self {
        let rig = fieldmaps::rig::CoilLimits::default();
        Self {
            max_current_a: rig.max_current_a,
            max_total_power_w: rig.max_total_power_w,
            coil_resistance_ohm: rig.coil_resistance_ohm,
        }
    }
}

/// Non-finite entries become zero, each coil is clipped to its limit, then all are scaled
/// together to respect the total power. Returns the currents (the first `requested.len()`
/// entries, at most `MAX_COILS`; the rest zero) and whether anything changed.
pub fn clamp_currents(requested: &[f64], limits: &CurrentLimits) -> ([f64; MAX_COILS], bool) {
    let mut changed = false;
    let mut out = [0.0; MAX_COILS];
    let max = limits.max_current_a.abs();
    for (o, r) in out.iter_mut().zip(requested) {
        *o = if r.is_finite() {
            r.clamp(-max, max)
        } else {
            0.0
        };
        changed |= *o != *r;
    }
    let power: f64 = out.iter().map(|c| c * c * limits.coil_resistance_ohm).sum();
    if power > limits.max_total_power_w && power > 0.0 {
        let scale = (limits.max_total_power_w.max(0.0) / power).sqrt();
        out.iter_mut().for_each(|c| *c *= scale);
        changed = true;
    }
    (out, changed)
}

/// Accepts a command only if it is newer than everything applied so far: a higher frame
/// (within the frame source's incarnation), and never from a control incarnation older than
/// the newest one seen, so nothing from before a restart is applied after it.
#[derive(Debug, Default)]
pub struct StaleFilter {
    newest_control_incarnation: u64,
    last_frame: Option<FrameStamp>,
}

impl StaleFilter {
    /// True if `cmd` is newer than everything applied so far.
    pub fn is_fresh(&self, cmd: &CoilCommand) -> bool {
        if cmd.control_incarnation < self.newest_control_incarnation {
            return false;
        }
        self.last_frame
            .is_none_or(|last| cmd.stamp.is_newer_than(&last))
    }

    /// Records `cmd` as applied.
    pub fn commit(&mut self, cmd: &CoilCommand) {
        self.newest_control_incarnation =
            self.newest_control_incarnation.max(cmd.control_incarnation);
        self.last_frame = Some(cmd.stamp);
    }
}
