//! The tracking error no controller can beat in the twin's flow noise, given how old the poses
//! are when the coils act (`experiments --noise-floor`).
//!
//! Per axis the capsule obeys m v̇ = −c v + k u + F (linearised: the twin's drag on its own
//! motion c, its coupling to the flow k), the noise velocity u is an Ornstein–Uhlenbeck process
//! (the twin's modes: per-axis variance σ² = RMS²/2, correlation time τ), and the coils' force
//! F acting at time t was computed from poses captured at least D earlier. Everything F does
//! is then fixed by what was known at t − D, so the error at t has at least the variance of
//! x(t) given all poses up to t − D: the steady Kalman filter's covariance on the poses
//! (period T, noise R), carried D ahead with no measurement. D runs over one frame, from the
//! command's start (L frames of camera latency plus the command delay after the capture) to
//! the next command's, and the floor is the RMS over that frame, both axes:
//! √(2 · mean P_xx(D)). The bound holds for any force, unlimited or not; it leaves out what
//! the twin adds beyond the noise (pulsation, form drag, walls), which a controller could in
//! principle predict.

use nalgebra::{Matrix3, Matrix6, Vector3};

/// The linearised capsule in the flow noise, as the twin has it
/// (`PlantModel::flow_noise_response`).
pub use millinav_plant::model::FlowNoiseResponse as NoisyCapsule;

/// How the loop sees the capsule.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sampling {
    pub frame_period_s: f64,
    /// Whole frames of camera latency.
    pub latency_frames: u32,
    /// From a frame's grab to its command reaching the coils (inside the frame), s.
    pub command_delay_s: f64,
    /// Localization noise per axis (1σ), m.
    pub pose_noise_m: f64,
}

/// The fluid particle's velocity time constant as a fraction of the noise's correlation time.
const FLUID_PARTICLE_LAG_FRACTION: f64 = 1e-3;
/// Points over the frame at which the carried covariance is averaged.
const FRAME_POINTS: usize = 20;
/// Kalman iterations towards the steady covariance (converges within a few correlation times).
const MAX_FILTER_STEPS: usize = 5000;

/// Per axis: the matrix of the state (x, v, u) and the process noise's intensity.
fn dynamics(capsule: &NoisyCapsule) -> (Matrix3<f64>, Matrix3<f64>) {
    let m = capsule.moving_mass_kg;
    let tau = capsule.correlation_time_s;
    let variance = capsule.noise_rms_speed_mps.powi(2) / 2.0;
    let a = Matrix3::new(
        0.0,
        1.0,
        0.0,
        0.0,
        -capsule.linear_drag_n_s_per_m / m,
        capsule.flow_coupling_n_s_per_m / m,
        0.0,
        0.0,
        -1.0 / tau,
    );
    let q = Matrix3::from_diagonal(&Vector3::new(0.0, 0.0, 2.0 * variance / tau));
    (a, q)
}

/// Transition and process-noise covariance over `h` seconds: Van Loan's method over a
/// step short enough for it to stay well conditioned (a fluid particle's drag is stiff),
/// then doubled back up to `h` (Φ(2s) = Φ(s)², Q(2s) = Q(s) + Φ(s) Q(s) Φ(s)ᵀ).
fn discretised(capsule: &NoisyCapsule, h: f64) -> (Matrix3<f64>, Matrix3<f64>) {
    let (a, q) = dynamics(capsule);
    let stiffness = a.abs().max() * h;
    let doublings = if stiffness > 0.5 {
        ((stiffness / 0.5).log2().ceil() as i32).min(60)
    } else {
        0
    };
    let step = h / 2f64.powi(doublings);
    let mut m = Matrix6::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-a * step));
    m.fixed_view_mut::<3, 3>(0, 3).copy_from(&(q * step));
    m.fixed_view_mut::<3, 3>(3, 3)
        .copy_from(&(a.transpose() * step));
    let e = m.exp();
    let mut phi: Matrix3<f64> = e.fixed_view::<3, 3>(3, 3).transpose();
    let mut qd = phi * e.fixed_view::<3, 3>(0, 3);
    for _ in 0..doublings {
        qd += phi * qd * phi.transpose();
        phi *= phi;
    }
    (phi, (qd + qd.transpose()) * 0.5)
}

