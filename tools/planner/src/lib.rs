//! The paper's planner (Sec. II-C, RIG.md "Planning"): canal mask → Euclidean distance
//! transform (OpenCV, DIST_L2) → 5 mm clearance core → cost = uniform + w_clear · centerline bias
//! → start/end projected to the nearest feasible pixel → 8-connected A* (`pathfinding`, step
//! costs 1 and √2 times the cell cost) → moving average (window 7) → 10 evenly spaced
//! waypoints → world coordinates.
//!
//! Units: SI inside (m); pixels for the grid; `_mm` only in the trajectory file.

use std::path::Path;

use fieldmaps::phantom::{rasterize, ImageGeometry, Phantom, PLANNER_CLEARANCE_M};
use nalgebra::Vector2;
use opencv::core as cv;
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};
use serde::{Deserialize, Serialize};

/// Fixed-point scale of A* costs: one straight step on a cell of cost 1 costs `COST_SCALE`.
/// Integer costs keep the search exact (`pathfinding` needs `Ord` costs).
pub const COST_SCALE: f64 = 1.0e6;

#[derive(Debug, thiserror::Error)]
pub enum PlanError {
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
    #[error("cannot read mask image {0}")]
    MaskUnreadable(String),
    #[error("mask is {got} bytes, expected {width}x{height} = {expected}")]
    MaskSize {
        width: u32,
        height: u32,
        expected: usize,
        got: usize,
    },
    #[error("invalid image geometry: {0}")]
    Geometry(String),
    #[error("invalid planner config: {0}")]
    Config(String),
    #[error("{which} point ({x_mm:.2}, {y_mm:.2}) mm lies outside the image")]
    OutsideImage {
        which: &'static str,
        x_mm: f64,
        y_mm: f64,
    },
    #[error("{which} point ({x_mm:.2}, {y_mm:.2}) mm lies outside the canal mask")]
    OutsideCanal {
        which: &'static str,
        x_mm: f64,
        y_mm: f64,
    },
    #[error("no pixel of the canal keeps {clearance_mm:.2} mm from the wall")]
    NoFeasibleCore { clearance_mm: f64 },
    #[error(
        "start and end cannot be connected within the {clearance_mm:.2} mm clearance core \
         (start projected to px {start:?}, end to px {end:?})"
    )]
    NotConnected {
        start: (u32, u32),
        end: (u32, u32),
        clearance_mm: f64,
    },
}

/// Planner parameters (paper defaults).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlannerConfig {
    /// Minimum wall clearance of the feasible core (paper: 5 mm).
    pub clearance_m: f64,
    /// Weight of the centerline bias in the cell cost (paper: 0.5).
    pub w_clear: f64,
    /// Moving-average window, samples (paper: 7).
    pub smoothing_window: usize,
    /// Evenly spaced output waypoints (paper: 10).
    pub waypoint_count: usize,
}

impl Default for PlannerConfig {
    fn default() -> Self {
        Self {
            clearance_m: PLANNER_CLEARANCE_M,
            w_clear: 0.5,
            smoothing_window: 7,
            waypoint_count: 10,
        }
    }
}

impl PlannerConfig {
    pub fn validate(&self) -> Result<(), PlanError> {
        if !(self.clearance_m.is_finite() && self.clearance_m >= 0.0) {
            return Err(PlanError::Config(
                "clearance must be finite and >= 0".into(),
            ));
        }
        if !(self.w_clear.is_finite() && self.w_clear >= 0.0) {
            return Err(PlanError::Config("w_clear must be finite and >= 0".into()));
        }
        if self.smoothing_window == 0 {
            return Err(PlanError::Config("smoothing window must be >= 1".into()));
        }
        if self.waypoint_count < 2 {
            return Err(PlanError::Config("need at least 2 waypoints".into()));
        }
        Ok(())
    }
}

/// Binary canal mask, row-major, non-zero = canal.
#[derive(Debug, Clone, PartialEq)]
pub struct Mask {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
}

