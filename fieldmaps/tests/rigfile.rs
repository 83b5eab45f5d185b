//! The rig file: `rigs/paper.toml` must describe the paper's rig (coils and the field they were
//! solved for, allocation subset, limits, camera, phantom, zones, robot), and every kind of bad
//! input must give one error naming the file and the field.

use std::path::{Path, PathBuf};

use fieldmaps::coils::CoilField;
use fieldmaps::fieldmap::CoilFieldMaps;
use fieldmaps::mask::CanalMask;
use fieldmaps::phantom::{ImageGeometry, Phantom};
use fieldmaps::rig::CoilLimits;
use fieldmaps::rigfile::{
    CameraPixelFormat, FieldModel, Rig, RigCoilField, RigFileError, ZoneKind, MAX_COILS,
};
use nalgebra::{Vector2, Vector3};

fn paper_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("rigs/paper.toml")
}

fn paper_text() -> String {
    std::fs::read_to_string(paper_path()).unwrap()
}

/// The paper's top camera: 1020 x 1020 px over 92 x 92 mm, centred on the origin.
fn paper_view() -> ImageGeometry {
    ImageGeometry {
        width_px: 1020,
        height_px: 1020,
        mm_per_px: 92.0 / 1020.0,
        origin_x_mm: -46.0,
        origin_y_mm: 46.0,
    }
}

fn paper() -> Rig {
    Rig::load(&paper_path()).unwrap_or_else(|e| panic!("{e}"))
}

/// Points inside the workspace and the control plane, off every axis of symmetry.
fn points() -> Vec<Vector3<f64>> {
    let mut pts = vec![Vector3::zeros()];
    for &x in &[-0.041, -0.013, 0.0, 0.022, 0.045] {
        for &y in &[-0.038, -0.004, 0.017, 0.049] {
            for &z in &[0.0, 0.006] {
                pts.push(Vector3::new(x, y, z));
            }
        }
    }
    pts
}

fn assert_same_field(a: &dyn CoilField, b: &dyn CoilField, what: &str) {
    assert_eq!(a.coil_count(), b.coil_count(), "{what}");
    for p in points() {
        for coil in 0..a.coil_count() {
            let (ba, ga) = a.field_and_gradient_per_amp(coil, &p);
            let (bb, gb) = b.field_and_gradient_per_amp(coil, &p);
            assert!(bb.norm() > 0.0 && gb.norm() > 0.0);
            assert!(
                (ba - bb).norm() <= 1e-9 * bb.norm(),
                "{what}: field of coil {coil} at {p:?}: {ba:?} vs {bb:?}"
            );
            assert!(
                (ga - gb).norm() <= 1e-9 * gb.norm(),
                "{what}: gradient of coil {coil} at {p:?}"
            );
        }
    }
}

#[test]
fn paper_rig_file_has_the_papers_coils() {
    let rig = paper();
    assert_eq!(rig.name, "paper");
    assert_eq!(rig.field_model, FieldModel::Analytic);
    let RigCoilField::Analytic(system) = &rig.coil_field else {
        panic!("paper.toml should use the analytic model");
    };
    // 12 planar coils, 4 units (N, E, S, W) of 3 concentric coils, unit-major.
    let names: Vec<&str> = system.coils.iter().map(|c| c.name.as_str()).collect();
    let expected: Vec<String> = ["N", "E", "S", "W"]
        .iter()
        .flat_map(|u| ["small", "mid", "large"].map(|s| format!("{u}_{s}")))
        .collect();
    assert_eq!(names, expected);
    assert_same_field(&rig.coil_field, &rig.winding_model().unwrap(), "analytic");
    // Positive current: the field at the centre points away from the unit; 4-fold symmetry.
    let o = Vector3::zeros();
    let id = |name: &str| rig.coil_index(name).unwrap();
    let b_n = system.field_per_amp(id("N_small"), &o);
    let b_e = system.field_per_amp(id("E_large"), &o);
    let b_s = system.field_per_amp(id("S_small"), &o);
    assert!(b_n.y < 0.0 && b_n.x.abs() < 1e-15 * b_n.norm());
    assert!(b_e.x < 0.0 && b_e.y.abs() < 1e-15 * b_e.norm());
    assert!((b_s + b_n).norm() < 1e-12 * b_n.norm());
    // The paper drives 8 of the 12: the small and large coil of every unit.
    let allocation: Vec<&str> = rig
        .allocation_coils
        .iter()
        .map(|&i| rig.coils[i].name.as_str())
        .collect();
    assert_eq!(
        allocation,
        ["N_small", "N_large", "E_small", "E_large", "S_small", "S_large", "W_small", "W_large"]
    );
    // 0.36 kW per coil at 60 V: 10 ohm, 6 A; 2.16 kW in all.
    assert_eq!(
        rig.coil_limits(),
        CoilLimits {
            max_current_a: 6.0,
            max_total_power_w: 2160.0,
            coil_resistance_ohm: 10.0,
        }
    );
    for c in &rig.coils {
        assert_eq!(
            (c.resistance_ohm, c.max_current_a),
            (10.0, 6.0),
            "{}",
            c.name
        );
    }
}

