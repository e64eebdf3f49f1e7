//! Tracking a recorded sequence frame by frame: the model from the instrument's mesh, one
//! [`track::Tracker::step`] per stereo frame, a JSON line per frame, overlays.

use std::io::Write;
use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, UnitQuaternion};
use serde::Serialize;
use track::{FrameInput, Mode, PartMesh, Status, StereoCameras, ToolGeometry, ToolModel, Tracker, TrackerConfig};

use crate::config::ToolSection;
use crate::input::{FrameTruth, Sequence};

/// Why a run failed.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The model could not be built.
    #[error("tool model: {0}")]
    Model(String),
    /// The tracker's configuration.
    #[error(transparent)]
    Config(#[from] track::ConfigError),
    /// A file could not be written.
    #[error("{path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        message: String,
    },
    /// No frame could be tracked (no image, no joints).
    #[error("no frame of {0} could be tracked (images or both arms' joints missing)")]
    Nothing(usize),
}

/// The tracker's model of the instrument rendered in `seq`, on fulcrumd's arm `cfg`.
pub fn build_model(
    seq: &Sequence,
    tool: &ToolSection,
    cfg: &controller::config::Config,
) -> Result<ToolModel, RunError> {
    build_model_for(seq.instrument, tool, cfg)
}

/// The tracker's model of an instrument of dimensions `instrument` (metres), as configured in
/// `tool`, on fulcrumd's arm `cfg` (the live process: the instrument's dimensions from its
/// configuration).
pub fn build_model_for(
    instrument: sim::endoscope::InstrumentGeometry,
    tool: &ToolSection,
    cfg: &controller::config::Config,
) -> Result<ToolModel, RunError> {
    let mut g = instrument;
    g.segments = tool.segments;
    g.shaft_length_m = tool.shaft_modelled_m;
    let mesh = g.mesh().map_err(|e| RunError::Model(e.to_string()))?;
    let parts: Vec<PartMesh> = mesh
        .parts
        .iter()
        .map(|(p, m)| PartMesh {
            part: match p {
                sim::endoscope::mesh::Part::Shaft => track::Part::Shaft,
                sim::endoscope::mesh::Part::Wrist => track::Part::Wrist,
                sim::endoscope::mesh::Part::Jaw1 => track::Part::Jaw1,
                sim::endoscope::mesh::Part::Jaw2 => track::Part::Jaw2,
            },
            positions: m.positions.clone(),
            triangles: m.triangles.clone(),
        })
        .collect();
    let arm = estimator::kinematics::Achilles::new(&cfg.kinematics).map_err(|e| RunError::Model(e.to_string()))?;
    let geometry = ToolGeometry {
        instrument_length_m: tool.instrument_length_m,
        wrist_length_m: g.wrist_length_m,
        shaft_radius_m: g.shaft_radius_m(),
        shaft_modelled_m: tool.shaft_modelled_m,
    };
    ToolModel::new(arm, geometry, &parts).map_err(|e| RunError::Model(e.to_string()))
}

