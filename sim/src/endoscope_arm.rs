//! The endoscope-holder arm on the encoder bus: its motion and its two encoder nodes.
//!
//! The arm is the ECM model of `docs/calibration.md` (remote centre of motion `{e}`, joints
//! `q = [yaw rad, pitch rad, insertion m, roll rad]`, kinematics
//! [`estimator::calib::rcm_arms::ecm_frames`]). It shares the tool arm's CAN bus
//! (`docs/can-protocol.md`):
//! - node `node_ids[0]` (default 4) sends TPDO1 `0x180 + node` with yaw and pitch, node
//!   `node_ids[1]` (default 5) insertion and roll, two little-endian `i32` counts each;
//!   yaw, pitch and roll in counts per revolution ([`EndoscopeArmConfig::counts_per_rev`]),
//!   insertion in counts per metre ([`EndoscopeArmConfig::insertion_counts_per_m`]);
//! - CANopen transmission type [`EndoscopeArmConfig::transmission_type`] (default 10): the
//!   nodes answer the SYNCs whose counter is a multiple of it (10, 20, …, 240 by default: as
//!   240 is a multiple of 10, exactly every 10th SYNC, and a lost SYNC does not shift the
//!   phase), so the bus stays within its load budget;
//! - heartbeats every `heartbeat_period_us`, sent at a SYNC half a transmission period away
//!   from the TPDOs (counter ≡ 5 mod 10 by default), so they never share a millisecond with
//!   the arm's own TPDOs.
//!
//! **Motion** ([`EndoscopeMotion`]): the holder keeps a view for `hold_s` seconds, then moves
//! smoothly (minimum-jerk in joint space) to a new view within `range` of `home_joints`
//! over `move_s` seconds; deterministic from `seed`. Times are seconds on the twin's clock
//! (sample `n` at `n · 1 ms`).

use core::f64::consts::TAU;

use hw_io::can::{Message, NodeId, TimedFrame};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::endoscope::config::PoseConfig;

/// Joints of the endoscope arm (yaw, pitch, insertion, roll).
pub const ECM_JOINTS: usize = 4;

/// Most frames the endoscope arm's nodes send in answer to one SYNC: two TPDOs and two
/// heartbeats.
pub const ECM_MAX_FRAMES_PER_SYNC: usize = 4;

/// Default node IDs of the endoscope arm's nodes (yaw and pitch; insertion and roll).
pub const DEFAULT_ECM_NODE_IDS: [u8; 2] = [4, 5];

/// Default CANopen transmission type of the endoscope arm's TPDOs: every 10th SYNC.
pub const DEFAULT_ECM_TRANSMISSION_TYPE: u8 = 10;

/// The frames of the endoscope arm's nodes for one SYNC, in bus order (microseconds).
pub type EcmFrames = heapless::Vec<TimedFrame, ECM_MAX_FRAMES_PER_SYNC>;

