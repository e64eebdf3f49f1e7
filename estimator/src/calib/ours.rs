//! comanip's pipeline: joint nonlinear refinement of `T_e_t` on the image distance (pixels)
//! between the projected tool axis and the observed line, robust (Huber, by iteratively
//! reweighted Levenberg-Marquardt), optionally whitened by the kinematic noise model, with a
//! covariance, the near-180° ambiguity detected and resolved, and named degenerate cases.
//!
//! Residuals: for observation `i` and each of its two line points `u_ij` (ideal pixels),
//! `r_ij = dist(u_ij, l_i(T))`, where `l_i = K⁻ᵀ (p_c × d_c)` is the image of the tool axis
//! (through robot 2's RCM `t`, direction `R m_i`) seen by camera `T_e_c(θ1,i)`. With a noise
//! model, each pair `r_i` is whitened by `Σ_i^{-1/2}`,
//! `Σ_i = σ_px² I + G_i diag(σ²) G_iᵀ`, `G_i = ∂r_i/∂δ_i` for the 18 frame perturbations
//! of the simulation protocol (ECM end effector, PSM frames 2 and 3): the maximum-likelihood
//! estimator of the linearised model, whose covariance the Cramér-Rao bound ([`super::crb`])
//! bounds.
//!
//! With a noise model, the objective also has the shaft-position likelihood
//! ([`super::shaft_position`]: each observed line point on the physical shaft and in front of
//! the camera, and the tip where a shaft end was seen), and each start's translation comes
//! from the observed shaft ends when the dataset has them
//! ([`super::shaft_position::translation_from_shaft_ends`]); [`OursConfig::shaft_position`]
//! turns both off.
//!
//! Stages with a noise model: the robust fit from the linear starts and their mirrors; the
//! border guard (refits on observations whose tip is predicted well inside the image); the
//! selection-aware stage ([`super::selection`]: the likelihood of the kept lines, on all
//! observations), refused when it runs away ([`OursResult::selection_refused`]); then (on by
//! default, [`SelectionConfig::moving_covariance_step`]) a last step adding how the lines'
//! covariances move with the pose ([`super::selection::moving_covariance_step`]), taken where
//! that information is significantly worth it ([`SelectionConfig::moving_step_worth_it`]).
//!
//! Parameters: `t` (metres, `{e}`) and a left rotation increment `δφ` (radians, `{e}`),
//! `R ← exp(δφ^) R`. The covariance is reported in that order `(tx, ty, tz, φx, φy, φz)`.

use std::vec::Vec;

use nalgebra::{
    Isometry3, Matrix2, Matrix3, Matrix6, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3, Vector6,
};

use super::KinematicNoise;
use super::paper::{
    PaperError, eq10_symmetric, kronecker_rotation, linear_translation, refine_quaternion, refine_quaternion_sym,
    translation_given_rotation, wxyz,
};
use super::prepare::{PENCIL_TOLERANCE, PrepareError, Prepared, PreparedSet, SAME_ORIENTATION_RAD, prepare};
use super::residual::{damped_search, residual, residual_and_jacobian, residual_covariance};
use super::selection::{
    SelectionConfig, SelectionError, kept_given_line_ln_at, moving_covariance_step, noise_at, refine_selected_with,
    tip_well_inside,
};
use super::shaft_position::{
    ShaftModel, TIP_DEPTH_RATIO, axis_seen_at, model_and_residuals_at, model_and_residuals_into,
    model_and_residuals_noise_at, residuals_at_with, stage_terms, translation_from_shaft_ends,
};
use super::{Observation, Setup, par};

/// Two refined candidates whose rotations differ by more than this (radians, 10°) are
/// different solutions for the ambiguity check.
pub const DISTINCT_SOLUTION_RAD: f64 = 0.1745;

/// The default of [`OursConfig::min_log_likelihood_ratio`]: `ln 1000`. The runner-up is
/// refused as an explanation of the data only when it is at least 1000 times less likely than
/// the best candidate (its posterior probability under equal priors below 0.1 %).
pub const DEFAULT_MIN_LOG_LIKELIHOOD_RATIO: f64 = 6.907_755_278_982_137;

/// A whitened residual norm that is not finite, or above this many Huber thresholds, counts as
/// this many thresholds in a candidate's negative log-likelihood: every candidate's cost, and
/// so the reported log-likelihood ratio, is finite by construction.
pub const RESIDUAL_CAP_THRESHOLDS: f64 = 1e6;

/// A border-guarded refit that lands farther than this from the previous fit, in standard
/// deviations of the previous fit's covariance (Mahalanobis), ends the guard: the guard
/// removes a bias, it does not find another solution.
pub const GUARD_MAX_SHIFT_SIGMAS: f64 = 20.0;

/// A candidate is an explanation of the data only when it puts at most this share of the
/// observations where no shaft can be ([`shaft_explanation`]: behind the camera, or off the
/// physical shaft by more than [`SHAFT_MARGIN`]): a line's image cannot tell its side of the
/// camera nor where along it the shaft lies, so a mirror of the solution, or a solution pushed
/// to a far distance, fits the lines as well as the true pose while placing the detected
/// shafts where no instrument is. Fixed in advance: the true pose of a simulated dataset
/// leaves out 0-2 % at σ ≤ 0.01 in metres (noise pushes tips across the camera plane), a
/// mirror or far pose 15-100 %.
pub const MAX_UNEXPLAINED_SHARE: f64 = 0.1;

/// How far beyond the physical shaft (the segment from robot 2's RCM, or the line's known
/// point, to the tool tip) an observed line point may meet the tool axis, in insertions,
/// before the observation counts as not explained ([`shaft_explanation`]). Generous: under
/// large kinematic noise (10 mm per frame) a fit slides along the axis by centimetres, and
/// 2-4 % of a true pose's observations meet it more than half an insertion beyond the shaft;
/// a pose pushed to a far distance puts them metres to kilometres off.
pub const SHAFT_MARGIN: f64 = 2.0;

/// Options of our pipeline.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OursConfig {
    /// Kinematic noise model used to whiten the residuals; `None`: plain pixel residuals.
    pub noise: Option<KinematicNoise>,
    /// Huber threshold in robust standard deviations of the (whitened) residual norm.
    pub huber_k: f64,
    /// Levenberg-Marquardt iterations per pass (two passes with a noise model).
    pub max_iterations: usize,
    /// Refuse the result ([`OursError::Ambiguous`]) when the runner-up candidate (a distinct
    /// solution, typically the mirror ≈180° about the line of sight) has a negative
    /// log-likelihood less than this above the best one (natural log, dimensionless; see
    /// [`DEFAULT_MIN_LOG_LIKELIHOOD_RATIO`]). Only candidates that explain where the shafts
    /// were seen ([`explains_shafts`]) take part: one that does not is no rival.
    pub min_log_likelihood_ratio: f64,
    /// Border guard (with a noise model only): keep observations whose predicted tool tip is
    /// at least this many standard deviations inside the image; 0 disables it.
    pub border_guard_sigmas: f64,
    /// An extra starting rotation `[w, x, y, z]` (robustness sweep); the linear start and
    /// both mirrors are always tried as well, and the lowest robust cost wins.
    pub initial_quaternion: Option<[f64; 4]>,
    /// The selection-aware final stage ([`super::selection`]; with a noise model only);
    /// `None` stops after the border-guarded robust fit.
    pub selection: Option<SelectionConfig>,
    /// With a noise model: add the shaft-position likelihood ([`super::shaft_position`]:
    /// each observed line point on the physical shaft, between robot 2's RCM and the tool
    /// tip, in front of the camera) to the objective. `false`: the lines alone (for
    /// comparison; the pose can then put the shafts where no instrument is and be refused,
    /// [`OursError::ShaftsNotExplained`]). Off whatever this says when the noise model has no
    /// kinematic terms ([`KinematicNoise::has_kinematic_terms`]): without the arms' noise the
    /// terms would pin the tips where the arm models say.
    pub shaft_position: bool,
    /// With a noise model: take it as known up to a common scale, estimated from the data. The
    /// pipeline solves once, then again with every standard deviation multiplied by the first
    /// fit's robust scale ([`OursResult::scale`], bounded to
    /// [`NOISE_SCALE_BOUNDS`]), and returns the second fit
    /// ([`OursResult::noise_scale`]). The line fit does not depend on the scale, but the
    /// shaft-position terms and the selection-aware stage do: a noise model 20× too large
    /// makes the stage correct a selection bias 20× larger than the data have (a live session
    /// of the twin: the stage ran away and was refused at every solve). `false` (the default):
    /// the noise model is taken as stated.
    pub estimate_noise_scale: bool,
    /// With a noise model: each candidate that, once refined, does not explain where the
    /// shafts were seen ([`explains_shafts`]) descends the likelihood the candidates are
    /// judged by ([`Candidate::nll`]: each observation whitened by its own covariance at the
    /// candidate's pose; the private `descend_likelihood`) before they are compared. The
    /// refinement minimises a surrogate (whitening held for a pass, Huber at a robust scale
    /// re-estimated every iteration), which can walk the true basin's candidate out of the
    /// physical region (tuning geometry 9017, metres, σ = 0.02: the mirror was then returned
    /// with exit 0). `false`: candidates are compared where the refinement left them.
    pub likelihood_descent: bool,
    /// With [`Self::likelihood_descent`] and the shaft-position terms: every distinct
    /// candidate that explains the shafts descends the likelihood too, and the candidates are
    /// compared (choice, runner-up, ambiguity) at their descended likelihoods, so a basin is
    /// judged by the best point found in it, not by where the surrogate refinement stopped.
    /// When the most likely basin is that of the candidate the refinement alone would return,
    /// that candidate's pose is returned unchanged (the robust refinement's estimate); only
    /// where the descent finds another basin more likely does the answer move. On the tuning
    /// geometries (metres, σ = 0.02) the true basin's refined candidates were 1 800-3 000
    /// nats less likely than the truth and than their own descended poses, and a mirror won
    /// (docs/calibration.md, session 25). `false`: only the unexplained candidates descend.
    pub descend_every_basin: bool,
    /// The search on a subsample (coarse to fine): when there are at least twice this many
    /// observations, the candidates (starts, 180° turns, descents, the choice of basin and its
    /// runner-up) are found on this many of them, spread over the dataset by a golden-ratio
    /// sequence (no aliasing with a grid of poses); the chosen basin and the runner-up are
    /// then refined on all observations and judged there (likelihood ratio, ambiguity,
    /// whether they explain the shafts). Anything the subsample's search cannot settle (an
    /// error other than [`OursError::Ambiguous`], a basin that fails on all observations) is
    /// searched again on all observations. `None`: always search on all observations.
    pub search_observations: Option<usize>,
    /// With a noise model, the search from a cover of rotation space: the 24 rotations of the
    /// cube group applied to the linear start (every rotation is within 62.8° of one), each a
    /// start of its own with its own translation, in place of the other minima of Eq. 10
    /// beside the linear start and its 180° turns (the lines-only start is still found from
    /// the usual starts). `Some(0.0)` (or below), the default: the cover is the search, every
    /// time. `Some(s)` with `s > 0` (e.g. [`POOR_FIT_SCALE`], the default until session 31):
    /// the usual starts are searched first, and the cover only when that answer fits the data
    /// more than `s` times worse than the noise model predicts (its robust scale
    /// [`OursResult::scale`], dimensionless), its outcome, answer or refusal, then being the
    /// pipeline's. `None`: never (the usual starts only).
    ///
    /// Why every time: the usual starts can all miss the true basin, and the mirror they then
    /// find can fit as well as the noise model predicts, which no trigger on the fit sees. On
    /// the tuning geometries (metres, σ = 0.02) the trigger returned such a mirror with exit 0
    /// in 1 of 1 200 trials (9060-9099, none in 4 000 more), the cover every time none in
    /// 4 200, and it answers more trials in every pool (e.g. 479 against 453 of 1 000 on
    /// 9140-9189). On a fresh held-out
    /// set (geometries 7100-7119, session 31) both returned no mirror, no millimetre refusal,
    /// and the cover answered more metre trials at every σ. It costs about twice the solve
    /// time (docs/calibration.md, sessions 30 and 31).
    pub cover_search_scale: Option<f64>,
}

/// The bounds of the noise scale [`OursConfig::estimate_noise_scale`] applies
/// (dimensionless): a robust scale outside them says the noise model is not a scale away
/// from the data's, and the pipeline goes no further than them.
pub const NOISE_SCALE_BOUNDS: [f64; 2] = [0.01, 100.0];

impl Default for OursConfig {
    fn default() -> Self {
        Self {
            noise: None,
            huber_k: 3.0,
            max_iterations: 50,
            min_log_likelihood_ratio: DEFAULT_MIN_LOG_LIKELIHOOD_RATIO,
            border_guard_sigmas: 2.0,
            initial_quaternion: None,
            selection: Some(SelectionConfig::default()),
            shaft_position: true,
            estimate_noise_scale: false,
            likelihood_descent: true,
            descend_every_basin: true,
            search_observations: Some(DEFAULT_SEARCH_OBSERVATIONS),
            cover_search_scale: Some(0.0),
        }
    }
}

