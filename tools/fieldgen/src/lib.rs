//! Library behind `fieldgen`: each subcommand's logic lives in its own module.
pub mod cfd;
pub mod coils;
pub mod fit_coils;
pub mod import;
pub mod import_coils;
pub mod lbm;
pub mod rig_check;
pub mod validate;
