//! The operator's commands to the running set (`millinav ctl`), handled by control between
//! poses: `goto` replans with the paper's A* planner on the rig's canal mask from the current
//! pose, `waypoints` follows a given path from it, `pause` holds position and `resume`
//! continues the held path where it stopped, `disarm` and `estop` (latched) zero the coils until
//! `arm`, which holds position until `resume` or a new path (arming never makes the robot chase
//! a reference that moved on meanwhile). A refused command changes nothing and says why; every
//! answer carries the state it produced, and goes to `operator_events.csv` and the recording.

use nalgebra::Vector2;
use serde::{Deserialize, Serialize};
use shm_schemas::{
    OperatorReply, OperatorRequest, OperatorState, OperatorVerb, MAX_OPERATOR_WAYPOINTS,
};

use crate::reference::Reference;
use fieldmaps::rigfile::Rig;
use millinav_kit::runlog::RunLogRow;
use millinav_planning::{Mask, PlannerConfig};

/// One answered request (`operator_events.csv`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OperatorEventRow {
    /// Control's clock, s.
    pub time_s: f64,
    pub request_id: u64,
    pub verb: String,
    pub accepted: bool,
    pub state: String,
    pub message: String,
}

impl RunLogRow for OperatorEventRow {
    const FILE_NAME: &'static str = "operator_events.csv";
    const COLUMNS: &'static [&'static str] = &[
        "time_s",
        "request_id",
        "verb",
        "accepted",
        "state",
        "message",
    ];
}

/// The operator's side of control: state, the path a pause holds, the planning domain.
pub struct Operator {
    state: OperatorState,
    /// The path `pause` (or a disarm) set aside, and when.
    held: Option<(Reference, f64)>,
    /// The last answer, so a resent request is answered again and not applied twice.
    last: Option<OperatorReply>,
    position_m: Option<Vector2<f64>>,
    mask: Mask,
    geometry: fieldmaps::phantom::ImageGeometry,
    canal: fieldmaps::mask::CanalMask,
    planner: PlannerConfig,
}

impl Operator {
    /// Starts tracking the scenario's path with coils allowed, or, in a session, disarmed.
    pub fn new(
        rig: &Rig,
        session: bool,
        clearance_m: f64,
    ) -> Result<Self, millinav_planning::PlanError> {
        let planner = PlannerConfig {
            clearance_m,
            ..PlannerConfig::default()
        };
        planner.validate()?;
        let canal = rig.phantom.mask.clone();
        let geometry = *canal.geometry();
        let mask = Mask::new(geometry.width_px, geometry.height_px, canal.to_bytes())?;
        Ok(Self {
            state: if session {
                OperatorState::Disarmed
            } else {
                OperatorState::Tracking
            },
            held: None,
            last: None,
            position_m: None,
            mask,
            geometry,
            canal,
            planner,
        })
    }

    pub fn state(&self) -> OperatorState {
        self.state
    }

