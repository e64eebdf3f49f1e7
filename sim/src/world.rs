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
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

use crate::endoscope::config::EndoscopeConfig;
use crate::endoscope::output::{OutputError, write_mask_png, write_png};
use crate::endoscope::render::{Occluder, StereoFrame, label};
use crate::endoscope::{
    InstrumentGeometry, InstrumentMesh, InstrumentState, SceneState, StereoRenderer, frame_mid_time_ns,
};
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
    /// Jaw pivot of the rendered instrument in `{i}` (its wrist link's length), metres.
    wrist_m: f64,
    /// The second instrument's trocar in `{e}` (set at the first recorded sample when the
    /// second instrument is on), metres.
    second_trocar: Option<Vector3<f64>>,
    /// A second instrument is in the scene.
    second: bool,
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
            wrist_m: instrument.wrist_length_m,
            second_trocar: None,
            second: false,
        })
    }

    /// Adds a second instrument (`false`: none), clutter that crosses in front of the tool
    /// arm's instrument: its trocar is the mirror image, through the endoscope arm's axis
    /// (`z` of `{e}`), of the point 12 cm behind the instrument's tip at the first recorded
    /// sample; its jaw pivot moves about the instrument's tip, 2.5 cm nearer the endoscope
    /// (along `−z` of `{e}`), by sines of 2 cm and 1.5 cm (periods 7.7 s and 5.3 s), the
    /// depth by 1 cm (9.1 s), its roll by 0.3 rad; jaws 0.2 rad. The renderer draws it when
    /// `realism.second_instrument` is on.
    pub fn set_second_instrument(&mut self, on: bool) {
        self.second = on;
    }

    fn second_at(&self, t_ns: u64, tool: &Isometry3<f64>) -> Option<InstrumentState> {
        let trocar = self.second_trocar?;
        let origin = self.history.front().map_or(t_ns, |s| s.t_ns);
        let t = t_ns.saturating_sub(origin) as f64 * 1e-9;
        let w = |period: f64, phase: f64| (std::f64::consts::TAU * t / period + phase).sin();
        let tip = (tool * nalgebra::Point3::new(0.0, 0.0, self.wrist_m)).coords;
        let target = tip + Vector3::new(0.02 * w(7.7, 0.0), 0.015 * w(5.3, 1.0), -0.025 + 0.01 * w(9.1, 2.0));
        let aim = target - trocar;
        let dir = aim.try_normalize(1e-9)?;
        let r = UnitQuaternion::rotation_between(&Vector3::z(), &dir).unwrap_or_else(UnitQuaternion::identity)
            * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3 * w(6.1, 0.5));
        let origin_i = target - dir * self.wrist_m;
        Some(InstrumentState {
            pose_world: Isometry3::from_parts(Translation3::from(origin_i), r),
            wrist_rad: 0.0,
            jaw_rad: [JAW_RAD; 2],
            psm_joints: None,
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
        if self.second && self.second_trocar.is_none() {
            let back = (s.instrument_in_ecm * nalgebra::Point3::new(0.0, 0.0, self.wrist_m - 0.12)).coords;
            self.second_trocar = Some(Vector3::new(-back.x, -back.y, back.z));
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
            Some(b) if k > 0 && t_ns > a.t_ns && b.t_ns > a.t_ns => {
                let u = (t_ns - a.t_ns) as f64 / (b.t_ns - a.t_ns) as f64;
                let ecm = core::array::from_fn(|j| a.ecm_joints[j] + (b.ecm_joints[j] - a.ecm_joints[j]) * u);
                (ecm, a.instrument_in_ecm.lerp_slerp(&b.instrument_in_ecm, u))
            }
            _ => (a.ecm_joints, a.instrument_in_ecm),
        };
        let instrument = InstrumentState { pose_world: pose, wrist_rad: 0.0, jaw_rad: [JAW_RAD; 2], psm_joints: None };
        let second = if self.second { self.second_at(t_ns, &pose) } else { None };
        Some(SceneState { ecm_joints: ecm, instrument, second })
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
/// 40 cm square of it, the light's reference distance 18 cm (the tissue is 21 cm from the
/// camera at the default insertion, twice the renderer's default working distance), and
/// without the second instrument.
pub fn default_endoscope_config() -> EndoscopeConfig {
    let mut c = EndoscopeConfig::default();
    c.light.reference_distance_m = 0.18;
    c.tissue.plane_z_m = 0.27;
    c.tissue.extent_m = 0.40;
    c.realism.second_instrument = false;
    c
}

/// A time window during which an occluder plate ([`Occluder`]) hides about `fraction` of
/// the instrument in the left eye ([`occluder_for`]); times in seconds from the first frame's
/// mid time. Written `START:DURATION:FRACTION[:tip|:shaft]` on the command line (`simrobot
/// generate --occlude 3:1:0.5`; the tip end hidden first unless `:shaft`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct OcclusionWindow {
    /// Start, seconds from the first frame.
    pub start_s: f64,
    /// Duration, seconds.
    pub duration_s: f64,
    /// Fraction of the instrument's visible length to hide (`1`: all of it).
    pub fraction: f64,
    /// Which end is hidden first: `false` the tip end (jaws, wrist, then the shaft), `true`
    /// the shaft's end (where it leaves the image), leaving the tip in view.
    pub from_shaft_end: bool,
}

impl OcclusionWindow {
    /// `true` when `t_s` (seconds from the first frame) lies in the window.
    pub fn contains(&self, t_s: f64) -> bool {
        t_s >= self.start_s && t_s < self.start_s + self.duration_s
    }
}

/// A malformed `--occlude` value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "occlusion window {0:?}: expected START_S:DURATION_S:FRACTION[:tip|:shaft], start and duration finite and >= 0, fraction in (0, 1]"
)]
pub struct OcclusionWindowError(pub String);

