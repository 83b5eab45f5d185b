//! camera: the frame source of the set. It reads raw frames from where the scenario (or the rig
//! file) says — a V4L2 device, a video file, a folder of images, a recorded run, or the twin's
//! raw camera — rectifies each onto the rig's canonical top view with one precomputed `remap`
//! (lens + registration from `[camera.calibration]`), and publishes it on the Frame service, so
//! vision and everything after it never see a lens. Drops, stalls, unplugs and the end of a
//! stream are events (`camera_events.csv`, the recording) and heartbeat counters.

pub mod record;
pub mod source;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use fieldmaps::phantom::ImageGeometry;
use fieldmaps::rigfile::{CameraPixelFormat, Rig};
use millinav_kit::ports::{FrameOutbox, Inbox};
use millinav_kit::rerun;
use millinav_kit::runlog::{RunLogRow, RunLogWriter};
use millinav_kit::scenario::Scenario;
use millinav_kit::{clock, env_vars, recording, ConfigError, Runtime};
use opencv::core as cv;
use opencv::imgproc;
use opencv::prelude::*;
use serde::{Deserialize, Serialize};
use shm_schemas::{deadlines, services, CoilCommand, FrameHeader, FrameStamp, PixelFormat};

use crate::record::{Recorder, ReplaySource};
use crate::source::{
    CaptureSource, Channels, DeviceRequest, FolderSource, FrameSource, Note, Pulled, RawFrame,
    SourceSpec, TwinSource,
};

/// How a file, folder or recording is paced.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Timing {
    /// At the stream's own timestamps (real time).
    #[default]
    Recorded,
    /// Each frame once control answered the previous one (or its deadline passed): every frame
    /// reaches vision, as fast as the set runs.
    Lockstep,
}

/// The scenario's `[camera]` table.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraConfig {
    /// Where frames come from (see `source::SOURCE_FORMS`); default: the rig file's
    /// `[camera] source`, else `"twin"`.
    pub source: Option<String>,
    /// Pacing of files, folders and recordings.
    pub timing: Timing,
    /// Frame rate asked of a device; the rate of a folder without `timestamps.csv`; the
    /// recording's nominal rate.
    pub fps: Option<f64>,
    /// Manual exposure asked of a device (backend units; V4L2: 100 µs), where it allows.
    pub exposure: Option<f64>,
    /// No frame for this long is a stall (an event, a source fault).
    pub stall_timeout_ms: u64,
    /// Wait between attempts to reopen a device that stopped delivering.
    pub reopen_after_ms: u64,
    /// Record the raw stream into the run (`millinav run --record-frames` sets it too).
    pub record_frames: bool,
    /// Log the raw frame (JPEG) to the recording every this many frames (0: never).
    pub log_raw_every_frames: u64,
}

impl Default for CameraConfig {
    fn default() -> Self {
        Self {
            source: None,
            timing: Timing::default(),
            fps: None,
            exposure: None,
            stall_timeout_ms: 1000,
            reopen_after_ms: 1000,
            record_frames: false,
            log_raw_every_frames: 50,
        }
    }
}

/// One thing the camera saw (`camera_events.csv`): a stall, a drop, an unplug, the end.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraEventRow {
    /// Run clock, s.
    pub time_s: f64,
    pub event: String,
    pub detail: String,
}

impl RunLogRow for CameraEventRow {
    const FILE_NAME: &'static str = "camera_events.csv";
    const COLUMNS: &'static [&'static str] = &["time_s", "event", "detail"];
}

/// The rectification from the raw frame onto the canonical view.
enum Rectifier {
    /// The camera delivers the canonical view itself (a rig without `[camera.calibration]`).
    Identity,
    /// OpenCV `remap` maps (CV_32FC1 map_x, map_y), from `fieldmaps::lens`.
    Remap(cv::Mat, cv::Mat),
}

