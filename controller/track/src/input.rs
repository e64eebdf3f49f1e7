//! A recorded sequence: stereo frames, both arms' joints from the candump log matched to the
//! frames' mid-exposure times, the cameras, and (when the directory has it) the renderer's
//! ground truth for scoring.
//!
//! - Frames: `DIR/frames.txt` (`t_mid_ns exposure_ns left right`, bus clock, nanoseconds),
//!   as `simrobot generate --frames` and `comanip-camera images` use it.
//! - The tool arm (Achilles-type, nodes 1-3): the log through fulcrumd's own acquisition
//!   (`controller::replay::replay_candump`), joints linearly interpolated between the two
//!   complete cycles around the frame's time.
//! - The endoscope arm (nodes 4-5): `controller::replay::endoscope_joints`, interpolated.
//! - Cameras: each eye's `camera_info` YAML (`--cameras left.yaml right.yaml`; the right eye's
//!   `P` gives the baseline); the rig's hand-eye `T_f_c` and the endoscope arm's RCM in the tool
//!   arm's base `T_b_e` come from the calibration: for a simulated run, the header of
//!   `DIR/truth.jsonl` (`config.camera.hand_eye`, `rcm_in_tool_base`), i.e. an exact
//!   calibration; `g_CB` augmentation covers an inexact one.

use std::path::{Path, PathBuf};

use estimator::calib::Intrinsics;
use hw_io::calib_files::TransformJson;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use serde::Deserialize;

/// Both arms' readings farther apart than this around a frame do not give its joints, ns.
pub const MAX_GAP_NS: u64 = 25_000_000;

/// The renderer's ground truth of the tracked instrument in one frame (left eye).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameTruth {
    /// Tip (jaw pivot) in the left camera frame, metres.
    pub tip_camera_m: Vector3<f64>,
    /// The instrument's orientation in the left camera frame.
    pub rotation_camera: UnitQuaternion<f64>,
    /// Instrument pixels visible in the left and right masks.
    pub instrument_px: [u64; 2],
    /// The instrument's visible fraction in the left and right eyes (occlusion by the second
    /// instrument or the occluder plate; `None`: out of view or not in the truth file).
    pub visible_fraction: [Option<f64>; 2],
    /// The occluder window's target fraction when one covers this frame
    /// (`simrobot generate --occlude`).
    pub occlusion_target: Option<f64>,
}

/// One stereo frame of the sequence.
#[derive(Clone, Debug)]
pub struct SeqFrame {
    /// Index in `frames.txt`.
    pub index: usize,
    /// Mid-exposure time, nanoseconds on the bus clock.
    pub t_ns: u64,
    /// Left and right image files.
    pub files: [PathBuf; 2],
    /// The tool arm's joints from the encoders at `t_ns`, radians (`None`: no complete cycles
    /// around it).
    pub encoder_rad: Option<[f64; 6]>,
    /// The endoscope arm's joints at `t_ns` (`None`: no readings around it).
    pub ecm_joints: Option<[f64; 4]>,
    /// Ground truth, when the directory has it.
    pub truth: Option<FrameTruth>,
}

/// A sequence ready to track.
#[derive(Clone, Debug)]
pub struct Sequence {
    /// The frames, in order.
    pub frames: Vec<SeqFrame>,
    /// Left and right intrinsics.
    pub intrinsics: [Intrinsics; 2],
    /// `T_cr_cl`, metres.
    pub right_from_left: Isometry3<f64>,
    /// Hand-eye `T_f_c` of the left eye on the endoscope arm, metres.
    pub hand_eye: Isometry3<f64>,
    /// `T_b_e`: the endoscope arm's RCM frame in the tool arm's base, metres.
    pub ecm_in_tool_base: Isometry3<f64>,
    /// The rendered instrument's dimensions.
    pub instrument: sim::endoscope::InstrumentGeometry,
}

impl Sequence {
    /// `T_cl_b` (the paper's `g_CB`) for endoscope joints `q`.
    pub fn left_from_base(&self, q: &[f64; 4]) -> Isometry3<f64> {
        left_from_base(&self.ecm_in_tool_base, &self.hand_eye, q)
    }
}

/// `T_cl_b` (the paper's `g_CB`, metres): the tool arm's base in the left camera frame, from
/// `T_b_e` (the endoscope arm's RCM frame in the tool arm's base: the calibration), the
/// hand-eye `T_f_c` and the endoscope arm's joints `q` (`[yaw rad, pitch rad, insertion m,
/// roll rad]`). The offline run and the live process both use it.
pub fn left_from_base(ecm_in_tool_base: &Isometry3<f64>, hand_eye: &Isometry3<f64>, q: &[f64; 4]) -> Isometry3<f64> {
    let t_e_c = estimator::calib::rcm_arms::camera_pose(q, hand_eye);
    (ecm_in_tool_base * t_e_c).inverse()
}

