//! The iceoryx2 files of one set: everything its prefix owns under its root directory and in
//! `/dev/shm`. A process killed while it creates a service leaves that service half-made (its
//! static config file still at mode 0600); iceoryx2 then answers `HangsInCreation` to every
//! later open, forever, and none of its own clean-ups removes the file. The supervisor uses this
//! module to start every set on a clean domain, to remove half-made services before it restarts
//! a child, and to leave nothing behind at shutdown.
//!
//! A prefix owns the files whose names begin with it. That is unambiguous only if no prefix is
//! the beginning of another; [`validate_prefix`] makes it so (letters, digits and '-', then one
//! final '_').

use std::os::unix::ffi::OsStrExt;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use iceoryx2::node::NodeView;
use iceoryx2::prelude::*;

use crate::{iox, KitError};

/// Where POSIX shared memory lives on Linux; iceoryx2 names its segments with the bare prefix.
const SHM_DIR: &str = "/dev/shm";
/// Mode of a static service config that its creator has not finished writing.
const MODE_BEING_CREATED: u32 = 0o600;

/// Checks an iceoryx2 prefix: ASCII letters, digits and '-', ending in exactly one '_'. So no
/// prefix begins another, and the files of one set are never taken for another's.
pub fn validate_prefix(prefix: &str) -> Result<(), String> {
    let Some(body) = prefix.strip_suffix('_') else {
        return Err("must end with '_' (e.g. millinav_)".into());
    };
    if body.is_empty() || !body.chars().all(|c| c.is_ascii_alphanumeric() || c == '-') {
        return Err("use ASCII letters, digits and '-', then one final '_'".into());
    }
    Ok(())
}

/// A node of the domain whose process is alive.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LiveNode {
    pub name: String,
    pub pid: i32,
}

/// What a clean-up removed.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Removed {
    pub files: usize,
    pub shared_memory: usize,
}

/// Half-made services found by [`Domain::sweep_half_made`].
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Sweep {
    /// Static config files removed: older than the creation timeout, so their creator is dead.
    pub removed: Vec<PathBuf>,
    /// The earliest time at which a half-made file that is still young may be removed; until
    /// then its creator may be alive and writing it.
    pub retry_at: Option<SystemTime>,
}

/// The files of one iceoryx2 prefix under one root.
#[derive(Debug, Clone)]
pub struct Domain {
    config: Config,
    prefix: Vec<u8>,
    root: PathBuf,
    service_dir: PathBuf,
    node_dir: PathBuf,
    static_suffix: Vec<u8>,
    shm_dir: PathBuf,
}

fn path_of(bytes: &[u8]) -> PathBuf {
    PathBuf::from(std::ffi::OsStr::from_bytes(bytes))
}

impl Domain {
    /// The domain of an iceoryx2 config (its prefix and root).
    pub fn of(config: &Config) -> Self {
        Self {
            config: config.clone(),
            prefix: config.global.prefix.as_bytes().to_vec(),
            root: path_of(config.global.root_path().as_bytes()),
            service_dir: path_of(config.global.service_dir().as_bytes()),
            node_dir: path_of(config.global.node_dir().as_bytes()),
            static_suffix: config
                .global
                .service
                .static_config_storage_suffix
                .as_bytes()
                .to_vec(),
            shm_dir: PathBuf::from(SHM_DIR),
        }
    }

    /// The same domain with its shared memory in another directory (for tests).
    pub fn with_shm_dir(mut self, dir: &Path) -> Self {
        self.shm_dir = dir.to_owned();
        self
    }

    /// How long iceoryx2 lets a creator take before it calls a service hung.
    pub fn creation_timeout(&self) -> Duration {
        self.config.global.creation_timeout
    }

    fn owns(&self, name: &std::ffi::OsStr) -> bool {
        name.as_bytes().starts_with(&self.prefix)
    }

