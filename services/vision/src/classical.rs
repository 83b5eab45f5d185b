//! Classical localizer (OpenCV): colour segmentation of the dyed body and the dark magnet,
//! contour moments for the centroid, the principal axis for the heading, and the magnet's side
//! of the body to tell tail from tip. It is the baseline and the fallback of the UNet path.

use fieldmaps::rig::CapsuleAppearance;
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
    /// Colour ranges of the body and the magnet (the rig file's `[robot.appearance]`).
    pub appearance: CapsuleAppearance,
}

impl ClassicalLocalizer {
    pub fn new(size: CapsuleSize, appearance: CapsuleAppearance) -> Self {
        Self { size, appearance }
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
        let look = &self.appearance;
        let scalar = |v: [f64; 3]| cv::Scalar::new(v[0], v[1], v[2], 0.0);
        let mut body = cv::Mat::default();
        cv::in_range(
            &hsv,
            &scalar(look.body_hsv_min),
            &scalar(look.body_hsv_max),
            &mut body,
        )?;
        // The magnet: dark whatever its hue.
        let mut magnet = cv::Mat::default();
        cv::in_range(
            &hsv,
            &cv::Scalar::new(0.0, 0.0, 0.0, 0.0),
            &cv::Scalar::new(180.0, 255.0, look.magnet_value_max, 0.0),
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

/// Why a reference frame could not calibrate the colours.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    #[error("the click ({col}, {row}) is outside the {width}x{height} frame")]
    OutsideFrame {
        col: i32,
        row: i32,
        width: i32,
        height: i32,
    },
    #[error("no saturated (dyed) pixels near the click: is the capsule there?")]
    NoBody,
    #[error("the dye's hue wraps past 180 (a red dye), which the ranges cannot hold")]
    HueWraps,
    #[error(
        "no dark magnet near the click: its darkest pixels (value {darkest:.0}) are not darker \
         than the dye's ({body_darkest:.0})"
    )]
    NoMagnet { darkest: f64, body_darkest: f64 },
    #[error("the calibrated ranges do not find the capsule at the click: {0}")]
    NotVerified(String),
    #[error("opencv: {0}")]
    OpenCv(String),
}

impl From<opencv::Error> for CalibrationError {
    fn from(e: opencv::Error) -> Self {
        Self::OpenCv(e.to_string())
    }
}

/// Threshold between the two classes of an 8-bit histogram that maximises the between-class
/// variance (Otsu).
fn otsu(values: &[u8]) -> u8 {
    let mut histogram = [0u64; 256];
    for &v in values {
        histogram[v as usize] += 1;
    }
    let total = values.len() as f64;
    let sum: f64 = histogram
        .iter()
        .enumerate()
        .map(|(v, &n)| v as f64 * n as f64)
        .sum();
    let (mut weight_low, mut sum_low, mut best, mut threshold) = (0.0, 0.0, -1.0, 0u8);
    for (v, &n) in histogram.iter().enumerate() {
        weight_low += n as f64;
        sum_low += v as f64 * n as f64;
        let weight_high = total - weight_low;
        if weight_low == 0.0 || weight_high == 0.0 {
            continue;
        }
        let between = weight_low
            * weight_high
            * (sum_low / weight_low - (sum - sum_low) / weight_high).powi(2);
        if between > best {
            best = between;
            threshold = v as u8;
        }
    }
    threshold
}

/// The `q`-quantile (0..=1) of `values` (sorted in place).
fn quantile(values: &mut [u8], q: f64) -> f64 {
    values.sort_unstable();
    let index = ((values.len().saturating_sub(1)) as f64 * q).round() as usize;
    values.get(index).map_or(0.0, |&v| f64::from(v))
}

/// Margin added around the measured colour ranges (hue in OpenCV units, saturation and value
/// in 8-bit levels): room for lighting drift and noise beyond the reference frame.
const HUE_MARGIN: f64 = 6.0;
const LEVEL_MARGIN: f64 = 15.0;

