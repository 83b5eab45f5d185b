//! No member declares a dependency it does not use: each dependency of a member's manifest
//! (normal, dev and build) is named in that member's Rust sources, as `name::`, `use name`,
//! `extern crate name` or `name!`. A dependency a member needs without naming it (one that only
//! aligns a feature, or that a macro of another crate names) is listed in the manifest's
//! `[package.metadata.cargo-machete] ignored`, with a comment saying why. Read from the
//! manifests and sources themselves, like `cargo machete`, without building anything.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use millinav_tests::sources::{rust_files, without_comment, workspace_root};

/// The crate name a dependency key is used by in code (`millinav-kit` → `millinav_kit`).
fn ident(dependency: &str) -> String {
    dependency.replace('-', "_")
}

/// Whether `code` names the crate `ident` as a path, an import, an extern crate or a macro's
/// crate.
fn names_crate(code: &str, ident: &str) -> bool {
    let bytes = code.as_bytes();
    let mut from = 0;
    while let Some(found) = code[from..].find(ident) {
        let start = from + found;
        let end = start + ident.len();
        from = end;
        let before = code[..start].chars().next_back();
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
            continue;
        }
        let rest = &code[end..];
        if rest.starts_with("::") {
            // `crate_name::x`, but not `self::crate_name` or `super::crate_name::x` (a module).
            let path_before = code[..start].trim_end();
            if !(path_before.ends_with("self::") || path_before.ends_with("super::")) {
                return true;
            }
        }
        let line_start = code[..start].rfind('\n').map_or(0, |i| i + 1);
        let head = code[line_start..start].trim();
        let is_word_end = bytes
            .get(end)
            .is_none_or(|&c| !(c.is_ascii_alphanumeric() || c == b'_'));
        if is_word_end
            && (head.ends_with("use")
                || head.ends_with("extern crate")
                || head.ends_with("pub use"))
        {
            return true;
        }
    }
    false
}

struct Member {
    dir: PathBuf,
    manifest: toml::Table,
}

fn members() -> Vec<Member> {
    let root = workspace_root();
    let text = std::fs::read_to_string(root.join("Cargo.toml")).expect("workspace Cargo.toml");
    let workspace: toml::Table = toml::from_str(&text).expect("workspace Cargo.toml parses");
    workspace["workspace"]["members"]
        .as_array()
        .expect("[workspace] members")
        .iter()
        .map(|path| {
            let dir = root.join(path.as_str().expect("member path"));
            let file = dir.join("Cargo.toml");
            let text = std::fs::read_to_string(&file).unwrap_or_else(|e| panic!("{file:?}: {e}"));
            let manifest = toml::from_str(&text).unwrap_or_else(|e| panic!("{file:?}: {e}"));
            Member { dir, manifest }
        })
        .collect()
}

/// The member's Rust files, leaving out members nested in its directory (`shm_schemas/core`).
fn own_sources(dir: &Path) -> Vec<PathBuf> {
    rust_files(dir)
        .into_iter()
        .filter(|file| {
            !file
                .ancestors()
                .skip(1)
                .take_while(|a| *a != dir)
                .any(|a| a.join("Cargo.toml").exists() || a.ends_with("target"))
        })
        .collect()
}

fn code_of(files: &[PathBuf]) -> String {
    let mut code = String::new();
    for file in files {
        let text = std::fs::read_to_string(file).unwrap_or_else(|e| panic!("{file:?}: {e}"));
        for line in text.lines() {
            code.push_str(without_comment(line));
            code.push('\n');
        }
    }
    code
}

fn declared(manifest: &toml::Table) -> BTreeSet<String> {
    ["dependencies", "dev-dependencies", "build-dependencies"]
        .iter()
        .filter_map(|key| manifest.get(*key).and_then(toml::Value::as_table))
        .flat_map(|table| table.keys().cloned())
        .collect()
}

fn ignored(manifest: &toml::Table) -> BTreeSet<String> {
    manifest
        .get("package")
        .and_then(|p| p.get("metadata"))
        .and_then(|m| m.get("cargo-machete"))
        .and_then(|c| c.get("ignored"))
        .and_then(toml::Value::as_array)
        .map(|list| {
            list.iter()
                .filter_map(|v| v.as_str().map(str::to_string))
                .collect()
        })
        .unwrap_or_default()
}

#[test]
fn every_declared_dependency_is_used() {
    let members = members();
    assert!(members.len() > 15, "found {} members", members.len());
    let mut unused = Vec::new();
    for member in &members {
        let name = member.manifest["package"]["name"].as_str().unwrap_or("?");
        let files = own_sources(&member.dir);
        assert!(
            !files.is_empty(),
            "{name}: no Rust sources under {:?}",
            member.dir
        );
        let code = code_of(&files);
        let ignored = ignored(&member.manifest);
        for dependency in declared(&member.manifest) {
            if !ignored.contains(&dependency) && !names_crate(&code, &ident(&dependency)) {
                unused.push(format!("{name}: {dependency}"));
            }
        }
    }
    assert!(
        unused.is_empty(),
        "dependencies no source names (remove them, or list them in \
         [package.metadata.cargo-machete] ignored with the reason): {unused:#?}"
    );
}

#[test]
fn the_matcher_sees_each_way_of_naming_a_crate_and_nothing_else() {
    for used in [
        "use nalgebra::Vector2;",
        "let v = nalgebra::Vector2::zeros();",
        "pub use nalgebra;",
        "extern crate nalgebra;",
        "    use nalgebra as na;",
        "x.map(nalgebra::norm)",
    ] {
        assert!(names_crate(used, "nalgebra"), "{used}");
    }
    for not_used in [
        "let nalgebra_like = 1;",
        "my_nalgebra::Vector2",
        "self::nalgebra::x",
        "\"nalgebra\"",
        "fn nalgebra() {}",
    ] {
        assert!(!names_crate(not_used, "nalgebra"), "{not_used}");
    }
    assert_eq!(ident("millinav-kit"), "millinav_kit");
}
