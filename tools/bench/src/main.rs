//! `bench`: runs the millinav benchmark suite and prints one Markdown table (median and p99 per
//! measurement, ratios measured in the same run, pass/fail against the project's targets).

use millinav_bench::workload::Workload;
use std::path::PathBuf;

use anyhow::Context;
use clap::{Parser, Subcommand};
use millinav_bench::stats::{markdown, time_each, Row, RowValue, Stats};
use millinav_bench::{control, e2e, ipc, vision};
use millinav_control::controllers::ControllerKind;

#[derive(Parser, Debug)]
#[command(
    name = "bench",
    about = "millinav benchmark suite: IPC (iceoryx2 vs Unix socket), vision (UNet ROI, classical \
             full frame and ROI), control (PID, SMC-DOB, MPC, allocation) and end to end through \
             the real process set in real-time mode. Prints a Markdown table of median and p99."
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Cmd>,
    /// Iterations per micro-benchmark (control, allocation) and per Pose IPC measurement.
    #[arg(long, default_value_t = 5000)]
    iters: usize,
    /// Iterations per vision measurement and per Frame IPC measurement.
    #[arg(long, default_value_t = 1000)]
    frame_iters: usize,
    /// Real-time seconds of the end-to-end run (the first second is start-up and not counted).
    #[arg(long, default_value_t = 12.0)]
    e2e_seconds: f64,
    /// Skip groups: any of ipc, vision, control, e2e.
    #[arg(long, value_delimiter = ',')]
    skip: Vec<String>,
    /// Scratch directory (sockets, iceoryx2 root, the end-to-end run); default a fresh one in /tmp.
    #[arg(long)]
    work_dir: Option<PathBuf>,
    /// Also time the experiments tool at the paper's 10 Hz loop and at 100 Hz: the full matrix
    /// in fast mode (`--trials 3 --beyond`, ≈ 2 and ≈ 5 minutes) and one full-length cell
    /// through the process set (≈ 20 s and ≈ 3 minutes), from which the process-set matrix is
    /// extrapolated.
    #[arg(long)]
    experiments: bool,
    /// With --experiments: run the whole process-set matrix at 10 Hz (≈ 35 minutes) instead of
    /// extrapolating it from one cell.
    #[arg(long, requires = "experiments")]
    experiments_process_matrix: bool,
    /// The scenario the workloads run on (its rig, trajectory, fluid and frame period); the
    /// end-to-end rows run its real-time variant. Relative paths from the workspace root.
    #[arg(long, default_value = "scenarios/short.toml")]
    scenario: PathBuf,
    /// Directory holding the `millinav` process-set binaries; default: next to this executable.
    #[arg(long)]
    bin_dir: Option<PathBuf>,
}

#[derive(Subcommand, Debug)]
enum Cmd {
    /// Internal: the receiving process of an IPC measurement (spawned by `bench` itself).
    #[command(hide = true)]
    IpcChild {
        #[arg(long, value_enum)]
        transport: ipc::Transport,
        #[arg(long, value_enum)]
        message: ipc::Message,
        #[arg(long)]
        iox_prefix: String,
        #[arg(long)]
        iox_root: PathBuf,
        #[arg(long)]
        socket: PathBuf,
        #[arg(long)]
        frame_width: u32,
        #[arg(long)]
        frame_height: u32,
    },
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    if let Some(Cmd::IpcChild {
        transport,
        message,
        iox_prefix,
        iox_root,
        socket,
        frame_width,
        frame_height,
    }) = cli.command
    {
        let rv = ipc::Rendezvous {
            iox_prefix,
            iox_root,
            socket,
            frame: ipc::FrameShape {
                width: frame_width,
                height: frame_height,
            },
        };
        return Ok(ipc::child(&rv, transport, message)?);
    }
    millinav_kit::iceoryx2::prelude::set_log_level(
        millinav_kit::iceoryx2::prelude::LogLevel::Error,
    );
    let work = match &cli.work_dir {
        Some(d) => d.clone(),
        None => std::env::temp_dir().join(format!("millinav-bench-{}", std::process::id())),
    };
    std::fs::create_dir_all(&work)?;
    let exe = std::env::current_exe()?;
    let bin_dir = match &cli.bin_dir {
        Some(d) => d.clone(),
        None => exe
            .parent()
            .context("executable has no directory")?
            .to_owned(),
    };
    let skip = |g: &str| cli.skip.iter().any(|s| s == g);
    let mut rows = Vec::new();
    let workload = millinav_bench::workload::Workload::load(&cli.scenario)?;
    let scene = vision::Scene::render(0, &workload)?;

