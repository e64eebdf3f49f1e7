//! The client side: what a guidance-force module links to read fulcrumd's output, generic over
//! the [`Message`] it reads.

use std::time::{Duration, Instant};

use iceoryx2::node::Node;
use iceoryx2::port::ReceiveError;
use iceoryx2::port::listener::{Listener, ListenerCreateError, ListenerWaitError};
use iceoryx2::port::subscriber::{Subscriber as IoxSubscriber, SubscriberCreateError};
use iceoryx2::prelude::ipc;

use super::continuity::{Continuity, ContinuityTracker};
use super::message::InvalidMessage;
use super::service::{self, OpenError, PublisherOptions, Services};
use super::{FulcrumSample, Message};

/// Longest single sleep inside [`Subscriber::wait`]: a safety net that re-checks the
/// buffer should a wake-up notification be lost (a daemon killed between its send and its
/// notify). Not a poll: an idle subscriber wakes 10 times a second.
const MAX_SLEEP: Duration = Duration::from_millis(100);

/// A message (by default a [`FulcrumSample`]) and how it follows the previous one.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Received<M: Message = FulcrumSample> {
    /// The message, copied out of shared memory; its version is [`Message::VERSION`].
    pub sample: M,
    /// Its continuity with the previous accepted message.
    pub event: Continuity,
}

/// What a subscriber has seen since it connected.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SubscriberCounters {
    /// Messages accepted (returned as [`Received`]).
    pub received: u64,
    /// Messages lost: the sum of every [`Continuity::Gap::missed`].
    pub missed: u64,
    /// Publisher (daemon) restarts seen ([`Continuity::Restart`]).
    pub restarts: u64,
    /// Messages refused for another layout version ([`RecvError::VersionMismatch`]) or a
    /// broken invariant ([`RecvError::Invalid`]).
    pub rejected: u64,
}

