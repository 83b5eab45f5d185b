//! The search grid: cell costs from the distance transform, and 8-connected A* over them.

use fieldmaps::phantom::ImageGeometry;

use crate::{distance_transform, Mask, PlanError, PlannerConfig};

/// Fixed-point scale of A* costs: one straight step on a cell of cost 1 costs `COST_SCALE`.
/// Integer costs keep the search exact (`pathfinding` needs `Ord` costs).
pub const COST_SCALE: f64 = 1.0e6;

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

/// The feasible core and its cell costs: pixels with clearance ≥ `clearance_m` get
/// 1 + w_clear · (1 − D/D_max), D the distance transform, D_max its maximum over the core
/// (cost 1 on the centerline of the widest part, 1 + w_clear at the core's edge).
pub fn cost_grid(
    mask: &Mask,
    geom: &ImageGeometry,
    config: &PlannerConfig,
) -> Result<(CostGrid, Vec<f32>), PlanError> {
    let dist = distance_transform(mask);
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

/// Nearest pixel (Euclidean) of the grid that is traversable.
pub(crate) fn nearest_feasible(grid: &CostGrid, from: (u32, u32)) -> Option<(u32, u32)> {
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
