//! `unet-import`: your own labelled camera frames (LabelMe JSON) → UNet training crops, cut
//! exactly as the vision service cuts them, in the split format `train.py` reads.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use fieldmaps::rigfile::Rig;
use indicatif::{ProgressBar, ProgressStyle};
use millinav_roi::dataset::Split;
use millinav_unet::labelme::{crop_frame, label_files, read_frame, CropPlan, LabelNames};

/// Imports LabelMe-labelled full frames (capsule polygon + tip and tail points) into train/ and
/// val/ splits of ROI crops with masks and keypoints. Frames must be the rig's top view (its
/// camera's resolution and mm/px). Format: tools/unet/LABELS.md.
#[derive(Parser)]
#[command(name = "unet-import", version)]
struct Args {
    /// A LabelMe .json file or a directory of them (images next to them, as `imagePath` says).
    #[arg(long)]
    labels: PathBuf,
    /// Output directory; gets train/ and val/.
    #[arg(long)]
    out: PathBuf,
    /// Rig file whose camera took the frames.
    #[arg(long)]
    rig: PathBuf,
    /// Every k-th frame goes to val/ (whole frames, so no crop of a val frame is trained on);
    /// 0: no val split.
    #[arg(long, default_value_t = 5)]
    val_every: usize,
    /// Crops around the capsule per frame (crop centre jittered like the tracker's offset).
    #[arg(long, default_value_t = 4)]
    crops_per_frame: usize,
    /// Crops without the capsule per frame.
    #[arg(long, default_value_t = 1)]
    negatives_per_frame: usize,
    /// Crop-centre jitter, px.
    #[arg(long, default_value_t = 40.0)]
    jitter_px: f64,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Label of the capsule polygon.
    #[arg(long, default_value = "capsule")]
    body_label: String,
    /// Label of the tip point (the cap end).
    #[arg(long, default_value = "tip")]
    tip_label: String,
    /// Label of the tail point (the magnet end).
    #[arg(long, default_value = "tail")]
    tail_label: String,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let rig = Rig::load(&args.rig)?;
    let names = LabelNames {
        body: args.body_label.clone(),
        tip: args.tip_label.clone(),
        tail: args.tail_label.clone(),
    };
    let plan = CropPlan {
        crops_per_frame: args.crops_per_frame,
        negatives_per_frame: args.negatives_per_frame,
        jitter_px: args.jitter_px,
        seed: args.seed,
    };
    let files = label_files(&args.labels)?;
    let bar = ProgressBar::new(files.len() as u64).with_style(
        ProgressStyle::with_template("[{bar:40}] {pos}/{len} frames {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let (mut train, mut val) = (Split::default(), Split::default());
    let (mut with_capsule, mut empty) = (0, 0);
    for (i, json) in files.iter().enumerate() {
        let frame = read_frame(json, &rig, &names)?;
        if frame.capsule.is_some() {
            with_capsule += 1;
        } else {
            empty += 1;
        }
        let to_val = args.val_every > 0 && (i + 1) % args.val_every == 0;
        let split = if to_val { &mut val } else { &mut train };
        crop_frame(
            &frame,
            rig.camera.geometry.mm_per_px,
            &plan,
            i as u64,
            split,
        )?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    for (name, split) in [("train", &train), ("val", &val)] {
        if split.is_empty() {
            continue;
        }
        let dir = args.out.join(name);
        split
            .save(&dir)
            .with_context(|| format!("writing {}", dir.display()))?;
        let positives = split.labels.iter().filter(|l| l.has_robot).count();
        println!(
            "{name}: {} crops ({positives} with the capsule) in {}",
            split.len(),
            dir.display()
        );
    }
    println!(
        "imported {} frames ({with_capsule} with a capsule, {empty} empty) from {}",
        files.len(),
        args.labels.display()
    );
    Ok(())
}