/// The endoscope-holder arm (`[endoscope_arm]` of the twin configuration, every key
/// optional).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EndoscopeArmConfig {
    /// The arm is on the bus (`simrobot --no-endoscope` turns it off).
    pub enabled: bool,
    /// Node IDs (1..=127, distinct, none of `encoder.node_ids`) of the node carrying yaw and
    /// pitch and of the node carrying insertion and roll.
    pub node_ids: [u8; 2],
    /// CANopen transmission type of the TPDOs: the nodes answer the SYNCs whose counter is a
    /// multiple of it (1..=240, a divisor of 240 so that the cadence survives the counter's
    /// wrap).
    pub transmission_type: u8,
    /// Resolution of yaw, pitch and roll, counts per revolution (≥ 1; 2^17 by default).
    pub counts_per_rev: u32,
    /// Resolution of the insertion, counts per metre (≥ 1; 10^6 by default: 1 µm).
    pub insertion_counts_per_m: u32,
    /// Delay from the SYNC to the nodes' frames, microseconds.
    pub latency_us: u64,
    /// Heartbeat period, microseconds; 0 disables heartbeats.
    pub heartbeat_period_us: u64,
    /// Seed of the motion (hold times, move times, views).
    pub seed: u64,
    /// The view held at the start and about which the views are drawn,
    /// `[yaw rad, pitch rad, insertion m, roll rad]`.
    pub home_joints: [f64; ECM_JOINTS],
    /// Each new view is `home_joints` plus a uniform draw in `±range` per joint (rad, rad, m,
    /// rad; each ≥ 0).
    pub range: [f64; ECM_JOINTS],
    /// Time a view is held, seconds (uniform in the range; 0 < min ≤ max ≤ 3600).
    pub hold_s: [f64; 2],
    /// Duration of a move to the next view, seconds (uniform in the range; 0.05 ≤ min ≤ max ≤
    /// 60).
    pub move_s: [f64; 2],
    /// `T_b_e`: the endoscope arm's RCM frame `{e}` in the tool arm's base frame `{b}`
    /// (metres; quaternion `[w, x, y, z]`). The default puts the endoscope's RCM 16 cm above
    /// the tool arm's default trocars, over their centre, looking straight down with the
    /// image's `x` along the base `y` (the trocars' long spread): at the default insertion
    /// (6 cm) the camera is 10 cm above the trocars and one view holds the four ports'
    /// workspace (the simulated abdomen has no wall). The instrument's tip is then in the
    /// image in 78-83 % of the samples of default scenarios, 96-100 % of those inside a
    /// trocar (`sim/tests/endoscope_arm.rs`).
    pub rcm_in_tool_base: PoseConfig,
}

impl Default for EndoscopeArmConfig {
    fn default() -> Self {
        let h = core::f64::consts::FRAC_1_SQRT_2;
        Self {
            enabled: true,
            node_ids: DEFAULT_ECM_NODE_IDS,
            transmission_type: DEFAULT_ECM_TRANSMISSION_TYPE,
            counts_per_rev: 1 << 17,
            insertion_counts_per_m: 1_000_000,
            latency_us: 100,
            heartbeat_period_us: 100_000,
            seed: 1,
            home_joints: [0.0, 0.0, 0.06, 0.0],
            range: [0.10, 0.08, 0.01, 0.15],
            hold_s: [3.0, 8.0],
            move_s: [1.0, 2.0],
            // z_e = -z_b, x_e = y_b, y_e = x_b: half a turn about (x_b + y_b)/√2.
            rcm_in_tool_base: PoseConfig { translation_m: [0.29, 0.0, 0.16], quaternion_wxyz: [0.0, h, h, 0.0] },
        }
    }
}

/// Why an [`EndoscopeArmConfig`] was refused; the message names the key.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum EndoscopeArmConfigError {
    /// A node ID outside 1..=127.
    #[error("endoscope_arm.node_ids[{index}] = {value}: must be a CANopen node ID 1..=127")]
    NodeIdOutOfRange {
        /// Index into `node_ids`.
        index: usize,
        /// The value given.
        value: u8,
    },
    /// The two node IDs are equal, or one is a node of the tool arm.
    #[error("endoscope_arm.node_ids = [{0}, {1}]: must be distinct and not one of encoder.node_ids")]
    NodeClash(u8, u8),
    /// The transmission type is not a divisor of 240 in 1..=240.
    #[error("endoscope_arm.transmission_type = {0}: must divide 240 (1, 2, 3, 4, 5, 6, 8, 10, 12, ..., 240)")]
    TransmissionType(u8),
    /// A resolution is zero.
    #[error("endoscope_arm.{0} = 0: must be at least 1")]
    Resolution(&'static str),
    /// A number is out of its range.
    #[error("endoscope_arm.{key} = {value}: allowed {allowed}")]
    OutOfRange {
        /// The key (with its index).
        key: &'static str,
        /// The value given.
        value: f64,
        /// The allowed range.
        allowed: &'static str,
    },
    /// `rcm_in_tool_base` is not a finite pose with a non-zero quaternion.
    #[error("endoscope_arm.rcm_in_tool_base: not a finite pose with a non-zero quaternion")]
    Pose,
}