/// What `prepare` checked and built.
pub struct CameraSetup {
    pub config: CameraConfig,
    pub spec: SourceSpec,
    pub rig: Arc<Rig>,
    /// The raw frames' size.
    pub raw_size: (u32, u32),
    rectifier: Rectifier,
}

fn config_error(scenario: &Scenario, field: &str, message: impl std::fmt::Display) -> ConfigError {
    ConfigError::new(format!(
        "scenario {}: [camera] {field}: {message}",
        scenario.path.display()
    ))
}

/// Validates `[camera]`, builds the rectification from the rig's calibration and checks the
/// source (a device is opened and one frame read; a file, folder or recording is read and its
/// frame size checked). Every failure is a configuration error naming the file and field: no
/// frame is published.
pub fn prepare(scenario: &Scenario) -> Result<CameraSetup, ConfigError> {
    let config: CameraConfig = scenario.section("camera")?;
    if let Some(fps) = config.fps {
        if !(fps.is_finite() && fps > 0.0) {
            return Err(config_error(
                scenario,
                "fps",
                format!("must be > 0, got {fps}"),
            ));
        }
    }
    if config.stall_timeout_ms == 0 {
        return Err(config_error(scenario, "stall_timeout_ms", "must be > 0"));
    }
    let rig = scenario.rig()?;
    let (text, from_rig) = match (&config.source, &rig.camera_source) {
        (Some(s), _) => (s.clone(), false),
        (None, Some(s)) => (s.clone(), true),
        (None, None) => ("twin".to_string(), false),
    };
    let spec = if from_rig {
        let dir = rig.path.parent().map(Path::to_path_buf).unwrap_or_default();
        SourceSpec::parse(&text, |p| dir.join(p)).map_err(|e| {
            ConfigError::new(format!(
                "rig file {}: camera.source: {e}",
                rig.path.display()
            ))
        })?
    } else {
        SourceSpec::parse(&text, |p| scenario.resolve(p))
            .map_err(|e| config_error(scenario, "source", e))?
    };
    let view = rig.camera.geometry;
    let (raw_size, rectifier) = rectifier_of(&rig, &view)?;
    let setup = CameraSetup {
        config,
        spec,
        rig,
        raw_size,
        rectifier,
    };
    check_source(&setup).map_err(|e| {
        config_error(
            scenario,
            "source",
            format!("{} ({}): {e}", text, setup.spec.describe()),
        )
    })?;
    Ok(setup)
}

/// The raw size and rectification of the rig's camera.
fn rectifier_of(rig: &Rig, view: &ImageGeometry) -> Result<((u32, u32), Rectifier), ConfigError> {
    let Some(calibration) = rig.camera.calibration else {
        return Ok(((view.width_px, view.height_px), Rectifier::Identity));
    };
    let rig_error = |m: String| {
        ConfigError::new(format!(
            "rig file {}: [camera.calibration]: {m}",
            rig.path.display()
        ))
    };
    let map = calibration.rectification_map(view).map_err(rig_error)?;
    let to_mat = |values: &[f32]| -> Result<cv::Mat, opencv::Error> {
        let mut mat = cv::Mat::new_rows_cols_with_default(
            map.height as i32,
            map.width as i32,
            cv::CV_32FC1,
            0.0.into(),
        )?;
        mat.data_typed_mut::<f32>()?.copy_from_slice(values);
        Ok(mat)
    };
    let maps = to_mat(&map.cols)
        .and_then(|x| Ok((x, to_mat(&map.rows)?)))
        .map_err(|e| rig_error(format!("building the rectification maps: {e}")))?;
    Ok((
        (calibration.image_width, calibration.image_height),
        Rectifier::Remap(maps.0, maps.1),
    ))
}

