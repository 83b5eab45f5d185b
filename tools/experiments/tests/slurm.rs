//! Campaigns through a real single-node Slurm cluster made from Debian's packages (`slurm-wlm`,
//! `munge`; `scripts/setup_slurm.sh` installs them): a generated munge key, a `slurm.conf` with
//! this machine's name and CPUs (`proctrack/linuxproc`, `select/cons_tres`, ports of its own),
//! and `munged`, `slurmctld` and `slurmd` started here as root and stopped by PID at the end.
//!
//! It runs a small fast-mode matrix through the Slurm backend, cancels one array task and
//! resumes it, and compares the collected table with the local backend's; then one process-mode
//! cell, killed by Slurm while it runs (no shared memory left, reported as failed by name) and
//! resumed; and the bad inputs that must stop before anything is submitted.
//!
//! Where it cannot be root or Slurm cannot start, it says SKIPPED with the reason; under
//! `CI=true` (where the test command installs Slurm) it fails instead.

mod common;
use common::{short_static_cells, text, without_wall_time};
use std::io::Write as _;
use std::os::unix::fs::PermissionsExt;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

const PARTITION: &str = "mxq";

/// A private Slurm cluster of this machine; its daemons die with it.
struct Cluster {
    dir: PathBuf,
    conf: PathBuf,
    daemons: Vec<(&'static str, Child)>,
}

impl Cluster {
    /// Starts the cluster, or says why it cannot.
    fn start() -> Result<Self, String> {
        // /proc/self belongs to the process's effective user.
        let euid = std::fs::metadata("/proc/self").map(|m| std::os::unix::fs::MetadataExt::uid(&m));
        if euid.ok() != Some(0) {
            return Err("not root: munged, slurmctld and slurmd are started as root".into());
        }
        for program in [
            "munged",
            "slurmctld",
            "slurmd",
            "sbatch",
            "squeue",
            "sinfo",
            "scancel",
        ] {
            let found = ["/usr/sbin", "/usr/bin", "/sbin", "/bin"]
                .iter()
                .any(|d| Path::new(d).join(program).is_file());
            if !found {
                return Err(format!(
                    "{program} is not installed (scripts/setup_slurm.sh installs slurm-wlm and munge)"
                ));
            }
        }
        let id = |flag: &str| -> Result<u32, String> {
            let out = Command::new("id")
                .args([flag, "munge"])
                .output()
                .map_err(|e| e.to_string())?;
            String::from_utf8_lossy(&out.stdout)
                .trim()
                .parse()
                .map_err(|_| "no munge user (install the munge package)".to_string())
        };
        let (uid, gid) = (id("-u")?, id("-g")?);
        let dir = std::env::temp_dir().join(format!("mx-slurm-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut cluster = Cluster {
            conf: dir.join("slurm.conf"),
            dir: dir.clone(),
            daemons: Vec::new(),
        };
        let io = |e: std::io::Error| e.to_string();
        for sub in ["state", "spool", "log", "work"] {
            std::fs::create_dir_all(dir.join(sub)).map_err(io)?;
        }
        std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o755)).map_err(io)?;
        // munged wants its key readable by it alone and its socket folder open to every user.
        let key_dir = dir.join("munge");
        let socket_dir = dir.join("msock");
        for (folder, mode) in [(&key_dir, 0o700), (&socket_dir, 0o755)] {
            std::fs::create_dir_all(folder).map_err(io)?;
            std::os::unix::fs::chown(folder, Some(uid), Some(gid)).map_err(io)?;
            std::fs::set_permissions(folder, std::fs::Permissions::from_mode(mode)).map_err(io)?;
        }
        let key = key_dir.join("munge.key");
        let mut bytes = vec![0u8; 128];
        std::fs::File::open("/dev/urandom")
            .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut bytes))
            .map_err(io)?;
        std::fs::write(&key, &bytes).map_err(io)?;
        std::os::unix::fs::chown(&key, Some(uid), Some(gid)).map_err(io)?;
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o400)).map_err(io)?;
        let socket = socket_dir.join("munge.sock");
        let log = |name: &str| std::fs::File::create(dir.join("log").join(name)).map_err(io);
        let munged = Command::new("munged")
            .arg("--foreground")
            .arg(format!("--socket={}", socket.display()))
            .arg(format!("--key-file={}", key.display()))
            .arg(format!(
                "--pid-file={}",
                key_dir.join("munged.pid").display()
            ))
            .arg(format!(
                "--log-file={}",
                key_dir.join("munged.log").display()
            ))
            .arg(format!("--seed-file={}", key_dir.join("seed").display()))
            .uid(uid)
            .gid(gid)
            .stdin(Stdio::null())
            .stdout(log("munged.out")?)
            .stderr(log("munged.err")?)
            .spawn()
            .map_err(|e| format!("starting munged: {e}"))?;
        cluster.daemons.push(("munged", munged));
        wait_until(Duration::from_secs(10), || socket.exists())
            .map_err(|_| format!("munged did not open its socket: {}", cluster.logs()))?;
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map_err(io)?
            .trim()
            .split('.')
            .next()
            .unwrap_or("localhost")
            .to_owned();
        // The node as slurmd sees it (CPUs, sockets, cores, threads), with little memory claimed.
        let detected = Command::new("slurmd")
            .arg("-C")
            .output()
            .map_err(|e| format!("slurmd -C: {e}"))?;
        let node_line = String::from_utf8_lossy(&detected.stdout)
            .lines()
            .find(|l| l.starts_with("NodeName="))
            .ok_or("slurmd -C printed no NodeName line")?
            .split_whitespace()
            .filter(|f| !f.starts_with("NodeName=") && !f.starts_with("RealMemory="))
            .collect::<Vec<_>>()
            .join(" ");
        let (ctld_port, slurmd_port) = (free_port()?, free_port()?);
        let d = dir.display();
        let conf = format!(
            "ClusterName=millinavtest\n\
             SlurmctldHost={host}(127.0.0.1)\n\
             SlurmctldPort={ctld_port}\nSlurmdPort={slurmd_port}\n\
             SlurmUser=root\nSlurmdUser=root\n\
             AuthType=auth/munge\nCredType=cred/munge\nAuthInfo=socket={socket}\n\
             StateSaveLocation={d}/state\nSlurmdSpoolDir={d}/spool\n\
             SlurmctldPidFile={d}/slurmctld.pid\nSlurmdPidFile={d}/slurmd.pid\n\
             SlurmctldLogFile={d}/log/slurmctld.log\nSlurmdLogFile={d}/log/slurmd.log\n\
             ProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\n\
             SelectType=select/cons_tres\nSelectTypeParameters=CR_Core\n\
             SchedulerType=sched/builtin\nJobCompType=jobcomp/none\n\
             JobAcctGatherType=jobacct_gather/none\nAccountingStorageType=accounting_storage/none\n\
             MpiDefault=none\nReturnToService=2\nKillWait=20\nMinJobAge=600\n\
             NodeName={host} NodeAddr=127.0.0.1 {node_line} RealMemory=1000 State=UNKNOWN\n\
             PartitionName={PARTITION} Nodes={host} Default=YES MaxTime=INFINITE State=UP\n",
            socket = socket.display()
        );
        std::fs::write(&cluster.conf, conf).map_err(io)?;
        for (name, program) in [("slurmctld", "slurmctld"), ("slurmd", "slurmd")] {
            let mut command = Command::new(program);
            command.arg("-D").arg("-f").arg(&cluster.conf);
            if name == "slurmctld" {
                command.arg("-i");
            }
            let child = command
                .env("SLURM_CONF", &cluster.conf)
                .stdin(Stdio::null())
                .stdout(log(&format!("{name}.out"))?)
                .stderr(log(&format!("{name}.err"))?)
                .spawn()
                .map_err(|e| format!("starting {name}: {e}"))?;
            cluster.daemons.push((name, child));
        }
        wait_until(Duration::from_secs(60), || {
            cluster
                .slurm("sinfo", &["-h", "-o", "%t"])
                .map(|o| String::from_utf8_lossy(&o.stdout).trim() == "idle")
                .unwrap_or(false)
        })
        .map_err(|_| format!("the node never became idle: {}", cluster.logs()))?;
        Ok(cluster)
    }

    fn slurm(&self, program: &str, args: &[&str]) -> std::io::Result<Output> {
        Command::new(program)
            .args(args)
            .env("SLURM_CONF", &self.conf)
            .output()
    }

    fn logs(&self) -> String {
        let mut text = String::new();
        for name in [
            "munged.err",
            "slurmctld.err",
            "slurmd.err",
            "slurmctld.log",
            "slurmd.log",
        ] {
            if let Ok(log) = std::fs::read_to_string(self.dir.join("log").join(name)) {
                let tail: Vec<&str> = log.lines().rev().take(8).collect();
                text += &format!(
                    "\n--- {name}:\n{}",
                    tail.into_iter().rev().collect::<Vec<_>>().join("\n")
                );
            }
        }
        text
    }

    /// `experiments` with this cluster's configuration, from the repository root.
    fn experiments(&self, args: &[&str]) -> Output {
        Command::new(env!("CARGO_BIN_EXE_experiments"))
            .current_dir(fieldmaps::data_root())
            .env("SLURM_CONF", &self.conf)
            .args(args)
            .stdin(Stdio::null())
            .output()
            .expect("experiments runs")
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        let _ = self.slurm("scancel", &["--me"]);
        // slurmd and slurmctld first, munged last; each by its PID.
        for (_, child) in self.daemons.iter_mut().rev() {
            let pid = nix::unistd::Pid::from_raw(child.id() as i32);
            let _ = nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM);
            let deadline = Instant::now() + Duration::from_secs(10);
            while Instant::now() < deadline && matches!(child.try_wait(), Ok(None)) {
                std::thread::sleep(Duration::from_millis(50));
            }
            let _ = child.kill();
            let _ = child.wait();
        }
        if std::thread::panicking() {
            eprintln!(
                "Slurm test directory kept: {}{}",
                self.dir.display(),
                self.logs()
            );
        } else {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

fn free_port() -> Result<u16, String> {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .map_err(|e| format!("no free port: {e}"))
}

fn wait_until(limit: Duration, mut ready: impl FnMut() -> bool) -> Result<(), ()> {
    let deadline = Instant::now() + limit;
    while Instant::now() < deadline {
        if ready() {
            return Ok(());
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    Err(())
}

/// The job id `experiments --backend slurm` printed.
fn job_id(output: &Output) -> String {
    let stdout = String::from_utf8_lossy(&output.stdout);
    stdout
        .split_whitespace()
        .skip_while(|w| *w != "job")
        .nth(1)
        .unwrap_or_else(|| panic!("no job id in {}", text(output)))
        .to_owned()
}

/// Shared-memory files and iceoryx2 roots of a campaign (its tag is "mx" + 8 hex digits of the
/// matrix hash).
fn iox_leftovers(out: &Path) -> Vec<String> {
    let manifest = std::fs::read_to_string(out.join("campaign/manifest.toml")).expect("manifest");
    let hash = manifest
        .lines()
        .find_map(|l| l.strip_prefix("matrix_sha256 = \""))
        .expect("matrix hash");
    let tag = format!("mx{}", &hash[..8]);
    [PathBuf::from("/dev/shm"), std::env::temp_dir()]
        .iter()
        .flat_map(|d| std::fs::read_dir(d).into_iter().flatten().flatten())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(&tag))
        .collect()
}

/// Cancels array task `task` (`<job>_<n>`), waits for the campaign in `out` to leave the queue,
/// and returns `status`'s output (which must exit 1: a cell failed) and its report.
fn cancel_and_wait(cluster: &Cluster, task: &str, out: &str) -> (Output, String) {
    let cancelled = cluster.slurm("scancel", &[task]).expect("scancel");
    assert!(cancelled.status.success());
    let status = cluster.experiments(&["status", out, "--wait"]);
    assert_eq!(status.status.code(), Some(1), "{}", text(&status));
    let report = String::from_utf8_lossy(&status.stderr).into_owned();
    (status, report)
}

#[test]
fn campaigns_run_through_a_single_node_slurm_cluster() {
    let cluster = match Cluster::start() {
        Ok(cluster) => cluster,
        Err(reason) => {
            if std::env::var("CI").is_ok_and(|v| v == "true") {
                panic!("the Slurm test cannot run under CI: {reason}");
            }
            let mut err = std::io::stderr();
            let _ = writeln!(
                err,
                "SKIPPED campaigns_run_through_a_single_node_slurm_cluster: {reason}"
            );
            return;
        }
    };
    let work = cluster.dir.join("work");
    let out = |name: &str| work.join(name).to_string_lossy().into_owned();
    let fast = [&short_static_cells("pid,mpc", "2")[..], &["--no-rrd"]].concat();

    // The local backend: the reference table.
    let local = cluster.experiments(&[&fast[..], &["--out", &out("local")]].concat());
    assert!(local.status.success(), "{}", text(&local));

    // Bad input stops before anything is submitted.
    let no_partition = cluster.experiments(
        &[
            &fast[..],
            &[
                "--out",
                &out("bad"),
                "--backend",
                "slurm",
                "--partition",
                "nosuch",
            ],
        ]
        .concat(),
    );
    assert!(!no_partition.status.success());
    let stderr = String::from_utf8_lossy(&no_partition.stderr);
    assert!(
        stderr.contains("nosuch")
            && stderr.contains("does not exist")
            && stderr.contains(PARTITION),
        "{}",
        text(&no_partition)
    );
    assert!(
        !work.join("bad/campaign").exists(),
        "planned although refused"
    );
    let other_matrix = cluster.experiments(
        &[
            &short_static_cells("pid", "1")[..],
            &["--no-rrd", "--out", &out("local"), "--backend", "slurm"],
        ]
        .concat(),
    );
    assert!(!other_matrix.status.success());
    assert!(
        String::from_utf8_lossy(&other_matrix.stderr).contains("another matrix"),
        "{}",
        text(&other_matrix)
    );
    let queue = cluster.slurm("squeue", &["-h"]).expect("squeue");
    assert!(queue.stdout.is_empty(), "a refused submission queued a job");

    // The same matrix as a job array, one task at a time; the last task is cancelled while
    // it waits, so it never runs.
    let submitted = cluster.experiments(
        &[
            &fast[..],
            &[
                "--out",
                &out("slurm"),
                "--backend",
                "slurm",
                "--partition",
                PARTITION,
                "--max-parallel",
                "1",
                "--poll-s",
                "0.5",
                "--no-wait",
            ],
        ]
        .concat(),
    );
    assert!(submitted.status.success(), "{}", text(&submitted));
    let job = job_id(&submitted);
    let (status, report) = cancel_and_wait(&cluster, &format!("{job}_3"), &out("slurm"));
    // Slurm keeps no record of an array task cancelled before it started (no accounting here).
    assert!(
        report.contains(&format!(
            "20cp_static_mpc_s2: array task {job}_3 left the queue without starting"
        )),
        "{}",
        text(&status)
    );
    assert!(
        report.contains("3 done") && report.contains("1 failed"),
        "{}",
        text(&status)
    );
    let early = cluster.experiments(&["collect", &out("slurm")]);
    assert!(!early.status.success());
    assert!(String::from_utf8_lossy(&early.stderr).contains("20cp_static_mpc_s2"));
    let resumed = cluster.experiments(&["resume", &out("slurm")]);
    assert!(resumed.status.success(), "{}", text(&resumed));
    assert!(
        String::from_utf8_lossy(&resumed.stdout).contains("20cp_static_mpc_s2"),
        "resume names what it runs again: {}",
        text(&resumed)
    );
    let read = |dir: &str, file: &str| {
        std::fs::read_to_string(work.join(dir).join(file))
            .unwrap_or_else(|e| panic!("{dir}/{file}: {e}"))
    };
    assert_eq!(read("slurm", "table.md"), read("local", "table.md"));
    assert_eq!(
        without_wall_time(&read("slurm", "results.csv")),
        without_wall_time(&read("local", "results.csv"))
    );
    // A result file carries the cell's metrics, its scenario and the build's content hash.
    let result = read("slurm", "campaign/results/20cp_static_pid_s1.toml");
    for key in [
        "build_sha256 = ",
        "scenario = ",
        "[metrics]",
        "rmse_mm = ",
        "slurm_task = ",
    ] {
        assert!(result.contains(key), "{key} missing in {result}");
    }

    // One process-mode cell, killed by Slurm while the set runs, then resumed.
    let submitted = cluster.experiments(
        &[
            &short_static_cells("pid", "1")[..],
            &[
                "--mode",
                "process",
                "--out",
                &out("process"),
                "--backend",
                "slurm",
                "--no-wait",
                "--poll-s",
                "0.5",
            ],
        ]
        .concat(),
    );
    assert!(submitted.status.success(), "{}", text(&submitted));
    let job = job_id(&submitted);
    let truth = work.join("process/runs/20cp_static_pid_s1/run/truth.csv");
    wait_until(Duration::from_secs(180), || {
        std::fs::read_to_string(&truth).is_ok_and(|t| t.lines().count() > 100)
    })
    .unwrap_or_else(|()| panic!("the process-mode cell never got going: {}", cluster.logs()));
    assert!(
        !iox_leftovers(&work.join("process")).is_empty(),
        "the running set has no shared memory?"
    );
    let (status, report) = cancel_and_wait(&cluster, &format!("{job}_0"), &out("process"));
    assert!(
        report.contains("20cp_static_pid_s1") && report.contains("SIGTERM"),
        "{}",
        text(&status)
    );
    assert!(!work
        .join("process/campaign/results/20cp_static_pid_s1.toml")
        .exists());
    let leftovers = iox_leftovers(&work.join("process"));
    assert!(leftovers.is_empty(), "the killed task left {leftovers:?}");
    let resumed = cluster.experiments(&["resume", &out("process")]);
    assert!(resumed.status.success(), "{}", text(&resumed));
    let table = read("process", "table.md");
    assert!(
        table.contains("| 20 cP, static | pid | 1 | 1/1 |"),
        "{table}"
    );
    assert!(work
        .join("process/campaign/results/20cp_static_pid_s1.toml")
        .is_file());
    assert!(iox_leftovers(&work.join("process")).is_empty());
}