impl std::str::FromStr for OcclusionWindow {
    type Err = OcclusionWindowError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let err = || OcclusionWindowError(s.to_string());
        let mut parts: Vec<&str> = s.split(':').map(str::trim).collect();
        let from_shaft_end = match parts.last() {
            Some(&"shaft") => true,
            Some(&"tip") => false,
            _ => {
                parts.push("tip");
                false
            }
        };
        parts.pop();
        let v: Vec<f64> = parts.iter().map(|x| x.parse::<f64>().map_err(|_| err())).collect::<Result<_, _>>()?;
        let [start_s, duration_s, fraction] = v[..] else { return Err(err()) };
        let ok = start_s.is_finite()
            && start_s >= 0.0
            && duration_s.is_finite()
            && duration_s >= 0.0
            && fraction.is_finite()
            && fraction > 0.0
            && fraction <= 1.0;
        if !ok {
            return Err(err());
        }
        Ok(Self { start_s, duration_s, fraction, from_shaft_end })
    }
}

/// An occluder plate hiding about `fraction` of the instrument in the left eye at `scene`
/// (mid time), tip end first (or the shaft's end first with `from_shaft_end`): the instrument's axis from the jaw tips back along the shaft
/// is sampled every millimetre, the samples in the left image weighted by their image length
/// over their depth (≈ the pixels they cover), and the plate covers the samples from the tip
/// end up to `fraction` of the weight. The plate lies in the plane `z = 0.8·(z_min − 5 mm)`
/// of the left eye (in front of what it covers), perpendicular to the optical axis, its long
/// side along the covered part's image, with a margin for the right eye's other disparity
/// (and 6 px); with `fraction = 1` it reaches 3 cm beyond the last visible sample. The
/// instrument's true visible fraction is the renderer's ground truth
/// ([`crate::endoscope::Visibility`]). `None` when the instrument is out of the left image or
/// too near the camera.
pub fn occluder_for(
    renderer: &StereoRenderer,
    scene: &SceneState,
    fraction: f64,
    from_shaft_end: bool,
) -> Option<Occluder> {
    if !(fraction.is_finite() && fraction > 0.0) {
        return None;
    }
    let cfg = renderer.config();
    let g = &cfg.instrument;
    let eyes = renderer.eye_poses(&scene.ecm_joints);
    let t_c_e = eyes[0].inverse();
    let t_c_i = t_c_e * scene.instrument.pose_world;
    let top = g.wrist_length_m + g.jaw_length_m;
    let n = ((top + g.shaft_length_m) / 0.001).ceil() as usize;
    let mut pts: Vec<(Vector3<f64>, f64)> = Vec::new();
    let mut prev: Option<nalgebra::Vector2<f64>> = None;
    for k in 0..=n {
        let p_i = nalgebra::Point3::new(0.0, 0.0, top - 0.001 * k as f64);
        let p_e = scene.instrument.pose_world * p_i;
        let Some(px) = renderer.project_world(&eyes[0], &p_e.coords) else {
            prev = None;
            continue;
        };
        let p_c = (t_c_i * p_i).coords;
        let w = prev.map_or(0.0, |q| (px - q).norm()) / p_c.z;
        pts.push((p_c, w));
        prev = Some(px);
    }
    if from_shaft_end {
        // Weights belong to the step toward the previous sample: shift them with the order.
        let w: Vec<f64> = pts.iter().map(|p| p.1).collect();
        pts.reverse();
        for (i, p) in pts.iter_mut().enumerate() {
            p.1 = if i == 0 { 0.0 } else { w[w.len() - i] };
        }
    }
    let total: f64 = pts.iter().map(|p| p.1).sum();
    let (first, _) = *pts.first()?;
    if total.is_nan() || total <= 0.0 {
        return None;
    }
    let mut cut = pts.len() - 1;
    let mut cum = 0.0;
    if fraction < 1.0 {
        for (i, p) in pts.iter().enumerate() {
            cum += p.1;
            if cum >= fraction * total {
                cut = i;
                break;
            }
        }
    }
    let covered = &pts[..=cut];
    let z_min = covered.iter().map(|p| p.0.z).fold(f64::INFINITY, f64::min);
    let z_max = covered.iter().map(|p| p.0.z).fold(0.0, f64::max);
    let z_p = 0.8 * (z_min - 0.005);
    if z_p.is_nan() || z_p <= 0.005 {
        return None;
    }
    let k = &cfg.camera.intrinsics;
    let m_px = k.fx * cfg.camera.baseline_m * (1.0 / z_p - 1.0 / z_max) + 6.0;
    let m = m_px * z_p / k.fx;
    let a = first * (z_p / first.z);
    let b = pts[cut].0 * (z_p / pts[cut].0.z);
    let len = (b - a).norm();
    let d = if len > 1e-6 { (b - a) / len } else { Vector3::x() };
    let e = Vector3::z().cross(&d).normalize();
    let tip_end = a - d * m;
    let cut_end = if fraction >= 1.0 { b + d * (m + 0.03) } else { b };
    let centre = (tip_end + cut_end) / 2.0;
    let half_along = (cut_end - tip_end).norm() / 2.0;
    let half_across = (g.shaft_radius_m() + 0.004) * z_p / z_min + m;
    let rot = nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[d, e, Vector3::z()]));
    let in_camera = Isometry3::from_parts(Translation3::from(centre), UnitQuaternion::from_rotation_matrix(&rot));
    Some(Occluder {
        pose_world: eyes[0] * in_camera,
        half_size_m: [half_along.max(1e-4), half_across.max(1e-4)],
        material: Occluder::GAUZE,
    })
}

