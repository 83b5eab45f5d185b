//! `fieldmaps`: the rig's data and physical laws, shared by the plant (digital twin) and the
//! controller so the two never disagree on physics.
//!
//! Units: SI everywhere inside (m, s, A, T, N, Pa·s, kg). Millimetres appear only in names that
//! say so (`_mm`) at user-facing edges (camera geometry, configs).
//!
//! - [`rig`]: robot, fluid and coil-driver parameters (paper / `RIG.md` defaults, TOML-loadable).
//! - [`physics`]: magnetic force/torque on a dipole, viscous drag, damping coefficient.
//! - [`coils`]: the 12-coil electromagnet (closed-form Biot–Savart), calibrated to the paper's FEA.
//! - [`allocation`]: current allocation (paper Eq. 2–4) and current/power limiting.
//! - [`phantom`]: parametric top-view heart phantom (signed distance field, raster mask).

pub mod allocation;
pub mod coils;
mod elliptic;
pub mod flowmap;
pub mod phantom;
pub mod physics;
pub mod rig;