/// [`OursConfig::search_observations`]'s default.
pub const DEFAULT_SEARCH_OBSERVATIONS: usize = 240;

/// A poor-fit trigger for [`OursConfig::cover_search_scale`] (dimensionless; its default
/// until session 31): a fit 1.5 times worse than the noise model predicts. On the tuning
/// geometries 9020-9059 at σ = 0.02 in metres, 21 of 1 200 trials were searched again, the
/// five mirrors among them; answers near the truth reach 1.5 only where the noise model's
/// linearisation is poor (2 % of them).
pub const POOR_FIT_SCALE: f64 = 1.5;

/// Why our pipeline failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OursError {
    /// Input or counting check failed (see [`PrepareError`]).
    #[error(transparent)]
    Prepare(#[from] PrepareError),
    /// Degenerate: robot 1's views are collinear with the line from robot 2's RCM to the
    /// camera (translation unobservable).
    #[error(
        "degenerate data: robot 1's views are collinear with the line from robot 2's RCM to the camera (eigenvalue ratio {ratio:.1e}); move the endoscope sideways"
    )]
    ViewsCollinear {
        /// Smallest over largest eigenvalue of Eq. 5's normal matrix.
        ratio: f64,
    },
    /// Degenerate: the observed lines form one pencil (see
    /// [`PaperError::LinesFormOnePencil`]).
    #[error(
        "degenerate data: the observed lines form a single pencil (identical, parallel or concurrent; eigenvalue ratio of the plane normals {ratio:.1e}); check the line detector"
    )]
    LinesFormOnePencil {
        /// Smallest over largest eigenvalue of `Σ n_c n_cᵀ` (camera frame).
        ratio: f64,
    },
    /// Degenerate: no initial rotation can be formed (tool orientations coplanar or each
    /// seen from a single view).
    #[error("degenerate data: the tool rotation is unobservable from these orientations ({detail})")]
    RotationUnobservable {
        /// What failed.
        detail: &'static str,
    },
    /// The noise model has a negative, non-finite or all-zero standard deviation.
    #[error("invalid noise model: standard deviations must be finite, ≥ 0, not all zero")]
    NoiseModel,
    /// The data cannot tell the best candidate from the runner-up (typically the mirror
    /// ≈180° about the line of sight): their negative log-likelihoods differ by less than
    /// [`OursConfig::min_log_likelihood_ratio`].
    #[error(
        "ambiguous solution: the runner-up ({angle_deg:.1}° from the best, {distance_mm:.1} mm away) is only exp({log_likelihood_ratio:.2}) times less likely than the best (need exp({min:.2})); widen the endoscope's and the tool's motions"
    )]
    Ambiguous {
        /// The best candidate.
        best: Box<Candidate>,
        /// The runner-up.
        runner_up: Box<Candidate>,
        /// `runner_up.nll − best.nll` (natural log, ≥ 0, finite).
        log_likelihood_ratio: f64,
        /// The configured minimum.
        min: f64,
        /// Rotation between the two, degrees.
        angle_deg: f64,
        /// Translation between the two, millimetres.
        distance_mm: f64,
    },
    /// Every candidate ended with a non-finite pose.
    #[error("the refinement diverged: no candidate ended with a finite pose")]
    NoConvergence,
    /// No candidate puts the detected shafts where an instrument can be: the most likely
    /// candidate puts `behind` observations behind the camera and `off_shaft` off the
    /// physical shaft, of `observations` (more than [`MAX_UNEXPLAINED_SHARE`]); typically a
    /// mirror solution or one pushed to a far distance, when the kinematic noise swamps the
    /// lines' parallax.
    #[error(
        "no solution explains where the shafts were seen: the most likely candidate puts {behind} of {observations} observed shafts behind the camera and {off_shaft} off the instrument's shaft (at most {max_share:.0}% allowed); the kinematic noise is too large for these motions, or the data are wrong"
    )]
    ShaftsNotExplained {
        /// Observations put behind the camera by the most likely candidate.
        behind: usize,
        /// Observations put off the physical shaft by it.
        off_shaft: usize,
        /// Observations.
        observations: usize,
        /// [`MAX_UNEXPLAINED_SHARE`] in percent.
        max_share: f64,
        /// The most likely candidate, `T_e_t` (metres).
        pose: Box<Isometry3<f64>>,
    },
    /// The normal matrix at the solution is singular (no covariance).
    #[error("the normal matrix at the solution is singular: the pose is not locally observable")]
    Singular,
}

/// Pixel residual statistics of a pose over all observations (both line points each).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ResidualStats {
    /// Observations used.
    pub count: usize,
    /// Root mean square point-to-line distance, pixels.
    pub rms_px: f64,
    /// Median point-to-line distance, pixels.
    pub median_px: f64,
    /// Largest point-to-line distance, pixels.
    pub max_px: f64,
    /// Observations inside the Huber threshold (full weight); `count` for the paper pipeline.
    pub inliers: usize,
}

/// Result of our pipeline.
#[derive(Clone, Copy, Debug)]
pub struct OursResult {
    /// `T_e_t`, metres.
    pub pose: Isometry3<f64>,
    /// Covariance of `(t m, δφ rad)` (left increment in `{e}`): `σ̂² (JᵀWJ)⁻¹`.
    pub covariance: Matrix6<f64>,
    /// Pixel residuals at the solution.
    pub residuals: ResidualStats,
    /// Robust scale of the (whitened) residual norms at the solution (≈1 when the noise
    /// model is right; pixels without a noise model).
    pub scale: f64,
    /// The runner-up: the most likely candidate that is a distinct solution (more than
    /// [`DISTINCT_SOLUTION_RAD`] away in rotation) and explains where the shafts were seen
    /// ([`explains_shafts`]), typically the mirror; when every start
    /// converged to the best, the best's mirror (180° about the line of sight to robot 2's
    /// RCM), refined if that converges elsewhere.
    pub alternative: Isometry3<f64>,
    /// Negative log-likelihood of the runner-up minus that of the result (natural log, ≥ 0,
    /// finite by construction; large = unambiguous). See [`Candidate::nll`].
    pub log_likelihood_ratio: f64,
    /// Levenberg-Marquardt iterations, all candidates.
    pub iterations: usize,
    /// Observations kept by the border guard (all of them when the guard is off or did not
    /// drop any).
    pub guard_kept: usize,
    /// The pose (`T_e_t`, metres) at which the border guard drew the observations it kept
    /// (its last round's start; `None` when the guard kept all of them).
    pub guard_from: Option<Isometry3<f64>>,
    /// The selection-aware stage's bookkeeping, when it ran and was applied.
    pub selection: Option<SelectionSummary>,
    /// Why the selection-aware stage was not applied (the pose is then the guarded fit).
    pub selection_refused: Option<SelectionError>,
    /// The factor the noise model's standard deviations were multiplied by
    /// ([`OursConfig::estimate_noise_scale`], dimensionless); `None` when the model was taken
    /// as stated.
    pub noise_scale: Option<f64>,
    /// How many observations the candidates were searched on
    /// ([`OursConfig::search_observations`]): all of them, or the subsample's size (the
    /// result itself is then refined and judged on all of them).
    pub searched_on: usize,
    /// This answer comes from a search from a cover of rotation space
    /// ([`OursConfig::cover_search_scale`]): with the cover every time (the default), every
    /// solve with a noise model and a linear start; with a poor-fit trigger, when the first
    /// search's answer fitted the data worse than the noise model predicts.
    pub cover_searched: bool,
}

/// One candidate solution and its negative log-likelihood.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Candidate {
    /// `T_e_t`, metres.
    pub pose: Isometry3<f64>,
    /// Negative log-likelihood of all observations (natural log, up to a constant common to
    /// all candidates): `Σ_i ρ(|Σ_i^{-1/2} r_i|) / ŝ² + ½ ln det Σ_i − ln P(kept_i | r_i)`, with
    /// `ρ` Huber's function at `huber_k · ŝ`, `ŝ` the smallest robust scale over the
    /// candidates, `Σ_i` the residual covariance at this candidate (identity pixels² without a
    /// noise model), and `P(kept_i | r_i)` the probability, under the detector's rule, that the
    /// line was recorded given where this candidate puts the tool tip (with a noise model only;
    /// [`super::selection::kept_given_line_ln`]).
    pub nll: f64,
}

/// What the selection-aware stage did with the observations.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SelectionSummary {
    /// Fitted with their selection.
    pub selected: usize,
    /// Fitted as plain lines (tip too close to the camera for the first-order model, but well
    /// inside the image).
    pub plain: usize,
    /// Left out (tip too close to the camera near the border, behind the camera, or a gross
    /// outlier of the first-order model).
    pub left_out: usize,
    /// How far the stage moved from the guarded fit, in its standard deviations.
    pub shift_sigmas: f64,
    /// The move failed the Hausman test, and the stage was taken because its pose is more
    /// than 1000 times more likely than the guarded fit's on all observations
    /// ([`apply_selection_stage`]).
    #[serde(default)]
    pub accepted_on_likelihood: bool,
    /// The last step on the likelihood with moving covariances
    /// ([`super::selection::moving_covariance_step`]): its information gain, that gain's
    /// jackknife standard error (both dimensionless) and whether it was taken; `None` when not
    /// tried or not computable. The standard error is `None` when it was not computed (it
    /// cannot change the decision: the gain is below
    /// [`SelectionConfig::moving_step_min_gain`], or [`SelectionConfig::moving_step_gain_z`] is
    /// not positive; [`SelectionConfig::moving_step_needs_sd`]) or is not finite (a
    /// leave-one-out gain could not be evaluated; the step is then taken only with
    /// `moving_step_min_gain = -∞`): always finite
    /// when present, so the summary survives a JSON round trip (serde_json writes a non-finite
    /// number as `null`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub moving_step: Option<(f64, Option<f64>, bool)>,
    /// The stage's move was judged by the measured test
    /// ([`SelectionConfig::influence_move_test`] with the guarded fit's influences valid:
    /// [`super::hausman::influence_move_test`]); `false`: the efficiency-based test.
    #[serde(default)]
    pub move_test_measured: bool,
    /// The move test's statistic and its refusal limit (both dimensionless: the statistic is
    /// χ²-distributed with [`super::hausman::MoveTest::dof`] degrees of freedom when the two
    /// fits are consistent; the limit is that distribution's quantile at one minus
    /// [`SelectionConfig::false_refusal_probability`]): how near the stage came to being
    /// refused. `None` when the test could not be computed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub move_statistic: Option<(f64, f64)>,
}

/// Inverse Cholesky factor `L⁻¹` of a 2×2 SPD matrix (identity if not SPD).
fn whitener(s: &Matrix2<f64>) -> Matrix2<f64> {
    match s.cholesky() {
        Some(c) => c.l().try_inverse().unwrap_or_else(Matrix2::identity),
        None => Matrix2::identity(),
    }
}

fn huber(e: f64, c: f64) -> f64 {
    if e <= c { 0.5 * e * e } else { c * (e - 0.5 * c) }
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mid = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    *m
}

/// Median of the norm of a 2-D standard normal vector, `√(2 ln 2)`.
const CHI2_MEDIAN: f64 = 1.177_410_022_515_474_6;

#[derive(Clone)]
struct Refined {
    r: Matrix3<f64>,
    t: Vector3<f64>,
    whiten: Vec<Matrix2<f64>>,
    scale: f64,
    iterations: usize,
    /// Stopped because it came within [`MERGE_SIGMAS`] of this already refined candidate
    /// (index into the caller's `done` list), whose pose it takes.
    merged: Option<usize>,
}

impl Refined {
    /// This candidate with `other`'s pose and robust scale (a merged candidate follows its
    /// target).
    fn at_pose_of(&self, other: &Refined) -> Refined {
        Refined { r: other.r, t: other.t, scale: other.scale, ..self.clone() }
    }
}

/// A candidate whose refinement comes within this many standard deviations (Mahalanobis, the
/// current Gauss-Newton metric over the robust scale²) of an already refined candidate of the
/// same objective (same whitening) is in that candidate's basin and converges to it: it is
/// merged (stopped and given that candidate's pose) instead of refined to the end.
const MERGE_SIGMAS: f64 = 0.1;

/// The robust scale of whitened residual norms (their median over that of a 2-D standard
/// normal's norm, at least `1e-12`); `scratch` is overwritten.
fn robust_scale_with(norms: &[f64], scratch: &mut Vec<f64>) -> f64 {
    scratch.clear();
    scratch.extend_from_slice(norms);
    (median(scratch) / CHI2_MEDIAN).max(1e-12)
}

