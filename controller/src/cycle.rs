//! One control cycle, in two deterministic stages shared by the live loop and `replay`.
//!
//! 1. [`Acquisition`]: the frames of the bus → this cycle's joint readings (encoder counts)
//!    and the data-health flags ([`CycleInput`]). Frames are decoded; TPDOs are assembled;
//!    EMCY and heartbeats feed the [`HealthMonitor`]; malformed frames (wrong DLC, unknown
//!    COB-ID, RTR, extended IDs) and foreign nodes are counted, never fatal.
//! 2. [`Estimation`]: a [`CycleInput`] → counts to radians → forward kinematics → trocar
//!    detector → [`CycleOutput`]. Pure function of its inputs and its own state, so a
//!    recording of the inputs reproduces the outputs bit for bit.
//!
//! ## Stale data policy
//! - Every cycle whose input is not valid (an incomplete cycle, a stale node, a failed
//!   SYNC, a bus error, a sample refused by the kinematics or the detector) publishes an
//!   invalid output, and the detector is **frozen** (not stepped): a **gap**.
//! - When valid input returns after a gap of at most `[detector] max_gap_s` (50 ms by
//!   default), the detector **resumes** where it was and checks the first fresh sample
//!   against its state ([`estimator::trocar::Detector::resume_after_gap`]: inside, a line
//!   that has left the fulcrum ends the insertion at once); a 3 ms glitch no longer throws
//!   the trocar away.
//! - After a longer gap, or an EMCY or a lost heartbeat (or a node not operational) at any
//!   point, the detector is **reset** before it next steps (the surgeon may have moved
//!   anywhere meanwhile). That first valid cycle carries `DETECTOR_RESET`.
//! - Valid only when every invalidating flag is clear; every float of a valid output is
//!   finite (checked), otherwise the output is downgraded to invalid with `BAD_SAMPLE`.
//!
//! Both stages are allocation-free after construction.

use estimator::kinematics::{Achilles, AchillesConfig, KinematicsConfigError};
use estimator::trocar::{
    ConfigError as DetectorConfigError, Detector, DetectorConfig, GapOutcome, LineSample, TrocarState,
};
use hw_io::can::{
    CanFrame, ConfigError as EncoderConfigError, DecodeError, ENCODER_NODES, EncoderConfig, JOINTS, JointAssembler,
    Message,
};
use hw_io::ipc::{FulcrumSample, HealthFlags as Flags, OutputState};
use serde::{Deserialize, Serialize};

use crate::health::{HealthConfig, HealthMonitor};

/// Node flags that make the detector reset whatever the gap's length (a node in fault or
/// silent: its data cannot be trusted until it recovers). A stale node only makes a gap.
const RESET_FLAGS: Flags = Flags::NODE1_EMCY
    .union(Flags::NODE2_EMCY)
    .union(Flags::NODE3_EMCY)
    .union(Flags::NODE1_HEARTBEAT)
    .union(Flags::NODE2_HEARTBEAT)
    .union(Flags::NODE3_HEARTBEAT);

/// One cycle's input to [`Estimation`]: what acquisition delivered.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct CycleInput {
    /// Joint readings 1..6, encoder counts (meaningful for the nodes in `received_mask`).
    pub counts: [i32; JOINTS],
    /// Bit k set when node k (joint order: joints 1-2, 3-4, 5-6) delivered its TPDO.
    pub received_mask: u8,
    /// Acquisition health flags (recorded as their `u32` bits, as before they were typed).
    pub flags: Flags,
}

