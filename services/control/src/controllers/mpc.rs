//! MPC baseline of paper Sec. II-C (Eq. 18–19): the nominal model M v̇ + c_t (v − V) = F over a
//! horizon of N steps of Δt, cost J = Σ_{k<N} (e_kᵀ Q e_k + F_kᵀ R F_k) + e_Nᵀ P e_N, force bounds
//! from the coil current limits, solved as a QP with Clarabel.
//!
//! The QP is condensed: the decision variable is the force sequence x = [F_0x, F_0y, …, F_{N−1}y]
//! and the predicted positions are affine in x (exact zero-order-hold discretisation of the
//! model, the flow estimate V held constant over the horizon). The future reference is
//! extrapolated from the current reference sample (position, velocity, acceleration), which is
//! exact on straight segments. Each F_k lies in a regular polygon inscribed in the circle
//! |F| ≤ F_max (default: octagon), F_max estimated from the current limits via the fieldmaps
//! allocation (or set in config).
//!
//! Warm start: Clarabel is an interior-point solver and has no primal/dual warm start. What is
//! reused instead: the Hessian and the constraints do not depend on the state, so the solver is
//! built (equilibration, KKT structure) once and only the linear term `q` is updated each step
//! (`DefaultSolver::update_q`).

use clarabel::algebra::CscMatrix;
use clarabel::solver::{DefaultSettings, DefaultSolver, IPSolver, NonnegativeConeT, SolverStatus};
use fieldmaps::allocation::{actuation_matrix_from, guaranteed_force, ForceBoundError};
use fieldmaps::coils::CoilField;
use fieldmaps::physics;
use fieldmaps::rig::CoilLimits;
use nalgebra::{DMatrix, DVector, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::interface::{ControlInput, ControlTerms, Controller, NominalModel};

/// `[control.mpc]` gains. Units: Q and P in 1/m², R in 1/N² (J is dimensionless).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MpcGains {
    /// Prediction horizon N (paper: 20).
    pub horizon: usize,
    /// Prediction step Δt (paper: 40 ms).
    pub step_ms: f64,
    /// Stage weight on the position error, per axis.
    pub q_per_m2: [f64; 2],
    /// Weight on the force, per axis.
    pub r_per_n2: [f64; 2],
    /// Terminal weight on the position error, per axis.
    pub p_per_m2: [f64; 2],
    /// Largest force magnitude; none = estimated from the coil current limits.
    pub max_force_n: Option<f64>,
    /// Sides of the force polygon inscribed in |F| ≤ F_max (4 = a box, ≥ 3).
    pub polygon_sides: usize,
    /// Use the flow estimate in the prediction (the paper's drag term with V).
    pub flow_feedforward: bool,
}

impl Default for MpcGains {
    /// The paper gives N and Δt but no weights. Ours: R/Q = 4e2 m²/N² (≈ the PID's stiffness
    /// Kp = 5e-2 N/m at steady state, since the unconstrained optimum of qe² + rF² has
    /// F/e ≈ √(q/r)), and a terminal weight 10 Q.
    fn default() -> Self {
        Self {
            horizon: 20,
            step_ms: 40.0,
            q_per_m2: [1.0, 1.0],
            r_per_n2: [4.0e2, 4.0e2],
            p_per_m2: [10.0, 10.0],
            max_force_n: None,
            polygon_sides: 8,
            flow_feedforward: true,
        }
    }
}

impl MpcGains {
    /// Invalid values replaced by the defaults (with a warning): the controller must never
    /// panic or produce NaN on a bad config.
    pub fn sanitized(&self) -> Self {
        let d = Self::default();
        let mut g = self.clone();
        let mut fixed = Vec::new();
        if !(1..=200).contains(&g.horizon) {
            g.horizon = d.horizon;
            fixed.push("horizon (1..=200)");
        }
        if !(g.step_ms.is_finite() && g.step_ms > 0.0) {
            g.step_ms = d.step_ms;
            fixed.push("step_ms (> 0)");
        }
        let ok = |w: &[f64; 2], strict: bool| {
            w.iter()
                .all(|v| v.is_finite() && if strict { *v > 0.0 } else { *v >= 0.0 })
        };
        if !ok(&g.q_per_m2, false) {
            g.q_per_m2 = d.q_per_m2;
            fixed.push("q_per_m2 (>= 0)");
        }
        if !ok(&g.r_per_n2, true) {
            g.r_per_n2 = d.r_per_n2;
            fixed.push("r_per_n2 (> 0)");
        }
        if !ok(&g.p_per_m2, false) {
            g.p_per_m2 = d.p_per_m2;
            fixed.push("p_per_m2 (>= 0)");
        }
        if g.max_force_n.is_some_and(|f| !(f.is_finite() && f > 0.0)) {
            g.max_force_n = None;
            fixed.push("max_force_n (> 0)");
        }
        if !(3..=64).contains(&g.polygon_sides) {
            g.polygon_sides = d.polygon_sides;
            fixed.push("polygon_sides (3..=64)");
        }
        if !fixed.is_empty() {
            tracing::warn!(?fixed, "invalid MPC gains replaced by defaults");
        }
        g
    }

