//! Parametric top-view phantom and camera image geometry.
//!
//! The canal (fluid) is a union of primitives — discs and thick polylines (chains of capsule
//! segments) — described by a signed distance field: negative in the canal, positive in the
//! agarose wall. Coordinates: metres, x right, y up, origin at the centre of the camera view.
//! A phantom is data ([`file`]): the paper's heart is `fieldmaps/rigs/paper/heart_phantom.toml`.

mod file;

use nalgebra::{Unit, Vector2};
use thiserror::Error;

pub use file::{PhantomFileError, PHANTOM_FORMAT, PHANTOM_VERSION};

/// Planner's minimum wall clearance (paper: 5 mm).
pub const PLANNER_CLEARANCE_M: f64 = 0.005;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum PhantomError {
    #[error("phantom has no primitives")]
    Empty,
    #[error("primitive {0} has a non-finite coordinate or a non-positive radius")]
    BadPrimitive(usize),
    #[error("{0} is not inside the canal")]
    PointOutside(&'static str),
    #[error("invalid image geometry: {0}")]
    BadImageGeometry(&'static str),
}

/// One piece of the canal.
#[derive(Debug, Clone, PartialEq)]
pub enum Primitive {
    Disc {
        center_m: Vector2<f64>,
        radius_m: f64,
    },
    /// Points swept by a disc of `radius_m` along the polyline.
    Tube {
        points_m: Vec<Vector2<f64>>,
        radius_m: f64,
    },
}

/// Unit vector of `v`, or `fallback` where `v` is (numerically) zero.
fn unit_or(v: Vector2<f64>, fallback: Vector2<f64>) -> Vector2<f64> {
    v.try_normalize(0.0).unwrap_or(fallback)
}

impl Primitive {
    /// Signed distance and its gradient (unit, pointing out of this primitive).
    fn sdf_and_normal(&self, p: &Vector2<f64>) -> (f64, Vector2<f64>) {
        match self {
            Primitive::Disc { center_m, radius_m } => {
                let d = p - center_m;
                (d.norm() - radius_m, unit_or(d, Vector2::x()))
            }
            Primitive::Tube { points_m, radius_m } => {
                let mut best = (f64::INFINITY, Vector2::x());
                if let [single] = points_m.as_slice() {
                    let d = p - single;
                    return (d.norm() - radius_m, unit_or(d, Vector2::x()));
                }
                for seg in points_m.windows(2) {
                    let (a, b) = (seg[0], seg[1]);
                    let ab = b - a;
                    let d = p - closest_point_on_segment(&a, &b, p);
                    let dist = d.norm() - radius_m;
                    if dist < best.0 {
                        // On the centreline the gradient is undefined; pick the left normal.
                        let left = unit_or(Vector2::new(-ab.y, ab.x), Vector2::x());
                        best = (dist, unit_or(d, left));
                    }
                }
                best
            }
        }
    }

    fn is_valid(&self) -> bool {
        let finite = |v: &Vector2<f64>| v.iter().all(|c| c.is_finite());
        match self {
            Primitive::Disc { center_m, radius_m } => finite(center_m) && *radius_m > 0.0,
            Primitive::Tube { points_m, radius_m } => {
                !points_m.is_empty() && points_m.iter().all(finite) && *radius_m > 0.0
            }
        }
    }
}

/// A flow inlet (for the CFD/flow model): a straight tube ending at `mouth_m`.
#[derive(Debug, Clone, PartialEq)]
pub struct Inlet {
    pub name: String,
    /// Where the tube opens into the chamber, m.
    pub mouth_m: Vector2<f64>,
    /// Flow direction (into the phantom).
    pub direction: Unit<Vector2<f64>>,
    pub diameter_m: f64,
    /// Straight length upstream of the mouth (the part outside the camera view included), m.
    pub length_m: f64,
}

/// The flow outlet (pressure outlet in the CFD).
#[derive(Debug, Clone, PartialEq)]
pub struct Outlet {
    pub name: String,
    /// Where the outlet tube leaves the pulmonary trunk, m.
    pub mouth_m: Vector2<f64>,
    /// Flow direction (out of the phantom).
    pub direction: Unit<Vector2<f64>>,
    pub diameter_m: f64,
}

/// The canal geometry plus its ports and the default navigation task.
#[derive(Debug, Clone, PartialEq)]
pub struct Phantom {
    primitives: Vec<Primitive>,
    inlets: Vec<Inlet>,
    outlet: Outlet,
    start_m: Vector2<f64>,
    end_m: Vector2<f64>,
}

impl Phantom {
    /// A custom phantom; `start_m` and `end_m` must lie in the canal.
    pub fn new(
        primitives: Vec<Primitive>,
        inlets: Vec<Inlet>,
        outlet: Outlet,
        start_m: Vector2<f64>,
        end_m: Vector2<f64>,
    ) -> Result<Self, PhantomError> {
        if primitives.is_empty() {
            return Err(PhantomError::Empty);
        }
        if let Some(i) = primitives.iter().position(|p| !p.is_valid()) {
            return Err(PhantomError::BadPrimitive(i));
        }
        let ph = Self {
            primitives,
            inlets,
            outlet,
            start_m,
            end_m,
        };
        if !ph.contains(&start_m) {
            return Err(PhantomError::PointOutside("start"));
        }
        if !ph.contains(&end_m) {
            return Err(PhantomError::PointOutside("end"));
        }
        Ok(ph)
    }

    pub fn primitives(&self) -> &[Primitive] {
        &self.primitives
    }

    /// Signed distance to the canal wall, m: < 0 in the fluid, > 0 in the wall.
    ///
    /// The union is the min over primitives: exact in the wall; in the fluid it is the depth
    /// inside the deepest single primitive, which never overestimates the true clearance.
    /// Non-finite `p` counts as wall (+∞).
    pub fn signed_distance(&self, p: &Vector2<f64>) -> f64 {
        self.signed_distance_and_normal(p).0
    }

    /// Unit gradient of [`Self::signed_distance`] (points into the wall). Where the gradient is
    /// undefined (a disc centre, a centreline) some unit vector is returned.
    pub fn wall_normal(&self, p: &Vector2<f64>) -> Vector2<f64> {
        self.signed_distance_and_normal(p).1
    }

    /// Both of the above in one pass.
    pub fn signed_distance_and_normal(&self, p: &Vector2<f64>) -> (f64, Vector2<f64>) {
        if !p.iter().all(|c| c.is_finite()) {
            return (f64::INFINITY, Vector2::x());
        }
        self.primitives
            .iter()
            .map(|prim| prim.sdf_and_normal(p))
            .fold((f64::INFINITY, Vector2::x()), |best, cand| {
                if cand.0 < best.0 {
                    cand
                } else {
                    best
                }
            })
    }

    /// Distance to the wall from a point in the canal (≤ 0 outside it), m.
    pub fn clearance(&self, p: &Vector2<f64>) -> f64 {
        -self.signed_distance(p)
    }

    pub fn contains(&self, p: &Vector2<f64>) -> bool {
        self.signed_distance(p) < 0.0
    }

    /// The default task's start.
    pub fn default_start(&self) -> Vector2<f64> {
        self.start_m
    }

    /// The default task's end.
    pub fn default_end(&self) -> Vector2<f64> {
        self.end_m
    }

    pub fn inlets(&self) -> Vec<Inlet> {
        self.inlets.clone()
    }

    pub fn outlet(&self) -> Outlet {
        self.outlet.clone()
    }
}

/// Camera image ↔ world mapping (top view).
///
/// Pixel (col, row) indices are continuous: integer values are pixel centres, so
/// x_mm = origin_x_mm + (col + 0.5)·mm_per_px and y_mm = origin_y_mm − (row + 0.5)·mm_per_px
/// (rows grow downward, y grows upward). `origin_*` is the outer corner of pixel (0, 0).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageGeometry {
    pub width_px: u32,
    pub height_px: u32,
    pub mm_per_px: f64,
    pub origin_x_mm: f64,
    pub origin_y_mm: f64,
}

impl ImageGeometry {
    /// Largest image [`rasterize`] will allocate (64 Mpx).
    pub const MAX_PIXELS: u64 = 1 << 26;

    pub fn validate(&self) -> Result<(), PhantomError> {
        if self.width_px == 0 || self.height_px == 0 {
            return Err(PhantomError::BadImageGeometry("zero size"));
        }
        if u64::from(self.width_px) * u64::from(self.height_px) > Self::MAX_PIXELS {
            return Err(PhantomError::BadImageGeometry("too many pixels"));
        }
        if !(self.mm_per_px.is_finite() && self.mm_per_px > 0.0) {
            return Err(PhantomError::BadImageGeometry("mm_per_px must be > 0"));
        }
        if !(self.origin_x_mm.is_finite() && self.origin_y_mm.is_finite()) {
            return Err(PhantomError::BadImageGeometry("non-finite origin"));
        }
        Ok(())
    }

    /// The contract's image ↔ world mapping for this geometry (what the camera puts in every
    /// `FrameHeader`); the conversions below delegate to it so the convention lives in one place.
    pub fn pixel_mapping(&self) -> shm_schemas_core::PixelMapping {
        shm_schemas_core::PixelMapping {
            mm_per_px: self.mm_per_px,
            origin_x_mm: self.origin_x_mm,
            origin_y_mm: self.origin_y_mm,
        }
    }

    /// Pixel coordinates → world point, m.
    pub fn px_to_world(&self, col: f64, row: f64) -> Vector2<f64> {
        Vector2::from(self.pixel_mapping().pixel_to_world_m(col, row))
    }

    /// World point (m) → continuous pixel coordinates (col, row).
    pub fn world_to_px(&self, p: &Vector2<f64>) -> (f64, f64) {
        self.pixel_mapping().world_to_pixel([p.x, p.y])
    }

    /// The pixel containing `p`, if it is in the image.
    pub fn pixel_of(&self, p: &Vector2<f64>) -> Option<(u32, u32)> {
        let (c, r) = self.world_to_px(p);
        let (c, r) = (c.round(), r.round());
        let inside = |v: f64, n: u32| v >= 0.0 && v < f64::from(n);
        (inside(c, self.width_px) && inside(r, self.height_px)).then_some((c as u32, r as u32))
    }
}

/// Canal mask value in [`rasterize`]'s output.
pub const MASK_CANAL: u8 = 255;
/// Wall mask value in [`rasterize`]'s output.
pub const MASK_WALL: u8 = 0;

/// Row-major mask (`width_px × height_px`), [`MASK_CANAL`] where the pixel centre is in the
/// canal, [`MASK_WALL`] elsewhere. Returns an empty vector if `geom` is invalid (see
/// [`ImageGeometry::validate`]).
pub fn rasterize(phantom: &Phantom, geom: &ImageGeometry) -> Vec<u8> {
    if geom.validate().is_err() {
        return Vec::new();
    }
    let (w, h) = (geom.width_px as usize, geom.height_px as usize);
    let mut mask = vec![MASK_WALL; w * h];
    for (row, line) in mask.chunks_exact_mut(w).enumerate() {
        for (col, px) in line.iter_mut().enumerate() {
            if phantom.contains(&geom.px_to_world(col as f64, row as f64)) {
                *px = MASK_CANAL;
            }
        }
    }
    mask
}

/// The point of segment a–b closest to `p` (`a` for a degenerate segment).
pub(crate) fn closest_point_on_segment(
    a: &Vector2<f64>,
    b: &Vector2<f64>,
    p: &Vector2<f64>,
) -> Vector2<f64> {
    let ab = b - a;
    let len2 = ab.norm_squared();
    let t = if len2 > 0.0 {
        ((p - a).dot(&ab) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    a + ab * t
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use std::collections::VecDeque;

    /// The paper's top camera as `fieldmaps/rigs/paper.toml` gives it: 1020 × 1020 px over
    /// 92 × 92 mm, centred on the origin (the view `paper/heart_mask.png` was drawn in).
    /// The paper's heart phantom, from its file.
    pub(crate) fn heart() -> Phantom {
        let path = crate::data_root().join("fieldmaps/rigs/paper/heart_phantom.toml");
        Phantom::load(&path).unwrap_or_else(|e| panic!("{e}"))
    }

    pub(crate) fn geom() -> ImageGeometry {
        ImageGeometry {
            width_px: 1020,
            height_px: 1020,
            mm_per_px: 92.0 / 1020.0,
            origin_x_mm: -46.0,
            origin_y_mm: 46.0,
        }
    }

    #[test]
    fn default_task_has_clearance() {
        let ph = heart();
        for (name, p) in [("start", ph.default_start()), ("end", ph.default_end())] {
            assert!(ph.contains(&p), "{name}");
            assert!(
                ph.clearance(&p) >= PLANNER_CLEARANCE_M,
                "{name}: {}",
                ph.clearance(&p)
            );
        }
    }

    /// 8-connected flood fill over pixels where `ok`, from `a` to `b`.
    fn connected(ok: &[bool], w: usize, h: usize, a: (u32, u32), b: (u32, u32)) -> bool {
        let idx = |c: usize, r: usize| r * w + c;
        let (a, b) = ((a.0 as usize, a.1 as usize), (b.0 as usize, b.1 as usize));
        if !ok[idx(a.0, a.1)] || !ok[idx(b.0, b.1)] {
            return false;
        }
        let mut seen = vec![false; w * h];
        let mut queue = VecDeque::from([a]);
        seen[idx(a.0, a.1)] = true;
        while let Some((c, r)) = queue.pop_front() {
            if (c, r) == b {
                return true;
            }
            for dr in -1i64..=1 {
                for dc in -1i64..=1 {
                    let (nc, nr) = (c as i64 + dc, r as i64 + dr);
                    if nc < 0 || nr < 0 || nc >= w as i64 || nr >= h as i64 {
                        continue;
                    }
                    let i = idx(nc as usize, nr as usize);
                    if ok[i] && !seen[i] {
                        seen[i] = true;
                        queue.push_back((nc as usize, nr as usize));
                    }
                }
            }
        }
        false
    }

    #[test]
    fn raster_is_connected_with_planner_clearance() {
        let ph = heart();
        let g = geom();
        let mask = rasterize(&ph, &g);
        let (w, h) = (g.width_px as usize, g.height_px as usize);
        assert_eq!(mask.len(), w * h);
        assert!(mask.iter().all(|&v| v == MASK_CANAL || v == MASK_WALL));
        let canal = mask.iter().filter(|&&v| v == MASK_CANAL).count();
        let frac = canal as f64 / mask.len() as f64;
        assert!((0.10..0.5).contains(&frac), "canal fraction {frac}");

        let start = g.pixel_of(&ph.default_start()).unwrap();
        let end = g.pixel_of(&ph.default_end()).unwrap();
        let canal_px: Vec<bool> = mask.iter().map(|&v| v == MASK_CANAL).collect();
        assert!(connected(&canal_px, w, h, start, end));
        // The planner's feasible core (≥ 5 mm from the wall) must connect start and end too.
        // The union SDF underestimates clearance, so this is conservative.
        let core: Vec<bool> = (0..w * h)
            .map(|i| {
                let p = g.px_to_world((i % w) as f64, (i / w) as f64);
                ph.clearance(&p) >= PLANNER_CLEARANCE_M
            })
            .collect();
        assert!(connected(&core, w, h, start, end));
    }

    #[test]
    fn canal_fits_the_view_except_ports() {
        let ph = heart();
        let g = geom();
        let mask = rasterize(&ph, &g);
        let w = g.width_px as usize;
        // Border pixels are wall except where the inlet/outlet tubes leave the view.
        let mut border_canal = Vec::new();
        for i in 0..w {
            for (c, r) in [(i, 0), (i, w - 1), (0, i), (w - 1, i)] {
                if mask[r * w + c] == MASK_CANAL {
                    border_canal.push(g.px_to_world(c as f64, r as f64));
                }
            }
        }
        assert!(!border_canal.is_empty());
        for p in border_canal {
            let near_port = (p.x - -0.020).abs() < 0.002 // inlet 1, top edge
                || (p.y - -0.001).abs() < 0.002 // inlet 2, left edge
                || (p.x - 0.013).abs() < 0.003; // outlet, top edge
            assert!(near_port, "{p:?}");
        }
    }

    #[test]
    fn ports_are_consistent() {
        let ph = heart();
        let inlets = ph.inlets();
        assert_eq!(inlets.len(), 2);
        for inlet in &inlets {
            assert!((inlet.diameter_m - 0.003).abs() < 1e-12);
            assert!((inlet.length_m - 0.085).abs() < 1e-12);
            // The mouth is on the chamber wall line, with the tube upstream of it in the canal.
            let up = inlet.mouth_m - inlet.direction.into_inner() * 0.002;
            assert!(
                ph.contains(&inlet.mouth_m) && ph.contains(&up),
                "{}",
                inlet.name
            );
            // The tube is narrower than the robot (2.8 mm) plus the planner clearance.
            assert!(ph.clearance(&up) < PLANNER_CLEARANCE_M);
        }
        let out = ph.outlet();
        let down = out.mouth_m + out.direction.into_inner() * 0.003;
        assert!(ph.contains(&out.mouth_m) && ph.contains(&down));
        // Inlet jets point into the paper's high-disturbance band (y in [-10, 0] mm), toward
        // the valve.
        let (lo, hi) = (-0.010, 0.0);
        assert!((lo..=hi).contains(&inlets[1].mouth_m.y));
        let neck = Vector2::new(-0.005, -0.0075);
        assert!(ph.contains(&neck) && (lo..=hi).contains(&neck.y));
    }

    #[test]
    fn sdf_and_normal_behave() {
        let ph = heart();
        // Right atrium: a point just inside its left wall.
        let p = Vector2::new(-0.030, 0.010);
        assert!((ph.signed_distance(&p) - -0.001).abs() < 1e-12);
        assert!((ph.wall_normal(&p) - Vector2::new(-1.0, 0.0)).norm() < 1e-12);
        // Far in the wall, exact distance to the nearest primitive.
        let q = Vector2::new(-0.040, 0.040);
        assert!(ph.signed_distance(&q) > 0.0 && !ph.contains(&q));
        // Normal = unit gradient of the SDF wherever it is differentiable.
        let h = 1e-7;
        for &(x, y) in &[
            (-0.030, 0.010),
            (-0.002, -0.010),
            (0.035, 0.0),
            (0.0145, 0.040),
            (-0.040, 0.040),
            (0.0, 0.0),
        ] {
            let p = Vector2::new(x, y);
            let grad = Vector2::new(
                ph.signed_distance(&(p + Vector2::x() * h))
                    - ph.signed_distance(&(p - Vector2::x() * h)),
                ph.signed_distance(&(p + Vector2::y() * h))
                    - ph.signed_distance(&(p - Vector2::y() * h)),
            ) / (2.0 * h);
            let n = ph.wall_normal(&p);
            assert!((n.norm() - 1.0).abs() < 1e-12);
            assert!((grad - n).norm() < 1e-5, "{p:?}: {grad:?} vs {n:?}");
        }
        // Non-finite input is wall, not a panic.
        assert!(!ph.contains(&Vector2::new(f64::NAN, 0.0)));
        assert!(ph.wall_normal(&Vector2::new(f64::INFINITY, 0.0)).norm() > 0.0);
    }

    #[test]
    fn custom_phantom_validation() {
        let ph = heart();
        let disc = Primitive::Disc {
            center_m: Vector2::zeros(),
            radius_m: 0.01,
        };
        let ok = Phantom::new(
            vec![disc.clone()],
            vec![],
            ph.outlet(),
            Vector2::zeros(),
            Vector2::new(0.005, 0.0),
        );
        assert!(ok.is_ok());
        let outside = Phantom::new(
            vec![disc],
            vec![],
            ph.outlet(),
            Vector2::zeros(),
            Vector2::new(0.02, 0.0),
        );
        assert_eq!(outside, Err(PhantomError::PointOutside("end")));
        let bad = Primitive::Tube {
            points_m: vec![],
            radius_m: 0.01,
        };
        let err = Phantom::new(
            vec![bad],
            vec![],
            ph.outlet(),
            Vector2::zeros(),
            Vector2::zeros(),
        );
        assert_eq!(err, Err(PhantomError::BadPrimitive(0)));
    }

    #[test]
    fn image_geometry_mapping() {
        let g = geom();
        let p00 = g.px_to_world(0.0, 0.0);
        let half = 0.5 * 92.0 / 1020.0;
        assert!((p00 - Vector2::new(-46.0 + half, 46.0 - half) * 1e-3).norm() < 1e-15);
        let last = g.px_to_world(1019.0, 1019.0);
        assert!((last - Vector2::new(46.0 - half, -46.0 + half) * 1e-3).norm() < 1e-15);
        for &(c, r) in &[(0.0, 0.0), (509.5, 509.5), (123.25, 987.0)] {
            let (c2, r2) = g.world_to_px(&g.px_to_world(c, r));
            assert!((c2 - c).abs() < 1e-9 && (r2 - r).abs() < 1e-9);
        }
        assert_eq!(g.pixel_of(&Vector2::zeros()), Some((510, 510)));
        assert_eq!(g.pixel_of(&Vector2::new(0.05, 0.0)), None);
        let bad = ImageGeometry {
            mm_per_px: 0.0,
            ..g
        };
        assert!(bad.validate().is_err());
        assert!(rasterize(&heart(), &bad).is_empty());
        let small = ImageGeometry {
            width_px: 64,
            height_px: 32,
            mm_per_px: 92.0 / 64.0,
            ..g
        };
        assert_eq!(rasterize(&heart(), &small).len(), 64 * 32);
    }
}
