//! The control process: the loop wired to its iceoryx2 ports.

use std::time::{Duration, Instant};

use anyhow::Context;
use millinav_kit::ports::{Inbox, Outbox};
use millinav_kit::recording;
use millinav_kit::runlog::{ControlRow, RunLogWriter};
use millinav_kit::scenario::Scenario;
use millinav_kit::{Runtime, ServiceLoop};
use nalgebra::Vector2;
use shm_schemas::{
    deadlines, services, CoilCommand, FlowEstimate, FrameStamp, OperatorReply, OperatorRequest,
    Pose,
};

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
    let mut control = setup.into_loop(scenario.viscosity_pa_s(), rt.env.incarnation);
    tracing::info!(controller = control.controller_name(), "control ready");
    log_planned_path(&rt.rec, &control.reference);
    rig3d::log_static(&rt.rec, control.rig());
    let poses = Inbox::<Pose>::new(&rt.node, services::POSE)?;
    let flows = Inbox::<FlowEstimate>::new(&rt.node, services::FLOW)?;
    let commands = Outbox::<CoilCommand>::new(&rt.node, services::COMMAND)?;
    let requests = Inbox::<OperatorRequest>::new(&rt.node, services::OPERATOR_REQUEST)?;
    let replies = Outbox::<OperatorReply>::new(&rt.node, services::OPERATOR_REPLY)?;
    let mut operator = Operator::new(
        control.rig(),
        millinav_kit::in_session(),
        control.config.replan_clearance_mm * 1e-3,
    )
    .context("the rig's canal mask for planning")?;
    std::fs::create_dir_all(&rt.env.run_dir)?;
    let mut operator_events = RunLogWriter::<OperatorEventRow>::in_run_dir(&rt.env.run_dir)?;
    let mut last_now_ns = 0;
    // Append: a restarted control continues the same log.
    let mut decisions = RunLogWriter::<ControlRow>::in_run_dir(&rt.env.run_dir)?;
    let mut flow_cache = Vec::new();
    let mut flow_misses: u64 = 0;
    // Wall time of the last flow estimate: flow is an input of the loop, and losing it must
    // bring the coils to zero within one command deadline, like losing the poses does.
    let mut last_flow = Instant::now();

    // "Now" for latency: lockstep holds the twin's clock at the frame's grab time until the
    // command arrives; in real time it is the run clock.
    let realtime = scenario.run.mode == millinav_kit::scenario::ClockMode::Realtime;
    let mut service_loop = ServiceLoop::new();
    let pose_input = service_loop.input_with_deadline(&poses, deadlines::POSE);
    service_loop.output(&commands);
    service_loop.output(&replies);
    service_loop.run(&mut rt.heartbeat, |wake| {
        if wake.missed_deadline(pose_input) {
            tracing::debug!("no pose within {:?}", deadlines::POSE);
        }
        for request in requests.receive_all()? {
            let now_ns = if realtime {
                rt.env.run_clock_ns()
            } else {
                last_now_ns
            };
            let now_s = now_ns as f64 * 1e-9;
            if let Some(reply) = operator.handle(&request, &mut control.reference, now_s) {
                replies.send(reply)?;
                log_operator(&rt.rec, &mut operator_events, &request, &reply, now_s)?;
            }
        }
        let Some(pose) = poses.latest()? else {
            return Ok(());
        };
        operator.observe(
            pose.is_usable()
                .then(|| Vector2::new(pose.position_m[0], pose.position_m[1])),
        );
        let flow = flow_for(
            &flows,
            &mut flow_cache,
            &pose.stamp,
            deadlines::FLOW_FOR_POSE,
        )?;
        if flow.is_none() {
            flow_misses += 1;
            if flow_misses == 1 || flow_misses.is_multiple_of(WARN_EVERY_FLOW_MISSES) {
                tracing::warn!(
                    seq = pose.stamp.seq,
                    flow_misses,
                    "no flow estimate for pose"
                );
            }
        }
        if flow.is_some() {
            last_flow = Instant::now();
        }
        let now_ns = if realtime {
            rt.env.run_clock_ns()
        } else {
            pose.stamp.grab_time_ns
        };
        last_now_ns = now_ns;
        let decision = if let Some(why) = operator.blocks_currents() {
            control.safe_at(&pose, why, now_ns)
        } else if last_flow.elapsed() > FLOW_LOST_AFTER {
            control.safe_at(&pose, "flow estimates lost", now_ns)
        } else {
            control.step_at(&pose, flow.as_ref(), now_ns)
        };
        commands.send(decision.command)?;
        decisions.append(&control_row(&pose, &decision, now_ns))?;
        // Flushed twice a second at 100 Hz: a killed control loses at most that much.
        if pose.stamp.seq.is_multiple_of(DECISIONS_PER_FLUSH) {
            decisions.flush()?;
        }
        recording::set_time(&rt.rec, pose.stamp.capture_time_ns, pose.stamp.seq);
        log_decision(&rt.rec, &pose, &decision);
        if pose.stamp.seq.is_multiple_of(RIG3D_EVERY) {
            let robot = control.rig().robot;
            rig3d::log_state(
                &rt.rec,
                control.rig(),
                control.coil_ids(),
                &decision.command,
                &pose,
                robot.length_m,
                robot.radius_m(),
            );
        }
        log_coil_gains(&rt.rec, &control, decision.gain_update);
        anyhow::Ok(())
    })?;
    Ok(())
}
