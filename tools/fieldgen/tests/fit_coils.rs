//! `fieldgen fit-coils` on synthetic gaussmeter data: a twin whose coils have known gain errors
//! and a background field, measured with probe noise. The fit must recover the gains within
//! 0.5 % and the background within 0.02 mT, report held-out errors, name outlier rows, refuse
//! rank-deficient and malformed files clearly, and the rig file must load the calibration.
use std::path::{Path, PathBuf};
use std::process::Command;

use fieldgen::fit_coils::{synthesize, write_measurements, Measurement};
use fieldmaps::calibration::{CalibratedField, CoilCalibration, CoilCorrection};
use fieldmaps::coils::CoilField;
use fieldmaps::rigfile::{Rig, RigCoilField};
use nalgebra::Vector3;

/// Small deterministic generator (xorshift64*), uniform and standard normal.
struct Rng(u64);

impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }

    fn normal(&mut self) -> f64 {
        let (u1, u2) = (self.uniform().max(1e-300), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("millinav-fit-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

const GAINS: [f64; 12] = [
    1.06, 0.93, 1.02, 0.97, 1.08, 0.95, 1.0, 1.04, 0.91, 1.03, 0.96, 1.07,
];

fn background_t() -> Vector3<f64> {
    Vector3::new(0.031e-3, -0.047e-3, 0.042e-3)
}

/// The paper rig's analytic model with the gain errors and background above.
fn truth(rig: &Rig) -> CalibratedField<RigCoilField> {
    CalibratedField {
        base: rig.coil_field.clone(),
        corrections: GAINS.iter().map(|&g| CoilCorrection::Gain(g)).collect(),
        background_t: background_t(),
    }
}

/// `n` rows: probe positions in the workspace, random currents up to 6 A in every coil,
/// 0.01 mT probe noise per component.
fn measurements(rig: &Rig, n: usize, seed: u64) -> Vec<Measurement> {
    let mut rng = Rng(seed);
    let positions: Vec<Vector3<f64>> = (0..n)
        .map(|_| {
            Vector3::new(
                (rng.uniform() - 0.5) * 0.08,
                (rng.uniform() - 0.5) * 0.08,
                (rng.uniform() - 0.5) * 0.01,
            )
        })
        .collect();
    let patterns: Vec<Vec<f64>> = (0..n)
        .map(|_| (0..12).map(|_| (rng.uniform() - 0.5) * 12.0).collect())
        .collect();
    synthesize(&truth(rig), &positions, &patterns, 0.01e-3, || rng.normal())
}

fn names(rig: &Rig) -> Vec<String> {
    rig.coils.iter().map(|c| c.name.clone()).collect()
}

fn fit_coils(args: &[&std::ffi::OsStr]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_fieldgen"))
        .arg("fit-coils")
        .args(args)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

/// A copy of the paper rig in `dir` whose field model is `field_model` (a TOML table; data
/// paths absolute).
fn rig_copy(dir: &Path, field_model: &str) -> PathBuf {
    let rigs = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fieldmaps/rigs")
        .canonicalize()
        .unwrap();
    let text = std::fs::read_to_string(rigs.join("paper.toml")).unwrap();
    let mut out = String::new();
    for line in text.lines() {
        let line = if line.starts_with("field_model") {
            format!("field_model = {field_model}")
        } else {
            line.replace("= \"paper/", &format!("= \"{}/paper/", rigs.display()))
                .replace("= \"../", &format!("= \"{}/../", rigs.display()))
        };
        out.push_str(&line);
        out.push('\n');
    }
    let path = dir.join("rig.toml");
    std::fs::write(&path, out).unwrap();
    path
}

#[test]
fn recovers_gains_and_background_and_the_rig_loads_it() {
    let rig = Rig::load_paper().unwrap();
    let dir = temp_dir("recover");
    let csv = dir.join("gauss.csv");
    let mut rows = measurements(&rig, 400, 7);
    // Three bad readings (probe slipped, a coil driver tripped): far outside the noise.
    for (k, i) in [17usize, 150, 333].iter().enumerate() {
        rows[*i].field_t += Vector3::new(0.8e-3, -0.5e-3 * k as f64, 0.3e-3);
    }
    write_measurements(&csv, &names(&rig), &rows).unwrap();
    let verify_csv = dir.join("verify.csv");
    write_measurements(&verify_csv, &names(&rig), &measurements(&rig, 60, 99)).unwrap();
    let cal_path = dir.join("cal/coils_cal.toml");
    let (ok, text) = fit_coils(&[
        "--measurements".as_ref(),
        csv.as_os_str(),
        "--verify".as_ref(),
        verify_csv.as_os_str(),
        "--out".as_ref(),
        cal_path.as_os_str(),
    ]);
    assert!(ok, "{text}");
    eprintln!("{text}");
    // Rows 17, 150, 333 sit on lines 19, 152, 335 (line 1 is the header).
    for line in [19, 152, 335] {
        assert!(text.contains(&format!("line {line}: residual")), "{text}");
    }
    assert!(text.contains("verify held out (every 5th row)"), "{text}");
    assert!(text.contains("verify.csv:"), "{text}");
    let cal = CoilCalibration::load(&cal_path).unwrap();
    for (k, want) in GAINS.iter().enumerate() {
        let CoilCorrection::Gain(got) = cal.corrections[k] else {
            panic!("not a gain")
        };
        assert!(
            (got / want - 1.0).abs() < 0.005,
            "coil {}: gain {got} vs {want}\n{text}",
            cal.coil_names[k]
        );
    }
    let bg_err = (cal.background_t - background_t()).abs().max();
    assert!(bg_err < 0.02e-3, "background off by {bg_err} T\n{text}");

    // The rig file references it; control's model then matches the truth closely.
    let rig_path = rig_copy(
        &dir,
        "{ kind = \"analytic\", calibration = \"cal/coils_cal.toml\" }",
    );
    let calibrated = Rig::load(&rig_path).unwrap();
    assert_eq!(
        calibrated.field_calibration,
        Some(dir.join("cal/coils_cal.toml"))
    );
    assert!(calibrated.summary().contains("+ calibration"));
    let p = Vector3::new(0.01, -0.02, 0.0);
    let currents = [2.0, 0.0, -3.0, 1.0, 0.0, 4.0, 0.0, -1.0, 2.5, 0.0, 0.0, 1.5];
    let (want, want_g) = truth(&rig).field_and_gradient(&currents, &p);
    let (got, got_g) = calibrated.coil_field.field_and_gradient(&currents, &p);
    assert!((got - want).norm() < 0.005 * want.norm(), "{got} vs {want}");
    assert!((got_g - want_g).norm() < 0.005 * want_g.norm());
    let (plain, _) = rig.coil_field.field_and_gradient(&currents, &p);
    assert!((plain - want).norm() > 3.0 * (got - want).norm());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn matrix_model_fits_too() {
    let rig = Rig::load_paper().unwrap();
    let dir = temp_dir("matrix");
    let csv = dir.join("gauss.csv");
    write_measurements(&csv, &names(&rig), &measurements(&rig, 300, 3)).unwrap();
    let out = dir.join("cal.toml");
    let (ok, text) = fit_coils(&[
        "--measurements".as_ref(),
        csv.as_os_str(),
        "--model".as_ref(),
        "matrix".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert!(ok, "{text}");
    let cal = CoilCalibration::load(&out).unwrap();
    for (k, want) in GAINS.iter().enumerate() {
        let CoilCorrection::Matrix(m) = cal.corrections[k] else {
            panic!("not a matrix")
        };
        // A pure gain error: the matrix is that gain times the identity.
        let err = (m - nalgebra::Matrix3::identity() * *want).abs().max();
        assert!(err < 0.02, "coil {k}: {m}\n{text}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn rank_deficient_and_malformed_files_are_refused_clearly() {
    let rig = Rig::load_paper().unwrap();
    let names = names(&rig);
    let dir = temp_dir("bad");
    let run = |rows: &[Measurement], extra: &[&str]| {
        let csv = dir.join("gauss.csv");
        write_measurements(&csv, &names, rows).unwrap();
        let out = dir.join("cal.toml");
        let mut args: Vec<&std::ffi::OsStr> = vec![
            "--measurements".as_ref(),
            csv.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ];
        args.extend(extra.iter().map(std::ffi::OsStr::new));
        fit_coils(&args)
    };
    // Probe fixed at one point and N_mid always at twice N_small's current: the two coils'
    // contributions are proportional in every row, so their gains cannot be told apart.
    // At the workspace centre every coil's field lies along its axis, so the N coils' fields
    // are parallel there.
    let mut rng = Rng(11);
    let patterns: Vec<Vec<f64>> = (0..120)
        .map(|_| {
            let mut i: Vec<f64> = (0..12).map(|_| (rng.uniform() - 0.5) * 12.0).collect();
            i[1] = 2.0 * i[0];
            i
        })
        .collect();
    let tied = synthesize(
        &truth(&rig),
        &vec![Vector3::zeros(); patterns.len()],
        &patterns,
        0.01e-3,
        || rng.normal(),
    );
    let (ok, text) = run(&tied, &[]);
    assert!(!ok);
    assert!(
        text.contains("rank-deficient") && text.contains("N_small") && text.contains("N_mid"),
        "{text}"
    );
    // A coil never driven: named, with the way out.
    let mut idle = measurements(&rig, 120, 12);
    for r in &mut idle {
        r.currents_a[4] = 0.0;
    }
    let (ok, text) = run(&idle, &[]);
    assert!(
        !ok && text.contains("E_mid") && text.contains("--unfitted"),
        "{text}"
    );
    let (ok, text) = run(&idle, &["--unfitted", "E_mid"]);
    assert!(ok, "{text}");
    assert!(text.contains("unfitted"), "{text}");

    // Malformed files: missing coil column, NaN, mixed units.
    let csv = dir.join("hand.csv");
    let header = |drop: &str| {
        let mut h = vec!["x_mm", "y_mm", "z_mm"]
            .into_iter()
            .map(String::from)
            .collect::<Vec<_>>();
        h.extend(
            names
                .iter()
                .filter(|n| *n != drop)
                .map(|n| format!("I_{n}_A")),
        );
        h.extend(["Bx_mT", "By_mT", "Bz_mT"].map(String::from));
        h.join(",")
    };
    let row = |count: usize, bz: &str| {
        let mut r = vec!["1".to_string(); 3 + count];
        r.extend(["0.1".to_string(), "0.2".into(), bz.to_string()]);
        r.join(",")
    };
    let fit_text = |text: String| {
        std::fs::write(&csv, text).unwrap();
        fit_coils(&[
            "--measurements".as_ref(),
            csv.as_os_str(),
            "--out".as_ref(),
            dir.join("x.toml").as_os_str(),
        ])
    };
    let (ok, text) = fit_text(format!("{}\n{}\n", header("W_large"), row(11, "0.3")));
    assert!(
        !ok && text.contains("coil W_large: no current column"),
        "{text}"
    );
    let (ok, text) = fit_text(format!(
        "{}\n{}\n{}\n",
        header(""),
        row(12, "0.3"),
        row(12, "NaN")
    ));
    assert!(
        !ok && text.contains("line 3") && text.contains("Bz_mT") && text.contains("NaN"),
        "{text}"
    );
    let (ok, text) = fit_text(format!(
        "{}\n{}\n",
        header("").replacen("y_mm", "y_m", 1),
        row(12, "0.3")
    ));
    assert!(!ok && text.contains("different units"), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}
