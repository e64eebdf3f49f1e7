//! # Hypotheses from the detected shaft (ours)
//!
//! The oriented, truncated chamfer of [`crate::measure`] has a basin a few millimetres wide: a
//! cloud 13 mm off never feels the truth. A shaft detector (our `vision::ours`, run by the
//! caller) finds the shaft's two contour lines in each eye wherever the instrument is; this
//! module turns them into joint hypotheses the tracker can re-seed from
//! ([`crate::Tracker::set_shaft_axis`], [`ProposalConfig`]):
//!
//! 1. [`triangulate_axis`]: each eye's projected axis (a line in undistorted pixels) and the
//!    eye's centre span a plane; the two planes meet in the shaft's axis, expressed in the tool
//!    arm's base frame. The detected span's ends (measured pixels, left eye), brought onto that
//!    axis (closest point to each end's ray), say where the visible shaft stops: one end is
//!    the shaft's distal end (the wrist link starts there) unless the tip is out of view.
//! 2. [`joints_for_axis`]: a reference hypothesis (the tracker's previous best) is moved, by a
//!    few Newton steps on the arm's forward kinematics, so that its instrument axis lies on the
//!    triangulated one (the smallest rotation of its axis onto it, its origin projected onto
//!    it), then slid along the axis and rolled about it by given amounts: the axis fixes four of
//!    the six degrees of freedom; the position along it and the roll are sampled by the tracker
//!    (about the detected distal end and about the reference) and decided by the measurement.
//!
//! Frames: everything returned is in the tool arm's base frame, metres; image lines in
//! undistorted pixels of each eye; span ends in measured (distorted) pixels.

use estimator::kinematics::JOINTS;
use nalgebra::{Isometry3, Matrix3, Matrix6, Translation3, UnitQuaternion, Vector2, Vector3, Vector6};

use crate::model::{StereoCameras, ToolModel};

/// The shaft's axis seen by both eyes, in the tool arm's base frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShaftAxis {
    /// A point on the axis, base frame, metres.
    pub point_m: Vector3<f64>,
    /// Unit direction of the axis, base frame (its sign is arbitrary).
    pub dir: Vector3<f64>,
    /// The detected span's two ends on the axis (left eye's rays brought onto it), base frame,
    /// metres; `None` when the caller gave no ends.
    pub ends_m: Option<[Vector3<f64>; 2]>,
}

/// Why two image lines give no axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum AxisError {
    /// A coefficient, a camera number or a span end is not finite, or a line has `a = b = 0`.
    #[error("a line coefficient, span end or camera number is not finite, or a line is degenerate")]
    NotFinite,
    /// The two planes through the eyes are (nearly) parallel: the axis lies in an epipolar
    /// plane and depth along it is not observable.
    #[error("the two eyes' planes are parallel (axis in an epipolar plane)")]
    Parallel,
}

/// The plane through eye `e`'s centre and its image line `abc` (undistorted pixels), in the
/// base frame: `(n, d)` with `n·X + d = 0`, `|n| = 1`.
fn plane_in_base(
    cams: &StereoCameras,
    eyes: &[Isometry3<f64>; 2],
    e: usize,
    abc: &[f64; 3],
) -> Option<(Vector3<f64>, f64)> {
    if !abc.iter().all(|v| v.is_finite()) || abc[0].hypot(abc[1]) < 1e-12 {
        return None;
    }
    let k = cams.intrinsics[e].k();
    let n_c = k.transpose() * Vector3::new(abc[0], abc[1], abc[2]);
    let t = &eyes[e];
    // X_c = R X_b + t:  n_c·(R X_b + t) = 0.
    let n_b = t.rotation.inverse() * n_c;
    let d = n_c.dot(&t.translation.vector);
    let norm = n_b.norm();
    (norm.is_finite() && norm > 0.0).then(|| (n_b / norm, d / norm))
}

