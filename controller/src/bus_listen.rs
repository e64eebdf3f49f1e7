//! A passive listener on the encoder bus: both arms' joints, time-indexed, for the processes
//! beside fulcrumd that pair camera frames with encoder readings (`comanip-calib live`,
//! `comanip-track live`).
//!
//! The listener opens **its own** SocketCAN socket on the bus fulcrumd drives (or reads any
//! [`CanBus`], e.g. a candump log through [`hw_io::can::ReplayBus`] in tests) and **never
//! sends**: no SYNC, no NMT, nothing that could disturb the loop. It decodes
//!
//! - the **tool arm** (fulcrumd's encoder nodes, default 1-3): the bus cut into cycles the way
//!   `fulcrumd replay` cuts a candump log ([`CycleCutter`], shared with
//!   [`crate::replay::replay_candump_reader`]): a SYNC opens a cycle, the TPDOs are collected
//!   by fulcrumd's own [`Acquisition`] until every node answered or `loop.frame_deadline_us`
//!   passed; a complete cycle without an invalidating health flag (stale node, EMCY, lost
//!   heartbeat, bus error) gives the six joints, radians, stamped with the cycle's SYNC;
//! - the **endoscope-holder arm** (nodes 4 and 5, every 10th SYNC; `docs/can-protocol.md`):
//!   each pair of its two TPDOs decoded with the arm's encoder model ([`EndoscopeDecoder`],
//!   shared with [`crate::replay::endoscope_joints`]) to `[yaw rad, pitch rad, insertion m,
//!   roll rad]`, stamped with the later TPDO's time;
//!
//! and keeps each arm's last [`ListenConfig::history`] samples in a bounded ring
//! ([`JointHistory`]: fixed capacity, allocated once, the oldest dropped).
//!
//! ## Clocks
//! Samples are stamped with the CAN receive times: **`CLOCK_REALTIME` nanoseconds** (the
//! kernel's `SO_TIMESTAMPNS`, Unix time; candump logs carry the same). Camera frames are
//! stamped on `CLOCK_MONOTONIC`: convert a frame's time with [`bus_time_ns`] and
//! [`hw_io::frame::realtime_minus_monotonic_ns`] (sampled near the frame's time) before asking.
//!
//! ## Asking "the joints at time t"
//! [`JointHistory::at`] (and [`BusDecoder::tool_at`] / [`BusDecoder::endoscope_at`],
//! [`ListenerThread::tool_at`] / [`ListenerThread::endoscope_at`]) answers with a [`JointsAt`]:
//! - between two samples: linear interpolation, refused ([`JointsAtError::Gap`]) when the two
//!   are more than [`Staleness::max_gap_ns`] apart (an arm that stopped answering between them);
//! - after the newest sample: the newest held, refused ([`JointsAtError::Stale`]) when it is
//!   more than [`Staleness::max_age_ns`] older than `t` (an arm that stopped answering, or a
//!   listener that fell behind);
//! - before the oldest sample kept: [`JointsAtError::BeforeHistory`]; no sample at all:
//!   [`JointsAtError::NoData`].
//!
//! ## Use
//! - Single-threaded, poll-driven: [`BusListener`] (`open` a SocketCAN interface, `open_for`
//!   it with kernel filters for some arms only, or wrap any [`CanBus`]; [`BusListener::poll`]
//!   drains what arrived), its [`BusDecoder`] answers.
//! - On its own thread: [`ListenerThread::spawn`] (what the live processes use: frames are read
//!   while the caller runs its detector), answered under a mutex.
//! - Offline or in tests: [`BusDecoder::on_frame`] fed with [`TimedFrame`]s.
//!
//! ## Stability
//! The public API of this module (the types and functions above, their fields and error
//! variants) is relied on by `comanip-calib live` and `comanip-track live`: extend it, do not
//! change it.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use hw_io::can::{CanBus, CanFrame, EncoderConfig, JOINTS, Message, RecvError, SYNC_COB_ID, SocketCanBus, TimedFrame};
use hw_io::ipc::HealthFlags;
use sim::endoscope_arm::{ECM_JOINTS, EndoscopeArmConfig};

use crate::config::Config;
use crate::cycle::{Acquisition, AcquisitionError, AcquisitionStats, CycleInput};
use crate::health::HealthConfig;

/// Default samples kept per arm: 4096 (4.1 s of the tool arm at 1 kHz, 41 s of the endoscope
/// arm at 100 Hz).
pub const DEFAULT_HISTORY: usize = 4096;

/// Most frames [`ListenerThread`] decodes under one lock.
const THREAD_BATCH: usize = 64;

/// Which arm.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Arm {
    /// The tool arm (fulcrumd's encoder nodes; six joints, radians).
    Tool,
    /// The endoscope-holder arm (nodes 4 and 5; yaw rad, pitch rad, insertion m, roll rad).
    Endoscope,
}

/// How old or sparse the samples around a time may be.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Staleness {
    /// Two samples more than this apart (nanoseconds) are not interpolated between.
    pub max_gap_ns: u64,
    /// The newest sample is held for a time at most this much after it (nanoseconds).
    pub max_age_ns: u64,
}

