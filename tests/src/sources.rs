//! The workspace's own sources and manifests, read by the tests that check the code's shape
//! (`no_paper_constants`, `crate_graph`): Rust files, which of them are unit-test modules, the
//! code a file runs outside its tests.

use std::path::{Path, PathBuf};

/// The repository's root (where the workspace `Cargo.toml` lives).
pub fn workspace_root() -> PathBuf {
    fieldmaps::data_root()
}

/// Every `.rs` file under `dir`, recursively (none when `dir` does not exist).
pub fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    collect_rust_files(dir, &mut out);
    out.sort();
    out
}

fn collect_rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_dir() {
            collect_rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The files of modules declared `#[cfg(test)] mod name;`: unit tests kept in a file of their
/// own (`name.rs` or `name/mod.rs` in the declaring module's directory).
pub fn test_module_files(files: &[PathBuf]) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for file in files {
        let Ok(text) = std::fs::read_to_string(file) else {
            continue;
        };
        let dir = module_dir(file);
        let mut lines = text.lines().map(str::trim);
        while let Some(line) = lines.next() {
            if line != "#[cfg(test)]" {
                continue;
            }
            let Some(next) = lines.next() else { break };
            let declared = module_item(next)
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

/// `line` without a leading visibility (`pub`, `pub(crate)`, `pub(super)`, `pub(in …)`), so a
/// `pub(crate) mod tests` reads as `mod tests`.
fn module_item(line: &str) -> &str {
    let Some(rest) = line.strip_prefix("pub") else {
        return line;
    };
    let rest = match rest.strip_prefix('(') {
        Some(scoped) => scoped.split_once(')').map_or(scoped, |(_, after)| after),
        None => rest,
    };
    rest.trim_start()
}

/// The directory holding the files of `file`'s child modules: `lib.rs`, `main.rs` and `mod.rs`
/// own their directory, `foo.rs` owns `foo/`.
fn module_dir(file: &Path) -> PathBuf {
    let stem = file.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    let parent = file.parent().unwrap_or(Path::new("."));
    if matches!(stem, "lib" | "main" | "mod") {
        parent.to_path_buf()
    } else {
        parent.join(stem)
    }
}

/// The source before its first inline `#[cfg(test)] mod name {` block (a `#[cfg(test)] mod
/// name;` declaration does not end it: code after it is still a code path).
pub fn before_inline_tests(text: &str) -> &str {
    const ATTRIBUTE: &str = "#[cfg(test)]";
    let mut from = 0;
    while let Some(at) = text[from..].find(ATTRIBUTE) {
        let start = from + at;
        let rest = text[start + ATTRIBUTE.len()..].trim_start();
        let header = rest.lines().next().unwrap_or("");
        if module_item(header).starts_with("mod ") && header.trim_end().ends_with('{') {
            return &text[..start];
        }
        from = start + 1;
    }
    text
}

/// `line` without its `//` comment (doc comments included).
pub fn without_comment(line: &str) -> &str {
    line.split("//").next().unwrap_or("")
}

/// The code paths of a crate's `src/`: each non-test file and its text before inline tests.
pub fn code_paths(src: &Path) -> Vec<(PathBuf, String)> {
    let files = rust_files(src);
    let tests = test_module_files(&files);
    files
        .into_iter()
        .filter(|f| !tests.contains(f))
        .filter_map(|f| {
            let text = std::fs::read_to_string(&f).ok()?;
            let code = before_inline_tests(&text).to_string();
            Some((f, code))
        })
        .collect()
}
