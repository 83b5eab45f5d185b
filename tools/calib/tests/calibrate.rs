//! Issue 16 test (a): `calib` recovers a known lens from synthetic checkerboard renders within
//! 0.5 px and the image-to-world registration within 0.1 mm; bad input is refused by name.

use std::path::{Path, PathBuf};

use fieldmaps::rigfile::{CameraCalibration, Rig};
use millinav_calib::registration::raw_pixel_to_world_mm;
use millinav_calib::rigwrite::{self, Update};
use millinav_calib::synthetic::{
    board_pose, board_shade, calibration_view, project, render_plane, top_camera_pose, Lens, Pose,
    DEMO_BOARD, DEMO_LENS,
};
use millinav_calib::{
    calibrate_intrinsics, rectification_maps, rectify, register, CalibError, Checkerboard, Fiducial,
};
use opencv::core::Mat;
use opencv::prelude::*;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

fn true_lens() -> Lens {
    DEMO_LENS
}

fn board() -> Checkerboard {
    DEMO_BOARD
}

fn views(count: usize) -> Vec<(PathBuf, Mat)> {
    (0..count)
        .map(|k| {
            let image = calibration_view(&true_lens(), &board(), k).unwrap();
            (PathBuf::from(format!("view{k:02}.png")), image)
        })
        .collect()
}

/// RMS reprojection error (px) of the recovered lens on views it was not calibrated on: the
/// board corners found in fresh renders of the true lens, against the corners projected with
/// the recovered lens at the pose `solvePnP` finds for it.
fn held_out_rms_px(estimate: &CameraCalibration) -> f64 {
    let lens = true_lens();
    let b = board();
    let (k, d) = millinav_calib::lens_mats(estimate).unwrap();
    let mut sum = 0.0;
    let mut count = 0.0;
    for (seed, (rx, ry, rz, centre)) in [
        (0.25, -0.15, 0.4, [0.1, 0.06, 0.44]),
        (-0.15, 0.3, -0.6, [-0.1, -0.05, 0.42]),
        (0.05, 0.05, 0.2, [0.15, -0.11, 0.48]),
    ]
    .into_iter()
    .enumerate()
    {
        let image = render_plane(
            &lens,
            &board_pose(&b, (rx, ry, rz), centre),
            2,
            2.0,
            100 + seed as u64,
            board_shade(&b),
        )
        .unwrap();
        let corners = millinav_calib::find_corners(&image, &b)
            .unwrap()
            .expect("board found");
        let object = b.object_points();
        let mut rvec = Mat::default();
        let mut tvec = Mat::default();
        assert!(
            opencv::calib3d::solve_pnp_def(&object, &corners, &k, &d, &mut rvec, &mut tvec)
                .unwrap()
        );
        let mut projected = opencv::core::Vector::<opencv::core::Point2f>::new();
        opencv::calib3d::project_points_def(&object, &rvec, &tvec, &k, &d, &mut projected).unwrap();
        for (p, c) in projected.iter().zip(corners.iter()) {
            sum += f64::from((p.x - c.x).powi(2) + (p.y - c.y).powi(2));
            count += 1.0;
        }
    }
    (sum / count).sqrt()
}

/// The top camera over the phantom: 0.35 m up, tilted a few degrees.
fn top_pose() -> Pose {
    top_camera_pose([0.01, -0.015, 0.35], (0.14, -0.09, 0.05))
}

fn fiducials(lens: &Lens, pose: &Pose, world_mm: &[(f64, f64)], noise_px: f64) -> Vec<Fiducial> {
    let points: Vec<[f64; 3]> = world_mm
        .iter()
        .map(|&(x, y)| [x * 1e-3, y * 1e-3, 0.0])
        .collect();
    let pixels = project(lens, pose, &points).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let noise = Normal::new(0.0, noise_px).unwrap();
    world_mm
        .iter()
        .zip(pixels)
        .enumerate()
        .map(|(i, (&(x, y), (u, v)))| Fiducial {
            name: format!("f{i}"),
            u_px: u + noise.sample(&mut rng),
            v_px: v + noise.sample(&mut rng),
            x_mm: x,
            y_mm: y,
        })
        .collect()
}

