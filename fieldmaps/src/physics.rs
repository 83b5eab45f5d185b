//! Physical laws shared by the plant and the controller (paper Sec. II-B).

use nalgebra::{Matrix3, Vector2, Vector3};

/// Vacuum permeability, T·m/A (CODATA 2018; ≈ 4π·1e-7).
pub const MU0: f64 = 1.256_637_062_12e-6;

/// The aligning torque |m|·B the orientation field gives by default (N·m): the paper's 1 mT on
/// its 0.86e-3 A·m² magnet (RIG.md). The field for another magnet is this over its |m|, so it
/// turns as briskly and, the field's pull on the magnet scaling with |m|·B as well, is pulled
/// toward the coils no harder.
pub const DEFAULT_ALIGNING_TORQUE_N_M: f64 = 8.6e-7;

/// Translational damping of a slender body, paper Eq. 7: c_t = 2π μ L / ln(L/r), N·s/m.
///
/// For the capsule (L = 7.4 mm, r = 1.4 mm): 5.6e-4 N·s/m at 20 cP, 1.2e-4 N·s/m at 4.3 cP.
/// The model needs L > r > 0 and μ > 0; otherwise the result is NaN (use
/// [`crate::rig::RobotParams::translational_damping`] for a checked version).
pub fn translational_damping(viscosity_pa_s: f64, length_m: f64, radius_m: f64) -> f64 {
    if !(viscosity_pa_s > 0.0 && radius_m > 0.0 && length_m > radius_m) {
        return f64::NAN;
    }
    2.0 * std::f64::consts::PI * viscosity_pa_s * length_m / (length_m / radius_m).ln()
}

/// Factor by which a plane wall multiplies the drag of a body of radius `radius_m` translating
/// parallel to it with a gap `gap_m` between body and wall (1 far away, growing without bound
/// as the gap closes). The larger of two sphere results, each valid at its own end:
/// Faxén's series for the centre at h = r + gap, 1 / (1 − 9/16 (r/h) + 1/8 (r/h)³ −
/// 45/256 (r/h)⁴ − 1/16 (r/h)⁵) (Happel & Brenner, *Low Reynolds number hydrodynamics*, 1965,
/// Eq. 7-4.28), and the lubrication limit of Goldman, Cox & Brenner (*Chem. Eng. Sci.* 22,
/// 637–651, 1967), 8/15 ln(r/gap) + 0.9588. For a capsule lying on the phantom floor, `radius_m`
/// is its cross-section's radius: a sphere of that radius is the closest shape with a closed
/// form. Sliding along its axis a cylinder has a stronger, gap^-½, singularity
/// ([`cylinder_axial_wall_friction`]). Across its axis the film under it carries the Couette
/// shear and a pressure-driven back-flow; in Reynolds' lubrication equation with gap
/// h = δ + x²/2r their gap^-½ contributions to the wall's shear cancel (flux 2/3 of the
/// surface speed × δ), so the force is of lower order, and this logarithm is the closest
/// closed form. NaN for a non-positive radius or a negative gap.
pub fn wall_drag_factor_parallel(gap_m: f64, radius_m: f64) -> f64 {
    if !(radius_m > 0.0 && gap_m >= 0.0) {
        return f64::NAN;
    }
    let ratio = radius_m / (radius_m + gap_m);
    let faxen = 1.0
        / (1.0 - 9.0 / 16.0 * ratio + ratio.powi(3) / 8.0
            - 45.0 / 256.0 * ratio.powi(4)
            - ratio.powi(5) / 16.0);
    let lubrication = if gap_m > 0.0 {
        8.0 / 15.0 * (radius_m / gap_m).ln() + 0.9588
    } else {
        f64::INFINITY
    };
    faxen.max(lubrication).max(1.0)
}

