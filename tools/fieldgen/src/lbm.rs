//! Steady incompressible laminar flow by the lattice Boltzmann method, in lattice units.
//!
//! - D2Q9, He–Luo incompressible equilibrium (density fluctuations carry the pressure; the
//!   velocity field is divergence-free at steady state), two-relaxation-time (TRT) collision
//!   with the "magic" parameter Λ = 3/16 (walls sit exactly halfway between nodes for Poiseuille
//!   flow, whatever the viscosity).
//! - A uniform body force `G` and a linear depth friction `−λ u` (the Hele-Shaw / depth-averaged
//!   term of [`crate::cfd`]), both through Guo's forcing with TRT-split relaxation; the friction
//!   enters the velocity definition implicitly (`u = (m + G/2) / (1 + λ/2)`), so it is stable for
//!   any λ ≥ 0.
//! - Boundaries on a rectangular lattice padded by one ghost layer: halfway bounce-back walls
//!   (any non-fluid cell), moving walls / velocity inlets (Ladd's momentum-corrected
//!   bounce-back), pressure outlets (the ghost supplies the equilibrium at ρ = 1 with the
//!   adjacent fluid node's velocity).
//!
//! Pull streaming fused with collision, two buffers. Lattice units: Δx = Δt = 1, c_s² = 1/3.

use thiserror::Error;

const Q: usize = 9;
const CX: [i64; Q] = [0, 1, 0, -1, 0, 1, -1, -1, 1];
const CY: [i64; Q] = [0, 0, 1, 0, -1, 1, 1, -1, -1];
const W: [f64; Q] = [
    4.0 / 9.0,
    1.0 / 9.0,
    1.0 / 9.0,
    1.0 / 9.0,
    1.0 / 9.0,
    1.0 / 36.0,
    1.0 / 36.0,
    1.0 / 36.0,
    1.0 / 36.0,
];
const OPP: [usize; Q] = [0, 3, 4, 1, 2, 7, 8, 5, 6];
/// TRT magic parameter.
const MAGIC: f64 = 3.0 / 16.0;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum LbmError {
    #[error("lattice must be at least 2x2 cells, got {0}x{1}")]
    TooSmall(usize, usize),
    #[error("cell ({0}, {1}) is outside the padded lattice")]
    OutOfRange(i64, i64),
    #[error("lattice viscosity {0} out of range (relaxation time must be in (0.5, 5))")]
    BadViscosity(f64),
    #[error("bad parameter: {0}")]
    BadParameter(&'static str),
    #[error("the domain has no fluid cells")]
    NoFluid,
    #[error("the solution diverged after {0} steps (non-finite velocity)")]
    Diverged(usize),
}

/// What a lattice cell (or ghost cell in the one-cell frame around the lattice) is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Node {
    Fluid,
    /// No-slip wall (halfway bounce-back).
    Wall,
    /// Wall or inlet moving with this velocity (lattice units).
    Moving([f64; 2]),
    /// Pressure outlet at the reference density.
    Pressure,
}

/// Physical-model parameters in lattice units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LbmParams {
    /// Kinematic viscosity, lattice units (τ = 3ν + 1/2).
    pub nu: f64,
    /// Linear friction coefficient λ (per time step): force density −λ·u.
    pub friction: f64,
    /// Uniform body force density.
    pub body_force: [f64; 2],
}

/// How a run ended.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Convergence {
    pub steps: usize,
    /// Last relative velocity change per step: ‖u(t) − u(t−K)‖₂ / (K ‖u(t)‖₂).
    pub residual: f64,
    pub converged: bool,
}

/// A D2Q9 TRT lattice with its state.
pub struct Lattice {
    nx: usize,
    ny: usize,
    /// Padded width (nx + 2).
    pw: usize,
    nodes: Vec<Node>,
    fluid: Vec<usize>,
    /// Per padded cell: fluid with all eight neighbours fluid (no boundary handling needed).
    interior: Vec<bool>,
    offsets: [isize; Q],
    params: LbmParams,
    omega_plus: f64,
    omega_minus: f64,
    f: Vec<f64>,
    f_new: Vec<f64>,
    u: Vec<[f64; 2]>,
    rho: Vec<f64>,
    steps: usize,
}

