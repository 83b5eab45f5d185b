//! The paper's planner (Sec. II-C, RIG.md "Planning"): canal mask → exact Euclidean distance
//! transform → 5 mm clearance core → cost = uniform + w_clear · centerline bias → start/end
//! projected to the nearest feasible pixel → 8-connected A* (`pathfinding`, step costs 1 and √2
//! times the cell cost) → moving average (window 7) → 10 evenly spaced waypoints → world
//! coordinates.
//!
//! A library for the services (control replans `goto` with it) and the `planner` tool; it
//! reads no image file and logs nowhere, so it pulls in neither OpenCV nor Rerun.
//!
//! Units: SI inside (m); pixels for the grid; `_mm` only in the trajectory file.

mod config;
mod distance;
mod error;
mod grid;
mod mask;
mod path;
mod pipeline;
mod scenario;

pub use config::PlannerConfig;
pub use distance::distance_transform;
pub use error::PlanError;
pub use grid::{astar_grid, cost_grid, step_cost, CostGrid, COST_SCALE};
pub use mask::{geometry_for, Mask};
pub use path::{moving_average, path_length, resample};
pub use pipeline::{plan, Plan};
pub use scenario::{scenario_with_plan, trajectory_toml};
