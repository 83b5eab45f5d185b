//! The `fieldgen cfd` command: its arguments, the rig's flow conditions, and the maps it writes
//! (with their speed images), solved in parallel with progress and a summary.

use super::*;

/// Writes a speed image (viridis-like ramp, 0 → `max_mps`) of `map` as an RGB PNG, north up.
pub fn write_speed_png(map: &FlowMap, max_mps: f64, path: &Path) -> anyhow::Result<()> {
    let (w, h) = (map.nx as u32, map.ny as u32);
    let mut data = Vec::with_capacity((w * h * 3) as usize);
    let ramp = [
        (0.0, [68.0, 1.0, 84.0]),
        (0.25, [59.0, 82.0, 139.0]),
        (0.5, [33.0, 145.0, 140.0]),
        (0.75, [94.0, 201.0, 98.0]),
        (1.0, [253.0, 231.0, 37.0]),
    ];
    for j in (0..map.ny).rev() {
        for i in 0..map.nx {
            let v = map.velocity_mps[j * map.nx + i];
            if v.norm() == 0.0 {
                data.extend_from_slice(&[0, 0, 0]);
                continue;
            }
            let t = (v.norm() / max_mps).clamp(0.0, 1.0);
            let k = ramp.iter().rposition(|r| r.0 <= t).unwrap_or(0).min(3);
            let (t0, c0) = ramp[k];
            let (t1, c1) = ramp[k + 1];
            let s = (t - t0) / (t1 - t0);
            for c in 0..3 {
                data.push((c0[c] + s * (c1[c] - c0[c])) as u8);
            }
        }
    }
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut writer = enc.write_header()?;
    writer.write_image_data(&data)?;
    writer.finish()?;
    Ok(())
}

