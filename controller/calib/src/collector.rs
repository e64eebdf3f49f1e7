//! The live calibration's collector (issue 19): pure logic, no I/O, fed in time order.
//!
//! Each [`Sample`] is one stereo frame with what the product knows at its exposure time: the
//! shaft detections of both eyes, the endoscope arm's joints and the tool arm's line (from
//! fulcrumd's fulcrum and axis, metres, the tool arm's base `{b}` = the calibration's `{t}`),
//! each with its age. The collector
//! - **refuses** what cannot be trusted or adds nothing, with a counted [`Refusal`] reason:
//!   frame-level (stale encoders, invalid fulcrum, frozen camera), per eye (no instrument, a
//!   second instrument, low detector confidence, blur, redundant);
//! - **keeps** an eye's line as an [`Observation`] through the fulcrum (projected onto the
//!   instrument axis, so that the point lies on the kinematic line) along the axis;
//! - reports the **predicted precision** from the Fisher information of the kept
//!   observations at the current estimate (`F = Σ JᵢᵀΣᵢ⁻¹Jᵢ` under the configured noise
//!   model, [`estimator::calib::crb`]'s model): the RMS translation at the mean fulcrum and
//!   at `{t}`'s origin, and the RMS rotation;
//! - **solves** (our pipeline, `estimator::calib::ours`) first when the data first allow it
//!   (a provisional estimate, to evaluate the information at), again every
//!   [`CollectorConfig::resolve_every`] kept observations, and finally when the predicted
//!   precision reaches the configured target ([`Event::Solved`]);
//! - **watches for drift** after a solve: each new kept observation's whitened residual
//!   (χ² with 2 degrees of freedom under the noise model) at the result; when more than
//!   [`CollectorConfig::drift_fraction`] of the last [`CollectorConfig::drift_window`]
//!   exceed [`CollectorConfig::drift_chi2`], the result is flagged and collection restarts.
//!
//! Once an estimate exists, "adds information" is measured: the observation's information
//! gain `ln det(F + Fᵢ) − ln det F` must exceed [`CollectorConfig::min_information_gain`];
//! before, a diversity test in joint space and in the image stands in for it.

use std::collections::BTreeMap;

use estimator::calib::ours::{OursConfig, OursError, solve_ours};
use estimator::calib::prepare::prepare_unchecked;
use estimator::calib::residual::{residual_and_jacobian, residual_covariance};
use estimator::calib::selection::SelectionError;
use estimator::calib::{Eye, KinematicNoise, Observation, Setup};
use nalgebra::{Isometry3, Matrix6, Vector3};

/// One eye's shaft detection, as the detector reported it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct EyeDetection {
    /// Shafts found (0: no instrument in view).
    pub found: usize,
    /// The best shaft's centreline end points, measured (distorted) pixels.
    pub ends_px: Option<[[f64; 2]; 2]>,
    /// The best shaft's confidence (the detector's, 0-1).
    pub confidence: f64,
    /// The runner-up shaft's confidence (0 when there is none).
    pub second_confidence: f64,
    /// Image sharpness (the caller's measure, e.g. the variance of the Laplacian, grey
    /// levels²); `None` when not measured.
    pub sharpness: Option<f64>,
}

/// The tool arm's line at the frame's time, from fulcrumd's output (metres, radians, the
/// arm's base `{b}`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ToolSample {
    /// True while fulcrumd says the instrument is inside a trocar with a valid fulcrum.
    pub fulcrum_valid: bool,
    /// The published fulcrum, metres, `{b}`.
    pub fulcrum_m: [f64; 3],
    /// The instrument axis (toward the tip), `{b}`.
    pub axis: [f64; 3],
    /// The wrist centre `P` (a point of the instrument axis), metres, `{b}`.
    pub wrist_m: [f64; 3],
    /// Distance from the wrist centre to the tip along the axis, metres.
    pub wrist_to_tip_m: f64,
    /// Age of the tool arm's encoder data at the frame's exposure mid time, nanoseconds.
    pub age_ns: u64,
    /// Distance in time from the frame's exposure mid time to the fulcrumd sample the line
    /// comes from, nanoseconds (`u64::MAX`: no sample, fulcrumd silent).
    pub fulcrum_age_ns: u64,
}

/// One stereo frame and both arms' data at its time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    /// Exposure mid time, nanoseconds (bus clock).
    pub t_ns: u64,
    /// A digest of the frame's pixels (both eyes): equal digests in a row = frozen camera.
    pub frame_digest: u64,
    /// Left and right eye detections.
    pub eyes: [EyeDetection; 2],
    /// The endoscope arm's joints `[yaw rad, pitch rad, insertion m, roll rad]`.
    pub ecm_joints: [f64; 4],
    /// Age of the endoscope joints at the frame's time, nanoseconds.
    pub ecm_age_ns: u64,
    /// The tool arm's line.
    pub tool: ToolSample,
}

