//! `vision-calibrate`: one-click colour calibration of the classical localizer on a reference
//! frame. Give a frame of your camera with the capsule in view and the pixel where you see it;
//! it measures the dye's and the magnet's colours there, checks that the ranges find the capsule,
//! and prints the rig file's `[robot.appearance]` table.
use std::path::PathBuf;

use anyhow::{bail, Context};
use clap::Parser;
use millinav_vision::classical::{calibrate_appearance, CapsuleSize};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual};
use opencv::{imgcodecs, imgproc};

#[derive(Parser)]
#[command(name = "vision-calibrate", version)]
struct Args {
    /// Reference frame (PNG or any image OpenCV reads), at the rig camera's size.
    #[arg(long)]
    frame: PathBuf,
    /// Pixel (column row) on the capsule, e.g. read off an image viewer.
    #[arg(long, num_args = 2, required = true, value_names = ["COL", "ROW"])]
    at_px: Vec<i32>,
    /// Rig file (capsule size, camera scale), e.g. fieldmaps/rigs/paper.toml.
    #[arg(long)]
    rig: PathBuf,
    /// Radius of the disc sampled around the click (px); default: 0.6 capsule lengths.
    #[arg(long)]
    radius_px: Option<i32>,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let rig = fieldmaps::rigfile::Rig::load(&args.rig)?;
    let path = args.frame.to_string_lossy().into_owned();
    let bgr = imgcodecs::imread(&path, imgcodecs::IMREAD_COLOR)
        .with_context(|| format!("reading {path}"))?;
    if bgr.empty() {
        bail!("{path}: not an image OpenCV can read");
    }
    let mut rgb = Mat::default();
    imgproc::cvt_color_def(&bgr, &mut rgb, imgproc::COLOR_BGR2RGB)?;
    let (width, height) = (rgb.cols(), rgb.rows());
    let geometry = rig.camera.geometry;
    if (width as u32, height as u32) != (geometry.width_px, geometry.height_px) {
        bail!(
            "{path}: {width}x{height} px, but rig {} has a {}x{} camera",
            rig.path.display(),
            geometry.width_px,
            geometry.height_px
        );
    }
    let size = CapsuleSize::of(&rig.robot);
    let radius = args
        .radius_px
        .unwrap_or((0.6 * size.length_m * 1e3 / geometry.mm_per_px).round() as i32);
    let bytes = rgb.data_bytes()?;
    let appearance = calibrate_appearance(
        bytes,
        width,
        height,
        (args.at_px[0], args.at_px[1]),
        radius,
        size,
        geometry.mm_per_px,
    )
    .with_context(|| format!("{path}: calibrating at {:?}", args.at_px))?;
    println!(
        "# vision-calibrate --frame {path} --at-px {} {}",
        args.at_px[0], args.at_px[1]
    );
    println!("[robot.appearance]");
    let list = |v: [f64; 3]| format!("[{:.0}, {:.0}, {:.0}]", v[0], v[1], v[2]);
    println!("body_hsv_min = {}", list(appearance.body_hsv_min));
    println!("body_hsv_max = {}", list(appearance.body_hsv_max));
    println!("magnet_value_max = {:.0}", appearance.magnet_value_max);
    Ok(())
}
