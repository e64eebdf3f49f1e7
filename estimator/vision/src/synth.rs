//! Synthetic endoscope-like test images with exact ground truth, for the detectors' tests and
//! benches (the simulator in `sim` is far richer, and far heavier to build).
//!
//! A scene is pink textured "tissue" (smooth value noise in two octaves, optional dark-red
//! vessel curves and bright pink fold bands) and any number of grey metal cylinders (the
//! shafts), seen by a camera with lens distortion. Each measured pixel is mapped to its
//! undistorted position (`Intrinsics::undistort_px`), so the silhouette is exact under
//! distortion; pixels the silhouette crosses are supersampled 4 × 4 (anti-aliasing). The
//! metal is shaded darker towards the silhouette (light at the camera), and uniform noise is
//! added per channel. Deterministic for a seed.

use estimator::calib::Intrinsics;
use nalgebra::{Vector2, Vector3};

use crate::shaft::{ImageLine, LineError};

/// The simulated endoscope's default camera (`sim::endoscope::config::CameraConfig`'s
/// default): 640×480 pixels, f = 400 px, principal point at the centre, mild barrel distortion
/// (k1 = −0.08, k2 = 0.01). The camera of the detectors' tests and benches.
pub fn endoscope_camera() -> Intrinsics {
    Intrinsics {
        fx: 400.0,
        fy: 400.0,
        cx: 319.5,
        cy: 239.5,
        skew: 0.0,
        width: 640,
        height: 480,
        distortion: [-0.08, 0.01, 0.0, 0.0, 0.0],
    }
}

/// A finite cylinder in the camera frame (metres; x right, y down, z forward).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cylinder {
    /// A point of the axis, metres, camera frame.
    pub point_m: [f64; 3],
    /// The axis direction (any length, not zero), camera frame.
    pub direction: [f64; 3],
    /// Radius, metres.
    pub radius_m: f64,
    /// The shaft's extent along the axis, metres from `point_m` along the unit direction
    /// (`[start, end]`, `start < end`).
    pub extent_m: [f64; 2],
    /// Metal brightness, 0..=1 (0.8 bright steel, 0.3 dark insulated shaft).
    pub albedo: f64,
}

impl Cylinder {
    fn unit_dir(&self) -> Vector3<f64> {
        let d = Vector3::from(self.direction);
        d / d.norm()
    }

    /// The true projected axis, undistorted pixels: `K⁻ᵀ (A × d)`.
    pub fn axis_line(&self, k: &Intrinsics) -> Result<ImageLine, LineError> {
        let m = Vector3::from(self.point_m).cross(&self.unit_dir());
        let l = k.k_inv().transpose() * m;
        ImageLine::new([l.x, l.y, l.z])
    }

    /// The measured (distorted) pixel of the axis point at `s` metres along the axis.
    pub fn axis_point_px(&self, k: &Intrinsics, s_m: f64) -> [f64; 2] {
        let p = Vector3::from(self.point_m) + s_m * self.unit_dir();
        let q = k.project(&p);
        [q.x, q.y]
    }

    /// Depth along the ray `r` (unnormalised, z = 1) of its hit, and the normalised distance
    /// of the ray from the axis (0 centre, 1 silhouette); `None` when missed.
    fn hit(&self, r: &Vector3<f64>) -> Option<(f64, f64)> {
        let a = Vector3::from(self.point_m);
        let d = self.unit_dir();
        // Closest points of the lines t·r and a + s·d.
        let (rr, rd, dd) = (r.dot(r), r.dot(&d), d.dot(&d));
        let (ra, da) = (r.dot(&a), d.dot(&a));
        let den = rr * dd - rd * rd;
        if den.abs() < 1e-15 {
            return None;
        }
        let t = (ra * dd - rd * da) / den;
        let s = (rd * ra - rr * da) / den;
        if t <= 0.0 || s < self.extent_m[0] || s > self.extent_m[1] {
            return None;
        }
        let dist = (t * r - (a + s * d)).norm();
        (dist < self.radius_m).then(|| (t, dist / self.radius_m))
    }
}

/// What to draw.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    /// The shafts (nearest wins where they overlap).
    pub shafts: Vec<Cylinder>,
    /// Texture and noise seed.
    pub seed: u64,
    /// Draw dark-red vessel curves.
    pub vessels: bool,
    /// Draw bright pink fold bands.
    pub folds: bool,
    /// Noise amplitude (uniform, ± this many 8-bit levels per channel).
    pub noise: f64,
}

fn hash(mut x: u64) -> u64 {
    x ^= x >> 33;
    x = x.wrapping_mul(0xff51_afd7_ed55_8ccd);
    x ^= x >> 33;
    x = x.wrapping_mul(0xc4ce_b9fe_1a85_ec53);
    x ^ (x >> 33)
}

