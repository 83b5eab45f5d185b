//! The robustness matrix (issue 21 point 5): one flow condition of the rig (on the paper's,
//! 20 cP at 7 cm/s, the cell with the paper's tightest SMC-DOB number; on any rig its most
//! viscous fluid at its lowest flow, which is the same rule), each disturbance of the twin
//! varied alone around the twin's default while the others stay there, for the scheduled
//! SMC-DOB and the baselines, at the paper's 10 Hz and at 100 Hz. A table and a heat map of
//! completion and RMSE ratio to the paper's SMC-DOB (on the paper's rig; RMSE elsewhere).

use std::fmt::Write as _;
use std::path::Path;

use fieldmaps::rigfile::Rig;
use millinav_kit::scenario::Scenario;
use plotters::prelude::*;

use crate::report::paper_smc_dob_rmse_mm;
use crate::{add_capture_to_coils_delay, cell_scenario, keys, Cell, FlowSetting, Metrics};

/// A disturbance the matrix varies.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Axis {
    /// `[plant.physics] pulsation_hz` (the controller is told the pump's rate).
    PulsationHz,
    /// `[plant.physics] pulsation_amplitude`, fraction of the steady flow.
    PulsationAmplitude,
    /// `[plant.physics.flow_noise] fraction`.
    FlowNoise,
    /// `[plant.physics.recirculation] strength_fraction`.
    Recirculation,
    /// `[plant.physics] coil_gain_error_std`: per-coil gain error the controller does not know.
    CoilGainError,
    /// Extra latency from capture to the coils, ms: whole frames of camera latency
    /// (`[plant.camera] latency_frames`), the rest inside the frame (`[plant]
    /// command_delay_ms`, told to control), [`crate::add_capture_to_coils_delay`].
    CameraLatencyMs,
    /// Viscosity, cP: every viscosity the rig has a flow map for at the matrix's flow.
    ViscosityCp,
}

/// The flow condition the matrix varies the disturbances around, and the viscosities its
/// viscosity axis visits.
#[derive(Debug, Clone, PartialEq)]
pub struct Around {
    pub viscosity_cp: f64,
    pub flow: FlowSetting,
    /// Every viscosity the rig has a map for at `flow`, lowest first.
    pub viscosities_cp: Vec<f64>,
}

impl Around {
    /// The rig's most viscous fluid at its lowest flow among that fluid's conditions (on the
    /// paper's rig 20 cP at 180 mL/min, 7 cm/s); an error names the rig when it has no flow
    /// condition.
    pub fn on_rig(rig: &Rig) -> anyhow::Result<Self> {
        let cp = |pa_s: f64| (pa_s * 1e4).round() / 10.0;
        let conditions = &rig.phantom.flow_conditions;
        let viscosity_cp = conditions
            .iter()
            .map(|c| cp(c.viscosity_pa_s))
            .max_by(f64::total_cmp)
            .ok_or_else(|| {
                anyhow::anyhow!(
                    "{}: phantom.flow: the robustness matrix varies a flow, and the rig has no \
                     [[phantom.flow]] condition",
                    rig.path.display()
                )
            })?;
        let flow_ml_min = conditions
            .iter()
            .filter(|c| cp(c.viscosity_pa_s) == viscosity_cp)
            .map(|c| c.flow_ml_min.round() as u32)
            .min()
            .expect("the most viscous fluid has a condition");
        let mut viscosities_cp: Vec<f64> = conditions
            .iter()
            .filter(|c| c.flow_ml_min.round() as u32 == flow_ml_min)
            .map(|c| cp(c.viscosity_pa_s))
            .collect();
        viscosities_cp.sort_by(f64::total_cmp);
        viscosities_cp.dedup();
        Ok(Self {
            viscosity_cp,
            flow: FlowSetting::Flow(flow_ml_min),
            viscosities_cp,
        })
    }
}

