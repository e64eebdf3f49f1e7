//! Ground truth per frame and per eye, computed analytically from the scene (never from the
//! rendered image).
//!
//! **Shaft contours.** For a cylinder of radius `r` with axis through `A` (camera frame,
//! metres) and unit direction `d`, the planes through the optical centre tangent to it are
//! parallel to `d` and at distance `r` from the axis: with `A⊥ = A − (A·d)d`, `ρ = |A⊥|`,
//! `e1 = A⊥/ρ`, `e2 = d × e1`, their unit normals are
//! `n± = (r/ρ) e1 ± √(1 − r²/ρ²) e2` (requires `ρ > r`: the camera outside the cylinder).
//! Each touches the cylinder along the generator `A + s d − r n±`, whose image is the contour
//! line `l± ∝ K⁻ᵀ n±` in undistorted pixels. The projected axis is `l_a ∝ K⁻ᵀ (A × d)`. Under
//! perspective the axis is *not* midway between the contours (the far side of the shaft
//! looks smaller), which is why both are given.
//!
//! **Under distortion** the contours are curves. Each line is given exactly in undistorted
//! (ideal) pixels, `a·u + b·v + c = 0` with `a² + b² = 1` (signed distance in pixels; the
//! shaft's inside is on the positive side of each contour, contour 0 on the positive side of
//! the axis line); the visible part's end points in ideal and in distorted (image) pixels; and
//! a polyline of [`POLYLINE_POINTS`] distorted points along the visible part. The visible part
//! is the part of the generator in front of the camera whose image lies inside the image
//! (it does not account for occlusion by the other instrument or the jaws).

use estimator::calib::Intrinsics;
use nalgebra::{Isometry3, Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::mesh::InstrumentGeometry;
use super::scene::InstrumentState;

/// Points in each contour's distorted polyline.
pub const POLYLINE_POINTS: usize = 17;

/// A pose as written to the ground-truth file: translation (metres) and unit quaternion
/// `[w, x, y, z]`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseTruth {
    /// Translation, metres.
    pub translation_m: [f64; 3],
    /// Rotation, unit quaternion `[w, x, y, z]`.
    pub quaternion_wxyz: [f64; 4],
}

impl From<&Isometry3<f64>> for PoseTruth {
    fn from(t: &Isometry3<f64>) -> Self {
        let q = t.rotation.quaternion();
        let v = t.translation.vector;
        Self { translation_m: [v.x, v.y, v.z], quaternion_wxyz: [q.w, q.i, q.j, q.k] }
    }
}

/// One image line of the ground truth (see the module documentation).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ImageLine {
    /// `[a, b, c]`: `a·u + b·v + c = 0` in undistorted pixels, `a² + b² = 1`.
    pub line_ideal: [f64; 3],
    /// Unit normal of the plane through the optical centre and the 3-D line, camera frame
    /// (same sign as `(a, b, c) ∝ K⁻ᵀ n`).
    pub plane_normal: [f64; 3],
    /// Visible part's end points (distal end first), undistorted pixels; `None` when no part
    /// of it is in the image.
    pub segment_ideal_px: Option<[[f64; 2]; 2]>,
    /// The same end points in distorted (image) pixels.
    pub segment_px: Option<[[f64; 2]; 2]>,
    /// Distorted points evenly spaced (in 3-D) along the visible part, distal first; empty
    /// when not visible.
    pub polyline_px: Vec<[f64; 2]>,
}

/// Ground truth of one instrument in one eye.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InstrumentTruth {
    /// Label of the instrument in the mask (1: the instrument, 2: the second one).
    pub label: u8,
    /// `T_c_i`: the instrument frame `{i}` in this eye's camera frame (metres).
    pub pose_in_camera: PoseTruth,
    /// Wrist pitch, radians.
    pub wrist_rad: f64,
    /// Jaw angles (jaw 1, jaw 2), radians, ≥ 0 open.
    pub jaw_rad: [f64; 2],
    /// The arm's joints when the scene gave them (`[yaw rad, pitch rad, insertion m, roll rad]`).
    pub psm_joints: Option<[f64; 4]>,
    /// The tip point (the jaws' pivot) in the camera frame, metres.
    pub tip_camera_m: [f64; 3],
    /// Its pixel (distorted), when in front of the camera and inside the image.
    pub tip_px: Option<[f64; 2]>,
    /// The jaw tips' pixels (distorted), when in front and inside the image.
    pub jaw_tips_px: [Option<[f64; 2]>; 2],
    /// The two shaft contours; `None` when the camera is inside the shaft's cylinder.
    pub contours: Option<[ImageLine; 2]>,
    /// The projected shaft axis; `None` when the axis passes through the optical centre.
    pub axis: Option<ImageLine>,
}

