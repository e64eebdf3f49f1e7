//! Collects the three TPDOs that answer one SYNC into the six joint readings.
//!
//! ```
//! use hw_io::can::{EncoderConfig, JointAssembler, Message, NodeId};
//! let mut asm = JointAssembler::from_config(&EncoderConfig::default()).unwrap();
//! asm.start_cycle(); // right after sending SYNC
//! let n = |k| NodeId::new(k).unwrap();
//! asm.accept(&Message::Tpdo { node: n(1), counts: [10, 20] }).unwrap();
//! asm.accept(&Message::Tpdo { node: n(3), counts: [50, 60] }).unwrap();
//! let missing = asm.counts().unwrap_err().missing;
//! assert_eq!(missing.iter().map(NodeId::get).collect::<Vec<_>>(), [2]);
//! asm.accept(&Message::Tpdo { node: n(2), counts: [30, 40] }).unwrap();
//! assert_eq!(asm.counts(), Ok([10, 20, 30, 40, 50, 60]));
//! ```

use super::encoder::{ConfigError, ENCODER_NODES, EncoderConfig, JOINTS, JOINTS_PER_NODE};
use super::protocol::{Message, NodeId};

/// A set of encoder nodes (a subset of the assembler's three), `Copy`, no heap.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MissingNodes {
    nodes: [NodeId; ENCODER_NODES],
    mask: u8,
}

impl MissingNodes {
    /// Number of nodes in the set, 0..=3.
    pub fn len(&self) -> usize {
        self.mask.count_ones() as usize
    }

    /// `true` if no node is missing.
    pub fn is_empty(&self) -> bool {
        self.mask == 0
    }

    /// `true` if `node` is in the set.
    pub fn contains(&self, node: NodeId) -> bool {
        self.iter().any(|n| n == node)
    }

    /// The nodes in the set, in joint order.
    pub fn iter(&self) -> impl Iterator<Item = NodeId> + '_ {
        self.nodes.iter().enumerate().filter(|(i, _)| self.mask & (1 << i) != 0).map(|(_, n)| *n)
    }
}

impl core::fmt::Display for MissingNodes {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        for (i, n) in self.iter().enumerate() {
            if i > 0 {
                write!(f, ", ")?;
            }
            write!(f, "{n}")?;
        }
        Ok(())
    }
}

/// Why a message was not taken into the current cycle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum AcceptError {
    /// A TPDO from a node that carries none of our joints.
    #[error("TPDO from node {node}, which is not an encoder node of this arm")]
    UnknownNode {
        /// The sending node.
        node: NodeId,
    },
    /// A second TPDO from the same node in one cycle; the newer counts replace the older.
    #[error("second TPDO from node {node} in one SYNC cycle")]
    Duplicate {
        /// The sending node.
        node: NodeId,
    },
    /// Not a TPDO (SYNC, heartbeat or EMCY): nothing to assemble.
    #[error("not a TPDO")]
    NotTpdo,
}

/// Not every node answered in this cycle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("no TPDO this cycle from node(s) {missing}")]
pub struct IncompleteCycle {
    /// The nodes that have not answered.
    pub missing: MissingNodes,
}

/// Assembles one SYNC cycle's TPDOs into six joint readings, encoder counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct JointAssembler {
    nodes: [NodeId; ENCODER_NODES],
    counts: [i32; JOINTS],
    received: u8,
}

impl JointAssembler {
    /// An assembler for the nodes carrying joints 1-2, 3-4 and 5-6 (distinct).
    pub fn new(nodes: [NodeId; ENCODER_NODES]) -> Result<Self, ConfigError> {
        EncoderConfig { node_ids: nodes.map(NodeId::get), ..Default::default() }.nodes()?;
        Ok(Self { nodes, counts: [0; JOINTS], received: 0 })
    }

    /// An assembler for the node IDs of a config.
    pub fn from_config(config: &EncoderConfig) -> Result<Self, ConfigError> {
        Self::new(config.nodes()?)
    }

    /// The nodes carrying joints 1-2, 3-4 and 5-6.
    pub fn nodes(&self) -> [NodeId; ENCODER_NODES] {
        self.nodes
    }

    /// Forget the previous cycle; call right after sending (or seeing) a SYNC.
    ///
    /// **Real-time (1 kHz loop):** called once a cycle; allocation-free.
    pub fn start_cycle(&mut self) {
        self.received = 0;
    }

