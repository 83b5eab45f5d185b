//! What a real camera would see of a plane (a checkerboard, the phantom): a pinhole with
//! OpenCV's plumb_bob distortion at a given pose. The calibration tests render views of a known
//! lens with it, and the twin can show vision a camera that is not square to the phantom.

use opencv::core::{self, Mat, Point2f, Point3f, TermCriteria, Vector};
use opencv::prelude::*;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

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

fn lens_mats(lens: &Lens) -> Result<(Mat, Mat), CalibError> {
    Ok((
        Mat::new_rows_cols_with_data(3, 3, &lens.camera_matrix)?.try_clone()?,
        Mat::new_rows_cols_with_data(1, 5, &lens.distortion)?.try_clone()?,
    ))
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
    let criteria = TermCriteria::new(
        core::TermCriteria_Type::COUNT as i32 | core::TermCriteria_Type::EPS as i32,
        30,
        1e-7,
    )?;
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
