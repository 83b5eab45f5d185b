//! Teaching the allocation the coil gains from measured headings
//! (`[control.gain_estimation]`): which currents acted when a frame was captured.

use fieldmaps::physics::wrap_angle;
use nalgebra::Vector2;
use shm_schemas::{Pose, MAX_COILS};

use super::{ControlLoop, ISSUED_HISTORY_LEN};
use crate::coil_gains::{CoilGainEstimator, GainUpdate};

impl ControlLoop {
    /// Remembers that `currents` act from `actuation_ns` on.
    pub(super) fn record_issued(&mut self, actuation_ns: u64, currents: [f64; MAX_COILS]) {
        if self.gain_estimator.is_none() {
            return;
        }
        if self.issued.len() == ISSUED_HISTORY_LEN {
            self.issued.pop_front();
        }
        self.issued.push_back((actuation_ns, currents));
    }

    /// Feeds the heading of a usable pose to the coil-gain estimate, with the currents that were
    /// in effect (and had settled) at its capture time; nothing when no command is known to
    /// have acted then.
    pub(super) fn learn_gains(&mut self, pose: &Pose, capture_ns: u64) -> Option<GainUpdate> {
        let estimator = self.gain_estimator.as_ref()?;
        // The field model speaks effective currents (a saturating coil makes less per ampere).
        let effective = |currents: &[f64; MAX_COILS]| -> Vec<f64> {
            self.coil_ids
                .iter()
                .zip(&self.saturation)
                .map(|(&id, curve)| {
                    let i = currents.get(id).copied().unwrap_or(0.0);
                    curve.as_ref().map_or(i, |c| c.effective(i))
                })
                .collect()
        };
        let position = Vector2::new(pose.position_m[0], pose.position_m[1]);
        // The commands that acted over the window before the capture, newest first, down to
        // the one in effect when the window opened: the field must have held its direction
        // through all of them, or the capsule is still turning. A command that reaches the
        // coils at the capture instant has not acted on what the frame shows (in lockstep a
        // delayed frame's capture time is a later command's actuation time).
        let window_start = capture_ns.saturating_sub(self.alignment_window_ns);
        let mut in_window = self
            .issued
            .iter()
            .rev()
            .skip_while(|(acted_ns, _)| *acted_ns >= capture_ns);
        let (acted_ns, in_effect) = in_window.next()?;
        let mut opened = *acted_ns <= window_start;
        let in_effect = effective(in_effect);
        if in_effect.iter().all(|i| *i == 0.0) {
            return None;
        }
        let heading =
            estimator.believed_field_heading(&self.rig.coil_field, &position, &in_effect)?;
        let tolerance = estimator.config().heading_noise_deg.to_radians();
        for (acted_ns, earlier) in in_window {
            if opened {
                break;
            }
            let earlier = estimator.believed_field_heading(
                &self.rig.coil_field,
                &position,
                &effective(earlier),
            )?;
            if wrap_angle(earlier - heading).abs() > tolerance {
                return None;
            }
            opened = *acted_ns <= window_start;
        }
        if !opened {
            // The history does not reach back over the whole window (just started).
            return None;
        }
        let estimator = self.gain_estimator.as_mut()?;
        Some(estimator.observe(
            &self.rig.coil_field,
            &position,
            pose.heading_rad,
            &in_effect,
            capture_ns,
        ))
    }

    /// The coil gains the allocation uses (allocation order, see [`Self::coil_ids`]), when
    /// estimating them online.
    pub fn coil_gains(&self) -> Option<Vec<f64>> {
        self.gain_estimator.as_ref().map(|e| e.gains())
    }

    /// How far the coil gains may be off (relative 1σ): the online estimate's uncertainty,
    /// RMS over the coils weighted by the last tracking command's currents (a coil that carries
    /// none adds no error, however little is known of it), else the prior the coil data is
    /// trusted to.
    pub(super) fn coil_gain_std(&self) -> f64 {
        let Some(estimator) = &self.gain_estimator else {
            return self.config.gain_estimation.prior_std;
        };
        let std = estimator.gain_std();
        let carried: Vec<f64> = self
            .coil_ids
            .iter()
            .map(|&id| {
                self.last_tracked
                    .map_or(0.0, |(_, currents)| currents.get(id).map_or(0.0, |i| i * i))
            })
            .collect();
        // Before any current flows, every coil counts alike.
        let weights = if carried.iter().all(|w| *w == 0.0) {
            vec![1.0; std.len()]
        } else {
            carried
        };
        let total: f64 = weights.iter().sum();
        let weighted: f64 = std.iter().zip(&weights).map(|(s, w)| s * s * w).sum();
        (weighted / total.max(f64::MIN_POSITIVE)).sqrt()
    }

    /// The estimator itself (counts of used and skipped frames, uncertainties), when on.
    pub fn gain_estimator(&self) -> Option<&CoilGainEstimator> {
        self.gain_estimator.as_ref()
    }
}
