//! Evaluation of the localizers on a dataset split (ROI crops with ground truth): pixel
//! precision / recall / IoU of the mask, keypoint errors in mm and per-crop latency, for the UNet
//! and the classical localizer on the same inputs.

use std::time::Instant;

use millinav_roi::dataset::Split;
use millinav_roi::roi::{Crop, DOWNSAMPLE, INPUT_PX};
use opencv::prelude::*;

use millinav_vision::classical::{ClassicalLocalizer, LocalizeError};
use millinav_vision::unet::{detection_from_output, UnetLocalizer};

/// Metrics of one localizer over a split.
#[derive(Debug, Clone, Default)]
pub struct Report {
    pub name: &'static str,
    pub samples: usize,
    pub precision: f64,
    pub recall: f64,
    pub iou: f64,
    /// Detections on crops with a robot / crops with a robot.
    pub detection_rate: f64,
    /// Detections on crops without a robot / crops without a robot.
    pub false_detection_rate: f64,
    /// True poses the gates rejected, / crops with a robot: no detection (the UNet's presence
    /// gate, the classical blob search), implausible mask area, implausible tip–tail spacing
    /// (UNet) or no visible magnet (classical).
    pub rejected_not_found: f64,
    pub rejected_area: f64,
    pub rejected_spacing: f64,
    pub centroid_err_mm_median: f64,
    pub centroid_err_mm_p95: f64,
    pub tip_err_mm_median: f64,
    pub tip_err_mm_p95: f64,
    pub latency_ms_median: f64,
    pub latency_ms_p99: f64,
}

fn quantile(values: &mut [f64], q: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    values.sort_by(|a, b| a.total_cmp(b));
    let i = ((values.len() - 1) as f64 * q).round() as usize;
    values[i]
}

#[derive(Default)]
struct Tally {
    tp: u64,
    fp: u64,
    fn_: u64,
    found: usize,
    with_robot: usize,
    false_found: usize,
    without_robot: usize,
    rejected: [usize; 3],
    centroid: Vec<f64>,
    tip: Vec<f64>,
    latency_ms: Vec<f64>,
}

impl Tally {
    fn mask(&mut self, predicted: &[u8], truth: &[u8]) {
        for (p, t) in predicted.iter().zip(truth) {
            match (*p > 0, *t > 0) {
                (true, true) => self.tp += 1,
                (true, false) => self.fp += 1,
                (false, true) => self.fn_ += 1,
                _ => {}
            }
        }
    }

    /// Counts why a true pose was rejected.
    fn rejected(&mut self, error: &LocalizeError) {
        match error {
            LocalizeError::ImplausibleArea { .. } => self.rejected[1] += 1,
            LocalizeError::Ambiguous => self.rejected[2] += 1,
            LocalizeError::NotFound | LocalizeError::OpenCv(_) => self.rejected[0] += 1,
        }
    }

    fn report(mut self, name: &'static str, samples: usize) -> Report {
        let tp = self.tp as f64;
        let rate = |n: usize| n as f64 / self.with_robot.max(1) as f64;
        Report {
            name,
            samples,
            precision: tp / (tp + self.fp as f64).max(1.0),
            recall: tp / (tp + self.fn_ as f64).max(1.0),
            iou: tp / (tp + self.fp as f64 + self.fn_ as f64).max(1.0),
            detection_rate: self.found as f64 / self.with_robot.max(1) as f64,
            false_detection_rate: self.false_found as f64 / self.without_robot.max(1) as f64,
            rejected_not_found: rate(self.rejected[0]),
            rejected_area: rate(self.rejected[1]),
            rejected_spacing: rate(self.rejected[2]),
            centroid_err_mm_median: quantile(&mut self.centroid, 0.5),
            centroid_err_mm_p95: quantile(&mut self.centroid, 0.95),
            tip_err_mm_median: quantile(&mut self.tip, 0.5),
            tip_err_mm_p95: quantile(&mut self.tip, 0.95),
            latency_ms_median: quantile(&mut self.latency_ms, 0.5),
            latency_ms_p99: quantile(&mut self.latency_ms, 0.99),
        }
    }
}

