//! The run's Rerun recording. Every process logs into the same recording id; each writes its own
//! `.rrd` under `<run_dir>/rrd/` (a process cannot share a file with another), and the supervisor
//! joins them into `<run_dir>/run.rrd` at shutdown. A viewer, when one is wanted, gets the same
//! stream over gRPC. Rerun is never in a control loop's critical path: the SDK batches and writes
//! on its own thread.

use std::path::{Path, PathBuf};

use rerun::sink::{FileSink, GrpcSink};
use shm_schemas::ServiceId;

use crate::{KitError, RunEnv};

pub const APPLICATION_ID: &str = "millinav";

/// Timeline of the run clock (sim time in lockstep), in seconds.
pub const RUN_TIMELINE: &str = "run_time";
/// Timeline of camera frame sequence numbers.
pub const FRAME_TIMELINE: &str = "frame";

/// Directory holding the per-process recordings of a run.
pub fn rrd_dir(run_dir: &Path) -> PathBuf {
    run_dir.join("rrd")
}

/// File of one process incarnation's recording.
pub fn rrd_path(run_dir: &Path, service: ServiceId, incarnation: u64) -> PathBuf {
    rrd_dir(run_dir).join(format!("{}-{incarnation}.rrd", service.name()))
}

/// Opens this process's stream of the run's recording (disabled when `MILLINAV_RERUN=off`).
pub fn open(env: &RunEnv, service: ServiceId) -> Result<rerun::RecordingStream, KitError> {
    if !env.rerun_enabled {
        return Ok(rerun::RecordingStream::disabled());
    }
    std::fs::create_dir_all(rrd_dir(&env.run_dir))?;
    let path = rrd_path(&env.run_dir, service, env.incarnation);
    let builder = rerun::RecordingStreamBuilder::new(APPLICATION_ID)
        .recording_id(env.recording_id.clone())
        // Only the supervisor describes the recording; the others just add data to it.
        .send_properties(service == ServiceId::Supervisor);
    let file = FileSink::new(&path).map_err(|e| KitError::Rerun(format!("{path:?}: {e}")))?;
    let rec = match &env.rerun_connect {
        Some(url) => {
            let uri = url
                .parse()
                .map_err(|e| KitError::Rerun(format!("viewer url {url:?}: {e}")))?;
            builder.set_sinks((file, GrpcSink::new(uri)))
        }
        None => builder.set_sinks((file,)),
    }
    .map_err(|e| KitError::Rerun(e.to_string()))?;
    Ok(rec)
}

/// Sets both timelines for what follows on this thread.
pub fn set_time(rec: &rerun::RecordingStream, run_time_ns: u64, frame_seq: u64) {
    rec.set_duration_secs(RUN_TIMELINE, crate::clock::ns_to_secs(run_time_ns));
    rec.set_time_sequence(FRAME_TIMELINE, frame_seq as i64);
}

/// Logs a scalar series point, ignoring logging errors (logging never stops control).
pub fn scalar(rec: &rerun::RecordingStream, path: &str, value: f64) {
    let _ = rec.log(path, &rerun::Scalars::single(value));
}

/// Joins the per-process recordings into one file. RRD streams concatenate: a decoder reads
/// one stream after another, and all of them carry the same recording id.
pub fn join_recordings(run_dir: &Path, out: &Path) -> Result<usize, KitError> {
    let mut parts: Vec<PathBuf> = std::fs::read_dir(rrd_dir(run_dir))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "rrd"))
        .collect();
    parts.sort();
    let mut joined = std::fs::File::create(out)?;
    for part in &parts {
        let mut input = std::fs::File::open(part)?;
        std::io::copy(&mut input, &mut joined)?;
    }
    Ok(parts.len())
}

/// A packed RGB camera image (`w`×`h`, 3 bytes a pixel) as the recording holds it: JPEG at
/// `quality` (1–100, the viewer's bandwidth and the file's size), the raw pixels at 0 or when
/// encoding fails.
pub fn camera_image(rgb: Vec<u8>, w: usize, h: usize, quality: u8) -> Box<dyn rerun::AsComponents> {
    match (quality > 0).then(|| jpeg(&rgb, w, h, quality)).flatten() {
        Some(bytes) => Box::new(rerun::EncodedImage::from_file_contents(bytes)),
        None => Box::new(rerun::Image::from_rgb24(rgb, [w as u32, h as u32])),
    }
}

/// `rgb` (`w`×`h`, 3 bytes a pixel) as a JPEG file at `quality` (clamped to 1–100); `None` when
/// the pixels are not `w`×`h` or do not encode.
pub fn jpeg(rgb: &[u8], w: usize, h: usize, quality: u8) -> Option<Vec<u8>> {
    if rgb.len() != w * h * 3 {
        return None;
    }
    let (w, h) = (u32::try_from(w).ok()?, u32::try_from(h).ok()?);
    let mut bytes = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, quality.clamp(1, 100))
        .encode(rgb, w, h, image::ExtendedColorType::Rgb8)
        .ok()?;
    Some(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_camera_image_encodes_to_a_jpeg_that_decodes_to_its_pixels() {
        let (w, h) = (48usize, 32usize);
        let rgb: Vec<u8> = (0..w * h)
            .flat_map(|i| {
                let (x, y) = (i % w, i / w);
                [(x * 5) as u8, (y * 7) as u8, 128]
            })
            .collect();
        let bytes = jpeg(&rgb, w, h, 90).expect("encodes");
        assert_eq!(&bytes[..2], &[0xFF, 0xD8], "a JPEG starts with SOI");
        let decoded = image::load_from_memory_with_format(&bytes, image::ImageFormat::Jpeg)
            .expect("decodes")
            .to_rgb8();
        assert_eq!((decoded.width(), decoded.height()), (w as u32, h as u32));
        let worst = rgb
            .iter()
            .zip(decoded.as_raw())
            .map(|(a, b)| a.abs_diff(*b))
            .max()
            .unwrap();
        assert!(worst <= 24, "largest pixel error {worst}");
        assert_eq!(jpeg(&rgb[1..], w, h, 90), None, "pixels not w×h×3");
    }
}
