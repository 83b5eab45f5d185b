//! Camera calibration for a rig (issue 16): the lens (intrinsics and distortion from
//! checkerboard views, OpenCV calib3d), the registration of the camera's undistorted pixels to
//! the world plane (a homography from four or more fiducials of known position), the one
//! rectification map that turns a raw frame into the rig's canonical top view, and the rig
//! file's `[camera.calibration]` table they are written to (ROS `camera_info` names).

pub mod registration;
pub mod rigwrite;
pub mod synthetic;

use std::path::PathBuf;

use fieldmaps::phantom::ImageGeometry;
use fieldmaps::rigfile::CameraCalibration;
use opencv::core::{self, Mat, Point2f, Point3f, Size, TermCriteria, Vector};
use opencv::prelude::*;
use opencv::{calib3d, imgproc};

pub use registration::{register, Fiducial, Registration};

/// Fewest views with a board found that a calibration accepts: OpenCV solves with three, but
/// the distortion terms are poorly conditioned below about ten (it warns of that).
pub const MIN_VIEWS: usize = 3;

#[derive(Debug, thiserror::Error)]
pub enum CalibError {
    #[error("{path}: {message}")]
    Image { path: PathBuf, message: String },
    #[error(
        "the board ({cols}x{rows} inner corners) was found in {found} of {total} images; a \
         calibration needs at least {MIN_VIEWS} (not found in: {missing})"
    )]
    TooFewViews {
        cols: i32,
        rows: i32,
        found: usize,
        total: usize,
        missing: String,
    },
    #[error("images differ in size: {first} is {w0}x{h0} px, {other} is {w1}x{h1} px")]
    MixedSizes {
        first: PathBuf,
        w0: i32,
        h0: i32,
        other: PathBuf,
        w1: i32,
        h1: i32,
    },
    #[error("{0}")]
    Invalid(String),
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

/// A planar checkerboard: its inner-corner grid and square size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Checkerboard {
    /// Inner corners along a row (columns) and along a column (rows).
    pub cols: i32,
    pub rows: i32,
    pub square_m: f64,
}

impl Checkerboard {
    pub fn validate(&self) -> Result<(), CalibError> {
        if self.cols < 2 || self.rows < 2 || self.cols == self.rows {
            return Err(CalibError::Invalid(format!(
                "a checkerboard needs at least 2x2 inner corners and different counts along its \
                 two sides (so its orientation is unambiguous), got {}x{}",
                self.cols, self.rows
            )));
        }
        if !(self.square_m.is_finite() && self.square_m > 0.0) {
            return Err(CalibError::Invalid(format!(
                "the square size must be > 0, got {} mm",
                self.square_m * 1e3
            )));
        }
        Ok(())
    }

    /// The inner corners on the board's plane (z = 0), m, row by row.
    pub fn object_points(&self) -> Vector<Point3f> {
        let mut points = Vector::new();
        for j in 0..self.rows {
            for i in 0..self.cols {
                points.push(Point3f::new(
                    (f64::from(i) * self.square_m) as f32,
                    (f64::from(j) * self.square_m) as f32,
                    0.0,
                ));
            }
        }
        points
    }
}

/// The board's inner corners in a grayscale image, refined to sub-pixel; `None` when the
/// board is not (entirely) visible.
pub fn find_corners(
    gray: &Mat,
    board: &Checkerboard,
) -> Result<Option<Vector<Point2f>>, CalibError> {
    let mut corners = Vector::<Point2f>::new();
    let found = calib3d::find_chessboard_corners(
        gray,
        Size::new(board.cols, board.rows),
        &mut corners,
        calib3d::CALIB_CB_ADAPTIVE_THRESH | calib3d::CALIB_CB_NORMALIZE_IMAGE,
    )?;
    if !found {
        return Ok(None);
    }
    let criteria = criteria(50, 1e-3)?;
    imgproc::corner_sub_pix(
        gray,
        &mut corners,
        Size::new(5, 5),
        Size::new(-1, -1),
        criteria,
    )?;
    Ok(Some(corners))
}

