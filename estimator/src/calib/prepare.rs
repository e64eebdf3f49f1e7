//! From observations to the quantities both pipelines use, plus the degenerate-data checks
//! that do not depend on the solution (robot 1 in too few views, robot 2 in too few
//! orientations). The check that needs the geometry (views collinear with the line from
//! robot 2's RCM to the camera) is made by the translation step, see
//! [`super::paper::linear_translation`].

use std::vec::Vec;

use nalgebra::{Isometry3, Matrix3, Matrix6, Vector2, Vector3};

use super::camera::{IntrinsicsError, LineError, plane_normal};
use super::rcm_arms::{ecm_frames, psm_axis, psm_frames};
use super::{Observation, Setup};

/// Camera centres closer than this (metres) are the same view of robot 1.
pub const SAME_VIEW_M: f64 = 1e-6;
/// The observed lines form one pencil (all through one image point, possibly at infinity:
/// identical, concurrent or parallel lines) when the smallest eigenvalue of `Σ n_c n_cᵀ`
/// (Eq. 1's unit normals in the camera frame) is below this fraction of the largest. Valid
/// protocol data sit above 0.05 at every noise level simulated, pencils below 1e-8.
pub const PENCIL_TOLERANCE: f64 = 1e-4;
/// Tool directions closer than this (radians) are the same orientation of robot 2.
pub const SAME_ORIENTATION_RAD: f64 = 1e-6;

/// One observation, prepared.
#[derive(Clone, Copy, Debug)]
pub struct Prepared {
    /// Camera orientation in `{e}` (`e_cR(θ1)`).
    pub r_ec: Matrix3<f64>,
    /// Optical centre in `{e}`, metres (`eO_c(θ1)`).
    pub o_ec: Vector3<f64>,
    /// Robot 1's end-effector frame `F4(θ1)` in `{e}`, metres.
    pub ecm_tip: Isometry3<f64>,
    /// Unit plane normal (Eq. 1) in the camera frame.
    pub n_c: Vector3<f64>,
    /// The same normal in `{e}`: `e_cR n_c`.
    pub n_e: Vector3<f64>,
    /// Unit tool axis `m(θ2)` in `{t}`.
    pub m_t: Vector3<f64>,
    /// Robot 2's frame 2 `F2(θ2)` in `{t}` (rotation only; its origin is the RCM, or the
    /// line's point [`Prepared::p_t`]).
    pub psm_f2: Isometry3<f64>,
    /// The known point of the tool's line in `{t}`, metres (zero for an RCM arm:
    /// [`super::Observation::tool_point_m`]).
    pub p_t: Vector3<f64>,
    /// Distance from the line's point to the tool tip along `m_t`, metres (robot 2's
    /// insertion for an RCM arm).
    pub insertion_m: f64,
    /// Where along the tool the camera can see the instrument, `[from, to]` metres from
    /// [`Prepared::p_t`] toward the tip ([`super::ShaftExtent`]: `[−before_point_m, |L| +
    /// beyond_tip_m]`).
    pub visible_m: [f64; 2],
    /// The two line points as ideal (undistorted) pixels.
    pub px: [Vector2<f64>; 2],
    /// Per line point: true when it is an end of the shaft (the tip or robot 2's RCM), i.e.
    /// the dataset says its points are the visible shaft's ends
    /// ([`super::SelectionRule::ends_are_shaft_ends`]) and this one is more than
    /// [`super::SHAFT_END_BORDER_PX`] inside the margin-shrunk image.
    pub shaft_end: [bool; 2],
    /// `Ad(T_f_eye⁻¹)` of the eye that saw this observation (6×6, `(ρ, φ)` order): maps a
    /// right perturbation of robot 1's end effector into that eye's frame.
    pub eye_inv_adjoint: Matrix6<f64>,
    /// Each line point's ray direction in the camera frame (unit depth, `K⁻¹ [u, 1]ᵀ`) and
    /// that direction normalised: fixed by [`Prepared::px`] (computed once here for the
    /// shaft-position terms, [`super::shaft_position`]).
    pub(crate) rays: [(Vector3<f64>, Vector3<f64>); 2],
    /// [`Prepared::psm_f2`]'s rotation as a matrix (computed once here for the noise
    /// Jacobians, [`super::residual::noise_jacobian`], [`super::selection::tip_projection`]).
    pub(crate) r2: Matrix3<f64>,
}