/// The steady covariance right after a pose.
fn filtered_covariance(capsule: &NoisyCapsule, sampling: &Sampling) -> Matrix3<f64> {
    let (phi, qd) = discretised(capsule, sampling.frame_period_s);
    let r = sampling.pose_noise_m.powi(2);
    let variance = capsule.noise_rms_speed_mps.powi(2) / 2.0;
    let mut p = Matrix3::from_diagonal(&Vector3::new(r, variance, variance));
    for _ in 0..MAX_FILTER_STEPS {
        let prior = phi * p * phi.transpose() + qd;
        let innovation = prior[(0, 0)] + r;
        let gain = prior.column(0) / innovation.max(f64::MIN_POSITIVE);
        let next = prior - gain * prior.row(0);
        let next = (next + next.transpose()) * 0.5;
        let converged = (next - p).abs().max() <= 1e-12 * next.abs().max();
        p = next;
        if converged {
            break;
        }
    }
    p
}

/// Per-axis variance of the position `age_s` after the last pose the command knows.
fn position_variance(capsule: &NoisyCapsule, filtered: &Matrix3<f64>, age_s: f64) -> f64 {
    if age_s <= 0.0 {
        return filtered[(0, 0)];
    }
    let (phi, qd) = discretised(capsule, age_s);
    (phi * filtered * phi.transpose() + qd)[(0, 0)]
}

/// A body that follows the flow at once (its drag's slope far above its mass over the
/// noise's correlation time): the limit the capsule approaches where the form drag's slope
/// c + 2k|u| grows with the flow it sits in.
pub fn fluid_particle(capsule: &NoisyCapsule) -> NoisyCapsule {
    let drag = capsule
        .linear_drag_n_s_per_m
        .max(capsule.flow_coupling_n_s_per_m);
    NoisyCapsule {
        moving_mass_kg: drag * capsule.correlation_time_s * FLUID_PARTICLE_LAG_FRACTION,
        linear_drag_n_s_per_m: drag,
        flow_coupling_n_s_per_m: drag,
        ..*capsule
    }
}

/// The RMS tracking error (both axes, m) that no controller beats in this noise (module
/// doc). 0 without noise; NaN for a capsule or sampling that is not physical.
pub fn rmse_floor_m(capsule: &NoisyCapsule, sampling: &Sampling) -> f64 {
    let physical = capsule.moving_mass_kg > 0.0
        && capsule.linear_drag_n_s_per_m >= 0.0
        && capsule.flow_coupling_n_s_per_m >= 0.0
        && capsule.correlation_time_s > 0.0
        && capsule.noise_rms_speed_mps.is_finite()
        && sampling.frame_period_s > 0.0
        && sampling.command_delay_s >= 0.0
        && sampling.pose_noise_m >= 0.0;
    if !physical {
        return f64::NAN;
    }
    if capsule.noise_rms_speed_mps == 0.0 {
        return 0.0;
    }
    let filtered = filtered_covariance(capsule, sampling);
    let start = sampling.latency_frames as f64 * sampling.frame_period_s + sampling.command_delay_s;
    let mean: f64 = (0..FRAME_POINTS)
        .map(|j| {
            let age = start + (j as f64 + 0.5) / FRAME_POINTS as f64 * sampling.frame_period_s;
            position_variance(capsule, &filtered, age)
        })
        .sum::<f64>()
        / FRAME_POINTS as f64;
    (2.0 * mean).sqrt()
}

/// One condition's floor (`experiments --noise-floor`).
#[derive(Debug, Clone, PartialEq)]
pub struct FloorRow {
    pub viscosity_cp: f64,
    pub flow: crate::FlowSetting,
    pub noise_rms_speed_mps: f64,
    pub sampling: Sampling,
    pub floor_m: f64,
    /// The same for a body that follows the flow at once ([`NoisyCapsule::fluid_particle`]).
    pub fluid_particle_floor_m: f64,
}

/// The floors of the twin one scenario runs: its noise, drag, frame period, camera latency and
/// command delay, and fast mode's pose noise.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScenarioFloor {
    pub noise_rms_speed_mps: f64,
    pub sampling: Sampling,
    pub floor_m: f64,
    /// The same for a body that follows the flow at once ([`NoisyCapsule::fluid_particle`]).
    pub fluid_particle_floor_m: f64,
}

