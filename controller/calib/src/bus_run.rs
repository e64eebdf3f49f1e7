//! Calibration from a recorded run: both arms' joints read from a candump log of the bus,
//! matched to the stereo frames by timestamp, the tool's line detected in both eyes.
//!
//! Input: the directory `simrobot generate --frames` writes (`docs/simulator.md`): `bus.log`
//! (candump, Unix microseconds), `frames/frames.txt` (each stereo frame's exposure mid time
//! on the bus clock, nanoseconds), `frames/left.yaml` (the camera) and `frames/truth.jsonl`
//! (its header: the endoscope's hand-eye and baseline, and the ground truth `T_b_e`).
//!
//! The chain, as the product would run it:
//! - **Tool arm** (the Achilles-type arm, nodes 1-3): the log cut into cycles and run through
//!   fulcrumd's own acquisition and estimation (`controller::replay::replay_candump`, the
//!   daemon's configuration): per cycle, the instrument axis `z` and, while the instrument is
//!   inside a trocar, the fulcrum `F` (metres, tool base `{b}`).
//! - **Endoscope arm** (nodes 4 and 5, every 10th SYNC): their TPDOs decoded to
//!   `[yaw, pitch, insertion, roll]` with the arm's encoder model
//!   (`sim::endoscope_arm::EndoscopeArmConfig`), linearly interpolated at the frame's time
//!   (refused when the two TPDOs around it are more than [`MAX_ECM_GAP_NS`] apart).
//! - **The observation**: the calibration's tool arm is an RCM arm; the Achilles arm's
//!   instrument pivots about the trocar instead, so the trocar is the RCM: `{t}` is the
//!   trocar's frame (origin at the median fulcrum of the trocar's cycles, axes parallel to
//!   `{b}`), and the tool joints are the RCM joints of the line through it along `z`:
//!   `yaw = atan2(z_x, z_z)`, `pitch = −asin(z_y)`, `insertion = (tip − F)·z`. Only frames
//!   whose cycle (the last SYNC before the frame's mid time) is inside the most observed
//!   trocar are used: the calibration has one `{t}`.
//! - **Ground truth**: `T_e_t = T_b_e⁻¹ · T_b_t` with `T_b_t` at the estimated trocar: what
//!   the calibration can recover (the fulcrum estimate's own error is not the calibration's).

use std::path::{Path, PathBuf};

use controller::config::Config;
use estimator::calib::{Intrinsics, KinematicNoise, Setup};
use hw_io::calib_files::TransformJson;
use hw_io::ipc::OutputState;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use serde::Deserialize;
use sim::endoscope_arm::EndoscopeArmConfig;

use crate::pixels::{PixelRun, PoseLines};

/// Two endoscope TPDOs more than this apart (nanoseconds) do not give the joints between
/// them (the arm answers every 10th SYNC: 10 ms apart when nothing is lost).
pub const MAX_ECM_GAP_NS: u64 = 25_000_000;

/// Why a run cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum BusRunError {
    /// A file cannot be read.
    #[error("{path}: {message}")]
    File {
        /// The file.
        path: PathBuf,
        /// Why.
        message: String,
    },
    /// The bus log cannot be replayed.
    #[error("bus log: {0}")]
    Replay(String),
    /// No frame had both arms' joints with the instrument inside a trocar.
    #[error("no frame has both arms' joints with the instrument inside a trocar ({frames} frames)")]
    Nothing {
        /// Frames listed.
        frames: usize,
    },
}

#[derive(Deserialize)]
struct CameraHeader {
    baseline_m: f64,
    hand_eye: TransformJson,
}

#[derive(Deserialize)]
struct ConfigHeader {
    camera: CameraHeader,
    /// The rendered instrument (absent in older runs: the renderer's default).
    #[serde(default)]
    instrument: sim::endoscope::InstrumentGeometry,
}

#[derive(Deserialize)]
struct Header {
    rcm_in_tool_base: TransformJson,
    config: ConfigHeader,
}

#[derive(Deserialize)]
struct ScenarioHeader {
    instrument_length_m: f64,
}

#[derive(Deserialize)]
struct RunHeader {
    scenario: ScenarioHeader,
    #[serde(default)]
    trocars_base_m: Vec<[f64; 3]>,
}

#[derive(Deserialize)]
struct FrameTruthEye {
    instruments: Vec<sim::endoscope::truth::InstrumentTruth>,
}

#[derive(Deserialize)]
struct FrameTruth {
    index: usize,
    left: FrameTruthEye,
    right: FrameTruthEye,
}

