//! The twin's camera: blur equivalence, lighting drift, ground truth, render cost.

use std::time::Instant;

use fieldmaps::mask::CanalMask;
use fieldmaps::phantom::ImageGeometry;
use fieldmaps::rigfile::Rig;
use millinav_plant::render::{
    blur_rgb, Camera, CameraConfig, CapsulePose, MASK_BODY, MASK_CAP, MASK_MAGNET,
};
use millinav_plant::rng_streams::run_rng;
use nalgebra::Vector2;

/// The paper rig's canal mask.
fn canal() -> CanalMask {
    Rig::load_paper().unwrap().phantom.mask
}

/// The paper rig's camera view.
fn view() -> ImageGeometry {
    Rig::load_paper().unwrap().camera.geometry
}

fn camera(config: CameraConfig) -> Camera {
    let mut rng = run_rng(7, 1);
    Camera::with_config(&canal(), view(), &mut rng, 3.0, config)
}

fn capsule(x_mm: f64, y_mm: f64, heading: f64) -> CapsulePose {
    let robot = Rig::load_paper().unwrap().robot;
    CapsulePose {
        position_m: Vector2::new(x_mm, y_mm) * 1e-3,
        heading_rad: heading,
        length_m: robot.length_m,
        diameter_m: robot.diameter_m,
    }
}

#[test]
fn region_blur_equals_whole_frame_blur() {
    for passes in [1, 2, 3] {
        let config = CameraConfig {
            blur_passes: passes,
            lighting_drift_amplitude: 0.05,
            ..CameraConfig::default()
        };
        let cam = camera(config);
        let (w, h) = (1020, 1020);
        for (pose, seq) in [
            (capsule(-16.0, 10.0, 0.7), 3),
            (capsule(-45.6, 45.6, 2.0), 4),
        ] {
            let t = 3.3;
            let fast = cam.render_sample(&pose, seq, t, &mut run_rng(1, seq)).rgb;
            // Reference: sharp background, capsule, blur of the whole frame, gain.
            let mut slow = cam.background(seq).to_vec();
            cam.draw_capsule(
                &mut slow,
                &pose.position_m,
                pose.heading_rad,
                pose.length_m,
                pose.diameter_m,
                &mut run_rng(1, seq),
            );
            blur_rgb(&mut slow, w, h, passes);
            let gain = (cam.lighting_gain(t) * 256.0).round() as u32;
            for b in slow.iter_mut() {
                *b = ((u32::from(*b) * gain + 128) >> 8).min(255) as u8;
            }
            let differing = fast.iter().zip(&slow).filter(|(a, b)| a != b).count();
            assert_eq!(differing, 0, "{passes} passes, pose {pose:?}");
        }
    }
}

#[test]
fn camera_new_is_unchanged_by_effects() {
    // `Camera::new` keeps the old behaviour: no blur, no drift.
    let mut rng = run_rng(7, 1);
    let plain = Camera::new(&canal(), view(), &mut rng, 3.0);
    let with = camera(CameraConfig::off());
    assert_eq!(plain.background(2), with.background(2));
    assert_eq!(plain.frame_background(2), plain.background(2));
    assert_eq!(plain.lighting_gain(12.0), 1.0);
}

#[test]
fn lighting_drifts_slowly_within_its_amplitude() {
    let cam = camera(CameraConfig::default());
    let a = CameraConfig::default().lighting_drift_amplitude;
    let gains: Vec<f64> = (0..6000)
        .map(|k| cam.lighting_gain(k as f64 * 0.01))
        .collect();
    let (lo, hi) = gains
        .iter()
        .fold((f64::MAX, f64::MIN), |(l, h), g| (l.min(*g), h.max(*g)));
    println!("lighting gain over 60 s: {lo:.3} .. {hi:.3}");
    assert!(lo >= 1.0 - a - 0.005 && hi <= 1.0 + a + 0.005);
    assert!(hi - lo > a * 0.5, "it does drift");
    // Slow: at most one quantisation step per frame.
    assert!(gains.windows(2).all(|w| (w[1] - w[0]).abs() <= 1.5 / 256.0));
}

