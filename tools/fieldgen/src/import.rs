//! `fieldgen import` (being written).

/// Arguments of `fieldgen import`.
#[derive(Debug, clap::Args)]
pub struct ImportArgs {}

pub fn run(_args: &ImportArgs) -> anyhow::Result<()> {
    anyhow::bail!("fieldgen import is not built yet")
}