/// Why a frame or an eye's line was not kept.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Refusal {
    /// Frame: an arm's data are older than [`CollectorConfig::max_age_ns`] (an arm that stops
    /// answering), or not finite.
    StaleEncoders,
    /// Frame: no fulcrumd output near the frame's time (fulcrumd silent or not running).
    NoFulcrum,
    /// Frame: the instrument is not inside a trocar with a valid fulcrum.
    InvalidFulcrum,
    /// Frame: identical to the previous frame, or its time not after the previous frame's
    /// (frozen camera: repeated images or a stalled clock).
    FrozenCamera,
    /// Eye: no instrument in view.
    NoInstrument,
    /// Eye: a second instrument, or two shafts the detector cannot tell apart.
    Ambiguous,
    /// Eye: detector confidence below [`CollectorConfig::min_confidence`].
    LowConfidence,
    /// Eye: image sharpness below [`CollectorConfig::min_sharpness`] (blur).
    Blurred,
    /// Eye: adds (almost) no information to what is kept.
    Redundant,
    /// Eye: the collection holds [`CollectorConfig::max_observations`] already (the line was
    /// still scored by the drift watch).
    Full,
}

impl Refusal {
    /// Every reason, in display order.
    pub const ALL: [Refusal; 10] = [
        Refusal::StaleEncoders,
        Refusal::NoFulcrum,
        Refusal::InvalidFulcrum,
        Refusal::FrozenCamera,
        Refusal::NoInstrument,
        Refusal::Ambiguous,
        Refusal::LowConfidence,
        Refusal::Blurred,
        Refusal::Redundant,
        Refusal::Full,
    ];

    /// A short name for progress lines and reports.
    pub fn name(self) -> &'static str {
        match self {
            Refusal::StaleEncoders => "stale encoders",
            Refusal::NoFulcrum => "no fulcrum",
            Refusal::InvalidFulcrum => "invalid fulcrum",
            Refusal::FrozenCamera => "frozen camera",
            Refusal::NoInstrument => "no instrument",
            Refusal::Ambiguous => "second instrument",
            Refusal::LowConfidence => "low confidence",
            Refusal::Blurred => "blurred",
            Refusal::Redundant => "redundant",
            Refusal::Full => "collection full",
        }
    }
}

/// The collector's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CollectorConfig {
    /// Camera, hand-eye, stereo transform and the detector's selection rule.
    pub setup: Setup,
    /// The noise model of one observation (pixels, and the frame perturbations of the camera
    /// and of the tool line's frame at the fulcrum): the weights and the Fisher information.
    pub noise: KinematicNoise,
    /// Oldest arm data accepted at a frame's time, nanoseconds.
    pub max_age_ns: u64,
    /// Lowest detector confidence accepted (0-1).
    pub min_confidence: f64,
    /// A runner-up shaft at least this confident makes the eye ambiguous (0-1).
    pub ambiguous_confidence: f64,
    /// Lowest sharpness accepted (same unit as [`EyeDetection::sharpness`]); 0 = no check.
    pub min_sharpness: f64,
    /// Before an estimate exists: a line is redundant when a kept line of the same eye is
    /// within this in every endoscope joint (radians; metres × 10 for the insertion) …
    pub min_joint_step_rad: f64,
    /// … and its tool axis within this angle, radians …
    pub min_axis_step_rad: f64,
    /// … and both end points' distances to the kept line below this, pixels.
    pub min_image_step_px: f64,
    /// With an estimate: the least information gain `ln det(F + Fᵢ) − ln det F` kept.
    pub min_information_gain: f64,
    /// Kept observations needed before the first (provisional) solve.
    pub min_observations: usize,
    /// The most observations one collection keeps (a bound on the process's memory and on
    /// each solve's time: the information gain of a new line falls only as 1/n, so without it
    /// an hours-long session would keep tens of thousands); beyond, lines are refused as
    /// [`Refusal::Full`] and the drift watch goes on.
    pub max_observations: usize,
    /// Re-solve every this many new kept observations (the information is evaluated at the
    /// latest estimate).
    pub resolve_every: usize,
    /// Target: predicted RMS translation at the mean fulcrum, metres.
    pub target_translation_m: f64,
    /// Target: predicted RMS rotation, radians.
    pub target_rotation_rad: f64,
    /// Drift: a kept observation misfits when its whitened χ² (2 degrees of freedom) at the
    /// result exceeds this.
    pub drift_chi2: f64,
    /// Drift: the window of recent kept observations scored.
    pub drift_window: usize,
    /// Drift: flagged when more than this fraction of the window misfits.
    pub drift_fraction: f64,
}

impl CollectorConfig {
    /// Defaults for `setup` and `noise`: 1 mm / 0.2° target, 100 ms oldest data.
    pub fn new(setup: Setup, noise: KinematicNoise) -> Self {
        Self {
            setup,
            noise,
            max_age_ns: 100_000_000,
            min_confidence: 0.5,
            ambiguous_confidence: 0.5,
            min_sharpness: 0.0,
            min_joint_step_rad: 0.2f64.to_radians(),
            min_axis_step_rad: 0.2f64.to_radians(),
            min_image_step_px: 1.0,
            min_information_gain: 1e-3,
            min_observations: 40,
            max_observations: 2000,
            resolve_every: 100,
            target_translation_m: 1e-3,
            target_rotation_rad: 0.2f64.to_radians(),
            drift_chi2: 13.8,
            drift_window: 40,
            drift_fraction: 0.5,
        }
    }
}

