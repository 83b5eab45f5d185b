//! One-click colour calibration on a reference frame whose capsule is not the twin's colour: the
//! default ranges (the twin's blue dye) miss it, the calibrated ones find it where it is.

use fieldmaps::rig::CapsuleAppearance;
use millinav_vision::classical::{
    calibrate_appearance, CalibrationError, CapsuleSize, ClassicalLocalizer,
};
use opencv::core::{self as cv, Mat, MatTraitConstManual};
use opencv::imgproc;

const SIZE: CapsuleSize = CapsuleSize {
    length_m: 7.4e-3,
    diameter_m: 2.8e-3,
};
const MM_PER_PX: f64 = 0.09;
const WIDTH: i32 = 320;
const HEIGHT: i32 = 240;

/// A beige frame with a capsule of `body_rgb` dye and a dark magnet at its tail, centred at
/// `centre` and turned by `angle_deg`.
fn frame(body_rgb: [f64; 3], centre: (f32, f32), angle_deg: f32) -> Vec<u8> {
    let mut image = Mat::new_rows_cols_with_default(
        HEIGHT,
        WIDTH,
        cv::CV_8UC3,
        cv::Scalar::new(228.0, 226.0, 214.0, 0.0),
    )
    .unwrap();
    let length = (SIZE.length_m * 1e3 / MM_PER_PX) as f32;
    let diameter = (SIZE.diameter_m * 1e3 / MM_PER_PX) as f32;
    let fill = |image: &mut Mat, c: (f32, f32), w: f32, colour: [f64; 3]| {
        let rect = cv::RotatedRect::new(
            cv::Point2f::new(c.0, c.1),
            cv::Size2f::new(w, diameter),
            angle_deg,
        )
        .unwrap();
        let mut corners = [cv::Point2f::default(); 4];
        rect.points(&mut corners).unwrap();
        let polygon: cv::Vector<cv::Point> = corners
            .iter()
            .map(|p| cv::Point::new(p.x.round() as i32, p.y.round() as i32))
            .collect();
        imgproc::fill_convex_poly_def(
            image,
            &polygon,
            cv::Scalar::new(colour[0], colour[1], colour[2], 0.0),
        )
        .unwrap();
    };
    fill(&mut image, centre, length, body_rgb);
    let (dx, dy) = (angle_deg.to_radians().cos(), angle_deg.to_radians().sin());
    let magnet_centre = (centre.0 - dx * length * 0.35, centre.1 - dy * length * 0.35);
    fill(&mut image, magnet_centre, length * 0.3, [30.0, 28.0, 25.0]);
    image.data_bytes().unwrap().to_vec()
}

#[test]
fn a_green_capsule_is_found_after_calibration_and_missed_before() {
    let rgb = frame([50.0, 170.0, 70.0], (150.0, 110.0), 25.0);
    let search = (0, 0, WIDTH, HEIGHT);
    let twin_ranges = ClassicalLocalizer::new(SIZE, CapsuleAppearance::default());
    assert!(twin_ranges
        .localize(&rgb, WIDTH, HEIGHT, search, MM_PER_PX)
        .is_err());

    let appearance =
        calibrate_appearance(&rgb, WIDTH, HEIGHT, (152, 111), 50, SIZE, MM_PER_PX).unwrap();
    appearance.validate().unwrap();
    println!("{appearance:?}");
    // Green is hue ≈ 65 of 180 in OpenCV's scale.
    assert!(appearance.body_hsv_min[0] < 65.0 && appearance.body_hsv_max[0] > 65.0);
    // The same ranges find the capsule in another frame, elsewhere and turned.
    let other = frame([50.0, 170.0, 70.0], (90.0, 160.0), -60.0);
    let (detection, _) = ClassicalLocalizer::new(SIZE, appearance)
        .localize(&other, WIDTH, HEIGHT, search, MM_PER_PX)
        .unwrap();
    let (cx, cy) = detection.centroid_px;
    assert!((cx - 90.0).hypot(cy - 160.0) < 3.0, "centroid ({cx}, {cy})");
    // The tail (magnet end) is where the magnet was drawn: −x, +y of the centre for −60°.
    let heading_deg = detection.heading_image_rad.to_degrees();
    assert!((heading_deg - -60.0).abs() < 5.0, "heading {heading_deg}°");
}

#[test]
fn a_click_off_the_capsule_or_outside_the_frame_is_refused_clearly() {
    let rgb = frame([50.0, 170.0, 70.0], (150.0, 110.0), 25.0);
    let error =
        calibrate_appearance(&rgb, WIDTH, HEIGHT, (20, 20), 30, SIZE, MM_PER_PX).unwrap_err();
    assert_eq!(error, CalibrationError::NoBody, "{error}");
    let error =
        calibrate_appearance(&rgb, WIDTH, HEIGHT, (400, 20), 30, SIZE, MM_PER_PX).unwrap_err();
    assert!(error.to_string().contains("outside"), "{error}");
    // A capsule without a visible magnet cannot give a magnet range.
    let plain = {
        let mut rgb = frame([50.0, 170.0, 70.0], (150.0, 110.0), 25.0);
        for px in rgb.chunks_exact_mut(3) {
            if px[0] < 40 {
                px.copy_from_slice(&[50, 170, 70]);
            }
        }
        rgb
    };
    let error =
        calibrate_appearance(&plain, WIDTH, HEIGHT, (150, 110), 50, SIZE, MM_PER_PX).unwrap_err();
    assert!(
        matches!(error, CalibrationError::NoMagnet { .. }),
        "{error}"
    );
}
