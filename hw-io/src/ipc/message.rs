//! What makes a type a shared-memory message: the [`Message`] trait.
//!
//! A message is a `#[repr(C)]`, fixed-size, pointer-free struct, written once into shared memory
//! and read in place by every subscriber, in any language that can declare the same C struct.
//! Every message carries three fields that the transport itself reads:
//!
//! - its **layout version** ([`Message::VERSION`]; a subscriber refuses any other version with
//!   [`RecvError::VersionMismatch`](super::RecvError::VersionMismatch));
//! - a **sequence** number, +1 per message of one publisher run;
//! - a **run id**, random per publisher start.
//!
//! From the last two the subscriber computes each message's [`Continuity`](super::Continuity)
//! (in order, gap, restart). [`FulcrumSample`](super::FulcrumSample) is the first message;
//! frames, the tracked tool pose and calibration results are meant to follow, each with its own
//! type name, version and service.

use core::fmt::Debug;

use iceoryx2::prelude::ZeroCopySend;

/// A versioned `#[repr(C)]` message that [`Publisher`](super::Publisher) and
/// [`Subscriber`](super::Subscriber) carry.
///
/// Implement it next to `#[derive(ZeroCopySend)]` and `#[type_name("...")]` (iceoryx2 matches
/// services by that name, the size and the alignment):
///
/// ```
/// use hw_io::ipc::{Message, ZeroCopySend};
///
/// /// A tool pose, metres and unit quaternion, robot base frame.
/// #[derive(Clone, Copy, Debug, ZeroCopySend)]
/// #[type_name("example::ToolPose")]
/// #[repr(C)]
/// struct ToolPose {
///     version: u32,
///     reserved: u32,
///     sequence: u64,
///     run_id: u64,
///     position_base_m: [f64; 3],
///     orientation_base: [f64; 4],
/// }
///
/// impl Message for ToolPose {
///     const TYPE_NAME: &'static str = "example::ToolPose";
///     const VERSION: u32 = 1;
///     fn version(&self) -> u32 { self.version }
///     fn sequence(&self) -> u64 { self.sequence }
///     fn run_id(&self) -> u64 { self.run_id }
/// }
/// # assert_eq!(ToolPose::VERSION, 1);
/// ```
///
/// Bump `VERSION` on any change of a field, its order, its units or its meaning; change the type
/// name (and so the service's type) when the size or alignment changes too.
pub trait Message: ZeroCopySend + Copy + Debug + 'static {
    /// The iceoryx2 type name, the same string as the type's `#[type_name("...")]` (checked by
    /// the tests of each message). Shown in errors.
    const TYPE_NAME: &'static str;
    /// The layout version this program reads and writes.
    const VERSION: u32;
    /// Name of the iceoryx2 node a [`Publisher`](super::Publisher) of this message creates (it
    /// shows in iceoryx2's tools). At most 64 characters.
    const PUBLISHER_NODE_NAME: &'static str = "comanip-publisher";
    /// Name of the iceoryx2 node a [`Subscriber`](super::Subscriber) of this message creates.
    const SUBSCRIBER_NODE_NAME: &'static str = "comanip-subscriber";

    /// The message's layout version field.
    fn version(&self) -> u32;
    /// The message's sequence number: 0 for the first message of a publisher run, +1 per
    /// message.
    fn sequence(&self) -> u64;
    /// The identifier of the publisher run that wrote the message (random per start).
    fn run_id(&self) -> u64;

    /// The message's own invariants, checked by the subscriber after the version
    /// ([`RecvError::Invalid`](super::RecvError::Invalid) when broken): what any publisher of
    /// this program guarantees, so that a corrupt or foreign writer cannot hand a subscriber,
    /// say, a NaN marked valid. The default accepts every message.
    fn check(&self) -> Result<(), InvalidMessage> {
        Ok(())
    }
}

/// A broken invariant of a received message ([`Message::check`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{what}")]
pub struct InvalidMessage {
    /// Which invariant, in words.
    pub what: &'static str,
}
