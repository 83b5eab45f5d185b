//! Currents for a force and the orientation field: the allocation of paper Eq. 2 over the rig's
//! coils, with their ratings, saturation, the learned gains and the slew bound.

use fieldmaps::allocation::{
    actuation_matrix_from, allocate_constrained_rated, allocate_constrained_slewed,
    allocate_limited_rated, clamp_to_ratings, AllocationError, ConstrainedSettings,
};
use fieldmaps::coils::CoilField;
use fieldmaps::physics;
use nalgebra::{DMatrix, DVector, Vector2, Vector3};
use shm_schemas::{Pose, MAX_COILS};

use super::feed::Fed;
use super::{ControlLoop, StepTiming, SLEW_SHORTFALL_FRACTION};

impl ControlLoop {
    /// Currents for a desired force and the orientation field at the robot's pose, and the force
    /// those currents make there (less than asked when the coils saturate). With `slew` (the
    /// previous currents and the largest step allowed now), the currents move toward the
    /// allocation's by one factor so that no coil steps further.
    pub(super) fn allocate(
        &self,
        position: &Vector2<f64>,
        heading: f64,
        force: &Vector2<f64>,
        slew: Option<(&[f64; MAX_COILS], f64)>,
    ) -> ([f64; MAX_COILS], Vector2<f64>) {
        self.allocate_with_field(position, heading, self.field_heading_rad, force, slew)
    }

    /// The field model's effective currents of real coil currents (allocation order): a
    /// saturating coil makes less field than its current.
    pub(super) fn effective_currents(&self, currents: &DVector<f64>) -> DVector<f64> {
        DVector::from_iterator(
            currents.len(),
            currents
                .iter()
                .zip(&self.saturation)
                .map(|(&i, curve)| curve.as_ref().map_or(i, |c| c.effective(i))),
        )
    }

    /// [`Self::allocate`] with the orientation field at `field_heading` (rad), the magnet at
    /// `heading`.
    pub(super) fn allocate_with_field(
        &self,
        position: &Vector2<f64>,
        heading: f64,
        field_heading: f64,
        force: &Vector2<f64>,
        slew: Option<(&[f64; MAX_COILS], f64)>,
    ) -> ([f64; MAX_COILS], Vector2<f64>) {
        let p3 = Vector3::new(position.x, position.y, 0.0);
        let a = self.actuation_matrix(&p3, heading);
        let omega0 = self.config.omega0_n_per_t;
        // The coils make the desired field less the calibrated background, which is there anyway.
        let background = self.rig.coil_field.background_field(&p3);
        let b = self.field_at(field_heading) - background.xy();
        let c = DVector::from_vec(vec![force.x, force.y, omega0 * b.x, omega0 * b.y]);
        let previous = slew.map(|(previous, max_step_a)| {
            let previous = DVector::from_iterator(
                self.coil_ids.len(),
                self.coil_ids
                    .iter()
                    .map(|&id| previous.get(id).copied().unwrap_or(0.0)),
            );
            (previous, max_step_a)
        });
        let mut currents = [0.0; MAX_COILS];
        let mut achieved = Vector2::zeros();
        if let Ok(effective) = self.solve(&a, &c, previous.as_ref()) {
            let allocated = self.real_currents(&effective, previous.as_ref());
            let wrench = &a * &self.effective_currents(&allocated);
            achieved = Vector2::new(wrench[0], wrench[1]);
            for (k, &id) in self.coil_ids.iter().enumerate() {
                if let Some(current) = currents.get_mut(id) {
                    *current = allocated[k];
                }
            }
        }
        (currents, achieved)
    }

    /// Paper Eq. 2's actuation matrix at `p3` for the magnet at `heading`, each coil's column
    /// scaled by its learned gain (a coil's force and field both scale with it).
    fn actuation_matrix(&self, p3: &Vector3<f64>, heading: f64) -> DMatrix<f64> {
        let moment = physics::in_plane_moment(self.robot.magnet_moment_am2, heading);
        let omega0 = self.config.omega0_n_per_t;
        let mut a =
            actuation_matrix_from(&self.rig.coil_field, p3, &moment, &self.coil_ids, omega0);
        if let Some(estimator) = &self.gain_estimator {
            for (k, gain) in estimator.gains().into_iter().enumerate() {
                a.column_mut(k).scale_mut(gain);
            }
        }
        a
    }

    /// The effective currents that make the wrench `c` with `a`: within reach of `previous`
    /// under a slew bound, else the constrained QP or the paper's pseudo-inverse and scaling.
    fn solve(
        &self,
        a: &DMatrix<f64>,
        c: &DVector<f64>,
        previous: Option<&(DVector<f64>, f64)>,
    ) -> Result<DVector<f64>, AllocationError> {
        let w = self.config.field_row_weight;
        let settings = ConstrainedSettings {
            row_weights: Some(DVector::from_vec(vec![1.0, 1.0, w, w])),
            ..ConstrainedSettings::default()
        };
        if let Some((previous, max_step_a)) = previous {
            // Under a slew limit the allocation itself stays within reach of the previous
            // currents, so the coils that can follow make up for those that cannot.
            let previous_effective = self.effective_currents(previous);
            allocate_constrained_slewed(
                a,
                c,
                &self.effective_ratings,
                &settings,
                &previous_effective,
                *max_step_a,
            )
            .map(|a| a.currents_a)
        } else if self.config.constrained_allocation {
            allocate_constrained_rated(a, c, &self.effective_ratings, &settings)
                .map(|a| a.currents_a)
        } else {
            allocate_limited_rated(a, c, &self.effective_ratings).map(|a| a.currents_a)
        }
    }

