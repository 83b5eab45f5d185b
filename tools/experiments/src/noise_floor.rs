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
//!
//! The pulsation has a floor of its own, even known exactly: the coils take one command per
//! frame and hold it, so no force cancels the stroke's push within a frame. Along the stream
//! the held capsule obeys m v̇ = −c v + c_u δu(t) + F, linearised about a capsule held still
//! in the steady stream of speed U (the form drag k|u|u adds 2kU to both slopes), with δu the
//! pump's stroke, U × (waveform − 1). The force is one value per frame, repeating with the
//! cycle in which the loop and the pump meet again; the floor is the least RMS position error
//! of that periodic steady state (`pulsation_hold_floor_m`), then the RMS over the path's
//! stream speeds. For the linearised capsule the two floors add in quadrature: the noise is
//! random and the stroke is not.

use nalgebra::{DMatrix, DVector, Matrix2, Matrix2xX, Matrix3, Matrix6, Vector2, Vector3};

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

/// The capsule held still in a steady stream, linearised for the pulsation's push on it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeldCapsule {
    pub moving_mass_kg: f64,
    /// Slope of the drag on the capsule's own motion, N·s/m.
    pub own_drag_n_s_per_m: f64,
    /// Slope of the flow's push on it, N·s/m.
    pub flow_push_n_s_per_m: f64,
}

impl HeldCapsule {
    /// `capsule` held in a stream of `speed_mps`: the form drag k|u|u (`quadratic_drag`,
    /// N·s²/m²) steepens both slopes by 2k·speed.
    pub fn in_stream(capsule: &NoisyCapsule, quadratic_drag: f64, speed_mps: f64) -> Self {
        let form = 2.0 * quadratic_drag * speed_mps.abs();
        Self {
            moving_mass_kg: capsule.moving_mass_kg,
            own_drag_n_s_per_m: capsule.linear_drag_n_s_per_m + form,
            flow_push_n_s_per_m: capsule.flow_coupling_n_s_per_m + form,
        }
    }
}

/// Most frames in the cycle the loop and the pump repeat in.
const MAX_FRAMES_PER_CYCLE: usize = 400;
/// Fewest integration steps per frame and per pulsation period.
const MIN_STEPS_PER_FRAME: f64 = 2.0;
const MIN_STEPS_PER_PULSATION: f64 = 40.0;
/// Cycles run before the error is measured: enough capsule time constants for the start to
/// be forgotten.
const WARM_UP_TIME_CONSTANTS: f64 = 12.0;

/// The fewest frames that span a whole number of pulsation periods (the closest to it within
/// [`MAX_FRAMES_PER_CYCLE`] when none does exactly); none when one period is longer than that.
fn frames_per_cycle(frame_period_s: f64, pulsation_hz: f64) -> Option<usize> {
    let mut best = (0, f64::INFINITY);
    for frames in 1..=MAX_FRAMES_PER_CYCLE {
        let periods = frames as f64 * frame_period_s * pulsation_hz;
        if periods < 1.0 - 1e-9 {
            continue;
        }
        let miss = (periods - periods.round()).abs();
        if miss < 1e-6 {
            return Some(frames);
        }
        if miss < best.1 {
            best = (frames, miss);
        }
    }
    (best.0 > 0).then_some(best.0)
}

/// Transition of (x, v) over `h` under m v̇ = −c v + m w, w held: (Φ, Γ).
fn held_transition(drag_rate_per_s: f64, h: f64) -> (Matrix2<f64>, Vector2<f64>) {
    let b = drag_rate_per_s;
    // (1 − e^(−bh)) / b and (h − that) / b, by their series where bh is small.
    let (decay, lag) = if b * h < 1e-6 {
        (h - b * h * h / 2.0, h * h / 2.0)
    } else {
        let decay = -(-b * h).exp_m1() / b;
        (decay, (h - decay) / b)
    };
    (
        Matrix2::new(1.0, decay, 0.0, (-b * h).exp()),
        Vector2::new(lag, decay),
    )
}

