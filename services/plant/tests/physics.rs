//! Sanity of the twin's physics: no motion without cause, terminal velocity F/c_t, friction,
//! walls (contact reported, no tunnelling), determinism for a seed.

mod common;

use common::*;
use fieldmaps::flowmap::FlowMap;
use millinav_plant::model::{PlantModel, PlantPhysicsConfig, PlantState};
use nalgebra::Vector2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// `config` without the recirculation vortex and the flow noise: the true flow is the steady
/// map times the pulsation.
fn steady_only(config: PlantPhysicsConfig) -> PlantPhysicsConfig {
    PlantPhysicsConfig {
        recirculation: millinav_plant::trueflow::RecirculationConfig {
            strength_fraction: 0.0,
            ..Default::default()
        },
        flow_noise: millinav_plant::trueflow::FlowNoiseConfig {
            fraction: 0.0,
            ..Default::default()
        },
        ..config
    }
}

fn linear_only() -> PlantPhysicsConfig {
    PlantPhysicsConfig {
        form_drag_coefficient: 0.0,
        ..Default::default()
    }
}

#[test]
fn no_motion_without_current_or_flow() {
    for friction in [0.0, 0.3] {
        let config = PlantPhysicsConfig {
            floor_friction_coefficient: friction,
            ..Default::default()
        };
        let m = model(FlowMap::zero(), config, 11);
        let start = m.initial_state(ra_start(), 0.7);
        let mut s = start.clone();
        for _ in 0..500 {
            m.step(&mut s, &currents(0.0, 0), FRAME_S);
        }
        assert!((s.time_s - 5.0).abs() < 1e-9);
        assert_eq!(
            s.position_m, start.position_m,
            "drifted with friction {friction}"
        );
        assert_eq!(s.velocity_mps, Vector2::zeros());
        assert_eq!(s.heading_rad, start.heading_rad);
        assert_eq!(s.last_true_flow_mps, Vector2::zeros());
        assert!(!s.wall_contact);
        assert_eq!(s.contact_events, 0);
    }
}

#[test]
fn a_floor_gap_slows_the_capsule_by_the_wall_correction() {
    let free = model(FlowMap::zero(), linear_only(), 1);
    let gap = 2e-5;
    let on_floor = model(
        FlowMap::zero(),
        PlantPhysicsConfig {
            floor_gap_m: Some(gap),
            ..linear_only()
        },
        1,
    );
    let factor = fieldmaps::physics::wall_drag_factor_parallel(gap, free.robot.diameter_m / 2.0);
    assert!(factor > 2.0 && factor < 4.0, "{factor}");
    assert!((on_floor.linear_drag() / free.linear_drag() - factor).abs() < 1e-9);
    let terminal_speed = |m: &PlantModel| {
        let mut s = m.initial_state(ra_start(), 0.3);
        for _ in 0..200 {
            m.step(&mut s, &currents(0.02, 9), FRAME_S);
        }
        s.velocity_mps.norm() / s.last_magnetic_force_n.norm()
    };
    let ratio = terminal_speed(&free) / terminal_speed(&on_floor);
    assert!((ratio / factor - 1.0).abs() < 0.02, "{ratio} vs {factor}");
}

#[test]
fn on_the_floor_the_flow_pushes_with_its_own_factor() {
    // Uniform steady flow, no current, no pulsation or disturbances: the capsule drifts at
    // flow × (flow factor / floor factor) once the transient has passed.
    let uniform = FlowMap {
        velocity_mps: vec![Vector2::new(2e-3, 0.0); 4],
        ..FlowMap::zero()
    };
    let gap = 3e-6;
    let config = PlantPhysicsConfig {
        floor_gap_m: Some(gap),
        floor_flow_factor: Some(1.7),
        pulsation_amplitude: 0.0,
        ..steady_only(linear_only())
    };
    let m = model(uniform, config, 3);
    let factor = fieldmaps::physics::wall_drag_factor_parallel(gap, m.robot.diameter_m / 2.0);
    let mut s = m.initial_state(ra_start(), 0.0);
    for _ in 0..100 {
        m.step(&mut s, &currents(0.0, 0), FRAME_S);
    }
    let expected = 2e-3 * 1.7 / factor;
    assert!(
        (s.velocity_mps.x / expected - 1.0).abs() < 0.01 && s.velocity_mps.y.abs() < 1e-9,
        "{:?} vs {expected}",
        s.velocity_mps
    );
}

