//! The small kit every millinav process shares: run environment, iceoryx2 node and ports with
//! one set of QoS settings, heartbeats, the run clock, the Rerun stream of the run, the service
//! loop and start-up, and configuration errors.

pub mod clock;
pub mod config;
pub mod contract;
pub mod iox_domain;
pub mod ports;
pub mod recording;
pub mod runlog;
pub mod scenario;
pub mod scratch;
pub mod service_loop;
pub mod service_main;
pub mod summary;
pub mod termination;

pub use config::{ConfigContext, ConfigError, EXIT_CONFIG};
pub use service_loop::{ServiceLoop, Wake};
pub use service_main::{service_main, ServiceArgs};

use std::path::PathBuf;
use std::str::FromStr;
use std::time::Duration;

use iceoryx2::prelude::*;
use shm_schemas::ServiceId;

pub use iceoryx2;
pub use rerun;

/// Environment variables by which the supervisor (or a test) configures a process.
pub mod env_vars {
    /// iceoryx2 file prefix; tests set a unique one so runs never see each other.
    pub const IOX_PREFIX: &str = "MILLINAV_IOX_PREFIX";
    /// iceoryx2 root directory for node and service descriptions.
    pub const IOX_ROOT: &str = "MILLINAV_IOX_ROOT";
    /// Directory of this run (recordings, pty link, logs).
    pub const RUN_DIR: &str = "MILLINAV_RUN_DIR";
    /// Rerun recording id shared by all processes of a run.
    pub const RECORDING_ID: &str = "MILLINAV_RECORDING_ID";
    /// Restart count of this process, set by the supervisor (0 on first start).
    pub const INCARNATION: &str = "MILLINAV_INCARNATION";
    /// `1`: a session (`millinav run --session`): control starts disarmed, the twin runs
    /// until the operator or a signal stops the set.
    pub const SESSION: &str = "MILLINAV_SESSION";
    /// `1`: the camera service records the raw stream (`millinav run --record-frames`).
    pub const RECORD_FRAMES: &str = "MILLINAV_RECORD_FRAMES";
    /// `1`: lock the process's memory at start (`mlockall`), set from the launch file.
    pub const LOCK_MEMORY: &str = "MILLINAV_LOCK_MEMORY";
    /// CLOCK_MONOTONIC nanoseconds at run start: the origin of the real-time run clock.
    pub const CLOCK_EPOCH_NS: &str = "MILLINAV_CLOCK_EPOCH_NS";
    /// `off` disables Rerun logging in this process.
    pub const RERUN: &str = "MILLINAV_RERUN";
    /// Optional gRPC URL of a Rerun viewer to stream to as well as the file.
    pub const RERUN_CONNECT: &str = "MILLINAV_RERUN_CONNECT";
}

#[derive(Debug, thiserror::Error)]
pub enum KitError {
    #[error("environment variable {name}={value:?} is invalid: {reason}")]
    BadEnv {
        name: &'static str,
        value: String,
        reason: String,
    },
    #[error("iceoryx2: {0}")]
    Iceoryx(String),
    #[error(
        "service {service}: the peer that created it speaks another contract version or payload \
         type (this process expects {expected:?}, millinav contract v{version}); rebuild or \
         restart every process of the set from the same version",
        version = shm_schemas::CONTRACT_VERSION
    )]
    ContractMismatch { service: String, expected: String },
    #[error("rerun: {0}")]
    Rerun(String),
    #[error("io: {0}")]
    Io(#[from] std::io::Error),
}

/// Maps any iceoryx2 error (they are Debug, not always Display) into a KitError.
pub fn iox<E: std::fmt::Debug>(context: &str) -> impl FnOnce(E) -> KitError + '_ {
    move |e| KitError::Iceoryx(format!("{context}: {e:?}"))
}

/// How this process was started: everything it needs to join the run.
#[derive(Debug, Clone)]
pub struct RunEnv {
    pub iox_prefix: Option<String>,
    pub iox_root: Option<PathBuf>,
    pub run_dir: PathBuf,
    pub recording_id: String,
    pub incarnation: u64,
    pub clock_epoch_ns: u64,
    pub rerun_enabled: bool,
    pub rerun_connect: Option<String>,
}

