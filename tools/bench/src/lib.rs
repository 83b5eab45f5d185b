//! millinav benchmark suite: workloads shared by the `bench` binary (median/p99 table) and the
//! criterion micro-benchmarks (`cargo bench -p millinav-bench`).

pub mod control;
pub mod e2e;
pub mod ipc;
pub mod stats;
pub mod vision;
pub mod workload;

use std::path::PathBuf;

/// The workspace root (scenarios, committed model).
pub fn workspace_root() -> PathBuf {
    fieldmaps::data_root()
}

#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error("{0}")]
    Setup(String),
    #[error("io: {0}")]
    Io(#[from] std::io::Error),
    #[error(transparent)]
    Kit(#[from] millinav_kit::KitError),
}