/// The least RMS position error (m) that a force held over each frame leaves against a
/// pulsation known exactly (module doc): `stream_deviation_mps(t)` is the stroke's deviation
/// from the steady stream, periodic with 1 / `pulsation_hz`. 0 without a pulsation; NaN for
/// a capsule or loop that is not physical, or a pump period longer than
/// [`MAX_FRAMES_PER_CYCLE`] frames (slower than 0.25 Hz at 100 Hz).
pub fn pulsation_hold_floor_m(
    capsule: &HeldCapsule,
    stream_deviation_mps: impl Fn(f64) -> f64,
    pulsation_hz: f64,
    frame_period_s: f64,
) -> f64 {
    let physical = capsule.moving_mass_kg > 0.0
        && capsule.own_drag_n_s_per_m > 0.0
        && capsule.flow_push_n_s_per_m >= 0.0
        && frame_period_s > 0.0
        && pulsation_hz.is_finite()
        && pulsation_hz >= 0.0;
    if !physical {
        return f64::NAN;
    }
    if pulsation_hz == 0.0 || capsule.flow_push_n_s_per_m == 0.0 {
        return 0.0;
    }
    let Some(frames) = frames_per_cycle(frame_period_s, pulsation_hz) else {
        return f64::NAN;
    };
    let steps_per_frame = MIN_STEPS_PER_FRAME
        .max((MIN_STEPS_PER_PULSATION * frame_period_s * pulsation_hz).ceil())
        as usize;
    let h = frame_period_s / steps_per_frame as f64;
    let cycle_s = frames as f64 * frame_period_s;
    let drag_rate = capsule.own_drag_n_s_per_m / capsule.moving_mass_kg;
    let warm_up_cycles = (WARM_UP_TIME_CONSTANTS / drag_rate / cycle_s).ceil() as usize;
    let (phi, gamma) = held_transition(drag_rate, h);
    // The state is affine in the unknowns z = (x offset, the force per unit mass of each
    // frame): columns of `sensitivity`, plus the pulsation's own response `driven`.
    let unknowns = frames + 1;
    let mut sensitivity = Matrix2xX::<f64>::zeros(unknowns);
    sensitivity[(0, 0)] = 1.0;
    let mut driven = Vector2::zeros();
    let mut normal = DMatrix::<f64>::zeros(unknowns, unknowns);
    let mut cross = DVector::<f64>::zeros(unknowns);
    let mut driven_square = 0.0;
    let push_rate = capsule.flow_push_n_s_per_m / capsule.moving_mass_kg;
    // Where the measured cycle starts: it must end there too (a steady state does not drift).
    let mut cycle_start = (DVector::<f64>::zeros(unknowns), 0.0);
    for cycle in 0..=warm_up_cycles {
        if cycle == warm_up_cycles {
            cycle_start = (sensitivity.row(0).transpose(), driven[0]);
        }
        for frame in 0..frames {
            for step in 0..steps_per_frame {
                let t = cycle_s * cycle as f64 + h * (frame * steps_per_frame + step) as f64;
                let push = push_rate * stream_deviation_mps(t + h / 2.0);
                sensitivity = phi * sensitivity;
                let mut this_frame = sensitivity.column_mut(frame + 1);
                this_frame += gamma;
                driven = phi * driven + gamma * push;
                if cycle == warm_up_cycles {
                    let row = sensitivity.row(0).transpose();
                    normal.ger(1.0, &row, &row, 1.0);
                    cross.axpy(driven[0], &row, 1.0);
                    driven_square += driven[0] * driven[0];
                }
            }
        }
    }
    // Least squares with the cycle's drift held at 0: the KKT system of Σ (row·z + driven)²
    // and drift·z + driven drift = 0.
    let drift = sensitivity.row(0).transpose() - cycle_start.0;
    let mut kkt = DMatrix::<f64>::zeros(unknowns + 1, unknowns + 1);
    kkt.view_mut((0, 0), (unknowns, unknowns))
        .copy_from(&normal);
    kkt.view_mut((unknowns, 0), (1, unknowns))
        .copy_from(&drift.transpose());
    kkt.view_mut((0, unknowns), (unknowns, 1)).copy_from(&drift);
    let mut rhs = DVector::<f64>::zeros(unknowns + 1);
    rhs.rows_mut(0, unknowns).copy_from(&(-&cross));
    rhs[unknowns] = cycle_start.1 - driven[0];
    let Ok(solution) = kkt.svd(true, true).solve(&rhs, 1e-14) else {
        return f64::NAN;
    };
    let z = solution.rows(0, unknowns);
    let residual = driven_square + 2.0 * cross.dot(&z) + z.dot(&(&normal * z));
    let samples = (frames * steps_per_frame) as f64;
    (residual.max(0.0) / samples).sqrt()
}

