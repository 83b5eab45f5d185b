//! The canal wall as a signed distance field sampled from a [`CanalMask`]: what the twin's
//! contact model and clearance checks need for any phantom, not only a parametric one.
//!
//! At each pixel centre the value is the distance to the nearest pixel of the other kind minus
//! half a pixel (the wall lies between the two pixel centres), negative in the canal and
//! positive in the wall; between centres it is interpolated bilinearly. Accuracy is about half
//! a mask pixel, well below the capsule's radius at any sensible mask resolution.

use std::sync::Arc;

use nalgebra::Vector2;

use crate::mask::{squared_distance_px, CanalMask, UNREACHED};
use crate::phantom::ImageGeometry;

/// Signed distance to the canal wall, m: < 0 in the fluid, > 0 in the wall.
#[derive(Debug, Clone, PartialEq)]
pub struct WallField {
    geometry: ImageGeometry,
    /// Row-major, m, at pixel centres.
    signed_m: Arc<[f32]>,
}

impl WallField {
    pub fn from_mask(mask: &CanalMask) -> Self {
        let geometry = *mask.geometry();
        let (w, h) = (mask.width() as usize, mask.height() as usize);
        let canal = mask.canal_flags();
        let walls: Vec<bool> = canal.iter().map(|&c| !c).collect();
        let to_wall = squared_distance_px(w, h, &walls);
        let to_canal = squared_distance_px(w, h, canal);
        let px_m = geometry.mm_per_px * 1e-3;
        // An all-canal or all-wall mask has no boundary: a large finite distance keeps the
        // interpolation finite.
        let far = (w + h) as f64;
        let signed_m = canal
            .iter()
            .enumerate()
            .map(|(i, &is_canal)| {
                let (d2, sign) = if is_canal {
                    (to_wall[i], -1.0)
                } else {
                    (to_canal[i], 1.0)
                };
                let d_px = if d2 >= UNREACHED { far } else { d2.sqrt() };
                (sign * (d_px - 0.5) * px_m) as f32
            })
            .collect();
        Self { geometry, signed_m }
    }

    pub fn geometry(&self) -> &ImageGeometry {
        &self.geometry
    }

    fn at_px(&self, col: usize, row: usize) -> f64 {
        f64::from(self.signed_m[row * self.geometry.width_px as usize + col])
    }

    /// Signed distance at `p` (m). Points outside the mask take the value at the nearest edge
    /// point; a non-finite `p` counts as wall (+∞).
    pub fn signed_distance(&self, p: &Vector2<f64>) -> f64 {
        if !(p.x.is_finite() && p.y.is_finite()) {
            return f64::INFINITY;
        }
        let (col, row) = self.geometry.world_to_px(p);
        let max_c = f64::from(self.geometry.width_px - 1);
        let max_r = f64::from(self.geometry.height_px - 1);
        let (c, r) = (col.clamp(0.0, max_c), row.clamp(0.0, max_r));
        let (c0, r0) = (c.floor() as usize, r.floor() as usize);
        let c1 = (c0 + 1).min(max_c as usize);
        let r1 = (r0 + 1).min(max_r as usize);
        let (fc, fr) = (c - c0 as f64, r - r0 as f64);
        let top = self.at_px(c0, r0) * (1.0 - fc) + self.at_px(c1, r0) * fc;
        let bottom = self.at_px(c0, r1) * (1.0 - fc) + self.at_px(c1, r1) * fc;
        top * (1.0 - fr) + bottom * fr
    }

    /// Unit gradient of [`Self::signed_distance`] (points into the wall), by central
    /// differences over one pixel; where it vanishes (a ridge) some unit vector is returned.
    pub fn wall_normal(&self, p: &Vector2<f64>) -> Vector2<f64> {
        let h = 0.5 * self.geometry.mm_per_px * 1e-3;
        let dx = Vector2::new(h, 0.0);
        let dy = Vector2::new(0.0, h);
        let g = Vector2::new(
            self.signed_distance(&(p + dx)) - self.signed_distance(&(p - dx)),
            self.signed_distance(&(p + dy)) - self.signed_distance(&(p - dy)),
        );
        g.try_normalize(1e-15).unwrap_or_else(Vector2::x)
    }

    /// Whether `p` is in the fluid (signed distance < 0).
    pub fn contains(&self, p: &Vector2<f64>) -> bool {
        self.signed_distance(p) < 0.0
    }

    /// Distance to the wall from a point in the canal (≤ 0 outside it), m.
    pub fn clearance(&self, p: &Vector2<f64>) -> f64 {
        -self.signed_distance(p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_the_parametric_phantom_within_a_pixel() {
        let geometry = crate::phantom::tests::geom();
        let heart = crate::phantom::tests::heart();
        let mask = CanalMask::from_phantom(&heart, &geometry).unwrap();
        let walls = WallField::from_mask(&mask);
        let px = geometry.mm_per_px * 1e-3;
        // Points on both sides of the atrium wall (disc centre (-16, 10) mm, r 15 mm) and deep
        // in the ventricle disc (centre (4, -24) mm, r 13 mm).
        for p_mm in [
            [-16.0, 10.0],
            [-16.0, -4.0],
            [-16.0, -6.0],
            [-31.5, 10.0],
            [4.0, -36.0],
            [4.0, -38.0],
        ] {
            let p = Vector2::new(p_mm[0], p_mm[1]) * 1e-3;
            let truth = heart.signed_distance(&p);
            let got = walls.signed_distance(&p);
            // The primitive union underestimates clearance deep inside; compare near walls.
            if truth.abs() < 3e-3 {
                assert!((got - truth).abs() < px, "{p_mm:?}: {got} vs {truth}");
            }
            assert_eq!(got < 0.0, truth < 0.0, "{p_mm:?}: {got} vs {truth}");
        }
        // The normal on the atrium's lower wall points down (into the wall).
        let n = walls.wall_normal(&(Vector2::new(-16.0, -4.5) * 1e-3));
        assert!(n.y < -0.95, "{n:?}");
        assert_eq!(
            walls.signed_distance(&Vector2::new(f64::NAN, 0.0)),
            f64::INFINITY
        );
    }
}