/// Pixels of the instrument (label 1) visible in eye `eye` (0 left, 1 right) of a rendered
/// frame.
pub fn instrument_pixels(frame: &StereoFrame, eye: usize) -> u64 {
    frame.images.get(eye).map_or(0, |img| img.labels.iter().filter(|&&l| l == label::INSTRUMENT).count() as u64)
}

/// Value of the `format` field of the frames' ground-truth header.
pub const FRAMES_FORMAT: &str = "comanip-world-frames";

/// Version of the frames' ground-truth format.
pub const FRAMES_VERSION: u32 = 1;

/// Why frames could not be rendered or written.
#[derive(Debug, thiserror::Error)]
pub enum FramesError {
    /// Rendering, PNG encoding or file output failed.
    #[error(transparent)]
    Output(#[from] OutputError),
    /// The world has no sample yet.
    #[error("no sample of the world recorded yet")]
    NoSample,
}

#[derive(Serialize)]
struct FramesHeader<'a> {
    #[serde(rename = "type")]
    kind: &'static str,
    format: &'static str,
    version: u32,
    /// Mid time of frame 0, nanoseconds on the bus clock.
    t0_ns: u64,
    fps: f64,
    rcm_in_tool_base: &'a crate::endoscope::config::PoseConfig,
    config: &'a EndoscopeConfig,
}

#[derive(Serialize)]
struct FramesLine<'a> {
    #[serde(rename = "type")]
    kind: &'static str,
    index: u64,
    t_mid_ns: u64,
    unix_time_us: u64,
    sample: u64,
    ecm_joints: [f64; ECM_JOINTS],
    tool_joints: [f64; 6],
    instrument_px: [u64; 2],
    /// The occluder window's fraction when one covers this frame.
    #[serde(skip_serializing_if = "Option::is_none")]
    occlusion_target: Option<f64>,
    files: [&'a str; 4],
    left: &'a crate::endoscope::EyeTruth,
    right: &'a crate::endoscope::EyeTruth,
}

#[derive(Serialize)]
struct FramesEnd {
    #[serde(rename = "type")]
    kind: &'static str,
    frames: u64,
    frames_with_instrument: u64,
}

