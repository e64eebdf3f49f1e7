//! Calibration from pixels: the paper's protocol (an `n_e⁴ × n_t²` grid of both arms' joints
//! with the Eq. 11 kinematic noise) rendered by the simulated stereo endoscope, the tool's
//! line detected in both eyes' images, and the calibration run on the detected lines, next to
//! the same poses with the exact (synthetic) lines.
//!
//! The scene is the renderer's world (`docs/vision.md`): `{e}` the endoscope arm's RCM, the
//! tool arm's RCM `{t}` at [`DemoMotion::instrument_rcm`] (the ground truth `T_e_t`), the
//! stereo endoscope of [`EndoscopeConfig`] (its intrinsics with distortion, its hand-eye
//! `T_f_c`, the right eye at `+baseline` along `x`, so `T_c_r = Tx(baseline)`).
//!
//! Kinematic noise: each observation's actual frames are the nominal ones perturbed as in
//! `sim::calib` (`T·exp(δ^)` on the ECM end effector and PSM frames 2 and 3). The renderer
//! computes the camera from the nominal joints, so the camera's perturbation is moved onto
//! the instrument (`T_e_i' = T_e_c · T_e_c_actual⁻¹ · T_e_i_actual`): the instrument is
//! where it actually is relative to the actual camera; only the tissue behind it moves by the
//! perturbation (background, no effect on the line).
//!
//! Line sources per image: `truth` (the exact projected axis, `sim::endoscope::truth`, kept
//! when at least [`MIN_SHAFT_PX`] of it is visible), and each detector's best detection
//! (`ends_px`). Eyes: `left` only, or `both` (two observations per pose).

use std::time::Instant;

use estimator::calib::ours::{OursConfig, solve_ours};
use estimator::calib::paper::{PaperConfig, solve_paper};
use estimator::calib::rcm_arms::{ecm_frames, psm_frames, se3_exp};
use estimator::calib::{Eye, KinematicNoise, Observation, Setup, pose_errors};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use sim::calib::NoiseUnits;
use sim::endoscope::{DemoMotion, EndoscopeConfig, InstrumentState, SceneState, StereoFrame, StereoRenderer};
use vision::shaft::ImageLine;
use vision::{RgbView, ShaftDetector};

/// Shortest visible shaft (pixels) for a truth line to be kept: the calibration protocol's
/// selection (`sim::calib::CalibGeometry::min_visible_px`).
pub const MIN_SHAFT_PX: f64 = 40.0;

/// The selection rule of the lines in these datasets (`estimator::calib::SelectionRule`): at
/// least [`MIN_SHAFT_PX`] of shaft visible, tip in view or not, no border margin (what a
/// line detector reports).
pub fn selection_rule() -> estimator::calib::SelectionRule {
    estimator::calib::SelectionRule {
        min_visible_shaft_px: MIN_SHAFT_PX,
        border_margin_px: 0.0,
        require_tip_in_view: false,
        // The detector's centreline is not cut where the shaft ends (its ends come from the
        // contours' extent): the points are only known to be on the shaft.
        ends_are_shaft_ends: false,
    }
}

/// Our shaft detector's precision of a line's end along the line on rendered frames, pixels
/// (`estimator::calib::ShaftExtent::end_sd_px`). Measured on the twin's live session of seed
/// 1 (the live calibration's tuning session, docs/calibration.md): the kept lines' ends that
/// lie past the image of the jaws' tips do so by 5.8 px (median), 11.4 px (p90), 13.9 px at
/// most, a half-normal of σ ≈ 7-9 px.
pub const DETECTOR_END_SD_PX: f64 = 8.0;

/// The part of the rendered instrument a detector can report as shaft
/// (`estimator::calib::ShaftExtent`): the renderer draws the jaws beyond the tip point (the jaw
/// pivot) and the whole shaft behind it, with no abdominal wall to hide the part outside the
/// trocar; our detector's end precision [`DETECTOR_END_SD_PX`].
pub fn rendered_shaft_extent(g: &sim::endoscope::InstrumentGeometry) -> estimator::calib::ShaftExtent {
    estimator::calib::ShaftExtent {
        beyond_tip_m: g.jaw_length_m,
        before_point_m: g.shaft_length_m + g.wrist_length_m,
        end_sd_px: DETECTOR_END_SD_PX,
    }
}

