//! Where along the tool the shaft was seen: the information a line model throws away.
//!
//! An observed line's two end points are where the detector saw the shaft: between the tool
//! tip and robot 2's RCM (the trocar; the endoscope is inside the body and sees no shaft
//! beyond it), in front of the camera. The line model ([`super::residual`]) only asks that the
//! points lie on the projected axis; a pose that puts them on the axis's extension, hundreds
//! of millimetres beyond the tip, or on its part behind the camera, fits the lines as well.
//! With metre-level kinematic noise that is where the line model's optimum goes (the noise
//! swamps the lines' parallax), so the lines alone cannot calibrate.
//!
//! Per observation, [`shaft_position_residuals`] gives [`TERMS`] residuals (standard
//! deviations; half their square is the negative log-likelihood to first order):
//! - each line point's position along the tool ([`axis_seen_at`], standard deviation
//!   [`position_sd_m`]): zero while on the part of the instrument the camera can see
//!   ([`Prepared::visible_m`], from the setup's [`super::ShaftExtent`]: by default the
//!   physical shaft from the RCM to the tip), the excess beyond it; for a point
//!   that is an end of the shaft ([`Prepared::shaft_end`]: the dataset says its points are the
//!   visible shaft's ends and this one is not on the image border) the distance from the nearer
//!   end, unless the tip model below places it;
//! - each line point's depth where it meets the axis: zero in front of the camera;
//! - the tip at a shaft end ([`super::selection::tip_at_end`]): where the pose and the line
//!   residuals put the tip along the observed line (its conditional distribution given the
//!   line, from the joint first-order noise of line and tip) against the observed end point,
//!   in pixels. This is the term that places the tool: it accounts for the correlation of the
//!   tip with the line residuals, which the metric terms above do not.
//!
//! Our pipeline adds them to its objective ([`super::ours`]) and to its selection-aware stage
//! ([`stage_terms`], passed to [`super::selection::refine_selected_with`]);
//! [`translation_from_shaft_ends`] gives the refinement's translation start. Layer: above
//! [`super::selection`] (whose tip model it uses), below [`super::ours`].

use nalgebra::{Matrix3, Matrix6, SMatrix, Vector2, Vector3, Vector6};

use super::KinematicNoise;
use super::prepare::{Prepared, PreparedSet};
use super::rcm_arms::skew;
use super::residual::{Jac6, residual, residual_and_jacobian};
use super::selection::{
    NoiseAt, TipEndModel, TipPixel, tip_end_model, tip_end_model_and_pixel, tip_end_model_at, tip_px,
};

/// Where the tool axis is seen at an observed line point: for the ray through ideal pixel `u`
/// (camera frame, direction `K⁻¹ [u, 1]ᵀ`, unit depth) and the tool axis of pose `(R, t)`
/// (`T_e_t`), their closest approach: `(depth, s)`, the ray's depth there (metres, camera
/// frame; negative: behind the camera) and the axis point's position along the tool from the
/// line's known point (metres, `s = 0` at robot 2's RCM or [`Prepared::p_t`], `s =`
/// [`Prepared::insertion_m`] at the tip). `None` when the ray is parallel to the axis (within
/// 1e-12, relative) or a value is not finite.
pub fn axis_seen_at(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    u: &Vector2<f64>,
) -> Option<(f64, f64)> {
    let (v, p, d) = ray_and_axis(set, o, r, t, u);
    closest_approach(&v, &p, &d)
}

/// The ray direction `v` (camera frame, unit depth) through ideal pixel `u`, and the tool
/// axis's point `p` (metres) and direction `d` (unit) in the camera frame at pose `(R, t)`.
fn ray_and_axis(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    u: &Vector2<f64>,
) -> (Vector3<f64>, Vector3<f64>, Vector3<f64>) {
    let (p, d) = axis_in_camera(o, r, t);
    (ray(set, u), p, d)
}