    /// The nodes of this domain whose processes are alive.
    pub fn live_nodes(&self) -> Result<Vec<LiveNode>, KitError> {
        let mut alive = Vec::new();
        Node::<ipc::Service>::list(&self.config, |state| {
            if let NodeState::Alive(view) = &state {
                let (name, pid) = view.details().as_ref().map_or_else(
                    || ("?".to_owned(), -1),
                    |d| {
                        (
                            String::from_utf8_lossy(d.name().as_bytes()).into_owned(),
                            d.process_id().value(),
                        )
                    },
                );
                alive.push(LiveNode { name, pid });
            }
            CallbackProgression::Continue
        })
        .map_err(iox("listing the nodes"))?;
        Ok(alive)
    }

    /// Removes every file and shared-memory segment of the prefix: static service configs,
    /// node records, listener sockets and `/dev/shm` segments. Only for a domain in which no
    /// process lives (check [`Domain::live_nodes`] first); what does not exist is skipped.
    pub fn wipe(&self) -> Result<Removed, KitError> {
        let mut removed = Removed::default();
        for dir in [&self.root, &self.service_dir, &self.node_dir] {
            removed.files += self.remove_owned_entries(dir)?;
        }
        removed.shared_memory = self.remove_owned_entries(&self.shm_dir)?;
        Ok(removed)
    }

    /// Removes the entries of `dir` that the prefix owns, and its subdirectories that hold
    /// nothing but such entries (a node's directory, a service's type definitions).
    fn remove_owned_entries(&self, dir: &Path) -> Result<usize, KitError> {
        let entries = match std::fs::read_dir(dir) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
            Err(e) => return Err(e.into()),
        };
        let mut count = 0;
        for entry in entries.flatten() {
            let path = entry.path();
            let Ok(kind) = entry.file_type() else {
                continue;
            };
            if kind.is_dir() {
                if self.dir_is_owned(&path) {
                    count += std::fs::read_dir(&path).map_or(0, |e| e.count());
                    remove_ignoring_absent(std::fs::remove_dir_all(&path))?;
                }
            } else if self.owns(&entry.file_name()) {
                remove_ignoring_absent(std::fs::remove_file(&path))?;
                count += 1;
            }
        }
        Ok(count)
    }

    /// A directory that holds entries, all of them the prefix's (directories of other prefixes
    /// or of iceoryx2 itself stay).
    fn dir_is_owned(&self, dir: &Path) -> bool {
        if dir == self.service_dir || dir == self.node_dir {
            return false;
        }
        let Ok(entries) = std::fs::read_dir(dir) else {
            return false;
        };
        let mut any = false;
        for entry in entries.flatten() {
            if !self.owns(&entry.file_name()) {
                return false;
            }
            any = true;
        }
        any
    }

    /// Removes the half-made services of the prefix: static config files still at mode 0600
    /// whose last change is older than the creation timeout (a live creator finishes within it,
    /// so their creator is dead). Younger ones are left, and `retry_at` says when to look again.
    pub fn sweep_half_made(&self, now: SystemTime) -> Result<Sweep, KitError> {
        let mut sweep = Sweep::default();
        let entries = match std::fs::read_dir(&self.service_dir) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(sweep),
            Err(e) => return Err(e.into()),
        };
        let hung_after = self.creation_timeout();
        for entry in entries.flatten() {
            let name = entry.file_name();
            if !self.owns(&name) || !name.as_bytes().ends_with(&self.static_suffix) {
                continue;
            }
            let Ok(meta) = entry.metadata() else {
                continue;
            };
            if !meta.is_file() || meta.permissions().mode() & 0o777 != MODE_BEING_CREATED {
                continue;
            }
            let changed = meta.modified().unwrap_or(now);
            let hung_at = changed + hung_after;
            if now >= hung_at {
                remove_ignoring_absent(std::fs::remove_file(entry.path()))?;
                sweep.removed.push(entry.path());
            } else {
                sweep.retry_at = Some(sweep.retry_at.map_or(hung_at, |t| t.min(hung_at)));
            }
        }
        Ok(sweep)
    }
}

