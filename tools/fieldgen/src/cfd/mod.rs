//! `fieldgen cfd`: steady laminar flow in the phantom → in-plane flow maps at the control plane.
//!
//! # Model (depth-averaged 2D, documented approximation)
//!
//! The paper solves the 3D phantom in ANSYS Fluent and keeps (Vx, Vy) on the plane z = 8 mm
//! above the inlet centreline. Here the phantom is the rig's top-view canal mask (`--rig`, its
//! `[phantom] mask`, or `--mask`) treated as a chamber of uniform effective depth `H`:
//!
//! - depth-averaged incompressible Navier–Stokes with a Hele-Shaw wall-friction term:
//!   ∂ū/∂t + (ū·∇)ū = −∇p/ρ + ν∇²ū − (12ν/H²) ū (Poiseuille profile across the depth);
//! - solved to steady state with the D2Q9 TRT lattice Boltzmann method of [`crate::lbm`];
//! - the ports are the rig's `[[phantom.inlets]]` / `[[phantom.outlets]]`. Each inlet carries
//!   Q/n (the paper gives 0.212 / 0.295 m/s "at each inlet" for 180 / 250 mL/min through its two
//!   D = 3 mm tubes, i.e. Q/2 per inlet) as a fully developed parabolic profile across its
//!   opening (the paper's 85 mm tubes are long enough for full development); every outlet is a
//!   pressure outlet at one common pressure, so several outlets share the flow by their
//!   resistance; all canal walls are no-slip;
//! - a port's opening is where its tube ends on the mask: from the mouth (`position_mm`), up
//!   the tube (against an inlet's `direction`, along an outlet's) through canal cells to the
//!   first non-canal cell — the image edge where the tube leaves the view (the paper's ports),
//!   or an in-view wall where the drawn tube or vessel ends (a fitting that leaves the control
//!   plane). The opening is cut square to the nearest image axis (a port may be at most 20°
//!   off it) and is at most the tube's diameter (+ one cell each side) wide. Canal that
//!   reaches the image edge with no port there is an error (it would silently be a wall);
//! - control plane: with a Poiseuille profile across the depth, the mid-depth velocity is
//!   1.5 × the depth average; the control plane is identified with mid-depth, so the map is
//!   1.5 · ū. `H` is the one calibration constant: `H = 12 mm` makes the peak in-chamber speed
//!   at 250 mL/min, 4.3 cP come out at ≈ 10 cm/s (the paper's CFD). The other three
//!   conditions use the same `H`: their peaks are predictions, not fits.
//!
//! The port tubes' stretches inside the view (narrower than the robot, so never navigated)
//! are solved but written as zero, so the map's peak is the in-phantom peak (the plant scales
//! its disturbance model by it); in the 2D model the outlet slot would otherwise be the
//! fastest place (it carries Q through a 4.2 mm slot).
//!
//! What this does not capture: 3D jet spreading from the round inlet tubes toward the control
//! plane, vertical secondary flows, the real (non-uniform) depth of the phantom.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use anyhow::Context;
use fieldmaps::flowmap::FlowMap;
use fieldmaps::mask::CanalMask;
use fieldmaps::phantom::{ImageGeometry, Inlet, Outlet};
use fieldmaps::rigfile::{FlowCondition, Rig, Zone, ZoneKind};
use nalgebra::Vector2;
use thiserror::Error;

use crate::lbm::{Convergence, Lattice, LbmError, LbmParams, Node};

/// Calibrated effective chamber depth (see the module docs), m.
pub const EFFECTIVE_DEPTH_M: f64 = 0.012;
/// Control-plane velocity / depth-averaged velocity (mid-depth of a Poiseuille profile).
pub const PLANE_FACTOR: f64 = 1.5;
/// Map nodes closer than this to the wall are left out of the "in-chamber" statistics, which
/// excludes the paper's inlet (3 mm) and outlet (4.2 mm) tubes, m.
pub const CHAMBER_CLEARANCE_M: f64 = 3.0e-3;

