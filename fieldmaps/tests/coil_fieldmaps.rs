//! Validation of the committed coil field maps (fieldmaps/coils/) and of the map loader's
//! error reporting on corrupted files.

use std::path::{Path, PathBuf};

use fieldmaps::allocation::{actuation_matrix, actuation_matrix_from, allocate_pinv};
use fieldmaps::coils::{CoilField, CoilSystem};
use fieldmaps::fieldmap::{
    CoilFieldMaps, CoilInfo, FieldMapError, GridSpec, Interpolation, MANIFEST_FILE,
};
use fieldmaps::physics::in_plane_moment;
use nalgebra::{DVector, Matrix3, Vector3};

/// Deterministic points in [-1, 1).
struct SeededRng(rand_chacha::ChaCha8Rng);
impl SeededRng {
    fn seeded(seed: u64) -> Self {
        Self(rand::SeedableRng::seed_from_u64(seed))
    }
    fn next(&mut self) -> f64 {
        rand::Rng::random_range(&mut self.0, -1.0..1.0)
    }
    fn point_in(&mut self, g: &GridSpec) -> Vector3<f64> {
        let max = g.max_m();
        Vector3::from_fn(|k, _| {
            let u = 0.5 * (self.next() + 1.0);
            g.origin_m[k] + u * (max[k] - g.origin_m[k])
        })
    }
}

fn committed() -> CoilFieldMaps {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("coils");
    CoilFieldMaps::load(&dir).unwrap_or_else(|e| {
        panic!("committed maps missing or bad ({e}); regenerate with `millinav maps coils --rig fieldmaps/rigs/paper.toml`")
    })
}

/// The paper rig's coils, from its rig file (the model the committed maps sample).
fn paper_coils() -> CoilSystem {
    let rig = fieldmaps::rigfile::Rig::load(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("rigs/paper.toml"),
    )
    .unwrap();
    rig.winding_model().unwrap()
}

#[test]
fn committed_maps_match_the_rig() {
    let maps = committed();
    let sys = paper_coils();
    assert_eq!(maps.coil_count(), sys.len());
    for (info, coil) in maps.coils().iter().zip(&sys.coils) {
        assert_eq!(info.name, coil.name);
        let turns = info.total_turns.unwrap();
        assert!(
            (turns / coil.total_turns() - 1.0).abs() < 1e-12,
            "{}",
            info.name
        );
    }
    // Covers the whole control-plane workspace square and some height around it.
    let g = maps.grid();
    assert!(g.covers(
        &Vector3::new(-0.05, -0.05, -0.005),
        &Vector3::new(0.05, 0.05, 0.005)
    ));
}

/// Stated bound (README): inside the grid box (|x|,|y| ≤ 50 mm, |z| ≤ 8 mm, 2 mm spacing), the
/// default interpolation is within 3e-4 (field) and 3e-3 (gradient) relative error of the direct
/// model for every coil; measured 1.3e-4 and 1.4e-3. Plain trilinear: 6e-3 / 1e-2.
#[test]
fn interpolation_error_is_bounded() {
    let sys = paper_coils();
    let mut maps = committed();
    for (scheme, bound_b, bound_g) in [
        (Interpolation::Quadratic, 3e-4, 3e-3),
        (Interpolation::Trilinear, 6e-3, 1e-2),
    ] {
        maps.set_interpolation(scheme);
        let mut rng = SeededRng::seeded(11);
        let (mut eb, mut eg) = (0.0f64, 0.0f64);
        for _ in 0..1500 {
            let p = rng.point_in(maps.grid());
            for c in 0..sys.len() {
                let (bd, gd) = sys.field_and_gradient_per_amp(c, &p);
                let (bi, gi) = maps.try_field_and_gradient_per_amp(c, &p).unwrap();
                eb = eb.max((bi - bd).norm() / bd.norm());
                eg = eg.max((gi - gd).norm() / gd.norm());
            }
        }
        println!("{scheme:?}: max relative error field {eb:.3e}, gradient {eg:.3e}");
        assert!(eb < bound_b && eg < bound_g, "{scheme:?}: {eb} {eg}");
    }
}

