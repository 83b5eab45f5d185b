//! `fieldgen rig-check`: load and validate a rig file, print what it describes.
use std::path::PathBuf;

use fieldmaps::rigfile::Rig;

#[derive(clap::Args, Debug)]
pub struct RigCheckArgs {
    /// Rig file to check (e.g. fieldmaps/rigs/paper.toml).
    #[arg(long)]
    pub rig: PathBuf,
}

/// Loads the rig (every file it names included) and prints its summary, or fails with the
/// error naming the file and the field.
pub fn run(args: &RigCheckArgs) -> anyhow::Result<()> {
    let rig = Rig::load(&args.rig)?;
    print!("{}", rig.summary());
    println!("rig ok");
    Ok(())
}
