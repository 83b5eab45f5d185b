//! Current allocation: paper Eq. 2 (actuation matrix), Eq. 3–4 (SVD pseudo-inverse), the
//! uniform current/power limiting that keeps the commanded direction of C, and a constrained
//! allocation (second-order cone program solved with Clarabel) that meets C exactly whenever
//! the per-coil and total-power limits allow it and otherwise returns the best limited fit.

use nalgebra::{DMatrix, DVector, Vector3};
use thiserror::Error;

use crate::coils::{CoilField, CoilSystem};
use crate::physics::magnetic_force;
use crate::rig::CoilLimits;

/// Singular values below `DEFAULT_RCOND · σ_max` are treated as zero in [`allocate_pinv`].
pub const DEFAULT_RCOND: f64 = 1e-9;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum AllocationError {
    #[error("actuation matrix has {rows} rows but the command has {len} entries")]
    DimensionMismatch { rows: usize, len: usize },
    #[error("actuation matrix or command contains NaN/inf")]
    NonFinite,
    #[error("actuation matrix is empty or zero (no coil can act)")]
    Degenerate,
    #[error("SVD did not converge")]
    SvdFailed,
    #[error("invalid tolerance {0}")]
    BadTolerance(f64),
    #[error("invalid coil limits: {0}")]
    BadLimits(String),
    #[error("invalid allocation settings: {0}")]
    BadSettings(&'static str),
}

/// Paper Eq. 2: the 4 × n map from the currents of `coil_ids` to
/// C = [F_x, F_y, ω0 B_x, ω0 B_y] for a dipole `moment` at `p`.
///
/// Column k: [mᵀ ∂B̃_k/∂x, mᵀ ∂B̃_k/∂y, ω0 B̃_kx, ω0 B̃_ky] with B̃_k the field of coil
/// `coil_ids[k]` per ampere. `ω0` (paper: "a unit conversion factor", N/T) balances field rows
/// against force rows in the least-norm solution. Unknown coil ids give zero columns (check
/// them once with [`CoilSystem::check_ids`]).
pub fn actuation_matrix(
    coils: &CoilSystem,
    p: &Vector3<f64>,
    moment: &Vector3<f64>,
    coil_ids: &[usize],
    omega0: f64,
) -> DMatrix<f64> {
    actuation_matrix_from(coils, p, moment, coil_ids, omega0)
}

/// [`actuation_matrix`] for any coil-field source, e.g. the interpolated grid maps
/// ([`crate::fieldmap::CoilFieldMaps`]) instead of the direct model.
pub fn actuation_matrix_from<F: CoilField + ?Sized>(
    coils: &F,
    p: &Vector3<f64>,
    moment: &Vector3<f64>,
    coil_ids: &[usize],
    omega0: f64,
) -> DMatrix<f64> {
    let mut a = DMatrix::zeros(4, coil_ids.len());
    for (k, &id) in coil_ids.iter().enumerate() {
        let (b, g) = coils.field_and_gradient_per_amp(id, p);
        let f = magnetic_force(moment, &g);
        a[(0, k)] = f.x;
        a[(1, k)] = f.y;
        a[(2, k)] = omega0 * b.x;
        a[(3, k)] = omega0 * b.y;
    }
    a
}

/// A·I = C must be well formed: one row of A per entry of C, and only finite numbers.
fn check_command(a: &DMatrix<f64>, c: &DVector<f64>) -> Result<(), AllocationError> {
    if a.nrows() != c.len() {
        return Err(AllocationError::DimensionMismatch {
            rows: a.nrows(),
            len: c.len(),
        });
    }
    if a.iter().chain(c.iter()).any(|v| !v.is_finite()) {
        return Err(AllocationError::NonFinite);
    }
    Ok(())
}

/// Why [`guaranteed_force`] has no answer.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum ForceBoundError {
    #[error("the orientation field alone exceeds the limits")]
    FieldInfeasible,
    #[error(transparent)]
    Allocation(#[from] AllocationError),
}

/// Bisection steps on the force scale α ∈ [0, 1]: 60 halvings reach the f64 resolution of α.
const FORCE_BISECTION_STEPS: u32 = 60;

/// The largest force magnitude (N, at most 1 N) the pseudo-inverse allocation of `a` reaches in
/// *every* one of `directions` evenly spaced in-plane directions while also producing the
/// field rows `field_rhs` (`[0, 0, ω0·Bx, ω0·By]`), with the currents within `feasible`. For
/// each direction d the currents are I(α) = pinv(A)·(field_rhs + α [d, 0, 0]); the feasible α
/// form an interval containing 0 when the field alone is feasible, so bisection finds its end.
pub fn guaranteed_force(
    a: &DMatrix<f64>,
    field_rhs: &DVector<f64>,
    directions: u32,
    feasible: impl Fn(&DVector<f64>) -> bool,
) -> Result<f64, ForceBoundError> {
    let i_field = allocate_pinv(a, field_rhs)?;
    if !feasible(&i_field) {
        return Err(ForceBoundError::FieldInfeasible);
    }
    let mut best = 1.0f64;
    for k in 0..directions.max(1) {
        let th = f64::from(k) * std::f64::consts::TAU / f64::from(directions.max(1));
        let unit = DVector::from_vec(vec![th.cos(), th.sin(), 0.0, 0.0]);
        let i_unit = allocate_pinv(a, &unit)?;
        let (mut lo, mut hi) = (0.0, 1.0);
        if feasible(&(&i_field + &i_unit * hi)) {
            continue;
        }
        for _ in 0..FORCE_BISECTION_STEPS {
            let mid = 0.5 * (lo + hi);
            if feasible(&(&i_field + &i_unit * mid)) {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        best = best.min(lo);
    }
    Ok(best)
}

/// Least-norm currents I = W Σ⁺ Uᵀ C (paper Eq. 3–4), with [`DEFAULT_RCOND`].
pub fn allocate_pinv(a: &DMatrix<f64>, c: &DVector<f64>) -> Result<DVector<f64>, AllocationError> {
    allocate_pinv_rcond(a, c, DEFAULT_RCOND)
}

/// [`allocate_pinv`] with singular values below `rcond · σ_max` dropped (rather than inverted
/// into huge currents along a direction the coils can barely produce).
pub fn allocate_pinv_rcond(
    a: &DMatrix<f64>,
    c: &DVector<f64>,
    rcond: f64,
) -> Result<DVector<f64>, AllocationError> {
    if !(rcond.is_finite() && (0.0..1.0).contains(&rcond)) {
        return Err(AllocationError::BadTolerance(rcond));
    }
    check_command(a, c)?;
    if a.is_empty() {
        return Err(AllocationError::Degenerate);
    }
    let svd = a
        .clone()
        .try_svd(true, true, f64::EPSILON, 1000)
        .ok_or(AllocationError::SvdFailed)?;
    let (Some(u), Some(v_t)) = (svd.u.as_ref(), svd.v_t.as_ref()) else {
        return Err(AllocationError::SvdFailed);
    };
    let s_max = svd.singular_values.max();
    if s_max.is_nan() || s_max <= 0.0 {
        return Err(AllocationError::Degenerate);
    }
    let cutoff = rcond * s_max;
    // Σ⁺ Uᵀ C, then W (= V) times that.
    let mut y = u.tr_mul(c);
    for (yi, &s) in y.iter_mut().zip(svd.singular_values.iter()) {
        *yi = if s > cutoff { *yi / s } else { 0.0 };
    }
    Ok(v_t.tr_mul(&y))
}

/// Per-coil ratings of the coils an allocation drives (in its column order): each coil's
/// current limit and resistance, and the total power budget over them.
#[derive(Debug, Clone, PartialEq)]
pub struct CoilRatings {
    pub max_current_a: DVector<f64>,
    pub resistance_ohm: DVector<f64>,
    pub max_total_power_w: f64,
}

impl CoilRatings {
    /// `n` coils that share one rating.
    pub fn uniform(limits: &CoilLimits, n: usize) -> Self {
        Self {
            max_current_a: DVector::from_element(n, limits.max_current_a),
            resistance_ohm: DVector::from_element(n, limits.coil_resistance_ohm),
            max_total_power_w: limits.max_total_power_w,
        }
    }

    pub fn len(&self) -> usize {
        self.max_current_a.len()
    }

    pub fn is_empty(&self) -> bool {
        self.max_current_a.is_empty()
    }

    fn valid(&self) -> Result<(), AllocationError> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if self.resistance_ohm.len() != self.len() {
            return Err(AllocationError::BadLimits(
                "one resistance per current limit".into(),
            ));
        }
        if !positive(self.max_total_power_w)
            || !self.max_current_a.iter().all(|&v| positive(v))
            || !self.resistance_ohm.iter().all(|&v| positive(v))
        {
            return Err(AllocationError::BadLimits(
                "current limits, resistances and the power budget must be finite and > 0".into(),
            ));
        }
        Ok(())
    }

    /// The same limits in the model's effective currents I·g(I) of saturating coils (`curves`
    /// in this order; `None` for a linear coil): the current limit becomes I_max·g(I_max) and
    /// the resistance R / g(I_max)², exact at the limit and conservative below it for a gain that
    /// falls with current.
    pub fn effective(&self, curves: &[Option<crate::rig::SaturationCurve>]) -> Self {
        let mut out = self.clone();
        for (k, curve) in curves.iter().enumerate().take(self.len()) {
            if let Some(curve) = curve {
                let g = curve.gain(self.max_current_a[k]);
                out.max_current_a[k] = self.max_current_a[k] * g;
                out.resistance_ohm[k] = self.resistance_ohm[k] / (g * g);
            }
        }
        out
    }

    /// Σ I_k² R_k, W.
    pub fn power_w(&self, currents: &DVector<f64>) -> f64 {
        currents
            .iter()
            .zip(self.resistance_ohm.iter())
            .map(|(i, r)| i * i * r)
            .sum()
    }
}

/// Scale all currents by one factor s ≤ 1 so that no |I_k| exceeds `max_current_a` and
/// Σ I_k² R ≤ `max_total_power_w`. Uniform scaling keeps the direction of A·I (the commanded
/// force/field direction) and only shortens it. Returns true if the currents were changed.
///
/// Non-finite currents or invalid limits zero every current (the safe state) and return true.
pub fn clamp_to_limits(currents: &mut DVector<f64>, limits: &CoilLimits) -> bool {
    if limits.validate().is_err() {
        let changed = currents.iter().any(|&i| i != 0.0);
        currents.fill(0.0);
        return changed;
    }
    clamp_to_ratings(currents, &CoilRatings::uniform(limits, currents.len()))
}

/// [`clamp_to_limits`] with each coil's own current limit and resistance.
pub fn clamp_to_ratings(currents: &mut DVector<f64>, ratings: &CoilRatings) -> bool {
    if ratings.valid().is_err()
        || ratings.len() != currents.len()
        || currents.iter().any(|i| !i.is_finite())
    {
        let changed = currents.iter().any(|&i| i != 0.0);
        currents.fill(0.0);
        return changed;
    }
    let peak_ratio = currents
        .iter()
        .zip(ratings.max_current_a.iter())
        .map(|(i, m)| i.abs() / m)
        .fold(0.0, f64::max);
    let power = ratings.power_w(currents);
    let mut scale: f64 = 1.0;
    if peak_ratio > 1.0 {
        scale = scale.min(1.0 / peak_ratio);
    }
    if power > ratings.max_total_power_w {
        scale = scale.min((ratings.max_total_power_w / power).sqrt());
    }
    if scale >= 1.0 {
        return false;
    }
    // A hair under the exact ratio so rounding can never land above a limit.
    *currents *= scale * (1.0 - 1e-12);
    true
}

/// Pseudo-inverse allocation followed by limiting.
#[derive(Debug, Clone, PartialEq)]
pub struct Allocation {
    pub currents_a: DVector<f64>,
    /// Factor applied by [`clamp_to_limits`] (1 when no limit was hit): A·I = scale · C for a
    /// feasible C.
    pub scale: f64,
}

/// [`allocate_pinv`] then [`clamp_to_limits`].
pub fn allocate_limited(
    a: &DMatrix<f64>,
    c: &DVector<f64>,
    limits: &CoilLimits,
) -> Result<Allocation, AllocationError> {
    limits
        .validate()
        .map_err(|e| AllocationError::BadLimits(e.to_string()))?;
    allocate_limited_rated(a, c, &CoilRatings::uniform(limits, a.ncols()))
}

/// [`allocate_pinv`] then [`clamp_to_ratings`].
pub fn allocate_limited_rated(
    a: &DMatrix<f64>,
    c: &DVector<f64>,
    ratings: &CoilRatings,
) -> Result<Allocation, AllocationError> {
    ratings.valid()?;
    let mut currents_a = allocate_pinv(a, c)?;
    let before = currents_a.norm();
    let scale = if clamp_to_ratings(&mut currents_a, ratings) && before > 0.0 {
        currents_a.norm() / before
    } else {
        1.0
    };
    Ok(Allocation { currents_a, scale })
}

/// How [`allocate_constrained`] met the command C.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AllocationStatus {
    /// A·I = C (to `feasibility_tol`) within the limits; among such currents, least ‖I‖.
    Exact,
    /// C is not reachable within the limits (or A cannot produce it at all): the currents
    /// minimise ‖A·I − C‖²_W + ε‖I‖² subject to the limits (least-squares best effort).
    BestEffort,
    /// The solver failed; the currents are [`allocate_limited`]'s (pseudo-inverse, uniformly
    /// scaled into the limits). Still within the limits.
    Fallback,
}

/// Settings of [`allocate_constrained`].
#[derive(Debug, Clone, PartialEq)]
pub struct ConstrainedSettings {
    /// Weight of each row of A·I − C in the best-effort objective (W = diag of these; all ≥ 0,
    /// not all 0). `None`: all ones. In the paper's C = [F_x, F_y, ω0 B_x, ω0 B_y], ω0 already
    /// balances the units, so equal weights are the natural default.
    pub row_weights: Option<DVector<f64>>,
    /// ε, relative: the objective is ‖Â x − Ĉ‖² + ε‖x‖² with x = I / I_max and Â = W^½ A I_max
    /// scaled to unit Frobenius norm (so ε is dimensionless; 1e-6 barely biases the fit).
    pub regularization: f64,
    /// C counts as met when ‖W^½(A·I − C)‖ ≤ feasibility_tol · ‖W^½ C‖.
    pub feasibility_tol: f64,
    /// Interior-point iteration cap per solve.
    pub max_iter: u32,
}

impl Default for ConstrainedSettings {
    fn default() -> Self {
        Self {
            row_weights: None,
            regularization: 1e-6,
            feasibility_tol: 1e-6,
            max_iter: 100,
        }
    }
}

/// Result of [`allocate_constrained`].
#[derive(Debug, Clone, PartialEq)]
pub struct ConstrainedAllocation {
    /// Currents, A; always |I_k| ≤ I_max and Σ I_k² R ≤ P_max.
    pub currents_a: DVector<f64>,
    pub status: AllocationStatus,
    /// ‖W^½(A·I − C)‖ / ‖W^½ C‖ (0 for C = 0).
    pub relative_residual: f64,
    /// Interior-point iterations over all solves.
    pub iterations: u32,
}

/// Constrained allocation: minimise ‖A·I − C‖²_W + ε‖I‖² subject to |I_k| ≤ I_max (box) and
/// Σ I_k² R ≤ P_max (a second-order cone: ‖I‖₂ ≤ √(P_max/R)), solved with Clarabel.
///
/// Two stages: (1) least ‖I‖ subject to A·I = C and the limits. If that is feasible the
/// status is [`AllocationStatus::Exact`]. (2) Otherwise the regularised weighted least squares
/// above, flagged [`AllocationStatus::BestEffort`]. Unlike [`allocate_limited`] (uniform
/// scaling, which keeps C's direction but gives up magnitude as soon as one coil saturates),
/// this redistributes current to the coils with headroom, so it meets strictly more commands.
///
/// Whatever the solver returns, the currents are passed through [`clamp_to_limits`], so the
/// limits hold exactly (no solver tolerance leaks through). Clarabel 0.11 is an interior-point
/// solver without warm start, so every call solves from scratch (≈ 10–20 iterations for 8–12
/// coils).
pub fn allocate_constrained(
    a: &DMatrix<f64>,
    c: &DVector<f64>,
    limits: &CoilLimits,
    settings: &ConstrainedSettings,
) -> Result<ConstrainedAllocation, AllocationError> {
    limits
        .validate()
        .map_err(|e| AllocationError::BadLimits(e.to_string()))?;
    allocate_constrained_rated(a, c, &CoilRatings::uniform(limits, a.ncols()), settings)
}

/// [`allocate_constrained`] with each coil's own current limit and resistance: the box is
/// |I_k| ≤ I_max,k and the cone Σ I_k² R_k ≤ P_max.
pub fn allocate_constrained_rated(
    a: &DMatrix<f64>,
    c: &DVector<f64>,
    ratings: &CoilRatings,
    settings: &ConstrainedSettings,
) -> Result<ConstrainedAllocation, AllocationError> {
    allocate_constrained_core(a, c, ratings, settings, None)
}

/// [`allocate_constrained_rated`] with a slew limit: every coil's current stays within
/// `max_step_a` of `previous_a` (in the same column order), on top of its limits. The whole
/// coil set shares the change: when one coil cannot follow, the others (the allocation has
/// more coils than rows) make up what they can of the command, where uniformly scaling the
/// step would hold every coil back. The previous currents are always feasible, so is this.
pub fn allocate_constrained_slewed(
    a: &DMatrix<f64>,
    c: &DVector<f64>,
    ratings: &CoilRatings,
    settings: &ConstrainedSettings,
    previous_a: &DVector<f64>,
    max_step_a: f64,
) -> Result<ConstrainedAllocation, AllocationError> {
    if previous_a.len() != a.ncols() {
        return Err(AllocationError::BadSettings(
            "previous currents must have one entry per coil",
        ));
    }
    if !(max_step_a.is_finite() && max_step_a >= 0.0) || previous_a.iter().any(|i| !i.is_finite()) {
        return Err(AllocationError::BadSettings(
            "the slew step and the previous currents must be finite (step >= 0)",
        ));
    }
    allocate_constrained_core(a, c, ratings, settings, Some((previous_a, max_step_a)))
}

fn allocate_constrained_core(
    a: &DMatrix<f64>,
    c: &DVector<f64>,
    ratings: &CoilRatings,
    settings: &ConstrainedSettings,
    slew: Option<(&DVector<f64>, f64)>,
) -> Result<ConstrainedAllocation, AllocationError> {
    check_command(a, c)?;
    ratings.valid()?;
    if ratings.len() != a.ncols() {
        return Err(AllocationError::BadLimits(format!(
            "{} coil ratings for {} coils",
            ratings.len(),
            a.ncols()
        )));
    }
    let eps = settings.regularization;
    if !(eps.is_finite() && eps >= 0.0) {
        return Err(AllocationError::BadSettings(
            "regularization must be finite and >= 0",
        ));
    }
    let tol = settings.feasibility_tol;
    if !(tol.is_finite() && tol > 0.0 && tol < 1.0) {
        return Err(AllocationError::BadSettings(
            "feasibility_tol must be in (0, 1)",
        ));
    }
    if settings.max_iter == 0 {
        return Err(AllocationError::BadSettings("max_iter must be > 0"));
    }
    let w_sqrt = match &settings.row_weights {
        None => DVector::from_element(a.nrows(), 1.0),
        Some(w) => {
            if w.len() != a.nrows() {
                return Err(AllocationError::BadSettings(
                    "row_weights must have one entry per row of A",
                ));
            }
            if w.iter().any(|v| !(v.is_finite() && *v >= 0.0)) || w.iter().all(|&v| v == 0.0) {
                return Err(AllocationError::BadSettings(
                    "row_weights must be finite, >= 0 and not all 0",
                ));
            }
            w.map(f64::sqrt)
        }
    };
    let n = a.ncols();
    if n == 0 {
        return Err(AllocationError::Degenerate);
    }
    let i_max = &ratings.max_current_a;
    // Normalised problem: x_k = I_k / I_max,k, Â = W^½ A diag(I_max) / s, Ĉ = W^½ C / s with
    // ‖Â‖_F = 1.
    let aw = DMatrix::from_fn(a.nrows(), n, |r, k| w_sqrt[r] * a[(r, k)] * i_max[k]);
    let cw = c.component_mul(&w_sqrt);
    let s = aw.norm();
    if !(s.is_finite() && s > 0.0) {
        return Err(AllocationError::Degenerate);
    }
    let ah = aw / s;
    let ch = &cw / s;
    // Power Σ x_k² I_max,k² R_k ≤ P_max as ‖d ⊙ x‖ ≤ 1.
    let power_weights = DVector::from_fn(n, |k, _| {
        i_max[k] * (ratings.resistance_ohm[k] / ratings.max_total_power_w).sqrt()
    });
    let residual_of = |x: &DVector<f64>| {
        let cn = ch.norm();
        if cn == 0.0 {
            0.0
        } else {
            (&ah * x - &ch).norm() / cn
        }
    };
    // Each coil's window in x: its limits, narrowed to the slew step around the previous
    // currents (clamped into the limits, so the window is never empty).
    let (lower, upper): (Vec<f64>, Vec<f64>) = (0..n)
        .map(|k| match slew {
            None => (-1.0, 1.0),
            Some((previous, step)) => (
                ((previous[k] - step) / i_max[k]).clamp(-1.0, 1.0),
                ((previous[k] + step) / i_max[k]).clamp(-1.0, 1.0),
            ),
        })
        .unzip();
    let zero_in_window = lower.iter().all(|&l| l <= 0.0) && upper.iter().all(|&u| u >= 0.0);
    if ch.norm() == 0.0 && zero_in_window {
        return Ok(ConstrainedAllocation {
            currents_a: DVector::zeros(n),
            status: AllocationStatus::Exact,
            relative_residual: 0.0,
            iterations: 0,
        });
    }

    let mut iterations = 0;
    let finish = |mut x: DVector<f64>, status: AllocationStatus, iterations: u32| {
        // The solver's tolerance must not leak past the window either.
        for (k, v) in x.iter_mut().enumerate() {
            *v = v.clamp(lower[k], upper[k]);
        }
        let mut currents_a = x.component_mul(i_max);
        clamp_to_ratings(&mut currents_a, ratings);
        x = currents_a.component_div(i_max);
        let relative_residual = residual_of(&x);
        let status = match status {
            AllocationStatus::Exact if relative_residual > tol => AllocationStatus::BestEffort,
            AllocationStatus::BestEffort if relative_residual <= tol => AllocationStatus::Exact,
            other => other,
        };
        ConstrainedAllocation {
            currents_a,
            status,
            relative_residual,
            iterations,
        }
    };

    // Stage 1: least norm subject to Â x = Ĉ and the limits.
    let p1 = dense_csc_upper(&DMatrix::identity(n, n));
    let q1 = vec![0.0; n];
    if let Some(sol) = solve_limited_socp(
        &p1,
        &q1,
        Some((&ah, &ch)),
        (&lower, &upper),
        &power_weights,
        settings.max_iter,
    ) {
        iterations += sol.iterations;
        if let Some(mut x) = sol.x {
            // Polish: remove the interior-point tolerance from the equality by a least-norm
            // correction (tiny; the final clamp absorbs any limit overshoot it causes).
            if let Ok(dx) = allocate_pinv(&ah, &(&ch - &ah * &x)) {
                let polished = &x + dx;
                if residual_of(&polished) < residual_of(&x) {
                    x = polished;
                }
            }
            if residual_of(&x) <= tol {
                return Ok(finish(x, AllocationStatus::Exact, iterations));
            }
        }
    }

    // Stage 2: min ‖Â x − Ĉ‖² + ε‖x‖² (½xᵀPx + qᵀx with P = 2(ÂᵀÂ + εI), q = −2ÂᵀĈ).
    let p2 = dense_csc_upper(&((ah.tr_mul(&ah) + DMatrix::identity(n, n) * eps) * 2.0));
    let q2: Vec<f64> = (ah.tr_mul(&ch) * -2.0).iter().copied().collect();
    if let Some(sol) = solve_limited_socp(
        &p2,
        &q2,
        None,
        (&lower, &upper),
        &power_weights,
        settings.max_iter,
    ) {
        iterations += sol.iterations;
        if let Some(x) = sol.x {
            return Ok(finish(x, AllocationStatus::BestEffort, iterations));
        }
    }

    // Solver failure: the uniform-scaling fallback, still within the limits (and with a slew
    // limit, the previous currents moved toward it by one factor, so no coil steps further).
    let fb = allocate_limited_rated(a, c, ratings)?;
    let mut fallback = fb.currents_a;
    if let Some((previous, step)) = slew {
        let change = &fallback - previous;
        let largest = change.amax();
        if largest > step {
            fallback = previous + change * (step / largest);
        }
    }
    let x = fallback.component_div(i_max);
    Ok(finish(x, AllocationStatus::Fallback, iterations))
}

struct SocpSolution {
    /// `None` unless the solver reports (almost) solved with a finite x.
    x: Option<DVector<f64>>,
    iterations: u32,
}

/// Column-major CSC of the upper triangle of a square matrix (Clarabel's P format). All
/// upper entries are stored, zeros included, so the pattern never depends on the data.
fn dense_csc_upper(m: &DMatrix<f64>) -> clarabel::algebra::CscMatrix<f64> {
    let n = m.ncols();
    let mut colptr = Vec::with_capacity(n + 1);
    let mut rowval = Vec::new();
    let mut nzval = Vec::new();
    colptr.push(0);
    for j in 0..n {
        for i in 0..=j {
            rowval.push(i);
            nzval.push(m[(i, j)]);
        }
        colptr.push(rowval.len());
    }
    clarabel::algebra::CscMatrix::new(n, n, colptr, rowval, nzval)
}

/// Solve min ½xᵀPx + qᵀx s.t. [Â x = Ĉ], lower_k ≤ x_k ≤ upper_k, ‖d ⊙ x‖₂ ≤ 1 with
/// Clarabel.
fn solve_limited_socp(
    p: &clarabel::algebra::CscMatrix<f64>,
    q: &[f64],
    equality: Option<(&DMatrix<f64>, &DVector<f64>)>,
    (lower, upper): (&[f64], &[f64]),
    d: &DVector<f64>,
    max_iter: u32,
) -> Option<SocpSolution> {
    use clarabel::solver::{
        DefaultSettings, DefaultSolver, IPSolver, SolverStatus, SupportedConeT,
    };
    let n = q.len();
    let m_eq = equality.map_or(0, |(a, _)| a.nrows());
    // Constraint rows (Clarabel form G x + s = h, s ∈ K):
    //   [Â]  x + s = Ĉ         s ∈ {0}^m      (stage 1 only)
    //   [ I] x + s = upper     s ≥ 0          (x ≤ upper)
    //   [−I] x + s = −lower    s ≥ 0          (−x ≤ −lower)
    //   [0ᵀ; −diag d] x + s = [1; 0]   s ∈ SOC    (‖d ⊙ x‖ ≤ 1)
    let rows = m_eq + 2 * n + 1 + n;
    let mut colptr = Vec::with_capacity(n + 1);
    let mut rowval = Vec::new();
    let mut nzval = Vec::new();
    colptr.push(0);
    for k in 0..n {
        if let Some((a, _)) = equality {
            for r in 0..m_eq {
                rowval.push(r);
                nzval.push(a[(r, k)]);
            }
        }
        rowval.push(m_eq + k);
        nzval.push(1.0);
        rowval.push(m_eq + n + k);
        nzval.push(-1.0);
        rowval.push(m_eq + 2 * n + 1 + k);
        nzval.push(-d[k]);
        colptr.push(rowval.len());
    }
    let g = clarabel::algebra::CscMatrix::new(rows, n, colptr, rowval, nzval);
    let mut h = Vec::with_capacity(rows);
    if let Some((_, c)) = equality {
        h.extend(c.iter().copied());
    }
    h.extend(upper.iter().copied());
    h.extend(lower.iter().map(|l| -l));
    h.push(1.0);
    h.extend(std::iter::repeat_n(0.0, n));
    let mut cones = Vec::with_capacity(3);
    if m_eq > 0 {
        cones.push(SupportedConeT::ZeroConeT(m_eq));
    }
    cones.push(SupportedConeT::NonnegativeConeT(2 * n));
    cones.push(SupportedConeT::SecondOrderConeT(n + 1));
    let settings = DefaultSettings {
        verbose: false,
        max_iter,
        tol_gap_abs: 1e-10,
        tol_gap_rel: 1e-10,
        tol_feas: 1e-10,
        ..DefaultSettings::default()
    };
    let mut solver = DefaultSolver::new(p, q, &g, &h, &cones, settings).ok()?;
    solver.solve();
    let sol = &solver.solution;
    let ok = matches!(
        sol.status,
        SolverStatus::Solved | SolverStatus::AlmostSolved
    ) && sol.x.iter().all(|v| v.is_finite());
    Some(SocpSolution {
        x: ok.then(|| DVector::from_column_slice(&sol.x)),
        iterations: sol.iterations,
    })
}

#[cfg(test)]
mod tests;
