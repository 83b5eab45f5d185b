//! Publish→receive latency between two processes: iceoryx2 through the kit's ports vs a Unix
//! domain socket (a copying transport). The receiver is a child process of the bench binary
//! (`bench ipc-child`); both stamp CLOCK_MONOTONIC, which is one clock for every process, so
//! one-way latency is measured directly. Each message is acknowledged before the next is sent
//! (no queueing), and the receiver sleeps in a blocking wait as the services do, so wake-up is
//! included. Over iceoryx2 the latency is also split into its phases (send, wake-up, take).

use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use millinav_kit::clock::monotonic_ns;
use millinav_kit::iceoryx2::prelude::*;
use millinav_kit::ports::{FrameInbox, FrameOutbox, Inbox, Outbox};
use millinav_kit::{iceoryx_config, iox};
use shm_schemas::{Flag, FrameHeader, FrameStamp, Pose};

use crate::BenchError;

/// Sequence value that ends a child's loop.
const STOP: u64 = u64::MAX;
const ACK_SERVICE: &str = "millinav/bench/ack";
const POSE_SERVICE: &str = "millinav/bench/pose";
/// Messages before the measured ones (connection set-up, page faults).
const WARMUP: u64 = 20;

/// What is sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Message {
    /// A camera frame through the kit's `FrameOutbox::send` (copies the pixels into shm).
    Frame,
    /// A camera frame written in place through `FrameOutbox::send_in_place` (zero-copy).
    FrameLoan,
    /// One `Pose` through `Outbox<Pose>`.
    Pose,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Transport {
    Iceoryx2,
    Uds,
}

/// Where the two processes may run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Placement {
    /// Wherever the scheduler puts them, as the services run: the receiver usually sleeps on
    /// the other core, and waking it there costs an inter-processor interrupt.
    Free,
    /// Both on one core (the first this process may use): the wake-up is a local switch.
    OneCore,
}

/// Pins the calling thread (and the children it spawns) to one core until dropped.
struct Pinned(Option<nix::sched::CpuSet>);

impl Pinned {
    fn new(placement: Placement) -> Result<Self, BenchError> {
        use nix::sched::{sched_getaffinity, sched_setaffinity, CpuSet};
        use nix::unistd::Pid;
        if placement == Placement::Free {
            return Ok(Self(None));
        }
        let affinity = |e: nix::Error| setup(&format!("cpu affinity: {e}"));
        let before = sched_getaffinity(Pid::from_raw(0)).map_err(affinity)?;
        let first = (0..CpuSet::count())
            .find(|&cpu| before.is_set(cpu).unwrap_or(false))
            .ok_or_else(|| setup("no usable cpu"))?;
        let mut one = CpuSet::new();
        one.set(first).map_err(affinity)?;
        sched_setaffinity(Pid::from_raw(0), &one).map_err(affinity)?;
        Ok(Self(Some(before)))
    }
}

impl Drop for Pinned {
    fn drop(&mut self) {
        if let Some(before) = &self.0 {
            let _ = nix::sched::sched_setaffinity(nix::unistd::Pid::from_raw(0), before);
        }
    }
}

/// Where the two processes meet, and the frames they pass (the rig camera's size).
#[derive(Debug, Clone)]
pub struct Rendezvous {
    pub iox_prefix: String,
    pub iox_root: PathBuf,
    pub socket: PathBuf,
    pub frame: FrameShape,
}

/// Width and height of an RGB8 frame, px.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameShape {
    pub width: u32,
    pub height: u32,
}

impl FrameShape {
    /// Bytes of one frame (3 per pixel).
    pub fn bytes(self) -> usize {
        3 * self.width as usize * self.height as usize
    }

    /// Bytes of one row.
    fn row_bytes(self) -> usize {
        3 * self.width as usize
    }
}

/// The frame a measurement sends: its pixels and shape.
#[derive(Debug, Clone, Copy)]
pub struct Frame<'a> {
    pub pixels: &'a [u8],
    pub shape: FrameShape,
}

impl Rendezvous {
    pub fn new(dir: &Path, frame: FrameShape) -> Self {
        Self {
            iox_prefix: format!("bench{}_", std::process::id()),
            iox_root: dir.join("iox"),
            socket: dir.join("ipc.sock"),
            frame,
        }
    }
}

fn node(rv: &Rendezvous, name: &str) -> Result<Node<ipc::Service>, BenchError> {
    let config = iceoryx_config(Some(&rv.iox_prefix), Some(&rv.iox_root))?;
    Ok(NodeBuilder::new()
        .name(&NodeName::new(name).map_err(iox("node name"))?)
        .config(&config)
        .create::<ipc::Service>()
        .map_err(iox("node"))?)
}

