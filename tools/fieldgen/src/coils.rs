//! `fieldgen coils`: sample a rig's Biot–Savart coil model as current-normalized field maps
//! B̃_i, ∇B̃_i on a 3D grid over the workspace, write them in the format of
//! `fieldmaps/coils/FORMAT.md`, compare model and maps with the rig's reference fields, verify
//! the interpolated maps against the direct model, and cross-check the direct model against
//! magpylib.
//!
//! `fieldgen coils --check` prints those numbers for the existing maps without rewriting them.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::{bail, Context};
use fieldmaps::coils::{CoilField, CoilSystem, FieldReading, ReferenceField};
use fieldmaps::fieldmap::{sample_coil, CoilFieldMaps, CoilInfo, GridSpec, Interpolation};
use fieldmaps::rigfile::{FieldModel, Rig};
use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

/// The grid of coil maps, centred on the workspace (z = 0 is the control plane).
#[derive(Debug, Clone, clap::Args)]
pub struct MapGridArgs {
    /// Map grid spacing, mm (shrunk slightly if needed so nodes land on the faces).
    #[arg(long, default_value_t = 2.0)]
    pub spacing_mm: f64,
    /// Half-extent of the map grid along x and y, mm (the paper's workspace is ±50 mm).
    #[arg(long, default_value_t = 50.0)]
    pub half_xy_mm: f64,
    /// Half-extent of the map grid along z, mm.
    #[arg(long, default_value_t = 8.0)]
    pub half_z_mm: f64,
}

impl MapGridArgs {
    pub fn spec(&self) -> anyhow::Result<GridSpec> {
        Ok(GridSpec::centered(
            [
                self.half_xy_mm * 1e-3,
                self.half_xy_mm * 1e-3,
                self.half_z_mm * 1e-3,
            ],
            self.spacing_mm * 1e-3,
        )?)
    }
}

/// Arguments of `fieldgen coils`.
#[derive(Debug, clap::Args)]
pub struct CoilsArgs {
    /// Rig file whose coils to model (their windings and turns), e.g.
    /// fieldmaps/rigs/paper.toml.
    #[arg(long)]
    pub rig: PathBuf,
    /// Map directory to write (or, with --check, to verify). Default: the `dir` of the rig's
    /// field model of kind "maps" (`twin_field_model`, else `field_model`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub grid: MapGridArgs,
    /// Do not regenerate: verify the existing maps and run the magpylib cross-check.
    #[arg(long)]
    pub check: bool,
    /// Also run the magpylib cross-check after generating (always on with --check).
    #[arg(long)]
    pub magpylib: bool,
    /// Random points for the interpolation check.
    #[arg(long, default_value_t = 4000)]
    pub verify_points: usize,
    /// Seed of the random verification points.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Worker threads for sampling.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Write the coils' filaments (centre, axis, radius, turns) as JSON to this file and exit.
    #[arg(long)]
    pub export_loops: Option<PathBuf>,
    /// Evaluate the direct model at the points of this JSON file ({"points_m": [[x, y, z], ...]})
    /// and exit; the result goes to --probe-out.
    #[arg(long, requires = "probe_out")]
    pub probe: Option<PathBuf>,
    /// Output JSON of --probe.
    #[arg(long, requires = "probe")]
    pub probe_out: Option<PathBuf>,
    /// Python with magpylib for the cross-check. Default: $MILLINAV_VENV/bin/python, else
    /// ~/.cache/millinav/venv/bin/python.
    #[arg(long)]
    pub python: Option<PathBuf>,
}

/// The closed-form model of a rig's coils, from the windings and turns the file gives.
pub fn rig_system(rig: &Rig) -> anyhow::Result<CoilSystem> {
    rig.winding_model().ok_or_else(|| {
        anyhow::anyhow!(
            "{}: [[coils]]: fieldgen coils needs `turns` and [coils.winding] on every coil to model it",
            rig.path.display()
        )
    })
}

/// Where the rig keeps its coil maps, if it uses any (the twin's first).
fn rig_maps_dir(rig: &Rig) -> Option<PathBuf> {
    [&rig.twin_field_model, &rig.field_model]
        .into_iter()
        .find_map(|m| match m {
            FieldModel::Maps(dir) => Some(dir.clone()),
            FieldModel::Analytic => None,
        })
}

