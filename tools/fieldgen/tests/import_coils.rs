//! `fieldgen import-coils` on synthetic lab data: exports written from the analytic model of the
//! paper's coils (COMSOL spreadsheet in mm with shuffled rows, COMSOL grid, CSV with gradient
//! columns in gauss) must import to within 1e-3 of the model; noisy data must still give smooth
//! gradients; bad files must be refused with the file, line or coil named.
use std::fmt::Write;
use std::path::{Path, PathBuf};
use std::process::Command;

use fieldmaps::coils::CoilField;
use fieldmaps::fieldmap::CoilFieldMaps;
use fieldmaps::rigfile::Rig;
use nalgebra::{Matrix3, Vector3};

struct Rng(u64);

impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("millinav-imp-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Data grid: 2.5 mm spacing over ±35 mm in x, y and ±7.5 mm in z (mm, integer steps).
fn data_points() -> Vec<Vector3<f64>> {
    let mut out = Vec::new();
    for k in -3..=3 {
        for j in -14..=14 {
            for i in -14..=14 {
                out.push(Vector3::new(i as f64, j as f64, k as f64) * 2.5e-3);
            }
        }
    }
    out
}

const CURRENT_A: f64 = 2.0;

/// The field of `coil` at the data points at the export current, each component with uniform
/// relative noise of standard deviation `noise`.
fn noisy_field(rig: &Rig, coil: usize, seed: u64, noise: f64) -> Vec<Vector3<f64>> {
    let mut rng = Rng(seed);
    data_points()
        .iter()
        .map(|p| {
            let b = rig.coil_field.field_per_amp(coil, p) * CURRENT_A;
            b.map(|v| v * (1.0 + noise * (rng.uniform() - 0.5) * 12f64.sqrt()))
        })
        .collect()
}

/// COMSOL spreadsheet export (mm, T), rows shuffled.
fn comsol_spreadsheet(rig: &Rig, coil: usize, seed: u64, noise: f64) -> String {
    let mut rng = Rng(seed ^ 0x5eed);
    let field = noisy_field(rig, coil, seed, noise);
    let mut rows: Vec<String> = data_points()
        .iter()
        .zip(&field)
        .map(|(p, b)| {
            format!(
                "{:.4} {:.4} {:.4} {:.9e} {:.9e} {:.9e}",
                p.x * 1e3,
                p.y * 1e3,
                p.z * 1e3,
                b.x,
                b.y,
                b.z
            )
        })
        .collect();
    for i in (1..rows.len()).rev() {
        let j = (rng.uniform() * (i + 1) as f64) as usize;
        rows.swap(i, j.min(i));
    }
    let mut text = String::new();
    writeln!(text, "% Model:              coils.mph").unwrap();
    writeln!(text, "% Version:            COMSOL 6.1.0.252").unwrap();
    writeln!(text, "% Dimension:          3").unwrap();
    writeln!(text, "% Nodes:              {}", rows.len()).unwrap();
    writeln!(text, "% Expressions:        3").unwrap();
    writeln!(text, "% Description:        Magnetic flux density, x component, Magnetic flux density, y component, Magnetic flux density, z component").unwrap();
    writeln!(text, "% Length unit:        mm").unwrap();
    writeln!(text, "% x                       y                        z                        mf.Bx (T)                mf.By (T)                mf.Bz (T)").unwrap();
    for r in rows {
        writeln!(text, "{r}").unwrap();
    }
    text
}

/// Worst error of central differences of the noisy samples at interior data points, relative
/// to the largest gradient there: what plain differencing would give.
fn finite_difference_error(rig: &Rig, coil: usize, seed: u64, noise: f64) -> f64 {
    let field = noisy_field(rig, coil, seed, noise);
    let points = data_points();
    let at =
        |i: i32, j: i32, k: i32| field[((k + 3) * 29 * 29 + (j + 14) * 29 + (i + 14)) as usize];
    let h = 2.5e-3;
    let (mut worst, mut largest) = (0.0f64, 0.0f64);
    for k in -2..=2 {
        for j in -11..=11 {
            for i in -11..=11 {
                let p = points[((k + 3) * 29 * 29 + (j + 14) * 29 + (i + 14)) as usize];
                let (_, g) = rig.coil_field.field_and_gradient_per_amp(coil, &p);
                let g = g * CURRENT_A;
                let cols = [
                    (at(i + 1, j, k) - at(i - 1, j, k)) / (2.0 * h),
                    (at(i, j + 1, k) - at(i, j - 1, k)) / (2.0 * h),
                    (at(i, j, k + 1) - at(i, j, k - 1)) / (2.0 * h),
                ];
                let fd = Matrix3::from_columns(&cols);
                worst = worst.max((fd - g).norm());
                largest = largest.max(g.norm());
            }
        }
    }
    worst / largest
}

/// COMSOL grid export (m, mT).
fn comsol_grid(rig: &Rig, coil: usize) -> String {
    let xs: Vec<f64> = (-14..=14).map(|i| i as f64 * 2.5e-3).collect();
    let zs: Vec<f64> = (-3..=3).map(|i| i as f64 * 2.5e-3).collect();
    let axis = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{x}"))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let mut text = String::from("% Model: coils.mph\n% Length unit: m\n% Grid\n");
    writeln!(text, "{}\n{}\n{}", axis(&xs), axis(&xs), axis(&zs)).unwrap();
    for (c, name) in ["Bx", "By", "Bz"].iter().enumerate() {
        writeln!(text, "% Data (mf.{name} (mT))").unwrap();
        for z in &zs {
            for y in &xs {
                let row: Vec<String> = xs
                    .iter()
                    .map(|x| {
                        let b = rig
                            .coil_field
                            .field_per_amp(coil, &Vector3::new(*x, *y, *z));
                        format!("{:.9e}", b[c] * CURRENT_A * 1e3)
                    })
                    .collect();
                writeln!(text, "{}", row.join(" ")).unwrap();
            }
        }
    }
    text
}

/// Generic CSV with gradient columns (mm, G, G/cm).
fn csv_with_gradients(rig: &Rig, coil: usize) -> String {
    let mut text = String::from("x [mm],y [mm],z [mm],Bx [G],By [G],Bz [G]");
    for i in ["x", "y", "z"] {
        for j in ["x", "y", "z"] {
            write!(text, ",dB{i}/d{j} [G/cm]").unwrap();
        }
    }
    text.push('\n');
    for p in data_points() {
        let (b, g) = rig.coil_field.field_and_gradient_per_amp(coil, &p);
        let (b, g) = (b * CURRENT_A * 1e4, g * CURRENT_A * 1e4 * 1e-2);
        write!(
            text,
            "{},{},{},{:e},{:e},{:e}",
            p.x * 1e3,
            p.y * 1e3,
            p.z * 1e3,
            b.x,
            b.y,
            b.z
        )
        .unwrap();
        for k in 0..9 {
            write!(text, ",{:e}", g[(k / 3, k % 3)]).unwrap();
        }
        text.push('\n');
    }
    text
}

fn import(args: &[String]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_fieldgen"))
        .arg("import-coils")
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ),
    )
}

