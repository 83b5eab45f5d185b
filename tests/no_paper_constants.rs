//! No paper constant in a service's code path: every service reads its rig (coils, camera,
//! phantom, robot, zones, limits) from the scenario's rig file. This greps the services'
//! sources (outside `#[cfg(test)]` modules) for the names and numbers that used to weld them
//! to the paper's rig. Defaults that a file overrides live in `fieldmaps` (the paper rig's
//! path, the parametric phantom used to draw `paper/heart_mask.png`), not in services.

use millinav_tests::sources::{code_paths, test_module_files, without_comment};

/// Names of the paper's rig in code, and its numbers as they were written there.
const FORBIDDEN: &[(&str, &str)] = &[
    ("paper_rig()", "the paper's coil layout in code"),
    ("default_heart()", "the paper's parametric phantom"),
    (
        "Phantom::",
        "a parametric phantom instead of the rig's mask",
    ),
    ("FRAME_FIELD_OF_VIEW_MM", "the paper camera's field of view"),
    ("FRAME_WIDTH", "the paper camera's width"),
    ("FRAME_HEIGHT", "the paper camera's height"),
    ("COIL_COUNT", "the paper's 12 coils"),
    ("DEFAULT_PLANAR_COILS", "the paper's 8 allocation coils"),
    ("ALL_COILS", "the paper's 12 coil indices"),
    ("_Y_RANGE_M", "the paper's zone bands"),
    ("ImageGeometry::default()", "the paper camera's geometry"),
    ("RobotParams::default()", "the paper's capsule"),
    ("CoilLimits::default()", "the paper's coil ratings"),
    ("CapsuleSize::default()", "the paper's capsule size"),
    ("load_default()", "the paper's committed coil maps"),
    ("load_paper()", "the paper's rig file"),
    ("1020", "the paper camera's 1020 px"),
    ("92.0", "the paper camera's 92 mm"),
    ("7.4e-3", "the paper capsule's length"),
    ("2.8e-3", "the paper capsule's diameter"),
    ("8.6e-4", "the paper magnet's moment"),
    ("-14.0, 2.5", "the paper's vortex centre"),
];

#[test]
fn services_name_no_paper_constant() {
    let services = fieldmaps::data_root().join("services");
    let mut files = Vec::new();
    for entry in std::fs::read_dir(&services).expect("services/").flatten() {
        // Unit tests may use the committed paper rig as their fixture.
        files.extend(code_paths(&entry.path().join("src")));
    }
    assert!(
        files.len() > 20,
        "found only {} service sources",
        files.len()
    );
    let mut hits = Vec::new();
    for (file, code) in &files {
        for (line_no, line) in code.lines().enumerate() {
            let line = without_comment(line);
            for (pattern, what) in FORBIDDEN {
                if names(line, pattern) {
                    hits.push(format!(
                        "{}:{}: `{pattern}` ({what})",
                        file.strip_prefix(&services).unwrap_or(file).display(),
                        line_no + 1
                    ));
                }
            }
        }
    }
    assert!(
        hits.is_empty(),
        "services name the paper's rig; the rig file should say it:\n{}",
        hits.join("\n")
    );
}

#[test]
fn test_modules_in_files_of_their_own_are_recognised() {
    let files = [fieldmaps::data_root().join("services/control/src/control_loop/mod.rs")];
    let found = test_module_files(&files);
    assert!(
        found.iter().any(|f| f.ends_with("control_loop/tests.rs")),
        "{found:?}"
    );
}

#[test]
fn the_grep_finds_what_it_looks_for() {
    // The scan would pass vacuously if the patterns never matched real code.
    // It runs the scan's own matcher, which must also not take a longer name's tail for one.
    let sample = "let c = CoilSystem::paper_rig(); let w = 1020; let p = CAP_PROP_FRAME_WIDTH;";
    let found: Vec<&str> = FORBIDDEN
        .iter()
        .map(|(p, _)| *p)
        .filter(|p| names(sample, p))
        .collect();
    assert_eq!(found, ["paper_rig()", "1020"]);
}

/// Whether `line` names `pattern`: a pattern that starts a name must not be the tail of a longer
/// one (OpenCV's `CAP_PROP_FRAME_WIDTH` is not the paper's `FRAME_WIDTH`).
fn names(line: &str, pattern: &str) -> bool {
    let is_ident = |c: char| c.is_ascii_alphanumeric() || c == '_';
    let starts_a_name = pattern
        .chars()
        .next()
        .is_some_and(|c| c.is_ascii_alphanumeric());
    line.match_indices(pattern)
        .any(|(at, _)| !starts_a_name || !line[..at].chars().next_back().is_some_and(is_ident))
}
