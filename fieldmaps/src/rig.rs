//! Rig parameters: robot, fluid and coil-driver limits, with defaults taken from the paper
//! (`reference/paper.tex`) and `RIG.md`. All values are SI.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::physics;

/// Errors from loading or validating rig parameters.
#[derive(Debug, Error)]
pub enum RigError {
    #[error("invalid rig parameter `{field}`: {reason}")]
    Invalid {
        field: &'static str,
        reason: &'static str,
    },
}

fn require_positive(field: &'static str, v: f64) -> Result<(), RigError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(RigError::Invalid {
            field,
            reason: "must be finite and > 0",
        })
    }
}

/// How the capsule looks to the classical localizer, in OpenCV's HSV scale (hue 0–180,
/// saturation and value 0–255): the dyed body is every pixel inside `body_hsv_min` ..=
/// `body_hsv_max`, the magnet every pixel with value ≤ `magnet_value_max` whatever its hue.
/// A hue range that wraps past 180 (a red dye) is not supported.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CapsuleAppearance {
    pub body_hsv_min: [f64; 3],
    pub body_hsv_max: [f64; 3],
    pub magnet_value_max: f64,
}

impl Default for CapsuleAppearance {
    /// The twin's rendering: blue dye and a lighter cap (hue ≈ 105..125), a near-black magnet.
    fn default() -> Self {
        Self {
            body_hsv_min: [95.0, 60.0, 60.0],
            body_hsv_max: [130.0, 255.0, 255.0],
            magnet_value_max: 70.0,
        }
    }
}

impl CapsuleAppearance {
    /// Checks the ranges; the error names the key and why.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        let top = [180.0, 255.0, 255.0];
        for (name, values) in [
            ("body_hsv_min", self.body_hsv_min),
            ("body_hsv_max", self.body_hsv_max),
        ] {
            for (channel, (v, t)) in values.iter().zip(top).enumerate() {
                if !(v.is_finite() && (0.0..=t).contains(v)) {
                    return Err((
                        name,
                        format!("channel {channel} must be within 0..={t}, got {v}"),
                    ));
                }
            }
        }
        for channel in 0..3 {
            if self.body_hsv_min[channel] > self.body_hsv_max[channel] {
                return Err((
                    "body_hsv_max",
                    format!(
                        "channel {channel} ({}) is below body_hsv_min's ({}); a hue range that wraps \
                         past 180 is not supported",
                        self.body_hsv_max[channel], self.body_hsv_min[channel]
                    ),
                ));
            }
        }
        let v = self.magnet_value_max;
        if !(v.is_finite() && (0.0..=255.0).contains(&v)) {
            return Err((
                "magnet_value_max",
                format!("must be within 0..=255, got {v}"),
            ));
        }
        Ok(())
    }
}

/// The capsule robot (a rig file's `[robot]`; the paper's capsule is in
/// `fieldmaps/rigs/paper.toml`, every value sourced there).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobotParams {
    /// Dipole moment of the embedded magnet, A·m².
    pub magnet_moment_am2: f64,
    /// Robot mass, kg.
    pub mass_kg: f64,
    /// Hydrodynamic added mass, kg.
    pub added_mass_kg: f64,
    /// Capsule length, m.
    pub length_m: f64,
    /// Capsule diameter, m.
    pub diameter_m: f64,
}

impl RobotParams {
    pub fn radius_m(&self) -> f64 {
        0.5 * self.diameter_m
    }

    /// Displaced volume (cylinder approximation), m³.
    pub fn volume_m3(&self) -> f64 {
        std::f64::consts::PI * self.radius_m().powi(2) * self.length_m
    }

    /// Mass the translational dynamics see: body + added mass, kg.
    pub fn effective_mass_kg(&self) -> f64 {
        self.mass_kg + self.added_mass_kg
    }

    /// Paper Eq. 7 damping coefficient in `fluid`, N·s/m.
    pub fn translational_damping(&self, fluid: &FluidParams) -> Result<f64, RigError> {
        self.validate()?;
        fluid.validate()?;
        Ok(physics::translational_damping(
            fluid.viscosity_pa_s,
            self.length_m,
            self.radius_m(),
        ))
    }

    pub fn validate(&self) -> Result<(), RigError> {
        require_positive("robot.magnet_moment_am2", self.magnet_moment_am2)?;
        require_positive("robot.mass_kg", self.mass_kg)?;
        require_positive("robot.length_m", self.length_m)?;
        require_positive("robot.diameter_m", self.diameter_m)?;
        if !(self.added_mass_kg.is_finite() && self.added_mass_kg >= 0.0) {
            return Err(RigError::Invalid {
                field: "robot.added_mass_kg",
                reason: "must be finite and >= 0",
            });
        }
        // Eq. 7 needs ln(L/r) > 0, i.e. a slender body.
        if self.length_m <= self.radius_m() {
            return Err(RigError::Invalid {
                field: "robot.length_m",
                reason: "must exceed the radius (slender-body drag model)",
            });
        }
        Ok(())
    }
}

