//! UNet localizer tooling shared by its binaries: importing a lab's own labelled frames.
pub mod labelme;
