//! Camera frames over shared memory: the frame service (`docs/frames.md`).
//!
//! A frame service, named e.g. `comanip/frames/endoscope`, is an iceoryx2 publish-subscribe
//! service whose payload is the frame's pixels (a `[u8]` slice: the eyes one after the other,
//! each `stride × height` bytes, rows top to bottom) and whose user header is a versioned
//! `#[repr(C)]` [`FrameHeader`] (sequence, camera id, timestamp, exposure, size, stride, pixel
//! format), plus an event service of the same name that wakes blocking subscribers, as for
//! fulcrumd's output ([`super::Publisher`]).
//!
//! Zero-copy: the publisher [`loan`](FramePublisher::loan)s a slot of shared memory, the camera
//! source writes the pixels straight into it ([`crate::camera::CameraSource::next_into`]), and
//! every subscriber reads them in place ([`ReceivedFrame::pixels`]) until it drops the frame.
//!
//! Times are nanoseconds of `CLOCK_MONOTONIC` (see [`crate::frame`] for pairing them with
//! the CAN receive timestamps, which are Unix time); sizes are pixels and bytes.

use std::time::{Duration, Instant};

use iceoryx2::node::Node;
use iceoryx2::port::ReceiveError;
use iceoryx2::port::listener::{Listener, ListenerCreateError, ListenerWaitError};
use iceoryx2::port::notifier::{Notifier, NotifierCreateError};
use iceoryx2::port::publisher::{Publisher as IoxPublisher, PublisherCreateError};
use iceoryx2::port::subscriber::{Subscriber as IoxSubscriber, SubscriberCreateError};
use iceoryx2::prelude::{AllocationStrategy, BackpressureStrategy, ServiceName, ZeroCopySend, ipc};
use iceoryx2::sample::Sample;
use iceoryx2::sample_mut::SampleMut;
use iceoryx2::service::builder::publish_subscribe::PublishSubscribeOpenOrCreateError;
use iceoryx2::service::port_factory::publish_subscribe;

use super::continuity::{Continuity, ContinuityTracker};
use super::publisher::PublishError;
use super::service::{self, EventFactory, OpenError, PublisherOptions};
use crate::frame::{FormatError, FrameFormat, FrameMeta, ImageLayout, PixelFormat, UnknownPixelFormat};

/// Layout version of [`FrameHeader`]. Bumped on any change of field, order or meaning.
pub const FRAME_HEADER_VERSION: u32 = 1;

/// The default frame service of the first endoscope.
pub const DEFAULT_FRAME_SERVICE: &str = "comanip/frames/endoscope";

/// The header of one frame on the frame service: 72 bytes, `#[repr(C)]`, no padding (the C
/// declaration is in `docs/frames.md`). iceoryx2 type name `comanip::FrameHeader`.
///
/// The pixels follow as the sample's payload (`payload_bytes` bytes).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("comanip::FrameHeader")]
#[repr(C)]
pub struct FrameHeader {
    /// Layout version, [`FRAME_HEADER_VERSION`]. Offset 0.
    pub version: u32,
    /// Which camera rig (configured; 0 for the first endoscope). Offset 4.
    pub camera_id: u32,
    /// 0 for the publisher run's first frame, +1 per frame. Offset 8.
    pub sequence: u64,
    /// Random per publisher start. Offset 16.
    pub run_id: u64,
    /// Mid time of the exposure, nanoseconds of `CLOCK_MONOTONIC`. Offset 24.
    pub timestamp_ns: u64,
    /// Exposure time, nanoseconds (0 when unknown). Offset 32.
    pub exposure_ns: u32,
    /// Number of eyes: 1 (mono) or 2 (stereo, left first). Offset 36.
    pub eyes: u32,
    /// Width of each eye's image, pixels. Offset 40.
    pub width: u32,
    /// Height of each eye's image, pixels. Offset 44.
    pub height: u32,
    /// Bytes from one row's start to the next. Offset 48.
    pub stride: u32,
    /// Pixel format code ([`PixelFormat::code`]: 1 gray8, 2 rgb8, 3 yuyv). Offset 52.
    pub pixel_format: u32,
    /// Bytes of pixels that follow: `eyes × stride × height`. Offset 56.
    pub payload_bytes: u64,
    /// Frames the camera source lost before this one since it was opened (a capture driver's
    /// sequence gaps), cumulative; frames lost in the transport show as sequence gaps instead.
    /// Offset 64.
    pub source_dropped: u64,
}

