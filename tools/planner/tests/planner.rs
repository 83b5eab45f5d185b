//! Planner tests: A* optimality against a brute-force Dijkstra on small grids, the default
//! phantom plan, and the error cases.

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use fieldmaps::phantom::{ImageGeometry, Phantom};
use millinav_planner::{load_mask, MaskLoadError};
use millinav_planning::{
    astar_grid, distance_transform, geometry_for, plan, step_cost, CostGrid, Mask, PlanError,
    PlannerConfig,
};
use nalgebra::Vector2;

struct SeededRng(rand_chacha::ChaCha8Rng);
impl SeededRng {
    fn seeded(seed: u64) -> Self {
        Self(rand::SeedableRng::seed_from_u64(seed))
    }
    fn next(&mut self) -> f64 {
        rand::Rng::random_range(&mut self.0, 0.0..1.0)
    }
}

/// Plain Dijkstra over every cell, written independently of the planner's neighbour code.
fn dijkstra(grid: &CostGrid, start: (u32, u32), goal: (u32, u32)) -> Option<u64> {
    let (w, h) = (grid.width as i64, grid.height as i64);
    let idx = |c: i64, r: i64| (r * w + c) as usize;
    let mut dist = vec![u64::MAX; (w * h) as usize];
    let mut heap = BinaryHeap::new();
    grid.cost(start.0, start.1)?;
    dist[idx(start.0.into(), start.1.into())] = 0;
    heap.push(Reverse((0u64, i64::from(start.0), i64::from(start.1))));
    while let Some(Reverse((d, c, r))) = heap.pop() {
        if d > dist[idx(c, r)] {
            continue;
        }
        if (c, r) == (i64::from(goal.0), i64::from(goal.1)) {
            return Some(d);
        }
        for (dc, dr) in [
            (-1, -1),
            (0, -1),
            (1, -1),
            (-1, 0),
            (1, 0),
            (-1, 1),
            (0, 1),
            (1, 1),
        ] {
            let (nc, nr) = (c + dc, r + dr);
            if nc < 0 || nr < 0 || nc >= w || nr >= h {
                continue;
            }
            let Some(cell) = grid.cells[idx(nc, nr)] else {
                continue;
            };
            let nd = d + step_cost(cell, dc != 0 && dr != 0);
            if nd < dist[idx(nc, nr)] {
                dist[idx(nc, nr)] = nd;
                heap.push(Reverse((nd, nc, nr)));
            }
        }
    }
    None
}

#[test]
fn astar_cost_is_optimal_on_small_grids() {
    let mut rng = SeededRng::seeded(3);
    let (mut reachable, mut unreachable) = (0, 0);
    for case in 0..400 {
        let (w, h) = (4 + (case % 9) as u32, 3 + (case % 7) as u32);
        let obstacle_rate = 0.1 + 0.3 * rng.next();
        let cells: Vec<Option<f64>> = (0..w * h)
            .map(|_| (rng.next() >= obstacle_rate).then(|| 1.0 + 1.5 * rng.next()))
            .collect();
        let grid = CostGrid {
            width: w,
            height: h,
            cells,
        };
        let pick = |rng: &mut SeededRng| {
            (
                (rng.next() * f64::from(w)) as u32 % w,
                (rng.next() * f64::from(h)) as u32 % h,
            )
        };
        let (start, goal) = (pick(&mut rng), pick(&mut rng));
        let best = dijkstra(&grid, start, goal);
        let found = astar_grid(&grid, start, goal);
        match (best, found) {
            (None, None) => unreachable += 1,
            (Some(best), Some((path, cost))) => {
                reachable += 1;
                assert_eq!(cost, best, "case {case}: A* {cost} vs Dijkstra {best}");
                assert_eq!(path.first(), Some(&start));
                assert_eq!(path.last(), Some(&goal));
                let mut recomputed = 0;
                for pair in path.windows(2) {
                    let (a, b) = (pair[0], pair[1]);
                    let (dc, dr) = (a.0.abs_diff(b.0), a.1.abs_diff(b.1));
                    assert!(
                        dc <= 1 && dr <= 1 && dc + dr > 0,
                        "case {case}: not 8-connected"
                    );
                    let cell = grid.cost(b.0, b.1).expect("path stays on free cells");
                    recomputed += step_cost(cell, dc == 1 && dr == 1);
                }
                assert_eq!(recomputed, cost, "case {case}");
            }
            (best, found) => panic!("case {case}: Dijkstra {best:?}, A* {found:?}"),
        }
    }
    assert!(
        reachable > 100 && unreachable > 10,
        "{reachable} / {unreachable}"
    );
}

