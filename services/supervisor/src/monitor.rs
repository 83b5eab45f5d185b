//! The monitor loop: reaping, restarts, heartbeats and hung services, the board's state, the
//! operator's `stop`, and the health records, every `MONITOR_TICK` until the set ends.

use super::*;

/// The heartbeat and health ports the supervisor listens on.
pub(super) struct Heartbeats {
    pub(super) listeners: Vec<(ServiceId, Listener<ipc::Service>)>,
    pub(super) health: Inbox<Heartbeat>,
    /// coilbus's status: the coil-driver board's state, faults and heat.
    pub(super) coil_status: Inbox<CoilStatus>,
    /// Operator requests: the supervisor answers `stop` (control the rest).
    pub(super) operator: Inbox<OperatorRequest>,
    pub(super) operator_replies: Outbox<OperatorReply>,
}

impl Heartbeats {
    pub(super) fn connect(rt: &Runtime, processes: &[ManagedProcess]) -> anyhow::Result<Self> {
        let listeners = processes
            .iter()
            .map(|p| Ok((p.id, heartbeat_listener(&rt.node, p.id)?)))
            .collect::<anyhow::Result<_>>()?;
        let health = Inbox::<Heartbeat>::new(&rt.node, services::HEALTH)?;
        let coil_status = Inbox::<CoilStatus>::new(&rt.node, services::COIL_STATUS)?;
        let operator = Inbox::<OperatorRequest>::new(&rt.node, services::OPERATOR_REQUEST)?;
        let operator_replies = Outbox::<OperatorReply>::new(&rt.node, services::OPERATOR_REPLY)?;
        Ok(Self {
            listeners,
            health,
            coil_status,
            operator,
            operator_replies,
        })
    }
}

