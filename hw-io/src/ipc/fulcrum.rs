//! The message fulcrumd publishes once per control cycle, and its typed state and health.
//!
//! Two layers, as for CAN (`can::CanFrame` raw, `can::Message` typed):
//! - the wire: [`FulcrumSample`], `#[repr(C)]`, its `state` and `health` plain `u32`s (what a C
//!   subscriber declares; layout version [`FULCRUM_SAMPLE_VERSION`]);
//! - the types Rust code uses: [`OutputState`] (an enum) and [`HealthFlags`] (a bit set),
//!   read from a sample with [`FulcrumSample::state`] and [`FulcrumSample::health`], and
//!   converted back only where a sample is filled in.
//!
//! Units and frames are in each field's doc and in `docs/output.md`.

use core::fmt;

use iceoryx2::prelude::ZeroCopySend;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use super::Message;
use super::message::InvalidMessage;

/// Layout version of [`FulcrumSample`]. Bumped on any change of field, order or meaning.
pub const FULCRUM_SAMPLE_VERSION: u32 = 1;

/// What a cycle's output says: whether it may be used, and whether the instrument is in a
/// trocar. On the wire ([`FulcrumSample::state`]) it is the `u32` of the variant: 0, 1, 2.
///
/// ```
/// use hw_io::ipc::{FulcrumSample, HealthFlags, OutputState};
///
/// # fn main() -> Result<(), Box<dyn core::error::Error>> {
/// let mut sample = FulcrumSample::invalid(HealthFlags::NODE2_STALE);
/// assert_eq!(sample.state()?, OutputState::Invalid);
/// sample.state = OutputState::Inside.into();
/// assert_eq!(sample.state()?, OutputState::Inside);
/// assert_eq!(sample.state()?.to_string(), "INSIDE");
/// sample.state = 7; // a value no version-1 daemon writes
/// assert!(sample.state().is_err());
/// # Ok(()) }
/// ```
///
/// Serialised (serde: flight recordings) as the `u32` of the variant, so a recording holds the
/// same bytes as when the state was a plain `u32`; an unknown value fails to deserialise with
/// [`UnknownState`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(into = "u32", try_from = "u32")]
#[repr(u32)]
pub enum OutputState {
    /// The estimate must not be used (stale, missing or faulty input, or the detector was just
    /// reset). The health flags say why. Wire value 0.
    #[default]
    Invalid = 0,
    /// Valid input, the instrument is not in a trocar. Wire value 1.
    Outside = 1,
    /// Valid input, the instrument passes through trocar `trocar_id`; `fulcrum_base_m` is the
    /// fulcrum (metres, robot base frame). Wire value 2.
    Inside = 2,
}

/// A `state` value that is not an [`OutputState`] (a newer or corrupt writer).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown output state {0} (known: 0 invalid, 1 outside, 2 inside)")]
pub struct UnknownState(pub u32);

impl OutputState {
    /// True for [`Outside`](Self::Outside) and [`Inside`](Self::Inside): the cycle's input was
    /// valid.
    pub const fn is_valid(self) -> bool {
        !matches!(self, Self::Invalid)
    }

    /// True for [`Inside`](Self::Inside).
    pub const fn is_inside(self) -> bool {
        matches!(self, Self::Inside)
    }
}

impl From<OutputState> for u32 {
    fn from(state: OutputState) -> Self {
        state as u32
    }
}

impl TryFrom<u32> for OutputState {
    type Error = UnknownState;

    fn try_from(value: u32) -> Result<Self, Self::Error> {
        match value {
            0 => Ok(Self::Invalid),
            1 => Ok(Self::Outside),
            2 => Ok(Self::Inside),
            other => Err(UnknownState(other)),
        }
    }
}

/// For people: `INVALID`, `outside`, `INSIDE` (the states that need attention in capitals, as
/// fulcrumd's log and `fulcrumd monitor` print them).
impl fmt::Display for OutputState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // `pad`: width and alignment apply (`{:<7}`).
        f.pad(match self {
            Self::Invalid => "INVALID",
            Self::Outside => "outside",
            Self::Inside => "INSIDE",
        })
    }
}