/// The interpolated gradient is symmetric and traceless to float32 rounding (1e-6 relative),
/// and central differences (h = 0.25 mm) of the interpolated field have divergence and curl
/// below 5e-3 of ‖∇B‖ and agree with the interpolated gradient to 5e-3 (measured: 2.9e-3,
/// 3.6e-3, 2.6e-3; the interpolant is continuous but its derivative jumps slightly at cell
/// faces).
#[test]
fn interpolated_field_is_divergence_and_curl_free() {
    let maps = committed();
    let mut rng = SeededRng::seeded(5);
    let h = 2.5e-4;
    let (mut worst_sym, mut worst_div, mut worst_curl, mut worst_fd) =
        (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for _ in 0..400 {
        let mut p = rng.point_in(maps.grid());
        // Keep the difference stencil inside the box.
        let max = maps.grid().max_m();
        for k in 0..3 {
            p[k] = p[k].clamp(maps.grid().origin_m[k] + h, max[k] - h);
        }
        for c in 0..maps.coil_count() {
            let (_, g) = maps.field_and_gradient_per_amp(c, &p);
            let n = g.norm();
            worst_sym = worst_sym
                .max(g.trace().abs() / n)
                .max((g - g.transpose()).norm() / n);
            let mut fd = Matrix3::zeros();
            for j in 0..3 {
                let mut e = Vector3::zeros();
                e[j] = h;
                let d =
                    (maps.field_per_amp(c, &(p + e)) - maps.field_per_amp(c, &(p - e))) / (2.0 * h);
                fd.set_column(j, &d);
            }
            worst_div = worst_div.max(fd.trace().abs() / n);
            worst_curl = worst_curl.max((fd - fd.transpose()).norm() / n);
            worst_fd = worst_fd.max((fd - g).norm() / n);
        }
    }
    println!(
        "interpolated ∇B: asymmetry/trace {worst_sym:.2e}; FD of interpolated B: div {worst_div:.2e}, \
         curl {worst_curl:.2e}, vs interpolated ∇B {worst_fd:.2e} (relative to ‖∇B‖)"
    );
    assert!(worst_sym < 1e-6, "{worst_sym}");
    assert!(worst_div < 5e-3, "{worst_div}");
    assert!(worst_curl < 5e-3, "{worst_curl}");
    assert!(worst_fd < 5e-3, "{worst_fd}");
}

#[test]
fn maps_drive_the_same_allocation_as_the_direct_model() {
    let sys = paper_coils();
    let maps = committed();
    let p = Vector3::new(0.012, -0.021, 0.0);
    let m = in_plane_moment(8.6e-4, 0.7);
    let ids: Vec<usize> = (0..sys.len()).collect();
    let a_direct = actuation_matrix(&sys, &p, &m, &ids, 0.1);
    let a_maps = actuation_matrix_from(&maps, &p, &m, &ids, 0.1);
    assert!((&a_maps - &a_direct).norm() < 2e-3 * a_direct.norm());
    let c = DVector::from_vec(vec![2e-5, -1e-5, 1e-4, 5e-5]);
    let i_direct = allocate_pinv(&a_direct, &c).unwrap();
    let i_maps = allocate_pinv(&a_maps, &c).unwrap();
    assert!((&i_maps - &i_direct).norm() < 1e-2 * i_direct.norm());
    // A trait object works as a drop-in too.
    let dynamic: &dyn CoilField = &maps;
    let (b, _) = dynamic.field_and_gradient(&vec![1.0; sys.len()], &p);
    assert!(b.iter().all(|v| v.is_finite()));
}

#[test]
fn out_of_grid_and_bad_queries() {
    let maps = committed();
    let outside = Vector3::new(0.0, 0.08, 0.0);
    assert!(matches!(
        maps.try_field_and_gradient_per_amp(0, &outside),
        Err(FieldMapError::OutOfGrid { .. })
    ));
    assert!(matches!(
        maps.try_field_and_gradient_per_amp(12, &Vector3::zeros()),
        Err(FieldMapError::BadIndex {
            index: 12,
            count: 12
        })
    ));
    // Infallible trait queries: clamped to the box, zeros for unknown coils, no panic on NaN.
    let edge = Vector3::new(0.0, 0.05, 0.0);
    assert_eq!(
        maps.field_and_gradient_per_amp(0, &outside),
        maps.field_and_gradient_per_amp(0, &edge)
    );
    assert_eq!(maps.field_per_amp(99, &edge), Vector3::zeros());
    let (b, g) = maps.field_and_gradient_per_amp(0, &Vector3::new(f64::NAN, 0.0, 0.0));
    assert!(b.iter().chain(g.iter()).all(|v| v.is_finite()));
}

// ---- corrupted files -------------------------------------------------------------------------

/// A small map set (2×… grid, 12 coils) written to a fresh temporary directory.
fn small_maps(tag: &str) -> (PathBuf, CoilFieldMaps) {
    let dir = std::env::temp_dir().join(format!(
        "millinav-fieldmap-test-{}-{tag}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    let sys = paper_coils();
    let grid = GridSpec::centered([0.01, 0.01, 0.004], 0.005).unwrap();
    let infos = sys
        .coils
        .iter()
        .map(|c| CoilInfo {
            name: c.name.clone(),
            ..Default::default()
        })
        .collect();
    let maps = CoilFieldMaps::sample(&sys, infos, grid).unwrap();
    maps.write(&dir, "test", "test", None).unwrap();
    (dir, maps)
}

fn load_err(dir: &Path) -> String {
    match CoilFieldMaps::load(dir) {
        Ok(_) => panic!("corrupted maps in {} loaded", dir.display()),
        Err(e) => e.to_string(),
    }
}

fn edit(path: &Path, f: impl FnOnce(&mut Vec<u8>)) {
    let mut bytes = std::fs::read(path).unwrap();
    f(&mut bytes);
    std::fs::write(path, bytes).unwrap();
}

fn replace_text(path: &Path, from: &str, to: &str) {
    let text = std::fs::read_to_string(path).unwrap();
    assert!(text.contains(from), "{from:?} not in {}", path.display());
    std::fs::write(path, text.replacen(from, to, 1)).unwrap();
}

#[test]
fn round_trip() {
    let (dir, maps) = small_maps("roundtrip");
    let back = CoilFieldMaps::load(&dir).unwrap();
    assert_eq!(back, maps);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn corrupted_files_give_clear_errors() {
    type Corruption = (&'static str, fn(&Path), &'static str, &'static str);
    let cases: [Corruption; 12] = [
        (
            "truncated",
            |d| edit(&d.join("N_mid.npy"), |b| b.truncate(b.len() - 100)),
            "N_mid.npy",
            "truncated",
        ),
        (
            "header-cut",
            |d| edit(&d.join("S_small.npy"), |b| b.truncate(40)),
            "S_small.npy",
            "truncated",
        ),
        (
            "extra",
            |d| edit(&d.join("E_large.npy"), |b| b.extend_from_slice(&[0; 8])),
            "E_large.npy",
            "mislabelled",
        ),
        (
            "dtype",
            |d| {
                edit(&d.join("W_small.npy"), |b| {
                    let at = b.windows(3).position(|w| w == b"<f4").unwrap();
                    b[at + 2] = b'8';
                })
            },
            "W_small.npy",
            "dtype",
        ),
        (
            "magic",
            |d| edit(&d.join("N_small.npy"), |b| b[1] = b'X'),
            "N_small.npy",
            "not a NumPy",
        ),
        (
            "nan",
            |d| {
                edit(&d.join("N_large.npy"), |b| {
                    let end = b.len();
                    b[end - 4..].copy_from_slice(&f32::NAN.to_le_bytes());
                })
            },
            "N_large.npy",
            "non-finite value NaN at node (ix=4, iy=4, iz=2), component dBz/dz",
        ),
        (
            "bitflip",
            |d| {
                edit(&d.join("S_mid.npy"), |b| {
                    let end = b.len();
                    b[end - 1] ^= 0x01;
                })
            },
            "S_mid.npy",
            "checksum mismatch",
        ),
        (
            "format",
            |d| {
                replace_text(
                    &d.join(MANIFEST_FILE),
                    "millinav-coil-fieldmap",
                    "something-else",
                )
            },
            MANIFEST_FILE,
            "mislabelled: format",
        ),
        (
            "units",
            |d| {
                replace_text(
                    &d.join(MANIFEST_FILE),
                    "field = \"T/A\"",
                    "field = \"mT/A\"",
                )
            },
            MANIFEST_FILE,
            "units",
        ),
        (
            "grid",
            |d| {
                replace_text(
                    &d.join(MANIFEST_FILE),
                    "shape = [5, 5, 3]",
                    "shape = [5, 6, 3]",
                )
            },
            "N_small.npy",
            "wrong grid",
        ),
        (
            "missing",
            |d| std::fs::remove_file(d.join("W_mid.npy")).unwrap(),
            "W_mid.npy",
            "cannot read",
        ),
        (
            "toml",
            |d| replace_text(&d.join(MANIFEST_FILE), "[grid]", "[grid"),
            MANIFEST_FILE,
            "not a valid manifest",
        ),
    ];
    for (tag, corrupt, file, what) in cases {
        let (dir, _) = small_maps(tag);
        corrupt(&dir);
        let msg = load_err(&dir);
        println!("{tag}: {msg}");
        assert!(msg.contains(file), "{tag}: {msg:?} should name {file}");
        assert!(msg.contains(what), "{tag}: {msg:?} should say {what:?}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
    // A directory without maps.
    let msg = load_err(Path::new("/nonexistent/millinav"));
    assert!(
        msg.contains("coils.toml") && msg.contains("cannot read"),
        "{msg}"
    );
}

#[test]
fn invalid_grids_and_parts_are_rejected() {
    assert!(GridSpec::centered([0.05, 0.05, 0.0], 0.002).is_err());
    assert!(GridSpec::centered([0.05, 0.05, 0.01], f64::NAN).is_err());
    let g = GridSpec::centered([0.01, 0.01, 0.01], 0.005).unwrap();
    assert_eq!(g.shape, [5, 5, 5]);
    let info = vec![CoilInfo {
        name: "a".into(),
        ..Default::default()
    }];
    assert!(CoilFieldMaps::from_parts(g, info.clone(), vec![vec![0.0; 3]]).is_err());
    let mut bad = vec![0.0f32; g.node_count() * 12];
    bad[7] = f32::INFINITY;
    assert!(CoilFieldMaps::from_parts(g, info.clone(), vec![bad]).is_err());
    let two = vec![info[0].clone(), info[0].clone()];
    let zeros = vec![0.0f32; g.node_count() * 12];
    assert!(CoilFieldMaps::from_parts(g, two, vec![zeros.clone(), zeros]).is_err());
}

#[test]
fn data_root_is_found_from_the_working_directory() {
    // Tests run inside the checkout, so the lookup must land on this repository's data.
    let root = fieldmaps::data_root();
    assert!(
        root.join("fieldmaps/coils/coils.toml").is_file(),
        "{}",
        root.display()
    );
}