#[test]
fn terminal_velocity_is_force_over_linear_drag() {
    let m = model(FlowMap::zero(), linear_only(), 1);
    let mut s = m.initial_state(ra_start(), 0.3);
    // A weak pull: the capsule aligns, then drifts slowly enough that the force is steady.
    for _ in 0..200 {
        m.step(&mut s, &currents(0.02, 9), FRAME_S);
    }
    let expected = s.last_magnetic_force_n / m.linear_drag();
    let rel = (s.velocity_mps - expected).norm() / expected.norm();
    println!(
        "terminal: |v| {:.4e} m/s, |F|/c_t {:.4e} m/s, relative error {rel:.4}",
        s.velocity_mps.norm(),
        expected.norm()
    );
    assert!(expected.norm() > 1e-4, "test needs a real force");
    assert!(rel < 0.01, "relative error {rel}");
}

#[test]
fn coulomb_friction_holds_a_weak_pull_and_slows_a_strong_one() {
    let with = |mu: f64, load: f64| {
        model(
            FlowMap::zero(),
            PlantPhysicsConfig {
                floor_friction_coefficient: mu,
                floor_extra_load_n: load,
                ..linear_only()
            },
            1,
        )
    };
    // Negligible friction: measures the force and the floor load (apparent weight + the
    // magnet's downward pull) of this pose.
    let probe_model = with(1e-15, 0.0);
    let mut probe = probe_model.initial_state(ra_start(), 0.3);
    for _ in 0..200 {
        probe_model.step(&mut probe, &currents(0.02, 9), FRAME_S);
    }
    let force = probe.last_magnetic_force_n.norm();
    let base_load = probe.last_floor_load_n;
    println!("friction: |F| {force:.3e} N, floor load without extra {base_load:.3e} N");

    // Static: μN ≥ 2|F| never lets it go.
    let mu = 0.5;
    let stuck = with(mu, (2.0 * force / mu - base_load).max(0.0));
    let mut s = probe.clone();
    s.velocity_mps = Vector2::zeros();
    let held = s.position_m;
    for _ in 0..100 {
        stuck.step(&mut s, &currents(0.02, 9), FRAME_S);
    }
    assert_eq!(s.position_m, held);

    // Sliding: μN = |F|/2 halves the terminal speed.
    let extra = base_load.max(force);
    let mu = 0.5 * force / (base_load + extra);
    let sliding = with(mu, extra);
    let mut s = probe.clone();
    for _ in 0..100 {
        sliding.step(&mut s, &currents(0.02, 9), FRAME_S);
    }
    let expected =
        (s.last_magnetic_force_n.norm() - mu * s.last_floor_load_n) / sliding.linear_drag();
    let rel = (s.velocity_mps.norm() - expected).abs() / expected;
    println!(
        "friction: |v| {:.4e} m/s vs (|F| − μN)/c_t {:.4e} m/s",
        s.velocity_mps.norm(),
        expected
    );
    assert!(rel < 0.03, "relative error {rel}");
}

fn assert_inside(m: &PlantModel, s: &PlantState, tolerance_m: f64) {
    let radius = m.robot.diameter_m / 2.0;
    let half = m.robot.length_m / 2.0 - radius;
    let axis = Vector2::new(s.heading_rad.cos(), s.heading_rad.sin());
    for offset in [-half, 0.0, half] {
        let p = s.position_m + axis * offset;
        let penetration = m.walls.signed_distance(&p) + radius;
        assert!(
            penetration <= tolerance_m,
            "capsule point {p:?} {:.3} mm into the wall at t = {:.3}",
            penetration * 1e3,
            s.time_s
        );
    }
}

