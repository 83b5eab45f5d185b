//! Solver validation (run with `cargo test --release -p fieldgen -- --nocapture` to see the
//! numbers) and an end-to-end phantom solve from a mask PNG.

use fieldgen::cfd::{phantom_ports, solve, CfdError, CfdSettings, Condition, CHAMBER_CLEARANCE_M};
use fieldgen::validate;
use fieldmaps::mask::CanalMask;
use fieldmaps::phantom::{ImageGeometry, Phantom};

#[test]
fn poiseuille_profile_and_mass_conservation() {
    let r = validate::poiseuille().unwrap();
    println!("{r}");
    assert!(r.convergence.converged);
    assert!(r.error < 5e-3, "profile error {}", r.error);
    assert!(r.mass_imbalance.unwrap() < 1e-4);
}

#[test]
fn brinkman_profile_with_depth_friction() {
    let r = validate::brinkman().unwrap();
    println!("{r}");
    assert!(r.convergence.converged);
    assert!(r.error < 5e-3, "profile error {}", r.error);
    assert!(r.mass_imbalance.unwrap() < 1e-4);
}

#[test]
fn lid_driven_cavity_re100_matches_ghia() {
    let (r, rows) = validate::cavity(validate::CAVITY_CELLS).unwrap();
    println!("{r}");
    for (y, g, o) in rows {
        println!("  y {y:.4}  Ghia {g:8.5}  LBM {o:8.5}");
    }
    assert!(r.convergence.converged);
    assert!(r.error < 0.01, "max error vs Ghia {}", r.error);
}

fn tmp(name: &str) -> std::path::PathBuf {
    std::env::temp_dir().join(format!("millinav-cfd-{}-{name}", std::process::id()))
}

#[test]
fn phantom_from_mask_png_conserves_mass() {
    let g = ImageGeometry::default();
    let phantom = Phantom::default_heart();
    let path = tmp("mask.png");
    CanalMask::from_phantom(&phantom, &g)
        .unwrap()
        .save_png(&path)
        .unwrap();
    let mask = CanalMask::load_png(&path, &g).unwrap();
    std::fs::remove_file(&path).ok();
    let settings = CfdSettings {
        dx_m: 0.6e-3,
        out_spacing_m: 1e-3,
        tolerance: 1e-6,
        ..CfdSettings::default()
    };
    let cond = Condition::new(180.0, 20.0);
    let (map, stats) = solve(
        &mask,
        &phantom_ports(&phantom, &g),
        &cond,
        &settings,
        |_, _| {},
    )
    .unwrap();
    println!("{}", stats.summary());
    assert!(stats.convergence.converged);
    assert!(stats.mass_imbalance() < 1e-2, "{}", stats.mass_imbalance());
    assert!(stats.chamber_peak_mps > 0.02 && stats.chamber_peak_mps < 0.2);
    // Wall is at rest; the flow goes from the right atrium toward the valve (−y at the neck).
    assert_eq!(
        map.sample(&nalgebra::Vector2::new(0.040, -0.040)).norm(),
        0.0
    );
    let neck = map.sample(&nalgebra::Vector2::new(-0.005, -0.0075));
    assert!(neck.y < 0.0, "{neck:?}");
}

#[test]
fn mask_without_a_port_is_a_clear_error() {
    let g = ImageGeometry::default();
    let phantom = Phantom::default_heart();
    let full = CanalMask::from_phantom(&phantom, &g).unwrap();
    // Close inlet 2 (left edge at y = −1 mm) by blanking the first 20 columns.
    let mut px: Vec<bool> = full.to_bytes().iter().map(|&b| b > 0).collect();
    for r in 0..g.height_px as usize {
        for c in 0..20 {
            px[r * g.width_px as usize + c] = false;
        }
    }
    let mask = CanalMask::from_pixels(g, px).unwrap();
    let settings = CfdSettings {
        dx_m: 1e-3,
        ..CfdSettings::default()
    };
    let err = solve(
        &mask,
        &phantom_ports(&phantom, &g),
        &Condition::new(180.0, 20.0),
        &settings,
        |_, _| {},
    )
    .unwrap_err();
    assert!(
        matches!(err, CfdError::MissingPort(ref p) if p == "inlet-2"),
        "{err}"
    );
}

/// Peak speed (m/s) over the map nodes in the heart chamber: on the canal and farther than
/// `CHAMBER_CLEARANCE_M` from the wall (the tubes left out), as the paper's peak in-phantom
/// speed is meant. Computed from the velocities, not from the header the generator wrote.
fn chamber_peak_from_velocities(map: &fieldmaps::flowmap::FlowMap, mask: &CanalMask) -> f64 {
    let geometry = *mask.geometry();
    let clearance = mask.clearance_map();
    let mut peak = 0.0f64;
    for j in 0..map.ny {
        for i in 0..map.nx {
            let p = map.origin_m + nalgebra::Vector2::new(i as f64, j as f64) * map.spacing_m;
            let Some((c, r)) = geometry.pixel_of(&p) else {
                continue;
            };
            let clear = clearance[r as usize * geometry.width_px as usize + c as usize];
            if mask.contains(&p) && clear > CHAMBER_CLEARANCE_M {
                peak = peak.max(map.velocity_mps[j * map.nx + i].norm());
            }
        }
    }
    peak
}

#[test]
fn committed_flow_maps_load_with_paper_peaks() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fieldmaps/flow");
    // The committed maps were solved on the parametric phantom (their `domain` header).
    let mask =
        CanalMask::from_phantom(&Phantom::default_heart(), &ImageGeometry::default()).unwrap();
    for (name, target) in [
        ("q180_mu4p3", 0.07),
        ("q180_mu20", 0.07),
        ("q250_mu4p3", 0.10),
        ("q250_mu20", 0.10),
    ] {
        let path = dir.join(format!("{name}.flow.csv"));
        let map = fieldmaps::flowmap::FlowMap::load(&path).unwrap();
        let chamber = chamber_peak_from_velocities(&map, &mask);
        println!(
            "{name}: chamber peak {:.1} mm/s (header {:.1}), map peak {:.1} mm/s",
            chamber * 1e3,
            map.chamber_peak_mps.unwrap_or(f64::NAN) * 1e3,
            map.peak_speed() * 1e3
        );
        assert!((map.nx, map.ny) == (185, 185));
        // Within 15 % of the paper's peak in-phantom speed.
        assert!((chamber / target - 1.0).abs() < 0.15, "{name}: {chamber}");
        // The header the controller and plant read (`condition_peak_speed`) says the same.
        let header = map.chamber_peak_mps.expect("chamber_peak_mps header");
        assert!(
            (header - chamber).abs() <= 1e-4,
            "{name}: header chamber_peak_mps {header} but the velocities peak at {chamber}"
        );
    }
}