/// One frame's result (a JSON line of `--out`).
#[derive(Clone, Debug, Serialize)]
pub struct FrameResult {
    /// Index in frames.txt.
    pub index: usize,
    /// Mid-exposure time, nanoseconds on the bus clock.
    pub t_ns: u64,
    /// TRACKING, UNCERTAIN or LOST (`SKIPPED`: no image or no joints).
    pub status: String,
    /// Tip (jaw pivot) in the left camera frame, metres (absent when LOST).
    pub tip_camera_m: Option<[f64; 3]>,
    /// Its orientation (frame 6's axes) in the left camera frame, `[w, x, y, z]`.
    pub tip_camera_wxyz: Option<[f64; 4]>,
    /// Tip in the tool arm's base frame, metres.
    pub tip_base_m: Option<[f64; 3]>,
    /// Its orientation in the base frame, `[w, x, y, z]`.
    pub tip_base_wxyz: Option<[f64; 4]>,
    /// Each jaw's opening, radians.
    pub jaw_rad: Option<f64>,
    /// The estimated `g_CB` correction (rotation vector rad, translation m).
    pub camera_delta: Option<[f64; 6]>,
    /// Particles' tip spread (weighted standard deviation), metres.
    pub spread_m: Option<f64>,
    /// Best hypothesis's cost per eye, pixels.
    pub best_cost_px: Option<f64>,
    /// Effective particles.
    pub effective_particles: Option<f64>,
    /// Ours: the best hypothesis's share of samples on a matching edge (both eyes' mean).
    pub inlier_share: Option<f64>,
    /// Ours with the offset model's prior LOST rule: the worse shaft contour line's inlier
    /// share (both eyes' mean), on frames whose inlier share was below the threshold.
    pub line_share: Option<f64>,
    /// Not LOST thanks to the prior (the visible shaft fits where the prior says it is).
    pub held_by_prior: bool,
    /// Re-initialised from the kinematics at this frame.
    pub reinitialised: bool,
    /// Re-initialised about a hypothesis on the detected shaft's axis at this frame
    /// (`[proposal]`, docs/tracking.md "Re-seeding from the detected shaft").
    #[serde(default)]
    pub reseeded_from_vision: bool,
    /// With `[proposal]`: the shaft's axis was detected in both eyes and triangulated.
    #[serde(default)]
    pub axis_detected: bool,
    /// With `[proposal]`: the best hypothesis on the detected axis's inlier share (0..1), on
    /// frames where re-seeding was tried.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reseed_share: Option<f64>,
    /// Against the renderer's ground truth (when known and a pose was published): tip position
    /// error, millimetres.
    pub error_mm: Option<f64>,
    /// … orientation error (angle of `R_est⁻¹·R_true`), degrees.
    pub error_deg: Option<f64>,
    /// The kinematics alone (encoders and calibration) against the truth, millimetres.
    pub kinematics_error_mm: Option<f64>,
    /// … its orientation error, degrees.
    pub kinematics_error_deg: Option<f64>,
    /// The instrument's visible fraction in the left and right eyes (the renderer's truth).
    pub visible_fraction: [Option<f64>; 2],
    /// The occluder window's target fraction when one covers this frame.
    pub occlusion_target: Option<f64>,
    /// Wall time of the step, milliseconds.
    pub step_ms: f64,
}

/// Position (mm) and orientation (degrees) errors of `pose` against `truth`.
pub fn errors(pose: &Isometry3<f64>, truth: &FrameTruth) -> (f64, f64) {
    let e = (pose.translation.vector - truth.tip_camera_m).norm() * 1e3;
    let r: UnitQuaternion<f64> = pose.rotation.inverse() * truth.rotation_camera;
    (e, r.angle().to_degrees())
}

fn wxyz(q: &UnitQuaternion<f64>) -> [f64; 4] {
    [q.w, q.i, q.j, q.k]
}

/// The cameras of frame `f` (`None` without endoscope joints).
pub fn cameras(seq: &Sequence, ecm: &[f64; 4]) -> StereoCameras {
    StereoCameras {
        intrinsics: seq.intrinsics,
        left_from_base: seq.left_from_base(ecm),
        right_from_left: seq.right_from_left,
    }
}

/// One stereo frame through the tracker, as the offline run and the live process do it: the
/// first frame initialises the particles about `start_joints` (default: the encoders' `enc`,
/// radians), then [`Tracker::step`] with the cameras `cams`, the two eyes' sRGB images and the
/// frame's mid-exposure time `time_ns` (nanoseconds, any epoch; the offset model's time step).
#[allow(clippy::too_many_arguments)]
pub fn step_frame(
    tracker: &mut Tracker,
    started: &mut bool,
    start_joints: Option<[f64; 6]>,
    enc: [f64; 6],
    cams: StereoCameras,
    rgb: [&[u8]; 2],
    time_ns: Option<u64>,
) -> Result<track::Estimate, track::StepError> {
    if !*started {
        if let Some(j) = enc.iter().position(|v| !v.is_finite()) {
            return Err(track::StepError::Encoder(j));
        }
        tracker.initialise(&start_joints.unwrap_or(enc), &enc);
        *started = true;
    }
    tracker.step(&FrameInput { encoder_rad: enc, cameras: cams, rgb, time_ns })
}

/// Our shaft detector (`vision::ours`) on both eyes, triangulated into the shaft's axis for
/// [`Tracker::set_shaft_axis`] (the tracker's re-seeding, `[proposal]`).
pub struct AxisDetector {
    eyes: [vision::ours::OursDetector; 2],
}

impl AxisDetector {
    /// Detectors for `seq`'s two cameras (default settings).
    pub fn new(seq: &Sequence) -> Result<Self, RunError> {
        let make = |k| {
            vision::ours::OursDetector::new(k, vision::ours::OursConfig::default())
                .map_err(|e| RunError::Model(format!("shaft detector: {e}")))
        };
        Ok(Self { eyes: [make(seq.intrinsics[0])?, make(seq.intrinsics[1])?] })
    }

