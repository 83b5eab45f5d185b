//! Each controller drives the plant library (the twin's physics) in-process along a straight and
//! a curved path in static 20 cP fluid. Nothing is rendered: the loop gets poses built from the
//! true state plus small noise (σ = 0.05 mm, 1°), one frame of 10 ms per step, and its command
//! is applied to the plant for the next frame. Error = |true position − reference| per frame
//! while the reference moves and for 2 s after it stops.

use std::path::Path;

use millinav_control::build_loop;
use millinav_kit::scenario::Scenario;
use millinav_plant::{build_model, initial_state, PlantConfig};
use nalgebra::Vector2;
use shm_schemas::{Flag, FrameStamp, Pose};

/// Deterministic Gaussian noise (LCG + Box–Muller), no extra dependency.
struct Noise(u64);
impl Noise {
    fn uniform(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn gauss(&mut self) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

#[derive(Debug, Clone, Copy)]
pub struct Stats {
    pub rmse_mm: f64,
    /// RMS of the frame-to-frame change of F_des (mN): chattering.
    pub force_jitter_mn: f64,
    pub p95_mm: f64,
    pub max_mm: f64,
    /// RMS error over the last 0.5 s of the run (the robot held at the end).
    pub final_mm: f64,
    pub rejected: usize,
}

fn scenario(controller: &str, waypoints_mm: &[[f64; 2]], speed_mm_s: f64) -> Scenario {
    let points: Vec<String> = waypoints_mm
        .iter()
        .map(|p| format!("[{}, {}]", p[0], p[1]))
        .collect();
    let text = format!(
        "[run]\nmode = \"lockstep\"\nseed = 1\nduration_s = 100.0\nframe_period_ms = 10.0\nrig = \"fieldmaps/rigs/paper.toml\"\n\
         [fluid]\nviscosity_cp = 20.0\n\
         [trajectory]\nwaypoints_mm = [{}]\nspeed_mm_s = {speed_mm_s}\nstart_time_s = 1.0\n\
         [control]\ncontroller = \"{controller}\"\n",
        points.join(", ")
    );
    Scenario::parse(&text, Path::new("in-process.toml")).expect("test scenario parses")
}

pub fn run(controller: &str, waypoints_mm: &[[f64; 2]], speed_mm_s: f64) -> Stats {
    let scenario = scenario(controller, waypoints_mm, speed_mm_s);
    let plant_config = PlantConfig::default();
    let model = build_model(&scenario, &plant_config).expect("plant model");
    let mut state = initial_state(&scenario, &plant_config, &model);
    let mut control = build_loop(&scenario, 1).expect("control loop");
    assert_eq!(control.controller_name(), controller);
    let dt = scenario.frame_period_s();
    let end = control.reference.end_time_s() + 2.0;
    let mut noise = Noise(42);
    let mut errors = Vec::new();
    let mut rejected = 0;
    let mut prev_force: Option<Vector2<f64>> = None;
    let mut jitter = Vec::new();
    let steps = (end / dt).ceil() as u64;
    for seq in 0..steps {
        let t = seq as f64 * dt;
        let position = [
            state.position_m.x + 5e-5 * noise.gauss(),
            state.position_m.y + 5e-5 * noise.gauss(),
        ];
        let pose = Pose {
            stamp: FrameStamp::new(seq, 1, (t * 1e9).round() as u64),
            position_m: position,
            heading_rad: state.heading_rad + 1f64.to_radians() * noise.gauss(),
            centroid_m: position,
            confidence: 1.0,
            valid: Flag::TRUE,
            ..Default::default()
        };
        let decision = control.step(&pose, None);
        let force = Vector2::new(
            decision.command.force_des_n[0],
            decision.command.force_des_n[1],
        );
        if let Some(p) = prev_force {
            jitter.push((force - p).norm_squared());
        }
        prev_force = Some(force);
        if decision.rejected.is_some() {
            rejected += 1;
        }
        if t >= 1.0 {
            let reference = control.reference.sample(t).position_m;
            errors.push((state.position_m - reference).norm() * 1e3);
        }
        let currents = decision.command.currents().expect("a well-formed command");
        assert_eq!(currents.len(), model.coil_count(), "one current per coil");
        model.step(&mut state, currents, dt);
    }
    let n = errors.len() as f64;
    let rmse_mm = (errors.iter().map(|e| e * e).sum::<f64>() / n).sqrt();
    let mut sorted = errors.clone();
    sorted.sort_by(f64::total_cmp);
    let p95_mm = sorted[((0.95 * n) as usize).min(sorted.len() - 1)];
    let force_jitter_mn = (jitter.iter().sum::<f64>() / jitter.len().max(1) as f64).sqrt() * 1e3;
    // RMS over the last 0.5 s, not one frame: a chattering controller's single last sample is
    // a draw from its limit cycle.
    let settle = errors.len().min((0.5 / dt).round() as usize).max(1);
    let tail = &errors[errors.len() - settle..];
    let final_mm = (tail.iter().map(|e| e * e).sum::<f64>() / tail.len() as f64).sqrt();
    Stats {
        rmse_mm,
        force_jitter_mn,
        p95_mm,
        max_mm: sorted[sorted.len() - 1],
        final_mm,
        rejected,
    }
}

/// Straight segment across the right atrium (15.6 mm).
const STRAIGHT_MM: [[f64; 2]; 2] = [[-22.0, 14.0], [-10.0, 4.0]];

/// Half circle of radius 8 mm around the atrium's centre (25.1 mm of path), 19 points.
fn curved_mm() -> Vec<[f64; 2]> {
    (0..19)
        .map(|i| {
            let th = (150.0 - 10.0 * i as f64).to_radians();
            [-16.0 + 8.0 * th.cos(), 10.0 + 8.0 * th.sin()]
        })
        .collect()
}

/// Paper speed (RIG.md): 0.5 mm/s.
///
/// Bounds (RMSE, max, mm) are set from measured runs with margin (see the report of issue 7):
/// pid 0.4 / 1.0, smc-dob 0.8 / 1.6, smc 2.5 / 4.0, mpc 0.15 / 0.3.
const SPEED_MM_S: f64 = 0.5;

fn check(controller: &str, rmse_bound_mm: f64, max_bound_mm: f64) {
    for (path, waypoints) in [("straight", STRAIGHT_MM.to_vec()), ("curved", curved_mm())] {
        let s = run(controller, &waypoints, SPEED_MM_S);
        eprintln!(
            "{controller:8} {path:8}: RMSE {:.3} mm, P95 {:.3} mm, max {:.3} mm, final {:.3} mm, \
             |ΔF| rms {:.4} mN/frame, rejected {}",
            s.rmse_mm, s.p95_mm, s.max_mm, s.final_mm, s.force_jitter_mn, s.rejected
        );
        assert_eq!(s.rejected, 0, "{controller} {path}: poses rejected");
        assert!(s.rmse_mm < rmse_bound_mm, "{controller} {path}: {s:?}");
        assert!(s.max_mm < max_bound_mm, "{controller} {path}: {s:?}");
        // Settled: 2 s after the reference stops, the robot sits at the end within the
        // controller's RMSE bound (a final error under the max bound is implied by the line
        // above and checks nothing).
        assert!(s.final_mm < rmse_bound_mm, "{controller} {path}: {s:?}");
    }
}

#[test]
fn pid_tracks() {
    check("pid", 0.4, 1.0);
}

#[test]
fn smc_dob_tracks() {
    check("smc-dob", 0.8, 1.6);
}

#[test]
fn smc_tracks() {
    check("smc", 2.5, 4.0);
}

#[test]
fn mpc_tracks() {
    check("mpc", 0.15, 0.3);
}