fn iso(t: &TransformJson) -> Isometry3<f64> {
    let [w, x, y, z] = t.quaternion_wxyz;
    Isometry3::from_parts(
        Translation3::from(Vector3::from(t.translation_m)),
        UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
    )
}

fn read(path: &Path) -> Result<String, BusRunError> {
    std::fs::read_to_string(path).map_err(|e| BusRunError::File { path: path.to_owned(), message: e.to_string() })
}

/// One stereo frame with both arms' joints from the bus.
#[derive(Clone, Debug)]
pub struct BusFrame {
    /// Index in frames.txt.
    pub index: usize,
    /// Left and right image files (relative to the frames directory).
    pub files: [String; 2],
    /// Endoscope joints at the frame's time.
    pub ecm_joints: [f64; 4],
    /// The cycle's trocar identity (fulcrumd's).
    pub trocar_id: u32,
    /// The cycle's fulcrum `F`, metres, `{b}`.
    pub fulcrum_b: Vector3<f64>,
    /// The cycle's instrument axis `z` (unit, toward the tip), `{b}`.
    pub axis_b: Vector3<f64>,
    /// The cycle's wrist centre `P`, metres, `{b}`.
    pub wrist_b: Vector3<f64>,
    /// Exposure mid time, nanoseconds (bus clock).
    pub t_ns: u64,
    /// True when fulcrumd said the instrument was inside a trocar in that cycle.
    pub inside: bool,
    /// Age of the endoscope TPDO before the frame's time, nanoseconds.
    pub ecm_age_ns: u64,
    /// Age of the tool arm's cycle (its SYNC) at the frame's time, nanoseconds.
    pub tool_age_ns: u64,
}

/// What [`read_run`] found.
#[derive(Clone, Debug)]
pub struct BusRunData {
    /// Frames with both arms' joints and the instrument inside a trocar.
    pub frames: Vec<BusFrame>,
    /// Every frame with both arms' joints, inside a trocar or not, in time order (the live
    /// replay: `comanip-calib live --replay`).
    pub timeline: Vec<BusFrame>,
    /// Frames listed in frames.txt.
    pub listed: usize,
    /// Frames left out: no cycle, no endoscope joints, or the instrument not inside.
    pub no_cycle: usize,
    /// … no endoscope joints around the frame's time.
    pub no_ecm: usize,
    /// … the instrument not inside a trocar.
    pub outside: usize,
    /// The camera.
    pub intrinsics: Intrinsics,
    /// Hand-eye `T_f_c`.
    pub hand_eye: Isometry3<f64>,
    /// Stereo baseline, metres.
    pub baseline_m: f64,
    /// Ground truth `T_b_e`.
    pub ecm_in_tool_base: Isometry3<f64>,
    /// Distance from the wrist centre to the tool tip along the instrument, metres (the
    /// scenario's instrument length, from the run's `truth.jsonl` header).
    pub tip_m: f64,
    /// What of the rendered instrument a detector can report (the renderer's jaws beyond the
    /// tip, the shaft outside the trocar: the twin has no abdominal wall), from the frames'
    /// header.
    pub shaft_extent: estimator::calib::ShaftExtent,
    /// The scenario's true trocars, metres, `{b}` (the run's ground truth; for the report).
    pub trocars_b: Vec<Vector3<f64>>,
    /// Truth lines per frame index and eye (measured-pixel segment), from the renderer.
    pub truth_lines: Vec<crate::pixels::EyeLines>,
}

