//! The run summary: what a run did, printed when it ends and written as `summary.json` in its
//! run directory. Tracking figures come from `control.csv` (what control saw: the measured pose
//! against the reference, on the rig as in the twin) and, in the twin, from `truth.csv` too (the
//! true position against the reference of the same frame). The completion rule is the one the
//! experiment tables use ([`tracking`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::runlog::{self, ContactRow, ControlRow, RunLogError, TruthRow};

/// "Failed to complete": the error stays above `FAIL_ERROR_M` for longer than `FAIL_TIME_S`
/// (the robot was lost or stuck), or the robot never arrives: it is not within `FAIL_ERROR_M`
/// of the final waypoint at any time after the reference reached it (a run cut short before
/// that must end within `FAIL_ERROR_M` of the reference). Arrival, not the last sample, because
/// at the outlet of the 10 cm/s maps the pulsatile jet pushes the capsule out and back every
/// second or so, and the last sample would make completion a coin toss.
pub const FAIL_ERROR_M: f64 = 5.0e-3;
pub const FAIL_TIME_S: f64 = 2.0;

/// Tracking figures of one error trace.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Tracking {
    pub samples: usize,
    pub rmse_mm: f64,
    pub p95_mm: f64,
    pub max_mm: f64,
    pub completed: bool,
}

/// One sample of a tracking error: time (s), error (m), whether the reference had finished.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorSample {
    pub time_s: f64,
    pub error_m: f64,
    pub reference_finished: bool,
}

/// RMSE, P95, max and completion (rule: [`FAIL_ERROR_M`]) of samples in time order.
pub fn tracking(samples: &[ErrorSample]) -> Tracking {
    let mut above_since: Option<f64> = None;
    let mut failed = false;
    let mut reference_finished = false;
    let mut arrived = false;
    for s in samples {
        reference_finished |= s.reference_finished;
        arrived |= s.reference_finished && s.error_m <= FAIL_ERROR_M;
        if s.error_m > FAIL_ERROR_M {
            let since = *above_since.get_or_insert(s.time_s);
            failed |= s.time_s - since > FAIL_TIME_S;
        } else {
            above_since = None;
        }
    }
    let final_error = samples.last().map_or(f64::INFINITY, |s| s.error_m);
    let n = samples.len();
    let rmse =
        (samples.iter().map(|s| s.error_m * s.error_m).sum::<f64>() / n.max(1) as f64).sqrt();
    let mut sorted: Vec<f64> = samples.iter().map(|s| s.error_m).collect();
    sorted.sort_by(|a, b| a.total_cmp(b));
    let p95 = sorted
        .get(((n as f64 - 1.0) * 0.95).round() as usize)
        .copied()
        .unwrap_or(f64::NAN);
    Tracking {
        samples: n,
        rmse_mm: rmse * 1e3,
        p95_mm: p95 * 1e3,
        max_mm: sorted.last().copied().unwrap_or(f64::NAN) * 1e3,
        completed: n > 0
            && !failed
            && if reference_finished {
                arrived
            } else {
                final_error <= FAIL_ERROR_M
            },
    }
}

/// What only the supervisor knows about a run.
#[derive(Debug, Clone, Default)]
pub struct RunFacts {
    /// How the run ended, in words.
    pub ending: String,
    pub duration_s: f64,
    /// Per service: deadline misses summed over its incarnations.
    pub deadline_misses: BTreeMap<String, u64>,
    /// Per service: restarts.
    pub restarts: BTreeMap<String, u64>,
    /// Coil resistance for the energy (None: energy not computed).
    pub coil_resistance_ohm: Option<f64>,
    /// The merged recording, when one was written.
    pub recording: Option<PathBuf>,
}