/// The run's parameters.
#[derive(Clone, Debug)]
pub struct PixelProtocol {
    /// Values per ECM joint (`n_e⁴` endoscope poses), 1..=4.
    pub n_e: usize,
    /// Values per PSM joint (`n_t²` tool directions), 1..=8.
    pub n_t: usize,
    /// σ of each component of δ (Eq. 11; see [`NoiseUnits`]).
    pub sigma: f64,
    /// Unit of δ's translation part.
    pub units: NoiseUnits,
    /// Seed of the kinematic noise (the renderer's own noise has the configuration's seed).
    pub seed: u64,
    /// The renderer (camera, realism options).
    pub endoscope: EndoscopeConfig,
    /// σ of each detected line point in our pipeline's noise model, pixels (the truth lines
    /// are exact projections and have none). Default: the live calibration's
    /// (`LiveConfig`'s `[noise] pixel_px`), what a user states for a detector's lines.
    pub detected_sigma_px: f64,
}

impl Default for PixelProtocol {
    /// 3⁴ × 3² poses, σ = 0.01 in millimetres, the renderer's default realism.
    fn default() -> Self {
        Self {
            n_e: 3,
            n_t: 3,
            sigma: 0.01,
            units: NoiseUnits::Millimetre,
            seed: 1,
            endoscope: sim::world::default_endoscope_config(),
            detected_sigma_px: crate::live_config::NoiseSection::default().pixel_px,
        }
    }
}

/// Why the run failed.
#[derive(Debug, thiserror::Error)]
pub enum PixelsError {
    /// Grid sizes out of range.
    #[error("grid sizes out of range: n_e = {n_e} (1..=4), n_t = {n_t} (1..=8)")]
    Grid {
        /// Values per ECM joint.
        n_e: usize,
        /// Values per PSM joint.
        n_t: usize,
    },
    /// A σ (the kinematic noise's or the detected lines' pixel σ) negative or not finite.
    #[error("noise σ must be finite and ≥ 0 (got {0})")]
    Sigma(f64),
    /// The renderer refused its configuration.
    #[error("renderer: {0}")]
    Renderer(String),
    /// A frame could not be rendered.
    #[error("render: {0}")]
    Render(String),
    /// An output file cannot be written.
    #[error("cannot write {0}")]
    Write(String),
}

/// One eye's line: its two ends (measured pixels) and the line (undistorted pixels).
pub type EyeLine = ([[f64; 2]; 2], ImageLine);

/// The left and the right eye's lines of one pose (`None`: no line in that eye).
pub type EyeLines = [Option<EyeLine>; 2];

/// One detector's accuracy on a run's frames (see [`detection_stats`]).
#[derive(Clone, Debug, PartialEq)]
pub struct DetectionStats {
    /// The detector's name.
    pub name: String,
    /// Truth lines (eyes with enough shaft visible).
    pub truth_lines: usize,
    /// Of those, the eyes where the detector found a shaft.
    pub detected: usize,
    /// Angle error, degrees: median and p95.
    pub angle_deg: [f64; 2],
    /// Offset at the truth segment's middle, pixels: median and p95.
    pub offset_px: [f64; 2],
    /// Median detection time per image, milliseconds.
    pub ms: f64,
}

/// One pose of the grid, rendered, with its lines.
#[derive(Clone, Debug)]
pub struct PoseLines {
    /// ECM joints `[yaw rad, pitch rad, insertion m, roll rad]`.
    pub ecm_joints: [f64; 4],
    /// PSM joints `[yaw rad, pitch rad, insertion m]`.
    pub psm_joints: [f64; 3],
    /// Per eye (left, right): the truth line's two ends (measured pixels) and its ideal line,
    /// when at least [`MIN_SHAFT_PX`] of the shaft is visible.
    pub truth: EyeLines,
    /// Per detector, per eye: the best detection's two ends (measured pixels) and centreline
    /// (undistorted pixels).
    pub detected: Vec<EyeLines>,
}

