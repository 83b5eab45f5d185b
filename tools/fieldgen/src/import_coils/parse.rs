//! Reading one coil's field export: COMSOL spreadsheet or grid text, ANSYS Maxwell field files,
//! generic CSV / whitespace tables. Units come from the file (column units, `% Length unit:`)
//! or, where the file is silent, from the command line; a disagreement is an error.

use std::collections::HashMap;

use nalgebra::{Matrix3, Vector3};

use super::ImportCoilError;
use crate::import::split as split_row;

/// One coil's samples in SI (field T at the export's current, gradient T/m).
#[derive(Debug, Clone, PartialEq)]
pub struct CoilSamples {
    pub positions_m: Vec<Vector3<f64>>,
    pub field_t: Vec<Vector3<f64>>,
    /// ∂B_i/∂x_j at each point when the file has all nine gradient columns.
    pub gradient_t_per_m: Option<Vec<Matrix3<f64>>>,
    /// File line of each sample (1-based), for messages.
    pub lines: Vec<u64>,
    /// What was recognised (for the provenance and the summary).
    pub format: &'static str,
    pub length_unit: String,
    pub field_unit: String,
}

/// Units the command line gives for files that do not say.
#[derive(Debug, Clone, Default)]
pub struct UnitHints {
    pub length: Option<String>,
    pub field: Option<String>,
}

pub(super) fn length_scale(unit: &str) -> Option<f64> {
    match unit {
        "m" => Some(1.0),
        "cm" => Some(1e-2),
        "mm" => Some(1e-3),
        "um" | "µm" => Some(1e-6),
        _ => None,
    }
}

pub(super) fn field_scale(unit: &str) -> Option<f64> {
    match unit {
        "t" | "tesla" => Some(1.0),
        "mt" => Some(1e-3),
        "ut" | "µt" => Some(1e-6),
        "g" | "gauss" => Some(1e-4),
        _ => None,
    }
}

/// `T/m`, `mT/mm`, `G/cm`, …
fn gradient_scale(unit: &str) -> Option<f64> {
    let (f, l) = unit.split_once('/')?;
    Some(field_scale(f)? / length_scale(l)?)
}

/// What a column holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Quantity {
    Position(usize),
    Field(usize),
    Gradient(usize, usize),
}

/// A column name split into its quantity and unit (lower case, no spaces).
fn classify(name: &str) -> (Option<Quantity>, Option<String>) {
    let lower = name.trim().trim_matches('"').to_lowercase();
    // Unit in brackets or parentheses at the end: "x [mm]", "mf.Bx (T)"; not the argument list
    // of "d(mf.Bx,y)".
    let (body, mut unit) = match trailing_group(&lower) {
        Some(open) if open > 0 && lower[..open].trim_end() != "d" => (
            lower[..open].trim().to_string(),
            Some(lower[open + 1..lower.len() - 1].trim().to_string()),
        ),
        _ => (lower.clone(), None),
    };
    let mut body: String = body.chars().filter(|c| !c.is_whitespace()).collect();
    // "x_mm", "bx_mt", "dbx/dx_t/m": unit after the last underscore, when it is one.
    if unit.is_none() {
        if let Some((stem, suffix)) = body.rsplit_once('_') {
            if length_scale(suffix).is_some()
                || field_scale(suffix).is_some()
                || gradient_scale(suffix).is_some()
            {
                unit = Some(suffix.to_string());
                body = stem.to_string();
            }
        }
    }
    let axis = |c: char| "xyz".find(c);
    let quantity = (|| {
        if let Some(k) = ["x", "y", "z"].iter().position(|a| *a == body) {
            return Some(Quantity::Position(k));
        }
        // d(mf.Bx,y) (COMSOL), dBx/dy, dBx_dy, dBxdy.
        let grad = body
            .strip_prefix("d(")
            .and_then(|s| s.strip_suffix(')'))
            .and_then(|s| s.split_once(','))
            .map(|(f, x)| (f.rsplit('.').next().unwrap_or(f).to_string(), x.to_string()))
            .or_else(|| {
                let s = body.strip_prefix('d')?;
                let s = s.rsplit('.').next().unwrap_or(s);
                let (f, x) = s
                    .split_once("/d")
                    .or_else(|| s.split_once("_d"))
                    .or_else(|| {
                        (s.len() == 4)
                            .then(|| s.split_at(2))
                            .map(|(f, x)| (f, &x[1..]))
                    })?;
                Some((f.to_string(), x.to_string()))
            });
        if let Some((f, x)) = grad {
            let mut fc = f.chars();
            if let (Some('b'), Some(i), None) = (fc.next(), fc.next(), fc.next()) {
                if let (Some(i), Some(j)) = (axis(i), x.chars().next().and_then(axis)) {
                    if x.len() == 1 {
                        return Some(Quantity::Gradient(i, j));
                    }
                }
            }
        }
        let field = body.rsplit('.').next().unwrap_or(&body);
        let mut fc = field.chars();
        if let (Some('b'), Some(i), None) = (fc.next(), fc.next(), fc.next()) {
            return axis(i).map(Quantity::Field);
        }
        None
    })();
    (quantity, unit)
}

