//! The camera's registration to the world plane: a homography from undistorted pixels to world
//! millimetres, fitted to four or more fiducials whose world positions are known.

use std::path::Path;

use fieldmaps::rigfile::CameraCalibration;
use opencv::core::{Mat, Point2d, Vector};
use opencv::prelude::*;

use crate::{undistort_pixels, CalibError};

/// One fiducial: where it appears in a raw frame and where it is in the world.
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
pub struct Fiducial {
    pub name: String,
    pub u_px: f64,
    pub v_px: f64,
    pub x_mm: f64,
    pub y_mm: f64,
}

/// Reads a fiducial CSV (header `name,u_px,v_px,x_mm,y_mm`), naming the file and the row of
/// any bad entry.
pub fn read_fiducials(path: &Path) -> Result<Vec<Fiducial>, CalibError> {
    let bad = |message: String| CalibError::Image {
        path: path.to_owned(),
        message,
    };
    let mut reader = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .comment(Some(b'#'))
        .from_path(path)
        .map_err(|e| bad(format!("cannot read: {e}")))?;
    let mut out = Vec::new();
    for (i, row) in reader.deserialize::<Fiducial>().enumerate() {
        let f = row.map_err(|e| {
            bad(format!(
                "row {}: {e} (expected the columns name,u_px,v_px,x_mm,y_mm)",
                i + 1
            ))
        })?;
        if ![f.u_px, f.v_px, f.x_mm, f.y_mm]
            .iter()
            .all(|v| v.is_finite())
        {
            return Err(bad(format!(
                "row {} ({}): every number must be finite",
                i + 1,
                f.name
            )));
        }
        out.push(f);
    }
    Ok(out)
}

/// A fitted registration and how well each fiducial lands.
#[derive(Debug, Clone, PartialEq)]
pub struct Registration {
    /// Undistorted raw pixels → world mm, row-major.
    pub image_to_world_mm: [f64; 9],
    /// Each fiducial's name and the distance from its mapped pixel to its world position, mm.
    pub residuals_mm: Vec<(String, f64)>,
    pub rms_mm: f64,
}

/// Smallest-over-largest spread of a point set (√ of the eigenvalue ratio of its covariance):
/// 0 for points on one line.
fn spread_ratio(points: &[(f64, f64)]) -> f64 {
    let n = points.len() as f64;
    let (mx, my) = points
        .iter()
        .fold((0.0, 0.0), |(a, b), p| (a + p.0 / n, b + p.1 / n));
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    for p in points {
        sxx += (p.0 - mx).powi(2);
        syy += (p.1 - my).powi(2);
        sxy += (p.0 - mx) * (p.1 - my);
    }
    let eig = nalgebra::Matrix2::new(sxx, sxy, sxy, syy).symmetric_eigenvalues();
    let (lo, hi) = (eig.min(), eig.max());
    if hi <= 0.0 {
        0.0
    } else {
        (lo.max(0.0) / hi).sqrt()
    }
}

/// Fits the homography from the fiducials' undistorted pixels to their world positions (least
/// squares over all of them). Refused: fewer than 4, repeated names, and fiducials (nearly) on
/// one line in the image or in the world, which leave the homography undetermined.
pub fn register(
    calibration: &CameraCalibration,
    fiducials: &[Fiducial],
) -> Result<Registration, CalibError> {
    if fiducials.len() < 4 {
        return Err(CalibError::Invalid(format!(
            "a registration needs at least 4 fiducials, got {}",
            fiducials.len()
        )));
    }
    for (i, f) in fiducials.iter().enumerate() {
        if fiducials[..i].iter().any(|g| g.name == f.name) {
            return Err(CalibError::Invalid(format!(
                "fiducial {:?} is listed twice",
                f.name
            )));
        }
    }
    let raw: Vec<(f64, f64)> = fiducials.iter().map(|f| (f.u_px, f.v_px)).collect();
    let world: Vec<(f64, f64)> = fiducials.iter().map(|f| (f.x_mm, f.y_mm)).collect();
    for (what, points) in [("image", &raw), ("world", &world)] {
        let ratio = spread_ratio(points);
        if ratio < 0.05 {
            return Err(CalibError::Invalid(format!(
                "the fiducials are degenerate: they lie (nearly) on one line in the {what} \
                 (spread ratio {ratio:.3}); use at least 4 spread over the phantom, no 3 of \
                 them in line"
            )));
        }
    }
    let undistorted = undistort_pixels(calibration, &raw)?;
    let src: Vector<Point2d> = undistorted
        .iter()
        .map(|&(u, v)| Point2d::new(u, v))
        .collect();
    let dst: Vector<Point2d> = world.iter().map(|&(x, y)| Point2d::new(x, y)).collect();
    let mut mask = Mat::default();
    let h = opencv::calib3d::find_homography(&src, &dst, &mut mask, 0, 3.0)?;
    if h.empty() {
        return Err(CalibError::Invalid(
            "no homography fits these fiducials (degenerate set)".into(),
        ));
    }
    let mut image_to_world_mm = [0.0; 9];
    for (i, v) in image_to_world_mm.iter_mut().enumerate() {
        *v = *h.at_2d::<f64>((i / 3) as i32, (i % 3) as i32)?;
    }
    let m = nalgebra::Matrix3::from_row_slice(&image_to_world_mm);
    let mut residuals_mm = Vec::with_capacity(fiducials.len());
    for (f, &(u, v)) in fiducials.iter().zip(&undistorted) {
        let p = m * nalgebra::Vector3::new(u, v, 1.0);
        let error = ((p.x / p.z - f.x_mm).powi(2) + (p.y / p.z - f.y_mm).powi(2)).sqrt();
        residuals_mm.push((f.name.clone(), error));
    }
    let rms_mm =
        (residuals_mm.iter().map(|(_, e)| e * e).sum::<f64>() / residuals_mm.len() as f64).sqrt();
    if !(rms_mm.is_finite() && image_to_world_mm.iter().all(|v| v.is_finite())) {
        return Err(CalibError::Invalid(
            "the homography is not finite (degenerate fiducials)".into(),
        ));
    }
    Ok(Registration {
        image_to_world_mm,
        residuals_mm,
        rms_mm,
    })
}

/// World position (mm) of a raw pixel through a calibration with a registration.
pub fn raw_pixel_to_world_mm(
    calibration: &CameraCalibration,
    u: f64,
    v: f64,
) -> Result<(f64, f64), CalibError> {
    let h = calibration
        .image_to_world_mm
        .ok_or_else(|| CalibError::Invalid("the camera has no registration".into()))?;
    let (uu, vv) = undistort_pixels(calibration, &[(u, v)])?[0];
    let p = nalgebra::Matrix3::from_row_slice(&h) * nalgebra::Vector3::new(uu, vv, 1.0);
    Ok((p.x / p.z, p.y / p.z))
}