/// The eye's projection: intrinsics plus the region of ideal pixels that maps into the image.
#[derive(Clone, Copy, Debug)]
pub struct EyeProjection {
    /// Intrinsics (pixels).
    pub k: Intrinsics,
    /// Ideal-pixel bounds `[u0, v0, u1, v1]` inside which projection is valid (the canvas).
    pub ideal_bounds: [f64; 4],
}

impl EyeProjection {
    /// Distorted pixel of a camera-frame point, `None` when behind the camera, outside the
    /// valid region or outside the image.
    pub fn project_in_image(&self, p: &Vector3<f64>) -> Option<Vector2<f64>> {
        if !p.iter().all(|v| v.is_finite()) || p.z <= 1e-6 {
            return None;
        }
        let ideal = self.k.k() * (p / p.z);
        let [u0, v0, u1, v1] = self.ideal_bounds;
        if !(ideal.x >= u0 && ideal.x <= u1 && ideal.y >= v0 && ideal.y <= v1) {
            return None;
        }
        let px = self.k.project(p);
        self.k.in_image(&px).then_some(px)
    }
}

fn homogeneous_line(k_inv_t: &Matrix3<f64>, n: &Vector3<f64>) -> [f64; 3] {
    let l = k_inv_t * n;
    let s = (l.x * l.x + l.y * l.y).sqrt();
    [l.x / s, l.y / s, l.z / s]
}

/// The image line of the 3-D line `p(s) = base + s·d`, `s ∈ [s0, s1]` (camera frame), with
/// plane normal `n` (unit, through the optical centre).
fn image_line(
    proj: &EyeProjection,
    n: Vector3<f64>,
    base: Vector3<f64>,
    d: Vector3<f64>,
    s0: f64,
    s1: f64,
) -> ImageLine {
    let k_inv_t = proj.k.k_inv().transpose();
    let line_ideal = homogeneous_line(&k_inv_t, &n);
    let at = |s: f64| base + d * s;
    // In front of the camera: z(s) ≥ 1 mm.
    let near = 1e-3;
    let (mut a, mut b) = (s0, s1);
    if d.z.abs() < 1e-15 {
        if base.z < near {
            (a, b) = (1.0, 0.0);
        }
    } else {
        let s_near = (near - base.z) / d.z;
        if d.z > 0.0 {
            a = a.max(s_near);
        } else {
            b = b.min(s_near);
        }
    }
    let mut out = ImageLine {
        line_ideal,
        plane_normal: [n.x, n.y, n.z],
        segment_ideal_px: None,
        segment_px: None,
        polyline_px: Vec::new(),
    };
    if a.is_nan() || b.is_nan() || a >= b {
        return out;
    }
    // Sample, keep the visible range, refine both ends by bisection.
    const SAMPLES: usize = 400;
    let vis = |s: f64| proj.project_in_image(&at(s)).is_some();
    let ss: Vec<f64> = (0..=SAMPLES).map(|i| a + (b - a) * i as f64 / SAMPLES as f64).collect();
    let Some(first) = ss.iter().position(|&s| vis(s)) else { return out };
    let last = ss.iter().rposition(|&s| vis(s)).unwrap_or(first);
    let refine = |mut inside: f64, mut outside: f64| {
        for _ in 0..40 {
            let m = 0.5 * (inside + outside);
            if vis(m) {
                inside = m;
            } else {
                outside = m;
            }
        }
        inside
    };
    let lo = if first > 0 { refine(ss[first], ss[first - 1]) } else { ss[0] };
    let hi = if last < SAMPLES { refine(ss[last], ss[last + 1]) } else { ss[SAMPLES] };
    let ideal = |s: f64| {
        let p = at(s);
        let q = proj.k.k() * (p / p.z);
        [q.x, q.y]
    };
    let dist = |s: f64| {
        let q = proj.k.project(&at(s));
        [q.x, q.y]
    };
    // Distal end first: the larger s.
    out.segment_ideal_px = Some([ideal(hi), ideal(lo)]);
    out.segment_px = Some([dist(hi), dist(lo)]);
    out.polyline_px =
        (0..POLYLINE_POINTS).map(|i| dist(hi + (lo - hi) * i as f64 / (POLYLINE_POINTS - 1) as f64)).collect();
    out
}

