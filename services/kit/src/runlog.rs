//! The run directory's CSV logs: one row type per log, written and read through the `csv` crate
//! by the processes that write them (plant, coilbus, supervisor) and the tools that read them
//! (experiments, bench, the test harness).
//!
//! Readers find columns by header name, so a column added later, or columns in another order,
//! never break a reader; a column a reader needs and the file lacks is an error naming the file
//! and the column. Writers open logs for appending and write the header only into a new file:
//! a restarted process continues its log. Free text (event details) is quoted by the `csv`
//! crate, never edited. Column names and order are those README documents.

use std::marker::PhantomData;
use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// A row of one run-directory log.
pub trait RunLogRow: Serialize + DeserializeOwned {
    /// File name inside a run directory.
    const FILE_NAME: &'static str;
    /// Columns in the order the writer writes them (the struct's field order).
    const COLUMNS: &'static [&'static str];
    /// Columns older files may lack; the row type gives them a default when read.
    const OPTIONAL_COLUMNS: &'static [&'static str] = &[];
}

#[derive(Debug, thiserror::Error)]
pub enum RunLogError {
    #[error("{}: {source}", .path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: missing column `{column}` (header: {header})", .path.display())]
    MissingColumn {
        path: PathBuf,
        column: &'static str,
        header: String,
    },
    #[error("{}: line {line}{}: {message}", .path.display(), column_suffix(.column))]
    BadRow {
        path: PathBuf,
        line: u64,
        column: Option<String>,
        message: String,
    },
    #[error("{}: cannot write a row: {message}", .path.display())]
    Write { path: PathBuf, message: String },
}

fn column_suffix(column: &Option<String>) -> String {
    column
        .as_ref()
        .map(|c| format!(", column `{c}`"))
        .unwrap_or_default()
}

/// Appends rows of one log; the header is written only when the file is new (or empty).
pub struct RunLogWriter<R> {
    out: csv::Writer<std::fs::File>,
    path: PathBuf,
    _row: PhantomData<fn(&R)>,
}

impl<R: RunLogRow> RunLogWriter<R> {
    /// Opens `<run_dir>/<R::FILE_NAME>` for appending.
    pub fn in_run_dir(run_dir: &Path) -> Result<Self, RunLogError> {
        Self::open_append(&run_dir.join(R::FILE_NAME))
    }

    /// Opens `path` for appending, writing the header first when the file is new or empty.
    pub fn open_append(path: &Path) -> Result<Self, RunLogError> {
        let io = |source| RunLogError::Io {
            path: path.to_owned(),
            source,
        };
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .map_err(io)?;
        let fresh = file.metadata().map_err(io)?.len() == 0;
        let mut out = csv::WriterBuilder::new()
            .has_headers(false)
            .from_writer(file);
        if fresh {
            out.write_record(R::COLUMNS)
                .and_then(|()| out.flush().map_err(csv::Error::from))
                .map_err(|e| RunLogError::Write {
                    path: path.to_owned(),
                    message: e.to_string(),
                })?;
        }
        Ok(Self {
            out,
            path: path.to_owned(),
            _row: PhantomData,
        })
    }

    /// Appends one row (buffered; see `flush`).
    pub fn append(&mut self, row: &R) -> Result<(), RunLogError> {
        self.out.serialize(row).map_err(|e| self.write_error(e))
    }

    /// Appends one row and flushes it, for logs that are read while the run goes on.
    pub fn append_now(&mut self, row: &R) -> Result<(), RunLogError> {
        self.append(row)?;
        self.flush()
    }

