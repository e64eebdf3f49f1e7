//! The measurement of one particle against one stereo frame: the paper's (a virtual edge image
//! per particle, chamfer distance to the Canny edges, Eq. 14-16) and ours (analytic shaft
//! contours and precomputed tip-edge candidates sampled and looked up in each eye's distance
//! field, oriented and truncated).

use nalgebra::{Isometry3, Point3, Vector3};

use crate::Particle;
use crate::edges::EdgeField;
use crate::model::{Part, StereoCameras, ToolModel, eye_in, project};

/// Parameters of our measurement (pixels).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OursCost {
    /// Truncation of a sample's cost, pixels (clutter and occlusion cost at most this).
    pub truncate_px: f64,
    /// Weight of the orientation mismatch, pixels for a model edge perpendicular to the image
    /// edge (`|cos|` of the angle between the model edge and the image gradient).
    pub orientation_px: f64,
    /// Samples along each of the shaft's two contour lines.
    pub shaft_samples: usize,
}

/// The shaft's two contour generators in the camera frame: for a cylinder of radius `r` whose
/// axis passes through `a` along unit `u` (camera frame, metres), the offsets from the axis of
/// the two lines where the rays from the camera centre graze it. `None` when the camera is
/// inside the cylinder.
pub fn shaft_contour_offsets(a: &Vector3<f64>, u: &Vector3<f64>, r: f64) -> Option<[Vector3<f64>; 2]> {
    let w = -a;
    let wp = w - u * w.dot(u);
    let d = wp.norm();
    if d.is_nan() || d <= r * 1.0001 {
        return None;
    }
    let wh = wp / d;
    let vh = u.cross(&wh);
    let c = r / d;
    let s = (1.0 - c * c).sqrt();
    Some([(wh * c + vh * s) * r, (wh * c - vh * s) * r])
}

#[inline]
fn sample_cost(f: &EdgeField, x: f64, y: f64, phi: f64, c: &OursCost) -> Option<f64> {
    f.lookup(x, y).map(|(d, gdir)| {
        let mis = (f64::from(gdir) - phi).cos().abs();
        (f64::from(d) + c.orientation_px * mis).min(c.truncate_px)
    })
}

/// Our fit of one eye: mean sample cost (pixels) and the share of the samples in the image
/// that lie on a matching edge (cost before truncation at most [`INLIER_PX`]).
/// `t_c_i`: the instrument in this camera.
fn eye_cost_ours(
    model: &ToolModel,
    k: &estimator::calib::Intrinsics,
    f: &EdgeField,
    t_c_i: &Isometry3<f64>,
    jaw: f64,
    c: &OursCost,
) -> (f64, f64) {
    let g = model.geometry();
    let (mut sum, mut n, mut inl) = (0.0, 0usize, 0usize);
    // Shaft: two analytic contour lines.
    let a = t_c_i.translation.vector;
    let u = t_c_i.rotation * Vector3::z();
    let Some(offs) = shaft_contour_offsets(&a, &u, g.shaft_radius_m) else {
        return (c.truncate_px, 0.0);
    };
    let ns = c.shaft_samples.max(2);
    for off in offs {
        let mut prev: Option<(f64, f64)> = None;
        for s in 0..ns {
            let t = -g.shaft_modelled_m * s as f64 / (ns - 1) as f64;
            let p = a + off + u * t;
            let q = project(k, &p);
            if let (Some(q), Some(pq)) = (q, prev) {
                let phi = (q.1 - pq.1).atan2(q.0 - pq.0);
                if let Some(v) = sample_cost(f, 0.5 * (q.0 + pq.0), 0.5 * (q.1 + pq.1), phi, c) {
                    sum += v;
                    n += 1;
                    inl += usize::from(v <= INLIER_PX);
                }
            }
            prev = q;
        }
    }
    // Tip parts: the precomputed candidate edges that are silhouette edges from this eye.
    for pe in &model.parts {
        if pe.part == Part::Shaft {
            continue;
        }
        let t_c_p = t_c_i * model.part_in_instrument(pe.part, jaw);
        let eye = eye_in(&t_c_p);
        for e in &pe.candidates {
            if !e.is_silhouette(&eye) {
                continue;
            }
            let pa = t_c_p * Point3::from(e.a);
            let pb = t_c_p * Point3::from(e.b);
            let (Some(qa), Some(qb)) = (project(k, &pa.coords), project(k, &pb.coords)) else { continue };
            let phi = (qb.1 - qa.1).atan2(qb.0 - qa.0);
            for s in [0.25, 0.75] {
                if let Some(v) = sample_cost(f, qa.0 + s * (qb.0 - qa.0), qa.1 + s * (qb.1 - qa.1), phi, c) {
                    sum += v;
                    n += 1;
                    inl += usize::from(v <= INLIER_PX);
                }
            }
        }
    }
    // Samples outside the image are left out (a tool partly out of view is no worse than one
    // in view); a hypothesis with too few samples in the image costs the truncation.
    if n < MIN_INSIDE { (c.truncate_px, 0.0) } else { (sum / n as f64, inl as f64 / n as f64) }
}