/// Counters of everything acquisition saw, since start-up.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct AcquisitionStats {
    /// Frames seen (in cycle and late).
    pub frames: u64,
    /// TPDOs taken into a cycle.
    pub tpdos: u64,
    /// TPDOs that arrived after their cycle's deadline (not used).
    pub late_tpdos: u64,
    /// Cycles closed.
    pub cycles: u64,
    /// Cycles closed without every TPDO.
    pub incomplete_cycles: u64,
    /// TPDOs missing at cycle ends, summed over nodes.
    pub missing_tpdos: u64,
    /// Frames with an unknown COB-ID (or an extended identifier, or RTR).
    pub unknown_id_frames: u64,
    /// Frames with a DLC that does not match their COB-ID.
    pub wrong_dlc_frames: u64,
    /// Frames that are otherwise malformed (SYNC counter out of range, unknown NMT state).
    pub malformed_frames: u64,
    /// Well-formed messages from nodes that are neither ours nor listed in
    /// `bus.other_node_ids`.
    pub foreign_node_frames: u64,
    /// Well-formed TPDOs, heartbeats and EMCYs of the other nodes expected on the bus
    /// (`bus.other_node_ids`: the endoscope arm's); ignored, never a health flag.
    #[serde(default)]
    pub other_node_frames: u64,
    /// Second TPDO of a node within one cycle (the newer replaces the older).
    pub duplicate_tpdos: u64,
    /// SYNC frames seen from another master on the bus.
    pub foreign_syncs: u64,
    /// EMCY messages from our nodes (raise and clear).
    pub emcy_frames: u64,
    /// Bus errors reported by the interface.
    pub bus_errors: u64,
}

/// Stage 1: frames → [`CycleInput`].
#[derive(Clone, Copy, Debug)]
pub struct Acquisition {
    assembler: JointAssembler,
    health: HealthMonitor,
    stats: AcquisitionStats,
    bus_error: bool,
    /// Bit `k` set: node `k` is another arm's node on the same bus (ignored).
    other_nodes: u128,
}

/// Why acquisition could not be set up.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum AcquisitionError {
    /// The encoder configuration is invalid.
    #[error(transparent)]
    Encoders(#[from] EncoderConfigError),
}

impl Acquisition {
    /// Acquisition for the encoder nodes of `encoders`, with health thresholds `health`.
    pub fn new(encoders: &EncoderConfig, health: HealthConfig) -> Result<Self, AcquisitionError> {
        let assembler = JointAssembler::from_config(encoders)?;
        let health = HealthMonitor::new(health, assembler.nodes());
        Ok(Self { assembler, health, stats: AcquisitionStats::default(), bus_error: false, other_nodes: 0 })
    }

    /// The same, with the node IDs of other nodes expected on the bus (`bus.other_node_ids`):
    /// their TPDOs, heartbeats and EMCYs are counted as `other_node_frames` and otherwise
    /// ignored. IDs of our own encoder nodes, and IDs outside 1..=127, are left out.
    pub fn with_other_nodes(mut self, node_ids: &[u8]) -> Self {
        let ours = self.assembler.nodes();
        for &id in node_ids {
            if (1..=127).contains(&id) && !ours.iter().any(|n| n.get() == id) {
                self.other_nodes |= 1u128 << id;
            }
        }
        self
    }

    /// `true` (and counted) when `msg` comes from one of the other nodes expected on the bus.
    fn is_other_node(&mut self, msg: &Message) -> bool {
        let node = match msg {
            Message::Tpdo { node, .. } | Message::Heartbeat { node, .. } | Message::Emcy { node, .. } => node.get(),
            Message::Sync { .. } => return false,
        };
        let other = self.other_nodes & (1u128 << node) != 0;
        self.stats.other_node_frames += u64::from(other);
        other
    }

    /// Counters since start-up.
    pub fn stats(&self) -> &AcquisitionStats {
        &self.stats
    }

    /// Decodes a frame and counts why it is malformed; `None` when it is.
    fn decode(&mut self, frame: &CanFrame) -> Option<Message> {
        self.stats.frames += 1;
        match Message::decode(frame) {
            Ok(m) => Some(m),
            Err(DecodeError::UnknownId { .. } | DecodeError::ExtendedId { .. } | DecodeError::RemoteFrame { .. }) => {
                self.stats.unknown_id_frames += 1;
                None
            }
            Err(DecodeError::WrongDlc { .. }) => {
                self.stats.wrong_dlc_frames += 1;
                None
            }
            Err(_) => {
                self.stats.malformed_frames += 1;
                None
            }
        }
    }