/// The lens as calibrated.
#[derive(Debug, Clone, PartialEq)]
pub struct Intrinsics {
    pub image_width: u32,
    pub image_height: u32,
    /// Row-major K.
    pub camera_matrix: [f64; 9],
    /// plumb_bob: k1, k2, p1, p2, k3.
    pub distortion: [f64; 5],
    /// RMS reprojection error over every corner of every view used, px.
    pub rms_px: f64,
    /// Each image with its own RMS reprojection error (px), or `None` where the board was not
    /// found (that image was not used).
    pub per_image: Vec<(PathBuf, Option<f64>)>,
}

impl Intrinsics {
    /// As the rig file's calibration (no registration yet).
    pub fn to_calibration(&self) -> CameraCalibration {
        CameraCalibration {
            image_width: self.image_width,
            image_height: self.image_height,
            camera_matrix: self.camera_matrix,
            distortion_coefficients: self.distortion,
            reprojection_error_px: Some(self.rms_px),
            image_to_world_mm: None,
            registration_residual_mm: None,
        }
    }
}

/// Calibrates the lens from grayscale views of `board` (`views`: each image's path, for the
/// report, and its pixels). Views where the board is not found are reported and skipped;
/// fewer than [`MIN_VIEWS`] with the board is an error naming the images without it.
pub fn calibrate_intrinsics(
    views: &[(PathBuf, Mat)],
    board: &Checkerboard,
    mut progress: impl FnMut(usize),
) -> Result<Intrinsics, CalibError> {
    board.validate()?;
    let first = views
        .first()
        .ok_or_else(|| CalibError::Invalid("no images given".into()))?;
    let size = first.1.size()?;
    let mut object_points = Vector::<Vector<Point3f>>::new();
    let mut image_points = Vector::<Vector<Point2f>>::new();
    let mut found_in = Vec::with_capacity(views.len());
    for (k, (path, image)) in views.iter().enumerate() {
        let this = image.size()?;
        if this != size {
            return Err(CalibError::MixedSizes {
                first: first.0.clone(),
                w0: size.width,
                h0: size.height,
                other: path.clone(),
                w1: this.width,
                h1: this.height,
            });
        }
        let corners = find_corners(image, board)?;
        if let Some(corners) = corners {
            object_points.push(board.object_points());
            image_points.push(corners);
            found_in.push(true);
        } else {
            found_in.push(false);
        }
        progress(k + 1);
    }
    let found = image_points.len();
    if found < MIN_VIEWS {
        let missing: Vec<String> = views
            .iter()
            .zip(&found_in)
            .filter(|(_, &f)| !f)
            .map(|((p, _), _)| p.display().to_string())
            .collect();
        return Err(CalibError::TooFewViews {
            cols: board.cols,
            rows: board.rows,
            found,
            total: views.len(),
            missing: missing.join(", "),
        });
    }
    let mut k = Mat::default();
    let mut d = Mat::default();
    let mut rvecs = Vector::<Mat>::new();
    let mut tvecs = Vector::<Mat>::new();
    let criteria = criteria(100, f64::EPSILON)?;
    let rms_px = calib3d::calibrate_camera(
        &object_points,
        &image_points,
        size,
        &mut k,
        &mut d,
        &mut rvecs,
        &mut tvecs,
        0,
        criteria,
    )?;
    let mut camera_matrix = [0.0; 9];
    for (i, v) in camera_matrix.iter_mut().enumerate() {
        *v = *k.at_2d::<f64>((i / 3) as i32, (i % 3) as i32)?;
    }
    let mut distortion = [0.0; 5];
    let flat = d.reshape(1, 1)?;
    for (i, v) in distortion.iter_mut().enumerate() {
        *v = *flat.at_2d::<f64>(0, i as i32)?;
    }
    // Each used view's own RMS reprojection error.
    let mut per_image = Vec::with_capacity(views.len());
    let mut used = 0;
    for ((path, _), &found) in views.iter().zip(&found_in) {
        if !found {
            per_image.push((path.clone(), None));
            continue;
        }
        let mut projected = Vector::<Point2f>::new();
        calib3d::project_points_def(
            &object_points.get(used)?,
            &rvecs.get(used)?,
            &tvecs.get(used)?,
            &k,
            &d,
            &mut projected,
        )?;
        let measured = image_points.get(used)?;
        let sum: f64 = projected
            .iter()
            .zip(measured.iter())
            .map(|(p, m)| f64::from((p.x - m.x).powi(2) + (p.y - m.y).powi(2)))
            .sum();
        per_image.push((path.clone(), Some((sum / projected.len() as f64).sqrt())));
        used += 1;
    }
    if !(rms_px.is_finite()
        && camera_matrix
            .iter()
            .chain(&distortion)
            .all(|v| v.is_finite()))
    {
        return Err(CalibError::Invalid(
            "the calibration did not converge (non-finite result): take more views, tilted \
             and spread over the whole image"
                .into(),
        ));
    }
    Ok(Intrinsics {
        image_width: size.width as u32,
        image_height: size.height as u32,
        camera_matrix,
        distortion,
        rms_px,
        per_image,
    })
}