/// Opens the source once and checks what it delivers, without publishing anything.
fn check_source(setup: &CameraSetup) -> Result<(), source::SourceError> {
    let what = setup.spec.describe();
    match &setup.spec {
        SourceSpec::Twin => Ok(()),
        SourceSpec::DevicePath(_) | SourceSpec::DeviceIndex(_) | SourceSpec::File(_) => {
            let mut notes = Vec::new();
            let mut capture =
                source::open_capture(&setup.spec, &device_request(setup), &mut notes)?;
            source::probe(&mut capture, &setup.spec, setup.raw_size)
        }
        SourceSpec::Folder(dir) => {
            let index = source::folder_index(dir, setup.config.fps.unwrap_or(10.0))?;
            let (image, _) = source::accept_pixels(source::read_image(&index[0].0)?, &what)?;
            source::check_size(&image, setup.raw_size, &what)
        }
        SourceSpec::Replay(run_dir) => {
            let image = ReplaySource::first_frame(run_dir)?;
            source::check_size(&image, setup.raw_size, &what)
        }
    }
}

fn device_request(setup: &CameraSetup) -> DeviceRequest {
    DeviceRequest {
        width: setup.raw_size.0,
        height: setup.raw_size.1,
        fps: setup.config.fps,
        exposure: setup.config.exposure,
    }
}

/// Validates the `[camera]` table and its source (what `--check` runs).
pub fn check_config(scenario: &Scenario) -> Result<(), ConfigError> {
    prepare(scenario).map(drop)
}

/// The frame service's side of a run: events, counters, recording, publishing.
struct Camera<'a> {
    rt: &'a mut Runtime,
    setup: &'a CameraSetup,
    frames: FrameOutbox,
    events: RunLogWriter<CameraEventRow>,
    recorder: Option<Recorder>,
    rectified: cv::Mat,
    converted: cv::Mat,
    published: u64,
    last_recorded: Option<FrameStamp>,
}

impl Camera<'_> {
    fn note(&mut self, note: &Note) {
        let time_s = clock::ns_to_secs(self.rt.env.run_clock_ns());
        if note.fault {
            self.rt.heartbeat.count_source_fault();
            tracing::warn!(event = note.event, "{}", note.detail);
        } else {
            tracing::info!(event = note.event, "{}", note.detail);
        }
        if note.dropped > 0 {
            self.rt.heartbeat.count_dropped(note.dropped);
        }
        let _ = self.events.append_now(&CameraEventRow {
            time_s,
            event: note.event.to_string(),
            detail: note.detail.clone(),
        });
        let _ = self.rt.rec.log(
            "camera/events",
            &rerun::TextLog::new(format!("{}: {}", note.event, note.detail)),
        );
    }

    /// Records (once per frame), rectifies and publishes a raw frame.
    fn publish(&mut self, frame: &RawFrame) -> anyhow::Result<()> {
        let what = self.setup.spec.describe();
        if let Err(e) = source::check_size(&frame.image, self.setup.raw_size, &what) {
            self.note(&Note::fault("bad_frame", e.to_string()));
            return Ok(());
        }
        let fresh = self
            .last_recorded
            .is_none_or(|last| !last.same_frame(&frame.stamp));
        if fresh {
            self.last_recorded = Some(frame.stamp);
            if let Some(recorder) = self.recorder.as_mut() {
                recorder.write(frame)?;
            }
            let every = self.setup.config.log_raw_every_frames;
            if every > 0 && frame.stamp.seq.is_multiple_of(every) {
                log_raw(&self.rt.rec, frame, RAW_LOG_JPEG_QUALITY);
            }
        }
        let view = self.setup.rig.camera.geometry;
        let rectified = match &self.setup.rectifier {
            Rectifier::Identity => &frame.image,
            Rectifier::Remap(map_x, map_y) => {
                imgproc::remap(
                    &frame.image,
                    &mut self.rectified,
                    map_x,
                    map_y,
                    imgproc::INTER_LINEAR,
                    cv::BORDER_CONSTANT,
                    cv::Scalar::all(0.0),
                )?;
                &self.rectified
            }
        };
        let (format, conversion) = match (self.setup.rig.camera.pixel_format, frame.channels) {
            (CameraPixelFormat::Rgb8, Channels::Rgb) => (PixelFormat::Rgb8, None),
            (CameraPixelFormat::Rgb8, Channels::Bgr) => {
                (PixelFormat::Rgb8, Some(imgproc::COLOR_BGR2RGB))
            }
            (CameraPixelFormat::Rgb8, Channels::Gray) => {
                (PixelFormat::Rgb8, Some(imgproc::COLOR_GRAY2RGB))
            }
            (CameraPixelFormat::Gray8, Channels::Gray) => (PixelFormat::Gray8, None),
            (CameraPixelFormat::Gray8, Channels::Bgr) => {
                (PixelFormat::Gray8, Some(imgproc::COLOR_BGR2GRAY))
            }
            (CameraPixelFormat::Gray8, Channels::Rgb) => {
                (PixelFormat::Gray8, Some(imgproc::COLOR_RGB2GRAY))
            }
        };
        let pixels = match conversion {
            None => rectified,
            Some(code) => {
                imgproc::cvt_color(rectified, &mut self.converted, code, 0)?;
                &self.converted
            }
        };
        let bytes = pixels.data_bytes()?;
        let channels = format.channels();
        let header = FrameHeader {
            stamp: frame.stamp,
            width: view.width_px,
            height: view.height_px,
            stride: view.width_px * channels,
            pixel_format: format as u32,
            ..Default::default()
        }
        .with_mapping(view.pixel_mapping());
        self.frames
            .send_in_place(header, bytes.len(), |out| out.copy_from_slice(bytes))?;
        self.published += 1;
        Ok(())
    }
}

