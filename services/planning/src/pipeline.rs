//! The whole pipeline: locate the ends, build the grid, search, smooth, resample, to world.

use fieldmaps::phantom::ImageGeometry;
use nalgebra::Vector2;

use crate::grid::nearest_feasible;
use crate::{astar_grid, cost_grid, moving_average, path_length, resample, Mask, PlanError};
use crate::{PlannerConfig, COST_SCALE};

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
