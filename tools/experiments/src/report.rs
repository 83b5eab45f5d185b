//! Reports: results.csv, a Markdown table laid out like the paper's Table I with the paper's
//! numbers beside ours, and PNG figures (plotters).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use plotters::prelude::*;

use millinav_kit::scenario::Scenario;

use crate::{keys, reference_of, Cell, FlowSetting, Metrics, TraceRow};

/// One finished run.
#[derive(Debug, Clone)]
pub struct Outcome {
    pub cell: Cell,
    pub metrics: Metrics,
    pub wall_s: f64,
}

/// The paper's numbers (RIG.md): RMSE / P95 / Max in mm as printed, or a note. The scheduled
/// variants are shown against the paper's SMC-DOB / SMC rows, which they replace.
fn paper(viscosity_cp: f64, flow: FlowSetting, controller: &str) -> &'static str {
    let cp20 = viscosity_cp > 10.0;
    let controller = match controller {
        "smc-dob-auto" => "smc-dob",
        "smc-auto" => "smc",
        other => other,
    };
    match (cp20, flow, controller) {
        (true, FlowSetting::Static, "pid") => "0.82 / 1.78 / 2.70",
        (true, FlowSetting::Static, "mpc") => "1.57 / 2.77 / 4.40",
        (true, FlowSetting::Static, "smc-dob") => "0.49 / 0.86 / 1.64",
        (false, FlowSetting::Static, "pid") | (false, FlowSetting::Static, "mpc") => "failed",
        (false, FlowSetting::Static, "smc-dob") => "1.05 / 1.90 / 3.21",
        (true, FlowSetting::Q180, "pid") => "1.59 / – / 10.47",
        (true, FlowSetting::Q180, "smc-dob") => "1.00 / – / 4.36",
        (true, FlowSetting::Q180, "smc") => "≈10x SMC-DOB",
        (true, FlowSetting::Q250, "smc-dob") => "< 2 / – / 8.2 (hand retune)",
        (false, FlowSetting::Q180, "pid") | (false, FlowSetting::Q180, "mpc") => "unstable",
        (false, FlowSetting::Q180, "smc-dob") => "1.60 / < 4 / 5.64",
        (false, FlowSetting::Q250, "smc-dob") => "– (paper ran 4.3 cP flow at 7 cm/s)",
        _ => "–",
    }
}

/// The paper's SMC-DOB RMSE (mm) per condition, as the bound the target compares with
/// ("< 2" at 10 cm/s, 20 cP is taken as 2). The paper ran 4.3 cP in flow only at 7 cm/s: its
/// abstract and Fig. 8 caption say 7 cm/s, and the 20 cP run it is compared with is the
/// 7 cm/s one (1.00 ± 0.02); one sentence of Sec. III-D says 10 cm/s.
pub fn paper_smc_dob_rmse_mm(viscosity_cp: f64, flow: FlowSetting) -> Option<f64> {
    match (viscosity_cp > 10.0, flow) {
        (true, FlowSetting::Static) => Some(0.49),
        (true, FlowSetting::Q180) => Some(1.00),
        (true, FlowSetting::Q250) => Some(2.0),
        (false, FlowSetting::Static) => Some(1.05),
        (false, FlowSetting::Q180) => Some(1.60),
        _ => None,
    }
}

/// Mean RMSE and completed trials of one controller in one condition.
#[derive(Debug, Clone, Copy)]
struct Summary {
    rmse_mm: f64,
    completed: usize,
    trials: usize,
}

