//! An iceoryx2 world of its own per test (unique prefix and root), so tests run in parallel
//! without seeing each other's services.

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};

use millinav_kit::iceoryx2::prelude::*;
use millinav_kit::iceoryx_config;

static NEXT: AtomicUsize = AtomicUsize::new(0);

/// A test's own iceoryx2 prefix and root; the root is removed when it is dropped.
pub struct Isolated {
    pub prefix: String,
    pub root: PathBuf,
}

impl Isolated {
    pub fn new() -> Self {
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let pid = std::process::id();
        Self {
            prefix: format!("mkt{pid}_{n}_"),
            // Short: iceoryx2's Unix socket paths under the root must fit in 108 bytes.
            root: PathBuf::from(format!("/tmp/mkt/{pid}-{n}")),
        }
    }

    pub fn config(&self) -> Config {
        iceoryx_config(Some(&self.prefix), Some(&self.root)).expect("iceoryx2 config")
    }

    /// A node of this test's world (several may exist, e.g. one per thread).
    pub fn node(&self) -> Node<ipc::Service> {
        NodeBuilder::new()
            .config(&self.config())
            .create::<ipc::Service>()
            .expect("node")
    }
}

impl Drop for Isolated {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.root);
    }
}