/// The tool axis's point `p` (metres) and direction `d` (unit) in the camera frame at pose
/// `(R, t)`: [`ray_and_axis`]'s, which do not depend on the line point (computed once per
/// observation).
fn axis_in_camera(o: &Prepared, r: &Matrix3<f64>, t: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    (o.r_ec.tr_mul(&(r * o.p_t + t - o.o_ec)), o.r_ec.tr_mul(&(r * o.m_t)))
}

/// The ray direction (camera frame, unit depth) through ideal pixel `u`: [`ray_and_axis`]'s.
fn ray(set: &PreparedSet, u: &Vector2<f64>) -> Vector3<f64> {
    set.k_inv_t.tr_mul(&Vector3::new(u.x, u.y, 1.0))
}

fn closest_approach(v: &Vector3<f64>, p: &Vector3<f64>, d: &Vector3<f64>) -> Option<(f64, f64)> {
    let (a, b, c) = (v.dot(v), v.dot(d), d.dot(d));
    let (vp, dp) = (v.dot(p), d.dot(p));
    let denom = a * c - b * b;
    if denom.is_nan() || denom.abs() <= 1e-12 * a * c {
        return None;
    }
    // Closest approach of λ v and p + s d: λ = (c v·p − b d·p) / (ac − b²), s = (b v·p − a d·p) / (ac − b²).
    let lambda = (c * vp - b * dp) / denom;
    let s = (b * vp - a * dp) / denom / c.sqrt();
    (lambda.is_finite() && s.is_finite()).then_some((lambda, s))
}

/// First-order standard deviation (metres) of where along the tool the axis is seen at a line
/// point, under `noise`: the point's along-axis noise (the three frames' translations), plus
/// its noise across the axis (translations; the tool's tilt about the RCM and about the tip,
/// `s` and `L − s` from them; the camera's rotation and the pixel noise at depth `depth`)
/// divided by `sin θ`, `θ` the angle between the line of sight and the axis (a grazing view
/// cannot place a point along the axis). `s` is clamped to the shaft, `depth` to ≥ 1 mm.
pub fn position_sd_m(
    noise: &KinematicNoise,
    focal_px: f64,
    insertion_m: f64,
    s: f64,
    depth: f64,
    sin_theta: f64,
) -> f64 {
    let l = insertion_m.abs();
    let s = s.clamp(0.0, l);
    let z = depth.max(1e-3);
    let st2 = noise.trans_m * noise.trans_m;
    let sr2 = noise.rot_rad * noise.rot_rad;
    let px = z * noise.pixel_px / focal_px.max(1e-9);
    let across2 = 3.0 * st2 + sr2 * (s * s + (l - s) * (l - s) + z * z) + px * px;
    let sin2 = (sin_theta * sin_theta).max(1e-6);
    // Floor: a micrometre (a noise model with no translation noise and an exact view).
    (3.0 * st2 + across2 / sin2).sqrt().max(1e-6)
}

/// Residuals per observation ([`shaft_position_residuals`]): the two line points' positions
/// along the tool, their depths, and the tip at a shaft end.
pub const TERMS: usize = 5;

/// The first-order tip model is used up to this relative depth standard deviation (the
/// selection stage's default, [`super::selection::SelectionConfig::default`]).
pub(crate) const TIP_DEPTH_RATIO: f64 = 0.3;

/// An observation's shaft-position noise model at one pose, held fixed while a refinement
/// moves (as the line residuals' whitening is): each line point's [`position_sd_m`] (`None`:
/// its ray is parallel to the axis) and the tip's model at a shaft end
/// ([`TipEndModel`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct ShaftModel {
    sds: [Option<f64>; 2],
    tip: Option<TipEndModel>,
}

/// [`ShaftModel`] of observation `o` at pose `(R, t)` under `noise`.
pub fn shaft_model(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    noise: &KinematicNoise,
) -> ShaftModel {
    ShaftModel { sds: sds_at(set, o, r, t, noise), tip: tip_end_model(set, o, r, t, noise, TIP_DEPTH_RATIO) }
}

