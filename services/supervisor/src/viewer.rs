//! The Rerun side of a run: the viewer the supervisor may spawn, its layout, and the joining
//! of the per-process recordings into `run.rrd`.

use super::*;

/// Port of the Rerun viewer the supervisor spawns (Rerun's default gRPC port).
pub const VIEWER_PORT: u16 = 9876;

/// Time a freshly spawned viewer gets to open its port before the services connect.
pub(super) const VIEWER_STARTUP_WAIT: Duration = Duration::from_millis(1500);

/// Starts a Rerun viewer when asked (or when `auto` and one is usable); returns its gRPC URL.
pub(super) fn start_viewer(mode: ViewerMode) -> anyhow::Result<Option<(Child, String)>> {
    let has_display =
        std::env::var_os("DISPLAY").is_some() || std::env::var_os("WAYLAND_DISPLAY").is_some();
    let wanted = match mode {
        ViewerMode::None => false,
        ViewerMode::Spawn => true,
        ViewerMode::Auto => has_display && which("rerun").is_some(),
    };
    if !wanted {
        return Ok(None);
    }
    let Some(rerun_bin) = which("rerun") else {
        bail!("--viewer spawn: no `rerun` executable on PATH (pip install rerun-sdk==0.36.3)");
    };
    let child = Command::new(rerun_bin)
        .arg("--port")
        .arg(VIEWER_PORT.to_string())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .process_group(0)
        .spawn()
        .context("spawning the Rerun viewer")?;
    // Give the viewer a moment to open its port before the services connect.
    std::thread::sleep(VIEWER_STARTUP_WAIT);
    Ok(Some((
        child,
        format!("rerun+http://127.0.0.1:{VIEWER_PORT}/proxy"),
    )))
}

/// Finds an executable on PATH.
pub fn which(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|dir| dir.join(name))
            .find(|candidate| candidate.is_file())
    })
}

/// Joins the per-process recordings into `<run_dir>/run.rrd` with the Rerun CLI when it is
/// installed (`rerun rrd merge`), otherwise leaves them in `<run_dir>/rrd/` and says so.
pub fn merge_recordings(run_dir: &Path) -> anyhow::Result<Option<PathBuf>> {
    let dir = recording::rrd_dir(run_dir);
    let mut parts: Vec<PathBuf> = match std::fs::read_dir(&dir) {
        Ok(entries) => entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "rrd"))
            .collect(),
        Err(_) => return Ok(None),
    };
    parts.sort();
    if parts.is_empty() {
        return Ok(None);
    }
    let Some(rerun_bin) = which("rerun") else {
        tracing::warn!(
            "`rerun` CLI not found: recordings left as parts in {} (open them together in the viewer)",
            dir.display()
        );
        return Ok(None);
    };
    let out = run_dir.join("run.rrd");
    let status = Command::new(rerun_bin)
        .args(["rrd", "merge"])
        .args(&parts)
        .arg("-o")
        .arg(&out)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .output()
        .context("running `rerun rrd merge`")?;
    if !status.status.success() {
        bail!(
            "`rerun rrd merge` failed: {}",
            String::from_utf8_lossy(&status.stderr).trim()
        );
    }
    Ok(Some(out))
}

/// The viewer's layout, sent with the recording: camera with its overlays and the top view
/// with paths and flow on the left; the 3D rig, the control series (error, force, d̂, currents)
/// and health and events on the right.
pub(super) fn viewer_layout() -> rerun::blueprint::Blueprint {
    use rerun::blueprint::{
        Blueprint, Horizontal, Spatial2DView, Spatial3DView, Tabs, TextLogView, TimeSeriesView,
        Vertical,
    };
    let series = |name: &str, origin: &str| TimeSeriesView::new(name).with_origin(origin).into();
    Blueprint::new(Horizontal::new([
        Vertical::new([
            Spatial2DView::new("camera").with_origin("/camera").into(),
            Spatial2DView::new("top view (mm)")
                .with_origin("/world")
                .into(),
        ])
        .into(),
        Vertical::new([
            Spatial3DView::new("rig (mm)").with_origin("/rig3d").into(),
            Tabs::new([
                series("error (mm)", "/control/error_mm"),
                series("force (N)", "/control/force_des_n"),
                series("d̂ (N)", "/control/d_hat_n"),
                series("currents (A)", "/control/current_a"),
                series("health", "/health"),
            ])
            .into(),
            TextLogView::new("events").with_origin("/supervisor").into(),
        ])
        .into(),
    ]))
}