impl Axis {
    pub const ALL: [Axis; 7] = [
        Axis::PulsationHz,
        Axis::PulsationAmplitude,
        Axis::FlowNoise,
        Axis::Recirculation,
        Axis::CoilGainError,
        Axis::CameraLatencyMs,
        Axis::ViscosityCp,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Axis::PulsationHz => "pulsation Hz",
            Axis::PulsationAmplitude => "pulsation amplitude",
            Axis::FlowNoise => "flow noise",
            Axis::Recirculation => "recirculation",
            Axis::CoilGainError => "coil gain error",
            Axis::CameraLatencyMs => "camera latency ms",
            Axis::ViscosityCp => "viscosity cP",
        }
    }

    /// The levels the matrix runs around `around` (the twin's default among them).
    pub fn levels(self, around: &Around) -> &[f64] {
        match self {
            Axis::PulsationHz => &[1.0, 2.0, 3.0],
            Axis::PulsationAmplitude => &[0.25, 0.5, 0.8],
            Axis::FlowNoise => &[0.1, 0.15, 0.2],
            Axis::Recirculation => &[0.0, 0.25, 0.5],
            Axis::CoilGainError => &[0.0, 0.05, 0.1],
            Axis::CameraLatencyMs => &[0.0, 50.0, 100.0],
            Axis::ViscosityCp => &around.viscosities_cp,
        }
    }
}

/// One run of the robustness matrix.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Case {
    pub axis: Axis,
    pub level: f64,
    /// The condition's fluid (the level on the viscosity axis) and flow.
    pub viscosity_cp: f64,
    pub flow: FlowSetting,
    pub frame_period_ms: f64,
    pub controller: String,
    pub seed: u64,
}

impl Case {
    pub fn name(&self) -> String {
        format!(
            "{}_{}_{}ms_{}_s{}",
            self.axis.name().replace(' ', "-"),
            self.level,
            self.frame_period_ms,
            self.controller,
            self.seed
        )
    }

    /// The matrix cell this case starts from.
    fn cell(&self) -> Cell {
        Cell {
            viscosity_cp: self.viscosity_cp,
            flow: self.flow,
            controller: self.controller.clone(),
            seed: self.seed,
        }
    }
}

/// Every case for `controllers` at the two loop rates around `around`.
pub fn cases(controllers: &[String], trials: u64, around: &Around) -> Vec<Case> {
    let mut out = Vec::new();
    for frame_period_ms in [100.0, 10.0] {
        for axis in Axis::ALL {
            for &level in axis.levels(around) {
                for controller in controllers {
                    for seed in 1..=trials {
                        let viscosity_cp = if axis == Axis::ViscosityCp {
                            level
                        } else {
                            around.viscosity_cp
                        };
                        out.push(Case {
                            axis,
                            level,
                            viscosity_cp,
                            flow: around.flow,
                            frame_period_ms,
                            controller: controller.clone(),
                            seed,
                        });
                    }
                }
            }
        }
    }
    out
}

/// The scenario text of a case: the matrix cell's, at the case's loop rate, with its axis set.
pub fn case_scenario(base: &Scenario, case: &Case) -> anyhow::Result<String> {
    let text = cell_scenario(base, &case.cell())?;
    let mut doc: toml::Table = toml::from_str(&text)?;
    keys::FRAME_PERIOD_MS.set(&mut doc, case.frame_period_ms)?;
    let level = case.level;
    match case.axis {
        Axis::PulsationHz => {
            keys::PULSATION_HZ.set(&mut doc, level)?;
            // The lab sets the pump, so the controller knows its rate.
            keys::CONTROL_PULSATION_HZ.set(&mut doc, level)?;
        }
        Axis::PulsationAmplitude => keys::PULSATION_AMPLITUDE.set(&mut doc, level)?,
        Axis::FlowNoise => keys::FLOW_NOISE_FRACTION.set(&mut doc, level)?,
        Axis::Recirculation => keys::RECIRCULATION_STRENGTH.set(&mut doc, level)?,
        Axis::CoilGainError => keys::COIL_GAIN_ERROR_STD.set(&mut doc, level)?,
        Axis::CameraLatencyMs => {
            add_capture_to_coils_delay(&mut doc, level, case.frame_period_ms)?;
        }
        Axis::ViscosityCp => {}
    }
    Ok(toml::to_string(&doc)?)
}

/// One finished case.
#[derive(Debug, Clone)]
pub struct CaseOutcome {
    pub case: Case,
    pub metrics: Metrics,
}

