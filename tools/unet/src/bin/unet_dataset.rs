//! `unet-dataset`: exports UNet training data from the twin's camera: ROI crops exactly as the
//! vision service prepares them, with ground-truth masks and tip/centroid/tail keypoints, over
//! varied pose, lighting, noise, blur and tracking offset. Splits use different seeds.
//!
//! `--style` sets the generator: `twin` renders the twin's own look; `randomized` varies the
//! scene per camera and per crop (canal and wall colours, dye shade, rim shading, specular
//! stripe, capsule scale ±12 %, air bubbles) so a model cannot learn one palette (train.py adds
//! the camera's shifts on top); `heldout` is a setting used by no training split (a cool-lit
//! palette, darker dye, strong rim shading and a fixed highlight), for an honest test split.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use fieldmaps::phantom::ImageGeometry;
use fieldmaps::rig::RobotParams;
use fieldmaps::rigfile::Rig;
use indicatif::{ProgressBar, ProgressStyle};
#[cfg(feature = "labelme")]
use millinav_plant::render::blur_rgb;
use millinav_plant::render::{Camera, Palette};
use millinav_roi::dataset::{Label, Split};
use millinav_roi::roi::{extract_mask, extract_rgb, Crop, CROP_PX};
#[cfg(feature = "labelme")]
use millinav_unet::labelme::{write_frame, Capsule};
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
    /// Rig file: camera, phantom and capsule, e.g. fieldmaps/rigs/paper.toml.
    #[arg(long)]
    rig: PathBuf,
    /// Generator setting: the twin's look, domain-randomized scenes, or the held-out setting.
    #[arg(long, value_enum, default_value_t = Style::Twin)]
    style: Style,
    /// Instead of crop splits, write this many labelled full frames (PNG + LabelMe JSON, every
    /// 8th one an empty canal) into --out: a stand-in for frames of your own camera that
    /// `unet-import` reads (tools/unet/LABELS.md). Seed: --seed.
    #[arg(long, value_name = "N")]
    labelme_frames: Option<usize>,
    /// Colour of the capsule's dyed body, "R,G,B" (e.g. another lab's dye); default the style's.
    #[arg(long, value_name = "R,G,B", value_parser = parse_rgb)]
    dye_rgb: Option<[u8; 3]>,
}

fn parse_rgb(text: &str) -> Result<[u8; 3], String> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let values: Result<Vec<u8>, _> = parts.iter().map(|p| p.parse::<u8>()).collect();
    match values {
        Ok(v) if v.len() == 3 => Ok([v[0], v[1], v[2]]),
        _ => Err(format!("{text:?}: want three values 0-255 as R,G,B")),
    }
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Style {
    /// The twin's palette, as the plant renders it.
    Twin,
    /// Scene colours, shading, capsule scale and bubbles drawn at random.
    Randomized,
    /// One fixed setting that no training split uses.
    Heldout,
}

impl Style {
    /// Palette of a camera (the background colours are baked into it).
    fn camera_palette(self, rng: &mut ChaCha8Rng) -> Palette {
        let base = Palette::default();
        match self {
            Style::Twin => base,
            Style::Randomized => {
                let mut jitter = |rgb: [f64; 3], spread: f64| {
                    let brightness = rng.random_range(0.72..1.08);
                    rgb.map(|v| v * brightness + rng.random_range(-spread..spread))
                };
                Palette {
                    canal_rgb: jitter(base.canal_rgb, 22.0),
                    wall_rgb: jitter(base.wall_rgb, 30.0),
                    ..base
                }
            }
            Style::Heldout => Palette {
                canal_rgb: [204.0, 214.0, 226.0],
                wall_rgb: [172.0, 152.0, 170.0],
                body_rgb: [28, 78, 172],
                cap_rgb: [150, 186, 228],
                magnet_rgb: [48, 42, 40],
                rim_shading: 0.35,
                specular: 70.0,
                specular_offset: 0.4,
            },
        }
    }

    /// Per-crop capsule look (colours and shading) on top of the camera's palette.
    fn capsule_palette(self, camera: Palette, rng: &mut ChaCha8Rng) -> Palette {
        if self != Style::Randomized {
            return camera;
        }
        let base = Palette::default();
        let shade = |rgb: [u8; 3], scale: f64, spread: f64, rng: &mut ChaCha8Rng| {
            rgb.map(|v| {
                (f64::from(v) * scale + rng.random_range(-spread..=spread))
                    .round()
                    .clamp(0.0, 255.0) as u8
            })
        };
        let dye = rng.random_range(0.7..1.2);
        let specular = if rng.random_bool(0.5) {
            rng.random_range(20.0..110.0)
        } else {
            0.0
        };
        let cap_scale = rng.random_range(0.8..1.1);
        let magnet_lift = rng.random_range(0.0..30.0);
        Palette {
            body_rgb: shade(base.body_rgb, dye, 20.0, rng),
            cap_rgb: shade(base.cap_rgb, cap_scale, 20.0, rng),
            magnet_rgb: shade(base.magnet_rgb, 1.0, 0.0, rng).map(|v| v + magnet_lift as u8),
            rim_shading: rng.random_range(0.0..0.45),
            specular,
            specular_offset: rng.random_range(-0.6..0.6),
            ..camera
        }
    }