pub fn run(args: &CoilsArgs) -> anyhow::Result<()> {
    let rig = crate::cfd::load_rig(&args.rig)?;
    let system = rig_system(&rig)?;
    if let Some(path) = &args.export_loops {
        write_json(path, &export_loops(&system))?;
        println!(
            "wrote {} coils' filaments to {}",
            system.len(),
            path.display()
        );
        return Ok(());
    }
    if let (Some(points), Some(out)) = (&args.probe, &args.probe_out) {
        let text = std::fs::read_to_string(points)
            .with_context(|| format!("reading {}", points.display()))?;
        let input: ProbeInput = serde_json::from_str(&text).with_context(|| {
            format!(
                "{}: expected {{\"points_m\": [[x, y, z], ...]}}",
                points.display()
            )
        })?;
        let result = probe(&system, &input.points_m)
            .with_context(|| format!("probing points of {}", points.display()))?;
        write_json(out, &result)?;
        println!("wrote {} probes to {}", input.points_m.len(), out.display());
        return Ok(());
    }

    let provenance = report_reference_fields(&rig, &system)?;
    let dir = match (&args.out, rig_maps_dir(&rig)) {
        (Some(out), _) => out.clone(),
        (None, Some(dir)) => dir,
        (None, None) => bail!(
            "{}: electromagnet: no field model of kind \"maps\" names a directory; give --out",
            args.rig.display()
        ),
    };
    if !args.check {
        let grid = args.grid.spec()?;
        let maps = generate(&system, grid, args.threads.max(1))?;
        let command = format!(
            "fieldgen coils --spacing-mm {} --half-xy-mm {} --half-z-mm {}",
            args.grid.spacing_mm, args.grid.half_xy_mm, args.grid.half_z_mm
        );
        let description = format!(
            "Current-normalized field and gradient of the {} coils of rig {} (closed-form \
             Biot-Savart of their windings); see FORMAT.md",
            system.len(),
            rig.name
        );
        maps.write(&dir, &description, &command, provenance)?;
        let bytes: u64 = std::fs::read_dir(&dir)?
            .filter_map(|e| e.ok()?.metadata().ok())
            .map(|m| m.len())
            .sum();
        println!(
            "wrote {} coil maps to {} ({:.1} MB in the directory)",
            maps.coils().len(),
            dir.display(),
            bytes as f64 / 1e6
        );
    }
    let maps = CoilFieldMaps::load(&dir)?;
    let g = maps.grid();
    println!(
        "maps: {} coils, grid {}×{}×{} nodes, spacing {:.3} mm, x,y ∈ [{:.1}, {:.1}] mm, z ∈ [{:.1}, {:.1}] mm",
        maps.coils().len(),
        g.shape[0],
        g.shape[1],
        g.shape[2],
        g.spacing_m[0] * 1e3,
        g.origin_m[0] * 1e3,
        g.max_m()[0] * 1e3,
        g.origin_m[2] * 1e3,
        g.max_m()[2] * 1e3,
    );
    report_map_reference_fields(&rig, &maps);
    println!(
        "interpolation error vs direct Biot–Savart at {} random points in the grid box, all {} coils \
         (relative: |ΔB̃|/|B̃| and ‖Δ∇B̃‖_F/‖∇B̃‖_F):",
        args.verify_points,
        maps.coils().len()
    );
    let mut maps = maps;
    for scheme in [Interpolation::Quadratic, Interpolation::Trilinear] {
        maps.set_interpolation(scheme);
        let err = interpolation_error(&system, &maps, args.verify_points, args.seed);
        println!(
            "  {:<9} field max {:.2e} (99th pct {:.2e}), gradient max {:.2e} (99th pct {:.2e}){}",
            format!("{scheme:?}"),
            err.field_max,
            err.field_p99,
            err.gradient_max,
            err.gradient_p99,
            if scheme == Interpolation::default() {
                "  [default]"
            } else {
                ""
            }
        );
    }

    if args.check || args.magpylib {
        run_magpylib_check(args)?;
    }
    Ok(())
}