fn dist(a: (f64, f64), b: (f64, f64)) -> f64 {
    ((a.0 - b.0).powi(2) + (a.1 - b.1).powi(2)).sqrt()
}

/// The UNet on every crop, through the service's own post-processing.
pub fn evaluate_unet(unet: &mut UnetLocalizer, split: &Split, expected_length_px: f64) -> Report {
    let mut t = Tally::default();
    // The crop origin does not matter for errors measured in input pixels.
    let crop = Crop { col0: 0, row0: 0 };
    let f = DOWNSAMPLE as f64;
    for i in 0..split.len() {
        let label = &split.labels[i];
        let start = Instant::now();
        let out = unet.infer(split.image(i));
        let detection = out
            .as_ref()
            .ok()
            .map(|o| detection_from_output(o, &crop, expected_length_px));
        t.latency_ms.push(start.elapsed().as_secs_f64() * 1e3);
        if let Ok(o) = &out {
            t.mask(&o.mask, split.mask(i));
        }
        let found = matches!(detection, Some(Ok(_)));
        let mm_per_input_px = label.mm_per_px * f;
        if label.has_robot {
            t.with_robot += 1;
            match &detection {
                Some(Err(e)) => t.rejected(e),
                None => t.rejected[0] += 1,
                Some(Ok(_)) => {}
            }
            if let Some(Ok(d)) = detection {
                t.found += 1;
                // Detection is in frame pixels of a crop at (0, 0): back to input pixels.
                let c = crop.frame_to_input(d.centroid_px.0, d.centroid_px.1);
                let tip = crop.frame_to_input(d.tip_px.0, d.tip_px.1);
                t.centroid.push(dist(c, label.centroid) * mm_per_input_px);
                t.tip.push(dist(tip, label.tip) * mm_per_input_px);
            }
        } else {
            t.without_robot += 1;
            t.false_found += usize::from(found);
        }
    }
    t.report("unet", split.len())
}

/// The classical localizer on the same crops (treated as frames at the crop's resolution).
pub fn evaluate_classical(classical: &ClassicalLocalizer, split: &Split) -> Report {
    let mut t = Tally::default();
    let n = INPUT_PX as i32;
    let f = DOWNSAMPLE as f64;
    for i in 0..split.len() {
        let label = &split.labels[i];
        let mm_per_input_px = label.mm_per_px * f;
        let start = Instant::now();
        let result = classical.localize(split.image(i), n, n, (0, 0, n, n), mm_per_input_px);
        t.latency_ms.push(start.elapsed().as_secs_f64() * 1e3);
        let mut predicted = vec![0u8; INPUT_PX * INPUT_PX];
        if let Ok((_, mask)) = &result {
            for (row, chunk) in predicted.chunks_mut(INPUT_PX).enumerate() {
                if let Ok(line) = mask.at_row::<u8>(row as i32) {
                    for (p, v) in chunk.iter_mut().zip(line) {
                        *p = u8::from(*v > 0);
                    }
                }
            }
        }
        t.mask(&predicted, split.mask(i));
        if label.has_robot {
            t.with_robot += 1;
            if let Err(e) = &result {
                t.rejected(e);
            }
            if let Ok((d, _)) = &result {
                t.found += 1;
                t.centroid
                    .push(dist(d.centroid_px, label.centroid) * mm_per_input_px);
                t.tip.push(dist(d.tip_px, label.tip) * mm_per_input_px);
            }
        } else {
            t.without_robot += 1;
            t.false_found += usize::from(result.is_ok());
        }
    }
    t.report("classical", split.len())
}

