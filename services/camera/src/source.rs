//! Where frames come from: the twin's raw camera (shared memory), a V4L2 device or a video file
//! (OpenCV `VideoCapture` on a grabber thread), a folder of images, or a recorded run.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::Arc;
use std::time::Duration;

use iceoryx2::prelude::*;
use millinav_kit::clock;
use millinav_kit::ports::FrameInbox;
use millinav_kit::runlog::{self, RunLogRow};
use opencv::core as cv;
use opencv::prelude::*;
use opencv::{imgcodecs, videoio};
use serde::{Deserialize, Serialize};
use shm_schemas::{services, FrameStamp, PixelFormat};

/// What the user named in `[camera] source`.
#[derive(Debug, Clone, PartialEq)]
pub enum SourceSpec {
    /// The twin's raw camera frames (`millinav/camera/raw`).
    Twin,
    /// A V4L2 device by path (`/dev/video0`).
    DevicePath(PathBuf),
    /// A V4L2 device by index (`video:0` or `0`).
    DeviceIndex(i32),
    /// A video file (`file:<path>`).
    File(PathBuf),
    /// A folder of images, sorted by name, with `timestamps.csv` when present (`folder:<dir>`).
    Folder(PathBuf),
    /// A run recorded with `--record-frames` (`replay:<run dir>`).
    Replay(PathBuf),
}

pub const SOURCE_FORMS: &str = "\"twin\", \"/dev/videoN\", \"video:N\", \"file:<video>\", \
     \"folder:<image dir>\" or \"replay:<run dir>\"";

impl SourceSpec {
    /// Parses a source string; relative paths resolve with `resolve`.
    pub fn parse(text: &str, resolve: impl Fn(&Path) -> PathBuf) -> Result<Self, String> {
        let text = text.trim();
        if text == "twin" {
            return Ok(Self::Twin);
        }
        if let Some(index) = text.strip_prefix("video:").or(Some(text)) {
            if let Ok(index) = index.parse::<i32>() {
                if index >= 0 {
                    return Ok(Self::DeviceIndex(index));
                }
            }
        }
        if text.starts_with("/dev/") {
            return Ok(Self::DevicePath(PathBuf::from(text)));
        }
        let path_of = |rest: &str| {
            if rest.is_empty() {
                Err(format!("{text:?} names no path"))
            } else {
                Ok(resolve(Path::new(rest)))
            }
        };
        if let Some(rest) = text.strip_prefix("file:") {
            return path_of(rest).map(Self::File);
        }
        if let Some(rest) = text.strip_prefix("folder:") {
            return path_of(rest).map(Self::Folder);
        }
        if let Some(rest) = text.strip_prefix("replay:") {
            return path_of(rest).map(Self::Replay);
        }
        Err(format!("{text:?} is not a source: use {SOURCE_FORMS}"))
    }

    /// Files, folders and recordings end; devices and the twin do not.
    pub fn is_finite(&self) -> bool {
        matches!(self, Self::File(_) | Self::Folder(_) | Self::Replay(_))
    }

    pub fn describe(&self) -> String {
        match self {
            Self::Twin => "the twin's raw camera".into(),
            Self::DevicePath(p) => format!("V4L2 device {}", p.display()),
            Self::DeviceIndex(i) => format!("V4L2 device index {i}"),
            Self::File(p) => format!("video file {}", p.display()),
            Self::Folder(p) => format!("image folder {}", p.display()),
            Self::Replay(p) => format!("recorded run {}", p.display()),
        }
    }
}

/// Channel order of a frame's pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Channels {
    Rgb,
    Bgr,
    Gray,
}

/// One frame as the source delivered it, before rectification.
pub struct RawFrame {
    /// 8-bit, 1 or 3 channels.
    pub image: cv::Mat,
    pub channels: Channels,
    /// Seq, incarnation and times; a paced source's times are its own media times until the
    /// pacer puts them on the run clock.
    pub stamp: FrameStamp,
}

/// Something the source saw that the run's events should say.
#[derive(Debug, Clone, PartialEq)]
pub struct Note {
    pub event: &'static str,
    pub detail: String,
    /// Counts as a source fault in the heartbeat.
    pub fault: bool,
    /// Frames lost.
    pub dropped: u64,
}