    if !skip("ipc") {
        eprintln!("ipc ...");
        rows.extend(ipc_rows(&cli, &exe, &work, &scene)?);
    }
    if !skip("vision") {
        eprintln!("vision ...");
        rows.extend(vision_rows(&cli, &scene)?);
    }
    if !skip("control") {
        eprintln!("control ...");
        rows.extend(control_rows(&cli, &workload)?);
    }
    if !skip("e2e") {
        eprintln!("end to end ({} s real time) ...", cli.e2e_seconds);
        rows.extend(e2e_rows(&bin_dir, &cli.scenario, &work, cli.e2e_seconds));
    }
    rows.extend(experiments_rows(&cli, &workload, &bin_dir, &work));
    println!("{}", markdown(&rows));
    if cli.work_dir.is_none() {
        let _ = std::fs::remove_dir_all(&work);
    }
    Ok(())
}

fn ratio_row(what: String, slow: &[f64], fast: &[f64], target: Option<f64>) -> Row {
    let (s, f) = (Stats::of(slow), Stats::of(fast));
    let (med, p99) = match (s, f) {
        (Some(s), Some(f)) => (s.median_ns / f.median_ns, s.p99_ns / f.p99_ns),
        _ => (f64::NAN, f64::NAN),
    };
    let row = Row {
        area: "IPC",
        what,
        value: RowValue::Number {
            median: med,
            p99,
            unit: "x",
            n: slow.len().min(fast.len()),
        },
        target: String::new(),
        verdict: millinav_bench::stats::Verdict::Info,
    };
    match target {
        Some(t) => row.target(format!("≥ {t:.0}x"), med >= t && p99 >= t),
        None => row,
    }
}

