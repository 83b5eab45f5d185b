//! The solver's ports: the rig's inlets and outlets as ports, the lattice over the mask's image,
//! and where each port's tube ends on the mask (its opening).

use super::*;

/// What a port is for the solver.
#[derive(Debug, Clone, PartialEq)]
pub enum PortKind {
    /// Velocity inlet carrying this fraction of the total flow.
    Inlet { flow_fraction: f64 },
    /// Pressure outlet.
    Outlet,
}

/// A port: where its tube meets the canal (the mouth), and which way the tube runs.
#[derive(Debug, Clone, PartialEq)]
pub struct Port {
    pub name: String,
    /// Where the port is defined, for errors, e.g. `fieldmaps/rigs/x.toml: phantom.inlets[0]`.
    pub origin: String,
    pub kind: PortKind,
    /// Where the tube opens into the canal, m.
    pub mouth_m: Vector2<f64>,
    /// Unit axis pointing away from the chamber (upstream for inlets, downstream for outlets).
    pub outward: Vector2<f64>,
    pub radius_m: f64,
}

impl Port {
    /// Whether `p` lies in this port's tube (beyond the mouth, within radius + 0.5 mm). Map
    /// nodes there are written as zero (see [`solve`]).
    pub fn in_tube(&self, p: &Vector2<f64>) -> bool {
        let d = p - self.mouth_m;
        let s = d.dot(&self.outward);
        s > 0.0 && (d - self.outward * s).norm() < self.radius_m + 0.5e-3
    }
}

/// The solver's ports from a rig's `[[phantom.inlets]]` / `[[phantom.outlets]]`: inlets share
/// the pump flow equally (the rig file gives no split), outlets are pressure outlets at one
/// common pressure (the split between several follows from their resistance).
pub fn rig_ports(rig_path: &Path, inlets: &[Inlet], outlets: &[Outlet]) -> Vec<Port> {
    let n = inlets.len().max(1) as f64;
    let file = rig_path.display();
    let mut ports: Vec<Port> = inlets
        .iter()
        .enumerate()
        .map(|(i, inlet)| Port {
            name: inlet.name.clone(),
            origin: format!("{file}: phantom.inlets[{i}]"),
            kind: PortKind::Inlet {
                flow_fraction: 1.0 / n,
            },
            mouth_m: inlet.mouth_m,
            outward: -inlet.direction.into_inner(),
            radius_m: 0.5 * inlet.diameter_m,
        })
        .collect();
    ports.extend(outlets.iter().enumerate().map(|(i, outlet)| Port {
        name: outlet.name.clone(),
        origin: format!("{file}: phantom.outlets[{i}]"),
        kind: PortKind::Outlet,
        mouth_m: outlet.mouth_m,
        outward: outlet.direction.into_inner(),
        radius_m: 0.5 * outlet.diameter_m,
    }));
    ports
}

/// The view rectangle of an image geometry, m.
pub(super) fn view_rect(g: &ImageGeometry) -> (Vector2<f64>, Vector2<f64>) {
    let lo = Vector2::new(
        g.origin_x_mm,
        g.origin_y_mm - f64::from(g.height_px) * g.mm_per_px,
    ) * 1e-3;
    let hi = Vector2::new(
        g.origin_x_mm + f64::from(g.width_px) * g.mm_per_px,
        g.origin_y_mm,
    ) * 1e-3;
    (lo, hi)
}

/// A port's opening: the row of fluid cells across the end of its tube, and the non-fluid
/// cells just beyond them that the solver turns into the inlet / outlet boundary.
#[derive(Debug, Clone)]
pub(super) struct Opening {
    /// Fluid cells across the tube end, in order.
    pub(super) cells: Vec<(i64, i64)>,
    /// Boundary cell beyond each fluid cell (ghost frame or an in-view wall cell).
    pub(super) ghosts: Vec<(i64, i64)>,
    /// Inward unit normal (a lattice axis).
    pub(super) inward: [f64; 2],
    pub(super) centre_m: Vector2<f64>,
}

/// Lattice laid over the mask's image: cell centres, mm ↔ index.
#[derive(Debug, Clone, Copy)]
pub(super) struct Grid {
    pub(super) nx: usize,
    pub(super) ny: usize,
    pub(super) dx: f64,
    /// Lower-left corner of the lattice, m.
    pub(super) x0: f64,
    pub(super) y0: f64,
}

impl Grid {
    pub(super) fn centre(&self, i: i64, j: i64) -> Vector2<f64> {
        Vector2::new(
            self.x0 + (i as f64 + 0.5) * self.dx,
            self.y0 + (j as f64 + 0.5) * self.dx,
        )
    }

    pub(super) fn inside(&self, i: i64, j: i64) -> bool {
        i >= 0 && j >= 0 && i < self.nx as i64 && j < self.ny as i64
    }

