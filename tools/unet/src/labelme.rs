//! Your own labelled frames → UNet training crops.
//!
//! Format: LabelMe JSON (one file per frame, next to or naming its image), chosen because it is a
//! plain, documented per-image file that the LabelMe desktop tool, CVAT and Label Studio export.
//! Each frame is a full camera frame already on the rig's top view (the camera's resolution,
//! the rig file's mm/px). Shapes:
//! - `polygon` labelled `capsule` (`--body-label`): the capsule's outline;
//! - `point` labelled `tip` and `tail` (`--tip-label`, `--tail-label`): the cap end and the magnet
//!   end, both required with a capsule; the centroid is their midpoint.
//!
//! A frame with no capsule polygon is an empty-canal frame (negative crops only). Each frame gives
//! `crops_per_frame` crops around the capsule (the tracking offset jittered as the service sees
//! it) and `negatives_per_frame` crops away from it, exactly as `unet-dataset` cuts the twin's
//! renders (`millinav_roi::roi`), written as a `millinav_roi::dataset::Split`.

use std::path::{Path, PathBuf};

use fieldmaps::rigfile::Rig;
use millinav_roi::dataset::{Label, Split};
use millinav_roi::roi::{extract_mask, extract_rgb, Crop, CROP_PX};
use opencv::core::{Mat, Point, Scalar, Vector, CV_8UC1};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Deserialize;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum LabelError {
    #[error("{}: {message}", path.display())]
    File { path: PathBuf, message: String },
}

fn err(path: &Path, message: impl Into<String>) -> LabelError {
    LabelError::File {
        path: path.to_owned(),
        message: message.into(),
    }
}

#[derive(Debug, Deserialize)]
#[serde(rename_all = "camelCase")]
struct LabelMeFile {
    image_path: String,
    image_height: u32,
    image_width: u32,
    #[serde(default)]
    shapes: Vec<Shape>,
}

#[derive(Debug, Deserialize)]
struct Shape {
    label: String,
    points: Vec<[f64; 2]>,
    #[serde(default = "default_shape_type")]
    shape_type: String,
}

fn default_shape_type() -> String {
    "polygon".into()
}

/// Shape labels.
#[derive(Debug, Clone)]
pub struct LabelNames {
    pub body: String,
    pub tip: String,
    pub tail: String,
}

impl Default for LabelNames {
    fn default() -> Self {
        Self {
            body: "capsule".into(),
            tip: "tip".into(),
            tail: "tail".into(),
        }
    }
}

/// A labelled frame, checked.
#[derive(Debug, Clone)]
pub struct LabelledFrame {
    pub json: PathBuf,
    /// RGB, row-major.
    pub rgb: Vec<u8>,
    pub width: usize,
    pub height: usize,
    /// The capsule: outline (px) and tip / tail (px), if the frame shows one.
    pub capsule: Option<Capsule>,
}

#[derive(Debug, Clone)]
pub struct Capsule {
    pub outline_px: Vec<(f64, f64)>,
    pub tip_px: (f64, f64),
    pub tail_px: (f64, f64),
}

