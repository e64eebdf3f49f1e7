//! What the renderer draws at one instant: the endoscope arm's joints and the instruments'
//! poses and joint angles; and [`DemoMotion`], a smooth deterministic motion of the
//! endoscope and two instruments about their trocars, for the `simrobot render` command,
//! the sample images and the tests.
//!
//! World frame: `{e}`, the endoscope arm's remote centre of motion (`docs/calibration.md`),
//! metres. The instruments move like the calibration's PSM-like arm about their own trocar
//! (RCM): `T_e_i = T_e_t · F3(yaw, pitch, insertion) · Rz(roll)`
//! ([`estimator::calib::rcm_arms::psm_frames`]).

use estimator::calib::rcm_arms::psm_frames;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// One instrument at one instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InstrumentState {
    /// `T_e_i`: the instrument frame `{i}` (origin at the shaft's distal end on its axis, `z`
    /// toward the tip; `sim::endoscope::mesh`) in the world `{e}`, metres.
    pub pose_world: Isometry3<f64>,
    /// Wrist pitch, radians.
    pub wrist_rad: f64,
    /// Jaw angles (jaw 1, jaw 2), radians, ≥ 0 open.
    pub jaw_rad: [f64; 2],
    /// The arm's joints `[yaw rad, pitch rad, insertion m, roll rad]` when the pose came from
    /// them (reported in the ground truth; the pose is what is drawn).
    pub psm_joints: Option<[f64; 4]>,
}

impl InstrumentState {
    /// An instrument held by an RCM arm whose RCM frame `{t}` is `t_e_t` in the world:
    /// `T_e_i = T_e_t · F3(q) · Rz(roll)`, `q = [yaw rad, pitch rad, insertion m, roll rad]`.
    pub fn from_rcm_arm(t_e_t: &Isometry3<f64>, q: [f64; 4], wrist_rad: f64, jaw_rad: [f64; 2]) -> Self {
        let f3 = psm_frames(&[q[0], q[1], q[2]])[2];
        let roll = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), q[3]);
        Self { pose_world: t_e_t * f3 * roll, wrist_rad, jaw_rad, psm_joints: Some(q) }
    }

    /// True when every number is finite.
    pub fn is_finite(&self) -> bool {
        let t = self.pose_world.translation.vector;
        let q = self.pose_world.rotation.quaternion();
        t.iter().all(|v| v.is_finite())
            && q.coords.iter().all(|v| v.is_finite())
            && self.wrist_rad.is_finite()
            && self.jaw_rad.iter().all(|v| v.is_finite())
    }
}

/// The scene at one instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneState {
    /// Endoscope arm joints `[yaw rad, pitch rad, insertion m, roll rad]` (ECM model).
    pub ecm_joints: [f64; 4],
    /// The instrument (label 1 in the mask).
    pub instrument: InstrumentState,
    /// The second instrument (label 2), drawn when the realism option is on.
    pub second: Option<InstrumentState>,
}

/// A smooth, deterministic scene motion: sums of sines, periods of seconds.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DemoMotion {
    /// Speed factor (1: a calm surgeon, tip speeds of a few cm/s; 4: a quick move).
    pub speed: f64,
    /// Phase offset, seconds (another stretch of the same motion).
    pub phase_s: f64,
}

impl Default for DemoMotion {
    fn default() -> Self {
        Self { speed: 1.0, phase_s: 0.0 }
    }
}

/// An RCM frame at `rcm` (world, metres) whose `z` axis aims at `target`, twisted by `twist`
/// radians about it.
fn aimed(rcm: Vector3<f64>, target: Vector3<f64>, twist: f64) -> Isometry3<f64> {
    let aim = (target - rcm).normalize();
    let r = UnitQuaternion::rotation_between(&Vector3::z(), &aim).unwrap_or_else(UnitQuaternion::identity)
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), twist);
    Isometry3::from_parts(Translation3::from(rcm), r)
}

impl DemoMotion {
    /// Trocar (RCM frame) of the instrument in `{e}`: 8 cm to the side of the endoscope's,
    /// aimed at a point 7 cm in front of the endoscope at its mean insertion.
    pub fn instrument_rcm() -> Isometry3<f64> {
        aimed(Vector3::new(0.078, -0.012, 0.03), Vector3::new(0.0, 0.006, 0.125), 0.3)
    }

    /// Trocar of the second instrument, on the other side, aimed a bit nearer the endoscope
    /// so that it crosses in front of the first.
    pub fn second_rcm() -> Isometry3<f64> {
        aimed(Vector3::new(-0.07, 0.035, 0.03), Vector3::new(0.012, -0.006, 0.112), -0.5)
    }

    /// The scene at time `t_ns` (nanoseconds on the caller's clock).
    pub fn state_at(&self, t_ns: u64) -> SceneState {
        let t = (t_ns as f64 * 1e-9 + self.phase_s) * self.speed;
        let w = |f: f64, p: f64| (std::f64::consts::TAU * f * t + p).sin();
        let ecm = [0.04 * w(0.05, 0.0), 0.03 * w(0.04, 1.0), 0.055 + 0.006 * w(0.03, 2.0), 0.05 * w(0.02, 0.5)];
        let d1 = (Vector3::new(0.0, 0.006, 0.125) - Self::instrument_rcm().translation.vector).norm();
        let q1 = [0.11 * w(0.23, 0.0), 0.09 * w(0.31, 1.0), d1 - 0.012 + 0.012 * w(0.17, 0.4), 0.6 * w(0.11, 0.0)];
        let inst = InstrumentState::from_rcm_arm(
            &Self::instrument_rcm(),
            q1,
            0.45 * w(0.4, 0.3),
            [0.25 * (1.0 + w(0.5, 0.0)), 0.25 * (1.0 + w(0.5, 0.0))],
        );
        let d2 = (Vector3::new(0.012, -0.006, 0.112) - Self::second_rcm().translation.vector).norm();
        let q2 = [0.16 * w(0.13, 2.0), 0.12 * w(0.19, 0.0), d2 - 0.01 + 0.01 * w(0.21, 1.0), 0.3 * w(0.07, 0.0)];
        let second = InstrumentState::from_rcm_arm(&Self::second_rcm(), q2, 0.3 * w(0.3, 1.0), [0.2, 0.2]);
        SceneState { ecm_joints: ecm, instrument: inst, second: Some(second) }
    }
}