/// [`ScenarioFloor`] of `scenario`.
pub fn scenario_floor(
    scenario: &millinav_kit::scenario::Scenario,
) -> anyhow::Result<ScenarioFloor> {
    let plant: millinav_plant::PlantConfig = scenario.section("plant")?;
    let model = millinav_plant::build_model(scenario, &plant)?;
    let capsule = model.flow_noise_response();
    let exposures = plant.camera.exposure_period_frames.max(1);
    let sampling = if exposures == 1 {
        Sampling {
            frame_period_s: scenario.frame_period_s(),
            latency_frames: plant.camera.latency_frames,
            command_delay_s: plant.command_delay_ms * 1e-3,
            pose_noise_m: crate::FAST_POSE_NOISE_M,
        }
    } else {
        // A camera slower than the loop: the poses come one exposure period apart and their
        // age at the coils runs over that period from the latency on, whatever the loop rate.
        Sampling {
            frame_period_s: scenario.frame_period_s() * f64::from(exposures),
            latency_frames: 0,
            command_delay_s: f64::from(plant.camera.latency_frames) * scenario.frame_period_s()
                + plant.command_delay_ms * 1e-3,
            pose_noise_m: crate::FAST_POSE_NOISE_M,
        }
    };
    Ok(ScenarioFloor {
        noise_rms_speed_mps: capsule.noise_rms_speed_mps,
        sampling,
        floor_m: rmse_floor_m(&capsule, &sampling),
        fluid_particle_floor_m: rmse_floor_m(&fluid_particle(&capsule), &sampling),
    })
}