/// Start of the bracketed group that ends `text`, if it ends with `)` or `]`.
fn trailing_group(text: &str) -> Option<usize> {
    let close = text.chars().last().filter(|c| matches!(c, ')' | ']'))?;
    let open = if close == ')' { '(' } else { '[' };
    let mut depth = 0;
    for (i, c) in text.char_indices().rev() {
        if c == close {
            depth += 1;
        } else if c == open {
            depth -= 1;
            if depth == 0 {
                return Some(i);
            }
        }
    }
    None
}

/// Splits a header line into column names: commas when there are any, else whitespace, with a
/// lone unit token ("(T)", "[mm]") joined to the name before it.
fn split_header(line: &str) -> Vec<String> {
    if line.contains(',') {
        return line.split(',').map(|s| s.trim().to_string()).collect();
    }
    let mut names: Vec<String> = Vec::new();
    for token in line.split_whitespace() {
        match names.last_mut() {
            Some(last) if token.starts_with(['(', '[']) => {
                last.push(' ');
                last.push_str(token);
            }
            _ => names.push(token.to_string()),
        }
    }
    names
}

fn is_data(line: &str) -> bool {
    let cells = split_row(line);
    !cells.is_empty()
        && cells
            .iter()
            .all(|c| c.parse::<f64>().is_ok() || c.eq_ignore_ascii_case("nan"))
}

/// Resolve a group's unit: from the columns (all equal), the file header, or the hint.
fn group_unit(
    file: &str,
    what: &str,
    column_units: &[(String, Option<String>)],
    header_unit: Option<&str>,
    hint: Option<&str>,
    hint_flag: &str,
) -> Result<String, ImportCoilError> {
    let given: Vec<&(String, Option<String>)> =
        column_units.iter().filter(|(_, u)| u.is_some()).collect();
    let from_columns = match given.first() {
        Some((_, Some(u))) => {
            if let Some((name, other)) = given.iter().find(|(_, v)| v.as_deref() != Some(u)) {
                return Err(ImportCoilError::Units {
                    file: file.into(),
                    message: format!(
                        "{what} columns use different units: {} is in {u}, {name} in {}",
                        given[0].0,
                        other.as_deref().unwrap_or("?")
                    ),
                });
            }
            if given.len() < column_units.len() {
                let missing: Vec<&str> = column_units
                    .iter()
                    .filter(|(_, u)| u.is_none())
                    .map(|(n, _)| n.as_str())
                    .collect();
                return Err(ImportCoilError::Units {
                    file: file.into(),
                    message: format!(
                        "{what} columns {} give no unit while {} does ({u})",
                        missing.join(", "),
                        given[0].0
                    ),
                });
            }
            Some(u.clone())
        }
        _ => None,
    };
    let from_file = from_columns.or_else(|| header_unit.map(str::to_string));
    match (from_file, hint) {
        (Some(u), Some(h)) if u != h.to_lowercase() => Err(ImportCoilError::Units {
            file: file.into(),
            message: format!("the file gives {what} in {u} but {hint_flag} says {h}"),
        }),
        (Some(u), _) => Ok(u),
        (None, Some(h)) => Ok(h.to_lowercase()),
        (None, None) => Err(ImportCoilError::Units {
            file: file.into(),
            message: format!("the file does not say the {what} unit; pass {hint_flag}"),
        }),
    }
}