    pub fn flush(&mut self) -> Result<(), RunLogError> {
        self.out.flush().map_err(|source| RunLogError::Io {
            path: self.path.clone(),
            source,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    fn write_error(&self, e: csv::Error) -> RunLogError {
        RunLogError::Write {
            path: self.path.clone(),
            message: e.to_string(),
        }
    }
}

/// Reads `<run_dir>/<R::FILE_NAME>`.
pub fn read_run_dir<R: RunLogRow>(run_dir: &Path) -> Result<Vec<R>, RunLogError> {
    read_rows(&run_dir.join(R::FILE_NAME))
}

/// Reads every complete row of a log (a last line still being written is left out).
pub fn read_rows<R: RunLogRow>(path: &Path) -> Result<Vec<R>, RunLogError> {
    let text = std::fs::read_to_string(path).map_err(|source| RunLogError::Io {
        path: path.to_owned(),
        source,
    })?;
    parse_rows(&text, path)
}

/// Parses a log's text; `path` names it in errors.
pub fn parse_rows<R: RunLogRow>(text: &str, path: &Path) -> Result<Vec<R>, RunLogError> {
    // A writer appends whole lines; anything after the last newline is a row in progress.
    let complete = match text.rfind('\n') {
        Some(end) => &text[..=end],
        None => "",
    };
    if complete.trim().is_empty() {
        return Ok(Vec::new());
    }
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(true)
        .from_reader(complete.as_bytes());
    let header = reader
        .headers()
        .map_err(|e| bad_row(path, &e, None))?
        .clone();
    for column in R::COLUMNS {
        if !R::OPTIONAL_COLUMNS.contains(column) && !header.iter().any(|h| h == *column) {
            return Err(RunLogError::MissingColumn {
                path: path.to_owned(),
                column,
                header: header.iter().collect::<Vec<_>>().join(","),
            });
        }
    }
    reader
        .deserialize()
        .map(|row| row.map_err(|e| bad_row(path, &e, Some(&header))))
        .collect()
}

fn bad_row(path: &Path, error: &csv::Error, header: Option<&csv::StringRecord>) -> RunLogError {
    let line = error.position().map_or(0, |p| p.line());
    let (column, message) = match error.kind() {
        csv::ErrorKind::Deserialize { err, .. } => (
            err.field()
                .and_then(|i| header?.get(i as usize))
                .map(str::to_owned),
            err.kind().to_string(),
        ),
        _ => (None, error.to_string()),
    };
    RunLogError::BadRow {
        path: path.to_owned(),
        line,
        column,
        message,
    }
}

/// Writes a float with 6 decimals (the logs' fixed format: same bytes for the same run).
fn fixed6<S: Serializer>(value: &f64, s: S) -> Result<S::Ok, S::Error> {
    s.collect_str(&format_args!("{value:.6}"))
}

/// Writes a float with 9 decimals (positions and speeds: sub-micrometre).
fn fixed9<S: Serializer>(value: &f64, s: S) -> Result<S::Ok, S::Error> {
    s.collect_str(&format_args!("{value:.9}"))
}

fn fixed6_some<S: Serializer>(value: &Option<f64>, s: S) -> Result<S::Ok, S::Error> {
    match value {
        Some(v) => fixed6(v, s),
        None => s.serialize_none(),
    }
}

/// A flag written as `0` / `1`.
mod flag01 {
    use super::*;

    pub fn serialize<S: Serializer>(value: &bool, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_u8(u8::from(*value))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<bool, D::Error> {
        match u8::deserialize(d)? {
            0 => Ok(false),
            1 => Ok(true),
            other => Err(serde::de::Error::custom(format!(
                "expected 0 or 1, found {other}"
            ))),
        }
    }
}

/// A frame sequence number written as `-1` when there is none.
mod frame_or_minus_one {
    use super::*;

    pub fn serialize<S: Serializer>(value: &Option<u64>, s: S) -> Result<S::Ok, S::Error> {
        match value {
            Some(seq) => s.serialize_u64(*seq),
            None => s.serialize_i64(-1),
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<u64>, D::Error> {
        let seq = i64::deserialize(d)?;
        Ok(u64::try_from(seq).ok())
    }
}

/// The plant's ground truth, one row per published frame (`truth.csv`; for metrics only, never
/// read by a controller). A republishing plant repeats a frame's row; a restarted plant counts
/// its frames from 0 again under a new `frame_incarnation`, so a frame is (incarnation, seq).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TruthRow {
    pub frame_seq: u64,
    /// Incarnation of the frame's source (logs written before this column existed: 0).
    #[serde(default)]
    pub frame_incarnation: u64,
    #[serde(serialize_with = "fixed6")]
    pub sim_time_s: f64,
    #[serde(serialize_with = "fixed9")]
    pub x_m: f64,
    #[serde(serialize_with = "fixed9")]
    pub y_m: f64,
    #[serde(serialize_with = "fixed9")]
    pub vx_mps: f64,
    #[serde(serialize_with = "fixed9")]
    pub vy_mps: f64,
    #[serde(serialize_with = "fixed6")]
    pub heading_rad: f64,
    #[serde(serialize_with = "fixed9")]
    pub flow_x_mps: f64,
    #[serde(serialize_with = "fixed9")]
    pub flow_y_mps: f64,
    #[serde(with = "flag01")]
    pub wall_contact: bool,
    #[serde(serialize_with = "fixed6")]
    pub max_abs_current_a: f64,
    pub lockstep_misses: u64,
    /// Σ I² over the coils (A²); traces written before this column existed lack it.
    #[serde(default, serialize_with = "fixed6_some")]
    pub sum_sq_current_a2: Option<f64>,
    /// Current in each of the rig's coils (A, space separated, the rig's order); traces written
    /// before this column existed lack it.
    #[serde(default)]
    pub coil_currents_a: Option<String>,
}

impl TruthRow {
    /// The per-coil currents as written by [`Self::format_currents`], if the row has them.
    pub fn currents(&self) -> Option<Result<Vec<f64>, std::num::ParseFloatError>> {
        self.coil_currents_a
            .as_deref()
            .map(|text| text.split_whitespace().map(str::parse).collect())
    }

    /// The `coil_currents_a` column for `currents`.
    pub fn format_currents(currents: &[f64]) -> String {
        currents
            .iter()
            .map(|c| format!("{c:.6}"))
            .collect::<Vec<_>>()
            .join(" ")
    }
}

impl RunLogRow for TruthRow {
    const FILE_NAME: &'static str = "truth.csv";
    const COLUMNS: &'static [&'static str] = &[
        "frame_seq",
        "frame_incarnation",
        "sim_time_s",
        "x_m",
        "y_m",
        "vx_mps",
        "vy_mps",
        "heading_rad",
        "flow_x_mps",
        "flow_y_mps",
        "wall_contact",
        "max_abs_current_a",
        "lockstep_misses",
        "sum_sq_current_a2",
        "coil_currents_a",
    ];
    const OPTIONAL_COLUMNS: &'static [&'static str] =
        &["frame_incarnation", "sum_sq_current_a2", "coil_currents_a"];
}

/// A wall contact starting or ending (`contacts.csv`), with the running onset count.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ContactRow {
    pub frame_seq: u64,
    #[serde(serialize_with = "fixed6")]
    pub sim_time_s: f64,
    /// `start` or `end`.
    pub event: String,
    #[serde(serialize_with = "fixed9")]
    pub x_m: f64,
    #[serde(serialize_with = "fixed9")]
    pub y_m: f64,
    pub contact_events: u64,
    #[serde(serialize_with = "fixed6")]
    pub contact_time_s: f64,
}

impl RunLogRow for ContactRow {
    const FILE_NAME: &'static str = "contacts.csv";
    const COLUMNS: &'static [&'static str] = &[
        "frame_seq",
        "sim_time_s",
        "event",
        "x_m",
        "y_m",
        "contact_events",
        "contact_time_s",
    ];
}

/// What the (emulated) Teensy received or did (`teensy_events.csv`), on the monotonic clock.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TeensyEventRow {
    pub monotonic_ns: u64,
    /// Frame of the command (`-1` in the file for board events without one).
    #[serde(with = "frame_or_minus_one")]
    pub frame_seq: Option<u64>,
    pub flags: u8,
    #[serde(serialize_with = "fixed6")]
    pub max_abs_current_a: f64,
    /// `command`, `safe_zero`, `watchdog_zero`, `unplugged`, `replugged`, `hang`,
    /// `hw_watchdog_reset`, `rebooted`, `rejected_coil_count`.
    pub event: String,
}

