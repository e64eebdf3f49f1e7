//! The client side: what a guidance-force module links to read fulcrumd's output.

use std::time::{Duration, Instant};

use iceoryx2::node::Node;
use iceoryx2::port::ReceiveError;
use iceoryx2::port::listener::{Listener, ListenerCreateError, ListenerWaitError};
use iceoryx2::port::subscriber::{Subscriber, SubscriberCreateError};
use iceoryx2::prelude::ipc;

use super::service::{self, OpenError, PublisherOptions, Services};
use super::{FULCRUM_SAMPLE_VERSION, FulcrumSample};

/// Longest single sleep inside [`FulcrumSubscriber::wait`]: a safety net that re-checks the
/// buffer should a wake-up notification be lost (a daemon killed between its send and its
/// notify). Not a poll: an idle subscriber wakes 10 times a second.
const MAX_SLEEP: Duration = Duration::from_millis(100);

/// How a received sample follows the previous one (see `docs/output.md`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Continuity {
    /// The first sample this subscriber receives: nothing to compare with.
    First,
    /// Same daemon run, `sequence` is the previous one plus 1.
    InOrder,
    /// Same daemon run, `sequence` jumped forward: `missed` samples were lost (this subscriber's
    /// buffer overflowed because it read too slowly, or it was not reading).
    Gap {
        /// Samples between the previous one and this one that never arrived.
        missed: u64,
    },
    /// The daemon restarted: a new `run_id`, or the sequence went back within the same
    /// `run_id`. Not an error: estimates start afresh (the detector refills its window).
    Restart,
}

/// A sample and how it follows the previous one.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Received {
    /// The sample, copied out of shared memory; its `version` is [`FULCRUM_SAMPLE_VERSION`].
    pub sample: FulcrumSample,
    /// Its continuity with the previous accepted sample.
    pub event: Continuity,
}

/// What a subscriber has seen since it connected.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SubscriberCounters {
    /// Samples accepted (returned as [`Received`]).
    pub received: u64,
    /// Samples lost: the sum of every [`Continuity::Gap::missed`].
    pub missed: u64,
    /// Daemon restarts seen ([`Continuity::Restart`]).
    pub restarts: u64,
    /// Samples refused for another layout version ([`RecvError::VersionMismatch`]).
    pub rejected: u64,
}

/// Why [`FulcrumSubscriber::connect`] failed.
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