    /// The best detection in each eye triangulated (base frame), `None` when either eye has
    /// none or the two do not give an axis. Images: sRGB bytes of each eye, the cameras' size.
    pub fn axis(&mut self, cams: &StereoCameras, rgb: [&[u8]; 2]) -> Option<track::ShaftAxis> {
        use vision::ShaftDetector;
        let mut det = [None, None];
        for (e, d) in det.iter_mut().enumerate() {
            let k = cams.intrinsics[e];
            let view = vision::RgbView::new(k.width as usize, k.height as usize, rgb[e]).ok()?;
            *d = self.eyes[e].detect(&view).ok()?.into_iter().next();
        }
        let [Some(l), Some(r)] = det else { return None };
        track::proposal::triangulate_axis(cams, [l.centreline.abc, r.centreline.abc], Some(l.ends_px)).ok()
    }
}

/// Where a run starts and what it writes.
pub struct RunOptions<'a> {
    /// First frame (index into the sequence).
    pub first: usize,
    /// Frames to track from `first` (`usize::MAX`: to the end).
    pub count: usize,
    /// Start from these joints instead of the encoders' (a perturbed start), radians.
    pub start_joints: Option<[f64; 6]>,
    /// Overlays directory.
    pub overlay: Option<&'a Path>,
    /// Progress after each frame.
    pub progress: &'a dyn Fn(usize),
    /// Joint-sensor noise added to every encoder reading the tracker gets (the paper's Fig.
    /// 10-11); `None`: the encoders as logged.
    pub encoder_noise: Option<EncoderNoise>,
}

/// Gaussian noise added to each encoder reading given to the tracker, independently per
/// frame and joint (the paper's "noise added to the joint sensor feedback"). The kinematics
/// baseline of the results uses the same noisy readings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EncoderNoise {
    /// Standard deviation per joint, radians.
    pub sigma_rad: [f64; 6],
    /// Seed of the noise.
    pub seed: u64,
}