    /// These gains with `max_force_n` filled in from the rig's current limits when unset.
    pub fn resolved(
        &self,
        site: &ForceSite<'_>,
        limits: &CoilLimits,
        field_t: &Vector2<f64>,
        omega0: f64,
    ) -> Self {
        let mut g = self.sanitized();
        if g.max_force_n.is_none() {
            g.max_force_n = Some(estimate_max_force_n(site, limits, field_t, omega0));
        }
        g
    }
}

/// Where and with what the force bound is estimated: the rig's coil model, the coils the
/// allocation drives, the robot's magnet, and the points of the path to be followed.
pub struct ForceSite<'a> {
    pub coils: &'a dyn CoilField,
    pub coil_ids: &'a [usize],
    pub magnet_moment_am2: f64,
    pub points_m: &'a [Vector2<f64>],
}

/// Mass the model falls back to when its own is not finite and positive, kg.
const MIN_MASS_KG: f64 = 1e-9;

/// Fallback force bound when the estimate is degenerate (the paper's 0.37 mN at 0.43 T/m).
pub const FALLBACK_MAX_FORCE_N: f64 = 3.7e-4;

/// Directions over which `estimate_max_force_n` takes its minimum.
const FORCE_BOUND_DIRECTIONS: u32 = 16;

/// Largest force magnitude the allocation's coils can produce in *every* direction while also
/// holding the orientation field `field_t`, within `limits` (per-coil current and total power),
/// taken as the minimum over 16 directions and the site's points (the path's waypoints), with
/// the control loop's pseudo-inverse allocation (`fieldmaps::allocation::guaranteed_force`).
pub fn estimate_max_force_n(
    site: &ForceSite<'_>,
    limits: &CoilLimits,
    field_t: &Vector2<f64>,
    omega0: f64,
) -> f64 {
    if limits.validate().is_err() || !(omega0.is_finite() && omega0 > 0.0) {
        return FALLBACK_MAX_FORCE_N;
    }
    if !(field_t.x.is_finite() && field_t.y.is_finite()) {
        return FALLBACK_MAX_FORCE_N;
    }
    let heading = if field_t.norm() > 0.0 {
        field_t.y.atan2(field_t.x)
    } else {
        std::f64::consts::FRAC_PI_4
    };
    let moment = physics::in_plane_moment(site.magnet_moment_am2, heading);
    let feasible = |i: &DVector<f64>| {
        i.amax() <= limits.max_current_a
            && i.norm_squared() * limits.coil_resistance_ohm <= limits.max_total_power_w
    };
    let mut best = f64::INFINITY;
    for p in site.points_m {
        let p3 = Vector3::new(p.x, p.y, 0.0);
        let a = actuation_matrix_from(site.coils, &p3, &moment, site.coil_ids, omega0);
        let field_rhs = DVector::from_vec(vec![0.0, 0.0, omega0 * field_t.x, omega0 * field_t.y]);
        match guaranteed_force(&a, &field_rhs, FORCE_BOUND_DIRECTIONS, feasible) {
            Ok(force) => best = best.min(force),
            Err(ForceBoundError::FieldInfeasible) => return FALLBACK_MAX_FORCE_N,
            // A point where the coils cannot act says nothing about the others.
            Err(ForceBoundError::Allocation(_)) => continue,
        }
    }
    if best.is_finite() && best > 0.0 {
        best
    } else {
        FALLBACK_MAX_FORCE_N
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MpcError {
    #[error("QP solver setup failed: {0}")]
    Setup(String),
    #[error("QP not solved: {0}")]
    NotSolved(String),
    #[error("QP data has the wrong size: expected {expected}, got {got}")]
    Size { expected: usize, got: usize },
    #[error("QP data is not finite")]
    NonFinite,
}

/// The condensed QP of one MPC step, in SI (forces in N):
/// minimise ½ xᵀ H x + gᵀ x over x = [F_0x, F_0y, …, F_{N−1}x, F_{N−1}y]
/// subject to nᵀ F_k ≤ `bound_n` for every `normals` n and every k.
#[derive(Debug, Clone)]
pub struct MpcQp {
    pub hessian: DMatrix<f64>,
    pub gradient: DVector<f64>,
    pub normals: Vec<Vector2<f64>>,
    pub bound_n: f64,
}

impl MpcQp {
    pub fn objective(&self, x: &DVector<f64>) -> f64 {
        0.5 * x.dot(&(&self.hessian * x)) + self.gradient.dot(x)
    }
}

/// Exact zero-order-hold discretisation of M v̇ = u − c v for one axis over `dt`:
/// [p, v]_{k+1} = A [p, v]_k + B u_k.
fn discretize(mass: f64, drag: f64, dt: f64) -> ([[f64; 2]; 2], [f64; 2]) {
    let a = drag / mass;
    if a * dt < 1e-9 {
        // Double integrator (no drag).
        return ([[1.0, dt], [0.0, 1.0]], [0.5 * dt * dt / mass, dt / mass]);
    }
    let one_minus_phi = -(-a * dt).exp_m1();
    let phi = 1.0 - one_minus_phi;
    (
        [[1.0, one_minus_phi / a], [0.0, phi]],
        [(dt - one_minus_phi / a) / drag, one_minus_phi / drag],
    )
}

/// MPC force controller (`controller = "mpc"`).
pub struct Mpc {
    gains: MpcGains,
    model: NominalModel,
    max_force_n: f64,
    /// Per axis and per k = 1..N: p_k = free_p[k]·[p0, v0] + Σ_j g[k][j] u_j (u = F + c V).
    free: Vec<[f64; 2]>,
    g: DMatrix<f64>,
    hessian: DMatrix<f64>,
    normals: Vec<Vector2<f64>>,
    /// Internal variable scaling: x̃ = x / force_scale, J̃ = J / cost_scale.
    force_scale: f64,
    cost_scale: f64,
    solver: Option<DefaultSolver<f64>>,
    last_solution: Option<DVector<f64>>,
    /// Solves that fell back to the clipped unconstrained solution.
    pub fallbacks: u64,
}

impl Mpc {
    /// `gains.max_force_n` unset means the fallback bound; use [`MpcGains::resolved`] first to
    /// estimate it from the rig.
    pub fn new(gains: MpcGains, model: NominalModel) -> Self {
        let gains = gains.sanitized();
        let max_force_n = gains.max_force_n.unwrap_or(FALLBACK_MAX_FORCE_N);
        let n = gains.horizon;
        let dt = gains.step_ms * 1e-3;
        // A non-physical mass becomes a negligible one: drag alone then sets the dynamics.
        let mass = if model.mass_kg.is_finite() && model.mass_kg > 0.0 {
            model.mass_kg
        } else {
            MIN_MASS_KG
        };
        let drag = if model.linear_drag_n_s_per_m.is_finite() {
            model.linear_drag_n_s_per_m.max(0.0)
        } else {
            0.0
        };
        let (ad, bd) = discretize(mass, drag, dt);
        // Free response rows and the input-to-position matrix G (N × N, lower triangular).
        let mut free = Vec::with_capacity(n);
        let mut state_map = [[1.0, 0.0], [0.0, 1.0]]; // A^k
        for _ in 0..n {
            state_map = mat2_mul(&ad, &state_map);
            free.push(state_map[0]);
        }
        let mut g = DMatrix::zeros(n, n);
        for j in 0..n {
            // Response to a unit input at step j: x_{j+1} = B, then x_{k+1} = A x_k.
            let mut x = bd;
            for k in j..n {
                if k > j {
                    x = [
                        ad[0][0] * x[0] + ad[0][1] * x[1],
                        ad[1][0] * x[0] + ad[1][1] * x[1],
                    ];
                }
                g[(k, j)] = x[0];
            }
        }
        let mut hessian = DMatrix::zeros(2 * n, 2 * n);
        for axis in 0..2 {
            for i in 0..n {
                for j in 0..n {
                    let mut h = 0.0;
                    for k in 0..n {
                        h += weight(&gains, k, n, axis) * g[(k, i)] * g[(k, j)];
                    }
                    if i == j {
                        h += gains.r_per_n2[axis];
                    }
                    hessian[(2 * i + axis, 2 * j + axis)] = 2.0 * h;
                }
            }
        }
        let sides = gains.polygon_sides;
        let normals = (0..sides)
            .map(|s| {
                let th = s as f64 * std::f64::consts::TAU / sides as f64;
                Vector2::new(th.cos(), th.sin())
            })
            .collect();
        let force_scale = max_force_n;
        let scaled_diag_max = hessian.diagonal().amax() * force_scale * force_scale;
        let cost_scale = if scaled_diag_max.is_finite() && scaled_diag_max > 0.0 {
            scaled_diag_max
        } else {
            1.0
        };
        let mut mpc = Self {
            gains,
            model: NominalModel {
                mass_kg: mass,
                linear_drag_n_s_per_m: drag,
            },
            max_force_n,
            free,
            g,
            hessian,
            normals,
            force_scale,
            cost_scale,
            solver: None,
            last_solution: None,
            fallbacks: 0,
        };
        match mpc.build_solver() {
            Ok(s) => mpc.solver = Some(s),
            Err(e) => tracing::error!("MPC: {e}; using the clipped unconstrained solution"),
        }
        mpc
    }

    pub fn gains(&self) -> &MpcGains {
        &self.gains
    }

    pub fn max_force_n(&self) -> f64 {
        self.max_force_n
    }

    /// Bound of nᵀF per polygon side: the polygon's vertices lie on |F| = F_max.
    fn side_bound(&self) -> f64 {
        self.max_force_n * (std::f64::consts::PI / self.gains.polygon_sides as f64).cos()
    }

    fn build_solver(&self) -> Result<DefaultSolver<f64>, MpcError> {
        let nv = self.hessian.nrows();
        let s = self.force_scale * self.force_scale / self.cost_scale;
        // Upper triangle of the scaled Hessian, column-compressed.
        let mut colptr = vec![0];
        let mut rowval = Vec::new();
        let mut nzval = Vec::new();
        for j in 0..nv {
            for i in 0..=j {
                let v = self.hessian[(i, j)] * s;
                if v != 0.0 {
                    rowval.push(i);
                    nzval.push(v);
                }
            }
            colptr.push(rowval.len());
        }
        let p = CscMatrix::new(nv, nv, colptr, rowval, nzval);
        // Constraint rows: for step k and side s, nᵀ x̃_k ≤ bound / force_scale.
        let sides = self.normals.len();
        let rows = sides * self.gains.horizon;
        let mut colptr = vec![0];
        let mut rowval = Vec::new();
        let mut nzval = Vec::new();
        for var in 0..nv {
            let (k, axis) = (var / 2, var % 2);
            for (si, n) in self.normals.iter().enumerate() {
                let v = n[axis];
                if v.abs() > 1e-15 {
                    rowval.push(k * sides + si);
                    nzval.push(v);
                }
            }
            colptr.push(rowval.len());
        }
        let a = CscMatrix::new(rows, nv, colptr, rowval, nzval);
        let b = vec![self.side_bound() / self.force_scale; rows];
        let q = vec![0.0; nv];
        let settings = DefaultSettings {
            verbose: false,
            presolve_enable: false,
            input_sparse_dropzeros: false,
            max_iter: 100,
            ..DefaultSettings::default()
        };
        DefaultSolver::new(&p, &q, &a, &b, &[NonnegativeConeT(rows)], settings)
            .map_err(|e| MpcError::Setup(e.to_string()))
    }

    /// The QP for one step (SI units).
    pub fn qp(&self, input: &ControlInput) -> MpcQp {
        let n = self.gains.horizon;
        let dt = self.gains.step_ms * 1e-3;
        let c = self.model.linear_drag_n_s_per_m;
        let flow = if self.gains.flow_feedforward && finite2(&input.flow_mps) {
            input.flow_mps
        } else {
            Vector2::zeros()
        };
        let r = &input.reference;
        let mut gradient = DVector::zeros(2 * n);
        for axis in 0..2 {
            let (p0, v0) = (input.position_m[axis], input.velocity_mps[axis]);
            // The drag on the flow enters as a constant input c·V.
            let flow_input = c * flow[axis];
            for k in 0..n {
                let t = (k + 1) as f64 * dt;
                let reference = r.position_m[axis]
                    + r.velocity_mps[axis] * t
                    + 0.5 * r.acceleration_mps2[axis] * t * t;
                let forced: f64 = (0..=k).map(|j| self.g[(k, j)]).sum::<f64>() * flow_input;
                let predicted_free = self.free[k][0] * p0 + self.free[k][1] * v0 + forced;
                let d = reference - predicted_free;
                let w = weight(&self.gains, k, n, axis);
                for i in 0..=k {
                    gradient[2 * i + axis] -= 2.0 * w * self.g[(k, i)] * d;
                }
            }
        }
        MpcQp {
            hessian: self.hessian.clone(),
            gradient,
            normals: self.normals.clone(),
            bound_n: self.side_bound(),
        }
    }

    /// Solves `qp` (whose Hessian and constraints must be this controller's, i.e. from
    /// [`Mpc::qp`]) with Clarabel; returns the force sequence x (N).
    pub fn solve(&mut self, qp: &MpcQp) -> Result<DVector<f64>, MpcError> {
        let nv = self.hessian.nrows();
        if qp.gradient.len() != nv {
            return Err(MpcError::Size {
                expected: nv,
                got: qp.gradient.len(),
            });
        }
        if qp.gradient.iter().any(|v| !v.is_finite()) {
            return Err(MpcError::NonFinite);
        }
        let Some(solver) = self.solver.as_mut() else {
            return Err(MpcError::Setup("no solver".into()));
        };
        let q: Vec<f64> = qp
            .gradient
            .iter()
            .map(|g| g * self.force_scale / self.cost_scale)
            .collect();
        solver
            .update_q(&q)
            .map_err(|e| MpcError::Setup(e.to_string()))?;
        solver.solve();
        let status = solver.solution.status;
        if !matches!(status, SolverStatus::Solved | SolverStatus::AlmostSolved) {
            return Err(MpcError::NotSolved(format!("{status:?}")));
        }
        let x = DVector::from_iterator(nv, solver.solution.x.iter().map(|v| v * self.force_scale));
        if x.iter().any(|v| !v.is_finite()) {
            return Err(MpcError::NonFinite);
        }
        Ok(x)
    }

    /// Unconstrained optimum with the first force pulled radially into the polygon.
    fn fallback(&self, qp: &MpcQp) -> Vector2<f64> {
        let Some(chol) = qp.hessian.clone().cholesky() else {
            return Vector2::zeros();
        };
        let x = chol.solve(&(-&qp.gradient));
        let f = Vector2::new(x[0], x[1]);
        let worst = self.normals.iter().map(|n| n.dot(&f)).fold(0.0, f64::max);
        let bound = self.side_bound();
        let f = if worst > bound {
            f * (bound / worst)
        } else {
            f
        };
        if finite2(&f) {
            f
        } else {
            Vector2::zeros()
        }
    }
}

fn finite2(v: &Vector2<f64>) -> bool {
    v.x.is_finite() && v.y.is_finite()
}

fn weight(g: &MpcGains, k: usize, n: usize, axis: usize) -> f64 {
    if k + 1 == n {
        g.p_per_m2[axis]
    } else {
        g.q_per_m2[axis]
    }
}

fn mat2_mul(a: &[[f64; 2]; 2], b: &[[f64; 2]; 2]) -> [[f64; 2]; 2] {
    [
        [
            a[0][0] * b[0][0] + a[0][1] * b[1][0],
            a[0][0] * b[0][1] + a[0][1] * b[1][1],
        ],
        [
            a[1][0] * b[0][0] + a[1][1] * b[1][0],
            a[1][0] * b[0][1] + a[1][1] * b[1][1],
        ],
    ]
}

impl Controller for Mpc {
    fn name(&self) -> &'static str {
        "mpc"
    }
    fn id(&self) -> u32 {
        4
    }
    fn update(&mut self, input: &ControlInput) -> (Vector2<f64>, ControlTerms) {
        let e = input.reference.position_m - input.position_m;
        let e_dot = input.reference.velocity_mps - input.velocity_mps;
        let terms = ControlTerms {
            error_m: e,
            error_rate_mps: e_dot,
            ..Default::default()
        };
        let usable = finite2(&input.position_m)
            && finite2(&input.velocity_mps)
            && finite2(&input.reference.position_m)
            && finite2(&input.reference.velocity_mps)
            && finite2(&input.reference.acceleration_mps2);
        if !usable {
            return (Vector2::zeros(), terms);
        }
        let qp = self.qp(input);
        let force = match self.solve(&qp) {
            Ok(x) => {
                let f = Vector2::new(x[0], x[1]);
                self.last_solution = Some(x);
                f
            }
            Err(err) => {
                self.fallbacks += 1;
                if self.fallbacks == 1 || self.fallbacks.is_multiple_of(100) {
                    tracing::warn!(%err, fallbacks = self.fallbacks, "MPC QP failed; clipped fallback");
                }
                self.fallback(&qp)
            }
        };
        (force, terms)
    }
    fn reset(&mut self) {
        self.last_solution = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn discretization_matches_fine_integration() {
        let (m, c, dt) = (5e-5, 5.6e-4, 0.04);
        let (a, b) = discretize(m, c, dt);
        let (p0, v0, u) = (0.001, 0.002, 1e-4);
        // RK4 on (p, v) with v̇ = (u − c v)/m.
        let (mut p, mut v) = (p0, v0);
        let steps = 1000;
        let h = dt / f64::from(steps);
        let acc = |v: f64| (u - c * v) / m;
        for _ in 0..steps {
            let (k1p, k1v) = (v, acc(v));
            let (k2p, k2v) = (v + 0.5 * h * k1v, acc(v + 0.5 * h * k1v));
            let (k3p, k3v) = (v + 0.5 * h * k2v, acc(v + 0.5 * h * k2v));
            let (k4p, k4v) = (v + h * k3v, acc(v + h * k3v));
            p += h / 6.0 * (k1p + 2.0 * k2p + 2.0 * k3p + k4p);
            v += h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v);
        }
        let p1 = a[0][0] * p0 + a[0][1] * v0 + b[0] * u;
        let v1 = a[1][0] * p0 + a[1][1] * v0 + b[1] * u;
        assert!((p1 - p).abs() < 1e-12 * p.abs().max(1.0), "{p1} vs {p}");
        assert!((v1 - v).abs() < 1e-10 * v.abs().max(1e-3), "{v1} vs {v}");
    }

    #[test]
    fn force_estimate_is_physical() {
        let rig = fieldmaps::rigfile::Rig::load_paper().unwrap();
        let points = [
            Vector2::new(-0.016, 0.012),
            Vector2::new(-0.006, -0.006),
            Vector2::new(0.004, -0.024),
        ];
        let site = ForceSite {
            coils: &rig.coil_field,
            coil_ids: &rig.allocation_coils,
            magnet_moment_am2: rig.robot.magnet_moment_am2,
            points_m: &points,
        };
        let f = estimate_max_force_n(
            &site,
            &rig.coil_limits(),
            &(Vector2::new(1e-3, 1e-3) * std::f64::consts::FRAC_1_SQRT_2),
            0.05,
        );
        // With the fieldmaps coil model and 6 A per coil the pseudo-inverse allocation reaches
        // 0.05–0.2 mN per direction at canal points; the bound is the smallest (≈ 0.037 mN).
        assert!(f > 1e-5 && f < 1e-3, "{f}");
    }

    #[test]
    fn bad_gains_never_panic() {
        let g = MpcGains {
            horizon: 0,
            step_ms: f64::NAN,
            r_per_n2: [0.0, -1.0],
            max_force_n: Some(-1.0),
            polygon_sides: 1,
            ..MpcGains::default()
        };
        let s = g.sanitized();
        assert_eq!(s.horizon, 20);
        assert_eq!(s.polygon_sides, 8);
        assert!(s.max_force_n.is_none());
        let _ = Mpc::new(
            g,
            NominalModel {
                mass_kg: f64::NAN,
                linear_drag_n_s_per_m: f64::NAN,
            },
        );
    }
}