/// Stream speeds the path's RMS is taken over, and the speed levels the floor is computed
/// at (interpolated between them).
const PATH_POINTS: usize = 200;
const SPEED_LEVELS: usize = 24;

/// The pulsation's hold floor over a path: the RMS over `stream_speeds_mps` (the steady
/// stream at evenly timed points of the reference) of each place's floor.
pub fn path_pulsation_hold_floor_m(
    capsule: &NoisyCapsule,
    quadratic_drag: f64,
    stream_speeds_mps: &[f64],
    waveform: &dyn Fn(f64) -> f64,
    pulsation_hz: f64,
    frame_period_s: f64,
) -> f64 {
    let fastest = stream_speeds_mps.iter().copied().fold(0.0, f64::max);
    if stream_speeds_mps.is_empty() || fastest == 0.0 {
        return 0.0;
    }
    let level_floor: Vec<f64> = (0..SPEED_LEVELS)
        .map(|i| {
            let speed = fastest * i as f64 / (SPEED_LEVELS - 1) as f64;
            let held = HeldCapsule::in_stream(capsule, quadratic_drag, speed);
            pulsation_hold_floor_m(
                &held,
                |t| speed * (waveform(t) - 1.0),
                pulsation_hz,
                frame_period_s,
            )
        })
        .collect();
    let mean_square = stream_speeds_mps
        .iter()
        .map(|speed| {
            let at = speed.abs() / fastest * (SPEED_LEVELS - 1) as f64;
            let below = (at.floor() as usize).min(SPEED_LEVELS - 2);
            let share = at - below as f64;
            let floor = level_floor[below] * (1.0 - share) + level_floor[below + 1] * share;
            floor * floor
        })
        .sum::<f64>()
        / stream_speeds_mps.len() as f64;
    mean_square.sqrt()
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
    /// The pump's stroke, known exactly, under the loop's hold ([`path_pulsation_hold_floor_m`]).
    pub pulsation_hold_floor_m: f64,
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
    /// The pump's stroke, known exactly, under the loop's hold ([`path_pulsation_hold_floor_m`]).
    pub pulsation_hold_floor_m: f64,
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
    // Along the reference; the coils hold each command for one loop frame, whatever the
    // camera's rate.
    let reference = crate::reference_of(scenario)?;
    let (start, end) = (
        reference.end_time_s() - reference.duration_s(),
        reference.end_time_s(),
    );
    let stream_speeds: Vec<f64> = (0..PATH_POINTS)
        .map(|i| {
            let t = start + (end - start) * (i as f64 + 0.5) / PATH_POINTS as f64;
            model
                .steady_flow
                .sample(&reference.sample(t).position_m)
                .norm()
        })
        .collect();
    let pulsation_hold_floor_m = path_pulsation_hold_floor_m(
        &capsule,
        model.quadratic_drag(),
        &stream_speeds,
        &|t| model.pulsation_factor(t),
        model.config.pulsation_hz,
        scenario.frame_period_s(),
    );
    Ok(ScenarioFloor {
        noise_rms_speed_mps: capsule.noise_rms_speed_mps,
        sampling,
        floor_m: rmse_floor_m(&capsule, &sampling),
        fluid_particle_floor_m: rmse_floor_m(&fluid_particle(&capsule), &sampling),
        pulsation_hold_floor_m,
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
            pulsation_hold_floor_m: floor.pulsation_hold_floor_m,
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

    /// The paper's capsule at 20 cP held in a 5 cm/s stream (the form drag steepens it).
    fn held() -> HeldCapsule {
        HeldCapsule::in_stream(&capsule(), 7.5e-3, 0.05)
    }

    /// A sinusoidal stroke of `amplitude_mps` at `hz`.
    fn sine(amplitude_mps: f64, hz: f64) -> impl Fn(f64) -> f64 {
        move |t| amplitude_mps * (std::f64::consts::TAU * hz * t).sin()
    }

    #[test]
    fn a_held_force_leaves_the_stroke_within_a_frame_and_a_faster_loop_less() {
        let stroke = sine(0.02, 3.0);
        assert_eq!(pulsation_hold_floor_m(&held(), &stroke, 0.0, 0.1), 0.0);
        let at_10_hz = pulsation_hold_floor_m(&held(), &stroke, 3.0, 0.1);
        let at_100_hz = pulsation_hold_floor_m(&held(), &stroke, 3.0, 0.01);
        assert!(at_10_hz > 0.0 && at_100_hz > 0.0, "{at_10_hz} {at_100_hz}");
        // Within a frame the stroke moves the capsule by about its push over the frame: the
        // error shrinks faster than the frame.
        assert!(at_100_hz < at_10_hz / 10.0, "{at_10_hz} {at_100_hz}");
        // Linear in the stroke.
        let doubled = pulsation_hold_floor_m(&held(), sine(0.04, 3.0), 3.0, 0.1);
        assert!(
            (doubled / at_10_hz - 2.0).abs() < 1e-6,
            "{doubled} {at_10_hz}"
        );
        let bad = HeldCapsule {
            moving_mass_kg: 0.0,
            ..held()
        };
        assert!(pulsation_hold_floor_m(&bad, &stroke, 3.0, 0.1).is_nan());
        // A pump period of 1000 frames is past the cycle the floor is solved over: not a guess.
        assert!(pulsation_hold_floor_m(&held(), sine(0.02, 0.1), 0.1, 0.01).is_nan());
    }

    #[test]
    fn a_force_held_for_a_whole_stroke_leaves_the_stroke_unanswered() {
        // One frame per period: the best held force is the stroke's mean, 0, and the capsule
        // swings as the linear system's frequency response says.
        let capsule = held();
        let (amplitude, hz) = (0.02, 3.0);
        let floor = pulsation_hold_floor_m(&capsule, sine(amplitude, hz), hz, 1.0 / hz);
        let omega = std::f64::consts::TAU * hz;
        let rate = capsule.own_drag_n_s_per_m / capsule.moving_mass_kg;
        let push = capsule.flow_push_n_s_per_m / capsule.moving_mass_kg * amplitude;
        let swing_rms = push / (omega * (omega * omega + rate * rate).sqrt()) / 2f64.sqrt();
        assert!(
            (floor / swing_rms - 1.0).abs() < 0.01,
            "{floor} vs {swing_rms}"
        );
    }

    #[test]
    fn no_held_force_beats_the_floor() {
        // A plain rule that knows the stroke: each frame, the force that cancels its mean
        // push over the frame. Simulated finely, its error is at or above the floor.
        let capsule = held();
        let stroke = sine(0.03, 3.0);
        let frame = 0.1;
        let floor = pulsation_hold_floor_m(&capsule, &stroke, 3.0, frame);
        let (m, c, cu) = (
            capsule.moving_mass_kg,
            capsule.own_drag_n_s_per_m,
            capsule.flow_push_n_s_per_m,
        );
        let h = 1e-5;
        let steps = (frame / h).round() as usize;
        let (mut x, mut v, mut squared, mut count) = (0.0, 0.0, 0.0, 0usize);
        let mut positions = Vec::new();
        for k in 0..100 {
            let t0 = k as f64 * frame;
            let mean_push = (0..100)
                .map(|j| cu * stroke(t0 + (j as f64 + 0.5) * frame / 100.0))
                .sum::<f64>()
                / 100.0;
            for j in 0..steps {
                let t = t0 + (j as f64 + 0.5) * h;
                v += (-c * v + cu * stroke(t) - mean_push) / m * h;
                x += v * h;
                if k >= 50 {
                    positions.push(x);
                }
            }
        }
        let mean = positions.iter().sum::<f64>() / positions.len() as f64;
        for p in &positions {
            squared += (p - mean).powi(2);
            count += 1;
        }
        let rule = (squared / count as f64).sqrt();
        assert!(
            floor <= rule * 1.001,
            "floor {floor} above the rule's {rule}"
        );
        assert!(
            floor > 0.2 * rule,
            "floor {floor} far below the rule's {rule}"
        );
    }
}
