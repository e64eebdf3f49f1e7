//! Virtual encoder nodes: the three CANopen-style nodes that answer the controller's SYNC
//! with the joint positions (see `docs/can-protocol.md`).
//!
//! The core is pure and step-based, with no threads and no clock: the caller tells
//! [`VirtualNodes::on_sync`] that a SYNC went out at time `t_us` (microseconds, any time base,
//! e.g. since the start of the scenario) with the true measured joint angles at that instant
//! (radians, joints 1..6), and gets back the frames the nodes put on the bus in answer,
//! stamped with the time they are sent (`t_us` plus the node's latency, microseconds, same
//! time base):
//! - TPDO1 `0x180 + node` of every operational node (two little-endian `i32` joint counts,
//!   quantised with [`hw_io::can::JointEncoder::rad_to_counts`]): node `node_ids[0]` carries joints 1-2,
//!   `node_ids[1]` joints 3-4, `node_ids[2]` joints 5-6;
//! - heartbeats `0x700 + node` every `heartbeat_period_us` (100 ms by default), first at
//!   the first SYNC;
//! - EMCY `0x080 + node` when an injected fault starts, and a clearing EMCY (code 0) when it
//!   ends.
//!
//! Faults: random TPDO dropouts (probability per SYNC, deterministic from the seed),
//! scripted dropout windows, NMT state (only an operational node sends TPDOs).
//!
//! Frames of one SYNC are returned in the order they win the bus: by send time, then by
//! COB-ID (CAN arbitration).

use hw_io::can::{
    CanBus, ConfigError, ENCODER_NODES, EncoderConfig, JOINTS, JOINTS_PER_NODE, JointToCountsError, Message, NmtState,
    NodeId, SendError, TimedFrame,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Most frames [`VirtualNodes::on_sync`] returns for one SYNC. Per node: one TPDO, one
/// heartbeat and up to three EMCYs; further due EMCYs wait for the next SYNC.
pub const MAX_FRAMES_PER_SYNC: usize = 5 * ENCODER_NODES;

/// Most EMCY frames one node sends in answer to one SYNC.
const MAX_EMCY_PER_SYNC: usize = 3;

/// Default heartbeat period, microseconds (100 ms).
pub const DEFAULT_HEARTBEAT_PERIOD_US: u64 = 100_000;

/// Default answer latency of a node after the SYNC, microseconds.
pub const DEFAULT_LATENCY_US: u64 = 100;

/// The frames of one SYNC cycle, in bus order; timestamps in microseconds (the caller's
/// time base).
pub type SyncFrames = heapless::Vec<TimedFrame, MAX_FRAMES_PER_SYNC>;

/// An injected fault of one node: an EMCY with `code` at `at_us`, and a clearing EMCY
/// (code 0, register 0) at `at_us + duration_us`. Times in microseconds, the time base of
/// [`VirtualNodes::on_sync`]; each EMCY goes out at the first SYNC at or after its time.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EmcyInjection {
    /// Start of the fault, microseconds.
    pub at_us: u64,
    /// Duration of the fault, microseconds.
    pub duration_us: u64,
    /// CiA 301 emergency error code (non-zero; e.g. `0x7305` incremental sensor fault).
    pub code: u16,
    /// CiA 301 error register (object 0x1001); 0 when absent from a configuration file.
    #[serde(default)]
    pub register: u8,
    /// Manufacturer-specific bytes; zeros when absent from a configuration file.
    #[serde(default)]
    pub vendor: [u8; 5],
}

