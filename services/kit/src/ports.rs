//! Typed ports with the QoS every participant must agree on. A data service always comes with a
//! companion event service so receivers can sleep in a WaitSet with a deadline.

use std::fmt::Debug;
use std::time::{Duration, Instant};

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use shm_schemas::{deadlines, services, FrameHeader, Heartbeat, ServiceId};

use crate::{iox, KitError};
use iceoryx2::service::builder::publish_subscribe::{
    PublishSubscribeOpenError, PublishSubscribeOpenOrCreateError,
};

/// An input a WaitSet can wait on (an `Inbox` or a `FrameInbox`).
pub trait Attachable: SynchronousMultiplexing + Debug {
    /// Consumes the pending announcements, so that the WaitSet sleeps again until the next one.
    fn drain_events(&self);
}

/// An output whose new subscribers must be connected now and then (`Outbox`, `FrameOutbox`).
pub trait Connects {
    fn update_connections(&self);
}

/// Samples a slow subscriber may queue before the oldest is overwritten (latest wins).
pub const SUBSCRIBER_BUFFER: usize = 4;
/// Frames are large: a subscriber keeps only the newest two.
pub const FRAME_SUBSCRIBER_BUFFER: usize = 2;
const MAX_PUBLISHERS: usize = 16;
const MAX_SUBSCRIBERS: usize = 12;
const MAX_NODES: usize = 32;

fn service_name(name: &str) -> Result<ServiceName, KitError> {
    ServiceName::new(name).map_err(iox("service name"))
}

/// iceoryx2's name of the type `T` in shared memory (the contract's versioned type name).
fn type_name_of<T: ZeroCopySend + ?Sized>() -> String {
    // SAFETY: only reads the name; every contract payload pins its layout at compile time.
    unsafe { <T as ZeroCopySend>::type_name() }.to_owned()
}

/// Maps a failure to open `service`; a payload or header type that does not match the
/// existing service (another contract version, or another type) becomes `ContractMismatch`.
fn open_error(
    service: &str,
    expected: String,
) -> impl FnOnce(PublishSubscribeOpenOrCreateError) -> KitError + '_ {
    move |e| match e {
        PublishSubscribeOpenOrCreateError::PublishSubscribeOpenError(
            PublishSubscribeOpenError::IncompatibleTypes,
        ) => KitError::ContractMismatch {
            service: service.to_owned(),
            expected,
        },
        other => iox(service)(other),
    }
}

/// Opens (or creates) the event service that announces samples on `data_service`.
pub fn open_event(
    node: &Node<ipc::Service>,
    event_service: &str,
) -> Result<iceoryx2::service::port_factory::event::PortFactory<ipc::Service>, KitError> {
    node.service_builder(&service_name(event_service)?)
        .event()
        .max_notifiers(MAX_PUBLISHERS * 2)
        .max_listeners(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .open_or_create()
        .map_err(iox(event_service))
}

fn open_pubsub<T: Debug + ZeroCopySend + 'static>(
    node: &Node<ipc::Service>,
    name: &str,
) -> Result<
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, T, ()>,
    KitError,
> {
    node.service_builder(&service_name(name)?)
        .publish_subscribe::<T>()
        // No history: a restarted consumer must never act on a command from before it started.
        .history_size(0)
        .subscriber_max_buffer_size(SUBSCRIBER_BUFFER)
        .enable_safe_overflow(true)
        .max_publishers(MAX_PUBLISHERS)
        .max_subscribers(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .open_or_create()
        .map_err(open_error(name, type_name_of::<T>()))
}

/// Publishes fixed-size messages and announces each one.
pub struct Outbox<T: Debug + ZeroCopySend + 'static> {
    publisher: Publisher<ipc::Service, T, ()>,
    notifier: Notifier<ipc::Service>,
}

impl<T: Debug + ZeroCopySend + Copy + 'static> Outbox<T> {
    pub fn new(node: &Node<ipc::Service>, name: &str) -> Result<Self, KitError> {
        let publisher = open_pubsub::<T>(node, name)?
            .publisher_builder()
            .create()
            .map_err(iox(name))?;
        let notifier = open_event(node, &services::event_service_of(name))?
            .notifier_builder()
            .create()
            .map_err(iox(name))?;
        Ok(Self {
            publisher,
            notifier,
        })
    }

    pub fn send(&self, value: T) -> Result<(), KitError> {
        self.publisher.send_copy(value).map_err(iox("send"))?;
        self.notifier.notify().map_err(iox("notify"))?;
        Ok(())
    }

    /// Connects subscribers that appeared since the last call.
    pub fn update_connections(&self) {
        let _ = self.publisher.update_connections();
    }
}

