//! Force controllers of paper Sec. II-C, each a small type behind one trait (`Controller`, in
//! `interface`, with what they all share). They see only what the rig sees: the estimated pose
//! (via position/velocity estimates), the reference, and the steady-map flow estimate. Gains
//! default to the paper's values (RIG.md).

mod interface;
pub mod mpc;
mod pid;
mod smc;

use serde::{Deserialize, Serialize};

pub use interface::{ControlInput, ControlTerms, Controller, NominalModel};
pub use mpc::{ForceSite, Mpc, MpcGains};
pub use pid::{Pid, PidGains};
pub use smc::{SmcDob, SmcGains};

/// Controllers selectable by name in a scenario's `[control]` table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum ControllerKind {
    #[default]
    Pid,
    SmcDob,
    Smc,
    Mpc,
    /// SMC-DOB with automatic gain scheduling (beyond the paper; pair it with
    /// `constrained_allocation = true`).
    SmcDobAuto,
    /// `smc-dob-auto` without the observer: the DOB ablation of the scheduled controller.
    SmcAuto,
}

impl ControllerKind {
    pub fn build(
        self,
        pid: &PidGains,
        smc: &SmcGains,
        mpc: &MpcGains,
        model: NominalModel,
    ) -> Box<dyn Controller> {
        match self {
            Self::Pid => Box::new(Pid::new(pid.clone(), model)),
            Self::SmcDob => Box::new(SmcDob::new(
                SmcGains {
                    use_dob: true,
                    ..smc.clone()
                },
                model,
            )),
            Self::Smc => Box::new(SmcDob::new(
                SmcGains {
                    use_dob: false,
                    ..smc.clone()
                },
                model,
            )),
            Self::Mpc => Box::new(Mpc::new(mpc.clone(), model)),
            Self::SmcDobAuto | Self::SmcAuto => Box::new(SmcDob::new(
                SmcGains {
                    use_dob: self == Self::SmcDobAuto,
                    auto_schedule: true,
                    ..smc.clone()
                },
                model,
            )),
        }
    }
}
