//! The orientation field's heading: where it points, when it turns toward more force or to pull
//! the magnet along its axis, and how far the capsule is from following it.

use fieldmaps::physics::wrap_angle;
use nalgebra::Vector2;
use shm_schemas::{Pose, MAX_COILS};

use super::feed::Fed;
use super::{
    ControlLoop, StepTiming, FIELD_HEADING_STEP_DEG, FIELD_HISTORY_LEN, FORCE_MADE_FRACTION,
    PULL_FORCE_AVERAGE_S, TURN_HYSTERESIS_FRACTION,
};

impl ControlLoop {
    /// The orientation field at `heading` (rad).
    pub(super) fn field_at(&self, heading: f64) -> Vector2<f64> {
        Vector2::new(heading.cos(), heading.sin()) * self.field_magnitude_t
    }

    /// The orientation field commanded now.
    pub(super) fn desired_field(&self) -> Vector2<f64> {
        self.field_at(self.field_heading_rad)
    }

    /// [`Self::allocate`], turning the orientation field by at most `max_turn_rad` when
    /// `field_heading_turn_deg` allows and the coils cannot make `force` at the present
    /// heading (see there). The magnet points `magnet_offset` (rad) from the field, and turns
    /// with it; `measured_heading` is the frame's.
    pub(super) fn allocate_turning(
        &mut self,
        position: &Vector2<f64>,
        measured_heading: f64,
        magnet_offset: f64,
        force: &Vector2<f64>,
        slew: Option<(&[f64; MAX_COILS], f64)>,
        max_turn_rad: f64,
    ) -> ([f64; MAX_COILS], Vector2<f64>) {
        let present = self.field_heading_rad;
        if self.config.field_heading_turn_deg.is_none() {
            // The field never turned: the magnet is where the frame shows it.
            return self.allocate(position, measured_heading, force, slew);
        }
        let pulling = self.pulling_heading(magnet_offset);
        let home = pulling.unwrap_or(self.config.field_heading_deg.to_radians());
        let miss = |achieved: &Vector2<f64>| (force - achieved).norm();
        let made = force.norm() * FORCE_MADE_FRACTION + 1e-12;
        let at = |this: &Self, field_heading: f64| {
            let magnet = field_heading + magnet_offset;
            this.allocate_with_field(position, magnet, field_heading, force, slew)
        };
        let stay = at(self, present);
        // A pulling heading (off the candidates' grid) is reached within half a step.
        let home_tolerance = if pulling.is_some() {
            FIELD_HEADING_STEP_DEG.to_radians() / 2.0
        } else {
            1e-9
        };
        let at_home = wrap_angle(present - home).abs() < home_tolerance;
        if at_home && miss(&stay.1) <= made {
            return stay;
        }
        let step = FIELD_HEADING_STEP_DEG.to_radians();
        let steps = (max_turn_rad / step + 1e-9).floor().max(0.0) as i32;
        let toward_home = |h: f64| wrap_angle(h - home).abs();
        let mut best = (present, stay, miss(&stay.1));
        let mut best_home = (miss(&stay.1) <= made).then_some((present, stay));
        for k in (-steps..=steps).filter(|k| *k != 0) {
            let heading = wrap_angle(present + f64::from(k) * step);
            let candidate = at(self, heading);
            let candidate_miss = miss(&candidate.1);
            if candidate_miss <= made {
                // Within reach: the one nearest the configured heading.
                if best_home.is_none_or(|(h, _)| toward_home(heading) < toward_home(h)) {
                    best_home = Some((heading, candidate));
                }
            } else if candidate_miss < best.2 * (1.0 - TURN_HYSTERESIS_FRACTION) {
                best = (heading, candidate, candidate_miss);
            }
        }
        let (heading, chosen) = match best_home {
            Some(found) => found,
            None => (best.0, best.1),
        };
        self.field_heading_rad = heading;
        chosen
    }

    /// The field heading that pulls the magnet along its axis toward the recent asked force
    /// (rad; of the two, the one nearer the present field), with `field_follows_force` where
    /// the fluid moves.
    pub(super) fn pulling_heading(&self, magnet_offset: f64) -> Option<f64> {
        let force = self.pull_force_n;
        let pulls = self.config.field_follows_force
            && self.config.max_current_slew_a_per_s.is_none()
            && self.fluid_moves;
        if !pulls || force.norm() == 0.0 {
            return None;
        }
        let along = force.y.atan2(force.x) - magnet_offset;
        let present = self.field_heading_rad;
        Some(
            if wrap_angle(along - present).abs() <= std::f64::consts::FRAC_PI_2 {
                wrap_angle(along)
            } else {
                wrap_angle(along + std::f64::consts::PI)
            },
        )
    }