/// Why [`FulcrumSubscriber::try_recv`] failed.
#[derive(Debug, thiserror::Error)]
pub enum RecvError {
    /// iceoryx2 could not take a sample (a connection to the publisher is broken).
    #[error("cannot receive: {0}")]
    Receive(#[source] ReceiveError),
    /// A sample of another layout version arrived. It was dropped and counted
    /// ([`SubscriberCounters::rejected`]); continuity is unaffected and the next call goes on
    /// with the next sample. Persistent: the daemon and this program disagree on the layout.
    #[error("sample layout version {found}, this subscriber reads version {expected}")]
    VersionMismatch {
        /// The sample's `version`.
        found: u32,
        /// [`FULCRUM_SAMPLE_VERSION`].
        expected: u32,
    },
}

/// Why [`FulcrumSubscriber::wait`] failed.
#[derive(Debug, thiserror::Error)]
pub enum WaitError {
    /// Taking the sample failed (see [`RecvError`]; a version mismatch is not fatal).
    #[error(transparent)]
    Recv(#[from] RecvError),
    /// Waiting on the event listener failed.
    #[error("cannot wait for a notification: {0}")]
    Listener(#[source] ListenerWaitError),
}

/// Reads a fulcrum output.
///
/// ```no_run
/// use std::time::Duration;
/// use hw_io::ipc::{Continuity, FulcrumSubscriber};
///
/// let mut sub = FulcrumSubscriber::connect("comanip/fulcrum")?;
/// loop {
///     match sub.wait(Duration::from_millis(10))? {
///         Some(r) if r.event == Continuity::Restart => println!("fulcrumd restarted"),
///         Some(r) => if let Some(f) = r.sample.fulcrum() { println!("fulcrum {f:?} m (base frame)") },
///         None => println!("no sample for 10 ms: fulcrumd is not running"),
///     }
/// }
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
///
/// Works whether the daemon runs or not, survives its restarts (each one shows as one
/// [`Continuity::Restart`]), and never busy-polls. Single-threaded (neither `Send` nor `Sync`).
#[derive(Debug)]
pub struct FulcrumSubscriber {
    subscriber: Subscriber<ipc::Service, FulcrumSample, ()>,
    listener: Listener<ipc::Service>,
    _node: Node<ipc::Service>,
    tracker: ContinuityTracker,
    counters: SubscriberCounters,
}

impl FulcrumSubscriber {
    /// Connects to the fulcrum output `service_name` with the default [`PublisherOptions`];
    /// creates the services when the daemon has not started yet.
    pub fn connect(service_name: &str) -> Result<Self, ConnectError> {
        Self::connect_with(service_name, &PublisherOptions::default())
    }

    /// As [`connect`](Self::connect), for a daemon started with other options (pass the same
    /// capacities; `iceoryx2_signal_handlers` is ignored: a subscriber never installs signal
    /// handlers).
    pub fn connect_with(service_name: &str, opts: &PublisherOptions) -> Result<Self, ConnectError> {
        // A subscriber never installs signal handlers.
        let Services { node, pubsub, event } = service::open_services(service_name, opts, "fulcrum-subscriber", false)?;
        let subscriber = pubsub
            .subscriber_builder()
            .buffer_size(opts.subscriber_buffer)
            .create()
            .map_err(ConnectError::Subscriber)?;
        let listener = event.listener_builder().create().map_err(ConnectError::Listener)?;
        Ok(Self {
            subscriber,
            listener,
            _node: node,
            tracker: ContinuityTracker::default(),
            counters: SubscriberCounters::default(),
        })
    }

    /// The next sample if one is buffered, else `None` at once.
    pub fn try_recv(&mut self) -> Result<Option<Received>, RecvError> {
        let Some(loaned) = self.subscriber.receive().map_err(RecvError::Receive)? else {
            return Ok(None);
        };
        let sample = *loaned.payload();
        drop(loaned); // give the slot back to the publisher at once
        if sample.version != FULCRUM_SAMPLE_VERSION {
            self.counters.rejected += 1;
            return Err(RecvError::VersionMismatch { found: sample.version, expected: FULCRUM_SAMPLE_VERSION });
        }
        let event = self.tracker.observe(sample.run_id, sample.sequence);
        self.counters.received += 1;
        match event {
            Continuity::Gap { missed } => self.counters.missed += missed,
            Continuity::Restart => self.counters.restarts += 1,
            Continuity::First | Continuity::InOrder => {}
        }
        Ok(Some(Received { sample, event }))
    }

    /// The next sample, blocking (on the event listener: the thread sleeps) for at most
    /// `timeout`; `None` when none arrived in time. Returns at once when one is buffered.
    pub fn wait(&mut self, timeout: Duration) -> Result<Option<Received>, WaitError> {
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
        self.counters
    }
}

/// Continuity of `(run_id, sequence)` pairs.
#[derive(Clone, Copy, Debug, Default)]
struct ContinuityTracker {
    last: Option<(u64, u64)>,
}

impl ContinuityTracker {
    fn observe(&mut self, run_id: u64, sequence: u64) -> Continuity {
        let event = match self.last {
            None => Continuity::First,
            Some((last_run, _)) if last_run != run_id => Continuity::Restart,
            Some((_, last_seq)) if sequence <= last_seq => Continuity::Restart,
            Some((_, last_seq)) if sequence == last_seq + 1 => Continuity::InOrder,
            Some((_, last_seq)) => Continuity::Gap { missed: sequence - last_seq - 1 },
        };
        self.last = Some((run_id, sequence));
        event
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn continuity_of_run_and_sequence() {
        let mut t = ContinuityTracker::default();
        assert_eq!(t.observe(7, 100), Continuity::First);
        assert_eq!(t.observe(7, 101), Continuity::InOrder);
        assert_eq!(t.observe(7, 105), Continuity::Gap { missed: 3 });
        assert_eq!(t.observe(7, 106), Continuity::InOrder);
        // A new run, even with a larger sequence.
        assert_eq!(t.observe(8, 107), Continuity::Restart);
        // The sequence goes back (or repeats) within one run_id: a restart too.
        assert_eq!(t.observe(8, 3), Continuity::Restart);
        assert_eq!(t.observe(8, 3), Continuity::Restart);
        assert_eq!(t.observe(8, 4), Continuity::InOrder);
        assert_eq!(t.observe(8, u64::MAX), Continuity::Gap { missed: u64::MAX - 5 });
    }
}