/// Reads and checks one LabelMe file and its image against the rig's camera.
pub fn read_frame(json: &Path, rig: &Rig, names: &LabelNames) -> Result<LabelledFrame, LabelError> {
    let text = std::fs::read_to_string(json).map_err(|e| err(json, format!("cannot read: {e}")))?;
    let file: LabelMeFile = serde_json::from_str(&text)
        .map_err(|e| err(json, format!("not a LabelMe JSON file: {e}")))?;
    let image_path = json
        .parent()
        .unwrap_or(Path::new("."))
        .join(&file.image_path);
    let bgr = imgcodecs::imread(&image_path, imgcodecs::IMREAD_COLOR)
        .map_err(|e| err(json, format!("imagePath {}: {e}", image_path.display())))?;
    if bgr.empty() {
        return Err(err(
            json,
            format!("imagePath {}: cannot read the image", image_path.display()),
        ));
    }
    let (width, height) = (bgr.cols() as usize, bgr.rows() as usize);
    if (width, height) != (file.image_width as usize, file.image_height as usize) {
        return Err(err(
            json,
            format!(
                "the image is {width}x{height} px but the file says imageWidth {} x imageHeight {}",
                file.image_width, file.image_height
            ),
        ));
    }
    let g = &rig.camera.geometry;
    if (width, height) != (g.width_px as usize, g.height_px as usize) {
        return Err(err(
            json,
            format!(
                "the image is {width}x{height} px but the rig's camera ({}) is {}x{}: label frames \
                 on the rig's top view (its resolution and mm/px)",
                rig.path.display(),
                g.width_px,
                g.height_px
            ),
        ));
    }
    let mut rgb_mat = Mat::default();
    imgproc::cvt_color_def(&bgr, &mut rgb_mat, imgproc::COLOR_BGR2RGB)
        .map_err(|e| err(json, e.to_string()))?;
    let rgb = rgb_mat
        .data_bytes()
        .map_err(|e| err(json, e.to_string()))?
        .to_vec();
    let inside = |p: &[f64; 2]| {
        p[0].is_finite()
            && p[1].is_finite()
            && (0.0..=width as f64).contains(&p[0])
            && (0.0..=height as f64).contains(&p[1])
    };
    let mut body = None;
    let mut tip = None;
    let mut tail = None;
    for (k, shape) in file.shapes.iter().enumerate() {
        if let Some(p) = shape.points.iter().find(|p| !inside(p)) {
            return Err(err(
                json,
                format!(
                    "shapes[{k}] ({:?}): point ({}, {}) lies outside the {width}x{height} image",
                    shape.label, p[0], p[1]
                ),
            ));
        }
        let one_point = |what: &str| -> Result<(f64, f64), LabelError> {
            match (shape.shape_type.as_str(), shape.points.as_slice()) {
                ("point", [p]) => Ok((p[0], p[1])),
                _ => Err(err(
                    json,
                    format!("shapes[{k}] ({what}): must be a `point` shape with one point"),
                )),
            }
        };
        if shape.label == names.body {
            if shape.shape_type != "polygon" || shape.points.len() < 3 {
                return Err(err(
                    json,
                    format!(
                        "shapes[{k}] ({:?}): the capsule must be a polygon of 3 or more points",
                        shape.label
                    ),
                ));
            }
            if body.is_some() {
                return Err(err(json, format!("shapes[{k}]: a second capsule polygon")));
            }
            body = Some(
                shape
                    .points
                    .iter()
                    .map(|p| (p[0], p[1]))
                    .collect::<Vec<_>>(),
            );
        } else if shape.label == names.tip {
            tip = Some(one_point(&names.tip)?);
        } else if shape.label == names.tail {
            tail = Some(one_point(&names.tail)?);
        }
    }
    let capsule = match (body, tip, tail) {
        (None, None, None) => None,
        (Some(outline_px), Some(tip_px), Some(tail_px)) => Some(Capsule {
            outline_px,
            tip_px,
            tail_px,
        }),
        (body, tip, tail) => {
            let missing: Vec<String> = [
                (body.is_none(), format!("a {:?} polygon", names.body)),
                (tip.is_none(), format!("a {:?} point", names.tip)),
                (tail.is_none(), format!("a {:?} point", names.tail)),
            ]
            .into_iter()
            .filter_map(|(m, s)| m.then_some(s))
            .collect();
            return Err(err(
                json,
                format!(
                    "a labelled capsule needs its outline, tip and tail; missing {}",
                    missing.join(", ")
                ),
            ));
        }
    };
    Ok(LabelledFrame {
        json: json.to_owned(),
        rgb,
        width,
        height,
        capsule,
    })
}