bitflags::bitflags! {
    /// The health of a cycle: one flag per condition; empty means all is well. On the wire
    /// ([`FulcrumSample::health`]) it is the `u32` of its bits (`docs/output.md` lists them).
    ///
    /// "Invalidating" flags ([`HealthFlags::INVALIDATING`]) force the state to
    /// [`OutputState::Invalid`] in the same cycle.
    ///
    /// **Unknown bits** (bits 15..=31, which no version-1 writer sets) are kept, never dropped:
    /// [`FulcrumSample::health`] and deserialisation use `from_bits_retain`, so a sample or a
    /// recording converts back to the same `u32`. They are not invalidating by themselves (the
    /// state field decides validity), [`HealthFlags::unknown`] returns them, and `Display` shows
    /// them as `unknown-0x…`.
    ///
    /// Serialised (serde: flight recordings) as the `u32` of the bits, so a recording holds the
    /// same bytes as when the health was a plain `u32`.
    ///
    /// ```
    /// use hw_io::ipc::HealthFlags;
    ///
    /// let h = HealthFlags::NODE_STALE[1] | HealthFlags::OVERRUN;
    /// assert!(h.intersects(HealthFlags::INVALIDATING));
    /// assert_eq!(h.bits(), 0x0402);
    /// assert_eq!(h.to_string(), "node2-stale,overrun");
    /// assert_eq!(HealthFlags::empty().to_string(), "ok");
    /// ```
    #[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
    pub struct HealthFlags: u32 {
        /// Encoder node 1 (joints 1-2): its TPDO has been missing for at least
        /// `stale_after_cycles` cycles. Bit 0. Invalidating.
        const NODE1_STALE = 1 << 0;
        /// Encoder node 2 (joints 3-4): stale, as [`Self::NODE1_STALE`]. Bit 1. Invalidating.
        const NODE2_STALE = 1 << 1;
        /// Encoder node 3 (joints 5-6): stale, as [`Self::NODE1_STALE`]. Bit 2. Invalidating.
        const NODE3_STALE = 1 << 2;
        /// Encoder node 1: an EMCY with a non-zero error code is active (cleared by an EMCY with
        /// error code 0x0000). Bit 3. Invalidating.
        const NODE1_EMCY = 1 << 3;
        /// Encoder node 2: EMCY active, as [`Self::NODE1_EMCY`]. Bit 4. Invalidating.
        const NODE2_EMCY = 1 << 4;
        /// Encoder node 3: EMCY active, as [`Self::NODE1_EMCY`]. Bit 5. Invalidating.
        const NODE3_EMCY = 1 << 5;
        /// Encoder node 1: its heartbeat stopped (none within the configured timeout) or it
        /// reports a state other than operational. Bit 6. Invalidating.
        const NODE1_HEARTBEAT = 1 << 6;
        /// Encoder node 2: heartbeat lost, as [`Self::NODE1_HEARTBEAT`]. Bit 7. Invalidating.
        const NODE2_HEARTBEAT = 1 << 7;
        /// Encoder node 3: heartbeat lost, as [`Self::NODE1_HEARTBEAT`]. Bit 8. Invalidating.
        const NODE3_HEARTBEAT = 1 << 8;
        /// This cycle lacks at least one TPDO at its deadline (the cycle's data are not used).
        /// Bit 9. Invalidating.
        const INCOMPLETE_CYCLE = 1 << 9;
        /// The previous cycle ran past its period (an overrun). Bit 10. Not invalidating.
        const OVERRUN = 1 << 10;
        /// The SYNC of this cycle could not be sent. Bit 11. Invalidating.
        const SYNC_SEND_FAILED = 1 << 11;
        /// The CAN interface reported an error (error frame, interface down). Bit 12.
        /// Invalidating.
        const BUS_ERROR = 1 << 12;
        /// Forward kinematics or the detector refused this cycle's joint values. Bit 13.
        /// Invalidating.
        const BAD_SAMPLE = 1 << 13;
        /// The detector was reset (a node fault, or a gap of invalid input longer than
        /// `detector.max_gap_s`) and is refilling its window. Bit 14. Not invalidating.
        const DETECTOR_RESET = 1 << 14;
    }
}

impl HealthFlags {
    /// [`Self::NODE1_STALE`], [`Self::NODE2_STALE`], [`Self::NODE3_STALE`]: in joint order,
    /// indexed like the encoder nodes.
    pub const NODE_STALE: [Self; 3] = [Self::NODE1_STALE, Self::NODE2_STALE, Self::NODE3_STALE];
    /// [`Self::NODE1_EMCY`], [`Self::NODE2_EMCY`], [`Self::NODE3_EMCY`].
    pub const NODE_EMCY: [Self; 3] = [Self::NODE1_EMCY, Self::NODE2_EMCY, Self::NODE3_EMCY];
    /// [`Self::NODE1_HEARTBEAT`], [`Self::NODE2_HEARTBEAT`], [`Self::NODE3_HEARTBEAT`].
    pub const NODE_HEARTBEAT: [Self; 3] = [Self::NODE1_HEARTBEAT, Self::NODE2_HEARTBEAT, Self::NODE3_HEARTBEAT];
    /// Every flag that makes the cycle's input invalid (the state is then
    /// [`OutputState::Invalid`]): all but `OVERRUN` and `DETECTOR_RESET` (`0x3BFF`).
    pub const INVALIDATING: Self = Self::all().difference(Self::OVERRUN.union(Self::DETECTOR_RESET));

