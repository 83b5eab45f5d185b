//! Named flow zones as polygons on the control plane.

use nalgebra::Vector2;

use crate::phantom::closest_point_on_segment;

/// What a zone means to the flow model and the controller (the paper's two regions).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ZoneKind {
    /// Where the inlet streams converge at the narrowing (paper: y ∈ [−10, 0] mm).
    HighDisturbance,
    /// Recirculation region (paper: y ∈ [−5, 10] mm).
    Recirculation,
}

impl ZoneKind {
    /// The name used in the rig file.
    pub fn as_str(self) -> &'static str {
        match self {
            ZoneKind::HighDisturbance => "high_disturbance",
            ZoneKind::Recirculation => "recirculation",
        }
    }
}

/// A named zone: a simple polygon in world coordinates (m). Points on its boundary count as
/// inside, so an axis-aligned rectangle reproduces a closed band test `lo ≤ v ≤ hi`.
#[derive(Debug, Clone, PartialEq)]
pub struct Zone {
    pub name: String,
    pub kind: ZoneKind,
    pub polygon_m: Vec<Vector2<f64>>,
    /// Centre of the twin's recirculation vortex in this zone (`center_mm`, optional); see
    /// [`super::RigPhantom::zone_center`].
    pub center_m: Option<Vector2<f64>>,
}

/// Distance (m) within which a point counts as on an edge: far below a camera pixel, far above
/// rounding of mm → m conversions.
const ON_EDGE_M: f64 = 1e-12;

impl Zone {
    /// Whether `p` is inside the polygon or on its boundary (even–odd rule). Non-finite is
    /// outside.
    pub fn contains(&self, p: &Vector2<f64>) -> bool {
        polygon_contains(&self.polygon_m, p)
    }

    /// Distance (m) from `p` to the polygon: 0 inside or on it, +∞ for non-finite `p`.
    pub fn distance_outside(&self, p: &Vector2<f64>) -> f64 {
        if !(p.x.is_finite() && p.y.is_finite()) {
            return f64::INFINITY;
        }
        if self.contains(p) {
            return 0.0;
        }
        let n = self.polygon_m.len();
        (0..n)
            .map(|i| {
                let (a, b) = (&self.polygon_m[i], &self.polygon_m[(i + 1) % n]);
                (p - closest_point_on_segment(a, b, p)).norm()
            })
            .fold(f64::INFINITY, f64::min)
    }

    /// Axis-aligned bounding box (min, max), m.
    pub fn bounds(&self) -> (Vector2<f64>, Vector2<f64>) {
        bounds(&self.polygon_m)
    }
}

pub(crate) fn bounds(polygon: &[Vector2<f64>]) -> (Vector2<f64>, Vector2<f64>) {
    let mut lo = Vector2::repeat(f64::INFINITY);
    let mut hi = Vector2::repeat(f64::NEG_INFINITY);
    for v in polygon {
        lo = lo.inf(v);
        hi = hi.sup(v);
    }
    (lo, hi)
}

fn on_segment(a: &Vector2<f64>, b: &Vector2<f64>, p: &Vector2<f64>) -> bool {
    (p - closest_point_on_segment(a, b, p)).norm() <= ON_EDGE_M
}

pub(crate) fn polygon_contains(polygon: &[Vector2<f64>], p: &Vector2<f64>) -> bool {
    if !(p.x.is_finite() && p.y.is_finite()) || polygon.len() < 3 {
        return false;
    }
    let n = polygon.len();
    let mut inside = false;
    for i in 0..n {
        let (a, b) = (&polygon[i], &polygon[(i + 1) % n]);
        if on_segment(a, b, p) {
            return true;
        }
        if (a.y > p.y) != (b.y > p.y) {
            let x_cross = a.x + (p.y - a.y) / (b.y - a.y) * (b.x - a.x);
            if p.x < x_cross {
                inside = !inside;
            }
        }
    }
    inside
}

#[cfg(test)]
mod tests {
    use super::*;

    fn zone(points: &[(f64, f64)]) -> Zone {
        Zone {
            name: "z".into(),
            kind: ZoneKind::Recirculation,
            polygon_m: points.iter().map(|&(x, y)| Vector2::new(x, y)).collect(),
            center_m: None,
        }
    }

    #[test]
    fn distance_outside_is_zero_inside_and_to_the_nearest_edge_outside() {
        let z = zone(&[(-1.0, -1.0), (2.0, -1.0), (2.0, 3.0), (-1.0, 3.0)]);
        assert_eq!(z.distance_outside(&Vector2::new(0.0, 0.0)), 0.0);
        assert!((z.distance_outside(&Vector2::new(0.0, 4.5)) - 1.5).abs() < 1e-12);
        assert!((z.distance_outside(&Vector2::new(5.0, 7.0)) - 5.0).abs() < 1e-12);
        assert_eq!(
            z.distance_outside(&Vector2::new(f64::NAN, 0.0)),
            f64::INFINITY
        );
    }

    #[test]
    fn rectangle_is_a_closed_band() {
        let z = zone(&[(-1.0, -1.0), (2.0, -1.0), (2.0, 3.0), (-1.0, 3.0)]);
        for (p, inside) in [
            ((0.0, 0.0), true),
            ((-1.0, -1.0), true),
            ((2.0, 1.0), true),
            ((0.5, 3.0), true),
            ((2.0 + 1e-9, 1.0), false),
            ((0.0, -1.0 - 1e-9), false),
            ((5.0, 0.0), false),
            ((f64::NAN, 0.0), false),
        ] {
            assert_eq!(z.contains(&Vector2::new(p.0, p.1)), inside, "{p:?}");
        }
    }

    #[test]
    fn concave_polygon() {
        // An L shape: the notch (1.5, 1.5) is outside.
        let z = zone(&[
            (0.0, 0.0),
            (2.0, 0.0),
            (2.0, 1.0),
            (1.0, 1.0),
            (1.0, 2.0),
            (0.0, 2.0),
        ]);
        assert!(z.contains(&Vector2::new(0.5, 1.5)));
        assert!(z.contains(&Vector2::new(1.5, 0.5)));
        assert!(!z.contains(&Vector2::new(1.5, 1.5)));
        let (lo, hi) = z.bounds();
        assert_eq!((lo, hi), (Vector2::zeros(), Vector2::new(2.0, 2.0)));
    }
}