pub(super) fn monitor(
    supervisor: &mut Supervisor,
    rt: &Runtime,
    heartbeats: &Heartbeats,
) -> anyhow::Result<Ending> {
    let waitset = WaitSetBuilder::new()
        .create::<ipc::Service>()
        .map_err(millinav_kit::iox("waitset"))?;
    let guards = heartbeats
        .listeners
        .iter()
        .map(|(id, listener)| {
            waitset
                .attach_deadline(listener, deadlines::HEARTBEAT)
                .map(|g| (*id, g))
                .map_err(millinav_kit::iox("attach heartbeat"))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let _tick = waitset
        .attach_interval(MONITOR_TICK)
        .map_err(millinav_kit::iox("attach tick"))?;
    let start = Instant::now();
    let mut latest_health: BTreeMap<u32, Heartbeat> = BTreeMap::new();
    let mut board = BoardView::default();
    loop {
        let mut beating = Vec::new();
        let result = waitset
            .wait_and_process_once_with_timeout(
                |attachment| {
                    for (id, guard) in &guards {
                        if attachment.has_event_from(guard) {
                            beating.push(*id);
                        }
                    }
                    CallbackProgression::Continue
                },
                MONITOR_TICK,
            )
            .map_err(millinav_kit::iox("waitset"))?;
        // A SIGCONT (the shell's `fg`, systemd after its SIGTERM) interrupts the wait too, and
        // may have erased iceoryx2's record of a SIGTERM before it: the kit's flag decides.
        if millinav_kit::termination::waitset_says_stop(&result) {
            supervisor
                .events
                .record(ServiceId::Supervisor, "signal", "shutting down");
            return Ok(Ending::Signal);
        }
        let now = Instant::now();
        note_heartbeats(supervisor, heartbeats, &mut beating, now);
        take_health(supervisor, heartbeats, &mut latest_health)?;
        for request in heartbeats.operator.receive_all()? {
            if request.verb == OperatorVerb::Stop as u32 {
                let reply = OperatorReply::new(
                    request.request_id,
                    true,
                    OperatorState::Stopping,
                    "stopping the set: control and coilbus first, coils to zero",
                );
                heartbeats.operator_replies.update_connections();
                heartbeats.operator_replies.send(reply)?;
                supervisor.events.record(
                    ServiceId::Supervisor,
                    "operator_stop",
                    "millinav ctl stop",
                );
                return Ok(Ending::OperatorStop);
            }
        }
        for status in heartbeats.coil_status.receive_all()? {
            if let Some(fault) = board.observe(&status, &mut supervisor.events, &rt.rec) {
                return Ok(Ending::BoardFault(fault));
            }
        }
        if let Some(ending) = supervisor.reap(&rt.node)? {
            // A process's last heartbeat (e.g. the camera's end-of-stream fault) may have
            // arrived since the read above.
            take_health(supervisor, heartbeats, &mut latest_health)?;
            return Ok(ending);
        }
        // A started process that stopped beating is hung (or stopped): kill it; reap restarts
        // it. One still starting only has its budget.
        if let Some(ending) = supervisor.watch_children(now) {
            return Ok(ending);
        }
        supervisor.restart_due()?;
        record_health(rt, &latest_health);
        if start.elapsed() > supervisor.options.max_wall_time {
            supervisor.events.record(
                ServiceId::Supervisor,
                "wall_time_limit",
                &format!("{:?}", supervisor.options.max_wall_time),
            );
            return Ok(Ending::WallTimeLimit);
        }
    }
}

/// Reads the health records that arrived: deadline misses per incarnation, and a supervisor
/// event for each new source fault.
pub(super) fn take_health(
    supervisor: &mut Supervisor,
    heartbeats: &Heartbeats,
    latest_health: &mut BTreeMap<u32, Heartbeat>,
) -> anyhow::Result<()> {
    let now = Instant::now();
    for beat in heartbeats.health.receive_all()? {
        if let Some(id) = ServiceId::from_repr(beat.service) {
            supervisor.note_started(id, beat.incarnation, now);
        }
        supervisor
            .deadline_misses
            .insert((beat.service, beat.incarnation), beat.deadline_misses);
        // A source fault (a camera that stalled, was unplugged or ended) goes into the
        // run's events; the service's own event log says why.
        let earlier = latest_health
            .get(&beat.service)
            .filter(|b| b.incarnation == beat.incarnation)
            .map_or(0, |b| b.source_faults);
        if beat.source_faults > earlier {
            if let Some(id) = ServiceId::from_repr(beat.service) {
                supervisor.events.record(
                    id,
                    "source_fault",
                    &format!(
                        "faults={} dropped_frames={} (details: {}_events.csv)",
                        beat.source_faults,
                        beat.dropped_samples,
                        id.name()
                    ),
                );
            }
        }
        latest_health.insert(beat.service, beat);
    }
    Ok(())
}

/// The coil-driver board as coilbus reports it: state and fault changes become supervisor
/// events (`supervisor_events.csv`, Rerun `supervisor/events`), state, fault and heat go to
/// Rerun under `health/board`.
#[derive(Default)]
pub(super) struct BoardView {
    state: Option<u8>,
    fault: Option<u8>,
}

impl BoardView {
    fn observe(
        &mut self,
        status: &CoilStatus,
        events: &mut EventLog,
        rec: &rerun::RecordingStream,
    ) -> Option<&'static str> {
        let mut new_fault = None;
        if self.state != Some(status.board_state) {
            self.state = Some(status.board_state);
            events.record(
                ServiceId::Coilbus,
                "board_state",
                board_state_name(status.board_state),
            );
        }
        if self.fault != Some(status.board_fault) {
            self.fault = Some(status.board_fault);
            let name = BoardFault::from_repr(status.board_fault).map_or("invalid", |f| f.name());
            if status.board_fault != BoardFault::None as u8 {
                tracing::warn!(fault = name, "coilbus holds the coils at zero: board fault");
                events.record(ServiceId::Coilbus, "board_fault", name);
                new_fault = Some(name);
            }
        }
        recording::scalar(rec, "health/board/state", f64::from(status.board_state));
        recording::scalar(rec, "health/board/fault", f64::from(status.board_fault));
        recording::scalar(
            rec,
            "health/board/thermal_permille",
            f64::from(status.thermal_permille),
        );
        new_fault
    }
}

/// Marks the processes that beat since the last tick (WaitSet events or pending ones).
pub(super) fn note_heartbeats(
    supervisor: &mut Supervisor,
    heartbeats: &Heartbeats,
    beating: &mut Vec<ServiceId>,
    now: Instant,
) {
    for (id, listener) in &heartbeats.listeners {
        let mut got = false;
        let _ = listener.try_wait(|_| got = true);
        if got && !beating.contains(id) {
            beating.push(*id);
        }
    }
    for process in supervisor.processes.iter_mut() {
        if beating.contains(&process.id) {
            process.last_beat = now;
        }
    }
}

/// The run clock and each service's deadline misses, into the recording.
pub(super) fn record_health(rt: &Runtime, latest_health: &BTreeMap<u32, Heartbeat>) {
    rt.rec
        .set_duration_secs(recording::RUN_TIMELINE, rt.env.run_clock_ns() as f64 * 1e-9);
    for (service, beat) in latest_health {
        if let Some(id) = ServiceId::from_repr(*service) {
            recording::scalar(
                &rt.rec,
                &format!("health/{}/deadline_misses", id.name()),
                beat.deadline_misses as f64,
            );
            if id == ServiceId::Camera {
                recording::scalar(
                    &rt.rec,
                    "health/camera/dropped_frames",
                    beat.dropped_samples as f64,
                );
                recording::scalar(
                    &rt.rec,
                    "health/camera/source_faults",
                    beat.source_faults as f64,
                );
            }
        }
    }
}