/// The summary of a run (`summary.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunSummary {
    pub run_dir: PathBuf,
    pub ending: String,
    pub duration_s: f64,
    /// Frames control answered (distinct frames).
    pub frames: usize,
    /// Control decisions (a frame shown twice is answered twice).
    pub decisions: usize,
    /// Frames whose pose control used.
    pub poses_used: usize,
    /// Measured pose against the reference, as control saw it (frames with a used pose).
    pub as_control_saw: Option<Tracking>,
    /// True position against the reference of the same frame (twin only).
    pub truth: Option<Tracking>,
    /// Frames in wall contact and contact onsets (twin only).
    pub wall_contact_frames: Option<usize>,
    pub wall_contacts: Option<u64>,
    pub deadline_misses: BTreeMap<String, u64>,
    pub restarts: BTreeMap<String, u64>,
    /// Largest commanded coil current, A.
    pub peak_current_a: f64,
    /// Joule heat of the commanded currents, Σ I² R dt, J.
    pub energy_j: Option<f64>,
    pub recording: Option<PathBuf>,
    /// The command that opens the recording.
    pub open_recording: Option<String>,
}

/// File name of the summary in a run directory.
pub const SUMMARY_JSON: &str = "summary.json";

/// Reads a run log when it exists (None when it does not).
fn rows_if_present<R: runlog::RunLogRow>(run_dir: &Path) -> Result<Option<Vec<R>>, RunLogError> {
    let path = run_dir.join(R::FILE_NAME);
    if !path.exists() {
        return Ok(None);
    }
    runlog::read_rows(&path).map(Some)
}

impl RunSummary {
    /// The summary of the run in `run_dir` from its logs and what the supervisor knows.
    pub fn compute(run_dir: &Path, facts: &RunFacts) -> Result<Self, RunLogError> {
        let control: Vec<ControlRow> = rows_if_present(run_dir)?.unwrap_or_default();
        let truth: Option<Vec<TruthRow>> = rows_if_present(run_dir)?;
        let contacts: Option<Vec<ContactRow>> = rows_if_present(run_dir)?;
        let reference_at = |row: &ControlRow| (row.reference_x_m, row.reference_y_m);
        // The last decision for each frame (a frame shown twice, or a restarted control, may
        // be answered more than once), in frame order. A frame is (incarnation, seq): a
        // restarted plant counts its frames from 0 again.
        let by_frame: BTreeMap<(u64, u64), &ControlRow> = control
            .iter()
            .map(|r| ((r.frame_incarnation, r.frame_seq), r))
            .collect();
        let seen: Vec<ErrorSample> = by_frame
            .values()
            .filter(|r| r.pose_used && r.measured_x_m.is_finite() && r.measured_y_m.is_finite())
            .map(|r| {
                let (rx, ry) = reference_at(r);
                ErrorSample {
                    time_s: r.time_s,
                    error_m: (r.measured_x_m - rx).hypot(r.measured_y_m - ry),
                    reference_finished: r.finished,
                }
            })
            .collect();
        let true_errors = truth.as_ref().map(|rows| {
            let mut last_frame = None;
            rows.iter()
                .filter(|t| {
                    let frame = Some((t.frame_incarnation, t.frame_seq));
                    let fresh = last_frame != frame;
                    last_frame = frame;
                    fresh
                })
                .filter_map(|t| {
                    let c = by_frame.get(&(t.frame_incarnation, t.frame_seq))?;
                    let (rx, ry) = reference_at(c);
                    Some(ErrorSample {
                        time_s: c.time_s,
                        error_m: (t.x_m - rx).hypot(t.y_m - ry),
                        reference_finished: c.finished,
                    })
                })
                .collect::<Vec<_>>()
        });
        let mut energy = 0.0;
        for pair in control.windows(2) {
            let dt = pair[1].time_s - pair[0].time_s;
            if dt.is_finite() && dt > 0.0 {
                energy += pair[1].sum_sq_current_a2 * dt;
            }
        }
        let recording = facts.recording.clone();
        Ok(Self {
            run_dir: run_dir.to_owned(),
            ending: facts.ending.clone(),
            duration_s: facts.duration_s,
            frames: by_frame.len(),
            decisions: control.len(),
            poses_used: seen.len(),
            as_control_saw: (!seen.is_empty()).then(|| tracking(&seen)),
            truth: true_errors.filter(|e| !e.is_empty()).map(|e| tracking(&e)),
            wall_contact_frames: truth
                .as_ref()
                .map(|rows| rows.iter().filter(|t| t.wall_contact).count()),
            wall_contacts: contacts.map(|rows| {
                rows.iter()
                    .filter(|c| c.event == "start")
                    .map(|c| c.contact_events)
                    .max()
                    .unwrap_or(0)
            }),
            deadline_misses: facts.deadline_misses.clone(),
            restarts: facts.restarts.clone(),
            peak_current_a: control.iter().fold(0.0, |m, r| m.max(r.max_abs_current_a)),
            energy_j: facts.coil_resistance_ohm.map(|r| energy * r),
            open_recording: recording.as_ref().map(|p| format!("rerun {}", p.display())),
            recording,
        })
    }