/// Free-stream translational friction of a circular cylinder of length `length_m` and radius
/// `radius_m` moving along its axis and across it, (axial, transverse) in N·s/m: Tirado & García
/// de la Torre's fits to exact numerical results (*J. Chem. Phys.* 71, 2581–2587, 1979),
/// f∥ = 2πμL / (ln p + γ∥) and f⊥ = 4πμL / (ln p + γ⊥), p = L / (2r), γ∥ = −0.207 + 0.980/p −
/// 0.133/p², γ⊥ = 0.839 + 0.185/p + 0.233/p², valid for 2 ≤ p ≤ 30. For the paper's capsule
/// (p = 2.64) that is 1.49× and 1.74× paper Eq. 7, which is the slender-body axial formula
/// without end corrections. NaN outside L > 2r > 0, μ > 0.
pub fn cylinder_translational_friction(
    viscosity_pa_s: f64,
    length_m: f64,
    radius_m: f64,
) -> (f64, f64) {
    if !(viscosity_pa_s > 0.0 && radius_m > 0.0 && length_m > 2.0 * radius_m) {
        return (f64::NAN, f64::NAN);
    }
    let p = length_m / (2.0 * radius_m);
    let ln_p = p.ln();
    let axial_end = -0.207 + 0.980 / p - 0.133 / (p * p);
    let transverse_end = 0.839 + 0.185 / p + 0.233 / (p * p);
    let two_pi_mu_l = 2.0 * std::f64::consts::PI * viscosity_pa_s * length_m;
    (
        two_pi_mu_l / (ln_p + axial_end),
        2.0 * two_pi_mu_l / (ln_p + transverse_end),
    )
}

/// Friction of a cylinder lying parallel to a plane wall with a gap `gap_m` and sliding along
/// its own axis, N·s/m: 2πμL / arccosh(1 + gap/r). Axial motion of a long cylinder is a
/// unidirectional Stokes flow, so the axial velocity is harmonic in the cross-section and the
/// force per length is μU times the capacitance per length of a cylinder above a grounded plane,
/// 2π / arccosh(h/r) with h the axis height (exact for an infinite cylinder; the ends of a
/// finite one add to it). It grows as (r/gap)^½, far faster than a sphere's logarithm, and is
/// meant for gaps where it exceeds the free-stream axial friction (below that the ends
/// dominate). NaN for a non-positive radius, length or viscosity, or a negative gap.
pub fn cylinder_axial_wall_friction(
    viscosity_pa_s: f64,
    length_m: f64,
    radius_m: f64,
    gap_m: f64,
) -> f64 {
    if !(viscosity_pa_s > 0.0 && radius_m > 0.0 && length_m > 0.0 && gap_m >= 0.0) {
        return f64::NAN;
    }
    2.0 * std::f64::consts::PI * viscosity_pa_s * length_m / (1.0 + gap_m / radius_m).acosh()
}

/// Slender-body rotational drag of a capsule about a transverse axis, N·m·s:
/// π μ L³ / (3 (ln(L/r) − 0.8)), the log term floored at 0.1 to stay finite for stubby bodies.
/// With a magnet of moment |m| in a field |B| the capsule turns into the field with time
/// constant drag / (|m|·|B|): 11 ms at 20 cP and 1 mT for the paper's capsule.
pub fn rotational_drag(viscosity_pa_s: f64, length_m: f64, radius_m: f64) -> f64 {
    let log_term = ((length_m / radius_m).ln() - 0.8).max(0.1);
    std::f64::consts::PI * viscosity_pa_s * length_m.powi(3) / (3.0 * log_term)
}

/// Force on a point dipole, F = ∇(m·B), i.e. F_j = Σ_i m_i ∂B_i/∂x_j (paper: F = mᵀ∇B).
///
/// `gradient[(i, j)] = ∂B_i/∂x_j`. In a current-free region the gradient is symmetric, so this
/// equals (m·∇)B.
pub fn magnetic_force(moment: &Vector3<f64>, gradient: &Matrix3<f64>) -> Vector3<f64> {
    gradient.tr_mul(moment)
}

/// Torque on a point dipole, T = m × B.
pub fn magnetic_torque(moment: &Vector3<f64>, field: &Vector3<f64>) -> Vector3<f64> {
    moment.cross(field)
}

