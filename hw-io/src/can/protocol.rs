//! The CANopen-style messages of the encoder bus and their codec (see `docs/can-protocol.md`).
//!
//! | message   | COB-ID        | DLC | payload                                          |
//! |-----------|---------------|-----|--------------------------------------------------|
//! | SYNC      | `0x080`       | 1   | counter 1..=240                                  |
//! | TPDO1     | `0x180 + k`   | 8   | two `i32` LE joint positions, encoder counts     |
//! | EMCY      | `0x080 + k`   | 8   | `u16` LE error code, `u8` error register, 5 vendor bytes |
//! | heartbeat | `0x700 + k`   | 1   | NMT state                                        |
//!
//! `k` is the node ID, 1..=127. Decoding is allocation-free and never panics: every frame
//! is either a [`Message`] or a [`DecodeError`].
//!
//! ```
//! use hw_io::can::{Message, NodeId};
//! let node = NodeId::new(2).unwrap();
//! let msg = Message::Tpdo { node, counts: [131_072, -5] };
//! let frame = msg.encode().unwrap();
//! assert_eq!(frame.data(), &[0x00, 0x00, 0x02, 0x00, 0xFB, 0xFF, 0xFF, 0xFF]);
//! assert_eq!(Message::decode(&frame), Ok(msg));
//! ```

use super::frame::{CanFrame, CanId};

/// COB-ID of SYNC (controller to all nodes).
pub const SYNC_COB_ID: u16 = 0x080;
/// COB-ID base of TPDO1: node `k` sends on `0x180 + k`.
pub const TPDO1_COB_ID_BASE: u16 = 0x180;
/// COB-ID base of EMCY: node `k` sends on `0x080 + k`.
pub const EMCY_COB_ID_BASE: u16 = 0x080;
/// COB-ID base of the heartbeat: node `k` sends on `0x700 + k`.
pub const HEARTBEAT_COB_ID_BASE: u16 = 0x700;
/// Largest SYNC counter value; the counter runs 1, 2, ..., 240, 1, ... (CiA 301).
pub const SYNC_COUNTER_MAX: u8 = 240;
/// DLC of SYNC, bytes.
pub const SYNC_DLC: u8 = 1;
/// DLC of TPDO1, bytes.
pub const TPDO_DLC: u8 = 8;
/// DLC of EMCY, bytes.
pub const EMCY_DLC: u8 = 8;
/// DLC of the heartbeat, bytes.
pub const HEARTBEAT_DLC: u8 = 1;

/// A CANopen node ID, 1..=127.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct NodeId(u8);

impl NodeId {
    /// Smallest node ID.
    pub const MIN: u8 = 1;
    /// Largest node ID.
    pub const MAX: u8 = 127;
    /// Node 1 (a placeholder for fixed-size arrays).
    pub(crate) const ONE: NodeId = NodeId(1);

    /// `Some` for 1..=127, else `None`.
    pub const fn new(id: u8) -> Option<Self> {
        if id >= Self::MIN && id <= Self::MAX { Some(Self(id)) } else { None }
    }

    /// The node ID as a number, 1..=127.
    pub const fn get(self) -> u8 {
        self.0
    }
}

impl core::fmt::Display for NodeId {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "{}", self.0)
    }
}

/// NMT state carried by a heartbeat (CiA 301).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum NmtState {
    /// `0x00`: boot-up message, sent once after reset.
    BootUp,
    /// `0x04`: stopped.
    Stopped,
    /// `0x05`: operational; TPDOs are being sent.
    Operational,
    /// `0x7F`: pre-operational; no TPDOs.
    PreOperational,
}

impl NmtState {
    /// The state byte on the bus.
    pub const fn to_byte(self) -> u8 {
        match self {
            NmtState::BootUp => 0x00,
            NmtState::Stopped => 0x04,
            NmtState::Operational => 0x05,
            NmtState::PreOperational => 0x7F,
        }
    }

    /// The state for a byte on the bus, `None` for any other value.
    pub const fn from_byte(b: u8) -> Option<Self> {
        match b {
            0x00 => Some(NmtState::BootUp),
            0x04 => Some(NmtState::Stopped),
            0x05 => Some(NmtState::Operational),
            0x7F => Some(NmtState::PreOperational),
            _ => None,
        }
    }
}

