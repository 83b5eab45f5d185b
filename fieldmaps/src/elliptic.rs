//! Complete elliptic integrals and the closed-form field of one circular current filament.

use std::f64::consts::PI;

use crate::physics::MU0;

/// Complete elliptic integrals K(m), E(m) of parameter m = k², given m and its complement
/// kc² = 1 − m (passed separately so callers can compute kc² without cancellation near m → 1).
///
/// Arithmetic–geometric mean: K = π / (2 AGM(1, kc)), E = K (1 − Σ_{n≥0} 2^{n−1} c_n²) with
/// c_0² = m. Converges quadratically; at most ~6 steps for kc ≥ 1e-6.
pub(crate) fn ellip_ke(m: f64, kc2: f64) -> (f64, f64) {
    let mut a = 1.0_f64;
    let mut b = kc2.max(0.0).sqrt();
    let mut weight = 0.5_f64;
    let mut sum = weight * m;
    // 64 iterations bound the loop even for NaN input (which then propagates, no panic).
    for _ in 0..64 {
        let c = 0.5 * (a - b);
        let a_next = 0.5 * (a + b);
        b = (a * b).sqrt();
        a = a_next;
        weight *= 2.0;
        sum += weight * c * c;
        // Stop at round-off level: a and b may then differ by an ulp forever, and 2ⁿ grows.
        if c.abs() <= 1e-15 * a {
            break;
        }
    }
    let k = PI / (2.0 * a);
    (k, k * (1.0 - sum))
}

/// g(m) = [(2 − m)E − 2(1 − m)K] / m², the combination in the radial field component.
/// Both terms tend to 2·π/2 as m → 0, so for small m the Maclaurin series is used instead
/// (f has no m⁰ or m¹ term).
fn radial_g(m: f64, k: f64, e: f64) -> f64 {
    if m >= 0.05 {
        return ((2.0 - m) * e - 2.0 * (1.0 - m) * k) / (m * m);
    }
    // K = π/2 Σ c_n mⁿ, E = π/2 Σ c_n mⁿ/(1 − 2n), c_n = [(2n−1)!!/(2n)!!]².
    // f_n = 2e_n − e_{n−1} − 2c_n + 2c_{n−1}. 20 terms: 0.05^20 ≪ ε.
    let mut c_prev = 0.25; // c_1
    let mut e_prev = -0.25; // e_1
    let mut sum = 0.0;
    let mut pow = 1.0;
    for n in 2..22 {
        let r = (2 * n - 1) as f64 / (2 * n) as f64;
        let c = c_prev * r * r;
        let e = c / (1.0 - 2.0 * n as f64);
        sum += (2.0 * e - e_prev - 2.0 * c + 2.0 * c_prev) * pow;
        pow *= m;
        c_prev = c;
        e_prev = e;
    }
    0.5 * PI * sum
}

/// Filaments closer than this to a point are treated as round wires of this radius: inside it
/// the field falls linearly to zero (like inside a conductor), so evaluation never yields ∞/NaN.
pub(crate) const WIRE_CORE_RADIUS_M: f64 = 1.0e-4;

/// Field of a unit-current loop of radius `a` in its local cylindrical frame, at (ρ ≥ 0, z).
/// Returns (B_ρ/ρ, B_z) in T/A. B_ρ/ρ is returned rather than B_ρ because it stays finite and
/// well-conditioned on the axis, which the gradient needs.
///
/// Smythe's closed form with D² = (a+ρ)² + z², d² = (a−ρ)² + z², m = 4aρ/D², kc² = d²/D²:
///   B_z = μ0/(2π D) [K + (a² − ρ² − z²)/d² E]
///   B_ρ = μ0 z/(2π ρ D) [−K + (a² + ρ² + z²)/d² E] = μ0 · 8 a² z ρ g(m) / (2π kc² D⁵)
fn loop_q_bz_raw(a: f64, rho: f64, z: f64) -> (f64, f64) {
    let dd2 = (a + rho) * (a + rho) + z * z;
    let d2 = (a - rho) * (a - rho) + z * z;
    let m = 4.0 * a * rho / dd2;
    let kc2 = d2 / dd2;
    let (k, e) = ellip_ke(m, kc2);
    let dd = dd2.sqrt();
    let c = MU0 / (2.0 * PI);
    let bz = c / dd * (k + (a * a - rho * rho - z * z) / d2 * e);
    let q = c * 8.0 * a * a * z * radial_g(m, k, e) / (kc2 * dd2 * dd2 * dd);
    (q, bz)
}

/// [`loop_q_bz_raw`] with the near-wire regularisation and ρ < 0 handled by symmetry
/// (B_ρ/ρ and B_z are even in ρ).
pub(crate) fn loop_q_bz(a: f64, rho: f64, z: f64) -> (f64, f64) {
    if !a.is_finite() || a <= 0.0 {
        // A degenerate loop encloses no area: no field.
        return (0.0, 0.0);
    }
    let rho = rho.abs();
    let d = (rho - a).hypot(z);
    if d >= WIRE_CORE_RADIUS_M || d.is_nan() {
        return loop_q_bz_raw(a, rho, z);
    }
    if d == 0.0 {
        return (0.0, 0.0);
    }
    // Evaluate on the core surface along the same direction from the wire, scale by d/r_core.
    let s = WIRE_CORE_RADIUS_M / d;
    let rho_c = a + (rho - a) * s;
    let (q_c, bz_c) = loop_q_bz_raw(a, rho_c, z * s);
    let shrink = d / WIRE_CORE_RADIUS_M;
    let q = if rho > 0.0 {
        q_c * rho_c / rho * shrink
    } else {
        q_c * shrink
    };
    (q, bz_c * shrink)
}