    fn on_status(&mut self, msg: &Message, now_ns: u64) {
        match msg {
            Message::Sync { .. } => self.stats.foreign_syncs += 1,
            Message::Emcy { .. } | Message::Heartbeat { .. } => {
                if self.health.on_message(msg, now_ns) {
                    if matches!(msg, Message::Emcy { .. }) {
                        self.stats.emcy_frames += 1;
                    }
                } else {
                    self.stats.foreign_node_frames += 1;
                }
            }
            Message::Tpdo { .. } => {}
        }
    }

    /// A frame received outside any cycle's collection window (before this cycle's SYNC):
    /// EMCY and heartbeats count; a TPDO is late and not used.
    ///
    /// **Real-time (1 kHz loop):** called for every frame drained before the SYNC; allocation-free, no I/O.
    pub fn on_frame_between_cycles(&mut self, frame: &CanFrame, now_ns: u64) {
        let Some(msg) = self.decode(frame) else { return };
        if self.is_other_node(&msg) {
            return;
        }
        match msg {
            Message::Tpdo { node, .. } => {
                if self.assembler.nodes().contains(&node) {
                    self.stats.late_tpdos += 1;
                } else {
                    self.stats.foreign_node_frames += 1;
                }
            }
            _ => self.on_status(&msg, now_ns),
        }
    }

    /// Opens a cycle: call right after sending SYNC.
    pub fn start_cycle(&mut self) {
        self.assembler.start_cycle();
        self.bus_error = false;
    }

    /// A frame received during the cycle's collection window.
    ///
    /// **Real-time (1 kHz loop):** called for every frame until the deadline; allocation-free, no I/O.
    pub fn on_frame(&mut self, frame: &CanFrame, now_ns: u64) {
        let Some(msg) = self.decode(frame) else { return };
        if self.is_other_node(&msg) {
            return;
        }
        match msg {
            Message::Tpdo { .. } => match self.assembler.accept(&msg) {
                Ok(()) => self.stats.tpdos += 1,
                Err(hw_io::can::AcceptError::Duplicate { .. }) => self.stats.duplicate_tpdos += 1,
                Err(_) => self.stats.foreign_node_frames += 1,
            },
            _ => self.on_status(&msg, now_ns),
        }
    }

    /// The interface reported an error during this cycle.
    pub fn on_bus_error(&mut self) {
        self.stats.bus_errors += 1;
        self.bus_error = true;
    }

    /// True when every node's TPDO of this cycle is in.
    pub fn is_complete(&self) -> bool {
        self.assembler.is_complete()
    }

    /// Closes the cycle at `now_ns`. `sync_failed`: this cycle's SYNC could not be sent.
    ///
    /// **Real-time (1 kHz loop):** called once per cycle at its deadline; allocation-free, no I/O.
    pub fn end_cycle(&mut self, now_ns: u64, sync_failed: bool) -> CycleInput {
        let (counts, missing) = self.assembler.counts_partial();
        let nodes = self.assembler.nodes();
        let mut received_mask = 0u8;
        for (k, n) in nodes.iter().enumerate() {
            if !missing.contains(*n) {
                received_mask |= 1 << k;
            }
        }
        let mut f = self.health.end_cycle(received_mask, now_ns);
        self.stats.cycles += 1;
        if !missing.is_empty() {
            f |= Flags::INCOMPLETE_CYCLE;
            self.stats.incomplete_cycles += 1;
            self.stats.missing_tpdos += missing.len() as u64;
        }
        if sync_failed {
            f |= Flags::SYNC_SEND_FAILED;
        }
        if self.bus_error {
            f |= Flags::BUS_ERROR;
        }
        CycleInput { counts, received_mask, flags: f }
    }
}

