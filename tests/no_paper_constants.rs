//! No paper constant in a service's code path: every service reads its rig (coils, camera,
//! phantom, robot, zones, limits) from the scenario's rig file. This greps the services'
//! sources (outside `#[cfg(test)]` modules) for the names and numbers that used to weld them
//! to the paper's rig. Defaults that a file overrides live in `fieldmaps` (the paper rig's
//! path, the parametric phantom used to draw `paper/heart_mask.png`), not in services.

use std::path::{Path, PathBuf};

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

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

#[test]
fn services_name_no_paper_constant() {
    let services = fieldmaps::data_root().join("services");
    let mut files = Vec::new();
    for entry in std::fs::read_dir(&services).expect("services/").flatten() {
        rust_files(&entry.path().join("src"), &mut files);
    }
    assert!(
        files.len() > 20,
        "found only {} service sources",
        files.len()
    );
    let test_modules = test_module_files(&files);
    let mut hits = Vec::new();
    for file in files.iter().filter(|f| !test_modules.contains(f)) {
        let text = std::fs::read_to_string(file).expect("readable source");
        // Unit tests may use the committed paper rig as their fixture.
        let code = before_inline_tests(&text);
        for (line_no, line) in code.lines().enumerate() {
            let line = line.split("//").next().unwrap_or("");
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

/// The source before its first inline `#[cfg(test)] mod name {` block (a `#[cfg(test)] mod
/// name;` declaration does not end the scan: code after it is still a code path).
fn before_inline_tests(text: &str) -> &str {
    let mut from = 0;
    while let Some(at) = text[from..].find("#[cfg(test)]") {
        let start = from + at;
        let rest = text[start + "#[cfg(test)]".len()..].trim_start();
        let header = rest.lines().next().unwrap_or("");
        if header.starts_with("mod ") && header.trim_end().ends_with('{') {
            return &text[..start];
        }
        from = start + 1;
    }
    text
}

/// The files of modules declared `#[cfg(test)] mod name;`: unit tests kept in a file of their
/// own (`name.rs` or `name/mod.rs` beside the declaring module's own directory).
fn test_module_files(files: &[PathBuf]) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for file in files {
        let Ok(text) = std::fs::read_to_string(file) else {
            continue;
        };
        let stem = file.file_stem().and_then(|s| s.to_str()).unwrap_or("");
        let parent = file.parent().unwrap_or(Path::new("."));
        // `lib.rs`, `main.rs` and `mod.rs` own their directory; `foo.rs` owns `foo/`.
        let dir = if matches!(stem, "lib" | "main" | "mod") {
            parent.to_path_buf()
        } else {
            parent.join(stem)
        };
        let mut lines = text.lines().map(str::trim);
        while let Some(line) = lines.next() {
            if line != "#[cfg(test)]" {
                continue;
            }
            let Some(next) = lines.next() else { break };
            let declared = next
                .strip_prefix("mod ")
                .and_then(|rest| rest.strip_suffix(';'))
                .map(str::trim);
            if let Some(name) = declared {
                out.push(dir.join(format!("{name}.rs")));
                out.push(dir.join(name).join("mod.rs"));
            }
        }
    }
    out
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
    let sample = "let c = CoilSystem::paper_rig(); let w = 1020;";
    let found: Vec<&str> = FORBIDDEN
        .iter()
        .map(|(p, _)| *p)
        .filter(|p| sample.contains(p))
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