/// Triangulates the shaft's axis from each eye's projected axis `lines` (`[a, b, c]`,
/// `a·u + b·v + c = 0` in **undistorted** pixels of that eye) with the cameras `cams` (no
/// `g_CB` correction); `ends_px`: the detected span's two ends in the **left** eye, measured
/// pixels. Returns the axis in the tool arm's base frame.
pub fn triangulate_axis(
    cams: &StereoCameras,
    lines: [[f64; 3]; 2],
    ends_px: Option<[[f64; 2]; 2]>,
) -> Result<ShaftAxis, AxisError> {
    if !cams.is_valid() {
        return Err(AxisError::NotFinite);
    }
    let eyes = cams.eyes_from_base(&[0.0; 6]);
    let (n0, d0) = plane_in_base(cams, &eyes, 0, &lines[0]).ok_or(AxisError::NotFinite)?;
    let (n1, d1) = plane_in_base(cams, &eyes, 1, &lines[1]).ok_or(AxisError::NotFinite)?;
    let dir = n0.cross(&n1);
    let s = dir.norm();
    // sin of the angle between the planes: below ~0.6° depth is not observable.
    if !(s.is_finite() && s > 0.01) {
        return Err(AxisError::Parallel);
    }
    let dir = dir / s;
    // The point of the axis nearest the left eye's centre.
    let c0 = eyes[0].inverse_transform_point(&nalgebra::Point3::origin()).coords;
    let a = Matrix3::from_rows(&[n0.transpose(), n1.transpose(), dir.transpose()]);
    let b = Vector3::new(-d0, -d1, dir.dot(&c0));
    let point = a.lu().solve(&b).ok_or(AxisError::Parallel)?;
    if !point.iter().all(|v| v.is_finite()) {
        return Err(AxisError::NotFinite);
    }
    let ends_m = match ends_px {
        None => None,
        Some(ends) => {
            let k = &cams.intrinsics[0];
            let kinv = k.k().try_inverse().ok_or(AxisError::NotFinite)?;
            let mut out = [Vector3::zeros(); 2];
            for (o, e) in out.iter_mut().zip(&ends) {
                if !e.iter().all(|v| v.is_finite()) {
                    return Err(AxisError::NotFinite);
                }
                let u = k.undistort_px(&Vector2::new(e[0], e[1]));
                let ray_c = kinv * Vector3::new(u.x, u.y, 1.0);
                let ray = eyes[0].rotation.inverse() * ray_c;
                *o = closest_on_line(&point, &dir, &c0, &ray).ok_or(AxisError::Parallel)?;
            }
            Some(out)
        }
    };
    Ok(ShaftAxis { point_m: point, dir, ends_m })
}

/// The point of the line `(p, d)` closest to the line `(c, r)` (`None` when parallel).
fn closest_on_line(p: &Vector3<f64>, d: &Vector3<f64>, c: &Vector3<f64>, r: &Vector3<f64>) -> Option<Vector3<f64>> {
    let w = p - c;
    let (a, b, cc) = (d.dot(d), d.dot(r), r.dot(r));
    let (dd, e) = (d.dot(&w), r.dot(&w));
    let den = a * cc - b * b;
    if den.abs() < 1e-12 * a * cc {
        return None;
    }
    let s = (b * e - cc * dd) / den;
    Some(p + d * s)
}

/// The pose error `[Δposition (m); rotation vector (rad)]` taking `from` to `to`, base frame.
fn pose_error(from: &Isometry3<f64>, to: &Isometry3<f64>) -> Vector6<f64> {
    let dp = to.translation.vector - from.translation.vector;
    let dr = (to.rotation * from.rotation.inverse()).scaled_axis();
    Vector6::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z)
}

