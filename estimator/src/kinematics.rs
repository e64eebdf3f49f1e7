//! Forward kinematics of an Achilles-type comanipulator.
//!
//! The arm has six revolute joints described by a standard Denavit-Hartenberg table
//! (`A_i = Rz(θ_i) · Tz(d_i) · Tx(a_i) · Rx(α_i)`). Joints 1-3 are motorised and place the
//! wrist centre P; joints 4-6 are passive and their axes intersect at P. The instrument is
//! rigidly held along the z axis of the last frame, so each sample gives a line
//! `(P, z)` in the robot base frame.
//!
//! Joint calibration: the DH angle of joint i is `θ_i = sign_i · q_i + zero_offset_i + theta_offset_i`
//! where `q_i` is the measured joint angle (radians), `sign_i` is ±1 (the encoder's sense of
//! rotation against the DH axis), `zero_offset_i` is the calibrated encoder zero (radians)
//! and `theta_offset_i` is the DH table's constant offset (radians).
//!
//! The default parameters describe a plausible arm with a reach of 0.6 m from the shoulder
//! (upper arm 0.30 m, forearm 0.30 m, shoulder 0.35 m above the base); see
//! `docs/kinematics.md` and `configs/fulcrumd.toml`.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Number of joints of the arm (3 motorised + 3 passive).
pub const JOINTS: usize = 6;

/// One row of a standard Denavit-Hartenberg table.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DhRow {
    /// Offset along the previous z axis, metres.
    pub d_m: f64,
    /// Length along the new x axis (common normal), metres.
    pub a_m: f64,
    /// Twist about the new x axis, radians.
    pub alpha_rad: f64,
    /// Constant added to the joint angle, radians.
    #[serde(default)]
    pub theta_offset_rad: f64,
}

/// Per-joint calibration: encoder sense and zero.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JointCalibration {
    /// +1 or -1: sense of the measured angle against the DH joint axis.
    pub sign: f64,
    /// Encoder zero correction, radians, added to `sign · q`.
    pub zero_offset_rad: f64,
}

impl Default for JointCalibration {
    fn default() -> Self {
        Self { sign: 1.0, zero_offset_rad: 0.0 }
    }
}

/// Kinematic parameters of the arm, as read from the `[kinematics]` table of a config file.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AchillesConfig {
    /// DH rows of joints 1..6 (base to instrument).
    pub dh: [DhRow; JOINTS],
    /// Calibration of joints 1..6.
    pub joints: [JointCalibration; JOINTS],
}

impl Default for AchillesConfig {
    fn default() -> Self {
        use core::f64::consts::FRAC_PI_2;
        let row = |d_m, a_m, alpha_rad| DhRow { d_m, a_m, alpha_rad, theta_offset_rad: 0.0 };
        Self {
            dh: [
                row(0.35, 0.0, FRAC_PI_2),  // 1: base yaw, shoulder 0.35 m above the base
                row(0.0, 0.30, 0.0),        // 2: shoulder pitch, upper arm 0.30 m
                row(0.0, 0.0, FRAC_PI_2),   // 3: elbow
                row(0.30, 0.0, -FRAC_PI_2), // 4: forearm 0.30 m to the wrist centre; passive
                row(0.0, 0.0, FRAC_PI_2),   // 5: passive
                row(0.0, 0.0, 0.0),         // 6: passive roll about the instrument axis
            ],
            joints: [JointCalibration::default(); JOINTS],
        }
    }
}

/// Why a kinematic configuration was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum KinematicsConfigError {
    /// A parameter is NaN or infinite.
    #[error("kinematics.{key}: must be a finite number, got {value}")]
    NotFinite {
        /// Config key, e.g. `dh[2].a_m`.
        key: &'static str,
        /// Offending value.
        value: f64,
    },
    /// A joint sign is neither +1 nor -1.
    #[error("kinematics.joints[{joint}].sign: must be 1 or -1, got {value}")]
    BadSign {
        /// Joint index, 0-based.
        joint: usize,
        /// Offending value.
        value: f64,
    },
    /// A length is larger than any plausible arm (10 m).
    #[error("kinematics.{key}: |value| must be at most 10 m, got {value}")]
    Implausible {
        /// Config key.
        key: &'static str,
        /// Offending value, metres.
        value: f64,
    },
}

/// Why one forward-kinematics evaluation failed.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum ForwardError {
    /// A joint angle is NaN or infinite.
    #[error("joint {joint} angle is not finite")]
    NonFiniteJoint {
        /// Joint index, 0-based.
        joint: usize,
    },
}