/// The rendered grid.
#[derive(Clone, Debug)]
pub struct PixelRun {
    /// Intrinsics, hand-eye and the right eye.
    pub setup: Setup,
    /// Ground truth `T_e_t`, metres.
    pub truth: Isometry3<f64>,
    /// The noise model of the truth lines (for our pipeline), `None` when noiseless.
    pub noise: Option<KinematicNoise>,
    /// The pixel σ of the detected lines in place of [`Self::noise`]'s, pixels (`None`: one
    /// model for every line source). See [`Self::noise_of`].
    pub detected_pixel_px: Option<f64>,
    /// Our pipeline takes the noise model as known up to a scale it estimates
    /// (`OursConfig::estimate_noise_scale`).
    pub estimate_noise_scale: bool,
    /// The detectors' names, in [`PoseLines::detected`]'s order.
    pub detectors: Vec<&'static str>,
    /// Every pose.
    pub poses: Vec<PoseLines>,
    /// Median detection time per image per detector, milliseconds.
    pub detect_ms: Vec<f64>,
    /// Rendering time, seconds.
    pub render_s: f64,
}

impl PixelRun {
    /// The noise model our pipeline is given for a line source: [`Self::noise`], with
    /// [`Self::detected_pixel_px`] for a detector's lines (`None` when noiseless: the pipeline
    /// then weighs every line alike, in pixels).
    pub fn noise_of(&self, source: LineSource) -> Option<KinematicNoise> {
        match (source, self.detected_pixel_px) {
            (LineSource::Detector(_), Some(pixel_px)) => self.noise.map(|n| KinematicNoise { pixel_px, ..n }),
            _ => self.noise,
        }
    }
}

fn grid(range: [f64; 2], n: usize) -> Vec<f64> {
    if n == 1 {
        return vec![0.5 * (range[0] + range[1])];
    }
    (0..n).map(|i| range[0] + (range[1] - range[0]) * i as f64 / (n - 1) as f64).collect()
}

fn draw(rng: &mut ChaCha8Rng, sigma: f64, rho_m: f64) -> Isometry3<f64> {
    let mut v = [0.0; 6];
    for x in &mut v {
        let z: f64 = rng.sample(StandardNormal);
        *x = z * sigma;
    }
    se3_exp(&(Vector3::new(v[0], v[1], v[2]) * rho_m), &Vector3::new(v[3], v[4], v[5]))
}

/// The PSM insertion of the grid: the tool tip 12 mm short of the point its trocar aims at
/// (7 cm in front of the endoscope at mid insertion).
pub fn psm_insertion_m() -> f64 {
    (Vector3::new(0.0, 0.006, 0.125) - DemoMotion::instrument_rcm().translation.vector).norm() - 0.012
}

