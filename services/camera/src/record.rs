//! Recording the raw camera stream losslessly (`millinav run --record-frames`) and replaying it
//! (`[camera] source = "replay:<run dir>"`).
//!
//! Layout inside a run directory: `frames/raw.mkv` (FFV1, lossless, BGR as OpenCV writes it) and
//! `frames/frames.csv` (one row per frame, in order: its stamp as the set saw it).

use std::path::{Path, PathBuf};
use std::time::Duration;

use millinav_kit::runlog::{self, RunLogRow, RunLogWriter};
use opencv::core as cv;
use opencv::prelude::*;
use opencv::{imgproc, videoio};
use serde::{Deserialize, Serialize};
use shm_schemas::FrameStamp;

use crate::source::{accept_pixels, FrameSource, Note, Pulled, RawFrame, SourceError};

pub const FRAMES_DIR: &str = "frames";
pub const VIDEO_FILE: &str = "raw.mkv";

/// One recorded frame's stamp (`frames/frames.csv`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecordedFrameRow {
    pub seq: u64,
    pub incarnation: u64,
    pub capture_time_ns: u64,
    pub grab_time_ns: u64,
}

impl RunLogRow for RecordedFrameRow {
    const FILE_NAME: &'static str = "frames.csv";
    const COLUMNS: &'static [&'static str] =
        &["seq", "incarnation", "capture_time_ns", "grab_time_ns"];
}

/// Writes every raw frame the service publishes.
pub struct Recorder {
    dir: PathBuf,
    fps: f64,
    writer: Option<videoio::VideoWriter>,
    rows: RunLogWriter<RecordedFrameRow>,
    bgr: cv::Mat,
    pub frames: u64,
}

impl Recorder {
    /// Starts a recording in `<run_dir>/frames` (an existing one, e.g. from a restarted camera
    /// service, is continued in a new numbered video: raw.1.mkv, ...; the CSV goes on).
    pub fn create(run_dir: &Path, fps: f64) -> Result<Self, SourceError> {
        let dir = run_dir.join(FRAMES_DIR);
        std::fs::create_dir_all(&dir)
            .map_err(|e| SourceError::Unusable(format!("cannot create {}: {e}", dir.display())))?;
        let rows = RunLogWriter::open_append(&dir.join(RecordedFrameRow::FILE_NAME))
            .map_err(|e| SourceError::Unusable(e.to_string()))?;
        Ok(Self {
            dir,
            fps,
            writer: None,
            rows,
            bgr: cv::Mat::default(),
            frames: 0,
        })
    }

    /// Appends a frame (lossless); the video opens on the first frame, at its size.
    pub fn write(&mut self, frame: &RawFrame) -> Result<(), SourceError> {
        let image = match frame.channels {
            crate::source::Channels::Bgr => &frame.image,
            crate::source::Channels::Rgb => {
                imgproc::cvt_color(&frame.image, &mut self.bgr, imgproc::COLOR_RGB2BGR, 0)?;
                &self.bgr
            }
            crate::source::Channels::Gray => {
                imgproc::cvt_color(&frame.image, &mut self.bgr, imgproc::COLOR_GRAY2BGR, 0)?;
                &self.bgr
            }
        };
        if self.writer.is_none() {
            let path = (0..)
                .map(|k| {
                    self.dir.join(if k == 0 {
                        VIDEO_FILE.to_string()
                    } else {
                        format!("raw.{k}.mkv")
                    })
                })
                .find(|p| !p.exists())
                .unwrap_or_else(|| self.dir.join(VIDEO_FILE));
            let fourcc = videoio::VideoWriter::fourcc('F', 'F', 'V', '1')?;
            let writer =
                videoio::VideoWriter::new(path.as_path(), fourcc, self.fps, image.size()?, true)?;
            if !writer.is_opened()? {
                return Err(SourceError::Unusable(format!(
                    "cannot write {} (OpenCV's FFmpeg backend has no FFV1 encoder?)",
                    path.display()
                )));
            }
            self.writer = Some(writer);
        }
        if let Some(writer) = self.writer.as_mut() {
            writer.write(image)?;
        }
        // Flushed per frame: a camera killed mid-run leaves a recording that replays to there.
        self.rows
            .append_now(&RecordedFrameRow {
                seq: frame.stamp.seq,
                incarnation: frame.stamp.incarnation,
                capture_time_ns: frame.stamp.capture_time_ns,
                grab_time_ns: frame.stamp.grab_time_ns,
            })
            .map_err(|e| SourceError::Unusable(e.to_string()))?;
        self.frames += 1;
        Ok(())
    }

