//! `fieldgen import` on small synthetic Fluent / OpenFOAM exports (tests/data/): the exported
//! field is linear, v = (0.05 + 1.0·x, −0.02 + 2.0·y) m/s with x, y in m, on ~680 jittered
//! points over ±10 mm (Fluent CSV also has a decoy plane at z = 0 with v = (−1, −1)).

use std::path::{Path, PathBuf};

use fieldgen::import::{
    import_file, parse_table, Conversion, ExportFormat, GridSpec, ImportError, LengthUnit, Method,
};
use nalgebra::Vector2;

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

fn grid() -> GridSpec {
    GridSpec {
        origin_m: Vector2::new(-0.008, -0.008),
        spacing_m: 0.001,
        nx: 17,
        ny: 17,
    }
}

fn analytic(p: &Vector2<f64>) -> Vector2<f64> {
    Vector2::new(0.05 + p.x, -0.02 + 2.0 * p.y)
}

/// Max |v − v_analytic| over the grid, m/s.
fn max_error(path: &Path, conv: &Conversion, method: Method) -> f64 {
    let g = grid();
    let (map, stats, points) =
        import_file(path, ExportFormat::Auto, conv, &g, None, method, 1.0e-3).unwrap();
    assert_eq!(stats.unfilled, 0, "{}", path.display());
    assert!(points >= 600, "{points}");
    let mut err: f64 = 0.0;
    for j in 0..g.ny {
        for i in 0..g.nx {
            let p = g.origin_m + Vector2::new(i as f64, j as f64) * g.spacing_m;
            err = err.max((map.velocity_mps[j * g.nx + i] - analytic(&p)).norm());
        }
    }
    err
}

#[test]
fn fluent_csv_on_the_control_plane() {
    let conv = Conversion {
        plane_m: Some((0.008, 0.25e-3)),
        ..Conversion::default()
    };
    let idw = max_error(&data("fluent_plane.csv"), &conv, Method::Idw);
    let nearest = max_error(&data("fluent_plane.csv"), &conv, Method::Nearest);
    println!(
        "Fluent CSV: max error IDW {:.2} mm/s, nearest {:.2} mm/s",
        idw * 1e3,
        nearest * 1e3
    );
    // Field gradient 2 /s over ≤ 1 mm: ≤ 2 mm/s.
    assert!(idw < 1.5e-3, "{idw}");
    assert!(nearest < 2.0e-3, "{nearest}");
}

#[test]
fn fluent_decoy_plane_shows_without_the_filter() {
    let conv = Conversion::default();
    let err = max_error(&data("fluent_plane.csv"), &conv, Method::Idw);
    assert!(err > 0.1, "{err}");
}

#[test]
fn fluent_ascii_in_millimetres() {
    let conv = Conversion {
        length: LengthUnit::Mm,
        ..Conversion::default()
    };
    let err = max_error(&data("fluent_ascii_mm.txt"), &conv, Method::Idw);
    println!("Fluent ASCII (mm): max error {:.2} mm/s", err * 1e3);
    assert!(err < 1.5e-3, "{err}");
}

#[test]
fn openfoam_raw_csv_and_headerless() {
    for name in [
        "openfoam_plane.raw",
        "openfoam_plane.csv",
        "openfoam_noheader.raw",
    ] {
        let err = max_error(&data(name), &Conversion::default(), Method::Idw);
        println!("{name}: max error {:.2} mm/s", err * 1e3);
        assert!(err < 1.5e-3, "{name}: {err}");
    }
}

#[test]
fn clear_errors_on_bad_exports() {
    let text = std::fs::read_to_string(data("fluent_bad_columns.csv")).unwrap();
    let err = parse_table(&text, ExportFormat::Fluent).unwrap_err();
    assert!(
        matches!(
            err,
            ImportError::MissingColumn {
                what: "x velocity",
                ..
            }
        ),
        "{err}"
    );
    let text = std::fs::read_to_string(data("fluent_bad_number.csv")).unwrap();
    let err = parse_table(&text, ExportFormat::Fluent).unwrap_err();
    assert!(matches!(err, ImportError::BadRow { line: 3, .. }), "{err}");
    assert!(matches!(
        parse_table("", ExportFormat::Auto),
        Err(ImportError::NoPoints(_))
    ));
    assert!(matches!(
        parse_table("1 2 3\n", ExportFormat::Fluent),
        Err(ImportError::NoHeader)
    ));
    // CFD-Post style names with units in brackets.
    let t = parse_table(
        "X [ m ], Y [ m ], Z [ m ], Velocity u [ m s^-1 ], Velocity v [ m s^-1 ]\n0.001, 0.002, 0, 0.1, 0.2\n",
        ExportFormat::Auto,
    )
    .unwrap();
    assert_eq!(t.position, vec![[0.001, 0.002, 0.0]]);
    assert_eq!(t.velocity, vec![[0.1, 0.2, 0.0]]);
}

#[test]
fn mask_zeroes_the_wall() {
    use fieldmaps::mask::CanalMask;
    use fieldmaps::phantom::Phantom;
    let geom = fieldmaps::rigfile::Rig::load_paper()
        .unwrap()
        .camera
        .geometry;
    let mask = CanalMask::from_phantom(
        &Phantom::load(&fieldmaps::data_root().join("fieldmaps/rigs/paper/heart_phantom.toml"))
            .unwrap(),
        &geom,
    )
    .unwrap();
    let g = GridSpec::view(&geom, 1e-3);
    let (map, stats, _) = import_file(
        &data("openfoam_plane.csv"),
        ExportFormat::Auto,
        &Conversion::default(),
        &g,
        Some(&mask),
        Method::Idw,
        1e-3,
    )
    .unwrap();
    assert!(stats.inside > 0 && stats.unfilled > 0);
    // A wall point inside the data's extent is zero; a canal point there is not.
    let wall = Vector2::new(0.009, 0.0);
    let canal = Vector2::new(-0.005, -0.0075);
    assert!(!mask.contains(&wall) && mask.contains(&canal));
    assert_eq!(map.sample(&wall), Vector2::zeros());
    assert!((map.sample(&canal) - analytic(&canal)).norm() < 2e-3);
}