/// The paper's targets, checked on this matrix (one line per check, "yes"/"no" first).
pub fn target_checks(outcomes: &[Outcome]) -> String {
    let mut by_condition: BTreeMap<(i64, FlowSetting), BTreeMap<String, Summary>> = BTreeMap::new();
    for ((v, flow, controller), list) in groups(outcomes) {
        let rmse: Vec<f64> = list.iter().map(|o| o.metrics.rmse_mm).collect();
        by_condition.entry((v, flow)).or_default().insert(
            controller,
            Summary {
                rmse_mm: mean_sd(&rmse).0,
                completed: list.iter().filter(|o| o.metrics.completed).count(),
                trials: list.len(),
            },
        );
    }
    let yes_no = |ok: bool| if ok { "yes" } else { "no" };
    let mut out = String::from("\n### Targets, checked on this matrix\n\n");
    for ((v, flow), runs) in &by_condition {
        let viscosity_cp = -*v as f64 / 10.0;
        let condition = format!("{viscosity_cp} cP, {}", flow.label());
        // Best: most trials completed, then lowest mean RMSE.
        let best = runs.iter().min_by(|a, b| {
            (b.1.completed, a.1.rmse_mm)
                .partial_cmp(&(a.1.completed, b.1.rmse_mm))
                .unwrap_or(std::cmp::Ordering::Equal)
        });
        if let Some((name, _)) = best {
            let _ = writeln!(
                out,
                "- {}: best is {name} ({condition})",
                yes_no(name.starts_with("smc-dob"))
            );
        }
        for (with, without) in [("smc-dob", "smc"), ("smc-dob-auto", "smc-auto")] {
            if let (Some(a), Some(b)) = (runs.get(with), runs.get(without)) {
                let ratio = b.rmse_mm / a.rmse_mm.max(1e-9);
                let verdict = if a.completed == 0 {
                    "n/a (fails with the DOB too)"
                } else {
                    yes_no(ratio > 1.5)
                };
                let _ = writeln!(
                    out,
                    "- {verdict}: removing the DOB from {with} multiplies RMSE by {ratio:.1} ({condition})"
                );
            }
        }
        if let Some(bound) = paper_smc_dob_rmse_mm(viscosity_cp, *flow) {
            for name in ["smc-dob", "smc-dob-auto"] {
                if let Some(s) = runs.get(name) {
                    let ok = s.completed == s.trials && s.rmse_mm <= bound;
                    let _ = writeln!(
                        out,
                        "- {}: {name} RMSE {:.2} mm, {}/{} completed, paper SMC-DOB {bound:.2} mm ({condition})",
                        yes_no(ok),
                        s.rmse_mm,
                        s.completed,
                        s.trials
                    );
                }
            }
        }
        if viscosity_cp < 10.0 {
            let twenty = by_condition.get(&(-200, *flow));
            for name in ["pid", "mpc"] {
                if let (Some(low), Some(high)) = (runs.get(name), twenty.and_then(|r| r.get(name)))
                {
                    let failed = low.completed < low.trials;
                    let ratio = low.rmse_mm / high.rmse_mm.max(1e-9);
                    let verdict = if !failed && high.completed < high.trials {
                        "n/a (fails at 20 cP already)"
                    } else {
                        yes_no(failed || ratio > 1.5)
                    };
                    let _ = writeln!(
                        out,
                        "- {verdict}: {name} at 4.3 cP completes {}/{}, RMSE x{ratio:.1} of 20 cP ({condition})",
                        low.completed,
                        low.trials
                    );
                }
            }
        }
    }
    out
}

fn mean_sd(values: &[f64]) -> (f64, f64) {
    let n = values.len().max(1) as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (mean, var.sqrt())
}

pub fn write_csv(outcomes: &[Outcome], path: &Path) -> std::io::Result<()> {
    let mut out = String::from(
        "viscosity_cp,flow,controller,seed,rmse_mm,p95_mm,max_mm,completed,wall_contact_frames,peak_current_a,energy_j,current_step_p95_a,current_tv_a_per_s,wall_s\n",
    );
    for o in outcomes {
        let m = &o.metrics;
        let _ = writeln!(
            out,
            "{},{},{},{},{:.4},{:.4},{:.4},{},{},{:.3},{:.3},{:.4},{:.2},{:.2}",
            o.cell.viscosity_cp,
            o.cell.flow.label(),
            o.cell.controller,
            o.cell.seed,
            m.rmse_mm,
            m.p95_mm,
            m.max_mm,
            m.completed,
            m.wall_contact_frames,
            m.peak_current_a,
            m.energy_j,
            m.current_step_p95_a,
            m.current_tv_a_per_s,
            o.wall_s
        );
    }
    std::fs::write(path, out)
}