fn frame_header(frame: FrameShape, seq: u64, stamp: u64) -> FrameHeader {
    FrameHeader {
        stamp: FrameStamp::new(seq, 0, stamp),
        width: frame.width,
        height: frame.height,
        stride: frame.width * 3,
        ..Default::default()
    }
}

fn pose(seq: u64, stamp: u64) -> Pose {
    Pose {
        stamp: FrameStamp::new(seq, 0, stamp),
        valid: Flag::TRUE,
        ..Default::default()
    }
}

fn payload_len(frame: FrameShape, message: Message) -> usize {
    match message {
        Message::Frame | Message::FrameLoan => frame.bytes(),
        Message::Pose => std::mem::size_of::<Pose>(),
    }
}

/// One measurement: the one-way latencies (ns) the receiver saw and, over iceoryx2, where each
/// went (the three phases add up to the latency).
#[derive(Debug, Clone, Default)]
pub struct Measured {
    pub latency_ns: Vec<f64>,
    /// Sender stamp → `send` returned (loan, write, publish, notify).
    pub send_ns: Vec<f64>,
    /// `send` returned → the receiver's blocking wait returned (the kernel's cross-process
    /// wake-up: iceoryx2's event is a Unix datagram).
    pub wake_ns: Vec<f64>,
    /// Receiver awake → sample in hand (`latest`).
    pub take_ns: Vec<f64>,
}

/// Runs one measurement: spawns the receiver, sends `count` messages, returns what the
/// receiver saw.
pub fn measure(
    exe: &Path,
    dir: &Path,
    transport: Transport,
    message: Message,
    count: u64,
    frame: Frame<'_>,
    placement: Placement,
) -> Result<Measured, BenchError> {
    let Frame {
        pixels,
        shape: frame,
    } = frame;
    if pixels.len() != frame.bytes() {
        return Err(setup(&format!(
            "{} pixel bytes for a {}x{} frame",
            pixels.len(),
            frame.width,
            frame.height
        )));
    }
    let _pinned = Pinned::new(placement)?;
    let rv = Rendezvous::new(dir, frame);
    let _ = std::fs::remove_file(&rv.socket);
    let listener = match transport {
        Transport::Uds => Some(UnixListener::bind(&rv.socket)?),
        Transport::Iceoryx2 => None,
    };
    let mut child = spawn_child(exe, &rv, transport, message)?;
    let stdout = child
        .stdout
        .take()
        .ok_or_else(|| setup("child has no stdout"))?;
    let mut lines = BufReader::new(stdout).lines();
    match lines.next() {
        Some(Ok(l)) if l == "ready" => {}
        other => {
            let _ = child.kill();
            return Err(setup(&format!("receiver did not start: {other:?}")));
        }
    }
    let sent = match transport {
        Transport::Iceoryx2 => send_iceoryx2(&rv, message, count, pixels),
        Transport::Uds => match listener {
            Some(l) => send_uds(&l, frame, message, count, pixels).map(|()| Vec::new()),
            None => Err(setup("no socket")),
        },
    };
    let send_done = match sent {
        Ok(done) => done,
        Err(e) => {
            let _ = child.kill();
            let _ = child.wait();
            return Err(e);
        }
    };
    let mut measured = Measured::default();
    for line in lines {
        let line = line?;
        let Some(received) = Received::parse(&line) else {
            continue;
        };
        measured
            .latency_ns
            .push(received.got_ns.saturating_sub(received.stamp_ns) as f64);
        if let (Some(woke), Some(&done)) = (received.woke_ns, send_done.get(received.seq as usize))
        {
            measured
                .send_ns
                .push(done.saturating_sub(received.stamp_ns) as f64);
            measured.wake_ns.push(woke.saturating_sub(done) as f64);
            measured
                .take_ns
                .push(received.got_ns.saturating_sub(woke) as f64);
        }
    }
    let status = child.wait()?;
    if !status.success() {
        return Err(setup(&format!("receiver exited with {status}")));
    }
    Ok(measured)
}

/// One measured message as the receiver reports it: `seq stamp got [woke]` (ns, CLOCK_MONOTONIC).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Received {
    seq: u64,
    stamp_ns: u64,
    got_ns: u64,
    woke_ns: Option<u64>,
}

