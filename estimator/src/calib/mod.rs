//! # Dual RCM-arm calibration from tool lines and encoders (offline, needs `std`)
//!
//! Registers an endoscope-holding RCM arm (robot 1, ECM-like) to a tool-holding RCM arm
//! (robot 2, PSM-like) from the image line of the tool shaft and the joint readings of both
//! arms only (Wang et al., "Vision-Based Calibration of Dual RCM-Based Robot Arms in
//! Human-Robot Collaborative Minimally Invasive Surgery", IEEE Robotics and Automation
//! Letters, 2017).
//!
//! ## Frames and units (see also `docs/calibration.md`)
//! - `{e}`: robot 1's remote centre of motion (RCM). `{t}`: robot 2's RCM. `{f}`: robot 1's
//!   end effector (endoscope tip). `{c}`: camera (optical centre; z forward, x right, y down).
//! - The unknown is `T_e_t` ([`nalgebra::Isometry3`]): maps `{t}` coordinates to `{e}`
//!   coordinates, `p_e = R p_t + t`; `t` is the paper's `eO_t` in metres, `R` its `e_tR`.
//! - Lengths in metres, angles in radians, image coordinates in pixels (origin at the centre of
//!   the top-left pixel, u right, v down, OpenCV convention).
//!
//! ## Layers
//! - [`rcm_arms`]: RCM-arm forward kinematics (ECM: yaw, pitch, insertion, roll; PSM: yaw,
//!   pitch, insertion) and the SE(3) exponential used for noise.
//! - [`camera`]: pinhole intrinsics with plumb-bob distortion, the image line → plane normal
//!   step (Eq. 1) and the projection of a 3-D line.
//! - [`prepare`]: one [`Observation`] → camera pose, plane normal and tool direction, and the
//!   degenerate-data checks shared by both pipelines.
//! - [`residual`]: the residual model (image distances in pixels, their Jacobians and
//!   covariance, the damped step), shared by what follows.
//! - [`paper`]: the paper's pipeline, faithful (Eq. 5, Eq. 7-9, Eq. 10).
//! - [`selection`]: the detector's acceptance rule ([`SelectionRule`]: visible shaft length,
//!   border margin, tip in view or not) as a likelihood, and our pipeline's final,
//!   selection-aware stage.
//! - [`shaft_position`]: where along the tool the shaft was seen (each line point on the
//!   physical shaft, in front of the camera, the tip at an observed shaft end, with the
//!   selection's tip model) as likelihood terms, and the translation from the shaft ends.
//! - [`ours`]: joint robust refinement on the image distance in pixels and the shaft
//!   positions, covariance, candidates compared by their likelihood with a typed refusal when
//!   the runner-up cannot be ruled out; ends with the selection stage (given the
//!   shaft-position terms as extra terms, so the stage does not import them).
//! - [`crb`]: the Cramér-Rao bounds for a geometry and a kinematic noise model, without and
//!   with the selection.
//!
//! The order is the import order: prepare → residual → paper / selection → shaft_position →
//! ours, with crb on residual and selection; no module imports one listed after it.

pub mod camera;
pub mod crb;
pub mod hausman;
pub mod ours;
pub mod paper;
mod par;
pub mod prepare;
pub mod rcm_arms;
pub mod residual;
pub mod selection;
pub mod shaft_position;
pub mod sigma_point;

use nalgebra::{Isometry3, SMatrix, Vector3};
use serde::{Deserialize, Serialize};

pub use camera::Intrinsics;

