//! The documentation's internal links: every relative link and image of the README, the docs
//! book and the reference pages beside the code must name a file of the repository, and a
//! `#fragment` a heading of the page it points at (as mdBook and GitHub make its anchor).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the repository")
        .to_owned()
}

/// The Markdown pages a reader follows links from.
fn pages(root: &Path) -> Vec<PathBuf> {
    let mut pages = vec![
        root.join("README.md"),
        root.join("shm_schemas/CONTRACT.md"),
        root.join("services/teensy_protocol/PROTOCOL.md"),
        root.join("firmware/FIRMWARE.md"),
    ];
    let mut dirs = vec![root.join("docs")];
    while let Some(dir) = dirs.pop() {
        let entries = std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        for entry in entries.flatten() {
            let path = entry.path();
            if path.is_dir() {
                // The built book.
                if path != root.join("docs/book") {
                    dirs.push(path);
                }
            } else if path.extension().is_some_and(|e| e == "md") {
                pages.push(path);
            }
        }
    }
    pages.retain(|p| p.is_file());
    pages.sort();
    pages
}

/// The targets of `[text](target)` and `![alt](target)` outside code spans and blocks.
fn links(text: &str) -> Vec<String> {
    let mut found = Vec::new();
    let mut in_block = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            in_block = !in_block;
            continue;
        }
        if in_block {
            continue;
        }
        // Code spans hold no links.
        let prose: String = line
            .split('`')
            .enumerate()
            .filter(|(i, _)| i % 2 == 0)
            .map(|(_, part)| part)
            .collect::<Vec<_>>()
            .join(" ");
        let mut rest = prose.as_str();
        while let Some(at) = rest.find("](") {
            let after = &rest[at + 2..];
            let Some(end) = after.find(')') else {
                break;
            };
            let target = after[..end].split_whitespace().next().unwrap_or("");
            found.push(target.to_owned());
            rest = &after[end..];
        }
    }
    found
}

/// A heading's anchor as mdBook and GitHub make it: lower case, spaces to '-', other
/// punctuation but '-' and '_' dropped.
fn anchor(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

fn anchors(text: &str) -> BTreeSet<String> {
    let mut in_block = false;
    let mut found = BTreeSet::new();
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            in_block = !in_block;
        } else if !in_block && line.starts_with('#') {
            found.insert(anchor(line.trim_start_matches('#')));
        }
    }
    found
}

/// What is wrong with one link of `page`, if anything.
fn broken(page: &Path, target: &str) -> Option<String> {
    if target.is_empty() {
        return Some("an empty link".into());
    }
    if target.contains("://") || target.starts_with("mailto:") {
        return None;
    }
    let (file, fragment) = match target.split_once('#') {
        Some((file, fragment)) => (file, Some(fragment)),
        None => (target, None),
    };
    let path = if file.is_empty() {
        page.to_owned()
    } else {
        page.parent().expect("a directory").join(file)
    };
    if !path.exists() {
        return Some(format!("{} does not exist", path.display()));
    }
    let fragment = fragment?;
    if path.extension().is_none_or(|e| e != "md") {
        return None;
    }
    let text = std::fs::read_to_string(&path).ok()?;
    (!anchors(&text).contains(fragment))
        .then(|| format!("{} has no heading #{fragment}", path.display()))
}

#[test]
fn every_internal_link_and_image_of_the_docs_resolves() {
    let root = root();
    let mut problems = Vec::new();
    let mut checked = 0;
    for page in pages(&root) {
        let text = std::fs::read_to_string(&page).expect("a page");
        for target in links(&text) {
            checked += 1;
            if let Some(problem) = broken(&page, &target) {
                let shown = page
                    .strip_prefix(&root)
                    .unwrap_or(&page)
                    .display()
                    .to_string();
                problems.push(format!("{shown}: ({target}): {problem}"));
            }
        }
    }
    assert!(
        checked > 100,
        "only {checked} links found: is the parser blind?"
    );
    assert!(
        problems.is_empty(),
        "broken links:\n{}",
        problems.join("\n")
    );
}

#[test]
fn the_checker_finds_a_missing_page_and_a_missing_heading() {
    let page = root().join("docs/bring-up.md");
    assert!(broken(&page, "coils.md").is_none());
    assert!(broken(&page, "nowhere.md").is_some());
    let text = std::fs::read_to_string(root().join("docs/coils.md")).expect("coils.md");
    let heading = anchors(&text).into_iter().next().expect("a heading");
    assert!(broken(&page, &format!("coils.md#{heading}")).is_none());
    assert!(broken(&page, "coils.md#no-such-heading").is_some());
    assert_eq!(
        anchor(" Gaussmeter measurements"),
        "gaussmeter-measurements"
    );
    assert_eq!(
        anchor("The `[restart]` table: 1.5 ms"),
        "the-restart-table-15-ms"
    );
    assert_eq!(
        links("see [a](a.md) and `[b](b.md)` and ![c](img/c.png)"),
        ["a.md", "img/c.png"]
    );
}
