//! Current allocation: paper Eq. 2 (actuation matrix), Eq. 3–4 (SVD pseudo-inverse), the
//! uniform current/power limiting that keeps the commanded direction of C, and a constrained
//! allocation (second-order cone program solved with Clarabel) that meets C exactly whenever
//! the per-coil and total-power limits allow it and otherwise returns the best limited fit.

use nalgebra::{DMatrix, DVector, Vector3};
use thiserror::Error;

use crate::coils::{paper_coil_id, CoilField, CoilSize, CoilSystem, CoilUnit, COIL_COUNT};
use crate::physics::magnetic_force;
use crate::rig::CoilLimits;

/// The 8 coils used for planar control by default: the small and large coil of every unit
/// (the pair the paper's FEA case characterises). The mid coils stay idle; pass
/// [`ALL_COILS`] to use them too.
pub const DEFAULT_PLANAR_COILS: [usize; 8] = [
    paper_coil_id(CoilUnit::North, CoilSize::Small),
    paper_coil_id(CoilUnit::North, CoilSize::Large),
    paper_coil_id(CoilUnit::East, CoilSize::Small),
    paper_coil_id(CoilUnit::East, CoilSize::Large),
    paper_coil_id(CoilUnit::South, CoilSize::Small),
    paper_coil_id(CoilUnit::South, CoilSize::Large),
    paper_coil_id(CoilUnit::West, CoilSize::Small),
    paper_coil_id(CoilUnit::West, CoilSize::Large),
];

/// All 12 coils.
pub const ALL_COILS: [usize; COIL_COUNT] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11];

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
mod tests {
    use super::*;
    use crate::phantom::Phantom;
    use crate::physics::in_plane_moment;
    use nalgebra::Vector2;

    /// Deterministic pseudo-random numbers in [-1, 1).
    struct SeededRng(rand_chacha::ChaCha8Rng);
    impl SeededRng {
        fn seeded(seed: u64) -> Self {
            Self(rand::SeedableRng::seed_from_u64(seed))
        }
        fn next(&mut self) -> f64 {
            rand::Rng::random_range(&mut self.0, -1.0..1.0)
        }
    }

    const OMEGA0: f64 = 0.1; // N/T: 1 mT of field weighs like 0.1 mN of force

    fn canal_points() -> Vec<Vector2<f64>> {
        let ph = Phantom::default_heart();
        vec![
            ph.default_start(),
            ph.default_end(),
            Vector2::new(-0.005, -0.0075),
            Vector2::new(0.004, -0.024),
            Vector2::new(0.029, -0.004),
            Vector2::new(-0.016, 0.010),
        ]
    }

    #[test]
    fn pinv_reproduces_commands() {
        let sys = CoilSystem::paper_rig();
        for p2 in canal_points() {
            assert!(Phantom::default_heart().contains(&p2));
            let p = Vector3::new(p2.x, p2.y, 0.0);
            for &heading in &[0.0_f64, 45.0, 90.0, 135.0, 200.0, -60.0] {
                let th = heading.to_radians();
                let m = in_plane_moment(8.6e-4, th);
                let a = actuation_matrix(&sys, &p, &m, &DEFAULT_PLANAR_COILS, OMEGA0);
                assert_eq!(a.shape(), (4, 8));
                // 30 µN force at 30° (≈ drag at 5 cm/s in 20 cP), 1 mT field along the heading.
                let c = DVector::from_vec(vec![
                    3e-5 * 0.866,
                    3e-5 * 0.5,
                    OMEGA0 * 1e-3 * th.cos(),
                    OMEGA0 * 1e-3 * th.sin(),
                ]);
                let i = allocate_pinv(&a, &c).unwrap();
                assert!(
                    (&a * &i - &c).norm() < 1e-9 * c.norm(),
                    "p={p:?} h={heading}"
                );

                // The same currents through the full field model give the same F and B.
                let mut all = [0.0; COIL_COUNT];
                for (k, &id) in DEFAULT_PLANAR_COILS.iter().enumerate() {
                    all[id] = i[k];
                }
                let (b, g) = sys.field_and_gradient(&all, &p);
                let f = magnetic_force(&m, &g);
                assert!((f.x - c[0]).abs() < 1e-9 * c.norm());
                assert!((f.y - c[1]).abs() < 1e-9 * c.norm());
                assert!((OMEGA0 * b.x - c[2]).abs() < 1e-9 * c.norm());
                assert!((OMEGA0 * b.y - c[3]).abs() < 1e-9 * c.norm());

                let a12 = actuation_matrix(&sys, &p, &m, &ALL_COILS, OMEGA0);
                let i12 = allocate_pinv(&a12, &c).unwrap();
                assert!((&a12 * &i12 - &c).norm() < 1e-9 * c.norm());
                // More coils, least norm: never needs more current norm than 8.
                assert!(i12.norm() <= i.norm() * (1.0 + 1e-9));
            }
        }
    }