#[derive(Debug, Error)]
pub enum CfdError {
    #[error(transparent)]
    Lbm(#[from] LbmError),
    #[error("the canal leaves the view at ({x_mm:.1}, {y_mm:.1}) mm on the image edge and no port's tube ends there (it would be a wall); add a port there or close the mask; ports: {ports}")]
    UnmatchedOpening { x_mm: f64, y_mm: f64, ports: String },
    /// A port the solver cannot place; `origin` names the rig file and the port's table.
    #[error("{origin}.{field}: {message}")]
    Port {
        origin: String,
        field: &'static str,
        message: String,
    },
    #[error("lattice too coarse for this condition: relaxation time {tau:.4} < 0.51; use a smaller --dx-mm")]
    TooCoarse { tau: f64 },
    #[error("bad parameter: {0}")]
    BadParameter(String),
}

/// A steady flow condition: pump flow and fluid viscosity.
#[derive(Debug, Clone, PartialEq)]
pub struct Condition {
    /// File stem, e.g. `q180_mu4p3`.
    pub name: String,
    /// Total pump flow, m³/s (split equally between the inlets).
    pub flow_m3_s: f64,
    /// Dynamic viscosity, Pa·s.
    pub viscosity_pa_s: f64,
}

impl Condition {
    pub fn new(flow_ml_min: f64, viscosity_cp: f64) -> Self {
        let cp = format!("{viscosity_cp}").replace('.', "p");
        Self {
            name: format!("q{flow_ml_min}_mu{cp}"),
            flow_m3_s: flow_ml_min * 1e-6 / 60.0,
            viscosity_pa_s: viscosity_cp * 1e-3,
        }
    }

    pub fn flow_ml_min(&self) -> f64 {
        self.flow_m3_s * 60.0e6
    }

    pub fn viscosity_cp(&self) -> f64 {
        self.viscosity_pa_s * 1e3
    }

    /// A rig's `[[phantom.flow]]` condition (named as in the rig file).
    pub fn from_rig(fc: &FlowCondition) -> Self {
        Self {
            name: fc.name.clone(),
            flow_m3_s: fc.flow_ml_min * 1e-6 / 60.0,
            viscosity_pa_s: fc.viscosity_pa_s,
        }
    }
}

/// Numerical and model settings.
#[derive(Debug, Clone, PartialEq)]
pub struct CfdSettings {
    /// Lattice spacing, m.
    pub dx_m: f64,
    /// Effective depth H of the depth-averaged model, m.
    pub depth_m: f64,
    pub density_kg_m3: f64,
    /// Lattice velocity of the fastest inlet node (Mach number control).
    pub lattice_velocity: f64,
    /// Steady-state tolerance on the relative velocity change per step.
    pub tolerance: f64,
    pub max_steps: usize,
    pub check_every: usize,
    /// Output grid spacing, m.
    pub out_spacing_m: f64,
}

impl Default for CfdSettings {
    fn default() -> Self {
        Self {
            dx_m: 0.3e-3,
            depth_m: EFFECTIVE_DEPTH_M,
            density_kg_m3: fieldmaps::rig::FluidParams::GLYCERIN_WATER_DENSITY,
            lattice_velocity: 0.12,
            tolerance: 1e-7,
            max_steps: 300_000,
            check_every: 200,
            out_spacing_m: 0.5e-3,
        }
    }
}

mod command;
mod ports;

pub use command::{load_rig, run, write_speed_png, CfdArgs};
use ports::{locate_openings, view_rect, Grid, Opening};
pub use ports::{rig_ports, Port, PortKind};

/// Diagnostics of one solve.
#[derive(Debug, Clone, PartialEq)]
pub struct CfdStats {
    pub condition: Condition,
    pub convergence: Convergence,
    pub lattice: (usize, usize),
    pub fluid_cells: usize,
    pub dx_m: f64,
    pub dt_s: f64,
    pub tau: f64,
    /// Mean inlet velocity (depth-averaged, each inlet), m/s.
    pub inlet_mean_mps: f64,
    /// Mean velocity in the fastest round inlet tube, its share of Q / (π D²/4), m/s.
    pub tube_mean_mps: f64,
    /// Reynolds number of that tube flow, ρ U D / μ.
    pub tube_reynolds: f64,
    /// Total inflow and outflow of the 2D model (× H), m³/s.
    pub inflow_m3_s: f64,
    pub outflow_m3_s: f64,
    /// Peak control-plane speed anywhere on the map, and where.
    pub peak_mps: f64,
    pub peak_at_m: Vector2<f64>,
    /// Peak control-plane speed in the chamber (clearance > 3 mm: the inlet and outlet tubes excluded).
    pub chamber_peak_mps: f64,
    pub chamber_peak_at_m: Vector2<f64>,
    /// Mean speed in the rig's high-disturbance zones / mean speed in the chamber.
    pub disturbance_mean_ratio: f64,
    /// Closed-streamline (recirculating) sample points (1 mm spacing in the chamber): count,
    /// fraction of all chamber samples, fraction of the samples inside the rig's recirculation
    /// zones and fraction of those outside them.
    pub recirculating_points: usize,
    pub recirculating_fraction: f64,
    pub recirculating_in_band: f64,
    pub recirculating_outside_band: f64,
    /// y extent (10th–90th percentile) of the recirculating points, m.
    pub recirculating_y_m: (f64, f64),
    pub seconds: f64,
}

impl CfdStats {
    pub fn mass_imbalance(&self) -> f64 {
        (self.inflow_m3_s - self.outflow_m3_s).abs() / self.inflow_m3_s.max(f64::MIN_POSITIVE)
    }

