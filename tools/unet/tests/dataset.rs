//! `unet-dataset`'s generator settings: the domain-randomized and held-out styles give crops
//! whose truth (mask, keypoints) still matches the capsule drawn, look unlike the twin's own
//! renders, and `--labelme-frames` writes labelled full frames that `unet-import` reads back
//! into the same kind of crops. Bad options are refused with the reason.
use std::path::{Path, PathBuf};
use std::process::Command;

use millinav_roi::dataset::Split;
use millinav_roi::roi::INPUT_PX;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("millinav-dataset-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Runs `bin` (unet-dataset or unet-import) on the paper's rig with `args`.
fn run(bin: &str, args: &[&str]) -> (bool, String) {
    let out = Command::new(bin)
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

fn dataset(args: &[&str]) -> (bool, String) {
    run(env!("CARGO_BIN_EXE_unet-dataset"), args)
}

/// Mask centroid and area of crop `i` (input pixels).
fn mask_moments(split: &Split, i: usize) -> ((f64, f64), f64) {
    let (mut n, mut sx, mut sy) = (0.0f64, 0.0, 0.0);
    for (k, &v) in split.mask(i).iter().enumerate() {
        if v > 0 {
            n += 1.0;
            sx += (k % INPUT_PX) as f64;
            sy += (k / INPUT_PX) as f64;
        }
    }
    ((sx / n.max(1.0), sy / n.max(1.0)), n)
}

/// Every crop with the capsule wholly inside: the mask's centroid is the labelled centroid and
/// the tip–tail distance is the capsule's length to the style's scale.
fn truth_matches_the_capsule(split: &Split, what: &str) {
    let rig = fieldmaps::rigfile::Rig::load_paper().unwrap();
    let mut checked = 0;
    for (i, label) in split.labels.iter().enumerate() {
        let length_px = rig.robot.length_m * 1e3 / label.mm_per_px / 2.0;
        let inside = |p: (f64, f64)| {
            (4.0..INPUT_PX as f64 - 4.0).contains(&p.0)
                && (4.0..INPUT_PX as f64 - 4.0).contains(&p.1)
        };
        if !label.has_robot || !inside(label.tip) || !inside(label.tail) {
            continue;
        }
        let (centroid, area) = mask_moments(split, i);
        let err = (centroid.0 - label.centroid.0).hypot(centroid.1 - label.centroid.1);
        assert!(
            err < 1.0,
            "{what} crop {i}: mask centroid {err:.2} px off the label"
        );
        let length = (label.tip.0 - label.tail.0).hypot(label.tip.1 - label.tail.1);
        assert!(
            (0.85..1.15).contains(&(length / length_px)),
            "{what} crop {i}: length {length:.1} px, capsule {length_px:.1} px"
        );
        assert!(area > 150.0, "{what} crop {i}: mask area {area}");
        checked += 1;
    }
    assert!(checked > 20, "{what}: only {checked} crops checked");
}

fn mean_rgb(split: &Split) -> [f64; 3] {
    let mut sum = [0.0; 3];
    let mut n = 0.0;
    for i in 0..split.len() {
        for px in split.image(i).chunks(3) {
            for c in 0..3 {
                sum[c] += f64::from(px[c]);
            }
            n += 1.0;
        }
    }
    sum.map(|s| s / n)
}

fn make(style: &str, dir: &Path) -> Split {
    let out = dir.join(style);
    let (ok, text) = dataset(&[
        "--out",
        out.to_str().unwrap(),
        "--train",
        "0",
        "--val",
        "0",
        "--test",
        "60",
        "--cameras",
        "3",
        "--style",
        style,
        "--seed",
        "77",
    ]);
    assert!(ok, "{text}");
    Split::load(&out.join("test")).unwrap()
}

#[test]
fn every_style_keeps_the_truth_on_the_capsule_and_the_styles_differ() {
    let dir = temp_dir("styles");
    let twin = make("twin", &dir);
    let randomized = make("randomized", &dir);
    let heldout = make("heldout", &dir);
    for (split, what) in [
        (&twin, "twin"),
        (&randomized, "randomized"),
        (&heldout, "heldout"),
    ] {
        truth_matches_the_capsule(split, what);
    }
    // The held-out setting is cool-lit (blue over red), the twin's canal warm (red over blue).
    let (t, h) = (mean_rgb(&twin), mean_rgb(&heldout));
    assert!(t[0] > t[2] && h[2] > h[0], "twin {t:?} heldout {h:?}");
    // Randomized crops of the same seed are not the twin's pixels.
    assert_ne!(twin.image(0), randomized.image(0));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
#[cfg(feature = "labelme")] // unet-import reads the frames with OpenCV
fn labelled_frames_import_back_into_crops_with_their_truth() {
    let dir = temp_dir("labelme");
    let frames = dir.join("frames");
    let (ok, text) = dataset(&[
        "--out",
        frames.to_str().unwrap(),
        "--labelme-frames",
        "16",
        "--style",
        "heldout",
        "--dye-rgb",
        "215,110,30",
        "--cameras",
        "2",
    ]);
    assert!(ok, "{text}");
    let jsons = std::fs::read_dir(&frames)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .path()
                .extension()
                .is_some_and(|x| x == "json")
        })
        .count();
    assert_eq!(jsons, 16, "{text}");
    let split_dir = dir.join("split");
    let (ok, text) = run(
        env!("CARGO_BIN_EXE_unet-import"),
        &[
            "--labels",
            frames.to_str().unwrap(),
            "--out",
            split_dir.to_str().unwrap(),
        ],
    );
    assert!(ok, "{text}");
    // 14 frames with the capsule (every 8th is empty), 2 empty.
    assert!(
        text.contains("16 frames (14 with a capsule, 2 empty)"),
        "{text}"
    );
    let train = Split::load(&split_dir.join("train")).unwrap();
    truth_matches_the_capsule(&train, "imported");
    // The dye is what was asked for: the capsule's pixels are orange, not the twin's blue.
    let (mut r, mut b, mut n) = (0.0, 0.0, 0.0);
    for i in 0..train.len() {
        for (px, &m) in train.image(i).chunks(3).zip(train.mask(i)) {
            if m > 0 {
                r += f64::from(px[0]);
                b += f64::from(px[2]);
                n += 1.0;
            }
        }
    }
    assert!(
        r / n > b / n + 40.0,
        "capsule mean red {} blue {}",
        r / n,
        b / n
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_bad_dye_is_refused_with_the_reason() {
    let dir = temp_dir("bad");
    let (ok, text) = dataset(&[
        "--out",
        dir.to_str().unwrap(),
        "--labelme-frames",
        "2",
        "--dye-rgb",
        "300,0,0",
    ]);
    assert!(!ok);
    assert!(
        text.contains("--dye-rgb") && text.contains("R,G,B"),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
