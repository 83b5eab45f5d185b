//! The latency predictor with its disturbance bandwidth chosen from the data: one
//! [`StatePredictor`] per candidate time constant (in delays), each scored on how well it
//! predicted the position the later poses then showed, the best one feeding the controller.
//!
//! How fast the disturbance estimate should follow depends on the flow: noise that stays
//! correlated for a few delays can be worth extrapolating from a quick estimate, a push that
//! reverses within the delay is not (the unit test below has one of each). Which a rig has is
//! measured here, not assumed: every candidate predicts the position at the actuation time, and
//! when a pose captured at that time arrives, its miss is recorded. The best predictor is not
//! always the best loop: at the coil limit a quick estimate learns within a delay the force the
//! loop's own commands failed to make, and on the twin's 10 cm/s jet at 100 ms that lost runs the
//! slow one held. So after any command the coils fell short of, the slowest candidate feeds the
//! controller for one scoring window: the misses scored meanwhile tell the limit, not the flow
//! (README, "Choosing the disturbance bandwidth from the data"). With no candidates the bank is
//! the single predictor of `disturbance_delays`, bit for bit.

use std::collections::VecDeque;

use nalgebra::Vector2;

use super::{LatencyConfig, Predicted, Predictor, StatePredictor, MOTION_SHARE_WINDOW_S};
use crate::controllers::NominalModel;

/// Averaging time of each candidate's prediction miss: the predictor's own averaging time for
/// what its model misses (several pulsation periods), so a choice reflects the flow, not one
/// stroke.
const SCORE_WINDOW_S: f64 = MOTION_SHARE_WINDOW_S;

/// A candidate takes over only when its mean-square miss is below this share of the active
/// one's: near-equal candidates do not trade places every pose (each change moves the state
/// the controller sees by the difference of their predictions).
const SWITCH_MARGIN: f64 = 0.8;

/// A command whose achieved force misses the asked one by more than this share of it fell short
/// (the coils at their limit): the slowest candidate is held for [`SCORE_WINDOW_S`] after it.
/// Measured: 0.02 and 0.1 hold the same runs, 0.3 loses one of ten (README).
pub const SHORTFALL_FRACTION: f64 = 0.1;

/// One candidate and its record.
struct Candidate {
    predictor: StatePredictor,
    /// Predictions not yet checked: (actuation time, predicted position, predicted velocity).
    pending: VecDeque<(u64, Vector2<f64>, Vector2<f64>)>,
    /// Mean-square miss of its checked predictions (m²; None before the first).
    miss_sq_m2: Option<f64>,
}

impl Candidate {
    /// Checks the predictions whose actuation time the pose at `capture_ns` has reached.
    fn score(&mut self, position_m: Vector2<f64>, capture_ns: u64, pose_interval_s: f64) {
        let mut due = None;
        while self.pending.front().is_some_and(|p| p.0 <= capture_ns) {
            due = self.pending.pop_front();
        }
        let Some((actuation_ns, predicted_m, velocity_mps)) = due else {
            return;
        };
        // The prediction carried at its own velocity to the pose's capture time (within a pose
        // interval of it; a gap longer than that is a hold, not a prediction to judge).
        let gap_s = (capture_ns - actuation_ns) as f64 * 1e-9;
        if gap_s > pose_interval_s.max(1e-3) * 1.5 {
            return;
        }
        let miss_sq = (position_m - (predicted_m + velocity_mps * gap_s)).norm_squared();
        if !miss_sq.is_finite() {
            return;
        }
        let alpha = 1.0 - (-pose_interval_s / SCORE_WINDOW_S).exp();
        self.miss_sq_m2 = Some(match self.miss_sq_m2 {
            Some(mean) => mean + alpha * (miss_sq - mean),
            None => miss_sq,
        });
    }
}

/// The predictors of every candidate disturbance bandwidth and which one is in use.
pub struct PredictorBank {
    config: LatencyConfig,
    candidates: Vec<Candidate>,
    active: usize,
    /// The slowest candidate: the one that starts and the one a shortfall holds.
    slowest: usize,
    last_capture_ns: Option<u64>,
    /// Until when the slowest candidate is held (actuation time of the last shortfall plus one
    /// scoring window).
    hold_slowest_until_ns: u64,
}