    /// The bits set that are no known flag (see "Unknown bits" above).
    pub const fn unknown(self) -> Self {
        self.difference(Self::all())
    }
}

/// For people: the set flags' names, comma-separated, `ok` when none: per node `nodeN-stale`,
/// `nodeN-emcy`, `nodeN-heartbeat` (nodes 1..3 in turn), then `incomplete-cycle`, `overrun`,
/// `sync-send-failed`, `bus-error`, `bad-sample`, `detector-reset`, then `unknown-0x…` for
/// unknown bits.
impl fmt::Display for HealthFlags {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        const OTHERS: [(HealthFlags, &str); 6] = [
            (HealthFlags::INCOMPLETE_CYCLE, "incomplete-cycle"),
            (HealthFlags::OVERRUN, "overrun"),
            (HealthFlags::SYNC_SEND_FAILED, "sync-send-failed"),
            (HealthFlags::BUS_ERROR, "bus-error"),
            (HealthFlags::BAD_SAMPLE, "bad-sample"),
            (HealthFlags::DETECTOR_RESET, "detector-reset"),
        ];
        if self.is_empty() {
            return f.write_str("ok");
        }
        let mut first = true;
        let mut sep = |f: &mut fmt::Formatter<'_>| {
            let s = if first { "" } else { "," };
            first = false;
            f.write_str(s)
        };
        for k in 0..3 {
            for (flags, what) in
                [(Self::NODE_STALE, "stale"), (Self::NODE_EMCY, "emcy"), (Self::NODE_HEARTBEAT, "heartbeat")]
            {
                if self.contains(flags[k]) {
                    sep(f)?;
                    write!(f, "node{}-{what}", k + 1)?;
                }
            }
        }
        for (flag, name) in OTHERS {
            if self.contains(flag) {
                sep(f)?;
                f.write_str(name)?;
            }
        }
        if !self.unknown().is_empty() {
            sep(f)?;
            write!(f, "unknown-{:#x}", self.unknown().bits())?;
        }
        Ok(())
    }
}

impl Serialize for HealthFlags {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_u32(self.bits())
    }
}

impl<'de> Deserialize<'de> for HealthFlags {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        u32::deserialize(deserializer).map(Self::from_bits_retain)
    }
}

/// One control cycle's estimate, as published by fulcrumd: the wire layout.
///
/// Every float is finite. Vectors are in the robot base frame; positions in metres. `state`
/// and `health` are the raw `u32`s a C subscriber sees; Rust code reads them typed with
/// [`state`](Self::state) and [`health`](Self::health).
#[derive(Clone, Copy, Debug, PartialEq, ZeroCopySend)]
#[type_name("comanip::FulcrumSample")]
#[repr(C)]
pub struct FulcrumSample {
    /// Layout version, [`FULCRUM_SAMPLE_VERSION`].
    pub version: u32,
    /// The [`OutputState`] as its `u32` (0 invalid, 1 outside, 2 inside); read it with
    /// [`state`](Self::state).
    pub state: u32,
    /// Cycle number since the daemon started (0 for the first cycle). Consecutive samples
    /// differ by one; a jump back means the daemon restarted (see `run_id`).
    pub sequence: u64,
    /// Random identifier of this daemon run: a new value after every (re)start.
    pub run_id: u64,
    /// Instant of this cycle's SYNC, nanoseconds of `CLOCK_MONOTONIC`.
    pub timestamp_ns: u64,
    /// The [`HealthFlags`] as their `u32` bits; read them with [`health`](Self::health).
    pub health: u32,
    /// Trocar identity while inside (see `estimator::trocar::TrocarState`), else 0.
    pub trocar_id: u32,
    /// Fulcrum, metres, robot base frame. Zero unless the state is inside.
    pub fulcrum_base_m: [f64; 3],
    /// Residual of the fit the decision rests on, metres (root-mean-square line distance in
    /// fast mode, mean line distance in paper mode); 0 when there is no fit.
    pub residual_m: f64,
    /// One-sigma uncertainty of the fulcrum along its worst direction, metres; 0 when there
    /// is no fit.
    pub fulcrum_std_m: f64,
    /// Conditioning of the fit, `λ_min(Σ(I − z zᵀ)) / n`, dimensionless in [0, 2/3]; 0 when
    /// there is no fit.
    pub conditioning: f64,
    /// Wrist centre P from forward kinematics, metres, robot base frame (zero when invalid).
    pub wrist_base_m: [f64; 3],
    /// Instrument axis z, unit vector, robot base frame (zero when invalid).
    pub axis_base: [f64; 3],
    /// Joint angles, radians, joints 1..6 (zero when the cycle is incomplete).
    pub joints_rad: [f64; 6],
    /// Lines in the detector's deciding window.
    pub window_fill: u16,
    /// Capacity of that window.
    pub window_len: u16,
    /// Lines in the latest fit (0 when none).
    pub fit_lines: u16,
    /// Reserved, zero.
    pub reserved: u16,
    /// How late this cycle woke up after its deadline, nanoseconds (the period error).
    pub wake_late_ns: u32,
    /// Time from wake-up to the publication of the previous cycle, nanoseconds.
    pub prev_cycle_compute_ns: u32,
}

