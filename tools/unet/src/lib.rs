//! UNet localizer tooling shared by its binaries: importing a lab's own labelled frames.
#[cfg(feature = "labelme")]
pub mod labelme;