    #[test]
    fn paper_heading_commands_fit_the_limits() {
        // Paper static tests: heading fixed at 45°. There the diagonal gradient terms, which
        // the opposing coil pairs control independently, give force in any direction; a force
        // across the moment needs off-diagonal terms, which vanish at the centre by symmetry.
        let sys = CoilSystem::paper_rig();
        let limits = CoilLimits::default();
        let th = 45f64.to_radians();
        let m = in_plane_moment(8.6e-4, th);
        let mut worst: f64 = 0.0;
        for p2 in canal_points() {
            let p = Vector3::new(p2.x, p2.y, 0.0);
            let a = actuation_matrix(&sys, &p, &m, &DEFAULT_PLANAR_COILS, OMEGA0);
            for k in 0..8 {
                let phi = k as f64 * std::f64::consts::FRAC_PI_4;
                // 30 µN (≈ drag at 5.4 cm/s in 20 cP) in any direction, 1 mT along the heading.
                // (50 µN needs up to ~7.8 A here: 6 A saturates in some directions, consistent
                // with the paper raising the current limit ×1.78 for 10 cm/s flow.)
                let c = DVector::from_vec(vec![
                    3e-5 * phi.cos(),
                    3e-5 * phi.sin(),
                    OMEGA0 * 1e-3 * th.cos(),
                    OMEGA0 * 1e-3 * th.sin(),
                ]);
                let mut i = allocate_pinv(&a, &c).unwrap();
                worst = worst.max(i.amax());
                assert!(!clamp_to_limits(&mut i, &limits), "p={p2:?} phi={phi}: {i}");
            }
        }
        println!("worst coil current at 45° heading: {worst:.2} A");
    }

    #[test]
    fn clamp_never_exceeds_limits() {
        let limits = CoilLimits::default();
        let mut rng = SeededRng::seeded(42);
        for trial in 0..2000 {
            let n = if trial % 2 == 0 { 8 } else { 12 };
            let mag = 10f64.powf(3.0 * rng.next()); // 1e-3 .. 1e3 A
            let orig = DVector::from_fn(n, |_, _| rng.next() * mag);
            let mut i = orig.clone();
            let scaled = clamp_to_limits(&mut i, &limits);
            assert!(i.amax() <= limits.max_current_a);
            assert!(i.norm_squared() * limits.coil_resistance_ohm <= limits.max_total_power_w);
            if scaled {
                // Same direction, shorter.
                let s = i.norm() / orig.norm();
                assert!(s < 1.0 && (&orig * s - &i).norm() <= 1e-12 * orig.norm());
            } else {
                assert_eq!(i, orig);
            }
        }
        // Only the total budget binds: 12 coils at 5 A = 3 kW > 2.16 kW.
        let mut i = DVector::from_element(12, 5.0);
        assert!(clamp_to_limits(&mut i, &limits));
        assert!((i.norm_squared() * 10.0 - 2160.0).abs() < 1e-6);
        // NaN or bad limits: safe state.
        let mut i = DVector::from_vec(vec![1.0, f64::NAN]);
        assert!(clamp_to_limits(&mut i, &limits));
        assert_eq!(i, DVector::zeros(2));
        let mut i = DVector::from_vec(vec![1.0, 2.0]);
        let bad = CoilLimits {
            max_current_a: f64::NAN,
            ..limits
        };
        assert!(clamp_to_limits(&mut i, &bad));
        assert_eq!(i, DVector::zeros(2));
    }

