//! The camera service's sources without hardware: image folders (with and without timestamps),
//! video files through VideoCapture, lossless recording and replay (and a truncated recording),
//! and bad input refused by `prepare` with the file and field named, before anything starts.

use std::path::{Path, PathBuf};
use std::time::Duration;

use millinav_camera::record::{Recorder, ReplaySource, FRAMES_DIR, VIDEO_FILE};
use millinav_camera::source::{
    CaptureSource, Channels, DeviceRequest, FolderSource, FrameSource, Pulled, RawFrame, SourceSpec,
};
use millinav_kit::scenario::Scenario;
use opencv::core as cv;
use opencv::prelude::*;
use opencv::{imgcodecs, videoio};
use shm_schemas::FrameStamp;

/// A fresh directory of this test process, removed when the test ends (passed or failed).
struct TempDir(PathBuf);

impl std::ops::Deref for TempDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn temp_dir(name: &str) -> TempDir {
    let dir = std::env::temp_dir().join(format!("millinav-camera-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    TempDir(dir)
}

/// A deterministic, textured 3-channel test image.
fn pattern(w: i32, h: i32, k: u8) -> cv::Mat {
    let mut m = cv::Mat::new_rows_cols_with_default(h, w, cv::CV_8UC3, 0.0.into()).unwrap();
    for (i, b) in m.data_bytes_mut().unwrap().iter_mut().enumerate() {
        *b = ((i * 7 + i / 97 * 13) as u8).wrapping_add(k.wrapping_mul(31));
    }
    m
}

fn pull_all(source: &mut dyn FrameSource) -> (Vec<RawFrame>, String) {
    let mut frames = Vec::new();
    let mut notes = Vec::new();
    for _ in 0..1000 {
        match source.pull(Duration::from_millis(500), &mut notes).unwrap() {
            Pulled::Frame(f) => frames.push(f),
            Pulled::Nothing => {}
            Pulled::Ended(why) => return (frames, why),
            Pulled::Terminated => panic!("terminated"),
        }
    }
    panic!("the source never ended");
}

#[test]
fn a_folder_plays_in_order_at_its_timestamps() {
    let dir = temp_dir("folder");
    for k in 0..4u8 {
        imgcodecs::imwrite_def(dir.join(format!("f{k}.png")), &pattern(64, 48, k)).unwrap();
    }
    std::fs::write(
        dir.join("timestamps.csv"),
        "file,time_s\nf0.png,10.0\nf1.png,10.05\nf2.png,10.2\nf3.png,10.25\n",
    )
    .unwrap();
    let mut source = FolderSource::open(&dir, 10.0, 0).unwrap();
    let (frames, why) = pull_all(&mut source);
    assert_eq!(frames.len(), 4);
    assert!(why.contains("4 images"), "{why}");
    let times: Vec<u64> = frames.iter().map(|f| f.stamp.capture_time_ns).collect();
    assert_eq!(times, vec![0, 50_000_000, 200_000_000, 250_000_000]);
    assert!(frames.iter().all(|f| f.channels == Channels::Bgr));
    assert_eq!(
        frames[2].image.data_bytes().unwrap(),
        pattern(64, 48, 2).data_bytes().unwrap()
    );
    // Without timestamps: sorted by name at the given rate.
    std::fs::remove_file(dir.join("timestamps.csv")).unwrap();
    let mut source = FolderSource::open(&dir, 20.0, 0).unwrap();
    let (frames, _) = pull_all(&mut source);
    assert_eq!(frames[3].stamp.capture_time_ns, 150_000_000);
    // A timestamps file naming a missing image is refused by row.
    std::fs::write(
        dir.join("timestamps.csv"),
        "file,time_s\nf0.png,0\nnope.png,1\n",
    )
    .unwrap();
    let error = FolderSource::open(&dir, 10.0, 0).err().unwrap().to_string();
    assert!(
        error.contains("row 3") && error.contains("nope.png"),
        "{error}"
    );
}

#[test]
fn a_video_file_plays_through_videocapture_to_its_end() {
    let dir = temp_dir("video");
    let path = dir.join("clip.avi");
    let mut writer = videoio::VideoWriter::new(
        &path,
        videoio::VideoWriter::fourcc('M', 'J', 'P', 'G').unwrap(),
        25.0,
        cv::Size::new(64, 48),
        true,
    )
    .unwrap();
    assert!(writer.is_opened().unwrap());
    for k in 0..6 {
        writer.write(&pattern(64, 48, k)).unwrap();
    }
    writer.release().unwrap();
    let request = DeviceRequest {
        width: 64,
        height: 48,
        fps: None,
        exposure: None,
    };
    let mut notes = Vec::new();
    let mut source = CaptureSource::start(
        SourceSpec::File(path),
        request,
        0,
        0,
        Duration::from_millis(100),
        &mut notes,
    )
    .unwrap();
    let (frames, why) = pull_all(&mut source);
    assert_eq!(frames.len(), 6, "{why}");
    assert!(why.contains("end of file after 6 frames"), "{why}");
    // The file's own timing: 25 fps.
    let step = frames[5].stamp.capture_time_ns - frames[4].stamp.capture_time_ns;
    assert!((step as f64 - 40e6).abs() < 1e6, "{step} ns");
    assert_eq!(frames[5].stamp.seq, 5);
}

fn write_recording(run_dir: &Path, frames: u8) {
    let mut recorder = Recorder::create(run_dir, 10.0).unwrap();
    for k in 0..frames {
        let mut rgb = cv::Mat::default();
        opencv::imgproc::cvt_color(
            &pattern(96, 64, k),
            &mut rgb,
            opencv::imgproc::COLOR_BGR2RGB,
            0,
        )
        .unwrap();
        recorder
            .write(&RawFrame {
                image: rgb,
                channels: Channels::Rgb,
                stamp: FrameStamp::new(u64::from(k), 2, u64::from(k) * 100_000_000)
                    .grabbed_at(u64::from(k) * 100_000_000 + 30_000_000),
            })
            .unwrap();
    }
    recorder.finish().unwrap();
}

#[test]
fn a_recording_replays_losslessly_with_its_stamps() {
    let run_dir = temp_dir("replay");
    write_recording(&run_dir, 12);
    let mut replay = ReplaySource::open(&run_dir).unwrap();
    assert_eq!(replay.frame_count(), 12);
    let (frames, why) = pull_all(&mut replay);
    assert!(why.contains("end of the recording (12 frames)"), "{why}");
    assert_eq!(frames.len(), 12);
    for (k, frame) in frames.iter().enumerate() {
        assert_eq!(frame.stamp.seq, k as u64);
        assert_eq!(frame.stamp.incarnation, 2);
        assert_eq!(
            frame.stamp.grab_time_ns,
            k as u64 * 100_000_000 + 30_000_000
        );
        // FFV1 is lossless: the very bytes that were recorded (as BGR).
        assert_eq!(frame.channels, Channels::Bgr);
        assert_eq!(
            frame.image.data_bytes().unwrap(),
            pattern(96, 64, k as u8).data_bytes().unwrap(),
            "frame {k} changed in the recording"
        );
    }
}

#[test]
fn a_truncated_recording_ends_with_the_reason() {
    let run_dir = temp_dir("truncated");
    write_recording(&run_dir, 40);
    let video = run_dir.join(FRAMES_DIR).join(VIDEO_FILE);
    let bytes = std::fs::read(&video).unwrap();
    std::fs::write(&video, &bytes[..bytes.len() / 2]).unwrap();
    let mut replay = ReplaySource::open(&run_dir).unwrap();
    let (frames, why) = pull_all(&mut replay);
    assert!(
        frames.len() < 40 && !frames.is_empty(),
        "{} frames",
        frames.len()
    );
    assert!(why.contains("truncated"), "{why}");
    assert!(
        why.contains(&format!("after {} of the 40", frames.len())),
        "{why}"
    );
}

/// A scenario on the committed vessel8 rig (it has a real camera) with `camera` as its table.
fn scenario(dir: &Path, camera: &str, rig: Option<&Path>) -> Scenario {
    let rig = rig.map_or_else(
        || "fieldmaps/rigs/vessel8.toml".to_string(),
        |p| p.display().to_string(),
    );
    let text = format!(
        "[run]\nmode = \"lockstep\"\nseed = 1\nduration_s = 1.0\nframe_period_ms = 100.0\n\
         rig = {rig:?}\n\n[fluid]\nviscosity_cp = 20.0\n\n[trajectory]\n\
         waypoints_mm = [[0.0, 0.0], [1.0, 0.0]]\nspeed_mm_s = 1.0\n\n[camera]\n{camera}\n"
    );
    let path = dir.join("scenario.toml");
    std::fs::write(&path, &text).unwrap();
    Scenario::load(&path).unwrap()
}

fn prepare_error(scenario: &Scenario) -> String {
    match millinav_camera::prepare(scenario) {
        Ok(_) => panic!("the camera accepted a bad source"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn bad_sources_are_refused_before_anything_is_published() {
    let dir = temp_dir("bad");
    // A device that is not there.
    let error = prepare_error(&scenario(&dir, "source = \"/dev/video97\"", None));
    assert!(
        error.contains("[camera] source") && error.contains("/dev/video97"),
        "{error}"
    );
    // Not a source at all.
    let error = prepare_error(&scenario(&dir, "source = \"webcam please\"", None));
    assert!(error.contains("replay:<run dir>"), "{error}");
    // A folder of 16-bit images: an unsupported pixel format.
    let deep = dir.join("deep");
    std::fs::create_dir_all(&deep).unwrap();
    let sixteen =
        cv::Mat::new_rows_cols_with_default(1024, 1280, cv::CV_16UC1, 1000.0.into()).unwrap();
    imgcodecs::imwrite_def(deep.join("a.png"), &sixteen).unwrap();
    let error = prepare_error(&scenario(
        &dir,
        &format!("source = \"folder:{}\"", deep.display()),
        None,
    ));
    assert!(
        error.contains("unsupported pixel format (16 bits"),
        "{error}"
    );
    // Frames of another size than the rig's camera.
    let small = dir.join("small");
    std::fs::create_dir_all(&small).unwrap();
    imgcodecs::imwrite_def(small.join("a.png"), &pattern(640, 480, 0)).unwrap();
    let error = prepare_error(&scenario(
        &dir,
        &format!("source = \"folder:{}\"", small.display()),
        None,
    ));
    assert!(
        error.contains("640x480") && error.contains("1280x1024"),
        "{error}"
    );
    // A run without a recording.
    let error = prepare_error(&scenario(
        &dir,
        &format!("source = \"replay:{}\"", dir.display()),
        None,
    ));
    assert!(error.contains("--record-frames"), "{error}");
    // A bad table value.
    let error = prepare_error(&scenario(&dir, "fps = -3.0", None));
    assert!(error.contains("[camera] fps"), "{error}");
}

/// A rig whose lens pushes part of the canonical view outside the raw image: the camera refuses
/// it (naming the rig file and table) instead of showing vision a half-black phantom.
#[test]
fn a_registration_that_misses_part_of_the_view_is_refused() {
    let dir = temp_dir("outside");
    let rigs = fieldmaps::data_root().join("fieldmaps/rigs");
    let text = std::fs::read_to_string(rigs.join("vessel8.toml")).unwrap();
    let text = text
        .replace(
            "\"vessel8/",
            &format!("\"{}/", rigs.join("vessel8").display()),
        )
        .replace(
            "distortion_coefficients = [-0.11, 0.06, 0.0006, -0.0004, 0.0]",
            "distortion_coefficients = [3.0, 5.0, 0.0, 0.0, 0.0]",
        );
    assert!(text.contains("[3.0, 5.0"), "vessel8.toml's lens changed");
    let rig = dir.join("rig.toml");
    std::fs::write(&rig, text).unwrap();
    let error = prepare_error(&scenario(&dir, "source = \"twin\"", Some(&rig)));
    assert!(
        error.contains("rig.toml") && error.contains("[camera.calibration]"),
        "{error}"
    );
    assert!(error.contains("outside the raw 1280x1024 image"), "{error}");
}