    /// Capsule size factor of a crop (a camera a little higher or lower than calibrated).
    fn scale(self, rng: &mut ChaCha8Rng) -> f64 {
        match self {
            Style::Twin => 1.0,
            Style::Randomized => rng.random_range(0.88..1.12),
            Style::Heldout => 0.95,
        }
    }

    /// Probability that a crop shows air bubbles.
    fn bubble_probability(self) -> f64 {
        match self {
            Style::Twin => 0.0,
            Style::Randomized => 0.4,
            Style::Heldout => 0.5,
        }
    }

    /// Range of the sensor noise σ of a camera.
    fn noise_range(self) -> std::ops::Range<f64> {
        match self {
            Style::Heldout => 3.0..10.0,
            _ => 1.0..8.0,
        }
    }
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let rig = Rig::load(&args.rig)?;
    if let Some(frames) = args.labelme_frames {
        std::fs::create_dir_all(&args.out)
            .with_context(|| format!("creating {}", args.out.display()))?;
        export_labelme(&rig, frames, &args)?;
        eprintln!("{frames} labelled frames in {}", args.out.display());
        return Ok(());
    }
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
            args.style,
            args.dye_rgb,
        )?;
        let dir = args.out.join(name);
        split
            .save(&dir)
            .with_context(|| format!("writing {}", dir.display()))?;
        eprintln!("{name}: {} samples in {}", split.len(), dir.display());
    }
    // What vision must know to crop another camera's frames at this model's scale.
    let model_length_px = rig.robot.length_m * 1e3
        / rig.camera.geometry.mm_per_px
        / millinav_roi::roi::DOWNSAMPLE as f64;
    eprintln!(
        "the capsule is {model_length_px:.2} model-input px long in these crops: a model \
         trained on them runs with [vision] model_capsule_length_px = {model_length_px:.2}"
    );
    Ok(())
}