/// Linear (Stokes-like) drag on the robot, paper Eq. 6: F = c_t · v_rel.
///
/// `relative_velocity` = fluid velocity − robot velocity, so the force pushes the robot toward
/// moving with the fluid (and opposes its motion in still fluid).
pub fn linear_drag(c_t: f64, relative_velocity: &Vector2<f64>) -> Vector2<f64> {
    relative_velocity * c_t
}

/// Quadratic (inertial) drag, F = ½ ρ C_d A |v_rel| v_rel, same sign convention as
/// [`linear_drag`]. The controller's nominal model omits it; the plant adds it because the robot
/// Reynolds number reaches ~190 at 10 cm/s in 4.3 cP fluid.
pub fn quadratic_drag(
    density_kg_m3: f64,
    drag_coefficient: f64,
    frontal_area_m2: f64,
    relative_velocity: &Vector2<f64>,
) -> Vector2<f64> {
    relative_velocity
        * (0.5 * density_kg_m3 * drag_coefficient * frontal_area_m2)
        * relative_velocity.norm()
}

/// Reynolds number ρ v L / μ.
pub fn reynolds_number(density_kg_m3: f64, speed_m_s: f64, length_m: f64, viscosity: f64) -> f64 {
    density_kg_m3 * speed_m_s * length_m / viscosity
}

/// In-plane dipole moment for a robot whose magnet axis has `heading_rad`, measured from +x
/// toward +y (counter-clockwise seen from the camera).
pub fn in_plane_moment(magnitude_am2: f64, heading_rad: f64) -> Vector3<f64> {
    Vector3::new(heading_rad.cos(), heading_rad.sin(), 0.0) * magnitude_am2
}