    pub fn summary(&self) -> String {
        let c = &self.condition;
        format!(
            "{name}: Q = {q:.0} mL/min, mu = {mu:.1} cP | tube U = {tu:.3} m/s (Re {re:.0}) | lattice {nx}x{ny} dx {dx:.3} mm, {cells} fluid cells, tau {tau:.3}, dt {dt:.2e} s | {steps} steps, residual {res:.1e}{conv} | mass imbalance {mi:.2e} | peak {pk:.1} mm/s at ({px:.1}, {py:.1}) mm, chamber peak {cp:.1} mm/s at ({cx:.1}, {cy:.1}) mm | high-disturbance zone mean speed x{hd:.2} the chamber mean | recirculating samples: {rn} ({rf:.0} % of chamber; {rb:.0} % of the recirculation zone's, {ro:.0} % elsewhere), y {ry0:.1}..{ry1:.1} mm | {secs:.1} s",
            name = c.name,
            q = c.flow_ml_min(),
            mu = c.viscosity_cp(),
            tu = self.tube_mean_mps,
            re = self.tube_reynolds,
            nx = self.lattice.0,
            ny = self.lattice.1,
            dx = self.dx_m * 1e3,
            cells = self.fluid_cells,
            tau = self.tau,
            dt = self.dt_s,
            steps = self.convergence.steps,
            res = self.convergence.residual,
            conv = if self.convergence.converged { "" } else { " (NOT converged)" },
            mi = self.mass_imbalance(),
            pk = self.peak_mps * 1e3,
            px = self.peak_at_m.x * 1e3,
            py = self.peak_at_m.y * 1e3,
            cp = self.chamber_peak_mps * 1e3,
            cx = self.chamber_peak_at_m.x * 1e3,
            cy = self.chamber_peak_at_m.y * 1e3,
            hd = self.disturbance_mean_ratio,
            rn = self.recirculating_points,
            rf = self.recirculating_fraction * 100.0,
            rb = self.recirculating_in_band * 100.0,
            ro = self.recirculating_outside_band * 100.0,
            ry0 = self.recirculating_y_m.0 * 1e3,
            ry1 = self.recirculating_y_m.1 * 1e3,
            secs = self.seconds,
        )
    }
}

/// Largest lattice accepted, cells (memory and run time).
const MAX_LATTICE_CELLS: usize = 16_000_000;
/// Upper bound on the relaxation time τ; the time step is shortened to keep τ at or below it.
const TAU_MAX: f64 = 1.5;
/// Lower bound on τ: below it the lattice is too coarse for the viscosity to be resolved.
const TAU_MIN: f64 = 0.51;
/// Passes that rescale an inlet's wall-side links so the injected flux matches the inlet's flow.
const INLET_FLUX_PASSES: usize = 2;

/// Solves one condition on `mask` with `ports`; `progress(steps, residual)` is called at each
/// convergence check.
pub fn solve(
    mask: &CanalMask,
    ports: &[Port],
    zones: &[Zone],
    condition: &Condition,
    settings: &CfdSettings,
    progress: impl FnMut(usize, f64),
) -> Result<(FlowMap, CfdStats), CfdError> {
    let started = Instant::now();
    check_parameters(condition, settings)?;
    let (lo, hi) = view_rect(mask.geometry());
    let grid = Grid::over(lo, hi, settings.dx_m)?;
    let fluid = grid.fluid_cells(mask);
    let openings: Vec<PortOpening<'_>> = locate_openings(&fluid, &grid, ports)?
        .into_iter()
        .zip(ports)
        .map(|(opening, port)| PortOpening { opening, port })
        .collect();
    let inlets = Inlets::new(&openings, condition, settings.depth_m, grid.dx)?;
    let nu = condition.viscosity_pa_s / settings.density_kg_m3;
    let units = LatticeUnits::new(settings, nu, grid.dx, inlets.peak_mps)?;
    let mut lat = build_lattice(&grid, &fluid, &openings, &inlets, &units)?;
    let convergence = lat.run(
        settings.max_steps,
        settings.tolerance,
        settings.check_every,
        progress,
    )?;
    let (inflow, outflow) = port_flows(&lat, &openings, &units, grid.dx, settings.depth_m);
    let map = sample_control_plane(
        &lat,
        &grid,
        mask,
        ports,
        &MapGrid::over(lo, hi, settings.out_spacing_m),
        &units,
    );

    // The fastest inlet tube: its share of Q through its round section.
    let (tube_mean, tube_diameter) = ports
        .iter()
        .filter_map(|p| match p.kind {
            PortKind::Inlet { flow_fraction } => Some((
                flow_fraction * condition.flow_m3_s
                    / (std::f64::consts::PI * p.radius_m * p.radius_m),
                2.0 * p.radius_m,
            )),
            PortKind::Outlet => None,
        })
        .fold((0.0, 0.0), |a, b| if b.0 > a.0 { b } else { a });
    let mut stats = CfdStats {
        condition: condition.clone(),
        convergence,
        lattice: (grid.nx, grid.ny),
        fluid_cells: lat.fluid_cells(),
        dx_m: grid.dx,
        dt_s: units.dt,
        tau: units.tau,
        inlet_mean_mps: inlets.mean_mps,
        tube_mean_mps: tube_mean,
        tube_reynolds: settings.density_kg_m3 * tube_mean * tube_diameter
            / condition.viscosity_pa_s,
        inflow_m3_s: inflow,
        outflow_m3_s: outflow,
        peak_mps: 0.0,
        peak_at_m: Vector2::zeros(),
        chamber_peak_mps: 0.0,
        chamber_peak_at_m: Vector2::zeros(),
        disturbance_mean_ratio: 0.0,
        recirculating_points: 0,
        recirculating_fraction: 0.0,
        recirculating_in_band: 0.0,
        recirculating_outside_band: 0.0,
        recirculating_y_m: (0.0, 0.0),
        seconds: 0.0,
    };
    let outlet_points: Vec<Vector2<f64>> = openings
        .iter()
        .filter(|po| po.port.kind == PortKind::Outlet)
        .map(|po| po.opening.centre_m)
        .collect();
    analyse(&map, mask, zones, &outlet_points, &mut stats);
    stats.seconds = started.elapsed().as_secs_f64();
    Ok((map, stats))
}

/// Rejects settings and conditions the solver cannot use.
fn check_parameters(condition: &Condition, settings: &CfdSettings) -> Result<(), CfdError> {
    let bad = |m: &str| Err(CfdError::BadParameter(m.to_string()));
    if !(settings.dx_m > 0.0 && settings.dx_m.is_finite()) {
        return bad("dx must be > 0");
    }
    if !(settings.depth_m > 0.0 && settings.depth_m.is_finite()) {
        return bad("depth must be > 0");
    }
    if !(settings.out_spacing_m > 0.0 && settings.out_spacing_m.is_finite()) {
        return bad("output spacing must be > 0");
    }
    if !(condition.flow_m3_s > 0.0 && condition.flow_m3_s.is_finite()) {
        return bad("flow must be > 0");
    }
    if !(condition.viscosity_pa_s > 0.0 && condition.viscosity_pa_s.is_finite()) {
        return bad("viscosity must be > 0");
    }
    if !(settings.lattice_velocity > 0.0 && settings.lattice_velocity <= 0.2) {
        return bad("lattice velocity must be in (0, 0.2]");
    }
    Ok(())
}

impl Grid {
    /// Square cells of about `dx_m` over the view rectangle `lo`..`hi`.
    fn over(lo: Vector2<f64>, hi: Vector2<f64>, dx_m: f64) -> Result<Self, CfdError> {
        let nx = ((hi.x - lo.x) / dx_m).round().max(2.0) as usize;
        let ny = ((hi.y - lo.y) / dx_m).round().max(2.0) as usize;
        if nx * ny > MAX_LATTICE_CELLS {
            return Err(CfdError::BadParameter(
                "lattice larger than 16 M cells; use a larger --dx-mm".to_string(),
            ));
        }
        Ok(Self {
            nx,
            ny,
            dx: (hi.x - lo.x) / nx as f64,
            x0: lo.x,
            y0: lo.y,
        })
    }