/// Arguments of `fieldgen cfd`.
#[derive(Debug, clap::Args)]
pub struct CfdArgs {
    /// Rig file: the canal mask, the ports (`[[phantom.inlets]]`, `[[phantom.outlets]]`), the
    /// zones and the flow conditions (`[[phantom.flow]]`), e.g. fieldmaps/rigs/paper.toml.
    #[arg(long)]
    pub rig: PathBuf,
    /// Solve every `[[phantom.flow]]` condition of the rig and write each to its `map` path
    /// (or into --out-dir under the same file name).
    #[arg(long)]
    pub all: bool,
    /// Total pump flow of a single condition, mL/min.
    #[arg(long)]
    pub flow_ml_min: Option<f64>,
    /// Viscosity of a single condition, cP.
    #[arg(long)]
    pub viscosity_cp: Option<f64>,
    /// Output file of a single condition (default: <out-dir>/<condition>.flow.csv).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write the maps here instead of the rig's `map` paths (with --all), or the single
    /// condition's <condition>.flow.csv.
    #[arg(long)]
    pub out_dir: Option<PathBuf>,
    /// Use this canal mask PNG instead of the rig's (same size and scale as the rig's mask,
    /// white = canal), e.g. to try an edited outline; the ports and zones stay the rig's.
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// Write the canal mask (the rig's, or --mask) as an 8-bit PNG here.
    #[arg(long)]
    pub write_mask: Option<PathBuf>,
    /// Also write <condition>.speed.png images next to the maps.
    #[arg(long)]
    pub images: bool,
    /// Run the solver validation cases and print their errors.
    #[arg(long)]
    pub validate: bool,
    /// Lattice spacing, mm.
    #[arg(long, default_value_t = 0.3)]
    pub dx_mm: f64,
    /// Output map spacing, mm.
    #[arg(long, default_value_t = 0.5)]
    pub out_spacing_mm: f64,
    /// Effective depth H of the depth-averaged model, mm (calibrated: see README).
    #[arg(long, default_value_t = EFFECTIVE_DEPTH_M * 1e3)]
    pub depth_mm: f64,
    /// Steady-state tolerance (relative velocity change per step).
    #[arg(long, default_value_t = 1e-7)]
    pub tolerance: f64,
    /// Step limit per condition.
    #[arg(long, default_value_t = 300_000)]
    pub max_steps: usize,
    /// Conditions solved in parallel.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

pub fn run(args: &CfdArgs) -> anyhow::Result<()> {
    let rig = load_rig(&args.rig)?;
    let mask = match &args.mask {
        Some(path) => {
            CanalMask::load_png(path, rig.phantom.mask.geometry()).with_context(|| {
                format!("--mask {} (must match the rig's mask size)", path.display())
            })?
        }
        None => rig.phantom.mask.clone(),
    };
    let did_something = write_mask_and_validate(args, &mask)?;
    let jobs = selected_conditions(args, &rig)?;
    if jobs.is_empty() {
        if !did_something {
            anyhow::bail!("nothing to do: give --all, --flow-ml-min with --viscosity-cp, --validate or --write-mask");
        }
        return Ok(());
    }
    let settings = CfdSettings {
        dx_m: args.dx_mm * 1e-3,
        depth_m: args.depth_mm * 1e-3,
        tolerance: args.tolerance,
        max_steps: args.max_steps,
        out_spacing_m: args.out_spacing_mm * 1e-3,
        ..CfdSettings::default()
    };
    let ports = rig_ports(&args.rig, &rig.phantom.inlets, &rig.phantom.outlets);
    for (_, path) in &jobs {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
    }
    let source = format!(
        "rig {} ({}), mask {}",
        rig.name,
        args.rig.display(),
        args.mask
            .as_deref()
            .unwrap_or(&rig.phantom.mask_path)
            .display()
    );
    let job = MapJob {
        args,
        mask: &mask,
        ports: &ports,
        zones: &rig.phantom.zones,
        settings: &settings,
        source: &source,
    };
    let outputs: Vec<(String, PathBuf)> = jobs
        .iter()
        .map(|(c, p)| (c.name.clone(), p.clone()))
        .collect();
    let conditions = jobs.into_iter().map(|(c, _)| c).collect();
    let results = solve_in_parallel(conditions, args.threads, settings.max_steps, |c, bar| {
        let path = outputs
            .iter()
            .find(|(name, _)| *name == c.name)
            .map(|(_, p)| p.as_path())
            .ok_or_else(|| anyhow::anyhow!("no output path for {}", c.name))?;
        job.solve_and_write(c, path, bar)
    })?;
    let mut failed = false;
    for (condition, result) in results {
        match result {
            Ok(stats) => println!("{}", stats.summary()),
            Err(e) => {
                failed = true;
                eprintln!("{}: {e:#}", condition.name);
            }
        }
    }
    if failed {
        anyhow::bail!("some conditions failed");
    }
    Ok(())
}

/// Loads a rig for the generators (`cfd`, `coils`, `import`), which may be about to make data
/// it names: when its flow maps fail (not made yet, or made for other conditions) the rest is
/// loaded and the `[[phantom.flow]]` conditions are read without their maps; when its twin's
/// coil maps fail, the twin falls back to the control model. Any other error is the loader's.
pub fn load_rig(path: &Path) -> anyhow::Result<Rig> {
    let mut err = match Rig::load(path) {
        Ok(rig) => return Ok(rig),
        Err(e) => e,
    };
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut doc: toml::Table = toml::from_str(&text)?;
    let mut flows = None;
    // At most one retry per tolerated failure.
    for _ in 0..2 {
        let field = err.field().unwrap_or_default();
        if field.starts_with("phantom.flow[") && flows.is_none() {
            flows = doc
                .get_mut("phantom")
                .and_then(toml::Value::as_table_mut)
                .and_then(|p| p.remove("flow"));
        } else if field == "electromagnet.twin_field_model" {
            doc.get_mut("electromagnet")
                .and_then(toml::Value::as_table_mut)
                .and_then(|e| e.remove("twin_field_model"));
        } else {
            return Err(err.into());
        }
        match Rig::parse(&toml::to_string(&doc)?, path) {
            Ok(mut rig) => {
                if flows.is_some() {
                    rig.phantom.flow_conditions = flow_conditions(path, flows)?;
                }
                return Ok(rig);
            }
            Err(e) => err = e,
        }
    }
    Err(err.into())
}

/// The `[[phantom.flow]]` conditions of the rig at `path`, their maps unchecked.
pub(super) fn flow_conditions(
    path: &Path,
    flows: Option<toml::Value>,
) -> anyhow::Result<Vec<FlowCondition>> {
    let dir = path.parent().unwrap_or(Path::new(""));
    let sections: Vec<FlowSection> = match flows {
        Some(v) => v
            .try_into()
            .map_err(|e| anyhow::anyhow!("{}: phantom.flow: {e}", path.display()))?,
        None => return Ok(Vec::new()),
    };
    let mut names = std::collections::HashSet::new();
    let mut out = Vec::with_capacity(sections.len());
    for (i, f) in sections.into_iter().enumerate() {
        let bad = |key: &str, what: &str| {
            anyhow::anyhow!("{}: phantom.flow[{i}].{key}: {what}", path.display())
        };
        if f.name.is_empty() || !names.insert(f.name.clone()) {
            return Err(bad("name", "must be non-empty and unique"));
        }
        if !(f.flow_ml_min.is_finite() && f.flow_ml_min > 0.0) {
            return Err(bad("flow_ml_min", "must be > 0"));
        }
        if !(f.viscosity_cp.is_finite() && f.viscosity_cp > 0.0) {
            return Err(bad("viscosity_cp", "must be > 0"));
        }
        out.push(FlowCondition {
            name: f.name,
            map_path: dir.join(&f.map),
            flow_ml_min: f.flow_ml_min,
            viscosity_pa_s: f.viscosity_cp * 1e-3,
        });
    }
    Ok(out)
}

/// A `[[phantom.flow]]` table as `fieldgen cfd` needs it (its map need not exist yet).
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct FlowSection {
    name: String,
    map: PathBuf,
    flow_ml_min: f64,
    viscosity_cp: f64,
}

/// The side tasks of `fieldgen cfd`: `--write-mask` and `--validate`. Returns whether any ran.
pub(super) fn write_mask_and_validate(args: &CfdArgs, mask: &CanalMask) -> anyhow::Result<bool> {
    let mut did_something = false;
    if let Some(path) = &args.write_mask {
        mask.save_png(path)?;
        println!(
            "wrote canal mask {} ({} canal px)",
            path.display(),
            mask.canal_pixels()
        );
        did_something = true;
    }
    if args.validate {
        let (_, text) = crate::validate::run_all()?;
        print!("{text}");
        did_something = true;
    }
    Ok(did_something)
}

/// The conditions the arguments ask for, each with its output file (none when they name no
/// condition).
pub(super) fn selected_conditions(
    args: &CfdArgs,
    rig: &Rig,
) -> anyhow::Result<Vec<(Condition, PathBuf)>> {
    let jobs = match (args.all, args.flow_ml_min, args.viscosity_cp) {
        (true, None, None) => {
            if rig.phantom.flow_conditions.is_empty() {
                anyhow::bail!(
                    "{}: phantom.flow: --all needs at least one [[phantom.flow]] condition",
                    args.rig.display()
                );
            }
            rig.phantom
                .flow_conditions
                .iter()
                .map(|fc| {
                    let path = match &args.out_dir {
                        Some(dir) => dir.join(fc.map_path.file_name().unwrap_or(fc.name.as_ref())),
                        None => fc.map_path.clone(),
                    };
                    (Condition::from_rig(fc), path)
                })
                .collect()
        }
        (false, Some(q), Some(mu)) => {
            let c = Condition::new(q, mu);
            let path = match (&args.out, &args.out_dir) {
                (Some(out), _) => out.clone(),
                (None, Some(dir)) => dir.join(format!("{}.flow.csv", c.name)),
                (None, None) => anyhow::bail!("give --out or --out-dir for a single condition"),
            };
            vec![(c, path)]
        }
        (false, None, None) => Vec::new(),
        (true, _, _) => anyhow::bail!("--all cannot be combined with --flow-ml-min/--viscosity-cp"),
        _ => anyhow::bail!("give both --flow-ml-min and --viscosity-cp (or --all)"),
    };
    if args.out.is_some() && args.all {
        anyhow::bail!("--out needs exactly one condition (use --out-dir with --all)");
    }
    Ok(jobs)
}

/// What every condition's solve shares: the domain, the settings and where maps go.
pub(super) struct MapJob<'a> {
    args: &'a CfdArgs,
    mask: &'a CanalMask,
    ports: &'a [Port],
    zones: &'a [Zone],
    settings: &'a CfdSettings,
    /// The domain's description for the map header.
    source: &'a str,
}