/// The precision the kept observations support (from the Fisher information at the current
/// estimate): RMS errors, `√tr` of the covariance blocks.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Precision {
    /// RMS translation of the mean fulcrum mapped into `{e}`, metres.
    pub fulcrum_m: f64,
    /// RMS translation of `{t}`'s origin (the tool arm's base), metres.
    pub origin_m: f64,
    /// RMS rotation, radians.
    pub rotation_rad: f64,
    /// The covariance `F⁻¹`, order `(tx, ty, tz m, φx, φy, φz rad)`.
    pub covariance: Matrix6<f64>,
}

/// Why a solve produced no calibration.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SolveError {
    /// Our pipeline failed (degenerate, ambiguous, unexplained shafts...).
    #[error(transparent)]
    Ours(#[from] OursError),
    /// The selection-aware stage was refused: the pose would be the unrefined (border-guarded)
    /// fit, which `calibrate` only hands out when the user accepts it; never published live.
    #[error("the selection-aware stage was refused ({0}); the unrefined estimate is not a calibration")]
    SelectionRefused(SelectionError),
}

/// A calibration the collector produced.
#[derive(Clone, Debug)]
pub struct Calibration {
    /// `T_e_t` (metres): the tool arm's base in the endoscope arm's RCM frame.
    pub pose: Isometry3<f64>,
    /// Its predicted precision (Fisher information of the observations used, at `pose`).
    pub precision: Precision,
    /// Our pipeline's result (its own covariance `σ̂² (JᵀWJ)⁻¹`, residuals, ambiguity).
    pub ours: estimator::calib::ours::OursResult,
    /// Observations used.
    pub observations: usize,
    /// Time of the last sample used, nanoseconds.
    pub t_ns: u64,
}

/// What one sample did.
#[derive(Clone, Debug)]
pub enum Event {
    /// Nothing beyond the counts.
    None,
    /// The target precision was reached: a calibration to publish (boxed: it is large).
    Solved(Box<Calibration>),
    /// Sustained misfit of new observations against the current calibration: it is flagged
    /// and collection restarted (fraction of the window that misfit).
    Drift {
        /// Fraction of the drift window above [`CollectorConfig::drift_chi2`].
        misfit_fraction: f64,
    },
}

/// Counts and state for a progress display.
#[derive(Clone, Debug, Default)]
pub struct Progress {
    /// Frames seen.
    pub frames: usize,
    /// Observations kept (eye lines) in the current collection.
    pub kept: usize,
    /// Refusals by reason (frame-level reasons count frames, the others eye images).
    pub refused: BTreeMap<Refusal, usize>,
    /// Fulcrum sites: published fulcrums more than 5 mm apart among the kept observations
    /// (a coverage figure; fulcrumd's first estimates at an entry scatter, so one trocar can
    /// count more than once).
    pub trocars: usize,
    /// Spread of the kept tool axes: the largest angle from their mean, radians.
    pub axis_spread_rad: f64,
    /// Spread of the kept endoscope poses: the largest yaw/pitch/roll range, radians.
    pub ecm_spread_rad: f64,
    /// The predicted precision, once an estimate exists.
    pub precision: Option<Precision>,
    /// Solves so far (provisional and final).
    pub solves: usize,
    /// Collections restarted by the drift watch.
    pub drifts: usize,
    /// The published calibration, if any.
    pub solved: bool,
}

/// The collector. Feed [`Collector::push`] in time order.
pub struct Collector {
    cfg: CollectorConfig,
    kept: Vec<Observation>,
    fisher: Matrix6<f64>,
    estimate: Option<Isometry3<f64>>,
    since_solve: usize,
    retry_at: usize,
    result: Option<Calibration>,
    drift: Vec<bool>,
    last_digest: Option<u64>,
    last_t_ns: Option<u64>,
    progress: Progress,
    trocars: Vec<Vector3<f64>>,
}

impl Collector {
    /// An empty collector.
    pub fn new(cfg: CollectorConfig) -> Self {
        Self {
            cfg,
            kept: Vec::new(),
            fisher: Matrix6::zeros(),
            estimate: None,
            since_solve: 0,
            retry_at: 0,
            result: None,
            drift: Vec::new(),
            last_digest: None,
            last_t_ns: None,
            progress: Progress::default(),
            trocars: Vec::new(),
        }
    }

    /// The counts and the predicted precision so far.
    pub fn progress(&self) -> &Progress {
        &self.progress
    }

    /// The kept observations of the current collection.
    pub fn observations(&self) -> &[Observation] {
        &self.kept
    }

    /// The current calibration, if one was solved (and not invalidated by drift).
    pub fn result(&self) -> Option<&Calibration> {
        self.result.as_ref()
    }

    fn refuse(&mut self, why: Refusal) {
        *self.progress.refused.entry(why).or_insert(0) += 1;
    }