impl Received {
    fn line(&self) -> String {
        match self.woke_ns {
            Some(w) => format!("{} {} {} {w}", self.seq, self.stamp_ns, self.got_ns),
            None => format!("{} {} {}", self.seq, self.stamp_ns, self.got_ns),
        }
    }

    fn parse(line: &str) -> Option<Self> {
        let mut f = line.split_whitespace().map(|v| v.parse::<u64>());
        let (seq, stamp_ns, got_ns) = (f.next()?.ok()?, f.next()?.ok()?, f.next()?.ok()?);
        let woke_ns = match f.next() {
            Some(v) => Some(v.ok()?),
            None => None,
        };
        Some(Self {
            seq,
            stamp_ns,
            got_ns,
            woke_ns,
        })
    }
}

fn setup(msg: &str) -> BenchError {
    BenchError::Setup(msg.to_owned())
}

fn spawn_child(
    exe: &Path,
    rv: &Rendezvous,
    transport: Transport,
    message: Message,
) -> Result<Child, BenchError> {
    let t = match transport {
        Transport::Iceoryx2 => "iceoryx2",
        Transport::Uds => "uds",
    };
    let m = match message {
        Message::Frame => "frame",
        Message::FrameLoan => "frame-loan",
        Message::Pose => "pose",
    };
    Ok(Command::new(exe)
        .args(["ipc-child", "--transport", t, "--message", m])
        .arg("--iox-prefix")
        .arg(&rv.iox_prefix)
        .arg("--iox-root")
        .arg(&rv.iox_root)
        .arg("--socket")
        .arg(&rv.socket)
        .arg("--frame-width")
        .arg(rv.frame.width.to_string())
        .arg("--frame-height")
        .arg(rv.frame.height.to_string())
        .stdout(Stdio::piped())
        .stdin(Stdio::null())
        .spawn()?)
}

/// Sends `count` messages (+ warm-up) and returns when each `send` returned, indexed by seq.
fn send_iceoryx2(
    rv: &Rendezvous,
    message: Message,
    count: u64,
    pixels: &[u8],
) -> Result<Vec<u64>, BenchError> {
    let node = node(rv, "bench-tx")?;
    let acks = Inbox::<Pose>::new(&node, ACK_SERVICE)?;
    let frames = match message {
        Message::Frame | Message::FrameLoan => Some(FrameOutbox::new(&node, rv.frame.bytes())?),
        _ => None,
    };
    let poses = match message {
        Message::Pose => Some(Outbox::<Pose>::new(&node, POSE_SERVICE)?),
        _ => None,
    };
    let send = |seq: u64| -> Result<u64, BenchError> {
        let stamp = monotonic_ns();
        if let Some(f) = &frames {
            f.update_connections();
            if message == Message::FrameLoan {
                // A camera or renderer writes its pixels straight into the loan; here only the
                // first row is written: the transport cost is what is measured.
                let (frame, row) = (rv.frame, rv.frame.row_bytes());
                f.send_in_place(frame_header(frame, seq, stamp), frame.bytes(), |payload| {
                    payload[..row].copy_from_slice(&pixels[..row]);
                })?;
            } else {
                f.send(frame_header(rv.frame, seq, stamp), pixels, |_| {})?;
            }
        }
        if let Some(p) = &poses {
            p.update_connections();
            p.send(pose(seq, stamp))?;
        }
        Ok(monotonic_ns())
    };
    let wait_ack = |seq: u64, timeout: Duration| -> Result<bool, BenchError> {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            if acks.receive_all()?.iter().any(|a| a.stamp.seq == seq) {
                return Ok(true);
            }
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            if left.is_zero() {
                return Ok(false);
            }
            acks.wait(left);
        }
    };
    // Connection: resend message 0 until the receiver answers.
    let mut connected = false;
    for _ in 0..100 {
        send(0)?;
        if wait_ack(0, Duration::from_millis(100))? {
            connected = true;
            break;
        }
    }
    if !connected {
        return Err(setup("iceoryx2 receiver never acknowledged"));
    }
    let mut send_done = vec![0; (count + WARMUP + 1) as usize];
    for seq in 1..=count + WARMUP {
        send_done[seq as usize] = send(seq)?;
        if !wait_ack(seq, Duration::from_secs(2))? {
            return Err(setup(&format!("no ack for message {seq}")));
        }
    }
    // The stop message may need a few tries if the receiver is busy.
    for _ in 0..20 {
        send(STOP)?;
        if wait_ack(STOP, Duration::from_millis(100))? {
            break;
        }
    }
    Ok(send_done)
}