/// One cycle's estimate: what is published (less the sequence and timing fields), typed; it
/// becomes the wire's `u32`s only in [`CycleOutput::to_sample`].
///
/// Recorded with postcard in every [`crate::rt_loop::CycleRecord`]: `state` as the `u32` of its
/// variant and `health` as its `u32` bits, the same bytes as when both were plain `u32`s (old
/// recordings replay, `controller/tests/replay_fixture.rs`). A recorded state that is no
/// [`OutputState`] fails to decode ([`crate::recorder::ReadError::Decode`]).
#[derive(Clone, Copy, Debug, PartialEq, Default, Serialize, Deserialize)]
pub struct CycleOutput {
    /// Invalid, outside or inside.
    pub state: OutputState,
    /// Trocar identity when inside, else 0.
    pub trocar_id: u32,
    /// Health flags: the input's plus `BAD_SAMPLE` / `DETECTOR_RESET`.
    pub health: Flags,
    /// Fulcrum, metres, robot base frame (zero unless inside).
    pub fulcrum_base_m: [f64; 3],
    /// Fit residual, metres (0 without a fit).
    pub residual_m: f64,
    /// One-sigma fulcrum uncertainty, metres (0 without a fit).
    pub fulcrum_std_m: f64,
    /// Fit conditioning, dimensionless (0 without a fit).
    pub conditioning: f64,
    /// Wrist centre P, metres, robot base frame (zero when invalid).
    pub wrist_base_m: [f64; 3],
    /// Instrument axis z, unit, robot base frame (zero when invalid).
    pub axis_base: [f64; 3],
    /// Joint angles 1..6, radians (zero when the cycle is incomplete).
    pub joints_rad: [f64; JOINTS],
    /// Lines in the detector's deciding window.
    pub window_fill: u16,
    /// Capacity of that window.
    pub window_len: u16,
    /// Lines in the latest fit.
    pub fit_lines: u16,
}

impl CycleOutput {
    /// True when every float field has the same bits as in `other` and every other field is
    /// equal (what `replay` checks).
    pub fn bit_identical(&self, other: &Self) -> bool {
        fn bits(a: &[f64], b: &[f64]) -> bool {
            a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
        }
        self.state == other.state
            && self.trocar_id == other.trocar_id
            && self.health == other.health
            && bits(&self.fulcrum_base_m, &other.fulcrum_base_m)
            && bits(
                &[self.residual_m, self.fulcrum_std_m, self.conditioning],
                &[other.residual_m, other.fulcrum_std_m, other.conditioning],
            )
            && bits(&self.wrist_base_m, &other.wrist_base_m)
            && bits(&self.axis_base, &other.axis_base)
            && bits(&self.joints_rad, &other.joints_rad)
            && self.window_fill == other.window_fill
            && self.window_len == other.window_len
            && self.fit_lines == other.fit_lines
    }

    fn all_finite(&self) -> bool {
        self.fulcrum_base_m
            .iter()
            .chain([self.residual_m, self.fulcrum_std_m, self.conditioning].iter())
            .chain(self.wrist_base_m.iter())
            .chain(self.axis_base.iter())
            .chain(self.joints_rad.iter())
            .all(|v| v.is_finite())
    }

    /// Fills the estimate fields of a published sample (the caller sets sequence, run id,
    /// timestamp and timings): the one place where state and health become the wire's `u32`s.
    pub fn to_sample(&self) -> FulcrumSample {
        let mut s = FulcrumSample::invalid(self.health);
        s.state = self.state.into();
        s.trocar_id = self.trocar_id;
        s.fulcrum_base_m = self.fulcrum_base_m;
        s.residual_m = self.residual_m;
        s.fulcrum_std_m = self.fulcrum_std_m;
        s.conditioning = self.conditioning;
        s.wrist_base_m = self.wrist_base_m;
        s.axis_base = self.axis_base;
        s.joints_rad = self.joints_rad;
        s.window_fill = self.window_fill;
        s.window_len = self.window_len;
        s.fit_lines = self.fit_lines;
        s
    }
}