/// The floor of every condition (viscosity × flow) among `cells`, each from its own cell
/// scenario on `base`.
pub fn condition_floors(
    base: &millinav_kit::scenario::Scenario,
    cells: &[crate::Cell],
) -> anyhow::Result<Vec<FloorRow>> {
    let mut rows: Vec<FloorRow> = Vec::new();
    for cell in cells {
        if rows
            .iter()
            .any(|r| r.viscosity_cp == cell.viscosity_cp && r.flow == cell.flow)
        {
            continue;
        }
        let text = crate::cell_scenario(base, cell)?;
        let scenario = millinav_kit::scenario::Scenario::parse(&text, &base.path)?;
        let floor = scenario_floor(&scenario)?;
        rows.push(FloorRow {
            viscosity_cp: cell.viscosity_cp,
            flow: cell.flow,
            noise_rms_speed_mps: floor.noise_rms_speed_mps,
            sampling: floor.sampling,
            floor_m: floor.floor_m,
            fluid_particle_floor_m: floor.fluid_particle_floor_m,
        });
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    /// The paper's capsule in 20 cP with the twin's noise at 7 cm/s (6.4 mm/s RMS).
    fn capsule() -> NoisyCapsule {
        NoisyCapsule {
            moving_mass_kg: 7.54e-5,
            linear_drag_n_s_per_m: 5.6e-4,
            flow_coupling_n_s_per_m: 5.6e-4,
            noise_rms_speed_mps: 6.4e-3,
            correlation_time_s: 0.3,
        }
    }

    fn sampling(frame_period_s: f64, latency_frames: u32) -> Sampling {
        Sampling {
            frame_period_s,
            latency_frames,
            command_delay_s: 0.0,
            pose_noise_m: 2e-5,
        }
    }

    #[test]
    fn no_noise_no_floor_and_older_poses_raise_it() {
        let still = NoisyCapsule {
            noise_rms_speed_mps: 0.0,
            ..capsule()
        };
        assert_eq!(rmse_floor_m(&still, &sampling(0.1, 1)), 0.0);
        let floors: Vec<f64> = (0..4)
            .map(|l| rmse_floor_m(&capsule(), &sampling(0.1, l)))
            .collect();
        assert!(floors.windows(2).all(|w| w[0] < w[1]), "{floors:?}");
        // A body that follows the flow at once is moved further by it, and as far as a fluid
        // particle whose velocity is an Ornstein–Uhlenbeck process: with poses that tell its
        // velocity nearly exactly, the displacement over a horizon T it cannot know has the
        // variance σ²τ²(2T/τ − 3 + 4e^(−T/τ) − e^(−2T/τ)) per axis.
        let particle = fluid_particle(&capsule());
        let fine = Sampling {
            frame_period_s: 1e-3,
            latency_frames: 100,
            command_delay_s: 0.0,
            pose_noise_m: 1e-9,
        };
        let (sigma, tau) = (capsule().noise_rms_speed_mps / 2f64.sqrt(), 0.3);
        let horizons =
            (0..FRAME_POINTS).map(|j| 0.1 + (j as f64 + 0.5) / FRAME_POINTS as f64 * 1e-3);
        let exact = (horizons
            .map(|t| {
                let x = t / tau;
                sigma.powi(2) * tau.powi(2) * (2.0 * x - 3.0 + 4.0 * (-x).exp() - (-2.0 * x).exp())
            })
            .sum::<f64>()
            * 2.0
            / FRAME_POINTS as f64)
            .sqrt();
        let floor = rmse_floor_m(&particle, &fine);
        assert!(
            (floor / exact - 1.0).abs() < 0.02,
            "{floor:.4e} vs {exact:.4e} m"
        );
        assert!(rmse_floor_m(&particle, &sampling(0.1, 1)) > floors[1]);
        // Twice the flow noise and twice the pose noise, twice the floor (the model is linear);
        // twice the flow noise alone, a little less (the poses then tell more of it).
        let louder = NoisyCapsule {
            noise_rms_speed_mps: 2.0 * capsule().noise_rms_speed_mps,
            ..capsule()
        };
        let noisier_poses = Sampling {
            pose_noise_m: 4e-5,
            ..sampling(0.1, 1)
        };
        let ratio = rmse_floor_m(&louder, &noisier_poses) / floors[1];
        assert!((ratio - 2.0).abs() < 1e-6, "ratio {ratio}");
        let ratio = rmse_floor_m(&louder, &sampling(0.1, 1)) / floors[1];
        assert!(ratio > 1.5 && ratio < 2.0, "ratio {ratio}");
        let never = Sampling {
            frame_period_s: 0.0,
            ..sampling(0.1, 1)
        };
        assert!(rmse_floor_m(&capsule(), &never).is_nan());
    }

    /// The floor is what a Kalman predictor achieves: simulated finely (Euler–Maruyama, not
    /// the transition the floor uses), the capsule's position carried from its poses to each
    /// point of the next frame misses by the floor's RMS.
    #[test]
    fn a_kalman_predictor_on_a_simulated_capsule_misses_by_the_floor() {
        let capsule = capsule();
        let sampling = sampling(0.1, 1);
        let (a, _) = dynamics(&capsule);
        let sigma = capsule.noise_rms_speed_mps / 2f64.sqrt();
        let tau = capsule.correlation_time_s;
        let (phi, qd) = discretised(&capsule, sampling.frame_period_s);
        let r = sampling.pose_noise_m.powi(2);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let substeps = 200;
        let h = sampling.frame_period_s / substeps as f64;
        let (mut truth, mut estimate) = (Vector3::new(0.0, 0.0, sigma), Vector3::zeros());
        let mut p = filtered_covariance(&capsule, &sampling);
        let frames = 6000;
        let (mut squared, mut count) = (0.0, 0);
        // The estimate after each pose, for the predictions one latency frame later.
        let mut history: Vec<Vector3<f64>> = Vec::new();
        for frame in 0..frames {
            let z: f64 = StandardNormal.sample(&mut rng);
            let measured = truth[0] + sampling.pose_noise_m * z;
            let prior = phi * p * phi.transpose() + qd;
            let gain = prior.column(0) / (prior[(0, 0)] + r);
            if frame > 0 {
                estimate = phi * estimate;
            }
            estimate += gain * (measured - estimate[0]);
            p = prior - gain * prior.row(0);
            history.push(estimate);
            for step in 0..substeps {
                if frame >= 100 && step % 10 == 5 {
                    // Known at this instant: the estimate after the pose `latency` frames back.
                    let known = history[frame - sampling.latency_frames as usize];
                    let age = (sampling.latency_frames as f64
                        + (step as f64 + 0.5) / substeps as f64)
                        * sampling.frame_period_s;
                    let carried = (a * age).exp() * known;
                    squared += (truth[0] - carried[0]).powi(2);
                    count += 1;
                }
                let w: f64 = StandardNormal.sample(&mut rng);
                let v_dot = a[(1, 1)] * truth[1] + a[(1, 2)] * truth[2];
                truth[0] += truth[1] * h;
                truth[1] += v_dot * h;
                truth[2] += -truth[2] / tau * h + sigma * (2.0 * h / tau).sqrt() * w;
            }
        }
        let simulated = (2.0 * squared / count as f64).sqrt();
        let floor = rmse_floor_m(&capsule, &sampling);
        assert!(
            (simulated / floor - 1.0).abs() < 0.1,
            "simulated {simulated:.3e} m vs floor {floor:.3e} m"
        );
    }
}