/// Why a received [`FrameHeader`] does not describe a usable frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameHeaderError {
    /// A layout version this program does not read.
    #[error("frame header layout version {found}, this program reads version {expected}")]
    Version {
        /// The header's version.
        found: u32,
        /// [`FRAME_HEADER_VERSION`].
        expected: u32,
    },
    /// The pixel format code is unknown.
    #[error(transparent)]
    PixelFormat(#[from] UnknownPixelFormat),
    /// Eyes or layout out of range.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// `payload_bytes` or the payload's real length disagrees with the layout.
    #[error("payload of {actual} bytes (header says {declared}), the layout needs {expected}")]
    PayloadLength {
        /// `eyes × stride × height`.
        expected: usize,
        /// The header's `payload_bytes`.
        declared: u64,
        /// The sample's payload length.
        actual: usize,
    },
}

impl FrameHeader {
    /// The header of frame `meta` (its `sequence` is used as is) of run `run_id`.
    pub fn new(meta: &FrameMeta, run_id: u64, source_dropped: u64) -> Self {
        Self {
            version: FRAME_HEADER_VERSION,
            camera_id: meta.camera_id,
            sequence: meta.sequence,
            run_id,
            timestamp_ns: meta.timestamp_ns,
            exposure_ns: meta.exposure_ns,
            eyes: meta.eyes,
            width: meta.layout.width,
            height: meta.layout.height,
            stride: meta.layout.stride,
            pixel_format: meta.layout.format.code(),
            payload_bytes: meta.payload_bytes() as u64,
            source_dropped,
        }
    }

    /// The frame's metadata, checked: version, pixel format, eyes, layout, and that
    /// `payload_len` (the payload's real length, bytes) and `payload_bytes` both match the layout.
    pub fn meta(&self, payload_len: usize) -> Result<FrameMeta, FrameHeaderError> {
        if self.version != FRAME_HEADER_VERSION {
            return Err(FrameHeaderError::Version { found: self.version, expected: FRAME_HEADER_VERSION });
        }
        let format = PixelFormat::from_code(self.pixel_format)?;
        let layout = ImageLayout { width: self.width, height: self.height, stride: self.stride, format };
        let frame_format = FrameFormat::new(self.eyes, layout)?;
        let expected = frame_format.payload_bytes();
        if self.payload_bytes != expected as u64 || payload_len != expected {
            return Err(FrameHeaderError::PayloadLength {
                expected,
                declared: self.payload_bytes,
                actual: payload_len,
            });
        }
        Ok(FrameMeta {
            sequence: self.sequence,
            camera_id: self.camera_id,
            timestamp_ns: self.timestamp_ns,
            exposure_ns: self.exposure_ns,
            eyes: self.eyes,
            layout,
        })
    }
}

impl PublisherOptions {
    /// Defaults for a frame service: 4 subscribers, each holding the 2 newest frames, no
    /// history. Shared memory of the publisher: about `payload × (4 × (2 + 2) + 2)` bytes
    /// (1.8 MB stereo 640×480 RGB frames: about 33 MB).
    pub fn frames() -> Self {
        Self { max_subscribers: 4, subscriber_buffer: 2, history: 0, iceoryx2_signal_handlers: false }
    }
}

/// Frames a subscriber may hold at once (each [`ReceivedFrame`] holds one shared-memory slot).
const MAX_BORROWED_FRAMES: usize = 2;

type FrameFactory = publish_subscribe::PortFactory<ipc::Service, [u8], FrameHeader>;

