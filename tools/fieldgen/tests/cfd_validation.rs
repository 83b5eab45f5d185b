//! Solver validation (run with `cargo test --release -p fieldgen -- --nocapture` to see the
//! numbers) and an end-to-end phantom solve from a mask PNG.

use std::path::{Path, PathBuf};

use fieldgen::cfd::{
    rig_ports, solve, CfdError, CfdSettings, Condition, Port, CHAMBER_CLEARANCE_M,
};
use fieldgen::validate;
use fieldmaps::mask::CanalMask;
use fieldmaps::phantom::Phantom;
use fieldmaps::rigfile::Rig;

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

fn rig_file(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../../fieldmaps/rigs/{name}.toml"))
}

/// The rig's ports, as `fieldgen cfd --rig` builds them.
fn ports_of(rig: &Rig) -> Vec<Port> {
    rig_ports(&rig.path, &rig.phantom.inlets, &rig.phantom.outlets)
}

fn coarse(dx_m: f64) -> CfdSettings {
    CfdSettings {
        dx_m,
        out_spacing_m: 1e-3,
        tolerance: 1e-6,
        ..CfdSettings::default()
    }
}

#[test]
fn phantom_from_mask_png_conserves_mass() {
    let rig = Rig::load(&rig_file("paper")).unwrap();
    let g = *rig.phantom.mask.geometry();
    let path = tmp("mask.png");
    rig.phantom.mask.save_png(&path).unwrap();
    let mask = CanalMask::load_png(&path, &g).unwrap();
    std::fs::remove_file(&path).ok();
    let cond = Condition::new(180.0, 20.0);
    let (map, stats) = solve(
        &mask,
        &ports_of(&rig),
        &rig.phantom.zones,
        &cond,
        &coarse(0.6e-3),
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

/// The paper's canal with inlet 2's tube cut short of the image edge (first 20 columns walled).
fn paper_with_inlet2_closed(rig: &Rig) -> CanalMask {
    let g = *rig.phantom.mask.geometry();
    let mut px: Vec<bool> = rig.phantom.mask.canal_flags().to_vec();
    for r in 0..g.height_px as usize {
        for c in 0..20 {
            px[r * g.width_px as usize + c] = false;
        }
    }
    CanalMask::from_pixels(g, px).unwrap()
}

#[test]
fn port_inside_the_view_opens_where_its_tube_ends() {
    // Inlet 2's tube now ends in the view: its inflow enters there, not at the image edge.
    let rig = Rig::load(&rig_file("paper")).unwrap();
    let mask = paper_with_inlet2_closed(&rig);
    let (map, stats) = solve(
        &mask,
        &ports_of(&rig),
        &rig.phantom.zones,
        &Condition::new(180.0, 20.0),
        &coarse(0.6e-3),
        |_, _| {},
    )
    .unwrap();
    println!("{}", stats.summary());
    assert!(stats.convergence.converged);
    assert!(stats.mass_imbalance() < 1e-2, "{}", stats.mass_imbalance());
    // The shortened tube still delivers its jet into the atrium (+x past the mouth; the tube
    // itself is written as zero).
    let jet = map.sample(&nalgebra::Vector2::new(-0.0245, -0.001));
    assert!(jet.x > 1e-3, "{jet:?}");
}

#[test]
fn vessel8_branch_outlet_on_its_end_cap() {
    // The second rig: one inlet on the left edge, the main outlet on the right edge and the
    // branch outlet on a cap inside the view.
    let rig = Rig::load(&rig_file("vessel8")).unwrap();
    let (map, stats) = solve(
        &rig.phantom.mask,
        &ports_of(&rig),
        &rig.phantom.zones,
        &Condition::new(120.0, 4.3),
        &coarse(0.5e-3),
        |_, _| {},
    )
    .unwrap();
    println!("{}", stats.summary());
    assert!(stats.convergence.converged);
    assert!(stats.mass_imbalance() < 1e-2, "{}", stats.mass_imbalance());
    // Both outlets take flow: down the branch's end stretch, right along the main vessel.
    let branch = map.sample(&nalgebra::Vector2::new(0.025, -0.026));
    assert!(branch.y < -1e-3, "{branch:?}");
    let main = map.sample(&nalgebra::Vector2::new(0.040, 0.0165));
    assert!(main.x > 1e-3, "{main:?}");
}

#[test]
fn port_errors_name_the_rig_file_and_field() {
    let rig = Rig::load(&rig_file("paper")).unwrap();
    let settings = coarse(1e-3);
    let cond = Condition::new(180.0, 20.0);
    let run = |mask: &CanalMask, ports: &[Port]| {
        solve(mask, ports, &rig.phantom.zones, &cond, &settings, |_, _| {}).unwrap_err()
    };
    let file = rig.path.display().to_string();

    // A mouth in the wall.
    let mut ports = ports_of(&rig);
    ports[1].mouth_m = nalgebra::Vector2::new(0.040, -0.040);
    let err = run(&rig.phantom.mask, &ports).to_string();
    assert!(
        err.starts_with(&format!("{file}: phantom.inlets[1].position_mm:")),
        "{err}"
    );

    // A direction pointing into the chamber: the walk crosses open canal.
    let mut ports = ports_of(&rig);
    ports[0].outward = -ports[0].outward;
    let err = run(&rig.phantom.mask, &ports).to_string();
    assert!(
        err.starts_with(&format!("{file}: phantom.inlets[0].direction:")),
        "{err}"
    );

    // Too oblique for an opening cut square to the lattice.
    let mut ports = ports_of(&rig);
    ports[2].outward = nalgebra::Vector2::new(1.0, 1.0).normalize();
    let err = run(&rig.phantom.mask, &ports).to_string();
    assert!(
        err.starts_with(&format!("{file}: phantom.outlets[0].direction:")),
        "{err}"
    );

    // Canal that leaves the view with no port there.
    let ports: Vec<Port> = ports_of(&rig)
        .into_iter()
        .filter(|p| p.name != "inlet-2")
        .collect();
    let err = run(&rig.phantom.mask, &ports);
    assert!(matches!(err, CfdError::UnmatchedOpening { .. }), "{err}");
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
    // The committed maps were solved on the parametric phantom (their `domain` header), which
    // the paper rig's mask rasterises.
    let mask = CanalMask::from_phantom(
        &Phantom::load(&fieldmaps::data_root().join("fieldmaps/rigs/paper/heart_phantom.toml"))
            .unwrap(),
        &fieldmaps::rigfile::Rig::load_paper()
            .unwrap()
            .camera
            .geometry,
    )
    .unwrap();
    assert_eq!(
        mask.canal_flags(),
        Rig::load(&rig_file("paper"))
            .unwrap()
            .phantom
            .mask
            .canal_flags()
    );
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