    /// The real coil currents of the allocation's effective ones (a saturating coil needs
    /// more), kept within the slew step and the ratings whatever the curve did.
    fn real_currents(
        &self,
        effective: &DVector<f64>,
        previous: Option<&(DVector<f64>, f64)>,
    ) -> DVector<f64> {
        let mut allocated = DVector::from_iterator(
            effective.len(),
            effective
                .iter()
                .zip(&self.saturation)
                .map(|(&i, curve)| curve.as_ref().map_or(i, |c| c.actual_for(i))),
        );
        // Guard: a saturating coil's real current may step further than its effective one.
        if let Some((previous, max_step_a)) = previous {
            let step = &allocated - previous;
            let largest = step.amax();
            if largest > *max_step_a {
                allocated = previous + step * (max_step_a / largest);
            }
        }
        // Guard: the real currents within the real ratings whatever the curve did.
        clamp_to_ratings(&mut allocated, &self.ratings);
        allocated
    }

    /// The wider step `[control.slew_yield]` allows when the slew-bounded allocation made
    /// `achieved` of `force`, short by more than its fraction; none while the bound holds.
    pub(super) fn yielded_step<'a>(
        &self,
        slew: Option<(&'a [f64; MAX_COILS], f64)>,
        force: &Vector2<f64>,
        achieved: &Vector2<f64>,
    ) -> Option<(&'a [f64; MAX_COILS], f64)> {
        let (previous, step) = slew?;
        let yielding = self.config.slew_yield.as_ref()?;
        let rate = self.config.max_current_slew_a_per_s?;
        ((force - achieved).norm() > yielding.shortfall_fraction * force.norm())
            .then(|| (previous, step * yielding.max_current_slew_a_per_s / rate))
    }

    /// The currents for `force` at the pose, the field turned as far as it may and needs to:
    /// under a slew bound (yielding where it withholds much of the force), and with the force
    /// the coils could make at their ratings for the controller.
    pub(super) fn allocate_force(
        &mut self,
        pose: &Pose,
        fed: &Fed,
        force: &Vector2<f64>,
        timing: &StepTiming,
        flow_mps: Vector2<f64>,
    ) -> Allocated {
        // The field is allocated where the robot will be when the command acts.
        let position_m = fed.position_m;
        let slew = self.slew_from(timing.actuation_ns);
        let slew = slew.as_ref().map(|(previous, step)| (previous, *step));
        let turned = self.turn_field_for(pose, fed, force, slew, timing, flow_mps);
        let (mut currents, mut achieved) = (turned.currents, turned.achieved);
        // The magnet's heading under the field chosen now (the offset between them kept).
        let magnet_heading = self.field_heading_rad + turned.magnet_offset_rad;
        if let Some(wider) = self.yielded_step(slew, force, &achieved) {
            // At the heading the bound chose: a turn is no reason to step faster.
            (currents, achieved) = self.allocate_with_field(
                &position_m,
                magnet_heading,
                self.field_heading_rad,
                force,
                Some(wider),
            );
        }
        // What the coils could make at their ratings, the slew bound aside: a controller that
        // keeps the coil limits out of its disturbance estimate must still see the bound's
        // shortfall, which passes within a few frames, or the estimate never makes up the
        // mean force the bound withholds and the robot sits off its path.
        let at_ratings = match slew {
            Some(_) if (force - achieved).norm() > force.norm() * SLEW_SHORTFALL_FRACTION => {
                let field_heading = self.field_heading_rad;
                self.allocate_with_field(&position_m, magnet_heading, field_heading, force, None)
                    .1
            }
            _ => achieved,
        };
        Allocated {
            currents,
            achieved,
            at_ratings,
        }
    }

    /// The previous tracking currents and the largest step the slew bound allows a command
    /// acting at `actuation_ns` (none without a bound).
    fn slew_from(&self, actuation_ns: u64) -> Option<([f64; MAX_COILS], f64)> {
        match (self.config.max_current_slew_a_per_s, &self.last_tracked) {
            (Some(rate), Some((t_prev, previous))) if actuation_ns > *t_prev => {
                Some((*previous, rate * (actuation_ns - t_prev) as f64 * 1e-9))
            }
            _ => None,
        }
    }
}

/// The currents of one tracking command and the forces they make.
pub(super) struct Allocated {
    pub currents: [f64; MAX_COILS],
    /// The force the currents make at the pose (less than asked when the coils cannot).
    pub achieved: Vector2<f64>,
    /// The force the coils could make at their ratings, the slew bound aside.
    pub at_ratings: Vector2<f64>,
}
