//! `planner`: the paper's A* pipeline on the canal mask → a trajectory file.
//!
//! planner [--rig fieldmaps/rigs/paper.toml] [--mask mask.png] [--start-mm X,Y] [--end-mm X,Y]
//!         [-o trajectory.toml] [--scenario-template scenarios/default.toml] [--speed-mm-s 0.5]
//!
//! The canal mask, its geometry and the default start and goal come from the rig file.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use fieldmaps::rigfile::Rig;
use millinav_planner::load_mask;
use millinav_planner::template::scenario_from_template;
use millinav_planning::{geometry_for, plan, trajectory_toml, Mask, PlannerConfig};
use nalgebra::Vector2;

#[derive(Parser, Debug)]
#[command(about = "A* path planner (paper Sec. II-C): canal mask -> trajectory waypoints")]
struct Args {
    /// Rig file: canal mask, its geometry, default start and goal (`[phantom.route]`), e.g.
    /// fieldmaps/rigs/paper.toml.
    #[arg(long)]
    rig: PathBuf,
    /// Canal mask image (white = canal) instead of the rig's. Same size as the rig's mask: the
    /// rig's geometry; otherwise centred on the origin at --mm-per-px.
    #[arg(long)]
    mask: Option<PathBuf>,
    /// mm per pixel of --mask (default: the rig's mask scale); the image is then centred on the
    /// origin.
    #[arg(long, requires = "mask")]
    mm_per_px: Option<f64>,
    /// Start point "x,y" in mm (default: the rig's `[phantom.route] start_mm`).
    #[arg(long, value_parser = parse_point, allow_hyphen_values = true)]
    start_mm: Option<[f64; 2]>,
    /// End point "x,y" in mm (default: the rig's `[phantom.route] end_mm`).
    #[arg(long, value_parser = parse_point, allow_hyphen_values = true)]
    end_mm: Option<[f64; 2]>,
    /// Minimum wall clearance, mm.
    #[arg(long, default_value_t = 5.0)]
    clearance_mm: f64,
    /// Centerline bias weight.
    #[arg(long, default_value_t = 0.5)]
    w_clear: f64,
    /// Moving-average window.
    #[arg(long, default_value_t = 7)]
    window: usize,
    /// Number of output waypoints.
    #[arg(long, default_value_t = 10)]
    waypoints: usize,
    /// Reference speed to write into the trajectory (omitted if not given).
    #[arg(long)]
    speed_mm_s: Option<f64>,
    /// Write a full scenario: this scenario file with its trajectory replaced, its `[run] rig`
    /// the --rig, its duration lengthened where the new path needs it, and its relative flow map
    /// re-based to where the scenario is written.
    #[arg(long)]
    scenario_template: Option<PathBuf>,
    /// Also write a Rerun recording (.rrd) of the plan drawn over the top-view image: the canal
    /// mask, or `--image` (e.g. a camera frame) when given.
    #[arg(long)]
    rrd: Option<std::path::PathBuf>,
    /// Background image for `--rrd` (PNG/JPEG of the same size as the mask).
    #[arg(long)]
    image: Option<std::path::PathBuf>,
    /// Output file (default: stdout).
    #[arg(short, long)]
    output: Option<PathBuf>,
}