impl EndoscopeArmConfig {
    /// Checks every key; `tool_node_ids` are the tool arm's encoder nodes (`encoder.node_ids`).
    pub fn validate(&self, tool_node_ids: &[u8]) -> Result<(), EndoscopeArmConfigError> {
        use EndoscopeArmConfigError as E;
        for (index, &value) in self.node_ids.iter().enumerate() {
            if NodeId::new(value).is_none() {
                return Err(E::NodeIdOutOfRange { index, value });
            }
        }
        let [a, b] = self.node_ids;
        if a == b || tool_node_ids.contains(&a) || tool_node_ids.contains(&b) {
            return Err(E::NodeClash(a, b));
        }
        let t = self.transmission_type;
        if t == 0 || 240 % u32::from(t) != 0 {
            return Err(E::TransmissionType(t));
        }
        if self.counts_per_rev == 0 {
            return Err(E::Resolution("counts_per_rev"));
        }
        if self.insertion_counts_per_m == 0 {
            return Err(E::Resolution("insertion_counts_per_m"));
        }
        const HOME: [&str; 4] = ["home_joints[0]", "home_joints[1]", "home_joints[2]", "home_joints[3]"];
        const RANGE: [&str; 4] = ["range[0]", "range[1]", "range[2]", "range[3]"];
        const LIMIT: [f64; 4] = [1.5, 1.5, 0.5, TAU];
        for j in 0..ECM_JOINTS {
            let (h, r) = (self.home_joints[j], self.range[j]);
            if !(h.is_finite() && h.abs() <= LIMIT[j]) {
                return Err(E::OutOfRange {
                    key: HOME[j],
                    value: h,
                    allowed: "finite, |yaw|, |pitch| <= 1.5, |insertion| <= 0.5, |roll| <= 2 pi",
                });
            }
            if !(r.is_finite() && (0.0..=LIMIT[j]).contains(&r)) {
                return Err(E::OutOfRange {
                    key: RANGE[j],
                    value: r,
                    allowed: "0 ..= 1.5 (yaw, pitch), 0.5 (insertion), 2 pi (roll)",
                });
            }
        }
        for (key, r, min, max) in [("hold_s", self.hold_s, 1e-3, 3600.0), ("move_s", self.move_s, 0.05, 60.0)] {
            for (k, v) in r.iter().enumerate() {
                if !(v.is_finite() && *v >= min && *v <= max) || r[0] > r[1] {
                    let key =
                        if key == "hold_s" { ["hold_s[0]", "hold_s[1]"][k] } else { ["move_s[0]", "move_s[1]"][k] };
                    return Err(E::OutOfRange {
                        key,
                        value: *v,
                        allowed: "hold_s in (0, 3600], move_s in [0.05, 60], min <= max",
                    });
                }
            }
        }
        if self.rcm_in_tool_base.isometry().is_none() {
            return Err(E::Pose);
        }
        Ok(())
    }

    /// `T_b_e`, the endoscope arm's RCM frame in the tool arm's base frame (metres), `None`
    /// when the configured pose is not usable.
    pub fn rcm_in_tool_base(&self) -> Option<nalgebra::Isometry3<f64>> {
        self.rcm_in_tool_base.isometry()
    }