impl Note {
    pub fn fault(event: &'static str, detail: impl Into<String>) -> Self {
        Self {
            event,
            detail: detail.into(),
            fault: true,
            dropped: 0,
        }
    }

    pub fn info(event: &'static str, detail: impl Into<String>) -> Self {
        Self {
            event,
            detail: detail.into(),
            fault: false,
            dropped: 0,
        }
    }
}

/// What one pull gave.
pub enum Pulled {
    Frame(RawFrame),
    /// Nothing within the timeout (the loop tracks stalls).
    Nothing,
    /// The stream is over (end of file, folder or recording), with the reason.
    Ended(String),
    /// SIGINT / SIGTERM arrived while the source waited: the service stops.
    Terminated,
}

#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    #[error("{0}")]
    Unusable(String),
    #[error("opencv: {0}")]
    OpenCv(#[from] opencv::Error),
    #[error(transparent)]
    Kit(#[from] millinav_kit::KitError),
}

/// A frame source.
pub trait FrameSource {
    /// Waits up to `timeout` for the next frame; notes go to `notes`.
    fn pull(&mut self, timeout: Duration, notes: &mut Vec<Note>) -> Result<Pulled, SourceError>;
    /// Sources that run at their own pace (files, folders, recordings) deliver media times the
    /// pacer schedules; live sources deliver run-clock times.
    fn paced(&self) -> bool;
}

/// Checks a decoded image's pixel format: 8-bit, 1 or 3 channels (4: alpha dropped).
pub fn accept_pixels(image: cv::Mat, what: &str) -> Result<(cv::Mat, Channels), SourceError> {
    let depth = image.depth();
    let channels = image.channels();
    if depth != cv::CV_8U || !matches!(channels, 1 | 3 | 4) {
        return Err(SourceError::Unusable(format!(
            "{what}: unsupported pixel format ({} bits, {channels} channels): the camera \
             service takes 8-bit gray, BGR or BGRA frames",
            match depth {
                cv::CV_16U | cv::CV_16S => 16,
                cv::CV_32F | cv::CV_32S => 32,
                cv::CV_64F => 64,
                _ => 8,
            }
        )));
    }
    if channels == 4 {
        let mut bgr = cv::Mat::default();
        opencv::imgproc::cvt_color(&image, &mut bgr, opencv::imgproc::COLOR_BGRA2BGR, 0)?;
        return Ok((bgr, Channels::Bgr));
    }
    Ok((
        image,
        if channels == 1 {
            Channels::Gray
        } else {
            Channels::Bgr
        },
    ))
}

// ---------------------------------------------------------------------------------------------
// The twin's raw camera.

/// Frames the plant renders through the rig's lens, from shared memory.
pub struct TwinSource {
    inbox: FrameInbox,
    expected: (u32, u32),
    last: Option<FrameStamp>,
}

impl TwinSource {
    pub fn open(node: &Node<ipc::Service>, expected: (u32, u32)) -> Result<Self, SourceError> {
        Ok(Self {
            inbox: FrameInbox::on(node, services::RAW_FRAME)?,
            expected,
            last: None,
        })
    }
}

impl FrameSource for TwinSource {
    fn pull(&mut self, timeout: Duration, notes: &mut Vec<Note>) -> Result<Pulled, SourceError> {
        let mut sample = self.inbox.latest()?;
        if sample.is_none() {
            if !self.inbox.wait(timeout) {
                return Ok(Pulled::Terminated);
            }
            sample = self.inbox.latest()?;
        }
        let Some(sample) = sample else {
            return Ok(Pulled::Nothing);
        };
        let header = *sample.user_header();
        let format = match header.validate(sample.payload().len()) {
            Ok(format) => format,
            Err(e) => {
                notes.push(Note::fault("bad_frame", format!("raw frame rejected: {e}")));
                return Ok(Pulled::Nothing);
            }
        };
        if (header.width, header.height) != self.expected || format != PixelFormat::Rgb8 {
            notes.push(Note::fault(
                "bad_frame",
                format!(
                    "raw frame is {}x{} {format:?}, the rig's camera delivers {}x{} rgb8",
                    header.width, header.height, self.expected.0, self.expected.1
                ),
            ));
            return Ok(Pulled::Nothing);
        }
        let stamp = header.stamp;
        if let Some(last) = self.last {
            if last.incarnation == stamp.incarnation && stamp.seq > last.seq + 1 {
                notes.push(Note {
                    dropped: stamp.seq - last.seq - 1,
                    ..Note::info(
                        "dropped_frames",
                        format!("seq {} → {}", last.seq, stamp.seq),
                    )
                });
            }
        }
        self.last = Some(stamp);
        let (w, h) = (header.width as i32, header.height as i32);
        let mut image = cv::Mat::new_rows_cols_with_default(h, w, cv::CV_8UC3, 0.0.into())?;
        let row_bytes = w as usize * 3;
        let out = image.data_bytes_mut()?;
        for (row, chunk) in out.chunks_exact_mut(row_bytes).enumerate() {
            let start = row * header.stride as usize;
            chunk.copy_from_slice(&sample.payload()[start..start + row_bytes]);
        }
        Ok(Pulled::Frame(RawFrame {
            image,
            channels: Channels::Rgb,
            stamp,
        }))
    }

    fn paced(&self) -> bool {
        false
    }
}

// ---------------------------------------------------------------------------------------------
// VideoCapture: devices and video files, read on a grabber thread.

/// Capture settings a device is asked for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeviceRequest {
    pub width: u32,
    pub height: u32,
    pub fps: Option<f64>,
    pub exposure: Option<f64>,
}