fn remove_ignoring_absent(result: std::io::Result<()>) -> Result<(), KitError> {
    match result {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e.into()),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::iceoryx_config;

    #[test]
    fn prefixes_never_begin_one_another() {
        for good in ["millinav_", "mt123-closed_", "a_"] {
            assert_eq!(validate_prefix(good), Ok(()), "{good}");
        }
        for bad in [
            "millinav",
            "millinav__",
            "a_b_",
            "_",
            "",
            "mill navi_",
            "mil/x_",
        ] {
            assert!(validate_prefix(bad).is_err(), "{bad:?} accepted");
        }
    }

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("iox-domain-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("scratch dir");
        dir
    }

    fn touch(path: &Path, mode: u32) {
        std::fs::create_dir_all(path.parent().expect("parent")).expect("dir");
        std::fs::write(path, b"x").expect("write");
        std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode)).expect("chmod");
    }

    #[test]
    fn a_half_made_service_is_swept_once_its_creator_must_be_dead() {
        let root = scratch("sweep");
        let config = iceoryx_config(Some("set-a_"), Some(&root)).expect("config");
        let domain = Domain::of(&config);
        let services = root.join("services");
        let stuck = services.join("set-a_abc.service");
        let done = services.join("set-a_def.service");
        let other = services.join("set-b_abc.service");
        touch(&stuck, 0o600);
        touch(&done, 0o400);
        touch(&other, 0o600);
        let changed = std::fs::metadata(&stuck).unwrap().modified().unwrap();

        // Within the creation timeout its creator may still be writing it.
        let young = domain.sweep_half_made(changed).expect("sweep");
        assert!(young.removed.is_empty());
        assert_eq!(young.retry_at, Some(changed + domain.creation_timeout()));
        assert!(stuck.exists());

        let old = domain
            .sweep_half_made(changed + domain.creation_timeout())
            .expect("sweep");
        assert_eq!(old.removed, vec![stuck.clone()]);
        assert_eq!(old.retry_at, None);
        assert!(!stuck.exists(), "the half-made service stays");
        assert!(done.exists(), "a finished service was removed");
        assert!(other.exists(), "another prefix's file was removed");
        let _ = std::fs::remove_dir_all(&root);
    }

    #[test]
    fn wipe_removes_what_the_prefix_owns_and_nothing_else() {
        let root = scratch("wipe");
        let shm = root.join("shm");
        std::fs::create_dir_all(&shm).unwrap();
        let config = iceoryx_config(Some("set-a_"), Some(&root)).expect("config");
        let domain = Domain::of(&config).with_shm_dir(&shm);
        let mine = [
            root.join("services/set-a_x.service"),
            root.join("nodes/set-a_1.node_monitor"),
            root.join("nodes/1/set-a_node.details"),
            root.join("set-a_7.event"),
            shm.join("set-a_hash_1.dynamic"),
        ];
        let theirs = [
            root.join("services/set-b_x.service"),
            root.join("nodes/2/set-b_node.details"),
            shm.join("set-b_hash_1.dynamic"),
        ];
        for path in mine.iter().chain(&theirs) {
            touch(path, 0o600);
        }
        let removed = domain.wipe().expect("wipe");
        assert_eq!(
            removed,
            Removed {
                files: 4,
                shared_memory: 1
            }
        );
        for path in &mine {
            assert!(!path.exists(), "{} stays", path.display());
        }
        assert!(!root.join("nodes/1").exists(), "the node's directory stays");
        for path in &theirs {
            assert!(path.exists(), "{} was removed", path.display());
        }
        assert!(domain.live_nodes().expect("list").is_empty());
        let _ = std::fs::remove_dir_all(&root);
    }
}