/// The shaft-position residuals of observation `o` at pose `(R, t)` under `noise` (its
/// [`ShaftModel`] built there): for each of its two line points, how far (in its
/// [`position_sd_m`]) the axis point seen there lies off the visible instrument
/// ([`Prepared::visible_m`]: by default `s < 0` beyond the RCM or `s > L` beyond the tip); for a point that is an end of the shaft,
/// [`Prepared::shaft_end`], how far from the nearer end, signed), then how far behind the
/// camera it lies (`depth < 0`), then the tip at a shaft end ([`TipEndModel::z`], which
/// replaces the first kind for its point); each 0 when within or not applicable.
/// Dimensionless, signed.
pub fn shaft_position_residuals(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    noise: &KinematicNoise,
) -> [f64; TERMS] {
    model_and_residuals_at(set, o, r, t, noise, false, None).1
}

/// [`shaft_model`] built at pose `(R, t)` and evaluated there: the model, the residuals
/// ([`residuals_at`]) and, with `grad`, their gradients ([`residuals_and_gradients_at`];
/// zeros without), bit for bit as those functions give them, computing each line point's
/// closest approach and the tip's projection once. `line`: observation `o`'s line residual
/// pair and its pose Jacobian at `(R, t)` ([`super::residual::residual_and_jacobian`]) when
/// the caller has them.
pub fn model_and_residuals_at(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    noise: &KinematicNoise,
    grad: bool,
    line: Option<(&Vector2<f64>, &Jac6)>,
) -> (ShaftModel, [f64; TERMS], [Vector6<f64>; TERMS]) {
    let mut out = (ShaftModel::default(), [0.0; TERMS], [Vector6::zeros(); TERMS]);
    model_and_residuals_into(set, o, r, t, noise, grad, line, (&mut out.0, &mut out.1, &mut out.2));
    out
}

/// [`model_and_residuals_at`] written into `out` (model, residuals, gradients) in place, the
/// same values: for the refinement's per-observation slots (no copy of the result).
#[allow(clippy::too_many_arguments, reason = "model_and_residuals_at's arguments and its result's slots")]
pub(crate) fn model_and_residuals_into(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    noise: &KinematicNoise,
    grad: bool,
    line: Option<(&Vector2<f64>, &Jac6)>,
    out: (&mut ShaftModel, &mut [f64; TERMS], &mut [Vector6<f64>; TERMS]),
) {
    let tip = tip_end_model_and_pixel(set, o, r, t, noise, TIP_DEPTH_RATIO);
    model_and_residuals_with_tip(set, o, r, t, noise, grad, line, tip, out);
}

/// [`model_and_residuals_at`] with the noise quantities already computed at the pose
/// ([`super::selection::noise_at`]): the same values, the tip's model not computed again.
#[allow(clippy::too_many_arguments, reason = "model_and_residuals_at's arguments and the noise quantities")]
pub(crate) fn model_and_residuals_noise_at(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    noise: &KinematicNoise,
    grad: bool,
    line: Option<(&Vector2<f64>, &Jac6)>,
    at: &NoiseAt,
) -> (ShaftModel, [f64; TERMS], [Vector6<f64>; TERMS]) {
    let mut out = (ShaftModel::default(), [0.0; TERMS], [Vector6::zeros(); TERMS]);
    let tip = tip_end_model_at(set, o, r, t, noise, TIP_DEPTH_RATIO, at);
    model_and_residuals_with_tip(set, o, r, t, noise, grad, line, tip, (&mut out.0, &mut out.1, &mut out.2));
    out
}