/// One decoded message of the encoder bus.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Message {
    /// SYNC from the controller, every 1 ms; `counter` is 1..=240.
    Sync {
        /// SYNC counter, 1..=240, wrapping from 240 to 1.
        counter: u8,
    },
    /// TPDO1 of an encoder node: the answer to one SYNC.
    Tpdo {
        /// Sending node.
        node: NodeId,
        /// Positions of the node's two joints, encoder counts (not wrapped).
        counts: [i32; 2],
    },
    /// Heartbeat of a node, every 100 ms.
    Heartbeat {
        /// Sending node.
        node: NodeId,
        /// The node's NMT state.
        state: NmtState,
    },
    /// Emergency message of a node; `code == 0` means "error reset / no error".
    Emcy {
        /// Sending node.
        node: NodeId,
        /// CiA 301 emergency error code; `0x0000` clears the fault.
        code: u16,
        /// CiA 301 error register (object 0x1001).
        register: u8,
        /// Manufacturer-specific bytes.
        vendor: [u8; 5],
    },
}

/// Why a [`Message`] could not be encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    /// A SYNC counter outside 1..=240.
    #[error("SYNC counter {counter} outside 1..=240")]
    SyncCounterOutOfRange {
        /// The counter given.
        counter: u8,
    },
}

/// Why a frame is not a valid message of the encoder bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// A 29-bit extended identifier: the protocol uses 11-bit identifiers only.
    #[error("extended identifier 0x{id:08X}: the encoder bus uses 11-bit identifiers only")]
    ExtendedId {
        /// The 29-bit identifier.
        id: u32,
    },
    /// A remote transmission request: the protocol uses no RTR frames.
    #[error("remote (RTR) frame on 0x{id:X}: the encoder bus uses no RTR frames")]
    RemoteFrame {
        /// The identifier (11 or 29 bits).
        id: u32,
    },
    /// An 11-bit identifier that is none of SYNC, TPDO1, EMCY or heartbeat of a node 1..=127.
    #[error("unknown COB-ID 0x{id:03X}")]
    UnknownId {
        /// The 11-bit identifier.
        id: u16,
    },
    /// The DLC does not match the message type.
    #[error("COB-ID 0x{id:03X}: DLC {got}, expected {expected}")]
    WrongDlc {
        /// The 11-bit identifier.
        id: u16,
        /// DLC the message type has, bytes.
        expected: u8,
        /// DLC received, bytes.
        got: u8,
    },
    /// A SYNC counter outside 1..=240.
    #[error("SYNC counter {counter} outside 1..=240")]
    SyncCounterOutOfRange {
        /// The counter received.
        counter: u8,
    },
    /// A heartbeat with a state byte that is no CiA 301 NMT state.
    #[error("node {node}: unknown NMT state 0x{state:02X} in heartbeat")]
    UnknownNmtState {
        /// Sending node.
        node: NodeId,
        /// The state byte received.
        state: u8,
    },
}

impl Message {
    /// The COB-ID (11-bit identifier) this message is sent on.
    ///
    /// **Real-time (1 kHz loop):** allocation-free.
    pub fn cob_id(&self) -> u16 {
        match *self {
            Message::Sync { .. } => SYNC_COB_ID,
            Message::Tpdo { node, .. } => TPDO1_COB_ID_BASE + u16::from(node.get()),
            Message::Heartbeat { node, .. } => HEARTBEAT_COB_ID_BASE + u16::from(node.get()),
            Message::Emcy { node, .. } => EMCY_COB_ID_BASE + u16::from(node.get()),
        }
    }