/// Print how the direct model meets each of the rig's reference fields and return the
/// comparison as manifest provenance (None when the rig gives none).
fn report_reference_fields(rig: &Rig, system: &CoilSystem) -> anyhow::Result<Option<toml::Table>> {
    if rig.reference_fields.is_empty() {
        println!(
            "reference fields: none in {} (the maps are the windings' Biot–Savart as given)",
            rig.path.display()
        );
        return Ok(None);
    }
    println!(
        "reference fields of {} vs the direct model:",
        rig.path.display()
    );
    let mut entries = Vec::new();
    for (k, reference) in rig.reference_fields.iter().enumerate() {
        let read = reference.measure(system);
        print_reference(k, rig, reference, &read);
        let mut t = toml::Table::new();
        t.insert("source".into(), reference.source.clone().into());
        let names: Vec<&str> = reference
            .currents_a
            .iter()
            .map(|&(i, _)| rig.coils[i].name.as_str())
            .collect();
        t.insert("coils".into(), toml::Value::try_from(names)?);
        let amps: Vec<f64> = reference.currents_a.iter().map(|&(_, a)| a).collect();
        t.insert("currents_a".into(), toml::Value::try_from(amps)?);
        let p = reference.point_m * 1e3;
        t.insert("point_mm".into(), toml::Value::try_from([p.x, p.y, p.z])?);
        t.insert(
            "reference_field_mt".into(),
            (reference.field_t * 1e3).into(),
        );
        t.insert("model_field_mt".into(), (read.field_t * 1e3).into());
        if let Some(g) = reference.gradient_t_per_m {
            t.insert("reference_gradient_mt_per_cm".into(), (g * 10.0).into());
            t.insert(
                "model_gradient_mt_per_cm".into(),
                (read.gradient_t_per_m * 10.0).into(),
            );
        }
        entries.push(toml::Value::Table(t));
    }
    let mut provenance = toml::Table::new();
    provenance.insert("reference_fields".into(), toml::Value::Array(entries));
    Ok(Some(provenance))
}

/// One line per reference: what the model gives, what the reference says, the relative error.
fn print_reference(k: usize, rig: &Rig, reference: &ReferenceField, read: &FieldReading) {
    let drive: Vec<String> = reference
        .currents_a
        .iter()
        .map(|&(i, a)| format!("{} {a:.3} A", rig.coils[i].name))
        .collect();
    let p = reference.point_m * 1e3;
    println!(
        "  [{k}] {} ({}) at ({:.1}, {:.1}, {:.1}) mm:",
        reference.source,
        drive.join(", "),
        p.x,
        p.y,
        p.z
    );
    let pct = |model: f64, expected: f64| (model / expected - 1.0) * 100.0;
    let mut line = format!(
        "      |B| {:.3} mT (reference {:.3} mT, {:+.3} %)",
        read.field_t * 1e3,
        reference.field_t * 1e3,
        pct(read.field_t, reference.field_t)
    );
    if let Some(g) = reference.gradient_t_per_m {
        line += &format!(
            ", gradient {:.3} mT/cm (reference {:.3} mT/cm, {:+.3} %)",
            read.gradient_t_per_m * 10.0,
            g * 10.0,
            pct(read.gradient_t_per_m, g)
        );
    }
    println!("{line}");
}

/// The reference fields measured on the interpolated maps (where the maps cover the point).
fn report_map_reference_fields(rig: &Rig, maps: &CoilFieldMaps) {
    for (k, reference) in rig.reference_fields.iter().enumerate() {
        let mut b = Vector3::zeros();
        let mut g = Matrix3::zeros();
        for &(i, amps) in &reference.currents_a {
            let name = &rig.coils[i].name;
            let Some(m) = maps.coil_index(name) else {
                println!("  [{k}] on the maps: they have no coil named {name}");
                return;
            };
            let Ok((bi, gi)) = maps.try_field_and_gradient_per_amp(m, &reference.point_m) else {
                println!("  [{k}] on the maps: they do not cover the point");
                return;
            };
            b += bi * amps;
            g += gi * amps;
        }
        let read = reference.reading(&b, &g);
        println!(
            "  [{k}] on the interpolated maps: |B| {:.3} mT, gradient {:.3} mT/cm",
            read.field_t * 1e3,
            read.gradient_t_per_m * 10.0
        );
    }
}