/// The upper triangle of `jᵀ j` (column by column, `a ≤ b`) into `out`: each element the same
/// arithmetic as the full product's.
fn gram_upper(out: &mut [f64; 21], j: &super::residual::Jac6) {
    let mut k = 0;
    for b in 0..6 {
        let (j0b, j1b) = (j[(0, b)], j[(1, b)]);
        for a in 0..=b {
            out[k] = j[(0, a)] * j0b + j[(1, a)] * j1b;
            k += 1;
        }
    }
}

/// `h += jᵀ j · wgt` on the upper triangle only, from [`gram_upper`]'s `jtj` (each element the
/// same arithmetic as the full product, so [`mirror_upper`] afterwards gives the full
/// product's sum bit for bit).
fn add_weighted_upper(h: &mut Matrix6<f64>, jtj: &[f64; 21], wgt: f64) {
    let mut k = 0;
    for b in 0..6 {
        for a in 0..=b {
            h[(a, b)] += jtj[k] * wgt;
            k += 1;
        }
    }
}

/// `h += j jᵀ · wgt` on the upper triangle only (the same arithmetic per element as the full
/// outer product; [`mirror_upper`] afterwards).
fn add_weighted_outer(h: &mut Matrix6<f64>, j: &Vector6<f64>, wgt: f64) {
    for b in 0..6 {
        for a in 0..=b {
            h[(a, b)] += j[a] * j[b] * wgt;
        }
    }
}

/// Copies the upper triangle of `h` onto its lower triangle.
fn mirror_upper(h: &mut Matrix6<f64>) {
    for b in 0..6 {
        for a in 0..b {
            h[(b, a)] = h[(a, b)];
        }
    }
}

/// Robust Levenberg-Marquardt from `(r0, t0)` with fixed whitening matrices.
///
/// `done`: converged candidates of the same objective (same `whiten`); when the refinement
/// comes within [`MERGE_SIGMAS`] of one, it stops and returns that one's pose, `merged` set.
/// With a noise model, the shaft-position terms ([`super::shaft_position`]) are added; their
/// noise models are rebuilt at every iteration's pose (held within its line search):
/// building them once per pass, as the whitening is, left more tuning trials unexplained.
fn refine(
    set: &PreparedSet,
    cfg: &OursConfig,
    whiten: Vec<Matrix2<f64>>,
    r0: Matrix3<f64>,
    t0: Vector3<f64>,
    done: &[(Matrix3<f64>, Vector3<f64>)],
) -> Refined {
    let mut merged = None;
    // The shaft-position models, rebuilt at each iteration's pose and held fixed within its
    // line search (the tip's noise moves with the pose far more than the lines' does).
    let shaft_noise = cfg.noise.as_ref().filter(|_| cfg.shaft_position);
    // Each observation's line weight (Huber) at the iteration's pose, for its shaft terms.
    let mut line_weights: Vec<f64> = Vec::with_capacity(if shaft_noise.is_some() { set.obs.len() } else { 0 });
    let mut r = r0;
    let mut t = t0;
    let mut iterations = 0;
    let mut scale = 1.0;
    {
        let mut lambda = 1e-4;
        // Buffers reused by every iteration.
        let mut norms = Vec::with_capacity(set.obs.len());
        let mut scratch = Vec::with_capacity(set.obs.len());
        // Each observation's whitened line residuals and Jacobian and, with the shaft terms,
        // its shaft model, residuals and gradients at the iteration's pose (computed per
        // observation, [`par`], and summed in order below).
        let mut at_pose: Vec<ObsTerms> = (0..set.obs.len()).map(|_| ObsTerms::default()).collect();
        // The line residuals at a trial pose, and each observation's shaft terms' cost there.
        let mut trial = Vec::with_capacity(set.obs.len());
        let mut trial_shaft: Vec<f64> = Vec::with_capacity(line_weights.capacity());
        let idx: Vec<usize> = (0..set.obs.len()).collect();
        for _ in 0..cfg.max_iterations {
            iterations += 1;
            let mut h = Matrix6::zeros();
            let mut g = Vector6::zeros();
            par::for_each_mut(&mut at_pose, |i, x| {
                let (o, w) = (&set.obs[i], &whiten[i]);
                let (res, jac) = residual_and_jacobian(set, o, &r, &t);
                (x.e, x.j) = (w * res, w * jac);
                x.norm = x.e.norm();
                // The weight-free parts of its Gauss-Newton terms (summed below, weighted).
                x.jte = x.j.transpose() * x.e;
                gram_upper(&mut x.jtj, &x.j);
                if let Some(noise) = shaft_noise {
                    let slots = (&mut x.model, &mut x.es, &mut x.gs);
                    model_and_residuals_into(set, o, &r, &t, noise, true, Some((&res, &jac)), slots);
                }
            });
            norms.clear();
            norms.extend(at_pose.iter().map(|x| x.norm));
            scale = robust_scale_with(&norms, &mut scratch);
            let c = cfg.huber_k * scale;
            let mut cost = 0.0;
            for x in &at_pose {
                let n = &x.norm;
                let wgt = if *n <= c { 1.0 } else { c / n };
                add_weighted_upper(&mut h, &x.jtj, wgt);
                g += x.jte * wgt;
                cost += huber(*n, c);
            }
            // The shaft-position terms (with a noise model): flat while every observed line
            // point is on the physical shaft, in front of the camera.
            if shaft_noise.is_some() {
                line_weights.clear();
                line_weights.extend(norms.iter().map(|n| if *n <= c { 1.0 } else { c / n }));
                for (x, lw) in at_pose.iter().zip(&line_weights) {
                    for (e, j) in x.es.iter().zip(&x.gs) {
                        if *e == 0.0 {
                            continue;
                        }
                        // In the line residuals' units (robust scale), Huber-weighted alike,
                        // and by its line's weight: a wrong line's end points say nothing.
                        let (e, j) = (e * scale, j * scale);
                        let n = e.abs();
                        let wgt = lw * if n <= c { 1.0 } else { c / n };
                        add_weighted_outer(&mut h, &j, wgt);
                        g += j * e * wgt;
                        cost += lw * huber(n, c);
                    }
                }
            }
            // The lower triangle, once (each element the same sum as the full products').
            mirror_upper(&mut h);
            let mut next = None;
            damped_search(&h, &g, &mut lambda, |step| {
                let t_new = t + step.fixed_rows::<3>(0);
                let r_new = Rotation3::new(step.fixed_rows::<3>(3).into_owned()).into_inner() * r;
                // Each observation's line residuals and their whitened norm.
                par::map_into(&idx, &mut trial, |&i| {
                    let res = residual(set, &set.obs[i], &r_new, &t_new);
                    (res, (whiten[i] * res).norm())
                });
                // The lines' cost, then the shaft terms' sum in the same order as a `sum` (from
                // −0), stopped once it exceeds `cost`: every term is ≥ 0, so a partial sum
                // above `cost` rejects the step as the whole sum would.
                let lines: f64 = trial.iter().map(|(_, n)| huber(*n, c)).sum::<f64>();
                let mut shaft = -0.0;
                if lines <= cost && shaft_noise.is_some() {
                    par::map_into(&idx, &mut trial_shaft, |&i| {
                        line_weights[i]
                            * residuals_at_with(set, &set.obs[i], &r_new, &t_new, &at_pose[i].model, &trial[i].0)
                                .iter()
                                .map(|e| huber((e * scale).abs(), c))
                                .sum::<f64>()
                    });
                    for v in &trial_shaft {
                        shaft += v;
                        if lines + shaft > cost {
                            break;
                        }
                    }
                }
                let new_cost = lines + shaft;
                let lower = new_cost <= cost;
                if lower {
                    let small = step.fixed_rows::<3>(0).norm() < 1e-12 && step.fixed_rows::<3>(3).norm() < 1e-12
                        || cost - new_cost <= 1e-14 * cost;
                    next = Some((t_new, r_new, small));
                }
                lower
            });
            let Some((t_new, r_new, small)) = next else { break };
            t = t_new;
            r = orthonormalize(&r_new);
            if small {
                break;
            }
            // In the basin of an already refined candidate: merged.
            let near = |(rj, tj): &(Matrix3<f64>, Vector3<f64>)| {
                let mut d = Vector6::zeros();
                d.fixed_rows_mut::<3>(0).copy_from(&(t - tj));
                d.fixed_rows_mut::<3>(3).copy_from(&Rotation3::from_matrix_unchecked(r * rj.transpose()).scaled_axis());
                d.dot(&(h * d)) <= (MERGE_SIGMAS * scale).powi(2)
            };
            if let Some(j) = done.iter().position(near) {
                (r, t) = done[j];
                merged = Some(j);
                break;
            }
        }
    }
    Refined { r, t, whiten, scale, iterations, merged }
}

/// One observation's terms at a [`refine`] iteration's pose: its whitened line residuals `e`,
/// their Jacobian `j` and norm, and with the shaft-position terms its shaft model, residuals
/// and gradients ([`model_and_residuals_at`]).
#[derive(Default)]
struct ObsTerms {
    e: Vector2<f64>,
    j: super::residual::Jac6,
    norm: f64,
    /// `jᵀ e` and the upper triangle of `jᵀ j` ([`gram_upper`]): the line terms' gradient and
    /// Gauss-Newton matrix before their Huber weight.
    jte: Vector6<f64>,
    jtj: [f64; 21],
    model: ShaftModel,
    es: [f64; super::shaft_position::TERMS],
    gs: [Vector6<f64>; super::shaft_position::TERMS],
}

/// True when `pose` is within `sigmas` standard deviations (Mahalanobis, `fit`'s covariance)
/// of `fit`'s pose.
fn within(fit: &OursResult, pose: &Isometry3<f64>, sigmas: f64) -> bool {
    let mut d = Vector6::zeros();
    d.fixed_rows_mut::<3>(0).copy_from(&(pose.translation.vector - fit.pose.translation.vector));
    d.fixed_rows_mut::<3>(3).copy_from(&(pose.rotation * fit.pose.rotation.inverse()).scaled_axis());
    match fit.covariance.try_inverse() {
        Some(info) => d.dot(&(info * d)).max(0.0).sqrt() <= sigmas,
        None => false,
    }
}

/// Candidates more than this (natural log, 10× the default ambiguity threshold) less likely
/// than the best after the first pass skip the second pass: the whitening refresh moves a
/// candidate's negative log-likelihood by far less, so they can be neither the result nor a
/// runner-up close enough to matter.
const SECOND_PASS_MARGIN_NATS: f64 = 10.0 * DEFAULT_MIN_LOG_LIKELIHOOD_RATIO;

/// Passes with the whitening refreshed at the candidate's current pose, after the first
/// (chosen on the tuning geometries 9000-9019: one pass left 15 of 200 metre-reading trials at
/// σ = 0.01 unexplained, three passes 6).
const WHITENING_PASSES: usize = 3;

/// At most this many other minima of Eq. 10 are refined as extra starts.
const MAX_EXTRA_STARTS: usize = 3;

/// The 24 rotations of the cube (signed permutation matrices with determinant +1).
fn cube_group() -> Vec<Matrix3<f64>> {
    let perms = [[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]];
    let mut out = Vec::with_capacity(24);
    for p in perms {
        for signs in 0..8u8 {
            let mut m = Matrix3::zeros();
            for (row, col) in p.iter().enumerate() {
                m[(row, *col)] = if signs & (1 << row) != 0 { -1.0 } else { 1.0 };
            }
            if m.determinant() > 0.0 {
                out.push(m);
            }
        }
    }
    out
}

fn pose_of(r: &Matrix3<f64>, t: &Vector3<f64>) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::from(*t), UnitQuaternion::from_matrix(r))
}

/// A candidate's negative log-likelihood ([`Candidate::nll`], plus with a noise model the
/// term of the detector's rule, [`kept_given_line_ln`]) at robust scale `s_ref`
/// (whitened units; pixels without a noise model). Finite by construction
/// ([`RESIDUAL_CAP_THRESHOLDS`]; a covariance whose determinant is not positive and finite
/// contributes no log-determinant).
fn candidate_nll(set: &PreparedSet, cfg: &OursConfig, r: &Matrix3<f64>, t: &Vector3<f64>, s_ref: f64) -> f64 {
    nll_parts(set, cfg, r, t).nll(cfg, s_ref)
}

/// The parts of a candidate's [`candidate_nll`] that do not depend on the robust scale: each
/// observation's whitened residual norm (its own covariance; pixels without a noise model) and
/// the sum of the log-determinants and the detector's-rule terms. Computed once per pose.
#[derive(Clone, Debug)]
struct NllParts {
    norms: Vec<f64>,
    /// The shaft-position residuals' magnitudes (non-zero ones only; standard deviations),
    /// each with its observation's index (weighted by that observation's line weight).
    shaft: Vec<(f64, usize)>,
    rest: f64,
}

