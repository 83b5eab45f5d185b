//! `fieldmaps`: the rig's data and physical laws, shared by the plant (digital twin) and the
//! controller so the two never disagree on physics.
//!
//! Units: SI everywhere inside (m, s, A, T, N, Pa·s, kg). Millimetres appear only in names that
//! say so (`_mm`) at user-facing edges (camera geometry, configs).
//!
//! - [`rig`]: robot, fluid and coil-driver parameters (a rig file gives them).
//! - [`physics`]: magnetic force/torque on a dipole, viscous drag, damping coefficient.
//! - [`coils`]: a rig's electromagnet (closed-form Biot–Savart) and its reference fields.
//! - [`fieldmap`]: current-normalized coil field maps on a 3D grid (file format, checked
//!   loading, trilinear interpolation); a drop-in [`coils::CoilField`] for the direct model.
//! - [`calibration`]: per-coil gain / 3 × 3 corrections and a background field fitted to
//!   gaussmeter data, applied over a base model.
//! - [`allocation`]: current allocation (paper Eq. 2–4), current/power limiting, and the
//!   constrained (QP/SOCP, Clarabel) allocation that respects both limits.
//! - [`lens`]: a real camera's lens (pinhole + plumb_bob) and registration: raw pixel ↔ world,
//!   the rectification map, and the twin's raw view.
//! - [`phantom`]: parametric top-view phantoms from a file (signed distance field, raster mask).
//! - [`rigfile`]: the rig as data: a TOML rig file (coils, camera, phantom, robot), its loader
//!   and validation (`fieldmaps/rigs/FORMAT.md`).

pub mod allocation;
pub mod calibration;
pub mod coils;
mod elliptic;
pub mod fieldmap;
pub mod flowmap;
pub mod lens;
pub mod mask;
pub mod phantom;
pub mod physics;
pub mod rig;
pub mod rigfile;
pub mod walls;

/// Environment variable naming the repository root that committed data (coil maps, flow maps,
/// the UNet model, scenarios) is read from.
pub const ROOT_ENV: &str = "MILLINAV_ROOT";

/// The repository root the committed data is read from: `MILLINAV_ROOT` when set, else the
/// nearest ancestor of the working directory that holds the committed coil maps, else the
/// checkout this binary was compiled from. Looking at run time first matters because build
/// trees are shared between checkouts (`CARGO_TARGET_DIR`): an up-to-date binary may have been
/// compiled in another clone, which can since have moved or changed.
pub fn data_root() -> std::path::PathBuf {
    use std::path::{Path, PathBuf};
    let holds_data = |dir: &Path| dir.join("fieldmaps/coils/coils.toml").is_file();
    if let Some(root) = std::env::var_os(ROOT_ENV).map(PathBuf::from) {
        return root;
    }
    if let Ok(cwd) = std::env::current_dir() {
        if let Some(found) = cwd.ancestors().find(|d| holds_data(d)) {
            return found.to_owned();
        }
    }
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}