    /// Writes `summary.json` into the run directory.
    pub fn write_json(&self) -> std::io::Result<PathBuf> {
        let path = self.run_dir.join(SUMMARY_JSON);
        let text = serde_json::to_string_pretty(self).map_err(std::io::Error::other)?;
        std::fs::write(&path, text + "\n")?;
        Ok(path)
    }

    /// The summary as a reader wants it at the end of a run.
    pub fn text(&self) -> String {
        let mut out = format!(
            "Run summary ({})\n  ended:            {}\n  duration:         {:.1} s, {} frames answered, {} poses used\n",
            self.run_dir.display(),
            self.ending,
            self.duration_s,
            self.frames,
            self.poses_used
        );
        let line = |what: &str, t: &Option<Tracking>| match t {
            Some(t) => format!(
                "  {what:<17} RMSE {:.3} mm, P95 {:.3} mm, max {:.3} mm, {}\n",
                t.rmse_mm,
                t.p95_mm,
                t.max_mm,
                if t.completed {
                    "completed"
                } else {
                    "NOT completed"
                }
            ),
            None => format!("  {what:<17} no samples\n"),
        };
        out += &line("as control saw:", &self.as_control_saw);
        if self.truth.is_some() {
            out += &line("truth (twin):", &self.truth);
        }
        if let (Some(frames), Some(onsets)) = (self.wall_contact_frames, self.wall_contacts) {
            out += &format!("  wall contacts:    {onsets} ({frames} frames)\n");
        }
        let per_service = |map: &BTreeMap<String, u64>| {
            if map.values().all(|&v| v == 0) {
                "none".to_string()
            } else {
                map.iter()
                    .filter(|(_, &v)| v > 0)
                    .map(|(k, v)| format!("{k} {v}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            }
        };
        out += &format!(
            "  deadline misses:  {}\n  restarts:         {}\n",
            per_service(&self.deadline_misses),
            per_service(&self.restarts)
        );
        out += &format!(
            "  peak current:     {:.2} A (commanded)",
            self.peak_current_a
        );
        if let Some(e) = self.energy_j {
            out += &format!(", coil heat {e:.1} J");
        }
        out += "\n";
        if let Some(open) = &self.open_recording {
            out += &format!("  recording:        {open}\n");
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(time_s: f64, error_mm: f64, finished: bool) -> ErrorSample {
        ErrorSample {
            time_s,
            error_m: error_mm * 1e-3,
            reference_finished: finished,
        }
    }

    #[test]
    fn tracking_figures_and_the_completion_rule() {
        let arrived = [
            sample(0.0, 1.0, false),
            sample(1.0, 2.0, false),
            sample(2.0, 0.5, true),
        ];
        let t = tracking(&arrived);
        assert!((t.rmse_mm - (5.25f64 / 3.0).sqrt()).abs() < 1e-9, "{t:?}");
        assert!((t.max_mm - 2.0).abs() < 1e-12 && t.completed, "{t:?}");
        // Lost for more than FAIL_TIME_S: not completed even if it comes back.
        let lost = [
            sample(0.0, 6.0, false),
            sample(2.5, 6.0, false),
            sample(3.0, 0.1, true),
        ];
        assert!(!tracking(&lost).completed);
        // Never arrived at the last waypoint after the reference got there.
        let short = [sample(0.0, 1.0, false), sample(1.0, 5.5, true)];
        assert!(!tracking(&short).completed);
        assert!(!tracking(&[]).completed);
    }

    /// A plant restarted mid-run counts its frames from 0 again: the summary must pair each
    /// truth row with the decision for the same (incarnation, seq), never with the other
    /// incarnation's frame of the same seq.
    #[test]
    fn a_restart_that_repeats_frame_seqs_does_not_mix_the_incarnations() {
        use crate::runlog::{RunLogRow, RunLogWriter, TruthRow};
        let dir = crate::scratch::ScratchDir::new("summary-restart").expect("scratch");
        let mut truth = RunLogWriter::<TruthRow>::in_run_dir(dir.path()).expect("truth");
        let mut control = RunLogWriter::<ControlRow>::in_run_dir(dir.path()).expect("control");
        // Incarnation 0 tracks a reference at x = 0 with 1 mm error, incarnation 1 one at
        // x = 10 mm with 3 mm error; both count seq 0..10.
        for (incarnation, reference_m, error_m) in [(0u64, 0.0, 1e-3), (1, 10e-3, 3e-3)] {
            for seq in 0..10u64 {
                let time_s = incarnation as f64 * 10.0 + seq as f64 * 0.01;
                truth
                    .append(&TruthRow {
                        frame_seq: seq,
                        frame_incarnation: incarnation,
                        sim_time_s: time_s,
                        x_m: reference_m + error_m,
                        y_m: 0.0,
                        vx_mps: 0.0,
                        vy_mps: 0.0,
                        heading_rad: 0.0,
                        flow_x_mps: 0.0,
                        flow_y_mps: 0.0,
                        wall_contact: false,
                        max_abs_current_a: 0.0,
                        lockstep_misses: 0,
                        sum_sq_current_a2: None,
                        coil_currents_a: None,
                    })
                    .expect("truth row");
                control
                    .append(&ControlRow {
                        frame_seq: seq,
                        frame_incarnation: incarnation,
                        time_s,
                        pose_used: true,
                        measured_x_m: reference_m + error_m,
                        measured_y_m: 0.0,
                        reference_x_m: reference_m,
                        reference_y_m: 0.0,
                        finished: false,
                        mode: 0,
                        max_abs_current_a: 0.0,
                        sum_sq_current_a2: 0.0,
                    })
                    .expect("control row");
            }
        }
        truth.flush().expect("flush");
        control.flush().expect("flush");
        assert!(dir.path().join(TruthRow::FILE_NAME).is_file());
        let facts = RunFacts {
            ending: "run complete".into(),
            duration_s: 20.0,
            deadline_misses: BTreeMap::new(),
            restarts: BTreeMap::new(),
            coil_resistance_ohm: None,
            recording: None,
        };
        let summary = RunSummary::compute(dir.path(), &facts).expect("summary");
        assert_eq!(summary.frames, 20, "both incarnations' frames count");
        let expected_mm = ((10.0 * 1.0 + 10.0 * 9.0) / 20.0f64).sqrt();
        for (name, tracked) in [("truth", &summary.truth), ("seen", &summary.as_control_saw)] {
            let rmse = tracked.as_ref().expect("tracking").rmse_mm;
            assert!((rmse - expected_mm).abs() < 1e-6, "{name}: {rmse} mm");
        }
    }
}