/// [`model_and_residuals_into`] with the tip's model and pixel at the pose given.
#[allow(clippy::too_many_arguments, reason = "model_and_residuals_into's arguments and the tip's model")]
fn model_and_residuals_with_tip(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    noise: &KinematicNoise,
    grad: bool,
    line: Option<(&Vector2<f64>, &Jac6)>,
    tip: Option<(TipEndModel, TipPixel)>,
    out: (&mut ShaftModel, &mut [f64; TERMS], &mut [Vector6<f64>; TERMS]),
) {
    let (m_out, e, g) = out;
    let focal = focal_px(set);
    let ends = with_end_precision(set, noise);
    let mut seen = [None; 2];
    let mut sds = [None; 2];
    // The axis (and its unit direction) once for both line points.
    let (p, d) = axis_in_camera(o, r, t);
    let d_unit = d.normalize();
    for (j, (v, v_unit)) in o.rays.iter().enumerate() {
        seen[j] = closest_approach(v, &p, &d);
        sds[j] = seen[j].and_then(|(depth, s)| sd_of_unit(&ends, focal, o.insertion_m, v_unit, &d_unit, depth, s));
    }
    *m_out = ShaftModel { sds, tip: tip.map(|x| x.0) };
    *e = metric_residuals(o, &seen, &sds, m_out.tip.map(|x| x.point));
    *g = [Vector6::zeros(); TERMS];
    if let Some((tm, tp)) = &tip {
        let z = match (grad, line) {
            (true, Some((res, jr))) => tm.z_with(o, tp, res, Some(jr)),
            (true, None) => {
                let (res, jr) = residual_and_jacobian(set, o, r, t);
                tm.z_with(o, tp, &res, Some(&jr))
            }
            (false, Some((res, _))) => tm.z_with(o, tp, res, None),
            (false, None) => tm.z_with(o, tp, &residual(set, o, r, t), None),
        };
        if let Some((z, dz)) = z {
            e[4] = z;
            g[4] = dz;
        }
    }
    if grad {
        metric_gradients(o, r, t, &sds, e, g);
    }
}

/// The focal length (pixels) of the set's camera, from `K⁻¹`.
fn focal_px(set: &PreparedSet) -> f64 {
    1.0 / set.k_inv_t[(0, 0)].abs().max(1e-300)
}

/// A line point's [`position_sd_m`] from its unit ray direction `v_unit`, the unit axis
/// direction `d_unit` and their closest approach `(depth, s)`; `None` when not finite.
fn sd_of_unit(
    noise: &KinematicNoise,
    focal: f64,
    insertion_m: f64,
    v_unit: &Vector3<f64>,
    d_unit: &Vector3<f64>,
    depth: f64,
    s: f64,
) -> Option<f64> {
    let sin_theta = v_unit.cross(d_unit).norm();
    let sd = position_sd_m(noise, focal, insertion_m, s, depth, sin_theta);
    sd.is_finite().then_some(sd)
}

/// [`shaft_position_residuals`] at pose `(R, t)` with a model built elsewhere.
pub fn residuals_at(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    m: &ShaftModel,
) -> [f64; TERMS] {
    let mut e = residuals_with(o, r, t, &m.sds, m.tip.map(|x| x.point));
    if let Some(z) = m.tip.and_then(|x| x.z(set, o, r, t, false)) {
        e[4] = z.0;
    }
    e
}

/// [`residuals_at`] with observation `o`'s line residual pair at `(R, t)` given (`res`,
/// [`super::residual::residual`]; the same values).
pub fn residuals_at_with(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    m: &ShaftModel,
    res: &Vector2<f64>,
) -> [f64; TERMS] {
    let mut e = residuals_with(o, r, t, &m.sds, m.tip.map(|x| x.point));
    if let Some(z) = m.tip.and_then(|tm| tip_px(set, o, r, t).and_then(|px| tm.z_at(o, &px, res))) {
        e[4] = z;
    }
    e
}

/// Each line point's [`position_sd_m`] at pose `(R, t)` (`None`: ray parallel to the axis).
fn sds_at(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    noise: &KinematicNoise,
) -> [Option<f64>; 2] {
    let focal = focal_px(set);
    let ends = with_end_precision(set, noise);
    o.px.map(|u| {
        let (v, p, d) = ray_and_axis(set, o, r, t, &u);
        let (depth, s) = closest_approach(&v, &p, &d)?;
        sd_of_unit(&ends, focal, o.insertion_m, &v.normalize(), &d.normalize(), depth, s)
    })
}

