//! Encoder configuration: which node carries which joints, and counts to radians.
//!
//! Node `node_ids[0]` carries joints 1-2, `node_ids[1]` joints 3-4, `node_ids[2]` joints
//! 5-6 (defaults 1, 2, 3). Per joint, the angle is
//!
//! ```text
//! q_rad = sign · (counts − zero_offset_counts) · 2π / counts_per_rev
//! ```
//!
//! and the reverse (for the simulator) rounds to the nearest count, halves away from zero.
//! Counts are not wrapped: a joint's counts grow past `counts_per_rev` if it turns more than
//! one revolution.
//!
//! In a TOML config (every key optional; defaults shown for joint 1):
//!
//! ```toml
//! [encoder]
//! node_ids = [1, 2, 3]
//! [[encoder.joints]]          # joint 1; six such tables, in joint order
//! counts_per_rev = 131072     # 2^17 counts per revolution
//! zero_offset_counts = 0      # counts at q = 0 rad
//! sign = 1                    # +1 or -1
//! ```

use core::f64::consts::TAU;

use serde::{Deserialize, Serialize};

use super::protocol::NodeId;

/// Number of joints on the encoder bus.
pub const JOINTS: usize = 6;
/// Number of encoder nodes.
pub const ENCODER_NODES: usize = 3;
/// Joints carried by one node's TPDO1.
pub const JOINTS_PER_NODE: usize = 2;
/// Default resolution, counts per revolution (2^17).
pub const DEFAULT_COUNTS_PER_REV: u32 = 1 << 17;
/// Default node IDs of the nodes carrying joints 1-2, 3-4 and 5-6.
pub const DEFAULT_NODE_IDS: [u8; ENCODER_NODES] = [1, 2, 3];

/// Conversion of one joint's encoder counts to radians.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct JointEncoder {
    /// Encoder resolution, counts per joint revolution (≥ 1; default 131072 = 2^17).
    pub counts_per_rev: u32,
    /// Encoder reading at joint angle 0 rad, counts (default 0).
    pub zero_offset_counts: i32,
    /// +1 if counts grow with the joint angle, -1 if they shrink (default +1).
    pub sign: i8,
}

impl Default for JointEncoder {
    fn default() -> Self {
        Self { counts_per_rev: DEFAULT_COUNTS_PER_REV, zero_offset_counts: 0, sign: 1 }
    }
}

/// Why a radian angle has no encoder count.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum ToCountsError {
    /// The angle is NaN or infinite.
    #[error("angle {rad} rad is not finite")]
    NotFinite {
        /// The angle given, radians.
        rad: f64,
    },
    /// The angle maps outside the `i32` count range.
    #[error("angle {rad} rad is outside the i32 count range")]
    OutOfRange {
        /// The angle given, radians.
        rad: f64,
    },
}

impl JointEncoder {
    fn counts_per_rev_f64(&self) -> f64 {
        // An unvalidated 0 is treated as 1 so that no NaN can come out.
        f64::from(self.counts_per_rev.max(1))
    }

    fn sign_f64(&self) -> f64 {
        if self.sign < 0 { -1.0 } else { 1.0 }
    }

    /// Joint angle, radians, for an encoder reading in counts. Always finite.
    ///
    /// **Real-time (1 kHz loop):** allocation-free.
    pub fn counts_to_rad(&self, counts: i32) -> f64 {
        let delta = i64::from(counts) - i64::from(self.zero_offset_counts);
        self.sign_f64() * delta as f64 * TAU / self.counts_per_rev_f64()
    }

    /// Encoder reading, counts, for a joint angle in radians, rounded to the nearest count
    /// (halves away from zero).
    pub fn rad_to_counts(&self, rad: f64) -> Result<i32, ToCountsError> {
        if !rad.is_finite() {
            return Err(ToCountsError::NotFinite { rad });
        }
        let counts =
            (self.sign_f64() * rad * self.counts_per_rev_f64() / TAU).round() + f64::from(self.zero_offset_counts);
        if counts < f64::from(i32::MIN) || counts > f64::from(i32::MAX) {
            return Err(ToCountsError::OutOfRange { rad });
        }
        Ok(counts as i32)
    }
}