impl RunLogRow for TeensyEventRow {
    const FILE_NAME: &'static str = "teensy_events.csv";
    const COLUMNS: &'static [&'static str] = &[
        "monotonic_ns",
        "frame_seq",
        "flags",
        "max_abs_current_a",
        "event",
    ];
}

/// A serial-link change seen by coilbus (`coilbus_link.csv`): `open`, or `lost` with the reason.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LinkEventRow {
    pub monotonic_ns: u64,
    pub event: String,
    pub detail: String,
}

impl RunLogRow for LinkEventRow {
    const FILE_NAME: &'static str = "coilbus_link.csv";
    const COLUMNS: &'static [&'static str] = &["monotonic_ns", "event", "detail"];
}

/// Something the supervisor did or saw (`supervisor_events.csv`): spawn, exit, restart,
/// heartbeat miss, cleanup, shutdown.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SupervisorEventRow {
    pub monotonic_ns: u64,
    pub service: String,
    pub event: String,
    pub detail: String,
}

impl RunLogRow for SupervisorEventRow {
    const FILE_NAME: &'static str = "supervisor_events.csv";
    const COLUMNS: &'static [&'static str] = &["monotonic_ns", "service", "event", "detail"];
}

/// One control decision (`control.csv`): what control saw, where the reference was, what it
/// commanded. The run summary's "as control saw it" figures come from here, on the rig as in
/// the twin.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ControlRow {
    pub frame_seq: u64,
    /// Incarnation of the frame's source (logs written before this column existed: 0).
    #[serde(default)]
    pub frame_incarnation: u64,
    /// Time on control's clock at which the command acts (the reference's time), s.
    #[serde(serialize_with = "fixed6")]
    pub time_s: f64,
    /// Whether the pose was used (a valid pose that passed control's gates).
    #[serde(with = "flag01")]
    pub pose_used: bool,
    /// The measured position (NaN without a valid pose).
    #[serde(serialize_with = "fixed9")]
    pub measured_x_m: f64,
    #[serde(serialize_with = "fixed9")]
    pub measured_y_m: f64,
    #[serde(serialize_with = "fixed9")]
    pub reference_x_m: f64,
    #[serde(serialize_with = "fixed9")]
    pub reference_y_m: f64,
    /// The reference has reached its last waypoint.
    #[serde(with = "flag01")]
    pub finished: bool,
    /// A `ControlMode` discriminant.
    pub mode: u32,
    /// Largest commanded coil current, A.
    #[serde(serialize_with = "fixed6")]
    pub max_abs_current_a: f64,
    /// Σ I² of the commanded currents, A².
    #[serde(serialize_with = "fixed6")]
    pub sum_sq_current_a2: f64,
}

