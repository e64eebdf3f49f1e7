//! The daemon's side: one publisher per output, generic over the [`Message`] it carries.

use std::time::Duration;

use iceoryx2::node::{Node, NodeWaitFailure};
use iceoryx2::port::notifier::{Notifier, NotifierCreateError, NotifierNotifyError};
use iceoryx2::port::publisher::{Publisher as IoxPublisher, PublisherCreateError};
use iceoryx2::port::{LoanError, SendError};
use iceoryx2::prelude::{BackpressureStrategy, ipc};

use super::service::{self, OpenError, PublisherOptions, Services};
use super::{FulcrumSample, Message};

/// Why [`Publisher::create`] failed.
#[derive(Debug, thiserror::Error)]
pub enum CreateError {
    /// The options, the name, the node or the services (shared with the subscriber side).
    #[error(transparent)]
    Open(#[from] OpenError),
    /// The publisher port could not be created; `ExceedsMaxSupportedPublishers` means another
    /// live publisher (a second daemon) owns this output.
    #[error("cannot create the publisher: {0}")]
    Publisher(#[source] PublisherCreateError),
    /// The notifier port could not be created (another live daemon owns this output).
    #[error("cannot create the notifier: {0}")]
    Notifier(#[source] NotifierCreateError),
}

/// Why [`Publisher::publish`] failed. The message was not delivered (`Loan`, `Send`) or
/// delivered without waking blocking subscribers (`Notify`; they still get it within their
/// wait's re-check interval).
#[derive(Debug, thiserror::Error)]
pub enum PublishError {
    /// No free slot in the shared-memory data segment.
    #[error("cannot loan a shared-memory slot: {0}")]
    Loan(#[source] LoanError),
    /// Delivery to the subscribers failed.
    #[error("cannot send the message: {0}")]
    Send(#[source] SendError),
    /// The wake-up notification failed.
    #[error("cannot notify the subscribers: {0}")]
    Notify(#[source] NotifierNotifyError),
}

/// Publishes messages `M` on an output and wakes its blocking subscribers.
///
/// Created once at start-up on the thread that will publish (the iceoryx2 ports are
/// single-threaded: a `Publisher` is neither `Send` nor `Sync`). fulcrumd's is a
/// [`FulcrumPublisher`].
///
/// ```no_run
/// use hw_io::ipc::{FulcrumSample, HealthFlags, OutputState, Publisher, PublisherOptions};
///
/// # fn main() -> Result<(), Box<dyn core::error::Error>> {
/// let mut publisher = Publisher::<FulcrumSample>::create("comanip/fulcrum", &PublisherOptions::default())?;
/// let run_id = 0x5eed; // random per start in a real daemon
/// for sequence in 0..1000 {
///     let mut sample = FulcrumSample::invalid(HealthFlags::empty());
///     sample.state = OutputState::Outside.into();
///     sample.sequence = sequence;
///     sample.run_id = run_id;
///     publisher.publish(&sample)?;
/// }
/// assert_eq!(publisher.published(), 1000);
/// # Ok(()) }
/// ```
///
/// ## Real-time use
/// [`publish`](Self::publish) copies the message (200 bytes for a [`FulcrumSample`]) into shared
/// memory, sends it and notifies: no lock, no blocking (a full subscriber buffer overwrites its
/// oldest message), and no heap allocation except iceoryx2's one 48-byte `Rc` per message,
/// which [`crate::rt_alloc`] serves from a static pool on a thread that called
/// [`crate::rt_alloc::enter_realtime`]. When a subscriber connects or goes away, the next
/// `publish` also updates the connections (opening or closing shared memory: system calls and
/// allocations, once per connect or disconnect).
#[derive(Debug)]
pub struct Publisher<M: Message> {
    publisher: IoxPublisher<ipc::Service, M, ()>,
    notifier: Notifier<ipc::Service>,
    node: Node<ipc::Service>,
    signal_handlers: bool,
    published: u64,
}

/// fulcrumd's publisher: [`FulcrumSample`]s, once per control cycle.
pub type FulcrumPublisher = Publisher<FulcrumSample>;

impl<M: Message> Publisher<M> {
    /// Opens (or creates) the output `service_name` for messages `M` and its publisher; the
    /// iceoryx2 node is named [`Message::PUBLISHER_NODE_NAME`].
    ///
    /// Creating the node also removes the iceoryx2 resources of dead processes, so a daemon
    /// restarted after a crash or SIGKILL takes over its output while subscribers keep running.
    pub fn create(service_name: &str, opts: &PublisherOptions) -> Result<Self, CreateError> {
        let Services { node, pubsub, event } =
            service::open_services::<M>(service_name, opts, M::PUBLISHER_NODE_NAME, opts.iceoryx2_signal_handlers)?;
        let publisher = pubsub
            .publisher_builder()
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()
            .map_err(CreateError::Publisher)?;
        let notifier = event.notifier_builder().create().map_err(CreateError::Notifier)?;
        let this = Self { publisher, notifier, node, signal_handlers: opts.iceoryx2_signal_handlers, published: 0 };
        if opts.iceoryx2_signal_handlers {
            // iceoryx2 registers its handlers on the first termination check.
            let _ = this.termination_requested();
        }
        Ok(this)
    }

    /// Publishes one message: loan a shared-memory slot, copy `message` into it verbatim (the
    /// caller sets every field, version, sequence and run id included), send it to every
    /// connected subscriber, then notify the event service so that blocking subscribers wake
    /// up.
    pub fn publish(&mut self, message: &M) -> Result<(), PublishError> {
        let slot = self.publisher.loan_uninit().map_err(PublishError::Loan)?;
        slot.write_payload(*message).send().map_err(PublishError::Send)?;
        self.published += 1;
        self.notifier.notify().map_err(PublishError::Notify)?;
        Ok(())
    }

    /// Messages sent since creation.
    pub fn published(&self) -> u64 {
        self.published
    }

    /// True when iceoryx2's signal handlers (option
    /// [`PublisherOptions::iceoryx2_signal_handlers`]) caught a SIGINT or SIGTERM since the last
    /// call. Always false when that option is off. Not for the real-time loop (a system call).
    pub fn termination_requested(&self) -> bool {
        // With the handlers on, iceoryx2 reports a caught SIGINT or SIGTERM as `TerminationRequest`
        // (`Interrupt` only means that the zero-length sleep was interrupted).
        self.signal_handlers && matches!(self.node.wait(Duration::ZERO), Err(NodeWaitFailure::TerminationRequest))
    }
}
