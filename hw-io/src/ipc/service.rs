//! The two iceoryx2 services behind one output, opened identically by both sides.
//!
//! An output named `N` is a publish-subscribe service `N` carrying one [`Message`] type (e.g.
//! [`FulcrumSample`](super::FulcrumSample)s) and an event service also named `N` (iceoryx2 keys
//! services by name *and* messaging pattern) whose notifications wake blocking subscribers. Both
//! sides call `open_or_create` with the same settings, derived from [`PublisherOptions`], so
//! whichever starts first creates them.

use iceoryx2::node::{Node, NodeCreationFailure};
use iceoryx2::prelude::{NodeBuilder, NodeName, ServiceName, SignalHandlingMode, ipc};
use iceoryx2::service::builder::event::EventOpenOrCreateError;
use iceoryx2::service::builder::publish_subscribe::PublishSubscribeOpenOrCreateError;
use iceoryx2::service::port_factory::{event, publish_subscribe};
use iceoryx2::service::service_name::ServiceNameError;

use super::Message;

/// Settings of an output (of any [`Message`]): the service's capacities and the publisher's signal handling.
///
/// The capacities are fixed when the service is created (by whichever side comes first) and
/// checked when it is opened: a subscriber must be given the same values as the daemon (the
/// defaults, unless the daemon's configuration says otherwise), else one of the two gets an
/// "incompatible" error.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PublisherOptions {
    /// Subscribers that can be connected at the same time (each holds a receive buffer in
    /// shared memory). Default 8. At least 1.
    pub max_subscribers: usize,
    /// Messages each subscriber's buffer holds; when it is full the oldest one is
    /// overwritten (the publisher never blocks) and the subscriber sees a
    /// [`Continuity::Gap`](super::Continuity::Gap). Default 64 (64 ms at 1 kHz). At least 1.
    pub subscriber_buffer: usize,
    /// Latest messages a newly connected subscriber receives at once. Default 0: a subscriber
    /// starts with the next message (the next cycle's sample). At most `subscriber_buffer`.
    pub history: usize,
    /// Install iceoryx2's own handlers for SIGINT, SIGTERM and other non-fatal signals when the
    /// publisher is created, and report a received SIGINT/SIGTERM through
    /// [`Publisher::termination_requested`](super::Publisher::termination_requested).
    /// Default `false`: fulcrumd handles signals itself, and with `false` iceoryx2 installs no
    /// signal handler at all. With `true`, SIGINT and SIGTERM no longer end the process: the
    /// owner must poll `termination_requested`.
    pub iceoryx2_signal_handlers: bool,
}

impl Default for PublisherOptions {
    fn default() -> Self {
        Self { max_subscribers: 8, subscriber_buffer: 64, history: 0, iceoryx2_signal_handlers: false }
    }
}

impl PublisherOptions {
    /// `Err(reason)` when a capacity is out of range (see the fields).
    pub(crate) fn check(&self) -> Result<(), &'static str> {
        if self.max_subscribers == 0 {
            return Err("max_subscribers must be at least 1");
        }
        if self.subscriber_buffer == 0 {
            return Err("subscriber_buffer must be at least 1");
        }
        if self.history > self.subscriber_buffer {
            return Err("history must not exceed subscriber_buffer");
        }
        Ok(())
    }

    /// Nodes that may open the services: every subscriber, the daemon, and one spare for a
    /// restarted daemon or subscriber whose dead predecessor has not been cleaned up yet.
    fn max_nodes(&self) -> usize {
        self.max_subscribers + 2
    }
}

/// The only publisher of an output: a second daemon on the same name is refused.
const MAX_PUBLISHERS: usize = 1;

pub(crate) type PubSubFactory<M> = publish_subscribe::PortFactory<ipc::Service, M, ()>;
pub(crate) type EventFactory = event::PortFactory<ipc::Service>;