impl MapJob<'_> {
    /// Solves `condition` and writes its map to `path` (and speed image with `--images`).
    fn solve_and_write(
        &self,
        condition: &Condition,
        path: &Path,
        bar: &indicatif::ProgressBar,
    ) -> anyhow::Result<CfdStats> {
        let (map, stats) = solve(
            self.mask,
            self.ports,
            self.zones,
            condition,
            self.settings,
            |steps, res| {
                bar.set_position(steps as u64);
                bar.set_message(format!("residual {res:.1e}"));
            },
        )?;
        bar.finish_with_message(format!(
            "residual {:.1e}, peak {:.1} mm/s",
            stats.convergence.residual,
            stats.chamber_peak_mps * 1e3
        ));
        std::fs::write(path, self.map_header(condition, &stats) + &map.to_text())
            .with_context(|| format!("writing {}", path.display()))?;
        if self.args.images {
            let png = path.with_extension("").with_extension("speed.png");
            write_speed_png(&map, stats.peak_mps, &png)?;
        }
        Ok(stats)
    }

    /// The `# key = value` lines that head a generated map.
    fn map_header(&self, condition: &Condition, stats: &CfdStats) -> String {
        let (source, settings) = (self.source, self.settings);
        format!(
            "# generated by: fieldgen cfd (depth-averaged D2Q9 TRT lattice Boltzmann, see fieldmaps/flow/README_SECTION.md)\n\
             # domain = {source}\n# condition = {}\n\
             # flow_ml_min = {}\n# viscosity_cp = {}\n# density_kg_m3 = {}\n\
             # effective_depth_mm = {}\n# control_plane_factor = {PLANE_FACTOR}\n\
             # lattice_dx_mm = {:.4}\n# steps = {}\n# residual = {:.3e}\n\
             # mass_imbalance = {:.3e}\n# peak_mps = {:.5}\n# chamber_peak_mps = {:.5}\n",
            condition.name,
            condition.flow_ml_min(),
            condition.viscosity_cp(),
            settings.density_kg_m3,
            settings.depth_m * 1e3,
            stats.dx_m * 1e3,
            stats.convergence.steps,
            stats.convergence.residual,
            stats.mass_imbalance(),
            stats.peak_mps,
            stats.chamber_peak_mps,
        )
    }
}