#[test]
fn a_fast_capsule_does_not_tunnel_and_contact_is_reported() {
    let m = model(FlowMap::zero(), PlantPhysicsConfig::default(), 2);
    let mut s = m.initial_state(ra_start(), std::f64::consts::PI);
    // 50 m/s towards the atrium's left wall (x = −31 mm): 25 mm per 0.5 ms substep.
    s.velocity_mps = Vector2::new(-50.0, 0.0);
    m.step(&mut s, &currents(0.0, 0), FRAME_S);
    assert!(s.wall_contact);
    assert_eq!(s.contact_events, 1);
    assert!(s.contact_time_s > 0.0);
    assert!(
        s.position_m.x > -0.0312,
        "went through the wall: {:?}",
        s.position_m
    );
    assert_inside(&m, &s, 0.05e-3);
}

#[test]
fn huge_currents_never_push_the_capsule_out_of_the_canal() {
    let m = model(FlowMap::zero(), PlantPhysicsConfig::default(), 3);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut s = m.initial_state(ra_start(), 0.0);
    let mut max_speed: f64 = 0.0;
    for frame in 0..400 {
        // A new wild command every 20 frames: up to 500 A per coil.
        let command: [f64; fieldmaps::rigfile::MAX_COILS] = if frame % 20 == 0 {
            std::array::from_fn(|_| rng.random_range(-500.0..500.0))
        } else {
            s.coil_currents_a
        };
        m.step(&mut s, &command, FRAME_S);
        max_speed = max_speed.max(s.velocity_mps.norm());
        assert!(s.position_m.iter().all(|c| c.is_finite()));
        assert!(
            m.walls.contains(&s.position_m),
            "centre left the canal at frame {frame}"
        );
        assert_inside(&m, &s, 0.05e-3);
    }
    println!(
        "huge currents: max speed {max_speed:.3} m/s, {} contact onsets, {:.2} s in contact",
        s.contact_events, s.contact_time_s
    );
    assert!(s.contact_events > 0);
}

/// A seeded sequence of commands exercised on a model with flow (noise and vortex active).
fn run_commands(seed: u64, frames: usize) -> Vec<PlantState> {
    let m = model(swirl_map(), PlantPhysicsConfig::default(), seed);
    let mut commands = ChaCha8Rng::seed_from_u64(99);
    let mut s = m.initial_state(ra_start(), 0.4);
    let mut trace = Vec::with_capacity(frames);
    for _ in 0..frames {
        let c: Vec<f64> = (0..coil_count())
            .map(|_| commands.random_range(-0.2..0.2))
            .collect();
        m.step(&mut s, &c, FRAME_S);
        trace.push(s.clone());
    }
    trace
}

#[test]
fn same_seed_same_commands_give_bit_identical_states() {
    let a = run_commands(42, 300);
    let b = run_commands(42, 300);
    assert_eq!(a, b);
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.position_m.x.to_bits(), y.position_m.x.to_bits());
        assert_eq!(
            x.last_true_flow_mps.y.to_bits(),
            y.last_true_flow_mps.y.to_bits()
        );
    }
    let c = run_commands(43, 300);
    assert_ne!(
        a.last().map(|s| s.position_m),
        c.last().map(|s| s.position_m)
    );
    assert_ne!(a[0].last_true_flow_mps, c[0].last_true_flow_mps);
}

