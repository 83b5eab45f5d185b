//! `vision-eval`: the vision service's localizers over a dataset split, side by side; with
//! `--robustness`, also under every family of real-camera image shift at three severities.
use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use indicatif::{ProgressBar, ProgressStyle};
use millinav_roi::dataset::Split;
use millinav_vision::classical::{CapsuleSize, ClassicalLocalizer};
use millinav_vision::unet::{find_onnxruntime, UnetLocalizer};
use millinav_vision_eval::eval::{
    evaluate_classical, evaluate_unet, robustness, robustness_table, table, Report,
};
use millinav_vision_eval::perturb::Family;

/// Prints precision, recall, IoU, detection rates, keypoint errors (mm) and per-crop latency of
/// the UNet and the classical localizer on a split made by `unet-dataset` (e.g.
/// tools/unet/testset).
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
    /// Rig file whose capsule the split shows, e.g. fieldmaps/rigs/paper.toml.
    #[arg(long)]
    rig: PathBuf,
    /// Also evaluate under lighting, colour cast, background texture, bubbles, glare, shadow,
    /// motion blur, noise, JPEG, scale ±10 % and partial occlusion, each at severities 1–3.
    #[arg(long)]
    robustness: bool,
    /// Seed of the shifts (--robustness).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Only the classical localizer (no ONNX Runtime needed).
    #[arg(long)]
    classical_only: bool,
    /// Also write the table (Markdown) to this file.
    #[arg(long)]
    out: Option<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let split =
        Split::load(&args.split).with_context(|| format!("loading {}", args.split.display()))?;
    let rig = fieldmaps::rigfile::Rig::load(&args.rig)?;
    let size = CapsuleSize::of(&rig.robot);
    let mm_per_px = split
        .labels
        .first()
        .map(|l| l.mm_per_px)
        .context("empty split")?;
    let mut unet = if args.classical_only {
        None
    } else {
        let runtime = find_onnxruntime(args.onnxruntime.as_deref())?;
        let mut unet = UnetLocalizer::load(&args.model, &runtime, size.length_m * 1e3, mm_per_px)?;
        // Warm-up so the first inference's allocations do not count as latency.
        for i in 0..split.len().min(5) {
            let _ = unet.infer(split.image(i));
        }
        Some(unet)
    };
    let expected = size.length_m * 1e3 / mm_per_px / millinav_roi::roi::DOWNSAMPLE as f64;
    let classical = ClassicalLocalizer::new(size, rig.appearance);
    let mut evaluate = |split: &Split| -> Vec<Report> {
        let mut reports = Vec::new();
        if let Some(unet) = unet.as_mut() {
            reports.push(evaluate_unet(unet, split, expected));
        }
        reports.push(evaluate_classical(&classical, split));
        reports
    };
    let text = if args.robustness {
        let bar = ProgressBar::new(1 + 3 * Family::ALL.len() as u64);
        bar.set_style(
            ProgressStyle::with_template("{msg:>20} [{bar:30}] {pos}/{len} shifts ({eta})")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        let rows = robustness(&split, args.seed, &mut evaluate, |family, s| {
            bar.set_message(format!("{family} {s}"));
            bar.inc(1);
        })?;
        bar.finish_and_clear();
        format!(
            "{} crops of {}, shift seed {}\n\n{}",
            split.len(),
            args.split.display(),
            args.seed,
            robustness_table(&rows)
        )
    } else {
        table(&evaluate(&split))
    };
    println!("{text}");
    if let Some(out) = &args.out {
        std::fs::write(out, &text).with_context(|| format!("writing {}", out.display()))?;
        eprintln!("wrote {}", out.display());
    }
    Ok(())
}