/// Renders the grid and detects the lines with each of `detectors`. `progress` is called
/// after each pose with the count done.
pub fn render_and_detect(
    p: &PixelProtocol,
    detectors: &mut [Box<dyn ShaftDetector + Send>],
    mut progress: impl FnMut(usize, usize),
) -> Result<PixelRun, PixelsError> {
    if !(1..=4).contains(&p.n_e) || !(1..=8).contains(&p.n_t) {
        return Err(PixelsError::Grid { n_e: p.n_e, n_t: p.n_t });
    }
    if !(p.sigma.is_finite() && p.sigma >= 0.0) {
        return Err(PixelsError::Sigma(p.sigma));
    }
    if !(p.detected_sigma_px.is_finite() && p.detected_sigma_px >= 0.0) {
        return Err(PixelsError::Sigma(p.detected_sigma_px));
    }
    let cfg = p.endoscope.clone();
    let k = cfg.camera.intrinsics;
    let hand_eye = cfg.camera.hand_eye.isometry().ok_or_else(|| PixelsError::Renderer("hand-eye not finite".into()))?;
    let right = Isometry3::from_parts(Translation3::new(cfg.camera.baseline_m, 0.0, 0.0), UnitQuaternion::identity());
    let mesh = cfg.instrument.mesh().map_err(|e| PixelsError::Renderer(e.to_string()))?;
    let mut renderer = StereoRenderer::new(cfg, mesh).map_err(|e| PixelsError::Renderer(e.to_string()))?;
    let truth = DemoMotion::instrument_rcm();
    // Endoscope: ±3.4° yaw and pitch, 45-65 mm insertion, ±17° roll about its RCM; tool:
    // ±7° yaw and pitch about its trocar (which aims into the view).
    let ecm: Vec<[f64; 4]> = {
        let (a, b, c, d) = (
            grid([-0.06, 0.06], p.n_e),
            grid([-0.06, 0.06], p.n_e),
            grid([0.045, 0.065], p.n_e),
            grid([-0.3, 0.3], p.n_e),
        );
        let mut v = Vec::new();
        for &q1 in &a {
            for &q2 in &b {
                for &q3 in &c {
                    for &q4 in &d {
                        v.push([q1, q2, q3, q4]);
                    }
                }
            }
        }
        v
    };
    let ins = psm_insertion_m();
    let psm: Vec<[f64; 3]> = {
        let (a, b) = (grid([-0.12, 0.12], p.n_t), grid([-0.12, 0.12], p.n_t));
        a.iter().flat_map(|&q1| b.iter().map(move |&q2| [q1, q2, ins])).collect()
    };
    let rho = p.units.metres();
    let mut rng = ChaCha8Rng::seed_from_u64(p.seed);
    let mut frame = StereoFrame::default();
    let mut poses = Vec::with_capacity(ecm.len() * psm.len());
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); detectors.len()];
    let total = ecm.len() * psm.len();
    let mut render_s = 0.0;
    for qe in &ecm {
        let f4 = ecm_frames(qe)[3];
        for qt in &psm {
            let (de, da, db) = if p.sigma > 0.0 {
                (draw(&mut rng, p.sigma, rho), draw(&mut rng, p.sigma, rho), draw(&mut rng, p.sigma, rho))
            } else {
                (Isometry3::identity(), Isometry3::identity(), Isometry3::identity())
            };
            let cam_nominal = f4 * hand_eye;
            let cam_actual = f4 * de * hand_eye;
            let fr = psm_frames(qt);
            let f3 = fr[1] * da * Isometry3::translation(0.0, 0.0, qt[2]) * db;
            let roll = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.4);
            let inst_actual = truth * f3 * roll;
            let inst = cam_nominal * cam_actual.inverse() * inst_actual;
            let state = SceneState {
                ecm_joints: *qe,
                instrument: InstrumentState { pose_world: inst, wrist_rad: 0.2, jaw_rad: [0.2, 0.2], psm_joints: None },
                second: None,
            };
            let t0 = Instant::now();
            renderer.render_into(0, &|_| state, &mut frame).map_err(|e| PixelsError::Render(e.to_string()))?;
            render_s += t0.elapsed().as_secs_f64();
            let truth_lines = [0, 1].map(|eye| {
                let inst = frame.truth[eye].instruments.first()?;
                let axis = inst.axis.as_ref()?;
                let seg = axis.segment_px?;
                let ideal = axis.segment_ideal_px?;
                let len = (ideal[0][0] - ideal[1][0]).hypot(ideal[0][1] - ideal[1][1]);
                let line = ImageLine::new(axis.line_ideal).ok()?;
                (len >= MIN_SHAFT_PX).then_some((seg, line))
            });
            let mut detected = Vec::with_capacity(detectors.len());
            for (d, det) in detectors.iter_mut().enumerate() {
                let mut per_eye = [None, None];
                for (eye, slot) in per_eye.iter_mut().enumerate() {
                    let img = &frame.images[eye];
                    let view = RgbView::new(img.width as usize, img.height as usize, &img.rgb)
                        .map_err(|e| PixelsError::Render(e.to_string()))?;
                    let t0 = Instant::now();
                    let found = det.detect(&view);
                    times[d].push(t0.elapsed().as_secs_f64() * 1e3);
                    if let Ok(found) = found
                        && let Some(best) = found.first()
                    {
                        *slot = Some((best.ends_px, best.centreline));
                    }
                }
                detected.push(per_eye);
            }
            poses.push(PoseLines { ecm_joints: *qe, psm_joints: *qt, truth: truth_lines, detected });
            progress(poses.len(), total);
        }
    }
    let detect_ms = times.iter_mut().map(|t| median(t)).collect();
    let noise = KinematicNoise { rot_rad: p.sigma, trans_m: p.sigma * rho, pixel_px: 0.0 };
    let noise = noise.is_valid().then_some(noise);
    Ok(PixelRun {
        setup: Setup {
            intrinsics: k,
            hand_eye,
            right_eye: Some(right),
            selection: selection_rule(),
            shaft_extent: rendered_shaft_extent(&p.endoscope.instrument),
        },
        truth,
        noise,
        detected_pixel_px: Some(p.detected_sigma_px),
        estimate_noise_scale: false,
        detectors: detectors.iter().map(|d| d.name()).collect(),
        poses,
        detect_ms,
        render_s,
    })
}

