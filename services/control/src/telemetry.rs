//! What control logs: the Rerun recording of each decision, `control.csv` and
//! `operator_events.csv`.

use millinav_kit::recording;
use millinav_kit::rerun;
use millinav_kit::runlog::{ControlRow, RunLogWriter};
use shm_schemas::{Flag, OperatorReply, OperatorRequest, OperatorState, OperatorVerb, Pose};

use crate::coil_gains::GainUpdate;
use crate::control_loop::{ControlLoop, Decision};
use crate::operator::OperatorEventRow;
use crate::reference::Reference;

pub(crate) fn log_decision(rec: &rerun::RecordingStream, pose: &Pose, d: &Decision) {
    let e = d.terms.error_m * 1e3;
    recording::scalar(rec, "control/error_mm/x", e.x);
    recording::scalar(rec, "control/error_mm/y", e.y);
    recording::scalar(rec, "control/error_mm/norm", e.norm());
    recording::scalar(
        rec,
        "control/error_rate_mm_s/x",
        d.terms.error_rate_mps.x * 1e3,
    );
    recording::scalar(
        rec,
        "control/error_rate_mm_s/y",
        d.terms.error_rate_mps.y * 1e3,
    );
    recording::scalar(rec, "control/sliding_surface/x", d.terms.sliding_surface.x);
    recording::scalar(rec, "control/sliding_surface/y", d.terms.sliding_surface.y);
    recording::scalar(rec, "control/d_hat_n/x", d.terms.disturbance_estimate_n.x);
    recording::scalar(rec, "control/d_hat_n/y", d.terms.disturbance_estimate_n.y);
    recording::scalar(rec, "control/force_des_n/x", d.command.force_des_n[0]);
    recording::scalar(rec, "control/force_des_n/y", d.command.force_des_n[1]);
    recording::scalar(rec, "control/mode", f64::from(d.command.mode));
    recording::scalar(rec, "control/pose_age_ms", d.pose_age_s * 1e3);
    recording::scalar(
        rec,
        "control/unpredicted_motion_share",
        d.unpredicted_motion_share,
    );
    recording::scalar(rec, "control/disturbance_delays", d.disturbance_delays);
    if let Some(cap) = d.force_cap_n {
        recording::scalar(rec, "control/force_cap_n", cap);
    }
    for (i, c) in d.command.currents().unwrap_or_default().iter().enumerate() {
        recording::scalar(rec, &format!("control/current_a/{i}"), *c);
    }
    let _ = rec.log(
        "world/reference",
        &rerun::Points2D::new([[
            (d.reference_m.x * 1e3) as f32,
            (d.reference_m.y * 1e3) as f32,
        ]])
        .with_radii([0.8]),
    );
    if d.rejected.is_none() {
        // Where the loop believes the robot is when this command acts.
        let _ = rec.log(
            "world/robot/predicted",
            &rerun::Points2D::new([[
                (d.predicted_position_m.x * 1e3) as f32,
                (d.predicted_position_m.y * 1e3) as f32,
            ]])
            .with_radii([0.6]),
        );
    }
    if pose.is_usable() {
        let _ = rec.log(
            "world/robot/heading",
            &rerun::Arrows2D::from_vectors([[
                (pose.heading_rad.cos() * 4.0) as f32,
                (pose.heading_rad.sin() * 4.0) as f32,
            ]])
            .with_origins([[
                (pose.position_m[0] * 1e3) as f32,
                (pose.position_m[1] * 1e3) as f32,
            ]]),
        );
    }
}

/// One operator request and its answer, into `operator_events.csv` (flushed: an operator reads
/// it while the run goes on) and the recording.
pub(crate) fn log_operator(
    rec: &rerun::RecordingStream,
    events: &mut RunLogWriter<OperatorEventRow>,
    request: &OperatorRequest,
    reply: &OperatorReply,
    now_s: f64,
) -> anyhow::Result<()> {
    let verb = OperatorVerb::from_repr(request.verb).map_or("unknown", OperatorVerb::name);
    let state = OperatorState::from_repr(reply.state).map_or("unknown", OperatorState::name);
    let accepted = reply.accepted == Flag::TRUE;
    let row = OperatorEventRow {
        time_s: now_s,
        request_id: request.request_id,
        verb: verb.to_string(),
        accepted,
        state: state.to_string(),
        message: reply.text(),
    };
    events.append_now(&row)?;
    let _ = rec.log(
        "operator/events",
        &rerun::TextLog::new(format!(
            "{verb}: {} ({state}): {}",
            if accepted { "done" } else { "refused" },
            row.message
        )),
    );
    tracing::info!(verb, accepted, state, message = %row.message, "operator request");
    Ok(())
}

/// The 3D rig view is drawn every this many frames (10 Hz at 100 Hz).
pub(crate) const RIG3D_EVERY: u64 = 10;

/// `control.csv` is flushed every this many frames.
pub(crate) const DECISIONS_PER_FLUSH: u64 = 50;

/// The `control.csv` row of one decision (for the run summary).
pub(crate) fn control_row(pose: &Pose, d: &Decision, now_ns: u64) -> ControlRow {
    let currents = d.command.currents().unwrap_or_default();
    let used = d.rejected.is_none() && pose.is_usable();
    let measured = if pose.is_usable() {
        pose.position_m
    } else {
        [f64::NAN; 2]
    };
    ControlRow {
        frame_seq: pose.stamp.seq,
        frame_incarnation: pose.stamp.incarnation,
        time_s: now_ns as f64 * 1e-9,
        pose_used: used,
        measured_x_m: measured[0],
        measured_y_m: measured[1],
        reference_x_m: d.reference_m.x,
        reference_y_m: d.reference_m.y,
        finished: d.finished,
        mode: d.command.mode,
        max_abs_current_a: currents.iter().fold(0.0, |m: f64, c| m.max(c.abs())),
        sum_sq_current_a2: currents.iter().map(|c| c * c).sum(),
    }
}

/// The online coil-gain estimate (per rig coil name) and what the last frame did to it.
pub(crate) fn log_coil_gains(
    rec: &rerun::RecordingStream,
    control: &ControlLoop,
    update: Option<GainUpdate>,
) {
    let (Some(estimator), Some(update)) = (control.gain_estimator(), update) else {
        return;
    };
    if update != GainUpdate::Used {
        let why = match update {
            GainUpdate::WeakField => "weak field",
            GainUpdate::Gated => "innovation gated",
            GainUpdate::Used | GainUpdate::TooSoon => return,
        };
        let _ = rec.log(
            "control/coil_gain/skipped",
            &rerun::TextLog::new(format!(
                "heading not used ({why}); used {}, gated {}, weak {}",
                estimator.used, estimator.gated, estimator.weak
            )),
        );
        return;
    }
    for (gain, &id) in estimator.gains().iter().zip(control.coil_ids()) {
        let name = control
            .rig()
            .coils
            .get(id)
            .map_or_else(|| id.to_string(), |c| c.name.clone());
        recording::scalar(rec, &format!("control/coil_gain/{name}"), *gain);
    }
}

pub(crate) fn log_planned_path(rec: &rerun::RecordingStream, reference: &Reference) {
    let path: Vec<[f32; 2]> = reference
        .waypoints()
        .iter()
        .map(|p| [(p.x * 1e3) as f32, (p.y * 1e3) as f32])
        .collect();
    let _ = rec.log_static("world/planned_path", &rerun::LineStrips2D::new([path]));
}