#[test]
fn paper_coils_make_the_papers_fea_field_at_its_peak() {
    // The turns were solved for the paper's FEA case (24.05 mT, 13.92 mT/cm with the north
    // unit's small and large coils at 0.36 kW each): the file must still meet it.
    let rig = paper();
    let [reference] = rig.reference_fields.as_slice() else {
        panic!("paper.toml should give one reference field");
    };
    assert_eq!(
        reference.currents_a,
        [
            (rig.coil_index("N_small").unwrap(), 6.0),
            (rig.coil_index("N_large").unwrap(), 6.0)
        ]
    );
    assert!((reference.field_t - 24.05e-3).abs() < 1e-12);
    assert!((reference.gradient_t_per_m.unwrap() - 1.392).abs() < 1e-12);
    let read = reference.measure(&rig.coil_field);
    println!("paper reference field on the model: {read:?}");
    assert!(
        (read.field_t / reference.field_t - 1.0).abs() < 1e-4,
        "{read:?}"
    );
    assert!(
        (read.gradient_t_per_m / reference.gradient_t_per_m.unwrap() - 1.0).abs() < 1e-4,
        "{read:?}"
    );
    // The reference point is where |B| peaks over the control-plane workspace (1 mm grid).
    let currents = reference.currents(rig.coils.len());
    let at_point = rig
        .coil_field
        .field_and_gradient(&currents, &reference.point_m)
        .0
        .norm();
    for ix in -50..=50 {
        for iy in -50..=50 {
            let p = Vector3::new(ix as f64, iy as f64, 0.0) * 1e-3;
            let b = rig.coil_field.field_and_gradient(&currents, &p).0.norm();
            assert!(
                b <= at_point * (1.0 + 1e-9),
                "|B| {b} at {p:?} > {at_point}"
            );
        }
    }
}

#[test]
fn reference_fields_are_checked_like_every_key() {
    let text = paper_text();
    let bad = [
        (
            "coils = [\"N_small\", \"N_large\"]      # paper",
            "coils = [\"N_small\", \"nope\"]",
            "electromagnet.reference_fields[0].coils[1]",
        ),
        (
            "power_w = 360.0 ",
            "current_a = 6.0\npower_w = 360.0 ",
            "electromagnet.reference_fields[0]: give exactly one",
        ),
        (
            "field_mt = 24.05 ",
            "field_mt = -1.0 ",
            "electromagnet.reference_fields[0].field_mt",
        ),
        (
            "direction = [0.0, 1.0, 0.0] ",
            "direction = [0.0, 0.0, 0.0] ",
            "electromagnet.reference_fields[0].direction",
        ),
    ];
    for (from, to, expect) in bad {
        assert!(text.contains(from), "{from}");
        let err = Rig::parse(&text.replacen(from, to, 1), &paper_path()).unwrap_err();
        assert!(err.to_string().contains(expect), "{expect}: {err}");
    }
}