fn parse_env<T: FromStr>(name: &'static str) -> Result<Option<T>, KitError>
where
    T::Err: std::fmt::Display,
{
    match std::env::var(name) {
        Ok(value) => value
            .trim()
            .parse::<T>()
            .map(Some)
            .map_err(|e| KitError::BadEnv {
                name,
                value,
                reason: e.to_string(),
            }),
        Err(_) => Ok(None),
    }
}

impl RunEnv {
    /// Reads the run environment; every variable has a sensible default for a manual start.
    pub fn from_env() -> Result<Self, KitError> {
        let iox_prefix: Option<String> = parse_env(env_vars::IOX_PREFIX)?;
        if let Some(prefix) = &iox_prefix {
            if let Err(reason) = iox_domain::validate_prefix(prefix) {
                return Err(KitError::BadEnv {
                    name: env_vars::IOX_PREFIX,
                    value: prefix.clone(),
                    reason,
                });
            }
        }
        let run_dir = parse_env::<PathBuf>(env_vars::RUN_DIR)?
            .unwrap_or_else(|| PathBuf::from("runs").join("manual"));
        Ok(Self {
            iox_prefix,
            iox_root: parse_env(env_vars::IOX_ROOT)?,
            run_dir,
            recording_id: parse_env(env_vars::RECORDING_ID)?
                .unwrap_or_else(|| format!("millinav-{}", std::process::id())),
            incarnation: parse_env(env_vars::INCARNATION)?.unwrap_or(0),
            clock_epoch_ns: match parse_env(env_vars::CLOCK_EPOCH_NS)? {
                Some(epoch) => epoch,
                None => clock::monotonic_ns(),
            },
            rerun_enabled: parse_env::<String>(env_vars::RERUN)?
                .map(|v| v != "off" && v != "0")
                .unwrap_or(true),
            rerun_connect: parse_env(env_vars::RERUN_CONNECT)?,
        })
    }

    /// The iceoryx2 config of this run (isolated by prefix and root when they are set).
    pub fn iceoryx_config(&self) -> Result<Config, KitError> {
        iceoryx_config(self.iox_prefix.as_deref(), self.iox_root.as_deref())
    }

    /// Nanoseconds since run start on the shared real-time run clock.
    pub fn run_clock_ns(&self) -> u64 {
        clock::monotonic_ns().saturating_sub(self.clock_epoch_ns)
    }
}

/// Builds an iceoryx2 config with an optional file prefix and root path.
pub fn iceoryx_config(
    prefix: Option<&str>,
    root: Option<&std::path::Path>,
) -> Result<Config, KitError> {
    let mut config = Config::default();
    if let Some(prefix) = prefix {
        config.global.prefix = FileName::new(prefix.as_bytes()).map_err(iox("iceoryx2 prefix"))?;
    }
    if let Some(root) = root {
        std::fs::create_dir_all(root)?;
        let mut text = root.to_string_lossy().into_owned();
        if !text.ends_with('/') {
            text.push('/');
        }
        let path = Path::new(text.as_bytes()).map_err(iox("iceoryx2 root"))?;
        config.global.set_root_path(&path);
    }
    Ok(config)
}

/// Sets up `tracing` to stderr, tagged with the process name.
pub fn init_tracing(service: ServiceId) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_target(false)
        .try_init();
    tracing::debug!(service = service.name(), "tracing ready");
    // iceoryx2 logs through its own logger; keep it to warnings and worse.
    set_log_level_from_env_or(LogLevel::Warn);
}

/// One process of the set: its node, its heartbeat and its Rerun stream.
pub struct Runtime {
    pub service: ServiceId,
    pub env: RunEnv,
    pub node: Node<ipc::Service>,
    pub heartbeat: ports::HeartbeatSender,
    pub rec: rerun::RecordingStream,
}

impl Runtime {
    /// Joins the run: reads the environment, creates the node, heartbeat and recording.
    pub fn start(service: ServiceId) -> Result<Self, KitError> {
        init_tracing(service);
        let env = RunEnv::from_env()?;
        let config = env.iceoryx_config()?;
        let name = format!("{}-{}", service.name(), env.incarnation);
        let node = NodeBuilder::new()
            .name(&NodeName::new(&name).map_err(iox("node name"))?)
            .config(&config)
            .create::<ipc::Service>()
            .map_err(iox("node"))?;
        termination::watch();
        let heartbeat = ports::HeartbeatSender::new(&node, service, env.incarnation)?;
        let rec = recording::open(&env, service)?;
        lock_memory_if_asked();
        tracing::info!(
            service = service.name(),
            incarnation = env.incarnation,
            pid = std::process::id(),
            "started"
        );
        Ok(Self {
            service,
            env,
            node,
            heartbeat,
            rec,
        })
    }

    /// True once SIGINT or SIGTERM has been received.
    pub fn shutdown_requested(&self) -> bool {
        if termination::requested() {
            return true;
        }
        // iceoryx2 forgets a request once it reported it: keep it.
        let requested = self.node.wait(Duration::ZERO).is_err();
        if requested {
            termination::mark_requested();
        }
        requested
    }
}

/// Locks the process's memory when the launch file asked for it (`MILLINAV_LOCK_MEMORY=1`);
/// without the permission (root, CAP_IPC_LOCK or a memlock limit) it runs unlocked and says so.
fn lock_memory_if_asked() {
    if std::env::var(env_vars::LOCK_MEMORY).as_deref() != Ok("1") {
        return;
    }
    use nix::sys::mman::{mlockall, MlockAllFlags};
    match mlockall(MlockAllFlags::MCL_CURRENT | MlockAllFlags::MCL_FUTURE) {
        Ok(()) => tracing::info!("memory locked (mlockall)"),
        Err(e) => tracing::warn!(
            "memory not locked: mlockall failed: {e} (needs root, CAP_IPC_LOCK or `ulimit -l`)"
        ),
    }
}

/// Whether this process runs in a session (`MILLINAV_SESSION=1`).
pub fn in_session() -> bool {
    std::env::var(env_vars::SESSION).as_deref() == Ok("1")
}