enum Grab {
    Frame {
        image: cv::Mat,
        capture_ns: u64,
        grab_ns: u64,
    },
    Note(Note),
    Ended(String),
}

/// Opens a capture: a device (V4L2) with the requested settings, or a file (any backend).
pub fn open_capture(
    spec: &SourceSpec,
    request: &DeviceRequest,
    notes: &mut Vec<Note>,
) -> Result<videoio::VideoCapture, SourceError> {
    let capture = match spec {
        SourceSpec::DevicePath(path) => {
            videoio::VideoCapture::from_file(path.as_path(), videoio::CAP_V4L2)?
        }
        SourceSpec::DeviceIndex(index) => videoio::VideoCapture::new(*index, videoio::CAP_V4L2)?,
        SourceSpec::File(path) => {
            if !path.is_file() {
                return Err(SourceError::Unusable(format!(
                    "video file {} does not exist or is not a file",
                    path.display()
                )));
            }
            videoio::VideoCapture::from_file(path.as_path(), videoio::CAP_ANY)?
        }
        other => {
            return Err(SourceError::Unusable(format!(
                "{} is not read with VideoCapture",
                other.describe()
            )))
        }
    };
    let mut capture = capture;
    if !capture.is_opened()? {
        return Err(SourceError::Unusable(format!(
            "cannot open {}: no such device, no permission, or a format no OpenCV backend reads",
            spec.describe()
        )));
    }
    if matches!(spec, SourceSpec::DevicePath(_) | SourceSpec::DeviceIndex(_)) {
        let mut set = |prop: i32, value: f64, what: &str| -> Result<(), SourceError> {
            if !capture.set(prop, value)? {
                notes.push(Note::info(
                    "setting_ignored",
                    format!("the backend did not accept {what} = {value}"),
                ));
            }
            Ok(())
        };
        set(
            videoio::CAP_PROP_FRAME_WIDTH,
            f64::from(request.width),
            "width",
        )?;
        set(
            videoio::CAP_PROP_FRAME_HEIGHT,
            f64::from(request.height),
            "height",
        )?;
        if let Some(fps) = request.fps {
            set(videoio::CAP_PROP_FPS, fps, "fps")?;
        }
        if let Some(exposure) = request.exposure {
            // V4L2: 1 = manual exposure (aperture priority is 3).
            set(videoio::CAP_PROP_AUTO_EXPOSURE, 1.0, "manual exposure")?;
            set(videoio::CAP_PROP_EXPOSURE, exposure, "exposure")?;
        }
    }
    Ok(capture)
}

