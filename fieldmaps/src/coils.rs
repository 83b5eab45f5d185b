//! A rig's electromagnet: coil geometry, closed-form Biot–Savart field and gradient, and the
//! comparison of a coil model with a field the rig is known to make (a rig file's
//! `[[electromagnet.reference_fields]]`).
//!
//! Each coil is a set of coaxial circular filaments ("loops") that sample the winding's
//! rectangular cross-section; every loop carries `turns_per_loop` turns. A loop's field is the
//! exact closed form with complete elliptic integrals; the gradient uses central differences of
//! that closed form in the loop's (ρ, z) half-plane with h = 1e-5 m, then the exact
//! axisymmetric tensor assembly (so the ∂/∂φ part, B_ρ/ρ, is analytic).

use nalgebra::{Matrix3, Unit, Vector3};
use thiserror::Error;

use crate::elliptic::{loop_local_with_gradient, loop_q_bz};
use crate::rig::RigError;

/// Errors from coil-system queries.
#[derive(Debug, Error)]
pub enum CoilError {
    #[error("coil index {index} out of range (system has {count} coils)")]
    BadIndex { index: usize, count: usize },
    #[error("expected {expected} currents, got {got}")]
    CurrentCount { expected: usize, got: usize },
    #[error(transparent)]
    Rig(#[from] RigError),
}

/// One coil: coaxial filaments sharing `axis`, placed at `center_m + axis · offset`.
#[derive(Debug, Clone, PartialEq)]
pub struct Coil {
    pub name: String,
    /// Centre of the winding (mid-plane of its axial extent), m.
    pub center_m: Vector3<f64>,
    /// Positive current circulates right-handed about `axis`, so the field at the coil centre
    /// points along `axis`.
    pub axis: Unit<Vector3<f64>>,
    /// (radius m, axial offset m) of each filament.
    pub loops: Vec<(f64, f64)>,
    pub turns_per_loop: f64,
}

/// A winding's rectangular cross-section (annulus `inner..outer` radius, `length` along the
/// axis, centred on the coil centre) and how finely filaments sample it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Winding {
    pub inner_radius_m: f64,
    pub outer_radius_m: f64,
    pub length_m: f64,
    pub radial_filaments: usize,
    pub axial_filaments: usize,
}

impl Coil {
    /// A coil of `turns` total turns spread evenly over the filaments that sample `winding`
    /// at the midpoints of a `radial × axial` grid of its cross-section.
    pub fn from_winding(
        name: String,
        center_m: Vector3<f64>,
        axis: Unit<Vector3<f64>>,
        winding: &Winding,
        turns: f64,
    ) -> Self {
        let (nr, na) = (winding.radial_filaments, winding.axial_filaments);
        let (ri, ro) = (winding.inner_radius_m, winding.outer_radius_m);
        let mut loops = Vec::with_capacity(nr * na);
        for a in 0..na {
            // Positive offset = along the axis.
            let offset = winding.length_m * ((a as f64 + 0.5) / na as f64 - 0.5);
            for r in 0..nr {
                loops.push((ri + (ro - ri) * (r as f64 + 0.5) / nr as f64, offset));
            }
        }
        Self {
            name,
            center_m,
            axis,
            loops,
            turns_per_loop: turns / (nr * na) as f64,
        }
    }

    pub fn total_turns(&self) -> f64 {
        self.turns_per_loop * self.loops.len() as f64
    }

    /// Local cylindrical coordinates of `p` w.r.t. the filament at `offset`:
    /// (ρ vector, ρ, z).
    fn local(&self, offset: f64, p: &Vector3<f64>) -> (Vector3<f64>, f64, f64) {
        let n = self.axis.into_inner();
        let r = p - (self.center_m + n * offset);
        let z = r.dot(&n);
        let rho_vec = r - n * z;
        let rho = rho_vec.norm();
        (rho_vec, rho, z)
    }

    /// Field per ampere of coil current, T/A.
    pub fn field_per_amp(&self, p: &Vector3<f64>) -> Vector3<f64> {
        let n = self.axis.into_inner();
        let mut b = Vector3::zeros();
        for &(radius, offset) in &self.loops {
            let (rho_vec, rho, z) = self.local(offset, p);
            let (q, bz) = loop_q_bz(radius, rho, z);
            // B_ρ e_ρ = (B_ρ/ρ) ρ_vec: no division by ρ, exact on the axis.
            b += rho_vec * q + n * bz;
        }
        b * self.turns_per_loop
    }

