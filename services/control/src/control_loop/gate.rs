//! The first stage: whether a pose may drive the coils, and what the loop does when it may not.

use nalgebra::Vector2;
use shm_schemas::{services, ControlMode, Pose};

use super::{ControlLoop, Decision, StepTiming, POSE_JUMP_SLACK_M};
use crate::controllers::ControlTerms;
use crate::latency::Predictor;

impl ControlLoop {
    /// Why a pose cannot be used at `actuation_ns`, if it cannot.
    pub(super) fn check_pose(
        &mut self,
        pose: &Pose,
        t_ns: u64,
        actuation_ns: u64,
    ) -> Option<&'static str> {
        match self.violations.check(services::POSE, pose.validity()) {
            Ok(true) => {}
            Ok(false) => return Some("pose flagged invalid by vision"),
            Err(_) => return Some("pose validity flag is not 0 or 1"),
        }
        if !pose.is_usable() {
            return Some("pose holds non-finite numbers");
        }
        let age_ms = actuation_ns.saturating_sub(t_ns) as f64 * 1e-6;
        if age_ms > self.config.latency.max_pose_age_ms {
            return Some("pose older than max_pose_age_ms");
        }
        let p = Vector2::new(pose.position_m[0], pose.position_m[1]);
        if !self.rig.phantom.contains(&p) {
            return Some("pose outside the canal");
        }
        if let Some((t_prev, p_prev)) = self.last_good {
            let dt = t_ns.saturating_sub(t_prev) as f64 * 1e-9;
            let reach = self.config.max_speed_mps * dt + POSE_JUMP_SLACK_M;
            if (p - p_prev).norm() > reach {
                return Some("pose jumped farther than the robot can move");
            }
        }
        None
    }

    /// The answer to a pose that cannot be used: hold the orientation field at the last good
    /// position while one is recent enough (`hold_timeout_ms`), else safe (zero currents). The
    /// controller and the predictor start afresh from it.
    pub(super) fn reject(
        &mut self,
        pose: &Pose,
        why: &'static str,
        timing: &StepTiming,
    ) -> Decision {
        let mut command = self.command_for(pose);
        let actuation_ns = timing.actuation_ns;
        let since_good_ms = self
            .last_good
            .map(|(t_prev, _)| timing.capture_ns.saturating_sub(t_prev) as f64 * 1e-6);
        let hold = since_good_ms.is_some_and(|ms| ms <= self.config.hold_timeout_ms);
        let mut held_force = Vector2::zeros();
        if hold {
            let (_, p) = self.last_good.unwrap_or((0, Vector2::zeros()));
            command.mode = ControlMode::Hold as u32;
            let heading = self.field_heading_rad;
            let (currents, achieved) = self.allocate(&p, heading, &Vector2::zeros(), None);
            command.currents_a = currents;
            held_force = achieved;
        } else {
            command.mode = ControlMode::Safe as u32;
        }
        self.last_mode = ControlMode::from_repr(command.mode).unwrap_or(ControlMode::Safe);
        self.last_tracked = Some((actuation_ns, command.currents_a));
        self.record_issued(actuation_ns, command.currents_a);
        let field = hold.then_some(self.field_heading_rad);
        self.record_field(actuation_ns, field);
        self.controller.reset();
        self.predictor.reset();
        self.predictor
            .commanded(actuation_ns, held_force, Vector2::zeros());
        let measured = Vector2::new(pose.position_m[0], pose.position_m[1]);
        Decision {
            command,
            terms: ControlTerms::default(),
            reference_m: timing.reference.position_m,
            finished: timing.reference.finished,
            rejected: Some(why),
            pose_age_s: timing.pose_age_s,
            fed_position_m: measured,
            predicted_position_m: measured,
            gain_update: None,
            unpredicted_motion_share: self.predictor.unpredicted_motion_share(),
            disturbance_delays: self.predictor.active_disturbance_delays(),
            force_cap_n: None,
        }
    }
}
