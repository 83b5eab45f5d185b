//! Start-up shared by every service binary: read the scenario, validate this service's table
//! and the files it names, then (unless `--check`) join the run and hand over to the service.

use std::path::PathBuf;
use std::process::ExitCode;

use shm_schemas::ServiceId;

use crate::config::{is_config_error, ConfigError, EXIT_CONFIG};
use crate::scenario::Scenario;
use crate::Runtime;

/// Command line every service binary takes.
#[derive(Debug, Clone, clap::Args)]
pub struct ServiceArgs {
    /// Scenario TOML file: the run, fluid and trajectory, plus this service's table.
    #[arg(long)]
    pub scenario: PathBuf,
    /// Only validate this service's scenario table and every file it names, starting nothing:
    /// exit 0 when it is fine, else print the error and exit 78 (EX_CONFIG).
    #[arg(long)]
    pub check: bool,
}

/// Runs one service process: loads the scenario, calls `prepare` (validation and loading of
/// everything the configuration names; its error is a configuration error), then, unless
/// `--check`, starts the runtime (iceoryx2 node, heartbeat, Rerun stream), calls `run` with what
/// `prepare` made, and flushes the recording. Returns 0, `EXIT_CONFIG` for a configuration error
/// (at check or at run time), or 1 for any other failure; the error goes to stderr.
pub fn service_main<S>(
    service: ServiceId,
    args: &ServiceArgs,
    prepare: impl FnOnce(&Scenario) -> Result<S, ConfigError>,
    run: impl FnOnce(&mut Runtime, &Scenario, S) -> anyhow::Result<()>,
) -> ExitCode {
    let prepared = Scenario::load(&args.scenario)
        .map_err(ConfigError::from)
        .and_then(|scenario| prepare(&scenario).map(|setup| (scenario, setup)));
    let (scenario, setup) = match prepared {
        Ok(prepared) => prepared,
        Err(error) => return failure(service, &anyhow::Error::new(error)),
    };
    if args.check {
        return ExitCode::SUCCESS;
    }
    let mut rt = match Runtime::start(service) {
        Ok(rt) => rt,
        Err(error) => return failure(service, &anyhow::Error::new(error)),
    };
    let result = run(&mut rt, &scenario, setup);
    let _ = rt.rec.flush_blocking();
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => failure(service, &error),
    }
}

/// Exit status for a service's failure: `EXIT_CONFIG` for a configuration error, else 1.
pub fn exit_status_of(error: &anyhow::Error) -> u8 {
    if is_config_error(error) {
        EXIT_CONFIG
    } else {
        1
    }
}

fn failure(service: ServiceId, error: &anyhow::Error) -> ExitCode {
    let status = exit_status_of(error);
    let kind = if status == EXIT_CONFIG {
        "configuration error"
    } else {
        "error"
    };
    eprintln!("millinav-{}: {kind}: {error:#}", service.name());
    ExitCode::from(status)
}

/// A service's whole `main.rs`: its command line (the kit's [`ServiceArgs`], its doc comment as
/// the `--help` text) and a `main` that hands the library's `prepare` and `run` to
/// [`service_main`]. The calling crate depends on `clap` and `shm_schemas`.
///
/// ```text
/// millinav_kit::service_binary! {
///     /// Localizes the capsule in camera frames and publishes its Pose.
///     name: "millinav-vision",
///     service: Vision,
///     library: millinav_vision,
/// }
/// ```
#[macro_export]
macro_rules! service_binary {
    (
        $(#[doc = $doc:expr])*
        name: $name:literal,
        service: $service:ident,
        library: $library:ident
        $(, after_help: $after_help:expr)?
        $(,)?
    ) => {
        $(#[doc = $doc])*
        #[derive(clap::Parser)]
        #[command(name = $name, version $(, after_help = $after_help)?)]
        struct Args {
            #[command(flatten)]
            service: $crate::ServiceArgs,
        }

        fn main() -> ::std::process::ExitCode {
            let args = <Args as clap::Parser>::parse();
            $crate::service_main(
                ::shm_schemas::ServiceId::$service,
                &args.service,
                $library::prepare,
                $library::run,
            )
        }
    };
}