impl PredictorBank {
    /// One predictor per `config.disturbance_delays_candidates` (none: the one of
    /// `disturbance_delays`). The slowest candidate starts: it is the safe one against stale
    /// information until the misses say otherwise.
    pub fn new(config: LatencyConfig, model: NominalModel) -> Self {
        let delays: Vec<f64> = if config.disturbance_delays_candidates.is_empty() {
            vec![config.disturbance_delays]
        } else {
            config.disturbance_delays_candidates.clone()
        };
        let slowest = delays
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .map_or(0, |(i, _)| i);
        let candidates = delays
            .into_iter()
            .map(|disturbance_delays| Candidate {
                predictor: StatePredictor::new(
                    LatencyConfig {
                        disturbance_delays,
                        ..config.clone()
                    },
                    model,
                ),
                pending: VecDeque::new(),
                miss_sq_m2: None,
            })
            .collect();
        Self {
            config,
            candidates,
            active: slowest,
            slowest,
            last_capture_ns: None,
            hold_slowest_until_ns: 0,
        }
    }

    /// The candidate in use.
    fn active(&self) -> &StatePredictor {
        &self.candidates[self.active].predictor
    }

    /// Switches to the candidate with the least miss when it beats the active one by the
    /// margin, unless a shortfall holds the slowest.
    fn choose(&mut self) {
        if self
            .last_capture_ns
            .is_some_and(|t| t < self.hold_slowest_until_ns)
        {
            self.active = self.slowest;
            return;
        }
        let Some(active_miss) = self.candidates[self.active].miss_sq_m2 else {
            return;
        };
        let best = self
            .candidates
            .iter()
            .enumerate()
            .filter_map(|(i, c)| c.miss_sq_m2.map(|m| (i, m)))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        if let Some((i, miss)) = best {
            if miss < SWITCH_MARGIN * active_miss {
                self.active = i;
            }
        }
    }
}

impl Predictor for PredictorBank {
    fn config(&self) -> &LatencyConfig {
        &self.config
    }

    /// The disturbance time constant in use, in delays.
    fn active_disturbance_delays(&self) -> f64 {
        self.active().config().disturbance_delays
    }

    /// See [`StatePredictor::reset`]; the candidates' records stay.
    fn reset(&mut self) {
        for candidate in &mut self.candidates {
            candidate.predictor.reset();
        }
    }

    /// See [`StatePredictor::commanded`].
    fn commanded(&mut self, start_ns: u64, force_n: Vector2<f64>, flow_mps: Vector2<f64>) {
        for candidate in &mut self.candidates {
            candidate.predictor.commanded(start_ns, force_n, flow_mps);
        }
    }

    /// Scores every candidate against this pose, then predicts with each; returns the active
    /// one's prediction.
    fn predict(
        &mut self,
        position_m: Vector2<f64>,
        capture_ns: u64,
        actuation_ns: u64,
        flow_mps: Vector2<f64>,
    ) -> Predicted {
        if self.candidates.len() == 1 {
            return self.candidates[0].predictor.predict(
                position_m,
                capture_ns,
                actuation_ns,
                flow_mps,
            );
        }
        let interval_s = self
            .last_capture_ns
            .filter(|&t| capture_ns > t)
            .map_or(0.0, |t| (capture_ns - t) as f64 * 1e-9);
        self.last_capture_ns = Some(capture_ns);
        for candidate in &mut self.candidates {
            candidate.score(position_m, capture_ns, interval_s);
        }
        self.choose();
        let mut chosen = Vec::with_capacity(self.candidates.len());
        for candidate in &mut self.candidates {
            let predicted =
                candidate
                    .predictor
                    .predict(position_m, capture_ns, actuation_ns, flow_mps);
            while candidate
                .pending
                .back()
                .is_some_and(|p| p.0 >= actuation_ns)
            {
                candidate.pending.pop_back();
            }
            candidate.pending.push_back((
                actuation_ns,
                position_m + predicted.motion_ahead_m,
                predicted.velocity_mps,
            ));
            chosen.push(predicted);
        }
        chosen.swap_remove(self.active)
    }