impl Staleness {
    /// The tool arm answers every SYNC (1 ms): 5 ms between samples, 20 ms of age.
    pub const TOOL: Self = Self { max_gap_ns: 5_000_000, max_age_ns: 20_000_000 };
    /// The endoscope arm answers every 10th SYNC (10 ms): 25 ms between samples (as
    /// `comanip-calib from-run`), 50 ms of age.
    pub const ENDOSCOPE: Self = Self { max_gap_ns: 25_000_000, max_age_ns: 50_000_000 };
}

/// How a [`JointsAt`] was obtained.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JointsKind {
    /// Linearly interpolated between the samples just before and just after the time.
    Interpolated,
    /// A sample at exactly that time.
    Exact,
    /// The newest sample, held (the time is after it, within [`Staleness::max_age_ns`]).
    Held,
}

/// An arm's joints at a time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointsAt<const N: usize> {
    /// Joints (tool: radians; endoscope: yaw rad, pitch rad, insertion m, roll rad).
    pub joints: [f64; N],
    /// How they were obtained.
    pub kind: JointsKind,
    /// Time of the sample at or just before the time asked, nanoseconds (`CLOCK_REALTIME`).
    pub before_ns: u64,
    /// Time of the sample just after it, when interpolated, nanoseconds (`CLOCK_REALTIME`).
    pub after_ns: Option<u64>,
    /// Time asked minus `before_ns`, nanoseconds: how old the data are at that time.
    pub age_ns: u64,
}

/// Why an arm's joints at a time cannot be given.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum JointsAtError {
    /// Nothing received from that arm yet (or nothing valid).
    #[error("no joint sample received yet")]
    NoData,
    /// The time is before the oldest sample kept.
    #[error("time {t_ns} ns is before the oldest sample kept ({oldest_ns} ns)")]
    BeforeHistory {
        /// The time asked, nanoseconds.
        t_ns: u64,
        /// The oldest sample's time, nanoseconds.
        oldest_ns: u64,
    },
    /// The two samples around the time are too far apart.
    #[error("the samples around the time are {gap_ns} ns apart (at most {max_ns} ns)")]
    Gap {
        /// Their distance, nanoseconds.
        gap_ns: u64,
        /// The allowed distance, nanoseconds.
        max_ns: u64,
    },
    /// The newest sample is too old at that time.
    #[error("the newest sample is {age_ns} ns older than the time (at most {max_ns} ns)")]
    Stale {
        /// Its age at the time, nanoseconds.
        age_ns: u64,
        /// The allowed age, nanoseconds.
        max_ns: u64,
    },
}

/// A bounded, time-ordered history of one arm's joints: fixed capacity (allocated once), the
/// oldest sample dropped when full. Times are nanoseconds (`CLOCK_REALTIME` for bus samples).
#[derive(Clone, Debug)]
pub struct JointHistory<const N: usize> {
    samples: VecDeque<(u64, [f64; N])>,
    capacity: usize,
    out_of_order: u64,
}

impl<const N: usize> JointHistory<N> {
    /// An empty history of at most `capacity` samples (at least 2).
    pub fn new(capacity: usize) -> Self {
        let capacity = capacity.max(2);
        Self { samples: VecDeque::with_capacity(capacity), capacity, out_of_order: 0 }
    }

    /// Appends a sample at `t_ns`. A sample older than the newest one, or with a non-finite
    /// joint, is not kept (counted in [`JointHistory::refused`]); one at the newest's time
    /// replaces it.
    pub fn push(&mut self, t_ns: u64, joints: [f64; N]) {
        if joints.iter().any(|v| !v.is_finite()) {
            self.out_of_order += 1;
            return;
        }
        match self.samples.back_mut() {
            Some(last) if t_ns < last.0 => {
                self.out_of_order += 1;
                return;
            }
            Some(last) if t_ns == last.0 => {
                last.1 = joints;
                return;
            }
            _ => {}
        }
        if self.samples.len() == self.capacity {
            self.samples.pop_front();
        }
        self.samples.push_back((t_ns, joints));
    }

    /// Samples held.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// True when no sample is held.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Most samples held.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Samples not kept: older than the newest, or not finite.
    pub fn refused(&self) -> u64 {
        self.out_of_order
    }

    /// The newest sample (time in nanoseconds, joints).
    pub fn latest(&self) -> Option<(u64, [f64; N])> {
        self.samples.back().copied()
    }

    /// The oldest sample kept (time in nanoseconds, joints).
    pub fn oldest(&self) -> Option<(u64, [f64; N])> {
        self.samples.front().copied()
    }