impl Lattice {
    /// An `nx × ny` lattice, every cell fluid, surrounded by walls.
    pub fn new(nx: usize, ny: usize, params: LbmParams) -> Result<Self, LbmError> {
        if nx < 2 || ny < 2 {
            return Err(LbmError::TooSmall(nx, ny));
        }
        if !(params.nu.is_finite() && params.nu > 0.0 && params.nu < 1.5) {
            return Err(LbmError::BadViscosity(params.nu));
        }
        if !(params.friction.is_finite() && params.friction >= 0.0) {
            return Err(LbmError::BadParameter("friction must be finite and ≥ 0"));
        }
        if !params.body_force.iter().all(|g| g.is_finite()) {
            return Err(LbmError::BadParameter("body force must be finite"));
        }
        let pw = nx + 2;
        let np = pw * (ny + 2);
        let mut nodes = vec![Node::Wall; np];
        for j in 0..ny {
            for i in 0..nx {
                nodes[(j + 1) * pw + i + 1] = Node::Fluid;
            }
        }
        let mut offsets = [0isize; Q];
        for q in 0..Q {
            offsets[q] = (CX[q] + CY[q] * pw as i64) as isize;
        }
        let tau = 3.0 * params.nu + 0.5;
        let omega_plus = 1.0 / tau;
        let omega_minus = 1.0 / (0.5 + MAGIC / (tau - 0.5));
        let mut f = vec![0.0; np * Q];
        for cell in f.chunks_exact_mut(Q) {
            cell.copy_from_slice(&W);
        }
        Ok(Self {
            nx,
            ny,
            pw,
            nodes,
            fluid: Vec::new(),
            interior: Vec::new(),
            offsets,
            params,
            omega_plus,
            omega_minus,
            f_new: f.clone(),
            f,
            u: vec![[0.0; 2]; np],
            rho: vec![1.0; np],
            steps: 0,
        })
    }

    pub fn nx(&self) -> usize {
        self.nx
    }

    pub fn ny(&self) -> usize {
        self.ny
    }

    pub fn params(&self) -> &LbmParams {
        &self.params
    }

    /// Relaxation time τ = 3ν + 1/2.
    pub fn tau(&self) -> f64 {
        3.0 * self.params.nu + 0.5
    }

    fn index(&self, i: i64, j: i64) -> Option<usize> {
        let (pi, pj) = (i + 1, j + 1);
        (pi >= 0 && pj >= 0 && pi < self.pw as i64 && pj < self.ny as i64 + 2)
            .then(|| pj as usize * self.pw + pi as usize)
    }

    /// Sets cell (i, j); i ∈ [−1, nx], j ∈ [−1, ny] (−1 and nx / ny are the ghost frame).
    /// Ghost cells must not be fluid.
    pub fn set(&mut self, i: i64, j: i64, node: Node) -> Result<(), LbmError> {
        let idx = self.index(i, j).ok_or(LbmError::OutOfRange(i, j))?;
        let ghost = i < 0 || j < 0 || i >= self.nx as i64 || j >= self.ny as i64;
        if ghost && node == Node::Fluid {
            return Err(LbmError::OutOfRange(i, j));
        }
        if let Node::Moving(v) = node {
            if !v.iter().all(|c| c.is_finite()) {
                return Err(LbmError::BadParameter(
                    "moving-wall velocity must be finite",
                ));
            }
        }
        self.nodes[idx] = node;
        Ok(())
    }

    pub fn node(&self, i: i64, j: i64) -> Option<Node> {
        self.index(i, j).map(|k| self.nodes[k])
    }

    pub fn is_fluid(&self, i: i64, j: i64) -> bool {
        self.node(i, j) == Some(Node::Fluid)
    }

    /// Velocity at cell (i, j) (zero outside the fluid), lattice units.
    pub fn velocity(&self, i: i64, j: i64) -> [f64; 2] {
        match self.index(i, j) {
            Some(k) if self.nodes[k] == Node::Fluid => self.u[k],
            _ => [0.0; 2],
        }
    }