impl<T: Debug + ZeroCopySend + Copy + 'static> Connects for Outbox<T> {
    fn update_connections(&self) {
        Outbox::update_connections(self);
    }
}

/// Receives fixed-size messages. It can be attached to a WaitSet (or a `ServiceLoop`)
/// directly: it wakes the WaitSet when a sample is announced.
#[derive(Debug)]
pub struct Inbox<T: Debug + ZeroCopySend + 'static> {
    subscriber: Subscriber<ipc::Service, T, ()>,
    listener: Listener<ipc::Service>,
}

impl<T: Debug + ZeroCopySend + Copy + 'static> Inbox<T> {
    pub fn new(node: &Node<ipc::Service>, name: &str) -> Result<Self, KitError> {
        // Its `wait` tells a termination from another signal by the kit's flag.
        crate::termination::watch();
        let subscriber = open_pubsub::<T>(node, name)?
            .subscriber_builder()
            .create()
            .map_err(iox(name))?;
        let listener = open_event(node, &services::event_service_of(name))?
            .listener_builder()
            .create()
            .map_err(iox(name))?;
        Ok(Self {
            subscriber,
            listener,
        })
    }

    /// Consumes pending event notifications (an undrained listener makes a WaitSet spin).
    pub fn drain_events(&self) {
        let _ = self.listener.try_wait(|_| {});
    }

    /// Sleeps until a sample is announced or `timeout` passes, whichever comes first. The
    /// announcement is consumed; the sample stays queued for `receive_all` / `latest`. Returns
    /// false when SIGINT / SIGTERM ended the wait: iceoryx2 hands the termination request to
    /// this wait (not to a later `Runtime::shutdown_requested`), so a loop must stop on false.
    pub fn wait(&self, timeout: Duration) -> bool {
        still_running(self.listener.timed_wait(|_| {}, timeout))
    }

    /// Every message queued since the last call, oldest first.
    pub fn receive_all(&self) -> Result<Vec<T>, KitError> {
        self.drain_events();
        let mut out = Vec::new();
        while let Some(sample) = self.subscriber.receive().map_err(iox("receive"))? {
            out.push(*sample.payload());
        }
        Ok(out)
    }

    /// The newest queued message, dropping older ones.
    pub fn latest(&self) -> Result<Option<T>, KitError> {
        Ok(self.receive_all()?.pop())
    }
}

impl<T: Debug + ZeroCopySend + 'static> FileDescriptorBased for Inbox<T> {
    fn file_descriptor(&self) -> &FileDescriptor {
        self.listener.file_descriptor()
    }
}

impl<T: Debug + ZeroCopySend + 'static> SynchronousMultiplexing for Inbox<T> {}

impl<T: Debug + ZeroCopySend + Copy + 'static> Attachable for Inbox<T> {
    fn drain_events(&self) {
        Inbox::drain_events(self);
    }
}

/// Publishes camera frames: `[u8]` payload with a `FrameHeader`.
pub struct FrameOutbox {
    publisher: Publisher<ipc::Service, [u8], FrameHeader>,
    notifier: Notifier<ipc::Service>,
}

fn open_frame_service(
    node: &Node<ipc::Service>,
    name: &str,
) -> Result<
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<
        ipc::Service,
        [u8],
        FrameHeader,
    >,
    KitError,