    #[test]
    fn allocate_limited_scales_uniformly() {
        let sys = CoilSystem::paper_rig();
        let m = in_plane_moment(8.6e-4, 0.3);
        let p = Vector3::new(0.0, -0.01, 0.0);
        let a = actuation_matrix(&sys, &p, &m, &DEFAULT_PLANAR_COILS, OMEGA0);
        // 50 mN is far beyond what 6 A can give at the centre.
        let c = DVector::from_vec(vec![5e-2, 0.0, 0.0, 0.0]);
        let out = allocate_limited(&a, &c, &CoilLimits::default()).unwrap();
        assert!(out.scale < 1.0 && out.scale > 0.0);
        assert!((&a * &out.currents_a - &c * out.scale).norm() < 1e-9 * c.norm() * out.scale);
    }

    #[test]
    fn per_coil_ratings_hold_and_beat_the_weakest_coil_for_all() {
        // The west coils are half as strong (3 A) and twice the resistance of the others.
        let sys = CoilSystem::paper_rig();
        let m = in_plane_moment(8.6e-4, 0.3);
        let p = Vector3::new(0.005, -0.01, 0.0);
        let a = actuation_matrix(&sys, &p, &m, &DEFAULT_PLANAR_COILS, OMEGA0);
        let n = DEFAULT_PLANAR_COILS.len();
        let mut ratings = CoilRatings::uniform(&CoilLimits::default(), n);
        for k in [6, 7] {
            ratings.max_current_a[k] = 3.0;
            ratings.resistance_ohm[k] = 20.0;
        }
        let weakest = CoilLimits {
            max_current_a: 3.0,
            coil_resistance_ohm: 20.0,
            ..CoilLimits::default()
        };
        let settings = ConstrainedSettings::default();
        let (mut rated_force, mut uniform_force) = (0.0, 0.0);
        for k in 0..16 {
            let angle = k as f64 * std::f64::consts::TAU / 16.0;
            let c = DVector::from_vec(vec![angle.cos() * 1e-2, angle.sin() * 1e-2, 0.0, 0.0]);
            let rated = allocate_constrained_rated(&a, &c, &ratings, &settings).unwrap();
            let i = &rated.currents_a;
            for j in 0..n {
                assert!(i[j].abs() <= ratings.max_current_a[j] * (1.0 + 1e-9), "{i}");
            }
            assert!(ratings.power_w(i) <= ratings.max_total_power_w * (1.0 + 1e-9));
            let uniform = allocate_constrained(&a, &c, &weakest, &settings).unwrap();
            let force = |i: &DVector<f64>| {
                let w = &a * i;
                (w[0] * angle.cos() + w[1] * angle.sin()).max(0.0)
            };
            rated_force += force(i);
            uniform_force += force(&uniform.currents_a);
            let mut clamped = i * 3.0;
            assert!(clamp_to_ratings(&mut clamped, &ratings));
            assert!(ratings.power_w(&clamped) <= ratings.max_total_power_w * (1.0 + 1e-9));
        }
        assert!(
            rated_force > 1.2 * uniform_force,
            "{rated_force} vs {uniform_force}"
        );
    }

    fn within_limits(i: &DVector<f64>, limits: &CoilLimits) -> bool {
        i.amax() <= limits.max_current_a
            && i.norm_squared() * limits.coil_resistance_ohm <= limits.max_total_power_w
    }