fn ipc_rows(
    cli: &Cli,
    exe: &std::path::Path,
    work: &std::path::Path,
    scene: &vision::Scene,
) -> anyhow::Result<Vec<Row>> {
    use ipc::{measure, Message, Placement, Transport};
    let frame = ipc::FrameShape {
        width: u32::try_from(scene.width)?,
        height: u32::try_from(scene.height)?,
    };
    let mb = format!("{:.1} MB", frame.bytes() as f64 / 1e6);
    let n_frame = cli.frame_iters as u64;
    let n_pose = cli.iters as u64;
    let m = |t, msg, n, placement| {
        let sent = ipc::Frame {
            pixels: &scene.rgb,
            shape: frame,
        };
        measure(exe, work, t, msg, n, sent, placement)
            .with_context(|| format!("IPC {t:?} {msg:?} {placement:?}"))
    };
    let p99_under = |v: &[f64], ns: f64| Stats::of(v).is_some_and(|s| s.p99_ns < ns);
    // Where an iceoryx2 latency goes, phase by phase (medians and p99s do not add up exactly).
    let phases = |label: &str, m: &ipc::Measured| {
        [
            (
                "sender: stamp → `send` returned (loan, write, publish, notify)",
                &m.send_ns,
            ),
            (
                "`send` returned → receiver awake (kernel wake-up of the blocked listener)",
                &m.wake_ns,
            ),
            ("receiver awake → sample in hand (`latest`)", &m.take_ns),
        ]
        .map(|(what, v)| Row::time("IPC", format!("{label}, {what}"), Stats::of(v)))
    };
    let pose_bytes = std::mem::size_of::<shm_schemas::Pose>();
    let mut rows = Vec::new();
    for placement in [Placement::Free, Placement::OneCore] {
        let (tag, suffix) = match placement {
            Placement::Free => ("", ""),
            Placement::OneCore => ("one core: ", " (both processes on one core)"),
        };
        let loan = m(Transport::Iceoryx2, Message::FrameLoan, n_frame, placement)?;
        let kit = m(Transport::Iceoryx2, Message::Frame, n_frame, placement)?;
        let uds = m(Transport::Uds, Message::Frame, n_frame, placement)?.latency_ns;
        let pose_iox = m(Transport::Iceoryx2, Message::Pose, n_pose, placement)?;
        let pose_uds = m(Transport::Uds, Message::Pose, n_pose, placement)?.latency_ns;
        rows.push(
            Row::time(
                "IPC",
                format!("{tag}Frame {mb}, iceoryx2 zero-copy (loan, write in place, send){suffix}"),
                Stats::of(&loan.latency_ns),
            )
            .target("p99 < 50 µs", p99_under(&loan.latency_ns, 50e3)),
        );
        rows.extend(phases(&format!("  {tag}zero-copy Frame"), &loan));
        rows.extend([
            Row::time(
                "IPC",
                format!("{tag}Frame {mb}, iceoryx2 kit `FrameOutbox::send` (memcpy into shm)"),
                Stats::of(&kit.latency_ns),
            )
            .target("p99 < 50 µs", p99_under(&kit.latency_ns, 50e3)),
            Row::time(
                "IPC",
                format!("{tag}Frame {mb}, Unix domain socket (write + read)"),
                Stats::of(&uds),
            ),
            ratio_row(
                format!("{tag}Frame: socket / iceoryx2 zero-copy"),
                &uds,
                &loan.latency_ns,
                Some(20.0),
            ),
            ratio_row(
                format!("{tag}Frame: socket / iceoryx2 kit send"),
                &uds,
                &kit.latency_ns,
                Some(20.0),
            ),
            Row::time(
                "IPC",
                format!("{tag}Pose {pose_bytes} B, iceoryx2 kit `Outbox`/`Inbox`"),
                Stats::of(&pose_iox.latency_ns),
            ),
        ]);
        rows.extend(phases(&format!("  {tag}Pose"), &pose_iox));
        rows.extend([
            Row::time(
                "IPC",
                format!("{tag}Pose {pose_bytes} B, Unix domain socket"),
                Stats::of(&pose_uds),
            ),
            ratio_row(
                format!("{tag}Pose: socket / iceoryx2"),
                &pose_uds,
                &pose_iox.latency_ns,
                None,
            ),
        ]);
    }
    Ok(rows)
}

fn vision_rows(cli: &Cli, scene: &vision::Scene) -> anyhow::Result<Vec<Row>> {
    let n = cli.frame_iters;
    let classical = vision::classical(scene);
    let mut rows = Vec::new();
    let full = scene.full();
    let roi = scene.roi(20.0);
    let found = |rect| {
        classical
            .localize(
                &scene.rgb,
                scene.width as i32,
                scene.height as i32,
                rect,
                scene.mm_per_px,
            )
            .is_ok()
    };
    let (found_full, found_roi) = (found(full), found(roi));
    match vision::unet(scene) {
        Ok(mut unet) => {
            let found_unet = unet
                .localize(&scene.rgb, scene.width, scene.height, scene.centroid_px)
                .is_ok();
            let infer_only = {
                let crop = vec![128u8; 96 * 96 * 3];
                time_each(20, n, |_| {
                    let _ = std::hint::black_box(unet.infer(&crop));
                })
            };
            let localize = time_each(20, n, |_| {
                let _ = std::hint::black_box(unet.localize(
                    &scene.rgb,
                    scene.width,
                    scene.height,
                    scene.centroid_px,
                ));
            });
            rows.push(Row::time(
                "vision",
                "UNet ROI: ONNX Runtime `infer` (96x96, 1 thread)",
                Stats::of(&infer_only),
            ));
            let p99 = Stats::of(&localize).map_or(f64::INFINITY, |s| s.p99_ns);
            rows.push(
                Row::time(
                    "vision",
                    format!(
                        "UNet ROI `localize` (crop + infer + keypoints){}",
                        if found_unet {
                            ""
                        } else {
                            " — capsule NOT found"
                        }
                    ),
                    Stats::of(&localize),
                )
                .target("p99 < 10 ms (100 Hz budget)", p99 < 10e6),
            );
        }
        Err(e) => rows.push(Row::text(
            "vision",
            "UNet ROI",
            format!("not measured: {e}"),
        )),
    }
    let t_full = time_each(5, n.min(300), |_| {
        let _ = std::hint::black_box(classical.localize(
            &scene.rgb,
            scene.width as i32,
            scene.height as i32,
            full,
            scene.mm_per_px,
        ));
    });
    let t_roi = time_each(20, n, |_| {
        let _ = std::hint::black_box(classical.localize(
            &scene.rgb,
            scene.width as i32,
            scene.height as i32,
            roi,
            scene.mm_per_px,
        ));
    });
    let note = |ok: bool| if ok { "" } else { " — capsule NOT found" };
    rows.push(Row::time(
        "vision",
        format!(
            "re-acquisition: classical full frame {}x{}{}",
            scene.width,
            scene.height,
            note(found_full)
        ),
        Stats::of(&t_full),
    ));
    rows.push(Row::time(
        "vision",
        format!(
            "classical ROI fallback (20 mm = 222 px square){}",
            note(found_roi)
        ),
        Stats::of(&t_roi),
    ));
    Ok(rows)
}