> {
    node.service_builder(&service_name(name)?)
        .publish_subscribe::<[u8]>()
        .user_header::<FrameHeader>()
        .history_size(0)
        .subscriber_max_buffer_size(FRAME_SUBSCRIBER_BUFFER)
        .enable_safe_overflow(true)
        .max_publishers(MAX_PUBLISHERS)
        .max_subscribers(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .open_or_create()
        .map_err(open_error(
            name,
            format!("[u8] with user header {}", type_name_of::<FrameHeader>()),
        ))
}

impl FrameOutbox {
    /// A publisher for frames of up to `max_frame_bytes` pixel bytes (the rig camera's
    /// width × height × channels).
    pub fn new(node: &Node<ipc::Service>, max_frame_bytes: usize) -> Result<Self, KitError> {
        Self::on(node, services::FRAME, max_frame_bytes)
    }

    /// A publisher on the frame service `name` (`services::FRAME` or `services::RAW_FRAME`).
    pub fn on(
        node: &Node<ipc::Service>,
        name: &str,
        max_frame_bytes: usize,
    ) -> Result<Self, KitError> {
        let publisher = open_frame_service(node, name)?
            .publisher_builder()
            .initial_max_slice_len(max_frame_bytes.max(1))
            .create()
            .map_err(iox(name))?;
        let notifier = open_event(node, &services::event_service_of(name))?
            .notifier_builder()
            .create()
            .map_err(iox(name))?;
        Ok(Self {
            publisher,
            notifier,
        })
    }

    /// Publishes `pixels` with `header`; `draw` may paint over the copied pixels in place.
    pub fn send(
        &self,
        header: FrameHeader,
        pixels: &[u8],
        draw: impl FnOnce(&mut [u8]),
    ) -> Result<(), KitError> {
        let mut sample = self
            .publisher
            .loan_slice_uninit(pixels.len())
            .map_err(iox("loan frame"))?;
        *sample.user_header_mut() = header;
        let mut sample = sample.write_from_slice(pixels);
        draw(sample.payload_mut());
        sample.send().map_err(iox("send frame"))?;
        self.notifier.notify().map_err(iox("notify frame"))?;
        Ok(())
    }

    /// Publishes a frame written in place into shared memory (zero-copy): `fill` gets the
    /// loaned payload of `len` bytes and writes what it needs to. Bytes it leaves alone hold
    /// whatever an earlier frame left in that chunk (zeros in a fresh segment), so a camera
    /// driver or renderer that rewrites every pixel, or only what changed, pays no copy.
    pub fn send_in_place(
        &self,
        header: FrameHeader,
        len: usize,
        fill: impl FnOnce(&mut [u8]),
    ) -> Result<(), KitError> {
        let mut sample = self
            .publisher
            .loan_slice_uninit(len)
            .map_err(iox("loan frame"))?;
        *sample.user_header_mut() = header;
        // SAFETY: the payload lies in this service's shared-memory data segment, which the OS
        // maps zero-filled and which only ever holds u8 frames; u8 has no invalid bit pattern,
        // so every byte of the chunk is an initialised u8 (stale pixels, not undefined ones).
        let mut sample = unsafe { sample.assume_init() };
        fill(sample.payload_mut());
        sample.send().map_err(iox("send frame"))?;
        self.notifier.notify().map_err(iox("notify frame"))?;
        Ok(())
    }

    pub fn update_connections(&self) {
        let _ = self.publisher.update_connections();
    }
}

impl Connects for FrameOutbox {
    fn update_connections(&self) {
        FrameOutbox::update_connections(self);
    }
}

/// Receives camera frames without copying them; attachable to a WaitSet like `Inbox`.
#[derive(Debug)]
pub struct FrameInbox {
    subscriber: Subscriber<ipc::Service, [u8], FrameHeader>,
    listener: Listener<ipc::Service>,
}

/// A received frame, borrowed from shared memory until dropped.
pub type FrameSample = Sample<ipc::Service, [u8], FrameHeader>;

impl FrameInbox {
    pub fn new(node: &Node<ipc::Service>) -> Result<Self, KitError> {
        Self::on(node, services::FRAME)
    }

    /// A subscriber on the frame service `name` (`services::FRAME` or `services::RAW_FRAME`).
    pub fn on(node: &Node<ipc::Service>, name: &str) -> Result<Self, KitError> {
        crate::termination::watch();
        let subscriber = open_frame_service(node, name)?
            .subscriber_builder()
            .create()
            .map_err(iox(name))?;
        let listener = open_event(node, &services::event_service_of(name))?
            .listener_builder()
            .create()
            .map_err(iox(name))?;
        Ok(Self {
            subscriber,
            listener,
        })
    }

    /// The newest frame, releasing any older queued ones.
    pub fn latest(&self) -> Result<Option<FrameSample>, KitError> {
        self.drain_events();
        let mut newest = None;
        while let Some(sample) = self.subscriber.receive().map_err(iox("receive frame"))? {
            newest = Some(sample);
        }
        Ok(newest)
    }

    /// Consumes pending event notifications (an undrained listener makes a WaitSet spin).
    pub fn drain_events(&self) {
        let _ = self.listener.try_wait(|_| {});
    }

    /// Sleeps until a frame is announced or `timeout` passes, whichever comes first; false when
    /// SIGINT / SIGTERM ended the wait (see `Inbox::wait`).
    pub fn wait(&self, timeout: Duration) -> bool {
        still_running(self.listener.timed_wait(|_| {}, timeout))
    }
}

impl FileDescriptorBased for FrameInbox {
    fn file_descriptor(&self) -> &FileDescriptor {
        self.listener.file_descriptor()
    }
}

impl SynchronousMultiplexing for FrameInbox {}

impl Attachable for FrameInbox {
    fn drain_events(&self) {
        FrameInbox::drain_events(self);
    }
}

/// Whether a listener's wait ended otherwise than by a termination signal (another signal,
/// e.g. SIGCONT, also interrupts it: the caller just waits again).
fn still_running(waited: Result<u64, iceoryx2::port::listener::ListenerWaitError>) -> bool {
    match waited {
        Err(iceoryx2::port::listener::ListenerWaitError::InterruptSignal) => {
            !crate::termination::interrupted_by_termination()
        }
        _ => !crate::termination::requested(),
    }
}

/// Signals liveness on the service's heartbeat event and publishes a `Heartbeat` record.
pub struct HeartbeatSender {
    service: ServiceId,
    incarnation: u64,
    notifier: Notifier<ipc::Service>,
    health: Outbox<Heartbeat>,
    last: Option<Instant>,
    cycles: u64,
    deadline_misses: u64,
    dropped_samples: u64,
    source_faults: u64,
}

impl HeartbeatSender {
    pub fn new(
        node: &Node<ipc::Service>,
        service: ServiceId,
        incarnation: u64,
    ) -> Result<Self, KitError> {
        let notifier = open_event(node, &service.heartbeat_service())?
            .notifier_builder()
            .create()
            .map_err(iox("heartbeat"))?;
        Ok(Self {
            service,
            incarnation,
            notifier,
            health: Outbox::new(node, services::HEALTH)?,
            last: None,
            cycles: 0,
            deadline_misses: 0,
            dropped_samples: 0,
            source_faults: 0,
        })
    }

    /// Counts a cycle and beats if the heartbeat period has passed. Cheap to call every cycle.
    pub fn beat(&mut self) {
        self.cycles += 1;
        // The loop's tick has the same period, so a wake a little earlier after the last beat
        // than that beat was after its own tick would otherwise skip a whole period (gaps of
        // 200 ms seen under load); a tenth of a period of slack keeps the beat on the tick.
        let due = self
            .last
            .is_none_or(|t| t.elapsed() >= deadlines::HEARTBEAT_PERIOD.mul_f64(0.9));
        if !due {
            return;
        }
        self.last = Some(Instant::now());
        let _ = self.notifier.notify();
        let _ = self.health.send(Heartbeat {
            service: self.service as u32,
            pid: std::process::id(),
            incarnation: self.incarnation,
            cycles: self.cycles,
            deadline_misses: self.deadline_misses,
            wall_time_ns: crate::clock::wall_ns(),
            dropped_samples: self.dropped_samples,
            source_faults: self.source_faults,
        });
    }

    /// Beats now, whatever the period: a service's last word before it exits.
    pub fn beat_now(&mut self) {
        self.last = None;
        self.beat();
    }

    /// Counts samples the source lost (a camera's dropped frames).
    pub fn count_dropped(&mut self, samples: u64) {
        self.dropped_samples += samples;
    }

    /// Counts one fault of the source (stall, unplug, read error, end of stream).
    pub fn count_source_fault(&mut self) {
        self.source_faults += 1;
    }

    /// Counts one missed input deadline; reported with the next heartbeat record.
    pub fn count_deadline_miss(&mut self) {
        self.deadline_misses += 1;
    }

    /// Input deadlines missed since start.
    pub fn deadline_misses(&self) -> u64 {
        self.deadline_misses
    }

    pub fn update_connections(&self) {
        self.health.update_connections();
    }
}

/// Listens to one service's heartbeat (used by the supervisor).
pub fn heartbeat_listener(
    node: &Node<ipc::Service>,
    service: ServiceId,
) -> Result<Listener<ipc::Service>, KitError> {
    open_event(node, &service.heartbeat_service())?
        .listener_builder()
        .create()
        .map_err(iox("heartbeat listener"))
}

/// Loop period used where a service has nothing better to wait on.
pub const IDLE_POLL: Duration = Duration::from_millis(20);
