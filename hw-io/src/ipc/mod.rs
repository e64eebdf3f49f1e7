//! Shared-memory messages (iceoryx2 0.10 publish-subscribe); `docs/output.md`. Feature `ipc`.
//!
//! An output, named e.g. `comanip/fulcrum`, is a publish-subscribe service of one [`Message`]
//! type plus an event service of the same name that wakes blocking subscribers. The transport
//! is generic: [`Publisher<M>`](Publisher) and [`Subscriber<M>`](Subscriber) carry any
//! versioned `#[repr(C)]` message, check its version and compute its [`Continuity`] from its
//! run id and sequence.
//!
//! fulcrumd's output is [`FulcrumSample`]s (iceoryx2 type name `comanip::FulcrumSample`, 200
//! bytes, `#[repr(C)]`), with typed views of its state ([`OutputState`]) and health
//! ([`HealthFlags`]):
//!
//! - The daemon: [`FulcrumPublisher::create`] once, then [`FulcrumPublisher::publish`] every
//!   cycle (1 kHz, from the real-time thread; see [`crate::rt_alloc`] for iceoryx2's one heap
//!   allocation per sample).
//! - A client: [`FulcrumSubscriber::connect`], then [`FulcrumSubscriber::wait`] (blocks on the
//!   event listener) or [`FulcrumSubscriber::try_recv`]; each [`Received`] sample says how it
//!   follows the previous one ([`Continuity`]): in order, after a gap, or after a daemon restart.
//!
//! ```no_run
//! use std::time::Duration;
//! use hw_io::ipc::{FulcrumSubscriber, OutputState};
//!
//! # fn main() -> Result<(), Box<dyn core::error::Error>> {
//! let mut sub = FulcrumSubscriber::connect("comanip/fulcrum")?;
//! if let Some(r) = sub.wait(Duration::from_secs(1))? {
//!     let state: OutputState = r.sample.state()?;
//!     println!("cycle {}: {state}, health {}", r.sample.sequence, r.sample.health());
//! }
//! # Ok(()) }
//! ```
//!
//! The live calibration publishes [`CalibrationSample`]s (`comanip-calib live`, issue 19); the
//! live tool tracker [`TrackSample`]s (`comanip-track live`, issue 18).
//!
//! Camera frames have their own service shape (a `#[repr(C)]` [`FrameHeader`] followed by the
//! pixels, zero-copy): [`FramePublisher`] and [`FrameSubscriber`], `docs/frames.md`.
//!
//! Either side may start first, subscribers may come and go, and the daemon may be restarted
//! (even after SIGKILL) under running subscribers. Neither side installs signal handlers unless
//! [`PublisherOptions::iceoryx2_signal_handlers`] asks for it. iceoryx2 keeps its state in
//! `/tmp/iceoryx2` and `/dev/shm/iox2_*`.

mod calibration;
mod continuity;
mod frames;
mod fulcrum;
mod message;
mod publisher;
mod service;
mod subscriber;
mod track;

pub mod logging;

pub use calibration::{CALIBRATION_SAMPLE_VERSION, CalibrationSample, CalibrationState, DEFAULT_CALIBRATION_SERVICE};
pub use continuity::Continuity;
pub use frames::{
    DEFAULT_FRAME_SERVICE, FRAME_HEADER_VERSION, FrameConnectError, FrameCounters, FrameCreateError, FrameHeader,
    FrameHeaderError, FramePublishError, FramePublisher, FrameRecvError, FrameSlot, FrameSubscriber, FrameWaitError,
    ReceivedFrame,
};
pub use fulcrum::{FULCRUM_SAMPLE_VERSION, FulcrumSample, HealthFlags, OutputState, UnknownState};
/// iceoryx2's derive macro and trait for shared-memory payloads, re-exported so that a crate
/// defining a [`Message`] needs no direct iceoryx2 dependency (`#[derive(ZeroCopySend)]`,
/// `#[type_name("...")]`, `#[repr(C)]`).
pub use iceoryx2::prelude::ZeroCopySend;
pub use logging::route_iceoryx2_logs_to_tracing;
pub use message::{InvalidMessage, Message};
pub use publisher::{CreateError, FulcrumPublisher, PublishError, Publisher};
pub use service::{OpenError, PublisherOptions};
pub use subscriber::{
    ConnectError, FulcrumSubscriber, ReceiveCheck, Received, RecvError, Subscriber, SubscriberCounters, WaitError,
};
pub use track::{DEFAULT_TRACK_SERVICE, TRACK_SAMPLE_VERSION, TrackReasons, TrackSample, TrackStatus};