/// Why an output's two services could not be opened (the part that
/// [`Publisher::create`](super::Publisher::create) and
/// [`Subscriber::connect`](super::Subscriber::connect) share).
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// The options are out of range (the message says which).
    #[error("invalid options: {0}")]
    InvalidOptions(&'static str),
    /// The service name is empty, too long or has invalid characters.
    #[error("invalid service name {name:?}: {source}")]
    InvalidServiceName {
        /// The name given.
        name: String,
        /// iceoryx2's reason.
        source: ServiceNameError,
    },
    /// The iceoryx2 node could not be created (permissions on /tmp/iceoryx2 or /dev/shm).
    #[error("cannot create the iceoryx2 node: {0}")]
    Node(#[source] NodeCreationFailure),
    /// The publish-subscribe service could not be opened or created; `IncompatibleTypes` or an
    /// incompatible capacity means it exists with other settings: another layout version, or
    /// the other side started with other [`PublisherOptions`].
    #[error("cannot open or create the publish-subscribe service: {0}")]
    Service(#[source] PublishSubscribeOpenOrCreateError),
    /// The event service could not be opened or created.
    #[error("cannot open or create the event service: {0}")]
    EventService(#[source] EventOpenOrCreateError),
}

/// A node and the two services of one output, opened (or created) with `opts`.
pub(crate) struct Services<M: Message> {
    pub node: Node<ipc::Service>,
    pub pubsub: PubSubFactory<M>,
    pub event: EventFactory,
}

/// Checks `opts`, creates a node named `node_name` (a constant of the message type) with or
/// without signal handlers, and opens or creates the output `service_name`'s two services for
/// messages `M`.
pub(crate) fn open_services<M: Message>(
    service_name: &str,
    opts: &PublisherOptions,
    node_name: &'static str,
    signal_handlers: bool,
) -> Result<Services<M>, OpenError> {
    opts.check().map_err(OpenError::InvalidOptions)?;
    let name = ServiceName::new(service_name)
        .map_err(|source| OpenError::InvalidServiceName { name: service_name.to_owned(), source })?;
    let node = node(node_name, signal_handlers).map_err(OpenError::Node)?;
    let pubsub = open_pubsub(&node, &name, opts).map_err(OpenError::Service)?;
    let event = open_event(&node, &name, opts).map_err(OpenError::EventService)?;
    Ok(Services { node, pubsub, event })
}

/// A node with the given signal handling. `node_name` is a constant of a message type.
pub(crate) fn node(node_name: &'static str, signal_handlers: bool) -> Result<Node<ipc::Service>, NodeCreationFailure> {
    let mode =
        if signal_handlers { SignalHandlingMode::HandleTerminationRequests } else { SignalHandlingMode::Disabled };
    let mut builder = NodeBuilder::new().signal_handling_mode(mode);
    // Node names are constants of the message types; an invalid one just leaves the node unnamed.
    if let Ok(name) = NodeName::new(node_name) {
        builder = builder.name(&name);
    }
    builder.create::<ipc::Service>()
}

fn open_pubsub<M: Message>(
    node: &Node<ipc::Service>,
    name: &ServiceName,
    opts: &PublisherOptions,
) -> Result<PubSubFactory<M>, PublishSubscribeOpenOrCreateError> {
    node.service_builder(name)
        .publish_subscribe::<M>()
        .max_publishers(MAX_PUBLISHERS)
        .max_subscribers(opts.max_subscribers)
        .max_nodes(opts.max_nodes())
        .subscriber_max_buffer_size(opts.subscriber_buffer)
        .history_size(opts.history)
        .enable_safe_overflow(true)
        .open_or_create()
}

pub(crate) fn open_event(
    node: &Node<ipc::Service>,
    name: &ServiceName,
    opts: &PublisherOptions,
) -> Result<EventFactory, EventOpenOrCreateError> {
    node.service_builder(name)
        .event()
        .max_notifiers(MAX_PUBLISHERS)
        .max_listeners(opts.max_subscribers)
        .max_nodes(opts.max_nodes())
        .open_or_create()
}