fn signed_distance(l: &[f64; 3], p: &Vector3<f64>, k: &Matrix3<f64>) -> f64 {
    let q = k * (p / p.z);
    l[0] * q.x + l[1] * q.y + l[2]
}

fn flip(l: &mut ImageLine) {
    l.line_ideal = l.line_ideal.map(|v| -v);
    l.plane_normal = l.plane_normal.map(|v| -v);
}

/// The ground truth of one instrument seen by one eye. `t_c_e` maps the world `{e}` into the
/// eye's camera frame.
pub fn instrument_truth(
    label: u8,
    state: &InstrumentState,
    geometry: &InstrumentGeometry,
    t_c_e: &Isometry3<f64>,
    proj: &EyeProjection,
) -> InstrumentTruth {
    let t_c_i = t_c_e * state.pose_world;
    let tip = t_c_i * nalgebra::Point3::from(geometry.jaw_pivot(state.wrist_rad));
    let jaw = geometry.jaw_tips(state.wrist_rad, state.jaw_rad).map(|p| t_c_i * nalgebra::Point3::from(p));
    let a = t_c_i.translation.vector; // distal end of the shaft, on the axis
    let d = t_c_i.rotation * Vector3::z();
    let r = geometry.shaft_radius_m();
    let len = geometry.shaft_length_m;
    let k = proj.k.k();
    let a_perp = a - d * a.dot(&d);
    let rho = a_perp.norm();
    let axis_n = a.cross(&d);
    let mut axis = (axis_n.norm() > 1e-12).then(|| image_line(proj, axis_n.normalize(), a, d, -len, 0.0));
    let contours = (rho > r * (1.0 + 1e-9)).then(|| {
        let e1 = a_perp / rho;
        let e2 = d.cross(&e1);
        let c = r / rho;
        let s = (1.0 - c * c).sqrt();
        let mk = |sign: f64| {
            let n = e1 * c + e2 * (sign * s);
            let mut l = image_line(proj, n, a - n * r, d, -len, 0.0);
            // The inside (the axis' image) on the positive side.
            let probe = if a.z > 1e-6 { a } else { a - d * len };
            if probe.z > 1e-6 && signed_distance(&l.line_ideal, &probe, &k) < 0.0 {
                flip(&mut l);
            }
            l
        };
        [mk(1.0), mk(-1.0)]
    });
    if let (Some(ax), Some(cs)) = (axis.as_mut(), contours.as_ref()) {
        // Contour 0 on the positive side of the axis line.
        let g = a - Vector3::from(cs[0].plane_normal) * r;
        let probe = if g.z > 1e-6 { g } else { g - d * len };
        if probe.z > 1e-6 && signed_distance(&ax.line_ideal, &probe, &k) < 0.0 {
            flip(ax);
        }
    }
    let px = |p: &nalgebra::Point3<f64>| proj.project_in_image(&p.coords).map(|q| [q.x, q.y]);
    InstrumentTruth {
        label,
        pose_in_camera: PoseTruth::from(&t_c_i),
        wrist_rad: state.wrist_rad,
        jaw_rad: state.jaw_rad,
        psm_joints: state.psm_joints,
        tip_camera_m: [tip.x, tip.y, tip.z],
        tip_px: px(&tip),
        jaw_tips_px: [px(&jaw[0]), px(&jaw[1])],
        contours,
        axis,
    }
}