    /// The frame for this message. Allocation-free.
    ///
    /// **Real-time (1 kHz loop):** called for every frame sent (the SYNC); allocation-free.
    pub fn encode(&self) -> Result<CanFrame, EncodeError> {
        let mut data = [0u8; 8];
        let dlc = match *self {
            Message::Sync { counter } => {
                if !(1..=SYNC_COUNTER_MAX).contains(&counter) {
                    return Err(EncodeError::SyncCounterOutOfRange { counter });
                }
                data[0] = counter;
                SYNC_DLC
            }
            Message::Tpdo { counts, .. } => {
                data[..4].copy_from_slice(&counts[0].to_le_bytes());
                data[4..].copy_from_slice(&counts[1].to_le_bytes());
                TPDO_DLC
            }
            Message::Heartbeat { state, .. } => {
                data[0] = state.to_byte();
                HEARTBEAT_DLC
            }
            Message::Emcy { code, register, vendor, .. } => {
                data[..2].copy_from_slice(&code.to_le_bytes());
                data[2] = register;
                data[3..].copy_from_slice(&vendor);
                EMCY_DLC
            }
        };
        // COB-IDs here are at most 0x77F and DLCs at most 8: always a valid frame.
        Ok(CanFrame::standard_masked(self.cob_id(), dlc, data))
    }

