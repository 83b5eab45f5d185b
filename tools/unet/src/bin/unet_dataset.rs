//! `unet-dataset`: exports UNet training data from the twin's camera: ROI crops exactly as the
//! vision service prepares them, with ground-truth masks and tip/centroid/tail keypoints, over
//! varied pose, lighting, noise, blur and tracking offset. Splits use different seeds.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use fieldmaps::phantom::ImageGeometry;
use fieldmaps::rig::RobotParams;
use fieldmaps::rigfile::Rig;
use indicatif::{ProgressBar, ProgressStyle};
use millinav_plant::render::Camera;
use millinav_roi::dataset::{Label, Split};
use millinav_roi::roi::{extract_mask, extract_rgb, Crop, CROP_PX};
use nalgebra::Vector2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Exports train/val/test splits of ROI crops with masks and keypoints.
#[derive(Parser)]
#[command(name = "unet-dataset", version)]
struct Args {
    /// Output directory; gets train/, val/ and test/ subdirectories.
    #[arg(long)]
    out: PathBuf,
    #[arg(long, default_value_t = 2400)]
    train: usize,
    #[arg(long, default_value_t = 400)]
    val: usize,
    #[arg(long, default_value_t = 400)]
    test: usize,
    /// Base seed; the splits use seed, seed+1 and seed+2.
    #[arg(long, default_value_t = 2025)]
    seed: u64,
    /// Cameras (background textures and noise levels) per split.
    #[arg(long, default_value_t = 6)]
    cameras: usize,
    /// Rig file: camera, phantom and capsule (default: the paper's, fieldmaps/rigs/paper.toml).
    #[arg(long)]
    rig: Option<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let rig = Rig::load_or_paper(args.rig.as_deref())?;
    for (offset, (name, count)) in [
        ("train", args.train),
        ("val", args.val),
        ("test", args.test),
    ]
    .into_iter()
    .enumerate()
    {
        if count == 0 {
            continue;
        }
        let split = export_split(
            &rig,
            count,
            args.seed + offset as u64,
            args.cameras.max(1),
            name,
        )?;
        let dir = args.out.join(name);
        split
            .save(&dir)
            .with_context(|| format!("writing {}", dir.display()))?;
        eprintln!("{name}: {} samples in {}", split.len(), dir.display());
    }
    Ok(())
}

/// A random pose with the whole capsule inside the canal.
fn random_pose(rig: &Rig, rng: &mut ChaCha8Rng, robot: &RobotParams) -> (Vector2<f64>, f64) {
    // Anywhere in the camera's view (the wall test below keeps the capsule in the canal).
    let g = &rig.camera.geometry;
    let top_left = g.px_to_world(0.0, 0.0);
    let bottom_right = g.px_to_world(f64::from(g.width_px - 1), f64::from(g.height_px - 1));
    loop {
        let p = Vector2::new(
            rng.random_range(top_left.x..bottom_right.x),
            rng.random_range(bottom_right.y..top_left.y),
        );
        let heading: f64 = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let axis = Vector2::new(heading.cos(), heading.sin());
        let half = robot.length_m / 2.0 - robot.radius_m();
        let margin = -robot.radius_m();
        if [p - axis * half, p, p + axis * half]
            .iter()
            .all(|q| rig.phantom.walls.signed_distance(q) < margin)
        {
            return (p, heading);
        }
    }
}

/// Ground-truth mask of the capsule in the frame (1 where the pixel centre is inside).
fn capsule_mask(
    geometry: &ImageGeometry,
    position: &Vector2<f64>,
    heading: f64,
    robot: &RobotParams,
    crop: &Crop,
    mask: &mut [u8],
) {
    let width = geometry.width_px as usize;
    let px_per_m = 1e3 / geometry.mm_per_px;
    let (cx, cy) = geometry.world_to_px(position);
    let (ax, ay) = (heading.cos(), -heading.sin());
    let radius = robot.radius_m() * px_per_m;
    let core_half = (robot.length_m / 2.0 - robot.radius_m()) * px_per_m;
    for row in crop.row0..crop.row0 + CROP_PX {
        for col in crop.col0..crop.col0 + CROP_PX {
            let (dx, dy) = (col as f64 - cx, row as f64 - cy);
            let along = dx * ax + dy * ay;
            let across = -dx * ay + dy * ax;
            let clamped = along.clamp(-core_half, core_half);
            let inside = (along - clamped).powi(2) + across.powi(2) <= radius * radius;
            mask[row * width + col] = u8::from(inside);
        }
    }
}