/// The encoder part of a config file: node IDs and per-joint conversion.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EncoderConfig {
    /// Node IDs (1..=127, distinct) of the nodes carrying joints 1-2, 3-4 and 5-6.
    pub node_ids: [u8; ENCODER_NODES],
    /// Conversion of joints 1..6, in joint order.
    pub joints: [JointEncoder; JOINTS],
}

impl Default for EncoderConfig {
    fn default() -> Self {
        Self { node_ids: DEFAULT_NODE_IDS, joints: [JointEncoder::default(); JOINTS] }
    }
}

/// Why an [`EncoderConfig`] was refused; the message names the offending key.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ConfigError {
    /// A node ID outside 1..=127.
    #[error("encoder.node_ids[{index}] = {value}: must be a CANopen node ID 1..=127")]
    NodeIdOutOfRange {
        /// Index into `node_ids`, 0-based.
        index: usize,
        /// The value given.
        value: u8,
    },
    /// The same node ID twice.
    #[error("encoder.node_ids[{second}] = {value}: same node ID as encoder.node_ids[{first}]")]
    DuplicateNodeId {
        /// Index of the first occurrence, 0-based.
        first: usize,
        /// Index of the repeat, 0-based.
        second: usize,
        /// The repeated node ID.
        value: u8,
    },
    /// A resolution of 0 counts per revolution.
    #[error("encoder.joints[{joint}].counts_per_rev = 0: must be at least 1")]
    ZeroCountsPerRev {
        /// Joint index, 0-based (joint 1 is 0).
        joint: usize,
    },
    /// A sign other than +1 or -1.
    #[error("encoder.joints[{joint}].sign = {value}: must be 1 or -1")]
    BadSign {
        /// Joint index, 0-based (joint 1 is 0).
        joint: usize,
        /// The value given.
        value: i8,
    },
}

/// A radian angle of one joint had no encoder count.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[error("joint index {joint}: {error}")]
pub struct JointToCountsError {
    /// Joint index, 0-based (joint 1 is 0).
    pub joint: usize,
    /// Why.
    #[source]
    pub error: ToCountsError,
}

