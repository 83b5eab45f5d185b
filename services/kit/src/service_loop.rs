//! The loop every event-driven service runs: sleep in a WaitSet until an input arrives, an
//! input misses its deadline or the heartbeat tick comes; then do the housekeeping every
//! service needs (count misses, beat, connect new subscribers) and hand the wake to the
//! service's own per-wake code. SIGINT / SIGTERM end the loop.
//!
//! ```no_run
//! # use millinav_kit::ports::{Inbox, Outbox};
//! # use millinav_kit::service_loop::ServiceLoop;
//! # fn demo(rt: &mut millinav_kit::Runtime) -> anyhow::Result<()> {
//! let poses = Inbox::<u64>::new(&rt.node, "in")?;
//! let out = Outbox::<u64>::new(&rt.node, "out")?;
//! let mut service_loop = ServiceLoop::new();
//! let pose_input = service_loop.input_with_deadline(&poses, std::time::Duration::from_millis(200));
//! service_loop.output(&out);
//! service_loop.run(&mut rt.heartbeat, |wake| {
//!     if wake.missed_deadline(pose_input) {
//!         tracing::debug!("late input");
//!     }
//!     for value in poses.receive_all()? {
//!         out.send(value + 1)?;
//!     }
//!     Ok::<(), anyhow::Error>(())
//! })?;
//! # Ok(())
//! # }
//! ```

use std::fmt::Debug;
use std::time::Duration;

use iceoryx2::prelude::*;
use iceoryx2::waitset::WaitSetRunResult;
use shm_schemas::deadlines;

use crate::ports::HeartbeatSender;
pub use crate::ports::{Attachable, Connects};
use crate::{iox, KitError};

/// Longest a service sleeps in its WaitSet between two wakes when the tick is slower. A
/// safety net: the heartbeat tick (100 ms) normally wakes the loop first.
pub const LONGEST_SLEEP: Duration = Duration::from_millis(100);

/// Most inputs one loop can watch (the wake records them in a bit mask).
pub const MAX_INPUTS: usize = 32;

/// Which input of a loop, as returned when it was added.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct InputId(usize);

/// What woke the loop this time.
#[derive(Debug, Clone, Default)]
pub struct Wake {
    fired: u32,
    missed: u32,
    ticked: bool,
    stop: bool,
}

impl Wake {
    /// A sample was announced on this input.
    pub fn fired(&self, input: InputId) -> bool {
        self.fired & (1 << input.0) != 0
    }

    /// This input's deadline passed without an announcement.
    pub fn missed_deadline(&self, input: InputId) -> bool {
        self.missed & (1 << input.0) != 0
    }

    /// Any input missed its deadline.
    pub fn any_missed(&self) -> bool {
        self.missed != 0
    }

    /// The tick of the loop came.
    pub fn ticked(&self) -> bool {
        self.ticked
    }

    /// Ends the loop after this wake (`run` returns `LoopEnd::Stopped`).
    pub fn stop(&mut self) {
        self.stop = true;
    }
}

/// Why `ServiceLoop::run` returned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LoopEnd {
    /// SIGINT or SIGTERM was received.
    Terminated,
    /// The per-wake code called `Wake::stop`.
    Stopped,
}

struct Input<'a> {
    source: &'a dyn Attachable,
    deadline: Option<Duration>,
}

/// A service's WaitSet loop: its inputs (each with an optional deadline), its outputs, and the
/// tick that drives the heartbeat (and whatever the service does on every wake).
pub struct ServiceLoop<'a> {
    inputs: Vec<Input<'a>>,
    outputs: Vec<&'a dyn Connects>,
    tick: Duration,
}

impl Default for ServiceLoop<'_> {
    fn default() -> Self {
        Self::new()
    }
}

impl<'a> ServiceLoop<'a> {
    /// A loop that ticks at the heartbeat period.
    pub fn new() -> Self {
        Self {
            inputs: Vec::new(),
            outputs: Vec::new(),
            tick: deadlines::HEARTBEAT_PERIOD,
        }
    }

    /// Wakes the loop on each announcement of `input`.
    pub fn input(&mut self, input: &'a dyn Attachable) -> InputId {
        self.add_input(input, None)
    }