/// One frame written by [`FrameWriter::write_next`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameInfo {
    /// Frame index from 0.
    pub index: u64,
    /// Exposure's mid time, nanoseconds on the bus clock.
    pub t_mid_ns: u64,
    /// Instrument pixels visible in the left and right masks.
    pub instrument_px: [u64; 2],
}

/// Smallest number of instrument pixels in the left image for a frame to count as showing
/// the instrument (in [`FrameWriter::frames_with_instrument`]).
pub const VISIBLE_MIN_PX: u64 = 20;

/// Renders stereo frames of a [`World`] at a fixed rate and writes them with their ground
/// truth: `DIR/frame_NNNNNN_{left,right}.png`, `DIR/frame_NNNNNN_{left,right}_mask.png` and
/// `DIR/truth.jsonl` (`header`, one `frame` line per frame with the bus time, both arms'
/// joints, the visible instrument pixels and each eye's [`crate::endoscope::EyeTruth`];
/// `end`). Frame `n`'s exposure is centred on `t0_ns + round(n·10⁹/fps)` (bus clock,
/// nanoseconds).
pub struct FrameWriter {
    dir: std::path::PathBuf,
    renderer: StereoRenderer,
    frame: StereoFrame,
    truth: BufWriter<File>,
    truth_path: std::path::PathBuf,
    t0_ns: u64,
    fps: f64,
    half_exposure_ns: u64,
    next: u64,
    with_instrument: u64,
    index: BufWriter<File>,
    index_path: std::path::PathBuf,
    exposure_ns: u64,
    occlusions: Vec<OcclusionWindow>,
}

impl FrameWriter {
    /// Creates `dir` and its `truth.jsonl` (header written) for frames from `t0_ns` (bus
    /// clock, nanoseconds) at `cfg.timing.fps`, the endoscope arm's RCM at `rcm_in_tool_base`.
    pub fn new(
        dir: &Path,
        cfg: &EndoscopeConfig,
        mesh: InstrumentMesh,
        t0_ns: u64,
        rcm_in_tool_base: &crate::endoscope::config::PoseConfig,
    ) -> Result<Self, FramesError> {
        std::fs::create_dir_all(dir).map_err(|source| OutputError::Io { path: dir.to_owned(), source })?;
        let renderer = StereoRenderer::new(cfg.clone(), mesh).map_err(OutputError::from)?;
        let truth_path = dir.join("truth.jsonl");
        let io = |source| OutputError::Io { path: truth_path.clone(), source };
        let mut truth = BufWriter::new(File::create(&truth_path).map_err(io)?);
        let header = FramesHeader {
            kind: "header",
            format: FRAMES_FORMAT,
            version: FRAMES_VERSION,
            t0_ns,
            fps: cfg.timing.fps,
            rcm_in_tool_base,
            config: cfg,
        };
        serde_json::to_writer(&mut truth, &header)
            .map_err(|source| OutputError::Json { path: truth_path.clone(), source })?;
        truth.write_all(b"\n").map_err(io)?;
        // The frame index of an image-sequence directory (`comanip-camera images DIR`,
        // docs/frames.md) and the two eyes' ROS camera_info.
        let index_path = dir.join(hw_io::camera::image_sequence::DEFAULT_INDEX);
        let index_io = |source| OutputError::Io { path: index_path.clone(), source };
        let mut index = BufWriter::new(File::create(&index_path).map_err(index_io)?);
        index
            .write_all(b"# comanip frame index 1 (simrobot generate --frames; bus clock, ns)\n# t_mid_ns exposure_ns left.png right.png\n")
            .map_err(index_io)?;
        let k = &cfg.camera.intrinsics;
        for (name, baseline) in [("left.yaml", None), ("right.yaml", Some(cfg.camera.baseline_m))] {
            let path = dir.join(name);
            std::fs::write(&path, hw_io::calib_files::write_camera_info_yaml(name, k, baseline))
                .map_err(|source| OutputError::Io { path, source })?;
        }
        Ok(Self {
            dir: dir.to_owned(),
            renderer,
            frame: StereoFrame::default(),
            truth,
            truth_path,
            t0_ns,
            fps: cfg.timing.fps,
            half_exposure_ns: (cfg.timing.exposure_s * 0.5e9).round() as u64,
            next: 0,
            with_instrument: 0,
            index,
            index_path,
            exposure_ns: (cfg.timing.exposure_s * 1e9).round() as u64,
            occlusions: Vec::new(),
        })
    }