/// The accuracy columns of a table row: precision, recall, IoU, detection rates, keypoint errors.
fn accuracy_cells(r: &Report) -> String {
    format!(
        "{:.2} % | {:.2} % | {:.2} % | {:.1} % | {:.1} % | {:.1} / {:.1} / {:.1} % | {} | {}",
        100.0 * r.precision,
        100.0 * r.recall,
        100.0 * r.iou,
        100.0 * r.detection_rate,
        100.0 * r.false_detection_rate,
        100.0 * r.rejected_not_found,
        100.0 * r.rejected_area,
        100.0 * r.rejected_spacing,
        pair_cell(r.centroid_err_mm_median, r.centroid_err_mm_p95, 3),
        pair_cell(r.tip_err_mm_median, r.tip_err_mm_p95, 3),
    )
}

/// "median / p95" of a quantity, or "–" when nothing was measured (no pose found to measure a
/// keypoint error on).
fn pair_cell(median: f64, tail: f64, decimals: usize) -> String {
    if median.is_finite() && tail.is_finite() {
        format!("{median:.decimals$} / {tail:.decimals$}")
    } else {
        "–".to_string()
    }
}

/// A Markdown table of reports side by side.
pub fn table(reports: &[Report]) -> String {
    let mut out = String::from(
        "| localizer | samples | precision | recall | IoU | detected | false det. | true poses rejected (not found / area / spacing) | centroid err mm (median / p95) | tip err mm (median / p95) | latency ms (median / p99) |\n|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in reports {
        out.push_str(&format!(
            "| {} | {} | {} | {} |\n",
            r.name,
            r.samples,
            accuracy_cells(r),
            pair_cell(r.latency_ms_median, r.latency_ms_p99, 2)
        ));
    }
    out
}

/// One localizer on one shift of the split.
#[derive(Debug, Clone)]
pub struct RobustnessRow {
    /// Family name, or "none" for the unshifted split.
    pub family: &'static str,
    pub severity: u32,
    pub description: String,
    pub report: Report,
}

/// Every localizer on the split as it is and under every family of
/// [`crate::perturb::Family`] at severities 1..=3. `localizers` evaluates a split with each
/// localizer (so the caller decides which run, e.g. without a UNet runtime); `progress` is told
/// each finished shift.
pub fn robustness(
    split: &Split,
    seed: u64,
    mut localizers: impl FnMut(&Split) -> Vec<Report>,
    mut progress: impl FnMut(&str, u32),
) -> opencv::Result<Vec<RobustnessRow>> {
    use crate::perturb::{perturb_split, Family};
    let mut rows = Vec::new();
    for report in localizers(split) {
        rows.push(RobustnessRow {
            family: "none",
            severity: 0,
            description: "the split as rendered".into(),
            report,
        });
    }
    progress("none", 0);
    for family in Family::ALL {
        for severity in 1..=3 {
            let shifted = perturb_split(split, family, severity, seed)?;
            for report in localizers(&shifted) {
                rows.push(RobustnessRow {
                    family: family.name(),
                    severity,
                    description: family.describe(severity),
                    report,
                });
            }
            progress(family.name(), severity);
        }
    }
    Ok(rows)
}

/// A Markdown table of the robustness suite (latency left out: it does not depend on the shift).
pub fn robustness_table(rows: &[RobustnessRow]) -> String {
    let mut out = String::from(
        "| shift | severity | localizer | precision | recall | IoU | detected | false det. | true poses rejected (not found / area / spacing) | centroid err mm (median / p95) | tip err mm (median / p95) |\n|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for row in rows {
        let r = &row.report;
        out.push_str(&format!(
            "| {} | {} | {} | {} |\n",
            row.family,
            if row.severity == 0 {
                "–".to_string()
            } else {
                format!("{} ({})", row.severity, row.description)
            },
            r.name,
            accuracy_cells(r),
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keypoint_errors_read_as_a_dash_when_nothing_was_found() {
        // No pose found: the tallies of keypoint errors are empty.
        let report = Tally::default().report("unet", 3);
        let row = table(&[report]);
        assert!(!row.contains("NaN"), "{row}");
        assert!(row.contains("| – | – | – |"), "{row}");
        assert_eq!(pair_cell(0.0123, 0.0456, 3), "0.012 / 0.046");
        assert_eq!(pair_cell(6.2, 6.69, 2), "6.20 / 6.69");
    }
}