    /// The command acting at `actuation_ns` asked `asked_n` and the coils made `achieved_n`:
    /// short by more than [`SHORTFALL_FRACTION`] of it, the slowest candidate is held for one
    /// scoring window.
    fn achieved(&mut self, actuation_ns: u64, asked_n: Vector2<f64>, achieved_n: Vector2<f64>) {
        if (asked_n - achieved_n).norm() > SHORTFALL_FRACTION * asked_n.norm() {
            let hold_ns = actuation_ns.saturating_add((SCORE_WINDOW_S * 1e9) as u64);
            self.hold_slowest_until_ns = self.hold_slowest_until_ns.max(hold_ns);
        }
    }

    /// See [`StatePredictor::lead_disturbance`] (the active candidate's).
    fn lead_disturbance(&self, from_ns: u64, span_s: f64) -> Option<Vector2<f64>> {
        self.active().lead_disturbance(from_ns, span_s)
    }

    /// See [`StatePredictor::unpredicted_motion_share`] (the active candidate's).
    fn unpredicted_motion_share(&self) -> f64 {
        self.active().unpredicted_motion_share()
    }

    /// See [`StatePredictor::expected_miss_m`] (the active candidate's).
    fn expected_miss_m(&self, horizon_s: f64) -> f64 {
        self.active().expected_miss_m(horizon_s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::latency::tests::{ns, simulate_with, MODEL};

    const CANDIDATES: [f64; 3] = [1.0, 2.0, 4.0];
    const FRAME_S: f64 = 0.01;
    const DELAY_S: f64 = 0.1;

    /// Poses every frame, `DELAY_S` old at actuation, of a body no force but `push` moves:
    /// the bank's final choice, and each candidate's RMS prediction miss when run alone (m).
    fn run(push: impl Fn(f64) -> Vector2<f64>, until_s: f64) -> (f64, Vec<f64>) {
        run_short_of(push, until_s, |_| false)
    }

    /// As [`run`], the coils falling short of the command acting at t where `short(t)`.
    fn run_short_of(
        push: impl Fn(f64) -> Vector2<f64>,
        until_s: f64,
        short: impl Fn(f64) -> bool,
    ) -> (f64, Vec<f64>) {
        let truth = simulate_with(&[], push, until_s + DELAY_S);
        let at = |t: f64| truth[(t / 1e-5).round() as usize].1;
        let config = |candidates: Vec<f64>, delays: f64| LatencyConfig {
            disturbance_delays: delays,
            disturbance_delays_candidates: candidates,
            ..LatencyConfig::default()
        };
        let mut bank = PredictorBank::new(config(CANDIDATES.to_vec(), 4.0), MODEL);
        let mut alone: Vec<PredictorBank> = CANDIDATES
            .iter()
            .map(|&d| PredictorBank::new(config(Vec::new(), d), MODEL))
            .collect();
        let mut miss_sq = vec![0.0; CANDIDATES.len()];
        let mut scored = 0;
        let frames = (until_s / FRAME_S).round() as usize;
        for k in (DELAY_S / FRAME_S).round() as usize..frames {
            let now = k as f64 * FRAME_S;
            let captured = now - DELAY_S;
            for predictor in std::iter::once(&mut bank).chain(alone.iter_mut()) {
                predictor.commanded(ns(now), Vector2::zeros(), Vector2::zeros());
            }
            let asked = Vector2::new(1e-5, 0.0);
            let made = if short(now) { asked * 0.5 } else { asked };
            bank.achieved(ns(now), asked, made);
            bank.predict(at(captured), ns(captured), ns(now), Vector2::zeros());
            for (i, predictor) in alone.iter_mut().enumerate() {
                let predicted =
                    predictor.predict(at(captured), ns(captured), ns(now), Vector2::zeros());
                if now > until_s / 2.0 {
                    miss_sq[i] +=
                        (at(captured) + predicted.motion_ahead_m - at(now)).norm_squared();
                }
            }
            if now > until_s / 2.0 {
                scored += 1;
            }
        }
        let rms = miss_sq.iter().map(|m| (m / scored as f64).sqrt()).collect();
        (bank.active_disturbance_delays(), rms)
    }

    /// The candidate with the least miss, and whether it beats the others by the margin.
    fn best(rms: &[f64]) -> f64 {
        let i = (0..rms.len())
            .min_by(|&a, &b| rms[a].total_cmp(&rms[b]))
            .unwrap();
        CANDIDATES[i]
    }

    /// A push that drifts slowly (0.3 Hz) is worth following quickly and carrying across the
    /// delay; one that reverses within the delay (4 Hz) is not. The bank picks, in each, the
    /// candidate that predicts best when run alone, and the two flows get different choices.
    #[test]
    fn chooses_the_bandwidth_that_predicts_best() {
        let wave = |hz: f64| {
            move |t: f64| {
                let s = (std::f64::consts::TAU * hz * t).sin();
                Vector2::new(2e-5 * s, -1e-5 * s)
            }
        };
        let (slow_choice, slow_rms) = run(wave(0.3), 12.0);
        let (fast_choice, fast_rms) = run(wave(4.0), 12.0);
        println!("0.3 Hz: chose {slow_choice}, alone {slow_rms:?}; 4 Hz: chose {fast_choice}, alone {fast_rms:?}");
        assert_eq!(slow_choice, best(&slow_rms), "{slow_rms:?}");
        assert_eq!(fast_choice, best(&fast_rms), "{fast_rms:?}");
        assert_ne!(slow_choice, fast_choice);
    }

    /// The slow drift has the bank choose the quick estimate; with the coils falling short of
    /// a command every 1.5 s it holds the slowest instead, and it goes back to the quick
    /// one within a few scoring windows of the last shortfall. A shortfall of less than
    /// `SHORTFALL_FRACTION` holds nothing.
    #[test]
    fn a_command_the_coils_fell_short_of_holds_the_slowest_candidate() {
        let drift = |t: f64| Vector2::new(2e-5 * (std::f64::consts::TAU * 0.3 * t).sin(), 0.0);
        let (free, _) = run(drift, 12.0);
        assert_eq!(free, 1.0);
        let every_1_5_s = |t: f64| (t % 1.5) < 0.05;
        let (held, _) = run_short_of(drift, 12.0, every_1_5_s);
        assert_eq!(held, 4.0);
        let (after, _) = run_short_of(drift, 24.0, |t: f64| t < 12.0 && every_1_5_s(t));
        assert_eq!(after, 1.0);

        let mut bank = PredictorBank::new(
            LatencyConfig {
                disturbance_delays_candidates: CANDIDATES.to_vec(),
                ..LatencyConfig::default()
            },
            MODEL,
        );
        let asked = Vector2::new(1e-5, 0.0);
        bank.achieved(ns(1.0), asked, asked * (1.0 - 0.5 * SHORTFALL_FRACTION));
        assert_eq!(bank.hold_slowest_until_ns, 0);
        bank.achieved(ns(1.0), asked, asked * (1.0 - 2.0 * SHORTFALL_FRACTION));
        assert_eq!(bank.hold_slowest_until_ns, ns(1.0 + SCORE_WINDOW_S));
    }

    /// Without candidates the bank is the single predictor of `disturbance_delays`.
    #[test]
    fn without_candidates_it_is_the_configured_predictor() {
        let config = LatencyConfig {
            disturbance_delays: 3.0,
            disturbance_delays_candidates: Vec::new(),
            ..LatencyConfig::default()
        };
        let mut bank = PredictorBank::new(config.clone(), MODEL);
        let mut single = StatePredictor::new(config, MODEL);
        assert_eq!(bank.active_disturbance_delays(), 3.0);
        for k in 0..50 {
            let t = k as f64 * FRAME_S;
            let p = Vector2::new(1e-4 * t * t, -2e-4 * t);
            bank.commanded(ns(t), Vector2::new(1e-6, 0.0), Vector2::zeros());
            single.commanded(ns(t), Vector2::new(1e-6, 0.0), Vector2::zeros());
            let a = bank.predict(p, ns(t), ns(t + DELAY_S), Vector2::zeros());
            let b = single.predict(p, ns(t), ns(t + DELAY_S), Vector2::zeros());
            assert_eq!(a, b);
        }
    }

    #[test]
    fn bad_candidates_are_named() {
        let config = LatencyConfig {
            disturbance_delays_candidates: vec![1.0, f64::NAN],
            ..LatencyConfig::default()
        };
        assert_eq!(
            config.invalid_field().map(|(name, _)| name),
            Some("disturbance_delays_candidates")
        );
    }
}