/// Groups trials by (viscosity, flow, controller).
fn groups(outcomes: &[Outcome]) -> BTreeMap<(i64, FlowSetting, String), Vec<&Outcome>> {
    let mut g: BTreeMap<(i64, FlowSetting, String), Vec<&Outcome>> = BTreeMap::new();
    for o in outcomes {
        g.entry((
            -(o.cell.viscosity_cp * 10.0) as i64,
            o.cell.flow,
            o.cell.controller.clone(),
        ))
        .or_default()
        .push(o);
    }
    g
}

/// The table; `with_paper` adds the paper's numbers beside ours (on the paper's rig).
pub fn markdown_table(outcomes: &[Outcome], mode: &str, with_paper: bool) -> String {
    let mut out = format!(
        "Mode: {mode}. Mean ± sd over trials; \"failed\" = error above {} mm for more than {} s, or never within it of the end after the reference got there.\n\n\
         \"ΔI p95\" = 95th percentile over frames of the largest per-coil current change in one frame; \"TV\" = total variation of the coil currents per second; \"heat\" = Joule heat Σ I² R dt in the coils.\n\n\
         | condition | controller | trials | completed | RMSE mm | P95 mm | Max mm | wall contacts | peak A | ΔI p95 A | TV A/s | heat J | paper RMSE / P95 / Max |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
        crate::FAIL_ERROR_M * 1e3,
        crate::FAIL_TIME_S
    );
    for ((_, flow, controller), list) in groups(outcomes) {
        let viscosity = list[0].cell.viscosity_cp;
        let done = list.iter().filter(|o| o.metrics.completed).count();
        let stat = |f: fn(&Metrics) -> f64| {
            let (m, s) = mean_sd(&list.iter().map(|o| f(&o.metrics)).collect::<Vec<_>>());
            format!("{m:.2} ± {s:.2}")
        };
        let _ = writeln!(
            out,
            "| {} cP, {} | {controller} | {} | {done}/{} | {} | {} | {} | {:.0} | {:.2} | {:.3} | {:.1} | {:.1} | {} |",
            viscosity,
            flow.label(),
            list.len(),
            list.len(),
            stat(|m| m.rmse_mm),
            stat(|m| m.p95_mm),
            stat(|m| m.max_mm),
            mean_sd(&list.iter().map(|o| o.metrics.wall_contact_frames as f64).collect::<Vec<_>>()).0,
            mean_sd(&list.iter().map(|o| o.metrics.peak_current_a).collect::<Vec<_>>()).0,
            mean_sd(&list.iter().map(|o| o.metrics.current_step_p95_a).collect::<Vec<_>>()).0,
            mean_sd(&list.iter().map(|o| o.metrics.current_tv_a_per_s).collect::<Vec<_>>()).0,
            mean_sd(&list.iter().map(|o| o.metrics.energy_j).collect::<Vec<_>>()).0,
            if with_paper {
                paper(viscosity, flow, &controller)
            } else {
                "–"
            }
        );
    }
    out
}

/// Registers a TrueType font for figure text; figures are skipped without one.
pub fn register_font() -> bool {
    for path in [
        "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
        "/usr/share/fonts/TTF/DejaVuSans.ttf",
    ] {
        if let Ok(bytes) = std::fs::read(path) {
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            if plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok() {
                return true;
            }
        }
    }
    false
}

