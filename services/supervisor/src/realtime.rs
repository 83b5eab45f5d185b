//! Real-time settings of a process (`[process.realtime]` in a launch file): SCHED_FIFO priority
//! and CPU affinity, applied by the supervisor to the child it just started (both are kept
//! across the child's own threads it creates later), and memory locking, which the child does
//! itself at start-up (`mlockall` does not survive `exec`; see `millinav_kit::Runtime::start`).
//! Where the system does not permit a setting (no root, CAP_SYS_NICE, rtprio or memlock limit),
//! the process runs without it and the supervisor says so in the run's events.

use nix::sched::{sched_setaffinity, CpuSet};
use nix::unistd::Pid;
use serde::{Deserialize, Serialize};

/// `[process.realtime]`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Realtime {
    /// SCHED_FIFO priority, 1–99 (absent: the normal scheduler).
    #[serde(default)]
    pub fifo_priority: Option<i32>,
    /// CPUs the process may run on (absent: any).
    #[serde(default)]
    pub cpus: Option<Vec<usize>>,
    /// Lock the process's memory (`mlockall`): no page fault stalls a cycle.
    #[serde(default)]
    pub lock_memory: bool,
}

impl Realtime {
    /// Whether anything is asked for.
    pub fn is_set(&self) -> bool {
        self.fifo_priority.is_some() || self.cpus.is_some() || self.lock_memory
    }

    /// What is wrong with the settings, if anything (checked when the launch file loads).
    pub fn validate(&self) -> Result<(), String> {
        if let Some(p) = self.fifo_priority {
            if !(1..=99).contains(&p) {
                return Err(format!(
                    "fifo_priority = {p}: SCHED_FIFO priorities are 1-99"
                ));
            }
        }
        if let Some(cpus) = &self.cpus {
            if cpus.is_empty() {
                return Err("cpus = []: name at least one CPU, or leave cpus out".into());
            }
            if let Some(c) = cpus.iter().find(|&&c| c >= CpuSet::count()) {
                return Err(format!("cpus: CPU {c} is beyond what Linux can address"));
            }
        }
        Ok(())
    }

    /// Applies priority and affinity to `pid`; one line per setting saying what happened.
    pub fn apply(&self, pid: u32) -> Vec<Outcome> {
        let mut outcomes = Vec::new();
        let pid_raw = pid as nix::libc::pid_t;
        if let Some(priority) = self.fifo_priority {
            let param = nix::libc::sched_param {
                sched_priority: priority,
            };
            // SAFETY: a plain system call on a pid with a valid, initialised parameter.
            let result =
                unsafe { nix::libc::sched_setscheduler(pid_raw, nix::libc::SCHED_FIFO, &param) };
            outcomes.push(if result == 0 {
                Outcome::Applied(format!("SCHED_FIFO priority {priority}"))
            } else {
                Outcome::Denied(format!(
                    "SCHED_FIFO priority {priority}: {} (needs root, CAP_SYS_NICE or an rtprio limit)",
                    std::io::Error::last_os_error()
                ))
            });
        }
        if let Some(cpus) = &self.cpus {
            let mut set = CpuSet::new();
            let filled = cpus.iter().try_for_each(|&c| set.set(c));
            let result = filled.and_then(|()| sched_setaffinity(Pid::from_raw(pid_raw), &set));
            outcomes.push(match result {
                Ok(()) => Outcome::Applied(format!("CPUs {cpus:?}")),
                Err(e) => Outcome::Denied(format!(
                    "CPUs {cpus:?}: {e} (a CPU this machine does not have, or not permitted)"
                )),
            });
        }
        outcomes
    }
}

/// What became of one setting.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    Applied(String),
    Denied(String),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_settings_are_named() {
        let bad = |r: Realtime| r.validate().unwrap_err();
        assert!(bad(Realtime {
            fifo_priority: Some(0),
            ..Default::default()
        })
        .contains("1-99"));
        assert!(bad(Realtime {
            cpus: Some(vec![]),
            ..Default::default()
        })
        .contains("cpus"));
        assert!(Realtime::default().validate().is_ok() && !Realtime::default().is_set());
    }

    #[test]
    fn affinity_applies_to_a_running_process_and_a_missing_cpu_is_denied() {
        let mut child = std::process::Command::new("sleep")
            .arg("5")
            .spawn()
            .unwrap();
        let pid = child.id();
        let ok = Realtime {
            cpus: Some(vec![0]),
            ..Default::default()
        }
        .apply(pid);
        assert!(matches!(&ok[..], [Outcome::Applied(_)]), "{ok:?}");
        let affinity = nix::sched::sched_getaffinity(Pid::from_raw(pid as i32)).unwrap();
        assert!(affinity.is_set(0).unwrap());
        let missing = Realtime {
            cpus: Some(vec![CpuSet::count() - 1]),
            ..Default::default()
        }
        .apply(pid);
        assert!(matches!(&missing[..], [Outcome::Denied(_)]), "{missing:?}");
        let _ = child.kill();
        let _ = child.wait();
    }
}
