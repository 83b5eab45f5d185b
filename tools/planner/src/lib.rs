//! The `planner` tool's image side: a canal mask read from an image file with OpenCV; and the
//! scenario it writes from a template (`template`). The planning itself is the
//! `millinav-planning` library.

pub mod template;

use std::path::{Path, PathBuf};

use millinav_planning::{Mask, PlanError};
use opencv::core as cv;
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};

#[derive(Debug, thiserror::Error)]
pub enum MaskLoadError {
    #[error("{path}: OpenCV: {source}")]
    OpenCv {
        path: PathBuf,
        source: opencv::Error,
    },
    #[error("{0}: not an image OpenCV can read")]
    Unreadable(PathBuf),
    #[error("{path}: {source}")]
    Mask { path: PathBuf, source: PlanError },
}

/// A mask image (white = canal; any format OpenCV reads, thresholded at 128).
pub fn load_mask(path: &Path) -> Result<Mask, MaskLoadError> {
    let opencv = |source| MaskLoadError::OpenCv {
        path: path.to_path_buf(),
        source,
    };
    let img = imgcodecs::imread(path.as_os_str(), imgcodecs::IMREAD_GRAYSCALE).map_err(opencv)?;
    if img.empty() {
        return Err(MaskLoadError::Unreadable(path.to_path_buf()));
    }
    let mut bin = cv::Mat::default();
    imgproc::threshold(&img, &mut bin, 127.0, 255.0, imgproc::THRESH_BINARY).map_err(opencv)?;
    let (w, h) = (bin.cols(), bin.rows());
    let data = if bin.is_continuous() {
        bin.data_bytes().map_err(opencv)?.to_vec()
    } else {
        bin.try_clone()
            .and_then(|m| m.data_bytes().map(<[u8]>::to_vec))
            .map_err(opencv)?
    };
    Mask::new(w as u32, h as u32, data).map_err(|source| MaskLoadError::Mask {
        path: path.to_path_buf(),
        source,
    })
}