/// `noise` with the detector's end precision ([`PreparedSet::end_sd_px`]) added to its pixel
/// term: the noise of a line point's position along the tool.
fn with_end_precision(set: &PreparedSet, noise: &KinematicNoise) -> KinematicNoise {
    KinematicNoise { pixel_px: noise.pixel_px.hypot(set.end_sd_px), ..*noise }
}

/// The metric residuals (the first four of [`shaft_position_residuals`]) with each line
/// point's standard deviation given; `tip_point`: the point the tip model places (no position
/// term there).
fn residuals_with(
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    sds: &[Option<f64>; 2],
    tip_point: Option<usize>,
) -> [f64; TERMS] {
    // [`axis_seen_at`] of each line point, the axis computed once.
    let (p, d) = axis_in_camera(o, r, t);
    let seen = [0, 1].map(|j| sds[j].and_then(|_| closest_approach(&o.rays[j].0, &p, &d)));
    metric_residuals(o, &seen, sds, tip_point)
}

/// [`residuals_with`] from each line point's closest approach `seen` ([`axis_seen_at`]).
fn metric_residuals(
    o: &Prepared,
    seen: &[Option<(f64, f64)>; 2],
    sds: &[Option<f64>; 2],
    tip_point: Option<usize>,
) -> [f64; TERMS] {
    let l = o.insertion_m.abs();
    let mut e = [0.0; TERMS];
    for j in 0..2 {
        let Some(sd) = sds[j] else { continue };
        let Some((depth, s)) = seen[j] else { continue };
        let excess = if tip_point == Some(j) {
            0.0
        } else if o.shaft_end[j] {
            // An end of the shaft: the nearer of the RCM (`s = 0`) and the tip (`s = L`).
            if s < 0.5 * l { s } else { s - l }
        } else if s < o.visible_m[0] {
            s - o.visible_m[0]
        } else if s > o.visible_m[1] {
            s - o.visible_m[1]
        } else {
            0.0
        };
        e[j] = excess / sd;
        e[2 + j] = depth.min(0.0) / sd;
    }
    e
}

/// [`residuals_at`] and, for the non-zero residuals, their analytic gradients w.r.t. the pose
/// `(t m, δφ rad)` (`R ← exp(δφ^) R`), the model (standard deviations, tip model) held
/// fixed. Zero residuals have a zero gradient (the metric penalties are flat inside the
/// shaft, with a continuous derivative).
pub fn residuals_and_gradients_at(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    m: &ShaftModel,
) -> ([f64; TERMS], [Vector6<f64>; TERMS]) {
    let tip_point = m.tip.map(|x| x.point);
    let mut e = residuals_with(o, r, t, &m.sds, tip_point);
    let mut g = [Vector6::zeros(); TERMS];
    if let Some((z, dz)) = m.tip.and_then(|x| x.z(set, o, r, t, true)) {
        e[4] = z;
        g[4] = dz;
    }
    metric_gradients(o, r, t, &m.sds, &e, &mut g);
    (e, g)
}

/// The gradients of the non-zero metric residuals `e` (the first four) into `g`.
fn metric_gradients(
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    sds: &[Option<f64>; 2],
    e: &[f64; TERMS],
    g: &mut [Vector6<f64>; TERMS],
) {
    // The axis and its pose Jacobians, built at most once for both line points.
    let mut axis: Option<AxisJacobians> = None;
    for (j, (v, _)) in o.rays.iter().enumerate() {
        let (ei, ed) = (e[j] != 0.0, e[2 + j] != 0.0);
        if !(ei || ed) {
            continue;
        }
        let Some(sd) = sds[j] else { continue };
        let ax = axis.get_or_insert_with(|| axis_jacobians(o, r, t));
        let Some((dl, ds)) = closest_approach_gradient_with(v, ax) else { continue };
        if ei {
            g[j] = ds / sd;
        }
        if ed {
            g[2 + j] = dl / sd;
        }
    }
}