/// One colour per controller, the same in every figure.
fn color_of(controller: &str) -> RGBColor {
    match controller {
        "pid" => BLUE,
        "mpc" => RED,
        "smc" => GREEN,
        "smc-dob" => MAGENTA,
        "smc-dob-auto" => RGBColor(255, 140, 0),
        "smc-auto" => RGBColor(0, 150, 150),
        _ => BLACK,
    }
}

type Res = Result<(), Box<dyn std::error::Error>>;

/// Which number of a run a bar chart shows.
#[derive(Debug, Clone, Copy)]
pub enum BarMetric {
    Rmse,
    P95,
    Max,
}

impl BarMetric {
    fn of(self, m: &crate::Metrics) -> f64 {
        match self {
            Self::Rmse => m.rmse_mm,
            Self::P95 => m.p95_mm,
            Self::Max => m.max_mm,
        }
    }
    fn label(self) -> &'static str {
        match self {
            Self::Rmse => "RMSE",
            Self::P95 => "P95 error",
            Self::Max => "max error",
        }
    }
}

/// Bars of one metric per condition and controller (mean of trials), for the controllers in
/// `only` (all when empty).
pub fn metric_bars(
    outcomes: &[Outcome],
    metric: BarMetric,
    only: &[&str],
    title: &str,
    path: &Path,
) -> Res {
    let kept: Vec<Outcome> = outcomes
        .iter()
        .filter(|o| only.is_empty() || only.contains(&o.cell.controller.as_str()))
        .cloned()
        .collect();
    let groups = groups(&kept);
    let conditions: Vec<(i64, FlowSetting)> = {
        let mut c: Vec<_> = groups.keys().map(|(v, f, _)| (*v, *f)).collect();
        c.dedup();
        c
    };
    let controllers: Vec<String> = {
        let mut c: Vec<String> = groups.keys().map(|(_, _, k)| k.clone()).collect();
        c.sort();
        c.dedup();
        c
    };
    let max = groups
        .values()
        .flat_map(|l| l.iter().map(|o| metric.of(&o.metrics)))
        .fold(1.0f64, f64::max)
        .min(20.0);
    let root = BitMapBackend::new(path, (1200, 600)).into_drawing_area();
    root.fill(&WHITE)?;
    let n = conditions.len() as f64;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..n, 0.0..max * 1.1)?;
    chart
        .configure_mesh()
        .y_desc(format!("{} (mm)", metric.label()))
        // Ticks every half condition; only the centres (i + 0.5) carry a label.
        .x_labels(2 * conditions.len() + 1)
        .x_label_formatter(&|x| {
            if (x - x.floor() - 0.5).abs() > 0.01 {
                return String::new();
            }
            conditions
                .get(x.floor() as usize)
                .map(|(v, f)| format!("{} cP {}", -*v as f64 / 10.0, f.label()))
                .unwrap_or_default()
        })
        .draw()?;
    let width = 0.8 / controllers.len() as f64;
    for (k, controller) in controllers.iter().enumerate() {
        let color = color_of(controller);
        let bars: Vec<Rectangle<(f64, f64)>> = conditions
            .iter()
            .enumerate()
            .filter_map(|(i, (v, f))| {
                let list = groups.get(&(*v, *f, controller.clone()))?;
                let (mean, _) = mean_sd(
                    &list
                        .iter()
                        .map(|o| metric.of(&o.metrics))
                        .collect::<Vec<_>>(),
                );
                let x0 = i as f64 + 0.1 + k as f64 * width;
                Some(Rectangle::new(
                    [(x0, 0.0), (x0 + width * 0.9, mean.min(max * 1.1))],
                    color.filled(),
                ))
            })
            .collect();
        chart
            .draw_series(bars)?
            .label(controller.clone())
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 10, y + 5)], color.filled()));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE)
        .border_style(BLACK)
        .draw()?;
    root.present()?;
    Ok(())
}