    /// Field (T/A) and gradient (T/(A·m), `[(i, j)] = ∂B_i/∂x_j`) per ampere.
    pub fn field_and_gradient_per_amp(&self, p: &Vector3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
        let n = self.axis.into_inner();
        let nn = n * n.transpose();
        let transverse = Matrix3::identity() - nn;
        let mut b = Vector3::zeros();
        let mut g = Matrix3::zeros();
        for &(radius, offset) in &self.loops {
            let (rho_vec, rho, z) = self.local(offset, p);
            let l = loop_local_with_gradient(radius, rho, z);
            b += rho_vec * l.q + n * l.bz;
            // On the axis e_ρ is undefined, but there ∂ρB_z = 0, ∂zB_ρ = 0 and ∂ρB_ρ = B_ρ/ρ,
            // so e_ρ = 0 gives the right (transversely isotropic) tensor.
            let e_rho = if rho > 0.0 {
                rho_vec / rho
            } else {
                Vector3::zeros()
            };
            let rr = e_rho * e_rho.transpose();
            // Axisymmetric field B = B_ρ(ρ,z) e_ρ + B_z(ρ,z) n:
            //   ∇B = ∂ρB_ρ e_ρe_ρᵀ + (B_ρ/ρ) e_φe_φᵀ + ∂zB_ρ e_ρnᵀ + ∂ρB_z n e_ρᵀ + ∂zB_z nnᵀ
            g += rr * l.d_rho_b_rho
                + (transverse - rr) * l.q
                + e_rho * n.transpose() * l.d_z_b_rho
                + n * e_rho.transpose() * l.d_rho_bz
                + nn * l.d_z_bz;
        }
        (b * self.turns_per_loop, g * self.turns_per_loop)
    }
}

/// A set of independently driven coils.
#[derive(Debug, Clone, PartialEq)]
pub struct CoilSystem {
    pub coils: Vec<Coil>,
}

impl CoilSystem {
    pub fn len(&self) -> usize {
        self.coils.len()
    }

    pub fn is_empty(&self) -> bool {
        self.coils.is_empty()
    }

    /// Check a coil subset once (e.g. at config time); the per-sample queries below return
    /// zeros for unknown indices instead of failing.
    pub fn check_ids(&self, coil_ids: &[usize]) -> Result<(), CoilError> {
        match coil_ids.iter().find(|&&i| i >= self.coils.len()) {
            Some(&index) => Err(CoilError::BadIndex {
                index,
                count: self.coils.len(),
            }),
            None => Ok(()),
        }
    }

    /// Field of coil `coil` per ampere at `p`, T/A. Zero for an out-of-range index.
    pub fn field_per_amp(&self, coil: usize, p: &Vector3<f64>) -> Vector3<f64> {
        self.coils
            .get(coil)
            .map_or_else(Vector3::zeros, |c| c.field_per_amp(p))
    }

    /// Gradient of coil `coil` per ampere at `p`, T/(A·m), `[(i, j)] = ∂B_i/∂x_j`.
    /// Zero for an out-of-range index.
    pub fn gradient_per_amp(&self, coil: usize, p: &Vector3<f64>) -> Matrix3<f64> {
        self.field_and_gradient_per_amp(coil, p).1
    }

    /// Both of the above in one pass (they share the elliptic-integral evaluations).
    pub fn field_and_gradient_per_amp(
        &self,
        coil: usize,
        p: &Vector3<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>) {
        self.coils.get(coil).map_or_else(
            || (Vector3::zeros(), Matrix3::zeros()),
            |c| c.field_and_gradient_per_amp(p),
        )
    }

    /// Superposed field (T) and gradient (T/m) for `currents_a[i]` in coil i. Currents past
    /// the coil count are ignored and missing ones count as zero; use
    /// [`Self::try_field_and_gradient`] to reject a length mismatch.
    pub fn field_and_gradient(
        &self,
        currents_a: &[f64],
        p: &Vector3<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>) {
        let mut b = Vector3::zeros();
        let mut g = Matrix3::zeros();
        for (coil, &i) in self.coils.iter().zip(currents_a) {
            // Idle coils cost nothing.
            if i != 0.0 {
                let (bc, gc) = coil.field_and_gradient_per_amp(p);
                b += bc * i;
                g += gc * i;
            }
        }
        (b, g)
    }

