//! The message fulcrumd publishes once per control cycle.
//!
//! `#[repr(C)]`, fixed size, no pointers: it is written once into shared memory and read
//! in place by every subscriber, in any language that can declare the same C struct. The
//! layout is versioned by [`FULCRUM_SAMPLE_VERSION`]; a subscriber refuses any other
//! version. Units and frames are in each field's doc and in `docs/output.md`.

use iceoryx2::prelude::ZeroCopySend;

/// Layout version of [`FulcrumSample`]. Bumped on any change of field, order or meaning.
pub const FULCRUM_SAMPLE_VERSION: u32 = 1;

/// `FulcrumSample::state`: the estimate must not be used (stale, missing or faulty input,
/// or the detector was just reset). The health flags say why.
pub const STATE_INVALID: u32 = 0;
/// `FulcrumSample::state`: valid input, the instrument is not in a trocar.
pub const STATE_OUTSIDE: u32 = 1;
/// `FulcrumSample::state`: valid input, the instrument passes through trocar `trocar_id`;
/// `fulcrum_base_m` is the fulcrum.
pub const STATE_INSIDE: u32 = 2;

/// Health flags (`FulcrumSample::health`), one bit each. Zero means all is well.
pub mod health {
    /// Encoder node 1, 2, 3 (bits 0, 1, 2; in joint order): its TPDO has been missing for at
    /// least `stale_after_cycles` cycles.
    pub const NODE_STALE: [u32; 3] = [1 << 0, 1 << 1, 1 << 2];
    /// Encoder node 1, 2, 3 (bits 3, 4, 5): an EMCY with a non-zero error code is active
    /// (cleared by an EMCY with error code 0x0000).
    pub const NODE_EMCY: [u32; 3] = [1 << 3, 1 << 4, 1 << 5];
    /// Encoder node 1, 2, 3 (bits 6, 7, 8): its heartbeat stopped (none within the configured
    /// timeout) or it reports a state other than operational.
    pub const NODE_HEARTBEAT: [u32; 3] = [1 << 6, 1 << 7, 1 << 8];
    /// This cycle lacks at least one TPDO at its deadline (the cycle's data are not used).
    pub const INCOMPLETE_CYCLE: u32 = 1 << 9;
    /// The previous cycle ran past its period (an overrun).
    pub const OVERRUN: u32 = 1 << 10;
    /// The SYNC of this cycle could not be sent.
    pub const SYNC_SEND_FAILED: u32 = 1 << 11;
    /// The CAN interface reported an error (error frame, interface down).
    pub const BUS_ERROR: u32 = 1 << 12;
    /// Forward kinematics or the detector refused this cycle's joint values.
    pub const BAD_SAMPLE: u32 = 1 << 13;
    /// The detector was reset because its input had gone stale; it is refilling its window.
    pub const DETECTOR_RESET: u32 = 1 << 14;
    /// Any flag that makes the cycle's input invalid (`state` is then [`super::STATE_INVALID`]).
    pub const INVALIDATING: u32 = NODE_STALE[0]
        | NODE_STALE[1]
        | NODE_STALE[2]
        | NODE_EMCY[0]
        | NODE_EMCY[1]
        | NODE_EMCY[2]
        | NODE_HEARTBEAT[0]
        | NODE_HEARTBEAT[1]
        | NODE_HEARTBEAT[2]
        | INCOMPLETE_CYCLE
        | SYNC_SEND_FAILED
        | BUS_ERROR
        | BAD_SAMPLE;
}

/// One control cycle's estimate, as published by fulcrumd.
///
/// Every float is finite. Vectors are in the robot base frame; positions in metres.
#[derive(Clone, Copy, Debug, PartialEq, ZeroCopySend)]
#[type_name("comanip::FulcrumSample")]
#[repr(C)]
pub struct FulcrumSample {
    /// Layout version, [`FULCRUM_SAMPLE_VERSION`].
    pub version: u32,
    /// [`STATE_INVALID`], [`STATE_OUTSIDE`] or [`STATE_INSIDE`].
    pub state: u32,
    /// Cycle number since the daemon started (0 for the first cycle). Consecutive samples
    /// differ by one; a jump back means the daemon restarted (see `run_id`).
    pub sequence: u64,
    /// Random identifier of this daemon run: a new value after every (re)start.
    pub run_id: u64,
    /// Instant of this cycle's SYNC, nanoseconds of `CLOCK_MONOTONIC`.
    pub timestamp_ns: u64,
    /// Bitwise OR of the [`health`] flags.
    pub health: u32,
    /// Trocar identity while inside (see `estimator::trocar::TrocarState`), else 0.
    pub trocar_id: u32,
    /// Fulcrum, metres, robot base frame. Zero unless `state == STATE_INSIDE`.
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
    /// An invalid sample with every field zero except `version`, `state` and `health`.
    pub const fn invalid(health: u32) -> Self {
        Self {
            version: FULCRUM_SAMPLE_VERSION,
            state: STATE_INVALID,
            sequence: 0,
            run_id: 0,
            timestamp_ns: 0,
            health,
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

    /// The fulcrum (metres, robot base frame) when this sample is valid and inside a trocar.
    pub fn fulcrum(&self) -> Option<[f64; 3]> {
        (self.version == FULCRUM_SAMPLE_VERSION && self.state == STATE_INSIDE).then_some(self.fulcrum_base_m)
    }

    /// True when the input of this cycle was valid (the state is outside or inside).
    pub fn is_valid(&self) -> bool {
        self.version == FULCRUM_SAMPLE_VERSION && self.state != STATE_INVALID
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
    fn invalid_has_no_fulcrum() {
        let s = FulcrumSample::invalid(health::NODE_STALE[1]);
        assert!(!s.is_valid());
        assert_eq!(s.fulcrum(), None);
        let mut inside = s;
        inside.state = STATE_INSIDE;
        inside.fulcrum_base_m = [0.1, 0.2, 0.3];
        assert_eq!(inside.fulcrum(), Some([0.1, 0.2, 0.3]));
        inside.version = 99;
        assert_eq!(inside.fulcrum(), None);
    }
}