/// Output of the forward kinematics for one sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WristPose {
    /// Wrist centre P, metres, robot base frame.
    pub wrist_base_m: Vector3<f64>,
    /// Instrument axis z (unit vector from the wrist towards the instrument tip), robot base frame.
    pub axis_base: Vector3<f64>,
    /// Full pose of the last frame in the robot base frame (metres).
    pub flange_base: Isometry3<f64>,
}

const KEYS_D: [&str; JOINTS] = ["dh[0].d_m", "dh[1].d_m", "dh[2].d_m", "dh[3].d_m", "dh[4].d_m", "dh[5].d_m"];
const KEYS_A: [&str; JOINTS] = ["dh[0].a_m", "dh[1].a_m", "dh[2].a_m", "dh[3].a_m", "dh[4].a_m", "dh[5].a_m"];
const KEYS_ALPHA: [&str; JOINTS] =
    ["dh[0].alpha_rad", "dh[1].alpha_rad", "dh[2].alpha_rad", "dh[3].alpha_rad", "dh[4].alpha_rad", "dh[5].alpha_rad"];
const KEYS_THETA: [&str; JOINTS] = [
    "dh[0].theta_offset_rad",
    "dh[1].theta_offset_rad",
    "dh[2].theta_offset_rad",
    "dh[3].theta_offset_rad",
    "dh[4].theta_offset_rad",
    "dh[5].theta_offset_rad",
];
const KEYS_ZERO: [&str; JOINTS] = [
    "joints[0].zero_offset_rad",
    "joints[1].zero_offset_rad",
    "joints[2].zero_offset_rad",
    "joints[3].zero_offset_rad",
    "joints[4].zero_offset_rad",
    "joints[5].zero_offset_rad",
];

impl AchillesConfig {
    /// Checks every parameter; the error names the offending key.
    pub fn validate(&self) -> Result<(), KinematicsConfigError> {
        for i in 0..JOINTS {
            let r = &self.dh[i];
            for (key, value, is_length) in [
                (KEYS_D[i], r.d_m, true),
                (KEYS_A[i], r.a_m, true),
                (KEYS_ALPHA[i], r.alpha_rad, false),
                (KEYS_THETA[i], r.theta_offset_rad, false),
                (KEYS_ZERO[i], self.joints[i].zero_offset_rad, false),
            ] {
                if !value.is_finite() {
                    return Err(KinematicsConfigError::NotFinite { key, value });
                }
                if is_length && value.abs() > 10.0 {
                    return Err(KinematicsConfigError::Implausible { key, value });
                }
            }
            let s = self.joints[i].sign;
            if s != 1.0 && s != -1.0 {
                return Err(KinematicsConfigError::BadSign { joint: i, value: s });
            }
        }
        Ok(())
    }
}

/// A validated Achilles-type arm, ready for allocation-free forward kinematics.
#[derive(Clone, Copy, Debug)]
pub struct Achilles {
    config: AchillesConfig,
}

impl Achilles {
    /// Validates `config` and builds the model.
    ///
    /// **Not for the real-time loop:** validates the configuration; call it at start-up.
    pub fn new(config: &AchillesConfig) -> Result<Self, KinematicsConfigError> {
        config.validate()?;
        Ok(Self { config: *config })
    }

    /// The parameters this model was built from.
    pub fn config(&self) -> &AchillesConfig {
        &self.config
    }

    /// DH angle (radians) of joint `i` for the measured angle `q_rad`.
    #[inline]
    pub fn dh_angle(&self, i: usize, q_rad: f64) -> f64 {
        let j = &self.config.joints[i];
        j.sign * q_rad + j.zero_offset_rad + self.config.dh[i].theta_offset_rad
    }

    /// Measured angle (radians) of joint `i` that gives the DH angle `theta_rad` (inverse of [`Self::dh_angle`]).
    #[inline]
    pub fn measured_angle(&self, i: usize, theta_rad: f64) -> f64 {
        let j = &self.config.joints[i];
        (theta_rad - j.zero_offset_rad - self.config.dh[i].theta_offset_rad) * j.sign
    }