    #[test]
    fn constrained_meets_feasible_commands_exactly() {
        let sys = CoilSystem::paper_rig();
        let limits = CoilLimits::default();
        let settings = ConstrainedSettings::default();
        let (mut exact_qp, mut exact_uniform, mut total, mut iters) = (0, 0, 0, 0);
        let t0 = std::time::Instant::now();
        for p2 in canal_points() {
            let p = Vector3::new(p2.x, p2.y, 0.0);
            for &heading in &[0.0_f64, 45.0, 90.0, 135.0, 200.0, -60.0] {
                let th = heading.to_radians();
                let m = in_plane_moment(8.6e-4, th);
                for ids in [&DEFAULT_PLANAR_COILS[..], &ALL_COILS[..]] {
                    let a = actuation_matrix(&sys, &p, &m, ids, OMEGA0);
                    for k in 0..8 {
                        let phi = k as f64 * std::f64::consts::FRAC_PI_4;
                        // 20 µN and 50 µN in any direction, 1 mT along the heading: some are
                        // out of reach at some headings (see the test above).
                        for f in [2e-5, 5e-5] {
                            let c = DVector::from_vec(vec![
                                f * phi.cos(),
                                f * phi.sin(),
                                OMEGA0 * 1e-3 * th.cos(),
                                OMEGA0 * 1e-3 * th.sin(),
                            ]);
                            let out = allocate_constrained(&a, &c, &limits, &settings).unwrap();
                            iters += out.iterations;
                            total += 1;
                            assert!(within_limits(&out.currents_a, &limits));
                            let res = (&a * &out.currents_a - &c).norm() / c.norm();
                            assert!((res - out.relative_residual).abs() < 1e-9);
                            if out.status == AllocationStatus::Exact {
                                exact_qp += 1;
                                assert!(res <= settings.feasibility_tol, "{res}");
                            }
                            let uniform = allocate_limited(&a, &c, &limits).unwrap();
                            if uniform.scale == 1.0 {
                                exact_uniform += 1;
                                // Reachable without scaling ⇒ the QP must find it too.
                                assert_eq!(
                                    out.status,
                                    AllocationStatus::Exact,
                                    "p={p2:?} h={heading}"
                                );
                            }
                            if f == 2e-5 && heading == 45.0 {
                                // Within what `paper_heading_commands_fit_the_limits` shows.
                                assert_eq!(out.status, AllocationStatus::Exact, "p={p2:?}");
                            }
                        }
                    }
                }
            }
        }
        let dt = t0.elapsed().as_secs_f64() / total as f64;
        println!(
            "constrained: {exact_qp}/{total} commands met exactly (uniform scaling: \
             {exact_uniform}); {:.1} interior-point iterations, {:.2} ms per allocation",
            iters as f64 / total as f64,
            dt * 1e3
        );
        assert!(exact_qp >= exact_uniform);
        // README ("Allocation"): "On 1152 test commands ... it meets 1069 exactly vs 980 for
        // uniform scaling". Deterministic (fixed commands, no warm start): a change here is a
        // change of the allocation, and the README figure must follow it.
        assert_eq!(
            (total, exact_qp, exact_uniform),
            (1152, 1069, 980),
            "(commands, met exactly by the constrained allocation, by uniform scaling) differ \
             from the README's figures"
        );
    }

    #[test]
    fn constrained_never_exceeds_limits() {
        let sys = CoilSystem::paper_rig();
        let mut rng = SeededRng::seeded(7);
        let settings = ConstrainedSettings::default();
        let mut counts = [0usize; 3];
        for trial in 0..400 {
            // Random tighter limits too, so both the box and the power cone bind.
            let limits = if trial % 2 == 0 {
                CoilLimits::default()
            } else {
                CoilLimits {
                    max_current_a: 1.0 + 5.0 * rng.next().abs(),
                    max_total_power_w: 100.0 + 2000.0 * rng.next().abs(),
                    coil_resistance_ohm: 10.0,
                }
            };
            let p = Vector3::new(0.04 * rng.next(), 0.04 * rng.next(), 0.005 * rng.next());
            let m = in_plane_moment(8.6e-4, 3.2 * rng.next());
            let ids: &[usize] = if trial % 3 == 0 {
                &DEFAULT_PLANAR_COILS
            } else {
                &ALL_COILS
            };
            let a = actuation_matrix(&sys, &p, &m, ids, OMEGA0);
            let mag = 10f64.powf(3.0 * rng.next()); // 1e-3 .. 1e3 × (50 µN, 5 mT·ω0)
            let c = DVector::from_vec(vec![
                5e-5 * mag * rng.next(),
                5e-5 * mag * rng.next(),
                OMEGA0 * 5e-3 * mag * rng.next(),
                OMEGA0 * 5e-3 * mag * rng.next(),
            ]);
            let out = allocate_constrained(&a, &c, &limits, &settings).unwrap();
            assert!(
                within_limits(&out.currents_a, &limits),
                "trial {trial}: {}",
                out.currents_a
            );
            counts[out.status as usize] += 1;
            match out.status {
                AllocationStatus::Exact => assert!(out.relative_residual <= 1e-6),
                _ => {
                    // Best effort is never worse than the uniform scaling it replaces.
                    let u = allocate_limited(&a, &c, &limits).unwrap();
                    let ru = (&a * &u.currents_a - &c).norm() / c.norm();
                    assert!(
                        out.relative_residual <= ru * (1.0 + 1e-6) + 1e-9,
                        "{} vs {ru}",
                        out.relative_residual
                    );
                }
            }
        }
        println!(
            "random commands: exact {}, best effort {}, fallback {}",
            counts[0], counts[1], counts[2]
        );
        assert!(counts[0] > 50 && counts[1] > 50, "{counts:?}");
        assert_eq!(counts[2], 0);
    }