/// The trials of one (axis, level, rate, controller), in the order of the table.
fn grouped(outcomes: &[CaseOutcome]) -> Vec<Vec<&CaseOutcome>> {
    let mut groups: Vec<Vec<&CaseOutcome>> = Vec::new();
    let mut sorted: Vec<&CaseOutcome> = outcomes.iter().collect();
    sorted.sort_by(|a, b| {
        (
            a.case.axis,
            a.case.frame_period_ms as i64,
            &a.case.controller,
        )
            .cmp(&(
                b.case.axis,
                b.case.frame_period_ms as i64,
                &b.case.controller,
            ))
            .then(a.case.level.total_cmp(&b.case.level))
    });
    for o in sorted {
        match groups.last_mut() {
            Some(group)
                if group[0].case.axis == o.case.axis
                    && group[0].case.level == o.case.level
                    && group[0].case.frame_period_ms == o.case.frame_period_ms
                    && group[0].case.controller == o.case.controller =>
            {
                group.push(o)
            }
            _ => groups.push(vec![o]),
        }
    }
    groups
}

/// The paper's SMC-DOB RMSE of a case's condition, mm (NaN where the paper has none).
fn paper_rmse_mm(case: &Case) -> f64 {
    let cell = case.cell();
    paper_smc_dob_rmse_mm(cell.viscosity_cp, cell.flow).unwrap_or(f64::NAN)
}

/// Summary of a group: completed trials, mean RMSE, and its ratio to the paper's SMC-DOB on
/// the paper's rig (None on another rig: the paper ran only its own).
fn summary(group: &[&CaseOutcome], on_paper_rig: bool) -> (usize, f64, Option<f64>) {
    let done = group.iter().filter(|o| o.metrics.completed).count();
    let rmse = group.iter().map(|o| o.metrics.rmse_mm).sum::<f64>() / group.len() as f64;
    let ratio = on_paper_rig.then(|| rmse / paper_rmse_mm(&group[0].case));
    (done, rmse, ratio)
}

/// What robustness.md's last column is.
const FLOOR_NOTE: &str = "Noise floor = the least RMSE any controller could reach in that \
     twin's flow noise with its poses, for the capsule / for a body that follows the flow at \
     once (`experiments --noise-floor`; README, \"The flow noise's floor\").";

/// `robustness.csv` (one row per run) and `robustness.md` (one row per setting, with the flow
/// noise's floor of its twin from `floor_m`: the capsule's and a flow follower's, m, see
/// `noise_floor`).
pub fn write_tables(
    outcomes: &[CaseOutcome],
    on_paper_rig: bool,
    floor_m: &dyn Fn(&Case) -> Option<(f64, f64)>,
    out: &Path,
) -> anyhow::Result<String> {
    let mut csv = String::from(
        "axis,level,frame_period_ms,controller,seed,rmse_mm,p95_mm,max_mm,completed,current_step_p95_a\n",
    );
    for o in outcomes {
        let (c, m) = (&o.case, &o.metrics);
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{:.4},{:.4},{:.4},{},{:.4}",
            c.axis.name(),
            c.level,
            c.frame_period_ms,
            c.controller,
            c.seed,
            m.rmse_mm,
            m.p95_mm,
            m.max_mm,
            m.completed,
            m.current_step_p95_a
        );
    }
    std::fs::write(out.join("robustness.csv"), csv)?;
    let mut md = if on_paper_rig {
        format!(
            "One factor at a time around the twin's default (20 cP, 7 cm/s: pulsation 3 Hz at 50 %, \
             flow noise 0.1, recirculation 0.25, coil gain error 0.03, no extra latency), fast mode. \
             Ratio = mean RMSE / the paper's SMC-DOB RMSE of that condition (1.00 mm at 20 cP, \
             1.60 mm at 4.3 cP, 7 cm/s). {FLOOR_NOTE}\n\n",
        )
    } else {
        let around = outcomes.iter().find(|o| o.case.axis != Axis::ViscosityCp);
        let condition = around.map_or_else(String::new, |o| {
            format!(" at {} cP, {}", o.case.viscosity_cp, o.case.flow.label())
        });
        format!(
            "One factor at a time around the base scenario's twin{condition}, fast mode. The \
             paper ran only its own rig, so there is no ratio to it here. {FLOOR_NOTE}\n\n"
        )
    };
    md.push_str(
        "| axis | level | loop | controller | completed | RMSE mm | ratio to paper | noise floor mm |\n\
         |---|---|---|---|---|---|---|---|\n",
    );
    for group in grouped(outcomes) {
        let c = &group[0].case;
        let (done, rmse, ratio) = summary(&group, on_paper_rig);
        let ratio = ratio.map_or_else(|| "–".to_string(), |r| format!("{r:.2}"));
        let floor = floor_m(c).map_or_else(
            || "–".to_string(),
            |(capsule, follower)| format!("{:.3} / {:.3}", capsule * 1e3, follower * 1e3),
        );
        let _ = writeln!(
            md,
            "| {} | {} | {} Hz | {} | {done}/{} | {rmse:.2} | {ratio} | {floor} |",
            c.axis.name(),
            c.level,
            1000.0 / c.frame_period_ms,
            c.controller,
            group.len()
        );
    }
    std::fs::write(out.join("robustness.md"), &md)?;
    Ok(md)
}