fn unit(h: u64) -> f64 {
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// Smooth value noise in `[-1, 1]` at cell size `cell` pixels.
fn value_noise(seed: u64, x: f64, y: f64, cell: f64) -> f64 {
    let (gx, gy) = (x / cell, y / cell);
    let (x0, y0) = (gx.floor(), gy.floor());
    let (fx, fy) = (gx - x0, gy - y0);
    let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
    let v = |i: f64, j: f64| {
        let h = hash(
            seed ^ ((i as i64 as u64).wrapping_mul(0x9e37_79b9) ^ (j as i64 as u64).wrapping_mul(0x85eb_ca6b) << 1),
        );
        2.0 * unit(h) - 1.0
    };
    let top = v(x0, y0) + sx * (v(x0 + 1.0, y0) - v(x0, y0));
    let bot = v(x0, y0 + 1.0) + sx * (v(x0 + 1.0, y0 + 1.0) - v(x0, y0 + 1.0));
    top + sy * (bot - top)
}

/// Tissue colour at a measured pixel position, linear 0..255 values.
fn tissue(scene: &Scene, x: f64, y: f64) -> [f64; 3] {
    let n1 = value_noise(scene.seed, x, y, 48.0);
    let n2 = value_noise(scene.seed ^ 0x55, x, y, 9.0);
    let mut c = [170.0 + 40.0 * n1 + 12.0 * n2, 85.0 + 25.0 * n1 + 8.0 * n2, 95.0 + 20.0 * n1 + 8.0 * n2];
    let mut blend = |col: [f64; 3], a: f64| {
        for (ci, k) in c.iter_mut().zip(col) {
            *ci += a * (k - *ci);
        }
    };
    if scene.folds {
        for f in 0..3u64 {
            let h = hash(scene.seed ^ (0xf01d + f));
            let (y0, amp, lam) = (60.0 + 360.0 * unit(h), 15.0 + 30.0 * unit(h >> 7), 120.0 + 200.0 * unit(h >> 14));
            let dist = (y - (y0 + amp * (x / lam + f as f64).sin())).abs();
            let a = (-(dist / 7.0).powi(2)).exp();
            blend([240.0, 185.0, 190.0], 0.9 * a);
        }
    }
    if scene.vessels {
        for v in 0..5u64 {
            let h = hash(scene.seed ^ (0x7e55 + v));
            let (x0, amp, lam) = (640.0 * unit(h), 20.0 + 60.0 * unit(h >> 7), 60.0 + 150.0 * unit(h >> 14));
            let dist = (x - (x0 + amp * (y / lam + v as f64).sin() + 0.3 * (y - 240.0))).abs();
            let a = (1.5 - dist).clamp(0.0, 1.0);
            blend([105.0, 28.0, 38.0], a);
        }
    }
    c
}

/// Renders `scene` as an 8-bit RGB image of `k`'s size (row-major).
pub fn render(k: &Intrinsics, scene: &Scene) -> Vec<u8> {
    let (w, h) = (k.width as usize, k.height as usize);
    let k_inv = k.k_inv();
    // Undistorted position of every pixel centre.
    let und: Vec<Vector2<f64>> =
        (0..w * h).map(|i| k.undistort_px(&Vector2::new((i % w) as f64, (i / w) as f64))).collect();
    let shade = |p: Vector2<f64>| -> Option<[f64; 3]> {
        let r = k_inv * Vector3::new(p.x, p.y, 1.0);
        let mut best: Option<(f64, [f64; 3])> = None;
        for c in &scene.shafts {
            if let Some((t, q)) = c.hit(&r)
                && best.is_none_or(|b| t < b.0)
            {
                let lit = c.albedo * (0.25 + 0.75 * (1.0 - q * q).max(0.0).sqrt()) * 255.0;
                best = Some((t, [lit, lit, lit * 1.03]));
            }
        }
        best.map(|b| b.1)
    };
    let mut out = vec![0u8; 3 * w * h];
    for yi in 0..h {
        for xi in 0..w {
            let i = yi * w + xi;
            let p = und[i];
            // Local Jacobian of the undistortion from the neighbours.
            let jx = if xi + 1 < w { und[i + 1] - p } else { p - und[i - 1] };
            let jy = if yi + 1 < h { und[i + w] - p } else { p - und[i - w] };
            let (x, y) = (xi as f64, yi as f64);
            let at = |dx: f64, dy: f64| p + jx * dx + jy * dy;
            let corners = [(-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)];
            let cover: Vec<bool> = corners.iter().map(|&(dx, dy)| shade(at(dx, dy)).is_some()).collect();
            let centre = shade(p);
            let mut col = [0.0; 3];
            if cover.iter().all(|&c| c == centre.is_some()) {
                col = centre.unwrap_or_else(|| tissue(scene, x, y));
            } else {
                let n = 4;
                for sy in 0..n {
                    for sx in 0..n {
                        let (dx, dy) = ((sx as f64 + 0.5) / n as f64 - 0.5, (sy as f64 + 0.5) / n as f64 - 0.5);
                        let c = shade(at(dx, dy)).unwrap_or_else(|| tissue(scene, x + dx, y + dy));
                        for (a, b) in col.iter_mut().zip(c) {
                            *a += b / (n * n) as f64;
                        }
                    }
                }
            }
            for (ch, c) in col.iter().enumerate() {
                let nz = scene.noise
                    * (2.0 * unit(hash(scene.seed ^ ((i * 3 + ch) as u64).wrapping_mul(0x2545_f491))) - 1.0);
                out[3 * i + ch] = (c + nz).round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    out
}
