//! `vision-eval`: the vision service's localizers over a dataset split, side by side.
use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use millinav_roi::dataset::Split;
use millinav_vision::classical::{CapsuleSize, ClassicalLocalizer};
use millinav_vision::eval::{evaluate_classical, evaluate_unet, table};
use millinav_vision::unet::{find_onnxruntime, UnetLocalizer};

/// Prints precision, recall, IoU, keypoint errors (mm) and per-crop latency of the UNet and the
/// classical localizer on a split made by `unet-dataset` (e.g. tools/unet/testset).
#[derive(Parser)]
#[command(name = "vision-eval", version)]
struct Args {
    /// Split directory (images.u8, masks.u8, labels.csv).
    #[arg(long, default_value = "tools/unet/testset")]
    split: PathBuf,
    /// ONNX model.
    #[arg(long, default_value = millinav_vision::DEFAULT_MODEL)]
    model: PathBuf,
    /// libonnxruntime.so (default: ORT_DYLIB_PATH, then the project venv).
    #[arg(long)]
    onnxruntime: Option<PathBuf>,
    /// Rig file whose capsule the split shows (default: the paper's, fieldmaps/rigs/paper.toml).
    #[arg(long)]
    rig: Option<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let split =
        Split::load(&args.split).with_context(|| format!("loading {}", args.split.display()))?;
    let rig = fieldmaps::rigfile::Rig::load_or_paper(args.rig.as_deref())?;
    let size = CapsuleSize::of(&rig.robot);
    let mm_per_px = split
        .labels
        .first()
        .map(|l| l.mm_per_px)
        .context("empty split")?;
    let runtime = find_onnxruntime(args.onnxruntime.as_deref())?;
    let mut unet = UnetLocalizer::load(&args.model, &runtime, size.length_m * 1e3, mm_per_px)?;
    let expected = size.length_m * 1e3 / mm_per_px / millinav_roi::roi::DOWNSAMPLE as f64;
    // Warm-up so the first inference's allocations do not count as latency.
    for i in 0..split.len().min(5) {
        let _ = unet.infer(split.image(i));
    }
    let reports = [
        evaluate_unet(&mut unet, &split, expected),
        evaluate_classical(&ClassicalLocalizer::new(size, rig.appearance), &split),
    ];
    println!("{}", table(&reports));
    Ok(())
}
