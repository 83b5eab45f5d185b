//! What a real camera would see of a plane (a checkerboard, the phantom): a pinhole with
//! OpenCV's plumb_bob distortion at a given pose. The calibration tests render views of a known
//! lens with it, and the twin can show vision a camera that is not square to the phantom.

use opencv::core::{self, Mat, Point2f, Point3f, Vector};
use opencv::prelude::*;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

use fieldmaps::rigfile::CameraCalibration;

use crate::{CalibError, Checkerboard};

/// A lens and its image size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lens {
    pub width: u32,
    pub height: u32,
    /// Row-major K.
    pub camera_matrix: [f64; 9],
    /// k1, k2, p1, p2, k3.
    pub distortion: [f64; 5],
}

/// A camera pose: world (plane) → camera, OpenCV's Rodrigues vector and translation (m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub rvec: [f64; 3],
    pub tvec: [f64; 3],
}

impl Pose {
    fn rotation(&self) -> Result<nalgebra::Matrix3<f64>, CalibError> {
        let r = Mat::new_rows_cols_with_data(3, 1, &self.rvec)?.try_clone()?;
        let mut m = Mat::default();
        opencv::calib3d::rodrigues_def(&r, &mut m)?;
        let mut out = nalgebra::Matrix3::zeros();
        for i in 0..3 {
            for j in 0..3 {
                out[(i, j)] = *m.at_2d::<f64>(i as i32, j as i32)?;
            }
        }
        Ok(out)
    }
}

impl Lens {
    /// The lens as a rig calibration (no registration).
    pub fn calibration(&self) -> CameraCalibration {
        CameraCalibration {
            image_width: self.width,
            image_height: self.height,
            camera_matrix: self.camera_matrix,
            distortion_coefficients: self.distortion,
            reprojection_error_px: None,
            image_to_world_mm: None,
            registration_residual_mm: None,
        }
    }
}

fn lens_mats(lens: &Lens) -> Result<(Mat, Mat), CalibError> {
    crate::lens_mats(&lens.calibration())
}

/// Raw pixel positions of world points (m) seen through `lens` at `pose`.
pub fn project(
    lens: &Lens,
    pose: &Pose,
    points_m: &[[f64; 3]],
) -> Result<Vec<(f64, f64)>, CalibError> {
    let (k, d) = lens_mats(lens)?;
    let object: Vector<Point3f> = points_m
        .iter()
        .map(|p| Point3f::new(p[0] as f32, p[1] as f32, p[2] as f32))
        .collect();
    let r = Mat::new_rows_cols_with_data(3, 1, &pose.rvec)?.try_clone()?;
    let t = Mat::new_rows_cols_with_data(3, 1, &pose.tvec)?.try_clone()?;
    let mut out = Vector::<Point2f>::new();
    opencv::calib3d::project_points_def(&object, &r, &t, &k, &d, &mut out)?;
    Ok(out
        .iter()
        .map(|p| (f64::from(p.x), f64::from(p.y)))
        .collect())
}

/// Renders the plane z = 0 as `lens` sees it from `pose`: every pixel averages
/// `supersample`² samples of `shade(x_m, y_m)` (0–255) at the plane points its sub-pixels look
/// at, plus Gaussian noise of `noise_std` grey levels (seeded). 8-bit grayscale.
pub fn render_plane(
    lens: &Lens,
    pose: &Pose,
    supersample: u32,
    noise_std: f64,
    seed: u64,
    shade: impl Fn(f64, f64) -> f64,
) -> Result<Mat, CalibError> {
    let (k, d) = lens_mats(lens)?;
    let s = supersample.max(1);
    let (w, h) = (lens.width as i32, lens.height as i32);
    let mut samples = Vector::<Point2f>::with_capacity((w * h) as usize * (s * s) as usize);
    for row in 0..h {
        for col in 0..w {
            for j in 0..s {
                for i in 0..s {
                    samples.push(Point2f::new(
                        col as f32 + (i as f32 + 0.5) / s as f32 - 0.5,
                        row as f32 + (j as f32 + 0.5) / s as f32 - 0.5,
                    ));
                }
            }
        }
    }
    // Normalized pinhole coordinates of each sample (the lens undone).
    let mut normalized = Vector::<Point2f>::new();
    let criteria = crate::criteria(30, 1e-7)?;
    opencv::calib3d::undistort_points_iter(
        &samples,
        &mut normalized,
        &k,
        &d,
        &core::no_array(),
        &core::no_array(),
        criteria,
    )?;
    let r = pose.rotation()?;
    let t = nalgebra::Vector3::from_row_slice(&pose.tvec);
    let rt = r.transpose();
    let origin = -(rt * t); // camera centre in plane coordinates
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let noise =
        Normal::new(0.0, noise_std.max(0.0)).map_err(|e| CalibError::Invalid(e.to_string()))?;
    let mut image = Mat::new_rows_cols_with_default(h, w, core::CV_8UC1, 0.0.into())?;
    let per_pixel = (s * s) as usize;
    for (pixel, chunk) in normalized.to_vec().chunks(per_pixel).enumerate() {
        let mut sum = 0.0;
        for p in chunk {
            let ray = rt * nalgebra::Vector3::new(f64::from(p.x), f64::from(p.y), 1.0);
            let value = if ray.z.abs() < 1e-12 {
                0.0
            } else {
                let lambda = -origin.z / ray.z;
                if lambda <= 0.0 {
                    0.0
                } else {
                    let hit = origin + ray * lambda;
                    shade(hit.x, hit.y)
                }
            };
            sum += value;
        }
        let grey = (sum / per_pixel as f64 + noise.sample(&mut rng))
            .round()
            .clamp(0.0, 255.0);
        let (row, col) = ((pixel as i32) / w, (pixel as i32) % w);
        *image.at_2d_mut::<u8>(row, col)? = grey as u8;
    }
    Ok(image)
}