impl EncoderConfig {
    /// Check every key; the first problem found is returned.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.nodes()?;
        for (joint, j) in self.joints.iter().enumerate() {
            if j.counts_per_rev == 0 {
                return Err(ConfigError::ZeroCountsPerRev { joint });
            }
            if j.sign != 1 && j.sign != -1 {
                return Err(ConfigError::BadSign { joint, value: j.sign });
            }
        }
        Ok(())
    }

    /// The node IDs, checked (1..=127 and distinct), carrying joints 1-2, 3-4, 5-6.
    pub fn nodes(&self) -> Result<[NodeId; ENCODER_NODES], ConfigError> {
        let mut nodes = [NodeId::ONE; ENCODER_NODES];
        for (index, &value) in self.node_ids.iter().enumerate() {
            nodes[index] = NodeId::new(value).ok_or(ConfigError::NodeIdOutOfRange { index, value })?;
            if let Some(first) = self.node_ids[..index].iter().position(|&v| v == value) {
                return Err(ConfigError::DuplicateNodeId { first, second: index, value });
            }
        }
        Ok(nodes)
    }

    /// Joint angles, radians, for the six encoder readings, counts.
    ///
    /// **Real-time (1 kHz loop):** called every cycle; allocation-free.
    pub fn counts_to_rad(&self, counts: &[i32; JOINTS]) -> [f64; JOINTS] {
        core::array::from_fn(|i| self.joints[i].counts_to_rad(counts[i]))
    }

    /// Encoder readings, counts, for six joint angles, radians (rounded to the nearest count).
    pub fn rad_to_counts(&self, rad: &[f64; JOINTS]) -> Result<[i32; JOINTS], JointToCountsError> {
        let mut out = [0i32; JOINTS];
        for (joint, (o, r)) in out.iter_mut().zip(rad).enumerate() {
            *o = self.joints[joint].rad_to_counts(*r).map_err(|error| JointToCountsError { joint, error })?;
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use core::f64::consts::PI;

    #[test]
    fn defaults_are_the_documented_ones() {
        let c = EncoderConfig::default();
        assert_eq!(c.node_ids, [1, 2, 3]);
        assert!(c.joints.iter().all(|j| j.counts_per_rev == 131_072 && j.zero_offset_counts == 0 && j.sign == 1));
        assert_eq!(c.validate(), Ok(()));
    }

    #[test]
    fn counts_to_rad_applies_offset_sign_and_resolution() {
        let j = JointEncoder { counts_per_rev: 4096, zero_offset_counts: 1000, sign: -1 };
        assert_eq!(j.counts_to_rad(1000), 0.0);
        assert!((j.counts_to_rad(1000 + 1024) + PI / 2.0).abs() < 1e-12);
        assert!((j.counts_to_rad(1000 - 2048) - PI).abs() < 1e-12);
        let d = JointEncoder::default();
        assert!((d.counts_to_rad(131_072) - 2.0 * PI).abs() < 1e-12);
        // Extreme values: no overflow.
        let far = JointEncoder { counts_per_rev: 1, zero_offset_counts: i32::MAX, sign: 1 };
        assert!(far.counts_to_rad(i32::MIN).is_finite());
    }

    #[test]
    fn rad_to_counts_rounds_and_refuses_garbage() {
        let j = JointEncoder { counts_per_rev: 4096, zero_offset_counts: 1000, sign: -1 };
        assert_eq!(j.rad_to_counts(-PI / 2.0), Ok(2024));
        // 0.4 count rounds down, 0.6 count rounds up.
        let count = TAU / 4096.0;
        assert_eq!(j.rad_to_counts(-0.4 * count), Ok(1000));
        assert_eq!(j.rad_to_counts(-0.6 * count), Ok(1001));
        assert!(matches!(j.rad_to_counts(f64::NAN), Err(ToCountsError::NotFinite { .. })));
        assert!(matches!(j.rad_to_counts(f64::INFINITY), Err(ToCountsError::NotFinite { .. })));
        assert!(matches!(j.rad_to_counts(1e9), Err(ToCountsError::OutOfRange { .. })));
        let c = EncoderConfig::default();
        let mut q = [0.0; JOINTS];
        q[4] = f64::NAN;
        assert_eq!(c.rad_to_counts(&q).unwrap_err().joint, 4);
    }

    #[test]
    fn validation_names_the_key() {
        let mut c = EncoderConfig { node_ids: [1, 0, 3], ..Default::default() };
        let e = c.validate().unwrap_err();
        assert_eq!(e, ConfigError::NodeIdOutOfRange { index: 1, value: 0 });
        assert!(e.to_string().contains("encoder.node_ids[1]"));
        c.node_ids = [1, 128, 3];
        assert_eq!(c.validate(), Err(ConfigError::NodeIdOutOfRange { index: 1, value: 128 }));
        c.node_ids = [4, 5, 4];
        let e = c.validate().unwrap_err();
        assert_eq!(e, ConfigError::DuplicateNodeId { first: 0, second: 2, value: 4 });
        assert!(e.to_string().contains("encoder.node_ids[2]"));
        c.node_ids = [4, 5, 6];
        c.joints[3].counts_per_rev = 0;
        let e = c.validate().unwrap_err();
        assert_eq!(e, ConfigError::ZeroCountsPerRev { joint: 3 });
        assert!(e.to_string().contains("encoder.joints[3].counts_per_rev"));
        c.joints[3].counts_per_rev = 10;
        c.joints[5].sign = 0;
        let e = c.validate().unwrap_err();
        assert_eq!(e, ConfigError::BadSign { joint: 5, value: 0 });
        assert!(e.to_string().contains("encoder.joints[5].sign"));
        c.joints[5].sign = -1;
        assert_eq!(c.validate(), Ok(()));
        assert_eq!(c.nodes().map(|n| n.map(NodeId::get)), Ok([4, 5, 6]));
    }
}