#[test]
fn default_phantom_plan() {
    let phantom =
        Phantom::load(&fieldmaps::data_root().join("fieldmaps/rigs/paper/heart_phantom.toml"))
            .unwrap();
    let geom = fieldmaps::rigfile::Rig::load_paper()
        .unwrap()
        .camera
        .geometry;
    let mask = Mask::from_phantom(&phantom, &geom).unwrap();
    let config = PlannerConfig::default();
    let p = plan(
        &mask,
        &geom,
        &phantom.default_start(),
        &phantom.default_end(),
        &config,
    )
    .unwrap();
    let wp = &p.waypoints_m;
    assert_eq!(wp.len(), 10);
    eprintln!(
        "default plan: {} A* px, cost {:.1}, smoothed length {:.2} mm, waypoint polyline {:.2} mm",
        p.pixel_path.len(),
        p.cost,
        p.smoothed_length_m * 1e3,
        p.waypoint_length_m() * 1e3
    );
    for w in p.waypoints_mm() {
        eprintln!("  [{:.3}, {:.3}]", w[0], w[1]);
    }
    // Start and end have ≥ 5 mm clearance: they are kept (within a pixel).
    let px = geom.mm_per_px * 1e-3;
    assert!((wp[0] - phantom.default_start()).norm() < px);
    assert!((wp[9] - phantom.default_end()).norm() < px);
    // Evenly spaced along the smoothed path: chords no longer than arc/9.
    let step = p.smoothed_length_m / 9.0;
    for pair in wp.windows(2) {
        assert!((pair[1] - pair[0]).norm() <= step * (1.0 + 1e-9) + 1e-12);
    }
    // Every waypoint keeps (almost) the 5 mm clearance, measured on the mask's distance
    // transform (the phantom's min-of-primitives SDF underestimates clearance at junctions);
    // smoothing may cut a corner slightly.
    let dist = distance_transform(&mask);
    for w in wp {
        let (c, r) = geom.pixel_of(w).unwrap();
        let clearance_m = f64::from(dist[(r * geom.width_px + c) as usize]) * px;
        eprintln!("  clearance {:.3} mm", clearance_m * 1e3);
        assert!(clearance_m > config.clearance_m - 0.3e-3, "{w:?}");
    }
    // The smoothed path stays inside the canal everywhere.
    for s in &p.smoothed_px {
        assert!(phantom.contains(&geom.px_to_world(s[0], s[1])));
    }
}

fn two_rooms() -> (Mask, ImageGeometry) {
    // 200 × 100 px at 0.5 mm/px: two 40 mm squares separated by a 2 px wall... plus nothing else.
    let (w, h) = (200u32, 100u32);
    let mut data = vec![0u8; (w * h) as usize];
    for r in 10..90 {
        for c in 10..95 {
            data[(r * w + c) as usize] = 255;
        }
        for c in 105..190 {
            data[(r * w + c) as usize] = 255;
        }
    }
    (Mask::new(w, h, data).unwrap(), geometry_for(w, h, 0.5))
}

#[test]
fn clear_errors() {
    let (mask, geom) = two_rooms();
    let cfg = PlannerConfig::default();
    let left = geom.px_to_world(50.0, 50.0);
    let right = geom.px_to_world(150.0, 50.0);
    // Same room: fine.
    assert!(plan(&mask, &geom, &left, &geom.px_to_world(60.0, 30.0), &cfg).is_ok());
    let e = plan(&mask, &geom, &left, &right, &cfg).unwrap_err();
    assert!(matches!(e, PlanError::NotConnected { .. }), "{e}");
    eprintln!("{e}");
    let outside = Vector2::new(1.0, 0.0);
    let e = plan(&mask, &geom, &outside, &right, &cfg).unwrap_err();
    assert!(
        matches!(e, PlanError::OutsideImage { which: "start", .. }),
        "{e}"
    );
    let wall = geom.px_to_world(100.0, 50.0);
    let e = plan(&mask, &geom, &left, &wall, &cfg).unwrap_err();
    assert!(
        matches!(e, PlanError::OutsideCanal { which: "end", .. }),
        "{e}"
    );
    let huge = PlannerConfig {
        clearance_m: 0.05,
        ..PlannerConfig::default()
    };
    let e = plan(&mask, &geom, &left, &right, &huge).unwrap_err();
    assert!(matches!(e, PlanError::NoFeasibleCore { .. }), "{e}");
    let bad = PlannerConfig {
        w_clear: f64::NAN,
        ..PlannerConfig::default()
    };
    assert!(matches!(
        plan(&mask, &geom, &left, &right, &bad),
        Err(PlanError::Config(_))
    ));
    assert!(Mask::new(3, 3, vec![0; 8]).is_err());
    assert!(matches!(
        load_mask(std::path::Path::new("/nonexistent/mask.png")),
        Err(MaskLoadError::Unreadable(_))
    ));
}

