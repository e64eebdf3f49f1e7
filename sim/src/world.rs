//! The two arms in one world: what the stereo endoscope on the endoscope-holder arm sees of
//! the tool arm's instrument, at any time on the bus clock.
//!
//! [`World`] records, sample by sample, the twin's ground truth ([`crate::twin::SimRobot`]:
//! the tool arm's true joints and flange pose, the endoscope arm's joints) and gives the
//! renderer's [`SceneState`] at a bus time ([`World::scene_at`]), interpolated between the
//! recorded samples (joints linearly, the instrument's pose by position and shortest
//! rotation). `simrobot generate --frames` renders with it; `simrobot live --camera` can
//! render in step with the live bus the same way (record each answered SYNC, render a frame
//! once the samples cover its exposure: [`World::covers`]).
//!
//! Frames (metres):
//! - `{b}` the tool arm's base frame (`docs/kinematics.md`); `{e}` the endoscope arm's RCM
//!   frame, the renderer's world (`docs/vision.md`); `T_b_e` is
//!   [`crate::endoscope_arm::EndoscopeArmConfig::rcm_in_tool_base`];
//! - the instrument `{i}` of the renderer (origin at the shaft's distal end, `z` toward the
//!   tip) is the tool arm's frame 6 (origin at the wrist centre P, `z` along the instrument)
//!   moved along its `z` by `instrument_length_m − wrist_length_m`, so that the rendered jaw
//!   pivot is the scenario's tip `P + L·z`: `T_e_i = T_b_e⁻¹ · T_b_6 · Tz(L − l_wrist)`.
//!
//! Times are nanoseconds on the bus clock: the candump log's timestamps (microseconds since
//! the Unix epoch) times 1000.

use std::collections::VecDeque;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use crate::endoscope::config::EndoscopeConfig;
use crate::endoscope::render::{StereoFrame, label};
use crate::endoscope::{InstrumentGeometry, InstrumentState, SceneState};
use crate::endoscope_arm::ECM_JOINTS;
use crate::twin::{SimRobot, TwinConfig};

/// Jaw opening of the rendered instrument, radians (each jaw; the tool arm has no jaw joint).
pub const JAW_RAD: f64 = 0.2;

/// Default span of the recorded history, nanoseconds (0.5 s: far more than one exposure).
pub const DEFAULT_KEEP_NS: u64 = 500_000_000;

/// One recorded sample of the world.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorldSample {
    /// Bus time of the sample's SYNC, nanoseconds.
    pub t_ns: u64,
    /// Sample index of the twin (0 = first SYNC answered).
    pub sample: u64,
    /// Endoscope arm joints `[yaw rad, pitch rad, insertion m, roll rad]`.
    pub ecm_joints: [f64; ECM_JOINTS],
    /// Tool arm's measured joint angles, radians (joints 1..6; the twin's true arm).
    pub tool_joints: [f64; 6],
    /// `T_e_i`: the rendered instrument frame in `{e}`, metres.
    pub instrument_in_ecm: Isometry3<f64>,
}

/// Why a [`World`] could not be built or could not record a sample.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum WorldError {
    /// The twin has no endoscope arm (`endoscope_arm.enabled = false`).
    #[error("the twin has no endoscope arm (endoscope_arm.enabled = false, or simrobot --no-endoscope)")]
    NoEndoscopeArm,
    /// `endoscope_arm.rcm_in_tool_base` is not a usable pose.
    #[error("endoscope_arm.rcm_in_tool_base: not a finite pose with a non-zero quaternion")]
    Pose,
    /// The twin has not answered a SYNC yet.
    #[error("the twin has answered no SYNC yet")]
    NoSample,
    /// The true forward kinematics failed (a non-finite joint).
    #[error("sample {0}: the tool arm's forward kinematics failed")]
    Kinematics(u64),
    /// A sample older than the last one recorded.
    #[error("sample at {t_ns} ns is older than the last recorded one ({last_ns} ns)")]
    Order {
        /// The time given, nanoseconds.
        t_ns: u64,
        /// The last recorded time, nanoseconds.
        last_ns: u64,
    },
}

/// The recent history of both arms and the scene at any covered time. See the module
/// documentation.
#[derive(Clone, Debug)]
pub struct World {
    ecm_from_base: Isometry3<f64>,
    shaft_end_m: f64,
    keep_ns: u64,
    history: VecDeque<WorldSample>,
}

impl World {
    /// A world for the twin configuration `twin` and the rendered instrument's dimensions
    /// `instrument`, keeping `keep_ns` nanoseconds of history (at least one sample).
    pub fn new(twin: &TwinConfig, instrument: &InstrumentGeometry, keep_ns: u64) -> Result<Self, WorldError> {
        if !twin.endoscope_arm.enabled {
            return Err(WorldError::NoEndoscopeArm);
        }
        let t_b_e = twin.endoscope_arm.rcm_in_tool_base().ok_or(WorldError::Pose)?;
        Ok(Self {
            ecm_from_base: t_b_e.inverse(),
            shaft_end_m: twin.scenario.instrument_length_m - instrument.wrist_length_m,
            keep_ns,
            history: VecDeque::with_capacity(1024),
        })
    }