impl FulcrumSample {
    /// An invalid sample with every field zero except `version`, `state` (invalid) and
    /// `health`.
    pub const fn invalid(health: HealthFlags) -> Self {
        Self {
            version: FULCRUM_SAMPLE_VERSION,
            state: OutputState::Invalid as u32,
            sequence: 0,
            run_id: 0,
            timestamp_ns: 0,
            health: health.bits(),
            trocar_id: 0,
            fulcrum_base_m: [0.0; 3],
            residual_m: 0.0,
            fulcrum_std_m: 0.0,
            conditioning: 0.0,
            wrist_base_m: [0.0; 3],
            axis_base: [0.0; 3],
            joints_rad: [0.0; 6],
            window_fill: 0,
            window_len: 0,
            fit_lines: 0,
            reserved: 0,
            wake_late_ns: 0,
            prev_cycle_compute_ns: 0,
        }
    }

    /// The typed state; [`UnknownState`] for a value that is no [`OutputState`] (not written by
    /// a version-1 daemon: treat the sample as invalid).
    pub fn state(&self) -> Result<OutputState, UnknownState> {
        OutputState::try_from(self.state)
    }

    /// The typed health flags, unknown bits kept (see [`HealthFlags`]).
    pub const fn health(&self) -> HealthFlags {
        HealthFlags::from_bits_retain(self.health)
    }

    /// The fulcrum (metres, robot base frame) when this sample has the right version and is
    /// inside a trocar.
    pub fn fulcrum(&self) -> Option<[f64; 3]> {
        (self.version == FULCRUM_SAMPLE_VERSION && self.state() == Ok(OutputState::Inside))
            .then_some(self.fulcrum_base_m)
    }

    /// True when this sample has the right version and the input of its cycle was valid (the
    /// state is outside or inside; an unknown state is not valid).
    pub fn is_valid(&self) -> bool {
        self.version == FULCRUM_SAMPLE_VERSION && self.state().is_ok_and(OutputState::is_valid)
    }
}

impl Message for FulcrumSample {
    const TYPE_NAME: &'static str = "comanip::FulcrumSample";
    const VERSION: u32 = FULCRUM_SAMPLE_VERSION;
    const PUBLISHER_NODE_NAME: &'static str = "fulcrumd";
    const SUBSCRIBER_NODE_NAME: &'static str = "fulcrum-subscriber";

    fn version(&self) -> u32 {
        self.version
    }

    fn sequence(&self) -> u64 {
        self.sequence
    }

    fn run_id(&self) -> u64 {
        self.run_id
    }