/// `robustness.png`: rows = axis and level, columns = controller at each loop rate; the colour
/// is the RMSE ratio to the paper on the paper's rig, the RMSE in mm on another (green ≤ 1,
/// red ≥ 10, log scale), with a red border when a trial failed to complete; the text is that
/// number and the completed trials.
pub fn heat_map(outcomes: &[CaseOutcome], on_paper_rig: bool, path: &Path) -> anyhow::Result<()> {
    let groups = grouped(outcomes);
    let mut rows: Vec<(Axis, f64)> = groups
        .iter()
        .map(|g| (g[0].case.axis, g[0].case.level))
        .collect();
    rows.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)));
    rows.dedup();
    let mut columns: Vec<(i64, String)> = groups
        .iter()
        .map(|g| {
            (
                -(g[0].case.frame_period_ms as i64),
                g[0].case.controller.clone(),
            )
        })
        .collect();
    columns.sort();
    columns.dedup();
    let (cell_w, cell_h, left, top) = (130u32, 26u32, 230u32, 60u32);
    let size = (
        left + cell_w * columns.len() as u32 + 20,
        top + cell_h * rows.len() as u32 + 20,
    );
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE)?;
    let font = ("sans-serif", 14).into_font();
    let title = if on_paper_rig {
        "RMSE / paper SMC-DOB (completed/trials); red border: not all completed"
    } else {
        "RMSE mm (completed/trials); red border: not all completed"
    };
    root.draw(&Text::new(title, (10, 10), ("sans-serif", 16).into_font()))?;
    for (j, (neg_period, controller)) in columns.iter().enumerate() {
        let x = (left + cell_w * j as u32) as i32;
        let label = format!("{controller} {:.0} Hz", 1000.0 / (-*neg_period) as f64);
        root.draw(&Text::new(label, (x + 4, top as i32 - 22), font.clone()))?;
    }
    for (i, (axis, level)) in rows.iter().enumerate() {
        let y = (top + cell_h * i as u32) as i32;
        root.draw(&Text::new(
            format!("{} = {level}", axis.name()),
            (10, y + 6),
            font.clone(),
        ))?;
        for (j, (neg_period, controller)) in columns.iter().enumerate() {
            let Some(group) = groups.iter().find(|g| {
                let c = &g[0].case;
                c.axis == *axis
                    && c.level == *level
                    && -(c.frame_period_ms as i64) == *neg_period
                    && &c.controller == controller
            }) else {
                continue;
            };
            let (done, rmse, ratio) = summary(group, on_paper_rig);
            let ratio = ratio.unwrap_or(rmse);
            let x = (left + cell_w * j as u32) as i32;
            // log10(ratio) from 0 (green) to 1 (red).
            let t = ratio.max(1e-3).log10().clamp(0.0, 1.0);
            let colour = if ratio <= 1.0 {
                RGBColor(120, 200, 120)
            } else {
                RGBColor(
                    (230.0 + 25.0 * t) as u8,
                    (200.0 * (1.0 - t) + 40.0) as u8,
                    (100.0 * (1.0 - t)) as u8,
                )
            };
            let rect = [(x, y), (x + cell_w as i32 - 2, y + cell_h as i32 - 2)];
            root.draw(&Rectangle::new(rect, colour.filled()))?;
            if done < group.len() {
                root.draw(&Rectangle::new(rect, RED.stroke_width(3)))?;
            }
            root.draw(&Text::new(
                format!("{ratio:.2} ({done}/{})", group.len()),
                (x + 6, y + 6),
                font.clone(),
            ))?;
        }
    }
    root.present()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_matrix_varies_around_each_rigs_most_viscous_fluid_at_its_lowest_flow() {
        let root = fieldmaps::data_root();
        let paper = Around::on_rig(&Rig::load_paper().unwrap()).unwrap();
        assert_eq!(
            paper,
            Around {
                viscosity_cp: 20.0,
                flow: FlowSetting::Q180,
                viscosities_cp: vec![4.3, 20.0],
            }
        );
        // vessel8: 6 cP at 200 mL/min, 4.3 cP at 120 and 200 mL/min.
        let vessel8 = Rig::load(&root.join("fieldmaps/rigs/vessel8.toml")).unwrap();
        let around = Around::on_rig(&vessel8).unwrap();
        assert_eq!(
            around,
            Around {
                viscosity_cp: 6.0,
                flow: FlowSetting::Flow(200),
                viscosities_cp: vec![4.3, 6.0],
            }
        );
        let base = Scenario::load(&root.join("scenarios/vessel8.toml")).unwrap();
        for case in cases(&["pid".to_string()], 1, &around) {
            let text = case_scenario(&base, &case).unwrap();
            let scenario = Scenario::parse(&text, &root.join("scenarios/case.toml")).unwrap();
            assert_eq!(scenario.fluid.viscosity_cp, case.viscosity_cp);
            assert!(text.contains("q200_mu"), "{}: {text}", case.name());
        }
    }

    #[test]
    fn every_axis_reaches_the_scenario() {
        let root = fieldmaps::data_root();
        let base = Scenario::load(&root.join("scenarios/paper.toml")).unwrap();
        let base_in_frame_ms = keys::COMMAND_DELAY_MS.number(&base.sections).unwrap_or(0.0);
        let controllers = vec!["smc-dob-auto".to_string()];
        let around = Around::on_rig(&Rig::load_paper().unwrap()).unwrap();
        let all = cases(&controllers, 1, &around);
        // 50 ms is half a frame at 10 Hz: run there too, inside the frame.
        for period in [10.0, 100.0] {
            assert!(all
                .iter()
                .any(|c| c.level == 50.0 && c.frame_period_ms == period));
        }
        for case in &all {
            let text = case_scenario(&base, case).unwrap();
            let scenario = Scenario::parse(&text, &root.join("scenarios/case.toml")).unwrap();
            assert_eq!(scenario.run.frame_period_ms, case.frame_period_ms);
            let expect = |key: &str| assert!(text.contains(key), "{}: {text}", case.name());
            match case.axis {
                Axis::PulsationHz => expect(&format!("pulsation_hz = {:?}", case.level)),
                Axis::PulsationAmplitude => {
                    expect(&format!("pulsation_amplitude = {:?}", case.level))
                }
                Axis::FlowNoise => expect(&format!("fraction = {:?}", case.level)),
                Axis::Recirculation => expect(&format!("strength_fraction = {:?}", case.level)),
                Axis::CoilGainError => expect(&format!("coil_gain_error_std = {:?}", case.level)),
                Axis::CameraLatencyMs => {
                    // The level comes on top of the base's own delay inside the frame (the
                    // scenario's pipeline), whole frames as camera latency, the rest inside.
                    let doc: toml::Table = toml::from_str(&text).unwrap();
                    let number = |table: &str, sub: Option<&str>, key: &str| {
                        let mut t = doc[table].as_table().unwrap();
                        if let Some(sub) = sub {
                            t = t[sub].as_table().unwrap();
                        }
                        t.get(key).map_or(0.0, |v| {
                            v.as_float().or(v.as_integer().map(|i| i as f64)).unwrap()
                        })
                    };
                    let total = base_in_frame_ms + case.level;
                    let frames = (total / case.frame_period_ms + 1e-9).floor();
                    let in_frame = total - frames * case.frame_period_ms;
                    let name = case.name();
                    assert_eq!(
                        number("plant", Some("camera"), "latency_frames"),
                        frames,
                        "{name}"
                    );
                    for (table, sub, key) in [
                        ("plant", None, "command_delay_ms"),
                        ("control", Some("latency"), "unstamped_delay_ms"),
                    ] {
                        let got = number(table, sub, key);
                        assert!((got - in_frame).abs() < 1e-9, "{name}: {key} {got}");
                    }
                }
                Axis::ViscosityCp => assert_eq!(scenario.fluid.viscosity_cp, case.level),
            }
        }
    }
}
