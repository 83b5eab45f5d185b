//! Validation cases for the lattice Boltzmann solver ([`crate::lbm`]), used by the test suite
//! and by `fieldgen cfd --validate`.
//!
//! - Plane Poiseuille flow in a straight channel (velocity inlet, pressure outlet, no-slip
//!   walls) against the analytic parabola with the same flux; mass conservation inlet vs outlet.
//! - The same channel with the depth-friction term against the analytic Brinkman profile.
//! - Lid-driven cavity at Re = 100 against Ghia, Ghia & Shin (1982), Table I (u on the vertical
//!   centreline).

use std::fmt;

use crate::lbm::{Convergence, Lattice, LbmError, LbmParams, Node};

/// Ghia, Ghia & Shin (1982), J. Comput. Phys. 48:387–411, Table I, Re = 100:
/// (y, u/U) on the vertical centreline x = 0.5 of the unit cavity (lid at y = 1).
pub const GHIA_RE100_U: [(f64, f64); 17] = [
    (1.0000, 1.00000),
    (0.9766, 0.84123),
    (0.9688, 0.78871),
    (0.9609, 0.73722),
    (0.9531, 0.68717),
    (0.8516, 0.23151),
    (0.7344, 0.00332),
    (0.6172, -0.13641),
    (0.5000, -0.20581),
    (0.4531, -0.21090),
    (0.2813, -0.15662),
    (0.1719, -0.10150),
    (0.1016, -0.06434),
    (0.0703, -0.04775),
    (0.0625, -0.04192),
    (0.0547, -0.03717),
    (0.0000, 0.00000),
];

/// One validation case's outcome.
#[derive(Debug, Clone, PartialEq)]
pub struct CaseReport {
    pub name: &'static str,
    /// The case's error measure (see `metric`).
    pub error: f64,
    pub metric: &'static str,
    /// Relative inflow/outflow mismatch, where the case has through-flow.
    pub mass_imbalance: Option<f64>,
    pub convergence: Convergence,
    pub cells: usize,
}

impl fmt::Display for CaseReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:<28} {} = {:.3e}", self.name, self.metric, self.error)?;
        if let Some(m) = self.mass_imbalance {
            write!(f, ", |Q_in − Q_out|/Q_in = {m:.2e}")?;
        }
        write!(
            f,
            "  ({} cells, {} steps, residual {:.1e}{})",
            self.cells,
            self.convergence.steps,
            self.convergence.residual,
            if self.convergence.converged {
                ""
            } else {
                ", NOT converged"
            }
        )
    }
}

/// Channel of `h` cells across and `l` long: plug inflow `u_in` on the left, pressure outlet on
/// the right; returns the lattice after convergence.
fn channel(
    h: usize,
    l: usize,
    nu: f64,
    friction: f64,
    u_in: f64,
) -> Result<(Lattice, Convergence), LbmError> {
    let mut lat = Lattice::new(
        l,
        h,
        LbmParams {
            nu,
            friction,
            body_force: [0.0; 2],
        },
    )?;
    // The inlet column includes the two corner ghosts, so every link into the first column
    // carries the plug velocity and the injected flux is exactly u_in·h.
    for j in -1..=h as i64 {
        lat.set(-1, j, Node::Moving([u_in, 0.0]))?;
    }
    for j in 0..h as i64 {
        lat.set(l as i64, j, Node::Pressure)?;
    }
    let conv = lat.run(200_000, 1e-9, 200, |_, _| {})?;
    Ok((lat, conv))
}

/// Flux through column i (lattice units, per unit depth).
fn column_flux(lat: &Lattice, i: i64) -> f64 {
    (0..lat.ny() as i64).map(|j| lat.velocity(i, j)[0]).sum()
}

fn profile_error(lat: &Lattice, i: i64, analytic: impl Fn(f64) -> f64) -> f64 {
    let peak = (0..lat.ny())
        .map(|j| analytic(j as f64 + 0.5))
        .fold(0.0, f64::max);
    (0..lat.ny() as i64)
        .map(|j| (lat.velocity(i, j)[0] - analytic(j as f64 + 0.5)).abs())
        .fold(0.0, f64::max)
        / peak.max(f64::MIN_POSITIVE)
}

/// Plane Poiseuille flow: max |u − u_analytic| / u_max over the cross-section at 3/4 of the
/// channel length (the walls are halfway between nodes), and the inflow/outflow imbalance.
pub fn poiseuille() -> Result<CaseReport, LbmError> {
    let (h, l, u) = (16usize, 96usize, 0.05);
    let (lat, convergence) = channel(h, l, 0.1, 0.0, u)?;
    let hf = h as f64;
    let error = profile_error(&lat, (3 * l / 4) as i64, |y| {
        6.0 * u * y * (hf - y) / (hf * hf)
    });
    let q_in = u * hf;
    let q_out = column_flux(&lat, l as i64 - 1);
    Ok(CaseReport {
        name: "Poiseuille channel",
        error,
        metric: "max |u−u_a|/u_max",
        mass_imbalance: Some((q_in - q_out).abs() / q_in),
        convergence,
        cells: lat.fluid_cells(),
    })
}