    /// Remembers that the orientation field points at `heading` (none: coils off) from
    /// `actuation_ns` on.
    pub(super) fn record_field(&mut self, actuation_ns: u64, heading: Option<f64>) {
        if self.field_history.len() == FIELD_HISTORY_LEN {
            self.field_history.pop_front();
        }
        self.field_history.push_back((actuation_ns, heading));
    }

    /// The magnet's heading minus the field's (rad), from a pose captured at `capture_ns` with
    /// `measured_heading`. A frame taken while the capsule was still turning after the field
    /// (or before the field it shows turned again) would put the magnet where it no longer is,
    /// so such a frame keeps the last offset measured on a settled one. Before any turn is on
    /// record the measured heading stands as it is, and so it does always for a field that
    /// never turns (`field_heading_turn_deg` unset).
    pub(super) fn magnet_offset(&mut self, measured_heading: f64, capture_ns: u64) -> f64 {
        let present = self.field_heading_rad;
        if self.config.field_heading_turn_deg.is_none() {
            return wrap_angle(measured_heading - present);
        }
        let window_start = capture_ns.saturating_sub(self.rotation_settle_ns);
        let mut settled = true;
        for (acted_ns, heading) in self.field_history.iter().rev() {
            let same = heading.is_some_and(|h| wrap_angle(h - present).abs() < 1e-9);
            if !same {
                settled = false;
                break;
            }
            if *acted_ns <= window_start {
                break;
            }
        }
        if settled {
            self.magnet_offset_rad = wrap_angle(measured_heading - present);
        }
        self.magnet_offset_rad
    }

    /// How far the field may turn for a command acting at `actuation_ns` (rad): the budget
    /// grown at the capsule's turning rate since the last command, up to
    /// `field_heading_turn_deg`.
    pub(super) fn field_turn_budget(&mut self, actuation_ns: u64) -> f64 {
        let cap = self
            .config
            .field_heading_turn_deg
            .map_or(0.0, |deg| deg.max(0.0).to_radians());
        let since_s = self
            .field_history
            .back()
            .map_or(f64::INFINITY, |(acted_ns, _)| {
                actuation_ns.saturating_sub(*acted_ns) as f64 * 1e-9
            });
        let grown = self.field_turn_budget_rad + self.max_field_turn_rate_rad_per_s * since_s;
        self.field_turn_budget_rad = grown.min(cap);
        self.field_turn_budget_rad
    }

    /// [`Self::allocate_turning`] for this step: the magnet's offset from the field measured
    /// on the pose, the turn budget grown since the last command and spent on the turn, and
    /// the force a pulling field follows averaged.
    pub(super) fn turn_field_for(
        &mut self,
        pose: &Pose,
        fed: &Fed,
        force: &Vector2<f64>,
        slew: Option<(&[f64; MAX_COILS], f64)>,
        timing: &StepTiming,
        flow_mps: Vector2<f64>,
    ) -> Turned {
        let magnet_offset_rad = self.magnet_offset(pose.heading_rad, timing.capture_ns);
        let max_turn_rad = self.field_turn_budget(timing.actuation_ns);
        self.pull_force_n +=
            (force - self.pull_force_n) * (1.0 - (-fed.dt_s / PULL_FORCE_AVERAGE_S).exp());
        self.fluid_moves = flow_mps.norm() > 0.0;
        let field_heading_before = self.field_heading_rad;
        let (currents, achieved) = self.allocate_turning(
            &fed.position_m,
            pose.heading_rad,
            magnet_offset_rad,
            force,
            slew,
            max_turn_rad,
        );
        self.field_turn_budget_rad = (self.field_turn_budget_rad
            - wrap_angle(self.field_heading_rad - field_heading_before).abs())
        .max(0.0);
        Turned {
            currents,
            achieved,
            magnet_offset_rad,
        }
    }
}

/// The allocation at the field heading chosen for a step.
pub(super) struct Turned {
    pub currents: [f64; MAX_COILS],
    pub achieved: Vector2<f64>,
    /// The magnet's heading minus the field's (rad).
    pub magnet_offset_rad: f64,
}