    /// Encoder counts of joints `q = [yaw rad, pitch rad, insertion m, roll rad]`, rounded to
    /// the nearest count (halves away from zero); `None` when a joint is not finite or out of
    /// the `i32` range.
    pub fn joints_to_counts(&self, q: &[f64; ECM_JOINTS]) -> Option<[i32; ECM_JOINTS]> {
        let per = |j: usize| {
            if j == 2 { f64::from(self.insertion_counts_per_m) } else { f64::from(self.counts_per_rev) / TAU }
        };
        let mut out = [0i32; ECM_JOINTS];
        for j in 0..ECM_JOINTS {
            let c = (q[j] * per(j)).round();
            if !(c.is_finite() && c >= f64::from(i32::MIN) && c <= f64::from(i32::MAX)) {
                return None;
            }
            out[j] = c as i32;
        }
        Some(out)
    }

    /// Joints `[yaw rad, pitch rad, insertion m, roll rad]` of encoder counts (the reverse of
    /// [`EndoscopeArmConfig::joints_to_counts`]; exact to half a count).
    pub fn counts_to_joints(&self, counts: &[i32; ECM_JOINTS]) -> [f64; ECM_JOINTS] {
        let rev = f64::from(self.counts_per_rev.max(1));
        let lin = f64::from(self.insertion_counts_per_m.max(1));
        [
            f64::from(counts[0]) * TAU / rev,
            f64::from(counts[1]) * TAU / rev,
            f64::from(counts[2]) / lin,
            f64::from(counts[3]) * TAU / rev,
        ]
    }
}

/// Minimum-jerk blend from 0 to 1 over `u` in [0, 1].
fn min_jerk(u: f64) -> f64 {
    let u = u.clamp(0.0, 1.0);
    u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)
}

/// One move of the holder between two held views.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Move {
    start_s: f64,
    end_s: f64,
    from: [f64; ECM_JOINTS],
    to: [f64; ECM_JOINTS],
}

/// The holder's motion: held views joined by smooth moves, deterministic from the seed. See
/// the module documentation.
#[derive(Clone, Debug)]
pub struct EndoscopeMotion {
    home: [f64; ECM_JOINTS],
    range: [f64; ECM_JOINTS],
    hold_s: [f64; 2],
    move_s: [f64; 2],
    rng: ChaCha8Rng,
    moves: Vec<Move>,
}

impl EndoscopeMotion {
    /// The motion of a validated configuration (no move generated yet: call
    /// [`EndoscopeMotion::extend_to`]).
    pub fn new(cfg: &EndoscopeArmConfig) -> Self {
        Self {
            home: cfg.home_joints,
            range: cfg.range,
            hold_s: cfg.hold_s,
            move_s: cfg.move_s,
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            moves: Vec::new(),
        }
    }

    fn uniform(rng: &mut ChaCha8Rng, r: [f64; 2]) -> f64 {
        if r[1] > r[0] { rng.random_range(r[0]..=r[1]) } else { r[0] }
    }

    /// Generates moves until the schedule covers `t_s` seconds (allocates; the same seed
    /// gives the same schedule however it is extended).
    pub fn extend_to(&mut self, t_s: f64) {
        let mut last_end = self.moves.last().map_or(0.0, |m| m.end_s);
        let mut at = self.moves.last().map_or(self.home, |m| m.to);
        // Bounded even for absurd inputs: hold_s >= 1 ms.
        while last_end <= t_s && t_s.is_finite() && self.moves.len() < 100_000_000 {
            let hold = Self::uniform(&mut self.rng, self.hold_s);
            let dur = Self::uniform(&mut self.rng, self.move_s);
            let mut to = self.home;
            for (j, v) in to.iter_mut().enumerate() {
                if self.range[j] > 0.0 {
                    *v += self.rng.random_range(-self.range[j]..=self.range[j]);
                }
            }
            let start_s = last_end + hold;
            let m = Move { start_s, end_s: start_s + dur, from: at, to };
            self.moves.push(m);
            last_end = m.end_s;
            at = to;
        }
    }

    /// Time up to which the schedule is generated, seconds (the end of the last move).
    pub fn covered_s(&self) -> f64 {
        self.moves.last().map_or(0.0, |m| m.end_s)
    }