impl NllParts {
    /// The negative log-likelihood at robust scale `s_ref` ([`candidate_nll`]).
    fn nll(&self, cfg: &OursConfig, s_ref: f64) -> f64 {
        let c = cfg.huber_k * s_ref;
        let cap = RESIDUAL_CAP_THRESHOLDS * c;
        let s2 = s_ref * s_ref;
        let capped = |e: &f64| huber(if e.is_finite() { e.min(cap) } else { cap }, c) / s2;
        // A shaft-position residual is in standard deviations; at robust scale `s_ref` it
        // weighs as a line residual of `e · s_ref` does.
        let quad: f64 = self.norms.iter().map(capped).sum::<f64>()
            + self
                .shaft
                .iter()
                .map(|(e, i)| {
                    let n = self.norms[*i];
                    let lw = if n.is_finite() && n > c {
                        c / n
                    } else if n.is_finite() {
                        1.0
                    } else {
                        0.0
                    };
                    lw * capped(&(e * s_ref))
                })
                .sum::<f64>();
        quad + self.rest
    }
}

fn nll_parts(set: &PreparedSet, cfg: &OursConfig, r: &Matrix3<f64>, t: &Vector3<f64>) -> NllParts {
    // Unused by the shaft terms without their gradients ([`model_and_residuals_at`]).
    let no_jacobian = super::residual::Jac6::zeros();
    // The detector's rule, and the deepest tip any term below conditions on its line.
    let kept_rule = SelectionConfig::default();
    let depth_ratio = kept_rule.depth_ratio.max(TIP_DEPTH_RATIO);
    // Per observation ([`par`]): its whitened norm, its shaft-position residuals, its
    // log-determinant and its detector's-rule term; summed in order below.
    let per_obs = par::map(&set.obs, |o| {
        let res = residual(set, o, r, t);
        // The noise model's quantities at this pose, once for the three terms below.
        let at = cfg.noise.as_ref().map(|noise| (noise, noise_at(set, o, r, t, noise, Some(depth_ratio))));
        let shaft = at.as_ref().filter(|_| cfg.shaft_position).map(|(noise, at)| {
            // [`super::shaft_position::shaft_position_residuals`] with the line residuals shared.
            model_and_residuals_noise_at(set, o, r, t, noise, false, Some((&res, &no_jacobian)), at).1
        });
        let (e, logdet) = match &at {
            Some((_, at)) => {
                let det = at.cov.determinant();
                let logdet = if det.is_finite() && det > 0.0 { det.ln() } else { 0.0 };
                ((whitener(&at.cov) * res).norm(), logdet)
            }
            None => (res.norm(), 0.0),
        };
        // With a noise model: that this line was recorded at all, given where this pose puts
        // the tool (the detector's rule; −ln P(kept | line), 0 where the first-order model
        // does not apply, a bounded penalty for a tip behind the camera).
        let kept = at.as_ref().map(|(noise, at)| kept_given_line_ln_at(set, o, r, t, noise, &kept_rule, at, &res));
        (e, shaft, logdet, kept)
    });
    let mut norms = Vec::with_capacity(set.obs.len());
    let mut shaft = Vec::new();
    let mut rest = 0.0;
    for (i, (e, es, logdet, kept)) in per_obs.into_iter().enumerate() {
        if let Some(es) = es {
            shaft.extend(es.iter().filter(|e| **e != 0.0).map(|e| (e.abs(), i)));
        }
        norms.push(e);
        rest += 0.5 * logdet;
        if let Some(kept) = kept {
            rest -= kept;
        }
    }
    NllParts { norms, shaft, rest }
}

/// Most iterations of [`descend_likelihood`].
const DESCENT_ITERATIONS: usize = 30;

/// `(r, t)` moved by `step` (`(t m, δφ rad)`, left increment), as [`refine`] moves it.
fn moved(r: &Matrix3<f64>, t: &Vector3<f64>, step: &Vector6<f64>) -> (Matrix3<f64>, Vector3<f64>) {
    let r_new = Rotation3::new(step.fixed_rows::<3>(3).into_owned()).into_inner() * r;
    (orthonormalize(&r_new), t + step.fixed_rows::<3>(0))
}

/// The Gauss-Newton matrix and gradient (w.r.t. `(t m, δφ rad)`) of [`candidate_nll`]'s
/// residual terms at `(r, t)` and robust scale `s_ref`: the line residuals whitened by their
/// own covariance at this pose (not a pass's, as in [`refine`]) and the shaft-position terms,
/// Huber-weighted as the likelihood weighs them. The log-determinants and the detector's-rule
/// terms are not in it: it gives [`descend_likelihood`] its directions, the whole likelihood
/// decides its steps.
fn likelihood_metric(
    set: &PreparedSet,
    cfg: &OursConfig,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    s_ref: f64,
) -> (Matrix6<f64>, Vector6<f64>) {
    let c = cfg.huber_k * s_ref;
    let s2 = s_ref * s_ref;
    let shaft_noise = cfg.noise.as_ref().filter(|_| cfg.shaft_position);
    let per_obs = par::map(&set.obs, |o| {
        let (res, jac) = residual_and_jacobian(set, o, r, t);
        // The noise model's quantities at this pose, once for the whitening and the shaft terms.
        let at = cfg.noise.as_ref().map(|noise| noise_at(set, o, r, t, noise, shaft_noise.map(|_| TIP_DEPTH_RATIO)));
        let w = match &at {
            Some(at) => whitener(&at.cov),
            None => Matrix2::identity(),
        };
        let (e, j) = (w * res, w * jac);
        let n = e.norm();
        if !n.is_finite() {
            return (Matrix6::zeros(), Vector6::zeros());
        }
        // Huber's weight; the shaft terms take their line's, as [`NllParts::nll`] does.
        let lw = if n <= c { 1.0 } else { c / n };
        let mut h = j.transpose() * j * (lw / s2);
        let mut g = j.transpose() * e * (lw / s2);
        if let (Some(noise), Some(at)) = (shaft_noise, &at) {
            let (_, es, js) = model_and_residuals_noise_at(set, o, r, t, noise, true, Some((&res, &jac)), at);
            for (e, j) in es.iter().zip(&js) {
                if *e != 0.0 {
                    // In standard deviations: weighs `huber(e · s_ref, c) / s_ref²`.
                    let n = (e * s_ref).abs();
                    let wgt = lw * if n <= c { 1.0 } else { c / n };
                    h += j * j.transpose() * wgt;
                    g += j * (e * wgt);
                }
            }
        }
        (h, g)
    });
    per_obs.iter().fold((Matrix6::zeros(), Vector6::zeros()), |a, x| (a.0 + x.0, a.1 + x.1))
}

/// Descends [`candidate_nll`] at robust scale `s_ref` from `(r, t)`: Levenberg-Marquardt on
/// [`likelihood_metric`] (the residuals whitened afresh at every iteration's pose), a step
/// taken only when it lowers the whole likelihood (log-determinants and the detector's rule
/// included). Never less likely than its start; stops when no damped step lowers it, when a
/// step is under a thousandth of a standard deviation, or after [`DESCENT_ITERATIONS`].
/// Returns the pose, its [`NllParts`] and the iterations.
///
/// The likelihood's own gradient (forward differences, log-determinants included) was tried
/// first: it walked candidates behind the camera, where the lines' predicted covariance is
/// smallest (`docs/calibration.md`, session 24).
fn descend_likelihood(
    set: &PreparedSet,
    cfg: &OursConfig,
    r0: &Matrix3<f64>,
    t0: &Vector3<f64>,
    s_ref: f64,
) -> (Matrix3<f64>, Vector3<f64>, NllParts, usize) {
    let (mut r, mut t) = (*r0, *t0);
    let mut parts = nll_parts(set, cfg, &r, &t);
    let mut f = parts.nll(cfg, s_ref);
    let mut iterations = 0;
    if !f.is_finite() {
        return (r, t, parts, iterations);
    }
    let mut lambda = 1e-3;
    for _ in 0..DESCENT_ITERATIONS {
        iterations += 1;
        let (h, g) = likelihood_metric(set, cfg, &r, &t, s_ref);
        if !(h.iter().all(|v| v.is_finite()) && g.iter().all(|v| v.is_finite())) {
            break;
        }
        let mut next = None;
        let step = damped_search(&h, &g, &mut lambda, |step| {
            let (rn, tn) = moved(&r, &t, step);
            let pn = nll_parts(set, cfg, &rn, &tn);
            let f_new = pn.nll(cfg, s_ref);
            let lower = f_new < f;
            if lower {
                next = Some((rn, tn, pn, f_new));
            }
            lower
        });
        let (Some(step), Some((rn, tn, pn, f_new))) = (step, next) else { break };
        // Under a thousandth of a standard deviation (the metric's).
        let small = step.dot(&(h * step)) <= 1e-6 || f - f_new <= 1e-12 * f.abs().max(1.0);
        (r, t, parts, f) = (rn, tn, pn, f_new);
        if small {
            break;
        }
    }
    (r, t, parts, iterations)
}

/// Moves candidate `x` to the end of its [`descend_likelihood`] at robust scale `s_ref`
/// (pose, robust scale of the descended residuals, iterations added) and returns its
/// likelihood parts there.
fn descend_candidate(set: &PreparedSet, cfg: &OursConfig, x: &mut Refined, s_ref: f64) -> NllParts {
    let (r, t, p, its) = descend_likelihood(set, cfg, &x.r, &x.t, s_ref);
    let mut scratch = Vec::with_capacity(p.norms.len());
    let scale = robust_scale_with(&p.norms, &mut scratch);
    (x.r, x.t, x.scale, x.iterations) = (r, t, scale, x.iterations + its);
    p
}

/// The runner-up of the candidates (`costs` their [`candidate_nll`], `ib` the best): the most
/// likely distinct solution; when there is none, the best's mirror, refined (kept refined only
/// if that converges to a distinct solution). Returns its pose and negative log-likelihood.
fn runner_up(
    set: &PreparedSet,
    cfg: &OursConfig,
    candidates: &[Refined],
    costs: &[f64],
    ib: usize,
    nll_of: &dyn Fn(&Matrix3<f64>, &Vector3<f64>) -> f64,
) -> (Isometry3<f64>, f64) {
    let best = &candidates[ib];
    let distinct =
        |r: &Matrix3<f64>| Rotation3::from_matrix_unchecked(best.r.transpose() * r).angle() > DISTINCT_SOLUTION_RAD;
    let alt = (0..candidates.len())
        .filter(|i| *i != ib && costs[*i].is_finite() && distinct(&candidates[*i].r))
        .min_by(|a, b| costs[*a].total_cmp(&costs[*b]));
    if let Some(i) = alt {
        return (pose_of(&candidates[i].r, &candidates[i].t), costs[i]);
    }
    // Every start went to the best: its mirror, refined.
    let [(r_m, t_m), ..] = flips(set, &best.r, &best.t);
    let refined = refine(set, cfg, whitening(set, cfg, &r_m, &t_m), r_m, t_m, &[]);
    let ok = refined.t.iter().chain(refined.r.iter()).all(|v| v.is_finite()) && distinct(&refined.r);
    if ok {
        let c = nll_of(&refined.r, &refined.t);
        return (pose_of(&refined.r, &refined.t), c);
    }
    (pose_of(&r_m, &t_m), nll_of(&r_m, &t_m))
}

/// Pose `(r, t)` turned 180° about the mean line of sight to the mean line point (robot 2's
/// RCM, or the mean fulcrum), about the mean tool direction, about the line of sight's part
/// across the tool, and about the normal of the plane of tool and line of sight; the mean line
/// point stays in place.
fn flips(set: &PreparedSet, r: &Matrix3<f64>, t: &Vector3<f64>) -> [(Matrix3<f64>, Vector3<f64>); 4] {
    let n = set.obs.len().max(1) as f64;
    let mean_c = set.obs.iter().map(|o| o.o_ec).sum::<Vector3<f64>>() / n;
    let mean_p = set.obs.iter().map(|o| o.p_t).sum::<Vector3<f64>>() / n;
    let mean_m = set.obs.iter().map(|o| o.m_t).sum::<Vector3<f64>>() / n;
    let point_e = r * mean_p + t;
    let sight = (point_e - mean_c).try_normalize(1e-12).unwrap_or_else(Vector3::z);
    let a = (r * mean_m).try_normalize(1e-12).unwrap_or_else(Vector3::z);
    let b = (sight - a * a.dot(&sight)).try_normalize(1e-9).unwrap_or_else(|| a.cross(&Vector3::x()).normalize());
    let c = a.cross(&b);
    [sight, a, b, c].map(|axis| {
        let flip = Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), core::f64::consts::PI).into_inner();
        let r_m = flip * r;
        (r_m, point_e - r_m * mean_p)
    })
}

/// A first-pass candidate refined again with the whitening refreshed at its pose, up to
/// [`WHITENING_PASSES`] times: with metre-level noise the residual covariance moves with the
/// pose, and one refresh leaves the fit where the first pass's weights put it. Stops when a
/// pass no longer moves the pose. `iterations` counts all passes.
fn polish(set: &PreparedSet, cfg: &OursConfig, first: Refined) -> Refined {
    let mut its = first.iterations;
    let mut x = first;
    for _ in 0..WHITENING_PASSES {
        let w1 = whitening(set, cfg, &x.r, &x.t);
        x = refine(set, cfg, w1, x.r, x.t, &[]);
        its += x.iterations;
        if x.iterations <= 1 {
            break;
        }
    }
    Refined { iterations: its, ..x }
}