/// Separable [w, 1−2w, w] blur of the crop region, `passes` times (camera defocus).
fn blur_region(frame: &mut [u8], width: usize, height: usize, crop: &Crop, w: f32, passes: usize) {
    let (c0, r0) = (crop.col0.saturating_sub(2), crop.row0.saturating_sub(2));
    let c1 = (crop.col0 + CROP_PX + 2).min(width);
    let r1 = (crop.row0 + CROP_PX + 2).min(height);
    let (rw, rh) = (c1 - c0, r1 - r0);
    let mut buf: Vec<f32> = Vec::with_capacity(rw * rh * 3);
    for r in r0..r1 {
        for c in c0..c1 {
            for ch in 0..3 {
                buf.push(frame[(r * width + c) * 3 + ch] as f32);
            }
        }
    }
    let mut tmp = buf.clone();
    for _ in 0..passes {
        for r in 0..rh {
            for c in 1..rw - 1 {
                for ch in 0..3 {
                    let i = (r * rw + c) * 3 + ch;
                    tmp[i] = w * buf[i - 3] + (1.0 - 2.0 * w) * buf[i] + w * buf[i + 3];
                }
            }
        }
        for r in 1..rh - 1 {
            for c in 0..rw {
                for ch in 0..3 {
                    let i = (r * rw + c) * 3 + ch;
                    buf[i] = w * tmp[i - rw * 3] + (1.0 - 2.0 * w) * tmp[i] + w * tmp[i + rw * 3];
                }
            }
        }
    }
    for r in 0..rh {
        for c in 0..rw {
            for ch in 0..3 {
                frame[((r0 + r) * width + c0 + c) * 3 + ch] =
                    buf[(r * rw + c) * 3 + ch].round().clamp(0.0, 255.0) as u8;
            }
        }
    }
}

fn export_split(
    rig: &Rig,
    count: usize,
    seed: u64,
    cameras: usize,
    name: &str,
) -> anyhow::Result<Split> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let geometry = rig.camera.geometry;
    let (width, height) = (geometry.width_px as usize, geometry.height_px as usize);
    let robot = rig.robot;
    let bar = ProgressBar::new((cameras + count) as u64).with_style(
        ProgressStyle::with_template("{msg:>6} [{bar:40}] {pos}/{len} {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_message(name.to_owned());
    let cams: Vec<Camera> = (0..cameras)
        .map(|_| {
            let noise = rng.random_range(1.0..8.0);
            let cam = Camera::new(&rig.phantom.mask, geometry, &mut rng, noise);
            bar.inc(1);
            cam
        })
        .collect();
    let mut split = Split::default();
    let mut frame = vec![0u8; width * height * 3];
    let mut mask = vec![0u8; width * height];
    let (mut image_out, mut mask_out) = (Vec::new(), Vec::new());
    for _ in 0..count {
        let cam = &cams[rng.random_range(0..cams.len())];
        let (position, heading) = random_pose(rig, &mut rng, &robot);
        frame.copy_from_slice(cam.background(rng.random_range(0..4)));
        cam.draw_capsule(
            &mut frame,
            &position,
            heading,
            robot.length_m,
            robot.diameter_m,
            &mut rng,
        );
        let keypoints = cam.keypoints(&position, heading, robot.length_m);
        // 8 % of the crops look at empty canal: the model must say "no robot".
        let has_robot = rng.random_range(0.0..1.0) > 0.08;
        let (centre_col, centre_row) = if has_robot {
            let jitter = 40.0;
            (
                keypoints.centroid_px.0 + rng.random_range(-jitter..jitter),
                keypoints.centroid_px.1 + rng.random_range(-jitter..jitter),
            )
        } else {
            let (elsewhere, _) = random_pose(rig, &mut rng, &robot);
            if (elsewhere - position).norm() < 0.02 {
                continue;
            }
            geometry.world_to_px(&elsewhere)
        };
        let crop = Crop::around(centre_col, centre_row, width, height).context("crop")?;
        if rng.random_range(0.0..1.0) < 0.6 {
            let passes = rng.random_range(1..3);
            blur_region(
                &mut frame,
                width,
                height,
                &crop,
                rng.random_range(0.05..0.25),
                passes,
            );
        }
        mask.iter_mut().for_each(|m| *m = 0);
        if has_robot {
            capsule_mask(&geometry, &position, heading, &robot, &crop, &mut mask);
        }
        extract_rgb(&frame, width, &crop, &mut image_out);
        extract_mask(&mask, width, &crop, &mut mask_out);
        // Lighting drift: a global gain and offset on what the camera sees.
        let gain = rng.random_range(0.8..1.2);
        let offset = rng.random_range(-15.0..15.0);
        image_out
            .iter_mut()
            .for_each(|v| *v = (*v as f64 * gain + offset).round().clamp(0.0, 255.0) as u8);
        let to_input = |p: (f64, f64)| crop.frame_to_input(p.0, p.1);
        split.push(
            &image_out,
            &mask_out,
            Label {
                has_robot,
                tip: to_input(keypoints.tip_px),
                centroid: to_input(keypoints.centroid_px),
                tail: to_input(keypoints.tail_px),
                crop_col0: crop.col0,
                crop_row0: crop.row0,
                mm_per_px: geometry.mm_per_px,
            },
        );
        bar.inc(1);
    }
    bar.finish();
    Ok(split)
}