    /// The message in a frame, or why it is none. Allocation-free; never panics.
    ///
    /// **Real-time (1 kHz loop):** called for every frame received; allocation-free, never
    /// panics.
    pub fn decode(frame: &CanFrame) -> Result<Self, DecodeError> {
        let id = match frame.id() {
            CanId::Extended(id) => {
                if frame.is_remote() {
                    return Err(DecodeError::RemoteFrame { id });
                }
                return Err(DecodeError::ExtendedId { id });
            }
            CanId::Standard(id) => id,
        };
        if frame.is_remote() {
            return Err(DecodeError::RemoteFrame { id: u32::from(id) });
        }
        let d = frame.data_padded();
        let expect_dlc = |expected: u8| {
            if frame.dlc() == expected { Ok(()) } else { Err(DecodeError::WrongDlc { id, expected, got: frame.dlc() }) }
        };
        // Function code = upper 4 bits of the 11-bit COB-ID; node = lower 7 bits.
        let function = id & 0x780;
        let node = NodeId::new((id & 0x7F) as u8);
        match (function, node) {
            (0x080, None) => {
                expect_dlc(SYNC_DLC)?;
                let counter = d[0];
                if !(1..=SYNC_COUNTER_MAX).contains(&counter) {
                    return Err(DecodeError::SyncCounterOutOfRange { counter });
                }
                Ok(Message::Sync { counter })
            }
            (0x080, Some(node)) => {
                expect_dlc(EMCY_DLC)?;
                Ok(Message::Emcy {
                    node,
                    code: u16::from_le_bytes([d[0], d[1]]),
                    register: d[2],
                    vendor: [d[3], d[4], d[5], d[6], d[7]],
                })
            }
            (0x180, Some(node)) => {
                expect_dlc(TPDO_DLC)?;
                Ok(Message::Tpdo {
                    node,
                    counts: [
                        i32::from_le_bytes([d[0], d[1], d[2], d[3]]),
                        i32::from_le_bytes([d[4], d[5], d[6], d[7]]),
                    ],
                })
            }
            (0x700, Some(node)) => {
                expect_dlc(HEARTBEAT_DLC)?;
                let state = NmtState::from_byte(d[0]).ok_or(DecodeError::UnknownNmtState { node, state: d[0] })?;
                Ok(Message::Heartbeat { node, state })
            }
            _ => Err(DecodeError::UnknownId { id }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn node(k: u8) -> NodeId {
        NodeId::new(k).unwrap()
    }

    #[test]
    fn node_ids_are_1_to_127() {
        assert_eq!(NodeId::new(0), None);
        assert_eq!(NodeId::new(128), None);
        assert_eq!(NodeId::new(1).map(NodeId::get), Some(1));
        assert_eq!(NodeId::new(127).map(NodeId::get), Some(127));
    }

    #[test]
    fn byte_layouts_match_the_spec() {
        let f = Message::Sync { counter: 240 }.encode().unwrap();
        assert_eq!((f.id(), f.data()), (CanId::Standard(0x080), &[240u8][..]));

        let f = Message::Tpdo { node: node(3), counts: [0x0403_0201, -2] }.encode().unwrap();
        assert_eq!(f.id(), CanId::Standard(0x183));
        assert_eq!(f.data(), &[1, 2, 3, 4, 0xFE, 0xFF, 0xFF, 0xFF]);

        let f = Message::Heartbeat { node: node(1), state: NmtState::Operational }.encode().unwrap();
        assert_eq!((f.id(), f.data()), (CanId::Standard(0x701), &[0x05u8][..]));
        let f = Message::Heartbeat { node: node(2), state: NmtState::PreOperational }.encode().unwrap();
        assert_eq!((f.id(), f.data()), (CanId::Standard(0x702), &[0x7Fu8][..]));

        let f =
            Message::Emcy { node: node(2), code: 0x7305, register: 0x81, vendor: [1, 2, 3, 4, 5] }.encode().unwrap();
        assert_eq!(f.id(), CanId::Standard(0x082));
        assert_eq!(f.data(), &[0x05, 0x73, 0x81, 1, 2, 3, 4, 5]);
    }

    #[test]
    fn every_message_round_trips() {
        let msgs = [
            Message::Sync { counter: 1 },
            Message::Sync { counter: 240 },
            Message::Tpdo { node: node(1), counts: [i32::MIN, i32::MAX] },
            Message::Tpdo { node: node(127), counts: [0, -1] },
            Message::Heartbeat { node: node(5), state: NmtState::BootUp },
            Message::Heartbeat { node: node(5), state: NmtState::Stopped },
            Message::Emcy { node: node(127), code: 0, register: 0, vendor: [0; 5] },
        ];
        for m in msgs {
            assert_eq!(Message::decode(&m.encode().unwrap()), Ok(m));
        }
    }

    #[test]
    fn sync_counter_range_is_enforced_both_ways() {
        assert_eq!(Message::Sync { counter: 0 }.encode(), Err(EncodeError::SyncCounterOutOfRange { counter: 0 }));
        assert_eq!(Message::Sync { counter: 241 }.encode(), Err(EncodeError::SyncCounterOutOfRange { counter: 241 }));
        for bad in [0u8, 241, 255] {
            let f = CanFrame::new_standard(0x080, &[bad]).unwrap();
            assert_eq!(Message::decode(&f), Err(DecodeError::SyncCounterOutOfRange { counter: bad }));
        }
    }

    #[test]
    fn wrong_dlc_is_reported_with_expected_and_got() {
        let cases = [(0x080u16, 0u8, 1u8), (0x080, 2, 1), (0x181, 7, 8), (0x701, 0, 1), (0x081, 1, 8)];
        for (id, got, expected) in cases {
            let f = CanFrame::new_standard(id, &[1u8; 8][..usize::from(got)]).unwrap();
            assert_eq!(Message::decode(&f), Err(DecodeError::WrongDlc { id, expected, got }));
        }
    }

    #[test]
    fn unknown_ids_are_reported() {
        // NMT (0x000), TIME (0x100), TPDO of node 0, RPDO1, SDO, heartbeat of node 0, LSS.
        for id in [0x000u16, 0x100, 0x180, 0x200, 0x281, 0x581, 0x601, 0x700, 0x7E5] {
            let f = CanFrame::new_standard(id, &[0; 8]).unwrap();
            assert_eq!(Message::decode(&f), Err(DecodeError::UnknownId { id }), "id {id:#x}");
        }
    }

    #[test]
    fn extended_and_remote_frames_are_refused() {
        let f = CanFrame::new_extended(0x181, &[0; 8]).unwrap();
        assert_eq!(Message::decode(&f), Err(DecodeError::ExtendedId { id: 0x181 }));
        let f = CanFrame::new_remote(CanId::Standard(0x181), 8).unwrap();
        assert_eq!(Message::decode(&f), Err(DecodeError::RemoteFrame { id: 0x181 }));
        let f = CanFrame::new_remote(CanId::Extended(0x1_0000), 0).unwrap();
        assert_eq!(Message::decode(&f), Err(DecodeError::RemoteFrame { id: 0x1_0000 }));
    }

    #[test]
    fn unknown_nmt_state_is_reported() {
        let f = CanFrame::new_standard(0x703, &[0x06]).unwrap();
        assert_eq!(Message::decode(&f), Err(DecodeError::UnknownNmtState { node: node(3), state: 0x06 }));
    }
}