/// The tool axis in the camera frame at a pose ([`axis_in_camera`]: point `p`, direction `d`)
/// and their Jacobians w.r.t. the pose `(t, δφ)`: what [`closest_approach_gradient_with`]
/// needs besides the ray, the same for both line points of an observation.
struct AxisJacobians {
    p: Vector3<f64>,
    d: Vector3<f64>,
    jp: SMatrix<f64, 3, 6>,
    jd: SMatrix<f64, 3, 6>,
    /// The gradients of `d·d` and `d·p`: the closest approach's parts that do not depend on
    /// the ray (computed once for both line points, the same arithmetic).
    dc: Vector6<f64>,
    ddp: Vector6<f64>,
}

/// [`AxisJacobians`] of observation `o` at pose `(R, t)`.
fn axis_jacobians(o: &Prepared, r: &Matrix3<f64>, t: &Vector3<f64>) -> AxisJacobians {
    let (p, d) = axis_in_camera(o, r, t);
    // ∂p/∂t = R_ecᵀ, ∂p/∂δφ = −R_ecᵀ [R p_t]×; ∂d/∂t = 0, ∂d/∂δφ = −R_ecᵀ [R m_t]×.
    let rt = o.r_ec.transpose();
    let mut jp = SMatrix::<f64, 3, 6>::zeros();
    jp.fixed_view_mut::<3, 3>(0, 0).copy_from(&rt);
    jp.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-rt * skew(&(r * o.p_t))));
    let mut jd = SMatrix::<f64, 3, 6>::zeros();
    jd.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-rt * skew(&(r * o.m_t))));
    let dc = (d.transpose() * jd).transpose() * 2.0;
    let ddp = (p.transpose() * jd + d.transpose() * jp).transpose();
    AxisJacobians { p, d, jp, jd, dc, ddp }
}

/// Gradients w.r.t. the pose `(t, δφ)` (`R ← exp(δφ^) R`) of [`axis_seen_at`]'s depth and
/// position along the tool (metres per metre / radian) for the ray `v` ([`ray`]) and the axis
/// `ax`, by differentiating the closest approach's closed form; `None` where [`axis_seen_at`]
/// is.
fn closest_approach_gradient_with(v: &Vector3<f64>, ax: &AxisJacobians) -> Option<(Vector6<f64>, Vector6<f64>)> {
    let AxisJacobians { p, d, jp, jd, dc, ddp } = ax;
    let (p, d, dc, ddp) = (*p, *d, *dc, *ddp);
    let v = *v;
    let (a, b, c) = (v.dot(&v), v.dot(&d), d.dot(&d));
    let (vp, dpr) = (v.dot(&p), d.dot(&p));
    let den = a * c - b * b;
    if den.is_nan() || den.abs() <= 1e-12 * a * c {
        return None;
    }
    let db = (v.transpose() * jd).transpose();
    let dvp = (v.transpose() * jp).transpose();
    let dden = dc * a - db * (2.0 * b);
    let lambda = (c * vp - b * dpr) / den;
    let dl = ((dc * vp + dvp * c - db * dpr - ddp * b) - dden * lambda) / den;
    let s0 = (b * vp - a * dpr) / den;
    let ds0 = ((db * vp + dvp * b - ddp * a) - dden * s0) / den;
    let sc = c.sqrt();
    let ds = ds0 / sc - dc * (0.5 * s0 / (c * sc));
    (dl.iter().chain(ds.iter()).all(|x| x.is_finite())).then_some((dl, ds))
}

/// Passes of [`translation_from_shaft_ends`]'s reweighting.
pub const ENDS_PASSES: usize = 6;