    /// Density (pressure / c_s²) at cell (i, j); 1 outside the fluid.
    pub fn density(&self, i: i64, j: i64) -> f64 {
        match self.index(i, j) {
            Some(k) if self.nodes[k] == Node::Fluid => self.rho[k],
            _ => 1.0,
        }
    }

    /// Mass per step that the moving (inlet) ghost cells in `cells` inject into the fluid
    /// through their links (Ladd bounce-back adds 6·w_q·c_q·u per link), lattice units. A
    /// velocity inlet's flux is exactly this, which differs from Σu where an inlet meets a wall.
    pub fn injected_flux(&self, cells: &[(i64, i64)]) -> f64 {
        let mut flux = 0.0;
        for &(i, j) in cells {
            let Some(Node::Moving(v)) = self.node(i, j) else {
                continue;
            };
            for q in 1..Q {
                if self.is_fluid(i + CX[q], j + CY[q]) {
                    flux += 6.0 * W[q] * (CX[q] as f64 * v[0] + CY[q] as f64 * v[1]);
                }
            }
        }
        flux
    }

    pub fn fluid_cells(&self) -> usize {
        self.nodes.iter().filter(|&&n| n == Node::Fluid).count()
    }

    pub fn steps(&self) -> usize {
        self.steps
    }

    fn prepare(&mut self) -> Result<(), LbmError> {
        self.fluid = (0..self.nodes.len())
            .filter(|&k| self.nodes[k] == Node::Fluid)
            .collect();
        if self.fluid.is_empty() {
            return Err(LbmError::NoFluid);
        }
        let mut interior = vec![false; self.nodes.len()];
        for &p in &self.fluid {
            interior[p] = self
                .offsets
                .iter()
                .all(|&o| self.nodes[(p as isize - o) as usize] == Node::Fluid);
        }
        self.interior = interior;
        Ok(())
    }

    /// One collide-and-stream step over all fluid cells.
    fn step(&mut self) {
        let (wp, wm) = (self.omega_plus, self.omega_minus);
        let (sp, sm) = (1.0 - 0.5 * wp, 1.0 - 0.5 * wm);
        let lambda = self.params.friction;
        let g = self.params.body_force;
        let f = &self.f;
        let nodes = &self.nodes;
        for &p in &self.fluid {
            let mut fin = [0.0f64; Q];
            let interior = self.interior[p];
            for q in 0..Q {
                let src = (p as isize - self.offsets[q]) as usize;
                if interior {
                    fin[q] = f[src * Q + q];
                    continue;
                }
                fin[q] = match nodes[src] {
                    Node::Fluid => f[src * Q + q],
                    Node::Wall => f[p * Q + OPP[q]],
                    Node::Moving(uw) => {
                        f[p * Q + OPP[q]]
                            + 6.0 * W[q] * (CX[q] as f64 * uw[0] + CY[q] as f64 * uw[1])
                    }
                    Node::Pressure => {
                        let u = self.u[p];
                        let cu = CX[q] as f64 * u[0] + CY[q] as f64 * u[1];
                        W[q] * (1.0 + 3.0 * cu + 4.5 * cu * cu - 1.5 * (u[0] * u[0] + u[1] * u[1]))
                    }
                };
            }
            let mut rho = 0.0;
            let (mut mx, mut my) = (0.0, 0.0);
            for q in 0..Q {
                rho += fin[q];
                mx += fin[q] * CX[q] as f64;
                my += fin[q] * CY[q] as f64;
            }
            let denom = 1.0 + 0.5 * lambda;
            let ux = (mx + 0.5 * g[0]) / denom;
            let uy = (my + 0.5 * g[1]) / denom;
            let fx = g[0] - lambda * ux;
            let fy = g[1] - lambda * uy;
            let usq = ux * ux + uy * uy;
            let uf = ux * fx + uy * fy;
            let out = &mut self.f_new[p * Q..p * Q + Q];
            for q in 0..Q {
                let o = OPP[q];
                let (cx, cy) = (CX[q] as f64, CY[q] as f64);
                let cu = cx * ux + cy * uy;
                let eq_plus = W[q] * (rho + 4.5 * cu * cu - 1.5 * usq);
                let eq_minus = W[q] * 3.0 * cu;
                let f_plus = 0.5 * (fin[q] + fin[o]);
                let f_minus = 0.5 * (fin[q] - fin[o]);
                let cf = cx * fx + cy * fy;
                let src = W[q] * (sm * 3.0 * cf + sp * (9.0 * cu * cf - 3.0 * uf));
                out[q] = fin[q] - wp * (f_plus - eq_plus) - wm * (f_minus - eq_minus) + src;
            }
            self.u[p] = [ux, uy];
            self.rho[p] = rho;
        }
        std::mem::swap(&mut self.f, &mut self.f_new);
        self.steps += 1;
    }