/// The capsule's full-frame mask (1 inside the polygon).
pub fn rasterize(capsule: &Capsule, width: usize, height: usize) -> opencv::Result<Vec<u8>> {
    let mut mask =
        Mat::new_rows_cols_with_default(height as i32, width as i32, CV_8UC1, Scalar::all(0.0))?;
    let polygon: Vector<Point> = capsule
        .outline_px
        .iter()
        // Pixel centres at integers: the outline's corners are at pixel edges.
        .map(|&(x, y)| Point::new((x - 0.5).round() as i32, (y - 0.5).round() as i32))
        .collect();
    let polygons: Vector<Vector<Point>> = std::iter::once(polygon).collect();
    imgproc::fill_poly_def(&mut mask, &polygons, Scalar::all(1.0))?;
    Ok(mask.data_bytes()?.to_vec())
}

/// How many crops a frame gives.
#[derive(Debug, Clone, Copy)]
pub struct CropPlan {
    pub crops_per_frame: usize,
    pub negatives_per_frame: usize,
    /// Tracking offset of the crop centre from the capsule, px (uniform ±).
    pub jitter_px: f64,
    pub seed: u64,
}

impl Default for CropPlan {
    fn default() -> Self {
        Self {
            crops_per_frame: 4,
            negatives_per_frame: 1,
            jitter_px: 40.0,
            seed: 1,
        }
    }
}

/// Crops of one frame appended to `split`.
pub fn crop_frame(
    frame: &LabelledFrame,
    mm_per_px: f64,
    plan: &CropPlan,
    frame_index: u64,
    split: &mut Split,
) -> Result<(), LabelError> {
    let mut rng = ChaCha8Rng::seed_from_u64(plan.seed ^ frame_index.wrapping_mul(0x9E37_79B9));
    let (w, h) = (frame.width, frame.height);
    let full_mask = match &frame.capsule {
        Some(c) => rasterize(c, w, h).map_err(|e| err(&frame.json, e.to_string()))?,
        None => vec![0u8; w * h],
    };
    let (mut image, mut mask) = (Vec::new(), Vec::new());
    let mut push = |crop: Crop, has_robot: bool, capsule: Option<&Capsule>| {
        extract_rgb(&frame.rgb, w, &crop, &mut image);
        extract_mask(&full_mask, w, &crop, &mut mask);
        let to_input = |p: (f64, f64)| crop.frame_to_input(p.0, p.1);
        let (tip, tail) = capsule.map_or(((0.0, 0.0), (0.0, 0.0)), |c| (c.tip_px, c.tail_px));
        let centroid = ((tip.0 + tail.0) / 2.0, (tip.1 + tail.1) / 2.0);
        split.push(
            &image,
            &mask,
            Label {
                has_robot,
                tip: to_input(tip),
                centroid: to_input(centroid),
                tail: to_input(tail),
                crop_col0: crop.col0,
                crop_row0: crop.row0,
                mm_per_px,
            },
        );
    };
    let no_crop = || {
        err(
            &frame.json,
            format!("the frame is smaller than a {CROP_PX} px crop"),
        )
    };
    if let Some(c) = &frame.capsule {
        let centre = (
            (c.tip_px.0 + c.tail_px.0) / 2.0,
            (c.tip_px.1 + c.tail_px.1) / 2.0,
        );
        for _ in 0..plan.crops_per_frame {
            let j = plan.jitter_px;
            let crop = Crop::around(
                centre.0 + rng.random_range(-j..=j),
                centre.1 + rng.random_range(-j..=j),
                w,
                h,
            )
            .ok_or_else(no_crop)?;
            push(crop, true, Some(c));
        }
    }
    // Negatives: crops that contain no capsule pixel (up to 50 tries each).
    for _ in 0..plan.negatives_per_frame {
        for _ in 0..50 {
            let crop = Crop::around(
                rng.random_range(0.0..w as f64),
                rng.random_range(0.0..h as f64),
                w,
                h,
            )
            .ok_or_else(no_crop)?;
            let empty = (crop.row0..crop.row0 + CROP_PX).all(|r| {
                full_mask[r * w + crop.col0..r * w + crop.col0 + CROP_PX]
                    .iter()
                    .all(|&m| m == 0)
            });
            if empty {
                push(crop, false, None);
                break;
            }
        }
    }
    Ok(())
}

