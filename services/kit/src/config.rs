//! Configuration errors: a scenario table or a file it names that a service cannot run with.
//! They are told apart from run-time failures so that the supervisor can stop the set at once
//! (a restart cannot fix a typo) and print the error instead of restarting with backoff.

use std::fmt::Display;

/// Exit status of a service whose configuration is bad (`EX_CONFIG` of BSD `sysexits.h`),
/// both for `--check` and at run time.
pub const EXIT_CONFIG: u8 = 78;

/// A configuration the service cannot run with. The message names the file and the field.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message}")]
pub struct ConfigError {
    message: String,
}

impl ConfigError {
    pub fn new(message: impl Into<String>) -> Self {
        Self {
            message: message.into(),
        }
    }

    pub fn message(&self) -> &str {
        &self.message
    }
}

/// Marks the error of a configuration step as a `ConfigError`, with what was being configured
/// (e.g. "scenario s.toml: [flow] map") in front of the cause.
pub trait ConfigContext<T> {
    fn config_context(self, what: impl Display) -> Result<T, ConfigError>;
}

impl<T, E: Display> ConfigContext<T> for Result<T, E> {
    fn config_context(self, what: impl Display) -> Result<T, ConfigError> {
        // `{:#}` prints an anyhow error's whole chain; other errors ignore the flag.
        self.map_err(|e| ConfigError::new(format!("{what}: {e:#}")))
    }
}

/// True when `error` (or any error in its chain) is a configuration error.
pub fn is_config_error(error: &anyhow::Error) -> bool {
    error.chain().any(|cause| cause.is::<ConfigError>())
}

#[cfg(test)]
mod tests {
    use super::*;
    use anyhow::Context;

    #[test]
    fn config_errors_are_found_through_context() {
        let bad: Result<(), ConfigError> = Err(ConfigError::new("[control] controler: unknown"));
        let wrapped = bad.context("starting control").unwrap_err();
        assert!(is_config_error(&wrapped));
        assert!(format!("{wrapped:#}").contains("[control] controler"));

        let io = std::fs::read("/nonexistent/millinav").context("reading");
        assert!(!is_config_error(&io.unwrap_err()));
    }

    #[test]
    fn context_names_what_was_configured() {
        let failed: Result<(), String> = Err("line 3: not a number".into());
        let error = failed
            .config_context("scenario s.toml: [flow] map m.txt")
            .unwrap_err();
        assert_eq!(
            error.message(),
            "scenario s.toml: [flow] map m.txt: line 3: not a number"
        );
    }
}
