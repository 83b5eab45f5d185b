//! `unet-import` on a small labelled set made here: frames from the twin's renderer with another
//! setting than the training data (other backgrounds, more noise), labelled as a person would in
//! LabelMe (a polygon around the capsule, tip and tail points), one frame without a capsule.
//! The crops must carry the same keypoints and (to the polygon's resolution) the same mask as the
//! renderer's own truth; bad label files must be refused naming the file and the shape.
#![cfg(feature = "labelme")] // unet-import reads the frames with OpenCV
use std::path::{Path, PathBuf};
use std::process::Command;

use fieldmaps::rigfile::Rig;
use millinav_plant::render::Camera;
use millinav_roi::dataset::Split;
use millinav_roi::roi::{Crop, INPUT_PX};
use millinav_unet::labelme::{write_frame, Capsule};
use nalgebra::Vector2;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("millinav-labelme-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Poses in the paper phantom's canal (right atrium, ventricle, outflow), heading rad.
const POSES: [(f64, f64, f64); 5] = [
    (-0.018, 0.012, 0.3),
    (-0.012, 0.006, -1.2),
    (0.002, -0.012, 2.5),
    (0.008, 0.012, 1.4),
    (-0.020, 0.016, -2.9),
];

struct Truth {
    tip: (f64, f64),
    tail: (f64, f64),
    centre: (f64, f64),
    axis: (f64, f64),
    radius_px: f64,
    core_half_px: f64,
}

impl Truth {
    fn inside(&self, col: f64, row: f64) -> bool {
        let (dx, dy) = (col - self.centre.0, row - self.centre.1);
        let along = dx * self.axis.0 + dy * self.axis.1;
        let across = -dx * self.axis.1 + dy * self.axis.0;
        let c = along.clamp(-self.core_half_px, self.core_half_px);
        (along - c).powi(2) + across.powi(2) <= self.radius_px.powi(2)
    }
}

/// Renders the labelled set into `dir`: one PNG + LabelMe JSON per frame; the last frame empty.
fn make_set(rig: &Rig, dir: &Path) -> Vec<Option<Truth>> {
    let g = rig.camera.geometry;
    let mut rng = ChaCha8Rng::seed_from_u64(777);
    // Another renderer setting than training's: more sensor noise, other backgrounds.
    let cam = Camera::new(&rig.phantom.mask, g, &mut rng, 10.0);
    let (w, h) = (g.width_px as usize, g.height_px as usize);
    let mut truths = Vec::new();
    for (k, pose) in POSES.iter().map(Some).chain([None]).enumerate() {
        let mut rgb = cam.background(k as u64).to_vec();
        let truth = pose.map(|&(x, y, heading)| {
            let p = Vector2::new(x, y);
            cam.draw_capsule(
                &mut rgb,
                &p,
                heading,
                rig.robot.length_m,
                rig.robot.diameter_m,
                &mut rng,
            );
            let kp = cam.keypoints(&p, heading, rig.robot.length_m);
            let px_per_m = 1e3 / g.mm_per_px;
            Truth {
                tip: kp.tip_px,
                tail: kp.tail_px,
                centre: kp.centroid_px,
                axis: (heading.cos(), -heading.sin()),
                radius_px: rig.robot.radius_m() * px_per_m,
                core_half_px: (rig.robot.length_m / 2.0 - rig.robot.radius_m()) * px_per_m,
            }
        });
        let clicked = truth
            .as_ref()
            .map(|t| Capsule::clicked(t.tip, t.tail, t.axis, t.radius_px));
        write_frame(dir, &format!("frame_{k:03}"), &rgb, w, h, clicked.as_ref()).unwrap();
        truths.push(truth);
    }
    truths
}

fn unet_import(args: &[&std::ffi::OsStr]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_unet-import"))
        .arg("--rig")
        .arg(fieldmaps::rigfile::paper_rig_path())
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ),
    )
}

