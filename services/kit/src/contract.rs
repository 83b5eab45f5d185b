//! What a receiver does with a payload that breaks the contract (a flag byte other than 0/1, a
//! coil count above `MAX_COILS`): it treats the payload as invalid, counts it, and logs the
//! first occurrence and then every `LOG_EVERY`-th, so a faulty peer cannot flood the log.

use shm_schemas::ContractError;

/// Log the first violation and then every this many.
pub const LOG_EVERY: u64 = 100;

/// Per-receiver count of payloads that broke the contract.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct ContractViolations {
    pub count: u64,
}

impl ContractViolations {
    /// Counts `error` in a payload received on `service`; logs it when due.
    pub fn record(&mut self, service: &str, error: &ContractError) {
        self.count += 1;
        if self.count == 1 || self.count.is_multiple_of(LOG_EVERY) {
            tracing::warn!(
                service,
                violations = self.count,
                "payload breaks the contract, treated as invalid: {error}"
            );
        }
    }

    /// Passes `checked` through, recording its error when it has one.
    pub fn check<T>(
        &mut self,
        service: &str,
        checked: Result<T, ContractError>,
    ) -> Result<T, ContractError> {
        if let Err(e) = &checked {
            self.record(service, e);
        }
        checked
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use shm_schemas::{Flag, Pose};

    #[test]
    fn violations_are_counted_and_passed_through() {
        let mut violations = ContractViolations::default();
        let good = Pose {
            valid: Flag::TRUE,
            ..Default::default()
        };
        assert_eq!(violations.check("pose", good.validity()), Ok(true));
        assert_eq!(violations.count, 0);
        let bad = Pose {
            valid: Flag::from_raw(3),
            ..Default::default()
        };
        assert!(violations.check("pose", bad.validity()).is_err());
        assert!(violations.check("pose", bad.validity()).is_err());
        assert_eq!(violations.count, 2);
    }
}
