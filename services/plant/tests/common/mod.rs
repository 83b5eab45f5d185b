//! Shared helpers of the plant's integration tests.
#![allow(dead_code)]

use std::sync::OnceLock;

use fieldmaps::flowmap::FlowMap;
use fieldmaps::rig::FluidParams;
use fieldmaps::rigfile::Rig;
use millinav_plant::model::{PlantModel, PlantPhysicsConfig};
use nalgebra::Vector2;

pub const FRAME_S: f64 = 0.01;

/// The committed paper rig, the tests' fixture (loaded once).
pub fn paper() -> &'static Rig {
    static RIG: OnceLock<Rig> = OnceLock::new();
    RIG.get_or_init(|| Rig::load_paper().unwrap())
}

/// Its coil count.
pub fn coil_count() -> usize {
    paper().coils.len()
}

pub fn fluid() -> FluidParams {
    FluidParams {
        viscosity_pa_s: 0.02,
        density_kg_m3: FluidParams::GLYCERIN_WATER_DENSITY,
    }
}

/// A smooth swirl (|v| ≈ 4 mm/s at 20 mm from the origin) covering the view.
pub fn swirl_map() -> FlowMap {
    let (nx, ny, h) = (21, 21, 0.005);
    let origin = Vector2::new(-0.05, -0.05);
    let mut velocity = Vec::with_capacity(nx * ny);
    for j in 0..ny {
        for i in 0..nx {
            let p = origin + Vector2::new(i as f64, j as f64) * h;
            velocity.push(Vector2::new(-p.y, p.x) * 0.2);
        }
    }
    FlowMap {
        nx,
        ny,
        origin_m: origin,
        spacing_m: h,
        velocity_mps: velocity,
        chamber_peak_mps: None,
    }
}

pub fn model(flow: FlowMap, config: PlantPhysicsConfig, seed: u64) -> PlantModel {
    PlantModel::new(
        paper().winding_model().unwrap(),
        paper().robot,
        &fluid(),
        &paper().phantom,
        flow,
        config,
        seed,
    )
}

/// Start in the right atrium with room all around (≈ 7 mm from the wall).
pub fn ra_start() -> Vector2<f64> {
    Vector2::new(-0.016, 0.010)
}

/// `value` A in coil `coil` (modulo the rig's coil count), none in the others.
pub fn currents(value: f64, coil: usize) -> Vec<f64> {
    let mut c = vec![0.0; coil_count()];
    let n = c.len();
    c[coil % n] = value;
    c
}

/// A link that configures the board for `channels` paper-rated coils (6 A, 10 Ω) with a
/// `watchdog_ms` board watchdog and arms it.
pub fn armed_link(
    link_path: &std::path::Path,
    channels: usize,
    watchdog_ms: u16,
) -> millinav_coilbus::link::SerialLink {
    let mut link = millinav_coilbus::link::SerialLink::new(link_path.to_owned(), 115_200);
    let limits = millinav_coilbus::safety::CurrentLimits::uniform(6.0, 10.0, 2160.0);
    let config = millinav_coilbus::board_config(&limits, channels, watchdog_ms);
    link.set_board_config(config);
    link.set_arm_wanted(true);
    assert!(
        link.wait_armed(std::time::Duration::from_secs(5)),
        "the board never armed"
    );
    link
}