    /// The joints at `t_ns` (module docs: interpolated between the two samples around it,
    /// the newest held after it, each within `staleness`).
    pub fn at(&self, t_ns: u64, staleness: &Staleness) -> Result<JointsAt<N>, JointsAtError> {
        let (Some(&first), Some(&last)) = (self.samples.front(), self.samples.back()) else {
            return Err(JointsAtError::NoData);
        };
        if t_ns < first.0 {
            return Err(JointsAtError::BeforeHistory { t_ns, oldest_ns: first.0 });
        }
        if t_ns >= last.0 {
            let age_ns = t_ns - last.0;
            if age_ns > staleness.max_age_ns {
                return Err(JointsAtError::Stale { age_ns, max_ns: staleness.max_age_ns });
            }
            let kind = if age_ns == 0 { JointsKind::Exact } else { JointsKind::Held };
            return Ok(JointsAt { joints: last.1, kind, before_ns: last.0, after_ns: None, age_ns });
        }
        // first.0 <= t < last.0: the first sample after t exists and is not the first.
        let j = self.samples.partition_point(|s| s.0 <= t_ns);
        let (Some(&a), Some(&b)) = (j.checked_sub(1).and_then(|i| self.samples.get(i)), self.samples.get(j)) else {
            return Err(JointsAtError::NoData);
        };
        if a.0 == t_ns {
            return Ok(JointsAt { joints: a.1, kind: JointsKind::Exact, before_ns: a.0, after_ns: None, age_ns: 0 });
        }
        let gap_ns = b.0 - a.0;
        if gap_ns > staleness.max_gap_ns {
            return Err(JointsAtError::Gap { gap_ns, max_ns: staleness.max_gap_ns });
        }
        let s = (t_ns - a.0) as f64 / gap_ns as f64;
        let mut joints = a.1;
        for (q, qb) in joints.iter_mut().zip(b.1) {
            *q += s * (qb - *q);
        }
        Ok(JointsAt { joints, kind: JointsKind::Interpolated, before_ns: a.0, after_ns: Some(b.0), age_ns: t_ns - a.0 })
    }
}

/// A frame's `CLOCK_MONOTONIC` time (nanoseconds) on the bus clock (`CLOCK_REALTIME`
/// nanoseconds), given `realtime − monotonic` ([`hw_io::frame::realtime_minus_monotonic_ns`]);
/// `None` when it falls outside `u64`.
pub fn bus_time_ns(monotonic_ns: u64, realtime_minus_monotonic_ns: i128) -> Option<u64> {
    u64::try_from(i128::from(monotonic_ns) + realtime_minus_monotonic_ns).ok()
}

/// Cuts a stream of bus frames into fulcrumd's cycles, the way `fulcrumd replay` cuts a candump
/// log: a SYNC opens a cycle; TPDOs are taken by [`Acquisition`] until every node answered or
/// `deadline_us` after the SYNC (by the frames' timestamps); later frames are "between
/// cycles" (late TPDOs counted, EMCY and heartbeats applied).
#[derive(Clone, Copy, Debug)]
pub struct CycleCutter {
    acq: Acquisition,
    deadline_us: u64,
    /// The open cycle's SYNC time, microseconds.
    open: Option<u64>,
}

/// One cycle closed by [`CycleCutter`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CutCycle {
    /// Time of the cycle's SYNC, microseconds (the frames' clock: Unix time on a bus).
    pub sync_us: u64,
    /// What acquisition made of the cycle's frames.
    pub input: CycleInput,
}

impl CycleCutter {
    /// A cutter with fulcrumd's acquisition of `encoders` / `health`, ignoring the other nodes
    /// `other_node_ids` (the endoscope arm's), closing cycles `deadline_us` after their SYNC.
    pub fn new(
        encoders: &EncoderConfig,
        health: HealthConfig,
        other_node_ids: &[u8],
        deadline_us: u32,
    ) -> Result<Self, AcquisitionError> {
        let acq = Acquisition::new(encoders, health)?.with_other_nodes(other_node_ids);
        Ok(Self { acq, deadline_us: u64::from(deadline_us), open: None })
    }

    /// The cutter of fulcrumd's configuration `cfg`.
    pub fn from_config(cfg: &Config) -> Result<Self, AcquisitionError> {
        Self::new(&cfg.bus.encoder, cfg.health, &cfg.bus.other_node_ids, cfg.cycle.frame_deadline_us)
    }

    /// Acquisition's counters so far.
    pub fn stats(&self) -> &AcquisitionStats {
        self.acq.stats()
    }

    /// Feeds one frame received at `t_us` (microseconds, non-decreasing); returns the cycle it
    /// closed, if any (at most one per frame).
    pub fn on_frame(&mut self, frame: &CanFrame, t_us: u64) -> Option<CutCycle> {
        let is_sync = !frame.is_extended() && frame.id().raw() == u32::from(SYNC_COB_ID);
        let mut closed = None;
        if let Some(sync_us) = self.open
            && (is_sync || t_us > sync_us.saturating_add(self.deadline_us))
        {
            closed = Some(self.close(sync_us, sync_us.saturating_add(self.deadline_us)));
        }
        if is_sync {
            self.acq.start_cycle();
            self.open = Some(t_us);
            return closed;
        }
        match self.open {
            Some(sync_us) => {
                self.acq.on_frame(frame, t_us.saturating_mul(1000));
                if self.acq.is_complete() {
                    closed = Some(self.close(sync_us, t_us));
                }
            }
            None => self.acq.on_frame_between_cycles(frame, t_us.saturating_mul(1000)),
        }
        closed
    }

    /// Closes the open cycle at its deadline (the end of a log); `None` when none is open.
    pub fn finish(&mut self) -> Option<CutCycle> {
        let sync_us = self.open?;
        Some(self.close(sync_us, sync_us.saturating_add(self.deadline_us)))
    }