/// Reads one export.
pub fn parse_export(
    text: &str,
    file: &str,
    hints: &UnitHints,
) -> Result<CoilSamples, ImportCoilError> {
    let lines: Vec<(u64, &str)> = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i as u64 + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty())
        .collect();
    let mut header_length_unit = None;
    for (_, l) in &lines {
        let body = l.trim_start_matches(['%', '#']).trim();
        if let Some((key, value)) = body.split_once(':') {
            if key.trim().eq_ignore_ascii_case("length unit") {
                header_length_unit = Some(value.trim().to_lowercase());
            }
        }
    }
    if lines.iter().any(|(_, l)| {
        l.trim_start_matches('%')
            .trim()
            .eq_ignore_ascii_case("grid")
    }) {
        return parse_comsol_grid(&lines, file, hints, header_length_unit.as_deref());
    }
    // Table: the last non-data line before the first data line names the columns.
    let first_data = lines
        .iter()
        .position(|(_, l)| !l.starts_with(['%', '#']) && is_data(l))
        .ok_or_else(|| ImportCoilError::Format {
            file: file.into(),
            message: "no numeric data rows".into(),
        })?;
    let header = lines[..first_data]
        .iter()
        .rev()
        .map(|(_, l)| l.trim_start_matches(['%', '#']).trim())
        .find(|l| !l.is_empty() && (!l.contains(':') || l.contains(',')))
        .ok_or_else(|| ImportCoilError::Format {
            file: file.into(),
            message: "no header row naming the columns (x y z Bx By Bz …)".into(),
        })?;
    let names = split_header(header);
    let mut columns: HashMap<Quantity, usize> = HashMap::new();
    let mut units: HashMap<Quantity, Option<String>> = HashMap::new();
    for (col, name) in names.iter().enumerate() {
        let (q, unit) = classify(name);
        if let Some(q) = q {
            if columns.insert(q, col).is_some() {
                return Err(ImportCoilError::Format {
                    file: file.into(),
                    message: format!("two columns for the same quantity ({name})"),
                });
            }
            units.insert(q, unit);
        }
    }
    let mut format = if lines[0].1.starts_with('%') {
        "COMSOL spreadsheet"
    } else {
        "table"
    };
    // Maxwell .fld: `X,Y,Z,Vector data "<Bx,By,Bz>"`, SI units.
    if !(0..3).all(|k| columns.contains_key(&Quantity::Field(k)))
        && header.to_lowercase().contains("<bx,by,bz>")
    {
        for k in 0..3 {
            columns.insert(Quantity::Position(k), k);
            columns.insert(Quantity::Field(k), 3 + k);
            units.insert(Quantity::Position(k), None);
            units.insert(Quantity::Field(k), None);
        }
        format = "Maxwell field file";
    }
    let group = |qs: &[Quantity]| -> Result<Vec<usize>, String> {
        qs.iter()
            .map(|q| columns.get(q).copied().ok_or_else(|| format!("{q:?}")))
            .collect()
    };
    let pos_q = [0, 1, 2].map(Quantity::Position);
    let field_q = [0, 1, 2].map(Quantity::Field);
    let grad_q: Vec<Quantity> = (0..9).map(|k| Quantity::Gradient(k / 3, k % 3)).collect();
    let missing = |what: &str| ImportCoilError::Format {
        file: file.into(),
        message: format!(
            "no {what} columns recognised; columns found: {} (expected x, y, z, Bx, By, Bz with \
             units, e.g. `x [mm]`, `mf.Bx (T)`, `Bx_mT`)",
            names.join(" | ")
        ),
    };
    let pos_cols = group(&pos_q).map_err(|_| missing("position"))?;
    let field_cols = group(&field_q).map_err(|_| missing("field"))?;
    let grad_count = grad_q.iter().filter(|q| columns.contains_key(q)).count();
    let grad_cols = match grad_count {
        0 => None,
        9 => Some(group(&grad_q).unwrap_or_default()),
        n => {
            return Err(ImportCoilError::Format {
                file: file.into(),
                message: format!("{n} of the 9 gradient columns dBi/dxj; give all nine or none"),
            })
        }
    };
    let unit_list = |qs: &[Quantity]| -> Vec<(String, Option<String>)> {
        qs.iter()
            .map(|q| (names[columns[q]].clone(), units[q].clone()))
            .collect()
    };
    let length_unit = group_unit(
        file,
        "length",
        &unit_list(&pos_q),
        header_length_unit.as_deref(),
        hints.length.as_deref(),
        "--length-unit",
    )?;
    let field_unit = group_unit(
        file,
        "field",
        &unit_list(&field_q),
        None,
        hints.field.as_deref(),
        "--field-unit",
    )?;
    let bad_unit = |what: &str, u: &str| ImportCoilError::Units {
        file: file.into(),
        message: format!("unknown {what} unit {u:?}"),
    };
    let ls = length_scale(&length_unit).ok_or_else(|| bad_unit("length", &length_unit))?;
    let fs = field_scale(&field_unit).ok_or_else(|| bad_unit("field", &field_unit))?;
    let gs = match &grad_cols {
        None => 0.0,
        Some(_) => {
            let default = format!("{field_unit}/{length_unit}");
            let u = group_unit(
                file,
                "gradient",
                &unit_list(&grad_q),
                Some(&default),
                None,
                "",
            )?;
            gradient_scale(&u).ok_or_else(|| bad_unit("gradient", &u))?
        }
    };
    let mut out = CoilSamples {
        positions_m: Vec::new(),
        field_t: Vec::new(),
        gradient_t_per_m: grad_cols.as_ref().map(|_| Vec::new()),
        lines: Vec::new(),
        format,
        length_unit,
        field_unit,
    };
    for &(line, text) in &lines[first_data..] {
        if text.starts_with(['%', '#']) {
            continue;
        }
        let cells = split_row(text);
        let value = |col: usize| -> Result<f64, ImportCoilError> {
            let raw = cells.get(col).copied().unwrap_or("");
            raw.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| ImportCoilError::Row {
                    file: file.into(),
                    line,
                    message: format!(
                        "column {} ({}): {raw:?} is not a finite number",
                        col + 1,
                        names.get(col).map_or("?", String::as_str)
                    ),
                })
        };
        let v3 = |cols: &[usize], s: f64| -> Result<Vector3<f64>, ImportCoilError> {
            Ok(Vector3::new(value(cols[0])?, value(cols[1])?, value(cols[2])?) * s)
        };
        out.positions_m.push(v3(&pos_cols, ls)?);
        out.field_t.push(v3(&field_cols, fs)?);
        if let (Some(cols), Some(g)) = (&grad_cols, out.gradient_t_per_m.as_mut()) {
            let mut m = Matrix3::zeros();
            for (k, &c) in cols.iter().enumerate() {
                m[(k / 3, k % 3)] = value(c)? * gs;
            }
            g.push(m);
        }
        out.lines.push(line);
    }
    Ok(out)
}