/// All observations, prepared, with the camera model.
#[derive(Clone, Debug)]
pub struct PreparedSet {
    /// Prepared observations, in input order.
    pub obs: Vec<Prepared>,
    /// `K⁻ᵀ`: maps a plane normal in the camera frame to a homogeneous pixel line.
    pub k_inv_t: Matrix3<f64>,
    /// `T_f_c`, metres.
    pub hand_eye: Isometry3<f64>,
    /// The camera intrinsics (pixels; image size for the border guard).
    pub intrinsics: super::Intrinsics,
    /// [`Setup::selection`](super::Setup::selection): the detector's acceptance rule.
    pub selection: super::SelectionRule,
    /// The detector's precision of a line's end along the line, pixels
    /// ([`super::ShaftExtent::end_sd_px`]).
    pub end_sd_px: f64,
    /// Smallest over largest eigenvalue of `Σ n_c n_cᵀ` (Eq. 1's unit normals in the camera
    /// frame): below [`PENCIL_TOLERANCE`] the lines form one pencil (checked by Eq. 5's step,
    /// [`super::paper::linear_translation`]).
    pub pencil_ratio: f64,
    /// Distinct views of robot 1 (distinct optical centres), counted up to the first 2.
    pub views: usize,
    /// Distinct orientations of robot 2's tool, counted up to the first 3.
    pub orientations: usize,
    /// True when some observation's tool line has its point away from the origin of `{t}`
    /// (an arm without a mechanical RCM): Eq. 5 then needs the rotation first
    /// ([`super::paper::translation_given_rotation`]).
    pub offset_points: bool,
}

/// Why observations cannot be prepared.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PrepareError {
    /// No observation at all.
    #[error("no observations")]
    Empty,
    /// The intrinsics are unusable.
    #[error("camera intrinsics: {0}")]
    Intrinsics(#[from] IntrinsicsError),
    /// The hand-eye transform (or the right eye's transform) is not finite.
    #[error("hand-eye transform is not finite")]
    HandEye,
    /// An observation from the right eye, but the setup has no right eye.
    #[error("observation {index}: from the right eye, but the setup has no right eye (stereo transform)")]
    NoRightEye {
        /// Observation index (0-based).
        index: usize,
    },
    /// A joint value is NaN or infinite.
    #[error("observation {index}: joint values must be finite")]
    Joint {
        /// Observation index (0-based).
        index: usize,
    },
    /// The observed line is unusable.
    #[error("observation {index}: line: {source}")]
    Line {
        /// Observation index (0-based).
        index: usize,
        /// What is wrong with the line.
        source: LineError,
    },
    /// The shaft extent's lengths are negative or not finite.
    #[error("shaft extent: beyond_tip_m, before_point_m and end_sd_px must be finite and ≥ 0 (got {0:?})")]
    ShaftExtent(super::ShaftExtent),
    /// The selection rule's lengths are negative or not finite.
    #[error("selection rule: min_visible_shaft_px and border_margin_px must be finite and ≥ 0 (got {0:?})")]
    Selection(super::SelectionRule),
    /// Degenerate: robot 1 (the endoscope) was seen from fewer than two views, so the depth
    /// of robot 2's RCM cannot be recovered.
    #[error(
        "degenerate data: robot 1 (endoscope) in fewer than two views ({views} distinct optical centre(s)); move the endoscope to at least two positions"
    )]
    TooFewViews {
        /// Distinct optical centres found.
        views: usize,
    },
    /// Degenerate: robot 2 (the tool) was seen in fewer than three orientations, so the
    /// rotation cannot be recovered.
    #[error(
        "degenerate data: robot 2 (tool) in fewer than three orientations ({orientations} distinct tool direction(s)); need at least three"
    )]
    TooFewToolOrientations {
        /// Distinct tool directions found.
        orientations: usize,
    },
}