#[test]
fn sample_has_mask_classes_and_keypoints() {
    let cam = camera(CameraConfig::default());
    let pose = capsule(-16.0, 10.0, 0.7);
    let sample = cam.render_sample(&pose, 0, 0.0, &mut run_rng(2, 0));
    let (w, h) = (1020usize, 1020usize);
    assert_eq!(sample.rgb.len(), w * h * 3);
    assert_eq!(sample.mask.len(), w * h);
    let count = |class: u8| sample.mask.iter().filter(|m| **m == class).count();
    let total = sample.mask.iter().filter(|m| **m != 0).count() as f64;
    let px_per_m = 1020.0 / 0.092;
    let r = pose.diameter_m / 2.0 * px_per_m;
    let area = std::f64::consts::PI * r * r + 2.0 * r * (pose.length_m * px_per_m - 2.0 * r);
    assert!(
        (total - area).abs() < 0.03 * area,
        "mask {total} px vs area {area:.0} px"
    );
    assert!(count(MASK_BODY) > 0 && count(MASK_CAP) > 0 && count(MASK_MAGNET) > 0);
    // Mask centroid ≈ the centroid keypoint; the cap lies toward the tip, the magnet toward the tail.
    let centroid = |pred: &dyn Fn(u8) -> bool| {
        let (mut sx, mut sy, mut n) = (0.0, 0.0, 0.0);
        for (i, m) in sample.mask.iter().enumerate() {
            if pred(*m) {
                sx += (i % w) as f64;
                sy += (i / w) as f64;
                n += 1.0;
            }
        }
        (sx / n, sy / n)
    };
    let k = sample.keypoints;
    let all = centroid(&|m| m != 0);
    assert!((all.0 - k.centroid_px.0).hypot(all.1 - k.centroid_px.1) < 1.0);
    let cap = centroid(&|m| m == MASK_CAP);
    let magnet = centroid(&|m| m == MASK_MAGNET);
    let dist = |a: (f64, f64), b: (f64, f64)| (a.0 - b.0).hypot(a.1 - b.1);
    assert!(dist(cap, k.tip_px) < dist(cap, k.tail_px));
    assert!(dist(magnet, k.tail_px) < dist(magnet, k.tip_px));
    // The dyed body is visibly blue in the image.
    let i = (k.centroid_px.1.round() as usize * w + k.centroid_px.0.round() as usize) * 3;
    assert!(sample.rgb[i + 2] > sample.rgb[i] + 60);
}

/// The plant's render path (background copy, then capsule, blur, lighting) run as the plant
/// runs it, frame after frame: each frame is fully rewritten. Its speed is printed for a look,
/// not asserted: timings belong to the bench.
#[test]
fn successive_frames_are_rewritten_by_the_render_path() {
    let cam = camera(CameraConfig {
        blur_passes: 2,
        ..CameraConfig::default()
    });
    let mut frame = vec![0u8; 1020 * 1020 * 3];
    let mut previous: Option<Vec<u8>> = None;
    let n = 50;
    let start = Instant::now();
    for seq in 0..n {
        let pose = capsule(-16.0 + seq as f64 * 0.2, 10.0, 0.1 * seq as f64);
        frame.copy_from_slice(cam.frame_background(seq));
        cam.finish_frame(
            &mut frame,
            &pose,
            seq,
            seq as f64 * 0.01,
            &mut run_rng(1, seq),
            None,
        );
        if let Some(prev) = &previous {
            let changed = frame.iter().zip(prev).filter(|(a, b)| a != b).count();
            // Fresh sensor noise on every pixel plus a capsule 0.2 mm further on: most bytes change.
            assert!(
                changed > frame.len() / 4,
                "frame {seq}: only {changed} of {} bytes changed",
                frame.len()
            );
        }
        previous = Some(frame.clone());
    }
    let per_frame_ms = start.elapsed().as_secs_f64() * 1e3 / n as f64;
    println!("render 1020x1020 (copy + capsule + blur + lighting): {per_frame_ms:.3} ms/frame");
}