/// The raw frame into the recording (JPEG, so a 1 MP frame costs ~0.3 MB, not 3).
fn log_raw(rec: &rerun::RecordingStream, frame: &RawFrame, jpeg_quality: u8) {
    let (w, h) = (frame.image.cols() as usize, frame.image.rows() as usize);
    let Ok(bytes) = frame.image.data_bytes() else {
        return;
    };
    let rgb: Vec<u8> = match frame.channels {
        Channels::Rgb => bytes.to_vec(),
        Channels::Gray => bytes.iter().flat_map(|&g| [g, g, g]).collect(),
        Channels::Bgr => bytes
            .chunks_exact(3)
            .flat_map(|px| [px[2], px[1], px[0]])
            .collect(),
    };
    recording::set_time(rec, frame.stamp.capture_time_ns, frame.stamp.seq);
    let _ = rec.log(
        "camera_raw/image",
        recording::camera_image(rgb, w, h, jpeg_quality).as_ref(),
    );
}

/// Opens the source named by the setup.
fn open_source(
    rt: &Runtime,
    setup: &CameraSetup,
    notes: &mut Vec<Note>,
) -> anyhow::Result<Box<dyn FrameSource>> {
    let incarnation = rt.env.incarnation;
    Ok(match &setup.spec {
        SourceSpec::Twin => Box::new(TwinSource::open(&rt.node, setup.raw_size)?),
        SourceSpec::DevicePath(_) | SourceSpec::DeviceIndex(_) | SourceSpec::File(_) => {
            Box::new(CaptureSource::start(
                setup.spec.clone(),
                device_request(setup),
                incarnation,
                rt.env.clock_epoch_ns,
                Duration::from_millis(setup.config.reopen_after_ms),
                notes,
            )?)
        }
        SourceSpec::Folder(dir) => Box::new(FolderSource::open(
            dir,
            setup.config.fps.unwrap_or(10.0),
            incarnation,
        )?),
        SourceSpec::Replay(run_dir) => Box::new(ReplaySource::open(run_dir)?),
    })
}