    /// Wakes the loop on each announcement of `input`, and reports a missed deadline when
    /// none came for `deadline` (again every `deadline` while none comes).
    pub fn input_with_deadline(
        &mut self,
        input: &'a dyn Attachable,
        deadline: Duration,
    ) -> InputId {
        self.add_input(input, Some(deadline))
    }

    fn add_input(&mut self, source: &'a dyn Attachable, deadline: Option<Duration>) -> InputId {
        assert!(
            self.inputs.len() < MAX_INPUTS,
            "a ServiceLoop watches at most {MAX_INPUTS} inputs"
        );
        self.inputs.push(Input { source, deadline });
        InputId(self.inputs.len() - 1)
    }

    /// An output whose subscribers the loop connects on every wake.
    pub fn output(&mut self, output: &'a dyn Connects) {
        self.outputs.push(output);
    }

    /// Wakes the loop at least every `period` (default: the heartbeat period). A period below
    /// `LONGEST_SLEEP` also shortens the longest sleep.
    pub fn tick_every(&mut self, period: Duration) {
        self.tick = period;
    }

    /// Runs until SIGINT / SIGTERM or until `on_wake` calls `Wake::stop`. On every wake it first
    /// drains the inputs' announcements (so the WaitSet never spins), counts missed deadlines
    /// into the heartbeat, beats and connects new subscribers, then calls `on_wake`, which
    /// takes the samples it wants from its inputs. An error from `on_wake` ends the loop.
    pub fn run<E: From<KitError>>(
        self,
        heartbeat: &mut HeartbeatSender,
        mut on_wake: impl FnMut(&mut Wake) -> Result<(), E>,
    ) -> Result<LoopEnd, E> {
        crate::termination::watch();
        let waitset = WaitSetBuilder::new()
            .create::<ipc::Service>()
            .map_err(iox("waitset"))?;
        let mut guards = Vec::with_capacity(self.inputs.len());
        for input in &self.inputs {
            let guard = match input.deadline {
                Some(deadline) => waitset.attach_deadline(input.source, deadline),
                None => waitset.attach_notification(input.source),
            }
            .map_err(iox("attach input"))?;
            guards.push(guard);
        }
        let tick = waitset
            .attach_interval(self.tick)
            .map_err(iox("attach tick"))?;
        let sleep = self.tick.min(LONGEST_SLEEP);
        loop {
            // A request that arrived while `on_wake` ran: iceoryx2 may have lost it already.
            if crate::termination::requested() {
                return Ok(LoopEnd::Terminated);
            }
            let mut wake = Wake::default();
            let result = waitset
                .wait_and_process_once_with_timeout(
                    |id| {
                        for (k, guard) in guards.iter().enumerate() {
                            if id.has_event_from(guard) {
                                wake.fired |= 1 << k;
                            } else if id.has_missed_deadline(guard) {
                                wake.missed |= 1 << k;
                            }
                        }
                        if id.has_event_from(&tick) {
                            wake.ticked = true;
                        }
                        CallbackProgression::Continue
                    },
                    sleep,
                )
                .map_err(iox("waitset"))?;
            // Any signal interrupts the wait; only SIGTERM / SIGINT end the loop.
            if crate::termination::waitset_says_stop(&result) {
                return Ok(LoopEnd::Terminated);
            }
            if matches!(result, WaitSetRunResult::Interrupt) {
                continue;
            }
            for input in &self.inputs {
                input.source.drain_events();
            }
            for _ in 0..wake.missed.count_ones() {
                heartbeat.count_deadline_miss();
            }
            keep_alive(heartbeat, &self.outputs);
            on_wake(&mut wake)?;
            if wake.stop {
                return Ok(LoopEnd::Stopped);
            }
        }
    }
}

/// The housekeeping of every wake: beat (when the heartbeat period has passed) and connect new
/// subscribers of the outputs and the heartbeat. For loops that are not a `ServiceLoop`.
pub fn keep_alive(heartbeat: &mut HeartbeatSender, outputs: &[&dyn Connects]) {
    heartbeat.beat();
    for output in outputs {
        output.update_connections();
    }
    heartbeat.update_connections();
}
