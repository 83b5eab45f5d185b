//! Current allocation: paper Eq. 2 (actuation matrix), Eq. 3–4 (SVD pseudo-inverse), and the
//! uniform current/power limiting that keeps the commanded direction of C.

use nalgebra::{DMatrix, DVector, Vector3};
use thiserror::Error;

use crate::coils::{paper_coil_id, CoilSize, CoilSystem, CoilUnit, COIL_COUNT};
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
    if a.nrows() != c.len() {
        return Err(AllocationError::DimensionMismatch {
            rows: a.nrows(),
            len: c.len(),
        });
    }
    if a.iter().chain(c.iter()).any(|v| !v.is_finite()) {
        return Err(AllocationError::NonFinite);
    }
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

/// Scale all currents by one factor s ≤ 1 so that no |I_k| exceeds `max_current_a` and
/// Σ I_k² R ≤ `max_total_power_w`. Uniform scaling keeps the direction of A·I (the commanded
/// force/field direction) and only shortens it. Returns true if the currents were changed.
///
/// Non-finite currents or invalid limits zero every current (the safe state) and return true.
pub fn clamp_to_limits(currents: &mut DVector<f64>, limits: &CoilLimits) -> bool {
    if limits.validate().is_err() || currents.iter().any(|i| !i.is_finite()) {
        let changed = currents.iter().any(|&i| i != 0.0);
        currents.fill(0.0);
        return changed;
    }
    let peak = currents.amax();
    let power = currents.norm_squared() * limits.coil_resistance_ohm;
    let mut scale: f64 = 1.0;
    if peak > limits.max_current_a {
        scale = scale.min(limits.max_current_a / peak);
    }
    if power > limits.max_total_power_w {
        scale = scale.min((limits.max_total_power_w / power).sqrt());
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
    let mut currents_a = allocate_pinv(a, c)?;
    let before = currents_a.norm();
    let scale = if clamp_to_limits(&mut currents_a, limits) && before > 0.0 {
        currents_a.norm() / before
    } else {
        1.0
    };
    Ok(Allocation { currents_a, scale })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::phantom::Phantom;
    use crate::physics::in_plane_moment;
    use nalgebra::Vector2;

    /// Deterministic pseudo-random numbers in [-1, 1) (no rand dependency needed).
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((self.0 >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
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
        let mut rng = Lcg(42);
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
