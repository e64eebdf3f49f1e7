//! Data health of the encoder nodes: missing TPDOs, EMCY, heartbeats.
//!
//! A node's data are **invalid** while any of these holds (each raises its own flag of
//! [`hw_io::ipc::HealthFlags`]):
//! - its TPDO has been missing for `stale_after_cycles` consecutive cycles (`NODE_STALE`);
//! - it has sent an EMCY with a non-zero error code not yet cleared by an EMCY with error
//!   code `0x0000` (`NODE_EMCY`);
//! - no heartbeat for `heartbeat_timeout_ms`, or its last heartbeat reported a state other
//!   than operational (`NODE_HEARTBEAT`). A node that has never sent a heartbeat gets the
//!   same timeout counted from start-up.
//!
//! A single missing TPDO below the stale threshold makes only that cycle incomplete
//! (`INCOMPLETE_CYCLE`, the cycle's data are not used and the detector is frozen); a stale,
//! faulty or silent node makes the detector reset (see [`crate::cycle`]). Recovery is
//! automatic: the flag drops as soon as the condition ends.
//!
//! Times are nanoseconds of `CLOCK_MONOTONIC` (or any monotonic time base, consistently).

use hw_io::can::{ENCODER_NODES, Message, NmtState, NodeId};
use hw_io::ipc::HealthFlags as Flags;
use serde::{Deserialize, Serialize};

/// Health thresholds (the `[health]` table of the config).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HealthConfig {
    /// Consecutive cycles without a node's TPDO after which the node is stale (≥ 1).
    pub stale_after_cycles: u32,
    /// A node whose last heartbeat is older than this is flagged, milliseconds (≥ 1;
    /// the protocol's heartbeat period is 100 ms).
    pub heartbeat_timeout_ms: u32,
}

impl Default for HealthConfig {
    fn default() -> Self {
        Self { stale_after_cycles: 3, heartbeat_timeout_ms: 350 }
    }
}

/// Why a [`HealthConfig`] was refused; the message names the key.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum HealthConfigError {
    /// `health.stale_after_cycles` is 0.
    #[error("health.stale_after_cycles = 0: must be at least 1")]
    StaleAfterZero,
    /// `health.heartbeat_timeout_ms` is 0.
    #[error("health.heartbeat_timeout_ms = 0: must be at least 1")]
    HeartbeatTimeoutZero,
}

impl HealthConfig {
    /// Checks every key.
    pub fn validate(&self) -> Result<(), HealthConfigError> {
        if self.stale_after_cycles == 0 {
            return Err(HealthConfigError::StaleAfterZero);
        }
        if self.heartbeat_timeout_ms == 0 {
            return Err(HealthConfigError::HeartbeatTimeoutZero);
        }
        Ok(())
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct NodeHealth {
    missed_cycles: u32,
    emcy_code: u16,
    last_heartbeat_ns: Option<u64>,
    nmt: Option<NmtState>,
}

/// Tracks the three encoder nodes' health; allocation-free.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HealthMonitor {
    config: HealthConfig,
    nodes: [NodeId; ENCODER_NODES],
    state: [NodeHealth; ENCODER_NODES],
    started_ns: Option<u64>,
}

impl HealthMonitor {
    /// A monitor for the nodes carrying joints 1-2, 3-4, 5-6 (in that order).
    ///
    /// **Not for the real-time loop:** call it at start-up (the loop owns the monitor
    /// afterwards).
    pub fn new(config: HealthConfig, nodes: [NodeId; ENCODER_NODES]) -> Self {
        let fresh = NodeHealth { missed_cycles: 0, emcy_code: 0, last_heartbeat_ns: None, nmt: None };
        Self { config, nodes, state: [fresh; ENCODER_NODES], started_ns: None }
    }

    fn index(&self, node: NodeId) -> Option<usize> {
        self.nodes.iter().position(|&n| n == node)
    }

    /// Takes an EMCY or heartbeat into account (other messages are ignored), received at
    /// `now_ns`. Returns false when the message came from a node that is not ours.
    ///
    /// **Real-time (1 kHz loop):** called for every EMCY and heartbeat; allocation-free.
    pub fn on_message(&mut self, msg: &Message, now_ns: u64) -> bool {
        match *msg {
            Message::Emcy { node, code, .. } => match self.index(node) {
                Some(k) => {
                    self.state[k].emcy_code = code;
                    true
                }
                None => false,
            },
            Message::Heartbeat { node, state } => match self.index(node) {
                Some(k) => {
                    self.state[k].last_heartbeat_ns = Some(now_ns);
                    self.state[k].nmt = Some(state);
                    true
                }
                None => false,
            },
            Message::Tpdo { node, .. } => self.index(node).is_some(),
            Message::Sync { .. } => true,
        }
    }