/// Whitening matrices `Σ_i^{-1/2}` at `(r, t)` (identity without a noise model).
fn whitening(set: &PreparedSet, cfg: &OursConfig, r: &Matrix3<f64>, t: &Vector3<f64>) -> Vec<Matrix2<f64>> {
    match &cfg.noise {
        Some(noise) => par::map(&set.obs, |o| whitener(&residual_covariance(set, o, r, t, noise))),
        None => vec![Matrix2::identity(); set.obs.len()],
    }
}

fn orthonormalize(r: &Matrix3<f64>) -> Matrix3<f64> {
    UnitQuaternion::from_matrix(r).to_rotation_matrix().into_inner()
}

/// Each observation's residual pair at pose `T_e_t`: the signed distances (pixels) of its two
/// line points to the tool axis projected by that pose, in input order.
pub fn observation_residuals(set: &PreparedSet, pose: &Isometry3<f64>) -> Vec<Vector2<f64>> {
    let r = pose.rotation.to_rotation_matrix().into_inner();
    let t = pose.translation.vector;
    set.obs.iter().map(|o| residual(set, o, &r, &t)).collect()
}

/// How a pose explains where the shafts were seen ([`shaft_explanation`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ShaftExplanation {
    /// Observations whose two observed line points both meet the tool axis behind the camera.
    pub behind: usize,
    /// Observations (in front) whose line points meet the axis outside the physical shaft.
    pub off_shaft: usize,
    /// Observations.
    pub observations: usize,
}

impl ShaftExplanation {
    /// True when at most [`MAX_UNEXPLAINED_SHARE`] of the observations are unexplained.
    pub fn explains(&self) -> bool {
        ((self.behind + self.off_shaft) as f64) <= MAX_UNEXPLAINED_SHARE * self.observations as f64
    }
}

/// How pose `T_e_t` explains where the shafts were seen: the observations whose two observed
/// line points both meet the tool axis behind the camera, and those (in front) whose line
/// points meet the axis outside the visible instrument, farther than `margin` insertions from
/// the segment [`Prepared::visible_m`] (by default between the line's known point, robot 2's
/// RCM, and the tip). The line model cannot
/// tell a line's side of the camera, nor where along the line the shaft is; the images can.
pub fn shaft_explanation(set: &PreparedSet, pose: &Isometry3<f64>, margin: f64) -> ShaftExplanation {
    let r = pose.rotation.to_rotation_matrix().into_inner();
    let t = pose.translation.vector;
    let (mut behind, mut off_shaft) = (0, 0);
    for o in &set.obs {
        let seen = o.px.map(|u| axis_seen_at(set, o, &r, &t, &u));
        if seen.iter().all(|x| x.is_some_and(|(z, _)| z <= 0.0)) {
            behind += 1;
        } else {
            let len = o.insertion_m.abs().max(1e-9);
            let [lo, hi] = o.visible_m;
            if seen.iter().flatten().any(|(_, s)| *s < lo - margin * len || *s > hi + margin * len) {
                off_shaft += 1;
            }
        }
    }
    ShaftExplanation { behind, off_shaft, observations: set.obs.len() }
}

/// True when pose `T_e_t` explains where the shafts were seen ([`shaft_explanation`] with
/// [`SHAFT_MARGIN`], [`ShaftExplanation::explains`]).
pub fn explains_shafts(set: &PreparedSet, pose: &Isometry3<f64>) -> bool {
    shaft_explanation(set, pose, SHAFT_MARGIN).explains()
}

/// Pixel residual statistics of pose `T_e_t` over prepared observations (unweighted).
pub fn residual_stats(set: &PreparedSet, pose: &Isometry3<f64>) -> ResidualStats {
    let mut d: Vec<f64> = observation_residuals(set, pose).iter().flat_map(|r| [r[0].abs(), r[1].abs()]).collect();
    let rms = (d.iter().map(|v| v * v).sum::<f64>() / d.len().max(1) as f64).sqrt();
    let max = d.iter().cloned().fold(0.0, f64::max);
    ResidualStats { count: set.obs.len(), rms_px: rms, median_px: median(&mut d), max_px: max, inliers: set.obs.len() }
}

/// Initial rotation when Eq. 8 is rank-deficient (e.g. exactly three tool orientations):
/// per tool orientation, the tool direction in `{e}` is the common null direction of its
/// plane normals; its sign puts the tool tip in front of the camera; Kabsch aligns `m` to it.
fn grouped_rotation(set: &PreparedSet, t0: &Vector3<f64>) -> Option<Matrix3<f64>> {
    let mut groups: Vec<(Vector3<f64>, Matrix3<f64>, usize, usize)> = Vec::new();
    for (i, o) in set.obs.iter().enumerate() {
        match groups.iter_mut().find(|g| g.0.cross(&o.m_t).norm() <= SAME_ORIENTATION_RAD && g.0.dot(&o.m_t) > 0.0) {
            Some(g) => {
                g.1 += o.n_e * o.n_e.transpose();
                g.2 += 1;
            }
            None => groups.push((o.m_t, o.n_e * o.n_e.transpose(), 1, i)),
        }
    }
    let mut h = Matrix3::zeros();
    let mut used = 0;
    for (m, s, count, first) in &groups {
        if *count < 2 {
            continue;
        }
        let eig = s.symmetric_eigen();
        let (imin, _) = eig.eigenvalues.argmin();
        let mut u: Vector3<f64> = eig.eigenvectors.column(imin).into_owned();
        let o = &set.obs[*first];
        let tip_c = o.r_ec.transpose() * (t0 + u * o.insertion_m - o.o_ec);
        if tip_c.z < 0.0 {
            u = -u;
        }
        h += u * m.transpose();
        used += 1;
    }
    if used < 2 {
        return None;
    }
    let svd = h.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut d = Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    Some(u * d * vt)
}

/// Our whole pipeline on raw observations.
pub fn solve_ours(setup: &Setup, observations: &[Observation], config: &OursConfig) -> Result<OursResult, OursError> {
    let set = prepare(setup, observations)?;
    solve_ours_prepared(&set, config)
}

/// Our pipeline on prepared observations.
pub fn solve_ours_prepared(set: &PreparedSet, cfg: &OursConfig) -> Result<OursResult, OursError> {
    // With the `parallel` feature: on rayon's pool ([`par::in_pool`]).
    par::in_pool(|| solve_with_scale(set, cfg))
}

/// [`solve_ours_prepared`]'s body: as stated, then, when asked, again with the noise model's
/// scale estimated ([`OursConfig::estimate_noise_scale`]).
fn solve_with_scale(set: &PreparedSet, cfg: &OursConfig) -> Result<OursResult, OursError> {
    let first = solve_as_stated(set, cfg)?;
    let Some(noise) = cfg.noise.filter(|_| cfg.estimate_noise_scale) else {
        return Ok(first);
    };
    let k = first.scale;
    if !(k.is_finite() && k > 0.0) {
        return Ok(first);
    }
    let k = k.clamp(NOISE_SCALE_BOUNDS[0], NOISE_SCALE_BOUNDS[1]);
    let scaled = OursConfig { noise: Some(noise.scaled(k)), estimate_noise_scale: false, ..*cfg };
    let mut second = solve_as_stated(set, &scaled)?;
    second.noise_scale = Some(k);
    Ok(second)
}

/// [`solve_ours_prepared`] with the noise model as stated.
fn solve_as_stated(set: &PreparedSet, cfg: &OursConfig) -> Result<OursResult, OursError> {
    // The shaft-position likelihood says where the arms put the tool. A noise model without
    // the arms' noise (pixels only) claims pixel precision for a tip at the end of two
    // kinematic chains, and any arm-model error then bends the fit to meet it (on a recorded
    // run of the twin, ~1 mm of model error: 10-81° off). The lines alone then.
    let cfg = &OursConfig {
        shaft_position: cfg.shaft_position && cfg.noise.is_some_and(|n| n.has_kinematic_terms()),
        ..*cfg
    };
    let mut result = solve_once(set, cfg, None)?;
    let Some(noise) = cfg.noise else {
        return Ok(result);
    };
    // Border guard: an observation is only in the dataset because its tool tip was in view,
    // which selects the noise of observations near the image border (tips pushed inward are
    // kept, pushed outward dropped) and biases the fit. Keep only observations whose tip is
    // predicted, from the current estimate, to lie at least `border_guard_sigmas` standard
    // deviations inside the image: their selection no longer depends on their own noise.
    let mut kept_before = set.obs.len();
    let guard_rounds = if cfg.border_guard_sigmas > 0.0 { 3 } else { 0 };
    for _ in 0..guard_rounds {
        let r = result.pose.rotation.to_rotation_matrix().into_inner();
        let t = result.pose.translation.vector;
        let obs: Vec<Prepared> = set
            .obs
            .iter()
            .filter(|o| tip_well_inside(set, o, &r, &t, &noise, cfg.border_guard_sigmas))
            .cloned()
            .collect();
        if obs.len() == kept_before || obs.len() < 12 {
            break;
        }
        kept_before = obs.len();
        let sub = PreparedSet { obs, ..set.clone() };
        match solve_once(&sub, cfg, Some(&result.pose)) {
            // A guarded refit must stay within the full fit's confidence region (the guard
            // removes a bias, it does not find another solution); else the guard stops.
            Ok(next) if !within(&result, &next.pose, GUARD_MAX_SHIFT_SIGMAS) => break,
            Ok(mut next) => {
                next.guard_kept = sub.obs.len();
                next.guard_from = Some(result.pose);
                next.alternative = result.alternative;
                next.log_likelihood_ratio = result.log_likelihood_ratio;
                next.searched_on = result.searched_on;
                next.cover_searched = result.cover_searched;
                result = next;
            }
            Err(_) => break,
        }
    }
    // The selection-aware stage, from the guarded fit, on all observations.
    Ok(match &cfg.selection {
        Some(sel) => apply_selection_stage(set, &noise, sel, cfg, result),
        None => result,
    })
}

/// The selection-aware stage ([`super::selection`]) from a guarded fit of
/// [`solve_ours_prepared`] (run with `selection: None`): the stage's pose, covariance and
/// bookkeeping, or the guarded fit with the reason when the stage is refused. For comparing
/// both without solving twice. `ours`: the guarded fit's options (its
/// [`OursConfig::shaft_position`] adds the shaft-position terms to the stage; its Huber
/// constant and border guard give the guarded fit's influences for
/// [`SelectionConfig::influence_move_test`]); its noise model is `noise`.
pub fn apply_selection_stage(
    set: &PreparedSet,
    noise: &KinematicNoise,
    cfg: &SelectionConfig,
    ours: &OursConfig,
    mut result: OursResult,
) -> OursResult {
    // As [`solve_as_stated`] gates them: no shaft-position terms without the arms' noise.
    let shaft_position = ours.shaft_position && noise.has_kinematic_terms();
    let influence = cfg
        .influence_move_test
        .then(|| guarded_influence(set, &OursConfig { noise: Some(*noise), shaft_position, ..*ours }, &result))
        .flatten();
    let terms = |o: &Prepared, r: &Matrix3<f64>, t: &Vector3<f64>, grad: bool| stage_terms(set, o, r, t, noise, grad);
    let extra: Option<super::selection::ExtraTerms<'_>> = if shaft_position { Some(&terms) } else { None };
    // A stage whose move fails the Hausman test is still taken when its pose is far more likely
    // than the guarded fit's on all observations (the candidates' likelihood,
    // [`candidate_nll`], by more than [`DEFAULT_MIN_LOG_LIKELIHOOD_RATIO`];
    // [`SelectionConfig::more_likely_overrides_test`]): the test says one of the two fits is
    // wrong, not which; the likelihood the candidates were chosen by does. On the tuning
    // geometries (metres, σ = 0.01) the refused stages had moved from guarded fits 4-8° off
    // to within 0.9° of the truth.
    let ocfg = OursConfig { noise: Some(*noise), shaft_position, ..OursConfig::default() };
    let nll = |p: &Isometry3<f64>| {
        candidate_nll(set, &ocfg, &p.rotation.to_rotation_matrix().into_inner(), &p.translation.vector, result.scale)
    };
    let mut on_likelihood = false;
    let fit = match refine_selected_with(set, noise, &result.pose, &result.covariance, cfg, extra, influence.as_deref())
    {
        Err(e @ SelectionError::RanAway { .. }) if cfg.more_likely_overrides_test => {
            let loose = SelectionConfig { false_refusal_probability: 0.0, ..*cfg };
            match refine_selected_with(
                set,
                noise,
                &result.pose,
                &result.covariance,
                &loose,
                extra,
                influence.as_deref(),
            ) {
                Ok(fit) if nll(&fit.pose) + DEFAULT_MIN_LOG_LIKELIHOOD_RATIO < nll(&result.pose) => {
                    on_likelihood = true;
                    Ok(fit)
                }
                _ => Err(e),
            }
        }
        other => other,
    };
    // The stage's pose must explain the shafts as the guarded fit does.
    let fit = fit.and_then(|fit| {
        let x = shaft_explanation(set, &fit.pose, SHAFT_MARGIN);
        if x.explains() {
            Ok(fit)
        } else {
            Err(SelectionError::ShaftsNotExplained {
                behind: x.behind,
                off_shaft: x.off_shaft,
                observations: x.observations,
                sigmas: fit.shift_sigmas,
                move_statistic: fit.move_test.map(|t| (t.statistic, t.limit)),
            })
        }
    });
    match fit {
        Ok(mut fit) => {
            // The last step on the moving covariances (on by default): the stage's
            // covariance is kept (the step's own, `MovingStep::covariance`, is smaller).
            let mut moving_step = None;
            let step = cfg.moving_covariance_step.then(|| moving_covariance_step(set, noise, cfg, &fit.pose, extra));
            if let Some(step) = step.flatten() {
                let take =
                    cfg.moving_step_worth_it(&step) && shaft_explanation(set, &step.pose, SHAFT_MARGIN).explains();
                let sd = step.information_gain_sd.filter(|sd| sd.is_finite());
                moving_step = Some((step.information_gain, sd, take));
                if take {
                    fit.pose = step.pose;
                }
            }
            result.covariance = fit.covariance;
            result.pose = fit.pose;
            result.residuals = ResidualStats { inliers: fit.selected + fit.plain, ..residual_stats(set, &fit.pose) };
            result.selection = Some(SelectionSummary {
                selected: fit.selected,
                plain: fit.plain,
                left_out: fit.left_out,
                shift_sigmas: fit.shift_sigmas,
                accepted_on_likelihood: on_likelihood,
                moving_step,
                move_test_measured: fit.move_test.is_some_and(|t| t.measured),
                move_statistic: fit.move_test.map(|t| (t.statistic, t.limit)),
            });
        }
        Err(e) => result.selection_refused = Some(e),
    }
    result
}