#[test]
fn start_near_a_wall_is_projected_into_the_core() {
    let (mask, geom) = two_rooms();
    // 1 px from the left room's wall: outside the 5 mm (10 px) core.
    let near_wall = geom.px_to_world(11.0, 50.0);
    let p = plan(
        &mask,
        &geom,
        &near_wall,
        &geom.px_to_world(80.0, 50.0),
        &PlannerConfig::default(),
    )
    .unwrap();
    let (c, _) = p.start_px;
    assert!(c >= 19, "projected to {:?}", p.start_px);
}

#[test]
fn png_mask_roundtrip() {
    use opencv::core as cv;
    let (mask, _) = two_rooms();
    let mat =
        cv::Mat::new_rows_cols_with_data::<u8>(mask.height as i32, mask.width as i32, &mask.data)
            .unwrap();
    let path = std::env::temp_dir().join(format!("millinav-planner-{}.png", std::process::id()));
    assert!(opencv::imgcodecs::imwrite_def(path.to_str().unwrap(), &mat).unwrap());
    let loaded = load_mask(&path).unwrap();
    let _ = std::fs::remove_file(&path);
    assert_eq!(loaded, mask);
}

/// OpenCV's exact distance transform (`DIST_L2`, `DIST_MASK_PRECISE`), which the planning
/// library's own must reproduce.
fn opencv_distance_transform(mask: &Mask) -> Vec<f32> {
    use opencv::core as cv;
    use opencv::prelude::*;
    let binary: Vec<u8> = mask
        .data
        .iter()
        .map(|&v| if v != 0 { 255 } else { 0 })
        .collect();
    let src =
        cv::Mat::new_rows_cols_with_data::<u8>(mask.height as i32, mask.width as i32, &binary)
            .unwrap();
    let mut dist = cv::Mat::default();
    opencv::imgproc::distance_transform(
        &src,
        &mut dist,
        opencv::imgproc::DIST_L2,
        opencv::imgproc::DIST_MASK_PRECISE,
        cv::CV_32F,
    )
    .unwrap();
    dist.try_clone()
        .unwrap()
        .data_typed::<f32>()
        .unwrap()
        .to_vec()
}

#[test]
fn distance_transform_equals_opencvs() {
    let mut rng = SeededRng::seeded(11);
    for case in 0..40 {
        let w = 1 + (rng.next() * 90.0) as u32;
        let h = 1 + (rng.next() * 90.0) as u32;
        let walls = 0.002 + 0.3 * rng.next();
        let mut data: Vec<u8> = (0..w * h)
            .map(|_| if rng.next() < walls { 0 } else { 255 })
            .collect();
        data[0] = 0; // at least one wall pixel (without one OpenCV's value is a sentinel)
        let mask = Mask::new(w, h, data).unwrap();
        let ours = distance_transform(&mask);
        let theirs = opencv_distance_transform(&mask);
        let worst = ours
            .iter()
            .zip(&theirs)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert_eq!(
            ours, theirs,
            "case {case}: {w}x{h}, worst difference {worst}"
        );
    }
    // And on the committed rig's canal mask, where the planner runs.
    let rig = fieldmaps::rigfile::Rig::load(&rig_file("paper")).unwrap();
    let geom = *rig.phantom.mask.geometry();
    let mask = Mask::new(geom.width_px, geom.height_px, rig.phantom.mask.to_bytes()).unwrap();
    assert_eq!(distance_transform(&mask), opencv_distance_transform(&mask));
}

fn rig_file(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join(format!("../../fieldmaps/rigs/{name}.toml"))
}

#[test]
fn plans_on_a_second_rig_from_its_route() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_planner"))
        .args(["--clearance-mm", "3", "--rig"])
        .arg(rig_file("vessel8"))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Default start and goal: the rig's [phantom.route].
    assert!(
        stdout.contains("start (-42.00, -19.90) mm -> end (24.00, -24.00) mm"),
        "{stdout}"
    );
}

#[test]
fn rig_without_route_needs_start_and_end() {
    // vessel8 without its [phantom.route], its data paths made absolute so the copy loads.
    let rigs = rig_file("vessel8")
        .parent()
        .unwrap()
        .canonicalize()
        .unwrap();
    let text = std::fs::read_to_string(rig_file("vessel8"))
        .unwrap()
        .replace("\"vessel8/", &format!("\"{}/vessel8/", rigs.display()));
    let start = text.find("[phantom.route]").unwrap();
    let end = start + text[start..].find("[[phantom.flow]]").unwrap();
    let text = format!("{}{}", &text[..start], &text[end..]);
    let dir = std::env::temp_dir().join(format!("millinav-planner-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let rig = dir.join("noroute.toml");
    std::fs::write(&rig, text).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_planner"))
        .arg("--rig")
        .arg(&rig)
        .output()
        .unwrap();
    std::fs::remove_dir_all(&dir).ok();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains(&format!("{}: [phantom.route]", rig.display())),
        "{stderr}"
    );
}