/// Sample all coils on `grid` with `threads` workers and a progress bar.
pub fn generate(
    system: &CoilSystem,
    grid: GridSpec,
    threads: usize,
) -> anyhow::Result<CoilFieldMaps> {
    let n = system.len();
    let bar = ProgressBar::new((n * grid.node_count()) as u64);
    bar.set_style(ProgressStyle::with_template(
        "sampling {bar:40} {percent:>3}% {human_pos}/{human_len} nodes×coils, eta {eta}",
    )?);
    let next = AtomicUsize::new(0);
    let mut data: Vec<Option<Vec<f32>>> = vec![None; n];
    std::thread::scope(|s| {
        let workers: Vec<_> = (0..threads.min(n))
            .map(|_| {
                s.spawn(|| {
                    let mut done = Vec::new();
                    loop {
                        let coil = next.fetch_add(1, Ordering::Relaxed);
                        if coil >= n {
                            break done;
                        }
                        let values = sample_coil(system, coil, &grid, |k| bar.inc(k as u64));
                        done.push((coil, values));
                    }
                })
            })
            .collect();
        for w in workers {
            if let Ok(done) = w.join() {
                for (coil, values) in done {
                    data[coil] = Some(values);
                }
            }
        }
    });
    bar.finish_and_clear();
    let data: Vec<Vec<f32>> = data
        .into_iter()
        .enumerate()
        .map(|(i, d)| d.with_context(|| format!("sampling coil {i} failed")))
        .collect::<anyhow::Result<_>>()?;
    let coils = system
        .coils
        .iter()
        .map(|c| CoilInfo {
            name: c.name.clone(),
            center_m: Some(c.center_m.into()),
            axis: Some(c.axis.into_inner().into()),
            total_turns: Some(c.total_turns()),
        })
        .collect();
    Ok(CoilFieldMaps::from_parts(grid, coils, data)?)
}

/// Maximum and 99th-percentile relative errors of the interpolated maps.
#[derive(Debug, Clone, Copy)]
pub struct InterpolationError {
    pub field_max: f64,
    pub field_p99: f64,
    pub gradient_max: f64,
    pub gradient_p99: f64,
}

/// Compare `maps` with `direct` at `n` uniformly random points of the maps' grid box, every coil.
pub fn interpolation_error<F: CoilField + ?Sized>(
    direct: &F,
    maps: &CoilFieldMaps,
    n: usize,
    seed: u64,
) -> InterpolationError {
    let g = *maps.grid();
    let max = g.max_m();
    let mut rng = SplitMix(seed);
    let mut ef = Vec::with_capacity(n * maps.coils().len());
    let mut eg = Vec::with_capacity(n * maps.coils().len());
    for _ in 0..n {
        let p = Vector3::from_fn(|k, _| g.origin_m[k] + rng.unit() * (max[k] - g.origin_m[k]));
        for coil in 0..maps.coil_count().min(direct.coil_count()) {
            let (bd, gd) = direct.field_and_gradient_per_amp(coil, &p);
            let (bi, gi) = maps.field_and_gradient_per_amp(coil, &p);
            ef.push((bi - bd).norm() / bd.norm());
            eg.push((gi - gd).norm() / gd.norm());
        }
    }
    let stats = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        let max = v.last().copied().unwrap_or(0.0);
        let p99 = v
            .get(((v.len() as f64) * 0.99) as usize)
            .copied()
            .unwrap_or(max);
        (max, p99)
    };
    let (field_max, field_p99) = stats(&mut ef);
    let (gradient_max, gradient_p99) = stats(&mut eg);
    InterpolationError {
        field_max,
        field_p99,
        gradient_max,
        gradient_p99,
    }
}

