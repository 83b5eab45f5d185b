//! What to do when a child exits or stops beating: the decisions, without the processes, so
//! they can be tested alone.

use std::os::unix::process::ExitStatusExt;
use std::process::ExitStatus;
use std::time::{Duration, Instant};

use shm_schemas::ServiceId;

use crate::launch::RestartPolicy;

/// Exit status of a child that rejected its configuration (`EX_CONFIG` of sysexits.h).
pub use millinav_kit::EXIT_CONFIG;

/// What a child's exit means for the set.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExitKind {
    /// The plant finished the scenario: the run is over.
    RunComplete,
    /// The child rejected its configuration: restarting cannot help, the set stops.
    ConfigError,
    /// Anything else (crash, kill, error): restart with backoff if the launch file says so.
    Failed,
}

pub fn classify_exit(service: ServiceId, status: ExitStatus) -> ExitKind {
    if status.code() == Some(i32::from(EXIT_CONFIG)) {
        ExitKind::ConfigError
    } else if matches!(service, ServiceId::Plant | ServiceId::Camera) && status.success() {
        ExitKind::RunComplete
    } else {
        ExitKind::Failed
    }
}

/// Restart delay of one process: doubles on each consecutive failure up to the maximum, and
/// starts over once the process has lived `stable_after_ms`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Backoff {
    next: Duration,
}

impl Backoff {
    pub fn new(policy: &RestartPolicy) -> Self {
        Self {
            next: Duration::from_millis(policy.initial_backoff_ms),
        }
    }

    /// The delay before restarting a process that died after living `lived`.
    pub fn after_exit(&mut self, lived: Duration, policy: &RestartPolicy) -> Duration {
        if lived >= Duration::from_millis(policy.stable_after_ms) {
            self.next = Duration::from_millis(policy.initial_backoff_ms);
        }
        let delay = self.next;
        self.next = (self.next * 2).min(Duration::from_millis(policy.max_backoff_ms));
        delay
    }
}

/// How long a live process has been silent, if that makes it hung: past its start-up grace
/// and without a heartbeat for longer than `heartbeat_deadline`.
pub fn silent_too_long(
    now: Instant,
    started_at: Instant,
    last_beat: Instant,
    grace: Duration,
    heartbeat_deadline: Duration,
) -> Option<Duration> {
    let silent = now.saturating_duration_since(last_beat);
    (now.saturating_duration_since(started_at) > grace && silent > heartbeat_deadline)
        .then_some(silent)
}

/// Exit status of a process that called `exit(code)`.
pub fn exited_with(code: i32) -> ExitStatus {
    ExitStatus::from_raw((code & 0xff) << 8)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn policy() -> RestartPolicy {
        RestartPolicy {
            initial_backoff_ms: 100,
            max_backoff_ms: 1000,
            stable_after_ms: 5000,
            startup_grace_ms: 3000,
        }
    }

    fn ms(v: u64) -> Duration {
        Duration::from_millis(v)
    }

    #[test]
    fn backoff_doubles_up_to_the_maximum() {
        let policy = policy();
        let mut backoff = Backoff::new(&policy);
        let delays: Vec<u64> = (0..6)
            .map(|_| backoff.after_exit(ms(10), &policy).as_millis() as u64)
            .collect();
        assert_eq!(delays, [100, 200, 400, 800, 1000, 1000]);
    }

    #[test]
    fn a_stable_run_resets_the_backoff() {
        let policy = policy();
        let mut backoff = Backoff::new(&policy);
        for _ in 0..4 {
            backoff.after_exit(ms(10), &policy);
        }
        assert_eq!(backoff.after_exit(ms(5000), &policy), ms(100));
        assert_eq!(backoff.after_exit(ms(4999), &policy), ms(200));
    }

    #[test]
    fn exits_are_classified() {
        let signalled = ExitStatus::from_raw(9); // killed by SIGKILL
        assert_eq!(
            classify_exit(ServiceId::Plant, exited_with(0)),
            ExitKind::RunComplete
        );
        assert_eq!(
            classify_exit(ServiceId::Control, exited_with(0)),
            ExitKind::Failed
        );
        assert_eq!(
            classify_exit(ServiceId::Plant, exited_with(1)),
            ExitKind::Failed
        );
        assert_eq!(
            classify_exit(ServiceId::Vision, signalled),
            ExitKind::Failed
        );
        for service in [ServiceId::Plant, ServiceId::Flow, ServiceId::Coilbus] {
            assert_eq!(
                classify_exit(service, exited_with(i32::from(EXIT_CONFIG))),
                ExitKind::ConfigError
            );
        }
    }

    #[test]
    fn silence_counts_only_after_the_grace_period() {
        let start = Instant::now();
        let grace = ms(3000);
        let deadline = ms(500);
        // Silent for 2 s but still starting up.
        assert_eq!(
            silent_too_long(start + ms(2000), start, start, grace, deadline),
            None
        );
        // Past the grace period, silent for 3.5 s.
        assert_eq!(
            silent_too_long(start + ms(3500), start, start, grace, deadline),
            Some(ms(3500))
        );
        // Past the grace period, last beat 400 ms ago: alive.
        assert_eq!(
            silent_too_long(start + ms(3500), start, start + ms(3100), grace, deadline),
            None
        );
    }
}
