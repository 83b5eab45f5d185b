//! The control process: the loop wired to its iceoryx2 ports.

use std::time::{Duration, Instant};

use anyhow::Context;
use millinav_kit::ports::{Inbox, Outbox};
use millinav_kit::recording;
use millinav_kit::rerun;
use millinav_kit::runlog::{ControlRow, RunLogWriter};
use millinav_kit::scenario::Scenario;
use millinav_kit::{RunEnv, Runtime, ServiceLoop};
use nalgebra::Vector2;
use shm_schemas::{
    deadlines, services, CoilCommand, FlowEstimate, FrameStamp, OperatorReply, OperatorRequest,
    Pose,
};

use crate::control_loop::{ControlLoop, Decision};
use crate::operator::{Operator, OperatorEventRow};
use crate::rig3d;
use crate::setup::ControlSetup;
use crate::telemetry::{
    control_row, log_coil_gains, log_decision, log_operator, log_planned_path, DECISIONS_PER_FLUSH,
    RIG3D_EVERY,
};

pub const FLOW_LOST_AFTER: Duration = Duration::from_millis(50);

/// Flow estimates kept for matching: only recent ones can match a new pose.
const FLOW_CACHE_LEN: usize = 16;

/// A warning is logged for the first missing flow estimate, then for every this many.
const WARN_EVERY_FLOW_MISSES: u64 = 100;

/// Waits (bounded) for the flow estimate made for the frame of `stamp`.
fn flow_for(
    flows: &Inbox<FlowEstimate>,
    cache: &mut Vec<FlowEstimate>,
    stamp: &FrameStamp,
    timeout: Duration,
) -> anyhow::Result<Option<FlowEstimate>> {
    let deadline = Instant::now() + timeout;
    loop {
        cache.extend(flows.receive_all()?);
        if cache.len() > FLOW_CACHE_LEN {
            cache.drain(..cache.len() - FLOW_CACHE_LEN);
        }
        if let Some(found) = cache.iter().rev().find(|f| f.stamp.same_frame(stamp)) {
            return Ok(Some(*found));
        }
        let now = Instant::now();
        if now >= deadline {
            return Ok(None);
        }
        flows.wait(deadline - now);
    }
}

/// The control process: each new pose (with the flow estimate made for it) gets a command.
pub fn run(rt: &mut Runtime, scenario: &Scenario, setup: ControlSetup) -> anyhow::Result<()> {
    let control = setup.into_loop(scenario.viscosity_pa_s(), rt.env.incarnation);
    tracing::info!(controller = control.controller_name(), "control ready");
    log_planned_path(&rt.rec, &control.reference);
    rig3d::log_static(&rt.rec, control.rig());
    let ports = Ports::open(rt)?;
    let mut service = Service::new(rt, scenario, control)?;
    let mut service_loop = ServiceLoop::new();
    let pose_input = service_loop.input_with_deadline(&ports.poses, deadlines::POSE);
    service_loop.output(&ports.commands);
    service_loop.output(&ports.replies);
    service_loop.run(&mut rt.heartbeat, |wake| {
        if wake.missed_deadline(pose_input) {
            tracing::debug!("no pose within {:?}", deadlines::POSE);
        }
        service.answer_operator(&ports, &rt.rec, &rt.env)?;
        let Some(pose) = ports.poses.latest()? else {
            return Ok(());
        };
        service.answer_pose(&ports, &rt.rec, &rt.env, &pose)
    })?;
    Ok(())
}

/// Control's iceoryx2 ports.
struct Ports {
    poses: Inbox<Pose>,
    flows: Inbox<FlowEstimate>,
    commands: Outbox<CoilCommand>,
    requests: Inbox<OperatorRequest>,
    replies: Outbox<OperatorReply>,
}

impl Ports {
    fn open(rt: &Runtime) -> anyhow::Result<Self> {
        Ok(Self {
            poses: Inbox::new(&rt.node, services::POSE)?,
            flows: Inbox::new(&rt.node, services::FLOW)?,
            commands: Outbox::new(&rt.node, services::COMMAND)?,
            requests: Inbox::new(&rt.node, services::OPERATOR_REQUEST)?,
            replies: Outbox::new(&rt.node, services::OPERATOR_REPLY)?,
        })
    }
}

/// The loop, the operator and the run logs between wakes.
struct Service {
    control: ControlLoop,
    operator: Operator,
    operator_events: RunLogWriter<OperatorEventRow>,
    decisions: RunLogWriter<ControlRow>,
    /// "Now" for latency: lockstep holds the twin's clock at the frame's grab time until the
    /// command arrives; in real time it is the run clock.
    realtime: bool,
    last_now_ns: u64,
    flow_cache: Vec<FlowEstimate>,
    flow_misses: u64,
    /// Wall time of the last flow estimate: flow is an input of the loop, and losing it must
    /// bring the coils to zero within one command deadline, like losing the poses does.
    last_flow: Instant,
}