    /// Closes the video and flushes the CSV.
    pub fn finish(&mut self) -> Result<(), SourceError> {
        if let Some(mut writer) = self.writer.take() {
            writer.release()?;
        }
        self.rows
            .flush()
            .map_err(|e| SourceError::Unusable(e.to_string()))
    }
}

/// The videos of a recording in order (raw.mkv, raw.1.mkv, ...).
fn recorded_videos(dir: &Path) -> Vec<PathBuf> {
    (0..)
        .map(|k| {
            dir.join(if k == 0 {
                VIDEO_FILE.to_string()
            } else {
                format!("raw.{k}.mkv")
            })
        })
        .take_while(|p| p.is_file())
        .collect()
}

/// Replays a recorded run's raw frames with their recorded stamps.
pub struct ReplaySource {
    rows: Vec<RecordedFrameRow>,
    videos: Vec<PathBuf>,
    capture: Option<videoio::VideoCapture>,
    next_video: usize,
    next: usize,
}

impl ReplaySource {
    /// Opens `<run_dir>/frames`; errors name what is missing.
    pub fn open(run_dir: &Path) -> Result<Self, SourceError> {
        let dir = run_dir.join(FRAMES_DIR);
        let csv = dir.join(RecordedFrameRow::FILE_NAME);
        if !csv.is_file() {
            return Err(SourceError::Unusable(format!(
                "{} has no recorded frames ({} missing): record a run with \
                 `millinav run --record-frames`",
                run_dir.display(),
                csv.display()
            )));
        }
        let rows: Vec<RecordedFrameRow> =
            runlog::read_rows(&csv).map_err(|e| SourceError::Unusable(e.to_string()))?;
        let videos = recorded_videos(&dir);
        if videos.is_empty() || rows.is_empty() {
            return Err(SourceError::Unusable(format!(
                "{}: the recording is empty (no {VIDEO_FILE} or no rows in {})",
                dir.display(),
                csv.display()
            )));
        }
        let mut source = Self {
            rows,
            videos,
            capture: None,
            next_video: 0,
            next: 0,
        };
        source.open_next_video()?;
        Ok(source)
    }

    pub fn frame_count(&self) -> usize {
        self.rows.len()
    }

    fn open_next_video(&mut self) -> Result<bool, SourceError> {
        let Some(path) = self.videos.get(self.next_video) else {
            self.capture = None;
            return Ok(false);
        };
        self.next_video += 1;
        let capture = videoio::VideoCapture::from_file(path.as_path(), videoio::CAP_FFMPEG)?;
        if !capture.is_opened()? {
            return Err(SourceError::Unusable(format!(
                "cannot open the recorded video {}",
                path.display()
            )));
        }
        self.capture = Some(capture);
        Ok(true)
    }

    /// Reads the first frame without consuming it, to check its size.
    pub fn first_frame(run_dir: &Path) -> Result<cv::Mat, SourceError> {
        let mut probe = Self::open(run_dir)?;
        let mut notes = Vec::new();
        match probe.pull(Duration::ZERO, &mut notes)? {
            Pulled::Frame(frame) => Ok(frame.image),
            _ => Err(SourceError::Unusable(format!(
                "{}: the recorded video holds no frame",
                run_dir.display()
            ))),
        }
    }
}

impl FrameSource for ReplaySource {
    fn pull(&mut self, _timeout: Duration, _notes: &mut Vec<Note>) -> Result<Pulled, SourceError> {
        let Some(row) = self.rows.get(self.next).cloned() else {
            return Ok(Pulled::Ended(format!(
                "end of the recording ({} frames)",
                self.rows.len()
            )));
        };
        let mut image = cv::Mat::default();
        loop {
            let Some(capture) = self.capture.as_mut() else {
                return Ok(Pulled::Ended(format!(
                    "the recording is truncated: its video ends after {} of the {} frames \
                     frames.csv lists",
                    self.next,
                    self.rows.len()
                )));
            };
            if capture.read(&mut image).unwrap_or(false) && !image.empty() {
                break;
            }
            self.open_next_video()?;
        }
        self.next += 1;
        let (image, channels) = accept_pixels(image, "recorded frame")?;
        Ok(Pulled::Frame(RawFrame {
            image,
            channels,
            stamp: FrameStamp {
                seq: row.seq,
                incarnation: row.incarnation,
                capture_time_ns: row.capture_time_ns,
                grab_time_ns: row.grab_time_ns,
            },
        }))
    }

    fn paced(&self) -> bool {
        true
    }
}
