//! Pointing TOML parser errors at a key path (`coils[3].winding.length_mm`).

/// `[name]` / `[[name]]` header of a line, with whether it is an array of tables. Lines of a
/// multi-line array value (`[1.0, 2.0],`) are not headers.
fn header_of(line: &str) -> Option<(String, bool)> {
    let line = line.split('#').next().unwrap_or("").trim();
    let (inner, array) = if let Some(rest) = line.strip_prefix("[[") {
        (rest.strip_suffix("]]")?, true)
    } else {
        (line.strip_prefix('[')?.strip_suffix(']')?, false)
    };
    let inner = inner.trim();
    let first = inner.chars().next()?;
    let key_like = (first.is_ascii_alphabetic() || first == '_')
        && inner
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.' | ' '));
    key_like.then(|| (inner.replace(' ', ""), array))
}

/// Best-effort key path (`coils[3].winding.length_mm`) of the TOML text at byte `offset`, from
/// the table headers above it; for pointing errors from the parser at a field.
pub(super) fn key_path_at(text: &str, offset: usize) -> String {
    let mut counts = std::collections::HashMap::<String, usize>::new();
    let mut table = String::new();
    let mut last_key: Option<String> = None;
    let mut line_start = 0;
    let indexed = |name: &str, counts: &std::collections::HashMap<String, usize>| {
        let mut out = String::new();
        let mut prefix = String::new();
        for (k, part) in name.split('.').enumerate() {
            if k > 0 {
                prefix.push('.');
                out.push('.');
            }
            prefix.push_str(part);
            out.push_str(part);
            if let Some(n) = counts.get(&prefix) {
                out.push_str(&format!("[{}]", n.saturating_sub(1)));
            }
        }
        out
    };
    for line in text.split_inclusive('\n') {
        let end = line_start + line.len();
        let here = offset >= line_start && offset < end;
        if let Some((name, array)) = header_of(line) {
            if array {
                *counts.entry(name.clone()).or_default() += 1;
            }
            table = indexed(&name, &counts);
            last_key = None;
            if here {
                return table;
            }
        } else {
            let code = line.split('#').next().unwrap_or("");
            if let Some((key, _)) = code.split_once('=') {
                let key = key.trim();
                if !key.is_empty() && !key.starts_with('[') && !key.starts_with('{') {
                    last_key = Some(key.trim_matches('"').to_string());
                }
            }
            if here {
                break;
            }
        }
        line_start = end;
    }
    match (table.is_empty(), last_key) {
        (_, None) => table,
        (true, Some(key)) => key,
        (false, Some(key)) => format!("{table}.{key}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn key_paths_follow_headers() {
        let text = "format = 1\n[electromagnet]\nfield_model = 2\n[[coils]]\nname = 1\n\
                    [[coils]]\nname = 2\nturns = 3\n[coils.winding]\nlength_mm = 4\n\
                    [phantom]\n[[phantom.zones]]\npolygon_mm = [\n  [1.0, 2.0],\n  [3.0, 4.0],\n]\n";
        let at = |needle: &str| key_path_at(text, text.find(needle).unwrap());
        assert_eq!(at("format"), "format");
        assert_eq!(at("field_model"), "electromagnet.field_model");
        assert_eq!(at("name = 1"), "coils[0].name");
        assert_eq!(at("turns"), "coils[1].turns");
        assert_eq!(at("length_mm"), "coils[1].winding.length_mm");
        assert_eq!(at("[3.0"), "phantom.zones[0].polygon_mm");
        assert_eq!(at("[[phantom.zones]]"), "phantom.zones[0]");
    }
}