    /// Why commands must be zero now, if they must.
    pub fn blocks_currents(&self) -> Option<&'static str> {
        match self.state {
            OperatorState::Disarmed => Some("disarmed by the operator"),
            OperatorState::EStopped => Some("emergency stop (latched until arm)"),
            OperatorState::Tracking | OperatorState::Paused | OperatorState::Stopping => None,
        }
    }

    /// Notes the latest measured position (for planning and holds).
    pub fn observe(&mut self, position_m: Option<Vector2<f64>>) {
        if position_m.is_some() {
            self.position_m = position_m;
        }
    }

    /// Applies `request` to `reference` at control time `now_s`; the answer to send (none for
    /// `stop`, which the supervisor answers).
    pub fn handle(
        &mut self,
        request: &OperatorRequest,
        reference: &mut Reference,
        now_s: f64,
    ) -> Option<OperatorReply> {
        if request.verb == OperatorVerb::Stop as u32 {
            return None;
        }
        if let Some(last) = self.last.filter(|l| l.request_id == request.request_id) {
            return Some(last);
        }
        let outcome = match OperatorVerb::from_repr(request.verb) {
            None => Err(format!("unknown verb {}", request.verb)),
            Some(verb) => self.apply(verb, request, reference, now_s),
        };
        let (accepted, message) = match outcome {
            Ok(message) => (true, message),
            Err(why) => (false, why),
        };
        let mut reply = OperatorReply::new(request.request_id, accepted, self.state, &message);
        if let Some(p) = self.position_m {
            reply.position_m = [p.x, p.y];
        }
        if let Some(end) = reference.waypoints().last() {
            reply.target_m = [end.x, end.y];
        }
        self.last = Some(reply);
        Some(reply)
    }

    fn here(&self) -> Result<Vector2<f64>, String> {
        self.position_m
            .ok_or_else(|| "no pose yet: the robot has not been seen".to_string())
    }

    fn hold_here(&mut self, reference: &mut Reference, now_s: f64) -> Result<(), String> {
        let here = self.here()?;
        if self.held.is_none() {
            self.held = Some((reference.clone(), now_s));
        }
        *reference = Reference::hold(here, reference.speed_mps());
        Ok(())
    }

    fn apply(
        &mut self,
        verb: OperatorVerb,
        request: &OperatorRequest,
        reference: &mut Reference,
        now_s: f64,
    ) -> Result<String, String> {
        let mm = |p: &Vector2<f64>| format!("({:.1}, {:.1}) mm", p.x * 1e3, p.y * 1e3);
        match verb {
            OperatorVerb::Status => Ok(self.state.name().to_string()),
            OperatorVerb::Goto | OperatorVerb::Waypoints => {
                let here = self.here()?;
                let path = if verb == OperatorVerb::Goto {
                    let [x, y] = request.waypoints_m[0];
                    let goal = Vector2::new(x, y);
                    let plan = millinav_planning::plan(
                        &self.mask,
                        &self.geometry,
                        &here,
                        &goal,
                        &self.planner,
                    )
                    .map_err(|e| format!("goal {} refused: {e}", mm(&goal)))?;
                    plan.waypoints_m
                } else {
                    let count = request.waypoint_count as usize;
                    if !(1..=MAX_OPERATOR_WAYPOINTS).contains(&count) {
                        return Err(format!(
                            "{count} waypoints: send 1 to {MAX_OPERATOR_WAYPOINTS}"
                        ));
                    }
                    let mut path = vec![here];
                    for (i, [x, y]) in request.waypoints_m[..count].iter().enumerate() {
                        let p = Vector2::new(*x, *y);
                        if !self.canal.contains(&p) {
                            return Err(format!(
                                "waypoint {} at {} is outside the canal",
                                i + 1,
                                mm(&p)
                            ));
                        }
                        path.push(p);
                    }
                    path
                };
                let points: Vec<[f64; 2]> = path.iter().map(|p| [p.x, p.y]).collect();
                let new = Reference::new(&points, reference.speed_mps(), now_s)
                    .map_err(|e| format!("path refused: {e}"))?;
                let length_mm = new.length_m() * 1e3;
                let end = new.waypoints().last().copied().unwrap_or(here);
                *reference = new;
                self.held = None;
                if self.state == OperatorState::Paused {
                    self.state = OperatorState::Tracking;
                }
                Ok(format!(
                    "following {} waypoints, {length_mm:.1} mm to {}",
                    points.len(),
                    mm(&end)
                ))
            }
            OperatorVerb::Pause => match self.state {
                OperatorState::Tracking => {
                    self.hold_here(reference, now_s)?;
                    self.state = OperatorState::Paused;
                    Ok(format!("holding at {}", mm(&self.here()?)))
                }
                OperatorState::Paused => Ok("already holding".into()),
                other => Err(format!("coils are off ({}): arm first", other.name())),
            },
            OperatorVerb::Resume => match (self.state, self.held.take()) {
                (OperatorState::Paused | OperatorState::Tracking, Some((path, since))) => {
                    *reference = path.delayed(now_s - since);
                    self.state = OperatorState::Tracking;
                    Ok(format!("resumed after {:.1} s", now_s - since))
                }
                (OperatorState::Paused | OperatorState::Tracking, None) => {
                    Err("nothing to resume: no path was paused".into())
                }
                (other, held) => {
                    self.held = held;
                    Err(format!("coils are off ({}): arm first", other.name()))
                }
            },
            OperatorVerb::Arm => match self.state {
                OperatorState::Disarmed | OperatorState::EStopped => {
                    if self.hold_here(reference, now_s).is_ok() {
                        self.state = OperatorState::Paused;
                        Ok(format!(
                            "armed, holding at {}; resume to continue",
                            mm(&self.here()?)
                        ))
                    } else {
                        self.state = OperatorState::Tracking;
                        Ok("armed (no pose yet: following the path)".into())
                    }
                }
                _ => Ok("already armed".into()),
            },
            OperatorVerb::Stop => Err("stop is the supervisor's".into()),
            OperatorVerb::Disarm | OperatorVerb::EStop => {
                if self.state == OperatorState::EStopped && verb == OperatorVerb::Disarm {
                    return Ok("emergency stop stays latched until arm".into());
                }
                // The path is set aside where the robot was (when it has been seen).
                let _ = self.hold_here(reference, now_s);
                self.state = if verb == OperatorVerb::EStop {
                    OperatorState::EStopped
                } else {
                    OperatorState::Disarmed
                };
                Ok("coils at zero".into())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn setup() -> (Operator, Reference) {
        let rig = Rig::load_paper().unwrap();
        let mut op = Operator::new(&rig, false, 5e-3).unwrap();
        op.observe(Some(Vector2::new(-0.018, 0.012)));
        let reference = Reference::new(&[[-0.018, 0.012], [-0.012, 0.006]], 1e-3, 0.0).unwrap();
        (op, reference)
    }

    fn ask(
        op: &mut Operator,
        r: &OperatorRequest,
        reference: &mut Reference,
        t: f64,
    ) -> OperatorReply {
        op.handle(r, reference, t)
            .expect("control answers every verb but stop")
    }

    fn request(id: u64, verb: OperatorVerb, points: &[[f64; 2]]) -> OperatorRequest {
        let mut r = OperatorRequest {
            request_id: id,
            verb: verb as u32,
            waypoint_count: points.len() as u32,
            ..Default::default()
        };
        r.waypoints_m[..points.len()].copy_from_slice(points);
        r
    }

    #[test]
    fn pause_holds_and_resume_continues_where_it_stopped() {
        let (mut op, mut reference) = setup();
        let before = reference.sample(2.0).position_m;
        let reply = ask(
            &mut op,
            &request(1, OperatorVerb::Pause, &[]),
            &mut reference,
            2.0,
        );
        assert_eq!(reply.accepted.raw(), 1, "{}", reply.text());
        assert_eq!(op.state(), OperatorState::Paused);
        let held = reference.sample(10.0).position_m;
        assert!((held - Vector2::new(-0.018, 0.012)).norm() < 1e-8);
        let reply = ask(
            &mut op,
            &request(2, OperatorVerb::Resume, &[]),
            &mut reference,
            7.0,
        );
        assert_eq!(reply.accepted.raw(), 1, "{}", reply.text());
        // Five seconds later on the clock, the path is where it was when paused.
        assert!((reference.sample(7.0).position_m - before).norm() < 1e-9);
    }

    #[test]
    fn estop_latches_until_arm_and_a_resent_request_is_not_applied_twice() {
        let (mut op, mut reference) = setup();
        let stop = request(5, OperatorVerb::EStop, &[]);
        ask(&mut op, &stop, &mut reference, 1.0);
        assert!(op.blocks_currents().is_some());
        let disarm = ask(
            &mut op,
            &request(6, OperatorVerb::Disarm, &[]),
            &mut reference,
            1.5,
        );
        assert!(disarm.text().contains("latched"));
        assert_eq!(op.state(), OperatorState::EStopped);
        let refused = ask(
            &mut op,
            &request(7, OperatorVerb::Resume, &[]),
            &mut reference,
            2.0,
        );
        assert_eq!(refused.accepted.raw(), 0);
        ask(
            &mut op,
            &request(8, OperatorVerb::Arm, &[]),
            &mut reference,
            3.0,
        );
        assert_eq!(op.state(), OperatorState::Paused);
        assert!(op.blocks_currents().is_none());
        // The same id again: the stored answer, no second arm.
        let again = ask(
            &mut op,
            &request(8, OperatorVerb::Arm, &[]),
            &mut reference,
            4.0,
        );
        assert!(again.text().starts_with("armed"), "{}", again.text());
    }

    #[test]
    fn goals_and_waypoints_outside_the_canal_are_refused_and_change_nothing() {
        let (mut op, mut reference) = setup();
        let before = reference.clone().waypoints().to_vec();
        let outside = ask(
            &mut op,
            &request(1, OperatorVerb::Goto, &[[0.040, 0.040]]),
            &mut reference,
            1.0,
        );
        assert_eq!(outside.accepted.raw(), 0);
        assert!(outside.text().contains("refused"), "{}", outside.text());
        let bad = ask(
            &mut op,
            &request(2, OperatorVerb::Waypoints, &[[-0.012, 0.008], [0.04, 0.04]]),
            &mut reference,
            1.0,
        );
        assert!(bad.text().contains("waypoint 2"), "{}", bad.text());
        assert_eq!(reference.waypoints(), &before[..]);
        let unknown = ask(
            &mut op,
            &OperatorRequest {
                request_id: 3,
                verb: 99,
                ..Default::default()
            },
            &mut reference,
            1.0,
        );
        assert!(unknown.text().contains("unknown verb 99"));
        assert_eq!(op.state(), OperatorState::Tracking);
    }

    #[test]
    fn a_session_starts_disarmed_and_stop_is_left_to_the_supervisor() {
        let rig = Rig::load_paper().unwrap();
        let mut op = Operator::new(&rig, true, 5e-3).unwrap();
        assert_eq!(op.state(), OperatorState::Disarmed);
        assert!(op.blocks_currents().is_some());
        let mut reference = Reference::new(&[[-0.018, 0.012], [-0.012, 0.006]], 1e-3, 0.0).unwrap();
        assert!(op
            .handle(&request(1, OperatorVerb::Stop, &[]), &mut reference, 0.0)
            .is_none());
    }

    #[test]
    fn goto_plans_through_the_canal_from_the_current_pose() {
        let (mut op, mut reference) = setup();
        let reply = ask(
            &mut op,
            &request(1, OperatorVerb::Goto, &[[0.0, -0.016]]),
            &mut reference,
            3.0,
        );
        assert_eq!(reply.accepted.raw(), 1, "{}", reply.text());
        let start = reference.waypoints()[0];
        let end = *reference.waypoints().last().unwrap();
        assert!(
            (start - Vector2::new(-0.018, 0.012)).norm() < 1e-3,
            "{start}"
        );
        assert!((end - Vector2::new(0.0, -0.016)).norm() < 1e-3, "{end}");
        assert!(reference.length_m() > 0.03);
        let rig = Rig::load_paper().unwrap();
        for t in 0..200 {
            let p = reference.sample(3.0 + f64::from(t)).position_m;
            assert!(
                rig.phantom.mask.contains(&p),
                "path leaves the canal at {p}"
            );
        }
    }
}
