//! No paper constant in a code path: every crate and tool of the workspace reads its rig (coils,
//! camera, phantom, robot, zones, limits) from a rig file that a scenario or a `--rig` names.
//! This greps the sources of every workspace member (outside `#[cfg(test)]` modules, examples
//! and integration tests, which may use the committed paper rig as their fixture) for the
//! names and numbers that used to weld them to the paper's rig. The paper's rig is data:
//! `fieldmaps/rigs/paper.toml` and the phantom file its mask was drawn from.

use millinav_tests::sources::{
    before_inline_tests, code_paths, test_module_files, without_comment,
};

/// A pattern that is a crate's own API (the parametric phantom type in `fieldmaps`): not
/// flagged in that crate's sources.
const OWN_API: &[(&str, &str)] = &[("Phantom::", "fieldmaps")];

/// Names of the paper's rig in code, and its numbers as they were written there.
const FORBIDDEN: &[(&str, &str)] = &[
    ("paper_rig()", "the paper's coil layout in code"),
    ("PaperRigLayout", "the paper's coil layout in code"),
    ("PAPER_RIG_TURNS", "the paper's turns in code"),
    ("paper_coil_id", "the paper's coil order in code"),
    ("load_or_paper", "the paper's rig when none is named"),
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
    ("::load_paper()", "the paper's rig file"),
    ("1020", "the paper camera's 1020 px"),
    ("92.0", "the paper camera's 92 mm"),
    ("7.4e-3", "the paper capsule's length"),
    ("2.8e-3", "the paper capsule's diameter"),
    ("8.6e-4", "the paper magnet's moment"),
    ("-14.0, 2.5", "the paper's vortex centre"),
];

#[test]
fn code_paths_name_no_paper_constant() {
    let root = fieldmaps::data_root();
    let mut files = Vec::new();
    for krate in workspace_crates(&root) {
        // Unit tests may use the committed paper rig as their fixture.
        files.extend(code_paths(&krate.join("src")));
    }
    assert!(files.len() > 100, "found only {} sources", files.len());
    let mut hits = Vec::new();
    for (file, code) in &files {
        for (line_no, line) in code.lines().enumerate() {
            let line = without_comment(line);
            for (pattern, what) in FORBIDDEN {
                let own = OWN_API
                    .iter()
                    .any(|(p, home)| p == pattern && file.starts_with(root.join(home)));
                if !own && names(line, pattern) {
                    hits.push(format!(
                        "{}:{}: `{pattern}` ({what})",
                        file.strip_prefix(&root).unwrap_or(file).display(),
                        line_no + 1
                    ));
                }
            }
        }
    }
    assert!(
        hits.is_empty(),
        "code paths name the paper's rig; the rig file should say it:\n{}",
        hits.join("\n")
    );
}

/// Every member of the workspace, from the root manifest (a new crate is scanned without
/// anyone remembering to add it here).
fn workspace_crates(root: &std::path::Path) -> Vec<std::path::PathBuf> {
    let text = std::fs::read_to_string(root.join("Cargo.toml")).expect("Cargo.toml");
    let manifest: toml::Table = text.parse().expect("Cargo.toml parses");
    let members = manifest["workspace"]["members"]
        .as_array()
        .expect("workspace.members");
    let crates: Vec<_> = members
        .iter()
        .map(|m| root.join(m.as_str().expect("member path")))
        .collect();
    assert!(
        crates.iter().any(|c| c.ends_with("tools/bench")) && crates.len() > 15,
        "{crates:?}"
    );
    crates
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
fn inline_test_modules_end_the_code_path_whatever_their_visibility() {
    for header in ["mod tests {", "pub(crate) mod tests {", "pub mod tests {"] {
        let text = format!("fn a() {{}}\n#[cfg(test)]\n{header}\n    const W: u32 = 1020;\n}}\n");
        assert_eq!(before_inline_tests(&text), "fn a() {}\n", "{header}");
    }
    // A declaration does not end it.
    let text = "#[cfg(test)]\npub(crate) mod tests;\nconst W: u32 = 1020;\n";
    assert_eq!(before_inline_tests(text), text);
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