    /// Pose of frame `i+1` relative to frame `i` for DH angle `theta_rad`.
    #[inline]
    fn link(row: &DhRow, theta_rad: f64) -> Isometry3<f64> {
        let rz = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), theta_rad);
        let rx = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), row.alpha_rad);
        // Rz(θ) Tz(d) Tx(a) Rx(α) = translation Rz(θ)·(a, 0, d), rotation Rz(θ)·Rx(α)
        let t = rz * Vector3::new(row.a_m, 0.0, row.d_m);
        Isometry3::from_parts(Translation3::from(t), rz * rx)
    }

    /// Forward kinematics from measured joint angles (radians) to the instrument line.
    /// Allocation-free.
    ///
    /// **Real-time (1 kHz loop):** called every cycle; allocation-free, no I/O, bounded time.
    pub fn forward(&self, q_rad: &[f64; JOINTS]) -> Result<WristPose, ForwardError> {
        let mut pose = Isometry3::identity();
        for (i, &q) in q_rad.iter().enumerate() {
            if !q.is_finite() {
                return Err(ForwardError::NonFiniteJoint { joint: i });
            }
            pose *= Self::link(&self.config.dh[i], self.dh_angle(i, q));
        }
        Ok(WristPose {
            wrist_base_m: pose.translation.vector,
            axis_base: pose.rotation * Vector3::z(),
            flange_base: pose,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use core::f64::consts::FRAC_PI_2;

    fn arm() -> Achilles {
        Achilles::new(&AchillesConfig::default()).unwrap()
    }

    #[test]
    fn zero_pose_matches_hand_computation() {
        let pose = arm().forward(&[0.0; 6]).unwrap();
        // Frame 1: origin (0, 0, 0.35), Rx(+90°): y1 = z0, z1 = -y0.
        // Frame 2: origin (0.30, 0, 0.35), same axes. Frame 3: Rx(+90°) again: z3 = -y2 = -z0.
        // The wrist centre is 0.30 m along z3: P = (0.30, 0, 0.05).
        assert!((pose.wrist_base_m - Vector3::new(0.30, 0.0, 0.05)).norm() < 1e-12, "{}", pose.wrist_base_m);
        assert!((pose.axis_base.norm() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn wrist_centre_does_not_depend_on_passive_joints() {
        let a = arm();
        let p0 = a.forward(&[0.3, 0.8, 0.5, 0.0, 0.0, 0.0]).unwrap();
        let p1 = a.forward(&[0.3, 0.8, 0.5, 1.1, -0.7, 2.0]).unwrap();
        assert!((p0.wrist_base_m - p1.wrist_base_m).norm() < 1e-12);
        assert!((p0.axis_base - p1.axis_base).norm() > 0.1, "passive joints must orient the axis");
    }

    #[test]
    fn roll_joint_does_not_move_the_axis() {
        let a = arm();
        let p0 = a.forward(&[0.3, 0.8, 0.5, 0.4, 0.6, 0.0]).unwrap();
        let p1 = a.forward(&[0.3, 0.8, 0.5, 0.4, 0.6, 1.5]).unwrap();
        assert!((p0.axis_base - p1.axis_base).norm() < 1e-12);
    }

    #[test]
    fn full_reach_is_upper_arm_plus_forearm() {
        // Elbow straight: q3 = +90° aligns the forearm with the upper arm (at q3 = 0 it hangs down).
        let pose = arm().forward(&[0.0, 0.0, FRAC_PI_2, 0.0, 0.0, 0.0]).unwrap();
        let shoulder = Vector3::new(0.0, 0.0, 0.35);
        assert!(((pose.wrist_base_m - shoulder).norm() - 0.60).abs() < 1e-12, "{}", pose.wrist_base_m);
    }

    #[test]
    fn sign_and_zero_offset_are_applied() {
        let mut cfg = AchillesConfig::default();
        cfg.joints[0] = JointCalibration { sign: -1.0, zero_offset_rad: 0.2 };
        let flipped = Achilles::new(&cfg).unwrap();
        let q = [0.5, 0.7, 0.3, 0.1, 0.2, 0.3];
        let mut q_ref = q;
        q_ref[0] = -0.5 + 0.2;
        let a = flipped.forward(&q).unwrap();
        let b = arm().forward(&q_ref).unwrap();
        assert!((a.wrist_base_m - b.wrist_base_m).norm() < 1e-12);
        assert!((flipped.measured_angle(0, flipped.dh_angle(0, 0.5)) - 0.5).abs() < 1e-15);
    }

    #[test]
    fn non_finite_joint_is_an_error() {
        assert_eq!(arm().forward(&[0.0, f64::NAN, 0.0, 0.0, 0.0, 0.0]), Err(ForwardError::NonFiniteJoint { joint: 1 }));
    }

    #[test]
    fn invalid_configs_name_their_key() {
        let mut c = AchillesConfig::default();
        c.dh[2].a_m = f64::NAN;
        assert!(matches!(c.validate(), Err(KinematicsConfigError::NotFinite { key: "dh[2].a_m", .. })));
        let mut c = AchillesConfig::default();
        c.joints[4].sign = 0.5;
        assert_eq!(c.validate(), Err(KinematicsConfigError::BadSign { joint: 4, value: 0.5 }));
        let mut c = AchillesConfig::default();
        c.dh[3].d_m = 42.0;
        assert!(matches!(c.validate(), Err(KinematicsConfigError::Implausible { key: "dh[3].d_m", .. })));
    }
}