impl RunLogRow for ControlRow {
    const FILE_NAME: &'static str = "control.csv";
    const COLUMNS: &'static [&'static str] = &[
        "frame_seq",
        "frame_incarnation",
        "time_s",
        "pose_used",
        "measured_x_m",
        "measured_y_m",
        "reference_x_m",
        "reference_y_m",
        "finished",
        "mode",
        "max_abs_current_a",
        "sum_sq_current_a2",
    ];
    const OPTIONAL_COLUMNS: &'static [&'static str] = &["frame_incarnation"];
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_dir(name: &str) -> crate::scratch::ScratchDir {
        crate::scratch::ScratchDir::new(&format!("runlog-{name}")).expect("temp dir")
    }

    fn truth(frame_seq: u64) -> TruthRow {
        TruthRow {
            frame_seq,
            frame_incarnation: 1,
            sim_time_s: 0.25,
            x_m: 1.5e-3,
            y_m: -2.25e-3,
            vx_mps: 1e-4,
            vy_mps: -3e-4,
            heading_rad: 0.5,
            flow_x_mps: 0.1,
            flow_y_mps: -0.05,
            wall_contact: true,
            max_abs_current_a: 4.5,
            lockstep_misses: 2,
            sum_sq_current_a2: Some(20.25),
            coil_currents_a: Some(TruthRow::format_currents(&[4.5, -0.25, 0.0])),
        }
    }

    fn contact() -> ContactRow {
        ContactRow {
            frame_seq: 9,
            sim_time_s: 0.09,
            event: "start".into(),
            x_m: 1e-3,
            y_m: 2e-3,
            contact_events: 1,
            contact_time_s: 0.01,
        }
    }

    fn teensy(frame_seq: Option<u64>) -> TeensyEventRow {
        TeensyEventRow {
            monotonic_ns: 123_456_789,
            frame_seq,
            flags: 1,
            max_abs_current_a: 2.5,
            event: "command".into(),
        }
    }

    /// Writes `rows` through a fresh writer, reads them back, and checks the header.
    fn round_trip<R: RunLogRow + PartialEq + std::fmt::Debug>(name: &str, rows: &[R]) {
        let dir = temp_dir(name);
        let path = dir.join(R::FILE_NAME);
        let mut writer = RunLogWriter::<R>::open_append(&path).expect("open");
        for row in rows {
            writer.append(row).expect("append");
        }
        writer.flush().expect("flush");
        let text = std::fs::read_to_string(&path).expect("read");
        assert_eq!(text.lines().next(), Some(R::COLUMNS.join(",").as_str()));
        let back: Vec<R> = read_rows(&path).expect("read rows");
        assert_eq!(back, rows);
    }

    #[test]
    fn every_row_type_round_trips_under_its_documented_header() {
        round_trip("truth", &[truth(0), truth(1)]);
        round_trip("contact", &[contact()]);
        round_trip("teensy", &[teensy(Some(7)), teensy(None)]);
        round_trip(
            "link",
            &[LinkEventRow {
                monotonic_ns: 5,
                event: "lost".into(),
                detail: "read failed: Input/output error (os error 5)".into(),
            }],
        );
        round_trip(
            "supervisor",
            &[SupervisorEventRow {
                monotonic_ns: 6,
                service: "control".into(),
                event: "spawn".into(),
                detail: "pid=42 incarnation=0".into(),
            }],
        );
    }

    #[test]
    fn the_struct_writes_exactly_the_documented_columns() {
        fn header_of<R: RunLogRow>(row: &R) -> String {
            let mut out = csv::Writer::from_writer(Vec::new());
            out.serialize(row).expect("serialize");
            let bytes = out.into_inner().expect("into inner");
            String::from_utf8(bytes)
                .expect("utf8")
                .lines()
                .next()
                .expect("header")
                .to_owned()
        }
        assert_eq!(header_of(&truth(0)), TruthRow::COLUMNS.join(","));
        assert_eq!(header_of(&contact()), ContactRow::COLUMNS.join(","));
        assert_eq!(header_of(&teensy(None)), TeensyEventRow::COLUMNS.join(","));
    }

    #[test]
    fn truth_keeps_its_fixed_decimal_format() {
        let dir = temp_dir("format");
        let path = dir.join("truth.csv");
        let mut writer = RunLogWriter::<TruthRow>::open_append(&path).expect("open");
        writer.append(&truth(3)).expect("append");
        writer.flush().expect("flush");
        let text = std::fs::read_to_string(&path).expect("read");
        assert_eq!(
            text.lines().nth(1),
            Some("3,1,0.250000,0.001500000,-0.002250000,0.000100000,-0.000300000,0.500000,0.100000000,-0.050000000,1,4.500000,2,20.250000,4.500000 -0.250000 0.000000")
        );
        let teensy_dir = temp_dir("format-teensy");
        let teensy_path = teensy_dir.join("teensy_events.csv");
        let mut writer = RunLogWriter::<TeensyEventRow>::open_append(&teensy_path).expect("open");
        writer.append_now(&teensy(None)).expect("append");
        let text = std::fs::read_to_string(&teensy_path).expect("read");
        assert_eq!(text.lines().nth(1), Some("123456789,-1,1,2.500000,command"));
    }

    #[test]
    fn a_reopened_log_appends_without_a_second_header() {
        let dir = temp_dir("append");
        let path = dir.join("supervisor_events.csv");
        let row = |event: &str| SupervisorEventRow {
            monotonic_ns: 1,
            service: "plant".into(),
            event: event.into(),
            detail: String::new(),
        };
        RunLogWriter::open_append(&path)
            .expect("first open")
            .append_now(&row("spawn"))
            .expect("append");
        RunLogWriter::open_append(&path)
            .expect("second open")
            .append_now(&row("restart"))
            .expect("append");
        let text = std::fs::read_to_string(&path).expect("read");
        assert_eq!(text.matches("monotonic_ns").count(), 1, "{text}");
        let rows: Vec<SupervisorEventRow> = read_rows(&path).expect("rows");
        assert_eq!(rows, vec![row("spawn"), row("restart")]);
    }

    #[test]
    fn readers_take_columns_by_name_ignoring_extra_and_reordered_ones() {
        let text = "event,added_later,flags,max_abs_current_a,frame_seq,monotonic_ns\n\
                    command,x,0,1.500000,12,1000\n\
                    watchdog_zero,y,0,0.000000,-1,2000\n";
        let rows: Vec<TeensyEventRow> =
            parse_rows(text, Path::new("run/teensy_events.csv")).expect("rows");
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].frame_seq, Some(12));
        assert_eq!(rows[0].monotonic_ns, 1000);
        assert!((rows[0].max_abs_current_a - 1.5).abs() < 1e-12);
        assert_eq!(rows[1].frame_seq, None);
        assert_eq!(rows[1].event, "watchdog_zero");
    }

    #[test]
    fn a_missing_column_names_the_file_and_the_column() {
        let text = "monotonic_ns,frame_seq,flags,event\n1,2,0,command\n";
        let err = parse_rows::<TeensyEventRow>(text, Path::new("run/teensy_events.csv"))
            .expect_err("max_abs_current_a is missing");
        let message = err.to_string();
        assert!(message.contains("run/teensy_events.csv"), "{message}");
        assert!(message.contains("`max_abs_current_a`"), "{message}");
    }

    #[test]
    fn an_optional_column_may_be_missing_in_older_files() {
        let mut header = TruthRow::COLUMNS.to_vec();
        header.truncate(header.len() - 2);
        header.retain(|c| *c != "frame_incarnation");
        let text = format!(
            "{}\n0,0.0,0.001,0.002,0,0,0,0,0,0,3.0,0\n",
            header.join(",")
        );
        let rows: Vec<TruthRow> = parse_rows(&text, Path::new("truth.csv")).expect("rows");
        assert_eq!(rows.len(), 1);
        assert_eq!(rows[0].sum_sq_current_a2, None);
        assert_eq!(rows[0].currents(), None);
        assert_eq!(rows[0].frame_incarnation, 0);
        assert!(!rows[0].wall_contact);
    }

    #[test]
    fn a_bad_value_names_file_line_and_column() {
        let text = "monotonic_ns,event,detail\n1,open,\nsoon,lost,x\n";
        let err = parse_rows::<LinkEventRow>(text, Path::new("coilbus_link.csv"))
            .expect_err("not a number");
        let message = err.to_string();
        assert!(message.contains("coilbus_link.csv"), "{message}");
        assert!(message.contains("line 3"), "{message}");
        assert!(message.contains("`monotonic_ns`"), "{message}");
    }

    #[test]
    fn free_text_with_commas_quotes_and_newlines_survives() {
        let dir = temp_dir("quote");
        let path = dir.join("coilbus_link.csv");
        let detail = "open /dev/ttyACM0 failed: \"busy\", retry, later\nsecond line";
        let mut writer = RunLogWriter::<LinkEventRow>::open_append(&path).expect("open");
        let row = LinkEventRow {
            monotonic_ns: 9,
            event: "lost".into(),
            detail: detail.into(),
        };
        writer.append_now(&row).expect("append");
        let rows: Vec<LinkEventRow> = read_rows(&path).expect("rows");
        assert_eq!(rows, vec![row]);
    }

    #[test]
    fn a_row_still_being_written_is_left_out() {
        let text = "monotonic_ns,service,event,detail\n1,plant,spawn,pid=1\n2,vision,sp";
        let rows: Vec<SupervisorEventRow> =
            parse_rows(text, Path::new("supervisor_events.csv")).expect("rows");
        assert_eq!(rows.len(), 1);
        assert_eq!(rows[0].service, "plant");
        let empty: Vec<SupervisorEventRow> =
            parse_rows("", Path::new("supervisor_events.csv")).expect("empty file");
        assert!(empty.is_empty());
    }

    #[test]
    fn a_row_with_too_few_fields_is_an_error_not_skipped() {
        let text = "monotonic_ns,event,detail\n1,open\n";
        assert!(parse_rows::<LinkEventRow>(text, Path::new("coilbus_link.csv")).is_err());
    }
}