/// Glycerin–water working fluid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FluidParams {
    pub viscosity_pa_s: f64,
    pub density_kg_m3: f64,
}

impl FluidParams {
    /// Density of the paper's glycerin–water mixtures (1113 kg/m³; the paper gives one value for
    /// its 4.3 cP and 20 cP mixtures): what a scenario's `[fluid]` and `fieldgen cfd` take when
    /// they are given no density.
    pub const GLYCERIN_WATER_DENSITY: f64 = 1113.0;

    pub fn validate(&self) -> Result<(), RigError> {
        require_positive("fluid.viscosity_pa_s", self.viscosity_pa_s)?;
        require_positive("fluid.density_kg_m3", self.density_kg_m3)
    }
}

/// Coil driver limits in one-value-for-all form (a rig's, from its file:
/// [`crate::rigfile::Rig::coil_limits`], or a scenario's `[control.limits]`, every key given).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CoilLimits {
    /// Per-coil current magnitude limit, A.
    pub max_current_a: f64,
    /// Total ohmic power over all coils, W.
    pub max_total_power_w: f64,
    /// Resistance of each coil, Ω.
    pub coil_resistance_ohm: f64,
}

impl CoilLimits {
    /// Current that dissipates `power_w` in one coil: I = sqrt(P/R).
    pub fn current_for_power(&self, power_w: f64) -> Result<f64, RigError> {
        self.validate()?;
        if !(power_w.is_finite() && power_w >= 0.0) {
            return Err(RigError::Invalid {
                field: "power_w",
                reason: "must be finite and >= 0",
            });
        }
        Ok((power_w / self.coil_resistance_ohm).sqrt())
    }

    /// Power one coil dissipates at the current limit, W.
    pub fn max_coil_power_w(&self) -> f64 {
        self.max_current_a.powi(2) * self.coil_resistance_ohm
    }

    pub fn validate(&self) -> Result<(), RigError> {
        require_positive("coil_limits.max_current_a", self.max_current_a)?;
        require_positive("coil_limits.max_total_power_w", self.max_total_power_w)?;
        require_positive("coil_limits.coil_resistance_ohm", self.coil_resistance_ohm)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The paper's capsule as `fieldmaps/rigs/paper.toml` gives it.
    fn capsule() -> RobotParams {
        RobotParams {
            magnet_moment_am2: 8.6e-4,
            mass_kg: 5.0e-5,
            added_mass_kg: 2.536e-5,
            length_m: 7.4e-3,
            diameter_m: 2.8e-3,
        }
    }

    #[test]
    fn limits_convert_power_and_current() {
        let l = CoilLimits {
            max_current_a: 6.0,
            max_total_power_w: 2160.0,
            coil_resistance_ohm: 10.0,
        };
        l.validate().unwrap();
        assert!((l.max_coil_power_w() - 360.0).abs() < 1e-9);
        assert!((l.current_for_power(360.0).unwrap() - 6.0).abs() < 1e-12);
        assert!(l.current_for_power(f64::NAN).is_err());
        let open = CoilLimits {
            coil_resistance_ohm: 0.0,
            ..l
        };
        assert!(open.current_for_power(1.0).is_err());
    }

    #[test]
    fn damping_presets() {
        let r = capsule();
        r.validate().unwrap();
        let fluid = |viscosity_pa_s| FluidParams {
            viscosity_pa_s,
            density_kg_m3: FluidParams::GLYCERIN_WATER_DENSITY,
        };
        // The paper's 65:35 (20 cP) and 40:60 (4.3 cP) glycerin–water mixtures at 23 °C.
        let c20 = r.translational_damping(&fluid(0.020)).unwrap();
        let c43 = r.translational_damping(&fluid(0.0043)).unwrap();
        assert!((c20 / 5.6e-4 - 1.0).abs() < 0.05, "{c20}");
        assert!((c43 / 1.2e-4 - 1.0).abs() < 0.05, "{c43}");
    }

    #[test]
    fn bad_capsules_are_refused() {
        let light = RobotParams {
            mass_kg: -1.0,
            ..capsule()
        };
        assert!(light.validate().is_err());
        let short = RobotParams {
            length_m: 1e-3,
            ..capsule()
        };
        assert!(short.validate().is_err());
    }
}

/// A coil's saturation: the effective gain g(|I|) = B(I) / (I · B̃) relative to the
/// current-normalised field model, given at a few currents and interpolated linearly (gain 1 at
/// zero current unless the first point says otherwise; the last gain holds beyond the last
/// point). The field magnitude I·g(I) must grow with the current, so every field the coil can
/// make has one current.
#[derive(Debug, Clone, PartialEq)]
pub struct SaturationCurve {
    /// (current A, gain), currents ascending and ≥ 0.
    points: Vec<(f64, f64)>,
}

impl SaturationCurve {
    /// Checks the points: currents ≥ 0 strictly ascending, gains finite > 0, I·g(I) increasing.
    pub fn new(points: &[[f64; 2]]) -> Result<Self, String> {
        if points.is_empty() {
            return Err("needs at least one [current_a, gain] point".into());
        }
        let mut pts: Vec<(f64, f64)> = Vec::with_capacity(points.len() + 1);
        if points[0][0] > 0.0 {
            pts.push((0.0, 1.0));
        }
        for (k, p) in points.iter().enumerate() {
            let [i, g] = *p;
            if !(i.is_finite() && i >= 0.0 && g.is_finite() && g > 0.0) {
                return Err(format!(
                    "point {k}: current must be finite and >= 0, gain finite and > 0, got [{i}, {g}]"
                ));
            }
            if let Some(&(prev, _)) = pts.last() {
                if i <= prev {
                    return Err(format!(
                        "point {k}: currents must ascend ({i} A after {prev} A)"
                    ));
                }
            }
            pts.push((i, g));
        }
        // I·g(I) is quadratic on each segment; its slope g + I g' is linear there, so positive
        // slopes at both ends of every segment make it increasing.
        for w in pts.windows(2) {
            let ((i0, g0), (i1, g1)) = (w[0], w[1]);
            let slope = (g1 - g0) / (i1 - i0);
            if g0 + i0 * slope <= 0.0 || g1 + i1 * slope <= 0.0 {
                return Err(format!(
                    "the field I·g(I) must grow with the current; it falls between {i0} A and {i1} A"
                ));
            }
        }
        Ok(Self { points: pts })
    }

