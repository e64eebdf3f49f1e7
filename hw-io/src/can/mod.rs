//! The encoder bus: frames, the CANopen-style protocol, and the bus backends.
//!
//! ## Layers
//! - [`CanFrame`] / [`TimedFrame`]: our own fixed-size classic-CAN frame (no heap), the
//!   only frame type the rest of comanip sees.
//! - Protocol ([`Message`], [`SyncSource`], [`SyncCounter`], [`JointAssembler`],
//!   [`EncoderConfig`], [`bus_load`]): SYNC every 1 ms, one TPDO1 per encoder node in
//!   answer, heartbeats, EMCY; encoder counts to radians. Pure, allocation-free, never
//!   panics on any frame. The byte layouts are in `docs/can-protocol.md`.
//! - Backends behind the one trait [`CanBus`]: [`SocketCanBus`] (Linux SocketCAN),
//!   [`InProcessBus`] (tests, simulator, demo), [`ReplayBus`] (candump logs). The
//!   [`candump`] module reads and writes can-utils log files.
//!
//! ## One cycle of the controller
//! ```
//! use std::time::Duration;
//! use hw_io::can::{CanBus, EncoderConfig, InProcessBus, JointAssembler, Message, NodeId, SyncSource};
//!
//! let config = EncoderConfig::default();
//! let bus = InProcessBus::new();
//! let mut controller = bus.endpoint().unwrap();
//! let mut nodes: Vec<_> = (0..3).map(|_| bus.endpoint().unwrap()).collect();
//! let mut sync = SyncSource::new();
//! let mut joints = JointAssembler::from_config(&config).unwrap();
//!
//! controller.send(&sync.next_frame()).unwrap();
//! joints.start_cycle();
//! for (k, node) in nodes.iter_mut().enumerate() {
//!     // A virtual encoder node answers the SYNC with its TPDO1.
//!     let _sync = node.recv_timeout(Duration::from_millis(1)).unwrap().unwrap();
//!     let id = NodeId::new(k as u8 + 1).unwrap();
//!     node.send(&Message::Tpdo { node: id, counts: [0, 32_768] }.encode().unwrap()).unwrap();
//! }
//! while !joints.is_complete() {
//!     let Some(rx) = controller.recv_timeout(Duration::from_millis(1)).unwrap() else { break };
//!     if let Ok(msg) = Message::decode(&rx.frame) {
//!         let _ = joints.accept(&msg);
//!     }
//! }
//! let q_rad = config.counts_to_rad(&joints.counts().unwrap());
//! assert!((q_rad[1] - std::f64::consts::FRAC_PI_2).abs() < 1e-12); // 2^15 of 2^17 counts
//! ```

mod assembler;
mod bus;
pub mod bus_load;
pub mod candump;
mod encoder;
mod frame;
mod in_process;
mod protocol;
mod replay;
pub mod rx_meta;
mod socketcan;
mod sync;

pub use assembler::{AcceptError, IncompleteCycle, JointAssembler, MissingNodes};
pub use bus::{CanBus, RecvError, SendError};
pub use encoder::{
    ConfigError, DEFAULT_COUNTS_PER_REV, DEFAULT_NODE_IDS, ENCODER_NODES, EncoderConfig, JOINTS, JOINTS_PER_NODE,
    JointEncoder, JointToCountsError, ToCountsError,
};
pub use frame::{
    CanFrame, CanId, FrameError, MAX_DLC, MAX_EXTENDED_ID, MAX_STANDARD_ID, TimedFrame, system_time_to_unix_us,
    unix_time_now_us,
};
pub use in_process::{DEFAULT_MAX_ENDPOINTS, DEFAULT_QUEUE_FRAMES, EndpointError, InProcessBus, InProcessEndpoint};
pub use protocol::{
    DecodeError, EMCY_COB_ID_BASE, EMCY_DLC, EncodeError, HEARTBEAT_COB_ID_BASE, HEARTBEAT_DLC, Message, NmtState,
    NodeId, SYNC_COB_ID, SYNC_COUNTER_MAX, SYNC_DLC, TPDO_DLC, TPDO1_COB_ID_BASE,
};
pub use replay::{Pacing, ReplayBus, ReplayOpenError};
pub use socketcan::{OpenError, SocketCanBus};
pub use sync::{CounterError, SyncCounter, SyncSource, next_sync_counter};