#[test]
fn calib_recovers_a_known_lens_and_registration() {
    let lens = true_lens();
    let views = views(16);
    let intrinsics = calibrate_intrinsics(&views, &board(), |_| {}).unwrap();
    println!(
        "K {:?}, D {:?}, RMS {:.3} px",
        intrinsics.camera_matrix, intrinsics.distortion, intrinsics.rms_px
    );
    assert!(intrinsics.per_image.iter().all(|(_, r)| r.is_some()));
    assert!(intrinsics.rms_px < 0.5, "RMS {}", intrinsics.rms_px);
    for (path, rms) in &intrinsics.per_image {
        assert!(rms.unwrap() < 0.5, "{}: {rms:?}", path.display());
    }
    let mut calibration = intrinsics.to_calibration();
    let held_out = held_out_rms_px(&calibration);
    println!("reprojection RMS on 3 views not used for the calibration: {held_out:.3} px");
    assert!(held_out < 0.5, "{held_out} px");
    assert!((calibration.camera_matrix[0] / 700.0 - 1.0).abs() < 0.01);

    // Registration from 9 fiducials over the phantom, each seen with 0.1 px of noise.
    let pose = top_pose();
    let world = [
        (-40.0, -38.0),
        (42.0, -40.0),
        (40.0, 41.0),
        (-39.0, 40.0),
        (0.0, -20.0),
        (15.0, 25.0),
        (-41.0, 2.0),
        (41.0, -3.0),
        (-2.0, 42.0),
    ];
    let registration = register(&calibration, &fiducials(&lens, &pose, &world, 0.1)).unwrap();
    println!("registration RMS {:.4} mm", registration.rms_mm);
    calibration.image_to_world_mm = Some(registration.image_to_world_mm);
    let mut worst: f64 = 0.0;
    let mut grid = Vec::new();
    for j in -4..=4 {
        for i in -4..=4 {
            grid.push((f64::from(i) * 11.0, f64::from(j) * 11.0));
        }
    }
    let points: Vec<[f64; 3]> = grid
        .iter()
        .map(|&(x, y)| [x * 1e-3, y * 1e-3, 0.0])
        .collect();
    for (&(x, y), (u, v)) in grid.iter().zip(project(&lens, &pose, &points).unwrap()) {
        let (wx, wy) = raw_pixel_to_world_mm(&calibration, u, v).unwrap();
        worst = worst.max(((wx - x).powi(2) + (wy - y).powi(2)).sqrt());
    }
    println!("registration error over the phantom: {worst:.4} mm");
    assert!(worst < 0.1, "{worst} mm");
}