    /// A valid sample (outside or inside) has every float finite and no invalidating flag
    /// (fulcrumd downgrades such an estimate to invalid before it publishes). An invalid sample,
    /// or one with an unknown state, is not checked: its floats mean nothing.
    fn check(&self) -> Result<(), InvalidMessage> {
        if !self.state().is_ok_and(OutputState::is_valid) {
            return Ok(());
        }
        if self.health().intersects(HealthFlags::INVALIDATING) {
            return Err(InvalidMessage { what: "valid state with an invalidating health flag" });
        }
        let finite = self
            .fulcrum_base_m
            .iter()
            .chain(&[self.residual_m, self.fulcrum_std_m, self.conditioning])
            .chain(&self.wrist_base_m)
            .chain(&self.axis_base)
            .chain(&self.joints_rad)
            .all(|v| v.is_finite());
        if !finite {
            return Err(InvalidMessage { what: "valid state with a non-finite float" });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_is_fixed() {
        // 8 + 8*3 (seq, run, ts) + 8 (health, trocar) + 24 + 24 + 24 + 24 + 48 + 8 + 8
        assert_eq!(core::mem::size_of::<FulcrumSample>(), 200);
        assert_eq!(core::mem::align_of::<FulcrumSample>(), 8);
        assert_eq!(core::mem::offset_of!(FulcrumSample, sequence), 8);
        assert_eq!(core::mem::offset_of!(FulcrumSample, fulcrum_base_m), 40);
    }

    #[test]
    fn the_type_name_is_iceoryx2s() {
        // SAFETY: `type_name` only returns the string of `#[type_name(..)]`; its safety contract
        // concerns implementing the trait (the layout), not calling it.
        let iceoryx2_name = unsafe { <FulcrumSample as ZeroCopySend>::type_name() };
        assert_eq!(iceoryx2_name, FulcrumSample::TYPE_NAME);
    }

    #[test]
    fn invalid_has_no_fulcrum() {
        let s = FulcrumSample::invalid(HealthFlags::NODE2_STALE);
        assert!(!s.is_valid());
        assert_eq!(s.fulcrum(), None);
        assert_eq!(s.health(), HealthFlags::NODE2_STALE);
        let mut inside = s;
        inside.state = OutputState::Inside.into();
        inside.fulcrum_base_m = [0.1, 0.2, 0.3];
        assert!(inside.is_valid());
        assert_eq!(inside.fulcrum(), Some([0.1, 0.2, 0.3]));
        inside.version = 99;
        assert_eq!(inside.fulcrum(), None);
        assert!(!inside.is_valid());
    }

    #[test]
    fn state_converts_both_ways_and_refuses_unknown_values() {
        for (state, wire) in [(OutputState::Invalid, 0u32), (OutputState::Outside, 1), (OutputState::Inside, 2)] {
            assert_eq!(u32::from(state), wire);
            assert_eq!(OutputState::try_from(wire), Ok(state));
        }
        assert_eq!(OutputState::try_from(3), Err(UnknownState(3)));
        let mut s = FulcrumSample::invalid(HealthFlags::empty());
        s.state = u32::MAX;
        assert_eq!(s.state(), Err(UnknownState(u32::MAX)));
        assert!(!s.is_valid(), "an unknown state is not valid");
        assert_eq!(s.fulcrum(), None);
        assert!(UnknownState(7).to_string().contains("unknown output state 7"));
    }

    #[test]
    fn invalidating_is_every_flag_but_overrun_and_reset() {
        assert_eq!(HealthFlags::INVALIDATING.bits(), 0x3BFF);
        assert!(!HealthFlags::INVALIDATING.intersects(HealthFlags::OVERRUN | HealthFlags::DETECTOR_RESET));
        for flags in [HealthFlags::NODE_STALE, HealthFlags::NODE_EMCY, HealthFlags::NODE_HEARTBEAT] {
            for (k, f) in flags.iter().enumerate() {
                assert_eq!(f.bits().count_ones(), 1);
                assert!(HealthFlags::INVALIDATING.contains(*f), "node {k}");
            }
        }
    }

    #[test]
    fn health_names_every_flag_and_keeps_unknown_bits() {
        assert_eq!(HealthFlags::empty().to_string(), "ok");
        assert_eq!(
            (HealthFlags::NODE3_STALE | HealthFlags::NODE1_HEARTBEAT | HealthFlags::NODE1_EMCY).to_string(),
            "node1-emcy,node1-heartbeat,node3-stale"
        );
        assert_eq!(
            HealthFlags::all().to_string(),
            "node1-stale,node1-emcy,node1-heartbeat,node2-stale,node2-emcy,node2-heartbeat,node3-stale,node3-emcy,\
             node3-heartbeat,incomplete-cycle,overrun,sync-send-failed,bus-error,bad-sample,detector-reset"
        );
        let mut s = FulcrumSample::invalid(HealthFlags::OVERRUN);
        s.health |= 1 << 20;
        let h = s.health();
        assert_eq!(h.bits(), s.health, "unknown bits are retained");
        assert_eq!(h.unknown().bits(), 1 << 20);
        assert_eq!(h.to_string(), "overrun,unknown-0x100000");
        assert!(!h.intersects(HealthFlags::INVALIDATING));
    }
}