    /// Take one node's two joint readings, counts, into the current cycle.
    ///
    /// **Real-time (1 kHz loop):** called for every TPDO; allocation-free.
    pub fn accept_tpdo(&mut self, node: NodeId, counts: [i32; 2]) -> Result<(), AcceptError> {
        let slot = self.nodes.iter().position(|&n| n == node).ok_or(AcceptError::UnknownNode { node })?;
        let first = slot * JOINTS_PER_NODE;
        self.counts[first..first + JOINTS_PER_NODE].copy_from_slice(&counts);
        let bit = 1u8 << slot;
        let duplicate = self.received & bit != 0;
        self.received |= bit;
        if duplicate { Err(AcceptError::Duplicate { node }) } else { Ok(()) }
    }

    /// Take a decoded message into the current cycle (TPDOs only).
    ///
    /// **Real-time (1 kHz loop):** called for every decoded message; allocation-free.
    pub fn accept(&mut self, msg: &Message) -> Result<(), AcceptError> {
        match *msg {
            Message::Tpdo { node, counts } => self.accept_tpdo(node, counts),
            _ => Err(AcceptError::NotTpdo),
        }
    }

    /// `true` once every node has answered in this cycle.
    ///
    /// **Real-time (1 kHz loop):** allocation-free.
    pub fn is_complete(&self) -> bool {
        self.missing().is_empty()
    }

    /// The nodes that have not answered in this cycle.
    ///
    /// **Real-time (1 kHz loop):** allocation-free.
    pub fn missing(&self) -> MissingNodes {
        let all = (1u8 << ENCODER_NODES) - 1;
        MissingNodes { nodes: self.nodes, mask: all & !self.received }
    }

    /// The six joint readings, counts, if every node answered in this cycle.
    ///
    /// **Real-time (1 kHz loop):** allocation-free.
    pub fn counts(&self) -> Result<[i32; JOINTS], IncompleteCycle> {
        let missing = self.missing();
        if missing.is_empty() { Ok(self.counts) } else { Err(IncompleteCycle { missing }) }
    }

    /// The six joint readings, counts, as far as they arrived: a joint whose node has not
    /// answered in this cycle keeps its last value from an earlier cycle (0 before any).
    ///
    /// **Real-time (1 kHz loop):** called at every cycle end; allocation-free.
    pub fn counts_partial(&self) -> ([i32; JOINTS], MissingNodes) {
        (self.counts, self.missing())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn n(k: u8) -> NodeId {
        NodeId::new(k).unwrap()
    }

    #[test]
    fn maps_nodes_to_joint_pairs_in_config_order() {
        let mut a = JointAssembler::new([n(7), n(5), n(6)]).unwrap();
        a.start_cycle();
        a.accept_tpdo(n(6), [5, 6]).unwrap();
        a.accept_tpdo(n(7), [1, 2]).unwrap();
        assert!(!a.is_complete());
        assert_eq!(a.missing().iter().collect::<Vec<_>>(), [n(5)]);
        assert_eq!(a.counts().unwrap_err().to_string(), "no TPDO this cycle from node(s) 5");
        a.accept_tpdo(n(5), [3, 4]).unwrap();
        assert_eq!(a.counts(), Ok([1, 2, 3, 4, 5, 6]));
    }

    #[test]
    fn reports_unknown_duplicate_and_non_tpdo() {
        let mut a = JointAssembler::from_config(&EncoderConfig::default()).unwrap();
        a.start_cycle();
        assert_eq!(a.accept_tpdo(n(4), [0, 0]), Err(AcceptError::UnknownNode { node: n(4) }));
        a.accept_tpdo(n(1), [1, 1]).unwrap();
        assert_eq!(a.accept_tpdo(n(1), [2, 2]), Err(AcceptError::Duplicate { node: n(1) }));
        assert_eq!(a.counts_partial().0[..2], [2, 2]);
        assert_eq!(a.accept(&Message::Sync { counter: 1 }), Err(AcceptError::NotTpdo));
    }

    #[test]
    fn start_cycle_clears_what_was_received() {
        let mut a = JointAssembler::from_config(&EncoderConfig::default()).unwrap();
        for k in 1..=3 {
            a.accept_tpdo(n(k), [1, 1]).unwrap();
        }
        assert!(a.is_complete());
        a.start_cycle();
        assert_eq!(a.missing().len(), 3);
        assert_eq!(a.missing().to_string(), "1, 2, 3");
        assert!(a.missing().contains(n(2)));
    }

    #[test]
    fn refuses_duplicate_nodes() {
        assert_eq!(
            JointAssembler::new([n(1), n(2), n(1)]),
            Err(ConfigError::DuplicateNodeId { first: 0, second: 2, value: 1 })
        );
    }
}