/// Puts a paced source's frames on the run clock: at their own timing, or one per answer of
/// control (lockstep).
struct Pacer {
    timing: Timing,
    /// (run clock, media time) of the first frame.
    origin: Option<(u64, u64)>,
    commands: Option<Inbox<CoilCommand>>,
    answered_once: bool,
}

/// JPEG quality of the raw frames in the recording.
const RAW_LOG_JPEG_QUALITY: u8 = 85;

/// How long a live source may take to deliver its first frame before that is a stall.
const FIRST_FRAME_PATIENCE: Duration = Duration::from_secs(10);

/// How often a lockstep pacer republishes the first frame while the chain starts.
const FIRST_FRAME_REPEAT: Duration = Duration::from_millis(200);
/// How long a lockstep pacer waits for the chain to answer the first frame before it goes on
/// by deadlines (a set without control).
const FIRST_ANSWER_PATIENCE: Duration = Duration::from_secs(60);

impl Pacer {
    /// Holds `frame` until it is due (recorded timing) and puts its stamp on the run clock.
    fn schedule(&mut self, rt: &Runtime, frame: &mut RawFrame) -> bool {
        if self.timing == Timing::Lockstep {
            return true;
        }
        let media = frame.stamp.capture_time_ns;
        let now = rt.env.run_clock_ns();
        let (run0, media0) = *self.origin.get_or_insert((now, media));
        let due = run0 + media.saturating_sub(media0);
        while rt.env.run_clock_ns() < due {
            if rt.shutdown_requested() {
                return false;
            }
            let left = due.saturating_sub(rt.env.run_clock_ns());
            std::thread::sleep(Duration::from_nanos(left.min(20_000_000)));
        }
        let shift = |t: u64| (t + run0).saturating_sub(media0);
        frame.stamp.capture_time_ns = shift(frame.stamp.capture_time_ns);
        frame.stamp.grab_time_ns = shift(frame.stamp.grab_time_ns.max(media));
        true
    }

    /// Lockstep: waits until control answered `stamp` (or its deadline passed); the first frame
    /// is republished until the chain answers it. Returns false on shutdown.
    fn await_answer(&mut self, camera: &mut Camera<'_>, frame: &RawFrame) -> anyhow::Result<bool> {
        let Some(commands) = &self.commands else {
            return Ok(true);
        };
        let started = Instant::now();
        let mut last_send = Instant::now();
        loop {
            if camera.rt.shutdown_requested() {
                return Ok(false);
            }
            for command in commands.receive_all()? {
                if command.stamp.same_frame(&frame.stamp) {
                    self.answered_once = true;
                    return Ok(true);
                }
            }
            let waited = started.elapsed();
            if self.answered_once && waited >= deadlines::LOCKSTEP_COMMAND {
                camera.rt.heartbeat.count_deadline_miss();
                return Ok(true);
            }
            if !self.answered_once {
                if waited >= FIRST_ANSWER_PATIENCE {
                    self.answered_once = true;
                    camera.note(&Note::fault(
                        "no_answer",
                        "control did not answer the first frame; pacing by deadlines",
                    ));
                    return Ok(true);
                }
                if last_send.elapsed() >= FIRST_FRAME_REPEAT {
                    camera.publish(frame)?;
                    last_send = Instant::now();
                }
            }
            millinav_kit::service_loop::keep_alive(&mut camera.rt.heartbeat, &[&camera.frames]);
            if !commands.wait(Duration::from_millis(20)) {
                return Ok(false);
            }
        }
    }
}