    /// [`Self::field_and_gradient`] that requires exactly one current per coil.
    pub fn try_field_and_gradient(
        &self,
        currents_a: &[f64],
        p: &Vector3<f64>,
    ) -> Result<(Vector3<f64>, Matrix3<f64>), CoilError> {
        if currents_a.len() != self.coils.len() {
            return Err(CoilError::CurrentCount {
                expected: self.coils.len(),
                got: currents_a.len(),
            });
        }
        Ok(self.field_and_gradient(currents_a, p))
    }

    /// Superposed field only, T.
    pub fn field(&self, currents_a: &[f64], p: &Vector3<f64>) -> Vector3<f64> {
        self.coils
            .iter()
            .zip(currents_a)
            .filter(|(_, &i)| i != 0.0)
            .map(|(c, &i)| c.field_per_amp(p) * i)
            .sum()
    }
}

/// Shared field models (e.g. one set of loaded maps used by many simulated runs).
impl<T: CoilField + ?Sized> CoilField for std::sync::Arc<T> {
    fn coil_count(&self) -> usize {
        (**self).coil_count()
    }

    fn field_and_gradient_per_amp(
        &self,
        coil: usize,
        p: &Vector3<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>) {
        (**self).field_and_gradient_per_amp(coil, p)
    }

    fn background_field(&self, p: &Vector3<f64>) -> Vector3<f64> {
        (**self).background_field(p)
    }
}

/// Anything that gives each coil's current-normalized field and gradient at a point: the direct
/// closed-form model ([`CoilSystem`]), the interpolated grid maps
/// ([`crate::fieldmap::CoilFieldMaps`]) or either with a calibration
/// ([`crate::calibration::CalibratedField`]). Code written against this trait can swap one for
/// the other.
pub trait CoilField {
    /// Number of independently driven coils.
    fn coil_count(&self) -> usize;

    /// Field (T/A) and gradient (T/(A·m), `[(i, j)] = ∂B_i/∂x_j`) of coil `coil` per ampere at
    /// `p` (m). Zero for an out-of-range index.
    fn field_and_gradient_per_amp(
        &self,
        coil: usize,
        p: &Vector3<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>);

    /// Field of coil `coil` per ampere, T/A.
    fn field_per_amp(&self, coil: usize, p: &Vector3<f64>) -> Vector3<f64> {
        self.field_and_gradient_per_amp(coil, p).0
    }

    /// Field (T) present at `p` whatever the currents: a calibrated background (earth, steel,
    /// remanence), uniform so without gradient. Zero unless a calibration says otherwise.
    fn background_field(&self, _p: &Vector3<f64>) -> Vector3<f64> {
        Vector3::zeros()
    }

    /// Superposed field (T) and gradient (T/m) for `currents_a[i]` in coil i, plus the
    /// background field. Currents past the coil count are ignored and missing ones count as
    /// zero.
    fn field_and_gradient(
        &self,
        currents_a: &[f64],
        p: &Vector3<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>) {
        let mut b = self.background_field(p);
        let mut g = Matrix3::zeros();
        for (coil, &i) in currents_a.iter().enumerate().take(self.coil_count()) {
            if i != 0.0 {
                let (bc, gc) = self.field_and_gradient_per_amp(coil, p);
                b += bc * i;
                g += gc * i;
            }
        }
        (b, g)
    }
}

impl CoilField for CoilSystem {
    fn coil_count(&self) -> usize {
        self.coils.len()
    }

    fn field_and_gradient_per_amp(
        &self,
        coil: usize,
        p: &Vector3<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>) {
        CoilSystem::field_and_gradient_per_amp(self, coil, p)
    }

    fn field_per_amp(&self, coil: usize, p: &Vector3<f64>) -> Vector3<f64> {
        CoilSystem::field_per_amp(self, coil, p)
    }

    fn field_and_gradient(
        &self,
        currents_a: &[f64],
        p: &Vector3<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>) {
        CoilSystem::field_and_gradient(self, currents_a, p)
    }
}