/// Runs `solve_one` for every condition on up to `threads` threads, each with its own progress
/// bar (`max_steps` long). Results come back in the order of `conditions`.
pub(super) fn solve_in_parallel(
    conditions: Vec<Condition>,
    threads: usize,
    max_steps: usize,
    solve_one: impl Fn(&Condition, &indicatif::ProgressBar) -> anyhow::Result<CfdStats> + Sync,
) -> anyhow::Result<Vec<(Condition, anyhow::Result<CfdStats>)>> {
    let bars = indicatif::MultiProgress::new();
    let style = indicatif::ProgressStyle::with_template(
        "{prefix:>14} [{elapsed_precise}] {bar:30} {pos}/{len} steps {msg}",
    )?;
    let jobs: Vec<(Condition, indicatif::ProgressBar)> = conditions
        .into_iter()
        .map(|c| {
            let bar = bars.add(indicatif::ProgressBar::new(max_steps as u64));
            bar.set_style(style.clone());
            bar.set_prefix(c.name.clone());
            (c, bar)
        })
        .collect();
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<(usize, anyhow::Result<CfdStats>)>> = Mutex::new(Vec::new());
    std::thread::scope(|scope| {
        for _ in 0..threads.clamp(1, jobs.len()) {
            scope.spawn(|| loop {
                let k = next.fetch_add(1, Ordering::SeqCst);
                let Some((condition, bar)) = jobs.get(k) else {
                    break;
                };
                let outcome = solve_one(condition, bar);
                if outcome.is_err() {
                    bar.abandon_with_message("failed");
                }
                if let Ok(mut r) = results.lock() {
                    r.push((k, outcome));
                }
            });
        }
    });
    let mut results = results
        .into_inner()
        .map_err(|_| anyhow::anyhow!("worker panicked"))?;
    results.sort_by_key(|r| r.0);
    let mut conditions: Vec<Option<Condition>> = jobs.into_iter().map(|(c, _)| Some(c)).collect();
    Ok(results
        .into_iter()
        .filter_map(|(k, r)| conditions[k].take().map(|c| (c, r)))
        .collect())
}