    /// `T_e_b`: the tool arm's base frame in the endoscope arm's RCM frame, metres.
    pub fn ecm_from_tool_base(&self) -> &Isometry3<f64> {
        &self.ecm_from_base
    }

    /// Records the sample the twin answered last, its SYNC at `t_ns` on the bus clock
    /// (nanoseconds; not older than the previous one). Forgets samples older than the kept
    /// span. Returns the recorded sample.
    pub fn record(&mut self, t_ns: u64, robot: &SimRobot) -> Result<WorldSample, WorldError> {
        let (Some(sample), Some(q), Some(ecm)) = (robot.sample(), robot.joints_rad(), robot.endoscope_joints()) else {
            return Err(if robot.config().endoscope_arm.enabled {
                WorldError::NoSample
            } else {
                WorldError::NoEndoscopeArm
            });
        };
        if let Some(last) = self.history.back()
            && t_ns < last.t_ns
        {
            return Err(WorldError::Order { t_ns, last_ns: last.t_ns });
        }
        let flange = robot.arm().forward(q).map_err(|_| WorldError::Kinematics(sample))?.flange_base;
        let offset = Isometry3::from_parts(Translation3::new(0.0, 0.0, self.shaft_end_m), UnitQuaternion::identity());
        let s = WorldSample {
            t_ns,
            sample,
            ecm_joints: ecm,
            tool_joints: *q,
            instrument_in_ecm: self.ecm_from_base * flange * offset,
        };
        while self.history.front().is_some_and(|f| f.t_ns.saturating_add(self.keep_ns) < t_ns) && self.history.len() > 1
        {
            self.history.pop_front();
        }
        self.history.push_back(s);
        Ok(s)
    }

    /// The recorded samples, oldest first.
    pub fn history(&self) -> impl Iterator<Item = &WorldSample> {
        self.history.iter()
    }

    /// `true` when the recorded samples span `[from_ns, to_ns]` (a frame whose exposure lies
    /// in it can be rendered exactly).
    pub fn covers(&self, from_ns: u64, to_ns: u64) -> bool {
        match (self.history.front(), self.history.back()) {
            (Some(a), Some(b)) => a.t_ns <= from_ns && to_ns <= b.t_ns,
            _ => false,
        }
    }

    /// The latest recorded sample at or before `t_ns` (the first one before it), `None` when
    /// nothing is recorded.
    pub fn sample_at(&self, t_ns: u64) -> Option<&WorldSample> {
        let k = self.history.partition_point(|s| s.t_ns <= t_ns);
        self.history.get(k.saturating_sub(1))
    }

    /// The renderer's scene at `t_ns` (bus clock, nanoseconds): interpolated between the two
    /// recorded samples around it; before the first or after the last recorded sample, that
    /// sample (the world is taken as still). `None` when nothing is recorded.
    pub fn scene_at(&self, t_ns: u64) -> Option<SceneState> {
        let k = self.history.partition_point(|s| s.t_ns <= t_ns);
        let a = self.history.get(k.saturating_sub(1))?;
        let (ecm, pose) = match self.history.get(k) {
            Some(b) if k > 0 && b.t_ns > a.t_ns => {
                let u = (t_ns - a.t_ns) as f64 / (b.t_ns - a.t_ns) as f64;
                let ecm = core::array::from_fn(|j| a.ecm_joints[j] + (b.ecm_joints[j] - a.ecm_joints[j]) * u);
                (ecm, a.instrument_in_ecm.lerp_slerp(&b.instrument_in_ecm, u))
            }
            _ => (a.ecm_joints, a.instrument_in_ecm),
        };
        let instrument = InstrumentState { pose_world: pose, wrist_rad: 0.0, jaw_rad: [JAW_RAD; 2], psm_joints: None };
        Some(SceneState { ecm_joints: ecm, instrument, second: None })
    }

    /// The tip (jaw pivot, the scenario's `P + L·z`) of the instrument at sample `s`, metres,
    /// in `{e}`.
    pub fn tip_in_ecm(&self, s: &WorldSample, instrument: &InstrumentGeometry) -> Vector3<f64> {
        (s.instrument_in_ecm * nalgebra::Point3::new(0.0, 0.0, instrument.wrist_length_m)).coords
    }
}

/// The renderer configuration `simrobot generate --frames` uses by default: the renderer's
/// defaults, with the tissue 27 cm from the endoscope's RCM along its axis (11 cm below the
/// tool arm's default trocars, beyond the deepest instrument tips of the default twin), a
/// 40 cm square of it, and without the second instrument.
pub fn default_endoscope_config() -> EndoscopeConfig {
    let mut c = EndoscopeConfig::default();
    c.tissue.plane_z_m = 0.27;
    c.tissue.extent_m = 0.40;
    c.realism.second_instrument = false;
    c
}

/// Pixels of the instrument (label 1) visible in eye `eye` (0 left, 1 right) of a rendered
/// frame.
pub fn instrument_pixels(frame: &StereoFrame, eye: usize) -> u64 {
    frame.images.get(eye).map_or(0, |img| img.labels.iter().filter(|&&l| l == label::INSTRUMENT).count() as u64)
}
