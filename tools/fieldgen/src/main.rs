//! `fieldgen`: regenerates the rig data committed under fieldmaps/.
use clap::{Parser, Subcommand};

/// Generates millinav's rig data: calibrated coil field maps and CFD flow maps of the phantom,
/// and converts CFD exports from other tools into millinav's flow-map format.
#[derive(Parser)]
#[command(name = "fieldgen", version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Coil field maps (Biot–Savart), calibrated to the paper's FEA numbers.
    Coils(fieldgen::coils::CoilsArgs),
    /// Steady laminar CFD of the phantom → flow maps at the control plane.
    Cfd(fieldgen::cfd::CfdArgs),
    /// Convert an ANSYS Fluent or OpenFOAM export into a millinav flow map.
    #[command(name = "import-flow", alias = "import")]
    Import(fieldgen::import::ImportArgs),
    /// Import per-coil field data (COMSOL, ANSYS Maxwell, CSV; FEA or measured) into coil maps,
    /// gradients from a curl- and divergence-free local fit.
    ImportCoils(fieldgen::import_coils::ImportCoilsArgs),
    /// Fit per-coil gains (or 3x3 corrections) and a background field to gaussmeter
    /// measurements; writes the calibration file a rig's field_model references.
    FitCoils(fieldgen::fit_coils::FitCoilsArgs),
    /// Load and validate a rig file; print its summary or the error.
    RigCheck(fieldgen::rig_check::RigCheckArgs),
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_target(false)
        .init();
    match Cli::parse().command {
        Command::Coils(args) => fieldgen::coils::run(&args),
        Command::Cfd(args) => fieldgen::cfd::run(&args),
        Command::Import(args) => fieldgen::import::run(&args),
        Command::ImportCoils(args) => fieldgen::import_coils::run(&args),
        Command::FitCoils(args) => fieldgen::fit_coils::run(&args),
        Command::RigCheck(args) => fieldgen::rig_check::run(&args),
    }
}
