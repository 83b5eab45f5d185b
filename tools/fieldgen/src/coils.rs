//! `fieldgen coils` (being written).

/// Arguments of `fieldgen coils`.
#[derive(Debug, clap::Args)]
pub struct CoilsArgs {}

pub fn run(_args: &CoilsArgs) -> anyhow::Result<()> {
    anyhow::bail!("fieldgen coils is not built yet")
}