    /// Feeds one sample (time order); returns what it caused.
    pub fn push(&mut self, s: &Sample) -> Event {
        self.progress.frames += 1;
        let frozen = self.last_digest == Some(s.frame_digest) || self.last_t_ns.is_some_and(|t| s.t_ns <= t);
        self.last_digest = Some(s.frame_digest);
        self.last_t_ns = Some(self.last_t_ns.map_or(s.t_ns, |t| t.max(s.t_ns)));
        let finite = s
            .ecm_joints
            .iter()
            .chain(&s.tool.axis)
            .chain(&s.tool.fulcrum_m)
            .chain(&s.tool.wrist_m)
            .all(|v| v.is_finite());
        if !finite || s.ecm_age_ns > self.cfg.max_age_ns || s.tool.age_ns > self.cfg.max_age_ns {
            self.refuse(Refusal::StaleEncoders);
            return Event::None;
        }
        if s.tool.fulcrum_age_ns > self.cfg.max_age_ns {
            self.refuse(Refusal::NoFulcrum);
            return Event::None;
        }
        if !s.tool.fulcrum_valid {
            self.refuse(Refusal::InvalidFulcrum);
            return Event::None;
        }
        if frozen {
            self.refuse(Refusal::FrozenCamera);
            return Event::None;
        }
        let Some(axis) = Vector3::from(s.tool.axis).try_normalize(1e-9) else {
            self.refuse(Refusal::StaleEncoders);
            return Event::None;
        };
        // The fulcrum projected onto the instrument axis: a point of the kinematic line.
        let wrist = Vector3::from(s.tool.wrist_m);
        let fulcrum = wrist + axis * (Vector3::from(s.tool.fulcrum_m) - wrist).dot(&axis);
        let tip = wrist + axis * s.tool.wrist_to_tip_m;
        let tip_m = (tip - fulcrum).dot(&axis);
        let mut event = Event::None;
        for (k, eye) in s.eyes.iter().enumerate() {
            let which = if k == 0 { Eye::Left } else { Eye::Right };
            if which == Eye::Right && self.cfg.setup.right_eye.is_none() {
                continue;
            }
            let Some(ends) = eye.ends_px.filter(|_| eye.found > 0) else {
                self.refuse(Refusal::NoInstrument);
                continue;
            };
            if eye.found > 1 && eye.second_confidence >= self.cfg.ambiguous_confidence {
                self.refuse(Refusal::Ambiguous);
                continue;
            }
            // (NaN confidence counts as low.)
            if eye.confidence.is_nan() || eye.confidence < self.cfg.min_confidence {
                self.refuse(Refusal::LowConfidence);
                continue;
            }
            if self.cfg.min_sharpness > 0.0 && eye.sharpness.is_some_and(|v| v.is_nan() || v < self.cfg.min_sharpness) {
                self.refuse(Refusal::Blurred);
                continue;
            }
            let Some(obs) = Observation::from_tool_line(s.ecm_joints, fulcrum.into(), axis.into(), tip_m, ends, which)
            else {
                self.refuse(Refusal::StaleEncoders);
                continue;
            };
            let info = match self.information(&obs) {
                Ok(Some(fi)) => {
                    if !self.adds_information(&obs, &fi) {
                        self.refuse(Refusal::Redundant);
                        continue;
                    }
                    Some(fi)
                }
                Ok(None) => {
                    if self.near_a_kept(&obs) {
                        self.refuse(Refusal::Redundant);
                        continue;
                    }
                    None
                }
                // A line the estimator cannot use (coincident points): no instrument line.
                Err(()) => {
                    self.refuse(Refusal::NoInstrument);
                    continue;
                }
            };
            if let Some(e) = self.score_drift(&obs) {
                event = e;
                continue;
            }
            if self.kept.len() >= self.cfg.max_observations {
                self.refuse(Refusal::Full);
                continue;
            }
            if let Some(fi) = info {
                self.fisher += fi;
            }
            self.keep(obs, Vector3::from(s.tool.fulcrum_m));
            if let Some(e) = self.maybe_solve(s.t_ns) {
                event = e;
            }
        }
        event
    }

