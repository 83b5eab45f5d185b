//! The UNet localizer's input, shared by the vision service and the training-data exporter
//! (`tools/unet`), so the model sees exactly the same input in training and on the rig:
//! - `roi`: crop a square region around the predicted position and downsample it by an integer
//!   factor with a box filter (the same as OpenCV's INTER_AREA for integer factors);
//! - `dataset`: the on-disk layout of a split (raw u8 arrays + a CSV of labels).

pub mod dataset;
pub mod roi;