/// Local cylindrical field and its derivatives for a unit-current loop.
#[derive(Debug, Clone, Copy)]
pub(crate) struct LoopLocal {
    /// B_ρ / ρ, T/(A·m)
    pub q: f64,
    pub bz: f64,
    pub d_rho_b_rho: f64,
    pub d_z_b_rho: f64,
    pub d_rho_bz: f64,
    pub d_z_bz: f64,
}

/// Central-difference step for the gradient, m. Truncation error ~ (h/d)² ≈ 1e-6 relative at
/// d = 1 cm from a wire; round-off ~ ε·d/h ≈ 1e-13.
pub(crate) const GRADIENT_STEP_M: f64 = 1.0e-5;

/// Field and in-plane (ρ, z) derivatives by central differences of the closed form. Uses the
/// loop's symmetry (B_ρ odd and B_z even in ρ) so ρ − h < 0 near the axis is fine.
pub(crate) fn loop_local_with_gradient(a: f64, rho: f64, z: f64) -> LoopLocal {
    let h = GRADIENT_STEP_M;
    let (q, bz) = loop_q_bz(a, rho, z);
    let (q_rp, bz_rp) = loop_q_bz(a, rho + h, z);
    let (q_rm, bz_rm) = loop_q_bz(a, rho - h, z);
    let (q_zp, bz_zp) = loop_q_bz(a, rho, z + h);
    let (q_zm, bz_zm) = loop_q_bz(a, rho, z - h);
    let inv2h = 0.5 / h;
    LoopLocal {
        q,
        bz,
        d_rho_b_rho: ((rho + h) * q_rp - (rho - h) * q_rm) * inv2h,
        d_z_b_rho: rho * (q_zp - q_zm) * inv2h,
        d_rho_bz: (bz_rp - bz_rm) * inv2h,
        d_z_bz: (bz_zp - bz_zm) * inv2h,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_values() {
        // Abramowitz & Stegun: K(0.5) = 1.854074677301372, E(0.5) = 1.350643881047675.
        let (k, e) = ellip_ke(0.5, 0.5);
        assert!((k - 1.854_074_677_301_372).abs() < 1e-14);
        assert!((e - 1.350_643_881_047_675).abs() < 1e-14);
        let (k0, e0) = ellip_ke(0.0, 1.0);
        assert!((k0 - PI / 2.0).abs() < 1e-15 && (e0 - PI / 2.0).abs() < 1e-15);
        // m → 1: E → 1, K ≈ ln(4/kc).
        let kc = 1e-6;
        let (k1, e1) = ellip_ke(1.0 - kc * kc, kc * kc);
        assert!((e1 - 1.0).abs() < 1e-9);
        assert!((k1 - (4.0 / kc).ln()).abs() < 1e-9);
    }

    #[test]
    fn radial_series_matches_closed_form_at_switch() {
        for &m in &[0.049_999, 0.05, 0.03, 0.07] {
            let (k, e) = ellip_ke(m, 1.0 - m);
            let direct = ((2.0 - m) * e - 2.0 * (1.0 - m) * k) / (m * m);
            let series = {
                let mut c_prev = 0.25;
                let mut e_prev = -0.25;
                let mut sum = 0.0;
                let mut pow = 1.0;
                for n in 2..40 {
                    let r = (2 * n - 1) as f64 / (2 * n) as f64;
                    let c = c_prev * r * r;
                    let en = c / (1.0 - 2.0 * n as f64);
                    sum += (2.0 * en - e_prev - 2.0 * c + 2.0 * c_prev) * pow;
                    pow *= m;
                    c_prev = c;
                    e_prev = en;
                }
                0.5 * PI * sum
            };
            assert!((direct / series - 1.0).abs() < 1e-11, "m={m}");
            assert!((radial_g(m, k, e) / series - 1.0).abs() < 1e-11, "m={m}");
        }
        assert!((radial_g(0.0, PI / 2.0, PI / 2.0) - 3.0 * PI / 16.0).abs() < 1e-15);
    }

    #[test]
    fn no_nan_near_wire_or_axis() {
        let a = 0.02;
        for &(rho, z) in &[
            (a, 0.0),
            (a + 1e-9, 0.0),
            (a, 1e-12),
            (a + 5e-5, 5e-5),
            (0.0, 0.0),
            (0.0, 0.1),
            (1e-300, 0.01),
            (-0.01, 0.01),
            (1.0, 0.0),
        ] {
            let l = loop_local_with_gradient(a, rho, z);
            for v in [l.q, l.bz, l.d_rho_b_rho, l.d_z_b_rho, l.d_rho_bz, l.d_z_bz] {
                assert!(v.is_finite(), "rho={rho} z={z}: {l:?}");
            }
        }
        let (q, bz) = loop_q_bz(0.0, 0.01, 0.01);
        assert_eq!((q, bz), (0.0, 0.0));
    }
}