/// One calibration observation: robot 1's joints, the tool's line in the tool arm's frame
/// `{t}`, and the tool shaft's line in the image.
///
/// **The tool's line** is "a line through a known point with a known direction in `{t}`"
/// (issue 19), so that both arm kinds fit:
/// - an RCM arm (the paper's PSM): the point is the RCM, the origin of `{t}`
///   (`tool_point_m = [0, 0, 0]`, the default) and the direction comes from its joints
///   (`psm_joints`, [`rcm_arms::psm_axis`]);
/// - an arm without a mechanical RCM (comanip's Achilles-type arm): `{t}` is the arm's base,
///   the point is the fulcrum fulcrumd publishes (the trocar, on the instrument axis) and the
///   direction the instrument axis; [`Observation::from_tool_line`] writes that direction as
///   the equivalent RCM joints (yaw, pitch) and the tip's distance from the point as the
///   "insertion".
///
/// The image side is shaped so that a line detector can feed it: any two distinct points of
/// the detected centreline (typically the segment's end points) in pixels, as measured
/// (distorted) image coordinates; [`Intrinsics::undistort_px`] is applied by the pipelines.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Observation {
    /// Robot 1 (ECM-like): `[yaw rad, pitch rad, insertion m, roll rad]`.
    pub ecm_joints: [f64; 4],
    /// Robot 2's line as RCM joints about [`Observation::tool_point_m`]:
    /// `[yaw rad, pitch rad, insertion m]`; the direction is [`rcm_arms::psm_axis`], the tool
    /// tip lies `insertion` metres from the point along it.
    pub psm_joints: [f64; 3],
    /// The known point of the tool's line in `{t}`, metres: robot 2's RCM (the origin, the
    /// default) for an RCM arm, the fulcrum for an arm without a mechanical RCM.
    #[serde(default, skip_serializing_if = "is_origin")]
    pub tool_point_m: [f64; 3],
    /// Two distinct points of the tool's centreline in the image, pixels `[[u, v], [u, v]]`.
    pub line_px: [[f64; 2]; 2],
    /// Which eye of a stereo endoscope saw the line (default: the left eye, the camera frame
    /// `{c}` of [`Setup::hand_eye`]; the right eye needs [`Setup::right_eye`]).
    #[serde(default)]
    pub eye: Eye,
}

fn is_origin(p: &[f64; 3]) -> bool {
    *p == [0.0; 3]
}

impl Observation {
    /// An RCM arm's observation: the tool's line through robot 2's RCM (the origin of `{t}`).
    pub fn rcm(ecm_joints: [f64; 4], psm_joints: [f64; 3], line_px: [[f64; 2]; 2], eye: Eye) -> Self {
        Self { ecm_joints, psm_joints, tool_point_m: [0.0; 3], line_px, eye }
    }

    /// An observation whose tool line is given directly in `{t}`: through `point_m` (metres)
    /// along `axis` (toward the tip; normalised here), the tip `tip_m` metres from the point.
    /// `None` when the axis is zero or not finite. The direction is stored as the RCM joints
    /// `yaw = atan2(a_x, a_z)`, `pitch = −asin(a_y)` ([`rcm_arms::psm_axis`] inverted).
    pub fn from_tool_line(
        ecm_joints: [f64; 4],
        point_m: [f64; 3],
        axis: [f64; 3],
        tip_m: f64,
        line_px: [[f64; 2]; 2],
        eye: Eye,
    ) -> Option<Self> {
        let a = Vector3::from(axis);
        if !a.iter().all(|v| v.is_finite()) {
            return None;
        }
        let a = a.try_normalize(1e-12)?;
        let psm_joints = [a.x.atan2(a.z), -a.y.clamp(-1.0, 1.0).asin(), tip_m];
        Some(Self { ecm_joints, psm_joints, tool_point_m: point_m, line_px, eye })
    }
}

/// An eye of a stereo endoscope. The left eye is the camera frame `{c}`; both eyes share the
/// intrinsics of [`Setup::intrinsics`] (a rectified or identical pair).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Eye {
    /// The left eye, `{c}`.
    #[default]
    Left,
    /// The right eye, at [`Setup::right_eye`] in `{c}`.
    Right,
}

/// Everything fixed across observations: camera intrinsics and robot 1's hand-eye transform.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Setup {
    /// Pinhole intrinsics (pixels) and distortion.
    pub intrinsics: Intrinsics,
    /// `T_f_c`: the camera frame in robot 1's end-effector frame (metres); the paper's `X`.
    pub hand_eye: Isometry3<f64>,
    /// `T_c_r`: the right eye's camera frame in the left eye's `{c}` (metres; for a parallel
    /// stereo endoscope a translation of the baseline along `x`). `None`: a single camera
    /// (observations from the right eye are refused).
    pub right_eye: Option<Isometry3<f64>>,
    /// How the line detector selected the observations (its acceptance rule); our pipeline's
    /// selection-aware stage models exactly this rule ([`selection`]).
    pub selection: SelectionRule,
    /// Where along the instrument the camera can see it ([`ShaftExtent`]; the default: from
    /// robot 2's RCM to the tool tip, as inside a patient).
    pub shaft_extent: ShaftExtent,
}