fn control_rows(cli: &Cli, workload: &Workload) -> anyhow::Result<Vec<Row>> {
    let n = cli.iters;
    let mut rows = Vec::new();
    for (kind, name) in [
        (ControllerKind::Pid, "PID"),
        (ControllerKind::SmcDob, "SMC-DOB"),
        (ControllerKind::Mpc, "MPC (clarabel QP)"),
    ] {
        let mut c = control::ControllerBench::new(kind, workload)?;
        let t = time_each(50, n, |k| c.step(k));
        let row = Row::time(
            "control",
            format!("{name}: controller update"),
            Stats::of(&t),
        );
        rows.push(if kind == ControllerKind::Mpc {
            let p99 = row.p99_ns().unwrap_or(f64::INFINITY);
            row.target("p99 < 2 ms", p99 < 2e6)
        } else {
            row
        });
        let mut l = control::LoopBench::new(kind, workload)?;
        let t = time_each(50, n, |k| l.step(k));
        rows.push(Row::time(
            "control",
            format!("{name}: `ControlLoop::step` (+ checks, pinv allocation)"),
            Stats::of(&t),
        ));
    }
    let a = control::AllocationBench::new(64, workload)?;
    let pinv = time_each(50, n, |k| a.pinv(k));
    let qp = time_each(20, n, |k| a.constrained(k));
    rows.push(Row::time(
        "allocation",
        "SVD pseudo-inverse `allocate_pinv` (4x8)",
        Stats::of(&pinv),
    ));
    rows.push(Row::time(
        "allocation",
        "constrained QP `allocate_constrained` (clarabel)",
        Stats::of(&qp),
    ));
    let (sp, sq) = (Stats::of(&pinv), Stats::of(&qp));
    if let (Some(sp), Some(sq)) = (sp, sq) {
        rows.push(Row {
            area: "allocation",
            what: "constrained / pinv".into(),
            value: RowValue::Number {
                median: sq.median_ns / sp.median_ns,
                p99: sq.p99_ns / sp.p99_ns,
                unit: "x",
                n,
            },
            target: String::new(),
            verdict: millinav_bench::stats::Verdict::Info,
        });
    }
    Ok(rows)
}

fn e2e_rows(
    bin_dir: &std::path::Path,
    scenario: &std::path::Path,
    work: &std::path::Path,
    seconds: f64,
) -> Vec<Row> {
    let r = match e2e::run(bin_dir, scenario, work, seconds) {
        Ok(r) => r,
        Err(e) => {
            return vec![Row::text(
                "end to end",
                "real-time process set",
                format!("not measured: {e}"),
            )]
        }
    };
    let p99 = Stats::of(&r.serial_ns).map_or(f64::INFINITY, |s| s.p99_ns);
    let hz = r.closed_loop_hz();
    vec![
        Row::time("end to end", "capture → Pose at control", Stats::of(&r.pose_ns)),
        Row::time("end to end", "capture → CoilCommand at coilbus", Stats::of(&r.command_ns)),
        Row::time("end to end", "capture → serial frame received by the Teensy", Stats::of(&r.serial_ns))
            .target("p99 < 10 ms", p99 < 10e6),
        Row {
            area: "end to end",
            what: format!(
                "closed-loop rate, UNet vision (commands at the Teensy / s; plant published {:.1} frames/s)",
                r.frame_hz()
            ),
            value: RowValue::Number { median: hz, p99: hz, unit: " Hz", n: r.commanded },
            target: String::new(),
            verdict: millinav_bench::stats::Verdict::Info,
        }
        .target("≥ 100 Hz", hz >= 100.0 * 0.99),
        Row::text(
            "end to end",
            format!("deadline misses (no command at the Teensy within {:.0} ms of capture)", r.frame_period_s * 1e3),
            format!("{} of {} frames ({:.1} %)", r.deadline_misses, r.frames, 100.0 * r.deadline_misses as f64 / r.frames.max(1) as f64),
        )
        .target("0", r.deadline_misses == 0),
    ]
}