    fn close(&mut self, sync_us: u64, end_us: u64) -> CutCycle {
        self.open = None;
        CutCycle { sync_us, input: self.acq.end_cycle(end_us.saturating_mul(1000), false) }
    }
}

/// Decodes the endoscope-holder arm's joints from its two nodes' TPDOs: a pair (one TPDO of
/// each node, less than 1 ms apart) gives `[yaw rad, pitch rad, insertion m, roll rad]` with the
/// arm's encoder model, stamped with the later TPDO's time.
#[derive(Clone, Debug)]
pub struct EndoscopeDecoder {
    arm: EndoscopeArmConfig,
    pending: [Option<(u64, [i32; 2])>; 2],
}

impl EndoscopeDecoder {
    /// A decoder for the arm `arm` (its node IDs and encoder resolutions).
    pub fn new(arm: &EndoscopeArmConfig) -> Self {
        Self { arm: arm.clone(), pending: [None, None] }
    }

    /// Feeds one frame received at `t_ns` (nanoseconds); returns the joints when it completes
    /// a pair (time in nanoseconds, joints).
    pub fn on_frame(&mut self, frame: &CanFrame, t_ns: u64) -> Option<(u64, [f64; ECM_JOINTS])> {
        let Ok(Message::Tpdo { node, counts }) = Message::decode(frame) else { return None };
        let k = self.arm.node_ids.iter().position(|&n| n == node.get())?;
        if let Some(slot) = self.pending.get_mut(k) {
            *slot = Some((t_ns, counts));
        }
        if let [Some((t0, a)), Some((t1, b))] = self.pending
            && t0.abs_diff(t1) < 1_000_000
        {
            self.pending = [None, None];
            return Some((t0.max(t1), self.arm.counts_to_joints(&[a[0], a[1], b[0], b[1]])));
        }
        None
    }
}

/// What a [`BusDecoder`] needs: fulcrumd's bus settings and the endoscope arm's encoder model.
#[derive(Clone, Debug)]
pub struct ListenConfig {
    /// The tool arm's encoder nodes and counts-to-radians conversion (`bus.encoder`).
    pub encoders: EncoderConfig,
    /// Health thresholds of the tool arm's nodes (`[health]`).
    pub health: HealthConfig,
    /// Cycle collection window after a SYNC, microseconds (`loop.frame_deadline_us`).
    pub frame_deadline_us: u32,
    /// The endoscope arm's nodes and resolutions (its node IDs are ignored by the tool arm's
    /// acquisition).
    pub endoscope: EndoscopeArmConfig,
    /// Samples kept per arm (ring capacity; at least 2).
    pub history: usize,
    /// Kernel receive queue asked for on a SocketCAN socket, bytes (0: the system default).
    pub receive_buffer_bytes: usize,
}

impl ListenConfig {
    /// The settings of fulcrumd's configuration `cfg` with the default endoscope arm and
    /// [`DEFAULT_HISTORY`].
    pub fn from_daemon(cfg: &Config) -> Self {
        Self {
            encoders: cfg.bus.encoder,
            health: cfg.health,
            frame_deadline_us: cfg.cycle.frame_deadline_us,
            endoscope: EndoscopeArmConfig::default(),
            history: DEFAULT_HISTORY,
            receive_buffer_bytes: cfg.bus.receive_buffer_bytes,
        }
    }
}

impl Default for ListenConfig {
    fn default() -> Self {
        Self::from_daemon(&Config::default())
    }
}

/// Counters of a listener, since it started.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ListenStats {
    /// Frames decoded.
    pub frames: u64,
    /// Tool-arm cycles closed.
    pub tool_cycles: u64,
    /// Tool-arm cycles kept as samples (complete, no invalidating flag).
    pub tool_samples: u64,
    /// Endoscope joint samples decoded.
    pub endoscope_samples: u64,
    /// Error frames and receive errors.
    pub errors: u64,
    /// Frames the kernel dropped from the listener's receive queue (when the backend tells).
    pub dropped_rx_frames: u64,
}