fn finite_iso(t: &Isometry3<f64>) -> bool {
    t.translation.vector.iter().all(|v| v.is_finite()) && t.rotation.coords.iter().all(|v| v.is_finite())
}

/// Prepares observations: camera poses from robot 1's joints and the hand-eye transform,
/// plane normals (Eq. 1) from undistorted line points, tool axes from robot 2's joints; then
/// checks the two counts the method needs (≥ 2 views of robot 1, ≥ 3 tool orientations).
pub fn prepare(setup: &Setup, observations: &[Observation]) -> Result<PreparedSet, PrepareError> {
    let set = prepare_unchecked(setup, observations)?;
    if set.views < 2 {
        return Err(PrepareError::TooFewViews { views: set.views });
    }
    if set.orientations < 3 {
        return Err(PrepareError::TooFewToolOrientations { orientations: set.orientations });
    }
    Ok(set)
}

/// [`prepare`] without the two counting checks (views, orientations; still counted in the
/// set): for scoring single observations against a known pose (the live collector's
/// information and drift checks). Input checks as [`prepare`].
pub fn prepare_unchecked(setup: &Setup, observations: &[Observation]) -> Result<PreparedSet, PrepareError> {
    if observations.is_empty() {
        return Err(PrepareError::Empty);
    }
    setup.intrinsics.validate()?;
    if !finite_iso(&setup.hand_eye) || setup.right_eye.is_some_and(|r| !finite_iso(&r)) {
        return Err(PrepareError::HandEye);
    }
    let left_ad = inverse_adjoint(&setup.hand_eye);
    let right = setup.hand_eye_of(super::Eye::Right).map(|x| (x, inverse_adjoint(&x)));
    if !setup.selection.is_valid() {
        return Err(PrepareError::Selection(setup.selection));
    }
    if !setup.shaft_extent.is_valid() {
        return Err(PrepareError::ShaftExtent(setup.shaft_extent));
    }
    let k_inv = setup.intrinsics.k_inv();
    let k_inv_t = k_inv.transpose();
    let mut obs = Vec::with_capacity(observations.len());
    for (index, o) in observations.iter().enumerate() {
        if !o.ecm_joints.iter().chain(o.psm_joints.iter()).chain(o.tool_point_m.iter()).all(|v| v.is_finite()) {
            return Err(PrepareError::Joint { index });
        }
        let px = [
            setup.intrinsics.undistort_px(&Vector2::from(o.line_px[0])),
            setup.intrinsics.undistort_px(&Vector2::from(o.line_px[1])),
        ];
        let n_c = plane_normal(&k_inv, &px[0], &px[1]).map_err(|source| PrepareError::Line { index, source })?;
        let (hand_eye, eye_inv_adjoint) = match o.eye {
            super::Eye::Left => (setup.hand_eye, left_ad),
            super::Eye::Right => right.ok_or(PrepareError::NoRightEye { index })?,
        };
        let tip = ecm_frames(&o.ecm_joints)[3];
        let cam = tip * hand_eye;
        let r_ec = cam.rotation.to_rotation_matrix().into_inner();
        let f2 = psm_frames(&o.psm_joints)[1];
        let (w, h) = (setup.intrinsics.width as f64, setup.intrinsics.height as f64);
        let inset = setup.selection.border_margin_px + super::SHAFT_END_BORDER_PX;
        let shaft_end = o.line_px.map(|[x, y]| {
            setup.selection.ends_are_shaft_ends
                && x >= inset
                && y >= inset
                && x <= w - 1.0 - inset
                && y <= h - 1.0 - inset
        });
        obs.push(Prepared {
            shaft_end,
            r_ec,
            o_ec: cam.translation.vector,
            ecm_tip: tip,
            n_c,
            n_e: r_ec * n_c,
            m_t: psm_axis(&o.psm_joints),
            psm_f2: f2,
            p_t: Vector3::from(o.tool_point_m),
            insertion_m: o.psm_joints[2],
            visible_m: [-setup.shaft_extent.before_point_m, o.psm_joints[2].abs() + setup.shaft_extent.beyond_tip_m],
            px,
            eye_inv_adjoint,
            rays: px.map(|u| {
                let v = k_inv_t.tr_mul(&Vector3::new(u.x, u.y, 1.0));
                (v, v.normalize())
            }),
            r2: f2.rotation.to_rotation_matrix().into_inner(),
        });
    }
    let (views, orientations, pencil_ratio) = counts(&obs);
    Ok(PreparedSet {
        pencil_ratio,
        obs,
        k_inv_t,
        hand_eye: setup.hand_eye,
        intrinsics: setup.intrinsics,
        selection: setup.selection,
        end_sd_px: setup.shaft_extent.end_sd_px,
        views,
        orientations,
        offset_points: observations.iter().any(|o| o.tool_point_m != [0.0; 3]),
    })
}