#[test]
fn rectification_puts_the_world_where_the_canonical_view_expects_it() {
    // A plane with a bright disc at (12, −7) mm, radius 4 mm, seen by the tilted lens; after
    // rectification onto a 0.2 mm/px view the disc's centroid is where the view maps (12, −7).
    let lens = true_lens();
    let pose = top_pose();
    let disc = |x: f64, y: f64| {
        if ((x - 0.012).powi(2) + (y + 0.007).powi(2)).sqrt() < 0.004 {
            240.0
        } else {
            30.0
        }
    };
    let raw = render_plane(&lens, &pose, 3, 0.0, 1, disc).unwrap();
    let world: Vec<(f64, f64)> = vec![(-40.0, -40.0), (40.0, -40.0), (40.0, 40.0), (-40.0, 40.0)];
    let mut calibration = intrinsics_of_truth();
    calibration.image_to_world_mm = Some(
        register(&calibration, &fiducials(&lens, &pose, &world, 0.0))
            .unwrap()
            .image_to_world_mm,
    );
    let view = fieldmaps::phantom::ImageGeometry {
        width_px: 400,
        height_px: 400,
        mm_per_px: 0.2,
        origin_x_mm: -40.0,
        origin_y_mm: 40.0,
    };
    let maps = rectification_maps(&calibration, &view).unwrap();
    let top = rectify(&raw, &maps).unwrap();
    let (mut sum, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for row in 0..400 {
        for col in 0..400 {
            let g = f64::from(*top.at_2d::<u8>(row, col).unwrap());
            if g > 135.0 {
                let x = -40.0 + (f64::from(col) + 0.5) * 0.2;
                let y = 40.0 - (f64::from(row) + 0.5) * 0.2;
                sum += 1.0;
                sx += x;
                sy += y;
            }
        }
    }
    let (cx, cy) = (sx / sum, sy / sum);
    let area = sum * 0.04;
    println!("disc centroid ({cx:.3}, {cy:.3}) mm, area {area:.1} mm²");
    assert!(((cx - 12.0).powi(2) + (cy + 7.0).powi(2)).sqrt() < 0.05);
    assert!((area / (std::f64::consts::PI * 16.0) - 1.0).abs() < 0.05);
}

#[test]
fn bad_input_is_refused_with_a_reason() {
    // Too few views with the board.
    let two = views(2);
    let error = calibrate_intrinsics(&two, &board(), |_| {}).unwrap_err();
    assert!(
        matches!(error, CalibError::TooFewViews { found: 2, .. }),
        "{error}"
    );
    // A grey image: the board is found nowhere, and the message names the image.
    let blank =
        Mat::new_rows_cols_with_default(600, 800, opencv::core::CV_8UC1, 128.0.into()).unwrap();
    let mut with_blank = views(3);
    with_blank.push((PathBuf::from("blank.png"), blank));
    let lens = calibrate_intrinsics(&with_blank, &board(), |_| {}).unwrap();
    assert_eq!(lens.per_image[3].1, None);
    let only_blank = vec![(PathBuf::from("blank.png"), with_blank.pop().unwrap().1)];
    let message = calibrate_intrinsics(&only_blank, &board(), |_| {})
        .unwrap_err()
        .to_string();
    assert!(message.contains("blank.png"), "{message}");
    // A square board (ambiguous orientation) and a bad square size.
    for bad in [
        Checkerboard {
            cols: 6,
            rows: 6,
            square_m: 0.02,
        },
        Checkerboard {
            cols: 8,
            rows: 5,
            square_m: 0.0,
        },
    ] {
        assert!(calibrate_intrinsics(&views(3), &bad, |_| {}).is_err());
    }

    // Fiducials: too few, collinear, repeated.
    let calibration = intrinsics_of_truth();
    let pose = top_pose();
    let lens = true_lens();
    let three = fiducials(&lens, &pose, &[(0.0, 0.0), (10.0, 0.0), (0.0, 10.0)], 0.0);
    assert!(register(&calibration, &three)
        .unwrap_err()
        .to_string()
        .contains("at least 4"));
    let line = fiducials(
        &lens,
        &pose,
        &[(-30.0, -30.0), (-10.0, -10.0), (10.0, 10.0), (30.0, 30.1)],
        0.0,
    );
    assert!(register(&calibration, &line)
        .unwrap_err()
        .to_string()
        .contains("degenerate"));
    let mut repeated = fiducials(
        &lens,
        &pose,
        &[(-30.0, -30.0), (30.0, -30.0), (30.0, 30.0), (-30.0, 30.0)],
        0.0,
    );
    repeated[3].name = repeated[0].name.clone();
    assert!(register(&calibration, &repeated)
        .unwrap_err()
        .to_string()
        .contains("twice"));
}

fn intrinsics_of_truth() -> CameraCalibration {
    true_lens().calibration()
}

/// A copy of the paper's rig file beside it (its relative paths must keep resolving), removed
/// when dropped.
struct RigCopy(PathBuf);
impl RigCopy {
    fn new(tag: &str) -> Self {
        let dir = fieldmaps::data_root().join("fieldmaps/rigs");
        let path = dir.join(format!(".calib-test-{tag}-{}.toml", std::process::id()));
        std::fs::copy(dir.join("paper.toml"), &path).unwrap();
        Self(path)
    }
}
impl Drop for RigCopy {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

fn write_lens(rig: &Path) {
    let lens = true_lens();
    let intrinsics = millinav_calib::Intrinsics {
        image_width: lens.width,
        image_height: lens.height,
        camera_matrix: lens.camera_matrix,
        distortion: lens.distortion,
        rms_px: 0.1,
        per_image: Vec::new(),
    };
    rigwrite::write(rig, Update::Intrinsics(&intrinsics)).unwrap();
}

#[test]
fn results_land_in_the_rig_file_and_a_bad_registration_is_refused() {
    let copy = RigCopy::new("write");
    let before = std::fs::read_to_string(&copy.0).unwrap();
    // A registration before any lens: refused, file untouched.
    let registration = millinav_calib::Registration {
        image_to_world_mm: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        residuals_mm: Vec::new(),
        rms_mm: 0.0,
    };
    let message = rigwrite::write(&copy.0, Update::Registration(&registration))
        .unwrap_err()
        .to_string();
    assert!(message.contains("calib intrinsics"), "{message}");
    assert_eq!(std::fs::read_to_string(&copy.0).unwrap(), before);

    write_lens(&copy.0);
    let rig = Rig::load(&copy.0).unwrap();
    let calibration = rig.camera.calibration.expect("the lens was written");
    assert_eq!(calibration.camera_matrix, true_lens().camera_matrix);
    assert!(std::fs::read_to_string(&copy.0)
        .unwrap()
        .contains("# paper: top camera 1020 x 1020 px"));

    // The identity maps the 92 mm view to pixels −46..46: outside the image. Refused, file kept.
    let with_lens = std::fs::read_to_string(&copy.0).unwrap();
    let message = rigwrite::write(&copy.0, Update::Registration(&registration))
        .unwrap_err()
        .to_string();
    assert!(message.contains("outside"), "{message}");
    assert_eq!(std::fs::read_to_string(&copy.0).unwrap(), with_lens);

    // A real registration of the tilted top camera is accepted and read back.
    let pose = top_pose();
    let world = [
        (-45.0, -45.0),
        (45.0, -45.0),
        (45.0, 45.0),
        (-45.0, 45.0),
        (0.0, 10.0),
    ];
    let good = register(&calibration, &fiducials(&true_lens(), &pose, &world, 0.0)).unwrap();
    rigwrite::write(&copy.0, Update::Registration(&good)).unwrap();
    let rig = Rig::load(&copy.0).unwrap();
    let back = rig.camera.calibration.unwrap().image_to_world_mm.unwrap();
    for (a, b) in back.iter().zip(&good.image_to_world_mm) {
        assert!((a - b).abs() <= 1e-12 * b.abs().max(1.0));
    }
}

#[test]
fn a_bad_calibration_table_is_named_by_file_and_field() {
    let good = "\n[camera.calibration]\nimage_width = 800\nimage_height = 600\n\
                camera_matrix = [700.0, 0.0, 400.0, 0.0, 700.0, 300.0, 0.0, 0.0, 1.0]\n\
                distortion_model = \"plumb_bob\"\n\
                distortion_coefficients = [-0.2, 0.05, 0.0, 0.0, 0.0]\n";
    for (tag, replace, with, field) in [
        (
            "model",
            "\"plumb_bob\"",
            "\"fisheye\"",
            "camera.calibration.distortion_model",
        ),
        (
            "coefficients",
            "[-0.2, 0.05, 0.0, 0.0, 0.0]",
            "[-0.2, 0.05]",
            "camera.calibration.distortion_coefficients",
        ),
        (
            "matrix",
            "700.0, 0.0, 400.0",
            "-700.0, 0.0, 400.0",
            "camera.calibration.camera_matrix",
        ),
        (
            "size",
            "image_width = 800",
            "image_width = 0",
            "camera.calibration.image_width",
        ),
    ] {
        let copy = RigCopy::new(tag);
        let text = std::fs::read_to_string(&copy.0).unwrap();
        // The table goes right after [camera]'s keys, before [phantom].
        let bad = good.replace(replace, with);
        let text = text.replacen("\n[phantom]", &format!("{bad}\n[phantom]"), 1);
        std::fs::write(&copy.0, text).unwrap();
        let message = Rig::load(&copy.0).unwrap_err().to_string();
        assert!(
            message.contains(field)
                && message.contains(&*copy.0.file_name().unwrap().to_string_lossy()),
            "{tag}: {message}"
        );
    }
}

/// The camera service and the twin use `fieldmaps::lens` (pure Rust) for the lens; it must be
/// OpenCV's model, which `calib` fits: the same raw pixel for the same ray, over the whole
/// image of a lens with strong barrel.
#[test]
fn the_shared_lens_model_is_opencvs() {
    let lens = true_lens();
    let calibration = lens.calibration();
    let identity = Pose {
        rvec: [0.0; 3],
        tvec: [0.0; 3],
    };
    let k = lens.camera_matrix;
    let mut worst = 0.0f64;
    for i in -6..=6 {
        for j in -5..=5 {
            let (x, y) = (f64::from(i) * 0.09, f64::from(j) * 0.08);
            let (u_cv, v_cv) = project(&lens, &identity, &[[x, y, 1.0]]).unwrap()[0];
            let (xd, yd) = calibration.distort_normalized(x, y);
            let (u, v) = (k[0] * xd + k[2], k[4] * yd + k[5]);
            worst = worst.max((u - u_cv).hypot(v - v_cv));
        }
    }
    // OpenCV projects in f32 points: agreement to its rounding.
    assert!(worst < 2e-3, "lens models differ by {worst} px");
}