/// A field the rig's coils are known to make: a gaussmeter reading or an FEA result for one
/// pattern of currents (a rig file's `[[electromagnet.reference_fields]]`).
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceField {
    /// Where the numbers come from (free text).
    pub source: String,
    /// (coil index, current A) of every driven coil; the others carry none.
    pub currents_a: Vec<(usize, f64)>,
    /// Where the field was measured, m.
    pub point_m: Vector3<f64>,
    /// The direction of the gradient, ∂|B|/∂s along it.
    pub direction: Unit<Vector3<f64>>,
    /// |B| there, T.
    pub field_t: f64,
    /// ∂|B|/∂s there, T/m, when known.
    pub gradient_t_per_m: Option<f64>,
}

/// |B| and ∂|B|/∂s of a coil model at a reference field's point and currents.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FieldReading {
    /// |B|, T.
    pub field_t: f64,
    /// ∂|B|/∂s along the reference's direction, T/m (the quantity that pushes a magnet aligned
    /// with B along that direction).
    pub gradient_t_per_m: f64,
}

impl ReferenceField {
    /// The full current vector of a rig with `coil_count` coils.
    pub fn currents(&self, coil_count: usize) -> Vec<f64> {
        let mut currents = vec![0.0; coil_count];
        for &(coil, amps) in &self.currents_a {
            if let Some(c) = currents.get_mut(coil) {
                *c = amps;
            }
        }
        currents
    }

    /// What a model gives at the point: `b` and `g` are its superposed field (T) and gradient
    /// (T/m) for [`Self::currents`] there.
    pub fn reading(&self, b: &Vector3<f64>, g: &Matrix3<f64>) -> FieldReading {
        let dir_derivative = g * self.direction.into_inner();
        // d|B|/ds = B̂ · (∂B/∂s); if B vanishes, |∂B/∂s| is the one-sided rate.
        let gradient = match b.try_normalize(0.0) {
            Some(bh) => bh.dot(&dir_derivative),
            None => dir_derivative.norm(),
        };
        FieldReading {
            field_t: b.norm(),
            gradient_t_per_m: gradient,
        }
    }

