//! Classical localizer (OpenCV): colour segmentation of the dyed body and the dark magnet,
//! contour moments for the centroid, the principal axis for the heading, and the magnet's side
//! of the body to tell tail from tip. It is the baseline and the fallback of the UNet path.

use opencv::core as cv;
use opencv::imgproc;
use opencv::prelude::*;

/// Capsule size seen from the top camera, used to reject blobs that are not the robot.
#[derive(Debug, Clone, Copy)]
pub struct CapsuleSize {
    pub length_m: f64,
    pub diameter_m: f64,
}

impl CapsuleSize {
    /// The rig's capsule (`[robot]` of the rig file).
    pub fn of(robot: &fieldmaps::rig::RobotParams) -> Self {
        Self {
            length_m: robot.length_m,
            diameter_m: robot.diameter_m,
        }
    }
}

/// A detection in pixel coordinates of the full frame (continuous, pixel centres at integers).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detection {
    pub centroid_px: (f64, f64),
    pub tip_px: (f64, f64),
    pub tail_px: (f64, f64),
    /// Heading in image axes (x right, y down), radians.
    pub heading_image_rad: f64,
    pub area_px: f64,
    pub confidence: f64,
}

/// Why a frame gave no pose.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LocalizeError {
    #[error("no robot-coloured blob in the search region")]
    NotFound,
    #[error(
        "blob area {area_px:.0} px is implausible for the capsule (expected ≈{expected_px:.0})"
    )]
    ImplausibleArea { area_px: f64, expected_px: f64 },
    #[error("tip and tail cannot be told apart (magnet not visible)")]
    Ambiguous,
    #[error("opencv: {0}")]
    OpenCv(String),
}

impl From<opencv::Error> for LocalizeError {
    fn from(e: opencv::Error) -> Self {
        Self::OpenCv(e.to_string())
    }
}

/// Pixel rectangle (col, row, width, height) of the frame to search.
pub type SearchRect = (i32, i32, i32, i32);

pub struct ClassicalLocalizer {
    pub size: CapsuleSize,
}

impl ClassicalLocalizer {
    pub fn new(size: CapsuleSize) -> Self {
        Self { size }
    }

    /// Localizes the capsule in `rgb` (tightly packed RGB rows of `width` pixels), searching
    /// only `rect`. `mm_per_px` sets the expected blob size.
    pub fn localize(
        &self,
        rgb: &[u8],
        width: i32,
        height: i32,
        rect: SearchRect,
        mm_per_px: f64,
    ) -> Result<(Detection, cv::Mat), LocalizeError> {
        let frame = cv::Mat::new_rows_cols_with_bytes::<cv::Vec3b>(height, width, rgb)?;
        let roi_rect = cv::Rect::new(rect.0, rect.1, rect.2, rect.3);
        let roi = frame.roi(roi_rect)?;
        let mut hsv = cv::Mat::default();
        imgproc::cvt_color_def(&roi, &mut hsv, imgproc::COLOR_RGB2HSV)?;
        // Blue dye and the lighter cap: hue ≈ 105..125 (of 180), clearly saturated.
        let mut body = cv::Mat::default();
        cv::in_range(
            &hsv,
            &cv::Scalar::new(95.0, 60.0, 60.0, 0.0),
            &cv::Scalar::new(130.0, 255.0, 255.0, 0.0),
            &mut body,
        )?;
        // The magnet: very dark whatever its hue.
        let mut magnet = cv::Mat::default();
        cv::in_range(
            &hsv,
            &cv::Scalar::new(0.0, 0.0, 0.0, 0.0),
            &cv::Scalar::new(180.0, 255.0, 70.0, 0.0),
            &mut magnet,
        )?;
        let mut robot = cv::Mat::default();
        cv::bitwise_or_def(&body, &magnet, &mut robot)?;

        let mut contours: cv::Vector<cv::Vector<cv::Point>> = cv::Vector::new();
        imgproc::find_contours(
            &robot,
            &mut contours,
            imgproc::RETR_EXTERNAL,
            imgproc::CHAIN_APPROX_NONE,
            cv::Point::new(rect.0, rect.1),
        )?;
        let px_per_m = 1e3 / mm_per_px;
        let expected_px = (self.size.length_m - self.size.diameter_m)
            * self.size.diameter_m
            * px_per_m
            * px_per_m
            + std::f64::consts::PI * (self.size.diameter_m * px_per_m / 2.0).powi(2);
        let mut best: Option<(f64, cv::Vector<cv::Point>)> = None;
        for contour in contours.iter() {
            let area = imgproc::contour_area_def(&contour)?;
            if best.as_ref().is_none_or(|(a, _)| area > *a) {
                best = Some((area, contour));
            }
        }
        let Some((_, contour)) = best else {
            return Err(LocalizeError::NotFound);
        };
        // Moments of the filled region (not the outline) so partial coverage weighs right.
        let bbox = imgproc::bounding_rect(&contour)?;
        let local = cv::Rect::new(bbox.x - rect.0, bbox.y - rect.1, bbox.width, bbox.height);
        let region = robot.roi(local)?;
        let m = imgproc::moments(&region, true)?;
        let area_px = m.m00;
        if !(0.4 * expected_px..=2.0 * expected_px).contains(&area_px) {
            return Err(LocalizeError::ImplausibleArea {
                area_px,
                expected_px,
            });
        }
        let cx = bbox.x as f64 + m.m10 / m.m00;
        let cy = bbox.y as f64 + m.m01 / m.m00;
        let axis_angle = 0.5 * (2.0 * m.mu11).atan2(m.mu20 - m.mu02);
        let (ax, ay) = (axis_angle.cos(), axis_angle.sin());

        // Tail = the magnet's end: its centroid lies on the tail side of the body centroid.
        let magnet_region = magnet.roi(local)?;
        let mm = imgproc::moments(&magnet_region, true)?;
        let min_magnet_px = 0.3 * (1e-3 * px_per_m).powi(2);
        if mm.m00 < min_magnet_px {
            return Err(LocalizeError::Ambiguous);
        }
        let mx = bbox.x as f64 + mm.m10 / mm.m00;
        let my = bbox.y as f64 + mm.m01 / mm.m00;
        let side = (mx - cx) * ax + (my - cy) * ay;
        let offset_px = side.abs();
        if offset_px < 0.15 * self.size.length_m * px_per_m {
            return Err(LocalizeError::Ambiguous);
        }
        // Unit vector tail → tip.
        let (hx, hy) = if side > 0.0 { (-ax, -ay) } else { (ax, ay) };
        // Ends: extreme projections of the outline on the axis.
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for p in contour.iter() {
            let s = (p.x as f64 - cx) * hx + (p.y as f64 - cy) * hy;
            lo = lo.min(s);
            hi = hi.max(s);
        }
        let area_score = 1.0 - ((area_px / expected_px) - 1.0).abs().min(1.0);
        let detection = Detection {
            centroid_px: (cx, cy),
            tip_px: (cx + hx * (hi + 0.5), cy + hy * (hi + 0.5)),
            tail_px: (cx + hx * (lo - 0.5), cy + hy * (lo - 0.5)),
            heading_image_rad: hy.atan2(hx),
            area_px,
            confidence: area_score.clamp(0.0, 1.0),
        };
        Ok((detection, robot))
    }
}
