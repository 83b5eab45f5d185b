//! Writes calibration results into a rig file's `[camera.calibration]` table, keeping the rest
//! of the file (comments, order) as it is, and refusing a result the rig loader would reject.

use std::path::Path;

use fieldmaps::rigfile::Rig;
use toml_edit::{value, Array, DocumentMut, Item, Table};

use crate::{CalibError, Intrinsics, Registration};

fn array(values: &[f64]) -> Array {
    values.iter().copied().collect()
}

/// What to write.
pub enum Update<'a> {
    /// The lens: replaces the whole table (a registration made with another lens is void).
    Intrinsics(&'a Intrinsics),
    /// The registration, beside the lens already in the file.
    Registration(&'a Registration),
}

/// Applies `update` to the rig file at `path` (written whole: temporary file + rename) and
/// loads the result; on a load error the file is left as it was and the error names it.
pub fn write(path: &Path, update: Update<'_>) -> Result<(), CalibError> {
    let bad = |message: String| CalibError::Image {
        path: path.to_owned(),
        message,
    };
    let text = std::fs::read_to_string(path).map_err(|e| bad(format!("cannot read: {e}")))?;
    let mut doc: DocumentMut = text
        .parse()
        .map_err(|e| bad(format!("not valid TOML: {e}")))?;
    let camera = doc
        .get_mut("camera")
        .and_then(Item::as_table_mut)
        .ok_or_else(|| bad("has no [camera] table".into()))?;
    match update {
        Update::Intrinsics(lens) => {
            let mut t = Table::new();
            t.decor_mut().set_prefix(
                "\n# The lens, from `calib intrinsics` (ROS camera_info names); the raw frames' size.\n",
            );
            t.insert("image_width", value(i64::from(lens.image_width)));
            t.insert("image_height", value(i64::from(lens.image_height)));
            t.insert("camera_matrix", value(array(&lens.camera_matrix)));
            t.insert("distortion_model", value("plumb_bob"));
            t.insert("distortion_coefficients", value(array(&lens.distortion)));
            t.insert("reprojection_error_px", value(lens.rms_px));
            camera.insert("calibration", Item::Table(t));
        }
        Update::Registration(registration) => {
            let t = camera
                .get_mut("calibration")
                .and_then(Item::as_table_mut)
                .ok_or_else(|| {
                    bad(
                        "has no [camera.calibration] lens yet: run `calib intrinsics --write` \
                         first"
                            .into(),
                    )
                })?;
            t.insert(
                "image_to_world_mm",
                value(array(&registration.image_to_world_mm)),
            );
            t.insert("registration_residual_mm", value(registration.rms_mm));
        }
    }
    let tmp = path.with_extension("toml.calib-tmp");
    std::fs::write(&tmp, doc.to_string()).map_err(|e| bad(format!("cannot write: {e}")))?;
    // Check the new file the way every service will load it, before it replaces the old one.
    let checked_path = tmp.with_file_name(
        path.file_name()
            .map(|n| format!(".{}.check.toml", n.to_string_lossy()))
            .unwrap_or_else(|| ".rig.check.toml".into()),
    );
    std::fs::rename(&tmp, &checked_path).map_err(|e| bad(format!("cannot write: {e}")))?;
    match Rig::load(&checked_path) {
        Ok(_) => {
            std::fs::rename(&checked_path, path).map_err(|e| bad(format!("cannot write: {e}")))
        }
        Err(e) => {
            let _ = std::fs::remove_file(&checked_path);
            // The loader names the file it read; that is this rig file, with the new table.
            let reason = e.to_string().replace(
                &checked_path.display().to_string(),
                &path.display().to_string(),
            );
            Err(bad(format!(
                "left unchanged: with the new calibration it would not load: {reason}"
            )))
        }
    }
}