#[test]
fn paper_rig_with_maps_model_is_the_committed_maps() {
    // Parsed as if it were paper.toml itself, so the relative paths still resolve.
    let text = paper_text().replace(
        "field_model = { kind = \"analytic\" }",
        "field_model = { kind = \"maps\", dir = \"../coils\" }",
    );
    let rig = Rig::parse(&text, &paper_path()).unwrap_or_else(|e| panic!("{e}"));
    assert!(matches!(rig.field_model, FieldModel::Maps(_)));
    let maps = CoilFieldMaps::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("coils")).unwrap();
    assert_same_field(&rig.coil_field, &maps, "maps");
}

#[test]
fn paper_camera_robot_and_flow_conditions() {
    let rig = paper();
    assert_eq!(rig.camera.geometry, paper_view());
    assert_eq!(rig.camera.pixel_format, CameraPixelFormat::Rgb8);
    // The paper's capsule (RIG.md): 7.4 x 2.8 mm, 8.6e-4 A m², 50 mg, added mass 0.5 rho V.
    let r = rig.robot;
    let volume = std::f64::consts::PI * 1.4e-3_f64.powi(2) * 7.4e-3;
    for (a, b) in [
        (r.magnet_moment_am2, 8.6e-4),
        (r.mass_kg, 5.0e-5),
        (r.added_mass_kg, 0.5 * 1113.0 * volume),
        (r.length_m, 7.4e-3),
        (r.diameter_m, 2.8e-3),
    ] {
        assert!((a / b - 1.0).abs() < 1e-12, "{a} vs {b}");
    }
    let flow = &rig.phantom.flow_conditions;
    let got: Vec<(&str, f64, f64)> = flow
        .iter()
        .map(|f| (f.name.as_str(), f.flow_ml_min, f.viscosity_pa_s))
        .collect();
    assert_eq!(
        got,
        vec![
            ("q180_mu20", 180.0, 0.020),
            ("q180_mu4p3", 180.0, 0.0043),
            ("q250_mu20", 250.0, 0.020),
            ("q250_mu4p3", 250.0, 0.0043),
        ]
    );
    for f in flow {
        assert!(f.map_path.is_file(), "{}", f.map_path.display());
    }
}

#[test]
fn paper_mask_and_ports_match_the_heart_phantom_file() {
    let rig = paper();
    let heart =
        Phantom::load(&fieldmaps::data_root().join("fieldmaps/rigs/paper/heart_phantom.toml"))
            .unwrap();
    let px_m = rig.camera.geometry.mm_per_px * 1e-3;
    let (mut compared, mut canal) = (0, 0);
    // 0.37 mm steps: not commensurate with the pixels, so points fall everywhere in them.
    for i in 0..=248 {
        for j in 0..=248 {
            let p = Vector2::new(-0.0459 + i as f64 * 0.00037, -0.0459 + j as f64 * 0.00037);
            if heart.signed_distance(&p).abs() <= px_m {
                continue; // within one pixel of the wall
            }
            compared += 1;
            canal += usize::from(heart.contains(&p));
            assert_eq!(rig.phantom.contains(&p), heart.contains(&p), "{p:?}");
        }
    }
    assert!(compared > 55_000 && canal > 10_000, "{compared} {canal}");
    // The committed PNG is exactly the default phantom's raster.
    let raster = CanalMask::from_phantom(&heart, &paper_view()).unwrap();
    assert_eq!(rig.phantom.mask, raster);

    let inlets = heart.inlets();
    assert_eq!(rig.phantom.inlets.len(), inlets.len());
    for (a, b) in rig.phantom.inlets.iter().zip(&inlets) {
        assert_eq!(a.name, b.name);
        assert!((a.mouth_m - b.mouth_m).norm() < 1e-12, "{}", a.name);
        assert!((a.direction.into_inner() - b.direction.into_inner()).norm() < 1e-12);
        assert!((a.diameter_m - b.diameter_m).abs() < 1e-12);
        assert!((a.length_m - b.length_m).abs() < 1e-12);
    }
    let outlet = heart.outlet();
    let [a] = rig.phantom.outlets.as_slice() else {
        panic!("one outlet expected");
    };
    assert_eq!(a.name, outlet.name);
    assert!((a.mouth_m - outlet.mouth_m).norm() < 1e-12);
    assert!((a.direction.into_inner() - outlet.direction.into_inner()).norm() < 1e-12);
    assert!((a.diameter_m - outlet.diameter_m).abs() < 1e-12);
}