/// One-click colour calibration: the capsule's colour ranges measured on a reference frame
/// (`rgb`, tightly packed RGB rows of `width`) around the pixel `click` (col, row) where the
/// user sees the capsule, within `radius_px` (about half the capsule's length). The dyed body
/// is the saturated class of the disc (Otsu on saturation), the magnet its darkest pixels; the
/// result is checked by localizing the capsule with it.
pub fn calibrate_appearance(
    rgb: &[u8],
    width: i32,
    height: i32,
    click: (i32, i32),
    radius_px: i32,
    localizer_size: CapsuleSize,
    mm_per_px: f64,
) -> Result<CapsuleAppearance, CalibrationError> {
    let (col, row) = click;
    if !(0..width).contains(&col) || !(0..height).contains(&row) {
        return Err(CalibrationError::OutsideFrame {
            col,
            row,
            width,
            height,
        });
    }
    let frame = cv::Mat::new_rows_cols_with_bytes::<cv::Vec3b>(height, width, rgb)?;
    let radius = radius_px.max(2);
    let rect = cv::Rect::new(
        (col - radius).max(0),
        (row - radius).max(0),
        (2 * radius + 1).min(width - (col - radius).max(0)),
        (2 * radius + 1).min(height - (row - radius).max(0)),
    );
    let mut hsv = cv::Mat::default();
    imgproc::cvt_color_def(&frame.roi(rect)?, &mut hsv, imgproc::COLOR_RGB2HSV)?;
    let mut disc: Vec<[u8; 3]> = Vec::new();
    for y in 0..rect.height {
        for x in 0..rect.width {
            let (dx, dy) = (rect.x + x - col, rect.y + y - row);
            if dx * dx + dy * dy <= radius * radius {
                let p = hsv.at_2d::<cv::Vec3b>(y, x)?;
                disc.push([p[0], p[1], p[2]]);
            }
        }
    }
    let saturations: Vec<u8> = disc.iter().map(|p| p[1]).collect();
    let saturation_split = otsu(&saturations);
    let body: Vec<[u8; 3]> = disc
        .iter()
        .copied()
        .filter(|p| p[1] > saturation_split)
        .collect();
    // A disc of one colour has no saturated class apart from its background.
    if body.len() < 10 || body.len() == disc.len() {
        return Err(CalibrationError::NoBody);
    }
    let mut hues: Vec<u8> = body.iter().map(|p| p[0]).collect();
    let (hue_low, hue_high) = (quantile(&mut hues, 0.01), quantile(&mut hues, 0.99));
    if hue_high - hue_low > 90.0 {
        return Err(CalibrationError::HueWraps);
    }
    let mut body_values: Vec<u8> = body.iter().map(|p| p[2]).collect();
    let body_darkest = quantile(&mut body_values, 0.02);
    let mut values: Vec<u8> = disc.iter().map(|p| p[2]).collect();
    let darkest = quantile(&mut values, 0.01);
    if body_darkest - darkest < 2.0 * LEVEL_MARGIN {
        return Err(CalibrationError::NoMagnet {
            darkest,
            body_darkest,
        });
    }
    // Halfway between the magnet and the dye's darkest pixels (whole levels: what a rig file
    // holds).
    let magnet_value_max = ((darkest + body_darkest) / 2.0).round();
    let appearance = CapsuleAppearance {
        body_hsv_min: [
            (hue_low - HUE_MARGIN).max(0.0).round(),
            (f64::from(saturation_split) + 1.0).min(255.0),
            (magnet_value_max + 1.0).min(255.0),
        ],
        body_hsv_max: [(hue_high + HUE_MARGIN).min(180.0).round(), 255.0, 255.0],
        magnet_value_max,
    };
    let search = (rect.x, rect.y, rect.width, rect.height);
    let localizer = ClassicalLocalizer::new(localizer_size, appearance);
    let (detection, _) = localizer
        .localize(rgb, width, height, search, mm_per_px)
        .map_err(|e| CalibrationError::NotVerified(e.to_string()))?;
    let (cx, cy) = detection.centroid_px;
    if (cx - f64::from(col)).hypot(cy - f64::from(row)) > f64::from(radius) {
        return Err(CalibrationError::NotVerified(format!(
            "found a capsule at ({cx:.0}, {cy:.0}), away from the click"
        )));
    }
    Ok(appearance)
}
