//! Sample statistics and the Markdown table.

use std::fmt::Write as _;
use std::time::Instant;

/// Median and p99 of a set of samples, nanoseconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stats {
    pub n: usize,
    pub median_ns: f64,
    pub p99_ns: f64,
}

impl Stats {
    /// Nearest-rank percentiles; `None` for no samples.
    pub fn of(samples: &[f64]) -> Option<Self> {
        if samples.is_empty() {
            return None;
        }
        let mut s = samples.to_vec();
        s.sort_by(|a, b| a.total_cmp(b));
        let rank = |q: f64| s[((q * s.len() as f64).ceil() as usize).clamp(1, s.len()) - 1];
        Some(Self {
            n: s.len(),
            median_ns: rank(0.5),
            p99_ns: rank(0.99),
        })
    }
}

/// Times `f` `iters` times after `warmup` untimed calls; one sample (ns) per call.
pub fn time_each(warmup: usize, iters: usize, mut f: impl FnMut(usize)) -> Vec<f64> {
    for i in 0..warmup {
        f(i);
    }
    (0..iters)
        .map(|i| {
            let t = Instant::now();
            f(warmup + i);
            t.elapsed().as_nanos() as f64
        })
        .collect()
}

/// Pass/fail of a row against its target.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    Pass,
    Fail,
    Info,
}

/// One line of the table.
#[derive(Debug, Clone)]
pub struct Row {
    pub area: &'static str,
    pub what: String,
    /// Statistics with the unit they are printed in (time rows: ns; ratio/rate rows: value).
    pub value: RowValue,
    pub target: String,
    pub verdict: Verdict,
}

#[derive(Debug, Clone)]
pub enum RowValue {
    Time(Stats),
    /// Median and p99 of a dimensionless quantity (ratios), or one number (p99 = median).
    Number {
        median: f64,
        p99: f64,
        unit: &'static str,
        n: usize,
    },
    Text(String),
}

impl Row {
    pub fn time(area: &'static str, what: impl Into<String>, stats: Option<Stats>) -> Self {
        Self {
            area,
            what: what.into(),
            value: match stats {
                Some(s) => RowValue::Time(s),
                None => RowValue::Text("no samples".into()),
            },
            target: String::new(),
            verdict: Verdict::Info,
        }
    }

    pub fn text(area: &'static str, what: impl Into<String>, text: impl Into<String>) -> Self {
        Self {
            area,
            what: what.into(),
            value: RowValue::Text(text.into()),
            target: String::new(),
            verdict: Verdict::Info,
        }
    }

    /// Sets a target and judges it with `pass`.
    pub fn target(mut self, target: impl Into<String>, pass: bool) -> Self {
        self.target = target.into();
        self.verdict = if pass { Verdict::Pass } else { Verdict::Fail };
        self
    }

    pub fn p99_ns(&self) -> Option<f64> {
        match self.value {
            RowValue::Time(s) => Some(s.p99_ns),
            _ => None,
        }
    }
}

/// Human time: ns, µs or ms with 3 significant-ish digits.
pub fn fmt_ns(ns: f64) -> String {
    if ns < 1e3 {
        format!("{ns:.0} ns")
    } else if ns < 1e6 {
        format!("{:.1} µs", ns / 1e3)
    } else if ns < 1e9 {
        format!("{:.2} ms", ns / 1e6)
    } else {
        format!("{:.2} s", ns / 1e9)
    }
}

/// The Markdown table of `rows`.
pub fn markdown(rows: &[Row]) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "| area | measurement | n | median | p99 | target | result |"
    );
    let _ = writeln!(out, "|---|---|---:|---:|---:|---|---|");
    for r in rows {
        let (n, med, p99) = match &r.value {
            RowValue::Time(s) => (s.n.to_string(), fmt_ns(s.median_ns), fmt_ns(s.p99_ns)),
            RowValue::Number {
                median,
                p99,
                unit,
                n,
            } => (
                n.to_string(),
                format!("{median:.1}{unit}"),
                format!("{p99:.1}{unit}"),
            ),
            RowValue::Text(t) => ("".into(), t.clone(), "".into()),
        };
        let verdict = match r.verdict {
            Verdict::Pass => "pass",
            Verdict::Fail => "**FAIL**",
            Verdict::Info => "",
        };
        let _ = writeln!(
            out,
            "| {} | {} | {} | {} | {} | {} | {} |",
            r.area, r.what, n, med, p99, r.target, verdict
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_use_nearest_rank() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        let s = Stats::of(&v).unwrap();
        assert_eq!(s.median_ns, 50.0);
        assert_eq!(s.p99_ns, 99.0);
        assert_eq!(Stats::of(&[]), None);
    }

    #[test]
    fn table_has_one_line_per_row() {
        let rows = vec![
            Row::time("x", "a", Stats::of(&[1.0, 2.0])).target("< 1 s", true),
            Row::text("x", "b", "pending"),
        ];
        let t = markdown(&rows);
        assert_eq!(t.lines().count(), 4);
        assert!(t.contains("pending"));
    }
}