/// Why estimation could not be set up.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EstimationError {
    /// The encoder configuration is invalid.
    #[error(transparent)]
    Encoders(#[from] EncoderConfigError),
    /// The kinematic configuration is invalid.
    #[error(transparent)]
    Kinematics(#[from] KinematicsConfigError),
    /// The detector configuration is invalid.
    #[error(transparent)]
    Detector(#[from] DetectorConfigError),
}

/// Stage 2: [`CycleInput`] → [`CycleOutput`]. Deterministic.
#[derive(Clone, Debug)]
pub struct Estimation {
    encoders: EncoderConfig,
    arm: Achilles,
    detector: Detector,
    reset_pending: bool,
    /// Consecutive cycles whose input never reached the detector since it last stepped
    /// (0 before its first step: nothing to resume).
    gap_cycles: u64,
    stepped: bool,
}

impl Estimation {
    /// Estimation with the given encoder conversion, arm model and detector.
    pub fn new(
        encoders: &EncoderConfig,
        kinematics: &AchillesConfig,
        detector: &DetectorConfig,
    ) -> Result<Self, EstimationError> {
        encoders.validate()?;
        Ok(Self {
            encoders: *encoders,
            arm: Achilles::new(kinematics)?,
            detector: Detector::new(detector)?,
            reset_pending: false,
            gap_cycles: 0,
            stepped: false,
        })
    }

    /// Processes one cycle's input.
    ///
    /// **Real-time (1 kHz loop):** called once per cycle (and by `replay`, bit for bit); allocation-free, no I/O, no clock.
    pub fn process(&mut self, input: &CycleInput) -> CycleOutput {
        let mut out = CycleOutput { state: OutputState::Invalid, health: input.flags, ..Default::default() };
        if input.flags.intersects(RESET_FLAGS) {
            self.reset_pending = true;
        }
        if input.flags.intersects(Flags::INVALIDATING) {
            if input.received_mask == (1 << ENCODER_NODES) - 1 {
                out.joints_rad = self.encoders.counts_to_rad(&input.counts);
            }
            self.gap_cycles += u64::from(self.stepped);
            return out;
        }
        let q = self.encoders.counts_to_rad(&input.counts);
        out.joints_rad = q;
        let Ok(pose) = self.arm.forward(&q) else {
            out.health |= Flags::BAD_SAMPLE;
            self.gap_cycles += u64::from(self.stepped);
            return out;
        };
        if self.reset_pending {
            self.detector.reset();
            self.reset_pending = false;
            out.health |= Flags::DETECTOR_RESET;
        } else if self.gap_cycles > 0 && self.detector.resume_after_gap(self.gap_cycles) == GapOutcome::Reset {
            out.health |= Flags::DETECTOR_RESET;
        }
        self.gap_cycles = 0;
        self.stepped = true;
        let est = self.detector.step(&LineSample::new(pose.wrist_base_m, pose.axis_base));
        out.wrist_base_m = pose.wrist_base_m.into();
        out.axis_base = pose.axis_base.into();
        out.window_fill = est.window_fill;
        out.window_len = est.window_len;
        if let Some(fit) = est.fit {
            out.residual_m = fit.residual_m;
            out.fulcrum_std_m = fit.std_m;
            out.conditioning = fit.conditioning;
            out.fit_lines = fit.lines;
        }
        if est.rejected.is_some() {
            out.health |= Flags::BAD_SAMPLE;
            return out;
        }
        match (est.state, est.fulcrum_base_m) {
            (TrocarState::Inside { id }, Some(f)) => {
                out.state = OutputState::Inside;
                out.trocar_id = u32::from(id);
                out.fulcrum_base_m = f.into();
            }
            _ => out.state = OutputState::Outside,
        }
        if !out.all_finite() {
            out.state = OutputState::Invalid;
            out.health |= Flags::BAD_SAMPLE;
            out.fulcrum_base_m = [0.0; 3];
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hw_io::can::{NmtState, NodeId};

    fn n(k: u8) -> NodeId {
        NodeId::new(k).unwrap()
    }

    fn frame(m: Message) -> CanFrame {
        m.encode().unwrap()
    }

    fn acquisition() -> Acquisition {
        let mut a = Acquisition::new(&EncoderConfig::default(), HealthConfig::default()).unwrap();
        for k in 1..=3 {
            a.on_frame_between_cycles(&frame(Message::Heartbeat { node: n(k), state: NmtState::Operational }), 0);
        }
        a
    }

    fn full_cycle(a: &mut Acquisition, t: u64, counts: [i32; 6]) -> CycleInput {
        a.start_cycle();
        for k in 0..3u8 {
            let c = [counts[2 * k as usize], counts[2 * k as usize + 1]];
            a.on_frame(&frame(Message::Tpdo { node: n(k + 1), counts: c }), t);
        }
        assert!(a.is_complete());
        a.end_cycle(t, false)
    }

    #[test]
    fn a_complete_cycle_is_clean_and_malformed_frames_are_counted() {
        let mut a = acquisition();
        a.start_cycle();
        a.on_frame(&CanFrame::new_standard(0x181, &[1, 2, 3]).unwrap(), 0); // wrong DLC
        a.on_frame(&CanFrame::new_standard(0x555, &[0; 8]).unwrap(), 0); // unknown COB-ID
        a.on_frame(&frame(Message::Tpdo { node: n(9), counts: [0, 0] }), 0); // foreign node
        for k in 1..=3 {
            a.on_frame(&frame(Message::Tpdo { node: n(k), counts: [k as i32, 0] }), 0);
        }
        let input = a.end_cycle(0, false);
        assert_eq!(input.flags, Flags::empty());
        assert_eq!(input.received_mask, 0b111);
        assert_eq!(input.counts[0], 1);
        let s = a.stats();
        assert_eq!((s.wrong_dlc_frames, s.unknown_id_frames, s.foreign_node_frames, s.tpdos), (1, 1, 1, 3));
    }

    #[test]
    fn other_nodes_are_counted_and_change_nothing() {
        // The same cycles with and without the endoscope arm's frames (nodes 4 and 5: TPDOs,
        // heartbeats, even an EMCY, in and between cycles) give the same inputs.
        let run = |with_others: bool| {
            let mut a = acquisition().with_other_nodes(&[4, 5, 2]); // 2 is ours: left out
            let mut inputs = Vec::new();
            for t in 0..400u64 {
                let ns = t * 1_000_000;
                if with_others {
                    a.on_frame_between_cycles(
                        &frame(Message::Heartbeat { node: n(4), state: NmtState::Operational }),
                        ns,
                    );
                }
                a.start_cycle();
                if with_others && t.is_multiple_of(10) {
                    a.on_frame(&frame(Message::Tpdo { node: n(4), counts: [7, 8] }), ns);
                    a.on_frame(&frame(Message::Tpdo { node: n(5), counts: [9, 10] }), ns);
                    let emcy = Message::Emcy { node: n(5), code: 0x7305, register: 1, vendor: [0; 5] };
                    a.on_frame(&frame(emcy), ns);
                }
                for k in 1..=3u8 {
                    a.on_frame(&frame(Message::Tpdo { node: n(k), counts: [t as i32, i32::from(k)] }), ns);
                }
                if t.is_multiple_of(100) {
                    for k in 1..=3 {
                        a.on_frame(&frame(Message::Heartbeat { node: n(k), state: NmtState::Operational }), ns);
                    }
                }
                inputs.push(a.end_cycle(ns, false));
            }
            (inputs, *a.stats())
        };
        let (with, s) = run(true);
        let (without, s0) = run(false);
        assert_eq!(with, without);
        assert!(with.iter().all(|i| i.flags.is_empty()), "no health flag");
        assert_eq!(s.other_node_frames, 400 + 40 * 3);
        assert_eq!((s.foreign_node_frames, s.unknown_id_frames, s.emcy_frames, s.duplicate_tpdos), (0, 0, 0, 0));
        assert_eq!(s.frames, s0.frames + 520);
        assert_eq!(AcquisitionStats { frames: s0.frames, other_node_frames: 0, ..s }, s0);
        // Without the list they are foreign (still no flag).
        let mut a = acquisition();
        a.on_frame(&frame(Message::Tpdo { node: n(4), counts: [0, 0] }), 0);
        assert_eq!((a.stats().foreign_node_frames, a.stats().other_node_frames), (1, 0));
    }

    #[test]
    fn missing_tpdo_gives_incomplete_then_stale() {
        let mut a = acquisition();
        a.start_cycle();
        a.on_frame(&frame(Message::Tpdo { node: n(1), counts: [0, 0] }), 0);
        a.on_frame(&frame(Message::Tpdo { node: n(3), counts: [0, 0] }), 0);
        let input = a.end_cycle(0, false);
        assert_eq!(input.flags, Flags::INCOMPLETE_CYCLE);
        assert_eq!(input.received_mask, 0b101);
        for _ in 0..2 {
            a.start_cycle();
            a.end_cycle(0, false);
        }
        a.start_cycle();
        let input = a.end_cycle(0, false);
        assert!(input.flags.contains(Flags::NODE2_STALE));
        // A late TPDO is counted, not used.
        a.on_frame_between_cycles(&frame(Message::Tpdo { node: n(2), counts: [0, 0] }), 0);
        assert_eq!(a.stats().late_tpdos, 1);
        assert_eq!(a.stats().incomplete_cycles, 4);
    }

    fn estimation() -> Estimation {
        Estimation::new(&EncoderConfig::default(), &AchillesConfig::default(), &DetectorConfig::default()).unwrap()
    }

    #[test]
    fn valid_input_gives_a_valid_outside_estimate_with_the_wrist_point() {
        let mut a = acquisition();
        let mut e = estimation();
        let out = e.process(&full_cycle(&mut a, 0, [0, 0, 32768, 0, 0, 0]));
        assert_eq!(out.state, OutputState::Outside);
        assert_eq!(out.health, Flags::empty());
        assert!(out.wrist_base_m.iter().any(|v| *v != 0.0));
        let sample = out.to_sample();
        assert!(sample.is_valid());
        assert_eq!(sample.fulcrum(), None);
    }

    #[test]
    fn invalid_input_is_never_published_as_valid_and_resets_after_node_faults() {
        let mut e = estimation();
        let mut a = acquisition();
        let good = full_cycle(&mut a, 0, [0, 0, 32768, 0, 0, 0]);
        assert_eq!(e.process(&good).state, OutputState::Outside);
        // Incomplete: invalid, frozen, no reset afterwards.
        let out = e.process(&CycleInput { flags: Flags::INCOMPLETE_CYCLE, received_mask: 0b011, ..good });
        assert_eq!(out.state, OutputState::Invalid);
        assert_eq!(out.joints_rad, [0.0; 6]);
        let out = e.process(&good);
        assert!(!out.health.contains(Flags::DETECTOR_RESET));
        // EMCY: invalid, and the next valid cycle resets the detector.
        let out = e.process(&CycleInput { flags: Flags::NODE1_EMCY, ..good });
        assert_eq!(out.state, OutputState::Invalid);
        assert_eq!(out.fulcrum_base_m, [0.0; 3]);
        let out = e.process(&good);
        assert_eq!(out.state, OutputState::Outside);
        assert!(out.health.contains(Flags::DETECTOR_RESET));
        assert!(!e.process(&good).health.contains(Flags::DETECTOR_RESET));
    }

    /// `CycleOutput` as it was recorded before state and health were typed.
    #[derive(Serialize, Deserialize)]
    struct RawOutput {
        state: u32,
        trocar_id: u32,
        health: u32,
        fulcrum_base_m: [f64; 3],
        residual_m: f64,
        fulcrum_std_m: f64,
        conditioning: f64,
        wrist_base_m: [f64; 3],
        axis_base: [f64; 3],
        joints_rad: [f64; JOINTS],
        window_fill: u16,
        window_len: u16,
        fit_lines: u16,
    }

    fn raw(state: u32, health: u32) -> RawOutput {
        RawOutput {
            state,
            trocar_id: 3,
            health,
            fulcrum_base_m: [0.25, -0.5, 1e-9],
            residual_m: 1e-4,
            fulcrum_std_m: 2e-4,
            conditioning: 0.3,
            wrist_base_m: [0.1, 0.2, 0.3],
            axis_base: [0.0, 0.6, 0.8],
            joints_rad: [0.1, -0.2, 0.3, -0.4, 0.5, -0.6],
            window_fill: 100,
            window_len: 128,
            fit_lines: 300,
        }
    }

    #[test]
    fn the_typed_output_records_the_same_postcard_bytes_as_the_raw_u32s() {
        let healths =
            [0, Flags::INCOMPLETE_CYCLE.bits() | Flags::OVERRUN.bits(), Flags::all().bits(), 1 << 20, u32::MAX];
        for state in [OutputState::Invalid, OutputState::Outside, OutputState::Inside] {
            for health in healths {
                let old = postcard::to_allocvec(&raw(u32::from(state), health)).unwrap();
                let typed: CycleOutput = postcard::from_bytes(&old).unwrap();
                assert_eq!((typed.state, typed.health.bits()), (state, health));
                assert_eq!(postcard::to_allocvec(&typed).unwrap(), old, "{state:?} {health:#x}");
            }
        }
        let input = CycleInput { counts: [1, -2, 3, -4, 5, -6], received_mask: 0b101, flags: Flags::NODE2_STALE };
        let bytes = postcard::to_allocvec(&input).unwrap();
        let raw_input: ([i32; JOINTS], u8, u32) = postcard::from_bytes(&bytes).unwrap();
        assert_eq!(raw_input, (input.counts, 0b101, Flags::NODE2_STALE.bits()));
    }

    #[test]
    fn a_recorded_unknown_state_is_a_decode_error_not_a_panic() {
        for state in [3, 7, u32::MAX] {
            let bytes = postcard::to_allocvec(&raw(state, 0)).unwrap();
            assert!(postcard::from_bytes::<CycleOutput>(&bytes).is_err(), "state {state}");
        }
    }

    #[test]
    fn to_sample_puts_the_wire_values_and_they_read_back_typed() {
        let out = CycleOutput {
            state: OutputState::Inside,
            trocar_id: 2,
            health: Flags::DETECTOR_RESET | Flags::OVERRUN,
            fulcrum_base_m: [0.1, 0.2, 0.3],
            ..Default::default()
        };
        let s = out.to_sample();
        assert_eq!((s.state, s.health), (2, Flags::DETECTOR_RESET.bits() | Flags::OVERRUN.bits()));
        assert_eq!((s.state(), s.health()), (Ok(out.state), out.health));
        assert_eq!(s.fulcrum(), Some([0.1, 0.2, 0.3]));
    }

    #[test]
    fn replaying_inputs_reproduces_outputs_bit_for_bit() {
        let mut a = acquisition();
        let inputs: Vec<CycleInput> = (0..500)
            .map(|i| full_cycle(&mut a, i * 1_000_000, [i as i32 * 7, 100, 32768 - i as i32, 5, i as i32, 9]))
            .collect();
        let run = |inputs: &[CycleInput]| {
            let mut e = estimation();
            inputs.iter().map(|i| e.process(i)).collect::<Vec<_>>()
        };
        let (x, y) = (run(&inputs), run(&inputs));
        assert!(x.iter().zip(&y).all(|(a, b)| a.bit_identical(b)));
        let mut z = y.clone();
        z[100].wrist_base_m[0] = f64::from_bits(z[100].wrist_base_m[0].to_bits() ^ 1);
        assert!(!x[100].bit_identical(&z[100]));
    }
}
