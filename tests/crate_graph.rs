//! The shape of the house: no arrow climbs back from a library or service to a tool, the
//! transport-free libraries stay free of iceoryx2, Rerun, OpenCV and ONNX Runtime, and no two
//! modules of a crate import each other (directly or around a loop). Read from the manifests
//! and sources themselves.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use millinav_tests::sources::{code_paths, without_comment, workspace_root};

/// Libraries the board, the planner and the domain share: no transport, no viewer, no vision.
const TRANSPORT_FREE: &[&str] = &[
    "shm_schemas_core",
    "fieldmaps",
    "millinav-planning",
    "millinav-teensy-protocol",
    "millinav-firmware-core",
];
const HEAVY: &[&str] = &["iceoryx2", "iceoryx2-bb-posix", "rerun", "opencv", "ort"];

struct Member {
    dir: PathBuf,
    /// Normal dependencies, by package name.
    normal: BTreeSet<String>,
    /// Normal, dev and build dependencies.
    all: BTreeSet<String>,
}

fn members() -> BTreeMap<String, Member> {
    let root = workspace_root();
    let text = std::fs::read_to_string(root.join("Cargo.toml")).expect("workspace Cargo.toml");
    let manifest: toml::Table = toml::from_str(&text).expect("workspace Cargo.toml parses");
    let paths = manifest["workspace"]["members"]
        .as_array()
        .expect("[workspace] members");
    let mut out = BTreeMap::new();
    for path in paths {
        let dir = root.join(path.as_str().expect("member path"));
        let file = dir.join("Cargo.toml");
        let text = std::fs::read_to_string(&file).unwrap_or_else(|e| panic!("{file:?}: {e}"));
        let manifest: toml::Table =
            toml::from_str(&text).unwrap_or_else(|e| panic!("{file:?}: {e}"));
        let name = manifest["package"]["name"].as_str().expect("package.name");
        let table_keys = |key: &str| -> BTreeSet<String> {
            manifest
                .get(key)
                .and_then(toml::Value::as_table)
                .map(|t| t.keys().cloned().collect())
                .unwrap_or_default()
        };
        let normal = table_keys("dependencies");
        let mut all = normal.clone();
        all.extend(table_keys("dev-dependencies"));
        all.extend(table_keys("build-dependencies"));
        out.insert(name.to_string(), Member { dir, normal, all });
    }
    out
}

fn is_tool_or_test(root: &Path, member: &Member) -> bool {
    let rel = member.dir.strip_prefix(root).unwrap_or(&member.dir);
    rel.starts_with("tools") || rel.starts_with("tests")
}

/// A service process: a member under `services/` with a `main.rs` of its own.
fn is_service_process(root: &Path, member: &Member) -> bool {
    let rel = member.dir.strip_prefix(root).unwrap_or(&member.dir);
    rel.starts_with("services") && member.dir.join("src/main.rs").exists()
}

#[test]
fn no_service_process_builds_on_another() {
    // What two processes share lives in a library (kit, the contract, the protocol), so one
    // service's internals never become another's API.
    let root = workspace_root();
    let members = members();
    let processes: Vec<&String> = members
        .iter()
        .filter(|(_, m)| is_service_process(&root, m))
        .map(|(name, _)| name)
        .collect();
    assert!(processes.len() >= 6, "found only {processes:?}");
    let mut arrows = Vec::new();
    for name in &processes {
        for dep in &members[*name].normal {
            if members
                .get(dep)
                .is_some_and(|d| is_service_process(&root, d))
            {
                arrows.push(format!("{name} -> {dep}"));
            }
        }
    }
    assert!(
        arrows.is_empty(),
        "services building on another service: {arrows:?}"
    );
}

#[test]
fn no_library_or_service_depends_on_a_tool() {
    let root = workspace_root();
    let members = members();
    assert!(members.len() > 15, "found {} members", members.len());
    let mut climbs = Vec::new();
    for (name, member) in members.iter().filter(|(_, m)| !is_tool_or_test(&root, m)) {
        for dep in &member.all {
            if members.get(dep).is_some_and(|d| is_tool_or_test(&root, d)) {
                climbs.push(format!("{name} -> {dep}"));
            }
        }
    }
    assert!(
        climbs.is_empty(),
        "arrows climbing back to a tool: {climbs:?}"
    );
}