/// Wraps to [−π, π); angles already in range are returned unchanged (bit for bit).
pub fn wrap_angle(a: f64) -> f64 {
    if (-std::f64::consts::PI..std::f64::consts::PI).contains(&a) {
        return a;
    }
    let two_pi = std::f64::consts::TAU;
    let mut x = (a + std::f64::consts::PI) % two_pi;
    if x < 0.0 {
        x += two_pi;
    }
    x - std::f64::consts::PI
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_wall_correction_matches_both_limits_and_grows_as_the_gap_closes() {
        let r = 1.4e-3;
        // Far away: no correction; Faxén at h = 2r: 1 / (1 − 9/32 + 1/64 − 45/4096 − 1/512).
        assert!((wall_drag_factor_parallel(1.0, r) - 1.0).abs() < 1e-3);
        let faxen_2r = 1.0 / (1.0 - 9.0 / 32.0 + 1.0 / 64.0 - 45.0 / 4096.0 - 1.0 / 512.0);
        assert!((wall_drag_factor_parallel(r, r) - faxen_2r).abs() < 1e-12);
        // Near contact: Goldman, Cox & Brenner's 8/15 ln(r/δ) + 0.9588 (3.41 at δ = r/100).
        let gcb = 8.0 / 15.0 * 100f64.ln() + 0.9588;
        assert!((wall_drag_factor_parallel(r / 100.0, r) - gcb).abs() < 1e-12);
        let mut last = 1.0;
        for gap in [1e-2, 1e-3, 3e-4, 1e-4, 3e-5, 1e-5, 1e-6] {
            let factor = wall_drag_factor_parallel(gap, r);
            assert!(factor >= last, "gap {gap}: {factor} < {last}");
            last = factor;
        }
        assert!(wall_drag_factor_parallel(0.0, r).is_infinite());
        assert!(wall_drag_factor_parallel(-1e-6, r).is_nan());
        assert!(wall_drag_factor_parallel(1e-6, 0.0).is_nan());
    }

    use super::*;

    #[test]
    fn cylinder_friction_matches_tirado_de_la_torre_and_the_wall_limit() {
        let (mu, l, r) = (0.020, 7.4e-3, 1.4e-3);
        let (axial, transverse) = cylinder_translational_friction(mu, l, r);
        let eq7 = translational_damping(mu, l, r);
        // p = 2.643: ln p = 0.972; axial 2πμL/1.117, transverse 4πμL/1.914.
        assert!((axial / eq7 - 1.491).abs() < 0.01, "{}", axial / eq7);
        assert!(
            (transverse / eq7 - 1.740).abs() < 0.01,
            "{}",
            transverse / eq7
        );
        // Their orientation average against the 1984 fit 3πμL/(ln p + 0.312 + 0.565/p − 0.1/p²).
        let p: f64 = l / (2.0 * r);
        let mean = 3.0 / (1.0 / axial + 2.0 / transverse);
        let fit = 3.0 * std::f64::consts::PI * mu * l / (p.ln() + 0.312 + 0.565 / p - 0.1 / p / p);
        assert!((mean / fit - 1.0).abs() < 0.03, "{mean} vs {fit}");
        assert!(cylinder_translational_friction(mu, 2.0e-3, r).0.is_nan());
        // Near the wall: 2πμL/√(2δ/r) to leading order, ×25 Eq. 7 at 3 µm.
        let near = cylinder_axial_wall_friction(mu, l, r, 3e-6);
        let leading = 2.0 * std::f64::consts::PI * mu * l / (2.0 * 3e-6 / r).sqrt();
        assert!((near / leading - 1.0).abs() < 1e-3, "{near} vs {leading}");
        assert!((near / eq7 - 25.5).abs() < 0.5, "{}", near / eq7);
        assert!(cylinder_axial_wall_friction(mu, l, r, 0.0).is_infinite());
        assert!(cylinder_axial_wall_friction(mu, l, r, -1e-6).is_nan());
        let mut last = f64::INFINITY;
        for gap in [1e-7, 1e-6, 1e-5, 1e-4, 1e-3] {
            let f = cylinder_axial_wall_friction(mu, l, r, gap);
            assert!(f < last);
            last = f;
        }
    }

    #[test]
    fn damping_matches_rig_md() {
        let c20 = translational_damping(0.020, 7.4e-3, 1.4e-3);
        let c43 = translational_damping(0.0043, 7.4e-3, 1.4e-3);
        assert!((c20 / 5.6e-4 - 1.0).abs() < 0.05, "{c20}");
        assert!((c43 / 1.2e-4 - 1.0).abs() < 0.05, "{c43}");
        assert!(translational_damping(0.02, 1e-3, 2e-3).is_nan());
        assert!(translational_damping(-1.0, 7.4e-3, 1.4e-3).is_nan());
    }

    #[test]
    fn paper_magnet_force() {
        // 0.43 T/m gradient along x of B_x: 8.6e-4 A·m² × 0.43 T/m ≈ 0.37 mN.
        let g = Matrix3::new(0.43, 0.0, 0.0, 0.0, -0.215, 0.0, 0.0, 0.0, -0.215);
        let f = magnetic_force(&Vector3::new(8.6e-4, 0.0, 0.0), &g);
        assert!((f.x - 0.37e-3).abs() < 0.005e-3);
        assert!(f.y.abs() < 1e-15 && f.z.abs() < 1e-15);
    }

    #[test]
    fn force_uses_transpose() {
        // F_j = Σ_i m_i ∂B_i/∂x_j: only gradient[(0, 1)] is set, m along x ⇒ force along y.
        let mut g = Matrix3::zeros();
        g[(0, 1)] = 2.0;
        let f = magnetic_force(&Vector3::new(1.0, 0.0, 0.0), &g);
        assert_eq!(f, Vector3::new(0.0, 2.0, 0.0));
    }

    #[test]
    fn torque_and_drag() {
        let t = magnetic_torque(&Vector3::x(), &Vector3::y());
        assert_eq!(t, Vector3::z());
        let d = linear_drag(2.0, &Vector2::new(1.0, -1.0));
        assert_eq!(d, Vector2::new(2.0, -2.0));
        let q = quadratic_drag(1000.0, 1.0, 2.0, &Vector2::new(3.0, 4.0));
        assert!((q - Vector2::new(3.0, 4.0) * 5000.0).norm() < 1e-9);
        let m = in_plane_moment(2.0, std::f64::consts::FRAC_PI_2);
        assert!((m - Vector3::new(0.0, 2.0, 0.0)).norm() < 1e-12);
        let re = reynolds_number(1113.0, 0.1, 7.4e-3, 0.0043);
        assert!((re - 191.5).abs() < 1.0, "{re}");
    }
}