/// The channel with depth friction λ: developed profile vs the Brinkman solution
/// u ∝ 1 − cosh(k(y − H/2)) / cosh(kH/2), k = √(λ/ν), scaled to the same flux.
pub fn brinkman() -> Result<CaseReport, LbmError> {
    let (h, l, u, nu, lambda) = (16usize, 96usize, 0.05, 0.1, 0.004);
    let (lat, convergence) = channel(h, l, nu, lambda, u)?;
    let hf = h as f64;
    let k = (lambda / nu).sqrt();
    let shape = |y: f64| 1.0 - (k * (y - 0.5 * hf)).cosh() / (0.5 * k * hf).cosh();
    // Mean of the shape over [0, H]: 1 − tanh(kH/2) / (kH/2).
    let mean = 1.0 - (0.5 * k * hf).tanh() / (0.5 * k * hf);
    let error = profile_error(&lat, (3 * l / 4) as i64, |y| u * shape(y) / mean);
    let q_in = u * hf;
    let q_out = column_flux(&lat, l as i64 - 1);
    Ok(CaseReport {
        name: "Brinkman (depth friction)",
        error,
        metric: "max |u−u_a|/u_max",
        mass_imbalance: Some((q_in - q_out).abs() / q_in),
        convergence,
        cells: lat.fluid_cells(),
    })
}

/// Lid-driven cavity, Re = 100, `n × n` cells (n odd puts a column on x = 0.5): max |u/U −
/// Ghia| over the 15 interior points of Ghia's table (the two end points are the boundary
/// values). Also returns the sampled centreline for printing.
pub fn cavity(n: usize) -> Result<(CaseReport, Vec<CentrelineRow>), LbmError> {
    let lid = 0.1;
    let nu = lid * n as f64 / 100.0;
    let mut lat = Lattice::new(
        n,
        n,
        LbmParams {
            nu,
            friction: 0.0,
            body_force: [0.0; 2],
        },
    )?;
    for i in 0..n as i64 {
        lat.set(i, n as i64, Node::Moving([lid, 0.0]))?;
    }
    let convergence = lat.run(400_000, 1e-8, 500, |_, _| {})?;
    let nf = n as f64;
    // u/U on x = 0.5 at height y (unit cavity), linear between cell centres.
    let centre = |y: f64| -> f64 {
        let x = 0.5 * nf - 0.5; // continuous cell index of x = 0.5
        let i0 = x.floor() as i64;
        let tx = x - i0 as f64;
        let col = |j: i64| (1.0 - tx) * lat.velocity(i0, j)[0] + tx * lat.velocity(i0 + 1, j)[0];
        let yc = (y * nf - 0.5).clamp(0.0, nf - 1.0);
        let j0 = (yc.floor() as i64).min(n as i64 - 2);
        let ty = yc - j0 as f64;
        ((1.0 - ty) * col(j0) + ty * col(j0 + 1)) / lid
    };
    let rows: Vec<(f64, f64, f64)> = GHIA_RE100_U
        .iter()
        .map(|&(y, u)| (y, u, centre(y)))
        .collect();
    let error = rows[1..rows.len() - 1]
        .iter()
        .map(|&(_, ghia, ours)| (ghia - ours).abs())
        .fold(0.0, f64::max);
    Ok((
        CaseReport {
            name: "lid-driven cavity Re=100",
            error,
            metric: "max |u/U−Ghia|",
            mass_imbalance: None,
            convergence,
            cells: lat.fluid_cells(),
        },
        rows,
    ))
}

/// (y, Ghia's u/U, this solver's u/U) on the cavity's vertical centreline.
pub type CentrelineRow = (f64, f64, f64);

/// Cavity size used by the tests and `--validate`.
pub const CAVITY_CELLS: usize = 81;

/// Runs every case and returns a printable report.
pub fn run_all() -> Result<(Vec<CaseReport>, String), LbmError> {
    let mut text = String::from("LBM solver validation (D2Q9 TRT, lattice units)\n");
    let p = poiseuille()?;
    let b = brinkman()?;
    let (c, rows) = cavity(CAVITY_CELLS)?;
    for r in [&p, &b, &c] {
        text.push_str(&format!("  {r}\n"));
    }
    text.push_str("  cavity centreline u/U:   y      Ghia     LBM\n");
    for (y, g, o) in rows {
        text.push_str(&format!(
            "                        {y:.4}  {g:8.5} {o:8.5}\n"
        ));
    }
    Ok((vec![p, b, c], text))
}
