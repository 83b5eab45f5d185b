//! coilbus's own safety rules: current limits and staleness. They hold whatever the controller
//! asks for, so they are deliberately independent of the control code.

use fieldmaps::rigfile::Rig;
use shm_schemas::{CoilCommand, FrameStamp, MAX_COILS};

/// Hard limits of the drivers and supplies, per coil (the rig file's `[[coils]]` and
/// `[electromagnet] max_total_power_w`, optionally lowered by the scenario).
#[derive(Debug, Clone, PartialEq)]
pub struct CurrentLimits {
    /// Per coil, either sign (entries past the rig's coils are unused).
    pub max_current_a: [f64; MAX_COILS],
    /// Per coil, for the total power.
    pub coil_resistance_ohm: [f64; MAX_COILS],
    /// Per coil: current it carries indefinitely, A, and its heat budget above that, A²·s
    /// (what the board's I²t protection is configured with).
    pub continuous_current_a: [f64; MAX_COILS],
    pub thermal_budget_a2s: [f64; MAX_COILS],
    /// The drivers' supply voltage, V.
    pub supply_v: f64,
    /// Sum of I²R over all coils.
    pub max_total_power_w: f64,
}

impl CurrentLimits {
    /// The same rating for every coil.
    pub fn uniform(max_current_a: f64, coil_resistance_ohm: f64, max_total_power_w: f64) -> Self {
        Self {
            max_current_a: [max_current_a; MAX_COILS],
            coil_resistance_ohm: [coil_resistance_ohm; MAX_COILS],
            continuous_current_a: [max_current_a; MAX_COILS],
            thermal_budget_a2s: [max_current_a * max_current_a * 10.0; MAX_COILS],
            supply_v: max_current_a * coil_resistance_ohm,
            max_total_power_w,
        }
    }

    /// The rig's per-coil ratings and total power.
    pub fn from_rig(rig: &Rig) -> Self {
        let mut limits = Self::uniform(0.0, 0.0, rig.max_total_power_w);
        limits.supply_v = rig.driver_supply_v;
        for (i, coil) in rig.coils.iter().take(MAX_COILS).enumerate() {
            limits.max_current_a[i] = coil.max_current_a;
            limits.coil_resistance_ohm[i] = coil.resistance_ohm;
            limits.continuous_current_a[i] = coil.continuous_current_a;
            limits.thermal_budget_a2s[i] = coil.thermal_budget_a2s;
        }
        limits
    }

    /// These limits, lowered (never raised) to `max_current_a` per coil and
    /// `max_total_power_w` in all where given.
    pub fn capped(mut self, max_current_a: Option<f64>, max_total_power_w: Option<f64>) -> Self {
        if let Some(cap) = max_current_a {
            self.max_current_a.iter_mut().for_each(|m| *m = m.min(cap));
        }
        if let Some(cap) = max_total_power_w {
            self.max_total_power_w = self.max_total_power_w.min(cap);
        }
        self
    }
}

/// Non-finite entries become zero, each coil is clipped to its limit, then all are scaled
/// together to respect the total power. Returns the currents (the first `requested.len()`
/// entries, at most `MAX_COILS`; the rest zero) and whether anything changed.
pub fn clamp_currents(requested: &[f64], limits: &CurrentLimits) -> ([f64; MAX_COILS], bool) {
    let mut changed = false;
    let mut out = [0.0; MAX_COILS];
    for ((o, r), max) in out.iter_mut().zip(requested).zip(&limits.max_current_a) {
        let max = max.abs();
        *o = if r.is_finite() {
            r.clamp(-max, max)
        } else {
            0.0
        };
        changed |= *o != *r;
    }
    let power: f64 = out
        .iter()
        .zip(&limits.coil_resistance_ohm)
        .map(|(c, r)| c * c * r)
        .sum();
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