impl Service {
    fn new(rt: &Runtime, scenario: &Scenario, control: ControlLoop) -> anyhow::Result<Self> {
        let operator = Operator::new(
            control.rig(),
            millinav_kit::in_session(),
            control.config.replan_clearance_mm * 1e-3,
        )
        .context("the rig's canal mask for planning")?;
        std::fs::create_dir_all(&rt.env.run_dir)?;
        Ok(Self {
            control,
            operator,
            operator_events: RunLogWriter::in_run_dir(&rt.env.run_dir)?,
            // Append: a restarted control continues the same log.
            decisions: RunLogWriter::in_run_dir(&rt.env.run_dir)?,
            realtime: scenario.run.mode == millinav_kit::scenario::ClockMode::Realtime,
            last_now_ns: 0,
            flow_cache: Vec::new(),
            flow_misses: 0,
            last_flow: Instant::now(),
        })
    }

    /// Answers every pending operator request.
    fn answer_operator(
        &mut self,
        ports: &Ports,
        rec: &rerun::RecordingStream,
        env: &RunEnv,
    ) -> anyhow::Result<()> {
        for request in ports.requests.receive_all()? {
            let now_ns = if self.realtime {
                env.run_clock_ns()
            } else {
                self.last_now_ns
            };
            let now_s = now_ns as f64 * 1e-9;
            let reference = &mut self.control.reference;
            if let Some(reply) = self.operator.handle(&request, reference, now_s) {
                ports.replies.send(reply)?;
                log_operator(rec, &mut self.operator_events, &request, &reply, now_s)?;
            }
        }
        Ok(())
    }

    /// The command for `pose`, sent, written to `control.csv` and logged.
    fn answer_pose(
        &mut self,
        ports: &Ports,
        rec: &rerun::RecordingStream,
        env: &RunEnv,
        pose: &Pose,
    ) -> anyhow::Result<()> {
        self.operator.observe(
            pose.is_usable()
                .then(|| Vector2::new(pose.position_m[0], pose.position_m[1])),
        );
        let flow = self.flow_for(ports, pose)?;
        let now_ns = if self.realtime {
            env.run_clock_ns()
        } else {
            pose.stamp.grab_time_ns
        };
        self.last_now_ns = now_ns;
        let decision = if let Some(why) = self.operator.blocks_currents() {
            self.control.safe_at(pose, why, now_ns)
        } else if self.last_flow.elapsed() > FLOW_LOST_AFTER {
            self.control.safe_at(pose, "flow estimates lost", now_ns)
        } else {
            self.control.step_at(pose, flow.as_ref(), now_ns)
        };
        ports.commands.send(decision.command)?;
        self.decisions
            .append(&control_row(pose, &decision, now_ns))?;
        // Flushed twice a second at 100 Hz: a killed control loses at most that much.
        if pose.stamp.seq.is_multiple_of(DECISIONS_PER_FLUSH) {
            self.decisions.flush()?;
        }
        self.log(rec, pose, &decision);
        Ok(())
    }

    /// The flow estimate made for `pose`'s frame, waited for within its deadline; a miss is
    /// counted and warned of now and then.
    fn flow_for(&mut self, ports: &Ports, pose: &Pose) -> anyhow::Result<Option<FlowEstimate>> {
        let flow = flow_for(
            &ports.flows,
            &mut self.flow_cache,
            &pose.stamp,
            deadlines::FLOW_FOR_POSE,
        )?;
        if flow.is_some() {
            self.last_flow = Instant::now();
        } else {
            self.flow_misses += 1;
            let misses = self.flow_misses;
            if misses == 1 || misses.is_multiple_of(WARN_EVERY_FLOW_MISSES) {
                tracing::warn!(
                    seq = pose.stamp.seq,
                    flow_misses = misses,
                    "no flow estimate for pose"
                );
            }
        }
        Ok(flow)
    }

    /// The decision into the recording (the 3D rig every `RIG3D_EVERY` frames).
    fn log(&self, rec: &rerun::RecordingStream, pose: &Pose, decision: &Decision) {
        let control = &self.control;
        recording::set_time(rec, pose.stamp.capture_time_ns, pose.stamp.seq);
        log_decision(rec, pose, decision);
        if pose.stamp.seq.is_multiple_of(RIG3D_EVERY) {
            let robot = &control.rig().robot;
            rig3d::log_state(
                rec,
                control.rig(),
                control.coil_ids(),
                &decision.command,
                pose,
                robot.length_m,
                robot.radius_m(),
            );
        }
        log_coil_gains(rec, control, decision.gain_update);
    }
}