/// Fewest samples inside the image for a hypothesis to be scored in an eye.
pub const MIN_INSIDE: usize = 8;

/// A sample whose cost (distance plus orientation mismatch, before truncation) is at most this
/// lies on a matching edge (an inlier), pixels.
pub const INLIER_PX: f64 = 3.0;

/// Our cost of a particle: the mean sample cost of each eye, summed over both eyes (pixels);
/// `f64::INFINITY` off the arm.
pub(crate) fn cost_ours(
    model: &ToolModel,
    cams: &StereoCameras,
    fields: &[EdgeField; 2],
    p: &Particle,
    c: &OursCost,
) -> f64 {
    let Some(t_b_i) = model.instrument_in_base(&p.joints) else { return f64::INFINITY };
    let eyes = cams.eyes_from_base(&p.camera_delta);
    let mut total = 0.0;
    for e in 0..2 {
        total += eye_cost_ours(model, &cams.intrinsics[e], &fields[e], &(eyes[e] * t_b_i), p.jaw_rad, c).0;
    }
    total
}

/// Our fit of a particle: the summed cost of [`cost_ours`] and the inlier share (samples
/// within [`INLIER_PX`] of a matching edge) of each eye, left then right; `(∞, [0, 0])` off
/// the arm. A partly hidden instrument keeps the inlier share of its visible part; a hidden
/// one has almost none.
pub(crate) fn fit_ours(
    model: &ToolModel,
    cams: &StereoCameras,
    fields: &[EdgeField; 2],
    p: &Particle,
    c: &OursCost,
) -> (f64, [f64; 2]) {
    let Some(t_b_i) = model.instrument_in_base(&p.joints) else { return (f64::INFINITY, [0.0; 2]) };
    let eyes = cams.eyes_from_base(&p.camera_delta);
    let mut total = 0.0;
    let mut inl = [0.0; 2];
    for e in 0..2 {
        let (m, f) = eye_cost_ours(model, &cams.intrinsics[e], &fields[e], &(eyes[e] * t_b_i), p.jaw_rad, c);
        total += m;
        inl[e] = f;
    }
    (total, inl)
}

/// Ours: per eye, the inlier share (samples within [`INLIER_PX`] of a matching edge, of the
/// samples inside the image) of the worse of the shaft's two contour lines of `p`; 0 for a
/// line with fewer than `MIN_INSIDE / 2` samples inside the image, or without contour lines.
/// Both lines fitting is what a shaft in view gives; a straight occluder border fits one.
pub fn shaft_line_shares(
    model: &ToolModel,
    cams: &StereoCameras,
    fields: &[EdgeField; 2],
    p: &Particle,
    c: &OursCost,
) -> [f64; 2] {
    let Some(t_b_i) = model.instrument_in_base(&p.joints) else { return [0.0; 2] };
    let eyes = cams.eyes_from_base(&p.camera_delta);
    let g = model.geometry();
    let ns = c.shaft_samples.max(2);
    let mut out = [0.0; 2];
    for (e, o) in out.iter_mut().enumerate() {
        let t_c_i = eyes[e] * t_b_i;
        let a = t_c_i.translation.vector;
        let u = t_c_i.rotation * Vector3::z();
        let Some(offs) = shaft_contour_offsets(&a, &u, g.shaft_radius_m) else { continue };
        let mut worst = f64::INFINITY;
        for off in offs {
            let (mut n, mut inl) = (0usize, 0usize);
            let mut prev: Option<(f64, f64)> = None;
            for s in 0..ns {
                let t = -g.shaft_modelled_m * s as f64 / (ns - 1) as f64;
                let q = project(&cams.intrinsics[e], &(a + off + u * t));
                if let (Some(q), Some(pq)) = (q, prev) {
                    let phi = (q.1 - pq.1).atan2(q.0 - pq.0);
                    if let Some(v) = sample_cost(&fields[e], 0.5 * (q.0 + pq.0), 0.5 * (q.1 + pq.1), phi, c) {
                        n += 1;
                        inl += usize::from(v <= INLIER_PX);
                    }
                }
                prev = q;
            }
            let share = if 2 * n < MIN_INSIDE { 0.0 } else { inl as f64 / n as f64 };
            worst = worst.min(share);
        }
        *o = worst;
    }
    out
}