#[test]
fn paper_zones_reproduce_the_flow_service_bands() {
    // services/flow FlowConfig defaults: closed bands y × x, in mm.
    let between = |v: f64, band: [f64; 2]| v >= band[0] && v <= band[1];
    let high = |x: f64, y: f64| between(y, [-10.0, 0.0]) && between(x, [-46.0, 20.0]);
    let recirc = |x: f64, y: f64| between(y, [-5.0, 10.0]) && between(x, [-46.0, 20.0]);
    let rig = paper();
    let (mut in_high, mut in_recirc) = (0, 0);
    // 0.5 mm steps hit every band edge exactly.
    for i in 0..=184 {
        for j in 0..=184 {
            let (x, y) = (-46.0 + 0.5 * i as f64, -46.0 + 0.5 * j as f64);
            let p = Vector2::new(x / 1e3, y / 1e3);
            let h = rig.phantom.in_zone(ZoneKind::HighDisturbance, &p);
            let r = rig.phantom.in_zone(ZoneKind::Recirculation, &p);
            assert_eq!(h, high(x, y), "high disturbance at ({x}, {y}) mm");
            assert_eq!(r, recirc(x, y), "recirculation at ({x}, {y}) mm");
            in_high += usize::from(h);
            in_recirc += usize::from(r);
        }
    }
    assert_eq!(in_high, 133 * 21);
    assert_eq!(in_recirc, 133 * 31);
    let names: Vec<&str> = rig
        .phantom
        .zones_at(Vector2::new(-0.010, -0.002))
        .map(|z| z.name.as_str())
        .collect();
    assert_eq!(names, ["inlet-convergence", "lower-atrium"]);
}

#[test]
fn every_paper_value_says_where_it_comes_from() {
    let text = paper_text();
    let mut previous = "";
    for (n, line) in text.lines().enumerate() {
        let code = line.split('#').next().unwrap().trim();
        let is_value = code.contains('=') && !code.starts_with('[');
        let commented = line.contains('#') || previous.trim_start().starts_with('#');
        assert!(!is_value || commented, "paper.toml line {}: {line}", n + 1);
        previous = line;
    }
}

#[test]
fn summary_names_the_parts() {
    let s = paper().summary();
    for needle in [
        "coils: 12",
        "analytic",
        "allocation: 8 coils",
        "1020x1020 px",
        "inlet-2",
        "pulmonary-trunk",
        "inlet-convergence",
        "flow conditions: 4",
    ] {
        assert!(s.contains(needle), "{needle} missing from\n{s}");
    }
}

// ---------------------------------------------------------------------------------------------
// Bad rig files: each written into a temp dir, each gives one error naming file and field.

struct TempDir(PathBuf);