/// Where along the instrument a detected line may lie: the part of the tool line the camera
/// can see and a detector can report as shaft, relative to the line's known point (robot 2's
/// RCM or the fulcrum, `s = 0`) and the tool tip (`s = L`, the insertion). Our pipeline's
/// shaft-position terms ([`shaft_position`]) ask each observed line point to lie in
/// `[−before_point_m, L + beyond_tip_m]`.
///
/// Inside a patient the abdominal wall hides the shaft beyond the trocar (`before_point_m =
/// 0`) and the tip is the end of what a detector reports (`beyond_tip_m = 0`): the default.
/// A bench or a simulator without a wall lets the camera see the shaft outside the trocar,
/// and an instrument whose tip point is the jaws' pivot has jaws beyond it that a detector
/// may take for shaft. Too small a value makes the pipeline refuse or bias good data (a line
/// point where the model says no shaft can be); too large only gives up some information.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShaftExtent {
    /// How far past the tool tip, along the tool axis, the detector may report the instrument
    /// (jaws, a tool head), metres (≥ 0).
    #[serde(default)]
    pub beyond_tip_m: f64,
    /// How far back from the line's known point (robot 2's RCM, the fulcrum: away from the
    /// tip) the camera can see the shaft, metres (≥ 0; 0 when a wall hides it).
    #[serde(default)]
    pub before_point_m: f64,
    /// The detector's precision of a line's end along the line, pixels (standard deviation,
    /// ≥ 0): how far past the instrument's image a detected end may lie (blur, shadow, the
    /// contours' extent). Added to the pixel noise where the shaft-position terms place a line
    /// point along the tool; 0: the ends are as precise as the lines.
    #[serde(default)]
    pub end_sd_px: f64,
}

impl ShaftExtent {
    /// True when every value is finite and ≥ 0.
    pub fn is_valid(&self) -> bool {
        [self.beyond_tip_m, self.before_point_m, self.end_sd_px].iter().all(|v| v.is_finite() && *v >= 0.0)
    }
}

/// The line detector's acceptance rule: which shaft images become observations. Stated in
/// the dataset; our pipeline models it ([`selection`]). Pixels are ideal (undistorted) for
/// the model; the simulator applies it on measured pixels.
///
/// A line is recorded when the part of the tool shaft (from its tip back toward robot 2's
/// RCM) that is in front of the camera and at least `border_margin_px` inside the image is
/// at least `min_visible_shaft_px` long, and, when `require_tip_in_view`, starts at the tip
/// (the tip itself is in view). The default is the plain line detector's rule: enough
/// visible shaft, tip or not, no margin, no minimum length.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SelectionRule {
    /// Shortest visible shaft recorded, pixels (≥ 0).
    #[serde(default)]
    pub min_visible_shaft_px: f64,
    /// The shaft counts as visible only this far inside the image border, pixels (≥ 0).
    #[serde(default)]
    pub border_margin_px: f64,
    /// True: a line is recorded only when the tool tip is in view (inside the margin).
    #[serde(default)]
    pub require_tip_in_view: bool,
    /// True: the two line points are the ends of the visible shaft, so a point more than
    /// [`SHAFT_END_BORDER_PX`] inside the margin-shrunk image is where the shaft itself ends
    /// (the tool tip, or robot 2's RCM), as the simulation protocol records them; our pipeline
    /// then asks the pose to put the shaft's end there ([`shaft_position`]). False (the
    /// default, and older files): the points are only known to lie on the visible shaft.
    #[serde(default)]
    pub ends_are_shaft_ends: bool,
}

/// A line point within this distance (pixels) of the margin-shrunk image border is where the
/// image cuts the shaft, not one of its ends ([`SelectionRule::ends_are_shaft_ends`]).
pub const SHAFT_END_BORDER_PX: f64 = 2.0;

impl SelectionRule {
    /// The rule of the original protocol and of version-1 datasets' `min_shaft_px`: the tip in
    /// the image and at least `min_shaft_px` of shaft visible from it.
    pub fn tip_in_view(min_shaft_px: f64) -> Self {
        Self {
            min_visible_shaft_px: min_shaft_px,
            border_margin_px: 0.0,
            require_tip_in_view: true,
            ends_are_shaft_ends: false,
        }
    }

    /// True when both lengths are finite and ≥ 0.
    pub fn is_valid(&self) -> bool {
        [self.min_visible_shaft_px, self.border_margin_px].iter().all(|v| v.is_finite() && *v >= 0.0)
    }
}

impl Setup {
    /// `T_f_eye`: the frame of `eye` in robot 1's end effector (metres); `None` for the right
    /// eye of a single camera.
    pub fn hand_eye_of(&self, eye: Eye) -> Option<Isometry3<f64>> {
        match eye {
            Eye::Left => Some(self.hand_eye),
            Eye::Right => self.right_eye.map(|r| self.hand_eye * r),
        }
    }
}