/// The guarded fit's influence per observation of `set` at its pose (`(t m, δφ rad)`: the
/// inverse of its Gauss-Newton matrix times the observation's score, both as its covariance
/// takes them: whitened line residuals with Huber weights at `huber_k · ŝ`, and the
/// shaft-position terms when `cfg.shaft_position`); zero for an observation the border guard
/// left out (drawn again at [`OursResult::guard_from`]). `None` without a noise model, when
/// the matrix is singular, or when the fit is not at a stationary point of that objective:
/// the influences' sum (one Newton step from the fit) more than [`MAX_GUARDED_OFFSET_SD`] of
/// the fit's standard deviations (in the influences' own metric) — the guarded fit stops after
/// [`WHITENING_PASSES`] re-whitenings, and its last objective need not be the one rebuilt
/// here; the stage then keeps the efficiency-based test.
fn guarded_influence(set: &PreparedSet, cfg: &OursConfig, result: &OursResult) -> Option<Vec<Vector6<f64>>> {
    let noise = cfg.noise?;
    let r = result.pose.rotation.to_rotation_matrix().into_inner();
    let t = result.pose.translation.vector;
    let guard = result.guard_from.map(|p| (p.rotation.to_rotation_matrix().into_inner(), p.translation.vector));
    let whiten = whitening(set, cfg, &r, &t);
    let c = cfg.huber_k * result.scale;
    let scale2 = result.scale * result.scale;
    let shaft_noise = cfg.noise.as_ref().filter(|_| cfg.shaft_position);
    let parts: Vec<(Matrix6<f64>, Vector6<f64>)> = set
        .obs
        .iter()
        .zip(&whiten)
        .map(|(o, w)| {
            if let Some((gr, gt)) = &guard
                && !tip_well_inside(set, o, gr, gt, &noise, cfg.border_guard_sigmas)
            {
                return (Matrix6::zeros(), Vector6::zeros());
            }
            let (res, jac) = residual_and_jacobian(set, o, &r, &t);
            let (e, j) = (w * res, w * jac);
            let n = e.norm();
            let lw = if n <= c { 1.0 } else { c / n };
            let (mut h, mut g) = (j.transpose() * j * lw, j.transpose() * e * lw);
            if let Some(noise) = shaft_noise {
                let (_, es, js) = model_and_residuals_at(set, o, &r, &t, noise, true, Some((&res, &jac)));
                for (e, j) in es.iter().zip(&js) {
                    if *e != 0.0 {
                        let n = (e * result.scale).abs();
                        let wgt = lw * if n <= c { 1.0 } else { c / n };
                        h += j * j.transpose() * (scale2 * wgt);
                        g += j * (e * scale2 * wgt);
                    }
                }
            }
            (h, g)
        })
        .collect();
    let h_inv = parts.iter().fold(Matrix6::zeros(), |a, p| a + p.0).try_inverse()?;
    let u: Vec<Vector6<f64>> = parts.iter().map(|p| h_inv * p.1).collect();
    let sum = u.iter().fold(Vector6::zeros(), |a, x| a + x);
    let spread = u.iter().fold(Matrix6::zeros(), |a, x| a + x * x.transpose());
    let offset2 = spread.try_inverse().map(|s| sum.dot(&(s * sum)))?;
    (offset2.is_finite() && offset2 <= MAX_GUARDED_OFFSET_SD * MAX_GUARDED_OFFSET_SD).then_some(u)
}

/// Largest distance (in the guarded fit's standard deviations, its influences' metric) from
/// the guarded fit to the stationary point of the guarded objective as the measured move test
/// rebuilds it ([`SelectionConfig::influence_move_test`]) for that test to be used (0.1: the fit is at that objective's minimum to a
/// tenth of its noise; on the default scene the distance is below 1e-4).
pub const MAX_GUARDED_OFFSET_SD: f64 = 0.1;

/// One solve. `from`: refine only from this pose (no linear start, no mirror), keeping the
/// ambiguity decision already made on the full data.
fn solve_once(set: &PreparedSet, cfg: &OursConfig, from: Option<&Isometry3<f64>>) -> Result<OursResult, OursError> {
    if cfg.noise.is_some_and(|n| !n.is_valid()) {
        return Err(OursError::NoiseModel);
    }
    let starts = start_rotations(set, cfg, from)?;
    // The search from a cover of rotation space ([`OursConfig::cover_search_scale`]): at once
    // with a limit of 0, else when the first search's answer fits worse than the limit.
    let cover = match cfg.cover_search_scale {
        Some(limit) if from.is_none() && cfg.noise.is_some() => starts.cover().map(|c| (limit, c)),
        _ => None,
    };
    let Some((limit, cover)) = cover else {
        return search(set, cfg, from, &starts);
    };
    if limit > 0.0 {
        let first = search(set, cfg, None, &starts);
        match &first {
            Ok(x) if x.scale > limit => {}
            _ => return first,
        }
    }
    search(set, cfg, None, &cover).map(|mut y| {
        y.cover_searched = true;
        y
    })
}

/// [`solve_once`]'s search from `starts`: on a subsample first when the dataset is large
/// ([`OursConfig::search_observations`]), else on all observations.
fn search(
    set: &PreparedSet,
    cfg: &OursConfig,
    from: Option<&Isometry3<f64>>,
    starts: &Starts,
) -> Result<OursResult, OursError> {
    if from.is_none()
        && let Some(n) = cfg.search_observations.filter(|n| *n >= 12 && set.obs.len() >= 2 * n)
        && let Some(result) = coarse_to_fine(set, cfg, starts, n)
    {
        return result;
    }
    solve_from(set, cfg, from, starts)
}

/// [`OursError::Ambiguous`] between `best` and `runner_up` (each a pose and its negative
/// log-likelihood); the ratio is their difference, at least 0.
fn ambiguous(cfg: &OursConfig, best: (Isometry3<f64>, f64), runner_up: (Isometry3<f64>, f64)) -> OursError {
    let ((b, c_b), (a, c_a)) = (best, runner_up);
    OursError::Ambiguous {
        best: Box::new(Candidate { pose: b, nll: c_b }),
        runner_up: Box::new(Candidate { pose: a, nll: c_a }),
        log_likelihood_ratio: (c_a - c_b).max(0.0),
        min: cfg.min_log_likelihood_ratio,
        angle_deg: (b.rotation.inverse() * a.rotation).angle().to_degrees(),
        distance_mm: (b.translation.vector - a.translation.vector).norm() * 1e3,
    }
}

/// `n` of `set`'s observations, spread over the set by the golden-ratio sequence (index `i`
/// kept when `frac(i φ⁻¹) < n / N`): a grid of poses in any order is sampled without aliasing.
fn subsample(set: &PreparedSet, n: usize) -> PreparedSet {
    const INV_PHI: f64 = 0.618_033_988_749_894_9;
    let f = n as f64 / set.obs.len().max(1) as f64;
    let obs = set.obs.iter().enumerate().filter(|(i, _)| (*i as f64 * INV_PHI).fract() < f).map(|(_, o)| *o).collect();
    set.with_observations(obs)
}

/// [`OursConfig::search_observations`]: the candidates searched on a subsample, the chosen
/// basin and its runner-up refined and judged on all observations. `None` when the
/// subsample cannot settle it (the caller then searches on all observations).
fn coarse_to_fine(
    set: &PreparedSet,
    cfg: &OursConfig,
    starts: &Starts,
    n: usize,
) -> Option<Result<OursResult, OursError>> {
    let sub = subsample(set, n);
    // A subsample that lost what the method needs (two views of robot 1, three tool
    // orientations, lines not all in one pencil) cannot stand in for the data.
    if sub.views < 2 || sub.orientations < 3 || sub.pencil_ratio.is_nan() || sub.pencil_ratio < PENCIL_TOLERANCE {
        return None;
    }
    let (best, alt) = match solve_from(&sub, cfg, None, starts) {
        Ok(x) => (x.pose, x.alternative),
        Err(OursError::Ambiguous { best, runner_up, .. }) => (best.pose, runner_up.pose),
        Err(_) => return None,
    };
    let distinct =
        |a: &Isometry3<f64>, b: &Isometry3<f64>| (a.rotation.inverse() * b.rotation).angle() > DISTINCT_SOLUTION_RAD;
    if !distinct(&best, &alt) {
        return None;
    }
    // The chosen basin, refined on all observations (its result is the answer).
    let mut w = solve_once(set, cfg, Some(&best)).ok()?;
    let rt = |p: &Isometry3<f64>| (p.rotation.to_rotation_matrix().into_inner(), p.translation.vector);
    // Judged as the full search judges its basins: at their descended likelihoods
    // ([`OursConfig::descend_every_basin`]), at one common robust scale.
    let descend = cfg.likelihood_descent && cfg.descend_every_basin;
    let judge = |p: &Isometry3<f64>, s_ref: f64| -> (f64, bool, Isometry3<f64>) {
        let (r, t) = rt(p);
        if descend {
            let (r, t, parts, _) = descend_likelihood(set, cfg, &r, &t, s_ref);
            let q = pose_of(&r, &t);
            (parts.nll(cfg, s_ref), explains_shafts(set, &q), q)
        } else {
            (candidate_nll(set, cfg, &r, &t, s_ref), explains_shafts(set, p), *p)
        }
    };
    // The runner-up where the subsample's search left it: as in the full search, a candidate
    // more than [`SECOND_PASS_MARGIN_NATS`] less likely than the best is compared where it is
    // (not refined further on all observations).
    let (r_a, t_a) = rt(&alt);
    let (r_w, t_w) = rt(&w.pose);
    let far = candidate_nll(set, cfg, &r_a, &t_a, w.scale) - candidate_nll(set, cfg, &r_w, &t_w, w.scale);
    let (mut a_pose, mut a_scale, mut a_its) = (alt, w.scale, 0);
    if far.is_nan() || far <= SECOND_PASS_MARGIN_NATS {
        let a = solve_once(set, cfg, Some(&alt)).ok()?;
        if distinct(&w.pose, &a.pose) {
            (a_pose, a_scale, a_its) = (a.pose, a.scale, a.iterations);
        } else {
            // No basin of its own on all observations: as the full search's runner-up when
            // every candidate went to the best, the best's mirror, refined.
            let [(r_m, t_m), ..] = flips(set, &r_w, &t_w);
            let x = refine(set, cfg, whitening(set, cfg, &r_m, &t_m), r_m, t_m, &[]);
            let ok = x.t.iter().chain(x.r.iter()).all(|v| v.is_finite()) && distinct(&w.pose, &pose_of(&x.r, &x.t));
            let (r, t) = if ok { (x.r, x.t) } else { (r_m, t_m) };
            (a_pose, a_scale, a_its) =
                (pose_of(&r, &t), if ok { x.scale } else { w.scale }, a.iterations + x.iterations);
        }
    }
    let s_ref = w.scale.min(a_scale);
    let ((c_w, e_w, d_w), (c_a, e_a, d_a)) = (judge(&w.pose, s_ref), judge(&a_pose, s_ref));
    if !(c_w.is_finite() && c_a.is_finite()) {
        return None;
    }
    // The runner-up descends into the best's basin: no rival basin was found on all
    // observations; searched again on all.
    if !distinct(&d_w, &d_a) {
        return None;
    }
    if c_a < c_w {
        // On all observations the runner-up's basin is the more likely: searched again on all.
        return None;
    }
    // The most likely basin does not explain the shafts: the full search refuses or decides.
    if !e_w {
        return None;
    }
    let llr = c_a - c_w;
    // A runner-up that does not explain the shafts is no rival, however likely its lines.
    if llr < cfg.min_log_likelihood_ratio && e_a {
        return Some(Err(ambiguous(cfg, (w.pose, c_w), (a_pose, c_a))));
    }
    w.alternative = a_pose;
    w.log_likelihood_ratio = llr;
    w.searched_on = sub.obs.len();
    w.iterations += a_its;
    Some(Ok(w))
}