    /// Joints `[yaw rad, pitch rad, insertion m, roll rad]` at `t_s` seconds on the twin's
    /// clock; past the generated schedule the last view is held. Allocation-free.
    pub fn joints_at(&self, t_s: f64) -> [f64; ECM_JOINTS] {
        let k = self.moves.partition_point(|m| m.start_s <= t_s);
        let Some(m) = k.checked_sub(1).and_then(|i| self.moves.get(i)) else { return self.home };
        if t_s >= m.end_s {
            return m.to;
        }
        let s = min_jerk((t_s - m.start_s) / (m.end_s - m.start_s));
        core::array::from_fn(|j| m.from[j] + (m.to[j] - m.from[j]) * s)
    }

    /// `true` while the holder moves at `t_s` (between the start and the end of a move).
    pub fn is_moving(&self, t_s: f64) -> bool {
        let k = self.moves.partition_point(|m| m.start_s <= t_s);
        k.checked_sub(1).and_then(|i| self.moves.get(i)).is_some_and(|m| t_s < m.end_s)
    }
}

/// The endoscope arm's two encoder nodes (always operational, no faults).
#[derive(Clone, Debug)]
pub struct EcmNodes {
    cfg: EndoscopeArmConfig,
    ids: [NodeId; 2],
    next_heartbeat_us: Option<u64>,
    tpdos_sent: u64,
}

impl EcmNodes {
    /// The nodes of a configuration validated with [`EndoscopeArmConfig::validate`]; `None`
    /// when a node ID is not valid.
    pub fn new(cfg: &EndoscopeArmConfig) -> Option<Self> {
        let ids = [NodeId::new(cfg.node_ids[0])?, NodeId::new(cfg.node_ids[1])?];
        Some(Self { cfg: cfg.clone(), ids, next_heartbeat_us: None, tpdos_sent: 0 })
    }

    /// `true` when the nodes send their TPDOs in answer to the SYNC with `counter`.
    pub fn answers(&self, counter: u8) -> bool {
        counter.is_multiple_of(self.cfg.transmission_type.max(1))
    }

    /// TPDOs sent so far (both nodes).
    pub fn tpdos_sent(&self) -> u64 {
        self.tpdos_sent
    }

