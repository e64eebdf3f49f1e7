//! Shared-memory output of fulcrumd (iceoryx2 0.10 publish-subscribe); `docs/output.md`.
//!
//! One fulcrum output, named e.g. `comanip/fulcrum`, is a publish-subscribe service of
//! [`FulcrumSample`]s (iceoryx2 type name `comanip::FulcrumSample`, 200 bytes, `#[repr(C)]`)
//! plus an event service of the same name that wakes blocking subscribers.
//!
//! - The daemon: [`FulcrumPublisher::create`] once, then [`FulcrumPublisher::publish`] every
//!   cycle (1 kHz, from the real-time thread; see [`crate::rt_alloc`] for iceoryx2's one heap
//!   allocation per sample).
//! - A client: [`FulcrumSubscriber::connect`], then [`FulcrumSubscriber::wait`] (blocks on the
//!   event listener) or [`FulcrumSubscriber::try_recv`]; each [`Received`] sample says how it
//!   follows the previous one ([`Continuity`]): in order, after a gap, or after a daemon restart.
//!
//! Either side may start first, subscribers may come and go, and the daemon may be restarted
//! (even after SIGKILL) under running subscribers. Neither side installs signal handlers unless
//! [`PublisherOptions::iceoryx2_signal_handlers`] asks for it. iceoryx2 keeps its state in
//! `/tmp/iceoryx2` and `/dev/shm/iox2_*`.

mod message;
mod publisher;
mod service;
mod subscriber;

pub mod logging;

pub use logging::route_iceoryx2_logs_to_tracing;
pub use message::{FULCRUM_SAMPLE_VERSION, FulcrumSample, STATE_INSIDE, STATE_INVALID, STATE_OUTSIDE, health};
pub use publisher::{CreateError, FulcrumPublisher, PublishError};
pub use service::{OpenError, PublisherOptions};
pub use subscriber::{ConnectError, Continuity, FulcrumSubscriber, Received, RecvError, SubscriberCounters, WaitError};