/// Reads one frame to check the source delivers what the rig expects (size, pixel format).
pub fn probe(
    capture: &mut videoio::VideoCapture,
    spec: &SourceSpec,
    expected: (u32, u32),
) -> Result<(), SourceError> {
    let mut image = cv::Mat::default();
    if !capture.read(&mut image)? || image.empty() {
        return Err(SourceError::Unusable(format!(
            "{} delivered no frame",
            spec.describe()
        )));
    }
    let (image, _) = accept_pixels(image, &spec.describe())?;
    check_size(&image, expected, &spec.describe())
}

pub fn check_size(image: &cv::Mat, expected: (u32, u32), what: &str) -> Result<(), SourceError> {
    let size = (image.cols() as u32, image.rows() as u32);
    if size != expected {
        return Err(SourceError::Unusable(format!(
            "{what} delivers {}x{} frames; the rig's camera (camera.calibration.image_width/\
             image_height, else camera.width_px/height_px) expects {}x{}",
            size.0, size.1, expected.0, expected.1
        )));
    }
    Ok(())
}

/// A device or video file read on its own thread, so a stalled driver never blocks the loop.
pub struct CaptureSource {
    frames: Receiver<Grab>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
    seq: u64,
    incarnation: u64,
    is_file: bool,
    period_ns: Option<u64>,
    last_capture_ns: Option<u64>,
}

impl CaptureSource {
    /// Opens the capture (an error names the device or file) and starts the grabber.
    pub fn start(
        spec: SourceSpec,
        request: DeviceRequest,
        incarnation: u64,
        epoch_ns: u64,
        reopen_after: Duration,
        notes: &mut Vec<Note>,
    ) -> Result<Self, SourceError> {
        let capture = open_capture(&spec, &request, notes)?;
        let is_file = matches!(spec, SourceSpec::File(_));
        let fps = capture.get(videoio::CAP_PROP_FPS).unwrap_or(0.0);
        let fps = request.fps.filter(|_| !is_file).unwrap_or(fps);
        let period_ns = (fps.is_finite() && fps > 0.0).then(|| (1e9 / fps) as u64);
        // Files are read only as fast as the pacer takes them; a device must not wait.
        let (tx, rx) = mpsc::sync_channel(if is_file { 2 } else { 4 });
        let stop = Arc::new(AtomicBool::new(false));
        let thread_stop = stop.clone();
        let thread = std::thread::Builder::new()
            .name("grabber".into())
            .spawn(move || {
                grab_loop(
                    capture,
                    spec,
                    request,
                    epoch_ns,
                    reopen_after,
                    &tx,
                    &thread_stop,
                )
            })
            .map_err(|e| SourceError::Unusable(format!("cannot start the grabber thread: {e}")))?;
        Ok(Self {
            frames: rx,
            stop,
            thread: Some(thread),
            seq: 0,
            incarnation,
            is_file,
            period_ns,
            last_capture_ns: None,
        })
    }
}