/// Behaviour of one virtual node; also its form in `simrobot`'s configuration file
/// (`[[nodes]]`, every key optional, defaults from [`NodeOptions::default`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NodeOptions {
    /// Delay from the SYNC to the node's frames, microseconds (may exceed the 1 ms SYNC
    /// period: the frame then arrives after the next SYNC).
    pub latency_us: u64,
    /// Probability (0..=1) that the node's TPDO is lost at a given SYNC.
    pub dropout_probability: f64,
    /// Scripted dropouts: no TPDO for a SYNC at `t_us` with `start <= t_us < end`
    /// (microseconds).
    pub dropout_windows_us: Vec<[u64; 2]>,
    /// Injected faults (EMCY and its clearing EMCY).
    pub emcy: Vec<EmcyInjection>,
    /// Heartbeat period, microseconds; 0 disables heartbeats.
    pub heartbeat_period_us: u64,
    /// Initial NMT state; only [`NmtState::Operational`] nodes send TPDOs. In a configuration
    /// file: `"operational"`, `"pre-operational"`, `"stopped"` or `"boot-up"`.
    #[serde(with = "nmt_by_name")]
    pub nmt: NmtState,
}

/// [`NmtState`] (a bus type without serde) by its kebab-case name in configuration files.
mod nmt_by_name {
    use hw_io::can::NmtState;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    #[derive(Serialize, Deserialize)]
    #[serde(rename_all = "kebab-case")]
    enum Name {
        Operational,
        PreOperational,
        Stopped,
        BootUp,
    }

    pub fn serialize<S: Serializer>(state: &NmtState, s: S) -> Result<S::Ok, S::Error> {
        match state {
            NmtState::Operational => Name::Operational,
            NmtState::PreOperational => Name::PreOperational,
            NmtState::Stopped => Name::Stopped,
            NmtState::BootUp => Name::BootUp,
        }
        .serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<NmtState, D::Error> {
        Ok(match Name::deserialize(d)? {
            Name::Operational => NmtState::Operational,
            Name::PreOperational => NmtState::PreOperational,
            Name::Stopped => NmtState::Stopped,
            Name::BootUp => NmtState::BootUp,
        })
    }
}

impl Default for NodeOptions {
    fn default() -> Self {
        Self {
            latency_us: DEFAULT_LATENCY_US,
            dropout_probability: 0.0,
            dropout_windows_us: Vec::new(),
            emcy: Vec::new(),
            heartbeat_period_us: DEFAULT_HEARTBEAT_PERIOD_US,
            nmt: NmtState::Operational,
        }
    }
}

/// Why virtual nodes could not be built.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum VirtualNodesError {
    /// The encoder configuration is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// A dropout probability outside 0..=1 (or NaN).
    #[error("node index {node}: dropout probability {value} outside 0..=1")]
    BadProbability {
        /// Node index, 0-based.
        node: usize,
        /// The value given.
        value: f64,
    },
}

/// Progress of one EMCY injection.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum EmcyProgress {
    Pending,
    Raised,
    Cleared,
}

#[derive(Clone, Debug)]
struct NodeState {
    nmt: NmtState,
    next_heartbeat_us: Option<u64>,
    emcy: Vec<EmcyProgress>,
    tpdos_sent: u64,
    tpdos_dropped: u64,
}

/// The three virtual encoder nodes of the arm. Deterministic from the seed.
#[derive(Clone, Debug)]
pub struct VirtualNodes {
    config: EncoderConfig,
    ids: [NodeId; ENCODER_NODES],
    options: [NodeOptions; ENCODER_NODES],
    state: [NodeState; ENCODER_NODES],
    rng: ChaCha8Rng,
    last_counter: Option<u8>,
}

impl VirtualNodes {
    /// Nodes from the encoder configuration (node IDs, counts per revolution, zero, sign),
    /// one [`NodeOptions`] per node (in `node_ids` order) and a seed for random dropouts.
    pub fn new(
        config: &EncoderConfig,
        options: [NodeOptions; ENCODER_NODES],
        seed: u64,
    ) -> Result<Self, VirtualNodesError> {
        config.validate()?;
        let ids = config.nodes()?;
        for (node, o) in options.iter().enumerate() {
            let p = o.dropout_probability;
            if !(0.0..=1.0).contains(&p) {
                return Err(VirtualNodesError::BadProbability { node, value: p });
            }
        }
        let state = core::array::from_fn(|k| NodeState {
            nmt: options[k].nmt,
            next_heartbeat_us: None,
            emcy: vec![EmcyProgress::Pending; options[k].emcy.len()],
            tpdos_sent: 0,
            tpdos_dropped: 0,
        });
        Ok(Self { config: *config, ids, options, state, rng: ChaCha8Rng::seed_from_u64(seed), last_counter: None })
    }