impl EncoderNoise {
    /// The noisy reading of frame `index`.
    pub fn apply(&self, index: usize, enc: &[f64; 6]) -> [f64; 6] {
        use rand::{Rng, SeedableRng};
        let mut r =
            rand_chacha::ChaCha8Rng::seed_from_u64(self.seed ^ (index as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        core::array::from_fn(|j| enc[j] + self.sigma_rad[j] * r.sample::<f64, _>(rand_distr::StandardNormal))
    }
}

/// Tracks `count` frames of `seq` from `first` with a tracker of `cfg` on `model`, returning
/// one result per frame.
pub fn track(
    seq: &Sequence,
    model: &ToolModel,
    cfg: TrackerConfig,
    opts: &RunOptions<'_>,
) -> Result<Vec<FrameResult>, RunError> {
    let mut tracker = Tracker::new(cfg, model.clone())?;
    let mut axes = match cfg.proposal {
        Some(_) => Some(AxisDetector::new(seq)?),
        None => None,
    };
    let mut out = Vec::new();
    let mut started = false;
    let mut sil = Vec::new();
    let end = opts.first.saturating_add(opts.count).min(seq.frames.len());
    for f in seq.frames.get(opts.first..end).unwrap_or_default() {
        let skipped = |index, t_ns| FrameResult {
            index,
            t_ns,
            status: "SKIPPED".into(),
            tip_camera_m: None,
            tip_camera_wxyz: None,
            tip_base_m: None,
            tip_base_wxyz: None,
            jaw_rad: None,
            camera_delta: None,
            spread_m: None,
            best_cost_px: None,
            effective_particles: None,
            inlier_share: None,
            line_share: None,
            held_by_prior: false,
            reinitialised: false,
            reseeded_from_vision: false,
            axis_detected: false,
            reseed_share: None,
            error_mm: None,
            error_deg: None,
            kinematics_error_mm: None,
            kinematics_error_deg: None,
            visible_fraction: f.truth.map_or([None; 2], |t| t.visible_fraction),
            occlusion_target: f.truth.and_then(|t| t.occlusion_target),
            step_ms: 0.0,
        };
        let (Some(enc), Some(ecm)) =
            (f.encoder_rad.map(|e| opts.encoder_noise.map_or(e, |n| n.apply(f.index, &e))), f.ecm_joints)
        else {
            out.push(skipped(f.index, f.t_ns));
            (opts.progress)(out.len());
            continue;
        };
        let imgs = [hw_io::camera::png::read_rgb(&f.files[0]), hw_io::camera::png::read_rgb(&f.files[1])];
        let [Ok(l), Ok(r)] = &imgs else {
            tracing::warn!(frame = f.index, "image unreadable; frame skipped");
            out.push(skipped(f.index, f.t_ns));
            (opts.progress)(out.len());
            continue;
        };
        let cams = cameras(seq, &ecm);
        let t0 = std::time::Instant::now();
        let mut axis_detected = false;
        if let Some(d) = axes.as_mut() {
            let a = d.axis(&cams, [&l.rgb, &r.rgb]);
            axis_detected = a.is_some();
            tracker.set_shaft_axis(a);
        }
        let est = match step_frame(
            &mut tracker,
            &mut started,
            opts.start_joints,
            enc,
            cams,
            [&l.rgb, &r.rgb],
            Some(f.t_ns),
        ) {
            Ok(e) => e,
            Err(e) => {
                tracing::warn!(frame = f.index, "frame refused: {e}");
                out.push(skipped(f.index, f.t_ns));
                (opts.progress)(out.len());
                continue;
            }
        };
        let step_ms = t0.elapsed().as_secs_f64() * 1e3;
        let status = match est.status {
            Status::Tracking => "TRACKING",
            Status::Uncertain => "UNCERTAIN",
            Status::Lost => "LOST",
        };
        let err = est.pose.as_ref().zip(f.truth.as_ref()).map(|(p, t)| errors(&p.tip_in_camera, t));
        let kin = f.truth.as_ref().and_then(|t| {
            let tip = model.tip_in_base(&enc)?;
            Some(errors(&(cams.left_from_base * tip), t))
        });
        if let Some(dir) = opts.overlay {
            crate::overlay::write(dir, f.index, seq, &tracker, &cams, est.pose.as_ref(), [l, r], &mut sil)?;
        }
        let p = est.pose;
        out.push(FrameResult {
            index: f.index,
            t_ns: f.t_ns,
            status: status.into(),
            tip_camera_m: p.map(|p| p.tip_in_camera.translation.vector.into()),
            tip_camera_wxyz: p.map(|p| wxyz(&p.tip_in_camera.rotation)),
            tip_base_m: p.map(|p| p.tip_in_base.translation.vector.into()),
            tip_base_wxyz: p.map(|p| wxyz(&p.tip_in_base.rotation)),
            jaw_rad: p.map(|p| p.jaw_rad),
            camera_delta: p.map(|p| p.camera_delta),
            spread_m: est.spread_m.is_finite().then_some(est.spread_m),
            best_cost_px: est.best_cost_px.is_finite().then_some(est.best_cost_px),
            effective_particles: Some(est.effective_particles),
            inlier_share: Some(tracker.last_inlier_share()).filter(|v| v.is_finite()),
            line_share: Some(tracker.last_line_share()).filter(|v| v.is_finite()),
            held_by_prior: est.held_by_prior,
            reinitialised: est.reinitialised,
            reseeded_from_vision: est.reseeded_from_vision,
            axis_detected,
            reseed_share: Some(tracker.last_reseed_share()).filter(|v| v.is_finite()),
            error_mm: err.map(|e| e.0),
            error_deg: err.map(|e| e.1),
            kinematics_error_mm: kin.map(|k| k.0),
            kinematics_error_deg: kin.map(|k| k.1),
            visible_fraction: f.truth.map_or([None; 2], |t| t.visible_fraction),
            occlusion_target: f.truth.and_then(|t| t.occlusion_target),
            step_ms,
        });
        (opts.progress)(out.len());
    }
    if out.iter().all(|r| r.status == "SKIPPED") {
        return Err(RunError::Nothing(out.len()));
    }
    Ok(out)
}

/// Writes the results as JSON Lines.
pub fn write_jsonl(path: &Path, results: &[FrameResult]) -> Result<(), RunError> {
    let werr = |e: std::io::Error| RunError::Write { path: path.to_owned(), message: e.to_string() };
    let mut w = std::io::BufWriter::new(std::fs::File::create(path).map_err(werr)?);
    for r in results {
        let line =
            serde_json::to_string(r).map_err(|e| RunError::Write { path: path.to_owned(), message: e.to_string() })?;
        writeln!(w, "{line}").map_err(werr)?;
    }
    w.flush().map_err(werr)
}

/// The mode's name.
pub fn mode_name(m: Mode) -> &'static str {
    match m {
        Mode::Paper => "paper",
        Mode::Ours => "ours",
    }
}

/// The motion model of `cfg`: `offset` (the kinematic error as state, `track::OffsetMotion`)
/// or `joints` (the random walk over the joints).
pub fn motion_name(cfg: &TrackerConfig) -> &'static str {
    if cfg.offset_motion.is_some() { "offset" } else { "joints" }
}