impl Drop for CaptureSource {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        // Unblock a grabber waiting to hand over a frame.
        while self.frames.try_recv().is_ok() {}
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// Capture time of the frame just read: the driver's buffer timestamp when it gives one on the
/// monotonic clock (V4L2), else now. Files: their media time.
fn capture_time_ns(
    capture: &videoio::VideoCapture,
    is_file: bool,
    epoch_ns: u64,
    now_ns: u64,
) -> u64 {
    let ms = capture.get(videoio::CAP_PROP_POS_MSEC).unwrap_or(0.0);
    if is_file {
        return (ms.max(0.0) * 1e6) as u64;
    }
    let driver_ns = (ms * 1e6) as u64;
    // A driver stamp on CLOCK_MONOTONIC lies a little before now; anything else (0, wall
    // clock, another epoch) is not usable.
    if ms > 0.0 && driver_ns <= now_ns && now_ns - driver_ns < 1_000_000_000 {
        driver_ns.saturating_sub(epoch_ns)
    } else {
        now_ns.saturating_sub(epoch_ns)
    }
}

fn grab_loop(
    mut capture: videoio::VideoCapture,
    spec: SourceSpec,
    request: DeviceRequest,
    epoch_ns: u64,
    reopen_after: Duration,
    tx: &SyncSender<Grab>,
    stop: &AtomicBool,
) {
    let is_file = matches!(spec, SourceSpec::File(_));
    let mut frames = 0u64;
    while !stop.load(Ordering::Relaxed) {
        let mut image = cv::Mat::default();
        let read = capture.read(&mut image);
        let now_ns = clock::monotonic_ns();
        match read {
            Ok(true) if !image.empty() => {
                frames += 1;
                let capture_ns = capture_time_ns(&capture, is_file, epoch_ns, now_ns);
                let grab = Grab::Frame {
                    image,
                    capture_ns,
                    grab_ns: now_ns.saturating_sub(epoch_ns),
                };
                if is_file {
                    if tx.send(grab).is_err() {
                        return;
                    }
                } else {
                    match tx.try_send(grab) {
                        Ok(()) => {}
                        Err(TrySendError::Full(_)) => {
                            let _ = tx.try_send(Grab::Note(Note {
                                dropped: 1,
                                ..Note::info("dropped_frames", "the service fell behind the device")
                            }));
                        }
                        Err(TrySendError::Disconnected(_)) => return,
                    }
                }
            }
            outcome if is_file => {
                let why = match outcome {
                    Err(e) => format!("read error after {frames} frames: {e}"),
                    _ => format!("end of file after {frames} frames"),
                };
                let _ = tx.send(Grab::Ended(why));
                return;
            }
            outcome => {
                // A device that stops delivering (unplugged, driver error): release it and
                // reopen until it is back or the service stops.
                let why = match outcome {
                    Err(e) => e.to_string(),
                    _ => "read returned no frame".into(),
                };
                let _ = tx.send(Grab::Note(Note::fault("read_failed", why)));
                let _ = capture.release();
                loop {
                    std::thread::sleep(reopen_after);
                    if stop.load(Ordering::Relaxed) {
                        return;
                    }
                    let mut notes = Vec::new();
                    match open_capture(&spec, &request, &mut notes) {
                        Ok(reopened) => {
                            capture = reopened;
                            let _ = tx.send(Grab::Note(Note::info("reopened", spec.describe())));
                            break;
                        }
                        Err(e) => {
                            let _ =
                                tx.send(Grab::Note(Note::fault("reopen_failed", e.to_string())));
                        }
                    }
                }
            }
        }
    }
}

impl FrameSource for CaptureSource {
    fn pull(&mut self, timeout: Duration, notes: &mut Vec<Note>) -> Result<Pulled, SourceError> {
        match self.frames.recv_timeout(timeout) {
            Ok(Grab::Frame {
                image,
                capture_ns,
                grab_ns,
            }) => {
                let (image, channels) = match accept_pixels(image, "frame") {
                    Ok(accepted) => accepted,
                    Err(e) => {
                        notes.push(Note::fault("bad_frame", e.to_string()));
                        return Ok(Pulled::Nothing);
                    }
                };
                if let (Some(period), Some(last)) = (self.period_ns, self.last_capture_ns) {
                    let gap = capture_ns.saturating_sub(last);
                    if !self.is_file && gap * 2 > period * 3 {
                        let lost = ((gap as f64 / period as f64).round() as u64).saturating_sub(1);
                        if lost > 0 {
                            notes.push(Note {
                                dropped: lost,
                                ..Note::info(
                                    "dropped_frames",
                                    format!("{:.1} ms between frames", gap as f64 * 1e-6),
                                )
                            });
                        }
                    }
                }
                self.last_capture_ns = Some(capture_ns);
                let stamp = FrameStamp::new(self.seq, self.incarnation, capture_ns)
                    .grabbed_at(if self.is_file { capture_ns } else { grab_ns });
                self.seq += 1;
                Ok(Pulled::Frame(RawFrame {
                    image,
                    channels,
                    stamp,
                }))
            }
            Ok(Grab::Note(note)) => {
                notes.push(note);
                Ok(Pulled::Nothing)
            }
            Ok(Grab::Ended(why)) => Ok(Pulled::Ended(why)),
            Err(RecvTimeoutError::Timeout) => Ok(Pulled::Nothing),
            Err(RecvTimeoutError::Disconnected) => Ok(Pulled::Ended("the grabber stopped".into())),
        }
    }