fn parse_point(s: &str) -> Result<[f64; 2], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [x, y] = parts.as_slice() else {
        return Err(format!("expected \"x,y\" in mm, got {s:?}"));
    };
    let x: f64 = x.parse().map_err(|e| format!("x: {e}"))?;
    let y: f64 = y.parse().map_err(|e| format!("y: {e}"))?;
    if !(x.is_finite() && y.is_finite()) {
        return Err("coordinates must be finite".into());
    }
    Ok([x, y])
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .init();
    let args = Args::parse();
    let rig = Rig::load(&args.rig)?;
    let rig_geom = *rig.phantom.mask.geometry();
    let (mask, geom) = match &args.mask {
        None => {
            let data = rig
                .phantom
                .mask
                .canal_flags()
                .iter()
                .map(|&c| if c { 255 } else { 0 })
                .collect();
            (
                Mask::new(rig_geom.width_px, rig_geom.height_px, data)?,
                rig_geom,
            )
        }
        Some(path) => {
            let mask = load_mask(path)?;
            let same_size = mask.width == rig_geom.width_px && mask.height == rig_geom.height_px;
            let geom = match args.mm_per_px {
                None if same_size => rig_geom,
                mpp => geometry_for(mask.width, mask.height, mpp.unwrap_or(rig_geom.mm_per_px)),
            };
            (mask, geom)
        }
    };
    let to_m = |p: [f64; 2]| Vector2::new(p[0], p[1]) * 1e-3;
    let (start, end) = match (args.start_mm.map(to_m), args.end_mm.map(to_m), rig.phantom.route) {
        (Some(s), Some(e), _) => (s, e),
        (s, e, Some(route)) => (s.unwrap_or(route.start_m), e.unwrap_or(route.end_m)),
        (_, _, None) => anyhow::bail!(
            "{}: [phantom.route]: the rig gives no default start and goal; add one or give --start-mm and --end-mm",
            args.rig.display()
        ),
    };
    let config = PlannerConfig {
        clearance_m: args.clearance_mm * 1e-3,
        w_clear: args.w_clear,
        smoothing_window: args.window,
        waypoint_count: args.waypoints,
    };
    let plan = plan(&mask, &geom, &start, &end, &config)?;
    tracing::info!(
        start_px = ?plan.start_px,
        end_px = ?plan.end_px,
        astar_pixels = plan.pixel_path.len(),
        astar_cost = plan.cost,
        smoothed_length_mm = plan.smoothed_length_m * 1e3,
        waypoint_length_mm = plan.waypoint_length_m() * 1e3,
        "planned"
    );
    if let Some(path) = &args.rrd {
        log_plan(path, args.image.as_deref(), &mask, &plan)?;
        tracing::info!(recording = %path.display(), "plan written to Rerun");
    }
    let text = match &args.scenario_template {
        Some(path) => {
            let (text, notes) = scenario_from_template(
                path,
                &args.rig,
                &plan,
                args.speed_mm_s,
                args.output.as_deref(),
            )?;
            for note in notes {
                tracing::warn!("{note}");
            }
            text
        }
        None => format!(
            "# millinav-planner: A* on the canal mask, {:.1} mm clearance, w_clear {}, window {},\n\
             # start ({:.2}, {:.2}) mm -> end ({:.2}, {:.2}) mm, path length {:.2} mm\n{}",
            config.clearance_m * 1e3,
            config.w_clear,
            config.smoothing_window,
            start.x * 1e3,
            start.y * 1e3,
            end.x * 1e3,
            end.y * 1e3,
            plan.waypoint_length_m() * 1e3,
            trajectory_toml(&plan, args.speed_mm_s)
        ),
    };
    match &args.output {
        Some(path) => {
            std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?
        }
        None => print!("{text}"),
    }
    Ok(())
}

/// Writes the plan over the top-view image to a Rerun recording (pixel coordinates).
fn log_plan(
    path: &std::path::Path,
    image: Option<&std::path::Path>,
    mask: &Mask,
    plan: &millinav_planning::Plan,
) -> anyhow::Result<()> {
    use opencv::prelude::*;
    let rec = rerun::RecordingStreamBuilder::new("millinav").save(path)?;
    let (w, h) = (mask.width as usize, mask.height as usize);
    let rgb: Vec<u8> = match image {
        Some(file) => {
            let bgr = opencv::imgcodecs::imread(file, opencv::imgcodecs::IMREAD_COLOR)?;
            if bgr.empty() || bgr.cols() as usize != w || bgr.rows() as usize != h {
                anyhow::bail!("{}: unreadable or not {w}x{h}", file.display());
            }
            let mut rgb = opencv::core::Mat::default();
            opencv::imgproc::cvt_color_def(&bgr, &mut rgb, opencv::imgproc::COLOR_BGR2RGB)?;
            rgb.data_bytes()?.to_vec()
        }
        None => (0..w * h)
            .flat_map(|i| {
                let v = if mask.is_canal((i % w) as u32, (i / w) as u32) {
                    230
                } else {
                    90
                };
                [v, v, v]
            })
            .collect(),
    };
    rec.log_static(
        "camera/image",
        &rerun::Image::from_rgb24(rgb, [w as u32, h as u32]),
    )?;
    let astar: Vec<[f32; 2]> = plan
        .pixel_path
        .iter()
        .map(|(c, r)| [*c as f32, *r as f32])
        .collect();
    rec.log_static("camera/plan/astar", &rerun::LineStrips2D::new([astar]))?;
    let smooth: Vec<[f32; 2]> = plan
        .smoothed_px
        .iter()
        .map(|p| [p[0] as f32, p[1] as f32])
        .collect();
    rec.log_static("camera/plan/smoothed", &rerun::LineStrips2D::new([smooth]))?;
    let ends = [
        [plan.start_px.0 as f32, plan.start_px.1 as f32],
        [plan.end_px.0 as f32, plan.end_px.1 as f32],
    ];
    rec.log_static(
        "camera/plan/start_end",
        &rerun::Points2D::new(ends)
            .with_labels(["start", "end"])
            .with_radii([6.0]),
    )?;
    rec.flush_blocking()?;
    Ok(())
}