    /// Nodes with default options (100 µs latency, no faults, 100 ms heartbeat, operational).
    pub fn with_defaults(config: &EncoderConfig) -> Result<Self, VirtualNodesError> {
        Self::new(config, Default::default(), 0)
    }

    /// The encoder configuration the nodes quantise with.
    pub fn config(&self) -> &EncoderConfig {
        &self.config
    }

    /// Node IDs, in joint order (joints 1-2, 3-4, 5-6).
    pub fn node_ids(&self) -> [NodeId; ENCODER_NODES] {
        self.ids
    }

    /// Options of node `index` (0-based, in `node_ids` order), or `None` past the end.
    pub fn options(&self, index: usize) -> Option<&NodeOptions> {
        self.options.get(index)
    }

    /// NMT state of node `index` (0-based), or `None` past the end.
    pub fn nmt(&self, index: usize) -> Option<NmtState> {
        self.state.get(index).map(|s| s.nmt)
    }

    /// Sets the NMT state of node `index` (0-based); returns false for an unknown index.
    pub fn set_nmt(&mut self, index: usize, state: NmtState) -> bool {
        match self.state.get_mut(index) {
            Some(s) => {
                s.nmt = state;
                true
            }
            None => false,
        }
    }

    /// TPDOs sent by node `index` (0-based) so far.
    pub fn tpdos_sent(&self, index: usize) -> u64 {
        self.state.get(index).map_or(0, |s| s.tpdos_sent)
    }

    /// TPDOs lost by node `index` (0-based) to dropouts so far (not counting silence in a
    /// non-operational NMT state).
    pub fn tpdos_dropped(&self, index: usize) -> u64 {
        self.state.get(index).map_or(0, |s| s.tpdos_dropped)
    }

    /// Counter of the last SYNC answered (1..=240 on a well-formed bus).
    pub fn last_sync_counter(&self) -> Option<u8> {
        self.last_counter
    }

    /// Answers one SYNC with `counter` sent at `t_us` (microseconds), the joints being at
    /// the measured angles `joints_rad` (radians, joints 1..6). Returns the frames the nodes
    /// send, stamped with their send time (microseconds, same time base), in bus order.
    /// Allocation-free. Fails, with no state changed, when a joint angle has no count
    /// (non-finite or out of the `i32` range).
    pub fn on_sync(
        &mut self,
        counter: u8,
        t_us: u64,
        joints_rad: &[f64; JOINTS],
    ) -> Result<SyncFrames, JointToCountsError> {
        let counts = self.config.rad_to_counts(joints_rad)?;
        self.last_counter = Some(counter);
        let mut out = SyncFrames::new();
        for k in 0..ENCODER_NODES {
            let node = self.ids[k];
            let opts = &self.options[k];
            let st = &mut self.state[k];
            let send_us = t_us.saturating_add(opts.latency_us);
            let mut push = |msg: Message| {
                if let Ok(frame) = msg.encode() {
                    // Capacity covers the worst case per node (see MAX_FRAMES_PER_SYNC).
                    let _ = out.push(TimedFrame { frame, unix_time_us: send_us });
                }
            };
            // EMCY: raise and clear injected faults that are due.
            let mut emcy_sent = 0;
            for (inj, progress) in opts.emcy.iter().zip(st.emcy.iter_mut()) {
                if emcy_sent == MAX_EMCY_PER_SYNC {
                    break;
                }
                if *progress == EmcyProgress::Pending && t_us >= inj.at_us {
                    push(Message::Emcy { node, code: inj.code, register: inj.register, vendor: inj.vendor });
                    *progress = EmcyProgress::Raised;
                    emcy_sent += 1;
                }
                if emcy_sent < MAX_EMCY_PER_SYNC
                    && *progress == EmcyProgress::Raised
                    && t_us >= inj.at_us.saturating_add(inj.duration_us)
                {
                    push(Message::Emcy { node, code: 0, register: 0, vendor: [0; 5] });
                    *progress = EmcyProgress::Cleared;
                    emcy_sent += 1;
                }
            }
            // TPDO1.
            if st.nmt == NmtState::Operational {
                let in_window = opts.dropout_windows_us.iter().any(|w| w[0] <= t_us && t_us < w[1]);
                let random_drop = opts.dropout_probability > 0.0 && self.rng.random_bool(opts.dropout_probability);
                if in_window || random_drop {
                    st.tpdos_dropped += 1;
                } else {
                    let j = k * JOINTS_PER_NODE;
                    push(Message::Tpdo { node, counts: [counts[j], counts[j + 1]] });
                    st.tpdos_sent += 1;
                }
            }
            // Heartbeat.
            if opts.heartbeat_period_us > 0 {
                let due = st.next_heartbeat_us.is_none_or(|next| t_us >= next);
                if due {
                    push(Message::Heartbeat { node, state: st.nmt });
                    let mut next = st.next_heartbeat_us.unwrap_or(t_us);
                    while next <= t_us {
                        next = next.saturating_add(opts.heartbeat_period_us);
                        if next == u64::MAX {
                            break;
                        }
                    }
                    st.next_heartbeat_us = Some(next);
                }
            }
        }
        out.sort_unstable_by_key(|f| (f.unix_time_us, f.frame.id().raw()));
        Ok(out)
    }
}