    fn paced(&self) -> bool {
        self.is_file
    }
}

// ---------------------------------------------------------------------------------------------
// A folder of images.

/// `timestamps.csv` of an image folder: one row per image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TimestampRow {
    /// Image file name inside the folder.
    pub file: String,
    /// Capture time, s (any origin; only differences matter).
    pub time_s: f64,
}

impl RunLogRow for TimestampRow {
    const FILE_NAME: &'static str = "timestamps.csv";
    const COLUMNS: &'static [&'static str] = &["file", "time_s"];
}

const IMAGE_EXTENSIONS: [&str; 7] = ["png", "jpg", "jpeg", "bmp", "tif", "tiff", "pgm"];

/// Images of a folder in capture order, each with its time (s).
pub fn folder_index(dir: &Path, fps: f64) -> Result<Vec<(PathBuf, f64)>, SourceError> {
    let unusable = |m: String| SourceError::Unusable(m);
    let csv = dir.join(TimestampRow::FILE_NAME);
    if csv.is_file() {
        let rows: Vec<TimestampRow> =
            runlog::read_rows(&csv).map_err(|e| unusable(e.to_string()))?;
        let mut index = Vec::with_capacity(rows.len());
        for (k, row) in rows.iter().enumerate() {
            let path = dir.join(&row.file);
            if !path.is_file() {
                return Err(unusable(format!(
                    "{} row {}: file {:?} is not in the folder",
                    csv.display(),
                    k + 2,
                    row.file
                )));
            }
            if !row.time_s.is_finite() || index.last().is_some_and(|(_, t)| row.time_s < *t) {
                return Err(unusable(format!(
                    "{} row {}: time_s = {} must be finite and not decrease",
                    csv.display(),
                    k + 2,
                    row.time_s
                )));
            }
            index.push((path, row.time_s));
        }
        if index.is_empty() {
            return Err(unusable(format!("{} lists no images", csv.display())));
        }
        return Ok(index);
    }
    let entries = std::fs::read_dir(dir)
        .map_err(|e| unusable(format!("cannot read image folder {}: {e}", dir.display())))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| IMAGE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(unusable(format!(
            "image folder {} holds no images ({})",
            dir.display(),
            IMAGE_EXTENSIONS.join(", ")
        )));
    }
    Ok(files
        .into_iter()
        .enumerate()
        .map(|(k, p)| (p, k as f64 / fps))
        .collect())
}

pub fn read_image(path: &Path) -> Result<cv::Mat, SourceError> {
    let image = imgcodecs::imread(path, imgcodecs::IMREAD_UNCHANGED)?;
    if image.empty() {
        return Err(SourceError::Unusable(format!(
            "cannot read image {} (missing, truncated or not an image)",
            path.display()
        )));
    }
    Ok(image)
}

/// Images read one per pull.
pub struct FolderSource {
    index: Vec<(PathBuf, f64)>,
    next: usize,
    incarnation: u64,
}

impl FolderSource {
    pub fn open(dir: &Path, fps: f64, incarnation: u64) -> Result<Self, SourceError> {
        Ok(Self {
            index: folder_index(dir, fps)?,
            next: 0,
            incarnation,
        })
    }
}

impl FrameSource for FolderSource {
    fn pull(&mut self, _timeout: Duration, notes: &mut Vec<Note>) -> Result<Pulled, SourceError> {
        let Some((path, time_s)) = self.index.get(self.next).cloned() else {
            return Ok(Pulled::Ended(format!(
                "end of folder ({} images)",
                self.index.len()
            )));
        };
        let seq = self.next as u64;
        self.next += 1;
        let image =
            match read_image(&path).and_then(|m| accept_pixels(m, &path.display().to_string())) {
                Ok(image) => image,
                Err(e) => {
                    notes.push(Note::fault("bad_frame", e.to_string()));
                    return Ok(Pulled::Nothing);
                }
            };
        let t_ns = clock::secs_to_ns(time_s - self.index[0].1);
        Ok(Pulled::Frame(RawFrame {
            image: image.0,
            channels: image.1,
            stamp: FrameStamp::new(seq, self.incarnation, t_ns).grabbed_at(t_ns),
        }))
    }

    fn paced(&self) -> bool {
        true
    }
}