/// Small multiples, one column per controller (three per row), with shared axes: the path in the
/// plane over the rig's whole canal mask (reference in black), and below it the tracking error
/// against time. Each panel names its controller and RMSE.
pub fn traces_figure(
    traces: &[(String, Vec<TraceRow>)],
    reference: &millinav_control::reference::Reference,
    canal: &fieldmaps::mask::CanalMask,
    title: &str,
    path: &Path,
) -> Res {
    const COLUMNS: usize = 3;
    const PATH_PANEL_PX: u32 = 460;
    const ERROR_PANEL_PX: u32 = 230;
    const TITLE_PX: u32 = 40;
    let n = traces.len().max(1);
    let columns = n.min(COLUMNS);
    let rows = n.div_ceil(COLUMNS);
    let width = 500 * columns as u32;
    let height = TITLE_PX + rows as u32 * (PATH_PANEL_PX + ERROR_PANEL_PX);
    let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
    root.fill(&WHITE)?;
    let (header, body) = root.split_vertically(TITLE_PX);
    header.titled(
        &format!("{title}: paths over the canal, tracking error (shared axes)"),
        ("sans-serif", 24),
    )?;

    // The whole canal (and the reference) sets the plane's extent.
    let geometry = canal.geometry();
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    let mut extend = |x: f64, y: f64| {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    };
    let width_px = canal.width() as usize;
    for (k, _) in canal.canal_flags().iter().enumerate().filter(|(_, c)| **c) {
        let p = geometry.px_to_world((k % width_px) as f64 + 0.5, (k / width_px) as f64 + 0.5);
        extend(p.x * 1e3, p.y * 1e3);
    }
    for p in reference.waypoints() {
        extend(p.x * 1e3, p.y * 1e3);
    }
    let pad = 2.0;
    let (x0, x1, y0, y1) = (x0 - pad, x1 + pad, y0 - pad, y1 + pad);
    // Square data cells, at most ~160 across the plane, at least one camera pixel.
    let cell_mm = ((x1 - x0).max(y1 - y0) / 160.0).max(geometry.mm_per_px);
    let canal_cells: Vec<(f64, f64)> = (0..((x1 - x0) / cell_mm).ceil() as usize)
        .flat_map(|i| {
            (0..((y1 - y0) / cell_mm).ceil() as usize)
                .map(move |j| (x0 + i as f64 * cell_mm, y0 + j as f64 * cell_mm))
        })
        .filter(|&(x, y)| {
            canal.contains(&nalgebra::Vector2::new(
                (x + 0.5 * cell_mm) * 1e-3,
                (y + 0.5 * cell_mm) * 1e-3,
            ))
        })
        .collect();

    let errors: Vec<Vec<(f64, f64)>> = traces
        .iter()
        .map(|(_, trace)| {
            trace
                .iter()
                .map(|r| {
                    let e = (r.position_m - reference.sample(r.time_s).position_m).norm() * 1e3;
                    (r.time_s, e)
                })
                .collect()
        })
        .collect();
    let t_max = traces
        .iter()
        .flat_map(|(_, t)| t.last().map(|r| r.time_s))
        .fold(1.0f64, f64::max);
    // Shared error axis: the largest 99th percentile over the controllers, capped at 20 mm.
    let e_cap = errors
        .iter()
        .map(|e| {
            let mut v: Vec<f64> = e.iter().map(|(_, e)| *e).collect();
            v.sort_by(f64::total_cmp);
            v.get(v.len().saturating_sub(1) * 99 / 100)
                .copied()
                .unwrap_or(0.0)
        })
        .fold(1.0f64, f64::max)
        .min(20.0)
        * 1.05;

    let cells = body.split_evenly((rows, columns));
    for (k, ((name, trace), error)) in traces.iter().zip(&errors).enumerate() {
        let cell = &cells[(k / COLUMNS) * columns + k % COLUMNS];
        let (top, bottom) = cell.split_vertically(PATH_PANEL_PX);
        let color = color_of(name);
        let rmse =
            (error.iter().map(|(_, e)| e * e).sum::<f64>() / error.len().max(1) as f64).sqrt();
        let worst = error.iter().map(|(_, e)| *e).fold(0.0, f64::max);
        let mut plane = ChartBuilder::on(&top)
            .caption(format!("{name}: RMSE {rmse:.2} mm"), ("sans-serif", 18))
            .margin(8)
            .x_label_area_size(30)
            .y_label_area_size(40)
            .build_cartesian_2d(x0..x1, y0..y1)?;
        plane
            .configure_mesh()
            .disable_mesh()
            .x_desc("x (mm)")
            .y_desc("y (mm)")
            .draw()?;
        plane.draw_series(canal_cells.iter().map(|&(x, y)| {
            Rectangle::new(
                [(x, y), (x + cell_mm, y + cell_mm)],
                RGBColor(225, 215, 200).filled(),
            )
        }))?;
        plane.draw_series(LineSeries::new(
            reference.waypoints().iter().map(|p| (p.x * 1e3, p.y * 1e3)),
            BLACK.stroke_width(2),
        ))?;
        plane.draw_series(LineSeries::new(
            trace
                .iter()
                .map(|r| (r.position_m.x * 1e3, r.position_m.y * 1e3)),
            color,
        ))?;
        let clipped = if worst > e_cap {
            format!(" (max {worst:.1} mm, clipped)")
        } else {
            String::new()
        };
        let mut chart = ChartBuilder::on(&bottom)
            .caption(format!("error{clipped}"), ("sans-serif", 14))
            .margin(8)
            .x_label_area_size(30)
            .y_label_area_size(40)
            .build_cartesian_2d(0.0..t_max, 0.0..e_cap)?;
        chart
            .configure_mesh()
            .x_desc("time (s)")
            .y_desc("error (mm)")
            .draw()?;
        chart.draw_series(LineSeries::new(
            error.iter().map(|&(t, e)| (t, e.min(e_cap))),
            color,
        ))?;
    }
    root.present()?;
    Ok(())
}