/// Median of `v` (sorted in place); NaN when empty.
pub fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) }
}

/// Where a dataset's lines come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LineSource {
    /// The exact projected axis (ground truth).
    Truth,
    /// Detector `i` of [`PixelRun::detectors`].
    Detector(usize),
}

/// The observations of one line source and eye set: a pose's eye contributes when its line
/// exists (truth: visible enough; detector: a detection).
pub fn observations(run: &PixelRun, source: LineSource, both_eyes: bool) -> Vec<Observation> {
    let mut out = Vec::new();
    for pose in &run.poses {
        let lines = match source {
            LineSource::Truth => &pose.truth,
            LineSource::Detector(i) => match pose.detected.get(i) {
                Some(l) => l,
                None => continue,
            },
        };
        for (eye, line) in lines.iter().enumerate() {
            if eye == 1 && !both_eyes {
                break;
            }
            if let Some((ends, _)) = line {
                out.push(Observation {
                    ecm_joints: pose.ecm_joints,
                    psm_joints: pose.psm_joints,
                    tool_point_m: [0.0; 3],
                    line_px: *ends,
                    eye: if eye == 0 { Eye::Left } else { Eye::Right },
                });
            }
        }
    }
    out
}

/// Angle (degrees) and offset (pixels, at the truth segment's middle) of a detected
/// centreline against the truth line; `None` without both.
pub fn line_error(truth: &EyeLine, detected: &ImageLine, k: &estimator::calib::Intrinsics) -> (f64, f64) {
    let (t, d) = (truth.1.abc, detected.abc);
    let cos = (t[0] * d[0] + t[1] * d[1]).abs().min(1.0);
    let angle = cos.acos().to_degrees();
    let a = k.undistort_px(&nalgebra::Vector2::from(truth.0[0]));
    let b = k.undistort_px(&nalgebra::Vector2::from(truth.0[1]));
    let m = (a + b) * 0.5;
    (angle, detected.distance_px(m.x, m.y).abs())
}

/// One row of the calibration-from-pixels table.
#[derive(Clone, Debug)]
pub struct CalibRow {
    /// Line source name (`truth`, or the detector's).
    pub source: String,
    /// `left` or `both`.
    pub eyes: &'static str,
    /// Observations used.
    pub observations: usize,
    /// Paper pipeline: translation error (mm) and rotation error (°), or the error message.
    pub paper: Result<(f64, f64), String>,
    /// Our pipeline: the same.
    pub ours: Result<(f64, f64), String>,
}