#[test]
fn true_flow_is_steady_times_pulsation_plus_disturbances() {
    let plain = model(swirl_map(), steady_only(PlantPhysicsConfig::default()), 5);
    let full = model(swirl_map(), PlantPhysicsConfig::default(), 5);
    let p = Vector2::new(-0.012, 0.003); // in the recirculation band
    let q = Vector2::new(0.0, -0.020); // below it
    let steady = swirl_map().sample(&p);
    // Mean of the pulsatile factor over a period is 1.
    let n = 3000;
    let mean: Vector2<f64> = (0..n)
        .map(|k| plain.true_flow(&p, k as f64 / (3.0 * n as f64)))
        .sum::<Vector2<f64>>()
        / n as f64;
    assert!(
        (mean - steady).norm() < 1e-3 * steady.norm(),
        "{mean} vs {steady}"
    );
    // ... and it pulses: along the steady direction, from its trough up to 1 + amplitude.
    let amplitude = PlantPhysicsConfig::default().pulsation_amplitude;
    assert!(amplitude > 0.0);
    let factors: Vec<f64> = (0..n)
        .map(|k| {
            let v = plain.true_flow(&p, k as f64 / (3.0 * n as f64));
            assert!(v.perp(&steady).abs() < 1e-9 * steady.norm_squared());
            v.dot(&steady) / steady.norm_squared()
        })
        .collect();
    let peak = factors.iter().cloned().fold(f64::MIN, f64::max);
    let trough = factors.iter().cloned().fold(f64::MAX, f64::min);
    assert!(
        (peak - (1.0 + amplitude)).abs() < 1e-3,
        "peak factor {peak}, expected {}",
        1.0 + amplitude
    );
    assert!(trough < 1.0 - 0.5 * amplitude, "trough factor {trough}");
    // The vortex changes the flow in the band, not below it.
    assert!((full.true_flow(&p, 0.4) - plain.true_flow(&p, 0.4)).norm() > 1e-5);
    assert_eq!(full.true_flow(&q, 0.4), plain.true_flow(&q, 0.4));
    // Noise is on top, and evolves.
    let mut s = full.initial_state(ra_start(), 0.0);
    let n0 = full.true_flow_with_noise(&q, 0.0, &s.flow_noise) - full.true_flow(&q, 0.0);
    full.step(&mut s, &currents(0.0, 0), 0.5);
    let n1 = full.true_flow_with_noise(&q, 0.0, &s.flow_noise) - full.true_flow(&q, 0.0);
    assert!(n0.norm() > 0.0 && n1.norm() > 0.0 && n0 != n1);
}

#[test]
fn a_command_delay_drives_the_previous_command_first() {
    let m = model(FlowMap::zero(), linear_only(), 3);
    let start = m.initial_state(ra_start(), 0.3);
    let previous = currents(0.02, 9);
    let next = currents(-0.02, 9);
    let delay_s = 0.4 * FRAME_S;

    // Zero delay is exactly `step`.
    let (mut plain, mut undelayed) = (start.clone(), start.clone());
    m.step(&mut plain, &next, FRAME_S);
    m.step_with_command_delay(&mut undelayed, &previous, &next, FRAME_S, 0.0);
    assert_eq!(plain, undelayed);

    // A delay is the previous command for that long, then the new one for the rest.
    let (mut split, mut delayed) = (start.clone(), start.clone());
    m.step(&mut split, &previous, delay_s);
    m.step(&mut split, &next, FRAME_S - delay_s);
    m.step_with_command_delay(&mut delayed, &previous, &next, FRAME_S, delay_s);
    assert_eq!(split.position_m, delayed.position_m);
    assert_eq!(split.coil_currents_a, delayed.coil_currents_a);
    assert!((delayed.time_s - FRAME_S).abs() < 1e-12);
    assert_ne!(
        delayed.position_m, plain.position_m,
        "the delay changed nothing"
    );

    // A delay of the whole frame (or more) keeps the previous command for the frame.
    let (mut held, mut whole) = (start.clone(), start);
    m.step(&mut held, &previous, FRAME_S);
    m.step_with_command_delay(&mut whole, &previous, &next, FRAME_S, 2.0 * FRAME_S);
    assert_eq!(held.position_m, whole.position_m);
}

/// The drag tensor of `m`'s capsule at `heading_rad`: c⊥·I + (c∥ − c⊥)·a·aᵀ.
fn drag_tensor(m: &PlantModel, heading_rad: f64) -> nalgebra::Matrix2<f64> {
    let drag = m.axial_drag();
    let axis = Vector2::new(heading_rad.cos(), heading_rad.sin());
    nalgebra::Matrix2::identity() * drag.transverse_n_s_per_m
        + axis * axis.transpose() * (drag.axial_n_s_per_m - drag.transverse_n_s_per_m)
}