    /// Closes a cycle at `now_ns`: `received_mask` has bit k set when node k (joint order)
    /// delivered its TPDO this cycle. Returns the node flags (stale, EMCY, heartbeat).
    ///
    /// **Real-time (1 kHz loop):** called at every cycle end; allocation-free.
    pub fn end_cycle(&mut self, received_mask: u8, now_ns: u64) -> Flags {
        let started = *self.started_ns.get_or_insert(now_ns);
        let timeout_ns = u64::from(self.config.heartbeat_timeout_ms) * 1_000_000;
        let mut out = Flags::empty();
        for k in 0..ENCODER_NODES {
            let st = &mut self.state[k];
            if received_mask & (1 << k) != 0 {
                st.missed_cycles = 0;
            } else {
                st.missed_cycles = st.missed_cycles.saturating_add(1);
            }
            if st.missed_cycles >= self.config.stale_after_cycles {
                out |= Flags::NODE_STALE[k];
            }
            if st.emcy_code != 0 {
                out |= Flags::NODE_EMCY[k];
            }
            let last = st.last_heartbeat_ns.unwrap_or(started);
            let silent = now_ns.saturating_sub(last) > timeout_ns;
            let not_operational = st.nmt.is_some_and(|s| s != NmtState::Operational);
            if silent || not_operational {
                out |= Flags::NODE_HEARTBEAT[k];
            }
        }
        out
    }

    /// The active EMCY error code of node `k` (0-based, joint order), 0 when none.
    ///
    /// **Real-time (1 kHz loop):** allocation-free.
    pub fn emcy_code(&self, k: usize) -> u16 {
        self.state.get(k).map_or(0, |s| s.emcy_code)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ids() -> [NodeId; 3] {
        [1, 2, 3].map(|k| NodeId::new(k).unwrap())
    }

    fn monitor() -> HealthMonitor {
        HealthMonitor::new(HealthConfig { stale_after_cycles: 3, heartbeat_timeout_ms: 250 }, ids())
    }

    fn heartbeats(m: &mut HealthMonitor, t: u64) {
        for n in ids() {
            m.on_message(&Message::Heartbeat { node: n, state: NmtState::Operational }, t);
        }
    }

    #[test]
    fn a_node_goes_stale_after_n_missed_cycles_and_recovers() {
        let mut m = monitor();
        heartbeats(&mut m, 0);
        assert_eq!(m.end_cycle(0b111, 0), Flags::empty());
        assert_eq!(m.end_cycle(0b101, 1_000_000), Flags::empty());
        assert_eq!(m.end_cycle(0b101, 2_000_000), Flags::empty());
        assert_eq!(m.end_cycle(0b101, 3_000_000), Flags::NODE_STALE[1]);
        assert_eq!(m.end_cycle(0b111, 4_000_000), Flags::empty());
    }

    #[test]
    fn emcy_sets_and_zero_code_clears() {
        let mut m = monitor();
        heartbeats(&mut m, 0);
        let n3 = ids()[2];
        m.on_message(&Message::Emcy { node: n3, code: 0x7300, register: 1, vendor: [0; 5] }, 0);
        assert_eq!(m.end_cycle(0b111, 0), Flags::NODE_EMCY[2]);
        assert_eq!(m.emcy_code(2), 0x7300);
        m.on_message(&Message::Emcy { node: n3, code: 0, register: 0, vendor: [0; 5] }, 0);
        assert_eq!(m.end_cycle(0b111, 0), Flags::empty());
    }

    #[test]
    fn heartbeat_timeout_and_non_operational_state_are_flagged() {
        let mut m = monitor();
        heartbeats(&mut m, 0);
        assert_eq!(m.end_cycle(0b111, 250_000_000), Flags::empty());
        // Nodes 1 and 3 keep beating, node 2 stops.
        for n in [ids()[0], ids()[2]] {
            m.on_message(&Message::Heartbeat { node: n, state: NmtState::Operational }, 200_000_000);
        }
        assert_eq!(m.end_cycle(0b111, 250_000_001), Flags::NODE_HEARTBEAT[1]);
        m.on_message(&Message::Heartbeat { node: ids()[1], state: NmtState::PreOperational }, 260_000_000);
        assert_eq!(m.end_cycle(0b111, 260_000_000), Flags::NODE_HEARTBEAT[1]);
        m.on_message(&Message::Heartbeat { node: ids()[1], state: NmtState::Operational }, 270_000_000);
        assert_eq!(m.end_cycle(0b111, 270_000_000), Flags::empty());
    }

    #[test]
    fn a_node_never_heard_is_flagged_after_the_timeout_from_start() {
        let mut m = monitor();
        assert_eq!(m.end_cycle(0b111, 1_000), Flags::empty());
        assert_eq!(
            m.end_cycle(0b111, 1_000 + 250_000_001),
            Flags::NODE_HEARTBEAT[0] | Flags::NODE_HEARTBEAT[1] | Flags::NODE_HEARTBEAT[2]
        );
    }

    #[test]
    fn foreign_nodes_are_reported_not_tracked() {
        let mut m = monitor();
        let n9 = NodeId::new(9).unwrap();
        assert!(!m.on_message(&Message::Emcy { node: n9, code: 1, register: 0, vendor: [0; 5] }, 0));
        heartbeats(&mut m, 0);
        assert_eq!(m.end_cycle(0b111, 0), Flags::empty());
    }

    #[test]
    fn config_validation_names_the_key() {
        let e = HealthConfig { stale_after_cycles: 0, ..Default::default() }.validate().unwrap_err();
        assert!(e.to_string().contains("health.stale_after_cycles"));
        let e = HealthConfig { heartbeat_timeout_ms: 0, ..Default::default() }.validate().unwrap_err();
        assert!(e.to_string().contains("health.heartbeat_timeout_ms"));
    }
}