/// Why a sequence cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum SequenceError {
    /// A file cannot be read or parsed.
    #[error("{path}: {message}")]
    File {
        /// The file.
        path: PathBuf,
        /// Why.
        message: String,
    },
    /// The candump log cannot be replayed.
    #[error("{path}: {source}")]
    Replay {
        /// The log.
        path: PathBuf,
        /// Why.
        source: controller::replay::ReplayError,
    },
    /// No frame listed.
    #[error("{0}: no frames listed")]
    NoFrames(PathBuf),
}

#[derive(Deserialize)]
struct CameraHeader {
    hand_eye: TransformJson,
}

#[derive(Deserialize)]
struct ConfigHeader {
    camera: CameraHeader,
    instrument: sim::endoscope::InstrumentGeometry,
}

#[derive(Deserialize)]
struct Header {
    rcm_in_tool_base: TransformJson,
    config: ConfigHeader,
}

#[derive(Deserialize)]
struct PoseJson {
    quaternion_wxyz: [f64; 4],
}

#[derive(Deserialize)]
struct InstrumentJson {
    label: u8,
    pose_in_camera: PoseJson,
    tip_camera_m: [f64; 3],
}

#[derive(Deserialize, Default, Clone, Copy)]
struct VisibilityJson {
    unoccluded_px: u64,
    visible_px: u64,
}

impl VisibilityJson {
    fn fraction(&self) -> Option<f64> {
        (self.unoccluded_px > 0).then(|| self.visible_px as f64 / self.unoccluded_px as f64)
    }
}

#[derive(Deserialize)]
struct EyeJson {
    instruments: Vec<InstrumentJson>,
    visibility: Option<VisibilityJson>,
}

#[derive(Deserialize)]
struct FrameJson {
    #[serde(rename = "type")]
    kind: String,
    #[serde(default)]
    index: usize,
    #[serde(default)]
    instrument_px: [u64; 2],
    #[serde(default)]
    occlusion_target: Option<f64>,
    left: Option<EyeJson>,
    right: Option<EyeJson>,
}

/// A transform of a calibration file as an isometry (metres).
pub fn iso(t: &TransformJson) -> Isometry3<f64> {
    let [w, x, y, z] = t.quaternion_wxyz;
    Isometry3::from_parts(
        Translation3::from(Vector3::from(t.translation_m)),
        UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
    )
}

fn read(path: &Path) -> Result<String, SequenceError> {
    std::fs::read_to_string(path).map_err(|e| SequenceError::File { path: path.to_owned(), message: e.to_string() })
}

/// The value of `samples` (time-ordered `(t_ns, value)`) at `t`, linearly interpolated between
/// the two samples around it; `None` outside them or when they are more than [`MAX_GAP_NS`] apart.
pub fn interpolate<const N: usize>(samples: &[(u64, [f64; N])], t: u64) -> Option<[f64; N]> {
    let j = samples.partition_point(|s| s.0 <= t);
    let a = samples.get(j.checked_sub(1)?)?;
    let b = samples.get(j)?;
    if b.0 - a.0 > MAX_GAP_NS {
        return None;
    }
    let s = (t - a.0) as f64 / (b.0 - a.0).max(1) as f64;
    Some(core::array::from_fn(|k| a.1[k] + s * (b.1[k] - a.1[k])))
}

/// The two eyes' intrinsics and `T_cr_cl` (metres) from their `camera_info` YAML files.
pub fn read_stereo(cameras: [&Path; 2]) -> Result<([Intrinsics; 2], Isometry3<f64>), SequenceError> {
    let (lt, rt) = (read(cameras[0])?, read(cameras[1])?);
    let stereo = hw_io::calib_files::parse_stereo_camera_info(&lt, &rt)
        .map_err(|e| SequenceError::File { path: cameras[0].to_owned(), message: e.to_string() })?;
    let r = stereo.rotation_right_left;
    let rot = nalgebra::Matrix3::new(r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2], r[2][0], r[2][1], r[2][2]);
    let right_from_left = Isometry3::from_parts(
        Translation3::from(Vector3::from(stereo.translation_right_left_m)),
        UnitQuaternion::from_matrix(&rot),
    );
    Ok(([stereo.left, stereo.right], right_from_left))
}

/// The rig of a simulated run, from its `truth.jsonl` header: the hand-eye `T_f_c`, the
/// endoscope arm's RCM in the tool arm's base `T_b_e` (metres; an exact calibration) and the
/// instrument's dimensions.
pub fn read_truth_rig(
    truth: &Path,
) -> Result<(Isometry3<f64>, Isometry3<f64>, sim::endoscope::InstrumentGeometry), SequenceError> {
    let text = read(truth)?;
    let header: Header = serde_json::from_str(text.lines().next().unwrap_or_default())
        .map_err(|e| SequenceError::File { path: truth.to_owned(), message: format!("header: {e}") })?;
    Ok((iso(&header.config.camera.hand_eye), iso(&header.rcm_in_tool_base), header.config.instrument))
}