    #[test]
    fn slewed_allocation_stays_in_reach_and_beats_scaling_the_step() {
        // A force that reverses between two commands: every coil within the step of its
        // previous current, and sharing the step over the coils meets more of the new command
        // than moving the whole current vector by one factor.
        let sys = CoilSystem::paper_rig();
        let heading = 45f64.to_radians();
        let m = in_plane_moment(8.6e-4, heading);
        let field = DVector::from_vec(vec![
            OMEGA0 * 1e-3 * heading.cos(),
            OMEGA0 * 1e-3 * heading.sin(),
        ]);
        let n = ALL_COILS.len();
        let ratings = CoilRatings::uniform(&CoilLimits::default(), n);
        let settings = ConstrainedSettings {
            row_weights: Some(DVector::from_vec(vec![1.0, 1.0, 1e4, 1e4])),
            ..ConstrainedSettings::default()
        };
        let step = 0.6;
        let (mut slewed_miss, mut scaled_miss) = (0.0, 0.0);
        for (case, p2) in canal_points().into_iter().enumerate() {
            let p = Vector3::new(p2.x, p2.y, 0.0);
            let a = actuation_matrix(&sys, &p, &m, &ALL_COILS, OMEGA0);
            let angle = case as f64;
            let command = |sign: f64| {
                DVector::from_vec(vec![
                    sign * 2e-5 * angle.cos(),
                    sign * 2e-5 * angle.sin(),
                    field[0],
                    field[1],
                ])
            };
            let before = allocate_constrained_rated(&a, &command(1.0), &ratings, &settings)
                .unwrap()
                .currents_a;
            let target = command(-1.0);
            let slewed =
                allocate_constrained_slewed(&a, &target, &ratings, &settings, &before, step)
                    .unwrap();
            let change = &slewed.currents_a - &before;
            assert!(
                change.amax() <= step * (1.0 + 1e-9),
                "case {case}: {change}"
            );
            for k in 0..n {
                assert!(slewed.currents_a[k].abs() <= ratings.max_current_a[k] * (1.0 + 1e-9));
            }
            let free = allocate_constrained_rated(&a, &target, &ratings, &settings)
                .unwrap()
                .currents_a;
            let free_step = &free - &before;
            let scaled = &before + &free_step * (step / free_step.amax()).min(1.0);
            let force_miss =
                |i: &DVector<f64>| ((&a * i).rows(0, 2) - target.rows(0, 2)).norm() / 2e-5;
            slewed_miss += force_miss(&slewed.currents_a);
            scaled_miss += force_miss(&scaled);
            // With no step at all the previous currents come back.
            let held = allocate_constrained_slewed(&a, &target, &ratings, &settings, &before, 0.0)
                .unwrap();
            assert!((&held.currents_a - &before).amax() <= 1e-9);
        }
        assert!(
            slewed_miss < 0.8 * scaled_miss,
            "slewed misses {slewed_miss}, scaling the step misses {scaled_miss}"
        );
    }