/// The run settings line of a matrix's table: mode, frame period, camera latency and whether
/// control compensates it, the twin's coil gain error, and the rig.
pub fn table_header(mode: &str, base: &Scenario) -> anyhow::Result<String> {
    let doc = &base.sections;
    let frames = keys::CAMERA_LATENCY_FRAMES
        .get(doc)
        .and_then(toml::Value::as_integer)
        .unwrap_or(0);
    let compensated = keys::LATENCY_COMPENSATE
        .get(doc)
        .and_then(toml::Value::as_bool)
        .unwrap_or(true);
    let gain_error = keys::COIL_GAIN_ERROR_STD
        .number(doc)
        .unwrap_or(millinav_plant::model::PlantPhysicsConfig::default().coil_gain_error_std);
    let cylinder = keys::DRAG_SHAPE.get(doc).and_then(toml::Value::as_str) == Some("cylinder");
    let mut floor = keys::FLOOR_GAP_M
        .get(doc)
        .and_then(|v| v.as_float())
        .map_or(String::new(), |gap| {
            format!(", capsule on the floor ({:.0} µm gap)", gap * 1e6)
        });
    if cylinder {
        floor.push_str(", the capsule's drag a cylinder's");
    }
    let command_delay = keys::COMMAND_DELAY_MS
        .number(doc)
        .filter(|ms| *ms > 0.0)
        .map_or(String::new(), |ms| {
            format!(" + {ms} ms from capture to the coils inside each frame")
        });
    let observer = match keys::VELOCITY_ESTIMATE
        .get(doc)
        .and_then(toml::Value::as_str)
    {
        Some("observer") => ", velocity from the model-based observer",
        _ => "",
    };
    let slew = keys::MAX_CURRENT_SLEW
        .number(doc)
        .map_or(String::new(), |rate| {
            // The yield's own defaults where the table names only one of its fields.
            let yielding = keys::SLEW_YIELD.get(doc).map(|_| {
                let defaults = millinav_control::SlewYieldConfig::default();
                let fraction = keys::SLEW_YIELD_SHORTFALL
                    .number(doc)
                    .unwrap_or(defaults.shortfall_fraction);
                let faster = keys::SLEW_YIELD_MAX_SLEW
                    .number(doc)
                    .unwrap_or(defaults.max_current_slew_a_per_s);
                format!(
                    " ({faster} A/s where that would withhold more than {:.0} % of the force)",
                    fraction * 100.0
                )
            });
            format!(
                ", coil currents slew-limited to {rate} A/s{}",
                yielding.unwrap_or_default()
            )
        });
    let camera_period = keys::CAMERA_EXPOSURE_PERIOD_FRAMES
        .number(doc)
        .filter(|frames| *frames > 1.0)
        .map_or(String::new(), |frames| {
            format!(
                " (the camera exposes every {} ms, the loop fed its latest exposure between)",
                frames * base.run.frame_period_ms
            )
        });
    let rig = base.rig()?;
    Ok(format!(
        "{mode}, {} ms frame period{camera_period}, {} ms extra camera latency{command_delay} ({}), \
         per-coil gain error σ {:.0} % unknown to control{floor}{observer}{slew}, rig {} ({})",
        base.run.frame_period_ms,
        frames as f64 * base.run.frame_period_ms,
        if compensated {
            "compensated"
        } else {
            "not compensated"
        },
        gain_error * 100.0,
        rig.name,
        rig.path
            .strip_prefix(fieldmaps::data_root())
            .unwrap_or(&rig.path)
            .display()
    ))
}