    /// Occluder windows of the next frames (times from the first frame): in a window, each
    /// frame gets the plate of [`occluder_for`] placed at its mid time.
    pub fn set_occlusions(&mut self, windows: Vec<OcclusionWindow>) {
        self.occlusions = windows;
    }

    /// Mid time of the next frame's exposure, nanoseconds on the bus clock.
    pub fn next_mid_ns(&self) -> u64 {
        frame_mid_time_ns(self.t0_ns, self.fps, self.next)
    }

    /// `true` when `world` has recorded samples up to the end of the next frame's exposure.
    pub fn ready(&self, world: &World) -> bool {
        world.history.back().is_some_and(|s| s.t_ns >= self.next_mid_ns().saturating_add(self.half_exposure_ns))
    }

    /// Frames per second.
    pub fn fps(&self) -> f64 {
        self.fps
    }

    /// Frames written so far.
    pub fn frames(&self) -> u64 {
        self.next
    }

    /// Frames so far with at least [`VISIBLE_MIN_PX`] instrument pixels in the left image.
    pub fn frames_with_instrument(&self) -> u64 {
        self.with_instrument
    }

    /// Renders and writes the next frame from `world` (call when [`FrameWriter::ready`]).
    pub fn write_next(&mut self, world: &World) -> Result<FrameInfo, FramesError> {
        let t = self.next_mid_ns();
        let mid = world.scene_at(t).ok_or(FramesError::NoSample)?;
        let sample = *world.sample_at(t).ok_or(FramesError::NoSample)?;
        let scene = |at: u64| world.scene_at(at).unwrap_or(mid);
        let rel_s = t.saturating_sub(self.t0_ns) as f64 * 1e-9;
        let window = self.occlusions.iter().find(|w| w.contains(rel_s)).copied();
        let target = window.map(|w| w.fraction);
        let occluder = window.and_then(|w| occluder_for(&self.renderer, &mid, w.fraction, w.from_shaft_end));
        self.renderer.set_occluder(occluder);
        self.renderer.render_into(t, &scene, &mut self.frame).map_err(OutputError::from)?;
        let n = self.next;
        let names = [
            format!("frame_{n:06}_left.png"),
            format!("frame_{n:06}_right.png"),
            format!("frame_{n:06}_left_mask.png"),
            format!("frame_{n:06}_right_mask.png"),
        ];
        for eye in 0..2 {
            write_png(&self.dir.join(&names[eye]), &self.frame.images[eye])?;
            write_mask_png(&self.dir.join(&names[2 + eye]), &self.frame.images[eye])?;
        }
        let px = [instrument_pixels(&self.frame, 0), instrument_pixels(&self.frame, 1)];
        let line = FramesLine {
            kind: "frame",
            index: n,
            t_mid_ns: t,
            unix_time_us: t / 1000,
            sample: sample.sample,
            ecm_joints: mid.ecm_joints,
            tool_joints: sample.tool_joints,
            instrument_px: px,
            occlusion_target: target,
            files: [&names[0], &names[1], &names[2], &names[3]],
            left: &self.frame.truth[0],
            right: &self.frame.truth[1],
        };
        let json = |source| OutputError::Json { path: self.truth_path.clone(), source };
        let io = |source| OutputError::Io { path: self.truth_path.clone(), source };
        serde_json::to_writer(&mut self.truth, &line).map_err(json)?;
        self.truth.write_all(b"\n").map_err(io)?;
        writeln!(self.index, "{t} {} {} {}", self.exposure_ns, names[0], names[1])
            .map_err(|source| OutputError::Io { path: self.index_path.clone(), source })?;
        self.next += 1;
        self.with_instrument += u64::from(px[0] >= VISIBLE_MIN_PX);
        Ok(FrameInfo { index: n, t_mid_ns: t, instrument_px: px })
    }

    fn line(&mut self, value: &impl Serialize) -> Result<(), FramesError> {
        serde_json::to_writer(&mut self.truth, value)
            .map_err(|source| OutputError::Json { path: self.truth_path.clone(), source })?;
        self.truth.write_all(b"\n").map_err(|source| OutputError::Io { path: self.truth_path.clone(), source })?;
        Ok(())
    }

    /// Writes the `end` line and flushes the ground truth.
    pub fn finish(mut self) -> Result<(), FramesError> {
        let end = FramesEnd { kind: "end", frames: self.next, frames_with_instrument: self.with_instrument };
        self.line(&end)?;
        self.truth.flush().map_err(|source| OutputError::Io { path: self.truth_path.clone(), source })?;
        self.index.flush().map_err(|source| OutputError::Io { path: self.index_path.clone(), source })?;
        Ok(())
    }
}