    fn keep(&mut self, obs: Observation, fulcrum: Vector3<f64>) {
        self.kept.push(obs);
        self.since_solve += 1;
        self.progress.kept = self.kept.len();
        if self.trocars.iter().all(|t| (t - fulcrum).norm() > 5e-3) {
            self.trocars.push(fulcrum);
        }
        self.progress.trocars = self.trocars.len();
        let axes: Vec<Vector3<f64>> =
            self.kept.iter().map(|o| estimator::calib::rcm_arms::psm_axis(&o.psm_joints)).collect();
        let mean = axes.iter().sum::<Vector3<f64>>().try_normalize(1e-12).unwrap_or_else(Vector3::z);
        self.progress.axis_spread_rad = axes.iter().map(|a| a.angle(&mean)).fold(0.0, f64::max);
        let range = |k: usize| {
            let (lo, hi) = self.kept.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), o| {
                (lo.min(o.ecm_joints[k]), hi.max(o.ecm_joints[k]))
            });
            hi - lo
        };
        self.progress.ecm_spread_rad = [0, 1, 3].map(range).into_iter().fold(0.0, f64::max);
    }

    /// The observation's Fisher information at the current estimate (`None` before one).
    #[allow(clippy::result_unit_err, reason = "private helper: the caller maps it to a refusal")]
    fn information(&self, obs: &Observation) -> Result<Option<Matrix6<f64>>, ()> {
        let Some(pose) = &self.estimate else { return Ok(None) };
        let set = prepare_unchecked(&self.cfg.setup, std::slice::from_ref(obs)).map_err(|_| ())?;
        let Some(o) = set.obs.first() else { return Err(()) };
        let (r, t) = (pose.rotation.to_rotation_matrix().into_inner(), pose.translation.vector);
        let (_, j) = residual_and_jacobian(&set, o, &r, &t);
        let cov = residual_covariance(&set, o, &r, &t, &self.cfg.noise);
        let si = cov.try_inverse().ok_or(())?;
        Ok(Some(j.transpose() * si * j))
    }

    fn adds_information(&self, obs: &Observation, fi: &Matrix6<f64>) -> bool {
        let before = self.fisher.cholesky();
        let after = (self.fisher + fi).cholesky();
        match (before, after) {
            (Some(b), Some(a)) => {
                let ld = |c: &nalgebra::Cholesky<f64, nalgebra::U6>| {
                    2.0 * c.l().diagonal().iter().map(|v| v.ln()).sum::<f64>()
                };
                ld(&a) - ld(&b) > self.cfg.min_information_gain
            }
            // Not yet full rank: anything new counts unless it repeats a kept line.
            _ => !self.near_a_kept(obs),
        }
    }

    /// True when a kept line of the same eye is within the diversity steps in joints, tool
    /// axis and image.
    fn near_a_kept(&self, obs: &Observation) -> bool {
        let c = &self.cfg;
        let m = estimator::calib::rcm_arms::psm_axis(&obs.psm_joints);
        self.kept.iter().any(|k| {
            k.eye == obs.eye
                && (0..4).all(|i| {
                    let scale = if i == 2 { 10.0 } else { 1.0 };
                    ((k.ecm_joints[i] - obs.ecm_joints[i]) * scale).abs() < c.min_joint_step_rad
                })
                && estimator::calib::rcm_arms::psm_axis(&k.psm_joints).angle(&m) < c.min_axis_step_rad
                && line_distance_px(&k.line_px, &obs.line_px) < c.min_image_step_px
        })
    }

    /// Drift watch after a solve: scores `obs` at the result; `Some(Drift)` restarts.
    fn score_drift(&mut self, obs: &Observation) -> Option<Event> {
        let result = self.result.as_ref()?;
        let set = prepare_unchecked(&self.cfg.setup, std::slice::from_ref(obs)).ok()?;
        let o = set.obs.first()?;
        let (r, t) = (result.pose.rotation.to_rotation_matrix().into_inner(), result.pose.translation.vector);
        let (res, _) = residual_and_jacobian(&set, o, &r, &t);
        let cov = residual_covariance(&set, o, &r, &t, &self.cfg.noise);
        let chi2 = cov.try_inverse().map_or(f64::INFINITY, |si| (res.transpose() * si * res)[(0, 0)]);
        self.drift.push(chi2.is_nan() || chi2 > self.cfg.drift_chi2);
        let w = self.cfg.drift_window.max(1);
        if self.drift.len() > w {
            self.drift.remove(0);
        }
        if self.drift.len() < w {
            return None;
        }
        let frac = self.drift.iter().filter(|b| **b).count() as f64 / w as f64;
        if frac > self.cfg.drift_fraction {
            self.restart();
            self.progress.drifts += 1;
            return Some(Event::Drift { misfit_fraction: frac });
        }
        None
    }

    /// Drops the collection and the result (drift) and starts again.
    pub fn restart(&mut self) {
        self.kept.clear();
        self.fisher = Matrix6::zeros();
        self.estimate = None;
        self.result = None;
        self.since_solve = 0;
        self.retry_at = 0;
        self.drift.clear();
        self.trocars.clear();
        let p = &mut self.progress;
        (p.kept, p.trocars, p.precision, p.solved, p.axis_spread_rad, p.ecm_spread_rad) = (0, 0, None, false, 0.0, 0.0);
    }

    /// Solves now, whatever the precision (the "on request" path); `None` when the data do
    /// not allow a solve yet.
    pub fn solve_now(&mut self, t_ns: u64) -> Option<Result<Calibration, SolveError>> {
        if self.kept.len() < self.cfg.min_observations {
            return None;
        }
        Some(self.solve(t_ns))
    }

    fn solve(&mut self, t_ns: u64) -> Result<Calibration, SolveError> {
        // The configured noise model is a prior guess of the session's noise (the twin's is
        // 20× smaller than the default's): the solve estimates its scale. The information and
        // the published precision keep the configured model (conservative: the errors of a
        // live session are mostly model error, which no noise scale describes).
        let cfg = OursConfig { noise: Some(self.cfg.noise), estimate_noise_scale: true, ..OursConfig::default() };
        let r = solve_ours(&self.cfg.setup, &self.kept, &cfg)?;
        self.progress.solves += 1;
        // A refused stage leaves a fit the data contradict (on the HIL bench once the mirror,
        // 161° off): neither published nor kept as the estimate the information accumulates at.
        if let Some(e) = r.selection_refused {
            return Err(SolveError::SelectionRefused(e));
        }
        self.estimate = Some(r.pose);
        self.since_solve = 0;
        // The information of every kept observation at the new estimate.
        self.fisher = Matrix6::zeros();
        if let Ok(set) = prepare_unchecked(&self.cfg.setup, &self.kept) {
            let (rr, tt) = (r.pose.rotation.to_rotation_matrix().into_inner(), r.pose.translation.vector);
            for o in &set.obs {
                let (_, j) = residual_and_jacobian(&set, o, &rr, &tt);
                if let Some(si) = residual_covariance(&set, o, &rr, &tt, &self.cfg.noise).try_inverse() {
                    self.fisher += j.transpose() * si * j;
                }
            }
        }
        let precision = self.precision_at(&r.pose).ok_or(SolveError::Ours(OursError::Singular))?;
        self.progress.precision = Some(precision);
        Ok(Calibration { pose: r.pose, precision, ours: r, observations: self.kept.len(), t_ns })
    }

    fn precision_at(&self, pose: &Isometry3<f64>) -> Option<Precision> {
        let cov = self.fisher.try_inverse()?;
        let mean_p = self.kept.iter().map(|o| Vector3::from(o.tool_point_m)).sum::<Vector3<f64>>()
            / self.kept.len().max(1) as f64;
        let rp = pose.rotation * mean_p;
        let mut j = nalgebra::SMatrix::<f64, 3, 6>::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&nalgebra::Matrix3::identity());
        j.fixed_view_mut::<3, 3>(0, 3).copy_from(&-rp.cross_matrix());
        let tr = |a: usize| (cov[(a, a)] + cov[(a + 1, a + 1)] + cov[(a + 2, a + 2)]).max(0.0).sqrt();
        Some(Precision {
            fulcrum_m: (j * cov * j.transpose()).trace().max(0.0).sqrt(),
            origin_m: tr(0),
            rotation_rad: tr(3),
            covariance: cov,
        })
    }

    fn maybe_solve(&mut self, t_ns: u64) -> Option<Event> {
        if self.result.is_some() || self.kept.len() < self.cfg.min_observations {
            return None;
        }
        // Between solves the information accumulates at the last estimate.
        if let Some(pose) = self.estimate {
            self.progress.precision = self.precision_at(&pose);
        }
        let reached = self.progress.precision.is_some_and(|p| {
            p.fulcrum_m <= self.cfg.target_translation_m && p.rotation_rad <= self.cfg.target_rotation_rad
        });
        let due = self.estimate.is_none() || self.since_solve >= self.cfg.resolve_every || reached;
        if !due || self.kept.len() < self.retry_at {
            return None;
        }
        let Ok(cal) = self.solve(t_ns) else {
            // Degenerate or ambiguous so far: try again after a few more observations.
            self.retry_at = self.kept.len() + self.cfg.min_observations.div_ceil(2).max(1);
            return None;
        };
        let reached = cal.precision.fulcrum_m <= self.cfg.target_translation_m
            && cal.precision.rotation_rad <= self.cfg.target_rotation_rad;
        if reached {
            self.progress.solved = true;
            self.result = Some(cal.clone());
            return Some(Event::Solved(Box::new(cal)));
        }
        None
    }
}