    /// Gain at current magnitude `i_abs`.
    pub fn gain(&self, i_abs: f64) -> f64 {
        let pts = &self.points;
        if i_abs <= pts[0].0 {
            return pts[0].1;
        }
        for w in pts.windows(2) {
            let ((i0, g0), (i1, g1)) = (w[0], w[1]);
            if i_abs <= i1 {
                return g0 + (g1 - g0) * (i_abs - i0) / (i1 - i0);
            }
        }
        pts[pts.len() - 1].1
    }

    /// The current-normalised model's equivalent current of a real current: I · g(|I|).
    pub fn effective(&self, current_a: f64) -> f64 {
        current_a * self.gain(current_a.abs())
    }

    /// The real current whose [`Self::effective`] current is `effective_a` (bisection on the
    /// increasing I·g(I)).
    pub fn actual_for(&self, effective_a: f64) -> f64 {
        let target = effective_a.abs();
        if !target.is_finite() {
            return 0.0;
        }
        let mut hi = target / self.gain(target).max(1e-6) + 1.0;
        while self.effective(hi) < target {
            hi *= 2.0;
        }
        let mut lo = 0.0;
        for _ in 0..80 {
            let mid = 0.5 * (lo + hi);
            if self.effective(mid) < target {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        0.5 * (lo + hi) * effective_a.signum()
    }
}

#[cfg(test)]
mod saturation_tests {
    use super::SaturationCurve;

    #[test]
    fn curve_interpolates_and_inverts() {
        let c = SaturationCurve::new(&[[2.0, 1.0], [6.0, 0.85]]).unwrap();
        assert_eq!(c.gain(1.0), 1.0);
        assert!((c.gain(4.0) - 0.925).abs() < 1e-12);
        assert_eq!(c.gain(9.0), 0.85);
        for i in [-5.5, -0.3, 0.0, 2.5, 5.9, 7.0] {
            assert!((c.actual_for(c.effective(i)) - i).abs() < 1e-9, "{i}");
        }
        assert!(SaturationCurve::new(&[]).is_err());
        assert!(SaturationCurve::new(&[[3.0, 1.0], [2.0, 0.9]]).is_err());
        // Field falls: 1 A × 1.0 then 2 A × 0.4.
        assert!(SaturationCurve::new(&[[1.0, 1.0], [2.0, 0.4]]).is_err());
    }
}