/// Both arms' joints from a candump log, in log order, stamped in nanoseconds on the log's clock
/// (Unix time): the tool arm's complete cycles through fulcrumd's own acquisition
/// (`controller::replay::replay_candump`, radians), the endoscope arm's node pairs
/// (`controller::replay::endoscope_joints`, `[yaw rad, pitch rad, insertion m, roll rad]`).
pub fn recorded_joints(candump: &Path, cfg: &controller::config::Config) -> Result<RecordedArms, SequenceError> {
    let replay = controller::replay::replay_candump(candump, cfg)
        .map_err(|source| SequenceError::Replay { path: candump.to_owned(), source })?;
    let tool: Vec<(u64, [f64; 6])> = replay
        .cycles
        .iter()
        .filter(|c| c.input.received_mask == 0b111 && c.output.joints_rad.iter().all(|v| v.is_finite()))
        .map(|c| (c.sync_unix_us * 1000, c.output.joints_rad))
        .collect();
    let ecm = controller::replay::endoscope_joints(candump, &sim::endoscope_arm::EndoscopeArmConfig::default())
        .map_err(|source| SequenceError::Replay { path: candump.to_owned(), source })?;
    Ok((tool, ecm))
}

/// Both arms' recorded joints: the tool arm's `(t_ns, joints rad)` and the endoscope arm's
/// `(t_ns, [yaw rad, pitch rad, insertion m, roll rad])`, time-ordered.
pub type RecordedArms = (Vec<(u64, [f64; 6])>, Vec<(u64, [f64; 4])>);

/// Reads a sequence: `frames_dir` (frames.txt, truth.jsonl), the candump log, the two eyes'
/// camera_info files; `cfg` is fulcrumd's configuration (the tool arm's encoders and
/// kinematics).
pub fn read_sequence(
    frames_dir: &Path,
    candump: &Path,
    cameras: [&Path; 2],
    cfg: &controller::config::Config,
) -> Result<Sequence, SequenceError> {
    let index_path = frames_dir.join("frames.txt");
    let mut listed: Vec<(u64, [PathBuf; 2])> = Vec::new();
    for line in read(&index_path)?.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')) {
        let f: Vec<&str> = line.split_whitespace().collect();
        let (Some(t), Some(l), Some(r)) = (f.first().and_then(|t| t.parse::<u64>().ok()), f.get(2), f.get(3)) else {
            return Err(SequenceError::File {
                path: index_path.clone(),
                message: format!("not `t_mid_ns exposure_ns left right`: {line}"),
            });
        };
        listed.push((t, [frames_dir.join(l), frames_dir.join(r)]));
    }
    if listed.is_empty() {
        return Err(SequenceError::NoFrames(index_path));
    }
    let (intrinsics, right_from_left) = read_stereo(cameras)?;
    let truth_path = frames_dir.join("truth.jsonl");
    let truth_text = read(&truth_path)?;
    let mut lines = truth_text.lines();
    let header: Header = serde_json::from_str(lines.next().unwrap_or_default())
        .map_err(|e| SequenceError::File { path: truth_path.clone(), message: format!("header: {e}") })?;
    let mut truths: Vec<Option<FrameTruth>> = vec![None; listed.len()];
    for l in lines {
        let Ok(f) = serde_json::from_str::<FrameJson>(l) else { continue };
        if f.kind != "frame" {
            continue;
        }
        let Some(left) = f.left else { continue };
        let visible_fraction = [
            left.visibility.and_then(|v| v.fraction()),
            f.right.as_ref().and_then(|e| e.visibility).and_then(|v| v.fraction()),
        ];
        let Some(i) = left.instruments.iter().find(|i| i.label == 1) else { continue };
        let [w, x, y, z] = i.pose_in_camera.quaternion_wxyz;
        if let Some(slot) = truths.get_mut(f.index) {
            *slot = Some(FrameTruth {
                tip_camera_m: Vector3::from(i.tip_camera_m),
                rotation_camera: UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
                instrument_px: f.instrument_px,
                visible_fraction,
                occlusion_target: f.occlusion_target,
            });
        }
    }
    let (tool, ecm) = recorded_joints(candump, cfg)?;
    let frames = listed
        .into_iter()
        .enumerate()
        .map(|(index, (t_ns, files))| SeqFrame {
            index,
            t_ns,
            files,
            encoder_rad: interpolate(&tool, t_ns),
            ecm_joints: interpolate(&ecm, t_ns),
            truth: truths.get(index).copied().flatten(),
        })
        .collect();
    Ok(Sequence {
        frames,
        intrinsics,
        right_from_left,
        hand_eye: iso(&header.config.camera.hand_eye),
        ecm_in_tool_base: iso(&header.rcm_in_tool_base),
        instrument: header.config.instrument,
    })
}