/// The camera process: pull, pace, rectify, publish, until the stream ends or the set stops.
pub fn run(rt: &mut Runtime, _scenario: &Scenario, setup: CameraSetup) -> anyhow::Result<()> {
    let view = setup.rig.camera.geometry;
    let frame_bytes = view.width_px as usize * view.height_px as usize * 3;
    let record = setup.config.record_frames
        || std::env::var(env_vars::RECORD_FRAMES).is_ok_and(|v| v == "1");
    let recorder = if record {
        Some(Recorder::create(
            &rt.env.run_dir,
            setup.config.fps.unwrap_or(10.0),
        )?)
    } else {
        None
    };
    let mut notes = Vec::new();
    let mut source = open_source(rt, &setup, &mut notes)?;
    let paced = source.paced();
    let commands = (paced && setup.config.timing == Timing::Lockstep)
        .then(|| Inbox::<CoilCommand>::new(&rt.node, services::COMMAND))
        .transpose()?;
    let frames = FrameOutbox::new(&rt.node, frame_bytes)?;
    let events = RunLogWriter::<CameraEventRow>::in_run_dir(&rt.env.run_dir)?;
    let stall_timeout = Duration::from_millis(setup.config.stall_timeout_ms);
    tracing::info!(source = %setup.spec.describe(), raw = ?setup.raw_size, record, "camera starting");
    let mut camera = Camera {
        rt,
        setup: &setup,
        frames,
        events,
        recorder,
        rectified: cv::Mat::default(),
        converted: cv::Mat::default(),
        published: 0,
        last_recorded: None,
    };
    camera.note(&Note::info("source_opened", setup.spec.describe()));
    let mut pacer = Pacer {
        timing: setup.config.timing,
        origin: None,
        commands,
        answered_once: false,
    };
    let mut last_frame = Instant::now();
    let mut stalled = false;
    let ended = loop {
        for note in notes.drain(..) {
            camera.note(&note);
        }
        if camera.rt.shutdown_requested() {
            break None;
        }
        millinav_kit::service_loop::keep_alive(&mut camera.rt.heartbeat, &[&camera.frames]);
        let pulled = source.pull(deadlines::HEARTBEAT_PERIOD / 2, &mut notes)?;
        match pulled {
            Pulled::Frame(mut frame) => {
                if stalled {
                    stalled = false;
                    notes.push(Note::info(
                        "source_recovered",
                        format!(
                            "frames again after {:.2} s",
                            last_frame.elapsed().as_secs_f64()
                        ),
                    ));
                }
                last_frame = Instant::now();
                if paced && !pacer.schedule(camera.rt, &mut frame) {
                    break None;
                }
                for note in notes.drain(..) {
                    camera.note(&note);
                }
                camera.publish(&frame)?;
                if paced && !pacer.await_answer(&mut camera, &frame)? {
                    break None;
                }
            }
            Pulled::Nothing => {
                // Before the first frame a source may take a while to start (a device's
                // exposure, the twin's board check): a longer patience.
                let patience = if camera.published == 0 {
                    stall_timeout.max(FIRST_FRAME_PATIENCE)
                } else {
                    stall_timeout
                };
                if !paced && !stalled && last_frame.elapsed() >= patience {
                    stalled = true;
                    notes.push(Note::fault(
                        "source_stalled",
                        format!(
                            "no frame from {} for {} ms",
                            setup.spec.describe(),
                            patience.as_millis()
                        ),
                    ));
                }
            }
            Pulled::Ended(why) => break Some(why),
            Pulled::Terminated => break None,
        }
    };
    for note in notes.drain(..) {
        camera.note(&note);
    }
    if let Some(why) = &ended {
        camera.note(&Note::fault("end_of_stream", why.clone()));
    }
    let published = camera.published;
    if let Some(recorder) = camera.recorder.as_mut() {
        recorder.finish()?;
        tracing::info!(frames = recorder.frames, "recording closed");
    }
    let _ = camera.events.flush();
    // The supervisor learns of the last faults (end of stream) before it sees the exit.
    camera.rt.heartbeat.beat_now();
    tracing::info!(published, "camera stopping");
    Ok(())
}

/// Where a run's recorded frames live (for tools and tests).
pub fn recording_dir(run_dir: &Path) -> PathBuf {
    run_dir.join(record::FRAMES_DIR)
}