/// `Ad(T⁻¹)` of a rigid transform, `(ρ, φ)` order: `[[R', [t']×R'], [0, R']]` with
/// `T⁻¹ = (R', t')`.
pub fn inverse_adjoint(t: &Isometry3<f64>) -> Matrix6<f64> {
    let xi = t.inverse();
    let rx = xi.rotation.to_rotation_matrix().into_inner();
    let mut ad = Matrix6::zeros();
    ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&rx);
    ad.fixed_view_mut::<3, 3>(0, 3).copy_from(&(super::rcm_arms::skew(&xi.translation.vector) * rx));
    ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&rx);
    ad
}

impl PreparedSet {
    /// This set with only `obs` (some of its observations), the solution-free checks' figures
    /// ([`Self::views`], [`Self::orientations`], [`Self::pencil_ratio`]) counted on them.
    pub fn with_observations(&self, obs: Vec<Prepared>) -> PreparedSet {
        let (views, orientations, pencil_ratio) = counts(&obs);
        PreparedSet { obs, views, orientations, pencil_ratio, ..*self }
    }
}

/// Distinct views of robot 1 (up to 2), distinct tool orientations (up to 3) and the pencil
/// ratio of the observations' plane normals ([`PreparedSet`]'s fields of the same names).
fn counts(obs: &[Prepared]) -> (usize, usize, f64) {
    let views = count_distinct(obs.iter().map(|p| p.o_ec), 2, |a, b| (a - b).norm() > SAME_VIEW_M);
    let orientations =
        count_distinct(obs.iter().map(|p| p.m_t), 3, |a, b| a.cross(b).norm() > SAME_ORIENTATION_RAD || a.dot(b) < 0.0);
    let normals = obs.iter().fold(Matrix3::zeros(), |acc, p| acc + p.n_c * p.n_c.transpose());
    let eig = normals.symmetric_eigen();
    let (lmin, lmax) = (eig.eigenvalues.min(), eig.eigenvalues.max());
    let pencil_ratio = if lmax > 0.0 { lmin.max(0.0) / lmax } else { 0.0 };
    (views, orientations, pencil_ratio)
}

/// Counts distinct items (pairwise `differ`), stopping at `enough`.
fn count_distinct<I: Iterator<Item = Vector3<f64>>>(
    items: I,
    enough: usize,
    differ: impl Fn(&Vector3<f64>, &Vector3<f64>) -> bool,
) -> usize {
    let mut found: Vec<Vector3<f64>> = Vec::with_capacity(enough);
    for v in items {
        if found.iter().all(|f| differ(f, &v)) {
            found.push(v);
            if found.len() >= enough {
                break;
            }
        }
    }
    found.len()
}