/// Why a [`BusDecoder`] / [`BusListener`] cannot be built.
#[derive(Debug, thiserror::Error)]
pub enum ListenError {
    /// The tool arm's encoder configuration is invalid.
    #[error(transparent)]
    Acquisition(#[from] AcquisitionError),
    /// The endoscope arm's configuration is invalid.
    #[error("endoscope arm: {0}")]
    Endoscope(#[from] sim::endoscope_arm::EndoscopeArmConfigError),
    /// The SocketCAN interface cannot be opened.
    #[error(transparent)]
    Open(#[from] hw_io::can::OpenError),
    /// The listener thread cannot be started.
    #[error("cannot start the bus listener thread: {0}")]
    Thread(#[source] std::io::Error),
}

/// Frames → both arms' joint histories (no I/O; [`BusListener`] and [`ListenerThread`] feed it).
#[derive(Clone, Debug)]
pub struct BusDecoder {
    cutter: CycleCutter,
    ecm: EndoscopeDecoder,
    encoders: EncoderConfig,
    tool: JointHistory<JOINTS>,
    endoscope: JointHistory<ECM_JOINTS>,
    stats: ListenStats,
}

impl BusDecoder {
    /// A decoder for `cfg`.
    pub fn new(cfg: &ListenConfig) -> Result<Self, ListenError> {
        cfg.endoscope.validate(&cfg.encoders.node_ids)?;
        let cutter = CycleCutter::new(&cfg.encoders, cfg.health, &cfg.endoscope.node_ids, cfg.frame_deadline_us)?;
        Ok(Self {
            cutter,
            ecm: EndoscopeDecoder::new(&cfg.endoscope),
            encoders: cfg.encoders,
            tool: JointHistory::new(cfg.history),
            endoscope: JointHistory::new(cfg.history),
            stats: ListenStats::default(),
        })
    }

    /// Feeds one received frame (its `unix_time_us`: `CLOCK_REALTIME` microseconds).
    pub fn on_frame(&mut self, frame: &TimedFrame) {
        self.stats.frames += 1;
        let t_us = frame.unix_time_us;
        if let Some(c) = self.cutter.on_frame(&frame.frame, t_us) {
            self.on_cycle(c);
        }
        if let Some((t, q)) = self.ecm.on_frame(&frame.frame, t_us.saturating_mul(1000)) {
            self.stats.endoscope_samples += 1;
            self.endoscope.push(t, q);
        }
    }

    fn on_cycle(&mut self, c: CutCycle) {
        self.stats.tool_cycles += 1;
        let complete = c.input.received_mask == (1u8 << hw_io::can::ENCODER_NODES) - 1;
        if complete && !c.input.flags.intersects(HealthFlags::INVALIDATING) {
            self.stats.tool_samples += 1;
            self.tool.push(c.sync_us.saturating_mul(1000), self.encoders.counts_to_rad(&c.input.counts));
        }
    }

    /// Counts a receive error (an error frame, an I/O error).
    pub fn on_error(&mut self) {
        self.stats.errors += 1;
    }

    /// The tool arm's joints (radians) at `t_ns` (`CLOCK_REALTIME` nanoseconds).
    pub fn tool_at(&self, t_ns: u64, staleness: &Staleness) -> Result<JointsAt<JOINTS>, JointsAtError> {
        self.tool.at(t_ns, staleness)
    }

    /// The endoscope arm's joints (yaw rad, pitch rad, insertion m, roll rad) at `t_ns`
    /// (`CLOCK_REALTIME` nanoseconds).
    pub fn endoscope_at(&self, t_ns: u64, staleness: &Staleness) -> Result<JointsAt<ECM_JOINTS>, JointsAtError> {
        self.endoscope.at(t_ns, staleness)
    }

    /// The tool arm's history.
    pub fn tool(&self) -> &JointHistory<JOINTS> {
        &self.tool
    }

    /// The endoscope arm's history.
    pub fn endoscope(&self) -> &JointHistory<ECM_JOINTS> {
        &self.endoscope
    }

    /// The tool arm's acquisition counters (malformed, foreign, late frames...).
    pub fn acquisition(&self) -> &AcquisitionStats {
        self.cutter.stats()
    }

    /// The listener's counters.
    pub fn stats(&self) -> ListenStats {
        self.stats
    }
}

/// A passive listener on a bus: reads frames, never sends.
#[derive(Debug)]
pub struct BusListener<B: CanBus> {
    bus: B,
    decoder: BusDecoder,
    ended: bool,
}

impl BusListener<SocketCanBus> {
    /// Opens its own SocketCAN socket on `iface` (receive queue `cfg.receive_buffer_bytes`).
    pub fn open(iface: &str, cfg: &ListenConfig) -> Result<Self, ListenError> {
        let mut bus = SocketCanBus::open(iface)?;
        if cfg.receive_buffer_bytes > 0 {
            // A smaller queue than asked only risks drops, which are counted.
            let _ = bus.set_receive_buffer(cfg.receive_buffer_bytes);
        }
        Self::new(bus, cfg)
    }
}

impl BusListener<SocketCanBus> {
    /// Opens its own SocketCAN socket on `iface` for the frames of `arms` only (kernel filters:
    /// the others never reach the listener, so reading the endoscope arm alone costs its 2 TPDOs
    /// every 10th SYNC instead of the whole bus). The tool arm needs the SYNCs, its nodes'
    /// TPDOs, heartbeats and EMCYs; the endoscope arm its two nodes' TPDOs. The histories of the
    /// arms left out stay empty ([`JointsAtError::NoData`]).
    pub fn open_for(iface: &str, cfg: &ListenConfig, arms: &[Arm]) -> Result<Self, ListenError> {
        let mut l = Self::open(iface, cfg)?;
        let mut ids: Vec<u16> = Vec::new();
        if arms.contains(&Arm::Tool) {
            ids.push(hw_io::can::SYNC_COB_ID);
            for &n in &cfg.encoders.node_ids {
                let n = u16::from(n);
                ids.extend([hw_io::can::TPDO1_COB_ID_BASE + n, hw_io::can::HEARTBEAT_COB_ID_BASE + n]);
                ids.push(hw_io::can::EMCY_COB_ID_BASE + n);
            }
        }
        if arms.contains(&Arm::Endoscope) {
            ids.extend(cfg.endoscope.node_ids.iter().map(|&n| hw_io::can::TPDO1_COB_ID_BASE + u16::from(n)));
        }
        l.bus
            .set_receive_filter(&ids)
            .map_err(|source| ListenError::Open(hw_io::can::OpenError::Io { interface: iface.to_owned(), source }))?;
        Ok(l)
    }
}

impl<B: CanBus> BusListener<B> {
    /// A listener on `bus` (any backend: a candump log through `ReplayBus` in tests).
    pub fn new(bus: B, cfg: &ListenConfig) -> Result<Self, ListenError> {
        Ok(Self { bus, decoder: BusDecoder::new(cfg)?, ended: false })
    }

    /// Waits at most `timeout` for a first frame, then takes every frame already queued (at
    /// most `max_frames`); returns how many were decoded. Receive errors are counted, never
    /// returned; the end of a replayed log sets [`BusListener::ended`].
    pub fn poll(&mut self, timeout: Duration, max_frames: usize) -> usize {
        let mut n = 0;
        let mut wait = timeout;
        while n < max_frames && !self.ended {
            match self.bus.recv_timeout(wait) {
                Ok(Some(f)) => {
                    self.decoder.on_frame(&f);
                    n += 1;
                }
                Ok(None) => break,
                Err(RecvError::EndOfReplay) => self.ended = true,
                Err(_) => {
                    self.decoder.on_error();
                    break;
                }
            }
            wait = Duration::ZERO;
        }
        self.decoder.stats.dropped_rx_frames = self.bus.dropped_rx_frames();
        n
    }

    /// True once a replayed log has no more frames (never for a live bus).
    pub fn ended(&self) -> bool {
        self.ended
    }

    /// The decoder: both arms' histories.
    pub fn decoder(&self) -> &BusDecoder {
        &self.decoder
    }
}

/// A [`BusListener`] on its own thread; the histories are read under a mutex.
#[derive(Debug)]
pub struct ListenerThread {
    shared: Arc<Mutex<BusDecoder>>,
    stop: Arc<AtomicBool>,
    ended: Arc<AtomicBool>,
    handle: Option<JoinHandle<()>>,
}

impl ListenerThread {
    /// Opens `iface` ([`BusListener::open`]) and listens on a thread named `bus-listen`.
    pub fn open(iface: &str, cfg: &ListenConfig) -> Result<Self, ListenError> {
        Self::spawn(BusListener::open(iface, cfg)?)
    }

    /// Opens `iface` for the frames of `arms` only ([`BusListener::open_for`]) and listens on a
    /// thread named `bus-listen`.
    pub fn open_for(iface: &str, cfg: &ListenConfig, arms: &[Arm]) -> Result<Self, ListenError> {
        Self::spawn(BusListener::open_for(iface, cfg, arms)?)
    }

    /// Runs `listener` on a thread until [`ListenerThread::stop`] (or drop), or the end of a
    /// replayed log. Receive errors are counted ([`ListenStats::errors`]) and retried every
    /// 20 ms (an interface that is down may come back).
    pub fn spawn<B: CanBus + Send + 'static>(listener: BusListener<B>) -> Result<Self, ListenError> {
        let BusListener { mut bus, decoder, ended: already_ended } = listener;
        let shared = Arc::new(Mutex::new(decoder));
        let stop = Arc::new(AtomicBool::new(false));
        let ended = Arc::new(AtomicBool::new(already_ended));
        let (s, st, en) = (Arc::clone(&shared), Arc::clone(&stop), Arc::clone(&ended));
        let handle = std::thread::Builder::new()
            .name("bus-listen".into())
            .spawn(move || {
                // Frames are taken in batches and decoded under one lock.
                let mut batch: Vec<TimedFrame> = Vec::with_capacity(THREAD_BATCH);
                while !st.load(Ordering::Relaxed) && !en.load(Ordering::Relaxed) {
                    let mut error = false;
                    let mut wait = Duration::from_millis(50);
                    while batch.len() < THREAD_BATCH {
                        match bus.recv_timeout(wait) {
                            Ok(Some(f)) => batch.push(f),
                            Ok(None) => break,
                            Err(RecvError::EndOfReplay) => {
                                en.store(true, Ordering::Relaxed);
                                break;
                            }
                            Err(_) => {
                                error = true;
                                break;
                            }
                        }
                        wait = Duration::ZERO;
                    }
                    {
                        let mut d = s.lock().unwrap_or_else(PoisonError::into_inner);
                        for f in &batch {
                            d.on_frame(f);
                        }
                        if error {
                            d.on_error();
                        }
                        d.stats.dropped_rx_frames = bus.dropped_rx_frames();
                    }
                    batch.clear();
                    if error {
                        // A bus that is down: retry without spinning.
                        std::thread::sleep(Duration::from_millis(20));
                    }
                }
                en.store(true, Ordering::Relaxed);
            })
            .map_err(ListenError::Thread)?;
        Ok(Self { shared, stop, ended, handle: Some(handle) })
    }

    fn with<T>(&self, f: impl FnOnce(&BusDecoder) -> T) -> T {
        f(&self.shared.lock().unwrap_or_else(PoisonError::into_inner))
    }

    /// The tool arm's joints (radians) at `t_ns` (`CLOCK_REALTIME` nanoseconds).
    pub fn tool_at(&self, t_ns: u64, staleness: &Staleness) -> Result<JointsAt<JOINTS>, JointsAtError> {
        self.with(|d| d.tool_at(t_ns, staleness))
    }

    /// The endoscope arm's joints (yaw rad, pitch rad, insertion m, roll rad) at `t_ns`
    /// (`CLOCK_REALTIME` nanoseconds).
    pub fn endoscope_at(&self, t_ns: u64, staleness: &Staleness) -> Result<JointsAt<ECM_JOINTS>, JointsAtError> {
        self.with(|d| d.endoscope_at(t_ns, staleness))
    }

    /// The newest sample's time of each arm (tool, endoscope), nanoseconds (`CLOCK_REALTIME`).
    pub fn latest_ns(&self) -> (Option<u64>, Option<u64>) {
        self.with(|d| (d.tool.latest().map(|s| s.0), d.endoscope.latest().map(|s| s.0)))
    }

    /// The listener's counters.
    pub fn stats(&self) -> ListenStats {
        self.with(BusDecoder::stats)
    }

    /// A copy of the decoder (both histories) as it is now.
    pub fn snapshot(&self) -> BusDecoder {
        self.with(Clone::clone)
    }

    /// True once the thread has stopped (stop asked, or the end of a replayed log).
    pub fn ended(&self) -> bool {
        self.ended.load(Ordering::Relaxed)
    }

    /// Stops the thread and waits for it (at most one receive timeout, 50 ms).
    pub fn stop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

impl Drop for ListenerThread {
    fn drop(&mut self) {
        self.stop();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hw_io::can::{NodeId, Pacing, ReplayBus, SyncSource};

    fn n(k: u8) -> NodeId {
        NodeId::new(k).unwrap()
    }

    fn tf(m: Message, t_us: u64) -> TimedFrame {
        TimedFrame { frame: m.encode().unwrap(), unix_time_us: t_us }
    }

    #[test]
    fn history_interpolates_holds_and_refuses_with_reasons() {
        let mut h = JointHistory::<2>::new(4);
        let st = Staleness { max_gap_ns: 10, max_age_ns: 5 };
        assert_eq!(h.at(0, &st), Err(JointsAtError::NoData));
        h.push(100, [0.0, 1.0]);
        h.push(110, [1.0, 3.0]);
        let a = h.at(104, &st).unwrap();
        assert_eq!(a.kind, JointsKind::Interpolated);
        assert!((a.joints[0] - 0.4).abs() < 1e-12 && (a.joints[1] - 1.8).abs() < 1e-12);
        assert_eq!((a.before_ns, a.after_ns, a.age_ns), (100, Some(110), 4));
        assert_eq!(h.at(110, &st).unwrap().kind, JointsKind::Exact);
        assert_eq!(h.at(100, &st).unwrap().joints, [0.0, 1.0]);
        let held = h.at(115, &st).unwrap();
        assert_eq!((held.kind, held.joints, held.age_ns), (JointsKind::Held, [1.0, 3.0], 5));
        assert_eq!(h.at(116, &st), Err(JointsAtError::Stale { age_ns: 6, max_ns: 5 }));
        assert_eq!(h.at(99, &st), Err(JointsAtError::BeforeHistory { t_ns: 99, oldest_ns: 100 }));
        h.push(150, [0.0, 0.0]); // 40 ns after: a gap
        assert_eq!(h.at(120, &st), Err(JointsAtError::Gap { gap_ns: 40, max_ns: 10 }));
        // Out of order and non-finite samples are refused and counted.
        h.push(120, [9.0, 9.0]);
        h.push(160, [f64::NAN, 0.0]);
        assert_eq!((h.len(), h.refused()), (3, 2));
    }

    #[test]
    fn history_is_bounded_and_drops_the_oldest() {
        let mut h = JointHistory::<1>::new(3);
        for t in 0..10u64 {
            h.push(t, [t as f64]);
            assert!(h.len() <= 3);
        }
        assert_eq!(h.oldest(), Some((7, [7.0])));
        assert_eq!(h.latest(), Some((9, [9.0])));
        assert_eq!(h.capacity(), 3);
        assert!(matches!(h.at(5, &Staleness::TOOL), Err(JointsAtError::BeforeHistory { .. })));
    }

    #[test]
    fn bus_time_adds_the_offset_and_refuses_overflow() {
        assert_eq!(bus_time_ns(1_000, 5_000), Some(6_000));
        assert_eq!(bus_time_ns(1_000, -500), Some(500));
        assert_eq!(bus_time_ns(1_000, -5_000), None);
        assert_eq!(bus_time_ns(u64::MAX, 1), None);
    }

    /// A bus of `cycles` SYNCs 1 ms apart from t0: the tool arm's three nodes answer each
    /// (joint 1 = cycle index counts), the endoscope arm's every 10th (yaw = index counts),
    /// unless `tool_silent_from` / `ecm_silent_from` say otherwise; heartbeats every 100.
    fn bus(cycles: u64, tool_silent_from: u64, ecm_silent_from: u64) -> Vec<TimedFrame> {
        let t0 = 1_700_000_000_000_000u64;
        let mut sync = SyncSource::new();
        let mut out = Vec::new();
        for c in 0..cycles {
            let t = t0 + c * 1000;
            out.push(TimedFrame { frame: sync.next_frame(), unix_time_us: t });
            if c % 100 == 0 {
                for k in 1..=5 {
                    let hb = Message::Heartbeat { node: n(k), state: hw_io::can::NmtState::Operational };
                    out.push(tf(hb, t + 10));
                }
            }
            if c < tool_silent_from {
                for k in 1..=3u8 {
                    out.push(tf(Message::Tpdo { node: n(k), counts: [c as i32, 0] }, t + 100 + u64::from(k)));
                }
            }
            if c % 10 == 0 && c < ecm_silent_from {
                out.push(tf(Message::Tpdo { node: n(4), counts: [c as i32, 0] }, t + 200));
                out.push(tf(Message::Tpdo { node: n(5), counts: [0, 0] }, t + 201));
            }
        }
        out
    }

    #[test]
    fn a_replayed_bus_gives_both_arms_at_a_time_and_staleness_when_an_arm_stops() {
        let frames = bus(500, 300, 200);
        let t0 = frames[0].unix_time_us * 1000;
        let cfg = ListenConfig { history: 100, ..ListenConfig::default() };
        let mut l = BusListener::new(ReplayBus::from_frames(frames, Pacing::AsFastAsPossible), &cfg).unwrap();
        while !l.ended() {
            l.poll(Duration::ZERO, 64);
        }
        let d = l.decoder();
        let s = d.stats();
        assert_eq!(s.tool_samples, 300);
        assert_eq!(s.endoscope_samples, 20);
        assert_eq!(d.tool().len(), 100, "bounded");
        // Tool at 250.5 ms: between cycles 250 and 251.
        let q = d.tool_at(t0 + 250_500_000, &Staleness::TOOL).unwrap();
        assert_eq!(q.kind, JointsKind::Interpolated);
        let (a, b) = (cfg.encoders.joints[0].counts_to_rad(250), cfg.encoders.joints[0].counts_to_rad(251));
        assert!((q.joints[0] - (a + b) / 2.0).abs() < 1e-9, "{}", q.joints[0]);
        // Endoscope at 105 ms: between the TPDO pairs of cycles 100 and 110.
        let e = d.endoscope_at(t0 + 105_201_000, &Staleness::ENDOSCOPE).unwrap();
        let (a, b) = (cfg.endoscope.counts_to_joints(&[100, 0, 0, 0]), cfg.endoscope.counts_to_joints(&[110, 0, 0, 0]));
        assert!((e.joints[0] - (a[0] + b[0]) / 2.0).abs() < 1e-9, "{}", e.joints[0]);
        // The tool arm stopped at cycle 300, the endoscope at 200: stale afterwards.
        assert!(matches!(d.tool_at(t0 + 400_000_000, &Staleness::TOOL), Err(JointsAtError::Stale { .. })));
        assert!(matches!(d.endoscope_at(t0 + 300_000_000, &Staleness::ENDOSCOPE), Err(JointsAtError::Stale { .. })));
        // Before the history kept.
        assert!(matches!(d.tool_at(t0 + 1_000_000, &Staleness::TOOL), Err(JointsAtError::BeforeHistory { .. })));
    }

    #[test]
    fn the_thread_gives_the_same_answers_as_the_decoder() {
        let frames = bus(300, 300, 300);
        let t = frames[0].unix_time_us * 1000 + 150_300_000;
        let cfg = ListenConfig::default();
        let mut direct = BusDecoder::new(&cfg).unwrap();
        for f in &frames {
            direct.on_frame(f);
        }
        let mut th = ListenerThread::spawn(
            BusListener::new(ReplayBus::from_frames(frames, Pacing::AsFastAsPossible), &cfg).unwrap(),
        )
        .unwrap();
        while !th.ended() {
            std::thread::sleep(Duration::from_millis(1));
        }
        assert_eq!(th.tool_at(t, &Staleness::TOOL), direct.tool_at(t, &Staleness::TOOL));
        assert_eq!(th.endoscope_at(t, &Staleness::ENDOSCOPE), direct.endoscope_at(t, &Staleness::ENDOSCOPE));
        assert_eq!(th.stats(), direct.stats());
        th.stop();
    }

    #[test]
    fn garbage_frames_are_counted_never_fatal() {
        let mut d = BusDecoder::new(&ListenConfig::default()).unwrap();
        let junk = [
            CanFrame::new_standard(0x181, &[1, 2, 3]).unwrap(),
            CanFrame::new_standard(0x555, &[0; 8]).unwrap(),
            CanFrame::new_standard(0x184, &[0xff; 8]).unwrap(),
            CanFrame::new_standard(0x080, &[]).unwrap(),
        ];
        for (i, f) in junk.iter().cycle().take(400).enumerate() {
            d.on_frame(&TimedFrame { frame: *f, unix_time_us: i as u64 });
        }
        assert_eq!(d.stats().frames, 400);
        assert!(d.acquisition().wrong_dlc_frames > 0);
        assert!(d.tool().is_empty());
    }

    #[test]
    fn a_bad_endoscope_configuration_is_a_typed_error() {
        let cfg = ListenConfig {
            endoscope: EndoscopeArmConfig { node_ids: [1, 5], ..Default::default() },
            ..Default::default()
        };
        assert!(matches!(BusDecoder::new(&cfg), Err(ListenError::Endoscope(_))));
    }
}