/// One `% Data` block of a COMSOL grid file: its quantity and unit (when labelled) and rows.
type DataBlock<'a> = (Option<Quantity>, Option<String>, Vec<(u64, Vec<&'a str>)>);

/// COMSOL's grid format: `% Grid`, one line of x values, one of y, one of z, then for each
/// expression a `% Data` block of nz·ny rows of nx values (x fastest, then y, then z), the
/// expression named on the `% Data` line or on a `%` line right after it (else Bx, By, Bz in
/// order).
fn parse_comsol_grid(
    lines: &[(u64, &str)],
    file: &str,
    hints: &UnitHints,
    header_length_unit: Option<&str>,
) -> Result<CoilSamples, ImportCoilError> {
    let err = |message: String| ImportCoilError::Format {
        file: file.into(),
        message,
    };
    let grid_at = lines
        .iter()
        .position(|(_, l)| {
            l.trim_start_matches('%')
                .trim()
                .eq_ignore_ascii_case("grid")
        })
        .unwrap_or(0);
    let axis_values = |k: usize| -> Result<Vec<f64>, ImportCoilError> {
        let (line, text) = lines
            .get(grid_at + 1 + k)
            .ok_or_else(|| err("grid axes missing after % Grid".into()))?;
        text.split_whitespace()
            .map(|t| {
                t.parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| ImportCoilError::Row {
                        file: file.into(),
                        line: *line,
                        message: format!("grid axis value {t:?} is not a finite number"),
                    })
            })
            .collect()
    };
    let axes = [axis_values(0)?, axis_values(1)?, axis_values(2)?];
    let length_unit = group_unit(
        file,
        "length",
        &[],
        header_length_unit,
        hints.length.as_deref(),
        "--length-unit",
    )?;
    let ls = length_scale(&length_unit).ok_or_else(|| ImportCoilError::Units {
        file: file.into(),
        message: format!("unknown length unit {length_unit:?}"),
    })?;
    let [nx, ny, nz] = [axes[0].len(), axes[1].len(), axes[2].len()];
    let mut blocks: Vec<DataBlock<'_>> = Vec::new();
    let mut i = grid_at + 4;
    while i < lines.len() {
        let (_, text) = lines[i];
        let body = text.trim_start_matches('%').trim();
        if text.starts_with('%') && body.to_lowercase().starts_with("data") {
            let mut label = body[4..]
                .trim()
                .trim_start_matches(['(', ':'])
                .trim()
                .to_string();
            if label.ends_with(')') && label.matches('(').count() < label.matches(')').count() {
                label.pop();
            }
            if label.is_empty() {
                if let Some((_, next)) = lines.get(i + 1).filter(|(_, l)| l.starts_with('%')) {
                    label = next.trim_start_matches('%').trim().to_string();
                    i += 1;
                }
            }
            let (q, unit) = if label.is_empty() {
                (None, None)
            } else {
                classify(&label)
            };
            blocks.push((q, unit, Vec::new()));
        } else if !text.starts_with('%') {
            let Some(block) = blocks.last_mut() else {
                return Err(err(format!(
                    "line {}: data before any % Data line",
                    lines[i].0
                )));
            };
            block
                .2
                .push((lines[i].0, text.split_whitespace().collect()));
        }
        i += 1;
    }
    if blocks.len() < 3 {
        return Err(err(format!(
            "{} % Data blocks; need Bx, By and Bz (and optionally the 9 gradient components)",
            blocks.len()
        )));
    }
    let mut field = vec![Vector3::zeros(); nx * ny * nz];
    let mut found = [false; 3];
    let mut field_units: Vec<(String, Option<String>)> = Vec::new();
    let mut values_of = Vec::new();
    for (k, (q, unit, rows)) in blocks.iter().enumerate() {
        let comp = match q {
            Some(Quantity::Field(c)) => *c,
            None if k < 3 => k,
            _ => continue,
        };
        if rows.len() != ny * nz {
            return Err(err(format!(
                "data block {} has {} rows; the grid needs ny·nz = {}",
                k + 1,
                rows.len(),
                ny * nz
            )));
        }
        let mut values = Vec::with_capacity(nx * ny * nz);
        for (line, cells) in rows {
            if cells.len() != nx {
                return Err(ImportCoilError::Row {
                    file: file.into(),
                    line: *line,
                    message: format!("{} values; the grid has nx = {nx}", cells.len()),
                });
            }
            for c in cells {
                values.push((
                    *line,
                    c.parse::<f64>()
                        .ok()
                        .filter(|v| v.is_finite())
                        .ok_or_else(|| ImportCoilError::Row {
                            file: file.into(),
                            line: *line,
                            message: format!("{c:?} is not a finite number"),
                        })?,
                ));
            }
        }
        found[comp] = true;
        field_units.push((format!("B{}", ["x", "y", "z"][comp]), unit.clone()));
        values_of.push((comp, values));
    }
    if found.iter().any(|f| !f) {
        return Err(err("data blocks for Bx, By and Bz not all found".into()));
    }
    let field_unit = group_unit(
        file,
        "field",
        &field_units,
        None,
        hints.field.as_deref(),
        "--field-unit",
    )?;
    let fs = field_scale(&field_unit).ok_or_else(|| ImportCoilError::Units {
        file: file.into(),
        message: format!("unknown field unit {field_unit:?}"),
    })?;
    let mut line_of = vec![0u64; nx * ny * nz];
    for (comp, values) in values_of {
        for (n, (line, v)) in values.into_iter().enumerate() {
            field[n][comp] = v * fs;
            line_of[n] = line;
        }
    }
    let mut positions = Vec::with_capacity(nx * ny * nz);
    for z in &axes[2] {
        for y in &axes[1] {
            for x in &axes[0] {
                positions.push(Vector3::new(*x, *y, *z) * ls);
            }
        }
    }
    Ok(CoilSamples {
        positions_m: positions,
        field_t: field,
        gradient_t_per_m: None,
        lines: line_of,
        format: "COMSOL grid",
        length_unit,
        field_unit,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn column_names_are_recognised() {
        let q = |n: &str| classify(n);
        assert_eq!(q("x"), (Some(Quantity::Position(0)), None));
        assert_eq!(
            q("x [mm]"),
            (Some(Quantity::Position(0)), Some("mm".into()))
        );
        assert_eq!(q("X_mm"), (Some(Quantity::Position(0)), Some("mm".into())));
        assert_eq!(q("mf.Bx (T)"), (Some(Quantity::Field(0)), Some("t".into())));
        assert_eq!(q("Bz_mT"), (Some(Quantity::Field(2)), Some("mt".into())));
        assert_eq!(
            q("d(mf.By,z) (T/m)"),
            (Some(Quantity::Gradient(1, 2)), Some("t/m".into()))
        );
        assert_eq!(
            q("dBx/dy [mT/mm]"),
            (Some(Quantity::Gradient(0, 1)), Some("mt/mm".into()))
        );
        assert_eq!(
            q("dBzdx_T/m"),
            (Some(Quantity::Gradient(2, 0)), Some("t/m".into()))
        );
        assert_eq!(q("mf.normB (T)").0, None);
        assert_eq!(
            split_header("x                       y        z        mf.Bx (T)      mf.By (T)"),
            vec!["x", "y", "z", "mf.Bx (T)", "mf.By (T)"]
        );
    }
}