/// Why [`Subscriber::connect`] failed.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    /// The options, the name, the node or the services (shared with the daemon's side);
    /// an incompatible service means the daemon runs another layout version or other options.
    #[error(transparent)]
    Open(#[from] OpenError),
    /// The subscriber port could not be created; `ExceedsMaxSupportedSubscribers` means all
    /// `max_subscribers` slots are taken by live subscribers.
    #[error("cannot create the subscriber: {0}")]
    Subscriber(#[source] SubscriberCreateError),
    /// The listener port could not be created.
    #[error("cannot create the listener: {0}")]
    Listener(#[source] ListenerCreateError),
}

/// Why [`Subscriber::try_recv`] failed.
#[derive(Debug, thiserror::Error)]
pub enum RecvError {
    /// iceoryx2 could not take a sample (a connection to the publisher is broken).
    #[error("cannot receive: {0}")]
    Receive(#[source] ReceiveError),
    /// A message of another layout version arrived. It was dropped and counted
    /// ([`SubscriberCounters::rejected`]); continuity is unaffected and the next call goes on
    /// with the next message. Persistent: the publisher and this program disagree on the layout.
    #[error("{type_name} layout version {found}, this subscriber reads version {expected}")]
    VersionMismatch {
        /// The message type's [`Message::TYPE_NAME`].
        type_name: &'static str,
        /// The message's version.
        found: u32,
        /// [`Message::VERSION`] of this program.
        expected: u32,
    },
    /// A message of the right version broke its own invariants ([`Message::check`]: for a
    /// [`FulcrumSample`], a valid state with a non-finite float or an invalidating flag). It was
    /// dropped and counted ([`SubscriberCounters::rejected`]); continuity is unaffected.
    #[error("{type_name} refused: {broken}")]
    Invalid {
        /// The message type's [`Message::TYPE_NAME`].
        type_name: &'static str,
        /// The invariant broken.
        broken: InvalidMessage,
    },
}

/// Why [`Subscriber::wait`] failed.
#[derive(Debug, thiserror::Error)]
pub enum WaitError {
    /// Taking the sample failed (see [`RecvError`]; a version mismatch is not fatal).
    #[error(transparent)]
    Recv(#[from] RecvError),
    /// Waiting on the event listener failed.
    #[error("cannot wait for a notification: {0}")]
    Listener(#[source] ListenerWaitError),
}

/// Reads an output of messages `M`; fulcrumd's is a [`FulcrumSubscriber`].
///
/// ```no_run
/// use std::time::Duration;
/// use hw_io::ipc::{Continuity, FulcrumSample, OutputState, Subscriber};
///
/// # fn main() -> Result<(), Box<dyn core::error::Error>> {
/// let mut sub = Subscriber::<FulcrumSample>::connect("comanip/fulcrum")?;
/// loop {
///     match sub.wait(Duration::from_millis(10))? {
///         Some(r) if r.event == Continuity::Restart => println!("fulcrumd restarted"),
///         Some(r) => match r.sample.state()? {
///             OutputState::Inside => println!("fulcrum {:?} m (base frame)", r.sample.fulcrum_base_m),
///             OutputState::Outside => {}
///             OutputState::Invalid => println!("invalid: {}", r.sample.health()),
///         },
///         None => println!("no sample for 10 ms: fulcrumd is not running"),
///     }
/// }
/// # }
/// ```
///
/// Works whether the publisher runs or not, survives its restarts (each one shows as one
/// [`Continuity::Restart`]), and never busy-polls. Single-threaded (neither `Send` nor `Sync`).
#[derive(Debug)]
pub struct Subscriber<M: Message> {
    subscriber: IoxSubscriber<ipc::Service, M, ()>,
    listener: Listener<ipc::Service>,
    _node: Node<ipc::Service>,
    check: ReceiveCheck,
}

/// The subscriber side's check of each message taken from shared memory, without the transport:
/// the layout version, then the continuity of `(run_id, sequence)` and the counters.
/// [`Subscriber::try_recv`] runs every message through it; it is public so that the check can
/// be tested (and fuzzed) on arbitrary bytes shaped as a message.
#[derive(Clone, Copy, Debug, Default)]
pub struct ReceiveCheck {
    tracker: ContinuityTracker,
    counters: SubscriberCounters,
}

impl ReceiveCheck {
    /// Checks `sample`, as [`Subscriber::try_recv`] does: a message of another layout version
    /// is refused ([`RecvError::VersionMismatch`], counted as rejected, continuity unchanged),
    /// and so is one that breaks its own invariants ([`Message::check`]:
    /// [`RecvError::Invalid`]); any other is returned with its [`Continuity`] and counted. Counters saturate.
    pub fn check<M: Message>(&mut self, sample: M) -> Result<Received<M>, RecvError> {
        if sample.version() != M::VERSION {
            self.counters.rejected = self.counters.rejected.saturating_add(1);
            return Err(RecvError::VersionMismatch {
                type_name: M::TYPE_NAME,
                found: sample.version(),
                expected: M::VERSION,
            });
        }
        if let Err(broken) = sample.check() {
            self.counters.rejected = self.counters.rejected.saturating_add(1);
            return Err(RecvError::Invalid { type_name: M::TYPE_NAME, broken });
        }
        let event = self.tracker.observe(sample.run_id(), sample.sequence());
        self.counters.received = self.counters.received.saturating_add(1);
        match event {
            Continuity::Gap { missed } => self.counters.missed = self.counters.missed.saturating_add(missed),
            Continuity::Restart => self.counters.restarts = self.counters.restarts.saturating_add(1),
            Continuity::First | Continuity::InOrder => {}
        }
        Ok(Received { sample, event })
    }

    /// What this check has seen so far.
    pub fn counters(&self) -> SubscriberCounters {
        self.counters
    }
}

/// A client of fulcrumd's output: [`FulcrumSample`]s, once per control cycle.
///
/// ```no_run
/// use std::time::Duration;
/// use hw_io::ipc::{Continuity, FulcrumSubscriber};
///
/// # fn main() -> Result<(), Box<dyn core::error::Error>> {
/// let mut sub = FulcrumSubscriber::connect("comanip/fulcrum")?;
/// loop {
///     match sub.wait(Duration::from_millis(10))? {
///         Some(r) if r.event == Continuity::Restart => println!("fulcrumd restarted"),
///         Some(r) => if let Some(f) = r.sample.fulcrum() { println!("fulcrum {f:?} m (base frame)") },
///         None => println!("no sample for 10 ms: fulcrumd is not running"),
///     }
/// }
/// # }
/// ```
pub type FulcrumSubscriber = Subscriber<FulcrumSample>;

impl<M: Message> Subscriber<M> {
    /// Connects to the output `service_name` of messages `M` with the default
    /// [`PublisherOptions`]; creates the services when the publisher has not started yet. The
    /// iceoryx2 node is named [`Message::SUBSCRIBER_NODE_NAME`].
    pub fn connect(service_name: &str) -> Result<Self, ConnectError> {
        Self::connect_with(service_name, &PublisherOptions::default())
    }

    /// As [`connect`](Self::connect), for a publisher started with other options (pass the same
    /// capacities; `iceoryx2_signal_handlers` is ignored: a subscriber never installs signal
    /// handlers).
    pub fn connect_with(service_name: &str, opts: &PublisherOptions) -> Result<Self, ConnectError> {
        // A subscriber never installs signal handlers.
        let Services { node, pubsub, event } =
            service::open_services::<M>(service_name, opts, M::SUBSCRIBER_NODE_NAME, false)?;
        let subscriber = pubsub
            .subscriber_builder()
            .buffer_size(opts.subscriber_buffer)
            .create()
            .map_err(ConnectError::Subscriber)?;
        let listener = event.listener_builder().create().map_err(ConnectError::Listener)?;
        Ok(Self { subscriber, listener, _node: node, check: ReceiveCheck::default() })
    }

    /// The next message if one is buffered, else `None` at once.
    pub fn try_recv(&mut self) -> Result<Option<Received<M>>, RecvError> {
        let Some(loaned) = self.subscriber.receive().map_err(RecvError::Receive)? else {
            return Ok(None);
        };
        let sample = *loaned.payload();
        drop(loaned); // give the slot back to the publisher at once
        self.check.check(sample).map(Some)
    }

    /// The next message, blocking (on the event listener: the thread sleeps) for at most
    /// `timeout`; `None` when none arrived in time. Returns at once when one is buffered.
    pub fn wait(&mut self, timeout: Duration) -> Result<Option<Received<M>>, WaitError> {
        let start = Instant::now();
        loop {
            if let Some(received) = self.try_recv()? {
                return Ok(Some(received));
            }
            let remaining = timeout.saturating_sub(start.elapsed());
            if remaining.is_zero() {
                return Ok(None);
            }
            match self.listener.timed_wait(|_| {}, remaining.min(MAX_SLEEP)) {
                Ok(_) | Err(ListenerWaitError::InterruptSignal) => {}
                Err(e) => return Err(WaitError::Listener(e)),
            }
        }
    }

    /// What this subscriber has seen since it connected.
    pub fn counters(&self) -> SubscriberCounters {
        self.check.counters()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ipc::{HealthFlags, OutputState};

    fn sample(state: OutputState, sequence: u64) -> FulcrumSample {
        let mut s = FulcrumSample::invalid(HealthFlags::empty());
        s.state = state.into();
        s.sequence = sequence;
        s.run_id = 7;
        s
    }

    #[test]
    fn a_valid_sample_with_a_nan_or_an_invalidating_flag_is_refused_and_counted() {
        let mut check = ReceiveCheck::default();
        let mut nan = sample(OutputState::Inside, 0);
        nan.fulcrum_base_m[1] = f64::NAN;
        assert!(matches!(check.check(nan), Err(RecvError::Invalid { .. })));
        let mut flagged = sample(OutputState::Outside, 1);
        flagged.health = HealthFlags::NODE2_STALE.bits();
        assert!(matches!(check.check(flagged), Err(RecvError::Invalid { .. })));
        // An invalid sample's floats mean nothing: accepted as it is.
        let mut invalid = sample(OutputState::Invalid, 2);
        invalid.wrist_base_m[0] = f64::INFINITY;
        assert!(check.check(invalid).is_ok());
        // The refused ones did not touch continuity: the accepted one is the first.
        assert_eq!(check.counters(), SubscriberCounters { received: 1, missed: 0, restarts: 0, rejected: 2 });
        assert_eq!(check.check(sample(OutputState::Outside, 3)).map(|r| r.event).ok(), Some(Continuity::InOrder));
    }

    #[test]
    fn the_missed_counter_saturates() {
        // Found while writing the `ipc_sample` fuzz target: two huge gaps overflowed `missed`.
        let mut check = ReceiveCheck::default();
        for (run, seq) in [(7, 0), (7, 1 << 63), (8, 0), (8, (1 << 63) + 5)] {
            let mut s = sample(OutputState::Outside, seq);
            s.run_id = run;
            assert!(check.check(s).is_ok());
        }
        assert_eq!(check.counters().missed, u64::MAX);
    }
}