/// Why [`FramePublisher::create`] failed.
#[derive(Debug, thiserror::Error)]
pub enum FrameCreateError {
    /// The format is out of range.
    #[error("invalid frame format: {0}")]
    Format(#[from] FormatError),
    /// The options, the name, the node or the event service.
    #[error(transparent)]
    Open(#[from] OpenError),
    /// The frame service could not be opened or created (it exists with other capacities or
    /// another header version).
    #[error("cannot open or create the frame service: {0}")]
    Service(#[source] PublishSubscribeOpenOrCreateError),
    /// The publisher port could not be created; `ExceedsMaxSupportedPublishers` means another
    /// live camera process owns this service.
    #[error("cannot create the frame publisher: {0}")]
    Publisher(#[source] PublisherCreateError),
    /// The notifier port could not be created.
    #[error("cannot create the notifier: {0}")]
    Notifier(#[source] NotifierCreateError),
}

/// Why [`FramePublisher::publish`] failed.
#[derive(Debug, thiserror::Error)]
pub enum FramePublishError {
    /// The pixels given are not one frame of the publisher's format.
    #[error("{got} bytes of pixels, one frame of this publisher's format is {expected}")]
    Size {
        /// [`FrameFormat::payload_bytes`].
        expected: usize,
        /// The length given.
        got: usize,
    },
    /// Loan, send or notify.
    #[error(transparent)]
    Publish(#[from] PublishError),
}

/// Why [`FrameSubscriber::connect`] failed.
#[derive(Debug, thiserror::Error)]
pub enum FrameConnectError {
    /// The options, the name, the node or the event service.
    #[error(transparent)]
    Open(#[from] OpenError),
    /// The frame service could not be opened or created (another header version or capacities).
    #[error("cannot open or create the frame service: {0}")]
    Service(#[source] PublishSubscribeOpenOrCreateError),
    /// The subscriber port could not be created (all `max_subscribers` slots taken).
    #[error("cannot create the frame subscriber: {0}")]
    Subscriber(#[source] SubscriberCreateError),
    /// The listener port could not be created.
    #[error("cannot create the listener: {0}")]
    Listener(#[source] ListenerCreateError),
}

/// Why [`FrameSubscriber::try_recv`] failed.
#[derive(Debug, thiserror::Error)]
pub enum FrameRecvError {
    /// iceoryx2 could not take a sample.
    #[error("cannot receive a frame: {0}")]
    Receive(#[source] ReceiveError),
    /// A frame whose header is not usable (another version, an unknown format, a length that
    /// disagrees with the layout). Dropped and counted ([`FrameCounters::rejected`]); the next
    /// call goes on with the next frame.
    #[error("frame refused: {0}")]
    Header(#[from] FrameHeaderError),
}

/// Why [`FrameSubscriber::wait`] failed.
#[derive(Debug, thiserror::Error)]
pub enum FrameWaitError {
    /// Taking the frame failed.
    #[error(transparent)]
    Recv(#[from] FrameRecvError),
    /// Waiting on the event listener failed.
    #[error("cannot wait for a notification: {0}")]
    Listener(#[source] ListenerWaitError),
}

/// What [`open_frame_service`] can fail on: the shared part or the frame service itself.
enum FrameOpenError {
    Open(OpenError),
    Service(PublishSubscribeOpenOrCreateError),
}

impl From<OpenError> for FrameOpenError {
    fn from(e: OpenError) -> Self {
        Self::Open(e)
    }
}

impl From<FrameOpenError> for FrameCreateError {
    fn from(e: FrameOpenError) -> Self {
        match e {
            FrameOpenError::Open(e) => Self::Open(e),
            FrameOpenError::Service(e) => Self::Service(e),
        }
    }
}

impl From<FrameOpenError> for FrameConnectError {
    fn from(e: FrameOpenError) -> Self {
        match e {
            FrameOpenError::Open(e) => Self::Open(e),
            FrameOpenError::Service(e) => Self::Service(e),
        }
    }
}

fn open_frame_service(
    service_name: &str,
    opts: &PublisherOptions,
    node_name: &'static str,
    signal_handlers: bool,
) -> Result<(Node<ipc::Service>, FrameFactory, EventFactory), FrameOpenError> {
    opts.check().map_err(OpenError::InvalidOptions)?;
    let name = ServiceName::new(service_name)
        .map_err(|source| OpenError::InvalidServiceName { name: service_name.to_owned(), source })?;
    let node = service::node(node_name, signal_handlers).map_err(OpenError::Node)?;
    let pubsub = node
        .service_builder(&name)
        .publish_subscribe::<[u8]>()
        .user_header::<FrameHeader>()
        .max_publishers(1)
        .max_subscribers(opts.max_subscribers)
        .max_nodes(opts.max_subscribers + 2)
        .subscriber_max_buffer_size(opts.subscriber_buffer)
        .subscriber_max_borrowed_samples(MAX_BORROWED_FRAMES)
        .history_size(opts.history)
        .enable_safe_overflow(true)
        .open_or_create()
        .map_err(FrameOpenError::Service)?;
    let event = service::open_event(&node, &name, opts).map_err(OpenError::EventService)?;
    Ok((node, pubsub, event))
}

/// Publishes the frames of one camera rig on a frame service and wakes its subscribers.
///
/// ```no_run
/// use hw_io::frame::{FrameFormat, ImageLayout, PixelFormat};
/// use hw_io::ipc::{FramePublisher, PublisherOptions};
///
/// # fn main() -> Result<(), Box<dyn core::error::Error>> {
/// let format = FrameFormat::new(2, ImageLayout::packed(640, 480, PixelFormat::Rgb8)?)?;
/// let mut publisher = FramePublisher::create("comanip/frames/endoscope", format, 0, &PublisherOptions::frames())?;
/// let mut slot = publisher.loan()?;
/// slot.pixels_mut().fill(128); // a camera source writes here (zero-copy)
/// let header = slot.send(1_000_000_000, 16_000_000)?; // mid-exposure time, exposure (ns)
/// assert_eq!(header.sequence, 0);
/// # Ok(()) }
/// ```
///
/// Single-threaded (iceoryx2 ports are neither `Send` nor `Sync`). A subscriber that reads too
/// slowly loses its oldest frames (the publisher never blocks) and sees a
/// [`Continuity::Gap`].
#[derive(Debug)]
pub struct FramePublisher {
    publisher: IoxPublisher<ipc::Service, [u8], FrameHeader>,
    notifier: Notifier<ipc::Service>,
    _node: Node<ipc::Service>,
    format: FrameFormat,
    camera_id: u32,
    run_id: u64,
    next_sequence: u64,
    source_dropped: u64,
}

/// A loaned shared-memory slot for one frame: write the pixels, then [`send`](Self::send) it.
/// Dropping it unsent gives the slot back and uses no sequence number.
#[derive(Debug)]
pub struct FrameSlot<'a> {
    sample: SampleMut<ipc::Service, [u8], FrameHeader>,
    publisher: &'a mut FramePublisher,
}

impl FramePublisher {
    /// Opens (or creates) the frame service `service_name` and its publisher for frames of
    /// `format` from camera rig `camera_id`. The run id is random.
    pub fn create(
        service_name: &str,
        format: FrameFormat,
        camera_id: u32,
        opts: &PublisherOptions,
    ) -> Result<Self, FrameCreateError> {
        format.validate()?;
        let (node, pubsub, event) =
            open_frame_service(service_name, opts, "comanip-frame-publisher", opts.iceoryx2_signal_handlers)?;
        let publisher = pubsub
            .publisher_builder()
            .initial_max_slice_len(format.payload_bytes())
            .allocation_strategy(AllocationStrategy::Static)
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .max_loaned_samples(2)
            .create()
            .map_err(FrameCreateError::Publisher)?;
        let notifier = event.notifier_builder().create().map_err(FrameCreateError::Notifier)?;
        Ok(Self {
            publisher,
            notifier,
            _node: node,
            format,
            camera_id,
            run_id: new_run_id(),
            next_sequence: 0,
            source_dropped: 0,
        })
    }

    /// The format of every frame this publisher sends.
    pub fn format(&self) -> FrameFormat {
        self.format
    }

    /// The random id of this publisher run (in every header).
    pub fn run_id(&self) -> u64 {
        self.run_id
    }

    /// Frames sent since creation.
    pub fn published(&self) -> u64 {
        self.next_sequence
    }

    /// Sets the cumulative count of frames the source lost, written into the following headers
    /// ([`FrameHeader::source_dropped`]).
    pub fn set_source_dropped(&mut self, dropped: u64) {
        self.source_dropped = dropped;
    }

    /// Loans a slot of shared memory for the next frame, its pixels zeroed.
    pub fn loan(&mut self) -> Result<FrameSlot<'_>, PublishError> {
        let len = self.format.payload_bytes();
        let mut uninit = self.publisher.loan_slice_uninit(len).map_err(PublishError::Loan)?;
        let payload = uninit.payload_mut();
        // SAFETY: `payload` is `len` valid, writable `MaybeUninit<u8>`s of the loaned chunk;
        // writing zero bytes over all of them initialises every element, so `assume_init` below
        // sees a fully initialised `[u8]`.
        unsafe { core::ptr::write_bytes(payload.as_mut_ptr(), 0, payload.len()) };
        // SAFETY: every element was initialised just above.
        let sample = unsafe { uninit.assume_init() };
        Ok(FrameSlot { sample, publisher: self })
    }

    /// Copies one frame's `pixels` (the eyes one after the other) into shared memory and sends it
    /// with its mid-exposure `timestamp_ns` and `exposure_ns` (nanoseconds, `CLOCK_MONOTONIC`).
    pub fn publish(
        &mut self,
        pixels: &[u8],
        timestamp_ns: u64,
        exposure_ns: u32,
    ) -> Result<FrameHeader, FramePublishError> {
        let expected = self.format.payload_bytes();
        if pixels.len() != expected {
            return Err(FramePublishError::Size { expected, got: pixels.len() });
        }
        let mut slot = self.loan()?;
        slot.pixels_mut().copy_from_slice(pixels);
        Ok(slot.send(timestamp_ns, exposure_ns)?)
    }
}

impl FrameSlot<'_> {
    /// The slot's pixels (`format().payload_bytes()` bytes, the eyes one after the other).
    pub fn pixels_mut(&mut self) -> &mut [u8] {
        self.sample.payload_mut()
    }

    /// Sets the cumulative count of frames the source lost ([`FrameHeader::source_dropped`] of
    /// this and the following frames).
    pub fn set_source_dropped(&mut self, dropped: u64) {
        self.publisher.source_dropped = dropped;
    }

    /// Sends the frame with its mid-exposure time and exposure (nanoseconds, `CLOCK_MONOTONIC`)
    /// to every subscriber, then wakes them; returns the header sent.
    pub fn send(mut self, timestamp_ns: u64, exposure_ns: u32) -> Result<FrameHeader, PublishError> {
        let p = &mut *self.publisher;
        let meta = FrameMeta {
            sequence: p.next_sequence,
            camera_id: p.camera_id,
            timestamp_ns,
            exposure_ns,
            eyes: p.format.eyes,
            layout: p.format.layout,
        };
        let header = FrameHeader::new(&meta, p.run_id, p.source_dropped);
        *self.sample.user_header_mut() = header;
        self.sample.send().map_err(PublishError::Send)?;
        p.next_sequence += 1;
        p.notifier.notify().map_err(PublishError::Notify)?;
        Ok(header)
    }
}

/// A random 64-bit run id (std's randomly keyed SipHash over the time and the process id).
fn new_run_id() -> u64 {
    use std::hash::BuildHasher;
    std::hash::RandomState::new().hash_one((std::time::SystemTime::now(), std::process::id()))
}

/// What a frame subscriber has seen since it connected.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrameCounters {
    /// Frames accepted.
    pub received: u64,
    /// Frames lost in the transport (this subscriber read too slowly): the sum of every
    /// [`Continuity::Gap::missed`].
    pub missed: u64,
    /// Publisher restarts seen.
    pub restarts: u64,
    /// Frames refused for their header ([`FrameRecvError::Header`]).
    pub rejected: u64,
    /// Frames the camera source lost, as the latest header says (cumulative, per publisher run).
    pub source_dropped: u64,
}

/// A frame read in place from shared memory, with how it follows the previous one. Holds a
/// shared-memory slot until dropped (a subscriber holds at most 2 at once).
#[derive(Debug)]
pub struct ReceivedFrame {
    sample: Sample<ipc::Service, [u8], FrameHeader>,
    meta: FrameMeta,
    /// Continuity with the previous accepted frame.
    pub event: Continuity,
}

impl ReceivedFrame {
    /// The frame's checked metadata (timestamp in nanoseconds of `CLOCK_MONOTONIC`).
    pub fn meta(&self) -> &FrameMeta {
        &self.meta
    }

    /// The raw header.
    pub fn header(&self) -> &FrameHeader {
        self.sample.user_header()
    }

    /// All pixels (the eyes one after the other), in shared memory.
    pub fn pixels(&self) -> &[u8] {
        self.sample.payload()
    }

    /// Eye `index`'s image (0 left, 1 right), `stride × height` bytes; `None` past the last eye.
    pub fn eye(&self, index: u32) -> Option<&[u8]> {
        if index >= self.meta.eyes {
            return None;
        }
        let n = self.meta.layout.eye_bytes();
        let start = index as usize * n;
        self.pixels().get(start..start + n)
    }
}

/// Reads a frame service.
///
/// ```no_run
/// use std::time::Duration;
/// use hw_io::ipc::{FrameSubscriber, PublisherOptions};
///
/// # fn main() -> Result<(), Box<dyn core::error::Error>> {
/// let mut sub = FrameSubscriber::connect("comanip/frames/endoscope", &PublisherOptions::frames())?;
/// if let Some(frame) = sub.wait(Duration::from_secs(1))? {
///     let m = frame.meta();
///     println!("frame {} at {} ns: {}×{} {}", m.sequence, m.timestamp_ns, m.layout.width, m.layout.height, m.layout.format);
///     let _left: &[u8] = frame.eye(0).unwrap_or_default();
/// }
/// # Ok(()) }
/// ```
#[derive(Debug)]
pub struct FrameSubscriber {
    subscriber: IoxSubscriber<ipc::Service, [u8], FrameHeader>,
    listener: Listener<ipc::Service>,
    _node: Node<ipc::Service>,
    tracker: ContinuityTracker,
    counters: FrameCounters,
}

/// Longest single sleep in [`FrameSubscriber::wait`] (re-check should a notification be lost).
const MAX_SLEEP: Duration = Duration::from_millis(100);

impl FrameSubscriber {
    /// Connects to the frame service `service_name` (same capacities as the publisher's:
    /// usually [`PublisherOptions::frames`]); creates it when no publisher runs yet.
    pub fn connect(service_name: &str, opts: &PublisherOptions) -> Result<Self, FrameConnectError> {
        let (node, pubsub, event) = open_frame_service(service_name, opts, "comanip-frame-subscriber", false)?;
        let subscriber = pubsub
            .subscriber_builder()
            .buffer_size(opts.subscriber_buffer)
            .create()
            .map_err(FrameConnectError::Subscriber)?;
        let listener = event.listener_builder().create().map_err(FrameConnectError::Listener)?;
        Ok(Self {
            subscriber,
            listener,
            _node: node,
            tracker: ContinuityTracker::default(),
            counters: FrameCounters::default(),
        })
    }

    /// The next frame if one is buffered, else `None` at once.
    pub fn try_recv(&mut self) -> Result<Option<ReceivedFrame>, FrameRecvError> {
        let Some(sample) = self.subscriber.receive().map_err(FrameRecvError::Receive)? else {
            return Ok(None);
        };
        let header = *sample.user_header();
        let meta = match header.meta(sample.payload().len()) {
            Ok(meta) => meta,
            Err(e) => {
                self.counters.rejected += 1;
                return Err(e.into());
            }
        };
        let event = self.tracker.observe(header.run_id, header.sequence);
        self.counters.received += 1;
        self.counters.source_dropped = header.source_dropped;
        match event {
            Continuity::Gap { missed } => self.counters.missed += missed,
            Continuity::Restart => self.counters.restarts += 1,
            Continuity::First | Continuity::InOrder => {}
        }
        Ok(Some(ReceivedFrame { sample, meta, event }))
    }

    /// The next frame, blocking on the event listener for at most `timeout`; `None` when none
    /// arrived in time.
    pub fn wait(&mut self, timeout: Duration) -> Result<Option<ReceivedFrame>, FrameWaitError> {
        let start = Instant::now();
        loop {
            if let Some(frame) = self.try_recv()? {
                return Ok(Some(frame));
            }
            let remaining = timeout.saturating_sub(start.elapsed());
            if remaining.is_zero() {
                return Ok(None);
            }
            match self.listener.timed_wait(|_| {}, remaining.min(MAX_SLEEP)) {
                Ok(_) | Err(ListenerWaitError::InterruptSignal) => {}
                Err(e) => return Err(FrameWaitError::Listener(e)),
            }
        }
    }

    /// What this subscriber has seen since it connected.
    pub fn counters(&self) -> FrameCounters {
        self.counters
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_is_72_bytes_without_padding_at_the_documented_offsets() {
        assert_eq!(core::mem::size_of::<FrameHeader>(), 72);
        assert_eq!(core::mem::align_of::<FrameHeader>(), 8);
        assert_eq!(core::mem::offset_of!(FrameHeader, version), 0);
        assert_eq!(core::mem::offset_of!(FrameHeader, camera_id), 4);
        assert_eq!(core::mem::offset_of!(FrameHeader, sequence), 8);
        assert_eq!(core::mem::offset_of!(FrameHeader, run_id), 16);
        assert_eq!(core::mem::offset_of!(FrameHeader, timestamp_ns), 24);
        assert_eq!(core::mem::offset_of!(FrameHeader, exposure_ns), 32);
        assert_eq!(core::mem::offset_of!(FrameHeader, eyes), 36);
        assert_eq!(core::mem::offset_of!(FrameHeader, width), 40);
        assert_eq!(core::mem::offset_of!(FrameHeader, height), 44);
        assert_eq!(core::mem::offset_of!(FrameHeader, stride), 48);
        assert_eq!(core::mem::offset_of!(FrameHeader, pixel_format), 52);
        assert_eq!(core::mem::offset_of!(FrameHeader, payload_bytes), 56);
        assert_eq!(core::mem::offset_of!(FrameHeader, source_dropped), 64);
    }

    fn meta() -> FrameMeta {
        FrameMeta {
            sequence: 5,
            camera_id: 1,
            timestamp_ns: 123,
            exposure_ns: 4,
            eyes: 2,
            layout: ImageLayout::packed(4, 3, PixelFormat::Rgb8).unwrap(),
        }
    }

    #[test]
    fn header_round_trips_and_every_inconsistency_is_refused() {
        let m = meta();
        let h = FrameHeader::new(&m, 9, 2);
        assert_eq!(h.meta(72), Ok(m));
        assert_eq!(h.payload_bytes, 72);
        assert_eq!(h.meta(71), Err(FrameHeaderError::PayloadLength { expected: 72, declared: 72, actual: 71 }));
        let mut bad = h;
        bad.version = 2;
        assert_eq!(bad.meta(72), Err(FrameHeaderError::Version { found: 2, expected: 1 }));
        let mut bad = h;
        bad.pixel_format = 9;
        assert_eq!(bad.meta(72), Err(FrameHeaderError::PixelFormat(UnknownPixelFormat(9))));
        let mut bad = h;
        bad.eyes = 3;
        assert_eq!(bad.meta(108), Err(FrameHeaderError::Format(FormatError::Eyes(3))));
        let mut bad = h;
        bad.stride = 2;
        assert!(matches!(bad.meta(72), Err(FrameHeaderError::Format(FormatError::Layout(_)))));
        let mut bad = h;
        bad.payload_bytes = 73;
        assert!(matches!(bad.meta(72), Err(FrameHeaderError::PayloadLength { declared: 73, .. })));
        let mut bad = h;
        bad.width = u32::MAX;
        assert!(bad.meta(72).is_err());
    }
}