    /// The cell containing `p`, if on the lattice.
    pub(super) fn cell_of(&self, p: &Vector2<f64>) -> Option<(i64, i64)> {
        let i = ((p.x - self.x0) / self.dx).floor() as i64;
        let j = ((p.y - self.y0) / self.dx).floor() as i64;
        self.inside(i, j).then_some((i, j))
    }
}

/// Cells along one side of the lattice, the ghost offset, and the inward normal.
pub(super) type Side = (Vec<(i64, i64)>, (i64, i64), [f64; 2]);

/// Runs of fluid cells on the image edge (where the canal leaves the view).
pub(super) fn edge_runs(fluid: &[bool], grid: &Grid) -> Vec<Vec<(i64, i64)>> {
    let (nx, ny) = (grid.nx as i64, grid.ny as i64);
    let is_fluid = |i: i64, j: i64| fluid[(j * nx + i) as usize];
    let sides: [Side; 4] = [
        ((0..nx).map(|i| (i, 0)).collect(), (0, -1), [0.0, 1.0]),
        ((0..nx).map(|i| (i, ny - 1)).collect(), (0, 1), [0.0, -1.0]),
        ((0..ny).map(|j| (0, j)).collect(), (-1, 0), [1.0, 0.0]),
        ((0..ny).map(|j| (nx - 1, j)).collect(), (1, 0), [-1.0, 0.0]),
    ];
    let mut runs = Vec::new();
    for (cells, _, _) in sides {
        let mut run: Vec<(i64, i64)> = Vec::new();
        for &(i, j) in &cells {
            if is_fluid(i, j) {
                run.push((i, j));
            } else if !run.is_empty() {
                runs.push(std::mem::take(&mut run));
            }
        }
        if !run.is_empty() {
            runs.push(run);
        }
    }
    runs
}

/// Largest angle between a port's direction and the nearest lattice axis: the opening is cut
/// square to that axis, so a more oblique tube would be misrepresented.
pub(super) const MAX_PORT_OBLIQUITY_DEG: f64 = 20.0;

