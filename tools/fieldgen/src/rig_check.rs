//! `fieldgen rig-check`: load and validate a rig file, print what it describes, and the force
//! its coils can guarantee on the canal while holding an orientation field.
use std::path::PathBuf;

use fieldmaps::allocation::{actuation_matrix_from, guaranteed_force};
use fieldmaps::physics::in_plane_moment;
use fieldmaps::rigfile::Rig;
use nalgebra::{DVector, Vector2, Vector3};

#[derive(clap::Args, Debug)]
pub struct RigCheckArgs {
    /// Rig file to check (e.g. fieldmaps/rigs/paper.toml).
    #[arg(long)]
    pub rig: PathBuf,
    /// Orientation-field magnitudes (mT) at which to report the guaranteed force, after the
    /// field services/control holds by default on this rig (the paper's aligning torque, 0.86
    /// µN·m, over the rig's magnet moment: 1 mT on the paper's rig), comma-separated; empty
    /// (`--field-mt=`) skips the budget.
    #[arg(long, value_parser = parse_fields_mt, default_value = "1,5,10")]
    pub field_mt: FieldsMt,
    /// Control's ω0 (N/T): weight of the field rows in the pseudo-inverse allocation
    /// (services/control `omega0_n_per_t`).
    #[arg(long, default_value_t = 0.05)]
    pub omega0: f64,
    /// Spacing of the canal sample points of the force budget, mm.
    #[arg(long, default_value_t = 2.0)]
    pub spacing_mm: f64,
    /// Fail unless the guaranteed force at every route point and field is at least this, mN.
    #[arg(long)]
    pub min_force_mn: Option<f64>,
}

/// Field magnitudes, mT, from a comma-separated list ("" for none).
#[derive(Debug, Clone, PartialEq)]
pub struct FieldsMt(pub Vec<f64>);

fn parse_fields_mt(text: &str) -> Result<FieldsMt, String> {
    text.split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .map(|t| match t.parse::<f64>() {
            Ok(mt) if mt.is_finite() && mt >= 0.0 => Ok(mt),
            _ => Err(format!("{t:?} is not a field magnitude ≥ 0 (mT)")),
        })
        .collect::<Result<Vec<_>, _>>()
        .map(FieldsMt)
}

/// Force directions and field headings tried at each point.
const FORCE_DIRECTIONS: u32 = 16;
const FIELD_HEADINGS: u32 = 8;

/// Which current limits the budget respects.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LimitModel {
    /// Each coil's own `max_current_a` and `resistance_ohm`.
    PerCoil,
    /// [`Rig::coil_limits`]: the lowest current limit and highest resistance for all coils, as
    /// services/control's allocation (and its MPC force bound) uses them.
    Conservative,
}

/// The largest force (N) the pseudo-inverse allocation guarantees at `p` (m) in every in-plane
/// direction, for every field heading, while holding a field of `field_t` (T) with the robot
/// aligned to it, within the limits (per-coil current, total power). As
/// services/control `estimate_max_force_n`, minimised over field headings as well. 0 when the
/// field alone is out of reach.
pub fn guaranteed_force_n(
    rig: &Rig,
    p: &Vector2<f64>,
    field_t: f64,
    omega0: f64,
    limits: LimitModel,
) -> f64 {
    let ids = &rig.allocation_coils;
    let conservative = rig.coil_limits();
    let (max_i, res): (Vec<f64>, Vec<f64>) = ids
        .iter()
        .map(|&k| match limits {
            LimitModel::PerCoil => (rig.coils[k].max_current_a, rig.coils[k].resistance_ohm),
            LimitModel::Conservative => {
                (conservative.max_current_a, conservative.coil_resistance_ohm)
            }
        })
        .unzip();
    let feasible = |i: &DVector<f64>| {
        i.iter().zip(&max_i).all(|(c, m)| c.abs() <= *m)
            && i.iter().zip(&res).map(|(c, r)| c * c * r).sum::<f64>() <= rig.max_total_power_w
    };
    let p3 = Vector3::new(p.x, p.y, 0.0);
    let mut best = f64::INFINITY;
    for h in 0..FIELD_HEADINGS {
        let heading = f64::from(h) * std::f64::consts::TAU / f64::from(FIELD_HEADINGS);
        let moment = in_plane_moment(rig.robot.magnet_moment_am2, heading);
        let a = actuation_matrix_from(&rig.coil_field, &p3, &moment, ids, omega0);
        let b = Vector2::new(heading.cos(), heading.sin()) * field_t;
        let rhs = DVector::from_vec(vec![0.0, 0.0, omega0 * b.x, omega0 * b.y]);
        match guaranteed_force(&a, &rhs, FORCE_DIRECTIONS, feasible) {
            Ok(force) => best = best.min(force),
            Err(_) => return 0.0,
        }
    }
    if best.is_finite() {
        best
    } else {
        0.0
    }
}

/// The force budget at one field magnitude.
#[derive(Debug, Clone, PartialEq)]
pub struct ForceBudget {
    pub field_t: f64,
    /// Guaranteed force at the route's start and end, N (conservative limits).
    pub route_n: Option<(f64, f64)>,
    /// Lowest guaranteed force over the canal sample points, N, and where (conservative).
    pub canal_min_n: f64,
    pub canal_min_at_m: Vector2<f64>,
    /// The same lowest force with each coil's own limits, N.
    pub canal_min_per_coil_n: f64,
    pub canal_points: usize,
}