    /// [`Self::reading`] of `model` at the reference's point and currents.
    pub fn measure(&self, model: &dyn CoilField) -> FieldReading {
        let (b, g) = model.field_and_gradient(&self.currents(model.coil_count()), &self.point_m);
        self.reading(&b, &g)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::MU0;
    use std::f64::consts::PI;

    fn single_loop(radius: f64, center: Vector3<f64>, axis: Vector3<f64>) -> Coil {
        Coil {
            name: "loop".into(),
            center_m: center,
            axis: Unit::new_normalize(axis),
            loops: vec![(radius, 0.0)],
            turns_per_loop: 1.0,
        }
    }

    /// Direct numerical Biot–Savart sum over `n` straight segments (midpoint rule).
    fn brute_force(coil: &Coil, p: &Vector3<f64>, n: usize) -> Vector3<f64> {
        let ax = coil.axis.into_inner();
        let u = ax.cross(&Vector3::new(0.3, -0.7, 0.6)).normalize();
        let v = ax.cross(&u); // u × v = ax: right-handed about the axis
        let mut b = Vector3::zeros();
        for &(a, off) in &coil.loops {
            let c = coil.center_m + ax * off;
            let dphi = 2.0 * PI / n as f64;
            for k in 0..n {
                let phi = (k as f64 + 0.5) * dphi;
                let x = c + (u * phi.cos() + v * phi.sin()) * a;
                let dl = (-u * phi.sin() + v * phi.cos()) * (a * dphi);
                let r = p - x;
                b += dl.cross(&r) / r.norm().powi(3);
            }
        }
        b * (MU0 / (4.0 * PI) * coil.turns_per_loop)
    }

    fn rel(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
        (a - b).norm() / b.norm()
    }

    #[test]
    fn on_axis_matches_closed_form() {
        let r = 0.03;
        let coil = single_loop(
            r,
            Vector3::new(0.01, -0.02, 0.005),
            Vector3::new(1.0, 2.0, -0.5),
        );
        let n = coil.axis.into_inner();
        for &z in &[-0.2, -0.05, -0.01, 0.0, 1e-6, 0.02, 0.1] {
            let p = coil.center_m + n * z;
            let expect = MU0 * r * r / (2.0 * (r * r + z * z).powf(1.5));
            let b = coil.field_per_amp(&p);
            assert!((b.dot(&n) / expect - 1.0).abs() < 1e-12, "z={z}");
            assert!((b - n * b.dot(&n)).norm() < 1e-12 * expect, "z={z}");
        }
    }

    #[test]
    fn off_axis_matches_brute_force_sum() {
        let coil = single_loop(
            0.025,
            Vector3::new(0.0, 0.07, 0.0),
            Vector3::new(0.2, -1.0, 0.1),
        );
        let ax = coil.axis.into_inner();
        let u = ax.cross(&Vector3::z()).normalize();
        // (ρ, z) pairs from near the axis to 2 mm from the wire and far away.
        for &(rho, z) in &[
            (1e-4, 0.01),
            (0.005, 0.0),
            (0.012, 0.03),
            (0.023, 0.0),
            (0.025, 0.002),
            (0.027, -0.001),
            (0.04, 0.01),
            (0.1, -0.08),
        ] {
            let p = coil.center_m + u * rho + ax * z;
            let b = coil.field_per_amp(&p);
            let bf = brute_force(&coil, &p, 20_000);
            assert!(rel(&b, &bf) < 1e-4, "rho={rho} z={z}: {b:?} vs {bf:?}");
        }
    }

    /// Three windings of different sizes at generic places and tilts around the workspace (not
    /// any rig's: the physics must hold for every layout).
    fn test_system() -> CoilSystem {
        let winding = |inner_radius_m, outer_radius_m| Winding {
            inner_radius_m,
            outer_radius_m,
            length_m: 0.015,
            radial_filaments: 3,
            axial_filaments: 2,
        };
        let coil = |name: &str, center: [f64; 3], axis: [f64; 3], w: Winding, turns| {
            Coil::from_winding(
                name.into(),
                Vector3::from(center),
                Unit::new_normalize(Vector3::from(axis)),
                &w,
                turns,
            )
        };
        CoilSystem {
            coils: vec![
                coil(
                    "a",
                    [0.0, 0.08, 0.0],
                    [0.0, -1.0, 0.0],
                    winding(0.01, 0.024),
                    200.0,
                ),
                coil(
                    "b",
                    [0.075, -0.025, 0.01],
                    [-1.0, 0.3, -0.1],
                    winding(0.02, 0.035),
                    150.0,
                ),
                coil(
                    "c",
                    [-0.06, -0.06, 0.0],
                    [1.0, 1.0, 0.0],
                    winding(0.04, 0.05),
                    120.0,
                ),
            ],
        }
    }

    #[test]
    fn windings_match_brute_force() {
        let sys = test_system();
        let p = Vector3::new(0.013, 0.021, 0.004);
        for c in &sys.coils {
            let b = c.field_per_amp(&p);
            assert!(rel(&b, &brute_force(c, &p, 4000)) < 1e-4, "{}", c.name);
        }
    }

    fn sample_points() -> Vec<Vector3<f64>> {
        let mut pts = vec![Vector3::zeros()];
        for &x in &[-0.045, -0.02, 0.0, 0.017, 0.04] {
            for &y in &[-0.04, -0.011, 0.0, 0.023, 0.049] {
                pts.push(Vector3::new(x, y, 0.0));
                pts.push(Vector3::new(x, y, 0.012));
            }
        }
        pts
    }

    #[test]
    fn gradient_is_divergence_and_curl_free() {
        let sys = test_system();
        for p in sample_points() {
            for i in 0..sys.len() {
                let g = sys.gradient_per_amp(i, &p);
                let norm = g.norm();
                assert!(norm > 0.0);
                assert!(g.trace().abs() < 1e-6 * norm, "div: coil {i} at {p:?}");
                assert!(
                    (g - g.transpose()).norm() < 1e-6 * norm,
                    "curl: coil {i} at {p:?}"
                );
            }
        }
    }

    #[test]
    fn gradient_matches_3d_differences_of_field() {
        let sys = test_system();
        let h = 1e-5;
        for p in sample_points().into_iter().step_by(3) {
            for i in 0..sys.len() {
                let g = sys.gradient_per_amp(i, &p);
                let mut fd = Matrix3::zeros();
                for j in 0..3 {
                    let mut e = Vector3::zeros();
                    e[j] = h;
                    let d = (sys.field_per_amp(i, &(p + e)) - sys.field_per_amp(i, &(p - e)))
                        / (2.0 * h);
                    fd.set_column(j, &d);
                }
                assert!((g - fd).norm() < 1e-6 * g.norm(), "coil {i} at {p:?}");
            }
        }
    }

    #[test]
    fn finite_at_wires_and_axes() {
        let sys = test_system();
        for c in &sys.coils {
            for &(a, off) in &c.loops {
                let n = c.axis.into_inner();
                let perp = n.cross(&Vector3::z()).normalize();
                let on_wire = c.center_m + n * off + perp * a;
                let on_axis = c.center_m + n * off;
                for p in [on_wire, on_wire + perp * 3e-5, on_axis] {
                    let (b, g) = c.field_and_gradient_per_amp(&p);
                    assert!(
                        b.iter().chain(g.iter()).all(|v| v.is_finite()),
                        "{}",
                        c.name
                    );
                }
            }
        }
    }

    #[test]
    fn signs_and_indices() {
        let sys = test_system();
        // Positive current: the field at a coil's centre points along its axis.
        for (i, c) in sys.coils.iter().enumerate() {
            let b = sys.field_per_amp(i, &c.center_m);
            assert!(b.normalize().dot(&c.axis) > 1.0 - 1e-12, "{}", c.name);
        }
        let o = Vector3::zeros();
        assert_eq!(sys.field_per_amp(99, &o), Vector3::zeros());
        assert!(sys.check_ids(&[0, 2]).is_ok());
        assert!(matches!(
            sys.check_ids(&[1, 3]),
            Err(CoilError::BadIndex { index: 3, .. })
        ));
        assert!(sys.try_field_and_gradient(&[1.0; 2], &o).is_err());
    }

    #[test]
    fn superposition() {
        let sys = test_system();
        let p = Vector3::new(0.01, -0.02, 0.003);
        let currents: Vec<f64> = (0..sys.len()).map(|i| (i as f64 - 1.2) * 0.4).collect();
        let (b, g) = sys.try_field_and_gradient(&currents, &p).unwrap();
        let mut b2 = Vector3::zeros();
        let mut g2 = Matrix3::zeros();
        for (i, &c) in currents.iter().enumerate() {
            b2 += sys.field_per_amp(i, &p) * c;
            g2 += sys.gradient_per_amp(i, &p) * c;
        }
        assert!((b - b2).norm() < 1e-12 * b.norm());
        assert!((g - g2).norm() < 1e-12 * g.norm());
        assert!((sys.field(&currents, &p) - b).norm() < 1e-12 * b.norm());
    }

    #[test]
    fn a_reference_field_reads_the_closed_form_on_a_loop_axis() {
        // One loop, 2 A: on its axis |B| = μ0 I r² / (2 (r² + z²)^(3/2)) and
        // d|B|/dz = −3 μ0 I r² z / (2 (r² + z²)^(5/2)).
        let (r, z, amps) = (0.03, 0.02, 2.0);
        let sys = CoilSystem {
            coils: vec![single_loop(r, Vector3::zeros(), Vector3::z())],
        };
        let reference = ReferenceField {
            source: "closed form".into(),
            currents_a: vec![(0, amps), (5, 1.0)],
            point_m: Vector3::new(0.0, 0.0, z),
            direction: Unit::new_unchecked(Vector3::z()),
            field_t: 0.0,
            gradient_t_per_m: None,
        };
        assert_eq!(reference.currents(1), [amps]);
        let read = reference.measure(&sys);
        let q = r * r + z * z;
        let field = MU0 * amps * r * r / (2.0 * q.powf(1.5));
        let gradient = -3.0 * MU0 * amps * r * r * z / (2.0 * q.powf(2.5));
        assert!((read.field_t / field - 1.0).abs() < 1e-12, "{read:?}");
        assert!(
            (read.gradient_t_per_m / gradient - 1.0).abs() < 1e-6,
            "{read:?}"
        );
    }
}
