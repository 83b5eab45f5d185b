//! `planner` (being written).
fn main() -> anyhow::Result<()> {
    anyhow::bail!("planner is not built yet")
}