fn experiments_rows(
    cli: &Cli,
    workload: &Workload,
    bin_dir: &std::path::Path,
    work: &std::path::Path,
) -> Vec<Row> {
    let exe = bin_dir.join("experiments");
    if !cli.experiments || !exe.is_file() {
        let why = if exe.is_file() {
            "not run (pass --experiments)"
        } else {
            "pending (experiments binary not built)"
        };
        return vec![Row::text(
            "experiments",
            "wall time, fast mode and process set",
            why,
        )];
    }
    // The README's matrix commands (10 Hz and 100 Hz), and through the process set one
    // full-length cell of each, or the whole 10 Hz matrix.
    let cells = millinav_experiments::rig_matrix(&workload.rig, 3, true).len();
    let run = |label: &str, args: &[&str]| -> Result<f64, String> {
        let t = std::time::Instant::now();
        let status = std::process::Command::new(&exe)
            .current_dir(millinav_bench::workspace_root())
            .args(args)
            // A timing: never reuse the cells of an earlier bench's campaign.
            .arg("--fresh")
            .arg("--out")
            .arg(work.join(format!("experiments-{label}")))
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status()
            .map_err(|e| format!("failed: {e}"))?;
        if !status.success() {
            return Err(format!("failed ({status})"));
        }
        Ok(t.elapsed().as_nanos() as f64)
    };
    let one_cell: &[&str] = &[
        "--mode",
        "process",
        "--trials",
        "1",
        "--controllers",
        "pid",
        "--only",
        "20cp_static",
    ];
    let mut rows = Vec::new();
    let push = |rows: &mut Vec<Row>, what: String, measured: Result<f64, String>| match measured {
        Ok(ns) => {
            rows.push(Row::time("experiments", what, Stats::of(&[ns])));
            Some(ns)
        }
        Err(why) => {
            rows.push(Row::text("experiments", what, why));
            None
        }
    };
    for (rate, period) in [("10 Hz", Some("100")), ("100 Hz", None)] {
        let period_args: Vec<&str> = period
            .map(|p| vec!["--frame-period-ms", p])
            .unwrap_or_default();
        let full: Vec<&str> = ["--trials", "3", "--beyond"]
            .into_iter()
            .chain(period_args.iter().copied())
            .collect();
        push(
            &mut rows,
            format!("experiments at {rate}, fast mode: full matrix, {cells} runs (wall time)"),
            run(&format!("fast-{rate}"), &full),
        );
        if period.is_some() && cli.experiments_process_matrix {
            let args: Vec<&str> = ["--mode", "process"]
                .into_iter()
                .chain(full.iter().copied())
                .collect();
            push(
                &mut rows,
                format!(
                    "experiments at {rate}, process set: full matrix, {cells} runs (wall time)"
                ),
                run(&format!("process-{rate}"), &args),
            );
            continue;
        }
        let args: Vec<&str> = one_cell.iter().chain(period_args.iter()).copied().collect();
        let cell = push(
            &mut rows,
            format!("experiments at {rate}, process set: one 240 s cell (20 cP static, PID)"),
            run(&format!("process-{rate}"), &args),
        );
        if let Some(ns) = cell {
            rows.push(Row::text(
                "experiments",
                format!(
                    "experiments at {rate}, process set: full matrix ({cells} runs), extrapolated"
                ),
                format!(
                    "≈ {:.1} h ({cells} × the cell above)",
                    ns * 1e-9 * cells as f64 / 3600.0
                ),
            ));
        }
    }
    rows
}