    #[test]
    fn constrained_bad_inputs() {
        let a = DMatrix::from_element(4, 8, 1e-4);
        let limits = CoilLimits::default();
        let s = ConstrainedSettings::default();
        assert!(matches!(
            allocate_constrained(&a, &DVector::zeros(3), &limits, &s),
            Err(AllocationError::DimensionMismatch { .. })
        ));
        let c = DVector::from_vec(vec![1e-5, 0.0, 0.0, f64::NAN]);
        assert_eq!(
            allocate_constrained(&a, &c, &limits, &s),
            Err(AllocationError::NonFinite)
        );
        let c = DVector::from_vec(vec![1e-5, 0.0, 0.0, 0.0]);
        let bad = CoilLimits {
            max_current_a: -1.0,
            ..limits
        };
        assert!(matches!(
            allocate_constrained(&a, &c, &bad, &s),
            Err(AllocationError::BadLimits(_))
        ));
        for s2 in [
            ConstrainedSettings {
                regularization: -1.0,
                ..Default::default()
            },
            ConstrainedSettings {
                feasibility_tol: 0.0,
                ..Default::default()
            },
            ConstrainedSettings {
                max_iter: 0,
                ..Default::default()
            },
            ConstrainedSettings {
                row_weights: Some(DVector::zeros(4)),
                ..Default::default()
            },
            ConstrainedSettings {
                row_weights: Some(DVector::from_element(3, 1.0)),
                ..Default::default()
            },
        ] {
            assert!(matches!(
                allocate_constrained(&a, &c, &limits, &s2),
                Err(AllocationError::BadSettings(_))
            ));
        }
        assert_eq!(
            allocate_constrained(&DMatrix::zeros(4, 8), &c, &limits, &s),
            Err(AllocationError::Degenerate)
        );
        // Zero command: zero currents, exact.
        let out = allocate_constrained(&a, &DVector::zeros(4), &limits, &s).unwrap();
        assert_eq!(out.status, AllocationStatus::Exact);
        assert_eq!(out.currents_a, DVector::zeros(8));
        // Rank 1 A with a C outside its range: best effort, finite, within limits.
        let c = DVector::from_vec(vec![1e-4, -2e-4, 3e-4, 0.0]);
        let out = allocate_constrained(&a, &c, &limits, &s).unwrap();
        assert_eq!(out.status, AllocationStatus::BestEffort);
        assert!(within_limits(&out.currents_a, &limits));
        // Weighted rows: weight 0 on the field rows ⇒ only the force is matched.
        let sys = CoilSystem::paper_rig();
        let a = actuation_matrix(
            &sys,
            &Vector3::zeros(),
            &in_plane_moment(8.6e-4, 0.3),
            &DEFAULT_PLANAR_COILS,
            OMEGA0,
        );
        let c = DVector::from_vec(vec![1e-4, 0.0, 10.0, 0.0]);
        let w = ConstrainedSettings {
            row_weights: Some(DVector::from_vec(vec![1.0, 1.0, 0.0, 0.0])),
            ..Default::default()
        };
        let out = allocate_constrained(&a, &c, &limits, &w).unwrap();
        let f = &a * &out.currents_a;
        assert!(
            (f[0] - 1e-4).abs() < 1e-6 * 1e-4 && f[1].abs() < 1e-9,
            "{f}"
        );
    }

    #[test]
    fn bad_inputs_are_errors() {
        let a = DMatrix::from_element(4, 8, 1e-4);
        assert!(matches!(
            allocate_pinv(&a, &DVector::zeros(3)),
            Err(AllocationError::DimensionMismatch { rows: 4, len: 3 })
        ));
        let mut an = a.clone();
        an[(1, 1)] = f64::NAN;
        assert_eq!(
            allocate_pinv(&an, &DVector::zeros(4)),
            Err(AllocationError::NonFinite)
        );
        assert_eq!(
            allocate_pinv(&DMatrix::zeros(4, 8), &DVector::from_element(4, 1.0)),
            Err(AllocationError::Degenerate)
        );
        assert_eq!(
            allocate_pinv(&DMatrix::zeros(4, 0), &DVector::zeros(4)),
            Err(AllocationError::Degenerate)
        );
        assert!(allocate_pinv_rcond(&a, &DVector::zeros(4), -1.0).is_err());
        // Rank 1 matrix: finite least-squares answer.
        let i = allocate_pinv(&a, &DVector::from_vec(vec![1.0, 2.0, 3.0, 4.0])).unwrap();
        assert!(i.iter().all(|v| v.is_finite()));
        // Unknown coil ids give zero columns, which get zero current.
        let sys = CoilSystem::paper_rig();
        let m = in_plane_moment(8.6e-4, 0.0);
        let a = actuation_matrix(&sys, &Vector3::zeros(), &m, &[0, 2, 3, 5, 6, 8, 9, 40], 0.1);
        assert!(a.column(7).iter().all(|&v| v == 0.0));
        let c = DVector::from_vec(vec![1e-5, 0.0, 1e-4, 0.0]);
        let i = allocate_pinv(&a, &c).unwrap();
        assert_eq!(i[7], 0.0);
    }
}
