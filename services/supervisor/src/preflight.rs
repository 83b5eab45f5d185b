//! Configuration checks before anything starts: every child runs once as
//! `<binary> --check --scenario <file> [args]`, which validates its scenario section and every
//! file it names, and exits 0 (fine) or 78 with the error on stderr. A set with one failing
//! check is not started; each failing child's own message goes to the console.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

/// How long one child may take to check its configuration (it loads the maps it names).
pub const CHECK_TIMEOUT: Duration = Duration::from_secs(60);
/// How often the checks are polled for completion.
const CHECK_POLL: Duration = Duration::from_millis(10);

/// One child to check.
#[derive(Debug, Clone)]
pub struct CheckTarget {
    pub name: String,
    pub executable: PathBuf,
    pub args: Vec<String>,
}

/// A child whose check did not pass.
#[derive(Debug, Clone)]
pub struct CheckFailure {
    pub name: String,
    pub executable: PathBuf,
    /// `exit status: 78`, `did not finish within 60s`, `could not start: …`.
    pub outcome: String,
    /// What the child printed (stdout and stderr), trimmed.
    pub output: String,
}

impl std::fmt::Display for CheckFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({}): {}",
            self.name,
            self.executable.display(),
            self.outcome
        )?;
        for line in self.output.lines() {
            write!(f, "\n    {line}")?;
        }
        Ok(())
    }
}

/// Runs every child's check at once, each writing to `<log_dir>/<name>.check.log`; the
/// failures, in launch order (empty when every check passed).
pub fn check_all(
    targets: &[CheckTarget],
    scenario: &Path,
    log_dir: &Path,
    timeout: Duration,
) -> std::io::Result<Vec<CheckFailure>> {
    std::fs::create_dir_all(log_dir)?;
    let started: Vec<(&CheckTarget, PathBuf, std::io::Result<Child>)> = targets
        .iter()
        .map(|target| {
            let log = log_dir.join(format!("{}.check.log", target.name));
            let child = start_check(target, scenario, &log);
            (target, log, child)
        })
        .collect();
    let deadline = Instant::now() + timeout;
    let mut failures = Vec::new();
    for (target, log, child) in started {
        let outcome = match child {
            Err(e) => Some(format!("could not start: {e}")),
            Ok(child) => match wait_until(child, deadline)? {
                Some(status) if status.success() => None,
                Some(status) => Some(status.to_string()),
                None => Some(format!(
                    "did not finish its configuration check within {timeout:?}"
                )),
            },
        };
        if let Some(outcome) = outcome {
            let output = std::fs::read_to_string(&log).unwrap_or_default();
            failures.push(CheckFailure {
                name: target.name.clone(),
                executable: target.executable.clone(),
                outcome,
                output: output.trim().to_owned(),
            });
        }
    }
    Ok(failures)
}

fn start_check(target: &CheckTarget, scenario: &Path, log: &Path) -> std::io::Result<Child> {
    let out = std::fs::File::create(log)?;
    Command::new(&target.executable)
        .arg("--check")
        .arg("--scenario")
        .arg(scenario)
        .args(&target.args)
        .stdin(Stdio::null())
        .stdout(out.try_clone()?)
        .stderr(out)
        .spawn()
}

/// The child's exit status, or None after killing it at `deadline`.
fn wait_until(mut child: Child, deadline: Instant) -> std::io::Result<Option<ExitStatus>> {
    loop {
        if let Some(status) = child.try_wait()? {
            return Ok(Some(status));
        }
        if Instant::now() >= deadline {
            let _ = child.kill();
            let _ = child.wait();
            return Ok(None);
        }
        std::thread::sleep(CHECK_POLL);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::PermissionsExt;

    fn temp_dir(name: &str) -> millinav_kit::scratch::ScratchDir {
        millinav_kit::scratch::ScratchDir::new(&format!("preflight-{name}")).expect("temp dir")
    }

    /// A fake service: `body` runs as a shell script with the supervisor's arguments.
    fn fake_child(dir: &Path, name: &str, body: &str) -> CheckTarget {
        let path = dir.join(name);
        std::fs::write(&path, format!("#!/bin/sh\n{body}\n")).expect("script");
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755)).expect("chmod");
        CheckTarget {
            name: name.into(),
            executable: path,
            args: vec!["--extra".into()],
        }
    }

    #[test]
    fn passing_checks_give_no_failures_and_see_the_agreed_arguments() {
        let dir = temp_dir("pass");
        let scenario = dir.join("scenario.toml");
        let args_log = dir.join("args");
        let target = fake_child(
            &dir,
            "plant",
            &format!("echo \"$@\" > {}\nexit 0", args_log.display()),
        );
        let failures =
            check_all(&[target], &scenario, &dir.join("logs"), CHECK_TIMEOUT).expect("checks");
        assert!(failures.is_empty(), "{failures:?}");
        let args = std::fs::read_to_string(&args_log).expect("args");
        assert_eq!(
            args.trim(),
            format!("--check --scenario {} --extra", scenario.display())
        );
    }

    #[test]
    fn every_failing_check_is_reported_with_its_own_message() {
        let dir = temp_dir("fail");
        let targets = [
            fake_child(
                &dir,
                "control",
                "echo \"scenario.toml: [control] unknown field controler\" >&2\nexit 78",
            ),
            fake_child(&dir, "flow", "exit 0"),
            fake_child(&dir, "vision", "echo 'model missing' >&2\nexit 3"),
        ];
        let failures = check_all(
            &targets,
            &dir.join("s.toml"),
            &dir.join("logs"),
            CHECK_TIMEOUT,
        )
        .expect("checks");
        let names: Vec<&str> = failures.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, ["control", "vision"]);
        assert!(failures[0].outcome.contains("78"), "{}", failures[0]);
        assert_eq!(
            failures[0].output,
            "scenario.toml: [control] unknown field controler"
        );
        let shown = failures[0].to_string();
        assert!(
            shown.contains("control") && shown.contains("controler"),
            "{shown}"
        );
        assert_eq!(failures[1].output, "model missing");
    }

    #[test]
    fn a_missing_executable_and_a_hung_check_are_failures() {
        let dir = temp_dir("odd");
        let missing = CheckTarget {
            name: "coilbus".into(),
            executable: dir.join("no-such-binary"),
            args: Vec::new(),
        };
        let hung = fake_child(&dir, "flow", "exec sleep 30");
        let failures = check_all(
            &[missing, hung],
            &dir.join("s.toml"),
            &dir.join("logs"),
            Duration::from_millis(300),
        )
        .expect("checks");
        assert_eq!(failures.len(), 2);
        assert!(
            failures[0].outcome.contains("could not start"),
            "{}",
            failures[0]
        );
        assert!(
            failures[1].outcome.contains("did not finish"),
            "{}",
            failures[1]
        );
    }
}