/// The map grid of the tests: ±30 mm, ±6 mm, 3 mm.
fn grid_args() -> Vec<String> {
    [
        "--half-xy-mm",
        "30",
        "--half-z-mm",
        "6",
        "--spacing-mm",
        "3",
    ]
    .map(String::from)
    .to_vec()
}

fn write_exports(rig: &Rig, dir: &Path, noise: f64) -> Vec<String> {
    let mut args = Vec::new();
    for (k, coil) in rig.coils.iter().enumerate() {
        let (file, text) = match k {
            10 => (
                dir.join(format!("{}.grid.txt", coil.name)),
                comsol_grid(rig, k),
            ),
            11 => (
                dir.join(format!("{}.csv", coil.name)),
                csv_with_gradients(rig, k),
            ),
            _ => (
                dir.join(format!("{}.txt", coil.name)),
                comsol_spreadsheet(rig, k, 100 + k as u64, noise),
            ),
        };
        std::fs::write(&file, text).unwrap();
        args.push("--coil".to_string());
        args.push(format!("{}={}@{CURRENT_A}", coil.name, file.display()));
    }
    args
}

/// Largest node error of `maps` against the analytic model, relative to the largest value on the
/// grid, for the field and the gradient of each coil.
fn worst_errors(rig: &Rig, maps: &CoilFieldMaps) -> Vec<(f64, f64)> {
    let g = *maps.grid();
    let [nx, ny, nz] = g.shape;
    (0..rig.coils.len())
        .map(|k| {
            let (mut eb, mut eg, mut mb, mut mg) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
            for iz in 0..nz {
                for iy in 0..ny {
                    for ix in 0..nx {
                        let p = g.node(ix, iy, iz);
                        let (b, gr): (Vector3<f64>, Matrix3<f64>) =
                            rig.coil_field.field_and_gradient_per_amp(k, &p);
                        let (bi, gi) = maps.try_field_and_gradient_per_amp(k, &p).unwrap();
                        eb = eb.max((bi - b).norm());
                        eg = eg.max((gi - gr).norm());
                        mb = mb.max(b.norm());
                        mg = mg.max(gr.norm());
                    }
                }
            }
            (eb / mb, eg / mg)
        })
        .collect()
}