/// The larger of `b`'s two end points' distances to the line through `a`'s (pixels); ∞ when
/// `a`'s points coincide.
fn line_distance_px(a: &[[f64; 2]; 2], b: &[[f64; 2]; 2]) -> f64 {
    let (dx, dy) = (a[1][0] - a[0][0], a[1][1] - a[0][1]);
    let n = dx.hypot(dy);
    if n.is_nan() || n <= 0.0 {
        return f64::INFINITY;
    }
    b.iter().map(|p| ((p[0] - a[0][0]) * dy - (p[1] - a[0][1]) * dx).abs() / n).fold(0.0, f64::max)
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
mod tests {
    use super::*;
    use estimator::calib::rcm_arms::psm_axis;
    use sim::calib::{CalibGeometry, CalibProtocol, NoiseUnits, generate_calibration};

    /// The paper's protocol (millimetre reading) as samples of an arm without a mechanical
    /// RCM whose fulcrum is the origin of `{t}`; the wrist 5 cm behind it on the axis.
    fn samples(seed: u64, n_t: usize) -> (Vec<Sample>, CollectorConfig, Isometry3<f64>) {
        samples_with(seed, n_t, NoiseUnits::Millimetre, 0.01)
    }

    /// The protocol's grid on the default geometry as samples, reading `units` at `sigma`.
    fn samples_with(
        seed: u64,
        n_t: usize,
        units: NoiseUnits,
        sigma: f64,
    ) -> (Vec<Sample>, CollectorConfig, Isometry3<f64>) {
        let p =
            CalibProtocol { geometry: CalibGeometry::default(), n_e: 3, n_t, sigma, units, pixel_sigma_px: 0.0, seed };
        let d = generate_calibration(&p).unwrap();
        let out = d
            .observations
            .iter()
            .enumerate()
            .map(|(i, o)| {
                let m = psm_axis(&o.psm_joints);
                Sample {
                    t_ns: i as u64 * 200_000_000,
                    frame_digest: i as u64,
                    eyes: [
                        EyeDetection {
                            found: 1,
                            ends_px: Some(o.line_px),
                            confidence: 0.9,
                            second_confidence: 0.0,
                            sharpness: Some(500.0),
                        },
                        EyeDetection::default(),
                    ],
                    ecm_joints: o.ecm_joints,
                    ecm_age_ns: 5_000_000,
                    tool: ToolSample {
                        fulcrum_valid: true,
                        fulcrum_m: [0.0; 3],
                        axis: m.into(),
                        wrist_m: (-m * 0.05).into(),
                        wrist_to_tip_m: 0.05 + o.psm_joints[2],
                        age_ns: 1_000_000,
                        fulcrum_age_ns: 1_000_000,
                    },
                }
            })
            .collect();
        (out, CollectorConfig::new(d.setup, d.noise.unwrap()), d.truth)
    }

    /// Sample `x` again as frame `i` of a later session, the tool arm moved by 2 cm on its cart.
    fn moved_2cm(x: &Sample, i: usize) -> Sample {
        let mut y = *x;
        y.frame_digest = 20_000 + i as u64;
        y.t_ns += 2_000_000_000_000;
        for v in [&mut y.tool.fulcrum_m, &mut y.tool.wrist_m] {
            v[0] += 0.02;
        }
        y
    }

    fn refused(c: &Collector, r: Refusal) -> usize {
        c.progress().refused.get(&r).copied().unwrap_or(0)
    }

    /// Pushes `bad` after one good sample and checks that exactly `why` was counted once
    /// and nothing was kept from it.
    fn refuses(why: Refusal, cfg_edit: impl Fn(&mut CollectorConfig), edit: impl Fn(&mut Sample)) {
        let (s, mut cfg, _) = samples(1, 2);
        cfg_edit(&mut cfg);
        let mut c = Collector::new(cfg);
        c.push(&s[0]);
        assert_eq!(c.progress().kept, 1);
        let mut bad = s[1];
        edit(&mut bad);
        c.push(&bad);
        assert_eq!(c.progress().kept, 1, "{why:?}: kept");
        assert_eq!(refused(&c, why), 1, "{why:?}: {:?}", c.progress().refused);
        assert_eq!(c.progress().refused.values().sum::<usize>(), 1, "{:?}", c.progress().refused);
    }

    #[test]
    fn each_refusal_reason_is_counted() {
        let none = |_: &mut CollectorConfig| {};
        refuses(Refusal::StaleEncoders, none, |s| s.ecm_age_ns = 500_000_000);
        refuses(Refusal::StaleEncoders, none, |s| s.tool.age_ns = 500_000_000);
        refuses(Refusal::StaleEncoders, none, |s| s.ecm_joints[0] = f64::NAN);
        refuses(Refusal::NoFulcrum, none, |s| s.tool.fulcrum_age_ns = u64::MAX);
        refuses(Refusal::InvalidFulcrum, none, |s| s.tool.fulcrum_valid = false);
        refuses(Refusal::FrozenCamera, none, |s| s.frame_digest = 0);
        refuses(Refusal::FrozenCamera, none, |s| s.t_ns = 0);
        refuses(Refusal::NoInstrument, none, |s| s.eyes[0] = EyeDetection::default());
        refuses(Refusal::Ambiguous, none, |s| {
            s.eyes[0].found = 2;
            s.eyes[0].second_confidence = 0.8;
        });
        refuses(Refusal::LowConfidence, none, |s| s.eyes[0].confidence = 0.1);
        refuses(Refusal::Blurred, |c| c.min_sharpness = 100.0, |s| s.eyes[0].sharpness = Some(10.0));
        // The same view again (a new frame, nothing moved): redundant.
        let (s, cfg, _) = samples(1, 2);
        let mut c = Collector::new(cfg);
        c.push(&s[0]);
        let mut again = s[0];
        again.frame_digest = 99;
        again.t_ns = s[0].t_ns + 1;
        c.push(&again);
        assert_eq!((c.progress().kept, refused(&c, Refusal::Redundant)), (1, 1));
        // A second, weak shaft is not a second instrument.
        let mut weak = s[1];
        weak.eyes[0].found = 2;
        weak.eyes[0].second_confidence = 0.1;
        c.push(&weak);
        assert_eq!(c.progress().kept, 2);
    }

    #[test]
    fn solves_when_the_predicted_precision_reaches_the_target_and_not_before() {
        let (s, mut cfg, truth) = samples(3, 3);
        cfg.target_translation_m = 2e-3;
        cfg.target_rotation_rad = 0.5f64.to_radians();
        let mut c = Collector::new(cfg);
        let mut solved = None;
        for x in &s {
            if let Event::Solved(cal) = c.push(x) {
                solved = Some(cal);
                break;
            }
        }
        let cal = solved.expect("target reached");
        assert!(cal.precision.fulcrum_m <= 2e-3 && cal.precision.rotation_rad <= 0.5f64.to_radians());
        assert!(cal.observations >= 40 && cal.observations < s.len());
        let e = estimator::calib::pose_errors(&cal.pose, &truth);
        assert!(e.translation_m < 3.0 * cal.precision.origin_m.max(1e-4), "{e:?} vs {:?}", cal.precision);
        assert!(e.rotation_rad < 3.0 * cal.precision.rotation_rad, "{e:?} vs {:?}", cal.precision);
        // An unreachable target: never published, but the precision is reported.
        let (s, mut cfg, _) = samples(3, 3);
        cfg.target_translation_m = 1e-7;
        let mut c = Collector::new(cfg);
        assert!(s.iter().all(|x| !matches!(c.push(x), Event::Solved(_))));
        assert!(c.result().is_none() && c.progress().precision.is_some() && c.progress().solves >= 1);
    }

    #[test]
    fn a_refused_selection_stage_is_no_calibration() {
        // The metre reading at σ = 0.03 (30 mm per frame), seed 4: the selection-aware stage
        // runs away from the guarded fit (Hausman statistic 68.9 against 27.9) and is refused
        // (as `calibrate`'s selection-refused case), with the noise model's scale estimated as
        // the collector does. (Seed 1 was this case until session 31; the search from the
        // cover of rotations every time answers it 37 mm / 3.4° off, its stage taken.)
        let (s, mut cfg, _) = samples_with(4, 3, NoiseUnits::Metre, 0.03);
        cfg.target_translation_m = 1e-7;
        let mut c = Collector::new(cfg);
        for x in &s {
            assert!(!matches!(c.push(x), Event::Solved(_)));
        }
        match c.solve_now(0) {
            Some(Err(SolveError::SelectionRefused(_))) => {}
            other => panic!("expected the refused stage: {:?}", other.map(|r| r.map(|c| c.ours.selection))),
        }
        assert!(c.result().is_none());
    }

    #[test]
    fn a_full_collection_refuses_new_lines_and_still_watches_for_drift() {
        // An unreachable target: the collection would grow with every new view; it stops at the cap.
        let (s, mut cfg, _) = samples(3, 3);
        cfg.target_translation_m = 1e-7;
        cfg.max_observations = 45;
        let mut c = Collector::new(cfg);
        for x in &s {
            c.push(x);
        }
        assert_eq!(c.progress().kept, 45, "capped");
        assert!(refused(&c, Refusal::Full) > 0, "{:?}", c.progress().refused);
        // A reachable target, the cap at the count it was reached with: full from the result on.
        cfg.target_translation_m = 2e-3;
        cfg.target_rotation_rad = 0.5f64.to_radians();
        cfg.drift_window = 10;
        cfg.max_observations = usize::MAX;
        let mut c = Collector::new(cfg);
        let at = s.iter().position(|x| matches!(c.push(x), Event::Solved(_))).expect("solved");
        cfg.max_observations = c.progress().kept;
        let mut c = Collector::new(cfg);
        assert_eq!(s.iter().position(|x| matches!(c.push(x), Event::Solved(_))), Some(at));
        // The tool arm moved by 2 cm on its cart: nothing can be kept, the drift is still seen.
        let mut drift = false;
        for (i, x) in s.iter().enumerate().take(60) {
            let y = moved_2cm(x, i);
            if matches!(c.push(&y), Event::Drift { .. }) {
                drift = true;
                break;
            }
        }
        assert!(drift, "drift flagged while full: {:?}", c.progress().refused);
        assert!(refused(&c, Refusal::Full) > 0, "{:?}", c.progress().refused);
        assert!(c.result().is_none(), "the result is dropped at drift");
    }

    #[test]
    fn too_little_data_publishes_nothing() {
        let (s, cfg, _) = samples(1, 3);
        let mut c = Collector::new(cfg);
        for x in s.iter().take(20) {
            assert!(matches!(c.push(x), Event::None));
        }
        assert!(c.result().is_none() && c.solve_now(0).is_none());
    }

    #[test]
    fn sustained_misfit_flags_drift_and_restarts() {
        let (s, mut cfg, _) = samples(3, 3);
        cfg.target_translation_m = 2e-3;
        cfg.target_rotation_rad = 0.5f64.to_radians();
        cfg.drift_window = 10;
        let mut c = Collector::new(cfg);
        let mut at = None;
        for (i, x) in s.iter().enumerate() {
            if let Event::Solved(_) = c.push(x) {
                at = Some(i);
                break;
            }
        }
        let at = at.expect("solved");
        // The same data again (fresh frames): consistent, no drift.
        let mut drift = false;
        for (i, x) in s.iter().enumerate().skip(at + 1).take(30) {
            let mut y = *x;
            y.frame_digest = 10_000 + i as u64;
            y.t_ns += 1_000_000_000_000;
            drift |= matches!(c.push(&y), Event::Drift { .. });
        }
        assert!(!drift && c.result().is_some());
        // The tool arm moved by 2 cm on its cart: its lines no longer fit.
        let mut flagged = None;
        for (i, x) in s.iter().enumerate().take(60) {
            let y = moved_2cm(x, i);
            if let Event::Drift { misfit_fraction } = c.push(&y) {
                flagged = Some(misfit_fraction);
                break;
            }
        }
        assert!(flagged.is_some_and(|f| f > 0.5), "{flagged:?}");
        assert!(c.result().is_none() && c.progress().kept == 0 && c.progress().drifts == 1);
    }
}