/// The kinematic noise model of the simulation protocol (Sec. IV, Eq. 11), used to weight our
/// pipeline and to compute the Cramér-Rao bound.
///
/// Every perturbed frame `T` (the ECM end effector, PSM frames 2 and 3) is `T·exp(δ^)`,
/// `δ = (ρ, φ)`, `ρ ~ N(0, trans_m² I3)` metres, `φ ~ N(0, rot_rad² I3)` radians, independent
/// per frame and per observation; plus isotropic pixel noise on the line points.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct KinematicNoise {
    /// Standard deviation of each rotation component of δ, radians.
    pub rot_rad: f64,
    /// Standard deviation of each translation component of δ, metres.
    pub trans_m: f64,
    /// Standard deviation of each image coordinate of the line points, pixels.
    pub pixel_px: f64,
}

impl KinematicNoise {
    /// True when the arms' frames have noise (`rot_rad` or `trans_m` positive): the model says
    /// where the arms may put the tool, not only how the lines are measured.
    pub fn has_kinematic_terms(&self) -> bool {
        self.rot_rad > 0.0 || self.trans_m > 0.0
    }

    /// Every standard deviation multiplied by `k` (dimensionless, > 0): the same model at
    /// another noise level.
    pub fn scaled(&self, k: f64) -> Self {
        Self { rot_rad: self.rot_rad * k, trans_m: self.trans_m * k, pixel_px: self.pixel_px * k }
    }

    /// True when every standard deviation is finite and non-negative and at least one is
    /// positive (a usable noise model).
    pub fn is_valid(&self) -> bool {
        let all = [self.rot_rad, self.trans_m, self.pixel_px];
        all.iter().all(|v| v.is_finite() && *v >= 0.0) && all.iter().any(|v| *v > 0.0)
    }

    /// Variances of the 18 frame perturbations `(δ_ECM, δ_PSM2, δ_PSM3)`, each `(ρ, φ)`:
    /// `ρ` in m², `φ` in rad².
    pub fn perturbation_variances(&self) -> [f64; 18] {
        let mut v = [0.0; 18];
        for (c, x) in v.iter_mut().enumerate() {
            *x = if c % 6 < 3 { self.trans_m * self.trans_m } else { self.rot_rad * self.rot_rad };
        }
        v
    }

    /// Covariance (pixels²) of `R` image quantities whose sensitivity to the 18 frame
    /// perturbations is `g` (pixels per metre / radian), each with its own pixel noise:
    /// `g diag(σ²) gᵀ + σ_px² I`.
    pub fn propagate<const R: usize>(&self, g: &SMatrix<f64, R, 18>) -> SMatrix<f64, R, R> {
        let mut cov = SMatrix::<f64, R, R>::identity() * (self.pixel_px * self.pixel_px);
        // The upper triangle, then mirrored: each element the same sum of
        // `g[(a, c)] g[(b, c)] σ_c²` over `c`, in the same order, as the full outer products'.
        for (c, v) in self.perturbation_variances().iter().enumerate() {
            for b in 0..R {
                let gb = g[(b, c)];
                for a in 0..=b {
                    cov[(a, b)] += g[(a, c)] * gb * *v;
                }
            }
        }
        for b in 0..R {
            for a in 0..b {
                cov[(b, a)] = cov[(a, b)];
            }
        }
        cov
    }
}

/// Translation error `e_t = |t − t_GT| / |t_GT|` (dimensionless; ×100 for per cent) and
/// absolute translation error in metres, rotation error `e_R = |log(Rᵀ R_GT)|` in radians.
pub fn pose_errors(estimate: &Isometry3<f64>, truth: &Isometry3<f64>) -> PoseErrors {
    let dt: Vector3<f64> = estimate.translation.vector - truth.translation.vector;
    let norm = truth.translation.vector.norm();
    let rel = if norm > 0.0 { dt.norm() / norm } else { dt.norm() };
    let e_r = (estimate.rotation.inverse() * truth.rotation).angle();
    PoseErrors { translation_rel: rel, translation_m: dt.norm(), rotation_rad: e_r }
}

/// Errors of an estimated `T_e_t` against the ground truth.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseErrors {
    /// `|t − t_GT| / |t_GT|`, dimensionless.
    pub translation_rel: f64,
    /// `|t − t_GT|`, metres.
    pub translation_m: f64,
    /// `|log(Rᵀ R_GT)|`, radians.
    pub rotation_rad: f64,
}