/// Finds each port's opening. From the cell of the mouth, walk up the tube (along the lattice
/// axis nearest to `outward`) through fluid cells until the next cell is not fluid: the image
/// edge, where the tube leaves the view (the paper's ports), or an in-view wall, where the
/// tube leaves the control plane or the drawn canal simply ends (a port anywhere on the mask).
/// The opening is the row of fluid cells across the tube there whose next cell is not fluid,
/// no wider than the tube (diameter + one cell each side).
pub(super) fn locate_openings(
    fluid: &[bool],
    grid: &Grid,
    ports: &[Port],
) -> Result<Vec<Opening>, CfdError> {
    let is_fluid = |i: i64, j: i64| grid.inside(i, j) && fluid[(j * grid.nx as i64 + i) as usize];
    let mut openings: Vec<Opening> = Vec::with_capacity(ports.len());
    for port in ports {
        let out = port.outward;
        let along_x = out.x.abs() >= out.y.abs();
        let cos = out.x.abs().max(out.y.abs()) / out.norm().max(f64::MIN_POSITIVE);
        if cos.is_nan() || cos < MAX_PORT_OBLIQUITY_DEG.to_radians().cos() {
            return Err(CfdError::Port {
                origin: port.origin.clone(),
                field: "direction",
                message: format!(
                    "{:.0}° from the nearest x or y axis; fieldgen cfd cuts a port's opening \
                     square to an image axis and accepts at most {MAX_PORT_OBLIQUITY_DEG}°",
                    cos.clamp(-1.0, 1.0).acos().to_degrees()
                ),
            });
        }
        let step: (i64, i64) = if along_x {
            (out.x.signum() as i64, 0)
        } else {
            (0, out.y.signum() as i64)
        };
        let across: (i64, i64) = (step.1.abs(), step.0.abs());
        let mouth_mm = (port.mouth_m.x * 1e3, port.mouth_m.y * 1e3);
        // The mouth lies on a canal pixel; at the lattice's coarser spacing its cell may fall
        // in the wall, so take the nearest fluid cell within one cell.
        let start = grid.cell_of(&port.mouth_m).and_then(|(i, j)| {
            let mut best: Option<((i64, i64), f64)> = None;
            for dj in -1..=1 {
                for di in -1..=1 {
                    if is_fluid(i + di, j + dj) {
                        let d = (grid.centre(i + di, j + dj) - port.mouth_m).norm();
                        if best.is_none_or(|b| d < b.1) {
                            best = Some(((i + di, j + dj), d));
                        }
                    }
                }
            }
            best.map(|b| b.0)
        });
        let Some(mut end) = start else {
            return Err(CfdError::Port {
                origin: port.origin.clone(),
                field: "position_mm",
                message: format!(
                    "({:.2}, {:.2}) mm is not in the canal at the lattice spacing {:.3} mm; \
                     move the mouth into the canal or use a smaller --dx-mm",
                    mouth_mm.0,
                    mouth_mm.1,
                    grid.dx * 1e3
                ),
            });
        };
        // Canal wider than this across the walk, past the first diameter, is open chamber, not
        // a tube: the direction points the wrong way.
        let diameter = 2.0 * port.radius_m;
        let max_cells = ((2.0 * diameter) / grid.dx).ceil() as i64 + 2;
        let width_at = |c: (i64, i64)| {
            let mut n = 1;
            for sign in [-1i64, 1] {
                let mut k = 1;
                while k <= max_cells
                    && is_fluid(c.0 + sign * k * across.0, c.1 + sign * k * across.1)
                {
                    n += 1;
                    k += 1;
                }
            }
            n
        };
        let first = end;
        for _ in 0..grid.nx + grid.ny {
            let next = (end.0 + step.0, end.1 + step.1);
            if !is_fluid(next.0, next.1) {
                break;
            }
            end = next;
            let walked = (end.0 - first.0).abs().max((end.1 - first.1).abs()) as f64 * grid.dx;
            if walked > diameter && width_at(end) > max_cells {
                return Err(CfdError::Port {
                    origin: port.origin.clone(),
                    field: "direction",
                    message: format!(
                        "from the mouth ({:.2}, {:.2}) mm away from the canal (up an inlet, down \
                         an outlet) the canal is still wider than twice the tube's diameter \
                         {:.2} mm after {:.1} mm: the direction must point into the phantom for \
                         an inlet and out of it for an outlet, and the mouth sit where the tube \
                         meets the canal",
                        mouth_mm.0,
                        mouth_mm.1,
                        diameter * 1e3,
                        walked * 1e3
                    ),
                });
            }
        }
        // The tube axis at the end cell's position along the walk.
        let c_end = grid.centre(end.0, end.1);
        let s_dir = Vector2::new(step.0 as f64, step.1 as f64);
        let s = (c_end - port.mouth_m).dot(&s_dir) / out.dot(&s_dir);
        let axis_at = port.mouth_m + out * s;
        let t_dir = Vector2::new(across.0 as f64, across.1 as f64);
        let half_width = port.radius_m + grid.dx;
        let is_cap = |c: (i64, i64)| {
            is_fluid(c.0, c.1)
                && !is_fluid(c.0 + step.0, c.1 + step.1)
                && (grid.centre(c.0, c.1) - axis_at).dot(&t_dir).abs() <= half_width
        };
        let mut cells = vec![end];
        for sign in [-1i64, 1] {
            let mut c = end;
            loop {
                c = (c.0 + sign * across.0, c.1 + sign * across.1);
                if !is_cap(c) {
                    break;
                }
                cells.push(c);
            }
        }
        cells.sort_unstable();
        let centre_m = cells
            .iter()
            .map(|&(i, j)| grid.centre(i, j))
            .sum::<Vector2<f64>>()
            / cells.len() as f64;
        let ghosts = cells
            .iter()
            .map(|&(i, j)| (i + step.0, j + step.1))
            .collect();
        let opening = Opening {
            cells,
            ghosts,
            inward: [-(step.0 as f64), -(step.1 as f64)],
            centre_m,
        };
        if let Some(k) = openings
            .iter()
            .position(|o| o.cells.iter().any(|c| opening.cells.contains(c)))
        {
            return Err(CfdError::Port {
                origin: port.origin.clone(),
                field: "position_mm",
                message: format!(
                    "its opening at ({:.1}, {:.1}) mm is also port {}'s; give every port its \
                     own tube",
                    centre_m.x * 1e3,
                    centre_m.y * 1e3,
                    ports[k].name
                ),
            });
        }
        openings.push(opening);
    }
    // Canal that leaves the view with no port there would be a silent wall: refuse it.
    for run in edge_runs(fluid, grid) {
        if !run
            .iter()
            .any(|c| openings.iter().any(|o| o.cells.contains(c)))
        {
            let centre = run
                .iter()
                .map(|&(i, j)| grid.centre(i, j))
                .sum::<Vector2<f64>>()
                / run.len() as f64;
            return Err(CfdError::UnmatchedOpening {
                x_mm: centre.x * 1e3,
                y_mm: centre.y * 1e3,
                ports: ports
                    .iter()
                    .map(|p| {
                        format!(
                            "{} at ({:.1}, {:.1}) mm",
                            p.name,
                            p.mouth_m.x * 1e3,
                            p.mouth_m.y * 1e3
                        )
                    })
                    .collect::<Vec<_>>()
                    .join(", "),
            });
        }
    }
    Ok(openings)
}