#[test]
fn fea_exports_import_to_the_model() {
    let rig = Rig::load_paper().unwrap();
    let dir = temp_dir("exact");
    let out = dir.join("maps");
    let mut args = write_exports(&rig, &dir, 0.0);
    args.extend(grid_args());
    args.extend(["--out".to_string(), out.display().to_string()]);
    let (ok, text) = import(&args);
    assert!(ok, "{text}");
    for needle in [
        "COMSOL spreadsheet",
        "COMSOL grid",
        "with gradients",
        "imported 12 coils",
    ] {
        assert!(text.contains(needle), "{needle} missing:\n{text}");
    }
    let maps = CoilFieldMaps::load(&out).unwrap();
    let manifest = std::fs::read_to_string(out.join("coils.toml")).unwrap();
    assert!(manifest.contains("fieldgen import-coils") && manifest.contains("N_small.txt"));
    for (k, (eb, eg)) in worst_errors(&rig, &maps).into_iter().enumerate() {
        eprintln!("coil {k}: field {eb:.2e}, gradient {eg:.2e}");
        assert!(
            eb < 1e-3 && eg < 1e-3,
            "coil {k}: field {eb:.2e}, gradient {eg:.2e}\n{text}"
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn noisy_data_gives_smooth_gradients() {
    // 1 % noise on every field sample (a good gaussmeter scan). Central differences of the
    // samples 2.5 mm apart would err by several % of the gradient; the potential fit, with the
    // settings README recommends for measured data, averages the noise down instead.
    let rig = Rig::load_paper().unwrap();
    let dir = temp_dir("noisy");
    let out = dir.join("maps");
    let mut args = write_exports(&rig, &dir, 0.01);
    args.extend(grid_args());
    args.extend(["--fit-degree", "3", "--fit-radius-spacings", "4"].map(String::from));
    args.extend(["--out".to_string(), out.display().to_string()]);
    let (ok, text) = import(&args);
    assert!(ok, "{text}");
    let maps = CoilFieldMaps::load(&out).unwrap();
    for (k, (eb, eg)) in worst_errors(&rig, &maps).into_iter().enumerate().take(10) {
        let fd = finite_difference_error(&rig, k, 100 + k as u64, 0.01);
        eprintln!("coil {k}: field {eb:.2e}, gradient {eg:.2e} (differences: {fd:.2e})");
        assert!(
            eb < 0.005 && eg < 0.035 && eg < 0.5 * fd,
            "coil {k}: field {eb:.2e}, gradient {eg:.2e} (differences: {fd:.2e})"
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_exports_are_named() {
    let rig = Rig::load_paper().unwrap();
    let dir = temp_dir("bad");
    let base = write_exports(&rig, &dir, 0.0);
    let out = dir.join("maps").display().to_string();
    let run = |coil_args: &[String], extra: &[&str]| {
        let mut args = coil_args.to_vec();
        args.extend(grid_args());
        args.extend(["--out".to_string(), out.clone()]);
        args.extend(extra.iter().map(|s| s.to_string()));
        import(&args)
    };
    // A coil missing.
    let (ok, text) = run(&base[..base.len() - 2], &[]);
    assert!(
        !ok && text.contains("no data for coil(s) W_large"),
        "{text}"
    );
    // Replace N_small's file with a broken variant and check the message names it.
    let n_small = dir.join("N_small.txt");
    let good = std::fs::read_to_string(&n_small).unwrap();
    let check = |broken: String, needles: &[&str]| {
        std::fs::write(&n_small, broken).unwrap();
        let (ok, text) = run(&base, &[]);
        assert!(!ok, "accepted:\n{text}");
        for needle in needles {
            assert!(text.contains(needle), "{needle} missing:\n{text}");
        }
    };
    let lines: Vec<&str> = good.lines().collect();
    // NaN on a data line (COMSOL writes NaN outside the geometry).
    let mut nan = lines.clone();
    let with_nan = format!("{} NaN", nan[20].rsplit_once(' ').unwrap().0);
    nan[20] = &with_nan;
    check(nan.join("\n"), &["N_small.txt: line 21", "NaN"]);
    // A duplicate point.
    let mut dup = lines.clone();
    dup.push(lines[9]);
    check(
        dup.join("\n"),
        &["N_small.txt", "duplicate point", "also on line 10"],
    );
    // Holes: 30 points missing from the grid.
    let holes: Vec<&str> = lines
        .iter()
        .enumerate()
        .filter(|(i, _)| i % 97 != 50)
        .map(|(_, l)| *l)
        .collect();
    check(holes.join("\n"), &["N_small.txt", "grid with holes"]);
    // Units: the header says mm, the command line m.
    std::fs::write(&n_small, &good).unwrap();
    let (ok, text) = run(&base, &["--length-unit", "m"]);
    assert!(
        !ok && text.contains("the file gives length in mm but --length-unit says m"),
        "{text}"
    );
    // Units: one column in another unit.
    let csv = dir.join("W_large.csv");
    let good_csv = std::fs::read_to_string(&csv).unwrap();
    std::fs::write(&csv, good_csv.replacen("By [G]", "By [mT]", 1)).unwrap();
    let (ok, text) = run(&base, &[]);
    assert!(
        !ok && text.contains("W_large.csv: units: field columns use different units"),
        "{text}"
    );
    std::fs::write(&csv, good_csv).unwrap();
    // Data that does not cover the map grid.
    let mut wide = base.clone();
    wide.extend(["--half-xy-mm", "45", "--out", &out].map(String::from));
    let (ok, text) = import(&wide);
    assert!(!ok && text.contains("lies outside the data"), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}
