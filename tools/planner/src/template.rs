//! A scenario written from a template with a new plan: the plan as its trajectory, its
//! `[run] rig` the rig planned on, the paths the template names relative to itself re-based to
//! where the new scenario is written, and a run long enough for the new path.

use std::path::{Component, Path, PathBuf};

use anyhow::Context;
use millinav_kit::scenario::Scenario;
use millinav_planning::{path_length, scenario_with_plan, Plan};

/// Time a run keeps after the reference reaches the goal, for the capsule to settle there:
/// this fraction of the travel time, at least `MIN_SETTLE_S`.
const SETTLE_FRACTION: f64 = 0.1;
const MIN_SETTLE_S: f64 = 5.0;

/// What the planner changed beyond the trajectory, to tell the user.
pub type Notes = Vec<String>;

/// The scenario text: `template` (read from `template_path`) with `plan`, to be written to
/// `output` (`None`: standard output, so re-based paths become absolute).
pub fn scenario_from_template(
    template_path: &Path,
    rig: &Path,
    plan: &Plan,
    speed_mm_s: Option<f64>,
    output: Option<&Path>,
) -> anyhow::Result<(String, Notes)> {
    let template = std::fs::read_to_string(template_path)
        .with_context(|| format!("reading scenario template {}", template_path.display()))?;
    let template_dir = absolute_dir(template_path)?;
    let output_dir = output.map(absolute_dir).transpose()?;
    let mut notes = Notes::new();
    let rig = rig_for_scenario(rig, output_dir.as_deref(), &mut notes)?;
    let text = scenario_with_plan(&template, plan, speed_mm_s, Some(&rig))?;
    let mut doc: toml::Table = toml::from_str(&text)?;
    rebase_flow_map(&mut doc, &template_dir, output_dir.as_deref(), &mut notes)?;
    let written_at = output.unwrap_or(template_path);
    long_enough_for_the_path(&mut doc, written_at, &mut notes)?;
    Ok((toml::to_string(&doc)?, notes))
}

/// `[flow] map` is read relative to the scenario file: from the new file's place it must name
/// the template's map still.
fn rebase_flow_map(
    doc: &mut toml::Table,
    template_dir: &Path,
    output_dir: Option<&Path>,
    notes: &mut Notes,
) -> anyhow::Result<()> {
    let Some(flow) = doc.get_mut("flow").and_then(toml::Value::as_table_mut) else {
        return Ok(());
    };
    let Some(map) = flow
        .get("map")
        .and_then(toml::Value::as_str)
        .map(PathBuf::from)
    else {
        return Ok(());
    };
    let rebased = rebase(&map, template_dir, output_dir, notes, "[flow] map");
    flow.insert("map".into(), rebased.to_string_lossy().into_owned().into());
    Ok(())
}

/// `path`, given relative to `from_dir`, as the new scenario must write it: unchanged when
/// absolute or when the scenario is written beside it, else relative to `to_dir` (absolute when
/// the scenario goes to standard output).
fn rebase(
    path: &Path,
    from_dir: &Path,
    to_dir: Option<&Path>,
    notes: &mut Notes,
    what: &str,
) -> PathBuf {
    if path.is_absolute() || to_dir == Some(from_dir) {
        return path.to_owned();
    }
    let target = lexically_normal(&from_dir.join(path));
    let rebased = match to_dir {
        Some(dir) => relative_path(dir, &target),
        None => target,
    };
    if rebased != path {
        notes.push(format!(
            "{what} {} is written as {} (the same file, from where the scenario goes)",
            path.display(),
            rebased.display()
        ));
    }
    rebased
}

/// `--rig` as the scenario must name it. A scenario's rig resolves from the repository root
/// first, then from the scenario: a path given from the root stays as it is; one given from
/// elsewhere is re-based like the template's paths.
fn rig_for_scenario(
    rig: &Path,
    output_dir: Option<&Path>,
    notes: &mut Notes,
) -> anyhow::Result<PathBuf> {
    let cwd = lexically_normal(&std::env::current_dir()?);
    let from_root = lexically_normal(&fieldmaps::data_root().join(rig));
    if rig.is_relative() && from_root == lexically_normal(&cwd.join(rig)) {
        return Ok(rig.to_owned());
    }
    Ok(rebase(rig, &cwd, output_dir, notes, "--rig"))
}

/// `[run] duration_s` at least the reference's travel time plus time to settle.
fn long_enough_for_the_path(
    doc: &mut toml::Table,
    written_at: &Path,
    notes: &mut Notes,
) -> anyhow::Result<()> {
    let scenario = Scenario::parse(&toml::to_string(doc)?, written_at)
        .context("the scenario written from the template")?;
    let trajectory = &scenario.trajectory;
    let waypoints: Vec<_> = trajectory
        .waypoints_mm
        .iter()
        .map(|p| nalgebra::Vector2::new(p[0], p[1]))
        .collect();
    let length_mm = path_length(&waypoints);
    let travel_s = length_mm / trajectory.speed_mm_s;
    let needed_s =
        (trajectory.start_time_s + travel_s + (SETTLE_FRACTION * travel_s).max(MIN_SETTLE_S))
            .ceil();
    let duration_s = scenario.run.duration_s;
    if duration_s < needed_s {
        let run = doc
            .get_mut("run")
            .and_then(toml::Value::as_table_mut)
            .context("the scenario has no [run] table")?;
        run.insert("duration_s".into(), needed_s.into());
        notes.push(format!(
            "[run] duration_s {duration_s} s -> {needed_s} s: the path is {length_mm:.1} mm at \
             {} mm/s from {} s, {travel_s:.1} s of travel and time to settle",
            trajectory.speed_mm_s, trajectory.start_time_s
        ));
    }
    Ok(())
}

/// The absolute directory a file is (or will be) in.
fn absolute_dir(file: &Path) -> anyhow::Result<PathBuf> {
    let dir = file.parent().filter(|d| !d.as_os_str().is_empty());
    let dir = match dir {
        Some(d) => d.to_owned(),
        None => PathBuf::from("."),
    };
    let absolute = std::path::absolute(&dir).with_context(|| format!("{}", dir.display()))?;
    Ok(lexically_normal(&absolute))
}

/// `path` without `.` and with each `..` taken against the component before it.
fn lexically_normal(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for component in path.components() {
        match component {
            Component::CurDir => {}
            Component::ParentDir => {
                if !out.pop() {
                    out.push("..");
                }
            }
            other => out.push(other),
        }
    }
    out
}

/// `target` (absolute, normal) as a path relative to the directory `base` (absolute, normal).
fn relative_path(base: &Path, target: &Path) -> PathBuf {
    let base: Vec<Component<'_>> = base.components().collect();
    let target_parts: Vec<Component<'_>> = target.components().collect();
    let common = base
        .iter()
        .zip(&target_parts)
        .take_while(|(a, b)| a == b)
        .count();
    let mut out = PathBuf::new();
    for _ in common..base.len() {
        out.push("..");
    }
    for part in &target_parts[common..] {
        out.push(part);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_path_relative_to_one_directory_is_rewritten_for_another() {
        let target = Path::new("/lab/rigs/ring/maps/q180.npz");
        assert_eq!(
            relative_path(Path::new("/lab/runs/today"), target),
            Path::new("../../rigs/ring/maps/q180.npz")
        );
        assert_eq!(
            relative_path(Path::new("/lab/rigs/ring"), target),
            Path::new("maps/q180.npz")
        );
        assert_eq!(
            lexically_normal(Path::new("/lab/runs/../rigs/./ring")),
            Path::new("/lab/rigs/ring")
        );
    }
}