    /// Answers one SYNC with `counter` sent at `t_us` (microseconds, the caller's time base),
    /// the arm at `q` (`[yaw rad, pitch rad, insertion m, roll rad]`): the TPDOs on every
    /// `transmission_type`-th SYNC, the heartbeats when due. Frames stamped `t_us +
    /// latency_us`, in bus order. `None`, with nothing changed, when a joint has no count.
    /// Allocation-free.
    pub fn on_sync(&mut self, counter: u8, t_us: u64, q: &[f64; ECM_JOINTS]) -> Option<EcmFrames> {
        let counts = self.cfg.joints_to_counts(q)?;
        let mut out = EcmFrames::new();
        let send_us = t_us.saturating_add(self.cfg.latency_us);
        let tt = self.cfg.transmission_type.max(1);
        if self.answers(counter) {
            for (k, node) in self.ids.iter().enumerate() {
                if let Ok(frame) = (Message::Tpdo { node: *node, counts: [counts[2 * k], counts[2 * k + 1]] }).encode()
                {
                    let _ = out.push(TimedFrame { frame, unix_time_us: send_us });
                    self.tpdos_sent += 1;
                }
            }
        }
        let period = self.cfg.heartbeat_period_us;
        if period > 0 && counter % tt == (tt / 2) % tt && self.next_heartbeat_us.is_none_or(|n| t_us >= n) {
            for node in self.ids {
                if let Ok(frame) = (Message::Heartbeat { node, state: hw_io::can::NmtState::Operational }).encode() {
                    let _ = out.push(TimedFrame { frame, unix_time_us: send_us });
                }
            }
            let mut next = self.next_heartbeat_us.unwrap_or(t_us);
            while next <= t_us {
                next = next.saturating_add(period);
                if next == u64::MAX {
                    break;
                }
            }
            self.next_heartbeat_us = Some(next);
        }
        out.sort_unstable_by_key(|f| (f.unix_time_us, f.frame.id().raw()));
        Some(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_round_trip_within_half_a_count() {
        let cfg = EndoscopeArmConfig::default();
        let q = [0.123, -0.0456, 0.0371234, 2.5];
        let back = cfg.counts_to_joints(&cfg.joints_to_counts(&q).unwrap());
        let rev = TAU / f64::from(cfg.counts_per_rev);
        for j in [0, 1, 3] {
            assert!((back[j] - q[j]).abs() <= rev / 2.0 + 1e-15, "joint {j}");
        }
        assert!((back[2] - q[2]).abs() <= 0.5e-6 + 1e-15);
        assert_eq!(cfg.joints_to_counts(&[f64::NAN, 0.0, 0.0, 0.0]), None);
        assert_eq!(cfg.joints_to_counts(&[0.0, 0.0, 1e6, 0.0]), None);
    }

    #[test]
    fn motion_holds_then_moves_smoothly_and_is_deterministic() {
        let cfg = EndoscopeArmConfig::default();
        let mut a = EndoscopeMotion::new(&cfg);
        a.extend_to(120.0);
        let mut b = EndoscopeMotion::new(&cfg);
        b.extend_to(30.0);
        b.extend_to(120.0);
        let (mut moving, mut prev) = (0u32, a.joints_at(0.0));
        assert_eq!(prev, cfg.home_joints);
        for i in 1..120_000 {
            let t = f64::from(i) * 1e-3;
            let q = a.joints_at(t);
            assert_eq!(q, b.joints_at(t), "same seed, same motion at {t} s");
            for j in 0..4 {
                assert!((q[j] - cfg.home_joints[j]).abs() <= cfg.range[j] + 1e-12);
                // Smooth: a move of at most 2 range in at least 1 s, peak speed 1.875 × mean.
                assert!((q[j] - prev[j]).abs() <= 2.0 * cfg.range[j] * 1.875e-3 + 1e-12, "joint {j} at {t} s");
            }
            moving += u32::from(a.is_moving(t));
            prev = q;
        }
        // Held 3-8 s, moving 1-2 s: moving 10-40 % of the time.
        let share = f64::from(moving) / 120_000.0;
        assert!((0.1..0.4).contains(&share), "moving {share}");
        let mut c = EndoscopeMotion::new(&EndoscopeArmConfig { seed: 2, ..cfg });
        c.extend_to(120.0);
        assert_ne!(c.joints_at(60.0), a.joints_at(60.0));
    }

    #[test]
    fn bad_configs_name_the_key() {
        let tool = [1, 2, 3];
        assert!(EndoscopeArmConfig::default().validate(&tool).is_ok());
        let bad = |f: fn(&mut EndoscopeArmConfig)| {
            let mut c = EndoscopeArmConfig::default();
            f(&mut c);
            c.validate(&tool).unwrap_err().to_string()
        };
        assert!(bad(|c| c.node_ids = [3, 5]).contains("node_ids"));
        assert!(bad(|c| c.node_ids = [0, 5]).contains("node_ids[0]"));
        assert!(bad(|c| c.transmission_type = 7).contains("transmission_type"));
        assert!(bad(|c| c.hold_s = [5.0, 2.0]).contains("hold_s"));
        assert!(bad(|c| c.move_s[0] = 0.0).contains("move_s[0]"));
        assert!(bad(|c| c.range[2] = f64::NAN).contains("range[2]"));
        assert!(bad(|c| c.home_joints[1] = 3.0).contains("home_joints[1]"));
        assert!(bad(|c| c.insertion_counts_per_m = 0).contains("insertion_counts_per_m"));
        assert!(bad(|c| c.rcm_in_tool_base.quaternion_wxyz = [0.0; 4]).contains("rcm_in_tool_base"));
    }
}