/// The LabelMe files in `dir` (sorted), or `dir` itself when it is one file.
pub fn label_files(dir: &Path) -> Result<Vec<PathBuf>, LabelError> {
    if dir.is_file() {
        return Ok(vec![dir.to_owned()]);
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| err(dir, format!("cannot list: {e}")))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(err(dir, "no LabelMe .json files"));
    }
    Ok(files)
}

impl Capsule {
    /// The outline a labeller clicks around a capsule seen from above: 13 points around each
    /// end cap (pixel-edge convention: the pixel centre (c, r) covers c − 0.5 … c + 0.5).
    /// `axis` is the unit tail → tip direction in image pixels.
    pub fn clicked(
        tip_px: (f64, f64),
        tail_px: (f64, f64),
        axis: (f64, f64),
        radius_px: f64,
    ) -> Capsule {
        let centre = ((tip_px.0 + tail_px.0) / 2.0, (tip_px.1 + tail_px.1) / 2.0);
        let half = ((tip_px.0 - tail_px.0).hypot(tip_px.1 - tail_px.1) / 2.0 - radius_px).max(0.0);
        let (ax, ay) = axis;
        let mut outline_px = Vec::new();
        for (end, start_angle) in [(1.0, -90.0f64), (-1.0, 90.0)] {
            let c = (centre.0 + end * half * ax, centre.1 + end * half * ay);
            for k in 0..=12 {
                let (sa, ca) = (start_angle + 15.0 * k as f64).to_radians().sin_cos();
                let dir = (ax * ca - ay * sa, ax * sa + ay * ca);
                outline_px.push((c.0 + radius_px * dir.0 + 0.5, c.1 + radius_px * dir.1 + 0.5));
            }
        }
        Capsule {
            outline_px,
            tip_px,
            tail_px,
        }
    }
}

/// Writes one frame as `<name>.png` + `<name>.json` (LabelMe) into `dir`, labelled with the
/// default names: what a labelled frame of your camera looks like.
pub fn write_frame(
    dir: &Path,
    name: &str,
    rgb: &[u8],
    width: usize,
    height: usize,
    capsule: Option<&Capsule>,
) -> Result<(), LabelError> {
    let names = LabelNames::default();
    let png = dir.join(format!("{name}.png"));
    let image = Mat::from_slice(rgb)
        .and_then(|m| m.reshape(3, height as i32)?.try_clone())
        .map_err(|e| err(&png, e.to_string()))?;
    let mut bgr = Mat::default();
    imgproc::cvt_color_def(&image, &mut bgr, imgproc::COLOR_RGB2BGR)
        .map_err(|e| err(&png, e.to_string()))?;
    let written =
        imgcodecs::imwrite(&png, &bgr, &Vector::new()).map_err(|e| err(&png, e.to_string()))?;
    if !written {
        return Err(err(&png, "cannot write the image"));
    }
    let point = |label: &str, p: (f64, f64)| serde_json::json!({"label": label, "shape_type": "point", "points": [[p.0, p.1]], "flags": {}});
    let shapes: Vec<serde_json::Value> = capsule
        .map(|c| {
            let outline: Vec<[f64; 2]> = c.outline_px.iter().map(|&(x, y)| [x, y]).collect();
            vec![
                serde_json::json!({"label": names.body, "shape_type": "polygon", "points": outline, "flags": {}}),
                point(&names.tip, c.tip_px),
                point(&names.tail, c.tail_px),
            ]
        })
        .unwrap_or_default();
    let json = serde_json::json!({
        "version": "5.4.1",
        "flags": {},
        "shapes": shapes,
        "imagePath": format!("{name}.png"),
        "imageData": null,
        "imageHeight": height,
        "imageWidth": width,
    });
    let path = dir.join(format!("{name}.json"));
    let text = serde_json::to_string_pretty(&json).map_err(|e| err(&path, e.to_string()))?;
    std::fs::write(&path, text).map_err(|e| err(&path, format!("cannot write: {e}")))
}
