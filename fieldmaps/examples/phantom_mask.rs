//! Writes the default phantom's canal mask on the paper camera's 1020 × 1020 px view:
//! `cargo run --example phantom_mask -- out.png` (8-bit grayscale PNG, white = canal; the
//! committed `fieldmaps/rigs/paper/heart_mask.png` was made this way) or `-- out.pgm`.
use fieldmaps::mask::CanalMask;
use fieldmaps::phantom::{rasterize, ImageGeometry, Phantom};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "phantom_mask.pgm".into());
    let geometry = ImageGeometry::default();
    if out.ends_with(".png") {
        let mask = CanalMask::from_phantom(&Phantom::default_heart(), &geometry)?;
        mask.save_png(std::path::Path::new(&out))?;
        return Ok(());
    }
    let mask = rasterize(&Phantom::default_heart(), &geometry);
    let mut bytes = format!("P5\n{} {}\n255\n", geometry.width_px, geometry.height_px).into_bytes();
    bytes.extend_from_slice(&mask);
    std::fs::write(out, bytes)?;
    Ok(())
}