/// The translation `t` (metres, `{e}`) that puts the tool's shaft ends on the rays through the
/// observed shaft-end points ([`Prepared::shaft_end`]) for a given rotation `R` (`T_e_t`):
/// each end point `R (p + m s) + t` (`s` the tip's `L`, or 0 for robot 2's RCM) on its ray from
/// the optical centre, least absolute distances to the rays (iteratively reweighted least
/// squares, [`ENDS_PASSES`] passes: robust to wrong lines). Each point is first taken as the
/// tip, then re-assigned to the nearer end at each pass's solution. A start
/// for the refinement far better conditioned than Eq. 5 when the kinematic noise is large: a
/// point fixes two directions where a line fixes one. `None` with fewer than three shaft-end
/// points or a singular system.
pub fn translation_from_shaft_ends(set: &PreparedSet, r: &Matrix3<f64>) -> Option<Vector3<f64>> {
    let ends: usize = set.obs.iter().map(|o| o.shaft_end.iter().filter(|e| **e).count()).sum();
    if ends < 3 {
        return None;
    }
    let mut t: Option<Vector3<f64>> = None;
    for _ in 0..ENDS_PASSES {
        let mut a = Matrix3::zeros();
        let mut b = Vector3::zeros();
        for o in &set.obs {
            for (j, u) in o.px.iter().enumerate() {
                if !o.shaft_end[j] {
                    continue;
                }
                let w = (o.r_ec * set.k_inv_t.tr_mul(&Vector3::new(u.x, u.y, 1.0))).normalize();
                let proj = Matrix3::identity() - w * w.transpose();
                let tip = r * (o.p_t + o.m_t * o.insertion_m);
                let rcm = r * o.p_t;
                // The nearer end at the current solution (the tip before there is one), and
                // a weight 1 / distance to the ray (least absolute distances, robust to wrong
                // lines), at least a millimetre.
                let (q, w) = match &t {
                    Some(t) => {
                        let (dr, dt) = ((proj * (rcm + t - o.o_ec)).norm(), (proj * (tip + t - o.o_ec)).norm());
                        if dr < dt { (rcm, 1.0 / dr.max(1e-3)) } else { (tip, 1.0 / dt.max(1e-3)) }
                    }
                    None => (tip, 1.0),
                };
                a += proj * w;
                b += proj * (o.o_ec - q) * w;
            }
        }
        let next = a.try_inverse().map(|inv| inv * b).filter(|v| v.iter().all(|x| x.is_finite()))?;
        t = Some(next);
    }
    t
}

/// Huber threshold (standard deviations) of [`stage_terms`], as the robust fit's default
/// ([`super::ours::OursConfig::huber_k`]).
const STAGE_HUBER_K: f64 = 3.0;

/// Observation `o`'s shaft-position terms as negative log-likelihood (Huber at 3 standard
/// deviations, the model built at `(R, t)`) and, when `grad`, their gradient w.r.t.
/// `(t m, δφ rad)` and Gauss-Newton matrix: the selection-aware stage's extra terms
/// ([`super::selection::refine_selected_with`]).
pub fn stage_terms(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    noise: &KinematicNoise,
    grad: bool,
) -> (f64, Vector6<f64>, Matrix6<f64>) {
    let (mut f, mut g, mut h) = (0.0, Vector6::zeros(), Matrix6::zeros());
    let huber = |e: f64| if e <= STAGE_HUBER_K { 0.5 * e * e } else { STAGE_HUBER_K * (e - 0.5 * STAGE_HUBER_K) };
    // The model built and evaluated at `(R, t)` in one pass.
    let (_, es, js) = model_and_residuals_at(set, o, r, t, noise, grad, None);
    if !grad {
        for e in es {
            f += huber(e.abs());
        }
        return (f, g, h);
    }
    for (e, j) in es.iter().zip(&js) {
        if *e == 0.0 {
            continue;
        }
        let n = e.abs();
        let wgt = if n <= STAGE_HUBER_K { 1.0 } else { STAGE_HUBER_K / n };
        f += huber(n);
        g += j * (e * wgt);
        h += j * j.transpose() * wgt;
    }
    (f, g, h)
}