    /// Runs until the relative velocity change per step, measured every `check_every` steps,
    /// is below `tolerance`, or `max_steps` have run. `progress` gets (steps, residual) at each
    /// check.
    pub fn run(
        &mut self,
        max_steps: usize,
        tolerance: f64,
        check_every: usize,
        mut progress: impl FnMut(usize, f64),
    ) -> Result<Convergence, LbmError> {
        if check_every == 0 || !(tolerance.is_finite() && tolerance > 0.0) {
            return Err(LbmError::BadParameter(
                "check_every must be > 0 and tolerance finite and > 0",
            ));
        }
        self.prepare()?;
        let mut previous: Vec<[f64; 2]> = self.fluid.iter().map(|&p| self.u[p]).collect();
        let mut residual = f64::INFINITY;
        let mut done = 0;
        while done < max_steps {
            let n = check_every.min(max_steps - done);
            for _ in 0..n {
                self.step();
            }
            done += n;
            let (mut diff, mut norm) = (0.0, 0.0);
            for (prev, &p) in previous.iter_mut().zip(&self.fluid) {
                let u = self.u[p];
                diff += (u[0] - prev[0]).powi(2) + (u[1] - prev[1]).powi(2);
                norm += u[0] * u[0] + u[1] * u[1];
                *prev = u;
            }
            if !(diff.is_finite() && norm.is_finite()) {
                return Err(LbmError::Diverged(self.steps));
            }
            residual = if norm > 0.0 {
                (diff / norm).sqrt() / n as f64
            } else {
                0.0
            };
            progress(self.steps, residual);
            if residual < tolerance && norm > 0.0 {
                return Ok(Convergence {
                    steps: self.steps,
                    residual,
                    converged: true,
                });
            }
        }
        Ok(Convergence {
            steps: self.steps,
            residual,
            converged: false,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_bad_input() {
        let p = LbmParams {
            nu: 0.1,
            friction: 0.0,
            body_force: [0.0; 2],
        };
        assert!(Lattice::new(1, 5, p).is_err());
        assert!(Lattice::new(5, 5, LbmParams { nu: -1.0, ..p }).is_err());
        assert!(Lattice::new(
            5,
            5,
            LbmParams {
                friction: f64::NAN,
                ..p
            }
        )
        .is_err());
        let mut l = Lattice::new(5, 5, p).unwrap();
        assert!(l.set(-1, 0, Node::Fluid).is_err());
        assert!(l.set(7, 0, Node::Wall).is_err());
        assert!(l.set(-1, 0, Node::Moving([f64::INFINITY, 0.0])).is_err());
        for j in 0..5 {
            for i in 0..5 {
                l.set(i, j, Node::Wall).unwrap();
            }
        }
        assert_eq!(l.run(10, 1e-6, 5, |_, _| {}), Err(LbmError::NoFluid));
    }

    #[test]
    fn fluid_at_rest_stays_at_rest() {
        let p = LbmParams {
            nu: 0.1,
            friction: 0.01,
            body_force: [0.0; 2],
        };
        let mut l = Lattice::new(8, 6, p).unwrap();
        let c = l.run(50, 1e-12, 10, |_, _| {}).unwrap();
        assert_eq!(c.steps, 50);
        assert_eq!(l.velocity(3, 3), [0.0, 0.0]);
        assert!((l.density(3, 3) - 1.0).abs() < 1e-14);
    }
}