fn send_uds(
    listener: &UnixListener,
    frame: FrameShape,
    message: Message,
    count: u64,
    pixels: &[u8],
) -> Result<(), BenchError> {
    let (mut stream, _) = listener.accept()?;
    let len = payload_len(frame, message);
    let mut buf = vec![0u8; 16 + len];
    buf[16..16 + len.min(pixels.len())].copy_from_slice(&pixels[..len.min(pixels.len())]);
    let mut ack = [0u8; 1];
    for seq in (1..=count + WARMUP).chain(std::iter::once(STOP)) {
        let stamp = monotonic_ns();
        buf[..8].copy_from_slice(&seq.to_le_bytes());
        buf[8..16].copy_from_slice(&stamp.to_le_bytes());
        stream.write_all(&buf)?;
        stream.read_exact(&mut ack)?;
    }
    Ok(())
}

/// The receiver (child process): prints `ready`, receives until the stop message, prints one
/// latency (ns) per measured message.
pub fn child(rv: &Rendezvous, transport: Transport, message: Message) -> Result<(), BenchError> {
    let mut received: Vec<Received> = Vec::new();
    let mut out = std::io::stdout().lock();
    match transport {
        Transport::Uds => {
            let mut stream = UnixStream::connect(&rv.socket)?;
            writeln!(out, "ready")?;
            out.flush()?;
            let mut buf = vec![0u8; 16 + payload_len(rv.frame, message)];
            loop {
                stream.read_exact(&mut buf)?;
                let now = monotonic_ns();
                let seq = u64::from_le_bytes(buf[..8].try_into().unwrap_or_default());
                let stamp = u64::from_le_bytes(buf[8..16].try_into().unwrap_or_default());
                stream.write_all(&[1])?;
                if seq == STOP {
                    break;
                }
                if seq > WARMUP {
                    received.push(Received {
                        seq,
                        stamp_ns: stamp,
                        got_ns: now,
                        woke_ns: None,
                    });
                }
            }
        }
        Transport::Iceoryx2 => {
            let node = node(rv, "bench-rx")?;
            let ack = Outbox::<Pose>::new(&node, ACK_SERVICE)?;
            let frames = match message {
                Message::Frame | Message::FrameLoan => Some(FrameInbox::new(&node)?),
                Message::Pose => None,
            };
            let poses = match message {
                Message::Pose => Some(Inbox::<Pose>::new(&node, POSE_SERVICE)?),
                _ => None,
            };
            writeln!(out, "ready")?;
            out.flush()?;
            let idle_limit = Duration::from_secs(10);
            let mut idle = std::time::Instant::now();
            loop {
                let mut got: Option<(u64, u64, u64)> = None;
                let mut woke = 0;
                if let Some(f) = &frames {
                    f.wait(Duration::from_millis(100));
                    woke = monotonic_ns();
                    if let Some(sample) = f.latest()? {
                        let now = monotonic_ns();
                        let h = sample.user_header();
                        got = Some((h.stamp.seq, h.stamp.capture_time_ns, now));
                    }
                }
                if let Some(p) = &poses {
                    p.wait(Duration::from_millis(100));
                    woke = monotonic_ns();
                    if let Some(m) = p.latest()? {
                        got = Some((m.stamp.seq, m.stamp.capture_time_ns, monotonic_ns()));
                    }
                }
                ack.update_connections();
                match got {
                    Some((seq, stamp, now)) => {
                        idle = std::time::Instant::now();
                        ack.send(pose(seq, 0))?;
                        if seq == STOP {
                            break;
                        }
                        if seq > WARMUP {
                            received.push(Received {
                                seq,
                                stamp_ns: stamp,
                                got_ns: now,
                                woke_ns: Some(woke),
                            });
                        }
                    }
                    None if idle.elapsed() > idle_limit => {
                        return Err(setup("receiver: no message for 10 s"));
                    }
                    None => {}
                }
            }
        }
    }
    for r in received {
        writeln!(out, "{}", r.line())?;
    }
    out.flush()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn receiver_lines_round_trip_and_reject_garbage() {
        for r in [
            Received {
                seq: 7,
                stamp_ns: 100,
                got_ns: 150,
                woke_ns: Some(140),
            },
            Received {
                seq: 8,
                stamp_ns: 200,
                got_ns: 260,
                woke_ns: None,
            },
        ] {
            assert_eq!(Received::parse(&r.line()), Some(r));
        }
        assert_eq!(Received::parse("ready"), None);
        assert_eq!(Received::parse("1 2"), None);
        assert_eq!(Received::parse("1 2 3 x"), None);
    }
}
