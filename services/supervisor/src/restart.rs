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

/// How long a process that has started (it beat once) has been silent, if that makes it hung.
/// A process that is still starting is never hung: [`startup_progress`] watches it instead.
pub fn silent_too_long(
    now: Instant,
    last_beat: Instant,
    heartbeat_deadline: Duration,
) -> Option<Duration> {
    let silent = now.saturating_duration_since(last_beat);
    (silent > heartbeat_deadline).then_some(silent)
}

/// How often a slow start is noted in the run's events (and on the console).
pub const SLOW_START_NOTE_EVERY: Duration = Duration::from_secs(10);

/// Where a process that has not beaten yet stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Startup {
    /// Starting, nothing to say.
    Starting,
    /// Still starting after this long: note it (a loaded or cold machine), do not kill it.
    Slow(Duration),
    /// Its start-up budget has passed without a heartbeat.
    OverBudget(Duration),
}

/// Where a starting process stands at `now`, given when it started, its budget, and when its
/// slowness was last noted.
pub fn startup_progress(
    now: Instant,
    started_at: Instant,
    budget: Duration,
    last_note: Option<Instant>,
) -> Startup {
    let waited = now.saturating_duration_since(started_at);
    if waited > budget {
        Startup::OverBudget(waited)
    } else if waited >= SLOW_START_NOTE_EVERY
        && last_note.is_none_or(|t| now.saturating_duration_since(t) >= SLOW_START_NOTE_EVERY)
    {
        Startup::Slow(waited)
    } else {
        Startup::Starting
    }
}

/// The recent failures of one process, to tell a restart storm (a process that keeps dying:
/// restarting it again will not help) from an occasional crash.
#[derive(Debug, Clone, Default)]
pub struct StormWatch {
    failures: std::collections::VecDeque<Instant>,
}

impl StormWatch {
    /// Records a failure at `at`; returns how many fell within the window when they make a
    /// storm.
    pub fn failed(&mut self, at: Instant, policy: &RestartPolicy) -> Option<usize> {
        let window = Duration::from_millis(policy.storm_window_ms);
        self.failures.push_back(at);
        while self
            .failures
            .front()
            .is_some_and(|t| at.saturating_duration_since(*t) > window)
        {
            self.failures.pop_front();
        }
        (self.failures.len() >= policy.storm_restarts as usize).then_some(self.failures.len())
    }
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
            startup_budget_ms: 3000,
            storm_restarts: 5,
            storm_window_ms: 60_000,
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
    fn silence_counts_against_a_started_process() {
        let start = Instant::now();
        let deadline = ms(500);
        assert_eq!(silent_too_long(start + ms(400), start, deadline), None);
        assert_eq!(
            silent_too_long(start + ms(3500), start, deadline),
            Some(ms(3500))
        );
    }

    #[test]
    fn a_slow_start_is_noted_every_ten_seconds_until_its_budget() {
        let start = Instant::now();
        let budget = ms(60_000);
        let at = |t| startup_progress(start + ms(t), start, budget, None);
        assert_eq!(at(9_000), Startup::Starting);
        assert_eq!(at(10_000), Startup::Slow(ms(10_000)));
        let noted = Some(start + ms(10_000));
        assert_eq!(
            startup_progress(start + ms(15_000), start, budget, noted),
            Startup::Starting
        );
        assert_eq!(
            startup_progress(start + ms(20_000), start, budget, noted),
            Startup::Slow(ms(20_000))
        );
        assert_eq!(at(60_001), Startup::OverBudget(ms(60_001)));
    }

    #[test]
    fn a_storm_is_so_many_failures_within_the_window() {
        let policy = RestartPolicy {
            storm_restarts: 3,
            storm_window_ms: 10_000,
            ..policy()
        };
        let start = Instant::now();
        let mut watch = StormWatch::default();
        // Failures spread wider than the window never make a storm.
        for k in 0..10 {
            assert_eq!(watch.failed(start + ms(6_000 * k), &policy), None);
        }
        let later = start + ms(100_000);
        assert_eq!(watch.failed(later, &policy), None);
        assert_eq!(watch.failed(later + ms(100), &policy), None);
        assert_eq!(watch.failed(later + ms(200), &policy), Some(3));
    }
}
