//! `fieldmaps`: the rig's data and physical laws, shared by the plant (digital twin) and the
//! controller so the two never disagree on physics.
//!
//! Units: SI everywhere inside (m, s, A, T, N, Pa·s, kg). Millimetres appear only in names that
//! say so (`_mm`) at user-facing edges (camera geometry, configs).
//!
//! - [`rig`]: robot, fluid and coil-driver parameters (paper / `RIG.md` defaults, TOML-loadable).
//! - [`physics`]: magnetic force/torque on a dipole, viscous drag, damping coefficient.
//! - [`coils`]: the 12-coil electromagnet (closed-form Biot–Savart), calibrated to the paper's FEA.
//! - [`fieldmap`]: current-normalized coil field maps on a 3D grid (file format, checked
//!   loading, trilinear interpolation); a drop-in [`coils::CoilField`] for the direct model.
//! - [`allocation`]: current allocation (paper Eq. 2–4), current/power limiting, and the
//!   constrained (QP/SOCP, Clarabel) allocation that respects both limits.
//! - [`phantom`]: parametric top-view heart phantom (signed distance field, raster mask).

pub mod allocation;
pub mod coils;
mod elliptic;
pub mod fieldmap;
pub mod flowmap;
pub mod mask;
pub mod phantom;
pub mod physics;
pub mod rig;
