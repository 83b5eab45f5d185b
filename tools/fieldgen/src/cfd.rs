//! `fieldgen cfd` (being written).

/// Arguments of `fieldgen cfd`.
#[derive(Debug, clap::Args)]
pub struct CfdArgs {}

pub fn run(_args: &CfdArgs) -> anyhow::Result<()> {
    anyhow::bail!("fieldgen cfd is not built yet")
}