#[test]
fn a_cylinder_moves_along_its_axis_more_easily_than_across_it() {
    let cylinder = |floor_gap_m| PlantPhysicsConfig {
        drag_shape: millinav_plant::model::DragShape::Cylinder,
        floor_gap_m,
        ..linear_only()
    };
    let free = model(FlowMap::zero(), cylinder(None), 1);
    let paper = model(FlowMap::zero(), linear_only(), 1);
    let eq7 = paper.linear_drag();
    let drag = free.axial_drag();
    // Tirado & García de la Torre for p = 2.64: 1.49× and 1.74× Eq. 7.
    assert!((drag.axial_n_s_per_m / eq7 - 1.49).abs() < 0.01, "{drag:?}");
    assert!(
        (drag.transverse_n_s_per_m / eq7 - 1.74).abs() < 0.01,
        "{drag:?}"
    );
    // On a 3 µm film sliding along the axis costs ×25 Eq. 7, across it the sphere's ×4.2.
    let on_floor = model(FlowMap::zero(), cylinder(Some(3e-6)), 1);
    let drag = on_floor.axial_drag();
    assert!((drag.axial_n_s_per_m / eq7 - 25.4).abs() < 0.5, "{drag:?}");
    let sphere = fieldmaps::physics::wall_drag_factor_parallel(3e-6, 1.4e-3);
    assert!(
        (drag.transverse_n_s_per_m / eq7 / 1.74 - sphere).abs() < 0.02,
        "{drag:?}"
    );
    // A steady pull: the velocity is the tensor's inverse times the force at the capsule's
    // heading, off the force's direction where the pull is not along the axis.
    for m in [&free, &on_floor] {
        let mut s = m.initial_state(ra_start(), 0.3);
        for _ in 0..200 {
            m.step(&mut s, &currents(0.02, 9), FRAME_S);
        }
        let expected = drag_tensor(m, s.heading_rad)
            .try_inverse()
            .expect("positive drags")
            * s.last_magnetic_force_n;
        let rel = (s.velocity_mps - expected).norm() / expected.norm();
        assert!(expected.norm() > 1e-5, "test needs a real force");
        assert!(rel < 0.01, "relative error {rel}");
    }
}

#[test]
fn a_cylinder_on_the_floor_drifts_in_the_flow_faster_across_than_along_its_axis() {
    let uniform = FlowMap {
        velocity_mps: vec![Vector2::new(2e-3, 0.0); 4],
        ..FlowMap::zero()
    };
    let config = PlantPhysicsConfig {
        drag_shape: millinav_plant::model::DragShape::Cylinder,
        floor_gap_m: Some(3e-6),
        floor_flow_factor: Some(1.7),
        pulsation_amplitude: 0.0,
        ..steady_only(linear_only())
    };
    let m = model(uniform, config, 3);
    let eq7 = model(FlowMap::zero(), linear_only(), 3).linear_drag();
    let drift = |heading: f64| {
        let mut s = m.initial_state(ra_start(), heading);
        for _ in 0..100 {
            m.step(&mut s, &currents(0.0, 0), FRAME_S);
        }
        s.velocity_mps
    };
    let drag = m.axial_drag();
    let along = drift(0.0);
    let across = drift(std::f64::consts::FRAC_PI_2);
    let expected_along = 2e-3 * 1.7 * eq7 / drag.axial_n_s_per_m;
    let expected_across = 2e-3 * 1.7 * eq7 / drag.transverse_n_s_per_m;
    assert!((along.x / expected_along - 1.0).abs() < 0.01, "{along:?}");
    assert!(
        (across.x / expected_across - 1.0).abs() < 0.01,
        "{across:?}"
    );
    assert!(along.y.abs() < 1e-9 && across.y.abs() < 1e-9);
}
