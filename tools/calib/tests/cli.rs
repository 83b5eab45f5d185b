//! The README's camera bring-up, as a newcomer runs it: `calib synth`, then `intrinsics`,
//! `homography` and `check` against a copy of the paper's rig file.

use std::path::PathBuf;
use std::process::Command;

use fieldmaps::rigfile::Rig;

fn calib(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_calib"))
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .output()
        .expect("calib runs");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "calib {args:?} failed:\n{text}");
    text
}

#[test]
fn synth_intrinsics_homography_check() {
    let root = fieldmaps::data_root();
    let rigs = root.join("fieldmaps/rigs");
    let rig = rigs.join(format!(".calib-cli-{}.toml", std::process::id()));
    std::fs::copy(rigs.join("paper.toml"), &rig).unwrap();
    let out: PathBuf = std::env::temp_dir().join(format!("calib-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let _cleanup = Cleanup(vec![rig.clone(), out.clone()]);
    let (rig_s, out_s) = (rig.to_str().unwrap(), out.to_str().unwrap());

    calib(&["synth", "--rig", rig_s, "--out", out_s]);
    let text = calib(&[
        "intrinsics",
        &format!("{out_s}/views"),
        "--inner-corners",
        "8x5",
        "--square-mm",
        "25",
        "--rig",
        rig_s,
        "--write",
    ]);
    assert!(text.contains("16 of 16 views used"), "{text}");
    let text = calib(&[
        "homography",
        "--fiducials",
        &format!("{out_s}/fiducials.csv"),
        "--rig",
        rig_s,
        "--write",
    ]);
    assert!(text.contains("9 fiducials"), "{text}");
    let calibration = Rig::load(&rig).unwrap().camera.calibration.unwrap();
    assert!(calibration.reprojection_error_px.unwrap() < 0.5);
    assert!(calibration.registration_residual_mm.unwrap() < 0.05);
    let check = out.join("check.png");
    calib(&[
        "check",
        "--rig",
        rig_s,
        "--frame",
        &format!("{out_s}/frame.png"),
        "--out",
        check.to_str().unwrap(),
    ]);
    let image = opencv::imgcodecs::imread(&check, opencv::imgcodecs::IMREAD_COLOR).unwrap();
    use opencv::prelude::*;
    assert_eq!((image.cols(), image.rows()), (1020, 1020));

    // A fiducial file with a bad row is refused, naming the file and the row.
    let bad = out.join("bad.csv");
    std::fs::write(&bad, "name,u_px,v_px,x_mm,y_mm\na,1,2,3,4\nb,1,two,3,4\n").unwrap();
    let failed = Command::new(env!("CARGO_BIN_EXE_calib"))
        .args([
            "homography",
            "--fiducials",
            bad.to_str().unwrap(),
            "--rig",
            rig_s,
        ])
        .env("RUST_BACKTRACE", "0")
        .output()
        .unwrap();
    let message = String::from_utf8_lossy(&failed.stderr);
    assert!(!failed.status.success());
    assert!(
        message.contains("bad.csv") && message.contains("row 2"),
        "{message}"
    );
}

/// Removes the rig copy and the output folder however the test ends.
struct Cleanup(Vec<PathBuf>);
impl Drop for Cleanup {
    fn drop(&mut self) {
        for path in &self.0 {
            let _ = std::fs::remove_file(path);
            let _ = std::fs::remove_dir_all(path);
        }
    }
}