impl Mask {
    pub fn new(width: u32, height: u32, data: Vec<u8>) -> Result<Self, PlanError> {
        let expected = width as usize * height as usize;
        if width == 0 || height == 0 || data.len() != expected {
            return Err(PlanError::MaskSize {
                width,
                height,
                expected,
                got: data.len(),
            });
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// The fieldmaps phantom rasterized on `geom` (the default planning domain).
    pub fn from_phantom(phantom: &Phantom, geom: &ImageGeometry) -> Result<Self, PlanError> {
        geom.validate()
            .map_err(|e| PlanError::Geometry(e.to_string()))?;
        Self::new(geom.width_px, geom.height_px, rasterize(phantom, geom))
    }

    /// A mask image (white = canal; any format OpenCV reads, thresholded at 128).
    pub fn load(path: &Path) -> Result<Self, PlanError> {
        let img = imgcodecs::imread(path.as_os_str(), imgcodecs::IMREAD_GRAYSCALE)?;
        if img.empty() {
            return Err(PlanError::MaskUnreadable(path.display().to_string()));
        }
        let mut bin = cv::Mat::default();
        imgproc::threshold(&img, &mut bin, 127.0, 255.0, imgproc::THRESH_BINARY)?;
        let (w, h) = (bin.cols(), bin.rows());
        let data = if bin.is_continuous() {
            bin.data_bytes()?.to_vec()
        } else {
            bin.try_clone()?.data_bytes()?.to_vec()
        };
        Self::new(w as u32, h as u32, data)
    }

    fn index(&self, col: u32, row: u32) -> usize {
        row as usize * self.width as usize + col as usize
    }

    pub fn is_canal(&self, col: u32, row: u32) -> bool {
        col < self.width && row < self.height && self.data[self.index(col, row)] != 0
    }
}

/// Geometry for a mask of `width × height` px: the default camera's mm/px and a field of view
/// centred on the origin.
pub fn geometry_for(width: u32, height: u32, mm_per_px: f64) -> ImageGeometry {
    ImageGeometry {
        width_px: width,
        height_px: height,
        mm_per_px,
        origin_x_mm: -0.5 * f64::from(width) * mm_per_px,
        origin_y_mm: 0.5 * f64::from(height) * mm_per_px,
    }
}

/// Per-pixel distance to the nearest wall pixel (px), OpenCV `distanceTransform`, DIST_L2 with
/// the precise mask.
pub fn distance_transform(mask: &Mask) -> Result<Vec<f32>, PlanError> {
    let binary: Vec<u8> = mask
        .data
        .iter()
        .map(|&v| if v != 0 { 255 } else { 0 })
        .collect();
    let src =
        cv::Mat::new_rows_cols_with_data::<u8>(mask.height as i32, mask.width as i32, &binary)?;
    let mut dist = cv::Mat::default();
    imgproc::distance_transform(
        &src,
        &mut dist,
        imgproc::DIST_L2,
        imgproc::DIST_MASK_PRECISE,
        cv::CV_32F,
    )?;
    let out = if dist.is_continuous() {
        dist.data_typed::<f32>()?.to_vec()
    } else {
        dist.try_clone()?.data_typed::<f32>()?.to_vec()
    };
    Ok(out)
}

/// Cell costs of a grid: `None` = not traversable.
#[derive(Debug, Clone, PartialEq)]
pub struct CostGrid {
    pub width: u32,
    pub height: u32,
    pub cells: Vec<Option<f64>>,
}

impl CostGrid {
    pub fn cost(&self, col: u32, row: u32) -> Option<f64> {
        if col >= self.width || row >= self.height {
            return None;
        }
        self.cells[row as usize * self.width as usize + col as usize]
    }

    /// The 8 neighbours of (col, row) that are traversable, with the integer step cost
    /// [`step_cost`] of entering them.
    pub fn successors(&self, (col, row): (u32, u32)) -> Vec<((u32, u32), u64)> {
        let mut out = Vec::with_capacity(8);
        for dr in -1i64..=1 {
            for dc in -1i64..=1 {
                if dr == 0 && dc == 0 {
                    continue;
                }
                let (c, r) = (i64::from(col) + dc, i64::from(row) + dr);
                if c < 0 || r < 0 || c >= i64::from(self.width) || r >= i64::from(self.height) {
                    continue;
                }
                let (c, r) = (c as u32, r as u32);
                if let Some(cell) = self.cost(c, r) {
                    out.push(((c, r), step_cost(cell, dr != 0 && dc != 0)));
                }
            }
        }
        out
    }

    /// Smallest cell cost (for the admissible heuristic); 0 when the grid is empty.
    pub fn min_cost(&self) -> f64 {
        self.cells
            .iter()
            .flatten()
            .copied()
            .fold(f64::INFINITY, f64::min)
            .clamp(0.0, f64::MAX)
    }
}

/// Integer cost of one step onto a cell of cost `cell`: ⌈(1 or √2) · cell · COST_SCALE⌉.
pub fn step_cost(cell: f64, diagonal: bool) -> u64 {
    let length = if diagonal {
        std::f64::consts::SQRT_2
    } else {
        1.0
    };
    (length * cell * COST_SCALE).ceil().max(0.0) as u64
}

/// 8-connected A* from `start` to `goal` with the octile-distance heuristic scaled by the
/// smallest cell cost (admissible and consistent with the ceil-rounded step costs). Returns the
/// pixel path (both ends included) and its integer cost.
pub fn astar_grid(
    grid: &CostGrid,
    start: (u32, u32),
    goal: (u32, u32),
) -> Option<(Vec<(u32, u32)>, u64)> {
    grid.cost(start.0, start.1)?;
    grid.cost(goal.0, goal.1)?;
    let min_cost = grid.min_cost();
    pathfinding::prelude::astar(
        &start,
        |&n| grid.successors(n),
        |&(c, r)| {
            let dx = f64::from(c.abs_diff(goal.0));
            let dy = f64::from(r.abs_diff(goal.1));
            let octile = dx.max(dy) + (std::f64::consts::SQRT_2 - 1.0) * dx.min(dy);
            (octile * min_cost * COST_SCALE).floor().max(0.0) as u64
        },
        |&n| n == goal,
    )
}

/// Centered moving average with the window shrunk symmetrically at the ends (so both
/// endpoints are kept exactly).
pub fn moving_average(points: &[[f64; 2]], window: usize) -> Vec<[f64; 2]> {
    let half = window.max(1) / 2;
    let n = points.len();
    (0..n)
        .map(|i| {
            let h = half.min(i).min(n - 1 - i);
            let slice = &points[i - h..=i + h];
            let k = slice.len() as f64;
            let sum = slice
                .iter()
                .fold([0.0, 0.0], |acc, p| [acc[0] + p[0], acc[1] + p[1]]);
            [sum[0] / k, sum[1] / k]
        })
        .collect()
}

/// `count` points evenly spaced by arc length along the polyline (both ends included).
pub fn resample(points: &[[f64; 2]], count: usize) -> Vec<[f64; 2]> {
    if points.is_empty() || count == 0 {
        return Vec::new();
    }
    let mut cumulative = vec![0.0];
    for w in points.windows(2) {
        let d = ((w[1][0] - w[0][0]).powi(2) + (w[1][1] - w[0][1]).powi(2)).sqrt();
        cumulative.push(cumulative[cumulative.len() - 1] + d);
    }
    let total = cumulative[cumulative.len() - 1];
    if count == 1 || total <= 0.0 {
        return vec![points[0]; count];
    }
    let mut out = Vec::with_capacity(count);
    let mut seg = 0;
    for i in 0..count {
        let s = total * i as f64 / (count - 1) as f64;
        while seg + 2 < cumulative.len() && cumulative[seg + 1] < s {
            seg += 1;
        }
        let len = cumulative[seg + 1] - cumulative[seg];
        let t = if len > 0.0 {
            ((s - cumulative[seg]) / len).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let (a, b) = (points[seg], points[seg + 1]);
        out.push([a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t]);
    }
    out
}

/// Polyline length.
pub fn path_length(points: &[Vector2<f64>]) -> f64 {
    points.windows(2).map(|w| (w[1] - w[0]).norm()).sum()
}

/// The feasible core and its cell costs: pixels with clearance ≥ `clearance_m` get
/// 1 + w_clear · (1 − D/D_max), D the distance transform, D_max its maximum over the core
/// (cost 1 on the centerline of the widest part, 1 + w_clear at the core's edge).
pub fn cost_grid(
    mask: &Mask,
    geom: &ImageGeometry,
    config: &PlannerConfig,
) -> Result<(CostGrid, Vec<f32>), PlanError> {
    let dist = distance_transform(mask)?;
    let min_px = config.clearance_m * 1e3 / geom.mm_per_px;
    let core = |d: f32| f64::from(d) >= min_px && d > 0.0;
    let d_max = dist
        .iter()
        .copied()
        .filter(|&d| core(d))
        .fold(0.0f32, f32::max);
    if d_max <= 0.0 {
        return Err(PlanError::NoFeasibleCore {
            clearance_mm: config.clearance_m * 1e3,
        });
    }
    let cells = dist
        .iter()
        .map(|&d| core(d).then(|| 1.0 + config.w_clear * (1.0 - f64::from(d / d_max))))
        .collect();
    Ok((
        CostGrid {
            width: mask.width,
            height: mask.height,
            cells,
        },
        dist,
    ))
}

/// Result of a plan.
#[derive(Debug, Clone)]
pub struct Plan {
    pub start_px: (u32, u32),
    pub end_px: (u32, u32),
    /// Raw A* pixel path.
    pub pixel_path: Vec<(u32, u32)>,
    /// A* cost (units of one straight step on a cost-1 cell).
    pub cost: f64,
    /// Smoothed path in pixel coordinates (col, row).
    pub smoothed_px: Vec<[f64; 2]>,
    /// Output waypoints, m.
    pub waypoints_m: Vec<Vector2<f64>>,
    /// Length of the smoothed path, m.
    pub smoothed_length_m: f64,
}

impl Plan {
    pub fn waypoints_mm(&self) -> Vec<[f64; 2]> {
        self.waypoints_m
            .iter()
            .map(|p| [round_to(p.x * 1e3, 3), round_to(p.y * 1e3, 3)])
            .collect()
    }

    /// Length of the waypoint polyline, m.
    pub fn waypoint_length_m(&self) -> f64 {
        path_length(&self.waypoints_m)
    }
}

fn round_to(v: f64, digits: i32) -> f64 {
    let s = 10f64.powi(digits);
    (v * s).round() / s
}

/// Nearest pixel (Euclidean) of the grid that is traversable.
fn nearest_feasible(grid: &CostGrid, from: (u32, u32)) -> Option<(u32, u32)> {
    let w = grid.width as usize;
    grid.cells
        .iter()
        .enumerate()
        .filter(|(_, c)| c.is_some())
        .map(|(i, _)| ((i % w) as u32, (i / w) as u32))
        .min_by_key(|&(c, r)| {
            let dx = i64::from(c) - i64::from(from.0);
            let dy = i64::from(r) - i64::from(from.1);
            dx * dx + dy * dy
        })
}

/// The whole pipeline on `mask` (in `geom`'s pixels) from `start_m` to `end_m`.
pub fn plan(
    mask: &Mask,
    geom: &ImageGeometry,
    start_m: &Vector2<f64>,
    end_m: &Vector2<f64>,
    config: &PlannerConfig,
) -> Result<Plan, PlanError> {
    config.validate()?;
    geom.validate()
        .map_err(|e| PlanError::Geometry(e.to_string()))?;
    if geom.width_px != mask.width || geom.height_px != mask.height {
        return Err(PlanError::Geometry(format!(
            "geometry is {}x{} px but the mask is {}x{}",
            geom.width_px, geom.height_px, mask.width, mask.height
        )));
    }
    let locate = |which: &'static str, p: &Vector2<f64>| {
        let (x_mm, y_mm) = (p.x * 1e3, p.y * 1e3);
        let px = geom
            .pixel_of(p)
            .ok_or(PlanError::OutsideImage { which, x_mm, y_mm })?;
        if !mask.is_canal(px.0, px.1) {
            return Err(PlanError::OutsideCanal { which, x_mm, y_mm });
        }
        Ok(px)
    };
    let start_raw = locate("start", start_m)?;
    let end_raw = locate("end", end_m)?;
    let (grid, _dist) = cost_grid(mask, geom, config)?;
    let clearance_mm = config.clearance_m * 1e3;
    let start_px =
        nearest_feasible(&grid, start_raw).ok_or(PlanError::NoFeasibleCore { clearance_mm })?;
    let end_px =
        nearest_feasible(&grid, end_raw).ok_or(PlanError::NoFeasibleCore { clearance_mm })?;
    let (pixel_path, cost) =
        astar_grid(&grid, start_px, end_px).ok_or(PlanError::NotConnected {
            start: start_px,
            end: end_px,
            clearance_mm,
        })?;
    let raw: Vec<[f64; 2]> = pixel_path
        .iter()
        .map(|&(c, r)| [f64::from(c), f64::from(r)])
        .collect();
    let smoothed_px = moving_average(&raw, config.smoothing_window);
    let to_world = |p: &[f64; 2]| geom.px_to_world(p[0], p[1]);
    let smoothed_m: Vec<Vector2<f64>> = smoothed_px.iter().map(to_world).collect();
    let waypoints_m = if pixel_path.len() < 2 {
        // Start and end project onto the same pixel: a degenerate but valid plan.
        vec![to_world(&raw[0]); config.waypoint_count]
    } else {
        resample(&smoothed_px, config.waypoint_count)
            .iter()
            .map(to_world)
            .collect()
    };
    Ok(Plan {
        start_px,
        end_px,
        pixel_path,
        cost: cost as f64 / COST_SCALE,
        smoothed_length_m: path_length(&smoothed_m),
        smoothed_px,
        waypoints_m,
    })
}

/// The `[trajectory]` block for a scenario file.
pub fn trajectory_toml(plan: &Plan, speed_mm_s: Option<f64>) -> String {
    let mut out = String::from("[trajectory]\nwaypoints_mm = [\n");
    for p in plan.waypoints_mm() {
        out.push_str(&format!("    [{:.3}, {:.3}],\n", p[0], p[1]));
    }
    out.push_str("]\n");
    if let Some(v) = speed_mm_s {
        out.push_str(&format!("speed_mm_s = {v}\n"));
    }
    out
}

/// `template` (a scenario's TOML text) with its `[trajectory] waypoints_mm` replaced by the
/// plan's waypoints (and `speed_mm_s` if given); other keys are kept.
pub fn scenario_with_plan(
    template: &str,
    plan: &Plan,
    speed_mm_s: Option<f64>,
    rig: Option<&std::path::Path>,
) -> Result<String, PlanError> {
    let mut doc: toml::Table = toml::from_str(template)
        .map_err(|e| PlanError::Config(format!("scenario template: {e}")))?;
    if let Some(rig) = rig {
        // The plan is on this rig's phantom: the scenario runs on it.
        let run = doc
            .entry("run")
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        let Some(run) = run.as_table_mut() else {
            return Err(PlanError::Config(
                "scenario template: `run` is not a table".into(),
            ));
        };
        run.insert("rig".into(), rig.to_string_lossy().into_owned().into());
    }
    let entry = doc
        .entry("trajectory")
        .or_insert_with(|| toml::Value::Table(toml::Table::new()));
    let Some(traj) = entry.as_table_mut() else {
        return Err(PlanError::Config(
            "scenario template: `trajectory` is not a table".into(),
        ));
    };
    let points = plan
        .waypoints_mm()
        .into_iter()
        .map(|p| toml::Value::Array(vec![p[0].into(), p[1].into()]))
        .collect();
    traj.insert("waypoints_mm".into(), toml::Value::Array(points));
    if let Some(v) = speed_mm_s {
        traj.insert("speed_mm_s".into(), v.into());
    }
    toml::to_string(&doc).map_err(|e| PlanError::Config(format!("cannot write scenario: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moving_average_keeps_ends_and_smooths() {
        let pts: Vec<[f64; 2]> = (0..10).map(|i| [i as f64, (i % 2) as f64]).collect();
        let s = moving_average(&pts, 7);
        assert_eq!(s[0], pts[0]);
        assert_eq!(s[9], pts[9]);
        assert!((s[5][1] - 3.0 / 7.0).abs() < 1e-12 || (s[5][1] - 4.0 / 7.0).abs() < 1e-12);
    }

    #[test]
    fn resample_is_even() {
        let pts = vec![[0.0, 0.0], [3.0, 0.0], [3.0, 6.0]];
        let r = resample(&pts, 4);
        assert_eq!(r.len(), 4);
        assert_eq!(r[0], [0.0, 0.0]);
        assert!((r[1][0] - 3.0).abs() < 1e-12 && r[1][1].abs() < 1e-12);
        assert!((r[2][1] - 3.0).abs() < 1e-12);
        assert_eq!(r[3], [3.0, 6.0]);
    }
}