#[test]
fn transport_free_libraries_pull_in_no_transport_viewer_or_vision() {
    let members = members();
    for name in TRANSPORT_FREE {
        // Everything `name` builds on among the workspace's crates, itself included.
        let mut seen = BTreeSet::new();
        let mut todo = vec![name.to_string()];
        while let Some(crate_name) = todo.pop() {
            let member = members
                .get(&crate_name)
                .unwrap_or_else(|| panic!("{crate_name} is not a workspace member"));
            if !seen.insert(crate_name.clone()) {
                continue;
            }
            for dep in &member.normal {
                assert!(
                    !HEAVY.contains(&dep.as_str()),
                    "{name} pulls in {dep} (through {crate_name})"
                );
                if members.contains_key(dep) {
                    todo.push(dep.clone());
                }
            }
        }
    }
}

/// The top-level module a file belongs to (`None` for the crate root, `lib.rs`/`main.rs`).
fn top_module(src: &Path, file: &Path) -> Option<String> {
    let rel = file.strip_prefix(src).ok()?;
    let first = rel.components().next()?.as_os_str().to_str()?;
    let name = first.strip_suffix(".rs").unwrap_or(first);
    (!matches!(name, "lib" | "main")).then(|| name.to_string())
}

/// `crate::name` paths in a line of code, and the names a `use crate::{a, b::c}` group opens.
fn crate_paths(line: &str) -> Vec<String> {
    let is_ident = |c: char| c.is_ascii_alphanumeric() || c == '_';
    let mut out = Vec::new();
    for (at, _) in line.match_indices("crate::") {
        if line[..at]
            .chars()
            .next_back()
            .is_some_and(|c| is_ident(c) || c == '$')
        {
            continue; // `$crate::`, `my_crate::`
        }
        let rest = &line[at + "crate::".len()..];
        if let Some(group) = rest.strip_prefix('{') {
            let group = group.split('}').next().unwrap_or("");
            for item in group.split(',') {
                let head: String = item.trim().chars().take_while(|&c| is_ident(c)).collect();
                if !head.is_empty() {
                    out.push(head);
                }
            }
        } else {
            let head: String = rest.chars().take_while(|&c| is_ident(c)).collect();
            out.push(head);
        }
    }
    out
}

/// The module import graph of one crate's `src/`: top-level module → the modules it names.
fn module_graph(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let files = code_paths(src);
    let modules: BTreeSet<String> = files
        .iter()
        .filter_map(|(f, _)| top_module(src, f))
        .collect();
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for (file, code) in &files {
        let Some(from) = top_module(src, file) else {
            continue;
        };
        // A multi-line `use crate::{...}` group, read as one line.
        let joined: String = code
            .lines()
            .map(without_comment)
            .collect::<Vec<_>>()
            .join(" ");
        for to in crate_paths(&joined) {
            if to != from && modules.contains(&to) {
                graph.entry(from.clone()).or_default().insert(to);
            }
        }
    }
    graph
}

/// The groups of modules that reach each other (strongly connected, more than one module).
fn cycles(graph: &BTreeMap<String, BTreeSet<String>>) -> Vec<Vec<String>> {
    let reach = |from: &String| {
        let mut seen = BTreeSet::new();
        let mut todo = vec![from.clone()];
        while let Some(m) = todo.pop() {
            for next in graph.get(&m).into_iter().flatten() {
                if seen.insert(next.clone()) {
                    todo.push(next.clone());
                }
            }
        }
        seen
    };
    let reaches: BTreeMap<&String, BTreeSet<String>> =
        graph.keys().map(|m| (m, reach(m))).collect();
    let mut grouped = BTreeSet::new();
    let mut out = Vec::new();
    for (m, from_m) in &reaches {
        if grouped.contains(*m) || !from_m.contains(*m) {
            continue;
        }
        let group: Vec<String> = from_m
            .iter()
            .filter(|other| reaches.get(other).is_some_and(|r| r.contains(*m)))
            .cloned()
            .collect();
        grouped.extend(group.iter().cloned());
        out.push(group);
    }
    out
}

#[test]
fn no_crate_has_a_module_cycle() {
    let mut found = Vec::new();
    for (name, member) in members() {
        for modules in cycles(&module_graph(&member.dir.join("src"))) {
            found.push(format!("{name}: {}", modules.join(" <-> ")));
        }
    }
    assert!(
        found.is_empty(),
        "module import cycles:\n{}",
        found.join("\n")
    );
}

#[test]
fn the_cycle_check_sees_a_cycle_and_its_paths() {
    // The check would pass vacuously if it never read a path or never closed a loop.
    assert_eq!(
        crate_paths("use crate::{a::X, b}; let y = crate::c::f(); $crate::d"),
        ["a", "b", "c"]
    );
    let graph: BTreeMap<String, BTreeSet<String>> = [
        ("a", vec!["b"]),
        ("b", vec!["c"]),
        ("c", vec!["a"]),
        ("d", vec!["a"]),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v.into_iter().map(String::from).collect()))
    .collect();
    assert_eq!(cycles(&graph), [vec!["a", "b", "c"]]);
}