/// Runs both pipelines on every line source × eye set.
pub fn calibrate_all(run: &PixelRun) -> Vec<CalibRow> {
    let mut sources = vec![(LineSource::Truth, "truth".to_string())];
    for (i, n) in run.detectors.iter().enumerate() {
        sources.push((LineSource::Detector(i), (*n).to_string()));
    }
    let mut rows = Vec::new();
    for (source, name) in sources {
        for (both, eyes) in [(false, "left"), (true, "both")] {
            let obs = observations(run, source, both);
            let paper = solve_paper(&run.setup, &obs, &PaperConfig::default())
                .map(|r| {
                    let e = pose_errors(&r.pose, &run.truth);
                    (e.translation_m * 1e3, e.rotation_rad.to_degrees())
                })
                .map_err(|e| e.to_string());
            let cfg = OursConfig {
                noise: run.noise_of(source),
                estimate_noise_scale: run.estimate_noise_scale,
                ..OursConfig::default()
            };
            // As `calibrate` judges it: a refused selection-aware stage is a failure (the
            // unrefined estimate is only handed out when the user accepts it).
            let ours = solve_ours(&run.setup, &obs, &cfg).map_err(|e| e.to_string()).and_then(|r| {
                let e = pose_errors(&r.pose, &run.truth);
                let (t, a) = (e.translation_m * 1e3, e.rotation_rad.to_degrees());
                match &r.selection_refused {
                    None => Ok((t, a)),
                    Some(why) => Err(format!(
                        "refused: the selection-aware stage was not applied ({why}); the unrefined estimate is {t:.3} mm / {a:.4}° off"
                    )),
                }
            });
            rows.push(CalibRow { source: name.clone(), eyes, observations: obs.len(), paper, ours });
        }
    }
    rows
}

/// Detection accuracy of each detector on the run's frames against the truth lines (both
/// eyes).
pub fn detection_stats(run: &PixelRun) -> Vec<DetectionStats> {
    let k = &run.setup.intrinsics;
    let mut out = Vec::new();
    for (i, name) in run.detectors.iter().enumerate() {
        let (mut n, mut found, mut ang, mut off) = (0, 0, Vec::new(), Vec::new());
        for pose in &run.poses {
            for eye in 0..2 {
                let Some(t) = &pose.truth[eye] else { continue };
                n += 1;
                if let Some(Some((_, l))) = pose.detected.get(i).map(|d| &d[eye]) {
                    found += 1;
                    let (a, o) = line_error(t, l, k);
                    ang.push(a);
                    off.push(o);
                }
            }
        }
        let q = |v: &mut Vec<f64>, f: f64| {
            v.sort_by(f64::total_cmp);
            if v.is_empty() { f64::NAN } else { v[((v.len() - 1) as f64 * f).round() as usize] }
        };
        out.push(DetectionStats {
            name: (*name).to_string(),
            truth_lines: n,
            detected: found,
            angle_deg: [q(&mut ang, 0.5), q(&mut ang, 0.95)],
            offset_px: [q(&mut off, 0.5), q(&mut off, 0.95)],
            ms: run.detect_ms.get(i).copied().unwrap_or(f64::NAN),
        });
    }
    out
}

