//! The MPC's QP against independent computations: its objective against a forward simulation of
//! the model, its Clarabel solution against a closed-form solve (unconstrained) and against
//! projected-gradient descent (box-constrained small case).

use millinav_control::controllers::mpc::{Mpc, MpcGains, MpcQp};
use millinav_control::controllers::{ControlInput, NominalModel};
use millinav_control::reference::ReferenceSample;
use nalgebra::{DVector, Vector2};

const MODEL: NominalModel = NominalModel {
    mass_kg: 5.0e-5,
    linear_drag_n_s_per_m: 5.6e-4,
};

fn input() -> ControlInput {
    ControlInput {
        dt_s: 0.01,
        delay_s: 0.0,
        position_m: Vector2::new(-0.012, 0.006),
        velocity_mps: Vector2::new(2.0e-4, -1.0e-4),
        reference: ReferenceSample {
            position_m: Vector2::new(-0.011, 0.0055),
            velocity_mps: Vector2::new(4.0e-4, -3.0e-4),
            acceleration_mps2: Vector2::new(1.0e-5, 0.0),
            finished: false,
        },
        flow_mps: Vector2::new(0.01, -0.02),
        high_disturbance: false,
        predicted_disturbance_n: None,
        coil_gain_std: 0.0,
        unpredicted_motion_share: 0.0,
    }
}

/// J(x) by simulating M v̇ = F + c_t V − c_t v with fine RK4 steps (independent of the
/// condensed matrices), reference extrapolated the same way the MPC does.
fn simulated_cost(g: &MpcGains, inp: &ControlInput, x: &DVector<f64>) -> f64 {
    let dt = g.step_ms * 1e-3;
    let sub = 200;
    let h = dt / f64::from(sub);
    let (mut p, mut v) = (inp.position_m, inp.velocity_mps);
    let c = MODEL.linear_drag_n_s_per_m;
    let mut j = 0.0;
    for k in 0..g.horizon {
        let f = Vector2::new(x[2 * k], x[2 * k + 1]);
        let acc = |v: Vector2<f64>| (f + inp.flow_mps * c - v * c) / MODEL.mass_kg;
        for _ in 0..sub {
            let (k1p, k1v) = (v, acc(v));
            let (k2p, k2v) = (v + k1v * (0.5 * h), acc(v + k1v * (0.5 * h)));
            let (k3p, k3v) = (v + k2v * (0.5 * h), acc(v + k2v * (0.5 * h)));
            let (k4p, k4v) = (v + k3v * h, acc(v + k3v * h));
            p += (k1p + k2p * 2.0 + k3p * 2.0 + k4p) * (h / 6.0);
            v += (k1v + k2v * 2.0 + k3v * 2.0 + k4v) * (h / 6.0);
        }
        let t = (k + 1) as f64 * dt;
        let r = &inp.reference;
        let reference = r.position_m + r.velocity_mps * t + r.acceleration_mps2 * (0.5 * t * t);
        let e = reference - p;
        let w = if k + 1 == g.horizon {
            g.p_per_m2
        } else {
            g.q_per_m2
        };
        j += w[0] * e.x * e.x
            + w[1] * e.y * e.y
            + g.r_per_n2[0] * f.x * f.x
            + g.r_per_n2[1] * f.y * f.y;
    }
    j
}

#[test]
fn qp_objective_matches_forward_simulation() {
    let gains = MpcGains {
        max_force_n: Some(1.0e-3),
        ..MpcGains::default()
    };
    let mpc = Mpc::new(gains.clone(), MODEL);
    let inp = input();
    let qp = mpc.qp(&inp);
    let zero = DVector::zeros(2 * gains.horizon);
    let j0 = simulated_cost(&gains, &inp, &zero);
    let mut seed = 7u64;
    for _ in 0..3 {
        let x = DVector::from_fn(2 * gains.horizon, |_, _| {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2e-4
        });
        let sim = simulated_cost(&gains, &inp, &x) - j0;
        let quad = qp.objective(&x);
        eprintln!("ΔJ simulated {sim:.6e}, QP {quad:.6e}");
        assert!(
            (sim - quad).abs() <= 1e-6 * sim.abs().max(j0),
            "{sim} vs {quad}"
        );
    }
}

#[test]
fn unconstrained_solution_matches_closed_form() {
    // A bound far above any force the optimum asks for: no constraint is active.
    let gains = MpcGains {
        max_force_n: Some(0.1),
        ..MpcGains::default()
    };
    let mut mpc = Mpc::new(gains, MODEL);
    let qp = mpc.qp(&input());
    let x = mpc.solve(&qp).expect("clarabel solves");
    let closed = qp
        .hessian
        .clone()
        .cholesky()
        .expect("H is positive definite")
        .solve(&(-&qp.gradient));
    let rel = (&x - &closed).norm() / closed.norm();
    eprintln!(
        "|x| = {:.3e} N, relative difference {rel:.2e}",
        closed.norm()
    );
    assert!(closed.amax() < 0.01, "the bound must be inactive");
    assert!(rel < 1e-4, "relative difference {rel}");
    let (jx, jc) = (qp.objective(&x), qp.objective(&closed));
    assert!((jx - jc).abs() <= 1e-8 * jc.abs(), "{jx} vs {jc}");
}

/// FISTA with projection onto the box |x_i| ≤ b (the 4-sided polygon, axis-aligned).
fn projected_gradient(qp: &MpcQp, b: f64, iterations: usize) -> DVector<f64> {
    let l = qp.hessian.clone().symmetric_eigen().eigenvalues.amax();
    let project = |v: DVector<f64>| v.map(|e| e.clamp(-b, b));
    let mut x = DVector::zeros(qp.gradient.len());
    let mut y = x.clone();
    let mut t = 1.0f64;
    for _ in 0..iterations {
        let grad = &qp.hessian * &y + &qp.gradient;
        let next = project(&y - grad / l);
        let t_next = 0.5 * (1.0 + (1.0 + 4.0 * t * t).sqrt());
        y = &next + (&next - &x) * ((t - 1.0) / t_next);
        x = next;
        t = t_next;
    }
    x
}

#[test]
fn constrained_solution_matches_projected_gradient() {
    let gains = MpcGains {
        horizon: 5,
        polygon_sides: 4,
        max_force_n: Some(2.0e-5),
        ..MpcGains::default()
    };
    let mut mpc = Mpc::new(gains, MODEL);
    let qp = mpc.qp(&input());
    // Axis-aligned square: the normals are ±x, ±y and the bound is the half side.
    assert_eq!(qp.normals.len(), 4);
    let b = qp.bound_n;
    let x = mpc.solve(&qp).expect("clarabel solves");
    let reference = projected_gradient(&qp, b, 200_000);
    let active = reference
        .iter()
        .filter(|v| (v.abs() - b).abs() < 1e-3 * b)
        .count();
    eprintln!("bound {b:.3e} N, active {active}/{}, x = {x:?}", x.len());
    assert!(active > 0, "the test case must have active constraints");
    assert!(x.amax() <= b * (1.0 + 1e-6));
    let diff = (&x - &reference).amax();
    eprintln!(
        "reference {reference:?}\nmax difference {diff:.3e} N, J {:.9e} vs {:.9e}",
        qp.objective(&x),
        qp.objective(&reference)
    );
    assert!(
        diff < 1e-4 * b,
        "max difference {diff:.3e} N (bound {b:.3e} N)"
    );
    let (jx, jr) = (qp.objective(&x), qp.objective(&reference));
    assert!((jx - jr).abs() <= 1e-7 * jr.abs(), "{jx} vs {jr}");
}