/// Joints (radians) whose instrument frame `{i}` ([`ToolModel::instrument_in_base`]) is
/// `target` (base frame), by damped Newton steps from `q0`; `None` when they do not come within
/// 0.05 mm and 0.5 mrad in `iterations` steps, or off the arm.
pub fn solve_instrument_pose(
    model: &ToolModel,
    q0: &[f64; JOINTS],
    target: &Isometry3<f64>,
    iterations: usize,
) -> Option<[f64; JOINTS]> {
    let mut q = *q0;
    let h = 1e-7;
    for _ in 0..iterations {
        let t = model.instrument_in_base(&q)?;
        let e = pose_error(&t, target);
        let (ep, er) = (e.fixed_rows::<3>(0).norm(), e.fixed_rows::<3>(3).norm());
        if ep < 5e-5 && er < 5e-4 {
            return Some(q);
        }
        let mut jac = Matrix6::zeros();
        for k in 0..JOINTS {
            let mut a = q;
            a[k] += h;
            let ta = model.instrument_in_base(&a)?;
            jac.set_column(k, &(pose_error(&t, &ta) / h));
        }
        // Damped least squares: steps stay bounded near a singular configuration.
        let jt = jac.transpose();
        let dq = (jt * jac + Matrix6::identity() * 1e-9).lu().solve(&(jt * e))?;
        for (qk, d) in q.iter_mut().zip(dq.iter()) {
            *qk += d.clamp(-0.3, 0.3);
        }
        if !q.iter().all(|v| v.is_finite()) {
            return None;
        }
    }
    let t = model.instrument_in_base(&q)?;
    let e = pose_error(&t, target);
    (e.fixed_rows::<3>(0).norm() < 5e-5 && e.fixed_rows::<3>(3).norm() < 5e-4).then_some(q)
}

/// The instrument frame of `q_ref` moved onto `axis`: its `z` turned onto the axis by the
/// smallest rotation (the axis's sign taken along the reference's `z`), its origin projected
/// onto the axis, then slid by `slide_m` along it (towards the tip) and rolled by `roll_rad`
/// about it. Base frame. `None` off the arm.
pub fn instrument_on_axis(
    model: &ToolModel,
    q_ref: &[f64; JOINTS],
    axis: &ShaftAxis,
    slide_m: f64,
    roll_rad: f64,
) -> Option<Isometry3<f64>> {
    let t = model.instrument_in_base(q_ref)?;
    let z = t.rotation * Vector3::z();
    let d = if axis.dir.dot(&z) >= 0.0 { axis.dir } else { -axis.dir };
    let turn = UnitQuaternion::rotation_between(&z, &d).unwrap_or_else(UnitQuaternion::identity);
    let roll = UnitQuaternion::from_scaled_axis(d * roll_rad);
    let o = t.translation.vector;
    let on = axis.point_m + d * d.dot(&(o - axis.point_m)) + d * slide_m;
    Some(Isometry3::from_parts(Translation3::from(on), roll * turn * t.rotation))
}

/// Joints (radians) of a hypothesis on the detected `axis`: `q_ref` (a reference hypothesis,
/// e.g. the tracker's previous best) moved by [`instrument_on_axis`] and solved back to the
/// arm's joints ([`solve_instrument_pose`], 12 steps). `None` when no joints reach it.
pub fn joints_for_axis(
    model: &ToolModel,
    q_ref: &[f64; JOINTS],
    axis: &ShaftAxis,
    slide_m: f64,
    roll_rad: f64,
) -> Option<[f64; JOINTS]> {
    let target = instrument_on_axis(model, q_ref, axis, slide_m, roll_rad)?;
    solve_instrument_pose(model, q_ref, &target, 12)
}

/// The slide (metres, along the axis oriented like `q_ref`'s instrument `z`) that puts
/// `q_ref`'s instrument origin (the shaft's distal end) on the detected span's distal end: the
/// end farther along the axis towards the tip. `None` without ends or off the arm.
pub fn slide_to_distal_end(model: &ToolModel, q_ref: &[f64; JOINTS], axis: &ShaftAxis) -> Option<f64> {
    let ends = axis.ends_m?;
    let t = model.instrument_in_base(q_ref)?;
    let z = t.rotation * Vector3::z();
    let d = if axis.dir.dot(&z) >= 0.0 { axis.dir } else { -axis.dir };
    let o = t.translation.vector;
    let s0 = d.dot(&(ends[0] - o));
    let s1 = d.dot(&(ends[1] - o));
    let s = s0.max(s1);
    s.is_finite().then_some(s)
}