/// Reads a `simrobot generate --frames` directory and matches the bus to the frames.
pub fn read_run(dir: &Path, cfg: &Config) -> Result<BusRunData, BusRunError> {
    let fdir = dir.join("frames");
    // Frames.
    let index_text = read(&fdir.join("frames.txt"))?;
    let mut listed: Vec<(u64, [String; 2])> = Vec::new();
    for line in index_text.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')) {
        let f: Vec<&str> = line.split_whitespace().collect();
        let (Some(t), Some(l), Some(r)) = (f.first().and_then(|t| t.parse::<u64>().ok()), f.get(2), f.get(3)) else {
            return Err(BusRunError::File {
                path: fdir.join("frames.txt"),
                message: format!("not `t_mid_ns exposure_ns left right`: {line}"),
            });
        };
        listed.push((t, [(*l).to_string(), (*r).to_string()]));
    }
    let cam_path = fdir.join("left.yaml");
    let intrinsics = hw_io::calib_files::parse_intrinsics_yaml(&read(&cam_path)?)
        .map_err(|e| BusRunError::File { path: cam_path.clone(), message: e.to_string() })?;
    // Header and per-frame truth.
    let truth_path = fdir.join("truth.jsonl");
    let truth_text = read(&truth_path)?;
    let bad = |m: String| BusRunError::File { path: truth_path.clone(), message: m };
    let mut lines = truth_text.lines();
    let header: Header =
        serde_json::from_str(lines.next().unwrap_or_default()).map_err(|e| bad(format!("header: {e}")))?;
    let mut truth_lines = vec![[None, None]; listed.len()];
    for l in lines {
        let Ok(ft) = serde_json::from_str::<FrameTruth>(l) else { continue };
        let Some(slot) = truth_lines.get_mut(ft.index) else { continue };
        for (eye, e) in [&ft.left, &ft.right].into_iter().enumerate() {
            slot[eye] = e.instruments.iter().find(|i| i.label == 1).and_then(|i| {
                let a = i.axis.as_ref()?;
                let (seg, ideal) = (a.segment_px?, a.segment_ideal_px?);
                let len = (ideal[0][0] - ideal[1][0]).hypot(ideal[0][1] - ideal[1][1]);
                (len >= crate::pixels::MIN_SHAFT_PX)
                    .then(|| vision::shaft::ImageLine::new(a.line_ideal).ok().map(|l| (seg, l)))
                    .flatten()
            });
        }
    }
    let run_truth = dir.join("truth.jsonl");
    let first = read(&run_truth)?.lines().next().unwrap_or_default().to_string();
    let run_header: RunHeader = serde_json::from_str(&first)
        .map_err(|e| BusRunError::File { path: run_truth.clone(), message: format!("header: {e}") })?;
    // The tool arm through fulcrumd's own pipeline.
    let bus = dir.join("bus.log");
    let replay = controller::replay::replay_candump(&bus, cfg).map_err(|e| BusRunError::Replay(e.to_string()))?;
    // The endoscope arm's TPDOs.
    let ecm = controller::replay::endoscope_joints(&bus, &EndoscopeArmConfig::default())
        .map_err(|e| BusRunError::Replay(e.to_string()))?;
    let mut out = Vec::new();
    let mut timeline = Vec::new();
    let (mut no_cycle, mut no_ecm, mut outside) = (0, 0, 0);
    let cycles = &replay.cycles;
    for (index, (t, files)) in listed.iter().enumerate() {
        // The last cycle whose SYNC is at or before the frame's mid time.
        let i = cycles.partition_point(|c| c.sync_unix_us * 1000 <= *t);
        let Some(c) = i.checked_sub(1).and_then(|i| cycles.get(i)) else {
            no_cycle += 1;
            continue;
        };
        if t.saturating_sub(c.sync_unix_us * 1000) > 2_000_000 {
            no_cycle += 1;
            continue;
        }
        let j = ecm.partition_point(|e| e.0 <= *t);
        let (Some(a), Some(b)) = (j.checked_sub(1).and_then(|j| ecm.get(j)), ecm.get(j)) else {
            no_ecm += 1;
            continue;
        };
        if b.0 - a.0 > MAX_ECM_GAP_NS {
            no_ecm += 1;
            continue;
        }
        let s = (*t - a.0) as f64 / (b.0 - a.0).max(1) as f64;
        let q = [0, 1, 2, 3].map(|k| a.1[k] + s * (b.1[k] - a.1[k]));
        let frame = BusFrame {
            index,
            files: files.clone(),
            ecm_joints: q,
            trocar_id: c.output.trocar_id,
            fulcrum_b: Vector3::from(c.output.fulcrum_base_m),
            axis_b: Vector3::from(c.output.axis_base),
            wrist_b: Vector3::from(c.output.wrist_base_m),
            t_ns: *t,
            inside: c.output.state == OutputState::Inside,
            ecm_age_ns: t.saturating_sub(a.0),
            tool_age_ns: t.saturating_sub(c.sync_unix_us * 1000),
        };
        timeline.push(frame.clone());
        if !frame.inside {
            outside += 1;
            continue;
        }
        out.push(frame);
    }
    if out.is_empty() {
        return Err(BusRunError::Nothing { frames: listed.len() });
    }
    Ok(BusRunData {
        frames: out,
        timeline,
        listed: listed.len(),
        no_cycle,
        no_ecm,
        outside,
        intrinsics,
        hand_eye: iso(&header.config.camera.hand_eye),
        baseline_m: header.config.camera.baseline_m,
        ecm_in_tool_base: iso(&header.rcm_in_tool_base),
        tip_m: run_header.scenario.instrument_length_m,
        shaft_extent: crate::pixels::rendered_shaft_extent(&header.config.instrument),
        trocars_b: run_header.trocars_base_m.iter().map(|t| Vector3::from(*t)).collect(),
        truth_lines,
    })
}