/// Full frames with LabelMe labels, as a person would label them (the capsule's outline, tip and
/// tail points), in the style's look.
#[cfg(feature = "labelme")]
fn export_labelme(rig: &Rig, frames: usize, args: &Args) -> anyhow::Result<()> {
    let mut rng = ChaCha8Rng::seed_from_u64(args.seed);
    let geometry = rig.camera.geometry;
    let (width, height) = (geometry.width_px as usize, geometry.height_px as usize);
    let bar = ProgressBar::new(frames as u64).with_style(
        ProgressStyle::with_template("frames [{bar:40}] {pos}/{len} {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut scene = Scene::new(rig, args.style, args.dye_rgb, args.cameras, &mut rng, || ());
    let px_per_m = 1e3 / geometry.mm_per_px;
    for k in 0..frames {
        let cam = scene.camera(&mut rng);
        let mut frame = cam.background(k as u64).to_vec();
        let capsule = (k % 8 != 7).then(|| {
            let (robot, position, heading) = random_capsule(rig, args.style, &mut rng);
            cam.draw_capsule(
                &mut frame,
                &position,
                heading,
                robot.length_m,
                robot.diameter_m,
                &mut rng,
            );
            let kp = cam.keypoints(&position, heading, robot.length_m);
            let axis = (heading.cos(), -heading.sin());
            Capsule::clicked(kp.tip_px, kp.tail_px, axis, robot.radius_m() * px_per_m)
        });
        blur_rgb(&mut frame, width, height, 1);
        write_frame(
            &args.out,
            &format!("frame_{k:04}"),
            &frame,
            width,
            height,
            capsule.as_ref(),
        )?;
        bar.inc(1);
    }
    bar.finish();
    Ok(())
}

/// Without OpenCV (built with --no-default-features) there is no image writer.
#[cfg(not(feature = "labelme"))]
fn export_labelme(_rig: &Rig, _frames: usize, _args: &Args) -> anyhow::Result<()> {
    anyhow::bail!(
        "--labelme-frames: this unet-dataset was built without OpenCV (--no-default-features); \
         build it with the default features to write labelled frames"
    )
}

/// The cameras of one export (each with its background palette baked in) and the style that
/// restyles the capsule for every sample.
struct Scene {
    cameras: Vec<Camera>,
    palettes: Vec<Palette>,
    style: Style,
    dye_rgb: Option<[u8; 3]>,
}

impl Scene {
    /// `count` cameras of `style` (at least one); `made` is told each one.
    fn new(
        rig: &Rig,
        style: Style,
        dye_rgb: Option<[u8; 3]>,
        count: usize,
        rng: &mut ChaCha8Rng,
        mut made: impl FnMut(),
    ) -> Self {
        let cameras: Vec<Camera> = (0..count.max(1))
            .map(|_| {
                let noise = rng.random_range(style.noise_range());
                let palette = style.camera_palette(rng);
                let camera = Camera::with_palette(
                    &rig.phantom.mask,
                    rig.camera.geometry,
                    rng,
                    noise,
                    palette,
                );
                made();
                camera
            })
            .collect();
        let palettes = cameras.iter().map(|c| c.palette).collect();
        Self {
            cameras,
            palettes,
            style,
            dye_rgb,
        }
    }

    /// A camera for the next sample, its capsule in this sample's look.
    fn camera(&mut self, rng: &mut ChaCha8Rng) -> &Camera {
        let which = rng.random_range(0..self.cameras.len());
        let camera = &mut self.cameras[which];
        camera.palette = self.style.capsule_palette(self.palettes[which], rng);
        if let Some(dye) = self.dye_rgb {
            camera.palette.body_rgb = dye;
        }
        camera
    }
}

/// The capsule at the style's scale and a random pose in the canal: (size, position, heading).
fn random_capsule(
    rig: &Rig,
    style: Style,
    rng: &mut ChaCha8Rng,
) -> (RobotParams, Vector2<f64>, f64) {
    let mut robot = rig.robot;
    let scale = style.scale(rng);
    robot.length_m *= scale;
    robot.diameter_m *= scale;
    let (position, heading) = random_pose(rig, rng, &robot);
    (robot, position, heading)
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

/// Air bubbles in the fluid around the crop centre: a bright thin rim and a faintly lighter
/// inside. They sit on the canal floor beside the capsule, never over it (its mask stays true).
fn draw_bubbles(frame: &mut [u8], capsule: &[u8], width: usize, crop: &Crop, rng: &mut ChaCha8Rng) {
    for _ in 0..rng.random_range(1..5) {
        let radius = rng.random_range(4.0..16.0);
        let bc = crop.col0 as f64 + rng.random_range(0.0..CROP_PX as f64);
        let br = crop.row0 as f64 + rng.random_range(0.0..CROP_PX as f64);
        let (rim, inside) = (rng.random_range(50.0..120.0), rng.random_range(5.0..30.0));
        for row in crop.row0..crop.row0 + CROP_PX {
            for col in crop.col0..crop.col0 + CROP_PX {
                let d = ((col as f64 - bc).powi(2) + (row as f64 - br).powi(2)).sqrt() / radius;
                let lift = if (0.82..1.0).contains(&d) {
                    rim
                } else if d < 0.82 {
                    inside
                } else {
                    continue;
                };
                if capsule[row * width + col] > 0 {
                    continue;
                }
                for v in &mut frame[(row * width + col) * 3..][..3] {
                    *v = (f64::from(*v) + lift).round().clamp(0.0, 255.0) as u8;
                }
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
    style: Style,
    dye_rgb: Option<[u8; 3]>,
) -> anyhow::Result<Split> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let geometry = rig.camera.geometry;
    let (width, height) = (geometry.width_px as usize, geometry.height_px as usize);
    let bar = ProgressBar::new((cameras + count) as u64).with_style(
        ProgressStyle::with_template("{msg:>6} [{bar:40}] {pos}/{len} {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_message(name.to_owned());
    let mut scene = Scene::new(rig, style, dye_rgb, cameras, &mut rng, || bar.inc(1));
    let mut split = Split::default();
    let mut frame = vec![0u8; width * height * 3];
    let mut mask = vec![0u8; width * height];
    let (mut image_out, mut mask_out) = (Vec::new(), Vec::new());
    for _ in 0..count {
        let cam = scene.camera(&mut rng);
        let (robot, position, heading) = random_capsule(rig, style, &mut rng);
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
        mask.iter_mut().for_each(|m| *m = 0);
        if has_robot {
            capsule_mask(&geometry, &position, heading, &robot, &crop, &mut mask);
        }
        // Twin style draws nothing here, so its splits stay as before.
        if style.bubble_probability() > 0.0 && rng.random_bool(style.bubble_probability()) {
            draw_bubbles(&mut frame, &mask, width, &crop, &mut rng);
        }
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