/// The force budget over the canal (points `spacing_m` apart) and at the route.
pub fn force_budget(rig: &Rig, field_t: f64, omega0: f64, spacing_m: f64) -> ForceBudget {
    let g = *rig.phantom.mask.geometry();
    let (w, h) = (
        f64::from(g.width_px) * g.mm_per_px * 1e-3,
        f64::from(g.height_px) * g.mm_per_px * 1e-3,
    );
    let lo = Vector2::new(g.origin_x_mm * 1e-3, g.origin_y_mm * 1e-3 - h);
    let force = |p: &Vector2<f64>, l| guaranteed_force_n(rig, p, field_t, omega0, l);
    let mut budget = ForceBudget {
        field_t,
        route_n: rig.phantom.route.map(|r| {
            (
                force(&r.start_m, LimitModel::Conservative),
                force(&r.end_m, LimitModel::Conservative),
            )
        }),
        canal_min_n: f64::INFINITY,
        canal_min_at_m: Vector2::zeros(),
        canal_min_per_coil_n: f64::INFINITY,
        canal_points: 0,
    };
    let (nx, ny) = (
        (w / spacing_m).floor() as usize,
        (h / spacing_m).floor() as usize,
    );
    for j in 0..ny {
        for i in 0..nx {
            let p = lo + Vector2::new(i as f64 + 0.5, j as f64 + 0.5) * spacing_m;
            if !rig.phantom.contains(&p) {
                continue;
            }
            budget.canal_points += 1;
            let f = force(&p, LimitModel::Conservative);
            if f < budget.canal_min_n {
                budget.canal_min_n = f;
                budget.canal_min_at_m = p;
            }
            budget.canal_min_per_coil_n = budget
                .canal_min_per_coil_n
                .min(force(&p, LimitModel::PerCoil));
        }
    }
    budget
}

/// Loads the rig (every file it names included) and prints its summary and force budget, or
/// fails with the error naming the file and the field.
pub fn run(args: &RigCheckArgs) -> anyhow::Result<()> {
    let (rig, maps_to_make) = load(args)?;
    print!("{}", rig.summary());
    if !(args.omega0.is_finite() && args.omega0 > 0.0) {
        anyhow::bail!("--omega0 must be > 0");
    }
    if !(args.spacing_mm.is_finite() && args.spacing_mm > 0.0) {
        anyhow::bail!("--spacing-mm must be > 0");
    }
    let mut weakest_route = f64::INFINITY;
    // Control's default field on this rig first, unless it is one of those asked for.
    let default_mt =
        fieldmaps::physics::DEFAULT_ALIGNING_TORQUE_N_M / rig.robot.magnet_moment_am2 * 1e3;
    let mut fields_mt = args.field_mt.0.clone();
    if !fields_mt.is_empty() && !fields_mt.iter().any(|mt| (mt - default_mt).abs() < 1e-9) {
        fields_mt.insert(0, default_mt);
    }
    for &mt in &fields_mt {
        let b = force_budget(&rig, mt * 1e-3, args.omega0, args.spacing_mm * 1e-3);
        let route = match b.route_n {
            Some((s, e)) => {
                weakest_route = weakest_route.min(s.min(e));
                format!("route start {:.3} mN, end {:.3} mN; ", s * 1e3, e * 1e3)
            }
            None => String::new(),
        };
        // 0 means the field alone (with zero force) is already beyond the limits somewhere.
        let reach = if b.canal_min_n > 0.0 {
            ""
        } else {
            " [the field alone is out of reach at some canal points]"
        };
        let shown = if (mt - default_mt).abs() < 1e-9 {
            format!("{mt:.3} mT, control's default for this magnet,")
        } else {
            format!("{mt} mT")
        };
        println!(
            "force budget at {shown} (ω0 {} N/T, any direction, any field heading): {route}canal minimum {:.3} mN at ({:.1}, {:.1}) mm over {} points ({:.3} mN with each coil's own limits){reach}",
            args.omega0,
            b.canal_min_n * 1e3,
            b.canal_min_at_m.x * 1e3,
            b.canal_min_at_m.y * 1e3,
            b.canal_points,
            b.canal_min_per_coil_n * 1e3,
        );
    }
    if let Some(min) = args.min_force_mn {
        if rig.phantom.route.is_none() {
            anyhow::bail!(
                "{}: phantom.route: --min-force-mn needs a [phantom.route]",
                args.rig.display()
            );
        }
        if weakest_route * 1e3 < min {
            anyhow::bail!(
                "guaranteed force on the route {:.3} mN < --min-force-mn {min}",
                weakest_route * 1e3
            );
        }
    }
    match maps_to_make {
        None => println!("rig ok"),
        Some(why) => println!(
            "rig ok, except its flow maps: {why}\n  make them: millinav maps cfd --all --rig {}",
            args.rig.display()
        ),
    }
    Ok(())
}

/// The rig, checked whole; or, when only its flow maps are not there yet (a new rig is checked
/// before its CFD maps are made), the rest of it and why the maps are missing. A map that is
/// there but wrong is an error like any other.
fn load(args: &RigCheckArgs) -> anyhow::Result<(Rig, Option<String>)> {
    match Rig::load(&args.rig) {
        Ok(rig) => Ok((rig, None)),
        Err(e) => {
            let missing_map = e
                .field()
                .is_some_and(|f| f.starts_with("phantom.flow[") && f.ends_with("].map"))
                && e.to_string().contains("cannot read flow map");
            if !missing_map {
                return Err(e.into());
            }
            Ok((crate::cfd::load_rig(&args.rig)?, Some(e.to_string())))
        }
    }
}