/// The metric bar charts and, per condition, the first trials' trajectories, into `out`.
pub fn write_figures(
    base: &Scenario,
    outcomes: &[Outcome],
    traces: &[(Cell, Vec<TraceRow>)],
    out: &Path,
) -> anyhow::Result<()> {
    let bars: [(BarMetric, &[&str], &str, &str); 4] = [
        (
            BarMetric::Rmse,
            &[],
            "RMSE by condition and controller (mean of trials)",
            "rmse_bars.png",
        ),
        (
            BarMetric::P95,
            &[],
            "P95 error by condition and controller (mean of trials)",
            "p95_bars.png",
        ),
        (
            BarMetric::Max,
            &[],
            "Max error by condition and controller (mean of trials)",
            "max_bars.png",
        ),
        (
            BarMetric::Rmse,
            &["smc-dob", "smc", "smc-dob-auto", "smc-auto"],
            "DOB ablation: RMSE with and without the observer",
            "dob_ablation.png",
        ),
    ];
    for (metric, only, title, file) in bars {
        metric_bars(outcomes, metric, only, title, &out.join(file))
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    let reference = reference_of(base)?;
    let mask = &base.rig()?.phantom.mask;
    let mut conditions: Vec<(i64, String)> = traces
        .iter()
        .map(|(c, _)| ((c.viscosity_cp * 10.0) as i64, c.flow.label().to_string()))
        .collect();
    conditions.sort();
    conditions.dedup();
    for (v, flow) in conditions {
        let mut runs: Vec<(String, Vec<TraceRow>)> = traces
            .iter()
            .filter(|(c, _)| (c.viscosity_cp * 10.0) as i64 == v && c.flow.label() == flow)
            .map(|(c, t)| (c.controller.clone(), t.clone()))
            .collect();
        runs.sort_by(|a, b| a.0.cmp(&b.0));
        let title = format!("{} cP, {flow}", v as f64 / 10.0);
        let file = format!(
            "traces_{}cp_{}.png",
            v as f64 / 10.0,
            flow.replace([' ', '/'], "")
        );
        traces_figure(&runs, &reference, mask, &title, &out.join(file))
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    Ok(())
}
