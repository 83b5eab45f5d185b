//! `millinav ctl`: the operator's commands to a running set, over iceoryx2 (the set's prefix
//! and root). A request is sent, and sent again with the same id until control answers or the
//! timeout passes; control applies it once and answers each copy with the state it produced.

use std::path::Path;
use std::time::{Duration, Instant};

use millinav_kit::iceoryx2::prelude::*;
use millinav_kit::ports::{Inbox, Outbox};
use serde::Deserialize;
use shm_schemas::{
    services, Flag, OperatorReply, OperatorRequest, OperatorState, OperatorVerb,
    MAX_OPERATOR_WAYPOINTS,
};

/// How often an unanswered request is sent again.
const RESEND_EVERY: Duration = Duration::from_millis(200);

#[derive(Debug, thiserror::Error)]
pub enum CtlError {
    #[error("{path}: {message}")]
    Waypoints { path: String, message: String },
    #[error("goal ({x_mm}, {y_mm}) mm is not a finite position")]
    BadGoal { x_mm: f64, y_mm: f64 },
    #[error(
        "no answer from control within {0:?}: is a set running with this --iox-prefix and --iox-root?"
    )]
    NoAnswer(Duration),
    #[error("iceoryx2: {0}")]
    Ipc(String),
}

/// A waypoints file: the scenario's `waypoints_mm` key (mm, x y pairs).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct WaypointsFile {
    waypoints_mm: Vec<[f64; 2]>,
}

/// The request for `verb`, with its goal or waypoints (mm at this edge, m inside).
pub fn request(
    verb: OperatorVerb,
    goal_mm: Option<[f64; 2]>,
    waypoints_file: Option<&Path>,
) -> Result<OperatorRequest, CtlError> {
    let mut request = OperatorRequest {
        request_id: std::process::id() as u64 ^ millinav_kit::clock::monotonic_ns(),
        verb: verb as u32,
        ..Default::default()
    };
    if let Some([x_mm, y_mm]) = goal_mm {
        if !(x_mm.is_finite() && y_mm.is_finite()) {
            return Err(CtlError::BadGoal { x_mm, y_mm });
        }
        request.waypoints_m[0] = [x_mm * 1e-3, y_mm * 1e-3];
        request.waypoint_count = 1;
    }
    if let Some(path) = waypoints_file {
        let bad = |message: String| CtlError::Waypoints {
            path: path.display().to_string(),
            message,
        };
        let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
        let file: WaypointsFile = toml::from_str(&text).map_err(|e| bad(e.to_string()))?;
        let n = file.waypoints_mm.len();
        if !(1..=MAX_OPERATOR_WAYPOINTS).contains(&n) {
            return Err(bad(format!(
                "waypoints_mm has {n} points; send 1 to {MAX_OPERATOR_WAYPOINTS}"
            )));
        }
        for (i, [x, y]) in file.waypoints_mm.iter().enumerate() {
            if !(x.is_finite() && y.is_finite()) {
                return Err(bad(format!("waypoints_mm[{i}] is not finite")));
            }
            request.waypoints_m[i] = [x * 1e-3, y * 1e-3];
        }
        request.waypoint_count = n as u32;
    }
    Ok(request)
}

/// Sends `request` to the set in the iceoryx2 namespace (`prefix`, `root`) and waits for the
/// answer.
pub fn send(
    request: &OperatorRequest,
    prefix: &str,
    root: &Path,
    timeout: Duration,
) -> Result<OperatorReply, CtlError> {
    let ipc_err = |e: &dyn std::fmt::Display| CtlError::Ipc(e.to_string());
    let config = millinav_kit::iceoryx_config(Some(prefix), Some(root)).map_err(|e| ipc_err(&e))?;
    let node = NodeBuilder::new()
        .config(&config)
        .create::<ipc::Service>()
        .map_err(|e| ipc_err(&e))?;
    let replies =
        Inbox::<OperatorReply>::new(&node, services::OPERATOR_REPLY).map_err(|e| ipc_err(&e))?;
    let requests = Outbox::<OperatorRequest>::new(&node, services::OPERATOR_REQUEST)
        .map_err(|e| ipc_err(&e))?;
    let start = Instant::now();
    while start.elapsed() < timeout {
        requests.update_connections();
        requests.send(*request).map_err(|e| ipc_err(&e))?;
        let resend_at = Instant::now() + RESEND_EVERY;
        while Instant::now() < resend_at {
            if let Some(reply) = replies
                .receive_all()
                .map_err(|e| ipc_err(&e))?
                .into_iter()
                .find(|r| r.request_id == request.request_id)
            {
                return Ok(reply);
            }
            replies.wait(resend_at.saturating_duration_since(Instant::now()));
        }
    }
    Err(CtlError::NoAnswer(timeout))
}

/// The answer as the operator reads it.
pub fn describe(verb: OperatorVerb, reply: &OperatorReply) -> String {
    let state = OperatorState::from_repr(reply.state).map_or("unknown", OperatorState::name);
    let at = |p: [f64; 2]| {
        if p[0].is_finite() && p[1].is_finite() {
            format!("({:.2}, {:.2}) mm", p[0] * 1e3, p[1] * 1e3)
        } else {
            "unknown".into()
        }
    };
    format!(
        "{}: {}: {}\nstate: {state}; robot at {}; path ends at {}",
        verb.name(),
        if reply.accepted == Flag::TRUE {
            "done"
        } else {
            "REFUSED"
        },
        reply.text(),
        at(reply.position_m),
        at(reply.target_m)
    )
}
