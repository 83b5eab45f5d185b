//! `vision-eval --robustness` on the committed test split: every family of image shift at three
//! severities, every localizer, one table row each, the unshifted rows equal to a plain run's.
use std::path::PathBuf;
use std::process::Command;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn vision_eval(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_vision-eval"))
        .current_dir(root())
        .args(["--rig", "fieldmaps/rigs/paper.toml"])
        .args(args)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// (shift, severity, localizer, precision %, recall %, detected %) of each table row.
fn rows(table: &str) -> Vec<(String, String, String, f64, f64, f64)> {
    let pct = |cell: &str| {
        cell.trim()
            .trim_end_matches('%')
            .trim()
            .parse::<f64>()
            .unwrap()
    };
    table
        .lines()
        .filter(|l| {
            l.starts_with("| ") && !l.starts_with("| shift") && !l.starts_with("| localizer")
        })
        .map(|l| {
            let c: Vec<&str> = l.split('|').map(str::trim).collect();
            (
                c[1].into(),
                c[2].into(),
                c[3].into(),
                pct(c[4]),
                pct(c[5]),
                pct(c[7]),
            )
        })
        .collect()
}

#[test]
fn every_family_and_severity_is_evaluated_for_every_localizer() {
    let table = vision_eval(&["--robustness"]);
    let rows = rows(&table);
    // The unshifted split, then 11 families x 3 severities, for the UNet and the classical one.
    assert_eq!(rows.len(), 2 * (1 + 11 * 3), "{table}");
    for family in [
        "lighting",
        "colour cast",
        "background texture",
        "bubbles",
        "glare",
        "shadow",
        "motion blur",
        "noise",
        "JPEG",
        "scale",
        "occlusion",
    ] {
        for localizer in ["unet", "classical"] {
            let n = rows
                .iter()
                .filter(|r| r.0 == family && r.2 == localizer)
                .count();
            assert_eq!(n, 3, "{family} {localizer}\n{table}");
        }
    }
    // The unshifted rows are what a plain run measures.
    let plain = vision_eval(&[]);
    for r in rows.iter().filter(|r| r.0 == "none") {
        let line = plain
            .lines()
            .find(|l| l.starts_with(&format!("| {} |", r.2)))
            .unwrap();
        assert!(line.contains(&format!("{:.2} %", r.3)), "{line} vs {r:?}");
    }
    // Severity grades: the strongest blur costs the classical localizer detections.
    let detected = |family: &str, severity: &str| {
        rows.iter()
            .find(|r| r.0 == family && r.1.starts_with(severity) && r.2 == "classical")
            .unwrap()
            .5
    };
    assert!(
        detected("motion blur", "3") < detected("motion blur", "1"),
        "{table}"
    );
    // The committed UNet, trained with these shifts (tools/unet/augment.py, its own code and
    // ranges), holds every family at the highest severity: floors a little under what it
    // measured when committed (README, Vision), so a retrained model that loses robustness fails.
    for r in rows
        .iter()
        .filter(|r| r.1.starts_with('3') && r.2 == "unet")
    {
        assert!(r.5 >= 99.0, "{} detected {} %\n{table}", r.0, r.5);
        assert!(
            r.3 >= PRECISION_FLOOR,
            "{} precision {} %\n{table}",
            r.0,
            r.3
        );
        assert!(r.4 >= RECALL_FLOOR, "{} recall {} %\n{table}", r.0, r.4);
    }
}

/// Lowest precision / recall (%) the committed UNet may show under any shift at severity 3.
const PRECISION_FLOOR: f64 = 97.5;
const RECALL_FLOOR: f64 = 97.5;