/// [`solve_once`]'s starts (they do not depend on [`OursConfig::shaft_position`]): the
/// translation `t0` (Eq. 5, or `from`'s), the starting rotations (`from`'s, or the configured
/// one and the linear start) and the other minima of Eq. 10, or in their place the cover of
/// rotation space ([`Starts::extra`]).
#[derive(Clone)]
struct Starts {
    t0: Vector3<f64>,
    starts: Vec<Matrix3<f64>>,
    /// The other minima of Eq. 10.
    eq10: Vec<Matrix3<f64>>,
    /// The linear start (Eq. 8-10), when there is one.
    linear: Option<Matrix3<f64>>,
    /// The cover of rotation space replaces [`Starts::eq10`] ([`Starts::cover`]).
    cover: bool,
}

impl Starts {
    /// These starts with the cover of rotation space ([`OursConfig::cover_search_scale`]) in
    /// place of the other minima of Eq. 10. `None` without a linear start.
    fn cover(&self) -> Option<Starts> {
        self.linear.map(|_| Starts { cover: true, ..self.clone() })
    }

    /// The starts beside the linear start and its turns: the other minima of Eq. 10, or with
    /// the cover, the 24 rotations of the cube group applied to the linear start (its own
    /// among them).
    fn extra(&self) -> Vec<Matrix3<f64>> {
        match (self.cover, self.linear) {
            (true, Some(r_lin)) => cube_group().into_iter().map(|g| g * r_lin).collect(),
            _ => self.eq10.clone(),
        }
    }
}

/// [`Starts`] of [`solve_once`].
fn start_rotations(set: &PreparedSet, cfg: &OursConfig, from: Option<&Isometry3<f64>>) -> Result<Starts, OursError> {
    let t0 = match from {
        Some(p) => p.translation.vector,
        None => linear_translation(set).map_err(|e| match e {
            PaperError::ViewsCollinear { ratio } => OursError::ViewsCollinear { ratio },
            PaperError::LinesFormOnePencil { ratio } => OursError::LinesFormOnePencil { ratio },
            _ => OursError::Singular,
        })?,
    };
    // The linear start: Kronecker rotation (Eq. 8-9) polished by Eq. 10 (cheap, 4 parameters);
    // per-orientation directions when Eq. 8 is rank-deficient.
    let linear = if from.is_some() {
        None
    } else {
        match kronecker_rotation(set) {
            Ok(r) => {
                let (q, _, _) = refine_quaternion(set, &wxyz(&UnitQuaternion::from_rotation_matrix(&r)));
                Some(q.to_rotation_matrix().into_inner())
            }
            Err(_) => grouped_rotation(set, &t0),
        }
    };
    let mut starts: Vec<Matrix3<f64>> = Vec::with_capacity(2);
    if let Some(p) = from {
        starts.push(p.rotation.to_rotation_matrix().into_inner());
    } else if let Some(q) = cfg.initial_quaternion {
        let q = nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]);
        if !(q.norm() > 0.0 && q.coords.iter().all(|v| v.is_finite())) {
            return Err(OursError::RotationUnobservable { detail: "initial quaternion is zero or not finite" });
        }
        starts.push(UnitQuaternion::from_quaternion(q).to_rotation_matrix().into_inner());
    }
    // The other minima of Eq. 10 (cheap: four parameters): polished from the 24 rotations of
    // the cube group applied to the linear start, kept when distinct, by increasing cost; the
    // linear start alone can sit in the wrong basin when the tool's directions span a narrow
    // cone.
    let mut extra: Vec<Matrix3<f64>> = Vec::new();
    if let Some(r_lin) = &linear {
        let mut minima: Vec<(f64, Matrix3<f64>)> = Vec::new();
        let sym = eq10_symmetric(set);
        for g in cube_group() {
            let (q, cost, _) = refine_quaternion_sym(&sym, &wxyz(&UnitQuaternion::from_matrix(&(g * r_lin))));
            let r = q.to_rotation_matrix().into_inner();
            let seen =
                |m: &Matrix3<f64>| Rotation3::from_matrix_unchecked(m.transpose() * r).angle() < DISTINCT_SOLUTION_RAD;
            if cost.is_finite() && !seen(r_lin) && !minima.iter().any(|(_, m)| seen(m)) {
                minima.push((cost, r));
            }
        }
        minima.sort_by(|a, b| a.0.total_cmp(&b.0));
        extra = minima.into_iter().take(MAX_EXTRA_STARTS).map(|(_, r)| r).collect();
    }
    match linear {
        Some(r) => starts.push(r),
        None if starts.is_empty() => {
            return Err(OursError::RotationUnobservable {
                detail: "no two tool orientations each seen from two views",
            });
        }
        None => {}
    }
    Ok(Starts { t0, starts, eq10: extra, linear, cover: false })
}