/// OpenCV matrices of a rig calibration's lens.
pub fn lens_mats(calibration: &CameraCalibration) -> Result<(Mat, Mat), CalibError> {
    let k = Mat::new_rows_cols_with_data(3, 3, &calibration.camera_matrix)?.try_clone()?;
    let d =
        Mat::new_rows_cols_with_data(1, 5, &calibration.distortion_coefficients)?.try_clone()?;
    Ok((k, d))
}

/// OpenCV's stop rule: `max_count` iterations or a step below `eps`.
pub(crate) fn criteria(max_count: i32, eps: f64) -> Result<TermCriteria, CalibError> {
    Ok(TermCriteria::new(
        core::TermCriteria_Type::COUNT as i32 | core::TermCriteria_Type::EPS as i32,
        max_count,
        eps,
    )?)
}

/// Undistorted pixel coordinates (the pinhole image the homography speaks) of raw pixels.
pub fn undistort_pixels(
    calibration: &CameraCalibration,
    raw: &[(f64, f64)],
) -> Result<Vec<(f64, f64)>, CalibError> {
    let (k, d) = lens_mats(calibration)?;
    let src: Vector<Point2f> = raw
        .iter()
        .map(|&(u, v)| Point2f::new(u as f32, v as f32))
        .collect();
    let mut dst = Vector::<Point2f>::new();
    let criteria = criteria(50, 1e-9)?;
    calib3d::undistort_points_iter(&src, &mut dst, &k, &d, &core::no_array(), &k, criteria)?;
    Ok(dst
        .iter()
        .map(|p| (f64::from(p.x), f64::from(p.y)))
        .collect())
}

/// The rectification map of a calibrated, registered camera: for every pixel of the canonical
/// top view (`view`), where in the raw frame to sample it (`map_x`, `map_y`, CV_32FC1, for
/// `imgproc::remap`). The numbers are `fieldmaps::lens`'s, the ones the camera service and the
/// twin use (checked against OpenCV's `projectPoints` in this crate's tests).
pub fn rectification_maps(
    calibration: &CameraCalibration,
    view: &ImageGeometry,
) -> Result<(Mat, Mat), CalibError> {
    let map = calibration
        .rectification_map(view)
        .map_err(CalibError::Invalid)?;
    let to_mat = |values: &[f32]| -> Result<Mat, CalibError> {
        let mut mat = Mat::new_rows_cols_with_default(
            map.height as i32,
            map.width as i32,
            core::CV_32FC1,
            0.0.into(),
        )?;
        mat.data_typed_mut::<f32>()?.copy_from_slice(values);
        Ok(mat)
    };
    Ok((to_mat(&map.cols)?, to_mat(&map.rows)?))
}

/// A raw frame rectified onto the canonical top view with precomputed maps (bilinear; outside
/// the raw frame: black).
pub fn rectify(raw: &Mat, maps: &(Mat, Mat)) -> Result<Mat, CalibError> {
    let mut out = Mat::default();
    imgproc::remap(
        raw,
        &mut out,
        &maps.0,
        &maps.1,
        imgproc::INTER_LINEAR,
        core::BORDER_CONSTANT,
        core::Scalar::all(0.0),
    )?;
    Ok(out)
}

/// Reads an image as 8-bit grayscale, naming the file when it cannot.
pub fn read_gray(path: &std::path::Path) -> Result<Mat, CalibError> {
    let image = opencv::imgcodecs::imread(path, opencv::imgcodecs::IMREAD_GRAYSCALE)?;
    if image.empty() {
        return Err(CalibError::Image {
            path: path.to_owned(),
            message: "not a readable image (PNG, JPEG, BMP, TIFF...)".into(),
        });
    }
    Ok(image)
}
