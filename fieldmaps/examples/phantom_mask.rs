//! Writes the default phantom's canal mask as a PGM image: `cargo run --example phantom_mask -- out.pgm`.
use fieldmaps::phantom::{rasterize, ImageGeometry, Phantom};

fn main() -> std::io::Result<()> {
    let out = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "phantom_mask.pgm".into());
    let geometry = ImageGeometry::default();
    let mask = rasterize(&Phantom::default_heart(), &geometry);
    let mut bytes = format!("P5\n{} {}\n255\n", geometry.width_px, geometry.height_px).into_bytes();
    bytes.extend_from_slice(&mask);
    std::fs::write(out, bytes)
}