/// [`solve_once`] from its [`Starts`].
fn solve_from(
    set: &PreparedSet,
    cfg: &OursConfig,
    from: Option<&Isometry3<f64>>,
    st: &Starts,
) -> Result<OursResult, OursError> {
    let Starts { t0, starts, .. } = st;
    let extra = st.extra();
    let t0 = *t0;
    // Each start and its 180° turns about the line of sight to robot 2's RCM and about the
    // three axes of the mean tool direction's frame (the tool axis, its component across the
    // line of sight, their normal): a line cannot tell the tool's direction from its opposite,
    // so a narrow cone of tool directions leaves these turns nearly unobservable from lines.
    let mean_c = set.obs.iter().map(|o| o.o_ec).sum::<Vector3<f64>>() / set.obs.len() as f64;
    let sight = (t0 - mean_c).try_normalize(1e-12).unwrap_or_else(Vector3::z);
    let mean_m = set.obs.iter().map(|o| o.m_t).sum::<Vector3<f64>>() / set.obs.len() as f64;
    let turns = |r0: &Matrix3<f64>| -> Vec<Matrix3<f64>> {
        let a = (r0 * mean_m).try_normalize(1e-12).unwrap_or_else(Vector3::z);
        let b = (sight - a * a.dot(&sight)).try_normalize(1e-9).unwrap_or_else(|| a.cross(&Vector3::x()).normalize());
        let c = a.cross(&b);
        let mut v = vec![*r0];
        for axis in [sight, a, b, c] {
            let flip =
                Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), core::f64::consts::PI).into_inner();
            v.push(flip * r0);
        }
        v
    };
    // Whitening is held fixed while candidates are refined (the same weights for all); it is
    // refreshed once at each candidate's solution for a second pass.
    // With tool lines through points away from `{t}`'s origin, each start's translation is
    // Eq. 5 given its rotation (with every point at the origin it is `t0` itself).
    // With the shaft-position term, from the observed shaft ends when there are enough of
    // them ([`translation_from_shaft_ends`]: a point fixes two directions, a line one).
    let with_ends = cfg.noise.is_some() && cfg.shaft_position && from.is_none();
    let t_of = |r0: &Matrix3<f64>| {
        let ends = if with_ends { translation_from_shaft_ends(set, r0) } else { None };
        match ends {
            Some(t) => t,
            None if set.offset_points && from.is_none() => translation_given_rotation(set, r0).unwrap_or(t0),
            None => t0,
        }
    };
    let r_w = *starts.last().unwrap_or(&Matrix3::identity());
    let w0 = whitening(set, cfg, &r_w, &t_of(&r_w));
    // Refined in turn; a candidate that enters the basin of one refined before it is merged
    // into it (`Refined::merged`), and merged candidates share their target's later passes.
    let mut firsts: Vec<Refined> = Vec::new();
    let mut done: Vec<(Matrix3<f64>, Vector3<f64>)> = Vec::new();
    let mut done_at: Vec<usize> = Vec::new();
    // With the shaft-position terms, the lines' own solution is one more start (pose and
    // translation as the lines put them): where the shaft terms are sharp (little kinematic
    // noise) and the shaft-end starts are thrown off (wrong lines), the lines find the basin.
    let lines_start: Option<(Matrix3<f64>, Vector3<f64>)> = if with_ends {
        let lines_cfg = OursConfig { shaft_position: false, ..*cfg };
        // The usual starts (they do not depend on the shaft-position terms), also in a search
        // from the cover ([`OursConfig::cover_search_scale`]): searching the cover a second
        // time for the lines' own solution cost 1.3-1.4 times the refinements and, on the tuning
        // geometries 9060-9099 (metres, σ = 0.02), answered fewer trials (523 against 538 of
        // 1 200) with the same guarded mirrors (docs/calibration.md, session 30).
        let usual = Starts { cover: false, ..st.clone() };
        let pose = match solve_from(set, &lines_cfg, None, &usual) {
            Ok(x) => Some(x.pose),
            Err(OursError::ShaftsNotExplained { pose, .. }) => Some(*pose),
            Err(OursError::Ambiguous { best, .. }) => Some(best.pose),
            Err(_) => None,
        };
        pose.map(|p| (p.rotation.to_rotation_matrix().into_inner(), p.translation.vector))
    } else {
        None
    };
    let pairs = starts
        .iter()
        .flat_map(|r0| if from.is_some() { vec![*r0] } else { turns(r0) })
        .chain(extra.iter().copied())
        .map(|r0| (r0, t_of(&r0)))
        .chain(lines_start);
    for (r0, t0s) in pairs {
        let x = refine(set, cfg, w0.clone(), r0, t0s, &done);
        match x.merged {
            Some(j) => firsts.push(Refined {
                iterations: x.iterations,
                merged: Some(done_at[j]),
                ..firsts[done_at[j]].clone()
            }),
            None => {
                done.push((x.r, x.t));
                done_at.push(firsts.len());
                firsts.push(x);
            }
        }
    }
    let finite = |x: &Refined| x.t.iter().chain(x.r.iter()).all(|v| v.is_finite());
    // Each distinct pose's likelihood parts, computed once ([`NllParts`]); none when refining
    // from a given pose (one candidate: nothing to compare).
    let parts_of =
        |x: &Refined| -> Option<NllParts> { (from.is_none() && finite(x)).then(|| nll_parts(set, cfg, &x.r, &x.t)) };
    let nll_at = |p: &Option<NllParts>, x: &Refined, s: f64| match p {
        Some(p) if s.is_finite() => p.nll(cfg, s),
        None if from.is_some() && finite(x) => 0.0,
        _ => f64::INFINITY,
    };
    let (candidates, parts): (Vec<Refined>, Vec<Option<NllParts>>) = if cfg.noise.is_none() {
        let parts = firsts.iter().map(|x| if x.merged.is_some() { None } else { parts_of(x) }).collect();
        (firsts, parts)
    } else {
        // A second pass with the whitening refreshed at each candidate's solution, for the
        // candidates within [`SECOND_PASS_MARGIN_NATS`] of the best after the first pass (the
        // others keep their first-pass pose and are compared as they are).
        let s0 = firsts.iter().filter(|x| finite(x)).map(|x| x.scale).fold(f64::INFINITY, f64::min);
        let parts0: Vec<Option<NllParts>> =
            firsts.iter().map(|x| if x.merged.is_some() { None } else { parts_of(x) }).collect();
        let nll0: Vec<f64> =
            firsts.iter().enumerate().map(|(i, x)| nll_at(&parts0[x.merged.unwrap_or(i)], x, s0)).collect();
        let best0 = nll0.iter().copied().fold(f64::INFINITY, f64::min);
        let mut seconds: Vec<Refined> = Vec::with_capacity(firsts.len());
        let mut parts: Vec<Option<NllParts>> = Vec::with_capacity(firsts.len());
        for (i, (first, c)) in firsts.into_iter().zip(nll0).enumerate() {
            if let Some(j) = first.merged {
                let iterations = first.iterations;
                seconds.push(Refined { iterations, merged: Some(j), ..seconds[j].clone() });
                parts.push(None);
                continue;
            }
            if c > best0 + SECOND_PASS_MARGIN_NATS {
                seconds.push(first);
                parts.push(parts0[i].clone());
                continue;
            }
            let second = Refined { whiten: w0.clone(), ..polish(set, cfg, first) };
            parts.push(parts_of(&second));
            seconds.push(second);
        }
        (seconds, parts)
    };
    // The standing mirrors (with the shaft-position terms): the most likely candidate (of those
    // that explain the shafts, if any) turned 180° about each of four axes ([`flips`]), each
    // refined in its own right. A line cannot tell the tool's direction from its opposite nor
    // its side of the camera; where every start went to one basin, the shaft terms can pull a
    // mirror in front of the camera far enough to explain the shafts (on the tuning
    // geometries: returned, 179° off, with exit 0), and the other basin must then be in the
    // comparison for the likelihood to decide, or to refuse. Each is polished ([`polish`])
    // whatever its first-pass likelihood: on the tuning geometries, polishing only those near
    // the best (as the starts are) refused 5 more of 200 trials at σ = 0.01 in metres.
    let (candidates, parts) = if with_ends {
        let (mut candidates, mut parts) = (candidates, parts);
        let s0 = candidates.iter().filter(|x| finite(x)).map(|x| x.scale).fold(f64::INFINITY, f64::min);
        let costs0: Vec<f64> =
            candidates.iter().enumerate().map(|(i, x)| nll_at(&parts[x.merged.unwrap_or(i)], x, s0)).collect();
        let order = |a: &usize, b: &usize| costs0[*a].total_cmp(&costs0[*b]);
        let finite_costs = (0..candidates.len()).filter(|i| costs0[*i].is_finite());
        let explaining = finite_costs.clone().filter(|i| {
            candidates[*i].merged.is_none() && explains_shafts(set, &pose_of(&candidates[*i].r, &candidates[*i].t))
        });
        if let Some(ib0) = explaining.min_by(order).or_else(|| finite_costs.min_by(order)) {
            let (rb, tb) = (candidates[ib0].r, candidates[ib0].t);
            // Independent of each other: refined concurrently ([`par`]), kept in turn order.
            let turned = par::map_each(&flips(set, &rb, &tb), |&(r_m, t_m)| {
                let t_m = translation_from_shaft_ends(set, &r_m).unwrap_or(t_m);
                let first = refine(set, cfg, w0.clone(), r_m, t_m, &[]);
                let m = Refined { whiten: w0.clone(), ..polish(set, cfg, first) };
                (parts_of(&m), m)
            });
            for (p, m) in turned {
                parts.push(p);
                candidates.push(m);
            }
        }
        (candidates, parts)
    } else {
        (candidates, parts)
    };
    // Candidates are compared by their likelihood on all observations, each with its own
    // residual covariance (the log-determinant keeps a pose from winning by inflating its
    // own predicted noise), at one common robust scale. Nothing depends on the scene's scale.
    let s_ref = candidates.iter().filter(|x| finite(x)).map(|x| x.scale).fold(f64::INFINITY, f64::min);
    if !s_ref.is_finite() {
        return Err(OursError::NoConvergence);
    }
    // Each distinct candidate that does not explain the shafts descends the likelihood it is
    // judged by ([`OursConfig::likelihood_descent`]); one that does is left where its
    // refinement ended (descending every candidate too left the millimetre errors as they
    // were, refused one more metre trial and cost more: docs/calibration.md, session 24).
    let (candidates, parts) = if cfg.likelihood_descent && cfg.noise.is_some() && from.is_none() {
        let (mut candidates, mut parts) = (candidates, parts);
        for i in 0..candidates.len() {
            if let Some(j) = candidates[i].merged {
                // A merged candidate shares its target's pose (`j < i`: already descended).
                candidates[i] = candidates[i].at_pose_of(&candidates[j]);
                continue;
            }
            let x = &candidates[i];
            if !finite(x) || explains_shafts(set, &pose_of(&x.r, &x.t)) {
                continue;
            }
            parts[i] = Some(descend_candidate(set, cfg, &mut candidates[i], s_ref));
        }
        (candidates, parts)
    } else {
        (candidates, parts)
    };
    let nll_of = |r: &Matrix3<f64>, t: &Vector3<f64>| candidate_nll(set, cfg, r, t, s_ref);
    let costs: Vec<f64> =
        candidates.iter().enumerate().map(|(i, x)| nll_at(&parts[x.merged.unwrap_or(i)], x, s_ref)).collect();
    // Only candidates that put the detected shafts where an instrument can be are
    // explanations of the data ([`explains_shafts`]); the others are left out of the choice
    // and of the ambiguity decision.
    // Once per distinct pose: a merged candidate shares its target's pose.
    let mut explains: Vec<bool> = Vec::with_capacity(candidates.len());
    for (i, x) in candidates.iter().enumerate() {
        let e = match x.merged {
            Some(j) if j < i => explains[j],
            _ => finite(x) && explains_shafts(set, &pose_of(&x.r, &x.t)),
        };
        explains.push(e);
    }
    let argmin = |c: &[f64], ok: &dyn Fn(usize) -> bool| {
        (0..c.len()).filter(|i| ok(*i) && c[*i].is_finite()).min_by(|a, b| c[*a].total_cmp(&c[*b]))
    };
    // With the shaft-position terms the likelihood itself weighs where the shafts are put:
    // the most likely candidate is the estimate, and when it does not explain the shafts the
    // data are refused rather than answered by a less likely candidate that does (which, on
    // the tuning geometries, was the mirror with exit 0). The lines alone cannot weigh it, so
    // there the candidates that do not explain the shafts are left out of the choice.
    let most_likely = argmin(&costs, &|_| true);
    let chosen = if with_ends { most_likely.filter(|i| explains[*i]) } else { argmin(&costs, &|i| explains[i]) };
    // Every basin judged at its descended likelihood ([`OursConfig::descend_every_basin`]):
    // the candidates that explain the shafts descend too (the others already did), and the
    // comparison below uses the descended poses and likelihoods; the winner keeps the
    // refinement's pose when the descent picks the refinement's own winner's basin.
    let (candidates, costs, explains, most_likely, chosen) =
        if cfg.descend_every_basin && cfg.likelihood_descent && with_ends {
            let mut desc = candidates.clone();
            let (mut costs_d, mut explains_d) = (costs.clone(), explains.clone());
            for i in 0..desc.len() {
                if let Some(j) = desc[i].merged {
                    // `j < i`: already descended.
                    desc[i] = desc[i].at_pose_of(&desc[j]);
                    (costs_d[i], explains_d[i]) = (costs_d[j], explains_d[j]);
                    continue;
                }
                if !explains[i] || !finite(&desc[i]) {
                    continue;
                }
                costs_d[i] = descend_candidate(set, cfg, &mut desc[i], s_ref).nll(cfg, s_ref);
                explains_d[i] = explains_shafts(set, &pose_of(&desc[i].r, &desc[i].t));
            }
            let most_likely_d = argmin(&costs_d, &|_| true);
            let chosen_d = most_likely_d.filter(|i| explains_d[*i]);
            if let (Some(a), Some(b)) = (chosen, chosen_d) {
                let angle = Rotation3::from_matrix_unchecked(candidates[a].r.transpose() * desc[b].r).angle();
                // Not more than the distinct-solution angle (NaN: the same rotation, rounded).
                if angle.is_nan() || angle <= DISTINCT_SOLUTION_RAD {
                    desc[b] = Refined { merged: desc[b].merged, ..candidates[a].clone() };
                }
            }
            (desc, costs_d, explains_d, most_likely_d, chosen_d)
        } else {
            (candidates, costs, explains, most_likely, chosen)
        };
    let Some(ib) = chosen else {
        let i = most_likely.ok_or(OursError::NoConvergence)?;
        let pose = pose_of(&candidates[i].r, &candidates[i].t);
        let x = shaft_explanation(set, &pose, SHAFT_MARGIN);
        return Err(OursError::ShaftsNotExplained {
            behind: x.behind,
            off_shaft: x.off_shaft,
            observations: x.observations,
            max_share: MAX_UNEXPLAINED_SHARE * 100.0,
            pose: Box::new(pose),
        });
    };
    let costs: Vec<f64> = costs.iter().zip(&explains).map(|(c, ok)| if *ok { *c } else { f64::INFINITY }).collect();
    let best = &candidates[ib];
    let c_best = costs[ib];
    let (alt_pose, c_alt) = if from.is_some() {
        (pose_of(&best.r, &best.t), c_best)
    } else {
        runner_up(set, cfg, &candidates, &costs, ib, &nll_of)
    };
    let llr = (c_alt - c_best).max(0.0);
    let best_pose = pose_of(&best.r, &best.t);
    // A runner-up that does not explain the shafts is no rival, however likely its lines.
    if from.is_none() && llr < cfg.min_log_likelihood_ratio && explains_shafts(set, &alt_pose) {
        return Err(ambiguous(cfg, (best_pose, c_best), (alt_pose, c_alt)));
    }
    // The winner's own whitening for its covariance.
    let best = &Refined { whiten: whitening(set, cfg, &best.r, &best.t), ..*best };
    // Covariance σ̂² (JᵀWJ)⁻¹ at the solution.
    let c = cfg.huber_k * best.scale;
    let mut h = Matrix6::zeros();
    let mut wsum = 0.0;
    let mut inliers = 0;
    let shaft_noise = cfg.noise.as_ref().filter(|_| cfg.shaft_position);
    // Each observation's line residuals, Jacobian and whitened norm, for the shaft terms below
    // (`best.whiten` is the whitening at the winner's pose).
    let mut lines = Vec::with_capacity(if shaft_noise.is_some() { set.obs.len() } else { 0 });
    for (o, w) in set.obs.iter().zip(&best.whiten) {
        let (res, jac) = residual_and_jacobian(set, o, &best.r, &best.t);
        let (e, j) = (w * res, w * jac);
        let n = e.norm();
        if shaft_noise.is_some() {
            lines.push((res, jac, n));
        }
        let wgt = if n <= c {
            inliers += 1;
            1.0
        } else {
            c / n
        };
        h += j.transpose() * j * wgt;
        wsum += wgt * n * n;
    }
    // The shaft-position terms' information (in the line residuals' units, as in [`refine`]).
    if let Some(noise) = shaft_noise {
        for (o, (res, jac, ln)) in set.obs.iter().zip(&lines) {
            let (_, es, js) = model_and_residuals_at(set, o, &best.r, &best.t, noise, true, Some((res, jac)));
            let ln = *ln;
            let lw = if ln <= c { 1.0 } else { c / ln };
            for (e, j) in es.iter().zip(&js) {
                if *e != 0.0 {
                    let n = (e * best.scale).abs();
                    let wgt = lw * if n <= c { 1.0 } else { c / n };
                    h += j * j.transpose() * (best.scale * best.scale * wgt);
                }
            }
        }
    }
    let dof = (2 * set.obs.len()).saturating_sub(6).max(1) as f64;
    let sigma2 = wsum / dof;
    let cov = h.try_inverse().ok_or(OursError::Singular)? * sigma2;
    if !cov.iter().all(|v| v.is_finite()) {
        return Err(OursError::Singular);
    }
    let pose = Isometry3::from_parts(Translation3::from(best.t), UnitQuaternion::from_matrix(&best.r));
    let mut residuals = residual_stats(set, &pose);
    residuals.inliers = inliers;
    Ok(OursResult {
        pose,
        covariance: cov,
        residuals,
        scale: best.scale,
        alternative: alt_pose,
        log_likelihood_ratio: llr,
        iterations: candidates.iter().map(|c| c.iterations).sum(),
        guard_kept: set.obs.len(),
        guard_from: None,
        selection: None,
        selection_refused: None,
        noise_scale: None,
        searched_on: set.obs.len(),
        cover_searched: false,
    })
}

#[cfg(test)]
mod tests {
    use super::{add_weighted_upper, gram_upper, mirror_upper};
    use crate::calib::residual::Jac6;
    use nalgebra::Matrix6;

    /// The upper-triangle Gauss-Newton sum, mirrored, is the full product's sum bit for bit.
    #[test]
    fn upper_triangle_gram_sum_is_the_full_sum_bit_for_bit() {
        // Deterministic, irregular values over several magnitudes and both signs.
        let mut x = 0.123_456_789_f64;
        let mut next = || {
            x = (x * 3.987_654_321 + 0.314_159).fract();
            (x - 0.5) * 10f64.powi(((x * 7.0) as i32) - 3)
        };
        let mut full = Matrix6::zeros();
        let mut upper = Matrix6::zeros();
        for _ in 0..200 {
            let j = Jac6::from_fn(|_, _| next());
            let wgt = next().abs().min(1.0);
            full += j.transpose() * j * wgt;
            let mut jtj = [0.0; 21];
            gram_upper(&mut jtj, &j);
            add_weighted_upper(&mut upper, &jtj, wgt);
        }
        mirror_upper(&mut upper);
        for (a, b) in full.iter().zip(upper.iter()) {
            assert_eq!(a.to_bits(), b.to_bits(), "{a} vs {b}");
        }
        assert!(full.iter().any(|v| *v != 0.0));
    }
}