/// The re-seeding from the detected shaft ([`crate::Tracker::set_shaft_axis`]; ours only).
///
/// On a frame with a detected axis, when the previous best hypothesis (moved by the encoders'
/// increment) fits poorly (inlier share below `trigger_share`), `count` hypotheses are put on
/// the axis ([`joints_for_axis`]: half slid about the detected distal end, half about the
/// reference's own position, by `N(0, slide_sigma_m²)`; rolled by `N(0, roll_sigma_rad²)`;
/// every other one with a jaw angle drawn uniformly in 0-0.8 rad), evaluated, the best refined (cost only: the prior is the one being questioned). If its
/// inlier share is at least `accept_share` and beats the reference's by `margin`, the cloud is
/// re-initialised about it (**a re-initialisation from vision**: as from the kinematics after
/// LOST frames, with the offset model's stationary spread; reverting to the start, the
/// offset's mean becomes the new hypothesis's offset). The cloud's weights are untouched
/// otherwise: this is a documented re-seeding rule, not a mixture proposal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProposalConfig {
    /// Hypotheses put on the axis per triggered frame.
    pub count: usize,
    /// Re-seeding is tried when the reference's inlier share (0..1) is below this.
    pub trigger_share: f64,
    /// The best hypothesis on the axis must reach this inlier share (0..1) ...
    pub accept_share: f64,
    /// ... and exceed the reference's by this much (0..1).
    pub margin: f64,
    /// Standard deviation of the slide along the axis, metres.
    pub slide_sigma_m: f64,
    /// Standard deviation of the roll about the axis, radians.
    pub roll_sigma_rad: f64,
    /// The detected axis is ignored when it is turned by more than this from the reference's
    /// instrument axis, radians ...
    pub max_angle_rad: f64,
    /// ... or passes farther than this from the reference's instrument origin, metres.
    pub max_distance_m: f64,
}

impl Default for ProposalConfig {
    fn default() -> Self {
        Self {
            count: 128,
            trigger_share: 0.5,
            accept_share: 0.45,
            margin: 0.1,
            slide_sigma_m: 0.004,
            roll_sigma_rad: 0.25,
            max_angle_rad: 0.5,
            max_distance_m: 0.04,
        }
    }
}

impl ProposalConfig {
    /// `None` when every value is in range, else the offending field's name.
    pub fn invalid_field(&self) -> Option<&'static str> {
        let share = |v: f64| v.is_finite() && (0.0..=1.0).contains(&v);
        let nonneg = |v: f64| v.is_finite() && v >= 0.0;
        if self.count == 0 || self.count > 100_000 {
            Some("proposal.count (1..=100000)")
        } else if !share(self.trigger_share) || !share(self.accept_share) || !share(self.margin) {
            Some("proposal.trigger_share/accept_share/margin (0..=1)")
        } else if !nonneg(self.slide_sigma_m) || !nonneg(self.roll_sigma_rad) {
            Some("proposal.slide_sigma_m/roll_sigma_rad (>= 0)")
        } else if !(self.max_angle_rad.is_finite()
            && self.max_angle_rad > 0.0
            && self.max_distance_m.is_finite()
            && self.max_distance_m > 0.0)
        {
            Some("proposal.max_angle_rad/max_distance_m (> 0)")
        } else {
            None
        }
    }
}

/// `true` when `axis` is within `cfg`'s angle and distance of `q_ref`'s instrument axis.
pub fn axis_consistent(model: &ToolModel, q_ref: &[f64; JOINTS], axis: &ShaftAxis, cfg: &ProposalConfig) -> bool {
    let Some(t) = model.instrument_in_base(q_ref) else { return false };
    let z = t.rotation * Vector3::z();
    let angle = axis.dir.dot(&z).abs().clamp(0.0, 1.0).acos();
    let w = t.translation.vector - axis.point_m;
    let dist = (w - axis.dir * axis.dir.dot(&w)).norm();
    angle <= cfg.max_angle_rad && dist <= cfg.max_distance_m
}
