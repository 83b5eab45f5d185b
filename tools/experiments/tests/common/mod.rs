//! Helpers shared by the campaign tests.

use std::process::Output;

/// A finished command's exit status and output, for assertion messages.
pub fn text(output: &Output) -> String {
    format!(
        "exit {}\n--- stdout:\n{}\n--- stderr:\n{}",
        output.status,
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    )
}

/// results.csv without its last column, the wall time (the one column that differs between two
/// runs of the same cells).
pub fn without_wall_time(csv: &str) -> String {
    csv.lines()
        .map(|l| l.rsplit_once(',').map_or(l, |(rest, _)| rest))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The arguments that select the short scenario's still 20 cP cells of `controllers` (comma
/// separated) with `trials` seeds: a small matrix that runs in seconds.
pub fn short_static_cells<'a>(controllers: &'a str, trials: &'a str) -> Vec<&'a str> {
    vec![
        "--base",
        "scenarios/short.toml",
        "--only",
        "20cp_static",
        "--controllers",
        controllers,
        "--trials",
        trials,
    ]
}