/// SplitMix64: small deterministic generator for verification points.
struct SplitMix(u64);
impl SplitMix {
    fn unit(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// JSON of `--export-loops`: every filament as a circular loop (SI units).
#[derive(Debug, Serialize, Deserialize)]
pub struct LoopsExport {
    pub units: String,
    pub convention: String,
    pub coils: Vec<CoilLoops>,
}

#[derive(Debug, Serialize, Deserialize)]
pub struct CoilLoops {
    pub name: String,
    pub center_m: [f64; 3],
    pub axis: [f64; 3],
    pub turns_per_loop: f64,
    pub loops: Vec<LoopExport>,
}

#[derive(Debug, Serialize, Deserialize)]
pub struct LoopExport {
    pub center_m: [f64; 3],
    pub radius_m: f64,
}

pub fn export_loops(system: &CoilSystem) -> LoopsExport {
    LoopsExport {
        units: "SI: m, A (per ampere of coil current), T".into(),
        convention: "positive current circulates right-handed about `axis`; each loop carries \
                     turns_per_loop turns"
            .into(),
        coils: system
            .coils
            .iter()
            .map(|c| {
                let n = c.axis.into_inner();
                CoilLoops {
                    name: c.name.clone(),
                    center_m: c.center_m.into(),
                    axis: n.into(),
                    turns_per_loop: c.turns_per_loop,
                    loops: c
                        .loops
                        .iter()
                        .map(|&(radius_m, offset)| LoopExport {
                            center_m: (c.center_m + n * offset).into(),
                            radius_m,
                        })
                        .collect(),
                }
            })
            .collect(),
    }
}

#[derive(Debug, Deserialize)]
struct ProbeInput {
    points_m: Vec<[f64; 3]>,
}

/// JSON of `--probe-out`: per point, per coil, the direct model's B̃ (T/A) and ∇B̃ (T/(A·m),
/// row-major ∂B_i/∂x_j).
#[derive(Debug, Serialize, Deserialize)]
pub struct ProbeOutput {
    pub coils: Vec<String>,
    pub points_m: Vec<[f64; 3]>,
    pub field_t_per_a: Vec<Vec<[f64; 3]>>,
    pub gradient_t_per_am: Vec<Vec<[f64; 9]>>,
}

pub fn probe(system: &CoilSystem, points: &[[f64; 3]]) -> anyhow::Result<ProbeOutput> {
    let mut field = Vec::with_capacity(points.len());
    let mut gradient = Vec::with_capacity(points.len());
    for (k, p) in points.iter().enumerate() {
        if p.iter().any(|v| !v.is_finite()) {
            bail!("point {k} {p:?} is not finite");
        }
        let p = Vector3::from(*p);
        let mut fs = Vec::with_capacity(system.len());
        let mut gs = Vec::with_capacity(system.len());
        for c in 0..system.len() {
            let (b, g) = system.field_and_gradient_per_amp(c, &p);
            fs.push(b.into());
            gs.push(std::array::from_fn(|k| g[(k / 3, k % 3)]));
        }
        field.push(fs);
        gradient.push(gs);
    }
    Ok(ProbeOutput {
        coils: system.coils.iter().map(|c| c.name.clone()).collect(),
        points_m: points.to_vec(),
        field_t_per_a: field,
        gradient_t_per_am: gradient,
    })
}

fn write_json<T: Serialize>(path: &Path, value: &T) -> anyhow::Result<()> {
    let text = serde_json::to_string(value)?;
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
}

/// Python of the project venv: `$MILLINAV_VENV/bin/python`, else `~/.cache/millinav/venv/bin/python`.
pub fn default_python() -> PathBuf {
    let venv = std::env::var_os("MILLINAV_VENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            let home = std::env::var_os("HOME")
                .map(PathBuf::from)
                .unwrap_or_default();
            home.join(".cache/millinav/venv")
        });
    venv.join("bin/python")
}

/// The cross-check script shipped next to this crate.
pub fn magpylib_script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("magpylib_check.py")
}

/// Why the magpylib check cannot run here, or `None` if it can.
pub fn magpylib_unavailable(python: &Path) -> Option<String> {
    match Command::new(python)
        .args(["-c", "import magpylib, numpy"])
        .output()
    {
        Err(e) => Some(format!("cannot run {}: {e}", python.display())),
        Ok(o) if !o.status.success() => Some(format!(
            "{} cannot import magpylib/numpy: {}",
            python.display(),
            String::from_utf8_lossy(&o.stderr)
                .trim()
                .lines()
                .last()
                .unwrap_or("")
        )),
        Ok(_) => None,
    }
}

fn run_magpylib_check(args: &CoilsArgs) -> anyhow::Result<()> {
    let python = args.python.clone().unwrap_or_else(default_python);
    if let Some(why) = magpylib_unavailable(&python) {
        println!(
            "magpylib cross-check SKIPPED: {why} (install: {}/../pip install magpylib)",
            python.parent().unwrap_or(Path::new(".")).display()
        );
        return Ok(());
    }
    let exe = std::env::current_exe().context("locating the fieldgen binary")?;
    let status = Command::new(&python)
        .arg(magpylib_script())
        .arg("--fieldgen")
        .arg(exe)
        .arg("--rig")
        .arg(&args.rig)
        .status()
        .with_context(|| format!("running {}", python.display()))?;
    if !status.success() {
        bail!("magpylib cross-check failed ({status})");
    }
    Ok(())
}