/// The most observed trocar's frames as an RCM arm's observations, with detection in both
/// eyes: a [`PixelRun`] (its `truth` is `T_e_t` at the median fulcrum) ready for
/// [`crate::pixels::calibrate_all`], the trocar's identity and its median fulcrum (metres,
/// `{b}`). Lines are weighted with an
/// isotropic pixel noise of `sigma_px` (no kinematic noise model). `progress(done, total)`
/// after each frame.
pub fn to_pixel_run(
    data: &BusRunData,
    frames_dir: &Path,
    detectors: &mut [Box<dyn vision::ShaftDetector + Send>],
    noise: KinematicNoise,
    estimate_noise_scale: bool,
    mut progress: impl FnMut(usize, usize),
) -> Result<(PixelRun, usize, Vector3<f64>), BusRunError> {
    // The most observed trocar.
    let mut ids: Vec<u32> = data.frames.iter().map(|f| f.trocar_id).collect();
    ids.sort_unstable();
    let mut best = (0u32, 0usize);
    for chunk in ids.chunk_by(|a, b| a == b) {
        if chunk.len() > best.1 {
            best = (chunk[0], chunk.len());
        }
    }
    let frames: Vec<&BusFrame> = data.frames.iter().filter(|f| f.trocar_id == best.0).collect();
    let med = |k: usize| {
        let mut v: Vec<f64> = frames.iter().map(|f| f.fulcrum_b[k]).collect();
        crate::pixels::median(&mut v)
    };
    let f_ref = Vector3::new(med(0), med(1), med(2));
    let t_b_t = Isometry3::from_parts(Translation3::from(f_ref), UnitQuaternion::identity());
    let truth = data.ecm_in_tool_base.inverse() * t_b_t;
    let mut poses = Vec::with_capacity(frames.len());
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); detectors.len()];
    for (n, f) in frames.iter().enumerate() {
        let z = f.axis_b;
        let tip = f.wrist_b + z * data.tip_m;
        let psm = [z.x.atan2(z.z), -z.y.clamp(-1.0, 1.0).asin(), (tip - f_ref).dot(&z)];
        let mut detected = Vec::with_capacity(detectors.len());
        let imgs: Vec<Option<hw_io::camera::png::RgbImage>> =
            f.files.iter().map(|file| hw_io::camera::png::read_rgb(&frames_dir.join(file)).ok()).collect();
        for (d, det) in detectors.iter_mut().enumerate() {
            let mut per_eye = [None, None];
            for (eye, slot) in per_eye.iter_mut().enumerate() {
                let Some(Some(img)) = imgs.get(eye) else { continue };
                let Ok(view) = vision::RgbView::new(img.width, img.height, &img.rgb) else { continue };
                let t0 = std::time::Instant::now();
                let found = det.detect(&view);
                times[d].push(t0.elapsed().as_secs_f64() * 1e3);
                if let Ok(found) = found
                    && let Some(b) = found.first()
                {
                    *slot = Some((b.ends_px, b.centreline));
                }
            }
            detected.push(per_eye);
        }
        let truth_lines = data.truth_lines.get(f.index).cloned().unwrap_or([None, None]);
        poses.push(PoseLines { ecm_joints: f.ecm_joints, psm_joints: psm, truth: truth_lines, detected });
        progress(n + 1, frames.len());
    }
    let right = Isometry3::from_parts(Translation3::new(data.baseline_m, 0.0, 0.0), UnitQuaternion::identity());
    let run = PixelRun {
        setup: Setup {
            intrinsics: data.intrinsics,
            hand_eye: data.hand_eye,
            right_eye: Some(right),
            selection: crate::pixels::selection_rule(),
            shaft_extent: data.shaft_extent,
        },
        truth,
        noise: noise.is_valid().then_some(noise),
        // One model for every line source: a recorded run states the pixel σ itself.
        detected_pixel_px: None,
        estimate_noise_scale,
        detectors: detectors.iter().map(|d| d.name()).collect(),
        poses,
        detect_ms: times.iter_mut().map(|t| crate::pixels::median(t)).collect(),
        render_s: 0.0,
    };
    Ok((run, best.0 as usize, f_ref))
}