/// Our silhouette of a hypothesis in one eye (`eye`: 0 left, 1 right) as pixel points (measured
/// pixels): the shaft's two contour lines and the tip parts' silhouette edges, each sampled
/// densely (for overlays; allocates into `out`).
pub fn silhouette_px(model: &ToolModel, cams: &StereoCameras, p: &Particle, eye: usize, out: &mut Vec<[f64; 2]>) {
    out.clear();
    let Some(t_b_i) = model.instrument_in_base(&p.joints) else { return };
    let Some(k) = cams.intrinsics.get(eye) else { return };
    let t_c_i = cams.eyes_from_base(&p.camera_delta)[eye.min(1)] * t_b_i;
    let g = model.geometry();
    let a = t_c_i.translation.vector;
    let u = t_c_i.rotation * Vector3::z();
    if let Some(offs) = shaft_contour_offsets(&a, &u, g.shaft_radius_m) {
        for off in offs {
            for s in 0..200 {
                let t = -g.shaft_modelled_m * f64::from(s) / 199.0;
                if let Some(q) = project(k, &(a + off + u * t)) {
                    out.push([q.0, q.1]);
                }
            }
        }
    }
    for pe in &model.parts {
        if pe.part == Part::Shaft {
            continue;
        }
        let t_c_p = t_c_i * model.part_in_instrument(pe.part, p.jaw_rad);
        let eye_p = eye_in(&t_c_p);
        for e in pe.candidates.iter().filter(|e| e.is_silhouette(&eye_p)) {
            for s in 0..=10 {
                let x = e.a + (e.b - e.a) * (f64::from(s) / 10.0);
                if let Some(q) = project(k, &(t_c_p * Point3::from(x)).coords) {
                    out.push([q.0, q.1]);
                }
            }
        }
    }
}

/// Draws the segment `a → b` (pixels) into `img` (`w × h`, row-major), clipped.
fn draw_line(img: &mut [u8], w: usize, h: usize, a: (f64, f64), b: (f64, f64)) {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let steps = dx.abs().max(dy.abs()).ceil().min(4096.0) as usize;
    for s in 0..=steps {
        let t = if steps == 0 { 0.0 } else { s as f64 / steps as f64 };
        let (x, y) = ((a.0 + t * dx).round(), (a.1 + t * dy).round());
        if x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h {
            img[y as usize * w + x as usize] = 1;
        }
    }
}

/// The paper's Algorithm 2 for one eye: the virtual image `img` (cleared, then the silhouette
/// edges of every part drawn, Algorithm 1 with Eq. 6 on every mesh edge) and its chamfer
/// distance to the real edges (mean distance field over the virtual edge pixels, pixels;
/// `None` when nothing is drawn).
pub(crate) fn paper_eye_chamfer(
    model: &ToolModel,
    k: &estimator::calib::Intrinsics,
    f: &EdgeField,
    t_c_i: &Isometry3<f64>,
    jaw: f64,
    img: &mut [u8],
) -> Option<f64> {
    let (w, h) = (f.width(), f.height());
    img.fill(0);
    for pe in &model.parts {
        let t_c_p = t_c_i * model.part_in_instrument(pe.part, jaw);
        let eye = eye_in(&t_c_p);
        for e in &pe.all {
            if !e.is_silhouette(&eye) {
                continue;
            }
            let pa = t_c_p * Point3::from(e.a);
            let pb = t_c_p * Point3::from(e.b);
            if let (Some(qa), Some(qb)) = (project(k, &pa.coords), project(k, &pb.coords)) {
                draw_line(img, w, h, qa, qb);
            }
        }
    }
    let (mut sum, mut n) = (0.0, 0usize);
    for (i, &v) in img.iter().enumerate() {
        if v != 0
            && let Some(d) = f.distance(i % w, i / w)
        {
            sum += f64::from(d.min(1e4));
            n += 1;
        }
    }
    (n > 0).then(|| sum / n as f64)
}

/// The paper's measurement of a particle, Eq. 15-16: `s = exp(−d/τ)` per eye, `π =
/// sqrt(s_l² + s_r²)`; returns `(π, mean chamfer distance in pixels)`. `img` is a scratch
/// virtual image of `width · height` bytes.
pub(crate) fn paper_score(
    model: &ToolModel,
    cams: &StereoCameras,
    fields: &[EdgeField; 2],
    p: &Particle,
    tau_px: f64,
    img: &mut [u8],
) -> (f64, f64) {
    let Some(t_b_i) = model.instrument_in_base(&p.joints) else { return (0.0, f64::INFINITY) };
    let eyes = cams.eyes_from_base(&p.camera_delta);
    let mut s2 = 0.0;
    let mut dsum = 0.0;
    for e in 0..2 {
        let d = paper_eye_chamfer(model, &cams.intrinsics[e], &fields[e], &(eyes[e] * t_b_i), p.jaw_rad, img)
            .unwrap_or(1e3);
        let s = (-d / tau_px).exp();
        s2 += s * s;
        dsum += d;
    }
    (s2.sqrt(), dsum / 2.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn contour_lines_are_tangent_to_the_cylinder_seen_from_the_origin() {
        let a = Vector3::new(0.01, -0.02, 0.1);
        let u = Vector3::new(0.3, 0.1, 1.0).normalize();
        let r = 0.004;
        let [o1, o2] = shaft_contour_offsets(&a, &u, r).unwrap();
        for o in [o1, o2] {
            assert!((o.norm() - r).abs() < 1e-12);
            assert!(o.dot(&u).abs() < 1e-12);
            // The ray to the contour point is perpendicular to the surface normal there.
            let p = a + o;
            assert!(p.dot(&o).abs() < 1e-12, "{}", p.dot(&o));
        }
        assert!(shaft_contour_offsets(&Vector3::new(0.001, 0.0, 0.1), &Vector3::z(), r).is_none());
    }
}
