//! The `millinav` front door's tool commands: each hands its arguments to one of the workspace's
//! tool executables, which sit next to `millinav` in the build (or install) directory, the way
//! `git` hands `git foo` to `git-foo`. The tool runs in this process (exec), so its output,
//! its exit code and its `--help` are the user's; its usage line reads `millinav <command>`.

use std::ffi::OsString;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};

/// A tool command of the front door: the words after `millinav` and the executable they run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tool {
    /// What the user types after `millinav` (`"maps"`, `"vision eval"`).
    pub words: &'static str,
    /// The executable next to `millinav`.
    pub executable: &'static str,
    /// Arguments put before the user's (a subcommand of the executable).
    pub leading: &'static [&'static str],
}

/// Every tool command, as `millinav --help` and the docs name them.
pub const TOOLS: &[Tool] = &[
    Tool {
        words: "maps",
        executable: "fieldgen",
        leading: &[],
    },
    Tool {
        words: "rig check",
        executable: "fieldgen",
        leading: &["rig-check"],
    },
    Tool {
        words: "calib",
        executable: "calib",
        leading: &[],
    },
    Tool {
        words: "plan",
        executable: "planner",
        leading: &[],
    },
    Tool {
        words: "vision dataset",
        executable: "unet-dataset",
        leading: &[],
    },
    Tool {
        words: "vision import-labels",
        executable: "unet-import",
        leading: &[],
    },
    Tool {
        words: "vision eval",
        executable: "vision-eval",
        leading: &[],
    },
    Tool {
        words: "vision appearance",
        executable: "vision-calibrate",
        leading: &[],
    },
    Tool {
        words: "experiments",
        executable: "experiments",
        leading: &[],
    },
    Tool {
        words: "bench",
        executable: "bench",
        leading: &[],
    },
];

/// Why a tool command could not start.
#[derive(Debug, thiserror::Error)]
pub enum FrontDoorError {
    #[error(
        "`millinav {words}` runs `{}`, which is not there: build the workspace \
         (`cargo build --release --workspace`, or ./scripts/run.sh) and run the `millinav` of \
         its target directory, or install the tools next to `millinav`",
        .path.display()
    )]
    Missing { words: &'static str, path: PathBuf },
    #[error("`millinav {words}` could not start `{}`: {source}", .path.display())]
    Exec {
        words: &'static str,
        path: PathBuf,
        source: std::io::Error,
    },
}

impl Tool {
    /// The tool for `words`, a command of [`TOOLS`].
    pub fn named(words: &str) -> Option<&'static Tool> {
        TOOLS.iter().find(|t| t.words == words)
    }

    /// The executable in `bin_dir`.
    pub fn path_in(&self, bin_dir: &Path) -> PathBuf {
        bin_dir.join(self.executable)
    }

    /// The command that runs the tool with the user's `args`, its program name (`argv[0]`)
    /// `millinav <words>` so that its usage and errors name what the user typed.
    pub fn command(
        &self,
        bin_dir: &Path,
        args: &[OsString],
    ) -> Result<std::process::Command, FrontDoorError> {
        let path = self.path_in(bin_dir);
        if !path.is_file() {
            return Err(FrontDoorError::Missing {
                words: self.words,
                path,
            });
        }
        let mut command = std::process::Command::new(&path);
        command
            .arg0(format!("millinav {}", self.words))
            .args(self.leading)
            .args(args);
        Ok(command)
    }

    /// Replaces this process with the tool; returns only when it could not start.
    pub fn exec(&self, bin_dir: &Path, args: &[OsString]) -> FrontDoorError {
        match self.command(bin_dir, args) {
            Ok(mut command) => FrontDoorError::Exec {
                words: self.words,
                path: self.path_in(bin_dir),
                source: command.exec(),
            },
            Err(e) => e,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_command_is_named_once_and_found_by_its_words() {
        for tool in TOOLS {
            assert_eq!(Tool::named(tool.words), Some(tool));
        }
        let mut words: Vec<_> = TOOLS.iter().map(|t| t.words).collect();
        words.sort_unstable();
        words.dedup();
        assert_eq!(words.len(), TOOLS.len());
        assert_eq!(Tool::named("fly"), None);
    }

    #[test]
    fn a_missing_executable_is_named_with_what_to_do() {
        let dir = std::env::temp_dir().join(format!("front-door-{}", std::process::id()));
        let error = Tool::named("vision eval")
            .expect("vision eval")
            .command(&dir, &[])
            .expect_err("nothing there");
        let text = error.to_string();
        assert!(text.contains("millinav vision eval"), "{text}");
        assert!(
            text.contains(&dir.join("vision-eval").display().to_string()),
            "{text}"
        );
        assert!(text.contains("cargo build --release --workspace"), "{text}");
    }

    #[test]
    fn the_tool_gets_its_subcommand_then_the_users_arguments() {
        let dir = std::env::temp_dir().join(format!("front-door-args-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        std::fs::write(dir.join("fieldgen"), b"").expect("stand-in");
        let command = Tool::named("rig check")
            .expect("rig check")
            .command(&dir, &["--rig".into(), "r.toml".into()])
            .expect("command");
        let args: Vec<_> = command.get_args().collect();
        assert_eq!(args, ["rig-check", "--rig", "r.toml"]);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