/// The Markdown report of a run: the protocol, the detection table and the calibration table.
pub fn report_markdown(p: &PixelProtocol, run: &PixelRun, rows: &[CalibRow], command: &str) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let k = &run.setup.intrinsics;
    let _ = writeln!(s, "<!-- written by `{command}` -->");
    let _ = writeln!(
        s,
        "Protocol: {}⁴ endoscope poses × {}² tool directions = {} stereo frames, σ = {} ({}), seed {}; camera {}×{}, f = {} px, distortion k1 = {}, baseline {} mm; rendering {:.1} s.\n",
        p.n_e,
        p.n_t,
        run.poses.len(),
        p.sigma,
        p.units.name(),
        p.seed,
        k.width,
        k.height,
        k.fx,
        k.distortion[0],
        run.setup.right_eye.map_or(0.0, |r| r.translation.vector.x * 1e3),
        run.render_s
    );
    let _ = writeln!(s, "Detection on these frames (both eyes; truth lines with ≥ {MIN_SHAFT_PX} px of shaft):\n");
    let _ = writeln!(
        s,
        "| detector | truth lines | detected | angle median / p95 (°) | offset median / p95 (px) | ms per image (median) |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|");
    s.push_str(&detection_rows(run));
    let _ = writeln!(
        s,
        "\nCalibration (e_t mm / e_R °, against the truth `T_e_t`). Our pipeline's noise model: the protocol's kinematic σ, and a pixel σ of {} px for the detected lines (the truth lines have none).\n",
        p.detected_sigma_px
    );
    let _ = writeln!(s, "| lines | eyes | observations | paper pipeline | our pipeline |");
    let _ = writeln!(s, "|---|---|---|---|---|");
    s.push_str(&calibration_rows(rows));
    s
}

/// Writes, into `dir/datasets/` (created), each line source's dataset with both eyes
/// (`dataset_<source>.json`, readable by `comanip-calib calibrate`) and the ground truth
/// (`truth.json`).
pub fn write_datasets(run: &PixelRun, p: &PixelProtocol, dir: &std::path::Path) -> Result<(), PixelsError> {
    use hw_io::calib_files::{CALIB_FILE_VERSION, TRUTH_FORMAT, TruthFile, to_json};
    let dir = &dir.join("datasets");
    std::fs::create_dir_all(dir).map_err(|e| PixelsError::Write(format!("{}: {e}", dir.display())))?;
    let write = |name: String, text: String| {
        let path = dir.join(name);
        std::fs::write(&path, text).map_err(|e| PixelsError::Write(format!("{}: {e}", path.display())))
    };
    let mut sources = vec![(LineSource::Truth, "truth".to_string())];
    for (i, n) in run.detectors.iter().enumerate() {
        sources.push((LineSource::Detector(i), (*n).to_string()));
    }
    for (source, name) in sources {
        let obs = observations(run, source, true);
        let file = crate::convert::dataset_json(&run.setup, &obs, run.noise_of(source));
        write(format!("dataset_{name}.json"), to_json(&file))?;
    }
    let t = TruthFile {
        format: TRUTH_FORMAT.into(),
        version: CALIB_FILE_VERSION,
        truth: crate::convert::transform_json(&run.truth),
        n_e: p.n_e,
        n_t: p.n_t,
        sigma: p.sigma,
        units: p.units.name().into(),
        pixel_sigma_px: 0.0,
        seed: p.seed,
        generated: run.poses.len(),
        dropped: run.poses.iter().filter(|q| q.truth[0].is_none()).count(),
        collided: 0,
        wrong_lines: vec![],
    };
    write("truth.json".into(), to_json(&t))
}

/// The rows of the detection table (Markdown, one per detector, after the header).
pub fn detection_rows(run: &PixelRun) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    for d in detection_stats(run) {
        let _ = writeln!(
            s,
            "| {} | {} | {} ({:.1} %) | {:.3} / {:.3} | {:.3} / {:.3} | {:.2} |",
            d.name,
            d.truth_lines,
            d.detected,
            100.0 * d.detected as f64 / d.truth_lines.max(1) as f64,
            d.angle_deg[0],
            d.angle_deg[1],
            d.offset_px[0],
            d.offset_px[1],
            d.ms
        );
    }
    s
}

/// The rows of the calibration table (Markdown, one per line source and eye set).
pub fn calibration_rows(rows: &[CalibRow]) -> String {
    use std::fmt::Write;
    let cell = |r: &Result<(f64, f64), String>| match r {
        Ok((t, a)) => format!("{t:.3} mm / {a:.4}°"),
        Err(e) => format!("failed: {e}"),
    };
    let mut s = String::new();
    for r in rows {
        let _ =
            writeln!(s, "| {} | {} | {} | {} | {} |", r.source, r.eyes, r.observations, cell(&r.paper), cell(&r.ours));
    }
    s
}