/// A printed checkerboard on white paper: black and white squares around the inner-corner grid
/// (corner (i, j) at (i, j)·square), a square of white margin around them, grey beyond.
pub fn board_shade(board: &Checkerboard) -> impl Fn(f64, f64) -> f64 + '_ {
    move |x, y| {
        let s = board.square_m;
        let (cols, rows) = (f64::from(board.cols), f64::from(board.rows));
        let inside =
            |v: f64, n: f64, margin: f64| v >= -s * (1.0 + margin) && v <= s * (n + margin);
        if inside(x, cols, 0.0) && inside(y, rows, 0.0) {
            let parity = ((x / s).floor() as i64 + (y / s).floor() as i64).rem_euclid(2);
            if parity == 0 {
                20.0
            } else {
                235.0
            }
        } else if inside(x, cols, 1.0) && inside(y, rows, 1.0) {
            235.0
        } else {
            150.0
        }
    }
}

/// `board` tilted by the Euler angles (rx, ry, rz) rad with its centre at `centre` (m) in the
/// camera frame.
pub fn board_pose(board: &Checkerboard, (rx, ry, rz): (f64, f64, f64), centre: [f64; 3]) -> Pose {
    let r = nalgebra::Rotation3::from_euler_angles(rx, ry, rz);
    let c = nalgebra::Vector3::new(
        f64::from(board.cols - 1) * board.square_m / 2.0,
        f64::from(board.rows - 1) * board.square_m / 2.0,
        0.0,
    );
    let t = nalgebra::Vector3::from_row_slice(&centre) - r * c;
    let axis = r.scaled_axis();
    Pose {
        rvec: [axis.x, axis.y, axis.z],
        tvec: [t.x, t.y, t.z],
    }
}

/// A camera above the world plane looking down (image right = world x, image down = world −y),
/// its optical centre at `centre_m`, then tilted by the Euler angles `tilt` (rad): a top camera
/// that is not square to the phantom.
pub fn top_camera_pose(centre_m: [f64; 3], tilt: (f64, f64, f64)) -> Pose {
    let down = nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::new(
        1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0,
    ));
    let r = nalgebra::Rotation3::from_euler_angles(tilt.0, tilt.1, tilt.2) * down;
    let t = -(r * nalgebra::Vector3::from_row_slice(&centre_m));
    let axis = r.scaled_axis();
    Pose {
        rvec: [axis.x, axis.y, axis.z],
        tvec: [t.x, t.y, t.z],
    }
}

/// Board poses that cover the image (centre, tilts, rotations, the four corners): what a
/// careful calibration session takes.
pub const CALIBRATION_POSES: [((f64, f64, f64), [f64; 3]); 16] = [
    ((0.0, 0.0, 0.0), [0.0, 0.0, 0.45]),
    ((0.35, 0.0, 0.1), [-0.12, -0.08, 0.42]),
    ((-0.3, 0.2, -0.1), [0.12, 0.08, 0.45]),
    ((0.2, -0.35, 0.3), [0.12, -0.09, 0.43]),
    ((-0.25, -0.3, -0.2), [-0.12, 0.09, 0.44]),
    ((0.1, 0.4, 0.05), [0.0, -0.1, 0.40]),
    ((-0.4, 0.1, 0.15), [0.0, 0.1, 0.45]),
    ((0.3, 0.3, -0.3), [-0.14, 0.0, 0.46]),
    ((-0.2, -0.4, 0.25), [0.14, 0.0, 0.46]),
    ((0.15, 0.15, 1.2), [0.05, 0.02, 0.38]),
    ((-0.1, 0.3, -1.0), [-0.05, -0.02, 0.39]),
    ((0.45, -0.1, 0.0), [0.02, 0.05, 0.50]),
    ((0.2, -0.2, 0.1), [-0.17, -0.12, 0.47]),
    ((-0.2, -0.2, -0.1), [0.17, -0.12, 0.47]),
    ((0.2, 0.2, -0.1), [0.17, 0.12, 0.47]),
    ((-0.2, 0.2, 0.1), [-0.17, 0.12, 0.47]),
];

/// The demonstration lens (`calib synth`, the tests): 800x600 px, clear barrel distortion,
/// an off-centre principal point.
pub const DEMO_LENS: Lens = Lens {
    width: 800,
    height: 600,
    camera_matrix: [700.0, 0.0, 402.3, 0.0, 705.0, 297.8, 0.0, 0.0, 1.0],
    distortion: [-0.28, 0.09, 0.0008, -0.0006, 0.0],
};

/// The demonstration board: 8x5 inner corners, 25 mm squares.
pub const DEMO_BOARD: Checkerboard = Checkerboard {
    cols: 8,
    rows: 5,
    square_m: 0.025,
};

/// View `k` of [`CALIBRATION_POSES`] of `board` through `lens` (2x2 supersampled, 2 grey levels
/// of noise seeded by `k`).
pub fn calibration_view(lens: &Lens, board: &Checkerboard, k: usize) -> Result<Mat, CalibError> {
    let (tilt, centre) = CALIBRATION_POSES[k % CALIBRATION_POSES.len()];
    render_plane(
        lens,
        &board_pose(board, tilt, centre),
        2,
        2.0,
        k as u64,
        board_shade(board),
    )
}