/// Sends `frames` (e.g. from [`VirtualNodes::on_sync`]) on `bus`, in order. The bus stamps
/// its own receive times; the frames' timestamps are not used.
pub fn send_frames(bus: &mut impl CanBus, frames: &[TimedFrame]) -> Result<(), SendError> {
    for f in frames {
        bus.send(&f.frame)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use hw_io::can::{EMCY_COB_ID_BASE, HEARTBEAT_COB_ID_BASE, JointEncoder, TPDO_DLC, TPDO1_COB_ID_BASE};

    const Q: [f64; 6] = [0.1, -0.8, 1.3, -3.0, 0.7, 12.5];

    fn tpdos(frames: &[TimedFrame]) -> Vec<(u8, [i32; 2])> {
        frames
            .iter()
            .filter_map(|f| match Message::decode(&f.frame) {
                Ok(Message::Tpdo { node, counts }) => Some((node.get(), counts)),
                _ => None,
            })
            .collect()
    }

    fn run(nodes: &mut VirtualNodes, syncs: u64) -> Vec<(u64, Vec<TimedFrame>)> {
        let mut counter = 0u8;
        (0..syncs)
            .map(|i| {
                counter = hw_io::can::next_sync_counter(counter);
                let t = i * 1000;
                (t, nodes.on_sync(counter, t, &Q).unwrap().to_vec())
            })
            .collect()
    }

    #[test]
    fn counts_match_rad_to_counts() {
        let mut cfg = EncoderConfig::default();
        cfg.joints[2] = JointEncoder { counts_per_rev: 4096, zero_offset_counts: 1234, sign: -1 };
        let mut nodes = VirtualNodes::with_defaults(&cfg).unwrap();
        let frames = nodes.on_sync(1, 0, &Q).unwrap();
        let expect = cfg.rad_to_counts(&Q).unwrap();
        let got = tpdos(&frames);
        assert_eq!(got.len(), 3);
        for (k, (node, counts)) in got.iter().enumerate() {
            assert_eq!(*node, k as u8 + 1);
            assert_eq!(counts, &[expect[2 * k], expect[2 * k + 1]]);
        }
    }

    #[test]
    fn every_sync_gets_three_tpdos_that_decode_to_the_joints() {
        let cfg = EncoderConfig { node_ids: [5, 9, 12], ..Default::default() };
        let mut nodes = VirtualNodes::with_defaults(&cfg).unwrap();
        let one_count = std::f64::consts::TAU / f64::from(hw_io::can::DEFAULT_COUNTS_PER_REV);
        for (t, frames) in run(&mut nodes, 250) {
            let mut seen = 0;
            for f in &frames {
                assert_eq!(f.unix_time_us, t + DEFAULT_LATENCY_US);
                if let Ok(Message::Tpdo { node, counts }) = Message::decode(&f.frame) {
                    let k = [5, 9, 12].iter().position(|&n| n == node.get()).unwrap();
                    assert_eq!(f.frame.id().raw(), u32::from(TPDO1_COB_ID_BASE) + u32::from(node.get()));
                    assert_eq!(f.frame.dlc(), TPDO_DLC);
                    for j in 0..2 {
                        let q = cfg.joints[2 * k + j].counts_to_rad(counts[j]);
                        assert!((q - Q[2 * k + j]).abs() <= one_count, "joint {}: {q} vs {}", 2 * k + j, Q[2 * k + j]);
                    }
                    seen += 1;
                }
            }
            assert_eq!(seen, 3, "at t = {t} us");
        }
        assert_eq!(nodes.last_sync_counter(), Some(10)); // 250 SYNCs: 240, then 1..=10
    }

    #[test]
    fn frames_are_in_bus_order() {
        let mut opts: [NodeOptions; 3] = Default::default();
        opts[0].latency_us = 300;
        opts[2].latency_us = 50;
        opts[1].emcy.push(EmcyInjection { at_us: 0, duration_us: 10, code: 0x7305, register: 1, vendor: [0; 5] });
        let mut nodes = VirtualNodes::new(&EncoderConfig::default(), opts, 1).unwrap();
        let frames = nodes.on_sync(1, 1000, &Q).unwrap();
        let keys: Vec<_> = frames.iter().map(|f| (f.unix_time_us, f.frame.id().raw())).collect();
        let mut sorted = keys.clone();
        sorted.sort();
        assert_eq!(keys, sorted);
        assert_eq!(keys[0], (1050, 0x183));
        assert_eq!(keys.len(), 3 + 3 + 2); // TPDOs, heartbeats, EMCY raised and cleared
    }

    #[test]
    fn scripted_dropout_window_suppresses_exactly_that_window() {
        let mut opts: [NodeOptions; 3] = Default::default();
        opts[1].dropout_windows_us.push([10_000, 20_000]);
        let mut nodes = VirtualNodes::new(&EncoderConfig::default(), opts, 1).unwrap();
        for (t, frames) in run(&mut nodes, 50) {
            let nodes_seen: Vec<u8> = tpdos(&frames).iter().map(|(n, _)| *n).collect();
            if (10_000..20_000).contains(&t) {
                assert_eq!(nodes_seen, vec![1, 3], "t = {t}");
            } else {
                assert_eq!(nodes_seen, vec![1, 2, 3], "t = {t}");
            }
        }
        assert_eq!(nodes.tpdos_dropped(1), 10);
        assert_eq!(nodes.tpdos_sent(1), 40);
        assert_eq!(nodes.tpdos_dropped(0), 0);
    }

    #[test]
    fn random_dropouts_are_deterministic_and_about_the_probability() {
        let mut opts: [NodeOptions; 3] = Default::default();
        opts[2].dropout_probability = 0.1;
        let count = |seed| {
            let mut nodes = VirtualNodes::new(&EncoderConfig::default(), opts.clone(), seed).unwrap();
            run(&mut nodes, 5000);
            nodes.tpdos_dropped(2)
        };
        let a = count(7);
        assert_eq!(a, count(7));
        assert!((400..600).contains(&a), "{a} of 5000 dropped");
        let mut bad = opts.clone();
        bad[0].dropout_probability = 1.5;
        assert!(matches!(
            VirtualNodes::new(&EncoderConfig::default(), bad, 0),
            Err(VirtualNodesError::BadProbability { node: 0, .. })
        ));
    }

    #[test]
    fn emcy_is_raised_and_cleared() {
        let mut opts: [NodeOptions; 3] = Default::default();
        opts[2].emcy.push(EmcyInjection {
            at_us: 5_500,
            duration_us: 10_000,
            code: 0x7305,
            register: 0x81,
            vendor: [1, 2, 3, 4, 5],
        });
        let mut nodes = VirtualNodes::new(&EncoderConfig::default(), opts, 1).unwrap();
        let mut emcys = Vec::new();
        for (t, frames) in run(&mut nodes, 40) {
            for f in &frames {
                if let Ok(Message::Emcy { node, code, register, vendor }) = Message::decode(&f.frame) {
                    assert_eq!(f.frame.id().raw(), u32::from(EMCY_COB_ID_BASE) + 3);
                    emcys.push((t, node.get(), code, register, vendor));
                }
            }
        }
        assert_eq!(emcys, vec![(6_000, 3, 0x7305, 0x81, [1, 2, 3, 4, 5]), (16_000, 3, 0, 0, [0; 5])]);
    }

    #[test]
    fn heartbeats_every_100_ms_with_the_nmt_state() {
        let mut nodes = VirtualNodes::with_defaults(&EncoderConfig::default()).unwrap();
        let mut beats: Vec<(u64, u8, NmtState)> = Vec::new();
        let mut counter = 0u8;
        for i in 0..1000u64 {
            let t = i * 1000;
            if t == 500_000 {
                assert!(nodes.set_nmt(0, NmtState::PreOperational));
            }
            counter = hw_io::can::next_sync_counter(counter);
            let frames = nodes.on_sync(counter, t, &Q).unwrap();
            for f in &frames {
                if let Ok(Message::Heartbeat { node, state }) = Message::decode(&f.frame) {
                    assert_eq!(f.frame.id().raw(), u32::from(HEARTBEAT_COB_ID_BASE) + u32::from(node.get()));
                    beats.push((t, node.get(), state));
                }
            }
            // A pre-operational node sends no TPDO.
            let n1 = tpdos(&frames).iter().any(|(n, _)| *n == 1);
            assert_eq!(n1, t < 500_000, "t = {t}");
        }
        for node in 1..=3u8 {
            let times: Vec<u64> = beats.iter().filter(|b| b.1 == node).map(|b| b.0).collect();
            assert_eq!(times, (0..10).map(|k| k * 100_000).collect::<Vec<_>>(), "node {node}");
        }
        assert!(beats.iter().filter(|b| b.1 == 1 && b.0 >= 500_000).all(|b| b.2 == NmtState::PreOperational));
        assert!(beats.iter().filter(|b| b.1 != 1 || b.0 < 500_000).all(|b| b.2 == NmtState::Operational));
        assert!(!nodes.set_nmt(3, NmtState::Stopped));
    }

    #[test]
    fn non_finite_joint_is_an_error_and_changes_nothing() {
        let mut nodes = VirtualNodes::with_defaults(&EncoderConfig::default()).unwrap();
        let mut q = Q;
        q[4] = f64::NAN;
        let err = nodes.on_sync(1, 0, &q).unwrap_err();
        assert_eq!(err.joint, 4);
        assert_eq!(nodes.tpdos_sent(0), 0);
        assert_eq!(nodes.last_sync_counter(), None);
        // The first heartbeat is still due at the next good SYNC.
        let frames = nodes.on_sync(2, 1000, &Q).unwrap();
        assert_eq!(frames.len(), 6);
    }

    #[test]
    fn frames_reach_a_bus() {
        let bus = hw_io::can::InProcessBus::new();
        let mut node_end = bus.endpoint().unwrap();
        let mut controller = bus.endpoint().unwrap();
        let mut nodes = VirtualNodes::with_defaults(&EncoderConfig::default()).unwrap();
        let frames = nodes.on_sync(1, 0, &Q).unwrap();
        send_frames(&mut node_end, &frames).unwrap();
        let mut got = 0;
        while let Some(rx) = controller.recv_timeout(std::time::Duration::ZERO).unwrap() {
            assert!(Message::decode(&rx.frame).is_ok());
            got += 1;
        }
        assert_eq!(got, frames.len());
    }
}