    /// Whether each cell (row-major from the lower-left corner) has its centre in the canal.
    fn fluid_cells(&self, mask: &CanalMask) -> Vec<bool> {
        (0..self.nx * self.ny)
            .map(|k| mask.contains(&self.centre((k % self.nx) as i64, (k / self.nx) as i64)))
            .collect()
    }
}

/// An opening of the lattice with the port it belongs to.
struct PortOpening<'a> {
    opening: Opening,
    port: &'a Port,
}

/// Physical inlet velocities: parabolic across each inlet opening, flux = fraction · Q / H.
struct Inlets {
    /// (index into the port openings, velocity of each cell across the opening in m/s).
    profiles: Vec<(usize, Vec<f64>)>,
    /// Largest mean inlet velocity, m/s.
    mean_mps: f64,
    /// Largest inlet cell velocity, m/s.
    peak_mps: f64,
}

impl Inlets {
    fn new(
        openings: &[PortOpening<'_>],
        condition: &Condition,
        depth_m: f64,
        dx: f64,
    ) -> Result<Self, CfdError> {
        let mut profiles: Vec<(usize, Vec<f64>)> = Vec::new();
        let mut mean_mps = 0.0f64;
        let mut peak_mps = 0.0f64;
        for (k, po) in openings.iter().enumerate() {
            if let PortKind::Inlet { flow_fraction } = po.port.kind {
                let n = po.opening.cells.len();
                let width = n as f64 * dx;
                let mean = flow_fraction * condition.flow_m3_s / (width * depth_m);
                let shape: Vec<f64> = (0..n)
                    .map(|c| {
                        let s = (c as f64 + 0.5) / n as f64;
                        4.0 * s * (1.0 - s)
                    })
                    .collect();
                let sum: f64 = shape.iter().sum();
                let profile: Vec<f64> = shape.iter().map(|s| s * mean * n as f64 / sum).collect();
                peak_mps = profile.iter().copied().fold(peak_mps, f64::max);
                mean_mps = mean_mps.max(mean);
                profiles.push((k, profile));
            }
        }
        if peak_mps <= 0.0 {
            return Err(CfdError::BadParameter("no inlet".to_string()));
        }
        Ok(Self {
            profiles,
            mean_mps,
            peak_mps,
        })
    }
}

/// The lattice's time step and the physical quantities in lattice units.
struct LatticeUnits {
    /// Time step, s.
    dt: f64,
    /// Kinematic viscosity in lattice units.
    nu_lat: f64,
    /// Relaxation time.
    tau: f64,
    /// Hele-Shaw wall friction per step.
    friction: f64,
    /// Physical velocity (m/s) → lattice velocity.
    to_lattice: f64,
    /// Lattice velocity → physical velocity (m/s).
    to_phys: f64,
}

impl LatticeUnits {
    /// Time step from the lattice Mach number of the fastest inlet cell, shortened to keep
    /// τ ≤ `TAU_MAX`.
    fn new(
        settings: &CfdSettings,
        nu: f64,
        dx: f64,
        peak_inlet_mps: f64,
    ) -> Result<Self, CfdError> {
        let h = settings.depth_m;
        let mut dt = settings.lattice_velocity * dx / peak_inlet_mps;
        if 3.0 * nu * dt / (dx * dx) + 0.5 > TAU_MAX {
            dt = (TAU_MAX - 0.5) / 3.0 * dx * dx / nu;
        }
        let nu_lat = nu * dt / (dx * dx);
        let tau = 3.0 * nu_lat + 0.5;
        if tau < TAU_MIN {
            return Err(CfdError::TooCoarse { tau });
        }
        Ok(Self {
            dt,
            nu_lat,
            tau,
            friction: 12.0 * nu / (h * h) * dt,
            to_lattice: dt / dx,
            to_phys: dx / dt,
        })
    }
}

/// The lattice with walls, the inlets' velocity profiles and the pressure outlets.
fn build_lattice(
    grid: &Grid,
    fluid: &[bool],
    openings: &[PortOpening<'_>],
    inlets: &Inlets,
    units: &LatticeUnits,
) -> Result<Lattice, CfdError> {
    let nx = grid.nx;
    let mut lat = Lattice::new(
        nx,
        grid.ny,
        LbmParams {
            nu: units.nu_lat,
            friction: units.friction,
            body_force: [0.0; 2],
        },
    )?;
    for (k, f) in fluid.iter().enumerate() {
        if !f {
            lat.set((k % nx) as i64, (k / nx) as i64, Node::Wall)?;
        }
    }
    for (k, profile) in &inlets.profiles {
        let op = &openings[*k].opening;
        // The links at the ends of an opening (next to the wall) carry less than Σu; rescale
        // so the mass actually injected is the inlet's flow.
        let target: f64 = profile.iter().sum::<f64>() * units.to_lattice;
        let mut gain = 1.0;
        for _ in 0..INLET_FLUX_PASSES {
            for (&(gi, gj), &u) in op.ghosts.iter().zip(profile) {
                let s = u * units.to_lattice * gain;
                lat.set(gi, gj, Node::Moving([op.inward[0] * s, op.inward[1] * s]))?;
            }
            let injected = lat.injected_flux(&op.ghosts);
            if injected > 0.0 {
                gain *= target / injected;
            }
        }
    }
    for po in openings {
        if po.port.kind == PortKind::Outlet {
            for &(gi, gj) in &po.opening.ghosts {
                lat.set(gi, gj, Node::Pressure)?;
            }
        }
    }
    Ok(lat)
}

/// Total inflow and outflow through the ports (2D flux × H), m³/s.
fn port_flows(
    lat: &Lattice,
    openings: &[PortOpening<'_>],
    units: &LatticeUnits,
    dx: f64,
    depth_m: f64,
) -> (f64, f64) {
    let mut inflow = 0.0;
    let mut outflow = 0.0;
    for po in openings {
        let op = &po.opening;
        let flux: f64 = op
            .cells
            .iter()
            .map(|&(i, j)| {
                let u = lat.velocity(i, j);
                (u[0] * op.inward[0] + u[1] * op.inward[1]) * units.to_phys * dx * depth_m
            })
            .sum();
        match po.port.kind {
            PortKind::Inlet { .. } => inflow += flux,
            PortKind::Outlet => outflow -= flux,
        }
    }
    (inflow, outflow)
}

/// The output map's nodes: `spacing_m` apart, centred on the view rectangle.
struct MapGrid {
    nx: usize,
    ny: usize,
    origin_m: Vector2<f64>,
    spacing_m: f64,
}

impl MapGrid {
    fn over(lo: Vector2<f64>, hi: Vector2<f64>, spacing_m: f64) -> Self {
        let sp = spacing_m;
        let nx = ((hi.x - lo.x) / sp).floor() as usize + 1;
        let ny = ((hi.y - lo.y) / sp).floor() as usize + 1;
        let origin_m = Vector2::new(
            0.5 * (lo.x + hi.x) - 0.5 * (nx - 1) as f64 * sp,
            0.5 * (lo.y + hi.y) - 0.5 * (ny - 1) as f64 * sp,
        );
        Self {
            nx,
            ny,
            origin_m,
            spacing_m,
        }
    }
}

/// Control-plane map: bilinear between cell centres (non-fluid cells are at rest), zero
/// outside the canal and in the port tubes, scaled from the depth average to the control plane.
fn sample_control_plane(
    lat: &Lattice,
    grid: &Grid,
    mask: &CanalMask,
    ports: &[Port],
    out: &MapGrid,
    units: &LatticeUnits,
) -> FlowMap {
    let dx = grid.dx;
    let scale = units.to_phys * PLANE_FACTOR;
    let mut velocity = Vec::with_capacity(out.nx * out.ny);
    for j in 0..out.ny {
        for i in 0..out.nx {
            let p = out.origin_m + Vector2::new(i as f64, j as f64) * out.spacing_m;
            if !mask.contains(&p) || ports.iter().any(|port| port.in_tube(&p)) {
                velocity.push(Vector2::zeros());
                continue;
            }
            let fx = (p.x - grid.x0) / dx - 0.5;
            let fy = (p.y - grid.y0) / dx - 0.5;
            let (i0, j0) = (fx.floor() as i64, fy.floor() as i64);
            let (tx, ty) = (fx - i0 as f64, fy - j0 as f64);
            let mut v = Vector2::zeros();
            for (di, dj, w) in [
                (0, 0, (1.0 - tx) * (1.0 - ty)),
                (1, 0, tx * (1.0 - ty)),
                (0, 1, (1.0 - tx) * ty),
                (1, 1, tx * ty),
            ] {
                let u = lat.velocity(i0 + di, j0 + dj);
                v += Vector2::new(u[0], u[1]) * w;
            }
            velocity.push(v * scale);
        }
    }
    FlowMap {
        nx: out.nx,
        ny: out.ny,
        origin_m: out.origin_m,
        spacing_m: out.spacing_m,
        velocity_mps: velocity,
        chamber_peak_mps: None,
    }
}

/// Peak speeds, the high-disturbance zones' mean speed, and recirculation found by tracing
/// streamlines: a sample point is recirculating when its streamline neither reaches the outlet
/// nor stalls within 400 mm of path but loops (returns within 0.5 mm of where it started).
fn analyse(
    map: &FlowMap,
    mask: &CanalMask,
    zones: &[Zone],
    outlets: &[Vector2<f64>],
    stats: &mut CfdStats,
) {
    let clearance = mask.clearance_map();
    let g = *mask.geometry();
    let clear_at = |p: &Vector2<f64>| {
        g.pixel_of(p)
            .map(|(c, r)| clearance[r as usize * g.width_px as usize + c as usize])
            .unwrap_or(0.0)
    };
    let in_zone =
        |p: &Vector2<f64>, kind: ZoneKind| zones.iter().any(|z| z.kind == kind && z.contains(p));
    let (mut band_sum, mut band_n, mut ch_sum, mut ch_n) = (0.0, 0usize, 0.0, 0usize);
    let mut chamber_points = Vec::new();
    for j in 0..map.ny {
        for i in 0..map.nx {
            let p = map.origin_m + Vector2::new(i as f64, j as f64) * map.spacing_m;
            let v = map.velocity_mps[j * map.nx + i];
            let s = v.norm();
            if s > stats.peak_mps {
                stats.peak_mps = s;
                stats.peak_at_m = p;
            }
            if !mask.contains(&p) || clear_at(&p) <= CHAMBER_CLEARANCE_M {
                continue;
            }
            if s > stats.chamber_peak_mps {
                stats.chamber_peak_mps = s;
                stats.chamber_peak_at_m = p;
            }
            ch_sum += s;
            ch_n += 1;
            if in_zone(&p, ZoneKind::HighDisturbance) {
                band_sum += s;
                band_n += 1;
            }
            // Streamline samples every 1 mm.
            if i % 2 == 0 && j % 2 == 0 {
                chamber_points.push(p);
            }
        }
    }
    if ch_n > 0 && band_n > 0 {
        stats.disturbance_mean_ratio = (band_sum / band_n as f64) / (ch_sum / ch_n as f64);
    }
    let step = 0.25e-3;
    let mut recirc = Vec::new();
    for &start in &chamber_points {
        let mut p = start;
        let mut travelled = 0.0;
        let mut looped = false;
        for _ in 0..1600 {
            let v1 = map.sample(&p);
            let n1 = v1.norm();
            if n1 < 1e-6 {
                break;
            }
            let mid = p + v1 / n1 * (0.5 * step);
            let v2 = map.sample(&mid);
            let n2 = v2.norm();
            if n2 < 1e-6 {
                break;
            }
            p += v2 / n2 * step;
            travelled += step;
            if outlets.iter().any(|o| (p - o).norm() < 3e-3) || !mask.contains(&p) {
                break;
            }
            if travelled > 5e-3 && (p - start).norm() < 0.5e-3 {
                looped = true;
                break;
            }
        }
        if looped {
            recirc.push(start);
        }
    }
    stats.recirculating_points = recirc.len();
    stats.recirculating_fraction = recirc.len() as f64 / chamber_points.len().max(1) as f64;
    let band_total = chamber_points
        .iter()
        .filter(|p| in_zone(p, ZoneKind::Recirculation))
        .count();
    let band_recirc = recirc
        .iter()
        .filter(|p| in_zone(p, ZoneKind::Recirculation))
        .count();
    stats.recirculating_in_band = band_recirc as f64 / band_total.max(1) as f64;
    stats.recirculating_outside_band =
        (recirc.len() - band_recirc) as f64 / (chamber_points.len() - band_total).max(1) as f64;
    if !recirc.is_empty() {
        let mut ys: Vec<f64> = recirc.iter().map(|p| p.y).collect();
        ys.sort_by(f64::total_cmp);
        let pct = |f: f64| ys[((ys.len() - 1) as f64 * f).round() as usize];
        stats.recirculating_y_m = (pct(0.1), pct(0.9));
    }
}
