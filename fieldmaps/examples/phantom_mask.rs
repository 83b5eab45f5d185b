//! Draws a phantom file's canal mask on a square camera view centred on the origin:
//! `cargo run -p fieldmaps --example phantom_mask -- PHANTOM.toml WIDTH_PX FIELD_MM OUT.png`
//! (8-bit grayscale PNG, white = canal) or `OUT.pgm`. The committed
//! `fieldmaps/rigs/paper/heart_mask.png` is
//! `-- fieldmaps/rigs/paper/heart_phantom.toml 1020 92 fieldmaps/rigs/paper/heart_mask.png`
//! (the paper camera: 1020 px over 92 mm).
use std::path::Path;

use fieldmaps::mask::CanalMask;
use fieldmaps::phantom::{rasterize, ImageGeometry, Phantom};

const USAGE: &str = "usage: phantom_mask PHANTOM.toml WIDTH_PX FIELD_MM OUT.png|OUT.pgm";

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [phantom, width_px, field_mm, out] = args.as_slice() else {
        return Err(USAGE.into());
    };
    let phantom = Phantom::load(Path::new(phantom))?;
    let width_px: u32 = width_px
        .parse()
        .map_err(|e| format!("WIDTH_PX: {e}; {USAGE}"))?;
    let field_mm: f64 = field_mm
        .parse()
        .map_err(|e| format!("FIELD_MM: {e}; {USAGE}"))?;
    let geometry = ImageGeometry {
        width_px,
        height_px: width_px,
        mm_per_px: field_mm / width_px as f64,
        origin_x_mm: -0.5 * field_mm,
        origin_y_mm: 0.5 * field_mm,
    };
    geometry.validate()?;
    if out.ends_with(".png") {
        let mask = CanalMask::from_phantom(&phantom, &geometry)?;
        mask.save_png(Path::new(out))?;
        return Ok(());
    }
    let mask = rasterize(&phantom, &geometry);
    let mut bytes = format!("P5\n{} {}\n255\n", geometry.width_px, geometry.height_px).into_bytes();
    bytes.extend_from_slice(&mask);
    std::fs::write(out, bytes)?;
    Ok(())
}