impl TempDir {
    fn new(tag: &str) -> Self {
        let dir =
            std::env::temp_dir().join(format!("millinav-rigfile-{}-{tag}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        Self(dir)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        std::fs::remove_dir_all(&self.0).ok();
    }
}

/// paper.toml with its data paths made absolute, so it can be written anywhere.
fn portable_paper_text() -> String {
    let rigs = Path::new(env!("CARGO_MANIFEST_DIR")).join("rigs");
    paper_text()
        .replace(
            "\"paper/heart_mask.png\"",
            &format!("{:?}", rigs.join("paper/heart_mask.png")),
        )
        .replace(
            "\"../flow/",
            &format!("\"{}/", rigs.join("../flow").display()),
        )
        .replace(
            "dir = \"../coils\"",
            &format!("dir = \"{}\"", rigs.join("../coils").display()),
        )
}

fn replace_once(text: &str, from: &str, to: &str) -> String {
    assert!(text.contains(from), "{from:?} not in the rig text");
    text.replacen(from, to, 1)
}

/// Writes `text` as a rig file in a fresh temp dir, loads it and returns the error.
fn load_err(tag: &str, text: &str) -> (RigFileError, PathBuf, TempDir) {
    let dir = TempDir::new(tag);
    let path = dir.0.join(format!("{tag}.toml"));
    std::fs::write(&path, text).unwrap();
    let err = Rig::load(&path).expect_err(tag);
    (err, path, dir)
}

/// The error names the file and `field`, and its message contains `says`.
fn expect_err(tag: &str, text: &str, field: &str, says: &str) {
    let (err, path, _dir) = load_err(tag, text);
    let shown = err.to_string();
    assert!(
        shown.starts_with(&format!("{}: {field}: ", path.display())),
        "{tag}: expected field {field}, got: {shown}"
    );
    assert_eq!(err.field(), Some(field), "{shown}");
    assert!(shown.contains(says), "{tag}: expected {says:?} in: {shown}");
}

#[test]
fn portable_copy_loads_from_a_temp_dir() {
    let dir = TempDir::new("portable");
    let path = dir.0.join("copy.toml");
    std::fs::write(&path, portable_paper_text()).unwrap();
    let rig = Rig::load(&path).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(rig.coils.len(), 12);
    assert_eq!(rig.path, path);
}

#[test]
fn unknown_keys_are_rejected_with_their_path() {
    let base = portable_paper_text();
    let t = replace_once(&base, "[camera]\n", "[camera]\ncolour = \"red\"\n");
    expect_err(
        "unknown-camera",
        &t,
        "camera.colour",
        "unknown field `colour`",
    );
    // In the third coil's table.
    let third = base.match_indices("[[coils]]\n").nth(2).unwrap().0 + "[[coils]]\n".len();
    let t = format!("{}wire_gauge = 18\n{}", &base[..third], &base[third..]);
    expect_err("unknown-coil", &t, "coils[2].wire_gauge", "unknown field");
    let t = replace_once(
        &base,
        "length_mm = 20.0 ",
        "length_mm = 20.0\ndepth_mm = 1 ",
    );
    expect_err(
        "unknown-winding",
        &t,
        "coils[0].winding.depth_mm",
        "unknown field",
    );
    let t = format!("colour = 1\n{base}");
    expect_err("unknown-top", &t, "colour", "unknown field");
}

#[test]
fn coil_count_limits() {
    // The twin's grid maps hold the paper's 12 coils; extra coils need the analytic model.
    let base = portable_paper_text().replace("twin_field_model = ", "# twin_field_model = ");
    let first = base.find("[[coils]]").unwrap();
    let end = base.find("[[coils]]\nname = \"N_mid\"").unwrap();
    let block = &base[first..end];
    let with_extra = |n: usize| {
        let extra: String = (0..n)
            .map(|k| block.replace("\"N_small\"", &format!("\"extra_{k}\"")))
            .collect();
        let at = base.find("[camera]").unwrap();
        format!("{}{extra}{}", &base[..at], &base[at..])
    };
    // Exactly the maximum loads.
    let dir = TempDir::new("sixteen");
    let path = dir.0.join("sixteen.toml");
    std::fs::write(&path, with_extra(MAX_COILS - 12)).unwrap();
    let rig = Rig::load(&path).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(rig.coils.len(), MAX_COILS);
    assert_eq!(MAX_COILS, 16);
    // One more does not.
    expect_err(
        "seventeen",
        &with_extra(MAX_COILS - 11),
        "coils",
        "17 coils, at most 16",
    );
    // None at all.
    let last = base.find("[camera]").unwrap();
    let no_coils = format!("{}{}", &base[..first], &base[last..]);
    expect_err("no-coils", &no_coils, "coils", "at least one coil");
}

#[test]
fn bad_coil_values() {
    let base = portable_paper_text();
    let t = replace_once(&base, "turns = 214.578", "turns = 0.0");
    expect_err("zero-turns", &t, "coils[0].turns", "must be > 0");
    let t = replace_once(
        &base,
        "center_mm = [0.0, 70.0, 0.0]",
        "center_mm = [0.0, nan, 0.0]",
    );
    expect_err("nan-centre", &t, "coils[0].center_mm", "must be finite");
    let t = replace_once(
        &base,
        "center_mm = [0.0, -70.0, 0.0]",
        "center_mm = [inf, -70.0, 0.0]",
    );
    expect_err("inf-centre", &t, "coils[6].center_mm", "must be finite");
    let t = replace_once(&base, "axis = [0.0, -1.0, 0.0]", "axis = [0.0, 0.0, 0.0]");
    expect_err("zero-axis", &t, "coils[0].axis", "non-zero");
    let t = replace_once(&base, "max_current_a = 6.0", "max_current_a = 0.0");
    expect_err("zero-current", &t, "coils[0].max_current_a", "> 0");
    let t = replace_once(&base, "resistance_ohm = 10.0", "resistance_ohm = -10.0");
    expect_err("negative-resistance", &t, "coils[0].resistance_ohm", "> 0");
    let t = replace_once(
        &base,
        "max_total_power_w = 2160.0",
        "max_total_power_w = 0.0",
    );
    expect_err("zero-power", &t, "electromagnet.max_total_power_w", "> 0");
    let t = replace_once(&base, "outer_radius_mm = 24.0", "outer_radius_mm = 5.0");
    expect_err(
        "inverted-winding",
        &t,
        "coils[0].winding.outer_radius_mm",
        "must exceed",
    );
    let t = replace_once(&base, "name = \"N_mid\"", "name = \"N_small\"");
    expect_err("duplicate-name", &t, "coils[1].name", "duplicate");
    let t = replace_once(&base, "turns = 214.578 ", "#");
    expect_err(
        "no-turns",
        &t,
        "coils[0].turns",
        "required by the analytic field model",
    );
    // Saturation curves: loaded when sound, refused when the field would fall with current.
    let sat =
        "max_current_a = 6.0                 # derived: I = V/R = 60 V / 10 Ω = sqrt(360 W / 10 Ω)
";
    let t = replace_once(
        &base,
        sat,
        "max_current_a = 6.0
saturation = [[2.0, 1.0], [6.0, 0.8]]
",
    );
    let dir = TempDir::new("saturation");
    let path = dir.0.join("sat.toml");
    std::fs::write(&path, &t).unwrap();
    let rig = Rig::load(&path).unwrap_or_else(|e| panic!("{e}"));
    let curve = rig.coils[0].saturation.as_ref().expect("coil 0 saturates");
    assert!((curve.gain(6.0) - 0.8).abs() < 1e-12);
    assert!(rig.coils[1].saturation.is_none());
    let t = replace_once(
        &base,
        sat,
        "max_current_a = 6.0
saturation = [[1.0, 1.0], [2.0, 0.3]]
",
    );
    expect_err("falling-field", &t, "coils[0].saturation", "must grow");
    let t = replace_once(
        &base,
        sat,
        "max_current_a = 6.0
saturation = [[3.0, 1.0], [2.0, 0.9]]
",
    );
    expect_err("unsorted-saturation", &t, "coils[0].saturation", "ascend");
}

#[test]
fn bad_electromagnet_values() {
    let base = portable_paper_text();
    let t = replace_once(
        &base,
        "[\"N_small\", \"N_large\"",
        "[\"N_small\", \"X_huge\"",
    );
    expect_err(
        "allocation",
        &t,
        "electromagnet.allocation_coils[1]",
        "no coil named \"X_huge\"",
    );
    let analytic = "field_model = { kind = \"analytic\" }";
    let t = replace_once(&base, analytic, "field_model = { kind = \"fem\" }");
    expect_err(
        "model",
        &t,
        "electromagnet.field_model.kind",
        "must be \"analytic\" or \"maps\", got \"fem\"",
    );
    // The retired string form says what to write instead.
    let t = replace_once(&base, analytic, "field_model = \"maps:../coils\"");
    expect_err(
        "model-string",
        &t,
        "electromagnet.field_model",
        "is a table now, not the string \"maps:../coils\"",
    );
    let t = replace_once(&base, analytic, "field_model = { kind = \"maps\" }");
    expect_err(
        "maps-without-dir",
        &t,
        "electromagnet.field_model.dir",
        "required by kind = \"maps\"",
    );
    let t = replace_once(
        &base,
        analytic,
        "field_model = { kind = \"analytic\", calibrate = \"x.toml\" }",
    );
    expect_err(
        "model-typo",
        &t,
        "electromagnet.field_model",
        "unknown field `calibrate`",
    );
    let t = replace_once(
        &base,
        analytic,
        "field_model = { kind = \"maps\", dir = \"no/such/dir\" }",
    );
    expect_err(
        "missing-maps",
        &t,
        "electromagnet.field_model",
        "cannot read",
    );
    // Maps whose coils are listed in another order than the rig's.
    let coils_dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("coils");
    let t = replace_once(
        &base,
        analytic,
        &format!(
            "field_model = {{ kind = \"maps\", dir = \"{}\" }}",
            coils_dir.display()
        ),
    );
    let t = replace_once(&t, "name = \"N_small\"", "name = \"Tmp\"");
    let t = replace_once(&t, "name = \"N_mid\"", "name = \"N_small\"");
    let t = replace_once(&t, "name = \"Tmp\"", "name = \"N_mid\"");
    expect_err(
        "maps-order",
        &t,
        "coils[0].name",
        "\"N_mid\", but the field maps",
    );
}

fn write_png(path: &Path, w: u32, h: u32, value: u8) {
    let file = std::fs::File::create(path).unwrap();
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Eight);
    let mut wr = enc.write_header().unwrap();
    wr.write_image_data(&vec![value; (w * h) as usize]).unwrap();
    wr.finish().unwrap();
}

#[test]
fn bad_masks() {
    let base = portable_paper_text();
    let mask_line = base
        .lines()
        .find(|l| l.starts_with("mask = "))
        .unwrap()
        .to_string();
    // Missing file.
    let t = replace_once(&base, &mask_line, "mask = \"missing.png\"");
    expect_err("missing-mask", &t, "phantom.mask", "cannot open mask");
    // A mask of the wrong size for the camera's field of view.
    let dir = TempDir::new("mask-files");
    let small = dir.0.join("small.png");
    write_png(&small, 64, 64, 255);
    let t = replace_once(&base, &mask_line, &format!("mask = {small:?}"));
    expect_err(
        "small-mask",
        &t,
        "phantom.mask",
        "is 64x64 px, expected 1020x1020 px",
    );
    // A mask scale that does not tile the field of view.
    let t = replace_once(
        &base,
        "mask_mm_per_px = 0.09019607843137255",
        "mask_mm_per_px = 0.07",
    );
    expect_err(
        "mask-scale",
        &t,
        "phantom.mask_mm_per_px",
        "not a whole number",
    );
    // Shifted against the camera.
    let t = replace_once(
        &base,
        "mask_origin_mm = [-46.0, 46.0]",
        "mask_origin_mm = [-40.0, 46.0]",
    );
    expect_err(
        "mask-origin",
        &t,
        "phantom.mask_origin_mm",
        "camera.origin_mm",
    );
    // Coarser mask over the same field of view is fine: 0.184 mm/px → 510 px.
    let coarse = dir.0.join("coarse.png");
    write_png(&coarse, 510, 510, 255);
    let t = replace_once(&base, &mask_line, &format!("mask = {coarse:?}"));
    let t = replace_once(
        &t,
        "mask_mm_per_px = 0.09019607843137255",
        "mask_mm_per_px = 0.1803921568627451",
    );
    let path = dir.0.join("coarse.toml");
    std::fs::write(&path, t).unwrap();
    let rig = Rig::load(&path).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(rig.phantom.mask.width(), 510);
}

#[test]
fn bad_ports_zones_and_flow() {
    let base = portable_paper_text();
    let t = replace_once(
        &base,
        "position_mm = [13.0, 37.0]",
        "position_mm = [40.0, -40.0]",
    );
    expect_err(
        "port-outside",
        &t,
        "phantom.outlets[0].position_mm",
        "not on a canal pixel",
    );
    let t = replace_once(&base, "diameter_mm = 3.0", "diameter_mm = 0.0");
    expect_err("port-diameter", &t, "phantom.inlets[0].diameter_mm", "> 0");
    let t = replace_once(&base, "direction = [1.0, 0.0]", "direction = [0.0, 0.0]");
    expect_err(
        "port-direction",
        &t,
        "phantom.inlets[1].direction",
        "non-zero",
    );

    // A zone in the agarose corner: no canal pixel inside.
    let wall = "polygon_mm = [[35.0, -45.0], [45.0, -45.0], [45.0, -35.0], [35.0, -35.0]]";
    let t = replace_once(
        &base,
        "polygon_mm = [[-46.0, -5.0], [20.0, -5.0], [20.0, 10.0], [-46.0, 10.0]]",
        wall,
    );
    expect_err(
        "zone-in-wall",
        &t,
        "phantom.zones[1].polygon_mm",
        "covers no canal pixel",
    );
    // A zone reaching far outside the view.
    let t = replace_once(
        &base,
        "[-46.0, -10.0], [20.0, -10.0]",
        "[-46.0, -10.0], [200.0, -10.0]",
    );
    expect_err("zone-far", &t, "phantom.zones[0].polygon_mm", "vertex 1");
    let t = replace_once(&base, "kind = \"recirculation\"", "kind = \"vortex\"");
    expect_err("zone-kind", &t, "phantom.zones[1].kind", "unknown variant");

    let t = replace_once(&base, "q250_mu4p3.flow.csv", "no_such_condition.flow.csv");
    expect_err(
        "missing-flow",
        &t,
        "phantom.flow[3].map",
        "cannot read flow map",
    );
    let t = replace_once(&base, "flow_ml_min = 180.0", "flow_ml_min = 200.0");
    expect_err(
        "flow-label",
        &t,
        "phantom.flow[0].flow_ml_min",
        "was made for",
    );
}

#[test]
fn bad_robot_camera_and_header() {
    let base = portable_paper_text();
    let t = replace_once(&base, "mass_kg = 5.0e-5", "mass_kg = -5.0e-5");
    expect_err("robot-mass", &t, "robot.mass_kg", "> 0");
    let t = replace_once(&base, "width_px = 1020", "width_px = 0");
    expect_err("camera-width", &t, "camera.width_px", "> 0");
    let t = replace_once(
        &base,
        "body_hsv_max = [130, 255, 255]",
        "body_hsv_max = [30, 255, 255]",
    );
    expect_err(
        "appearance-wrap",
        &t,
        "robot.appearance.body_hsv_max",
        "wraps past 180",
    );
    let t = replace_once(&base, "magnet_value_max = 70", "magnet_value_max = 300");
    expect_err(
        "appearance-range",
        &t,
        "robot.appearance.magnet_value_max",
        "0..=255",
    );
    let t = replace_once(&base, "pixel_format = \"rgb8\"", "pixel_format = \"bayer\"");
    expect_err(
        "camera-format",
        &t,
        "camera.pixel_format",
        "unknown variant",
    );
    let t = replace_once(&base, "version = 1", "version = 2");
    expect_err("version", &t, "version", "reads version 1");
    let t = replace_once(&base, "magnet_moment_am2 = 8.6e-4", "");
    expect_err(
        "robot-missing",
        &t,
        "robot",
        "missing field `magnet_moment_am2`",
    );

    let missing = Path::new("/nonexistent/rig.toml");
    let err = Rig::load(missing).unwrap_err();
    assert!(matches!(err, RigFileError::Read { .. }), "{err}");
    assert!(
        err.to_string().starts_with("/nonexistent/rig.toml: "),
        "{err}"
    );
}