#[test]
fn labelled_frames_become_crops_with_the_renderers_truth() {
    let rig = Rig::load_paper().unwrap();
    let dir = temp_dir("good");
    let truths = make_set(&rig, &dir);
    let out = dir.join("split");
    let (ok, text) = unet_import(&[
        "--labels".as_ref(),
        dir.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--val-every".as_ref(),
        "3".as_ref(),
    ]);
    assert!(ok, "{text}");
    assert!(
        text.contains("imported 6 frames (5 with a capsule, 1 empty)"),
        "{text}"
    );
    let train = Split::load(&out.join("train")).unwrap();
    let val = Split::load(&out.join("val")).unwrap();
    // Frames 3 and 6 (1-based) are val: 1 capsule frame + the empty one.
    assert_eq!(val.len(), 4 + 1 + 1, "{text}");
    assert_eq!(train.len(), 4 * 4 + 4, "{text}");
    let frames_of = |split: &Split, ks: &[usize]| -> Vec<usize> {
        ks.iter()
            .flat_map(|&k| std::iter::repeat_n(k, 5))
            .take(split.len())
            .collect()
    };
    for (split, ks) in [
        (&train, frames_of(&train, &[0, 1, 3, 4])),
        (&val, vec![2, 2, 2, 2, 2, 5]),
    ] {
        for (i, &k) in ks.iter().enumerate() {
            let label = &split.labels[i];
            let mask = split.mask(i);
            let Some(t) = truths[k].as_ref().filter(|_| label.has_robot) else {
                assert!(
                    mask.iter().all(|&m| m == 0),
                    "a negative crop with capsule pixels"
                );
                continue;
            };
            let crop = Crop {
                col0: label.crop_col0,
                row0: label.crop_row0,
            };
            // labels.csv keeps 4 decimals of an input pixel.
            let (tx, ty) = crop.frame_to_input(t.tip.0, t.tip.1);
            assert!(
                (label.tip.0 - tx).abs() < 1e-3 && (label.tip.1 - ty).abs() < 1e-3,
                "frame {k} crop {i}: {:?} vs {:?}",
                label.tip,
                (tx, ty)
            );
            let (cx, cy) = crop.frame_to_input(t.centre.0, t.centre.1);
            assert!((label.centroid.0 - cx).abs() < 1e-3 && (label.centroid.1 - cy).abs() < 1e-3);
            // Mask against the renderer's analytic capsule, at the model's resolution.
            let (mut both, mut either) = (0, 0);
            for r in 0..INPUT_PX {
                for c in 0..INPUT_PX {
                    let (col, row) = crop.input_to_frame(c as f64, r as f64);
                    let truth = t.inside(col, row);
                    let got = mask[r * INPUT_PX + c] > 0;
                    both += usize::from(truth && got);
                    either += usize::from(truth || got);
                }
            }
            let iou = both as f64 / either.max(1) as f64;
            assert!(iou > 0.85, "frame {k} crop {i}: IoU {iou:.3}");
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_label_files_name_the_file_and_the_shape() {
    let rig = Rig::load_paper().unwrap();
    let dir = temp_dir("bad");
    make_set(&rig, &dir);
    let json = dir.join("frame_000.json");
    let good = std::fs::read_to_string(&json).unwrap();
    let check = |text: String, needles: &[&str]| {
        std::fs::write(&json, text).unwrap();
        let out = dir.join("split");
        let (ok, msg) = unet_import(&[
            "--labels".as_ref(),
            json.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ]);
        assert!(!ok, "accepted:\n{msg}");
        for n in needles {
            assert!(msg.contains(n), "{n:?} missing:\n{msg}");
        }
    };
    let mut v: serde_json::Value = serde_json::from_str(&good).unwrap();
    // A polygon point outside the image.
    v["shapes"][0]["points"][3] = serde_json::json!([1500.0, 20.0]);
    check(
        v.to_string(),
        &["frame_000.json", "shapes[0]", "outside the 1020x1020 image"],
    );
    // The tail point missing.
    let mut v: serde_json::Value = serde_json::from_str(&good).unwrap();
    v["shapes"].as_array_mut().unwrap().remove(2);
    check(
        v.to_string(),
        &["frame_000.json", "missing a \"tail\" point"],
    );
    // The file's image size disagrees with the image.
    let mut v: serde_json::Value = serde_json::from_str(&good).unwrap();
    v["imageWidth"] = serde_json::json!(1024);
    check(v.to_string(), &["frame_000.json", "imageWidth 1024"]);
    // The image is missing.
    let mut v: serde_json::Value = serde_json::from_str(&good).unwrap();
    v["imagePath"] = serde_json::json!("nope.png");
    check(v.to_string(), &["frame_000.json", "nope.png"]);
    std::fs::remove_dir_all(&dir).ok();
}
